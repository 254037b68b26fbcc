#pragma once
/// @file
/// The parallel coordinate-measuring machine (PCMM) of seed 001 (Oiwa): a 3-SPR parallel mechanism.
///
/// - The base carries three spherical joints B_i = (rb_i cos thb_i, rb_i sin thb_i, zb_i) (frame W,
///   z up, the stage hangs below the base).
/// - The stage carries three revolute joints at S_i = (rs_i cos ths_i, rs_i sin ths_i, 0) in the stage
///   frame, with axis a_i = (-sin(ths_i + gs_i), cos(ths_i + gs_i), 0) (tangential at gs_i = 0).
/// - Leg i is prismatic with a gauge: its length is l_i + q_i (q_i the gauge reading, l_i the initial
///   length). The revolute joint keeps the leg perpendicular to its axis: (P_i - B_i) . (R a_i) = 0.
/// - Three leg lengths fix the stage pose (6 equations in 6 unknowns, solved by Newton).
/// - The probe tip sits at `tip_S` in the stage frame (not a calibration parameter).
/// - A redundant passive link with its own gauge runs from the base joint (0, 0, bz) to the stage
///   joint (sx, sy, sz) (stage frame); the gauge reads |link| - lp0.
///
/// The 26 parameters (file units mm / deg; radians inside), in vector order:
///   bz, sx, sy, sz, lp0, l1, l2, l3, rb1, thb1, zb1, rb2, thb2, zb2, rb3, thb3, zb3,
///   rs1, ths1, gs1, rs2, ths2, gs2, rs3, ths3, gs3.
/// Templated on the scalar so that calibration differentiates it with ceres::Jet.
#include <Eigen/Geometry>
#include <array>
#include <cmath>
#include <string_view>
#include <type_traits>

#include "cscam/kin/xmini.hpp"  // xmini_detail::scalar_cast / matrix_cast (Jet-aware helpers)

namespace cscam::kin {

inline constexpr std::size_t kPcmmParamCount = 26;

/// Name, unit, group and nominal value of one PCMM parameter (file units).
struct PcmmParamInfo {
  std::string_view name, unit, group;
  double nominal;
  [[nodiscard]] constexpr bool angle() const { return unit == "deg"; }
};

/// The nominal desktop PCMM: base joints on a 250 mm circle, stage joints on an 80 mm circle, legs of
/// 350 mm initial length, the stage about 400 mm below the base at home, the passive link from 50 mm
/// below the base centre to a stage point off the centre.
inline const std::array<PcmmParamInfo, kPcmmParamCount>& pcmm_param_info() {
  static const std::array<PcmmParamInfo, kPcmmParamCount> t{{
      {"bz", "mm", "passive", -50.0},  {"sx", "mm", "passive", 30.0},   {"sy", "mm", "passive", 20.0},
      {"sz", "mm", "passive", 25.0},   {"lp0", "mm", "passive", 300.0}, {"l1", "mm", "legs", 350.0},
      {"l2", "mm", "legs", 350.0},     {"l3", "mm", "legs", 350.0},     {"rb1", "mm", "base", 250.0},
      {"thb1", "deg", "base", 90.0},   {"zb1", "mm", "base", 0.0},      {"rb2", "mm", "base", 250.0},
      {"thb2", "deg", "base", 210.0},  {"zb2", "mm", "base", 0.0},      {"rb3", "mm", "base", 250.0},
      {"thb3", "deg", "base", 330.0},  {"zb3", "mm", "base", 0.0},      {"rs1", "mm", "stage", 80.0},
      {"ths1", "deg", "stage", 90.0},  {"gs1", "deg", "stage", 0.0},    {"rs2", "mm", "stage", 80.0},
      {"ths2", "deg", "stage", 210.0}, {"gs2", "deg", "stage", 0.0},    {"rs3", "mm", "stage", 80.0},
      {"ths3", "deg", "stage", 330.0}, {"gs3", "deg", "stage", 0.0},
  }};
  return t;
}

/// Index constants of the parameter vector.
namespace pcmm_idx {
inline constexpr int bz = 0, sx = 1, sy = 2, sz = 3, lp0 = 4, l1 = 5, rb1 = 8, rs1 = 17;
}  // namespace pcmm_idx

/// The parameter vector (mm, rad inside).
template <typename T>
using PcmmParams = std::array<T, kPcmmParamCount>;

/// The nominal parameters (mm, rad).
inline PcmmParams<double> pcmm_nominal() {
  PcmmParams<double> p{};
  for (std::size_t i = 0; i < kPcmmParamCount; ++i) {
    const auto& in = pcmm_param_info()[i];
    p[i] = in.angle() ? in.nominal * M_PI / 180.0 : in.nominal;
  }
  return p;
}

/// Joint geometry derived from the parameters.
template <typename T>
struct PcmmGeometry {
  using Vec3 = Eigen::Matrix<T, 3, 1>;
  std::array<Vec3, 3> B;  ///< base joints (W)
  std::array<Vec3, 3> S;  ///< stage joints (stage frame)
  std::array<Vec3, 3> a;  ///< revolute axes (stage frame)
  std::array<T, 3> l0;    ///< leg initial lengths
  Vec3 link_base, link_stage;
  T lp0;
  explicit PcmmGeometry(const PcmmParams<T>& p) {
    using std::cos;
    using std::sin;
    for (int i = 0; i < 3; ++i) {
      const T rb = p[8 + 3 * i], thb = p[9 + 3 * i], zb = p[10 + 3 * i];
      const T rs = p[17 + 3 * i], ths = p[18 + 3 * i], gs = p[19 + 3 * i];
      B[i] = Vec3(rb * cos(thb), rb * sin(thb), zb);
      S[i] = Vec3(rs * cos(ths), rs * sin(ths), T(0));
      a[i] = Vec3(-sin(ths + gs), cos(ths + gs), T(0));
      l0[i] = p[5 + i];
    }
    link_base = Vec3(T(0), T(0), p[0]);
    link_stage = Vec3(p[1], p[2], p[3]);
    lp0 = p[4];
  }
};

/// Stage pose: position of the stage origin and orientation, in W.
template <typename T>
struct PcmmPose {
  Eigen::Matrix<T, 3, 1> p;
  Eigen::Matrix<T, 3, 3> R;
};

/// The six FK equations (leg length - (l0 + q), revolute constraint) at stage pose `x`.
template <typename T, typename S>
Eigen::Matrix<T, 6, 1> pcmm_residual(const PcmmGeometry<T>& g, const PcmmPose<S>& x, const Eigen::Vector3d& q) {
  using Vec3 = Eigen::Matrix<T, 3, 1>;
  Eigen::Matrix<T, 6, 1> F;
  const Vec3 p = xmini_detail::matrix_cast<T>(x.p);
  const Eigen::Matrix<T, 3, 3> R = xmini_detail::matrix_cast<T>(x.R);
  for (int i = 0; i < 3; ++i) {
    const Vec3 d = p + R * g.S[i] - g.B[i];
    using std::sqrt;
    F[i] = sqrt(d.squaredNorm()) - (g.l0[i] + T(q[i]));
    F[3 + i] = d.dot(R * g.a[i]);
  }
  return F;
}

/// d(residual)/d(dp, dw) for a left perturbation R <- exp(dw) R (analytic, double).
Eigen::Matrix<double, 6, 6> pcmm_residual_jacobian(const PcmmGeometry<double>& g, const PcmmPose<double>& x);

/// Home pose guess: stage level, 400 mm under the base.
inline PcmmPose<double> pcmm_home_pose() { return {Eigen::Vector3d(0, 0, -400), Eigen::Matrix3d::Identity()}; }

/// Newton solve in double for leg gauge readings q (mm). `x` is the start on entry, the solution on
/// exit. Returns false if it does not converge to 1e-12 mm.
bool pcmm_solve(const PcmmGeometry<double>& g, const Eigen::Vector3d& q, PcmmPose<double>& x, int max_iter = 50);

/// Forward kinematics for any scalar: solves in double (warm start `ws`, updated), then one Newton
/// correction in T at the solution, which carries the exact derivatives (implicit function theorem).
/// Returns false if the mechanism cannot be assembled.
template <typename T>
bool pcmm_forward(const PcmmParams<T>& p, const Eigen::Vector3d& q, PcmmPose<double>& ws, PcmmPose<T>& out) {
  PcmmParams<double> pd;
  for (std::size_t i = 0; i < kPcmmParamCount; ++i) pd[i] = xmini_detail::scalar_cast<double>(p[i]);
  const PcmmGeometry<double> gd(pd);
  PcmmPose<double> x = ws;
  if (!pcmm_solve(gd, q, x)) {
    x = pcmm_home_pose();
    if (!pcmm_solve(gd, q, x)) return false;
  }
  ws = x;
  if constexpr (std::is_same_v<T, double>) {
    out = x;
  } else {
    const PcmmGeometry<T> g(p);
    const Eigen::Matrix<T, 6, 1> F = pcmm_residual(g, x, q);
    const Eigen::Matrix<double, 6, 6> Jinv = pcmm_residual_jacobian(gd, x).inverse();
    const Eigen::Matrix<T, 6, 1> dx = -(xmini_detail::matrix_cast<T>(Jinv) * F);
    const Eigen::Matrix<T, 3, 1> w = dx.template tail<3>();
    Eigen::Matrix<T, 3, 3> W;  // first-order exp(dw): values are zero, only derivatives matter
    W << T(1), -w.z(), w.y(), w.z(), T(1), -w.x(), -w.y(), w.x(), T(1);
    out.p = xmini_detail::matrix_cast<T>(x.p) + dx.template head<3>();
    out.R = W * xmini_detail::matrix_cast<T>(x.R);
  }
  return true;
}

/// Probe tip in W for stage pose x and tip offset (stage frame).
template <typename T>
Eigen::Matrix<T, 3, 1> pcmm_tip(const PcmmPose<T>& x, const Eigen::Vector3d& tip_S) {
  return x.p + x.R * tip_S.cast<T>();
}
/// Passive-link gauge reading |link| - lp0 (mm) at stage pose x.
template <typename T>
T pcmm_link_reading(const PcmmGeometry<T>& g, const PcmmPose<T>& x) {
  using std::sqrt;
  const Eigen::Matrix<T, 3, 1> d = x.p + x.R * g.link_stage - g.link_base;
  return sqrt(d.squaredNorm()) - g.lp0;
}

/// Leg gauge readings that put the probe tip at `tip_W` (inverse kinematics by Newton on the forward
/// model). Returns false if no assembly is found.
bool pcmm_inverse(const PcmmParams<double>& p, const Eigen::Vector3d& tip_S, const Eigen::Vector3d& tip_W,
                  Eigen::Vector3d& q);

}  // namespace cscam::kin
