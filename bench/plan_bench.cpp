// The C-space planner on the workload: a 10,000-point path, 1 deg grid over the full rotary ranges,
// against a part of about 200,000 triangles (the seed-002 groove, finely tessellated), A/C trunnion.
// Also the two scaling curves: time vs number of points (expected linear) and time vs number of grid cells
// (expected far below linear: cells are evaluated lazily).
#include <benchmark/benchmark.h>
#include <sys/resource.h>
#include <unistd.h>

#include <array>
#include <cmath>
#include <cstdio>
#include <sstream>

#include "cscam/cl/program.hpp"
#include "cscam/core/units.hpp"
#include "cscam/cspace/cspace.hpp"
#include "cscam/cspace/machine_scene.hpp"
#include "cscam/geom/groove.hpp"
#include "cscam/geom/scene.hpp"
#include "cscam/machine/machine.hpp"
#include "cscam/plan/plan.hpp"
#include "cscam/plan/stream.hpp"

namespace {

struct Fixture {
  cscam::machine::Machine m = cscam::machine::load(std::string(CSCAM_SOURCE_DIR) + "/machines/trunnion-ac.yaml");
  cscam::geom::Scene scene;
  cscam::geom::ToolShape tool = cscam::geom::ToolShape::from_cutter(10, 5, 30);
  size_t triangles = 0;
  Fixture() {
    auto mesh = cscam::geom::make_benchmark_part(200000);
    triangles = mesh.triangle_count();
    scene.add("groove", cscam::geom::ObstacleRole::Part, std::move(mesh));
    scene.build(false);
  }
};

Fixture& fixture() {
  static Fixture f;
  return f;
}

/// A finishing pass along the groove floor whose CL axes wobble +-4 deg around the normal (a curved floor).
cscam::cl::Program path(int n) {
  std::ostringstream o;
  o.precision(10);
  o << "UNITS/MM\nMULTAX\nCUTTER/10,5\nFEDRAT/MMPM,1000\n";
  for (int i = 0; i < n; ++i) {
    const double s = double(i) / (n - 1), x = -45 + 90 * s;
    const double tx = cscam::deg2rad(4.0) * std::sin(2 * M_PI * 3 * s),
                 ty = cscam::deg2rad(3.0) * std::cos(2 * M_PI * 2 * s);
    const Eigen::Vector3d u = Eigen::Vector3d(std::tan(tx), std::tan(ty), 1).normalized();
    o << "GOTO/" << x << ",0,0," << u.x() << "," << u.y() << "," << u.z() << "\n";
  }
  return cscam::cl::read_text(o.str(), "bench.cls");
}

void run(benchmark::State& state, int n, double res_deg, double cone_deg) {
  auto& f = fixture();
  const auto prog = path(n);
  cscam::plan::Options o;
  o.cspace.cone_rad = cscam::deg2rad(cone_deg);
  o.cspace.resolution_rad = cscam::deg2rad(res_deg);
  o.cspace.ball_radius_mm = 5;
  o.cspace.check_collision = true;
  const cscam::plan::Planner planner(f.m, f.m.kinematics(), &f.scene, &f.tool, o);
  cscam::plan::Plan p;
  for (auto _ : state) p = planner.run(prog);
  state.counters["points"] = n;
  state.counters["grid_cells_full"] = (360.0 * 2 / res_deg) * (150.0 / res_deg);
  state.counters["cells_enumerated"] = static_cast<double>(p.counters.cells_enumerated);
  state.counters["collision_queries"] = static_cast<double>(p.counters.collision);
  state.counters["tier"] = p.segments.empty() ? 0 : static_cast<int>(p.segments[0].tier);
  state.counters["triangles"] = static_cast<double>(f.triangles);
}

void BM_Plan10k(benchmark::State& s) { run(s, 10000, 1.0, 5.0); }
void BM_PlanPoints(benchmark::State& s) { run(s, static_cast<int>(s.range(0)), 1.0, 5.0); }
void BM_PlanResolution(benchmark::State& s) { run(s, 2000, 4.0 / static_cast<double>(s.range(0)), 5.0); }

/// Issue 4: the XMINI planner on the seed-000 cut (+-20 mm along X, vertical tool) with a 1 deg cone,
/// 0.05 deg tilt refinement for the leg-monotonic re-plan (rotary grid 0.25 deg).
void BM_XminiSeed000(benchmark::State& state) {
  const auto m = cscam::machine::load(std::string(CSCAM_SOURCE_DIR) + "/machines/xmini.yaml");
  const auto prog = cscam::cl::read_file(std::string(CSCAM_SOURCE_DIR) + "/examples/xmini/seed000_x_cut.cls");
  cscam::plan::Options o;
  o.cspace.cone_rad = cscam::deg2rad(1.0);
  o.cspace.resolution_rad = cscam::deg2rad(static_cast<double>(state.range(0)) / 100.0);
  o.tilt_step_rad = cscam::deg2rad(0.05);
  o.monotone_axes = {0, 1, 2};
  const cscam::plan::Planner planner(m, m.kinematics(), nullptr, nullptr, o);
  cscam::plan::Plan p;
  for (auto _ : state) p = planner.run(prog);
  state.counters["grid_deg"] = static_cast<double>(state.range(0)) / 100.0;
  state.counters["legs_monotonic"] = p.segments.empty() ? 0 : p.segments[0].legs.monotonic();
}
BENCHMARK(BM_XminiSeed000)->Arg(25)->Arg(5)->Unit(benchmark::kMillisecond)->Iterations(1);

BENCHMARK(BM_Plan10k)->Unit(benchmark::kMillisecond)->Iterations(1);
BENCHMARK(BM_PlanPoints)->Arg(1250)->Arg(2500)->Arg(5000)->Arg(10000)->Unit(benchmark::kMillisecond)->Iterations(1);
// resolution 4, 2, 1, 0.5 deg: 16x more grid cells from first to last
BENCHMARK(BM_PlanResolution)->Arg(1)->Arg(2)->Arg(4)->Arg(8)->Unit(benchmark::kMillisecond)->Iterations(1);

/// Issue 11, part 3: the hard case. A narrower groove (mouth 15 mm: a D10 tool tilted across it by more than
/// ~11 deg hits the lip), 10,000 points whose CL axis swings +-12 deg across the groove (8 periods) and +-10 deg
/// along it (5 periods), cone 8 deg: no fixed orientation, no fixed axis and no monotonic pair covers the swings
/// (tiers 1-3 fail), and near each swing's extreme the lip removes most of the cone.
struct HardFixture {
  cscam::machine::Machine m = cscam::machine::load(std::string(CSCAM_SOURCE_DIR) + "/machines/trunnion-ac.yaml");
  cscam::geom::Scene scene;
  cscam::geom::ToolShape tool = cscam::geom::ToolShape::from_cutter(10, 5, 30);
  size_t triangles = 0;
  HardFixture() {
    cscam::geom::GrooveParams g;
    g.mouth_width_mm = 15.0;
    auto mesh = cscam::geom::make_benchmark_part(200000, g);
    triangles = mesh.triangle_count();
    scene.add("groove", cscam::geom::ObstacleRole::Part, std::move(mesh));
    scene.build(false);
  }
};

HardFixture& hard_fixture() {
  static HardFixture f;
  return f;
}

cscam::cl::Program hard_path(int n) {
  std::ostringstream o;
  o.precision(10);
  o << "UNITS/MM\nMULTAX\nCUTTER/10,5\nFEDRAT/MMPM,1000\n";
  for (int i = 0; i < n; ++i) {
    const double s = double(i) / (n - 1), x = -45 + 90 * s;
    const double tx = cscam::deg2rad(10.0) * std::sin(2 * M_PI * 5 * s),
                 ty = cscam::deg2rad(12.0) * std::sin(2 * M_PI * 8 * s);
    const Eigen::Vector3d u = Eigen::Vector3d(std::tan(tx), std::tan(ty), 1).normalized();
    o << "GOTO/" << x << ",0,0," << u.x() << "," << u.y() << "," << u.z() << "\n";
  }
  return cscam::cl::read_text(o.str(), "hard.cls");
}

double peak_rss_mb() {
  rusage ru{};
  getrusage(RUSAGE_SELF, &ru);
  return static_cast<double>(ru.ru_maxrss) / 1024.0;
}

/// The resident memory now (not the peak), MB: before planning, to tell the planner's share of the peak.
double rss_now_mb() {
  long pages = 0, resident = 0;
  if (FILE* f = std::fopen("/proc/self/statm", "r")) {
    if (std::fscanf(f, "%ld %ld", &pages, &resident) != 2) resident = 0;
    std::fclose(f);
  }
  return static_cast<double>(resident) * static_cast<double>(sysconf(_SC_PAGESIZE)) / (1024.0 * 1024.0);
}

/// The planner's work and memory as benchmark counters (what issue 11 asks to report).
void report_plan(benchmark::State& state, const cscam::plan::Plan& p, std::array<int, 2> rotaries) {
  state.counters["cells_enumerated"] = static_cast<double>(p.counters.cells_enumerated);
  state.counters["cells_evaluated"] = static_cast<double>(p.counters.ik);
  state.counters["collision_queries"] = static_cast<double>(p.counters.collision);
  state.counters["certified"] = static_cast<double>(p.counters.certified);
  state.counters["witnessed"] = static_cast<double>(p.counters.witnessed);
  state.counters["sweeps"] = static_cast<double>(p.counters.swept);
  state.counters["swept_queries"] = static_cast<double>(p.counters.swept_queries);
  state.counters["swept_collisions"] = static_cast<double>(p.swept.collisions);
  state.counters["planner_s"] = p.seconds;
  state.counters["peak_rss_mb"] = peak_rss_mb();
  // The answer's quality beside its cost: a faster search must not buy its speed with a longer rotary path.
  double travel_rad = 0.0;
  for (std::size_t k = 1; k < p.axes.size(); ++k)
    for (const int j : rotaries) travel_rad += std::abs(p.axes[k][j] - p.axes[k - 1][j]);
  state.counters["rotary_travel_deg"] = cscam::rad2deg(travel_rad);
}

void BM_PlanHard(benchmark::State& state) {
  auto& f = hard_fixture();
  const int n = static_cast<int>(state.range(0));
  const auto prog = hard_path(n);
  cscam::plan::Options o;
  o.cspace.cone_rad = cscam::deg2rad(8.0);
  o.cspace.ball_radius_mm = 5;
  o.cspace.check_collision = true;
  // In windows of range(1) moves (the cone near the vertical holds thousands of cells per point: bounded memory);
  // 0: automatic, as `cscam plan` cuts them (by the cell budget).
  cscam::plan::WindowOptions w;
  w.window = static_cast<std::size_t>(state.range(1));
  cscam::plan::Plan p;
  for (auto _ : state) p = cscam::plan::plan_windowed(f.m, f.m.kinematics(), &f.scene, &f.tool, o, prog, w);
  // The share of the cone's cells that collisions remove, over 50 points spread along the path (every cell).
  const cscam::cspace::Space sp(f.m.kinematics(), &f.scene, &f.tool, o.cspace);
  cscam::geom::QueryWorkspace ws;
  cscam::cspace::Counters c;
  double cells = 0, colliding = 0;
  for (int i = 0; i < 50; ++i) {
    const auto& mv = prog.moves[static_cast<size_t>(i) * prog.moves.size() / 50];
    std::vector<cscam::cspace::Cell> cs;
    sp.enumerate({mv.tip_in_part_mm, mv.axis_in_part.normalized()}, cs, std::numeric_limits<std::size_t>::max(), c);
    for (auto& cell : cs) {
      sp.evaluate({mv.tip_in_part_mm, mv.axis_in_part.normalized()}, cell, ws, c);
      cells += 1;
      colliding += cell.status == cscam::cspace::Status::Collision;
    }
  }
  int tier = 0;
  for (const auto& g : p.segments) tier = std::max(tier, static_cast<int>(g.tier));
  state.counters["points"] = n;
  state.counters["triangles"] = static_cast<double>(f.triangles);
  state.counters["tier"] = tier;
  state.counters["windows"] = static_cast<double>(p.windows);
  state.counters["cone_cells_colliding_pct"] = 100.0 * colliding / std::max(1.0, cells);
  report_plan(state, p, f.m.kinematics()->rotary_pair());
}
// 10,000 points is the target (windows of 1000 moves, and the automatic windows); 1,000 for a quick look.
BENCHMARK(BM_PlanHard)
    ->Args({1000, 1000})
    ->Args({10000, 1000})
    ->Args({10000, 0})
    ->Unit(benchmark::kMillisecond)
    ->Iterations(1);

/// 1,000,000 points (the easy groove finishing pass, cone 5, collision on), planned in windows of range(0) moves
/// (plan_windowed; 0: the automatic window): time and peak memory (of the whole process, the 200,000-triangle part
/// and the 1M-move program and plan included).
void BM_Plan1M(benchmark::State& state) {
  auto& f = fixture();
  const auto prog = path(1000000);
  cscam::plan::Options o;
  o.cspace.cone_rad = cscam::deg2rad(5.0);
  o.cspace.ball_radius_mm = 5;
  o.cspace.check_collision = true;
  cscam::plan::WindowOptions w;
  w.window = static_cast<std::size_t>(state.range(0));
  const double rss_before = rss_now_mb();  // the part, its BVH and the 1M-move program
  cscam::plan::Plan p;
  for (auto _ : state) p = cscam::plan::plan_windowed(f.m, f.m.kinematics(), &f.scene, &f.tool, o, prog, w);
  int tier = 0;
  for (const auto& g : p.segments) tier = std::max(tier, static_cast<int>(g.tier));
  state.counters["points"] = 1e6;
  state.counters["rss_before_plan_mb"] = rss_before;
  state.counters["window"] = static_cast<double>(cscam::plan::effective_window(prog.moves.size(), w));
  state.counters["tier"] = tier;
  report_plan(state, p, f.m.kinematics()->rotary_pair());
}
BENCHMARK(BM_Plan1M)->Arg(0)->Unit(benchmark::kMillisecond)->Iterations(1);

/// NX's real path (348 points, Haas UMC-750 with its machine bodies) at cone 5, as `cscam plan --cone 5` runs it.
void BM_PlanNxCone5(benchmark::State& state) {
  const auto m = cscam::machine::load(std::string(CSCAM_SOURCE_DIR) + "/machines/haas-umc750.yaml");
  const auto prog = cscam::cl::read_file(std::string(CSCAM_SOURCE_DIR) + "/examples/nx-haas-umc750/variable_axis.cls");
  // As plan_cmd's setup: the CL's cutter with the machine's holder, the machine bodies in the scene.
  const cscam::cl::Tool* t = nullptr;
  for (const auto& tt : prog.tools)
    if (tt.diameter_mm > 0 && !t) t = &tt;
  if (!t) {
    state.SkipWithError("no cutter in the NX file");
    return;
  }
  cscam::geom::ToolDefaults d;
  if (m.geometry.holder_diameter_mm > 0) d.holder_diameter_mm = m.geometry.holder_diameter_mm;
  if (m.geometry.holder_length_mm > 0) d.holder_length_mm = m.geometry.holder_length_mm;
  if (m.geometry.spindle_diameter_mm > 0) d.spindle = {m.geometry.spindle_diameter_mm, m.geometry.spindle_length_mm};
  const auto tool = cscam::geom::ToolShape::from_cutter(t->diameter_mm, t->corner_radius_mm,
                                                        t->length_mm > 0 ? t->length_mm : 3.0 * t->diameter_mm, d);
  const auto kin = m.make_kinematics(m.default_tool_length_mm);
  cscam::geom::Scene scene, head;
  const auto bodies = cscam::cspace::add_machine_bodies(m, std::max(0.0, tool.gauge_length_mm()), scene, head);
  if (bodies.head_bodies) head.build(false);
  scene.build(false);
  cscam::plan::Options o;
  o.cspace.cone_rad = cscam::deg2rad(static_cast<double>(state.range(0)));
  if (t->is_ball()) o.cspace.ball_radius_mm = 0.5 * t->diameter_mm;
  o.cspace.check_collision = true;
  cscam::plan::Plan p;
  for (auto _ : state)
    p = cscam::plan::plan_windowed(m, kin, &scene, &tool, o, prog, {}, bodies.head_bodies ? &head : nullptr);
  int tier = 0;
  for (const auto& g : p.segments) tier = std::max(tier, static_cast<int>(g.tier));
  state.counters["points"] = static_cast<double>(prog.moves.size());
  state.counters["tier"] = tier;
  report_plan(state, p, kin->rotary_pair());
}
BENCHMARK(BM_PlanNxCone5)->Arg(5)->Unit(benchmark::kMillisecond)->Iterations(1);

}  // namespace

BENCHMARK_MAIN();
