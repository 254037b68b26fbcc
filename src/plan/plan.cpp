#include "cscam/plan/plan.hpp"

#include <fmt/format.h>
#include <sys/resource.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <utility>

#include "cscam/core/error.hpp"
#include "cscam/core/tolerances.hpp"
#include "cscam/core/units.hpp"
#include "cscam/kin/track.hpp"
#include "detail/search.hpp"

namespace cscam::plan {

const char* to_string(Tier t) {
  switch (t) {
    case Tier::Fixed2:
      return "fixed 2 axes + simultaneous 3 axes";
    case Tier::Fixed1:
      return "fixed 1 axis + simultaneous 4 axes (monotonic)";
    case Tier::Monotonic:
      return "simultaneous 5 axes, both rotaries monotonic";
    case Tier::Shortest:
      return "simultaneous 5 axes, shortest rotary path";
  }
  return "?";
}

const char* to_string(Reorientation r) {
  switch (r) {
    case Reorientation::None:
      return "none";
    case Reorientation::Clear:
      return "clear";
    case Reorientation::Collides:
      return "collides";
    case Reorientation::Uncertified:
      return "uncertified";
  }
  return "?";
}

const char* to_string(FailureCause c) {
  switch (c) {
    case FailureCause::Orientation:
      return "orientation";
    case FailureCause::Stroke:
      return "stroke";
    case FailureCause::Collision:
      return "collision";
    case FailureCause::Transition:
      return "transition";
  }
  return "?";
}

std::string failure_text(FailureCause cause, const std::string& detail) {
  if (cause == FailureCause::Transition) return detail;
  return detail.empty() ? std::string(to_string(cause)) : std::string(to_string(cause)) + ": " + detail;
}

const char* to_string(Legs l) {
  switch (l) {
    case Legs::NotCounted:
      return "not counted";
    case Legs::Monotonic:
      return "monotonic";
    case Legs::ReversalRemoved:
      return "reversal removed";
    case Legs::TiltedMonotonic:
      return "reversal removed by tilting";
    case Legs::Reverses:
      return "reverses";
  }
  return "?";
}

std::string LegReport::text() const {
  switch (state) {
    case Legs::NotCounted:
      return "";
    case Legs::Monotonic:
      return "monotonic";
    case Legs::ReversalRemoved:
      return fmt::format("monotonic: the reversal of {} at CL line {} removed", axes, line);
    case Legs::TiltedMonotonic:
      return fmt::format("monotonic: the reversal of {} at CL line {} removed by tilting at most {:.3f} deg", axes,
                         line, rad2deg(max_tilt_rad));
    case Legs::Reverses:
      return fmt::format(
          "{} reverses at CL line {} ({:.4f}, {:.4f}, {:.4f}); it cannot be avoided at this cone "
          "(no monotonic path beyond CL line {}: {})",
          axes, line, tip_mm.x(), tip_mm.y(), tip_mm.z(), blocked_line, why);
  }
  return "";
}

std::string Plan::summary() const {
  std::string s;
  for (std::size_t i = 0; i < segments.size(); ++i) {
    const auto& g = segments[i];
    std::string reo;
    if (g.reorientation != Reorientation::None)
      reo = std::string("; reorientation into it: ") + to_string(g.reorientation) +
            (g.reorientation_detail.empty() ? "" : ": " + g.reorientation_detail);
    const std::string lines = g.first_line == g.last_line ? fmt::format("CL line {}", g.first_line)
                                                          : fmt::format("CL lines {}-{}", g.first_line, g.last_line);
    s += fmt::format("segment {} ({}): {} — {}{}\n", i + 1, lines,
                     g.positioning ? "positioning (rapid moves only)" : to_string(g.tier), g.description, reo);
    for (const auto& f : g.failures)
      s += fmt::format("    tier {} failed at CL line {}: {}\n", static_cast<int>(f.tier), f.line, f.reason());
    if (g.legs.state != Legs::NotCounted) s += "    legs: " + g.legs.text() + "\n";
    if (g.approach_moves_replaced)
      s += fmt::format("    approach/retract: {} move(s) along the chosen tool axis\n", g.approach_moves_replaced);
    if (g.swept_collisions || g.swept_uncertified)
      s += fmt::format("    swept: {} move(s) collide, {} uncertified (first into CL line {}: {})\n",
                       g.swept_collisions, g.swept_uncertified, g.swept_first_line, g.swept_first_detail);
  }
  if (windows > 1) s += fmt::format("planned in {} windows ({}), continuous at the joins\n", windows, window_rule);
  if (points_beyond_cap)
    s += fmt::format("{} point(s) needed cells beyond the first cells per point: searched their whole cone\n",
                     points_beyond_cap);
  for (const auto& w : warnings) s += "warning: " + w + "\n";
  return s;
}

cl::Program Plan::reference(const cl::Program& cl) const {
  CSCAM_CHECK(cl.moves.size() == program.moves.size(), "a plan of this CL program");
  cl::Program ref = cl;
  for (std::size_t m : replaced_moves) ref.moves[m] = program.moves[m];
  return ref;
}

Planner::Planner(const machine::Machine& machine, std::shared_ptr<const kin::Kinematics> kinematics,
                 const geom::Scene* scene, const geom::ToolShape* tool, Options options, const geom::Scene* head)
    : machine_(machine),
      kin_(std::move(kinematics)),
      space_(kin_, scene, tool, options.cspace, head),
      opt_(std::move(options)) {}

namespace {

/// Segments: a rapid (or the first move) starts one; the feed moves after it continue it. [first, last] moves.
std::vector<std::pair<std::size_t, std::size_t>> split_segments(const cl::Program& program) {
  std::vector<std::pair<std::size_t, std::size_t>> segs;
  for (std::size_t i = 0; i < program.moves.size(); ++i) {
    if (i == 0 || program.moves[i].kind == cl::MotionKind::Rapid)
      segs.emplace_back(i, i);
    else
      segs.back().second = i;
  }
  return segs;
}

/// Writes a segment's chosen cells into the plan: axis values, and the tip and axis they give.
void write_back(const kin::Kinematics& kin, const detail::SegmentCells& d, const std::vector<const cspace::Cell*>& path,
                Plan& plan) {
  for (std::size_t k = 0; k < d.layers.size(); ++k) {
    const std::size_t m = d.layers[k].move;
    plan.axes[m] = path[k]->axes;
    const kin::Posed tp = kin.forward(path[k]->axes);
    plan.program.moves[m].tip_in_part_mm = tp.tip_mm;
    plan.program.moves[m].axis_in_part = tp.axis;
  }
}

/// Approach and retract run along the tool axis: a CL approach (retract) along the CL axis of the point it leads
/// into (out of) follows the chosen axis instead, at the same distance, with that point's rotaries; otherwise the
/// new tilt would be dragged along the old approach line (through the material beside it). Moves whose end moved
/// lose their swept certificate.
int replace_approach_retract(const kin::Kinematics& kin, const Options& opt, const cl::Program& program, std::size_t s,
                             std::size_t e, Plan& plan, std::vector<char>& swept_ok) {
  const auto& moves = program.moves;
  int replaced = 0;
  // Windowed planning: move 0 is the previous window's last move (kept), and a last move that the next window
  // continues is no retract.
  const bool pinned0 = s == 0 && opt.start_rotaries.has_value();
  const bool open_end = opt.continues && e + 1 == moves.size();
  if (e > s && !pinned0 && moves[s].kind == cl::MotionKind::Rapid &&
      detail::along_chosen_axis(kin, program, plan, s, s + 1)) {
    ++replaced;
    swept_ok[s + 1] = 0;
  }
  if (e > s + 1 && !open_end && moves[e].kind != cl::MotionKind::Rapid &&
      detail::along_chosen_axis(kin, program, plan, e, e - 1)) {
    ++replaced;
    swept_ok[e] = 0;
  }
  if (e == s && s > 0 && moves[s].kind == cl::MotionKind::Rapid &&
      detail::along_chosen_axis(kin, program, plan, s, s - 1))
    ++replaced;
  return replaced;
}

/// The swept check's hits, per segment: colliding or uncertified moves and reorientations, with a warning each
/// (the first move per segment only).
void attribute_swept_hits(const std::string& file, Plan& plan) {
  std::size_t g = 0;
  for (const SweptHit& h : plan.swept.hits) {
    while (g + 1 < plan.segments.size() && plan.segments[g].last_move < h.move) ++g;
    SegmentReport& rep = plan.segments[g];
    const bool collides = h.result.status == cspace::SweepStatus::Collides;
    if (h.reorientation) {
      if (rep.reorientation == Reorientation::Collides) continue;
      rep.reorientation = collides ? Reorientation::Collides : Reorientation::Uncertified;
      rep.reorientation_detail = h.result.detail;
      plan.warnings.push_back(fmt::format("{}: the reorientation into the segment starting here {} ({})",
                                          SourceLoc{file, rep.first_line, 0}.str(),
                                          collides ? "collides" : "cannot be certified free", h.result.detail));
      continue;
    }
    (collides ? rep.swept_collisions : rep.swept_uncertified)++;
    if (rep.swept_collisions + rep.swept_uncertified == 1) {
      rep.swept_first_line = h.line;
      rep.swept_first_detail = h.result.detail;
      plan.warnings.push_back(
          fmt::format("{}: the move into this point {} between CL points ({}, at {:.0f} % of the move)",
                      SourceLoc{file, h.line, 0}.str(), collides ? "collides" : "cannot be certified free",
                      h.result.detail, 100.0 * h.result.t));
    }
  }
}

/// Segments entered with other rotaries than the previous one ended at, and not found colliding: a clear
/// reorientation.
void mark_clear_reorientations(const kin::Kinematics& kin, Plan& plan) {
  const auto rp = kin.rotary_pair();
  for (std::size_t i = 1; i < plan.segments.size(); ++i) {
    auto& rep = plan.segments[i];
    const kin::Axes &from = plan.axes[plan.segments[i - 1].last_move], &to = plan.axes[rep.first_move];
    if (rep.reorientation == Reorientation::None &&
        (std::abs(from[rp[0]] - to[rp[0]]) > 1e-9 || std::abs(from[rp[1]] - to[rp[1]]) > 1e-9))
      rep.reorientation = Reorientation::Clear;
  }
}

/// A segment of rapid moves only cuts nothing, yet the cascade gives it an orientation of its own (the CL's, near
/// home): the tool then turned into it and out again for the next cut. Where the orientation the previous segment
/// ends with, else the one the next segment starts with, suits every point of it (in the cone, inside the strokes, no
/// collision at the point), it takes that one. Skipped: a segment whose moves were re-placed along a neighbour's axis
/// (already that neighbour's), and, in windowed planning, a pinned first move or a last move that the next window
/// continues. The moves between points are checked afterwards, with every other move (check_program): those into,
/// inside and out of a changed segment lose the certificates its own swept check gave them (swept_ok).
void adopt_neighbour_orientations(const cspace::Space& space, const kin::Kinematics& kin, const Options& opt,
                                  const cl::Program& program,
                                  const std::vector<std::pair<std::size_t, std::size_t>>& segs, Plan& plan,
                                  std::vector<char>& swept_ok, double retract_plane_z) {
  const auto rp = kin.rotary_pair();
  const double res = space.options().resolution_rad;
  auto fixed_at = [&](double r1, double r2, const std::string& why) {
    return fmt::format("rotaries fixed at {} = {:.3f} deg, {} = {:.3f} deg ({})",
                       kin.axes()[static_cast<std::size_t>(rp[0])].name, rad2deg(r1),
                       kin.axes()[static_cast<std::size_t>(rp[1])].name, rad2deg(r2), why);
  };
  geom::QueryWorkspace ws;
  for (std::size_t g = 0; g < segs.size() && g < plan.segments.size(); ++g) {
    SegmentReport& rep = plan.segments[g];
    const auto [s, e] = segs[g];
    if (!rep.positioning) continue;
    if (rep.approach_moves_replaced > 0) {
      // A single rapid re-placed along the previous point's chosen axis (a retract) has that point's rotaries: the
      // cascade's description named its own.
      if (e == s && s > 0 && plan.axes[s][rp[0]] == plan.axes[s - 1][rp[0]] &&
          plan.axes[s][rp[1]] == plan.axes[s - 1][rp[1]])
        rep.description =
            fixed_at(plan.axes[s][rp[0]], plan.axes[s][rp[1]], "along the previous segment's last tool axis");
      continue;
    }
    if (s == 0 && opt.start_rotaries) continue;
    if (opt.continues && e + 1 == program.moves.size()) continue;
    struct Candidate {
      std::size_t from;
      const char* which;
    };
    std::vector<Candidate> candidates;
    if (g > 0) candidates.push_back({segs[g - 1].second, "previous"});
    if (g + 1 < segs.size()) candidates.push_back({segs[g + 1].first, "next"});
    for (const Candidate& cand : candidates) {
      const double r1 = plan.axes[cand.from][rp[0]], r2 = plan.axes[cand.from][rp[1]];
      if (plan.axes[s][rp[0]] == r1 && plan.axes[s][rp[1]] == r2) break;  // already there
      std::vector<kin::Axes> axes;
      for (std::size_t m = s; m <= e; ++m) {
        const kin::Posed cl{program.moves[m].tip_in_part_mm, program.moves[m].axis_in_part.normalized()};
        cspace::Cell cell;
        cell.r1 = r1;
        cell.r2 = r2;
        cell.i1 = static_cast<int>(std::lround(r1 / res));
        cell.i2 = static_cast<int>(std::lround(r2 / res));
        if (!space.in_cone(cl, r1, r2, &cell.orient_err)) break;
        space.evaluate(cl, cell, ws, plan.counters);
        if (cell.status != cspace::Status::Feasible) break;
        // Without a Z axis the post retracts along the tool axis at both ends of a segment (as the cascade's cells
        // were chosen to allow): the new orientation must allow it too.
        kin::Axes up;
        if (std::isfinite(retract_plane_z) && (m == s || m == e) &&
            !kin::retract_along_axis(kin, cell.axes, retract_plane_z, tol::kLimitSlackMm, up))
          break;
        axes.push_back(cell.axes);
      }
      if (axes.size() != e - s + 1) continue;
      // The moves into, inside and out of the segment lose their swept certificates.
      for (std::size_t m = s; m <= std::min(e + 1, program.moves.size() - 1); ++m) swept_ok[m] = 0;
      for (std::size_t m = s; m <= e; ++m) {
        plan.axes[m] = axes[m - s];
        const kin::Posed tp = kin.forward(axes[m - s]);
        plan.program.moves[m].tip_in_part_mm = tp.tip_mm;
        plan.program.moves[m].axis_in_part = tp.axis;
      }
      rep.description = fixed_at(r1, r2, fmt::format("the {} segment's orientation: no turn of its own", cand.which));
      break;
    }
  }
}

}  // namespace

Plan Planner::run(const cl::Program& program) const {
  const auto t0 = std::chrono::steady_clock::now();
  Plan plan;
  plan.program = program;
  plan.axes.assign(program.moves.size(), kin::Axes::Zero());
  const auto& moves = program.moves;
  const bool exact = space_.options().cone_rad <= 0;
  std::vector<char> swept_ok(moves.size(), 0);  // moves certified free by a segment's own swept check
  const auto segs = split_segments(program);
  // Without a Z axis the post retracts along the tool axis to the safe plane: the segment ends must allow it.
  const double retract_plane_z =
      kin_->traits().retract_axis < 0 ? machine_.post.safe_z_mm : std::numeric_limits<double>::quiet_NaN();
  for (const auto& [s, e] : segs) {
    const kin::Axes* prefer = plan.segments.empty() ? nullptr : &plan.axes[segs[plan.segments.size() - 1].second];
    const detail::SegmentView view{space_, opt_, program, kin_, exact, prefer, retract_plane_z};
    detail::SegmentCells cells = detail::make_cells(view, s, e, plan.counters);
    detail::Cascade c = detail::run_cascade(view, cells, plan.points_beyond_cap);
    std::vector<cspace::Cell> kept;  // outlives c.path when it points here
    detail::avoid_swept_collisions(view, cells, c, kept, swept_ok, plan.points_beyond_cap);
    SegmentReport rep;
    rep.first_move = s;
    rep.last_move = e;
    rep.first_line = moves[s].line;
    rep.last_line = moves[e].line;
    rep.tier = c.tier;
    rep.positioning =
        std::all_of(moves.begin() + static_cast<std::ptrdiff_t>(s), moves.begin() + static_cast<std::ptrdiff_t>(e) + 1,
                    [](const cl::Move& mv) { return mv.kind == cl::MotionKind::Rapid; });
    rep.failures = std::move(c.failures);
    rep.description = std::move(c.description);
    if (!opt_.monotone_axes.empty() && cells.layers.size() > 2) {
      const std::vector<const cspace::Cell*> swept_path = c.path;
      rep.legs = detail::replan_legs(view, cells, c.path, rep.tier, rep.description);
      // A re-planned path has moves the swept check above never saw: the final check takes them all.
      if (c.path != swept_path)
        for (std::size_t m = s; m <= e; ++m) swept_ok[m] = 0;
    }
    write_back(*kin_, cells, c.path, plan);
    rep.approach_moves_replaced = replace_approach_retract(*kin_, opt_, program, s, e, plan, swept_ok);
    plan.segments.push_back(std::move(rep));
  }
  adopt_neighbour_orientations(space_, *kin_, opt_, program, segs, plan, swept_ok, retract_plane_z);
  // Every move between points, checked swept: feed blocks, approach and retract, and the reorientation into each
  // segment as the post performs it.
  plan.swept = check_program(space_, machine_, plan.program, plan.axes, plan.counters, &swept_ok);
  attribute_swept_hits(program.file, plan);
  if (space_.checks_collision()) mark_clear_reorientations(*kin_, plan);
  plan.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  rusage ru{};
  if (getrusage(RUSAGE_SELF, &ru) == 0) plan.peak_memory_mb = static_cast<double>(ru.ru_maxrss) / 1024.0;
  return plan;
}

}  // namespace cscam::plan
