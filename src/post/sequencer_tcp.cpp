// The motion sequencer (sequencer.hpp) under tool-tip control: one block per CL point in tip words, the control
// interpolates; points inserted where its interpolation of the rotary words would turn the tool axis away.
#include <fmt/format.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <optional>
#include <utility>
#include <vector>

#include "cscam/core/error.hpp"
#include "cscam/core/segment.hpp"
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
    Linearizer::ClAxes ends;
    const Linearizer::ClAxes* cl = tcp_cl_axes(mv, ends);
    bool reached = false;  // tcp_reconfigure cut to mv itself
    if (!vectors_ && traits_.tcp_rotary_words == kin::Traits::TcpRotaryWords::MachineAngles) {
      const kin::Posed pose0{cart_tip_, cart_axis_}, pose1{mv.tip_in_part_mm, axis};
      // A planned pair of axis values whose words keep the tool in the cone is the plan's own way between the points,
      // even where tracking the great circle of the two axes would need another branch (beside the singular pole).
      if (!continues_branch(pose0, cart_q_, pose1, q) && !(cl && words_in_cone(pose0, cart_q_, pose1, q, *cl)))
        reached = tcp_reconfigure(pose0, pose1, q, mv, feed_mm_min);
    }
    if (!reached) tcp_feed(cart_move_, cart_q_, mv, q, feed_mm_min, cl);
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
/// pose0) and q1 (at mv) lie on different branches or windings, and the words' linear interpolation would swing the
/// tool. Makes the turns plan_turns says, as Sequencer::reconfigure does. Returns whether it cut to mv itself.
bool Sequencer::tcp_reconfigure(const kin::Posed& pose0, const kin::Posed& pose1, const kin::Axes& q1,
                                const cl::Move& mv, double feed_mm_min) {
  const kin::Axes q0 = cart_q_;
  const cl::Move m0 = cart_move_;
  const Turns t = plan_turns(pose0, q0, pose1, q1, m0, mv);
  switch (t.kind) {
    case Turns::Kind::None:
      return false;
    case Turns::Kind::AtStart:
      tcp_turn_at(pose0, q0, t.start, mv, feed_mm_min);
      return false;
    case Turns::Kind::CutThenTurn:
      tcp_feed(m0, q0, mv, t.end, feed_mm_min, nullptr);
      tcp_turn_at(pose1, t.end, q1, mv, feed_mm_min);
      return true;
    case Turns::Kind::BothEnds:
      tcp_turn_at(pose0, q0, t.start, mv, feed_mm_min);
      tcp_feed(m0, t.start, mv, t.end, feed_mm_min, nullptr);
      if (t.turn_at_end) tcp_turn_at(pose1, t.end, q1, mv, feed_mm_min);
      return true;
  }
  return false;
}

/// Under tool-tip control: turns the rotaries from qa to qb (the same pose, another branch or winding) at `pose` by
/// retract along the tool axis, turn, plunge. `mv` is the CL move the turn is made for.
void Sequencer::tcp_turn_at(const kin::Posed& pose, const kin::Axes& qa, const kin::Axes& qb, const cl::Move& mv,
                            double feed_mm_min) {
  const SourceLoc where{prog_.file, mv.line, 0};
  const double d = m_.post.singularity.retract_mm;
  const Vec3 up = pose.tip_mm + d * pose.axis;
  kin::Axes q_up = qa, qn_up = qb;
  if (!kin_.solve_for_rotaries(kin::Posed{up, pose.axis}, q_up) ||
      !kin_.solve_for_rotaries(kin::Posed{up, pose.axis}, qn_up) || !kin_.check_limits(q_up).empty() ||
      !kin_.check_limits(qn_up).empty())
    throw InputError(where, fmt::format("the rotaries must flip or unwind before CL line {} ({}) but the tool cannot "
                                        "retract {:.1f} mm along its axis inside the limits "
                                        "(post.singularity.retract_mm)",
                                        mv.line, rotary_change(kin_, qa, qb), d));
  stop_exactly_at_last_feed();
  emit_tcp_feed(up, pose.axis, q_up, feed_mm_min);  // out along the tool axis
  const kin::Axes v = cartesian_words(up, pose.axis, qn_up);
  emit_g0(v);
  track_control(v, pose.axis);
  cart_q_ = qn_up;
  resume_blend_ = false;
  emit_tcp_feed(pose.tip_mm, pose.axis, qb, feed_mm_min);  // and straight back in
  resume_blend_ = true;
  ++sum_.retracts;
  sum_.warnings.push_back(
      fmt::format("{}: rotaries flip or unwind before CL line {} ({}): retract {:.1f} mm along "
                  "the tool axis, turn, plunge",
                  where.str(), mv.line, rotary_change(kin_, qa, qb), d));
}

/// The feed m0 (at q0) -> m1 (at q1) under tool-tip control, in the pieces tcp_pieces splits it into.
void Sequencer::tcp_feed(const cl::Move& m0, const kin::Axes& q0, const cl::Move& m1, const kin::Axes& q1,
                         double feed_mm_min, const Linearizer::ClAxes* cl) {
  tcp_pieces(m0, q0, m1, q1, cl);
  for (const auto& pc : tcp_pieces_) emit_tcp_feed(pc.tip, pc.axis, pc.q, feed_mm_min);
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

/// The CL axes (the cone reference of a planned program) at the ends of the TCP segment into the program move m1, from
/// the previous program move where the sequencer last was; null without a cone reference or after an inserted point.
const Linearizer::ClAxes* Sequencer::tcp_cl_axes(const cl::Move& m1, Linearizer::ClAxes& ends) const {
  const auto& moves = prog_.moves;
  if (opt_.cone_deg <= 0 || &m1 <= moves.data() || &m1 >= moves.data() + moves.size()) return nullptr;
  const cl::Move& m0 = *(&m1 - 1);
  if (cart_move_.line != m0.line || cart_move_.tip_in_part_mm != m0.tip_in_part_mm) return nullptr;
  return cl_axes(m0, m1, ends);  // the same lookup as the machine-coordinate feeds'
}

/// Whether the control's interpolation of the words from (pose0, q0) to (pose1, q1) keeps the tool axis within the cone
/// (plus the axis tolerance) of the CL's interpolated axis, sampled finely (the pieces are then judged one by one).
bool Sequencer::words_in_cone(const kin::Posed& pose0, const kin::Axes& q0, const kin::Posed& pose1,
                              const kin::Axes& q1, const Linearizer::ClAxes& cl) const {
  const Slerp cl_axis(cl.from.normalized(), cl.to.normalized());
  const double cos_cone_tol = std::cos(std::min(kPi, deg2rad(opt_.cone_deg) + tol_axis_rad_));
  const kin::Axes wa = cartesian_words(pose0.tip_mm, pose0.axis, q0),
                  wb = cartesian_words(pose1.tip_mm, pose1.axis, q1);
  constexpr int kSamples = 32;
  for (int k = 0; k <= kSamples; ++k) {
    const double t = static_cast<double>(k) / kSamples;
    Vec3 u;
    if (!axis_of_words(wa + t * (wb - wa), u)) return false;
    if (cl_axis.best_dot(u, std::max(0.0, t - 0.25), std::min(1.0, t + 0.25)) < cos_cone_tol) return false;
  }
  return true;
}

/// The linearizer of tool-tip control: the control moves the tip straight (exactly the CL segment) and
/// interpolates the rotary words linearly; where that turns the axis away from the CL's interpolated axis by
/// more than the axis tolerance, points are inserted (tip on the segment, axis on the CL's great circle). With a cone
/// reference (`cl`: a planned program's CL axes at the segment's ends), an axis within the cone plus the tolerance of
/// the CL's own interpolated axis is accepted as well, and an inserted point keeps the rotaries the words pass through:
/// near a singular orientation the great circle of two planned axes can pass on the other side of the pole from the
/// words' interpolation, and following it swings the primary half a turn (as Linearizer::axis_ok).
void Sequencer::tcp_pieces(const cl::Move& m0, const kin::Axes& q0, const cl::Move& m1, const kin::Axes& q1,
                           const Linearizer::ClAxes* cl) {
  tcp_pieces_.clear();
  const Slerp axis(m0.axis_in_part.normalized(), m1.axis_in_part.normalized());
  const std::optional<Slerp> cl_axis =
      cl ? std::optional<Slerp>(Slerp(cl->from.normalized(), cl->to.normalized())) : std::nullopt;
  const double cos_cone_tol = std::cos(std::min(kPi, deg2rad(opt_.cone_deg) + tol_axis_rad_));
  // The controlled points: tips, or ball centres where a plan tilted the tool within a cone and keeps those on the CL
  // path. The control moves the tip along a straight line between two blocks while it turns the axis, so a ball centre
  // leaves the straight line by the offset times the axis's departure from its chord: up to 0.03 mm for a 3 mm ball
  // turned 20 deg in one step. Pieces are split until the centre stays within the tolerance too.
  const double off = opt_.control_offset_mm;
  const Vec3 C0 = m0.tip_in_part_mm + off * axis(0.0), C1 = m1.tip_in_part_mm + off * axis(1.0);
  const Vec3 c01 = C1 - C0;
  const double L2 = c01.squaredNorm();
  struct Span {
    double sa, sb;
    kin::Axes qa, qb;
    Vec3 ta, tb, ua, ub;  // tips and axes at the ends
    int depth;
  };
  std::vector<Span> stack{{0.0, 1.0, q0, q1, m0.tip_in_part_mm, m1.tip_in_part_mm, axis(0.0), axis(1.0), 0}};
  while (!stack.empty()) {
    const Span sp = stack.back();
    stack.pop_back();
    const kin::Axes wa = cartesian_words(sp.ta, sp.ua, sp.qa), wb = cartesian_words(sp.tb, sp.ub, sp.qb);
    bool bad = false;
    if (opt_.linearise && sp.depth < opt_.max_subdivision_depth) {
      for (double t : {0.5, 0.25, 0.75}) {
        Vec3 u;
        bool ok = true;
        if (vectors_) {  // the vector on the great circle, as the gate reads it (gnomonic coordinates)
          ok = sp.ua.z() > 0 && sp.ub.z() > 0;
          u = Vec3(sp.ua.x() / sp.ua.z() + t * (sp.ub.x() / sp.ub.z() - sp.ua.x() / sp.ua.z()),
                   sp.ua.y() / sp.ua.z() + t * (sp.ub.y() / sp.ub.z() - sp.ua.y() / sp.ua.z()), 1.0)
                  .normalized();
        } else {
          ok = axis_of_words(wa + t * (wb - wa), u);
        }
        const bool axis_ok = ok && (u.dot(axis(sp.sa + t * (sp.sb - sp.sa))) >= cos_tol_axis_ ||
                                    (cl_axis && cl_axis->best_dot(u, sp.sa, sp.sb) >= cos_cone_tol));
        if (!axis_ok ||
            (off != 0.0 && point_segment_distance(sp.ta + t * (sp.tb - sp.ta) + off * u, C0, c01, L2) > tol_mm_)) {
          bad = true;
          break;
        }
      }
    }
    if (bad) {
      const double sm = 0.5 * (sp.sa + sp.sb);
      kin::Axes qm = 0.5 * (sp.qa + sp.qb);
      Vec3 um = axis(sm), tm = C0 + sm * c01 - off * um;
      bool placed = false;
      if (cl_axis && !vectors_) {
        // The rotaries the words pass through at the middle, if their axis lies in the cone: only the tip is moved
        // (onto the path with that axis).
        Vec3 uw;
        if (axis_of_words(0.5 * (wa + wb), uw) && cl_axis->best_dot(uw, sp.sa, sp.sb) >= cos_cone_tol) {
          const Vec3 tw = C0 + sm * c01 - off * uw;
          kin::Axes qw = qm;
          if (kin_.solve_for_rotaries(kin::Posed{tw, uw}, qw) && kin_.check_limits(qw).empty()) {
            qm = qw, um = uw, tm = tw;
            placed = true;
          }
        }
      }
      if (!placed) {
        bool jumped = false;
        const kin::Posed from{sp.ta, sp.ua}, to{tm, um};
        ++sum_.ik_calls;
        placed = kin::track_checked(kin_, sp.qa, from, to, qm, jumped) && !jumped;
        if (!placed) {
          // From a singular start (the tool along the primary rotary's axis, which then turns freely) the branch is
          // the end's: tracked back from there. The halves are judged again like any span.
          ++sum_.ik_calls;
          placed = kin::track_checked(kin_, sp.qb, kin::Posed{sp.tb, sp.ub}, to, qm, jumped) && !jumped;
        }
      }
      if (placed) {
        check_limits(qm, m1);
        ++sum_.inserted_points;
        stack.push_back({sm, sp.sb, qm, sp.qb, tm, sp.tb, um, sp.ub, sp.depth + 1});
        stack.push_back({sp.sa, sm, sp.qa, qm, sp.ta, tm, sp.ua, um, sp.depth + 1});
        continue;
      }
    }
    tcp_pieces_.push_back({sp.tb, sp.ub, sp.qb});
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
    double minutes = std::max(block_minutes(cart_q_, q, programmed), block_minutes(ctrl_before, ctrl_q_, programmed));
    if (traits_.tcp_rotary_words == kin::Traits::TcpRotaryWords::VirtualWrist) {
      // The control interpolates the virtual wrist words themselves: beside the pole their C swings with the tool
      // vector's azimuth while the machine's own wrist hardly moves (the XMINI's at a 0.06 deg tilt: 87 deg per mm).
      kin::Axes words_from = v;
      for (const int r : kin_.rotary_pair()) words_from[r] = cur_[r];
      minutes = std::max(minutes, block_minutes(words_from, v, programmed));
    }
    const double f = minutes > programmed * (1.0 + 1e-9) ? word_length(cur_, v) / minutes : feed_mm_min * feed_to_file_;
    emit_per_minute(f);
  }
  cur_ = v;
  cart_q_ = q;
  cart_tip_ = tip;
  cart_axis_ = axis;
}

}  // namespace cscam::post::detail
