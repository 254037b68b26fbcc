// The motion sequencer (sequencer.hpp): the modes its blocks are written in: tool-tip control on and off around
// tilted work planes, the planes themselves (3+2), rotary clamps, and the blend mode of the feed blocks (exact stop
// around retracts and turns, narrower corner blends where the control's would leave the tolerances).
#include <fmt/format.h>

#include <cctype>
#include <cmath>
#include <string>

#include "blend.hpp"
#include "cscam/core/error.hpp"
#include "cscam/core/rotations.hpp"
#include "sequencer.hpp"

namespace cscam::post::detail {

void Sequencer::tool_tip_control_on(int cl_line) {
  if (tool_h_ == 0 && !warned_h0_) {
    warned_h0_ = true;
    sum_.warnings.push_back(
        fmt::format("{}: tool-tip control with length offset register H0: H0 cancels the tool length on "
                    "most controls",
                    SourceLoc{prog_.file, cl_line, 0}.str()));
  }
  fmt_->tcp_on(buf_, tool_h_);
  tcp_on_ = true;
}

// --- Rotary clamps around indexed (3+2) stretches -----------------------------------------------------

/// The rotaries with clamp codes that the stretch of feed moves after the rapid at i keeps where the rapid put them.
unsigned Sequencer::indexed_from(const std::vector<kin::Axes>& axes, size_t i) const {
  unsigned still = 0;
  for (int r : kin_.rotary_pair())
    if (!clamp_codes_[static_cast<size_t>(r)][0].empty()) still |= 1u << r;
  if (still == 0) return 0;
  size_t j = i + 1;
  for (; j < axes.size() && prog_.moves[j].kind == cl::MotionKind::Feed && still != 0; ++j)
    for (int r : kin_.rotary_pair())
      if (rounded(r, axes[j][r]) != rounded(r, axes[i][r])) still &= ~(1u << r);
  return j > i + 1 ? still : 0u;
}

/// Whether the stretch of feed moves after the rapid at i keeps every rotary where the rapid put it (3+2).
bool Sequencer::fixed_from(const std::vector<kin::Axes>& axes, size_t i) const {
  const auto rp = kin_.rotary_pair();
  size_t j = i + 1;
  for (; j < axes.size() && prog_.moves[j].kind == cl::MotionKind::Feed; ++j)
    for (int r : rp)
      if (rounded(r, axes[j][r]) != rounded(r, axes[i][r])) return false;
  return j > i + 1;
}

/// Every rotary at 0 as printed: machine and part frames agree, a plane would add nothing.
bool Sequencer::at_rotary_zero(const kin::Axes& q) const {
  for (int r : kin_.rotary_pair())
    if (rounded(r, q[r]) != 0) return false;
  return true;
}

// --- Tool-tip control around tilted work planes --------------------------------------------------------
// A control refuses a tilted plane under TCP (G68.2 in G43.4 mode, CYCLE800 under TRAORI): a TCP program
// cancels TCP for each 3+2 stretch that gets a plane and writes that stretch exactly as the non-TCP program
// does (safe Z, turn, clamp, plane, cut in plane words, plane off), then switches TCP on again.

/// Whether the cut after the rapids from move i on (or after move i itself, the first) is a 3+2 stretch that gets
/// a plane; nothing when no cut follows (the last rapids keep the mode they find).
std::optional<bool> Sequencer::plane_ahead(const std::vector<kin::Axes>& axes, size_t i) const {
  const auto& moves = prog_.moves;
  size_t j = i;
  while (moves[j].kind == cl::MotionKind::Rapid && j + 1 < moves.size() && moves[j + 1].kind == cl::MotionKind::Rapid)
    ++j;
  if (j + 1 >= moves.size()) return std::nullopt;
  return fixed_from(axes, j) && !at_rotary_zero(axes[j]);
}

/// Into a 3+2 stretch: out along the tool axis under TCP (as before any rotary change of the TCP program), TCP
/// off, the plain length offset, and machine words from here on.
void Sequencer::switch_to_machine(int cl_line) {
  if (have_state_) axis_retract(SourceLoc{prog_.file, cl_line, 0});
  if (tcp_on_) {
    fmt_->tcp_off(buf_);
    tcp_on_ = false;
  }
  fmt_->length_on(buf_, tool_h_);
  cart_ = false;
  vectors_ = false;
  axis_retract_ = false;            // planes need a Z axis: machine Z retracts
  if (have_state_) cur_ = cart_q_;  // the machine axes where TCP left the tool
  forget_words();
  at_cut_ = false;
}

/// Out of a 3+2 stretch into a simultaneous one: out along the axis, the plane off, up to the safe Z, the clamps
/// released, TCP on again; the TCP rapid that follows positions the tool.
void Sequencer::switch_to_tcp(int cl_line) {
  exit_along_axis();
  work_plane_off();
  if (have_state_) emit_safe_z();
  unclamp_rotaries();
  restore_tcp_state();
  tool_tip_control_on(cl_line);
}

/// The TCP program's settings again, with its Cartesian state at the machine axes the tool is at.
void Sequencer::restore_tcp_state() {
  cart_ = true;
  vectors_ = tcp_vectors_;
  axis_retract_ = tcp_axis_retract_;
  if (have_state_) {
    const kin::Posed here = kin_.forward(cur_);
    cart_q_ = ctrl_q_ = cur_;
    cart_tip_ = here.tip_mm;
    cart_axis_ = here.axis;
    cur_ = cartesian_words(here.tip_mm, here.axis, cur_);
  }
  forget_words();
}

/// The words change meaning (tip words <-> machine words): every word and the feed are written again.
void Sequencer::forget_words() {
  have_word_.fill(false);
  last_feed_ = -1.0;
}

// --- Tilted work planes (3+2) ------------------------------------------------------------------------

/// Switches the work plane of the rotaries in q on: its Z is the tool axis there (origin: the part's).
void Sequencer::work_plane_on(const kin::Axes& q) {
  if (plane_active_) return;
  plane_R_ = fmt_->plane_on(buf_, rot::plane_for_tool_axis(kin_.forward(q).axis));
  plane_active_ = true;
  plane_words_ = fmt_->plane_form() == Formatter::PlaneForm::Rotated;
  plane_rot_ = {rounded(kin_.rotary_pair()[0], q[kin_.rotary_pair()[0]]),
                rounded(kin_.rotary_pair()[1], q[kin_.rotary_pair()[1]])};
  for (int s : xyz_) have_word_[static_cast<size_t>(s)] = false;  // the words now mean plane coordinates
  ++sum_.work_planes;
}

void Sequencer::work_plane_off() {
  if (!plane_active_) return;
  fmt_->plane_off(buf_);
  plane_active_ = false;
  for (int s : xyz_) have_word_[static_cast<size_t>(s)] = false;  // machine coordinates again: all written
}

/// add_words in a work plane: the tip of q in the plane's X Y Z (all three whenever a linear word is asked
/// for: one machine axis moves the tip along a tilted direction); the rotaries must not turn.
bool Sequencer::add_plane_words(const kin::Axes& q, std::initializer_list<int> which, bool force) {
  bool linear = false;
  for (int i : which) {
    if (!m_.axes[static_cast<size_t>(i)].rotary()) {
      linear = true;
      continue;
    }
    const auto rp = kin_.rotary_pair();
    CSCAM_CHECK(rounded(i, q[i]) == plane_rot_[i == rp[0] ? 0 : 1], "a rotary turns inside a tilted work plane");
  }
  if (!linear) return false;
  const Vec3 p = plane_R_.transpose() * kin_.forward(q).tip_mm;
  bool any = false;
  for (int k = 0; k < 3; ++k) {
    const auto u = static_cast<size_t>(xyz_[static_cast<size_t>(k)]);
    const long long r = round_half_away(p[k] * to_file_[u] * scale_[u]);
    if (!force && have_word_[u] && r == last_[u]) continue;
    blk_.words.push_back({static_cast<int>(u), r, decimals_[u], false});
    last_[u] = r;
    written_[u] = p[k];
    have_word_[u] = true;
    any = true;
  }
  return any;
}

void Sequencer::clamp_rotaries(unsigned which) {
  for (int r : kin_.rotary_pair()) {
    const auto& c = clamp_codes_[static_cast<size_t>(r)];
    if (((which >> r) & 1u) && !c[0].empty() && !clamped_[static_cast<size_t>(r)]) {
      fmt_->clamp(buf_, c[0]);
      clamped_[static_cast<size_t>(r)] = true;
    }
  }
}

void Sequencer::unclamp_rotaries() {
  for (int r : kin_.rotary_pair()) {
    if (!clamped_[static_cast<size_t>(r)]) continue;
    fmt_->clamp(buf_, clamp_codes_[static_cast<size_t>(r)][1]);
    clamped_[static_cast<size_t>(r)] = false;
  }
}

// --- Blend modes: exact stop around retracts and turns, corners bounded to the tolerances ------------------

/// Makes the control stop exactly at the end of the last feed block written (the cut before a retract, whose
/// blend mode was fixed when the control queued it) and at every block's after it, until resume_blend_.
void Sequencer::stop_exactly_at_last_feed() {
  if (exact_words_.empty() || exact_ || !last_blk_.tracked()) return;
  exact_ = true;
  resume_blend_ = false;
  set_mode(last_blk_, exact_words_);
}

/// Gives a tracked feed block the blend mode `mode` (its words, when the mode in force before it differs). The
/// block after the previous one is rewritten too: the mode before it changed. One word of the group per block: a
/// block that asked for another mode is rewritten, never given a second word.
void Sequencer::set_mode(FeedBlock& b, const std::string& mode) {
  CSCAM_CHECK(b.tracked() && (&b == &last_blk_ || &b == &prev_blk_), "set_mode: a tracked feed block");
  b.mode = mode;
  rewrite_words(b, b.mode == b.before ? std::string() : b.mode);
  if (&b == &prev_blk_ && last_blk_.tracked()) {
    last_blk_.before = mode;
    rewrite_words(last_blk_, last_blk_.mode == last_blk_.before ? std::string() : last_blk_.mode);
  } else if (&b == &last_blk_) {
    mode_ = mode;
  }
}

/// Replaces the words inserted at the start of a tracked block, and moves the offsets after them.
void Sequencer::rewrite_words(FeedBlock& b, const std::string& words) {
  if (words == b.words) return;
  const std::size_t p = words_at(b.at);
  const std::string old = b.words.empty() ? std::string() : b.words + " ";
  const std::string now = words.empty() ? std::string() : words + " ";
  CSCAM_CHECK(buf_.compare(p, old.size(), old) == 0, "a tracked block starts with the words inserted there");
  buf_.replace(p, old.size(), now);
  auto move = [&](std::size_t& at) {
    if (at != std::string::npos && at > p) at = at + now.size() - old.size();
  };
  move(b.end);
  if (&b == &prev_blk_) {
    move(last_blk_.at);
    move(last_blk_.end);
  }
  if (scanned_ > p) scanned_ = scanned_ + now.size() - old.size();  // the words hold no newline
  b.words = words;
}

/// The tool at q, remembered for the last few q: neighbouring corners share two of their three points.
kin::Posed Sequencer::pose_at(const kin::Axes& q) {
  for (const auto& [at, pose] : fk_memo_)
    if (at == q) return pose;
  auto& slot = fk_memo_[fk_memo_next_];
  fk_memo_next_ = (fk_memo_next_ + 1) % fk_memo_.size();
  slot = {q, kin_.forward(q)};
  return slot.second;
}

/// After the feed block q1 -> q2 that follows the feed block q0 -> q1 (both still in buf_): where the control
/// blends their corner as parabolic_corner() models, the whole blend must keep the tip within the tolerance of the
/// path, pass the corner's point within it, and keep the tool axis within the axis tolerance of the blocks' axes
/// (CornerBlendCheck). If it would not, the first block gets a smaller blend tolerance (the reach shrinks with P
/// where the turn lets P bound it) or exact path, and the second the post's own again.
void Sequencer::bound_corner_blend(const kin::Axes& q0, const kin::Axes& q1, const kin::Axes& q2) {
  const double p = fmt_->tolerance_in_program_units();
  const auto c = parabolic_corner(q0, q1, q2, control_axes_, p);
  if (!c) return;
  const kin::Posed A = pose_at(q0), B = pose_at(q1), C = pose_at(q2);
  const CornerBlendCheck check(kin_, *c, q1, A, B, C, tol_mm_, tol_axis_rad_);
  const double worst = check.excess(c->reach);
  if (worst <= 1.0 + 1e-9) return;
  std::string words;
  if (std::isfinite(c->reach_per_p)) {
    // The deviation grows with the reach about linearly: aim at 90 % of the tolerance, then check.
    const double step = fmt_->blend_tolerance_resolution();
    double p_new = std::floor(0.9 * c->reach / worst / c->reach_per_p / step) * step;
    while (p_new >= step && check.excess(p_new * c->reach_per_p) > 1.0) p_new = std::floor(0.5 * p_new / step) * step;
    if (p_new >= step) words = fmt_->blend_within_words(p_new);
  }
  if (words.empty()) {
    words = exact_words_;
    if (words.empty()) return;
    ++sum_.exact_corners;
  } else {
    ++sum_.narrowed_corners;
  }
  set_mode(prev_blk_, words);
  set_mode(last_blk_, fmt_->blend_words());
}

/// Where the words of the block that begins at buf_[at] start (after its N number).
std::size_t Sequencer::words_at(std::size_t at) const {
  CSCAM_CHECK(at <= buf_.size(), "words_at: the block is still in the buffer");
  std::size_t p = at;
  if (p < buf_.size() && buf_[p] == 'N') {
    ++p;
    while (p < buf_.size() && std::isdigit(static_cast<unsigned char>(buf_[p])) != 0) ++p;
    if (p < buf_.size() && buf_[p] == ' ') ++p;
  }
  return p;
}

}  // namespace cscam::post::detail
