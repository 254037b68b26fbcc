#include "cscam/plan/stream.hpp"

#include <fmt/format.h>
#include <sys/resource.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <exception>
#include <limits>
#include <map>
#include <optional>
#include <string>
#include <utility>

#include "cscam/core/error.hpp"
#include "cscam/core/tolerances.hpp"
#include "cscam/core/units.hpp"
#include "cscam/kin/track.hpp"

namespace cscam::plan {

namespace {
constexpr double kInfinity = std::numeric_limits<double>::infinity();
}  // namespace

std::size_t effective_window(std::size_t moves, const WindowOptions& w) {
  const std::size_t n = w.window > 0 ? w.window : (moves > w.auto_above ? w.auto_window : 0);
  // A window covers at least two moves (its pinned first move and one more), and fewer moves need no windows.
  if (n == 0 || moves <= n + 1) return 0;
  return std::max<std::size_t>(n, 2);
}

std::vector<std::pair<std::size_t, std::size_t>> windows_by_cost(const cl::Program& program,
                                                                 const std::vector<double>& cost, double budget) {
  const auto& mv = program.moves;
  const std::size_t n = mv.size();
  CSCAM_CHECK(cost.size() == n, "a cost per move");
  std::vector<std::pair<std::size_t, std::size_t>> out;
  if (n == 0) return out;
  // Costs of moves [0, m): the cost of (a, b] is at[b + 1] - at[a + 1].
  std::vector<double> at(n + 1, 0.0);
  for (std::size_t m = 0; m < n; ++m) at[m + 1] = at[m] + cost[m];
  auto between = [&](std::size_t a, std::size_t b) { return at[b + 1] - at[a + 1]; };
  for (std::size_t a = 0;;) {
    if (a + 1 >= n || between(a, n - 1) <= budget) {
      out.emplace_back(a, n - 1);
      break;
    }
    // The furthest end within the budget (a window covers at least its pinned move and one more).
    std::size_t last = a + 1;
    while (last + 1 < n && between(a, last + 1) <= budget) ++last;
    if (last + 1 >= n) {  // the last move alone is over the budget: it ends the program's last window
      out.emplace_back(a, n - 1);
      break;
    }
    // Prefer a segment end once half the budget is used: the next window then starts a whole segment.
    std::size_t b = 0;
    for (std::size_t c = last; c > a && between(a, c) > 0.5 * budget; --c)
      if (mv[c + 1].kind == cl::MotionKind::Rapid) {
        b = c;
        break;
      }
    if (b == 0) {
      // Inside a segment: at a feed move (a pinned rapid would be a segment start the later window cannot approach).
      b = last;
      while (b > a + 1 && mv[b].kind == cl::MotionKind::Rapid) --b;
    }
    out.emplace_back(a, b);
    a = b;
  }
  return out;
}

std::vector<std::pair<std::size_t, std::size_t>> windows_of(const cl::Program& program, std::size_t window) {
  const std::size_t n = program.moves.size();
  if (n == 0) return {};
  if (window < 2 || n <= window + 1) return {{0, n - 1}};
  return windows_by_cost(program, std::vector<double>(n, 1.0), static_cast<double>(window));
}

namespace {

/// The strongest tier a stitched path satisfies on moves [f, l]: both rotaries constant, one constant and the other
/// monotonic, both monotonic, or none of these.
Tier tier_of_path(const std::vector<kin::Axes>& axes, std::size_t f, std::size_t l, int r1, int r2) {
  auto constant = [&](int ax) {
    for (std::size_t m = f + 1; m <= l; ++m)
      if (std::abs(axes[m][ax] - axes[f][ax]) > tol::kRoundTripRad) return false;
    return true;
  };
  auto monotone = [&](int ax) {
    bool up = true, down = true;
    for (std::size_t m = f + 1; m <= l; ++m) {
      const double d = axes[m][ax] - axes[m - 1][ax];
      up = up && d >= -tol::kRoundTripRad;
      down = down && d <= tol::kRoundTripRad;
    }
    return up || down;
  };
  const bool c1 = constant(r1), c2 = constant(r2);
  if (c1 && c2) return Tier::Fixed2;
  const bool m1 = monotone(r1), m2 = monotone(r2);
  if ((c1 && m2) || (c2 && m1)) return Tier::Fixed1;
  if (m1 && m2) return Tier::Monotonic;
  return Tier::Shortest;
}

/// The last move of the segment that starts at move `s` (a rapid, or the program's first move, starts one).
std::size_t segment_end(const cl::Program& program, std::size_t s) {
  std::size_t e = s;
  while (e + 1 < program.moves.size() && program.moves[e + 1].kind != cl::MotionKind::Rapid) ++e;
  return e;
}

/// The pre-pass's answer: an orientation for a whole segment, or why there is none.
struct WholeSegment {
  std::optional<std::array<double, 2>> rotaries;
  std::size_t tried = 0, untried = 0;  ///< candidates given feasibility walks; left when the budget ran out
};

/// A grid cell feasible at every point of moves [s, e] (within the cone, inside the strokes, collision-free). The
/// candidates are the cells of point `s`, closest to its CL axis first, then nearest `entry` (windings tie exactly).
/// Each is tested as tier 1 tests its candidates: orientation over the whole range before any query, and the points
/// that rejected earlier candidates first (move-to-front), so that a candidate failing where its neighbour failed
/// costs one check; feasibility with a clearance certificate (one query per margin of travel). With a finite
/// `retract_plane_z_mm` (a machine without a Z axis) the tool must also retract from the segment's ends along its
/// axis to that plane. The checks spent on candidates that fail are bounded (16 walks of the segment, as many
/// candidates as that buys); a window sees only its own points, so a segment longer than a window is given the
/// orientation found here as its start.
WholeSegment whole_segment_orientation(const cspace::Space& sp, const cl::Program& program, std::size_t s,
                                       std::size_t e, std::size_t cap, std::array<double, 2> entry,
                                       double retract_plane_z_mm, cspace::Counters& c) {
  WholeSegment out;
  if (sp.options().cone_rad <= 0) return out;  // exact cells: tier 1 decides inside the windows
  auto pose = [&](std::size_t m) {
    return kin::Posed{program.moves[m].tip_in_part_mm, program.moves[m].axis_in_part.normalized()};
  };
  std::vector<cspace::Cell> cells;
  sp.enumerate(pose(s), cells, 64 * cap, c);  // tier 1's share for its first point
  // Equally close orientations (every winding of one, to float precision) nearest the entry first.
  auto rank = [&](const cspace::Cell& x) {
    return std::pair{std::lround(static_cast<double>(x.orient_err) * 1e6),
                     std::abs(x.r1 - entry[0]) + std::abs(x.r2 - entry[1])};
  };
  std::stable_sort(cells.begin(), cells.end(),
                   [&](const cspace::Cell& x, const cspace::Cell& y) { return rank(x) < rank(y); });
  const std::size_t n = e - s + 1;
  // Work spent on candidates that fail, in point evaluations (an orientation check, one FK and no query, counts as
  // 1/16 of one): at most 16 walks of the segment, as many candidates as that buys.
  constexpr std::size_t kOrientPerEval = 16;
  const std::size_t budget = kOrientPerEval * (16 * n + 4096);
  std::size_t spent = 0;
  std::vector<std::size_t> order(n);  // points, those that rejected a candidate first
  for (std::size_t k = 0; k < n; ++k) order[k] = s + k;
  auto to_front = [&](std::size_t oi) {
    std::rotate(order.begin(), order.begin() + static_cast<std::ptrdiff_t>(oi),
                order.begin() + static_cast<std::ptrdiff_t>(oi) + 1);
  };
  geom::QueryWorkspace ws;
  for (std::size_t ci = 0; ci < cells.size(); ++ci) {
    if (spent > budget) {
      out.untried = cells.size() - ci;
      break;
    }
    const cspace::Cell& cell = cells[ci];
    bool ok = true;
    double dot = 0;
    std::size_t oi = 0;
    for (; oi < n && ok; ++oi)
      if (!sp.in_cone_cos(pose(order[oi]), cell.r1, cell.r2, dot)) {
        ok = false;
        to_front(oi);
      }
    spent += oi;
    if (!ok) continue;
    ++out.tried;
    cspace::Certificate cert;
    for (oi = 0; oi < n && ok; ++oi) {
      const std::size_t m = order[oi];
      cspace::Cell x = cell;
      x.status = cspace::Status::Unknown;
      sp.evaluate(pose(m), x, ws, c, &cert);
      ok = x.status == cspace::Status::Feasible;
      // At the segment's ends a machine without a Z axis retracts along the tool axis (the planner's own rule there).
      kin::Axes up;
      if (ok && (m == s || m == e) && std::isfinite(retract_plane_z_mm))
        ok = kin::retract_along_axis(sp.kinematics(), x.axes, retract_plane_z_mm, tol::kLimitSlackMm, up);
      if (!ok) to_front(oi);
    }
    if (ok) {
      out.rotaries = std::array<double, 2>{cell.r1, cell.r2};
      return out;
    }
    spent += kOrientPerEval * oi;
  }
  return out;
}

/// The parts of one segment that windows planned separately.
struct Parts {
  std::vector<SegmentReport> reports;
  std::vector<std::size_t> joins;  ///< move index where each later part starts (pinned)
};

}  // namespace

void fit_cyclic_windows(const kin::Kinematics& kin, const cl::Program& program, cspace::Options& options) {
  const auto rp = kin.rotary_pair();
  const auto& ax = kin.axes();
  // Around the track, the cells a cone may need: half a turn each way (near the singular axis the cone spans every
  // primary angle) and the largest default rotary step.
  constexpr double kMargin = kPi + 20.0 * kPi / 180.0;
  // As cspace::Space bounds the grid of such an axis by default.
  const double span = options.cone_rad <= 0 ? 2.0 * options.cyclic_span_rad : options.cyclic_span_rad;
  std::array<bool, 2> wide{};
  for (int j = 0; j < 2; ++j) {
    const kin::AxisInfo& a = ax[static_cast<std::size_t>(rp[static_cast<std::size_t>(j)])];
    wide[static_cast<std::size_t>(j)] = (a.cyclic || a.max - a.min > 2 * span) && (a.max > span || a.min < -span);
  }
  if (!wide[0] && !wide[1]) return;
  // The windings a conventional post would turn through: every CL axis by the IK solution nearest the last.
  std::array<double, 2> lo{kInfinity, kInfinity}, hi{-kInfinity, -kInfinity};
  kin::Axes q = kin::Axes::Zero(), out;
  for (const cl::Move& mv : program.moves) {
    if (!kin::nearest_solution(kin, kin::Posed{mv.tip_in_part_mm, mv.axis_in_part.normalized()}, q, out))
      continue;  // unreachable: the planner names it
    q = out;
    for (std::size_t j = 0; j < 2; ++j) {
      lo[j] = std::min(lo[j], q[rp[j]]);
      hi[j] = std::max(hi[j], q[rp[j]]);
    }
  }
  for (std::size_t j = 0; j < 2; ++j)
    if (wide[j] && std::isfinite(lo[j]) && (lo[j] < -span || hi[j] > span))
      options.cyclic_window_rad[j] = {std::min(-span, lo[j] - kMargin), std::max(span, hi[j] + kMargin)};
}

namespace {

/// Steps of half a turn or more of a cyclic rotary into a feed move of a plan: unwinds on the part (the post turns them
/// with a retract). A turn into a rapid (between two cuts) is a reorientation, which the post makes above the part.
std::size_t cyclic_unwinds(const kin::Kinematics& kin, const Plan& p) {
  std::size_t n = 0;
  const auto& moves = p.program.moves;
  for (const int r : kin.rotary_pair()) {
    if (!kin.axes()[static_cast<std::size_t>(r)].cyclic) continue;
    for (std::size_t i = 1; i < p.axes.size() && i < moves.size(); ++i)
      n += moves[i].kind != cl::MotionKind::Rapid && std::abs(p.axes[i][r] - p.axes[i - 1][r]) >= kPi ? 1 : 0;
  }
  return n;
}

Plan plan_windowed_on(const machine::Machine& machine, const std::shared_ptr<const kin::Kinematics>& kinematics,
                      const geom::Scene* scene, const geom::ToolShape* tool, const Options& options,
                      const cl::Program& program, const WindowOptions& w, const geom::Scene* head);

}  // namespace

Plan plan_windowed(const machine::Machine& machine, const std::shared_ptr<const kin::Kinematics>& kinematics,
                   const geom::Scene* scene, const geom::ToolShape* tool, const Options& options,
                   const cl::Program& program, const WindowOptions& w, const geom::Scene* head) {
  const auto t0 = std::chrono::steady_clock::now();
  const auto& cw = options.cspace.cyclic_window_rad;
  if (std::isfinite(cw[0][0]) || std::isfinite(cw[1][0]))  // the caller's grid
    return plan_windowed_on(machine, kinematics, scene, tool, options, program, w, head);
  // The default grid holds a cyclic rotary within +-cyclic_span. Where the plan on it has to unwind such a rotary (or
  // finds no path, at cone 0, where a spiral leaves it), the program is planned again on the windings it needs, and
  // that plan is kept if it unwinds less. A plan without unwinds is not redone: more windings of the same
  // orientations crowd tier 4's beam (NX's path at cone 5: 4 % more rotary travel).
  std::optional<Plan> first;
  std::exception_ptr first_error;
  try {
    first = plan_windowed_on(machine, kinematics, scene, tool, options, program, w, head);
  } catch (const InputError&) {
    first_error = std::current_exception();
  }
  const std::size_t unwinds = first ? cyclic_unwinds(*kinematics, *first) : 0;
  if (first && unwinds == 0) return std::move(*first);
  Options wide = options;
  fit_cyclic_windows(*kinematics, program, wide.cspace);
  if (!std::isfinite(wide.cspace.cyclic_window_rad[0][0]) && !std::isfinite(wide.cspace.cyclic_window_rad[1][0])) {
    if (first_error) std::rethrow_exception(first_error);
    return std::move(*first);
  }
  try {
    Plan second = plan_windowed_on(machine, kinematics, scene, tool, wide, program, w, head);
    if (!first || cyclic_unwinds(*kinematics, second) < unwinds) {
      if (first) {
        second.counters += first->counters;  // the work of both plans
        second.peak_memory_mb = std::max(second.peak_memory_mb, first->peak_memory_mb);
      }
      second.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
      return second;
    }
  } catch (const InputError&) {
    if (first_error) std::rethrow_exception(first_error);
  }
  first->seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return std::move(*first);
}

namespace {

Plan plan_windowed_on(const machine::Machine& machine, const std::shared_ptr<const kin::Kinematics>& kinematics,
                      const geom::Scene* scene, const geom::ToolShape* tool, const Options& options,
                      const cl::Program& program, const WindowOptions& w, const geom::Scene* head) {
  const auto t0 = std::chrono::steady_clock::now();
  const std::size_t window = effective_window(program.moves.size(), w);
  std::unique_ptr<cspace::Space> space;  // for the cell counts and the orientation pre-pass
  std::vector<std::pair<std::size_t, std::size_t>> wins;
  std::string rule;
  if (window > 0) {
    wins = windows_of(program, window);
    rule = fmt::format("{} moves each", window);
  } else if (w.window == 0 && w.cell_budget > 0 && program.moves.size() > 2) {
    // The points' cell lists (what the planner keeps per point) against the budget: counted at every kStride-th
    // point (neighbouring points have cones of about the same size), at most the cap a layer lists.
    constexpr std::size_t kStride = 8;
    space = std::make_unique<cspace::Space>(kinematics, scene, tool, options.cspace, head);
    const auto& mv = program.moves;
    std::vector<double> cells(mv.size(), 0.0);
    for (std::size_t m0 = 0; m0 < mv.size(); m0 += kStride) {
      const auto n = static_cast<double>(
          space->count_in_cone({mv[m0].tip_in_part_mm, mv[m0].axis_in_part.normalized()}, options.max_cells_per_point));
      for (std::size_t m = m0; m < std::min(mv.size(), m0 + kStride); ++m) cells[m] = n;
    }
    wins = windows_by_cost(program, cells, static_cast<double>(w.cell_budget));
    rule = fmt::format("at most {} listed cells each", w.cell_budget);
  }
  if (wins.size() <= 1) return Planner(machine, kinematics, scene, tool, options, head).run(program);
  CSCAM_CHECK(!options.start_rotaries && !options.open_segment_rotaries,
              "plan_windowed pins the windows' moves itself");
  const auto rp = kinematics->rotary_pair();
  const std::size_t n = program.moves.size();
  Plan out;
  out.program = program;
  out.axes.assign(n, kin::Axes::Zero());
  std::map<std::size_t, Parts> split;  // index into out.segments -> its parts, for segments that windows split
  cl::Program sub;
  sub.file = program.file;
  sub.part_name = program.part_name;
  sub.source_units = program.source_units;
  sub.multax = program.multax;
  sub.msys = program.msys;
  sub.tools = program.tools;
  for (std::size_t wi = 0; wi < wins.size(); ++wi) {
    const auto [a, b] = wins[wi];
    sub.moves.assign(program.moves.begin() + static_cast<std::ptrdiff_t>(a),
                     program.moves.begin() + static_cast<std::ptrdiff_t>(b) + 1);
    Options o = options;
    if (wi > 0) {
      // The join: the previous window's last move as it was planned (its tool pose is the FK of its axes, so the
      // pinned cell reproduces those axes), with its rotaries as the only cell.
      sub.moves[0] = out.program.moves[a];
      o.start_rotaries = std::array<double, 2>{out.axes[a][rp[0]], out.axes[a][rp[1]]};
    }
    o.continues = b + 1 < n && program.moves[b + 1].kind != cl::MotionKind::Rapid;
    // The window's last segment starts here (the program's first move, or a rapid after the pinned join).
    std::size_t open = b;
    while (open > a && program.moves[open].kind != cl::MotionKind::Rapid) --open;
    const bool starts_here = open > a || (wi == 0 && open == 0);
    if (o.continues && starts_here) {
      // ... and runs past this window: if one orientation suits all of it, start there (as one run's tier 1 would
      // find it), so that the windows can keep it.
      if (!space) space = std::make_unique<cspace::Space>(kinematics, scene, tool, options.cspace, head);
      const std::size_t end = segment_end(program, open);
      const std::array<double, 2> entry =
          wi == 0 ? std::array<double, 2>{0.0, 0.0} : std::array<double, 2>{out.axes[a][rp[0]], out.axes[a][rp[1]]};
      const WholeSegment found = whole_segment_orientation(
          *space, program, open, end, options.max_cells_per_point, entry,
          kinematics->traits().retract_axis < 0 ? machine.post.safe_z_mm : std::numeric_limits<double>::quiet_NaN(),
          out.counters);
      o.open_segment_rotaries = found.rotaries;
      if (!found.rotaries && found.untried > 0)
        out.warnings.push_back(fmt::format(
            "CL lines {}-{}: windowed planning looked for one orientation for the whole segment and stopped after {} "
            "candidates ({} untried, the search's budget); the windows chose their own, which may turn the rotaries "
            "where one run would not (plan with a larger --window)",
            program.moves[open].line, program.moves[end].line, found.tried, found.untried));
    }
    Plan p = Planner(machine, kinematics, scene, tool, o, head).run(sub);
    const std::size_t from = wi == 0 ? 0 : 1;  // the pinned move stays as the previous window planned it
    for (std::size_t i = from; i < sub.moves.size(); ++i) {
      out.axes[a + i] = p.axes[i];
      out.program.moves[a + i] = p.program.moves[i];
    }
    out.counters += p.counters;
    out.points_beyond_cap += p.points_beyond_cap;
    for (std::size_t m : p.replaced_moves)
      if (m >= from) out.replaced_moves.push_back(a + m);
    for (auto& x : p.warnings) out.warnings.push_back(std::move(x));
    out.swept.moves += p.swept.moves;
    out.swept.collisions += p.swept.collisions;
    out.swept.uncertified += p.swept.uncertified;
    for (SweptHit& h : p.swept.hits) {
      h.move += a;
      out.swept.hits.push_back(std::move(h));
    }
    for (std::size_t g = 0; g < p.segments.size(); ++g) {
      SegmentReport rep = std::move(p.segments[g]);
      rep.first_move += a;
      rep.last_move += a;
      for (TierFailure& f : rep.failures) f.move += a;
      if (wi > 0 && g == 0) {
        // The pinned move alone: it ended the previous window's last segment (the cut fell at a segment end).
        if (rep.last_move == a) continue;
        // Otherwise this continues the previous window's last segment.
        const std::size_t at = out.segments.size() - 1;
        Parts& parts = split[at];
        if (parts.reports.empty()) parts.reports.push_back(out.segments[at]);
        parts.reports.push_back(rep);
        parts.joins.push_back(a);
        out.segments[at].last_move = rep.last_move;
        out.segments[at].last_line = rep.last_line;
        continue;
      }
      out.segments.push_back(std::move(rep));
    }
  }
  // Segments planned in several windows: the tier their stitched path satisfies, and why the stronger ones failed.
  for (auto& [at, parts] : split) {
    SegmentReport& seg = out.segments[at];
    const Tier tier = tier_of_path(out.axes, seg.first_move, seg.last_move, rp[0], rp[1]);
    std::vector<TierFailure> failures;
    for (int t = static_cast<int>(Tier::Fixed2); t < static_cast<int>(tier); ++t) {
      const TierFailure* first = nullptr;
      for (const SegmentReport& r : parts.reports)
        for (const TierFailure& f : r.failures)
          if (static_cast<int>(f.tier) == t && !first) first = &f;
      if (first) {
        failures.push_back(*first);
        continue;
      }
      // Every window reached this tier on its own, but their paths do not join into one of it.
      const std::size_t j = parts.joins.front();
      failures.push_back({static_cast<Tier>(t), j, program.moves[j].line, FailureCause::Transition,
                          fmt::format("windowed: the windows' paths do not join into one (first join at CL line {})",
                                      program.moves[j].line)});
    }
    seg.tier = tier;
    seg.failures = std::move(failures);
    bool same = true;
    for (const SegmentReport& r : parts.reports) same = same && r.description == parts.reports.front().description;
    seg.description = same ? parts.reports.front().description
                           : fmt::format("planned in {} windows, continuous at the joins; first window: {}",
                                         parts.reports.size(), parts.reports.front().description);
    for (std::size_t i = 1; i < parts.reports.size(); ++i) {
      const SegmentReport& r = parts.reports[i];
      seg.approach_moves_replaced += r.approach_moves_replaced;
      if (seg.swept_collisions + seg.swept_uncertified == 0 && r.swept_collisions + r.swept_uncertified > 0) {
        seg.swept_first_line = r.swept_first_line;
        seg.swept_first_detail = r.swept_first_detail;
      }
      seg.swept_collisions += r.swept_collisions;
      seg.swept_uncertified += r.swept_uncertified;
      if (seg.legs.state == Legs::NotCounted || seg.legs.state == Legs::Monotonic) seg.legs = r.legs;
    }
  }
  out.windows = wins.size();
  out.window_rule = rule;
  out.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  rusage ru{};
  if (getrusage(RUSAGE_SELF, &ru) == 0) out.peak_memory_mb = static_cast<double>(ru.ru_maxrss) / 1024.0;
  return out;
}

}  // namespace

}  // namespace cscam::plan
