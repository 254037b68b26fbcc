#include "cscam/kin/xmini_kinematics.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <limits>
#include <stdexcept>

#include "cscam/core/tolerances.hpp"
#include "cscam/core/units.hpp"

namespace cscam::kin {

namespace {

using Vec3 = Eigen::Vector3d;

/// Newton on the platform state (tip placement) stops at this residual; below kXminiIkResidualMm it
/// also stops once an iteration no longer halves the residual (the round-off floor of ~1e-13 mm).
constexpr double kTipStopMm = 1e-12;
constexpr int kTipMaxIterations = 30;

std::atomic<std::uint64_t> g_next_id{1};

/// The FK warm start of this thread for model `id`. A workspace never crosses models: a state of
/// another geometry could converge to a different assembly mode.
XminiWorkspace& workspace_for(std::uint64_t id) {
  thread_local std::uint64_t owner = 0;
  thread_local XminiWorkspace ws;
  if (owner != id) {
    ws.reset();
    owner = id;
  }
  return ws;
}

/// The assembly mode of the real machine: platform below the base, tilts well inside +-90 deg.
bool physical_state(const XminiState<double>& x) {
  return x[3] > 0.0 && std::abs(x[0]) < 0.5 * kPi && std::abs(x[1]) < 0.5 * kPi && x.allFinite();
}

std::string first_passive(const std::vector<XminiLimitViolation>& v) {
  for (const auto& e : v)
    if (e.joint == XminiJoint::Alpha || e.joint == XminiJoint::Beta) return e.describe();
  return {};
}

}  // namespace

std::vector<AxisInfo> XminiKinematics::axes_for(const XminiLimits& lim, const std::array<double, 5>& max_feed) {
  std::vector<AxisInfo> ax(5);
  for (std::size_t i = 0; i < 5; ++i) {
    ax[i].name = kXminiAxisNames[i];
    ax[i].max_feed = max_feed[i];
  }
  for (std::size_t i = 0; i < 3; ++i) {
    ax[i].type = AxisType::Linear;
    ax[i].min = lim.q_min_mm[i];
    ax[i].max = lim.q_max_mm[i];
  }
  ax[3].type = AxisType::Rotary;
  ax[3].min = lim.c_min_rad;
  ax[3].max = lim.c_max_rad;
  ax[4].type = AxisType::Rotary;
  ax[4].min = lim.a_min_rad;
  ax[4].max = lim.a_max_rad;
  return ax;
}

XminiKinematics::XminiKinematics(XminiModel model) : XminiKinematics(model, axes_for(model.limits())) {}

XminiKinematics::XminiKinematics(XminiModel model, std::vector<AxisInfo> axes)
    : model_(std::move(model)), axes_(std::move(axes)), id_(g_next_id.fetch_add(1)) {
  if (axes_.size() != 5) throw std::invalid_argument("the XMINI has exactly 5 axes (q1 q2 q3 c a)");
  for (std::size_t i = 0; i < 5; ++i) {
    if (axes_[i].name != kXminiAxisNames[i])
      throw std::invalid_argument(
          fmt::format("XMINI axis {} must be named '{}', got '{}'", i, kXminiAxisNames[i], axes_[i].name));
    if (axes_[i].rotary() != (i >= 3))
      throw std::invalid_argument(
          fmt::format("XMINI axis '{}' must be {}", axes_[i].name, i >= 3 ? "rotary" : "linear"));
  }
}

Posed XminiKinematics::forward(const Axes& q) const {
  XminiWorkspace& ws = workspace_for(id_);
  XminiFkResult<double> r = model_.forward(q, ws);
  if (r.summary.converged && !physical_state(r.state)) {  // warm start led to another assembly mode
    ws.reset();
    r = model_.forward(q, ws);
  }
  if (!r.summary.converged || !physical_state(r.state)) {
    ws.reset();
    const double inf = std::numeric_limits<double>::infinity();
    return Posed{Vec3(inf, inf, inf), Vec3::UnitZ()};
  }
  return Posed{r.pose.tip_in_W_mm, r.pose.u_in_W};
}

void XminiKinematics::to_solutions(const Posed& pose, const std::vector<XminiIkSolution>& in, bool principal_only,
                                   std::vector<Solution>& out) const {
  out.clear();
  std::array<bool, 2> exact_branch{false, false};  // [0]: branch +1, [1]: branch -1
  for (const XminiIkSolution& s : in) {
    if (!s.exact) continue;
    exact_branch[s.branch > 0 ? 0 : 1] = true;
    if (principal_only && s.winding != 0) continue;
    Solution o;
    o.axes = s.joints();
    o.branch = s.branch > 0 ? 0 : 1;
    o.singular = s.singular;
    if (!s.violations.empty()) o.violation = s.violations.front().describe();
    out.push_back(std::move(o));
  }
  // A branch without an exact solution: an unreachable direction near the C axis (psi, gx, gy off nominal). Its
  // nearest reachable axis, tip exact, flagged with the angle it is off, if within tol::kReachSlackRad.
  for (const XminiIkSolution& s : in) {
    const int b = s.branch > 0 ? 0 : 1;
    if (s.exact || exact_branch[b] || (principal_only && s.winding != 0)) continue;
    Solution o;
    o.axes = s.joints();
    double err = 0.0;
    if (!nearest_reachable(pose, o.axes, err, o.violation) || !(err <= tol::kReachSlackRad)) continue;
    o.axis_error_rad = std::max(err, std::numeric_limits<double>::min());
    o.branch = b;
    o.singular = s.singular;
    const bool dup = std::any_of(out.begin(), out.end(), [&](const Solution& e) {
      return !e.exact() && (e.axes - o.axes).cwiseAbs().maxCoeff() < 1e-9;
    });
    if (!dup) out.push_back(std::move(o));
  }
}

bool XminiKinematics::nearest_reachable(const Posed& pose, Axes& q, double& axis_error_rad,
                                        std::string& violation) const {
  const Vec3 ut = pose.axis.normalized();
  const Vec3 e1 = ut.unitOrthogonal(), e2 = ut.cross(e1);
  XminiState<double> x;
  auto resid = [&](double c, double a, Eigen::Vector2d& r, Vec3* u_out = nullptr) {
    x = platform_start(c, a, pose.tip_mm);
    if (!solve_platform_for_tip(c, a, pose.tip_mm, x)) return false;
    const Vec3 u = tool_pose(model_.geometry(), x, c, a, model_.tool_length_mm()).u_in_W;
    if (!(u.dot(ut) > 0.0)) return false;
    r << u.dot(e1), u.dot(e2);
    if (u_out) *u_out = u;
    return true;
  };
  double c = q[3], a = q[4];
  Eigen::Vector2d r, rc, ra, rt;
  if (!resid(c, a, r)) return false;
  double lambda = 1e-3;
  constexpr double kStep = 1e-7;  // forward differences (rad)
  for (int it = 0; it < 40 && r.norm() > 1e-15; ++it) {
    if (!resid(c + kStep, a, rc) || !resid(c, a + kStep, ra)) return false;
    Eigen::Matrix2d J;
    J.col(0) = (rc - r) / kStep;
    J.col(1) = (ra - r) / kStep;
    const Eigen::Matrix2d A = J.transpose() * J;
    const Eigen::Vector2d g = J.transpose() * r;
    bool improved = false;
    for (int k = 0; k < 12 && !improved; ++k) {
      Eigen::Matrix2d M = A;
      M.diagonal() += lambda * A.diagonal() + Eigen::Vector2d::Constant(1e-30);
      const Eigen::Vector2d step = -M.ldlt().solve(g);
      if (!step.allFinite()) break;
      if (resid(c + step[0], a + step[1], rt) && rt.norm() < r.norm()) {
        c += step[0];
        a += step[1];
        r = rt;
        lambda = std::max(1e-12, 0.1 * lambda);
        improved = true;
      } else {
        lambda *= 10.0;
      }
    }
    if (!improved) break;
  }
  Vec3 u;
  if (!resid(c, a, r, &u)) return false;
  axis_error_rad = std::atan2(u.cross(ut).norm(), u.dot(ut));
  const XminiPlatform<double> P = platform_from_state(model_.geometry(), x);
  q[3] = c;
  q[4] = a;
  q.head<3>() = P.rho_mm - model_.geometry().L0_mm;
  const auto v = kin::check_limits(model_.limits(), q, x);
  violation = v.empty() ? std::string() : v.front().describe();
  return true;
}

void XminiKinematics::inverse_all(const Posed& pose, const Axes* hint, std::vector<Solution>& out) const {
  thread_local std::vector<XminiIkSolution> sols;
  model_.inverse(pose.tip_mm, pose.axis, sols, hint ? std::optional<double>((*hint)[3]) : std::nullopt);
  to_solutions(pose, sols, false, out);
}

void XminiKinematics::inverse_branches(const Posed& pose, const Axes* hint, std::vector<Solution>& out) const {
  thread_local std::vector<XminiIkSolution> sols;
  model_.inverse(pose.tip_mm, pose.axis, sols, hint ? std::optional<double>((*hint)[3]) : std::nullopt);
  to_solutions(pose, sols, true, out);
}

XminiState<double> XminiKinematics::platform_start(double c_rad, double a_rad, const Vec3& tip_W_mm) const {
  const XminiGeometry<double>& g = model_.geometry();
  const Vec3 w_P = wrist_in_platform(g, c_rad, a_rad, model_.tool_length_mm()).tip_P_mm;
  const Vec3 tip_B = g.R_WB.transpose() * (tip_W_mm - g.p_WB_mm);
  // Untilted platform: the wrist centre S = E + sC, which lies in the legs' plane (alpha) and, for the
  // nominal leg 2, on the line whose tilt is beta (the spec's closed form).
  const Vec3 S = tip_B - w_P + g.sC_P_mm;
  const double alpha = std::atan2(-S.y(), S.z());
  const Vec3 d = xmini_detail::rot_x(alpha).transpose() * (S - g.A2_B_mm);
  const double beta = d.z() >= 0 ? std::atan2(d.x(), d.z()) : std::atan2(-d.x(), -d.z());
  const Vec3 E = tip_B - xmini_detail::rot_x(alpha) * xmini_detail::rot_y(beta) * w_P;
  const Vec3 w(0.0, -std::sin(alpha), std::cos(alpha));
  return XminiState<double>(alpha, beta, E.x(), E.dot(w));
}

bool XminiKinematics::solve_platform_for_tip(double c_rad, double a_rad, const Vec3& tip_W_mm,
                                             XminiState<double>& x) const {
  using xmini_detail::ex_cross;
  using xmini_detail::ey_cross;
  const XminiGeometry<double>& g = model_.geometry();
  const Vec3 w_P = wrist_in_platform(g, c_rad, a_rad, model_.tool_length_mm()).tip_P_mm;
  const Vec3 tip_B = g.R_WB.transpose() * (tip_W_mm - g.p_WB_mm);
  double prev = std::numeric_limits<double>::infinity();
  for (int it = 0; it <= kTipMaxIterations; ++it) {
    const XminiPlatform<double> P = platform_from_state(g, x);
    const Vec3 Rw = P.R_BP * w_P;
    Eigen::Vector4d G;
    G.head<3>() = P.E_B_mm + Rw - tip_B;
    G[3] = P.leg2_constraint_mm;
    const double norm = G.cwiseAbs().maxCoeff();
    if (!std::isfinite(norm)) return false;
    if (norm <= kTipStopMm || (norm < kXminiIkResidualMm && norm >= 0.5 * prev)) return physical_state(x);
    if (it == kTipMaxIterations) return false;
    // Columns alpha, beta, Eu, Ev of d(tip_B, leg-2 constraint)/dx.
    const Vec3 w(0.0, -std::sin(x[0]), std::cos(x[0]));
    Eigen::Matrix4d J;
    J.block<3, 1>(0, 0) = x[3] * ex_cross(w) + ex_cross(Rw);
    J.block<3, 1>(0, 1) = P.R_BP * ey_cross(w_P);
    J.block<3, 1>(0, 2) = Vec3::UnitX();
    J.block<3, 1>(0, 3) = w;
    J.row(3) = platform_residual_jacobian(g, x, P).row(3);
    x -= J.partialPivLu().solve(G);
    prev = norm;
  }
  return false;
}

bool XminiKinematics::solve_for_rotaries(const Posed& pose, Axes& q) const {
  XminiState<double> x = platform_start(q[3], q[4], pose.tip_mm);
  if (!solve_platform_for_tip(q[3], q[4], pose.tip_mm, x)) return false;
  const XminiPlatform<double> P = platform_from_state(model_.geometry(), x);
  q.head<3>() = P.rho_mm - model_.geometry().L0_mm;
  return first_passive(kin::check_limits(model_.limits(), q, x)).empty();
}

bool XminiKinematics::tool_axis_at(double primary, double secondary, const Vec3& tip_mm, Vec3& axis) const {
  XminiState<double> x = platform_start(primary, secondary, tip_mm);
  if (!solve_platform_for_tip(primary, secondary, tip_mm, x)) return false;
  Axes q;
  q << 0.0, 0.0, 0.0, primary, secondary;
  if (!first_passive(kin::check_limits(model_.limits(), q, x)).empty()) return false;
  axis = tool_pose(model_.geometry(), x, primary, secondary, model_.tool_length_mm()).u_in_W;
  return true;
}

std::string XminiKinematics::passive_violation(const Axes& q) const {
  XminiWorkspace& ws = workspace_for(id_);
  const XminiFkResult<double> r = model_.forward(q, ws);
  if (!r.summary.converged) return "the legs admit no platform position (forward kinematics does not converge)";
  return first_passive(kin::check_limits(model_.limits(), q, r.state));
}

std::string XminiKinematics::all_violations(const Axes& q) const {
  XminiWorkspace& ws = workspace_for(id_);
  const XminiFkResult<double> r = model_.forward(q, ws);
  if (!r.summary.converged) return "the legs admit no platform position (forward kinematics does not converge)";
  const auto v = kin::check_limits(model_.limits(), q, r.state);
  return v.empty() ? std::string() : v.front().describe();
}

}  // namespace cscam::kin
