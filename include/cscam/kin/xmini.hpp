#pragma once
/// @file
/// Kinematic model of the XMINI, an Exechon-type parallel kinematic machine (PKM), exactly as fixed
/// in docs/xmini.md.
///
/// Three actuated legs (strokes q1, q2, q3) move a platform with three degrees of freedom, described
/// by the platform state x = (alpha, beta, Eu, Ev). A serial C axis and A axis on the platform carry
/// the spindle. Internally everything is in mm and radians; only XminiParamInfo and
/// XminiParams::set/get use file units (mm and degrees).
///
/// Design (Pinocchio style):
/// - XminiParams<T> / XminiGeometry<T>: the geometric parameters, templated on the scalar so that
///   calibration can differentiate the model with ceres::Jet.
/// - XminiModel: params + limits + tool length, immutable after construction, safe to share between
///   threads for const use.
/// - XminiWorkspace: per-thread scratch (the last forward-kinematics solution, used as a warm start).
///
/// The model does no I/O.
#include <Eigen/Core>
#include <Eigen/Geometry>
#include <Eigen/LU>
#include <array>
#include <cstddef>
#include <optional>
#include <string>
#include <string_view>
#include <type_traits>
#include <vector>

#include "cscam/core/units.hpp"

namespace cscam::kin {

// ---------------------------------------------------------------------------------------------------
// Scalar helpers
// ---------------------------------------------------------------------------------------------------
namespace xmini_detail {

/// The plain value of a scalar: itself for double, the real part for ceres::Jet (recursively, so a
/// Jet of Jets works too). Found without including Ceres: any type with a member `a` is a Jet.
inline double value_of(double x) { return x; }
template <typename J>
requires requires(const J& j) { j.a; }
double value_of(const J& j) { return value_of(j.a); }

/// Converts between scalar types: double -> Jet by the Jet's constructor, Jet -> double by value_of.
template <typename U, typename T>
U scalar_cast(const T& x) {
  if constexpr (std::is_same_v<U, T>) {
    return x;
  } else if constexpr (std::is_same_v<U, double>) {
    return value_of(x);
  } else {
    return U(x);
  }
}

template <typename U, typename T, int R, int C>
Eigen::Matrix<U, R, C> matrix_cast(const Eigen::Matrix<T, R, C>& m) {
  Eigen::Matrix<U, R, C> out;
  for (int i = 0; i < R; ++i)
    for (int j = 0; j < C; ++j) out(i, j) = scalar_cast<U>(m(i, j));
  return out;
}

template <typename T>
Eigen::Matrix<T, 3, 3> rot_x(const T& angle) {
  using std::cos;
  using std::sin;
  const T c = cos(angle), s = sin(angle);
  Eigen::Matrix<T, 3, 3> R;
  R << T(1), T(0), T(0), T(0), c, -s, T(0), s, c;
  return R;
}
template <typename T>
Eigen::Matrix<T, 3, 3> rot_y(const T& angle) {
  using std::cos;
  using std::sin;
  const T c = cos(angle), s = sin(angle);
  Eigen::Matrix<T, 3, 3> R;
  R << c, T(0), s, T(0), T(1), T(0), -s, T(0), c;
  return R;
}
template <typename T>
Eigen::Matrix<T, 3, 3> rot_z(const T& angle) {
  using std::cos;
  using std::sin;
  const T c = cos(angle), s = sin(angle);
  Eigen::Matrix<T, 3, 3> R;
  R << c, -s, T(0), s, c, T(0), T(0), T(0), T(1);
  return R;
}
/// e_x x v, without forming the cross-product matrix.
template <typename T>
Eigen::Matrix<T, 3, 1> ex_cross(const Eigen::Matrix<T, 3, 1>& v) {
  return Eigen::Matrix<T, 3, 1>(T(0), -v.z(), v.y());
}
/// e_y x v.
template <typename T>
Eigen::Matrix<T, 3, 1> ey_cross(const Eigen::Matrix<T, 3, 1>& v) {
  return Eigen::Matrix<T, 3, 1>(v.z(), T(0), -v.x());
}
/// e_z x v.
template <typename T>
Eigen::Matrix<T, 3, 1> ez_cross(const Eigen::Matrix<T, 3, 1>& v) {
  return Eigen::Matrix<T, 3, 1>(-v.y(), v.x(), T(0));
}

}  // namespace xmini_detail

// ---------------------------------------------------------------------------------------------------
// Parameters
// ---------------------------------------------------------------------------------------------------

/// Number of named XMINI parameters (the calibration parameter vector).
inline constexpr std::size_t kXminiParamCount = 38;

/// The forward-kinematics Newton stops when the largest of the four residuals (mm) is below this.
inline constexpr double kXminiFkResidualMm = 1e-12;
/// An IK solution counts as exact when its remaining residual (mm) is below this.
inline constexpr double kXminiIkResidualMm = 1e-10;

/// Name, unit and nominal value (file units: mm or deg) of one parameter, from the spec's table.
struct XminiParamInfo {
  std::string_view name;
  std::string_view unit;  ///< "mm" or "deg"
  double nominal = 0.0;   ///< in `unit`
  [[nodiscard]] constexpr bool angle() const { return unit == "deg"; }
};

/// The spec's parameter table, in the spec's order (the order of XminiParams' members).
const std::array<XminiParamInfo, kXminiParamCount>& xmini_param_info();
/// Index of a parameter by name. Throws cscam::InputError on an unknown name (listing the valid ones).
std::size_t xmini_param_index(std::string_view name);

/// Every geometric parameter of the XMINI, in the spec's order. Lengths in mm, angles in radians.
/// Templated on the scalar so calibration can use ceres::Jet.
template <typename T>
struct XminiParams {
  static constexpr std::size_t kCount = kXminiParamCount;

  // base placement: T_WB = Trans(pWB) Rx(180 deg + theta0) Ry(eps_y) Rz(eps_z)
  T pWB_x{}, pWB_y{}, pWB_z{}, theta0{}, eps_y{}, eps_z{};
  // base joints (B frame)
  T A1x{}, A3x{}, l1{}, l3{}, A2x{}, A2y{}, A2z{};
  // platform joints (P frame); axis of leg 2's revolute u2 = Rz(phi) Ry(chi) e_x
  T b1x{}, b1z{}, b3x{}, b3z{}, c2x{}, c2y{}, c2z{}, phi{}, chi{};
  // leg offsets: q_i = rho_i - L0_i
  T L01{}, L02{}, L03{};
  // wrist: T_PA = Trans(sC) Rx(gC1) Ry(gC2) Rz(c + c0) Trans(0, e, f) Ry(psi) Rx(a + a0)
  T sCx{}, sCy{}, sCz{}, gC1{}, gC2{}, c0{}, e{}, f{}, psi{}, a0{};
  // spindle gauge point in frame A
  T gx{}, gy{}, gz{};

  /// Pointers to the members, in the spec's order.
  static const std::array<T XminiParams::*, kCount>& members() {
    static const std::array<T XminiParams::*, kCount> m{
        &XminiParams::pWB_x, &XminiParams::pWB_y, &XminiParams::pWB_z, &XminiParams::theta0, &XminiParams::eps_y,
        &XminiParams::eps_z, &XminiParams::A1x,   &XminiParams::A3x,   &XminiParams::l1,     &XminiParams::l3,
        &XminiParams::A2x,   &XminiParams::A2y,   &XminiParams::A2z,   &XminiParams::b1x,    &XminiParams::b1z,
        &XminiParams::b3x,   &XminiParams::b3z,   &XminiParams::c2x,   &XminiParams::c2y,    &XminiParams::c2z,
        &XminiParams::phi,   &XminiParams::chi,   &XminiParams::L01,   &XminiParams::L02,    &XminiParams::L03,
        &XminiParams::sCx,   &XminiParams::sCy,   &XminiParams::sCz,   &XminiParams::gC1,    &XminiParams::gC2,
        &XminiParams::c0,    &XminiParams::e,     &XminiParams::f,     &XminiParams::psi,    &XminiParams::a0,
        &XminiParams::gx,    &XminiParams::gy,    &XminiParams::gz};
    return m;
  }

  /// Name, unit and nominal value of every parameter (file units), in order.
  static const std::array<XminiParamInfo, kCount>& info() { return xmini_param_info(); }

  /// The spec's nominal machine.
  static XminiParams nominal() {
    XminiParams p;
    for (std::size_t i = 0; i < kCount; ++i) {
      const XminiParamInfo& in = info()[i];
      p[i] = T(in.angle() ? deg2rad(in.nominal) : in.nominal);
    }
    return p;
  }

  /// Parameter i (internal units: mm, rad).
  T& operator[](std::size_t i) { return this->*members()[i]; }
  const T& operator[](std::size_t i) const { return this->*members()[i]; }

  /// Sets a parameter by name, in file units (deg for angles). Throws InputError on an unknown name.
  void set(std::string_view name, double value_file_units) {
    const std::size_t i = xmini_param_index(name);
    (*this)[i] = T(info()[i].angle() ? deg2rad(value_file_units) : value_file_units);
  }
  /// A parameter by name, in file units (deg for angles). Throws InputError on an unknown name.
  [[nodiscard]] T get(std::string_view name) const {
    const std::size_t i = xmini_param_index(name);
    return info()[i].angle() ? rad2deg((*this)[i]) : (*this)[i];
  }

  /// The flat parameter vector (internal units), in the spec's order.
  [[nodiscard]] std::array<T, kCount> to_array() const {
    std::array<T, kCount> a;
    for (std::size_t i = 0; i < kCount; ++i) a[i] = (*this)[i];
    return a;
  }
  static XminiParams from_array(const std::array<T, kCount>& a) {
    XminiParams p;
    for (std::size_t i = 0; i < kCount; ++i) p[i] = a[i];
    return p;
  }
  [[nodiscard]] Eigen::Matrix<T, static_cast<int>(kCount), 1> to_vector() const {
    Eigen::Matrix<T, static_cast<int>(kCount), 1> v;
    for (std::size_t i = 0; i < kCount; ++i) v[static_cast<Eigen::Index>(i)] = (*this)[i];
    return v;
  }
  static XminiParams from_vector(const Eigen::Matrix<T, static_cast<int>(kCount), 1>& v) {
    XminiParams p;
    for (std::size_t i = 0; i < kCount; ++i) p[i] = v[static_cast<Eigen::Index>(i)];
    return p;
  }

  /// The same parameters in another scalar type (Jet -> double keeps the values only).
  template <typename U>
  [[nodiscard]] XminiParams<U> cast() const {
    XminiParams<U> p;
    for (std::size_t i = 0; i < kCount; ++i) p[i] = xmini_detail::scalar_cast<U>((*this)[i]);
    return p;
  }
};

/// The parameters turned into the vectors and rotations the equations use. Building it costs the
/// trigonometry of the fixed angles once; XminiModel keeps one.
template <typename T>
struct XminiGeometry {
  using Vec3 = Eigen::Matrix<T, 3, 1>;
  using Mat3 = Eigen::Matrix<T, 3, 3>;

  Mat3 R_WB;                               ///< base orientation in W
  Vec3 p_WB_mm;                            ///< base origin in W
  T A1x_mm{}, A3x_mm{}, l1_mm{}, l3_mm{};  ///< legs 1/3 base joints: A_i = A_ix e_x + l_i w(alpha)
  Vec3 A2_B_mm;                            ///< leg-2 spherical joint in B
  Vec3 b1_P_mm, b3_P_mm, c2_P_mm;          ///< platform joints in P
  Vec3 u2_P;                               ///< leg-2 revolute axis in P (unit)
  Vec3 L0_mm;                              ///< leg offsets
  Vec3 sC_P_mm;                            ///< C-axis origin in P
  Mat3 R_PC0;                              ///< Rx(gC1) Ry(gC2): C-axis orientation in P
  T c0_rad{}, a0_rad{};                    ///< rotary zero offsets
  Vec3 ef_mm;                              ///< (0, e, f): C frame to A frame offset
  Mat3 R_psi;                              ///< Ry(psi)
  T sin_psi{}, cos_psi{};
  Vec3 gauge_A_mm;  ///< spindle gauge point in A
  /// psi = gx = gy = e = 0 exactly: then the two wrist branches (a, c) and (-a, c + 180 deg) give the
  /// same tool pose for the same platform state, so IK solves the platform once for both.
  bool wrist_branches_share_platform = false;

  XminiGeometry() = default;
  explicit XminiGeometry(const XminiParams<T>& p) {
    using std::cos;
    using std::sin;
    using xmini_detail::rot_x;
    using xmini_detail::rot_y;
    using xmini_detail::rot_z;
    // Rx(180 deg) is applied exactly rather than through cos(pi + theta0).
    const Mat3 flip = Eigen::DiagonalMatrix<T, 3>(T(1), T(-1), T(-1)).toDenseMatrix();
    R_WB = flip * rot_x(p.theta0) * rot_y(p.eps_y) * rot_z(p.eps_z);
    p_WB_mm = Vec3(p.pWB_x, p.pWB_y, p.pWB_z);
    A1x_mm = p.A1x;
    A3x_mm = p.A3x;
    l1_mm = p.l1;
    l3_mm = p.l3;
    A2_B_mm = Vec3(p.A2x, p.A2y, p.A2z);
    b1_P_mm = Vec3(p.b1x, T(0), p.b1z);
    b3_P_mm = Vec3(p.b3x, T(0), p.b3z);
    c2_P_mm = Vec3(p.c2x, p.c2y, p.c2z);
    u2_P = Vec3(cos(p.phi) * cos(p.chi), sin(p.phi) * cos(p.chi), -sin(p.chi));
    L0_mm = Vec3(p.L01, p.L02, p.L03);
    sC_P_mm = Vec3(p.sCx, p.sCy, p.sCz);
    R_PC0 = rot_x(p.gC1) * rot_y(p.gC2);
    c0_rad = p.c0;
    a0_rad = p.a0;
    ef_mm = Vec3(T(0), p.e, p.f);
    R_psi = rot_y(p.psi);
    sin_psi = sin(p.psi);
    cos_psi = cos(p.psi);
    gauge_A_mm = Vec3(p.gx, p.gy, p.gz);
    using xmini_detail::value_of;
    wrist_branches_share_platform =
        value_of(p.psi) == 0.0 && value_of(p.gx) == 0.0 && value_of(p.gy) == 0.0 && value_of(p.e) == 0.0;
  }
};

// ---------------------------------------------------------------------------------------------------
// Limits
// ---------------------------------------------------------------------------------------------------

/// Joint limits (internal units). Defaults are the spec's; a machine file may override them.
struct XminiLimits {
  std::array<double, 3> q_min_mm{0.0, 0.0, 0.0};
  std::array<double, 3> q_max_mm{350.0, 350.0, 350.0};
  double alpha_max_rad = deg2rad(25.0);  ///< |alpha| <= this (passive joint)
  double beta_max_rad = deg2rad(25.0);   ///< |beta| <= this (passive joint)
  double a_min_rad = deg2rad(-50.0);
  double a_max_rad = deg2rad(50.0);
  double c_min_rad = deg2rad(-270.0);  ///< cabled head: C must unwind
  double c_max_rad = deg2rad(270.0);
};

/// The joints a limit can apply to.
enum class XminiJoint { Q1, Q2, Q3, C, A, Alpha, Beta };

/// One broken limit. `value` and `limit` are in internal units (mm or rad).
struct XminiLimitViolation {
  XminiJoint joint = XminiJoint::Q1;
  double value = 0.0;
  double limit = 0.0;
  bool above = true;  ///< value > limit (else value < limit)
  /// E.g. "q2 = 361.200 mm exceeds stroke limit 350 mm" or "a = -55.000 deg is below A-axis limit -50 deg".
  [[nodiscard]] std::string describe() const;
};

// ---------------------------------------------------------------------------------------------------
// Platform and tool
// ---------------------------------------------------------------------------------------------------

/// Platform state x = (alpha rad, beta rad, Eu mm, Ev mm).
template <typename T>
using XminiState = Eigen::Matrix<T, 4, 1>;
/// Joint values (q1, q2, q3 in mm; c, a in rad), the order of kin::Axes.
template <typename T>
using XminiJoints = Eigen::Matrix<T, 5, 1>;

/// The home platform state, also the cold start of forward kinematics.
inline XminiState<double> xmini_home_state() { return XminiState<double>(0.0, 0.0, 0.0, 600.0); }

/// Everything that follows from a platform state, in frame B.
template <typename T>
struct XminiPlatform {
  Eigen::Matrix<T, 3, 3> R_BP;                     ///< Rx(alpha) Ry(beta)
  Eigen::Matrix<T, 3, 1> E_B_mm;                   ///< platform origin
  std::array<Eigen::Matrix<T, 3, 1>, 3> leg_B_mm;  ///< base joint centre -> platform joint, legs 1..3
  Eigen::Matrix<T, 3, 1> rho_mm;                   ///< leg lengths |leg_i|
  Eigen::Matrix<T, 3, 1> u2_B;                     ///< leg-2 revolute axis R_BP u2
  T leg2_constraint_mm{};                          ///< leg_2 . u2_B; zero on the machine
};

/// Legs, leg lengths and the leg-2 constraint for platform state x.
template <typename T>
XminiPlatform<T> platform_from_state(const XminiGeometry<T>& g, const XminiState<T>& x) {
  using std::cos;
  using std::sin;
  using std::sqrt;
  using Vec3 = Eigen::Matrix<T, 3, 1>;
  const T& alpha = x[0];
  const T& beta = x[1];
  const T& Eu = x[2];
  const T& Ev = x[3];
  const T ca = cos(alpha), sa = sin(alpha);
  const Vec3 w(T(0), -sa, ca);  // Rx(alpha) e_z, in-plane direction of legs 1 and 3
  XminiPlatform<T> P;
  P.R_BP = xmini_detail::rot_x(alpha) * xmini_detail::rot_y(beta);
  P.E_B_mm = Vec3(Eu, T(0), T(0)) + Ev * w;
  const Vec3 A1 = Vec3(g.A1x_mm, T(0), T(0)) + g.l1_mm * w;
  const Vec3 A3 = Vec3(g.A3x_mm, T(0), T(0)) + g.l3_mm * w;
  P.leg_B_mm[0] = P.E_B_mm + P.R_BP * g.b1_P_mm - A1;
  P.leg_B_mm[1] = P.E_B_mm + P.R_BP * g.c2_P_mm - g.A2_B_mm;
  P.leg_B_mm[2] = P.E_B_mm + P.R_BP * g.b3_P_mm - A3;
  for (int i = 0; i < 3; ++i) P.rho_mm[i] = sqrt(P.leg_B_mm[static_cast<std::size_t>(i)].squaredNorm());
  P.u2_B = P.R_BP * g.u2_P;
  P.leg2_constraint_mm = P.leg_B_mm[1].dot(P.u2_B);
  return P;
}
template <typename T>
XminiPlatform<T> platform_from_state(const XminiParams<T>& p, const XminiState<T>& x) {
  return platform_from_state(XminiGeometry<T>(p), x);
}

/// (rho1, rho2, rho3, leg-2 constraint) in mm for platform state x = (alpha, beta, Eu, Ev).
template <typename T>
Eigen::Matrix<T, 4, 1> leg_lengths(const XminiGeometry<T>& g, const XminiState<T>& x) {
  const XminiPlatform<T> P = platform_from_state(g, x);
  return Eigen::Matrix<T, 4, 1>(P.rho_mm[0], P.rho_mm[1], P.rho_mm[2], P.leg2_constraint_mm);
}
template <typename T>
Eigen::Matrix<T, 4, 1> leg_lengths(const XminiParams<T>& p, const XminiState<T>& x) {
  return leg_lengths(XminiGeometry<T>(p), x);
}

/// The four forward-kinematics equations F(x) = (rho_i(x) - rho_i, leg-2 constraint), in mm.
template <typename T>
Eigen::Matrix<T, 4, 1> platform_residual(const XminiGeometry<T>& g, const XminiState<T>& x,
                                         const Eigen::Matrix<T, 3, 1>& rho_mm) {
  Eigen::Matrix<T, 4, 1> F = leg_lengths(g, x);
  F.template head<3>() -= rho_mm;
  return F;
}

/// dF/dx of platform_residual (4x4, analytic) at state x, given P = platform_from_state(g, x).
/// Columns: alpha, beta (mm/rad), Eu, Ev (mm/mm).
template <typename T>
Eigen::Matrix<T, 4, 4> platform_residual_jacobian(const XminiGeometry<T>& g, const XminiState<T>& x,
                                                  const XminiPlatform<T>& P) {
  using std::cos;
  using std::sin;
  using Vec3 = Eigen::Matrix<T, 3, 1>;
  using xmini_detail::ex_cross;
  using xmini_detail::ey_cross;
  const T ca = cos(x[0]), sa = sin(x[0]);
  const Vec3 w(T(0), -sa, ca);
  const Vec3 dw = ex_cross(w);  // d w / d alpha
  const std::array<const Vec3*, 3> b{&g.b1_P_mm, &g.c2_P_mm, &g.b3_P_mm};
  const std::array<T, 3> l{g.l1_mm, T(0), g.l3_mm};  // A_i moves with alpha through its l offset
  Eigen::Matrix<T, 4, 4> J;
  std::array<Vec3, 3> dleg_dalpha, dleg_dbeta;
  for (std::size_t i = 0; i < 3; ++i) {
    const Vec3 Rb = P.R_BP * *b[i];
    dleg_dalpha[i] = (x[3] - l[i]) * dw + ex_cross(Rb);
    dleg_dbeta[i] = P.R_BP * ey_cross(*b[i]);
    const Vec3 n = P.leg_B_mm[i] / P.rho_mm[static_cast<int>(i)];
    const int r = static_cast<int>(i);
    J(r, 0) = n.dot(dleg_dalpha[i]);
    J(r, 1) = n.dot(dleg_dbeta[i]);
    J(r, 2) = n.x();
    J(r, 3) = n.dot(w);
  }
  const Vec3& d2 = P.leg_B_mm[1];
  const Vec3& v = P.u2_B;
  J(3, 0) = dleg_dalpha[1].dot(v) + d2.dot(ex_cross(v));
  J(3, 1) = dleg_dbeta[1].dot(v) + d2.dot(P.R_BP * ey_cross(g.u2_P));
  J(3, 2) = v.x();
  J(3, 3) = w.dot(v);
  return J;
}
/// dF/dx of platform_residual (4x4, analytic) at state x.
template <typename T>
Eigen::Matrix<T, 4, 4> platform_residual_jacobian(const XminiGeometry<T>& g, const XminiState<T>& x) {
  return platform_residual_jacobian(g, x, platform_from_state(g, x));
}

/// Tool pose in W: the tip (mm) and u, the unit vector from the tip toward the spindle.
template <typename T>
struct XminiToolPose {
  Eigen::Matrix<T, 3, 1> tip_in_W_mm;
  Eigen::Matrix<T, 3, 1> u_in_W;
};

/// Wrist geometry in P for commands (c, a): tip position and z_A (spindle -> tip direction).
template <typename T>
struct XminiWristInP {
  Eigen::Matrix<T, 3, 1> tip_P_mm;
  Eigen::Matrix<T, 3, 1> zA_P;
};

/// The wrist chain T_PA applied to the tool tip g + L e_z and to e_z.
template <typename T>
XminiWristInP<T> wrist_in_platform(const XminiGeometry<T>& g, const T& c_rad, const T& a_rad, double tool_length_mm) {
  using Vec3 = Eigen::Matrix<T, 3, 1>;
  const Eigen::Matrix<T, 3, 3> R_PC = g.R_PC0 * xmini_detail::rot_z(T(c_rad + g.c0_rad));
  const Eigen::Matrix<T, 3, 3> R_CA = g.R_psi * xmini_detail::rot_x(T(a_rad + g.a0_rad));
  const Vec3 tip_A = g.gauge_A_mm + Vec3(T(0), T(0), T(tool_length_mm));
  XminiWristInP<T> w;
  w.tip_P_mm = g.sC_P_mm + R_PC * (g.ef_mm + R_CA * tip_A);
  w.zA_P = R_PC * R_CA.col(2);
  return w;
}

/// Tool pose for platform state x and wrist commands (c, a) in rad: u_W = -R_WB R_BP R_PA e_z.
template <typename T>
XminiToolPose<T> tool_pose(const XminiGeometry<T>& g, const XminiState<T>& x, const T& c_rad, const T& a_rad,
                           double tool_length_mm) {
  using Vec3 = Eigen::Matrix<T, 3, 1>;
  const Eigen::Matrix<T, 3, 3> R_BP = xmini_detail::rot_x(x[0]) * xmini_detail::rot_y(x[1]);
  using std::cos;
  using std::sin;
  const Vec3 E_B = Vec3(x[2], -x[3] * sin(x[0]), x[3] * cos(x[0]));
  const XminiWristInP<T> w = wrist_in_platform(g, c_rad, a_rad, tool_length_mm);
  XminiToolPose<T> pose;
  pose.tip_in_W_mm = g.p_WB_mm + g.R_WB * (E_B + R_BP * w.tip_P_mm);
  pose.u_in_W = -(g.R_WB * (R_BP * w.zA_P));
  return pose;
}
template <typename T>
XminiToolPose<T> tool_pose(const XminiParams<T>& p, const XminiState<T>& x, const T& c_rad, const T& a_rad,
                           double tool_length_mm) {
  return tool_pose(XminiGeometry<T>(p), x, c_rad, a_rad, tool_length_mm);
}

// ---------------------------------------------------------------------------------------------------
// Forward kinematics
// ---------------------------------------------------------------------------------------------------

/// How a Newton solve ended.
struct XminiSolveSummary {
  bool converged = false;
  int iterations = 0;
  double residual_norm = 0.0;  ///< largest absolute residual, mm
};

/// Per-thread scratch: the last forward-kinematics solution, used as the next warm start.
struct XminiWorkspace {
  XminiState<double> last_state = xmini_home_state();
  bool has_last = false;
  /// Forget the warm start (the next FK starts from home).
  void reset() {
    last_state = xmini_home_state();
    has_last = false;
  }
};

/// Forward-kinematics result: the platform state, the tool pose and how the Newton solve went.
template <typename T>
struct XminiFkResult {
  XminiState<T> state;
  XminiToolPose<T> pose;
  XminiSolveSummary summary;
};

/// Solves the four platform equations for x given leg lengths rho (mm), by Newton with the analytic
/// Jacobian, starting from `x` (in/out). Stops at residual <= kXminiFkResidualMm.
XminiSolveSummary solve_platform(const XminiGeometry<double>& g, const Eigen::Vector3d& rho_mm, XminiState<double>& x,
                                 int max_iterations = 30);

/// Forward kinematics in double: joints (q1, q2, q3 mm; c, a rad) -> platform state and tool pose.
/// Warm-started from ws.last_state if ws.has_last (falls back to home if that does not converge);
/// on success the solution is stored back in ws.
XminiFkResult<double> xmini_forward(const XminiGeometry<double>& g, const XminiJoints<double>& q, double tool_length_mm,
                                    XminiWorkspace& ws);

/// Forward kinematics for any scalar (double, ceres::Jet).
///
/// For a Jet, Newton's method runs in double on the values, then ONE Newton correction step is taken
/// in T at the converged point: x_T = x* - J(x*)^{-1} F_T(x*). Since F(x*) = 0 to 1e-12, this leaves
/// the value unchanged but gives the derivatives of x exactly by the implicit function theorem,
/// dx/dp = -J^{-1} dF/dp; differentiating through the Newton iterations instead would be slower and
/// carry the (meaningless) history of the iterations.
template <typename T>
XminiFkResult<T> xmini_forward(const XminiParams<T>& p, const XminiJoints<T>& q, double tool_length_mm,
                               XminiWorkspace& ws) {
  if constexpr (std::is_same_v<T, double>) {
    return xmini_forward(XminiGeometry<double>(p), q, tool_length_mm, ws);
  } else {
    const XminiGeometry<double> gd(p.template cast<double>());
    const XminiJoints<double> qd = xmini_detail::matrix_cast<double>(q);
    const XminiFkResult<double> rd = xmini_forward(gd, qd, tool_length_mm, ws);
    const XminiGeometry<T> g(p);
    const Eigen::Matrix<T, 3, 1> rho = q.template head<3>() + g.L0_mm;
    const XminiState<T> x0 = xmini_detail::matrix_cast<T>(rd.state);
    const Eigen::Matrix<T, 4, 1> F = platform_residual(g, x0, rho);
    const Eigen::Matrix4d J_inv = platform_residual_jacobian(gd, rd.state).inverse();
    XminiFkResult<T> r;
    r.state = x0 - xmini_detail::matrix_cast<T>(J_inv) * F;
    r.pose = tool_pose(g, r.state, T(q[3]), T(q[4]), tool_length_mm);
    r.summary = rd.summary;
    return r;
  }
}

/// Jacobian of the tool pose (tip_W mm; u_W) with respect to the joints (q1, q2, q3 mm; c, a rad),
/// 6x5, analytic: dx/dq = (dF/dx)^{-1} [I3; 0] by implicit differentiation of the platform equations,
/// composed with the wrist chain. `x` must be the FK solution of `q`.
Eigen::Matrix<double, 6, 5> xmini_jacobian(const XminiGeometry<double>& g, const XminiState<double>& x,
                                           const XminiJoints<double>& q, double tool_length_mm);

// ---------------------------------------------------------------------------------------------------
// Inverse kinematics
// ---------------------------------------------------------------------------------------------------

/// One inverse-kinematics solution (one wrist branch, one C winding).
struct XminiIkSolution {
  double q1_mm = 0, q2_mm = 0, q3_mm = 0;                    ///< leg strokes q_i = rho_i - L0_i
  double c_rad = 0, a_rad = 0;                               ///< wrist commands
  double alpha_rad = 0, beta_rad = 0, Eu_mm = 0, Ev_mm = 0;  ///< platform state
  /// +1: the closed form's '+' root, a + a0 = +acos(...) >= 0 (so a >= 0 whenever |a| > |a0|);
  /// -1: the other wrist branch, (-a, c + 180 deg) exactly when psi = gx = gy = e = 0 and nearly
  /// otherwise. The meaning of the `branch` column of xmini-vectors.csv.
  int branch = +1;
  /// c = c_principal + winding * 360 deg, with c_principal in (-180, 180] deg.
  int winding = 0;
  /// The tool axis was (within kSingularRad) parallel to the C axis: c was undetermined and taken
  /// from the hint (or 0 without one; +180 deg on branch -1).
  bool singular = false;
  /// The equations were solved to kXminiIkResidualMm and the direction was reachable (with psi != 0,
  /// directions within |psi| of the C axis are not: the nearest one, a + a0 = 0, is returned, inexact).
  bool exact = false;
  double residual_mm = 0;  ///< remaining residual of the equations
  int iterations = 0;      ///< Newton iterations spent on this branch (0 when shared or exact at the start)
  std::vector<XminiLimitViolation> violations;  ///< broken limits; empty when all are respected

  [[nodiscard]] XminiJoints<double> joints() const { return XminiJoints<double>(q1_mm, q2_mm, q3_mm, c_rad, a_rad); }
  [[nodiscard]] XminiState<double> state() const { return XminiState<double>(alpha_rad, beta_rad, Eu_mm, Ev_mm); }
  /// Exact and inside every limit.
  [[nodiscard]] bool feasible() const { return exact && violations.empty(); }
};

/// Limits broken by joints q at platform state x (empty when none). Slack: tol::kLimitSlack*.
std::vector<XminiLimitViolation> check_limits(const XminiLimits& limits, const XminiJoints<double>& q,
                                              const XminiState<double>& x);

/// Inverse kinematics: every solution for tool tip `tip_in_W_mm` and tool axis `u_in_W` (tip ->
/// spindle; normalised here): both wrist branches, each with every C winding inside the C limits
/// (the principal value, flagged, if none is). Solutions that break other limits are returned and
/// flagged. `c_hint_rad` resolves the singular wrist (u along the C axis). `out` is cleared first
/// (a caller reuses its capacity: no allocation per pose once warm).
///
/// Method: the six equations (tip 3, direction 2, leg-2 constraint 1) in (alpha, beta, Eu, Ev, c, a)
/// are reduced exactly to two: for a given platform orientation (alpha, beta) the wrist (c, a) follows
/// in closed form from the direction, then E from the tip; what remains is E lying in the legs' plane
/// and the leg-2 constraint. Newton on these 2 equations in (alpha, beta), started from the spec's
/// closed form (exact for the nominal parameters), solves the full system for any parameters.
/// Throws InputError if u has zero length.
void xmini_inverse(const XminiGeometry<double>& g, const XminiLimits& limits, double tool_length_mm,
                   const Eigen::Vector3d& tip_in_W_mm, const Eigen::Vector3d& u_in_W, std::optional<double> c_hint_rad,
                   std::vector<XminiIkSolution>& out);

/// The feasible solutions only (exact and inside every limit).
std::vector<XminiIkSolution> feasible_solutions(const std::vector<XminiIkSolution>& all);

// ---------------------------------------------------------------------------------------------------
// The model
// ---------------------------------------------------------------------------------------------------

/// The XMINI: parameters, limits and tool length. Immutable after construction; thread-safe for const
/// use. Scratch lives in an XminiWorkspace (one per thread).
class XminiModel {
 public:
  /// Throws InputError on a non-finite parameter, a tool length that is negative or not finite, or
  /// |psi| >= 90 deg.
  explicit XminiModel(const XminiParams<double>& params = XminiParams<double>::nominal(),
                      const XminiLimits& limits = {}, double tool_length_mm = 50.0);

  [[nodiscard]] const XminiParams<double>& params() const { return params_; }
  [[nodiscard]] const XminiGeometry<double>& geometry() const { return geometry_; }
  [[nodiscard]] const XminiLimits& limits() const { return limits_; }
  [[nodiscard]] double tool_length_mm() const { return tool_length_mm_; }
  /// The same machine with another tool.
  [[nodiscard]] XminiModel with_tool_length(double tool_length_mm) const {
    return XminiModel(params_, limits_, tool_length_mm);
  }

  /// Forward kinematics (see xmini_forward).
  [[nodiscard]] XminiFkResult<double> forward(const XminiJoints<double>& q, XminiWorkspace& ws) const {
    return xmini_forward(geometry_, q, tool_length_mm_, ws);
  }
  /// All IK solutions into `out` (see xmini_inverse).
  void inverse(const Eigen::Vector3d& tip_in_W_mm, const Eigen::Vector3d& u_in_W, std::vector<XminiIkSolution>& out,
               std::optional<double> c_hint_rad = std::nullopt) const {
    xmini_inverse(geometry_, limits_, tool_length_mm_, tip_in_W_mm, u_in_W, c_hint_rad, out);
  }
  [[nodiscard]] std::vector<XminiIkSolution> inverse(const Eigen::Vector3d& tip_in_W_mm, const Eigen::Vector3d& u_in_W,
                                                     std::optional<double> c_hint_rad = std::nullopt) const {
    std::vector<XminiIkSolution> out;
    inverse(tip_in_W_mm, u_in_W, out, c_hint_rad);
    return out;
  }
  /// d(tip_W, u_W)/d(q1, q2, q3, c, a), 6x5, at joints q (runs FK first).
  [[nodiscard]] Eigen::Matrix<double, 6, 5> jacobian(const XminiJoints<double>& q, XminiWorkspace& ws) const;
  /// Limits broken by a joint vector at platform state x.
  [[nodiscard]] std::vector<XminiLimitViolation> check_limits(const XminiJoints<double>& q,
                                                              const XminiState<double>& x) const {
    return kin::check_limits(limits_, q, x);
  }

 private:
  XminiParams<double> params_;
  XminiGeometry<double> geometry_;
  XminiLimits limits_;
  double tool_length_mm_;
};

}  // namespace cscam::kin
