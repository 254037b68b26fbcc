// XMINI kinematics: parameter table, forward-kinematics Newton, the analytic tool Jacobian, inverse
// kinematics (reduced 2x2 Newton around the spec's closed form) and limit checks.
#include "cscam/kin/xmini.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <iterator>
#include <limits>
#include <unsupported/Eigen/AutoDiff>

#include "cscam/core/error.hpp"
#include "cscam/core/tolerances.hpp"

namespace cscam::kin {

// ---------------------------------------------------------------------------------------------------
// Parameters
// ---------------------------------------------------------------------------------------------------

const std::array<XminiParamInfo, kXminiParamCount>& xmini_param_info() {
  static constexpr std::array<XminiParamInfo, kXminiParamCount> kInfo{{
      {"pWB_x", "mm", 0.0},  {"pWB_y", "mm", 0.0},  {"pWB_z", "mm", 900.0}, {"theta0", "deg", 0.0},
      {"eps_y", "deg", 0.0}, {"eps_z", "deg", 0.0}, {"A1x", "mm", -150.0},  {"A3x", "mm", 150.0},
      {"l1", "mm", 0.0},     {"l3", "mm", 0.0},     {"A2x", "mm", 0.0},     {"A2y", "mm", 200.0},
      {"A2z", "mm", 0.0},    {"b1x", "mm", -75.0},  {"b1z", "mm", 0.0},     {"b3x", "mm", 75.0},
      {"b3z", "mm", 0.0},    {"c2x", "mm", 0.0},    {"c2y", "mm", 100.0},   {"c2z", "mm", 0.0},
      {"phi", "deg", 0.0},   {"chi", "deg", 0.0},   {"L01", "mm", 450.0},   {"L02", "mm", 450.0},
      {"L03", "mm", 450.0},  {"sCx", "mm", 0.0},    {"sCy", "mm", 0.0},     {"sCz", "mm", 150.0},
      {"gC1", "deg", 0.0},   {"gC2", "deg", 0.0},   {"c0", "deg", 0.0},     {"e", "mm", 0.0},
      {"f", "mm", 0.0},      {"psi", "deg", 0.0},   {"a0", "deg", 0.0},     {"gx", "mm", 0.0},
      {"gy", "mm", 0.0},     {"gz", "mm", 100.0},
  }};
  return kInfo;
}

std::size_t xmini_param_index(std::string_view name) {
  const auto& info = xmini_param_info();
  for (std::size_t i = 0; i < info.size(); ++i)
    if (info[i].name == name) return i;
  std::string names;
  for (const auto& in : info) names += (names.empty() ? "" : ", ") + std::string(in.name);
  throw InputError(fmt::format("unknown XMINI parameter '{}' (known: {})", name, names));
}

// ---------------------------------------------------------------------------------------------------
// Limits
// ---------------------------------------------------------------------------------------------------

std::string XminiLimitViolation::describe() const {
  const char* name = "?";
  const char* kind = "?";
  bool angle = true;
  switch (joint) {
    case XminiJoint::Q1:
      name = "q1", kind = "stroke", angle = false;
      break;
    case XminiJoint::Q2:
      name = "q2", kind = "stroke", angle = false;
      break;
    case XminiJoint::Q3:
      name = "q3", kind = "stroke", angle = false;
      break;
    case XminiJoint::C:
      name = "c", kind = "C-axis";
      break;
    case XminiJoint::A:
      name = "a", kind = "A-axis";
      break;
    case XminiJoint::Alpha:
      name = "alpha", kind = "passive-joint";
      break;
    case XminiJoint::Beta:
      name = "beta", kind = "passive-joint";
      break;
  }
  const double v = angle ? rad2deg(value) : value;
  const double l = angle ? rad2deg(limit) : limit;
  const char* unit = angle ? "deg" : "mm";
  return fmt::format("{} = {:.3f} {} {} {} limit {:g} {}", name, v, unit, above ? "exceeds" : "is below", kind, l,
                     unit);
}

std::vector<XminiLimitViolation> check_limits(const XminiLimits& lim, const XminiJoints<double>& q,
                                              const XminiState<double>& x) {
  std::vector<XminiLimitViolation> out;
  const double slack_mm = tol::kLimitSlackMm;
  const double slack_rad = deg2rad(tol::kLimitSlackDeg);
  auto check = [&](XminiJoint j, double v, double lo, double hi, double slack) {
    if (v > hi + slack) out.push_back({j, v, hi, true});
    if (v < lo - slack) out.push_back({j, v, lo, false});
  };
  const XminiJoint legs[3] = {XminiJoint::Q1, XminiJoint::Q2, XminiJoint::Q3};
  for (int i = 0; i < 3; ++i) {
    const auto k = static_cast<std::size_t>(i);
    check(legs[i], q[i], lim.q_min_mm[k], lim.q_max_mm[k], slack_mm);
  }
  check(XminiJoint::C, q[3], lim.c_min_rad, lim.c_max_rad, slack_rad);
  check(XminiJoint::A, q[4], lim.a_min_rad, lim.a_max_rad, slack_rad);
  check(XminiJoint::Alpha, x[0], -lim.alpha_max_rad, lim.alpha_max_rad, slack_rad);
  check(XminiJoint::Beta, x[1], -lim.beta_max_rad, lim.beta_max_rad, slack_rad);
  return out;
}

// ---------------------------------------------------------------------------------------------------
// Forward kinematics
// ---------------------------------------------------------------------------------------------------

XminiSolveSummary solve_platform(const XminiGeometry<double>& g, const Eigen::Vector3d& rho_mm, XminiState<double>& x,
                                 int max_iterations) {
  XminiSolveSummary s;
  for (int it = 0;; ++it) {
    const XminiPlatform<double> P = platform_from_state(g, x);
    Eigen::Vector4d F(P.rho_mm[0] - rho_mm[0], P.rho_mm[1] - rho_mm[1], P.rho_mm[2] - rho_mm[2], P.leg2_constraint_mm);
    s.residual_norm = F.cwiseAbs().maxCoeff();
    s.iterations = it;
    if (!std::isfinite(s.residual_norm)) return s;
    if (s.residual_norm <= kXminiFkResidualMm) {
      s.converged = true;
      return s;
    }
    if (it == max_iterations) return s;
    const Eigen::Matrix4d J = platform_residual_jacobian(g, x, P);
    x -= J.partialPivLu().solve(F);
  }
}

XminiFkResult<double> xmini_forward(const XminiGeometry<double>& g, const XminiJoints<double>& q, double tool_length_mm,
                                    XminiWorkspace& ws) {
  const Eigen::Vector3d rho = q.head<3>() + g.L0_mm;
  XminiFkResult<double> r;
  r.state = ws.has_last ? ws.last_state : xmini_home_state();
  r.summary = solve_platform(g, rho, r.state);
  if (!r.summary.converged && ws.has_last) {  // a stale warm start: try again from home
    const int spent = r.summary.iterations;
    r.state = xmini_home_state();
    r.summary = solve_platform(g, rho, r.state);
    r.summary.iterations += spent;
  }
  if (r.summary.converged) {
    ws.last_state = r.state;
    ws.has_last = true;
  }
  r.pose = tool_pose(g, r.state, q[3], q[4], tool_length_mm);
  return r;
}

Eigen::Matrix<double, 6, 5> xmini_jacobian(const XminiGeometry<double>& g, const XminiState<double>& x,
                                           const XminiJoints<double>& q, double tool_length_mm) {
  using Vec3 = Eigen::Vector3d;
  using xmini_detail::ex_cross;
  using xmini_detail::ey_cross;
  using xmini_detail::ez_cross;
  const XminiPlatform<double> P = platform_from_state(g, x);
  // Platform: F(x, q) = 0 with dF/dq = -[I3; 0], so dx/dq = (dF/dx)^{-1} [I3; 0].
  Eigen::Matrix<double, 4, 3> I43 = Eigen::Matrix<double, 4, 3>::Zero();
  I43.topRows<3>().setIdentity();
  const Eigen::Matrix<double, 4, 3> dx_dq = platform_residual_jacobian(g, x, P).partialPivLu().solve(I43);

  const double c_p = q[3] + g.c0_rad, a_p = q[4] + g.a0_rad;
  const Eigen::Matrix3d Rz = xmini_detail::rot_z(c_p), Rx = xmini_detail::rot_x(a_p);
  const Eigen::Matrix3d R_CA = g.R_psi * Rx;
  const Vec3 tip_A = g.gauge_A_mm + Vec3(0, 0, tool_length_mm);
  const Vec3 h_C = g.ef_mm + R_CA * tip_A;  // tip in the C frame (after Rz)
  const Vec3 tip_P = g.sC_P_mm + g.R_PC0 * Rz * h_C;
  const Vec3 zA_P = g.R_PC0 * Rz * R_CA.col(2);
  const Eigen::Matrix3d& R = P.R_BP;

  // d(tip_B, u_B)/dx, 6x4.
  const double sa = std::sin(x[0]), ca = std::cos(x[0]);
  const Vec3 w(0, -sa, ca);
  Eigen::Matrix<double, 6, 4> D;
  D.block<3, 1>(0, 0) = x[3] * ex_cross(w) + ex_cross(Vec3(R * tip_P));
  D.block<3, 1>(3, 0) = -ex_cross(Vec3(R * zA_P));
  D.block<3, 1>(0, 1) = R * ey_cross(tip_P);
  D.block<3, 1>(3, 1) = -(R * ey_cross(zA_P));
  D.block<3, 1>(0, 2) = Vec3::UnitX();
  D.block<3, 1>(3, 2).setZero();
  D.block<3, 1>(0, 3) = w;
  D.block<3, 1>(3, 3).setZero();

  Eigen::Matrix<double, 6, 5> J_B;
  J_B.leftCols<3>() = D * dx_dq;
  // Wrist: c turns about z_C, a about x_A.
  J_B.block<3, 1>(0, 3) = R * g.R_PC0 * ez_cross(Vec3(Rz * h_C));
  J_B.block<3, 1>(3, 3) = -(R * g.R_PC0 * ez_cross(Vec3(Rz * R_CA.col(2))));
  const Eigen::Matrix3d R_PCpsi = g.R_PC0 * Rz * g.R_psi;
  J_B.block<3, 1>(0, 4) = R * R_PCpsi * ex_cross(Vec3(Rx * tip_A));
  J_B.block<3, 1>(3, 4) = -(R * R_PCpsi * ex_cross(Vec3(Rx.col(2))));

  Eigen::Matrix<double, 6, 5> J_W;
  J_W.topRows<3>() = g.R_WB * J_B.topRows<3>();
  J_W.bottomRows<3>() = g.R_WB * J_B.bottomRows<3>();
  return J_W;
}

// ---------------------------------------------------------------------------------------------------
// Inverse kinematics
// ---------------------------------------------------------------------------------------------------
namespace {

using Vec3 = Eigen::Vector3d;
using AD = Eigen::AutoDiffScalar<Eigen::Vector2d>;  // forward mode in (alpha, beta)

inline double val(double x) { return x; }
inline double val(const AD& x) { return x.value(); }

/// The IK request, expressed in B.
struct IkTarget {
  Vec3 tip_B_mm;
  Vec3 k_B;       ///< direction spindle -> tip (= -u) in B
  Vec3 tip_A_mm;  ///< tool tip in frame A: gauge + L e_z
  double c_hint_rad = 0.0;
};

/// The two reduced equations and what they determine, for one platform orientation.
template <typename S>
struct Reduced {
  Eigen::Matrix<S, 2, 1> r;  ///< (E . n(alpha), leg-2 constraint), mm
  S cos_c, sin_c;            ///< c' = c + c0
  S cos_a, sin_a;            ///< a' = a + a0
  Eigen::Matrix<S, 3, 1> E_B;
  bool singular = false;  ///< z_A parallel to the C axis: c' taken from the hint
  bool clamped = false;   ///< direction within psi of the C axis: unreachable, nearest taken
};

/// For platform orientation (alpha, beta): the wrist (c, a) in closed form from the tool direction
/// (any gC1, gC2, psi, c0, a0), then E from the tip, then the two equations not yet used: E in the
/// plane of legs 1 and 3, and the leg-2 revolute constraint.
template <typename S>
Reduced<S> eval_reduced(const XminiGeometry<double>& g, const IkTarget& t, const S& alpha, const S& beta, int branch) {
  using std::cos;
  using std::sin;
  using std::sqrt;
  using V = Eigen::Matrix<S, 3, 1>;
  const S ca = cos(alpha), sa = sin(alpha), cb = cos(beta), sb = sin(beta);
  Eigen::Matrix<S, 3, 3> R;  // Rx(alpha) Ry(beta)
  R << cb, S(0), sb, sa * sb, ca, -sa * cb, -ca * sb, sa, ca * cb;

  // Tool direction in P, then in the C-axis frame before Rz: m = R_PC0^T R^T k.
  V kP, m;
  for (int i = 0; i < 3; ++i) kP[i] = R(0, i) * t.k_B[0] + R(1, i) * t.k_B[1] + R(2, i) * t.k_B[2];
  for (int i = 0; i < 3; ++i) m[i] = g.R_PC0(0, i) * kP[0] + g.R_PC0(1, i) * kP[1] + g.R_PC0(2, i) * kP[2];

  // m = Rz(c') w with w = Ry(psi) Rx(a') e_z = (sin psi cos a', -sin a', cos psi cos a').
  Reduced<S> out;
  const S mxy2 = m[0] * m[0] + m[1] * m[1];
  out.cos_a = m[2] / g.cos_psi;
  const double tan_psi = g.sin_psi / g.cos_psi;
  const S sin_a2 = mxy2 - tan_psi * tan_psi * m[2] * m[2];
  const double kSing2 = tol::kSingularRad * tol::kSingularRad;
  if (val(sin_a2) <= kSing2) {
    // At (or beyond) the fold a' = 0: sqrt has no derivative there; use the value only.
    out.clamped = val(sin_a2) < -kSing2;
    out.sin_a = S(0);
    out.cos_a = S(val(m[2]) >= 0 ? 1.0 : -1.0);
  } else {
    out.sin_a = double(branch) * sqrt(sin_a2);
  }
  const S wx = g.sin_psi * out.cos_a, wy = -out.sin_a;
  out.singular = val(mxy2) < kSing2;
  if (out.singular) {
    const double c_p = t.c_hint_rad + g.c0_rad + (branch < 0 ? kPi : 0.0);
    out.cos_c = S(std::cos(c_p));
    out.sin_c = S(std::sin(c_p));
  } else {
    // Rz(c') turns (wx, wy) onto (mx, my): cos/sin from the dot and cross products.
    const S n = sqrt((wx * wx + wy * wy) * mxy2);
    out.cos_c = (wx * m[0] + wy * m[1]) / n;
    out.sin_c = (wx * m[1] - wy * m[0]) / n;
  }

  // Tip in P: sC + R_PC0 Rz(c') (ef + R_psi Rx(a') tip_A).
  const Vec3& tA = t.tip_A_mm;
  V rxa;  // Rx(a') tip_A
  rxa << S(tA[0]), out.cos_a * tA[1] - out.sin_a * tA[2], out.sin_a * tA[1] + out.cos_a * tA[2];
  V h;
  for (int i = 0; i < 3; ++i)
    h[i] = g.ef_mm[i] + g.R_psi(i, 0) * rxa[0] + g.R_psi(i, 1) * rxa[1] + g.R_psi(i, 2) * rxa[2];
  const V rzh(out.cos_c * h[0] - out.sin_c * h[1], out.sin_c * h[0] + out.cos_c * h[1], h[2]);
  V tip_P;
  for (int i = 0; i < 3; ++i)
    tip_P[i] = g.sC_P_mm[i] + g.R_PC0(i, 0) * rzh[0] + g.R_PC0(i, 1) * rzh[1] + g.R_PC0(i, 2) * rzh[2];

  for (int i = 0; i < 3; ++i)
    out.E_B[i] = t.tip_B_mm[i] - (R(i, 0) * tip_P[0] + R(i, 1) * tip_P[1] + R(i, 2) * tip_P[2]);
  out.r[0] = out.E_B[1] * ca + out.E_B[2] * sa;  // E . n(alpha), n = Rx(alpha) e_y
  V d2, u2;
  for (int i = 0; i < 3; ++i) {
    d2[i] = out.E_B[i] + R(i, 0) * g.c2_P_mm[0] + R(i, 1) * g.c2_P_mm[1] + R(i, 2) * g.c2_P_mm[2] - g.A2_B_mm[i];
    u2[i] = R(i, 0) * g.u2_P[0] + R(i, 1) * g.u2_P[1] + R(i, 2) * g.u2_P[2];
  }
  out.r[1] = d2[0] * u2[0] + d2[1] * u2[1] + d2[2] * u2[2];
  return out;
}

/// One wrist branch solved: platform orientation, wrist angles and E (all in double).
struct BranchSolution {
  double alpha = 0, beta = 0;
  double c_p = 0, a_p = 0;  ///< c + c0, a + a0
  Vec3 E_B = Vec3::Zero();
  bool singular = false, clamped = false, converged = false;
  double residual_mm = 0;
  int iterations = 0;
};

constexpr int kIkMaxIterations = 20;
constexpr double kIkStopMm = 1e-12;  // Newton stops here; round-off floor is ~1e-13 mm

BranchSolution solve_branch(const XminiGeometry<double>& g, const IkTarget& t, double alpha0, double beta0,
                            int branch) {
  Eigen::Vector2d x(alpha0, beta0);
  BranchSolution s;
  double prev = std::numeric_limits<double>::infinity();
  for (int it = 0;; ++it) {
    const AD alpha(x[0], 2, 0), beta(x[1], 2, 1);
    const Reduced<AD> red = eval_reduced(g, t, alpha, beta, branch);
    const double norm = std::max(std::abs(red.r[0].value()), std::abs(red.r[1].value()));
    const bool floor = norm < kXminiIkResidualMm && norm >= 0.5 * prev;  // no more progress possible
    if (norm <= kIkStopMm || floor || it == kIkMaxIterations || !std::isfinite(norm)) {
      s.alpha = x[0];
      s.beta = x[1];
      s.c_p = std::atan2(red.sin_c.value(), red.cos_c.value());
      s.a_p = std::atan2(red.sin_a.value(), red.cos_a.value());
      s.E_B = Vec3(red.E_B[0].value(), red.E_B[1].value(), red.E_B[2].value());
      s.singular = red.singular;
      s.clamped = red.clamped;
      s.residual_mm = norm;
      s.converged = norm <= kXminiIkResidualMm && !red.clamped;
      s.iterations = it;
      return s;
    }
    Eigen::Matrix2d J;
    J.row(0) = red.r[0].derivatives().transpose();
    J.row(1) = red.r[1].derivatives().transpose();
    const double det = J(0, 0) * J(1, 1) - J(0, 1) * J(1, 0);
    const Eigen::Vector2d r(red.r[0].value(), red.r[1].value());
    x -= Eigen::Vector2d(J(1, 1) * r[0] - J(0, 1) * r[1], -J(1, 0) * r[0] + J(0, 0) * r[1]) / det;
    prev = norm;
  }
}

/// Adds one solution per C winding inside the limits (or the principal one, flagged, if none is).
void emit(const XminiGeometry<double>& g, const XminiLimits& lim, const BranchSolution& b, int branch, int iterations,
          std::vector<XminiIkSolution>& out) {
  XminiIkSolution s;
  const double sa = std::sin(b.alpha), ca = std::cos(b.alpha);
  s.alpha_rad = b.alpha;
  s.beta_rad = b.beta;
  s.Eu_mm = b.E_B[0];
  s.Ev_mm = -b.E_B[1] * sa + b.E_B[2] * ca;  // E . w(alpha)
  const XminiPlatform<double> P = platform_from_state(g, s.state());
  s.q1_mm = P.rho_mm[0] - g.L0_mm[0];
  s.q2_mm = P.rho_mm[1] - g.L0_mm[1];
  s.q3_mm = P.rho_mm[2] - g.L0_mm[2];
  s.a_rad = b.a_p - g.a0_rad;
  const double c_principal = wrap_pi(b.c_p - g.c0_rad);
  s.branch = branch;
  s.singular = b.singular;
  s.exact = b.converged;
  s.residual_mm = b.residual_mm;
  s.iterations = iterations;

  const double slack = deg2rad(tol::kLimitSlackDeg), turn = 2.0 * kPi;
  const int kmin = static_cast<int>(std::ceil((lim.c_min_rad - slack - c_principal) / turn));
  const int kmax = static_cast<int>(std::floor((lim.c_max_rad + slack - c_principal) / turn));
  auto push = [&](int k) {
    out.push_back(s);
    XminiIkSolution& o = out.back();
    o.winding = k;
    o.c_rad = c_principal + k * turn;
    o.violations = check_limits(lim, o.joints(), o.state());
  };
  if (kmin > kmax) {
    push(0);
  } else {
    for (int k = kmin; k <= kmax; ++k) push(k);
  }
}

}  // namespace

void xmini_inverse(const XminiGeometry<double>& g, const XminiLimits& limits, double tool_length_mm,
                   const Eigen::Vector3d& tip_in_W_mm, const Eigen::Vector3d& u_in_W, std::optional<double> c_hint_rad,
                   std::vector<XminiIkSolution>& out) {
  out.clear();
  const double u_norm = u_in_W.norm();
  if (!(u_norm > 1e-12) || !std::isfinite(u_norm)) throw InputError("XMINI IK: the tool axis u has zero length");
  IkTarget t;
  t.tip_B_mm = g.R_WB.transpose() * (tip_in_W_mm - g.p_WB_mm);
  t.k_B = -(g.R_WB.transpose() * u_in_W) / u_norm;
  t.tip_A_mm = g.gauge_A_mm + Vec3(0, 0, tool_length_mm);
  t.c_hint_rad = c_hint_rad.value_or(0.0);

  // The spec's closed form (exact for nominal parameters): S = tip - (gz + L) k is the wrist centre;
  // it lies in the plane of legs 1 and 3, which gives alpha; the leg-2 constraint gives beta.
  const Vec3 S = t.tip_B_mm - t.tip_A_mm.z() * t.k_B;
  const double alpha0 = std::atan2(-S.y(), S.z());
  const Vec3 d = S - g.A2_B_mm;
  const double ca = std::cos(alpha0), sa = std::sin(alpha0);
  const double vx = d.x(), vz = -sa * d.y() + ca * d.z();
  const double beta0 = vz >= 0 ? std::atan2(vx, vz) : std::atan2(-vx, -vz);  // the root with cos(beta) > 0

  const BranchSolution plus = solve_branch(g, t, alpha0, beta0, +1);
  emit(g, limits, plus, +1, plus.iterations, out);
  if (g.wrist_branches_share_platform) {
    // (-a', c' + 180 deg) gives the same tool pose from the same platform state (see XminiGeometry).
    BranchSolution minus = plus;
    minus.a_p = -plus.a_p;
    minus.c_p = plus.c_p + kPi;
    emit(g, limits, minus, -1, 0, out);
  } else {
    // The other branch's platform differs only through psi, gx, gy, e: start from this one.
    const bool warm = plus.converged;
    const BranchSolution minus = solve_branch(g, t, warm ? plus.alpha : alpha0, warm ? plus.beta : beta0, -1);
    emit(g, limits, minus, -1, minus.iterations, out);
  }
}

std::vector<XminiIkSolution> feasible_solutions(const std::vector<XminiIkSolution>& all) {
  std::vector<XminiIkSolution> out;
  std::copy_if(all.begin(), all.end(), std::back_inserter(out), [](const XminiIkSolution& s) { return s.feasible(); });
  return out;
}

// ---------------------------------------------------------------------------------------------------
// The model
// ---------------------------------------------------------------------------------------------------

XminiModel::XminiModel(const XminiParams<double>& params, const XminiLimits& limits, double tool_length_mm)
    : params_(params), geometry_(params), limits_(limits), tool_length_mm_(tool_length_mm) {
  for (std::size_t i = 0; i < XminiParams<double>::kCount; ++i)
    if (!std::isfinite(params_[i]))
      throw InputError(fmt::format("XMINI parameter {} is not finite", xmini_param_info()[i].name));
  if (!std::isfinite(tool_length_mm) || tool_length_mm < 0)
    throw InputError(fmt::format("XMINI tool length {} mm must be finite and >= 0", tool_length_mm));
  if (!(geometry_.cos_psi > 1e-6))
    throw InputError(fmt::format("XMINI psi = {} deg: |psi| must be below 90 deg", rad2deg(params_.psi)));
}

Eigen::Matrix<double, 6, 5> XminiModel::jacobian(const XminiJoints<double>& q, XminiWorkspace& ws) const {
  const XminiFkResult<double> fk = forward(q, ws);
  return xmini_jacobian(geometry_, fk.state, q, tool_length_mm_);
}

}  // namespace cscam::kin
