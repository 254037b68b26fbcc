#pragma once
// A control's corner blending, seen from the post: how far a control that blends two straight blocks within a
// tolerance P moves the joints off the corner when the blocks move rotaries as well (LinuxCNC's parabolic blend;
// docs/linuxcnc.md). Pure maths on joint values: no G-code.
#include <Eigen/Core>
#include <array>
#include <limits>
#include <optional>

#include "cscam/kin/kinematics.hpp"

namespace cscam::post {

/// LinuxCNC blends two straight segments that move A B C (or U V W) parabolically: the first decelerates to a stop
/// over its last `reach` while the second accelerates from its start, both measured along the segment's leading group
/// of axes (X Y Z, else U V W, else A B C, in program units). P bounds that reach only through the angle between the
/// leading directions, reach <= 2 P / sin(turn / 2), and never bounds the other axes, which ride along. Each segment
/// accelerates at what its slowest axis allows: a segment that turns a rotary fast per mm is slow to stop, and the
/// next one, if quicker, runs far into its own line meanwhile (measured: 0.12 mm while C still had 0.14 deg to go).
struct ParabolicCorner {
  double reach = 0.0;  ///< the first segment's part of the blend at the given P, in its leading group's units
  /// Reach per unit of P where P bounds it; infinity where the turn is too small for the control to apply P
  /// (LinuxCNC: under 2e-3 rad), and then only half the shorter segment bounds the reach.
  double reach_per_p = std::numeric_limits<double>::infinity();
  double out_per_reach =
      1.0;                 ///< how far the second segment runs meanwhile, per unit of reach (its acceleration ratio)
  double out_limit = 0.0;  ///< and at most: the second segment's length
  kin::Axes in_per_length = kin::Axes::Zero();   ///< the first move per unit of its leading length (model units)
  kin::Axes out_per_length = kin::Axes::Zero();  ///< the second move per unit of its leading length

  /// The joints at fraction s in [0, 1] of the blend of reach `reach` around the corner q1: the first move still
  /// reach (1 - s)^2 short of it, the second past it by `ratio` x reach x s^2, at most out_limit (each at constant
  /// acceleration).
  [[nodiscard]] kin::Axes at(const kin::Axes& q1, double reach, double s, double ratio) const {
    const double out = std::min(ratio * reach, out_limit);
    return q1 + (out * s * s) * out_per_length - (reach * (1.0 - s) * (1.0 - s)) * in_per_length;
  }
};

/// What the blend of one corner does to the tool, in tolerances (<= 1: within): the tip's distance from the path
/// A B C (the tool tip at q0, q1, q2), how far from B it passes, and the tool axis's distance from the axes the
/// unblended moves show between the two points the blend joins.
class CornerBlendCheck {
 public:
  /// A, B, C: the tool at q0, q1 (the corner) and q2.
  CornerBlendCheck(const kin::Kinematics& kin, const ParabolicCorner& corner, const kin::Axes& q1, const kin::Posed& A,
                   const kin::Posed& B, const kin::Posed& C, double tol_mm, double tol_axis_rad);
  /// The largest deviation over the blend of reach `reach`: its middle and, unless that is well inside, sixteenths
  /// of it and a golden-section search around the worst (the nearest segment changes inside the blend: the
  /// deviation has a sharp peak, seldom in the middle).
  [[nodiscard]] double excess(double reach) const;

 private:
  struct Sample {
    double deviation = 0.0;  ///< from the path and the axes, in tolerances
    double miss = 0.0;       ///< distance from the corner's point B, in tolerances
  };
  struct Ends {  ///< the tool axis where the blend leaves the first block and joins the second (once per reach)
    bool known = false;
    Eigen::Vector3d from, to;
  };
  [[nodiscard]] Sample sample(double reach, double s, Ends& ends) const;
  const kin::Kinematics& kin_;
  const ParabolicCorner& c_;
  kin::Axes q1_;
  const kin::Posed &A_, &B_, &C_;
  double tol_mm_, tol_axis_rad_;
};

/// Axis groups as the control's planner sees them.
enum class AxisGroup { Xyz = 0, Uvw = 1, Abc = 2 };

/// How the control sees the axis slots: each one's group, its program units per model unit (mm or inch, deg per rad)
/// and its acceleration in program units per s^2 (only ratios matter; LinuxCNC's MAX_ACCELERATION; 0: no limit).
/// A segment accelerates at its leading length / max over axes of (axis travel / axis acceleration), as LinuxCNC's
/// canon computes it.
struct ControlAxes {
  std::array<AxisGroup, 5> group{};
  std::array<double, 5> to_program{};
  std::array<double, 5> accel{};
};

/// The corner at q1 between the straight joint moves q0 -> q1 and q1 -> q2, blended at tolerance p (program units).
/// nullopt when a move does not move.
std::optional<ParabolicCorner> parabolic_corner(const kin::Axes& q0, const kin::Axes& q1, const kin::Axes& q2,
                                                const ControlAxes& axes, double p);

}  // namespace cscam::post
