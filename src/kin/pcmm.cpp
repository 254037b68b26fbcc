// The seed-001 parallel CMM: forward-kinematics Newton, its analytic Jacobian, inverse by Newton.
#include "cscam/kin/pcmm.hpp"

#include <Eigen/LU>

namespace cscam::kin {

namespace {
Eigen::Matrix3d exp_so3(const Eigen::Vector3d& w) {
  const double a = w.norm();
  if (a < 1e-300) return Eigen::Matrix3d::Identity();
  return Eigen::AngleAxisd(a, w / a).toRotationMatrix();
}
}  // namespace

Eigen::Matrix<double, 6, 6> pcmm_residual_jacobian(const PcmmGeometry<double>& g, const PcmmPose<double>& x) {
  Eigen::Matrix<double, 6, 6> J;
  for (int i = 0; i < 3; ++i) {
    const Eigen::Vector3d Rs = x.R * g.S[i];
    const Eigen::Vector3d Ra = x.R * g.a[i];
    const Eigen::Vector3d d = x.p + Rs - g.B[i];
    const Eigen::Vector3d n = d.normalized();
    // d(Rv) = dw x Rv; a . (dw x v) = dw . (v x a)
    J.block<1, 3>(i, 0) = n.transpose();
    J.block<1, 3>(i, 3) = Rs.cross(n).transpose();
    J.block<1, 3>(3 + i, 0) = Ra.transpose();
    J.block<1, 3>(3 + i, 3) = (Rs.cross(Ra) + Ra.cross(d)).transpose();
  }
  return J;
}

bool pcmm_solve(const PcmmGeometry<double>& g, const Eigen::Vector3d& q, PcmmPose<double>& x, int max_iter) {
  for (int it = 0; it < max_iter; ++it) {
    const Eigen::Matrix<double, 6, 1> F = pcmm_residual<double>(g, x, q);
    if (!F.allFinite()) return false;
    if (F.cwiseAbs().maxCoeff() <= 1e-12) return true;
    const Eigen::Matrix<double, 6, 6> J = pcmm_residual_jacobian(g, x);
    const Eigen::Matrix<double, 6, 1> dx = J.partialPivLu().solve(-F);
    if (!dx.allFinite()) return false;
    x.p += dx.head<3>();
    x.R = exp_so3(dx.tail<3>()) * x.R;
    if (it > 3 && dx.norm() < 1e-15) break;
  }
  const Eigen::Matrix<double, 6, 1> F = pcmm_residual<double>(g, x, q);
  return F.allFinite() && F.cwiseAbs().maxCoeff() <= 1e-10;
}

bool pcmm_inverse(const PcmmParams<double>& p, const Eigen::Vector3d& tip_S, const Eigen::Vector3d& tip_W,
                  Eigen::Vector3d& q) {
  const PcmmGeometry<double> g(p);
  PcmmPose<double> ws = pcmm_home_pose();
  // Start: leg lengths for a level stage with its origin under the tip.
  PcmmPose<double> guess{tip_W - tip_S, Eigen::Matrix3d::Identity()};
  for (int i = 0; i < 3; ++i) q[i] = (guess.p + g.S[i] - g.B[i]).norm() - g.l0[i];
  ws = guess;
  for (int it = 0; it < 50; ++it) {
    PcmmPose<double> x;
    if (!pcmm_forward<double>(p, q, ws, x)) return false;
    const Eigen::Vector3d r = pcmm_tip(x, tip_S) - tip_W;
    if (r.norm() < 1e-11) return true;
    Eigen::Matrix3d J;
    for (int j = 0; j < 3; ++j) {
      Eigen::Vector3d qh = q;
      qh[j] += 1e-6;
      PcmmPose<double> ws2 = ws, xh;
      if (!pcmm_forward<double>(p, qh, ws2, xh)) return false;
      J.col(j) = (pcmm_tip(xh, tip_S) - pcmm_tip(x, tip_S)) / 1e-6;
    }
    q -= J.partialPivLu().solve(r);
  }
  return false;
}

}  // namespace cscam::kin
