#pragma once
/// @file
/// A generic serial 5-axis machine: two kinematic chains from the machine base, one carrying the part
/// (table side) and one carrying the tool (head side). Covers table-table, head-table, head-head and
/// non-orthogonal (nutating) machines. Every joint is described at the home configuration (all axes 0)
/// in the base frame, as a product of exponentials: a linear joint by its direction, a rotary joint by
/// its direction and a point on its axis.
#include <Eigen/Geometry>
#include <array>
#include <vector>

#include "cscam/kin/kinematics.hpp"

namespace cscam::kin {

enum class Side { Table, Head };

/// Geometry of one joint, templated so that calibration can differentiate it.
template <typename T>
struct JointGeometry {
  AxisType type = AxisType::Linear;
  Side side = Side::Head;
  Eigen::Matrix<T, 3, 1> direction = Eigen::Matrix<T, 3, 1>::UnitX();  ///< unit
  Eigen::Matrix<T, 3, 1> pivot_mm = Eigen::Matrix<T, 3, 1>::Zero();    ///< a point on a rotary axis
  T offset = T(0);  ///< added to the commanded value (zero-point error; rad or mm)

  template <typename U>
  JointGeometry<U> cast() const {
    JointGeometry<U> g;
    g.type = type;
    g.side = side;
    g.direction = direction.template cast<U>();
    g.pivot_mm = pivot_mm.template cast<U>();
    g.offset = U(offset);
    return g;
  }
};

/// The geometric parameters of a serial machine (everything FK depends on).
template <typename T>
struct SerialGeometry {
  std::array<JointGeometry<T>, 5> joints;  ///< in axis order (the order of Axes)
  std::vector<int> table_chain;            ///< joint indices from the base outward to the part
  std::vector<int> head_chain;             ///< joint indices from the base outward to the tool
  Eigen::Matrix<T, 3, 1> tool_direction_home = Eigen::Matrix<T, 3, 1>::UnitZ();  ///< tip -> spindle
  Eigen::Matrix<T, 3, 1> gauge_home_mm = Eigen::Matrix<T, 3, 1>::Zero();         ///< spindle gauge point at home
  Eigen::Matrix<T, 3, 1> part_origin_home_mm = Eigen::Matrix<T, 3, 1>::Zero();   ///< CL origin at home
  T tool_length_mm = T(0);  ///< gauge point to tip, along the tool axis

  template <typename U>
  SerialGeometry<U> cast() const {
    SerialGeometry<U> g;
    for (size_t i = 0; i < 5; ++i) g.joints[i] = joints[i].template cast<U>();
    g.table_chain = table_chain;
    g.head_chain = head_chain;
    g.tool_direction_home = tool_direction_home.template cast<U>();
    g.gauge_home_mm = gauge_home_mm.template cast<U>();
    g.part_origin_home_mm = part_origin_home_mm.template cast<U>();
    g.tool_length_mm = U(tool_length_mm);
    return g;
  }
};

namespace detail {
template <typename T>
Eigen::Matrix<T, 3, 3> axis_angle(const Eigen::Matrix<T, 3, 1>& w, const T& angle) {
  using std::cos;
  using std::sin;
  const T c = cos(angle), s = sin(angle), v = T(1) - c;
  Eigen::Matrix<T, 3, 3> R;
  R << c + w.x() * w.x() * v, w.x() * w.y() * v - w.z() * s, w.x() * w.z() * v + w.y() * s,  //
      w.y() * w.x() * v + w.z() * s, c + w.y() * w.y() * v, w.y() * w.z() * v - w.x() * s,   //
      w.z() * w.x() * v - w.y() * s, w.z() * w.y() * v + w.x() * s, c + w.z() * w.z() * v;
  return R;
}
}  // namespace detail

/// Forward kinematics of a serial machine, for any scalar (double, ceres::Jet).
/// `q` are the five axis values (mm / rad). Returns the tool pose in the part frame.
template <typename T, typename Q>
Pose<T> serial_forward(const SerialGeometry<T>& g, const Q& q) {
  using Vec = Eigen::Matrix<T, 3, 1>;
  // Head chain, applied from the outermost joint inward to the tool at home.
  Vec tip = g.gauge_home_mm - g.tool_length_mm * g.tool_direction_home;
  Vec axis = g.tool_direction_home;
  for (auto it = g.head_chain.rbegin(); it != g.head_chain.rend(); ++it) {
    const JointGeometry<T>& j = g.joints[*it];
    const T v = T(q[*it]) + j.offset;
    if (j.type == AxisType::Linear) {
      tip += j.direction * v;
    } else {
      const Eigen::Matrix<T, 3, 3> R = detail::axis_angle<T>(j.direction, v);
      tip = R * (tip - j.pivot_mm) + j.pivot_mm;
      axis = R * axis;
    }
  }
  // Undo the table chain from the base outward: base frame -> part frame.
  for (int idx : g.table_chain) {
    const JointGeometry<T>& j = g.joints[idx];
    const T v = T(q[idx]) + j.offset;
    if (j.type == AxisType::Linear) {
      tip -= j.direction * v;
    } else {
      const Eigen::Matrix<T, 3, 3> Rt = detail::axis_angle<T>(j.direction, v).transpose();
      tip = Rt * (tip - j.pivot_mm) + j.pivot_mm;
      axis = Rt * axis;
    }
  }
  return Pose<T>{tip - g.part_origin_home_mm, axis};
}

/// The serial machine as a Kinematics (double precision, closed-form IK).
class SerialKinematics final : public Kinematics {
 public:
  /// Validates the geometry (exactly two rotaries and three linear joints, unit directions,
  /// linear directions spanning space). Throws std::invalid_argument with a message on failure.
  SerialKinematics(SerialGeometry<double> geometry, std::vector<AxisInfo> axes);

  [[nodiscard]] const std::vector<AxisInfo>& axes() const override { return axes_; }
  [[nodiscard]] std::array<int, 2> rotary_pair() const override { return rot_; }
  /// The default traits, and linear axes that translate (three prismatic joints of unit direction).
  [[nodiscard]] Traits traits() const override {
    Traits t = Kinematics::traits();
    t.linear_axes_translate = true;
    return t;
  }
  /// serial_forward's arithmetic, operation for operation, on steps laid out once (no chain lists, the products
  /// of each rotary's direction components taken once): FK is most of the post's and the gate's work.
  [[nodiscard]] Posed forward(const Axes& q) const override;
  void inverse_all(const Posed& pose, const Axes* hint, std::vector<Solution>& out) const override;
  void inverse_branches(const Posed& pose, const Axes* hint, std::vector<Solution>& out) const override;
  bool solve_for_rotaries(const Posed& pose, Axes& q) const override;
  bool tool_axis_at(double primary, double secondary, const Eigen::Vector3d& /*tip_mm*/,
                    Eigen::Vector3d& axis) const override {
    axis = axis_for_rotaries(primary, secondary);
    return true;
  }
  bool axis_factors(double primary, double secondary, Eigen::Matrix3d* R_primary,
                    Eigen::Vector3d* v_secondary) const override;

  bool head_in_part(const Axes& q, Eigen::Isometry3d& T) const override;
  /// From the joint spans and the distances of the moved point from the pivots, without trigonometry: each
  /// rotary joint (rate w, the point at most rho from its pivot, moving at most V) adds w rho to the speed and
  /// w^2 rho + 2 w V to the acceleration; each linear joint adds its span to the speed (docs/safety.md).
  bool motion_bound(const Axes& qa, const Axes& qb, MotionBound& out) const override;
  bool link_in_part(int axis, const Axes& q, Eigen::Isometry3d& T) const override;
  bool links_in_part(const Axes& q, int n, unsigned used, Eigen::Isometry3d* T) const override;
  [[nodiscard]] int head_link() const override {
    return geometry_.head_chain.empty() ? 0 : 1 + geometry_.head_chain.back();
  }
  [[nodiscard]] const SerialGeometry<double>& geometry() const { return geometry_; }
  /// The tool axis in the part frame that the two rotary values give (independent of the linear axes).
  [[nodiscard]] Eigen::Vector3d axis_for_rotaries(double primary, double secondary) const;

 private:
  struct Rigid {  // x -> R x + t
    Eigen::Matrix3d R;
    Eigen::Vector3d t;
  };
  [[nodiscard]] std::array<Rigid, 5> joint_motions(const Axes& q) const;
  [[nodiscard]] Rigid part_from_base(const std::array<Rigid, 5>& J) const;
  bool chain_link(int axis, const std::array<Rigid, 5>& J, const Rigid& part_from_base, Eigen::Isometry3d& T) const;
  /// One joint as forward() and solve_for_rotaries() apply it.
  struct Step {
    int axis = 0;
    bool rotary = false;
    bool table = false;  ///< undone (inverse) from the base outward
    int lin_col = -1;    ///< a linear joint's column of solve_for_rotaries' A
    Eigen::Vector3d direction, pivot_mm;
    double offset = 0.0;
    double wxx = 0, wxy = 0, wxz = 0, wyy = 0, wyz = 0, wzz = 0;  ///< detail::axis_angle's direction products
  };
  /// detail::axis_angle(step.direction, angle), from the step's products.
  [[nodiscard]] static Eigen::Matrix3d rotation(const Step& j, double angle);
  SerialGeometry<double> geometry_;
  std::vector<AxisInfo> axes_;
  std::vector<Step> steps_;   ///< head chain from its outermost joint inward, then the table chain outward
  Eigen::Vector3d tip_home_;  ///< gauge_home_mm - tool_length_mm * tool_direction_home
  // solve_for_rotaries: t0 and A after the leading linear steps (constants), and where the rest begins.
  Eigen::Vector3d solve_t0_;
  Eigen::Matrix3d solve_A_;
  std::size_t solve_first_ = 0;
  std::array<int, 2> rot_{};      ///< rotary joints in Paden-Kahan order: u = Rot(w1, s1 q1) Rot(w2, s2 q2) d0
  std::array<double, 2> sign_{};  ///< -1 for a table rotary (its inverse enters), +1 for a head rotary
  std::array<int, 3> lin_{};
};

}  // namespace cscam::kin
