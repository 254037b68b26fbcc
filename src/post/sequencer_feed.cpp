// The motion sequencer (sequencer.hpp): feed moves: a CL arc as one G2/G3, straight and linearised feeds, the
// segments linearised in parallel ahead of the sequencer, and the blocks' timing (max_feed, G93 or G94).
#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <utility>
#include <vector>

#include "cscam/core/parallel.hpp"
#include "cscam/core/units.hpp"
#include "cscam/kin/track.hpp"
#include "linearize.hpp"
#include "sequencer.hpp"

namespace cscam::post::detail {

void Sequencer::feed(const cl::Move& m0, const kin::Axes& q0_in, const cl::Move& m1, const kin::Axes& q1) {
  cur_line_ = m1.line;
  std::optional<kin::Axes> q0 = q0_in;
  const double fr = m1.feed_mm_per_min > 0 ? m1.feed_mm_per_min : kFallbackFeedMmMin;
  const kin::Posed pose0{m0.tip_in_part_mm, m0.axis_in_part.normalized()};
  const kin::Posed pose1{m1.tip_in_part_mm, m1.axis_in_part.normalized()};
  const bool turned = !continues_branch(pose0, q0_in, pose1, q1);
  if (turned) q0 = reconfigure(pose0, q0_in, pose1, q1, m0, m1, fr);
  if (q0) {  // else reconfigure reached m1 itself
    try {
      feed_linear(m0, *q0, m1, q1);
    } catch (const BranchChangeError&) {
      // Beside (not through) a singular orientation q1's branch may swing the primary half a turn within a piece of
      // the segment too short for the linearizer's halving, which crosses there holding the primary and so ends on
      // the other wrist branch: the branch is followed with CL points inserted along the swing.
      if (follow_swing(m0, *q0, m1, q1)) {
        at_cut_ = true;
        cut_move_ = m1;
        if (cut_move_.feed_mm_per_min <= 0) cut_move_.feed_mm_per_min = kFallbackFeedMmMin;
        return;
      }
      // continues_branch takes a small rotary change as continuous unchecked, but beside a singular orientation even
      // a small one can end on another branch (A changing sign): turned as for any flip. (The linearizer refuses
      // before it writes a block.)
      if (turned) throw;
      q0 = reconfigure(pose0, q0_in, pose1, q1, m0, m1, fr);
      if (q0) feed_linear(m0, *q0, m1, q1);
    }
  }
  at_cut_ = true;
  cut_move_ = m1;
  if (cut_move_.feed_mm_per_min <= 0) cut_move_.feed_mm_per_min = kFallbackFeedMmMin;
}

/// When moves[i] is the first point of a CL arc that can be one circular block (rotaries fixed over the whole
/// arc, its machine-coordinate plane XY, ZX or YZ, no event inside), writes that block and returns the index
/// of the arc's end move; else returns 0 and writes nothing. In a tilted work plane whose words are its
/// coordinates (G68.2, CYCLE800) the arc is written in them when its normal is the plane's Z (G17 there, the
/// plane's own XY); under Haas G254 the words stay machine words and so do the rules.
std::size_t Sequencer::arc_end(const std::vector<kin::Axes>& axes, std::size_t i) {
  if (!arcs_ || i == 0) return 0;
  const bool in_plane = plane_active_ && plane_words_;
  const auto& moves = prog_.moves;
  const int a = moves[i].arc_index;
  if (a < 0 || moves[i - 1].arc_index == a || moves[i - 1].kind != cl::MotionKind::Feed) return 0;
  const cl::Arc& arc = prog_.arcs[static_cast<std::size_t>(a)];
  const std::size_t end = arc.end_move;
  if (end < i || end >= moves.size()) return 0;
  for (std::size_t k = i; k <= end; ++k)
    if (moves[k].arc_index != a || moves[k].kind != cl::MotionKind::Feed ||
        moves[k].feed_mm_per_min != moves[end].feed_mm_per_min || rotaries_differ(axes[k]))
      return 0;
  for (const cl::Event& e : prog_.events)
    if (e.before_move > i && e.before_move <= end) return 0;
  // The rotaries are fixed: the machine's linear axes follow the tip rigidly. Where do the centre and the
  // normal go?
  const kin::Axes& q0 = axes[i - 1];
  const Vec3 cl_axis = moves[i - 1].axis_in_part.normalized();
  const Vec3 lift = opt_.control_offset_mm * cl_axis;  // the controlled point (a ball centre) moves in parallel
  auto machine_xyz = [&](const Vec3& p, Vec3& out) {
    kin::Axes q = q0;
    if (!kin_.solve_for_rotaries(kin::Posed{p, cl_axis}, q)) return false;
    for (int k = 0; k < 3; ++k) out[k] = q[xyz_[static_cast<size_t>(k)]];
    return true;
  };
  // The X Y Z words of a tip p (part frame): the machine's linear axes, or in a plane its coordinates (the
  // frame of the printed angles, as add_plane_words writes them).
  auto word_xyz = [&](const Vec3& p, Vec3& out) {
    if (!in_plane) return machine_xyz(p, out);
    kin::Axes q = q0;
    if (!kin_.solve_for_rotaries(kin::Posed{p, cl_axis}, q)) return false;
    out = plane_R_.transpose() * kin_.forward(q).tip_mm;
    return true;
  };
  Vec3 c_m, cn_m;
  if (!word_xyz(arc.centre_in_part_mm + lift, c_m) ||
      !word_xyz(arc.centre_in_part_mm + lift + arc.normal_in_part, cn_m))
    return 0;
  const Vec3 n_m = cn_m - c_m;
  int w = -1;
  for (int k = 0; k < 3; ++k)
    if (std::abs(std::abs(n_m[k]) - 1.0) < 1e-9) w = k;
  if (w < 0 || std::abs(n_m.norm() - 1.0) > 1e-9) return 0;  // not a machine plane (or not a rigid map)
  if (in_plane && w != 2) return 0;                          // in a plane only its XY: other arcs are points
  // The machine's X Y Z per unit of each word (identity for machine words): the feed cap below.
  Eigen::Matrix3d word_to_machine = Eigen::Matrix3d::Identity();
  if (in_plane) {
    Vec3 at, step;
    if (!machine_xyz(arc.centre_in_part_mm + lift, at)) return 0;
    for (int j = 0; j < 3; ++j) {
      if (!machine_xyz(arc.centre_in_part_mm + lift + plane_R_.col(j), step)) return 0;
      word_to_machine.col(j) = step - at;
    }
  }
  const int plane = w == 2 ? 17 : (w == 1 ? 18 : 19);
  const int u = (w + 1) % 3, v = (w + 2) % 3;  // (X,Y) for G17, (Z,X) for G18, (Y,Z) for G19
  auto xyz_of = [&](const kin::Axes& q) {
    return in_plane ? Vec3(plane_R_.transpose() * kin_.forward(q).tip_mm) : Vec3(q[xyz_[0]], q[xyz_[1]], q[xyz_[2]]);
  };
  const Vec3 p0 = xyz_of(q0), p1 = xyz_of(axes[end]);
  const double r = arc.radius_mm;
  const double ccw_sign = n_m[w] > 0 ? 1.0 : -1.0;  // the CL's counter-clockwise, seen from +w
  const double sweep = ccw_sign * arc.sweep_rad;
  const double ang0 = std::atan2(p0[v] - c_m[v], p0[u] - c_m[u]);
  // Every CL point of the arc on the machine helix (else the map is not what we assumed: points).
  const double on_helix = 0.1 * tol_mm_;
  // In a plane its Z (from the printed angles) and the CL's normal differ by ~1e-7 rad: a helix' points project
  // some nm off, so the angle along the arc gets the slack of the distance check there.
  const double slack_rad = in_plane ? on_helix / r : 1e-9, t_slack = in_plane ? slack_rad / arc.sweep_rad : 1e-9;
  for (std::size_t k = i; k <= end; ++k) {
    const Vec3 p = xyz_of(axes[k]);
    const double rk = std::hypot(p[u] - c_m[u], p[v] - c_m[v]);
    double d = std::atan2(p[v] - c_m[v], p[u] - c_m[u]) - ang0;
    d = sweep > 0 ? std::fmod(d + 4 * kPi, 2 * kPi) : -std::fmod(-d + 4 * kPi, 2 * kPi);
    if (k == end && std::abs(d) < slack_rad) d = sweep;  // a full circle ends where it started
    const double t = d / sweep;
    if (std::abs(rk - r) > on_helix || t < -t_slack || t > 1 + t_slack ||
        std::abs(p[w] - (p0[w] + t * (p1[w] - p0[w]))) > on_helix)
      return 0;
  }
  // The centre relative to the printed start, as the control reads I J K; a short radius would be all rounding.
  const auto su = static_cast<size_t>(xyz_[static_cast<size_t>(u)]);
  if (r < 100.0 / scale_[su] || !have_word_[su]) return 0;
  BlockSpec::Arc words;
  words.clockwise = sweep < 0;
  words.plane = plane;
  words.decimals = decimals_[su];
  for (int k : {u, v}) {
    const auto s = static_cast<size_t>(xyz_[static_cast<size_t>(k)]);
    if (!have_word_[s]) return 0;
    words.ijk[static_cast<size_t>(k)] = round_half_away(c_m[k] * to_file_[s] * scale_[s]) - last_[s];
    words.write[static_cast<size_t>(k)] = true;
  }
  // Feed: the path's speed F; no machine axis exceeds max_feed (in the arc's plane each peaks at F r |sweep| / L,
  // times its share of the plane's two directions in a tilted plane).
  cur_line_ = arc.line;
  const double dw = p1[w] - p0[w];
  const double len = std::hypot(r * arc.sweep_rad, dw);
  double f_mm = moves[end].feed_mm_per_min > 0 ? moves[end].feed_mm_per_min : kFallbackFeedMmMin;
  const double programmed = f_mm;
  for (int k = 0; k < 3; ++k) {
    const double vmax = m_.axes[static_cast<size_t>(xyz_[static_cast<size_t>(k)])].max_feed;
    const double share = (r * arc.sweep_rad * std::hypot(word_to_machine(k, u), word_to_machine(k, v)) +
                          std::abs(dw * word_to_machine(k, w))) /
                         len;
    if (vmax > 0 && share > 0) f_mm = std::min(f_mm, vmax / share);
  }
  if (f_mm < programmed * (1.0 - 1e-9) && capped_blocks_++ == 0) first_capped_line_ = next_nc_line();
  start(BlockSpec::Motion::Linear);
  if (!add_words(axes[end], {0, 1, 2, 3, 4})) add_words(axes[end], {xyz_[static_cast<size_t>(u)]}, true);
  blk_.arc = words;
  set_mode94();
  const double f = f_mm * feed_to_file_;
  emit_per_minute(f);
  ++sum_.arc_blocks;
  cur_ = axes[end];
  at_cut_ = true;
  cut_move_ = moves[end];
  if (cut_move_.feed_mm_per_min <= 0) cut_move_.feed_mm_per_min = kFallbackFeedMmMin;
  return end;
}

/// The block time (minutes) for a move qa -> qb at the programmed feed, slowed so that no axis exceeds its
/// max_feed; counts the blocks slowed so.
double Sequencer::block_minutes(const kin::Axes& qa, const kin::Axes& qb, double programmed_minutes) {
  double minutes = programmed_minutes;
  for (int i = 0; i < 5; ++i) {
    const double vmax = m_.axes[static_cast<size_t>(i)].max_feed;
    if (vmax <= 0) continue;
    // The move as the control sees it is between the printed (rounded) words: a short block's rounding may
    // make it longer than the model's.
    const double f = to_file_[static_cast<size_t>(i)] * scale_[static_cast<size_t>(i)];
    const double printed = std::abs(static_cast<double>(round_half_away(qb[i] * f) - round_half_away(qa[i] * f))) / f;
    minutes = std::max(minutes, std::max(std::abs(qb[i] - qa[i]), printed) / vmax);
  }
  if (minutes > programmed_minutes * (1.0 + 1e-9) + 1e-12 && programmed_minutes > 0) {
    if (capped_blocks_++ == 0) first_capped_line_ = next_nc_line();
  }
  return std::max(minutes, 1e-6);
}

/// The length an RS274 control measures a G94 block by: the linear words' distance (file units), else the
/// rotary words' angle (deg).
double Sequencer::word_length(const kin::Axes& wa, const kin::Axes& wb) const {
  double lin2 = 0.0, rot2 = 0.0;
  for (int i = 0; i < 5; ++i) {  // between the printed (rounded) words, as the control measures it
    const double f = to_file_[static_cast<size_t>(i)] * scale_[static_cast<size_t>(i)];
    const double d =
        static_cast<double>(round_half_away(wb[i] * f) - round_half_away(wa[i] * f)) / scale_[static_cast<size_t>(i)];
    (m_.axes[static_cast<size_t>(i)].rotary() ? rot2 : lin2) += d * d;
  }
  return lin2 > 1e-18 ? std::sqrt(lin2) : std::sqrt(rot2);
}

/// The IK branch (Solution::branch) that q takes at pose, or -1 when no solution is q.
int Sequencer::branch_of(const kin::Posed& pose, const kin::Axes& q) const {
  std::vector<kin::Solution> sols;
  kin_.inverse_branches(pose, &q, sols);
  for (kin::Solution& s : sols) {
    kin_.nearest_winding(s.axes, q);
    if (rotary_jump(s.axes, q) < 1e-6) return s.branch;
  }
  return -1;
}

/// The branch from q0 (at m0) followed to q1 (at m1) where the linearizer refused the feed q0 -> q1. Beside (not
/// through) a singular orientation one IK branch swings the primary half a turn over a piece of the segment far shorter
/// than the rest; nearest-solution tracking and the linearizer's halving both cross there holding the primary, which
/// keeps the tool within the tolerance but ends on the other branch. Here the branch is followed by its index (the
/// closed-form root, which the swing keeps), with CL points inserted on the segment (tip along the chord, axis along
/// the great circle, as the linearizer interpolates) by halving wherever the rotaries change by more than
/// kSwingStepRad between two; each piece is then fed as any segment. False, with nothing written, when q0 and q1 are
/// on different branches, the branch leaves the limits, the swing is a jump at the finest halving (the singular
/// orientation itself), or the linearizer refuses a piece.
bool Sequencer::follow_swing(const cl::Move& m0, const kin::Axes& q0, const cl::Move& m1, const kin::Axes& q1) {
  constexpr double kSwingStepRad = 0.0872664626;  // 5 deg, as kin::track's steps
  constexpr int kMaxHalvings = 48;                // 2^-48 of the segment: the round-off of the tip
  const double off = opt_.control_offset_mm;
  const Vec3 u0 = m0.axis_in_part.normalized(), u1 = m1.axis_in_part.normalized();
  const Vec3 P0 = m0.tip_in_part_mm + off * u0, P1 = m1.tip_in_part_mm + off * u1;
  const Slerp axis(u0, u1);
  auto move_at = [&](double s) {
    cl::Move m = m1;
    m.axis_in_part = axis(s);
    m.tip_in_part_mm = P0 + s * (P1 - P0) - off * m.axis_in_part;
    return m;
  };
  auto pose_of = [](const cl::Move& m) { return kin::Posed{m.tip_in_part_mm, m.axis_in_part.normalized()}; };
  const int branch = branch_of(pose_of(m0), q0);
  if (branch < 0 || branch_of(pose_of(m1), q1) != branch) return false;
  // The solution on `branch` at m nearest `near` in winding, inside every limit.
  std::vector<kin::Solution> sols;
  auto on_branch = [&](const cl::Move& m, const kin::Axes& near, kin::Axes& q) {
    kin_.inverse_branches(pose_of(m), &near, sols);
    for (kin::Solution& s : sols) {
      if (s.branch != branch || s.singular) continue;
      kin_.nearest_winding(s.axes, near);
      q = s.axes;
      return kin_.check_limits(q).empty() && kin_.passive_violation(q).empty();
    }
    return false;
  };
  struct Point {
    double s;
    cl::Move m;
    kin::Axes q;
    int depth;
  };
  std::vector<Point> pts{{0.0, m0, q0, 0}};
  std::vector<Point> todo{{1.0, m1, q1, 0}};  // the points still to reach, the next one last
  while (!todo.empty()) {
    const Point& a = pts.back();
    Point& b = todo.back();
    if (rotary_jump(a.q, b.q) <= kSwingStepRad) {
      pts.push_back(b);
      todo.pop_back();
      continue;
    }
    const int depth = std::max(a.depth, b.depth) + 1;
    if (depth > kMaxHalvings) return false;
    const double sm = 0.5 * (a.s + b.s);
    Point mid{sm, move_at(sm), kin::Axes::Zero(), depth};
    if (!on_branch(mid.m, a.q, mid.q)) return false;
    todo.push_back(std::move(mid));
  }
  if (pts.size() <= 2) return false;  // nothing to insert: the linearizer's refusal stands
  // Every piece is split first, so that a refusal leaves nothing written.
  std::vector<Linearizer::Piece> scratch;
  Linearizer::Stats st;
  for (std::size_t k = 1; k < pts.size(); ++k) {
    try {
      lin_.split(pts[k - 1].m, pts[k - 1].q, pts[k].m, pts[k].q, prog_.file, scratch, st, nullptr);
    } catch (const InputError&) {
      return false;
    }
  }
  for (std::size_t k = 1; k < pts.size(); ++k) feed_linear(pts[k - 1].m, pts[k - 1].q, pts[k].m, pts[k].q);
  sum_.inserted_points += pts.size() - 2;
  sum_.warnings.push_back(fmt::format(
      "{}: the rotaries swing beside a singular orientation between CL lines {} and "
      "{} ({}): followed with {} CL points inserted",
      SourceLoc{prog_.file, m1.line, 0}.str(), m0.line, m1.line, rotary_change(kin_, q0, q1), pts.size() - 2));
  return true;
}

/// Feed from q0 (at m0) to q1 (at m1) on one branch, linearised so that the tip stays within the
/// tolerance of the straight CL segment and the axis within its tolerance of the interpolated CL axis.
void Sequencer::feed_linear(const cl::Move& m0, const kin::Axes& q0, const cl::Move& m1, const kin::Axes& q1) {
  const double feed_mm_min = m1.feed_mm_per_min > 0 ? m1.feed_mm_per_min : kFallbackFeedMmMin;
  Linearizer::Stats st;
  bool split = false;
  if (!rotaries_differ(q1) && traits_.parallel) {
    // A parallel machine's legs, moved linearly, move the tip straight only approximately (a 48 mm plunge on the
    // XMINI bows by 0.03 mm): one block where that is within the tolerance, else the linearizer's pieces.
    Linearizer::ClAxes ends;
    lin_.split(m0, q0, m1, q1, prog_.file, pieces_, st, cl_axes(m0, m1, ends));
    split = pieces_.size() > 1;
  }
  if (!rotaries_differ(q1) && !split) {
    // Pure linear motion: the machine moves straight, exactly the CL segment.
    start(BlockSpec::Motion::Linear);
    if (!add_words(q1, {0, 1, 2, 3, 4})) return;  // a repeated point: nothing to do
    set_mode94();
    const double len_mm = (q1 - q0).norm();  // linear axes only differ
    const double programmed = len_mm / feed_mm_min;
    const double minutes = block_minutes(q0, q1, programmed);
    const double f = (minutes > programmed * (1.0 + 1e-9) ? len_mm / minutes : feed_mm_min) * feed_to_file_;
    emit_per_minute(f);
    cur_ = q1;
    return;
  }
  if (!split && !split_ahead(m0, q0, m1, q1, st)) {
    Linearizer::ClAxes ends;
    lin_.split(m0, q0, m1, q1, prog_.file, pieces_, st, cl_axes(m0, m1, ends));
  }
  sum_.inserted_points += st.inserted_points;
  sum_.ik_calls += st.ik_calls;
  sum_.max_checked_tip_deviation_mm = std::max(sum_.max_checked_tip_deviation_mm, st.max_checked_tip_deviation_mm);
  for (auto& w : st.warnings) sum_.warnings.push_back(std::move(w));
  kin::Axes qa = q0;
  for (const auto& pc : pieces_) {
    emit_timed(qa, pc.q_end, pc.path_mm, feed_mm_min);
    qa = pc.q_end;
  }
  cur_ = q1;
}

/// The CL's own axes at the ends of the program's segment m0 -> m1 (both moves of prog_), in `ends`; null where
/// no cone reference was given or the moves are not consecutive moves of the program.
const Linearizer::ClAxes* Sequencer::cl_axes(const cl::Move& m0, const cl::Move& m1, Linearizer::ClAxes& ends) const {
  const cl::Program* ref = opt_.cone_reference;
  const auto& moves = prog_.moves;
  if (!ref || &m1 <= moves.data() || &m1 >= moves.data() + moves.size()) return nullptr;
  const auto i = static_cast<std::size_t>(&m1 - moves.data());
  if (&m0 != &moves[i - 1] || i >= ref->moves.size()) return nullptr;
  ends = {ref->moves[i - 1].axis_in_part, ref->moves[i].axis_in_part};
  return &ends;
}

/// The linearisation of a CL segment is a pure function of its ends and their axis values, and most of the
/// post's time: the segments ahead (moves[i - 1] -> moves[i] at axes[i - 1], axes[i]) are split in parallel, a
/// window at a time, and taken from there when the sequencer asks for exactly that segment. While the sequencer
/// works through one window the next is split in the background, so the two overlap. A segment whose split
/// throws, or one the sequencer asks for with other axis values (after a retract or flip), is split here as
/// before, so the output and the errors are those of the sequential post. Not on models whose FK/IK depend on
/// call order (the XMINI): there the numbers must come in order.
bool Sequencer::split_ahead(const cl::Move& m0, const kin::Axes& q0, const cl::Move& m1, const kin::Axes& q1,
                            Linearizer::Stats& st) {
  if (!axes_ || traits_.forward_depends_on_call_order) return false;
  const auto& moves = prog_.moves;
  if (&m1 <= moves.data() || &m1 >= moves.data() + moves.size()) return false;
  const std::size_t i = static_cast<std::size_t>(&m1 - moves.data());
  const auto& axes = *axes_;
  if (&m0 != &moves[i - 1] || i >= axes.size() || q0 != axes[i - 1] || q1 != axes[i]) return false;
  if (i < ahead_begin_ || i >= ahead_begin_ + ahead_.size()) {
    if (next_pending_) {
      next_job_.wait();
      next_pending_ = false;
    }
    if (i >= next_begin_ && i < next_begin_ + next_.size()) {
      ahead_.swap(next_);
      ahead_begin_ = next_begin_;
    } else {
      ahead_begin_ = i;
      split_window(ahead_, i, std::min(moves.size(), i + kAheadWindow));
    }
    // The window after this one, beside the sequencer.
    const std::size_t begin = ahead_begin_ + ahead_.size();
    if (begin < moves.size()) {
      next_begin_ = begin;
      next_pending_ = true;
      next_job_.run(
          [this, begin, end = std::min(moves.size(), begin + kAheadWindow)] { split_window(next_, begin, end); });
    } else {
      next_.clear();
    }
  }
  Ahead& a = ahead_[i - ahead_begin_];
  if (!a.ready) return false;
  a.ready = false;
  pieces_.swap(a.pieces);
  st = std::move(a.stats);
  return true;
}

/// Splits the segments ending at moves [begin, end) into `window` (in parallel; reads only the program, the axes
/// and lin_proto_, so it may run beside the sequencer).
void Sequencer::split_window(std::vector<Ahead>& window, std::size_t begin, std::size_t end) const {
  const auto& moves = prog_.moves;
  const auto& axes = *axes_;
  window.assign(end - begin, Ahead{});
  parallel_range(begin, end, 64, [&](const tbb::blocked_range<std::size_t>& r) {
    Linearizer lin = lin_proto_;  // its scratch stack is per task
    for (std::size_t k = r.begin(); k != r.end(); ++k) {
      if (moves[k].kind == cl::MotionKind::Rapid || moves[k - 1].kind == cl::MotionKind::Rapid) continue;
      Ahead& a = window[k - begin];
      try {
        Linearizer::ClAxes ends;
        lin.split(moves[k - 1], axes[k - 1], moves[k], axes[k], prog_.file, a.pieces, a.stats,
                  cl_axes(moves[k - 1], moves[k], ends));
        a.ready = true;
      } catch (...) {  // split again in order, where it throws for the sequential post too
        a = Ahead{};
      }
    }
  });
}

/// A feed block qa -> qb that covers tip_len_mm of the CL path: inverse time (G93) where the dialect has it,
/// else a per-minute F that gives the same block time by the control's own measure of the block length.
void Sequencer::emit_timed(const kin::Axes& qa, const kin::Axes& qb, double tip_len_mm, double feed_mm_min) {
  const double minutes = block_minutes(qa, qb, tip_len_mm / feed_mm_min);
  start(BlockSpec::Motion::Linear);
  if (!add_words(qb, {0, 1, 2, 3, 4})) return;
  const bool after_straight_feed = corner_open_;  // emit() closes it
  if (inverse_time_) {
    if (!mode93_) {
      blk_.feed_mode = BlockSpec::FeedMode::InverseTime;
      mode93_ = true;
    }
    last_feed_ = -1;
    emit(std::min(1.0 / minutes, 999999.0));
  } else {
    const double f = word_length(qa, qb) / minutes;
    last_feed_ = f;
    emit(f);
  }
  // The corner with the block before, when that one was a straight feed block ending here and the control
  // blends it (not in exact path around a retract).
  if (bound_corners_ && after_straight_feed && prev_blk_.tracked() && !exact_ && prev_blk_.mode != exact_words_ &&
      qa == corner_q1_ && !(plane_active_ && plane_words_))
    bound_corner_blend(corner_q0_, qa, qb);
  corner_q0_ = qa;
  corner_q1_ = qb;
  corner_open_ = true;
}

void Sequencer::emit_feed_to(const kin::Axes& from, const kin::Axes& q, double tip_len_mm, double feed_mm_min) {
  emit_timed(from, q, tip_len_mm, feed_mm_min);
  cur_ = q;
}

}  // namespace cscam::post::detail
