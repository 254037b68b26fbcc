#include "plan_cmd.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <memory>
#include <sstream>

#include "cscam/cl/program.hpp"
#include "cscam/core/atomic_file.hpp"
#include "cscam/core/error.hpp"
#include "cscam/core/tolerances.hpp"
#include "cscam/core/units.hpp"
#include "cscam/cspace/machine_scene.hpp"
#include "cscam/gate/gate.hpp"
#include "cscam/geom/mesh.hpp"
#include "cscam/geom/mesh_check.hpp"
#include "cscam/geom/scene.hpp"
#include "cscam/machine/machine.hpp"
#include "cscam/nc/reader.hpp"
#include "cscam/plan/plan.hpp"
#include "cscam/plan/stream.hpp"
#include "cscam/post/post.hpp"
#include "cscam/report/json.hpp"
#include "cscam/report/letters.hpp"
#include "cscam/report/stats.hpp"
#include "cscam/report/svg.hpp"
#include "cscam/report/verify.hpp"
#include "validators.hpp"

namespace fs = std::filesystem;

namespace cscam::cli {

namespace {

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
  std::vector<geom::MeshCheckReport> mesh_reports;  ///< validation of every mesh file loaded
  std::size_t machine_bodies = 0;
  bool planner_ignores_machine = false;          ///< --no-machine-geometry
  std::vector<std::string>* warnings = nullptr;  ///< where warnings go (batch); null: printed to stderr
  void warn(const std::string& message) const {
    if (warnings)
      warnings->push_back(message);
    else
      std::cerr << "warning: " << message << "\n";
  }
  /// The head scene the planner sees.
  [[nodiscard]] const geom::Scene* planner_head() const {
    return has_head && !planner_ignores_machine ? &head : nullptr;
  }
};

/// Says what validation repaired in a mesh, and what it warns about, as warnings of the run.
void warn_mesh_report(const Setup& s, const std::string& path, const geom::MeshCheckReport& r) {
  for (const auto& line : r.repairs) s.warn(fmt::format("{}: repaired: {}", path, line));
  for (const auto& line : r.warnings) s.warn(fmt::format("{}: {}", path, line));
}

/// A part, fixture or machine mesh file, validated and repaired (what was repaired becomes a warning).
geom::Mesh checked_mesh(Setup& s, const std::string& path, double scale) {
  geom::MeshCheckReport r;
  geom::Mesh mesh = geom::load_checked_mesh(path, scale, {}, &r);
  warn_mesh_report(s, path, r);
  s.mesh_reports.push_back(std::move(r));
  return mesh;
}

nlohmann::json mesh_reports_json(const Setup& s) {
  nlohmann::json out = nlohmann::json::array();
  for (const auto& r : s.mesh_reports)
    out.push_back({{"source", r.source},
                   {"triangles_in", r.triangles_in},
                   {"triangles_out", r.triangles_out},
                   {"closed", r.closed},
                   {"components", r.components},
                   {"volume_mm3", std::isfinite(r.volume_mm3) ? nlohmann::json(report::rounded(r.volume_mm3, 3))
                                                              : nlohmann::json(nullptr)},
                   {"duplicate_vertices_merged", r.duplicate_vertices_merged},
                   {"degenerate_faces_removed", r.degenerate_faces_removed + r.repeated_index_faces_removed},
                   {"duplicate_faces_removed", r.duplicate_faces_removed},
                   {"border_edges_stitched", r.border_edges_stitched},
                   {"faces_reoriented", r.faces_reoriented},
                   {"component_overlaps", r.component_overlaps},
                   {"repairs", r.repairs},
                   {"warnings", r.warnings}});
  return out;
}

/// The collision scene of a run: the part and fixture meshes, the machine file's table and head meshes and bodies, and
/// the checked tool from the CL's first cutter with the machine's holder; the planner's options from `a`. Without a
/// cutter size: an error with `require_tool`, else a warning and no collision checks.
void add_scene(Setup& s, const PlanArgs& a, const std::vector<cl::Tool>& tools, bool require_tool);

/// The planner's options that no machine can use, refused before any work: a cone past the horizontal, a grid coarser
/// than any cone it could resolve or so fine that a few points fill the memory, a negative clearance, an SVG folder
/// that is a file.
void check_plan_args(const PlanArgs& a) {
  if (!(a.cone_deg >= 0.0 && a.cone_deg <= 90.0))
    throw InputError(
        fmt::format("--cone {}: expected 0..90 deg (the deviation of the tool axis from the CL axis)", a.cone_deg));
  if (!(a.resolution_deg > 0.0 && a.resolution_deg <= 30.0))
    throw InputError(fmt::format("--resolution {}: expected a grid step in (0, 30] deg", a.resolution_deg));
  // Cells of the cone at every CL point: the C-space rows the search keeps grow with it.
  constexpr double kMaxConeCells = 50000.0;
  const double cells = kPi * std::pow(a.cone_deg / a.resolution_deg, 2);
  if (cells > kMaxConeCells)
    throw InputError(
        fmt::format("--resolution {} deg at --cone {} deg gives about {:.0f} grid cells at every CL point "
                    "(at most {:.0f}, or the search outgrows the memory): coarsen the resolution to at "
                    "least {:.2f} deg",
                    a.resolution_deg, a.cone_deg, cells, kMaxConeCells, a.cone_deg * std::sqrt(kPi / kMaxConeCells)));
  if (!(a.clearance_mm >= 0.0) || !std::isfinite(a.clearance_mm))
    throw InputError(fmt::format("--clearance {}: expected a distance >= 0 mm", a.clearance_mm));
  if (!a.svg_dir.empty() && fs::exists(a.svg_dir) && !fs::is_directory(a.svg_dir))
    throw InputError(SourceLoc{a.svg_dir}, "--svg: exists and is not a folder");
}

/// The first tool with a size (CUTTER/ or TLDATA/): the cutter the checks use until a tool change says otherwise.
const cl::Tool* first_sized_tool(const std::vector<cl::Tool>& tools) {
  for (const auto& t : tools)
    if (t.diameter_mm > 0) return &t;
  return nullptr;
}

/// The planner checks every move with one cutter (the CL's first) and, tilting a ball mill, keeps that ball's centre on
/// the path: where the program changes to a cutter of another shape, the later moves would be checked and posted for
/// the wrong one (the safety gate then refuses the plan, or a collision of the real cutter goes unseen). Refused at the
/// first move cut with it, while the cutter matters (collision checks, or a cone with a ball mill).
void refuse_a_second_cutter(const Setup& s) {
  const bool ball_cone = s.opt.cspace.cone_rad > 0 && std::any_of(s.prog.tools.begin(), s.prog.tools.end(),
                                                                  [](const cl::Tool& t) { return t.is_ball(); });
  if (!s.opt.cspace.check_collision && !ball_cone) return;
  const cl::Tool* first = nullptr;
  for (const auto& mv : s.prog.moves) {
    if (mv.tool_index < 0) continue;
    const cl::Tool& t = s.prog.tools[static_cast<std::size_t>(mv.tool_index)];
    if (!(t.diameter_mm > 0)) continue;
    if (!first) {
      first = &t;
      continue;
    }
    if (!t.same_shape(*first))
      throw InputError(
          SourceLoc{s.prog.file, mv.line, 0},
          fmt::format("this move is cut with {} (diameter {:g}, corner radius {:g}, length {:g} mm) after {} "
                      "(diameter {:g}, corner radius {:g}, length {:g} mm): the planner plans one cutter per run; plan "
                      "each tool's operations as a CL file of its own",
                      t.number > 0 ? fmt::format("tool {}", t.number) : std::string("a cutter"), t.diameter_mm,
                      t.corner_radius_mm, t.length_mm,
                      first->number > 0 && first->number != t.number ? fmt::format("tool {}", first->number)
                                                                     : std::string("another cutter"),
                      first->diameter_mm, first->corner_radius_mm, first->length_mm));
  }
}

std::unique_ptr<Setup> setup(const PlanArgs& a, std::vector<std::string>* warnings = nullptr) {
  check_plan_args(a);
  auto s = std::make_unique<Setup>();
  s->warnings = warnings;
  s->m = machine::load(resolve_machine(a.machine));
  cl::ReadOptions ro;
  ro.units = parse_units(a.units);
  ro.require_feed = true;
  if (a.default_feed > 0) ro.default_feed_mm_per_min = a.default_feed;
  s->prog = cl::read_file(a.cl, ro);
  for (const auto& w : s->prog.warnings) s->warn(w.where.str() + ": " + w.message);
  // On a head-side rotary machine the tool length is part of the kinematics: from the option, else the CL's
  // tool, else the machine default with a warning (as the post command does).
  std::string tool_note;
  s->tool_length = post::tool_length_for(s->m, a.tool_length, s->prog, tool_note);
  if (!tool_note.empty()) s->warn(tool_note);
  s->kin = s->m.make_kinematics(s->tool_length);
  add_scene(*s, a, s->prog.tools, true);
  refuse_a_second_cutter(*s);
  return s;
}

/// A part or fixture mesh far from the CL path (another origin, or units), or a part far smaller than the cutting moves
/// that 25.4 times larger would meet them (inches read as mm): it would constrain nothing, and the plan would be
/// "collision-free" against it. (Not with --mesh-scale given: the user has chosen the unit.)
void warn_if_off_the_path(Setup& s, const std::string& path, const geom::Mesh& mesh, geom::ObstacleRole role,
                          double a_scale) {
  Eigen::AlignedBox3d cl_box;
  for (const auto& mv : s.prog.moves) cl_box.extend(mv.tip_in_part_mm);
  const Eigen::AlignedBox3d box = mesh.bounding_box();
  if (cl_box.isEmpty() || box.isEmpty()) return;
  const Eigen::Vector3d gap =
      (box.min() - cl_box.max()).cwiseMax(cl_box.min() - box.max()).cwiseMax(Eigen::Vector3d::Zero());
  const double reach_mm = s.tool_length + 100.0;  // the tool and its holder reach no further from the tip
  if (gap.norm() > reach_mm) {
    s.warn(fmt::format(
        "{}: the mesh lies {:.0f} mm from the CL path (its box x {:.1f}..{:.1f}, y {:.1f}..{:.1f}, z "
        "{:.1f}..{:.1f} mm): nothing of the tool reaches it; another origin or unit (--mesh-scale)?",
        path, gap.norm(), box.min().x(), box.max().x(), box.min().y(), box.max().y(), box.min().z(), box.max().z()));
    return;
  }
  // A part in inches read as mm sits near the origin at 1/25.4 of its size, often inside the path's box: the
  // cutting moves then span far more than the part does, and the part scaled by 25.4 would meet them.
  if (role != geom::ObstacleRole::Part || a_scale != 1.0) return;
  Eigen::AlignedBox3d cut_box;
  for (const auto& mv : s.prog.moves)
    if (mv.kind != cl::MotionKind::Rapid) cut_box.extend(mv.tip_in_part_mm);
  if (cut_box.isEmpty()) return;
  const double cut_mm = cut_box.diagonal().norm(), part_mm = box.diagonal().norm();
  constexpr double kInch = 25.4;
  const Eigen::AlignedBox3d as_inches(kInch * box.min(), kInch * box.max());
  if (part_mm > 0 && cut_mm > 10.0 * part_mm && as_inches.intersects(cut_box))
    s.warn(
        fmt::format("{}: the part spans {:.2f} mm across but the cutting moves {:.1f} mm; scaled by 25.4 it would "
                    "meet them: a mesh in inches? (--mesh-scale 25.4)",
                    path, part_mm, cut_mm));
}

void add_scene(Setup& s, const PlanArgs& a, const std::vector<cl::Tool>& tools, bool require_tool) {
  for (const auto& [paths, role] :
       {std::pair{&a.parts, geom::ObstacleRole::Part}, std::pair{&a.fixtures, geom::ObstacleRole::Fixture}})
    for (const auto& p : *paths) {
      geom::Mesh mesh = checked_mesh(s, p, a.mesh_scale);
      warn_if_off_the_path(s, p, mesh, role, a.mesh_scale);
      s.scene.add(fs::path(p).filename().string(), role, std::move(mesh));
    }
  // Machine meshes from the machine file: the table moves with the part (fixed in the part frame), the head
  // moves with the spindle. Both are given in the machine frame at home.
  if (!s.m.geometry.table_mesh.empty()) {
    geom::Mesh table = checked_mesh(s, s.m.geometry.table_mesh, 1.0);
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    if (s.m.serial) T.translation() = -s.m.serial->part_origin_home_mm;
    table.transform(T);
    s.scene.add("machine table", geom::ObstacleRole::Fixture, std::move(table));
  }
  if (!s.m.geometry.head_mesh.empty()) {
    s.head.add("machine head", geom::ObstacleRole::Machine, checked_mesh(s, s.m.geometry.head_mesh, 1.0));
    s.has_head = true;
  }
  // The tool: from the CL (first tool), the rest from the machine file's holder settings.
  const cl::Tool* t = first_sized_tool(tools);
  auto& o = s.opt;
  o.cspace.cone_rad = deg2rad(a.cone_deg);
  o.cspace.min_tilt_rad = deg2rad(a.min_tilt_deg);
  o.cspace.resolution_rad = deg2rad(a.resolution_deg);
  o.max_step_rad = deg2rad(a.max_step_deg);
  o.beam_states = a.beam;
  o.tilt_step_rad = deg2rad(a.tilt_step_deg);
  o.cspace.collision.clearance_mm = a.clearance_mm;
  {
    // At cone 0 a jump is planned only where the post can follow it: the post's own rule, with the options the plan is
    // posted with (the tolerance; the plan's tip is the tip there).
    post::Options po;
    po.tolerance_mm = a.tolerance;
    po.strategy = "planned";
    o.can_bridge = [setup = &s, po](const kin::Axes& q0, const kin::Posed& p0, const kin::Axes& q1,
                                    const kin::Posed& p1) {
      return post::can_follow(*setup->kin, setup->m, po, p0, q0, p1, q1);
    };
  }
  // On a parallel machine the actuated legs' reversals count too (every Cartesian move moves every leg).
  if (s.kin->traits().parallel)
    for (int i = 0; i < 5; ++i)
      if (!s.m.axes[static_cast<size_t>(i)].rotary()) o.monotone_axes.push_back(i);
  if (t) {
    const double flute = t->length_mm > 0 ? t->length_mm : 3.0 * t->diameter_mm;
    s.tool =
        std::make_unique<geom::ToolShape>(cspace::tool_on_machine(s.m, t->diameter_mm, t->corner_radius_mm, flute));
    if (t->is_ball()) o.cspace.ball_radius_mm = 0.5 * t->diameter_mm;
  }
  // Machine bodies (geometry.bodies). The head is lifted to where the checked tool shape's holder ends when
  // that is above the kinematic gauge point (tool length 0 on a table-table machine: the control compensates).
  // With --no-machine-geometry the planner ignores them, but the report's independent collision count and the
  // safety gate still check against them (as with --no-collision).
  if (!s.m.geometry.bodies.empty() && !s.tool)
    s.warn(a.cl + ": no CUTTER/ or TLDATA/: the machine's bodies are not checked");
  if (!s.m.geometry.bodies.empty() && s.tool) {
    const double lift = std::max(0.0, s.tool->gauge_length_mm() - s.tool_length);
    auto bodies = cspace::add_machine_bodies(s.m, lift, s.scene, s.head);
    for (auto& r : bodies.mesh_reports) {
      warn_mesh_report(s, r.source, r);
      s.mesh_reports.push_back(std::move(r));
    }
    s.machine_bodies = bodies.fixed_bodies + bodies.head_bodies;
    if (bodies.head_bodies) s.has_head = true;
  }
  if (s.has_head) s.head.build(false);
  s.scene.build(false);  // collision only: nothing asks for distances
  const bool meshes =
      !a.parts.empty() || !a.fixtures.empty() || !s.m.geometry.table_mesh.empty() || s.has_head || s.machine_bodies > 0;
  s.has_meshes = meshes;
  o.cspace.check_collision = meshes && !a.no_collision;
  if (a.no_machine_geometry) {
    o.cspace.collision.roles =
        static_cast<unsigned>(geom::ObstacleRole::Part) | static_cast<unsigned>(geom::ObstacleRole::Fixture);
    s.planner_ignores_machine = true;
  }
  if (meshes && !t) {
    if (require_tool)
      throw InputError(SourceLoc{a.cl},
                       "collision checking needs the cutter size: the CL file has no CUTTER/ or TLDATA/");
    s.warn(a.cl + ": no CUTTER/ or TLDATA/: the moves are not checked against the machine's meshes");
    s.has_meshes = false;
  }
}

/// Posts `prog` at `axes`; a planned program with the CL it was planned from (Plan::reference), whose axes the cone
/// is around.
std::string post_to_string(const Setup& s, const cl::Program& prog, const std::vector<kin::Axes>& axes,
                           const PlanArgs& a, const std::string& strategy, post::Summary& sum,
                           const cl::Program* cone_reference = nullptr) {
  post::Options po;
  po.dialect = a.dialect;
  po.tolerance_mm = a.tolerance;
  po.source_name = fs::path(a.cl).filename().string();
  po.strategy = strategy;
  po.tool_length_mm = s.tool_length;
  po.tcp = a.tcp;
  po.work_plane = a.work_plane;
  // A tilted ball mill keeps its centre on the CL path: post (and verify) the centre. At cone 0 the
  // orientation is the CL's and the tip is controlled as usual.
  if (strategy != "conventional" && s.opt.cspace.cone_rad > 0) po.control_offset_mm = s.opt.cspace.ball_radius_mm;
  if (cone_reference) {
    po.cone_deg = a.cone_deg;
    po.cone_reference = cone_reference;
  }
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
  nc::Program ncp = nc::read_text(text, name, report::axis_letters(s.m));
  report::resolve_work_planes(ncp, s.m);  // tilted-plane words as the machine axes they move
  auto st = report::compute(ncp, names, rot);
  st.source = name;
  return st;
}

/// The safety gate's options for a program of this run; with meshes, rapids are checked against them.
gate::Options gate_options(const Setup& s, const PlanArgs& a, double cone_deg) {
  gate::Options g = gate::options_for(s.m, a.tolerance, 0.0, cone_deg);
  if (s.has_meshes && s.tool) {
    cspace::Options co = s.opt.cspace;
    co.check_collision = true;
    co.collision.roles = geom::kAllRoles;
    auto space =
        std::make_shared<const cspace::Space>(s.kin, &s.scene, s.tool.get(), co, s.has_head ? &s.head : nullptr);
    // One path check per worker: the gate's samples come in path order, so most are covered by a certificate.
    g.make_collision =
        [space](int /*tool_changes: the planner's program has one cutter*/) -> gate::Options::CollisionCheck {
      auto check = std::make_shared<cspace::PathCheck>(space);
      return [check](const kin::Axes& q, bool whole_tool) {
        return (*check)(q, whole_tool ? cspace::SweepMode::Rapid : cspace::SweepMode::Cutting);
      };
    };
  }
  return g;
}

/// Verifies NC text against `ref`: the CL program, or for a planned program Plan::reference (the approach/retract
/// moves the planner re-placed along the chosen tool axis are checked against their planned poses).
report::VerifyResult verify_text(const Setup& s, const std::string& text, double cone_deg, const cl::Program& ref) {
  const report::VerifyOptions vo = report::verify_options_for(s.m, 0.0, 0.0, cone_deg);
  nc::Program ncp = nc::read_text(text, "planned.ngc", report::axis_letters(s.m));
  if (const std::string why = report::resolve_work_planes(ncp, *s.kin); !why.empty()) throw InputError(why);
  return report::verify(ncp, ref, *s.kin, vo);
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

/// The planner's answer, in windows of --window moves (automatic: above 50,000 moves, or by the cell budget) so that
/// memory stays bounded.
plan::Plan planned(const Setup& s, const PlanArgs& a, const geom::Scene* head) {
  plan::WindowOptions w;
  w.window = a.window;
  return plan::plan_windowed(s.m, s.kin, &s.scene, s.tool.get(), s.opt, s.prog, w, head);
}
plan::Plan planned(const Setup& s, const PlanArgs& a) { return planned(s, a, s.planner_head()); }

int run_plan(const PlanArgs& a) {
  auto s = setup(a);
  const plan::Planner planner(s->m, s->kin, &s->scene, s->tool.get(), s->opt, s->planner_head());
  const plan::Plan p = planned(*s, a);
  const cl::Program ref = p.reference(s->prog);
  post::Summary sum;
  const std::string text = post_to_string(*s, p.program, p.axes, a, "cspace-planner", sum, &ref);
  const std::string out = a.out.empty() ? fs::path(a.cl).stem().string() + ".planned.ngc" : a.out;
  const gate::Summary v =
      gate::write_checked(out, text, ref, s->m, *s->kin, gate_options(*s, a, a.cone_deg), &sum.cl_line_of_nc_line);
  if (!a.svg_dir.empty()) write_svgs(*s, planner, p, post::conventional_axes(s->prog, s->m, *s->kin), a.svg_dir);
  for (const auto& x : sum.warnings) s->warn(x);  // the post's (capped feeds, a dialect without planes, ...)
  std::cout << p.summary();
  std::cout << fmt::format("wrote {} ({} blocks); verify: {}\n", out, sum.blocks, v.message);
  std::cout << fmt::format(
      "planner: {:.3f} s, {} cells enumerated, {} IK, {} stroke and {} collision queries, {} more for {} swept "
      "moves, peak memory {:.0f} MB\n",
      p.seconds, p.counters.cells_enumerated, p.counters.ik, p.counters.stroke, p.counters.collision,
      p.counters.swept_queries, p.counters.swept, p.peak_memory_mb);
  return 0;
}

/// Per segment, for compare --json: CL line range, tier and why earlier tiers failed, the fixed values or ranges,
/// rotary travel and reversals, linear travel against the conventional program's, and the swept check. Returns
/// notes for segments whose linear travel a fixed (3+2) orientation made much longer.
std::vector<std::string> segment_reports(const Setup& s, const plan::Plan& p, const std::vector<kin::Axes>* conv,
                                         nlohmann::json& out) {
  std::vector<std::string> notes;
  for (std::size_t g = 0; g < p.segments.size(); ++g) {
    const auto& seg = p.segments[g];
    nlohmann::json fails = nlohmann::json::array();
    for (const auto& f : seg.failures)
      fails.push_back({{"tier", static_cast<int>(f.tier)},
                       {"cl_line", f.line},
                       {"cause", plan::to_string(f.cause)},
                       {"reason", f.reason()}});
    nlohmann::json axes = nlohmann::json::object();
    for (int j = 0; j < 5; ++j) {
      const auto J = static_cast<std::size_t>(j);
      const bool rot = s.m.axes[J].rotary();
      const double scale = rot ? 180.0 / kPi : 1.0,
                   hyst = rot ? tol::kReversalHysteresisDeg : tol::kReversalHysteresisMm;
      auto walk = [&](const std::vector<kin::Axes>& q, double& travel, int& reversals, double& lo, double& hi) {
        travel = 0;
        reversals = 0;
        lo = hi = q[seg.first_move][j] * scale;
        int dir = 0;
        double ext = lo;
        for (std::size_t m = seg.first_move + 1; m <= seg.last_move; ++m) {
          const double v = q[m][j] * scale;
          travel += std::abs(v - q[m - 1][j] * scale);
          lo = std::min(lo, v);
          hi = std::max(hi, v);
          if (dir == 0) {
            if (std::abs(v - ext) > hyst) dir = v > ext ? 1 : -1, ext = v;
          } else if (dir * (v - ext) > 0) {
            ext = v;
          } else if (std::abs(v - ext) > hyst) {
            ++reversals;
            dir = -dir;
            ext = v;
          }
        }
      };
      double tp, tc, lo, hi, lo_c, hi_c;
      int rv, rc;
      walk(p.axes, tp, rv, lo, hi);
      axes[s.m.post.letters[J]] = {{"range", {report::rounded(lo, 4), report::rounded(hi, 4)}},
                                   {"travel", report::rounded(tp, 4)},
                                   {"reversals", rv},
                                   {"unit", rot ? "deg" : "mm"}};
      if (!conv) continue;  // no conventional axis values to compare with (its IK failed)
      walk(*conv, tc, rc, lo_c, hi_c);
      axes[s.m.post.letters[J]]["conventional_travel"] = report::rounded(tc, 4);
      axes[s.m.post.letters[J]]["conventional_reversals"] = rc;
      // A fixed orientation can turn a short path into long linear strokes (the table no longer follows it).
      if (!rot && tp > 1.25 * tc && tp - tc > 10.0)
        notes.push_back(
            fmt::format("segment {} (CL lines {}-{}): the {} makes {} travel {:.0f} mm instead of {:.0f} "
                        "mm{} at the CL points",
                        g + 1, seg.first_line, seg.last_line,
                        seg.tier == plan::Tier::Fixed2 ? "fixed (3+2) orientation" : "chosen orientation",
                        s.m.post.letters[J], tp, tc,
                        // (a ratio to a travel of almost nothing says nothing)
                        tc >= 1.0 ? fmt::format(" (x{:.2f})", tp / tc) : std::string()));
    }
    out.push_back(
        {{"cl_lines", {seg.first_line, seg.last_line}},
         {"tier", static_cast<int>(seg.tier)},
         {"tier_name", plan::to_string(seg.tier)},
         {"positioning", seg.positioning},
         {"description", seg.description},
         {"earlier_tiers_failed", std::move(fails)},
         {"axes", std::move(axes)},
         {"reorientation", plan::to_string(seg.reorientation)},
         {"reorientation_detail", seg.reorientation_detail},
         {"swept_collisions", seg.swept_collisions},
         {"swept_uncertified", seg.swept_uncertified},
         {"swept_first", seg.swept_collisions + seg.swept_uncertified
                             ? nlohmann::json{{"cl_line", seg.swept_first_line}, {"detail", seg.swept_first_detail}}
                             : nlohmann::json()},
         {"approach_moves_replaced", seg.approach_moves_replaced},
         {"legs", seg.legs.text()}});
  }
  return notes;
}

int run_compare(const PlanArgs& a) {
  auto s = setup(a);
  const auto t0 = std::chrono::steady_clock::now();
  // The conventional post may fail where the planner does not (a path through a singular orientation that a blind
  // choice of rotaries cannot follow): that is a result of the comparison, reported, not the end of it.
  std::vector<kin::Axes> conv;
  post::Summary sc;
  std::string conv_text, conv_error;
  try {
    conv = post::conventional_axes(s->prog, s->m, *s->kin);
    conv_text = post_to_string(*s, s->prog, conv, a, "conventional", sc);
  } catch (const InputError& e) {
    conv_error = e.what();
  }
  const bool has_conv = conv_error.empty();
  const bool has_conv_axes = conv.size() == s->prog.moves.size();
  const double conv_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const plan::Planner planner(s->m, s->kin, &s->scene, s->tool.get(), s->opt, s->planner_head());
  const plan::Plan p = planned(*s, a);
  const cl::Program ref = p.reference(s->prog);
  post::Summary sp;
  const std::string plan_text = post_to_string(*s, p.program, p.axes, a, "cspace-planner", sp, &ref);
  // A warning both programs raise (e.g. the CL's H0) once, as the file's.
  auto in = [](const std::vector<std::string>& v, const std::string& x) {
    return std::find(v.begin(), v.end(), x) != v.end();
  };
  for (const auto& x : sc.warnings) s->warn(in(sp.warnings, x) ? "both programs: " + x : "conventional program: " + x);
  for (const auto& x : sp.warnings)
    if (!in(sc.warnings, x)) s->warn("planned program: " + x);
  const auto vc = has_conv ? verify_text(*s, conv_text, 0.0, s->prog) : report::VerifyResult{};
  const auto vp = verify_text(*s, plan_text, a.cone_deg, ref);
  const auto stc = has_conv ? stats_of(*s, conv_text, "conventional") : report::Stats{};
  auto stp = stats_of(*s, plan_text, "planner");
  // An independent collision check of both programs against the meshes (even when the planner was told
  // to ignore them): FK of every CL point's axis values, tool vs scene.
  // And every move between the points, swept (feed blocks, approach/retract, reorientations).
  struct Hits {
    std::size_t n = 0;
    int first_line = 0;
    plan::SweptSummary swept;
  };
  auto count_collisions = [&](const cl::Program& prog, const std::vector<kin::Axes>& axes) {
    Hits h;
    if (!s->has_meshes || !s->tool) return h;
    cspace::Options co = s->opt.cspace;
    co.check_collision = true;
    co.collision.roles = geom::kAllRoles;
    geom::QueryWorkspace ws;
    cspace::Counters cc;
    const cspace::Space space_h(s->kin, &s->scene, s->tool.get(), co, s->has_head ? &s->head : nullptr);
    for (std::size_t i = 0; i < prog.moves.size(); ++i)
      if (!space_h.collision_at_axes(axes[i], ws, cc).empty()) {
        if (!h.n) h.first_line = prog.moves[i].line;
        ++h.n;
      }
    h.swept = plan::check_program(space_h, s->m, prog, axes, cc);
    return h;
  };
  const Hits hc = has_conv_axes ? count_collisions(s->prog, conv) : Hits{}, hp = count_collisions(p.program, p.axes);
  const std::size_t conv_collisions = hc.n;
  std::string tiers;
  int counts[5] = {0, 0, 0, 0, 0};
  int positioning = 0;  // rapid-only segments (retracts, traverses): they cut nothing, so no tier is counted for them
  for (const auto& g : p.segments) g.positioning ? ++positioning : ++counts[static_cast<int>(g.tier)];
  tiers = fmt::format("{} / {} / {} / {}", counts[1], counts[2], counts[3], counts[4]);
  std::cout << fmt::format("cone {:.2f} deg, resolution {:.3f} deg, collision {}\n", a.cone_deg, a.resolution_deg,
                           s->opt.cspace.check_collision ? "on" : "off");
  if (s->machine_bodies)
    std::cout << fmt::format("machine bodies: {}{}\n", s->machine_bodies,
                             s->planner_ignores_machine ? " (ignored by the planner, still checked below)" : "");
  // Without a conventional program its column shows "-" (the table then has the planner's only).
  auto conv_cell = [&](const auto& v) { return has_conv ? fmt::format("{}", v) : std::string("-"); };
  auto conv_axes_cell = [&](const auto& v) { return has_conv_axes ? fmt::format("{}", v) : std::string("-"); };
  if (has_conv) {
    std::cout << report::table({stc, stp}, {"conventional", "planner"});
  } else {
    std::cout << "conventional program: not posted: " << conv_error << "\n";
    std::cout << report::table({stp}, {"planner"});
  }
  std::cout << fmt::format("{:<28}{:>22}{:>22}\n", "NC blocks", conv_cell(sc.blocks), sp.blocks);
  std::cout << fmt::format("{:<28}{:>22}{:>22}\n", "verify", has_conv ? (vc.ok ? "ok" : "FAILED") : "-",
                           vp.ok ? "ok" : "FAILED");
  // Why a program failed back-simulation (the table has room for the verdict only).
  if (has_conv && !vc.ok) std::cout << "conventional program: verify " << vc.message << "\n";
  if (!vp.ok) std::cout << "planned program: verify " << vp.message << "\n";
  if (s->has_meshes) {
    std::cout << fmt::format("{:<28}{:>22}{:>22}\n", "colliding CL points", conv_axes_cell(hc.n), hp.n);
    std::cout << fmt::format("{:<28}{:>22}{:>22}\n", "colliding moves (swept)", conv_axes_cell(hc.swept.collisions),
                             hp.swept.collisions);
    if (hc.swept.uncertified || hp.swept.uncertified)
      std::cout << fmt::format("{:<28}{:>22}{:>22}\n", "uncertified moves (swept)",
                               conv_axes_cell(hc.swept.uncertified), hp.swept.uncertified);
  }
  std::cout << fmt::format("{:<28}{:>22}{:>22}\n", "segment tiers 1/2/3/4", "-", tiers);
  if (positioning) std::cout << fmt::format("{:<28}{:>22}{:>22}\n", "positioning segments", "-", positioning);
  std::cout << fmt::format("{:<28}{:>22}{:>22.3f}\n", "time (s)", conv_cell(fmt::format("{:.3f}", conv_s)), p.seconds);
  std::cout << fmt::format(
      "planner queries: {} cells, {} IK, {} stroke, {} collision, {} more for {} swept moves; peak memory {:.0f} MB\n",
      p.counters.cells_enumerated, p.counters.ik, p.counters.stroke, p.counters.collision, p.counters.swept_queries,
      p.counters.swept, p.peak_memory_mb);
  std::cout << p.summary();
  if (hc.n)
    std::cout << fmt::format("the conventional program collides at {} CL points (first at CL line {})\n", hc.n,
                             hc.first_line);
  auto first_swept = [&](const char* who, const Hits& h) {
    for (const auto& x : h.swept.hits)
      if (x.result.status == cspace::SweepStatus::Collides) {
        std::cout << fmt::format(
            "the {} program collides between points at {} moves (first: the {} into CL line {}, "
            "{:.0f} % along: {})\n",
            who, h.swept.collisions, x.reorientation ? "reorientation" : "move", x.line, 100.0 * x.result.t,
            x.result.detail);
        return;
      }
  };
  first_swept("conventional", hc);
  first_swept("planned", hp);
  if (hp.n)
    std::cout << fmt::format("the planned program collides at {} CL points (first at CL line {}){}\n", hp.n,
                             hp.first_line, s->opt.cspace.check_collision ? "" : ": collision pruning was off");
  nlohmann::json tier_list = nlohmann::json::array();
  for (const auto& g : p.segments) tier_list.push_back(static_cast<int>(g.tier));
  nlohmann::json segs = nlohmann::json::array();
  const std::vector<std::string> flags = segment_reports(*s, p, has_conv_axes ? &conv : nullptr, segs);
  for (const auto& f : flags) std::cout << "note: " << f << "\n";
  nlohmann::json jc = {{"cl", a.cl},
                       {"machine", s->m.name},
                       {"cone_deg", a.cone_deg},
                       {"resolution_deg", a.resolution_deg},
                       {"collision", s->opt.cspace.check_collision},
                       {"machine_bodies", s->machine_bodies},
                       {"meshes", mesh_reports_json(*s)},
                       {"conventional", has_conv ? nlohmann::json{{"stats", stc.json()},
                                                                  {"blocks", sc.blocks},
                                                                  {"verify_ok", vc.ok},
                                                                  {"verify", vc.message},
                                                                  {"colliding_points", conv_collisions},
                                                                  {"colliding_moves_swept", hc.swept.collisions},
                                                                  {"uncertified_moves_swept", hc.swept.uncertified},
                                                                  {"seconds", report::rounded(conv_s, 4)}}
                                                 : nlohmann::json{{"error", conv_error}}},
                       {"planner",
                        {{"stats", stp.json()},
                         {"blocks", sp.blocks},
                         {"verify_ok", vp.ok},
                         {"verify", vp.message},
                         {"colliding_points", hp.n},
                         {"colliding_moves_swept", hp.swept.collisions},
                         {"uncertified_moves_swept", hp.swept.uncertified},
                         {"points_beyond_cell_cap", p.points_beyond_cap},
                         {"seconds", report::rounded(p.seconds, 4)},
                         {"tiers", std::move(tier_list)},
                         {"queries",
                          {{"cells", p.counters.cells_enumerated},
                           {"ik", p.counters.ik},
                           {"stroke", p.counters.stroke},
                           {"collision", p.counters.collision},
                           {"swept_moves", p.counters.swept},
                           {"swept_queries", p.counters.swept_queries}}},
                         {"peak_memory_mb", report::rounded(p.peak_memory_mb, 1)},
                         {"windows", p.windows},
                         {"window_rule", p.window_rule}}}};
  jc["planner"]["segments"] = std::move(segs);
  // JSON only where asked: a run must not leave files in the working directory it was not told to write.
  if (!a.json_out.empty()) {
    const std::string json = jc.dump(2) + "\n";
    write_file_atomically(a.json_out, [&](std::ostream& os) { os << json; });
    std::cout << "JSON: " << a.json_out << "\n";
  }
  if (!a.out.empty())
    gate::write_checked(a.out, plan_text, ref, s->m, *s->kin, gate_options(*s, a, a.cone_deg), &sp.cl_line_of_nc_line);
  if (!a.svg_dir.empty()) write_svgs(*s, planner, p, conv, a.svg_dir);
  return vp.ok ? 0 : 1;
}

void common_options(CLI::App* c, PlanArgs& a) {
  c->add_option("cl", a.cl, "CL file")->required();
  c->add_option("-m,--machine", a.machine, "machine file or bundled machine name")->required();
  c->add_option("--part", a.parts, "part mesh(es) (STL, OBJ, PLY, ...)");
  c->add_option("--fixture", a.fixtures, "fixture mesh(es)");
  c->add_option("--mesh-scale", a.mesh_scale, "multiply mesh coordinates by this to get mm")->check(cli::kPositive);
  c->add_option("--cone", a.cone_deg, "allowed tool-axis deviation from the CL axis, deg (0: exact)");
  c->add_option("--min-tilt", a.min_tilt_deg, "minimum tilt from the CL axis (ball mills), deg")
      ->check(cli::kNonNegative);
  c->add_option("--resolution", a.resolution_deg, "C-space grid resolution, deg")->check(cli::kPositive);
  c->add_option("--tilt-step", a.tilt_step_deg,
                "tilt grid inside the cone for the leg (PKM) re-plan, deg (default: resolution)")
      ->check(cli::kPositive);
  c->add_option("--max-step", a.max_step_deg,
                "largest rotary step per point, deg, in tiers 2-4 (0: 20 grid steps, which tier 4 exceeds only where "
                "no cell within it follows the CL axis; a value given here is never exceeded)")
      ->check(cli::kNonNegative);
  c->add_option("--beam", a.beam,
                fmt::format("tier 4 (shortest path): states kept per point at first, widened 4x up to {} where the "
                            "search dead-ends; wider finds slightly less rotary travel, slower",
                            plan::Options::kWidestBeam))
      ->check(CLI::Range(std::size_t{1}, plan::Options::kWidestBeam));
  c->add_option("--clearance", a.clearance_mm, "collision clearance of shank, holder and spindle, mm")
      ->check(cli::kNonNegative);
  c->add_option("--tool-length", a.tool_length, "gauge-to-tip tool length, mm (0: the CL's or the machine file's)")
      ->check(cli::kNonNegative);
  c->add_option("--tolerance", a.tolerance, "post linearisation tolerance, mm (0: the machine file's)")
      ->check(cli::kNonNegative);
  c->add_option("--dialect", a.dialect, "post dialect override");
  c->add_option("--units", a.units, "force CL units (mm or inch)");
  c->add_option("--default-feed", a.default_feed,
                "feed, mm/min, for cutting moves the CL gives no feed rate for (default: such a CL is an error)")
      ->check(cli::kPositive);
  c->add_option("--svg", a.svg_dir, "write C-space and axis pictures into this directory");
  c->add_flag("--no-collision", a.no_collision, "ignore the meshes (to show what the plan would hit)");
  auto* tcp = c->add_flag_function(
      "--tcp", [&a](std::int64_t) { a.tcp = true; }, "tool-tip control on (default: the machine's post.tcp)");
  c->add_flag_function(
       "--no-tcp", [&a](std::int64_t) { a.tcp = false; }, "tool-tip control off: machine coordinates")
      ->excludes(tcp);
  c->add_option("--work-plane", a.work_plane,
                "3+2 segments: tilted (G68.2, G254, CYCLE800, PLANE SPATIAL) or machine coordinates (default: the "
                "machine's post.work_plane)")
      ->check(CLI::IsMember({"tilted", "machine"}));
  c->add_option("--window", a.window,
                "plan in windows of N moves, each continuing where the previous ended (bounded memory); "
                "default: 1000 above 50,000 moves, else windows of at most 4,000,000 listed C-space cells where the "
                "points' cones hold more (none otherwise)");
  c->add_flag("--no-machine-geometry", a.no_machine_geometry,
              "leave the machine file's bodies (geometry.bodies) out of the collision scene");
}

}  // namespace

std::function<gate::Options::CollisionCheck(int)> collision_for_post(const machine::Machine& m,
                                                                     const std::shared_ptr<const kin::Kinematics>& kin,
                                                                     double tool_length, const cl::Program& prog,
                                                                     const PlanArgs& a,
                                                                     std::vector<std::string>& warnings) {
  // The scene with the CL's first cutter: the moves before any tool change, and any tool without a size of its own.
  auto first = std::make_shared<Setup>();
  first->warnings = &warnings;
  first->m = m;
  first->tool_length = tool_length;
  first->kin = kin;
  add_scene(*first, a, prog.tools, false);
  first->warnings = nullptr;  // (the setup outlives this call: nothing may point at the caller's list)
  auto make_first = gate_options(*first, a, 0.0).make_collision;
  if (!make_first) return {};
  // Each tool change's cutter, in the program's order (the k-th change of the NC program loads the k-th tool of the
  // CL's changes, as the post writes them), a scene per distinct shape: each move is checked with the cutter that
  // cuts it.
  using Make = std::function<gate::Options::CollisionCheck(int)>;
  std::vector<std::shared_ptr<Setup>> keep{first};
  std::vector<Make> by_change{make_first};  // [k]: after the k-th tool change (0: before any)
  std::vector<std::pair<const cl::Tool*, Make>> shapes;
  const cl::Tool* first_tool = first_sized_tool(prog.tools);
  for (const cl::Event& e : prog.events) {
    if (e.kind != cl::Event::Kind::ToolChange) continue;
    const cl::Tool* t = e.tool_index >= 0 && static_cast<std::size_t>(e.tool_index) < prog.tools.size()
                            ? &prog.tools[static_cast<std::size_t>(e.tool_index)]
                            : nullptr;
    if (!t || !(t->diameter_mm > 0) || !first_tool || t->same_shape(*first_tool)) {
      by_change.push_back(make_first);
      continue;
    }
    Make make;
    for (const auto& [shape, mk] : shapes)
      if (shape->same_shape(*t)) make = mk;
    if (!make) {
      auto s = std::make_shared<Setup>();
      std::vector<std::string> again;  // the meshes' warnings were given with the first cutter's scene
      s->warnings = &again;
      s->m = m;
      s->tool_length = tool_length;
      s->kin = kin;
      add_scene(*s, a, {*t}, false);
      s->warnings = nullptr;
      make = gate_options(*s, a, 0.0).make_collision;
      keep.push_back(s);
      shapes.emplace_back(t, make);
    }
    by_change.push_back(make);
  }
  // The scenes live as long as the checks that use them. A change the CL does not have (more in the NC than in the
  // CL) is checked with the first cutter, as before the tools were told apart.
  return [keep = std::move(keep), by_change = std::move(by_change)](int k) {
    const std::size_t at = k >= 0 && static_cast<std::size_t>(k) < by_change.size() ? static_cast<std::size_t>(k) : 0;
    return by_change[at](k);
  };
}

PlanWritten plan_and_write(const PlanArgs& a, const std::string& out) {
  PlanWritten w;
  auto s = setup(a, &w.warnings);
  const plan::Plan p = planned(*s, a, s->has_head ? &s->head : nullptr);
  const cl::Program ref = p.reference(s->prog);
  const std::string text = post_to_string(*s, p.program, p.axes, a, "cspace-planner", w.post, &ref);
  w.gate =
      gate::write_checked(out, text, ref, s->m, *s->kin, gate_options(*s, a, a.cone_deg), &w.post.cl_line_of_nc_line);
  for (const auto& x : w.post.warnings) w.warnings.push_back(x);
  w.machine_name = s->m.name;
  w.nc_text = text;
  return w;
}

std::function<int()> add_plan_commands(CLI::App& app) {
  auto args = std::make_shared<PlanArgs>();
  auto* plan_cmd = app.add_subcommand("plan", "Plan tool orientations in the rotary C-space and write the NC program");
  common_options(plan_cmd, *args);
  plan_cmd->add_option("-o,--output", args->out, "NC file to write");
  auto* cmp = app.add_subcommand("compare", "Conventional post vs C-space planner: travel, reversals, tiers");
  common_options(cmp, *args);
  cmp->add_option("--json-out", args->json_out, "write the comparison as JSON to this file (default: none)");
  cmp->add_option("-o,--output", args->out, "also write the planned NC program here");
  return [args, plan_cmd, cmp]() -> int {
    if (*plan_cmd) return run_plan(*args);
    if (*cmp) return run_compare(*args);
    return -1;
  };
}

}  // namespace cscam::cli
