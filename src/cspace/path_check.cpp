// Collision checks along a path with a clearance certificate carried from pose to pose (the safety gate's samples).
#include <algorithm>
#include <cmath>

#include "cscam/core/error.hpp"
#include "cscam/cspace/cspace.hpp"

namespace cscam::cspace {

namespace {
constexpr double kMinPathProbeMm = 1.0 / 16.0;  // below it a probe certifies little more than its own pose
constexpr int kCooldownPoses = 16;              // exact checks before probing again after the smallest probe failed
// Largest margin probed for the bodies above the cutter and the head: in open space a larger one certifies longer
// stretches (the rotating frames move the head fast); near obstacles the probe halves. The cutter's own margin stays
// within the rapid check's cap (its tip cylinder covers no more).
constexpr double kBodyMarginCapMm = 20.0;
}  // namespace

PathCheck::PathCheck(std::shared_ptr<const Space> space) : space_(std::move(space)) {
  CSCAM_CHECK(space_ != nullptr, "PathCheck needs a space");
  const Space& sp = *space_;
  if (!sp.checks_collision()) return;
  usable_ = true;
  frame_link_[0] = -1;  // obstacles without a link stay in the part frame
  frames_ = 1;
  unsigned seen = 0;
  for (std::size_t i = 0; i < sp.scene_->obstacle_count(); ++i) {
    const int l = sp.scene_->obstacle_link(i);
    if (l < 0 || ((seen >> l) & 1u)) continue;
    seen |= 1u << l;
    if (frames_ >= kMaxFrames) {
      usable_ = false;
      break;
    }
    frame_link_[static_cast<std::size_t>(frames_++)] = l;
  }
  if (sp.head_)
    for (std::size_t i = 0; i < sp.head_->obstacle_count(); ++i) {
      const int l = sp.head_->obstacle_link(i);
      int g = 0;
      while (g < heads_ && head_link_[static_cast<std::size_t>(g)] != l) ++g;
      if (g == heads_) {
        if (heads_ >= kMaxHeads) {
          usable_ = false;
          break;
        }
        head_link_[static_cast<std::size_t>(heads_++)] = l;
      }
      if (g == heads_ - 1 && head_box_[static_cast<std::size_t>(g)].isEmpty())
        head_box_[static_cast<std::size_t>(g)] = sp.head_->obstacle_bounds(i);
      else
        head_box_[static_cast<std::size_t>(g)].extend(sp.head_->obstacle_bounds(i));
    }
  probe_mm_ = kBodyMarginCapMm;
  cutter_probe_mm_ = kRapidSweepMarginCapMm;
  translate_ = sp.kin_->traits().linear_axes_translate;
  const auto& axes = sp.kin_->axes();
  for (std::size_t i = 0; i < rotary_.size() && i < axes.size(); ++i) rotary_[i] = axes[i].rotary();
}

bool PathCheck::frames_at(const kin::Axes& q, const kin::Posed& pose, Frames& out) const {
  const Space& sp = *space_;
  Space::LinkPoses links;
  if (sp.links_ > 0 && !Space::place_links(*sp.kin_, q, sp.links_, links, sp.used_links_)) return false;
  std::array<Eigen::Isometry3d, kMaxHeads> heads;
  for (int g = 0; g < heads_; ++g) {
    const int l = head_link_[static_cast<std::size_t>(g)];
    if (l >= 0)
      heads[static_cast<std::size_t>(g)] = links[static_cast<std::size_t>(l)];
    else if (!sp.head_pose(q, nullptr, heads[static_cast<std::size_t>(g)]))
      return false;
  }
  for (int f = 0; f < frames_; ++f) {
    const auto F = static_cast<std::size_t>(f);
    const int l = frame_link_[F];
    const Eigen::Isometry3d to_frame =
        l < 0 ? Eigen::Isometry3d::Identity() : links[static_cast<std::size_t>(l)].inverse();
    out.tip[F] = to_frame * pose.tip_mm;
    out.axis[F] = to_frame.linear() * pose.axis;
    for (int g = 0; g < heads_; ++g)
      out.head[F * kMaxHeads + static_cast<std::size_t>(g)] = to_frame * heads[static_cast<std::size_t>(g)];
  }
  return true;
}

std::string PathCheck::operator()(const kin::Axes& q, SweepMode mode) {
  const Space& sp = *space_;
  if (!sp.checks_collision()) return {};
  if (valid_ && translate_ && mode == mode_) {
    // The rotaries where the certificate was taken: every body has only been translated, by at most the sum of the
    // linear axes' changes (a retract, an approach, a 3+2 cut), relative to the part and to every link.
    double moved_mm = 0.0;
    bool turned = false;
    for (int i = 0; i < 5; ++i) {
      if (rotary_[static_cast<std::size_t>(i)])
        turned = turned || q[i] != at_q_[i];
      else
        moved_mm += std::abs(q[i] - at_q_[i]);
    }
    if (!turned && moved_mm <= std::min(margin_mm_, cutter_margin_mm_)) {
      ++counters_.certified;
      ++counters_.translated;
      return {};
    }
  }
  const kin::Posed pose = sp.kin_->forward(q);
  Frames now;
  // (After a failed smallest probe, the poses of the cool-down are checked exactly: no frames needed.)
  const bool placed = usable_ && cooldown_ == 0 && frames_at(q, pose, now);
  if (placed && valid_ && mode == mode_) {
    // How far any point of the tool (symmetric about its axis: its tip's motion plus its axis' turn times the lever)
    // and of the head has moved since the certified pose, relative to every frame that carries obstacles.
    double d_cutter = 0.0, d_body = 0.0;
    for (int f = 0; f < frames_; ++f) {
      const auto F = static_cast<std::size_t>(f);
      const double tip = (now.tip[F] - at_.tip[F]).norm(), turn = (now.axis[F] - at_.axis[F]).norm();
      d_cutter = std::max(d_cutter, tip + sp.cutter_reach_mm_ * turn);
      d_body = std::max(d_body, tip + sp.reach_mm_ * turn);
      for (int g = 0; g < heads_; ++g) {
        // Any rigid motion: a point x of the meshes moves by at most the motion of their box's centre c plus
        // |R_a - R_b| |x - c|, and |R_a - R_b| = 2 sin(theta / 2) = sqrt(3 - trace(R_a^T R_b)).
        const Eigen::Isometry3d& a = now.head[F * kMaxHeads + static_cast<std::size_t>(g)];
        const Eigen::Isometry3d& b = at_.head[F * kMaxHeads + static_cast<std::size_t>(g)];
        const Eigen::AlignedBox3d& box = head_box_[static_cast<std::size_t>(g)];
        const Eigen::Vector3d c = box.center();
        const double turn = std::sqrt(std::max(0.0, 3.0 - (a.linear().transpose() * b.linear()).trace()));
        d_body = std::max(d_body, (a * c - b * c).norm() + 0.5 * box.diagonal().norm() * turn);
      }
    }
    if (d_cutter <= cutter_margin_mm_ && d_body <= margin_mm_) {
      ++counters_.certified;
      return {};
    }
  }
  valid_ = false;
  if (placed && cooldown_ == 0) {
    // Probe: free with these margins, this pose certifies the poses that follow within them.
    Space::LinkPoses links;
    geom::CheckOptions scratch;
    const Eigen::Isometry3d* head_placed = nullptr;
    const geom::CheckOptions& co = sp.with_links(q, links, scratch, &head_placed);
    // A cutting pose's check leaves out the cutting end up to the relief, and its probe lowers that by the cutter's
    // margin; a larger margin is probed with the whole tool (the rapid check, which covers the cutting check).
    const SweepMode probe_mode =
        mode == SweepMode::Cutting && cutter_probe_mm_ > sp.cutting_margin_cap_mm() ? SweepMode::Rapid : mode;
    bool free = sp.collision_inflated_placed(co, pose, probe_mm_, probe_mode, ws_, counters_, cutter_probe_mm_).empty();
    Eigen::Isometry3d head;
    if (free && sp.head_ && sp.head_pose(q, head_placed, head))
      free = geom::meshes_apart(*sp.head_, head, *sp.scene_, co, probe_mm_);
    if (free) {
      valid_ = true;
      mode_ = mode;
      margin_mm_ = probe_mm_;
      cutter_margin_mm_ = cutter_probe_mm_;
      at_ = now;
      at_q_ = q;
      probe_mm_ = std::min(kBodyMarginCapMm, 2.0 * probe_mm_);
      cutter_probe_mm_ = std::min(kRapidSweepMarginCapMm, 2.0 * cutter_probe_mm_);
      return {};
    }
    if (cutter_probe_mm_ <= kMinPathProbeMm) cooldown_ = kCooldownPoses;
    probe_mm_ = std::max(kMinPathProbeMm, 0.5 * probe_mm_);
    cutter_probe_mm_ = std::max(kMinPathProbeMm, 0.5 * cutter_probe_mm_);
  } else if (cooldown_ > 0) {
    --cooldown_;
  }
  return sp.collision_at_axes(q, ws_, counters_, mode);
}

}  // namespace cscam::cspace
