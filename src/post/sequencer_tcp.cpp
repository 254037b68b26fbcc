// The motion sequencer (sequencer.hpp) under tool-tip control: one block per CL point in tip words, the control
// interpolates; points inserted where its interpolation of the rotary words would turn the tool axis away.
#include <fmt/format.h>

#include <array>
#include <cmath>
#include <limits>
#include <utility>
#include <vector>

#include "cscam/core/error.hpp"
#include "cscam/core/tolerances.hpp"
#include "cscam/core/units.hpp"
#include "cscam/kin/track.hpp"
#include "linearize.hpp"
#include "sequencer.hpp"

namespace cscam::post::detail {

namespace {

// Rotary words of the XMINI in Cartesian mode: the tool vector u (W) as the virtual wrist angles (C, A)
// of an untilted platform, u = (-sin A sin C, -sin A cos C, cos A) (docs/xmini.md with R_BP = I and
// nominal wrist): the two branches (C, A) and (C + 180 deg, -A); the one nearest to the machine's own
// wrist values q_c, q_a is taken, so branch and winding follow the chosen axis path. At A = 0, C = q_c.
std::array<double, 2> xmini_virtual_ca(const Vec3& u_W, double q_c, double q_a) {
  const Vec3 u = u_W.normalized();
  const double s = std::hypot(u.x(), u.y());
  if (s < tol::kSingularRad) return {q_c, u.z() >= 0 ? 0.0 : kPi};
  const double a = std::atan2(s, u.z());
  const double c = std::atan2(-u.x(), -u.y());
  std::array<double, 2> best{};
  double best_d = std::numeric_limits<double>::infinity();
  for (const auto& [cb, ab] : {std::pair{c, a}, std::pair{c + kPi, -a}}) {
    const double cw = cb + 2.0 * kPi * std::round((q_c - cb) / (2.0 * kPi));  // winding nearest to q_c
    const double d = std::abs(cw - q_c) + std::abs(ab - q_a);
    if (d < best_d) {
      best_d = d;
      best = {cw, ab};
    }
  }
  return best;
}

}  // namespace

// --- Cartesian mode: one block per CL point, the control interpolates ------------------------

/// The words of a Cartesian block in the machine's axis slots: tip in the linear slots, in the
/// rotary slots the machine's rotaries (serial: they alone set the tool vector) or, for a virtual-wrist
/// model (the XMINI), the virtual wrist angles of the tool vector (xmini_virtual_ca).
kin::Axes Sequencer::cartesian_words(const Vec3& tip, const Vec3& axis, const kin::Axes& q) const {
  kin::Axes v = q;
  int k = 0;
  for (int i = 0; i < 5; ++i)
    if (!m_.axes[static_cast<size_t>(i)].rotary()) v[i] = tip[k++];
  if (traits_.tcp_rotary_words == kin::Traits::TcpRotaryWords::VirtualWrist) {
    const auto rp = kin_.rotary_pair();
    const auto ca = xmini_virtual_ca(axis, q[rp[0]], q[rp[1]]);
    v[rp[0]] = ca[0];
    v[rp[1]] = ca[1];
  }
  return v;
}

void Sequencer::cartesian(const cl::Move& mv, const kin::Axes& q) {
  cur_line_ = mv.line;
  const Vec3 axis = mv.axis_in_part.normalized();
  const kin::Axes v = cartesian_words(mv.tip_in_part_mm, axis, q);
  // Positioned (rapid) at a CL rapid, and where the tool is off the CL path: at the start, or after a retract.
  bool position = !have_state_ || off_path_ || mv.kind == cl::MotionKind::Rapid;
  if (position && mv.kind != cl::MotionKind::Rapid) {
    // A feed move: positioned above it along the axis, then fed in (as Sequencer::approach); with no room above it,
    // positioned onto it as a CL rapid would be.
    cl::Move above = mv;
    above.kind = cl::MotionKind::Rapid;
    above.tip_in_part_mm = mv.tip_in_part_mm + m_.post.singularity.retract_mm * axis;
    kin::Axes q_above;
    if (kin::nearest_solution(kin_, kin::Posed{above.tip_in_part_mm, axis}, q, q_above) &&
        rotary_jump(q_above, q) <= kFlipCheckRad && kin_.check_limits(q_above).empty()) {
      cartesian(above, q_above);
      position = false;
    }
  }
  if (position) {
    if (axis_retract_ && rotaries_differ(v)) {
      if (have_state_) axis_retract(SourceLoc{prog_.file, mv.line, 0});
      Vec3 above;
      if (tcp_retract_point(mv.tip_in_part_mm, axis, q, above)) {
        kin::Axes va = v;
        int k = 0;
        for (int i = 0; i < 5; ++i)
          if (!m_.axes[static_cast<size_t>(i)].rotary()) va[i] = above[k++];
        turn_stepwise(va);
        const bool rot = rotaries_differ(va);
        start(BlockSpec::Motion::Rapid);
        if (add_words(va, {0, 1, 2, 3, 4})) {
          add_vector(axis, rot);
          set_mode94();
          emit();
        }
        cur_ = va;
        track_control(va, axis);
      }
    }
    turn_stepwise(v);
    const bool rot = rotaries_differ(v);
    start(BlockSpec::Motion::Rapid);
    if (add_words(v, {0, 1, 2, 3, 4})) {
      add_vector(axis, rot);
      set_mode94();
      emit();
    }
  } else {
    const double feed_mm_min = mv.feed_mm_per_min > 0 ? mv.feed_mm_per_min : kFallbackFeedMmMin;
    if (!vectors_ && traits_.tcp_rotary_words == kin::Traits::TcpRotaryWords::MachineAngles) {
      const kin::Posed pose0{cart_tip_, cart_axis_}, pose1{mv.tip_in_part_mm, axis};
      if (!continues_branch(pose0, cart_q_, pose1, q)) tcp_reconfigure(pose0, pose1, q, mv, feed_mm_min);
    }
    tcp_pieces(cart_move_, cart_q_, mv, q);
    for (const auto& pc : tcp_pieces_) emit_tcp_feed(pc.tip, pc.axis, pc.q, feed_mm_min);
  }
  if (position) track_control(v, axis);
  off_path_ = false;
  cur_ = v;
  cart_q_ = q;
  cart_tip_ = mv.tip_in_part_mm;
  cart_axis_ = axis;
  cart_move_ = mv;
  have_state_ = true;
}

/// Under tool-tip control with the machine's rotary angles as words: the axis values at the last point (cart_q_,
/// pose0) and q1 (at mv) lie on different branches or windings, and the words' linear interpolation would swing
/// the tool through other orientations on the path. As reconfigure does in machine coordinates: retract along the
/// tool axis, turn the rotary words there (a rapid; the control holds the tip), plunge back; cart_q_ is then q1's
/// branch at pose0, from which the cut to mv continues.
void Sequencer::tcp_reconfigure(const kin::Posed& pose0, const kin::Posed& pose1, const kin::Axes& q1,
                                const cl::Move& mv, double feed_mm_min) {
  const SourceLoc where{prog_.file, mv.line, 0};
  const kin::Axes q0 = cart_q_;
  refuse_if_asked(q0, q1, cart_move_, mv);
  kin::Axes q0n;
  if (!branch_back(pose0, pose1, q1, q0n)) q0n = nearest_at_start(pose0, q0, q1, cart_move_, mv);
  if (rotary_jump(q0, q0n) < 1e-9) return;  // tracking stalled near a singularity: same branch after all
  const double d = m_.post.singularity.retract_mm;
  const Vec3 up = pose0.tip_mm + d * pose0.axis;
  kin::Axes q_up = q0, qn_up = q0n;
  if (!kin_.solve_for_rotaries(kin::Posed{up, pose0.axis}, q_up) ||
      !kin_.solve_for_rotaries(kin::Posed{up, pose0.axis}, qn_up) || !kin_.check_limits(q_up).empty() ||
      !kin_.check_limits(qn_up).empty())
    throw InputError(where, fmt::format("the rotaries must flip or unwind before CL line {} ({}) but the tool cannot "
                                        "retract {:.1f} mm along its axis inside the limits "
                                        "(post.singularity.retract_mm)",
                                        mv.line, rotary_change(kin_, q0, q0n), d));
  stop_exactly_at_last_feed();
  emit_tcp_feed(up, pose0.axis, q_up, feed_mm_min);  // out along the tool axis
  const kin::Axes v = cartesian_words(up, pose0.axis, qn_up);
  emit_g0(v);
  track_control(v, pose0.axis);
  cart_q_ = qn_up;
  resume_blend_ = false;
  emit_tcp_feed(pose0.tip_mm, pose0.axis, q0n, feed_mm_min);  // and straight back in
  resume_blend_ = true;
  ++sum_.retracts;
  sum_.warnings.push_back(
      fmt::format("{}: rotaries flip or unwind before CL line {} ({}): retract {:.1f} mm along "
                  "the tool axis, turn, plunge",
                  where.str(), mv.line, rotary_change(kin_, q0, q0n), d));
}

/// The tool axis that the words v (tip + rotary words) give, as the control interpolates them.
bool Sequencer::axis_of_words(const kin::Axes& v, Vec3& axis) const {
  const auto rp = kin_.rotary_pair();
  if (traits_.tcp_rotary_words == kin::Traits::TcpRotaryWords::VirtualWrist) {
    const double c = v[rp[0]], a = v[rp[1]];
    axis = Vec3(-std::sin(a) * std::sin(c), -std::sin(a) * std::cos(c), std::cos(a));
    return true;
  }
  Vec3 tip;
  int k = 0;
  for (int i = 0; i < 5; ++i)
    if (!m_.axes[static_cast<size_t>(i)].rotary()) tip[k++] = v[i];
  return kin_.tool_axis_at(v[rp[0]], v[rp[1]], tip, axis);
}

/// The linearizer of tool-tip control: the control moves the tip straight (exactly the CL segment) and
/// interpolates the rotary words linearly; where that turns the axis away from the CL's interpolated axis by
/// more than the axis tolerance, points are inserted (tip on the segment, axis on the CL's great circle).
void Sequencer::tcp_pieces(const cl::Move& m0, const kin::Axes& q0, const cl::Move& m1, const kin::Axes& q1) {
  tcp_pieces_.clear();
  const Vec3 P0 = m0.tip_in_part_mm, P1 = m1.tip_in_part_mm;
  const Slerp axis(m0.axis_in_part.normalized(), m1.axis_in_part.normalized());
  struct Span {
    double sa, sb;
    kin::Axes qa, qb;
    int depth;
  };
  std::vector<Span> stack{{0.0, 1.0, q0, q1, 0}};
  while (!stack.empty()) {
    const Span sp = stack.back();
    stack.pop_back();
    const Vec3 ta = P0 + sp.sa * (P1 - P0), tb = P0 + sp.sb * (P1 - P0);
    const kin::Axes wa = cartesian_words(ta, axis(sp.sa), sp.qa), wb = cartesian_words(tb, axis(sp.sb), sp.qb);
    bool bad = false;
    if (opt_.linearise && sp.depth < opt_.max_subdivision_depth) {
      const Vec3 ua = axis(sp.sa), ub = axis(sp.sb);
      for (double t : {0.5, 0.25, 0.75}) {
        Vec3 u;
        bool ok = true;
        if (vectors_) {  // the vector on the great circle, as the gate reads it (gnomonic coordinates)
          ok = ua.z() > 0 && ub.z() > 0;
          u = Vec3(ua.x() / ua.z() + t * (ub.x() / ub.z() - ua.x() / ua.z()),
                   ua.y() / ua.z() + t * (ub.y() / ub.z() - ua.y() / ua.z()), 1.0)
                  .normalized();
        } else {
          ok = axis_of_words(wa + t * (wb - wa), u);
        }
        if (!ok || u.dot(axis(sp.sa + t * (sp.sb - sp.sa))) < cos_tol_axis_) {
          bad = true;
          break;
        }
      }
    }
    if (bad) {
      const double sm = 0.5 * (sp.sa + sp.sb);
      const Vec3 um = axis(sm);
      kin::Axes qm;
      bool jumped = false;
      const kin::Posed from{ta, axis(sp.sa)}, to{P0 + sm * (P1 - P0), um};
      ++sum_.ik_calls;
      bool tracked = kin::track_checked(kin_, sp.qa, from, to, qm, jumped) && !jumped;
      if (!tracked) {
        // From a singular start (the tool along the primary rotary's axis, which then turns freely) the branch is the
        // end's: tracked back from there. The halves are judged again like any span.
        ++sum_.ik_calls;
        tracked = kin::track_checked(kin_, sp.qb, kin::Posed{tb, axis(sp.sb)}, to, qm, jumped) && !jumped;
      }
      if (tracked) {
        check_limits(qm, m1);
        ++sum_.inserted_points;
        stack.push_back({sm, sp.sb, qm, sp.qb, sp.depth + 1});
        stack.push_back({sp.sa, sm, sp.qa, qm, sp.depth + 1});
        continue;
      }
    }
    tcp_pieces_.push_back({tb, axis(sp.sb), sp.qb});
  }
}

/// The machine axes the control moves to for the tip words v (IK nearest to its previous axes, as the gate
/// reads the program back).
void Sequencer::track_control(const kin::Axes& v, const Vec3& cl_axis) {
  Vec3 tip, u = cl_axis;
  int k = 0;
  for (int i = 0; i < 5; ++i)
    if (!m_.axes[static_cast<size_t>(i)].rotary()) tip[k++] = v[i];
  if (!vectors_ && !axis_of_words(v, u)) return;
  if (!vectors_ && traits_.tcp_rotary_words == kin::Traits::TcpRotaryWords::MachineAngles) {
    kin::Axes q = ctrl_q_;
    for (const int r : kin_.rotary_pair()) q[r] = v[r];
    if (kin_.solve_for_rotaries(kin::Posed{tip, u}, q)) ctrl_q_ = q;
    return;
  }
  kin::Axes sol;
  if (kin::nearest_solution(kin_, kin::Posed{tip, u}, ctrl_q_, sol)) ctrl_q_ = sol;
}

/// One tool-tip-control feed block to (tip, axis) with machine axes q there.
void Sequencer::emit_tcp_feed(const Vec3& tip, const Vec3& axis, const kin::Axes& q, double feed_mm_min) {
  const kin::Axes v = cartesian_words(tip, axis, q);
  const bool rot = rotaries_differ(v);
  start(BlockSpec::Motion::Linear);
  if (add_words(v, {0, 1, 2, 3, 4})) {
    add_vector(axis, rot);
    set_mode94();
    // The control moves the tip at F; slowed so that no machine axis exceeds its max_feed.
    const double tip_mm = (tip - cart_tip_).norm();
    const double programmed = tip_mm / feed_mm_min;
    // Judged by the planned axes and by what the control computes from the words (its IK nearest to where it
    // is: near a singularity it may turn a rotary much more than the plan).
    const kin::Axes ctrl_before = ctrl_q_;
    track_control(v, axis);
    const double minutes =
        std::max(block_minutes(cart_q_, q, programmed), block_minutes(ctrl_before, ctrl_q_, programmed));
    const double f = minutes > programmed * (1.0 + 1e-9) ? word_length(cur_, v) / minutes : feed_mm_min * feed_to_file_;
    emit_per_minute(f);
  }
  cur_ = v;
  cart_q_ = q;
  cart_tip_ = tip;
  cart_axis_ = axis;
}

}  // namespace cscam::post::detail
