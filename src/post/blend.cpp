#include "blend.hpp"

#include <Eigen/Core>
#include <algorithm>
#include <cmath>

#include "cscam/core/segment.hpp"

namespace cscam::post {

namespace {

/// LinuxCNC applies P only where the leading directions turn by more than this (TP_MIN_ARC_ANGLE on each side).
constexpr double kMinTurnForTolerance = 2e-3;

/// A move's leading group: its displacement there (program units) and the whole move per unit of that length.
struct Leading {
  Eigen::Vector3d direction = Eigen::Vector3d::Zero();
  double length = 0.0;
  kin::Axes per_length = kin::Axes::Zero();
  double accel = 0.0;  ///< along the leading length: what the slowest axis allows
};

std::optional<Leading> leading(const kin::Axes& from, const kin::Axes& to, const ControlAxes& axes) {
  const auto& group = axes.group;
  const auto& to_program = axes.to_program;
  for (const AxisGroup g : {AxisGroup::Xyz, AxisGroup::Uvw, AxisGroup::Abc}) {
    Eigen::Vector3d d = Eigen::Vector3d::Zero();
    int k = 0;
    for (std::size_t i = 0; i < 5; ++i)
      if (group[i] == g && k < 3) d[k++] = (to[static_cast<int>(i)] - from[static_cast<int>(i)]) * to_program[i];
    const double length = d.norm();
    if (length <= 1e-12) continue;  // the control takes the next group when this one does not move
    Leading out;
    out.direction = d / length;
    out.length = length;
    out.per_length = (to - from) / length;
    double slowest = 0.0;  // max over axes of (axis units per leading unit) / axis acceleration
    for (std::size_t i = 0; i < 5; ++i)
      if (axes.accel[i] > 0)
        slowest = std::max(slowest, std::abs(out.per_length[static_cast<int>(i)]) * to_program[i] / axes.accel[i]);
    out.accel = slowest > 0 ? 1.0 / slowest : 0.0;
    return out;
  }
  return std::nullopt;
}

}  // namespace

std::optional<ParabolicCorner> parabolic_corner(const kin::Axes& q0, const kin::Axes& q1, const kin::Axes& q2,
                                                const ControlAxes& axes, double p) {
  const auto in = leading(q0, q1, axes);
  const auto out = leading(q1, q2, axes);
  if (!in || !out) return std::nullopt;
  ParabolicCorner c;
  // Each segment gives the blend at most half its length (its time to reach speed is half its duration).
  c.reach = 0.5 * std::min(in->length, out->length);
  const double turn = std::acos(std::clamp(in->direction.dot(out->direction), -1.0, 1.0));
  if (turn > kMinTurnForTolerance) {
    c.reach_per_p = 2.0 / std::sin(0.5 * turn);
    c.reach = std::min(c.reach, p * c.reach_per_p);
  }
  // The second segment accelerates at its own rate while the first stops at its own.
  c.out_per_reach = in->accel > 0 && out->accel > 0 ? out->accel / in->accel : 1.0;
  c.out_limit = out->length;
  c.in_per_length = in->per_length;
  c.out_per_length = out->per_length;
  return c;
}

namespace {

/// The largest f over [lo, hi] near a sampled maximum at `at`: a golden-section search (12 steps) in at +- width.
template <class F>
double refine_max(const F& f, double at, double width, double best) {
  constexpr double kGolden = 0.3819660112501051;
  double lo = std::max(0.0, at - width), hi = std::min(1.0, at + width);
  double x1 = lo + kGolden * (hi - lo), x2 = hi - kGolden * (hi - lo);
  double f1 = f(x1), f2 = f(x2);
  for (int it = 0; it < 12; ++it) {
    if (f1 > f2) {
      hi = x2, x2 = x1, f2 = f1;
      x1 = lo + kGolden * (hi - lo), f1 = f(x1);
    } else {
      lo = x1, x1 = x2, f1 = f2;
      x2 = hi - kGolden * (hi - lo), f2 = f(x2);
    }
  }
  return std::max({best, f1, f2});
}

}  // namespace

CornerBlendCheck::CornerBlendCheck(const kin::Kinematics& kin, const ParabolicCorner& corner, const kin::Axes& q1,
                                   const kin::Posed& A, const kin::Posed& B, const kin::Posed& C, double tol_mm,
                                   double tol_axis_rad)
    : kin_(kin), c_(corner), q1_(q1), A_(A), B_(B), C_(C), tol_mm_(tol_mm), tol_axis_rad_(tol_axis_rad) {}

CornerBlendCheck::Sample CornerBlendCheck::sample(double reach, double s, Ends& ends) const {
  const double ratio = c_.out_per_reach;
  const kin::Posed m = kin_.forward(c_.at(q1_, reach, s, ratio));
  Sample out;
  const double tip = std::min(point_segment_distance(m.tip_mm, A_.tip_mm, B_.tip_mm),
                              point_segment_distance(m.tip_mm, B_.tip_mm, C_.tip_mm));
  // The axis against the corner's bounds its distance from the axes of both blocks (B is on both); only where that
  // is not well inside, the blend's two ends are needed (chords of unit vectors: about the angle at these sizes).
  double axis = std::acos(std::clamp(m.axis.dot(B_.axis), -1.0, 1.0));
  if (axis > 0.5 * tol_axis_rad_) {
    if (!ends.known) {
      ends.from = kin_.forward(c_.at(q1_, reach, 0.0, ratio)).axis;
      ends.to = kin_.forward(c_.at(q1_, reach, 1.0, ratio)).axis;
      ends.known = true;
    }
    axis =
        std::min(point_segment_distance(m.axis, ends.from, B_.axis), point_segment_distance(m.axis, B_.axis, ends.to));
  }
  out.deviation = std::max(tip / tol_mm_, axis / tol_axis_rad_);
  out.miss = (m.tip_mm - B_.tip_mm).norm() / tol_mm_;
  return out;
}

double CornerBlendCheck::excess(double reach) const {
  Ends ends;
  const Sample mid = sample(reach, 0.5, ends);
  double worst = mid.deviation, at = 0.5, closest = mid.miss, closest_at = 0.5;
  if (std::max(worst, closest) <= 0.5) return std::max(worst, closest);
  for (int k = 0; k <= 16; ++k) {
    if (k == 8) continue;
    const Sample x = sample(reach, k / 16.0, ends);
    if (x.deviation > worst) worst = x.deviation, at = k / 16.0;
    if (x.miss < closest) closest = x.miss, closest_at = k / 16.0;
  }
  worst = refine_max([&](double s) { return sample(reach, s, ends).deviation; }, at, 1.0 / 16.0, worst);
  closest = -refine_max([&](double s) { return -sample(reach, s, ends).miss; }, closest_at, 1.0 / 16.0, -closest);
  return std::max(worst, closest);
}

}  // namespace cscam::post
