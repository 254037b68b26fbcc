#pragma once
/// @file
/// The XMINI parallel kinematic machine (docs/xmini.md, model in xmini.hpp) behind the generic
/// kin::Kinematics interface, so that the conventional post, the C-space planner and verification
/// drive it like any serial machine.
///
/// Axis order (q1, q2, q3, c, a) = kin::Axes: leg strokes in mm, wrist commands in radians. The part
/// frame of the interface is the machine frame W. rotary_pair() = {3 (c, primary), 4 (a, secondary)}.
///
/// What differs from a serial machine:
/// - The tool axis depends on the tip position (parasitic platform tilt): tool_axis_at() needs the tip.
/// - The passive joints alpha and beta have limits that no axis value shows. AxisInfo limits cover the
///   strokes, C and A (so Kinematics::check_limits sees them); alpha and beta are checked where the
///   platform state is known: inverse_*() put them into Solution::violation, solve_for_rotaries() and
///   tool_axis_at() fail when the platform would leave them, and passive_violation(q) checks any q.
#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "cscam/kin/kinematics.hpp"
#include "cscam/kin/xmini.hpp"

namespace cscam::kin {

/// Axis names of the XMINI, in the order of kin::Axes.
inline constexpr std::array<const char*, 5> kXminiAxisNames{"q1", "q2", "q3", "c", "a"};

/// The XMINI as a Kinematics. Immutable and thread-safe for const use: forward kinematics keeps its
/// Newton warm start in a thread_local workspace (one per thread and model).
class XminiKinematics final : public Kinematics {
 public:
  /// Axis descriptions for the given limits: q1..q3 linear (mm), c and a rotary (rad), not cyclic.
  /// `max_feed` per axis in mm/min or rad/min (0 = unknown).
  static std::vector<AxisInfo> axes_for(const XminiLimits& limits, const std::array<double, 5>& max_feed = {});

  /// The model with axes_for(model.limits()).
  explicit XminiKinematics(XminiModel model);
  /// The model with explicit axis descriptions (names q1 q2 q3 c a in this order, types linear x3 then
  /// rotary x2; their limits should be the model's). Throws std::invalid_argument otherwise.
  XminiKinematics(XminiModel model, std::vector<AxisInfo> axes);

  [[nodiscard]] const std::vector<AxisInfo>& axes() const override { return axes_; }
  [[nodiscard]] std::array<int, 2> rotary_pair() const override { return {3, 4}; }
  /// No Z axis (legs): retracts go along the tool axis; under TCP the rotary words are a virtual wrist.
  [[nodiscard]] Traits traits() const override {
    Traits t;
    t.tcp_rotary_words = Traits::TcpRotaryWords::VirtualWrist;
    t.parallel = true;
    t.forward_depends_on_call_order = true;
    return t;
  }
  /// FK. If the legs admit no assembly (Newton fails), the tip is +infinity in every coordinate so that
  /// every distance test downstream fails loudly instead of passing on NaN.
  [[nodiscard]] Posed forward(const Axes& q) const override;
  /// Every wrist branch (branch 0: a + a0 >= 0, branch 1: the other) with every C winding inside the
  /// C limits. Only exact solutions are returned; violated limits (strokes, C, A, alpha, beta) are
  /// flagged in Solution::violation (the first one). `hint` supplies c at the singular wrist.
  void inverse_all(const Posed& pose, const Axes* hint, std::vector<Solution>& out) const override;
  /// The two wrist branches with principal c in (-pi, pi].
  void inverse_branches(const Posed& pose, const Axes* hint, std::vector<Solution>& out) const override;
  /// With c = q[3] and a = q[4] held, the strokes q1..q3 that put the tip at pose.tip_mm (Newton on
  /// the platform state: 3 tip equations + the leg-2 constraint). The tool axis then follows from the
  /// platform attitude and is in general NOT pose.axis. Returns false when Newton fails or the platform
  /// would leave the passive-joint limits (alpha, beta); the strokes are not limit-checked here.
  bool solve_for_rotaries(const Posed& pose, Axes& q) const override;
  /// The tool axis (W) that wrist commands (c = primary, a = secondary) give with the tip at tip_mm.
  bool tool_axis_at(double primary, double secondary, const Eigen::Vector3d& tip_mm,
                    Eigen::Vector3d& axis) const override;

  /// The first broken passive-joint limit (alpha, beta) at joints q, or empty. Runs FK.
  [[nodiscard]] std::string passive_violation(const Axes& q) const override;
  /// Every limit at q (strokes, C, A and the passive joints), the first broken one, or empty.
  [[nodiscard]] std::string all_violations(const Axes& q) const;

  [[nodiscard]] const XminiModel& model() const { return model_; }

 private:
  /// Newton for the platform state x that puts the tip at tip_W_mm with wrist (c, a). x is the start on
  /// entry and the solution on exit.
  bool solve_platform_for_tip(double c_rad, double a_rad, const Eigen::Vector3d& tip_W_mm, XminiState<double>& x) const;
  /// A start for solve_platform_for_tip: the untilted platform under the wrist, put into the legs' plane.
  [[nodiscard]] XminiState<double> platform_start(double c_rad, double a_rad, const Eigen::Vector3d& tip_W_mm) const;
  void to_solutions(const Posed& pose, const std::vector<XminiIkSolution>& in, bool principal_only,
                    std::vector<Solution>& out) const;
  /// Where a wrist branch has no exact solution (with psi != 0 directions within |psi| of the C axis are
  /// unreachable; with gx, gy != 0 the tip swings with C about the pole): the (c, a) nearest `q`'s whose tool axis
  /// is closest to pose.axis with the tip exactly at pose.tip_mm (Levenberg-Marquardt on the axis error, the platform
  /// solved for the tip at every step). Sets q (legs too), the angle left and the broken limit; false if none.
  bool nearest_reachable(const Posed& pose, Axes& q, double& axis_error_rad, std::string& violation) const;

  XminiModel model_;
  std::vector<AxisInfo> axes_;
  std::uint64_t id_;  ///< keys the thread_local FK warm start (a workspace must not cross models)
};

}  // namespace cscam::kin
