#pragma once
/// @file
/// Types shared by every kinematic model: axis descriptions, poses, IK solutions.
#include <Eigen/Core>
#include <string>
#include <vector>

namespace cscam::kin {

/// Five machine axes. Linear axes in mm, rotary axes in radians (degrees only in files and G-code).
using Axes = Eigen::Matrix<double, 5, 1>;

enum class AxisType { Linear, Rotary };

/// What the planner and the post need to know about one axis.
struct AxisInfo {
  std::string name;  ///< lower case, as in the machine file: x, y, z, a, b, c, q1, ...
  AxisType type = AxisType::Linear;
  double min = 0.0;  ///< mm or rad
  double max = 0.0;
  bool cyclic = false;     ///< a rotary that may turn without end (limits then only bound the output)
  double max_feed = 0.0;   ///< mm/min or rad/min; 0 = unknown
  double max_accel = 0.0;  ///< mm/s^2 or rad/s^2 (the control's, e.g. LinuxCNC's MAX_ACCELERATION); 0 = unknown
  [[nodiscard]] bool rotary() const { return type == AxisType::Rotary; }
};

/// A tool pose in the part frame: tip position and unit axis from tip toward the spindle.
template <typename T>
struct Pose {
  Eigen::Matrix<T, 3, 1> tip_mm;
  Eigen::Matrix<T, 3, 1> axis;
};
using Posed = Pose<double>;

/// One inverse-kinematics solution.
struct Solution {
  Axes axes = Axes::Zero();
  int branch = 0;         ///< which closed-form root (0/1; meaning is model specific)
  bool singular = false;  ///< the primary rotary was undetermined and taken from the hint
  /// Angle between the requested tool axis and the one these axes give: 0 for an exact solution; for a requested axis
  /// just outside the reachable orientations (within tol::kReachSlackRad) the nearest reachable one is returned and
  /// this says how far it is (the tip is exact either way).
  double axis_error_rad = 0.0;
  std::string violation;  ///< empty when every axis is inside its limits, else the first broken limit
  [[nodiscard]] bool exact() const { return axis_error_rad == 0.0; }
  [[nodiscard]] bool feasible() const { return violation.empty(); }
};

}  // namespace cscam::kin
