// The motion sequencer (sequencer.hpp): rapid positioning, retracts (to a safe Z, or along the tool axis on a
// machine without a Z axis), flips and unwinds of the rotaries between two feed points, PKM repositioning.
#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <vector>

#include "cscam/core/error.hpp"
#include "cscam/core/tolerances.hpp"
#include "cscam/core/units.hpp"
#include "cscam/kin/track.hpp"
#include "linearize.hpp"
#include "sequencer.hpp"

namespace cscam::post::detail {

// --- Rapid positioning -------------------------------------------------------------------------------------

void Sequencer::emit_safe_z() {
  // Up to the safe Z, never down to it: a part taller than the machine file's safe Z is cut above it, and a "retract"
  // down to that plane would drive the tool into the part.
  kin::Axes q = cur_;
  q[z_] = std::max(safe_z_, cur_[z_]);
  start(BlockSpec::Motion::Rapid);
  if (add_words(q, {z_})) {
    set_mode94();
    emit();
  }
  if (q[z_] > cur_[z_]) off_path_ = true;
  cur_[z_] = q[z_];
}

/// Rapid blocks that bring the rotaries written modulo 360 (reached the short way) to q's in steps of less
/// than half a turn, every axis moving proportionally: the control then turns the way the model does.
void Sequencer::turn_stepwise(const kin::Axes& q) {
  double worst = 0.0;
  for (int i = 0; i < 5; ++i)
    if (shortest_[static_cast<size_t>(i)] && have_word_[static_cast<size_t>(i)])
      worst = std::max(worst, std::abs(q[i] - written_[static_cast<size_t>(i)]));
  const int n = static_cast<int>(std::ceil(worst / deg2rad(170.0)));
  if (n <= 1) return;
  kin::Axes from = cur_;
  for (int i = 0; i < 5; ++i)
    if (have_word_[static_cast<size_t>(i)]) from[i] = written_[static_cast<size_t>(i)];
  for (int k = 1; k < n; ++k) {
    const kin::Axes mid = from + (static_cast<double>(k) / n) * (q - from);
    start(BlockSpec::Motion::Rapid);
    if (add_words(mid, {0, 1, 2, 3, 4})) {
      set_mode94();
      emit();
    }
  }
}

/// One rapid block to q (nothing when every word is unchanged).
void Sequencer::emit_g0(const kin::Axes& q) {
  turn_stepwise(q);
  start(BlockSpec::Motion::Rapid);
  if (add_words(q, {0, 1, 2, 3, 4})) {
    set_mode94();
    emit();
  }
  cur_ = q;
}

/// Rapid positioning. With a rotary change: retract, rotate, position, plunge.
void Sequencer::rapid(const kin::Axes& q, const cl::Move& mv) {
  cur_line_ = mv.line;
  const auto rp = kin_.rotary_pair();
  std::vector<int> lin;
  for (int i = 0; i < 5; ++i)
    if (i != rp[0] && i != rp[1]) lin.push_back(i);
  // Leaving a plane: before the rotaries turn, out along the tool axis (in the plane) first; a rapid that keeps
  // them (and no 3+2 stretch after it) just ends the plane, the same motion as in machine coordinates.
  if (plane_active_ && (rotaries_differ(q) || !pending_plane_)) {
    if (rotaries_differ(q)) exit_along_axis();
    work_plane_off();
  }
  if (pending_plane_ && !rotaries_differ(q)) work_plane_on(q);  // the rotaries are already there
  if (rotaries_differ(q) && z_ >= 0) {
    exit_along_axis();
    if (have_state_) emit_safe_z();
    // The rotaries turn and the tool travels at the safe Z, or higher where the tool already is or is going (the CL's
    // own clearance above a part taller than the safe Z).
    const double plane = std::max({safe_z_, q[z_], have_state_ ? cur_[z_] : safe_z_});
    kin::Axes at_safe = have_state_ ? cur_ : q;
    at_safe[z_] = plane;
    at_safe[rp[0]] = q[rp[0]];
    at_safe[rp[1]] = q[rp[1]];
    check_limits(at_safe, mv);
    if (!have_state_) {  // the safe start: up first, wherever the tool is
      start(BlockSpec::Motion::Rapid);
      set_mode94();
      add_words(at_safe, {z_}, true);
      emit();
    }
    turn_stepwise(at_safe);
    start(BlockSpec::Motion::Rapid);
    set_mode94();
    if (add_words(at_safe, {rp[0], rp[1]})) emit();
    if (pending_plane_) work_plane_on(at_safe);  // positioned: the plane, then the approach in it
    kin::Axes above = q;
    above[z_] = plane;
    start(BlockSpec::Motion::Rapid);
    bool any = false;
    for (int i : lin)
      if (i != z_) any = add_words(above, {i}, !have_word_[static_cast<size_t>(i)]) || any;
    if (any) emit();  // already above the point: no empty block (a control would still move)
  }
  if (rotaries_differ(q) && z_ < 0 && axis_retract_) pkm_reposition(q, mv);
  start(BlockSpec::Motion::Rapid);
  set_mode94();
  if (!add_words(q, {0, 1, 2, 3, 4})) add_words(q, {lin[0]}, true);
  emit();
  cur_ = q;
  have_state_ = true;
  at_cut_ = false;
  off_path_ = false;
}

void Sequencer::approach(const kin::Axes& q, const cl::Move& mv) {
  // A rapid straight onto a point the CL cuts at would strike the part at rapid speed (a feed from wherever the
  // tool waits would cut a diagonal the CL never asked for): positioned above it, then fed in along the axis.
  const kin::Posed at = kin_.forward(q);
  cl::Move above = mv;
  above.kind = cl::MotionKind::Rapid;
  above.tip_in_part_mm = at.tip_mm + m_.post.singularity.retract_mm * at.axis;
  above.axis_in_part = at.axis;
  kin::Axes q_above;
  if (!kin::nearest_solution(kin_, kin::Posed{above.tip_in_part_mm, at.axis}, q, q_above) ||
      rotary_jump(q_above, q) > kFlipCheckRad || !kin_.check_limits(q_above).empty()) {
    rapid(q, mv);  // no room above it along the axis: positioned onto it, as the CL's own rapid would be
    return;
  }
  rapid(q_above, above);
  cl::Move from = above;
  from.tip_in_part_mm = kin_.forward(q_above).tip_mm;
  resume_blend_ = false;  // the plunge stops exactly on the point (no blend into the cut); the cut blends again
  feed_linear(from, q_above, mv, q);
  stop_exactly_at_last_feed();
  resume_blend_ = true;
  at_cut_ = true;
  cut_move_ = mv;
  if (cut_move_.feed_mm_per_min <= 0) cut_move_.feed_mm_per_min = kFallbackFeedMmMin;
}

/// After a cut, before a retract that is not along the tool axis (machine Z up, a tool change, the end):
/// feed out post.singularity.retract_mm along the tool axis first, so that a tilted tool under an
/// overhang does not drag through it on the way up.
void Sequencer::exit_along_axis() {
  if (!at_cut_ || cart_ || axis_retract_) return;
  at_cut_ = false;
  stop_exactly_at_last_feed();
  // Along the machine's actual tool axis (a planned program may tilt away from the CL axis).
  const kin::Posed here = kin_.forward(cur_);
  cl::Move from = cut_move_, up = cut_move_;
  from.tip_in_part_mm = here.tip_mm;
  from.axis_in_part = here.axis;
  up.tip_in_part_mm = here.tip_mm + m_.post.singularity.retract_mm * here.axis;
  up.axis_in_part = here.axis;
  kin::Axes q_up;
  if (!kin::nearest_solution(kin_, kin::Posed{up.tip_in_part_mm, here.axis}, cur_, q_up) ||
      rotary_jump(q_up, cur_) > kFlipCheckRad)
    return;  // no room along the axis: the plain retract follows (and the gate checks it against the meshes)
  feed_linear(from, cur_, up, q_up);
  off_path_ = true;
}

// --- Branch flips and unwinds between two feed points ------------------------------------------

/// Whether q1 continues the solution branch of q0 (no flip, no change of winding). Small rotary
/// changes always do; large ones are checked by tracking the pose continuously from q0.
bool Sequencer::continues_branch(const kin::Posed& pose0, const kin::Axes& q0, const kin::Posed& pose1,
                                 const kin::Axes& q1) const {
  if (rotary_jump(q0, q1) < kFlipCheckRad) return true;
  kin::Axes tracked;
  bool jumped = false;
  if (!kin::track_checked(kin_, q0, pose0, pose1, tracked, jumped)) return false;
  return !jumped && rotary_jump(tracked, q1) < 1e-6;
}

Sequencer::Turns Sequencer::plan_turns(const kin::Posed& pose0, const kin::Axes& q0, const kin::Posed& pose1,
                                       const kin::Axes& q1, const cl::Move& m0, const cl::Move& m1) const {
  refuse_if_asked(q0, q1, m0, m1);
  // The branch that starts at qa on pose0 and runs continuously to pose1 inside the limits, there.
  auto runs_through = [&](const kin::Axes& qa, kin::Axes& qb) {
    bool jumped = false;
    return kin::track_checked(kin_, qa, pose0, pose1, qb, jumped) && !jumped && kin_.check_limits(qb).empty();
  };
  Turns t;
  if (!branch_back(pose0, pose1, q1, t.start)) {
    if (runs_through(q0, t.end) && rotary_jump(t.end, q1) >= kFlipCheckRad) {
      t.kind = Turns::Kind::CutThenTurn;
      return t;
    }
    std::vector<kin::Solution> sols;
    kin_.inverse_all(pose0, &q0, sols);
    std::sort(sols.begin(), sols.end(), [&](const kin::Solution& a, const kin::Solution& b) {
      return rotary_jump(q0, a.axes) < rotary_jump(q0, b.axes);
    });
    for (const kin::Solution& sol : sols) {
      if (!sol.feasible() || rotary_jump(q0, sol.axes) < kFlipCheckRad || !runs_through(sol.axes, t.end)) continue;
      t.kind = Turns::Kind::BothEnds;
      t.start = sol.axes;
      t.turn_at_end = rotary_jump(t.end, q1) >= kFlipCheckRad;
      return t;
    }
    t.start = nearest_at_start(pose0, q0, q1, m0, m1);
  }
  t.kind = rotary_jump(q0, t.start) < 1e-9 ? Turns::Kind::None : Turns::Kind::AtStart;
  return t;
}

/// q0 (at m0) and q1 (at m1) lie on different branches or windings: a rotary limit or the branch rule
/// forces a flip or an unwind, made as plan_turns says. Returns the axis values at m0 from which the feed to q1
/// continues, or nothing where m1 was reached here (with q1).
std::optional<kin::Axes> Sequencer::reconfigure(const kin::Posed& pose0, const kin::Axes& q0, const kin::Posed& pose1,
                                                const kin::Axes& q1, const cl::Move& m0, const cl::Move& m1,
                                                double feed_mm_min) {
  const Turns t = plan_turns(pose0, q0, pose1, q1, m0, m1);
  switch (t.kind) {
    case Turns::Kind::None:
      return q0;
    case Turns::Kind::AtStart:
      turn_at(m0, pose0, q0, t.start, m1, feed_mm_min);
      return t.start;
    case Turns::Kind::CutThenTurn:
      feed_linear(m0, q0, m1, t.end);
      turn_at(m1, pose1, t.end, q1, m1, feed_mm_min);
      return std::nullopt;
    case Turns::Kind::BothEnds:
      turn_at(m0, pose0, q0, t.start, m1, feed_mm_min);
      feed_linear(m0, t.start, m1, t.end);
      if (t.turn_at_end) turn_at(m1, pose1, t.end, q1, m1, feed_mm_min);
      return std::nullopt;
  }
  return q0;
}

/// An error when the machine file says the post must not flip (post.singularity.flip: refuse).
void Sequencer::refuse_if_asked(const kin::Axes& q0, const kin::Axes& q1, const cl::Move& m0,
                                const cl::Move& m1) const {
  if (m_.post.singularity.flip == "refuse")
    throw InputError(SourceLoc{prog_.file, m1.line, 0},
                     fmt::format("the rotaries must flip or unwind between CL lines {} and {} ({}): a rotary limit "
                                 "or the branch rule forces it, and post.singularity.flip is 'refuse'",
                                 m0.line, m1.line, rotary_change(kin_, q0, q1)));
}

/// q1's branch at pose0, in q0n: followed back from q1 (at pose1), so that the feed from pose0 to pose1 is
/// continuous on it. False when it cannot get there inside the limits.
bool Sequencer::branch_back(const kin::Posed& pose0, const kin::Posed& pose1, const kin::Axes& q1,
                            kin::Axes& q0n) const {
  bool jumped = false;
  return kin::track_checked(kin_, q1, pose1, pose0, q0n, jumped) && !jumped;
}

/// The solution at pose0 (m0) nearest q1, for a turn made there when q1's branch cannot be followed back; an error
/// when none is inside the limits.
kin::Axes Sequencer::nearest_at_start(const kin::Posed& pose0, const kin::Axes& q0, const kin::Axes& q1,
                                      const cl::Move& m0, const cl::Move& m1) const {
  kin::Axes q0n;
  std::string why;
  if (!kin::nearest_solution(kin_, pose0, q1, q0n, &why))
    throw InputError(
        SourceLoc{prog_.file, m1.line, 0},
        fmt::format("the rotaries must flip or unwind between CL lines {} and {} ({}) but no axis "
                    "values inside the limits hold the tool at CL line {}{}",
                    m0.line, m1.line, rotary_change(kin_, q0, q1), m0.line, why.empty() ? "" : ": " + why));
  return q0n;
}

/// Turns the rotaries from qa to qb (the same pose, another branch or winding) at the CL point m (pose): in place
/// when the joint move keeps the tool pose within tolerance (at the singular point itself), else by retract along
/// the tool axis, turn, plunge. `next` is the CL move the turn is made for (its line and feed).
void Sequencer::turn_at(const cl::Move& m, const kin::Posed& pose, const kin::Axes& qa, const kin::Axes& qb,
                        const cl::Move& next, double feed_mm_min) {
  const auto& pol = m_.post.singularity;
  const SourceLoc where{prog_.file, next.line, 0};
  // In place: the straight joint move qa -> qb keeps the tool pose (e.g. the primary turning while the
  // tool axis lies along it).
  if (pol.flip == "auto") {
    const Vec3 ctrl = pose.tip_mm + opt_.control_offset_mm * pose.axis;
    const int n = std::clamp(static_cast<int>(std::ceil(rad2deg(rotary_jump(qa, qb)))), 2, 720);
    bool held = true;
    for (int k = 1; k < n && held; ++k) {
      const kin::Axes q = qa + (static_cast<double>(k) / n) * (qb - qa);
      const kin::Posed p = kin_.forward(q);
      held = (p.tip_mm + opt_.control_offset_mm * p.axis - ctrl).norm() <= tol_mm_ &&
             p.axis.dot(pose.axis) >= cos_tol_axis_ && kin_.passive_violation(q).empty();
    }
    if (held) {
      check_limits(qb, next);
      emit_feed_to(qa, qb, 0.0, feed_mm_min);
      ++sum_.reorientations;
      sum_.warnings.push_back(fmt::format("{}: rotaries turned in place at CL line {} ({}), the tool held", where.str(),
                                          m.line, rotary_change(kin_, qa, qb)));
      return;
    }
  }
  // Retract along the tool axis, turn at the safe position, come back above the point, plunge. The tip goes out and
  // in along the axis the machine actually has at each end of the turn (FK of qa, of qb): a calibrated machine may
  // reach the CL axis only to within a hundredth of a degree or so, and a plunge along the CL axis then runs beside
  // the tool's own (0.015 mm over 10 mm at 1.5 mrad), which the gate rightly takes for a cut off the path. The
  // orientation asked of the IK stays the CL axis, as at the point itself: near the pole a request a hair off it
  // would land on a primary half a turn away.
  const double d = pol.retract_mm;
  kin::Axes up0, up1;
  // (Not on a machine whose FK is warm-started from its previous solve, the XMINI: from one branch to the other it
  // may converge elsewhere. Its IK reaches the CL axis to within its own slack.)
  const bool own_axis = !kin_.traits().forward_depends_on_call_order;
  auto above_m = [&](const kin::Axes& q) {  // the point d above m along q's tool axis, at next's feed
    Vec3 axis = pose.axis;
    if (own_axis) {
      const Vec3 a = kin_.forward(q).axis;
      if (std::atan2(a.cross(pose.axis).norm(), a.dot(pose.axis)) <= tol::kReachSlackRad) axis = a;
    }
    cl::Move up = m;
    up.tip_in_part_mm = pose.tip_mm + d * axis;
    up.axis_in_part = pose.axis;
    up.feed_mm_per_min = feed_mm_min;
    up.line = next.line;
    return up;
  };
  const cl::Move m_up0 = above_m(qa), m_up1 = above_m(qb);
  if (!kin::nearest_solution(kin_, {m_up0.tip_in_part_mm, pose.axis}, qa, up0) ||
      !kin::nearest_solution(kin_, {m_up1.tip_in_part_mm, pose.axis}, qb, up1) ||
      rotary_jump(up0, qa) > kFlipCheckRad || rotary_jump(up1, qb) > kFlipCheckRad)
    throw InputError(where, fmt::format("the rotaries must flip or unwind at CL line {} ({}) but the tool cannot "
                                        "retract {:.1f} mm along its axis inside the limits "
                                        "(post.singularity.retract_mm)",
                                        m.line, rotary_change(kin_, qa, qb), d));
  stop_exactly_at_last_feed();     // no blend of the cut into the retract, nor of the plunge into the cut
  feed_linear(m, qa, m_up0, up0);  // straight out along the tool axis (linearised: a PKM's joints are not)
  at_cut_ = false;                 // already out
  rapid(up1, next);
  resume_blend_ = false;
  cl::Move m_back = m;
  m_back.feed_mm_per_min = feed_mm_min;
  m_back.line = next.line;
  feed_linear(m_up1, up1, m_back, qb);  // and straight back in
  resume_blend_ = true;
  ++sum_.retracts;
  sum_.warnings.push_back(
      fmt::format("{}: rotaries flip or unwind at CL line {} ({}): retract {:.1f} mm along the "
                  "tool axis, turn, plunge",
                  where.str(), m.line, rotary_change(kin_, qa, qb), d));
}

// --- Retract along the tool axis (machines without a Z axis, e.g. the XMINI; Cartesian mode) -----

/// The point where the tip, leaving along the tool axis (or vertically when the axis is nearly
/// horizontal), reaches the plane z = safe_z_mm. False when the tip is already at or above it.
bool Sequencer::retract_point(const Vec3& tip, const Vec3& axis, Vec3& up) const {
  return kin::axial_retract_point(tip, axis, m_.post.safe_z_mm, tol::kLimitSlackMm, up);
}

/// Under tool-tip control: the point up the tool axis from the tip (machine axes q there) where the machine's
/// Z reaches the safe Z; on a machine without one, where the tip reaches the plane z = safe_z_mm. False when
/// already there, or when the tool axis does not lift the machine's Z.
bool Sequencer::tcp_retract_point(const Vec3& tip, const Vec3& axis, const kin::Axes& q, Vec3& up) const {
  if (z_ < 0) return retract_point(tip, axis, up);
  const Vec3 dir = axis.normalized();
  kin::Axes q1 = q;  // the same rotaries, the tip 1 mm up the axis: the linear axes are affine in it
  if (!kin_.solve_for_rotaries(kin::Posed{tip + dir, dir}, q1)) return false;
  const double slope = q1[z_] - q[z_];
  if (slope < kin::kMinRetractAxisZ) return false;
  double d = (safe_z_ - q[z_]) / slope;
  // A steep tool reaches the safe Z only far out along its axis: the linear axes (affine in d) stop it at their
  // limits, short of the safe Z, rather than the program leaving the machine's travel.
  double d_travel = std::numeric_limits<double>::infinity();
  for (int i = 0; i < 5; ++i) {
    const auto& a = m_.axes[static_cast<size_t>(i)];
    const double rate = q1[i] - q[i];
    if (a.rotary() || std::abs(rate) < 1e-12) continue;
    d_travel = std::min(d_travel, ((rate > 0 ? a.max : a.min) - q[i]) / rate - kRetractLimitMarginMm);
  }
  if (d_travel < d) {
    d = d_travel;
    if (!retract_short_warned_) {
      retract_short_warned_ = true;
      sum_.warnings.push_back(fmt::format(
          "{}: the retract along a tilted tool axis (under tool-tip control) stops at the machine's travel, below "
          "the safe Z {} mm: the rotaries turn there (the gate checks the turn against the machine's bodies)",
          prog_.file, safe_z_));
    }
  }
  if (d <= tol::kLimitSlackMm) return false;
  up = tip + d * dir;
  return true;
}

/// Joint values with the tip of q moved along its tool axis to the safe plane, the axis kept (by IK).
kin::Axes Sequencer::pkm_retracted(const kin::Axes& q, const SourceLoc& where) {
  kin::Axes out;
  Vec3 up;
  if (!kin::retract_along_axis(kin_, q, m_.post.safe_z_mm, tol::kLimitSlackMm, out, &up))
    throw InputError(where, fmt::format("cannot retract the tool along its axis to the safe plane z = {:.3f} mm "
                                        "(post.safe_z_mm): no axis values inside the limits put the tip at "
                                        "({:.3f}, {:.3f}, {:.3f}) with this tool axis",
                                        m_.post.safe_z_mm, up.x(), up.y(), up.z()));
  return out;
}

/// Retract before a tool change and at the end of the program.
void Sequencer::axis_retract(const SourceLoc& where) {
  if (!axis_retract_) return;
  if (cart_) {
    Vec3 up;
    if (!tcp_retract_point(cart_tip_, cart_axis_, cart_q_, up)) return;
    kin::Axes v = cur_;
    int k = 0;
    for (int i = 0; i < 5; ++i)
      if (!m_.axes[static_cast<size_t>(i)].rotary()) v[i] = up[k++];
    emit_g0(v);
    off_path_ = true;
    track_control(v, cart_axis_);
    cart_tip_ = up;
    kin::Axes q_up = cart_q_;
    if (kin_.solve_for_rotaries(kin::Posed{up, cart_axis_}, q_up)) cart_q_ = q_up;
    return;
  }
  emit_g0(pkm_retracted(cur_, where));
  off_path_ = true;
}

/// Joint-space rapid to q with a rotary change: retract along the current tool axis, turn to q's tool
/// axis at the safe plane, go above q (along its axis); the caller then plunges to q.
void Sequencer::pkm_reposition(const kin::Axes& q, const cl::Move& mv) {
  const SourceLoc where{prog_.file, mv.line, 0};
  if (!have_state_) {
    emit_g0(pkm_retracted(q, where));
    return;
  }
  kin::Axes up, turned, above;  // the planner's swept check sweeps the same moves
  if (!kin::reposition_at_plane(kin_, cur_, q, m_.post.safe_z_mm, tol::kLimitSlackMm, up, turned, above)) {
    // The retract that leaves the limits says so (the one above q first).
    (void)pkm_retracted(q, where);
    (void)pkm_retracted(cur_, where);
    CSCAM_CHECK(false, "reposition_at_plane failed where both retracts succeed");
  }
  emit_g0(up);
  emit_g0(turned);
  emit_g0(above);
}

}  // namespace cscam::post::detail
