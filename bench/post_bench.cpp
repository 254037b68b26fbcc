// Throughput of the whole conventional post of one file: parse -> IK -> post (with linearisation) -> safety gate (with
// the machine's bodies in its collision scene) -> write, on a generated variable-axis CL file for the A/C trunnion, at
// 1 and 2 threads (the gate samples blocks in parallel). Target: >= 1,000,000 CL points/s on 2 cores. Per-stage times
// are reported as counters.
#include <benchmark/benchmark.h>
#include <fmt/format.h>
#include <tbb/task_arena.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <random>
#include <sstream>

#include "cscam/cl/program.hpp"
#include "cscam/cspace/cspace.hpp"
#include "cscam/cspace/machine_scene.hpp"
#include "cscam/gate/gate.hpp"
#include "cscam/machine/machine.hpp"
#include "cscam/post/post.hpp"

namespace {

/// A smooth variable-axis finishing path: a raster over a dome whose normals tilt up to ~35 deg.
std::string make_cl(size_t points, const std::string& path) {
  std::ofstream out(path);
  out << "PARTNO BENCH\nUNITS/MM\nMULTAX/ON\nCUTTER/10,5\nLOADTL/1\nSPINDL/8000,CLW\nFEDRAT/MMPM,2000\n";
  const size_t per_row = 1000;
  const double R = 200.0;
  for (size_t i = 0; i < points; ++i) {
    const size_t row = i / per_row, k = i % per_row;
    const double x = -80.0 + 160.0 * (row % 2 ? (per_row - 1 - k) : k) / (per_row - 1);
    const double y = -80.0 + 160.0 * static_cast<double>(row % 200) / 199.0;
    const double zz = std::sqrt(R * R - x * x - y * y);
    const double z = zz - R + 40.0;  // above the platter face (the machine's bodies are in the gate's scene)
    const double ni = x / R, nj = y / R, nk = zz / R;
    if (k == 0) out << "RAPID\n";
    out << fmt::format("GOTO/{:.4f},{:.4f},{:.4f},{:.7f},{:.7f},{:.7f}\n", x, y, z, ni, nj, nk);
  }
  out << "FINI\n";
  return path;
}

using Clock = std::chrono::steady_clock;
double since(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

void BM_PostPipeline(benchmark::State& state) {
  const size_t n = static_cast<size_t>(state.range(0));
  const int threads = static_cast<int>(state.range(1));
  const bool bodies = state.range(2) != 0;  // the machine's bodies in the gate's collision scene
  const std::string dir = std::filesystem::temp_directory_path().string();
  const std::string cl_path = make_cl(n, dir + "/cscam_bench_" + std::to_string(::getpid()) + ".cls");
  const std::string nc_path = dir + "/cscam_bench_" + std::to_string(::getpid()) + ".ngc";
  const auto m = cscam::machine::load(std::string(CSCAM_SOURCE_DIR) + "/machines/trunnion-ac.yaml");
  const auto kin = m.kinematics();
  // The gate checks every move against the machine's own bodies, as `cscam post` does: the CL's D10 ball on the
  // machine's holder.
  const auto tool = cscam::cspace::tool_on_machine(m, 10, 5, 30);
  cscam::geom::Scene scene, head;
  cscam::cspace::add_machine_bodies(m, std::max(0.0, tool.gauge_length_mm() - cscam::post::tool_length_for(m, 0)),
                                    scene, head);
  scene.build(false);
  head.build(false);
  cscam::cspace::Options co;
  co.check_collision = true;
  co.collision.roles = cscam::geom::kAllRoles;
  const auto space = std::make_shared<const cscam::cspace::Space>(kin, &scene, &tool, co, &head);
  cscam::gate::Options go = cscam::gate::options_for(m, 0, 0, 0);
  // Every worker's path check, for the count of collision queries and certified samples.
  auto checks = std::make_shared<std::vector<std::shared_ptr<cscam::cspace::PathCheck>>>();
  auto checks_mutex = std::make_shared<std::mutex>();
  if (bodies)
    go.make_collision = [space, checks, checks_mutex](int) -> cscam::gate::Options::CollisionCheck {
      auto check = std::make_shared<cscam::cspace::PathCheck>(space);
      {
        const std::lock_guard<std::mutex> lock(*checks_mutex);
        checks->push_back(check);
      }
      return [check](const cscam::kin::Axes& q, bool whole_tool) {
        return (*check)(q, whole_tool ? cscam::cspace::SweepMode::Rapid : cscam::cspace::SweepMode::Cutting);
      };
    };
  size_t blocks = 0, inserted = 0, collision_checks = 0, narrowed = 0;
  double t_read = 0, t_ik = 0, t_post = 0, t_gate = 0;
  tbb::task_arena arena(threads);
  for (auto _ : state) {
    arena.execute([&] {
      auto t = Clock::now();
      cscam::cl::ReadOptions ro;
      ro.require_feed = true;
      const auto prog = cscam::cl::read_file(cl_path, ro);
      t_read += since(t);
      t = Clock::now();
      const auto axes = cscam::post::conventional_axes(prog, m, *kin);
      t_ik += since(t);
      t = Clock::now();
      cscam::post::Options po;
      cscam::post::Summary sum;
      std::ostringstream os;
      cscam::post::write_nc(os, prog, m, *kin, axes, po, sum);
      const std::string text = std::move(os).str();
      t_post += since(t);
      t = Clock::now();
      const auto gs = cscam::gate::write_checked(nc_path, text, prog, m, *kin, go, &sum.cl_line_of_nc_line);
      collision_checks = gs.collision_checks;
      t_gate += since(t);
      blocks = sum.blocks;
      inserted = sum.inserted_points;
      narrowed = sum.narrowed_corners + sum.exact_corners;
    });
  }
  state.SetItemsProcessed(static_cast<int64_t>(state.iterations() * n));
  const double it = static_cast<double>(state.iterations());
  state.counters["blocks"] = static_cast<double>(blocks);
  state.counters["inserted"] = static_cast<double>(inserted);
  state.counters["corners_bounded"] = static_cast<double>(narrowed);           // blends narrowed (G64 P) or made exact
  state.counters["collision_checks"] = static_cast<double>(collision_checks);  // samples the gate checked
  double queries = 0, certified = 0;
  for (const auto& c : *checks) {
    queries += static_cast<double>(c->counters().collision);
    certified += static_cast<double>(c->counters().certified);
  }
  state.counters["collision_queries"] = queries / it;  // FCL queries (probes and exact checks)
  state.counters["certified"] = certified / it;        // samples covered by a clearance certificate
  state.counters["read_s"] = t_read / it;
  state.counters["ik_s"] = t_ik / it;
  state.counters["post_s"] = t_post / it;
  state.counters["gate_write_s"] = t_gate / it;
  std::remove(cl_path.c_str());
  std::remove(nc_path.c_str());
}
BENCHMARK(BM_PostPipeline)
    ->ArgNames({"points", "threads", "bodies"})
    ->Args({1000000, 1, 1})
    ->Args({1000000, 2, 1})
    ->Args({1000000, 2, 0})
    ->Unit(benchmark::kMillisecond)
    ->Iterations(1)
    ->UseRealTime();

}  // namespace

BENCHMARK_MAIN();
