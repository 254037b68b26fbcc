// Throughput of the whole conventional post: parse -> IK -> post (with linearisation) -> write,
// on a generated variable-axis CL file for the A/C trunnion. Target: >= 500,000 CL points/s on one core.
#include <benchmark/benchmark.h>
#include <fmt/format.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <random>

#include "cscam/cl/program.hpp"
#include "cscam/core/atomic_file.hpp"
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
    const double z = zz - R + 20.0;
    const double ni = x / R, nj = y / R, nk = zz / R;
    if (k == 0) out << "RAPID\n";
    out << fmt::format("GOTO/{:.4f},{:.4f},{:.4f},{:.7f},{:.7f},{:.7f}\n", x, y, z, ni, nj, nk);
  }
  out << "FINI\n";
  return path;
}

void BM_PostPipeline(benchmark::State& state) {
  const size_t n = static_cast<size_t>(state.range(0));
  const std::string dir = std::filesystem::temp_directory_path().string();
  const std::string cl_path = make_cl(n, dir + "/cscam_bench.cls");
  const auto m = cscam::machine::load(std::string(CSCAM_SOURCE_DIR) + "/machines/trunnion-ac.yaml");
  const auto kin = m.kinematics();
  size_t blocks = 0, inserted = 0;
  for (auto _ : state) {
    const auto prog = cscam::cl::read_file(cl_path);
    const auto axes = cscam::post::conventional_axes(prog, m, *kin);
    cscam::post::Options po;
    cscam::post::Summary sum;
    cscam::write_file_atomically(dir + "/cscam_bench.ngc",
                                 [&](std::ostream& os) { cscam::post::write_nc(os, prog, m, *kin, axes, po, sum); });
    blocks = sum.blocks;
    inserted = sum.inserted_points;
  }
  state.SetItemsProcessed(static_cast<int64_t>(state.iterations() * n));
  state.counters["blocks"] = static_cast<double>(blocks);
  state.counters["inserted"] = static_cast<double>(inserted);
  std::remove(cl_path.c_str());
  std::remove((dir + "/cscam_bench.ngc").c_str());
}
BENCHMARK(BM_PostPipeline)->Arg(1000000)->Unit(benchmark::kMillisecond)->Iterations(1);

}  // namespace

BENCHMARK_MAIN();
