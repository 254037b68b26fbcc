#include "plan_cmd.hpp"

#include <fmt/format.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <memory>
#include <sstream>

#include "cscam/cl/program.hpp"
#include "cscam/core/atomic_file.hpp"
#include "cscam/core/error.hpp"
#include "cscam/core/units.hpp"
#include "cscam/geom/mesh.hpp"
#include "cscam/geom/scene.hpp"
#include "cscam/machine/machine.hpp"
#include "cscam/nc/reader.hpp"
#include "cscam/gate/gate.hpp"
#include "cscam/plan/plan.hpp"
#include "cscam/post/post.hpp"
#include "cscam/report/json.hpp"
#include "cscam/report/letters.hpp"
#include "cscam/report/stats.hpp"
#include "cscam/report/svg.hpp"
#include "cscam/report/verify.hpp"

namespace fs = std::filesystem;

namespace cscam::cli {

namespace {

struct PlanArgs {
  std::string cl, machine, out, dialect, units, svg_dir, json_out;
  std::vector<std::string> parts, fixtures;
  double cone_deg = 0, min_tilt_deg = 0, resolution_deg = 1.0, clearance_mm = 0.5, tool_length = 0, tolerance = 0;
  double max_step_deg = 0, mesh_scale = 1.0, tilt_step_deg = 0;
  double default_feed = 0;  ///< mm/min for feed moves without a feed rate; 0: such a CL file is an error
  bool no_collision = false, json = false;
};

/// Everything a planning run needs, loaded once from the arguments.
struct Setup {
  machine::Machine m;
  cl::Program prog;
  std::shared_ptr<const kin::Kinematics> kin;
  geom::Scene scene;
  geom::Scene head;  ///< machine meshes that move with the spindle
  bool has_head = false;
  std::unique_ptr<geom::ToolShape> tool;
  plan::Options opt;
  double tool_length = 0;
  bool has_meshes = false;
};

std::unique_ptr<Setup> setup(const PlanArgs& a) {
  auto s = std::make_unique<Setup>();
  s->m = machine::load(resolve_machine(a.machine));
  cl::ReadOptions ro;
  ro.units = parse_units(a.units);
  ro.require_feed = true;
  if (a.default_feed > 0) ro.default_feed_mm_per_min = a.default_feed;
  s->prog = cl::read_file(a.cl, ro);
  for (const auto& w : s->prog.warnings) std::cerr << "warning: " << w.where.str() << ": " << w.message << "\n";
  s->tool_length = post::tool_length_for(s->m, a.tool_length);
  s->kin = s->m.make_kinematics(s->tool_length);
  for (const auto& p : a.parts)
    s->scene.add(fs::path(p).filename().string(), geom::ObstacleRole::Part, geom::load_mesh(p, a.mesh_scale));
  for (const auto& p : a.fixtures)
    s->scene.add(fs::path(p).filename().string(), geom::ObstacleRole::Fixture, geom::load_mesh(p, a.mesh_scale));
  // Machine meshes from the machine file: the table moves with the part (fixed in the part frame), the head
  // moves with the spindle. Both are given in the machine frame at home.
  if (!s->m.geometry.table_mesh.empty()) {
    geom::Mesh table = geom::load_mesh(s->m.geometry.table_mesh);
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    if (s->m.serial) T.translation() = -s->m.serial->part_origin_home_mm;
    table.transform(T);
    s->scene.add("machine table", geom::ObstacleRole::Fixture, std::move(table));
  }
  if (!s->m.geometry.head_mesh.empty()) {
    s->head.add("machine head", geom::ObstacleRole::Machine, geom::load_mesh(s->m.geometry.head_mesh));
    s->head.build(false);
    s->has_head = true;
  }
  s->scene.build(false);  // collision only: nothing asks for distances
  // The tool: from the CL (first tool), the rest from the machine file's holder settings.
  const cl::Tool* t = nullptr;
  for (const auto& tt : s->prog.tools)
    if (tt.diameter_mm > 0) {
      t = &tt;
      break;
    }
  auto& o = s->opt;
  o.cspace.cone_rad = deg2rad(a.cone_deg);
  o.cspace.min_tilt_rad = deg2rad(a.min_tilt_deg);
  o.cspace.resolution_rad = deg2rad(a.resolution_deg);
  o.max_step_rad = deg2rad(a.max_step_deg);
  o.tilt_step_rad = deg2rad(a.tilt_step_deg);
  o.cspace.collision.clearance_mm = a.clearance_mm;
  // On a parallel machine the actuated legs' reversals count too (every Cartesian move moves every leg).
  if (s->kin->traits().parallel)
    for (int i = 0; i < 5; ++i)
      if (!s->m.axes[static_cast<size_t>(i)].rotary()) o.monotone_axes.push_back(i);
  const bool meshes = !a.parts.empty() || !a.fixtures.empty() || !s->m.geometry.table_mesh.empty() || s->has_head;
  s->has_meshes = meshes;
  o.cspace.check_collision = meshes && !a.no_collision;
  if (meshes && !t)
    throw InputError(SourceLoc{a.cl},
                     "collision checking needs the cutter size: the CL file has no CUTTER/ or TLDATA/");
  if (t) {
    geom::ToolDefaults d;
    if (s->m.geometry.holder_diameter_mm > 0) d.holder_diameter_mm = s->m.geometry.holder_diameter_mm;
    if (s->m.geometry.holder_length_mm > 0) d.holder_length_mm = s->m.geometry.holder_length_mm;
    if (s->m.geometry.spindle_diameter_mm > 0)
      d.spindle = {s->m.geometry.spindle_diameter_mm, s->m.geometry.spindle_length_mm};
    const double flute = t->length_mm > 0 ? t->length_mm : 3.0 * t->diameter_mm;
    s->tool =
        std::make_unique<geom::ToolShape>(geom::ToolShape::from_cutter(t->diameter_mm, t->corner_radius_mm, flute, d));
    if (t->is_ball()) o.cspace.ball_radius_mm = 0.5 * t->diameter_mm;
  }
  return s;
}

std::string post_to_string(const Setup& s, const cl::Program& prog, const std::vector<kin::Axes>& axes,
                           const PlanArgs& a, const std::string& strategy, post::Summary& sum) {
  post::Options po;
  po.dialect = a.dialect;
  po.tolerance_mm = a.tolerance;
  po.source_name = fs::path(a.cl).filename().string();
  po.strategy = strategy;
  po.tool_length_mm = s.tool_length;
  // A tilted ball mill keeps its centre on the CL path: post (and verify) the centre. At cone 0 the
  // orientation is the CL's and the tip is controlled as usual.
  if (strategy != "conventional" && s.opt.cspace.cone_rad > 0) po.control_offset_mm = s.opt.cspace.ball_radius_mm;
  std::ostringstream os;
  post::write_nc(os, prog, s.m, *s.kin, axes, po, sum);
  return os.str();
}

report::Stats stats_of(const Setup& s, const std::string& text, const std::string& name) {
  std::array<std::string, 5> names;
  std::array<bool, 5> rot{};
  for (size_t i = 0; i < 5; ++i) {
    names[i] = s.m.post.letters[i];
    rot[i] = s.m.axes[i].rotary();
  }
  auto st = report::compute(nc::read_text(text, name, report::axis_letters(s.m)), names, rot);
  st.source = name;
  return st;
}

/// The safety gate's options for a program of this run; with meshes, rapids are checked against them.
gate::Options gate_options(const Setup& s, const PlanArgs& a, double cone_deg) {
  gate::Options g = gate::options_for(s.m, a.tolerance, 0.0, cone_deg);
  if (s.has_meshes && s.tool) {
    cspace::Options co = s.opt.cspace;
    co.check_collision = true;
    auto space = std::make_shared<const cspace::Space>(s.kin, &s.scene, s.tool.get(), co, s.has_head ? &s.head : nullptr);
    auto ws = std::make_shared<geom::QueryWorkspace>();
    auto cc = std::make_shared<cspace::Counters>();
    g.collision = [space, ws, cc](const kin::Axes& q) { return space->collision_at_axes(q, *ws, *cc); };
  }
  return g;
}

report::VerifyResult verify_text(const Setup& s, const std::string& text, double cone_deg) {
  const report::VerifyOptions vo = report::verify_options_for(s.m, 0.0, 0.0, cone_deg);
  return report::verify(nc::read_text(text, "planned.ngc", report::axis_letters(s.m)), s.prog, *s.kin, vo);
}

void write_svgs(const Setup& s, const plan::Planner& planner, const plan::Plan& p, const std::vector<kin::Axes>& conv,
                const std::string& dir) {
  fs::create_directories(dir);
  const auto rp = s.kin->rotary_pair();
  const std::string n1 = s.m.post.letters[static_cast<size_t>(rp[0])],
                    n2 = s.m.post.letters[static_cast<size_t>(rp[1])];
  for (std::size_t g = 0; g < p.segments.size(); ++g) {
    const auto& seg = p.segments[g];
    if (seg.last_move == seg.first_move) continue;
    const auto sp = planner.sample_segment(s.prog, p, g);
    const std::string title = fmt::format("C-space of segment {} (CL lines {}-{}): {}", g + 1, seg.first_line,
                                          seg.last_line, plan::to_string(seg.tier));
    write_file_atomically((fs::path(dir) / fmt::format("segment{}_cspace.svg", g + 1)).string(),
                          [&](std::ostream& os) { os << report::cspace_svg(sp, n1, n2, title); });
    write_file_atomically((fs::path(dir) / fmt::format("segment{}_axes.svg", g + 1)).string(), [&](std::ostream& os) {
      os << report::axis_plot_svg({conv, p.axes}, {"conventional", "planner"}, rp, {n1, n2}, seg.first_move,
                                  seg.last_move, fmt::format("Rotary axes along segment {}", g + 1));
    });
  }
}

int run_plan(const PlanArgs& a) {
  auto s = setup(a);
  const plan::Planner planner(s->m, s->kin, &s->scene, s->tool.get(), s->opt, s->has_head ? &s->head : nullptr);
  const plan::Plan p = planner.run(s->prog);
  post::Summary sum;
  const std::string text = post_to_string(*s, p.program, p.axes, a, "cspace-planner", sum);
  const std::string out = a.out.empty() ? fs::path(a.cl).stem().string() + ".planned.ngc" : a.out;
  const gate::Summary v =
      gate::write_checked(out, text, p.program, s->m, *s->kin, gate_options(*s, a, a.cone_deg), &sum.cl_line_of_nc_line);
  if (!a.svg_dir.empty()) write_svgs(*s, planner, p, post::conventional_axes(s->prog, s->m, *s->kin), a.svg_dir);
  std::cout << p.summary();
  std::cout << fmt::format("wrote {} ({} blocks); verify: {}\n", out, sum.blocks, v.message);
  std::cout << fmt::format("planner: {:.3f} s, {} cells enumerated, {} IK, {} stroke and {} collision queries\n",
                           p.seconds, p.counters.cells_enumerated, p.counters.ik, p.counters.stroke,
                           p.counters.collision);
  return 0;
}

int run_compare(const PlanArgs& a) {
  auto s = setup(a);
  const auto t0 = std::chrono::steady_clock::now();
  const auto conv = post::conventional_axes(s->prog, s->m, *s->kin);
  post::Summary sc;
  const std::string conv_text = post_to_string(*s, s->prog, conv, a, "conventional", sc);
  const double conv_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const plan::Planner planner(s->m, s->kin, &s->scene, s->tool.get(), s->opt, s->has_head ? &s->head : nullptr);
  const plan::Plan p = planner.run(s->prog);
  post::Summary sp;
  const std::string plan_text = post_to_string(*s, p.program, p.axes, a, "cspace-planner", sp);
  const auto vc = verify_text(*s, conv_text, 0.0);
  const auto vp = verify_text(*s, plan_text, a.cone_deg);
  auto stc = stats_of(*s, conv_text, "conventional");
  auto stp = stats_of(*s, plan_text, "planner");
  // An independent collision check of both programs against the meshes (even when the planner was told
  // to ignore them): FK of every CL point's axis values, tool vs scene.
  struct Hits {
    std::size_t n = 0;
    int first_line = 0;
  };
  auto count_collisions = [&](const std::vector<kin::Axes>& axes) {
    Hits h;
    if (!s->has_meshes || !s->tool) return h;
    cspace::Options co = s->opt.cspace;
    co.check_collision = true;
    geom::QueryWorkspace ws;
    cspace::Counters cc;
    const cspace::Space space_h(s->kin, &s->scene, s->tool.get(), co, s->has_head ? &s->head : nullptr);
    for (std::size_t i = 0; i < s->prog.moves.size(); ++i)
      if (!space_h.collision_at_axes(axes[i], ws, cc).empty()) {
        if (!h.n) h.first_line = s->prog.moves[i].line;
        ++h.n;
      }
    return h;
  };
  const Hits hc = count_collisions(conv), hp = count_collisions(p.axes);
  const std::size_t conv_collisions = hc.n;
  std::string tiers;
  int counts[5] = {0, 0, 0, 0, 0};
  for (const auto& g : p.segments) ++counts[static_cast<int>(g.tier)];
  tiers = fmt::format("{} / {} / {} / {}", counts[1], counts[2], counts[3], counts[4]);
  std::cout << fmt::format("cone {:.2f} deg, resolution {:.3f} deg, collision {}\n", a.cone_deg, a.resolution_deg,
                           s->opt.cspace.check_collision ? "on" : "off");
  std::cout << report::table({stc, stp}, {"conventional", "planner"});
  std::cout << fmt::format("{:<28}{:>22}{:>22}\n", "NC blocks", sc.blocks, sp.blocks);
  std::cout << fmt::format("{:<28}{:>22}{:>22}\n", "verify", vc.ok ? "ok" : "FAILED", vp.ok ? "ok" : "FAILED");
  if (s->has_meshes) std::cout << fmt::format("{:<28}{:>22}{:>22}\n", "colliding CL points", hc.n, hp.n);
  std::cout << fmt::format("{:<28}{:>22}{:>22}\n", "segment tiers 1/2/3/4", "-", tiers);
  std::cout << fmt::format("{:<28}{:>22.3f}{:>22.3f}\n", "time (s)", conv_s, p.seconds);
  std::cout << fmt::format("planner queries: {} cells, {} IK, {} stroke, {} collision\n", p.counters.cells_enumerated,
                           p.counters.ik, p.counters.stroke, p.counters.collision);
  std::cout << p.summary();
  if (hc.n)
    std::cout << fmt::format("the conventional program collides at {} CL points (first at CL line {})\n", hc.n,
                             hc.first_line);
  if (hp.n)
    std::cout << fmt::format("the planned program collides at {} CL points (first at CL line {}){}\n", hp.n,
                             hp.first_line, s->opt.cspace.check_collision ? "" : ": collision pruning was off");
  nlohmann::json tier_list = nlohmann::json::array();
  for (const auto& g : p.segments) tier_list.push_back(static_cast<int>(g.tier));
  const nlohmann::json jc = {{"cl", a.cl},
                             {"machine", s->m.name},
                             {"cone_deg", a.cone_deg},
                             {"resolution_deg", a.resolution_deg},
                             {"collision", s->opt.cspace.check_collision},
                             {"conventional",
                              {{"stats", stc.json()},
                               {"blocks", sc.blocks},
                               {"verify_ok", vc.ok},
                               {"colliding_points", conv_collisions},
                               {"seconds", report::rounded(conv_s, 4)}}},
                             {"planner",
                              {{"stats", stp.json()},
                               {"blocks", sp.blocks},
                               {"verify_ok", vp.ok},
                               {"colliding_points", hp.n},
                               {"seconds", report::rounded(p.seconds, 4)},
                               {"tiers", std::move(tier_list)},
                               {"queries",
                                {{"cells", p.counters.cells_enumerated},
                                 {"ik", p.counters.ik},
                                 {"stroke", p.counters.stroke},
                                 {"collision", p.counters.collision}}}}}};
  const std::string json = jc.dump(2) + "\n";
  // Default: beside the working directory, never next to the (possibly read-only) input.
  const std::string json_path = a.json_out.empty() ? fs::path(a.cl).stem().string() + ".compare.json" : a.json_out;
  write_file_atomically(json_path, [&](std::ostream& os) { os << json; });
  std::cout << "JSON: " << json_path << "\n";
  if (!a.out.empty())
    gate::write_checked(a.out, plan_text, p.program, s->m, *s->kin, gate_options(*s, a, a.cone_deg),
                        &sp.cl_line_of_nc_line);
  if (!a.svg_dir.empty()) write_svgs(*s, planner, p, conv, a.svg_dir);
  return vp.ok ? 0 : 1;
}

void common_options(CLI::App* c, PlanArgs& a) {
  c->add_option("cl", a.cl, "CL file")->required();
  c->add_option("-m,--machine", a.machine, "machine file or bundled machine name")->required();
  c->add_option("--part", a.parts, "part mesh(es) (STL, OBJ, PLY, ...)");
  c->add_option("--fixture", a.fixtures, "fixture mesh(es)");
  c->add_option("--mesh-scale", a.mesh_scale, "multiply mesh coordinates by this to get mm");
  c->add_option("--cone", a.cone_deg, "allowed tool-axis deviation from the CL axis, deg (0: exact)");
  c->add_option("--min-tilt", a.min_tilt_deg, "minimum tilt from the CL axis (ball mills), deg");
  c->add_option("--resolution", a.resolution_deg, "C-space grid resolution, deg")->check(CLI::PositiveNumber);
  c->add_option("--tilt-step", a.tilt_step_deg,
                "tilt grid inside the cone for the leg (PKM) re-plan, deg (default: resolution)");
  c->add_option("--max-step", a.max_step_deg, "shortest-path tier: largest rotary step per point, deg");
  c->add_option("--clearance", a.clearance_mm, "collision clearance of shank, holder and spindle, mm");
  c->add_option("--tool-length", a.tool_length, "gauge-to-tip tool length, mm");
  c->add_option("--tolerance", a.tolerance, "post linearisation tolerance, mm");
  c->add_option("--dialect", a.dialect, "post dialect override");
  c->add_option("--units", a.units, "force CL units (mm or inch)");
  c->add_option("--default-feed", a.default_feed,
                "feed, mm/min, for cutting moves the CL gives no feed rate for (default: such a CL is an error)")
      ->check(CLI::PositiveNumber);
  c->add_option("--svg", a.svg_dir, "write C-space and axis pictures into this directory");
  c->add_flag("--no-collision", a.no_collision, "ignore the meshes (to show what the plan would hit)");
}

}  // namespace

std::function<int()> add_plan_commands(CLI::App& app) {
  auto args = std::make_shared<PlanArgs>();
  auto* plan_cmd = app.add_subcommand("plan", "Plan tool orientations in the rotary C-space and write the NC program");
  common_options(plan_cmd, *args);
  plan_cmd->add_option("-o,--output", args->out, "NC file to write");
  auto* cmp = app.add_subcommand("compare", "Conventional post vs C-space planner: travel, reversals, tiers");
  common_options(cmp, *args);
  cmp->add_option("--json-out", args->json_out, "where to write the JSON comparison (default: CL name .compare.json)");
  cmp->add_option("-o,--output", args->out, "also write the planned NC program here");
  return [args, plan_cmd, cmp]() -> int {
    if (*plan_cmd) return run_plan(*args);
    if (*cmp) return run_compare(*args);
    return -1;
  };
}

}  // namespace cscam::cli
