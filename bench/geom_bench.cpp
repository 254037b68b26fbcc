// geom: FCL collision and distance query rates of a tool against the ~200,000-triangle benchmark part
// (the seed-002 groove, finely tessellated), at random poses near its surface; and the BVH build time.
// No main(): link with benchmark::benchmark_main.
#include <benchmark/benchmark.h>

#include <cmath>
#include <random>
#include <vector>

#include "cscam/core/units.hpp"
#include "cscam/geom/groove.hpp"
#include "cscam/geom/scene.hpp"

namespace {

using namespace cscam;
using namespace cscam::geom;

const Mesh& part() {
  static const Mesh m = make_benchmark_part(200000);
  return m;
}

const Scene& scene() {
  static const Scene s = [] {
    Scene sc;
    sc.add("groove", ObstacleRole::Part, part());
    sc.build();
    return sc;
  }();
  return s;
}

/// Ball mill D6 (flutes 25, shank 20), holder D15 x 40, spindle nose D60 x 30.
const ToolShape& tool() {
  static const ToolShape t = [] {
    ToolDefaults d;
    d.shank_length_mm = 20.0;
    d.spindle = {60.0, 30.0};
    return ToolShape::from_cutter(6.0, 3.0, 25.0, d);
  }();
  return t;
}

/// Poses with the ball touching the floor or a wall (tip = contact + r n - r a), axis within 45 deg of the
/// groove's upward direction: roughly half of them collide, like the cells of a C-space grid.
const std::vector<kin::Posed>& poses() {
  static const std::vector<kin::Posed> v = [] {
    const GrooveParams p;  // the benchmark part keeps the default dimensions
    std::mt19937_64 rng(2026);
    std::uniform_real_distribution<double> u01(0.0, 1.0);
    std::vector<kin::Posed> out;
    const double r = 3.0;
    for (int i = 0; i < 4096; ++i) {
      const double x = -45.0 + 90.0 * u01(rng);
      Eigen::Vector3d contact, normal;
      if (u01(rng) < 0.5) {  // floor
        contact = {x, (u01(rng) - 0.5) * 24.0, 0.0};
        normal = Eigen::Vector3d::UnitZ();
      } else {  // a wall: the analytic profile, inward normal from the arc centre
        const double z = 1.0 + 18.0 * u01(rng), side = u01(rng) < 0.5 ? -1.0 : 1.0;
        const GrooveProfile g = groove_profile(p);
        const double y = groove_half_width_at(p, z);
        contact = {x, side * y, z};
        normal = Eigen::Vector3d(0.0, side * (g.centre_y_mm - y), g.centre_z_mm - z).normalized();
      }
      const double t = deg2rad(45.0) * std::sqrt(u01(rng)), ph = 2.0 * kPi * u01(rng);
      const Eigen::Vector3d a(std::sin(t) * std::cos(ph), std::sin(t) * std::sin(ph), std::cos(t));
      const Eigen::Vector3d centre = contact + r * normal;
      out.push_back({centre - r * a, a});
    }
    return out;
  }();
  return v;
}

/// Arg 0: collision hierarchy only; arg 1: collision + distance hierarchies (the default build()).
void BM_BvhBuild(benchmark::State& state) {
  const Mesh& m = part();
  for (auto _ : state) {
    state.PauseTiming();
    Scene s;
    s.add("groove", ObstacleRole::Part, m);
    state.ResumeTiming();
    s.build(state.range(0) != 0);
    benchmark::DoNotOptimize(s.triangle_count());
  }
  state.counters["triangles"] = static_cast<double>(m.triangle_count());
}
BENCHMARK(BM_BvhBuild)->Arg(0)->Arg(1)->Unit(benchmark::kMillisecond);

void BM_CollisionQuery(benchmark::State& state) {
  const Scene& s = scene();
  const auto& ps = poses();
  QueryWorkspace ws;
  CheckOptions o;
  o.clearance_mm = 0.5;
  std::size_t i = 0, hits = 0;
  for (auto _ : state) {
    const CollisionResult r = check(s, tool(), ps[i++ & (ps.size() - 1)], o, ws);
    hits += r.collides;
    benchmark::DoNotOptimize(r.collides);
  }
  state.SetItemsProcessed(state.iterations());
  state.counters["queries/s"] =
      benchmark::Counter(static_cast<double>(ws.stats.collision_queries), benchmark::Counter::kIsRate);
  // Per-thread ratios: averaged over threads (the benchmark sums counters over threads by default).
  state.counters["colliding"] = benchmark::Counter(static_cast<double>(hits) / static_cast<double>(state.iterations()),
                                                   benchmark::Counter::kAvgThreads);
  state.counters["fcl_calls/query"] = benchmark::Counter(
      static_cast<double>(ws.stats.fcl_collide_calls) / static_cast<double>(ws.stats.collision_queries),
      benchmark::Counter::kAvgThreads);
}
BENCHMARK(BM_CollisionQuery);
BENCHMARK(BM_CollisionQuery)->Threads(2)->UseRealTime();

void BM_ClearanceQuery(benchmark::State& state) {
  const Scene& s = scene();
  const auto& ps = poses();
  QueryWorkspace ws;
  std::size_t i = 0;
  for (auto _ : state) benchmark::DoNotOptimize(clearance(s, tool(), ps[i++ & (ps.size() - 1)], {}, ws));
  state.SetItemsProcessed(state.iterations());
  state.counters["queries/s"] =
      benchmark::Counter(static_cast<double>(ws.stats.distance_queries), benchmark::Counter::kIsRate);
  state.counters["fcl_calls/query"] =
      static_cast<double>(ws.stats.fcl_distance_calls) / static_cast<double>(ws.stats.distance_queries);
}
BENCHMARK(BM_ClearanceQuery);

}  // namespace
