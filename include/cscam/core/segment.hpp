#pragma once
/// @file
/// Distance from a point to a straight segment: the measure of the linearisation, the gate, the blend check and
/// the servo trace, one definition for all of them.
#include <Eigen/Core>
#include <algorithm>

namespace cscam {

/// Distance from p to the segment a + t ab, t in [0, 1], with L2 = |ab|^2 given (once per segment in loops);
/// `t` (if given) receives the parameter of the nearest point. A segment of length 0 is the point a.
inline double point_segment_distance(const Eigen::Vector3d& p, const Eigen::Vector3d& a, const Eigen::Vector3d& ab,
                                     double L2, double* t = nullptr) {
  const double s = L2 > 0 ? std::clamp((p - a).dot(ab) / L2, 0.0, 1.0) : 0.0;
  if (t) *t = s;
  return (a + s * ab - p).norm();
}

/// Distance from p to the segment a b.
inline double point_segment_distance(const Eigen::Vector3d& p, const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  const Eigen::Vector3d ab = b - a;
  return point_segment_distance(p, a, ab, ab.squaredNorm());
}

}  // namespace cscam
