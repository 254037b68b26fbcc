#include "cscam/kin/serial.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "cscam/core/tolerances.hpp"
#include "cscam/core/units.hpp"

namespace cscam::kin {

namespace {

using Vec3 = Eigen::Vector3d;

/// Paden-Kahan subproblem 1: the angle about unit `w` that turns p into q (both projected onto the
/// plane normal to w). Returns false when p is (nearly) parallel to w: the angle is then undetermined.
bool pk1(const Vec3& w, const Vec3& p, const Vec3& q, double& angle) {
  const Vec3 pp = p - w * w.dot(p);
  const Vec3 qp = q - w * w.dot(q);
  if (pp.norm() < tol::kSingularRad || qp.norm() < tol::kSingularRad) return false;
  angle = std::atan2(w.dot(pp.cross(qp)), pp.dot(qp));
  return true;
}

}  // namespace

std::string Kinematics::check_limits(const Axes& q) const {
  const auto& ax = axes();
  for (int i = 0; i < 5; ++i) {
    const AxisInfo& a = ax[static_cast<size_t>(i)];
    const double slack = a.rotary() ? deg2rad(tol::kLimitSlackDeg) : tol::kLimitSlackMm;
    if (q[i] < a.min - slack || q[i] > a.max + slack) {
      if (a.rotary())
        return fmt::format("{} = {:.4f} deg outside its limits [{:.4f}, {:.4f}] deg", a.name, rad2deg(q[i]),
                           rad2deg(a.min), rad2deg(a.max));
      return fmt::format("{} = {:.4f} mm outside its limits [{:.4f}, {:.4f}] mm", a.name, q[i], a.min, a.max);
    }
  }
  return {};
}

void Kinematics::nearest_winding(Axes& s, const Axes& prev) const {
  const auto& ax = axes();
  for (int i = 0; i < 5; ++i) {
    const AxisInfo& a = ax[static_cast<size_t>(i)];
    if (!a.rotary()) continue;
    const double turns = std::round((prev[i] - s[i]) / (2.0 * kPi));
    double v = s[i] + turns * 2.0 * kPi;
    // Keep inside the limits if the nearest winding is not: step one turn back toward the range.
    if (v > a.max && v - 2.0 * kPi >= a.min) v -= 2.0 * kPi;
    if (v < a.min && v + 2.0 * kPi <= a.max) v += 2.0 * kPi;
    s[i] = v;
  }
}

void Kinematics::expand_windings(const Solution& base, std::vector<Solution>& out) const {
  const auto rp = rotary_pair();
  const auto& ax = axes();
  auto range = [&](int i, double v, int& kmin, int& kmax) {
    const AxisInfo& a = ax[static_cast<size_t>(i)];
    const double slack = deg2rad(tol::kLimitSlackDeg);
    kmin = static_cast<int>(std::ceil((a.min - slack - v) / (2.0 * kPi)));
    kmax = static_cast<int>(std::floor((a.max + slack - v) / (2.0 * kPi)));
  };
  int k0min, k0max, k1min, k1max;
  range(rp[0], base.axes[rp[0]], k0min, k0max);
  range(rp[1], base.axes[rp[1]], k1min, k1max);
  if (k0min > k0max || k1min > k1max) {  // no winding inside the limits: keep the base, flagged
    Solution s = base;
    s.violation = check_limits(s.axes);
    out.push_back(std::move(s));
    return;
  }
  for (int k0 = k0min; k0 <= k0max; ++k0)
    for (int k1 = k1min; k1 <= k1max; ++k1) {
      Solution s = base;
      s.axes[rp[0]] += k0 * 2.0 * kPi;
      s.axes[rp[1]] += k1 * 2.0 * kPi;
      s.violation = check_limits(s.axes);
      out.push_back(std::move(s));
    }
}

SerialKinematics::SerialKinematics(SerialGeometry<double> geometry, std::vector<AxisInfo> axes)
    : geometry_(std::move(geometry)), axes_(std::move(axes)) {
  if (axes_.size() != 5) throw std::invalid_argument("a serial machine needs exactly 5 axes");
  std::vector<int> rot_table, rot_head;
  int nlin = 0;
  for (int i = 0; i < 5; ++i) {
    auto& j = geometry_.joints[static_cast<size_t>(i)];
    if (std::abs(j.direction.norm() - 1.0) > 1e-6)
      throw std::invalid_argument(fmt::format("axis {}: direction must be a unit vector", axes_[i].name));
    j.direction.normalize();
    if (j.type != axes_[i].type) throw std::invalid_argument("axis type mismatch between geometry and axis info");
    if (j.type == AxisType::Linear) {
      if (nlin < 3) lin_[static_cast<size_t>(nlin)] = i;
      ++nlin;
    }
  }
  if (nlin != 3) throw std::invalid_argument(fmt::format("a serial 5-axis machine needs 3 linear axes, got {}", nlin));
  for (int idx : geometry_.table_chain)
    if (geometry_.joints[static_cast<size_t>(idx)].type == AxisType::Rotary) rot_table.push_back(idx);
  for (int idx : geometry_.head_chain)
    if (geometry_.joints[static_cast<size_t>(idx)].type == AxisType::Rotary) rot_head.push_back(idx);
  if (geometry_.table_chain.size() + geometry_.head_chain.size() != 5)
    throw std::invalid_argument("every axis must be in exactly one chain (table or head)");
  // u_part = R_tn^T ... R_t1^T R_h1 ... R_hm d0: table rotaries outermost first (inverse), then head.
  std::vector<std::pair<int, double>> order;
  for (auto it = rot_table.rbegin(); it != rot_table.rend(); ++it) order.emplace_back(*it, -1.0);
  for (int idx : rot_head) order.emplace_back(idx, 1.0);
  if (order.size() != 2)
    throw std::invalid_argument(fmt::format("a 5-axis machine needs 2 rotary axes, got {}", order.size()));
  rot_ = {order[0].first, order[1].first};
  sign_ = {order[0].second, order[1].second};
  const Vec3 w1 = geometry_.joints[static_cast<size_t>(rot_[0])].direction;
  const Vec3 w2 = geometry_.joints[static_cast<size_t>(rot_[1])].direction;
  if (w1.cross(w2).norm() < 1e-6) throw std::invalid_argument("the two rotary axes are parallel");
  Eigen::Matrix3d L;
  for (int k = 0; k < 3; ++k) L.col(k) = geometry_.joints[static_cast<size_t>(lin_[static_cast<size_t>(k)])].direction;
  if (std::abs(L.determinant()) < 1e-6) throw std::invalid_argument("the linear axes do not span space");
  auto add_step = [&](int idx, bool table) {
    const auto& j = geometry_.joints[static_cast<size_t>(idx)];
    Step st;
    st.axis = idx;
    st.rotary = j.type == AxisType::Rotary;
    st.table = table;
    for (int c = 0; c < 3; ++c)
      if (lin_[static_cast<size_t>(c)] == idx) st.lin_col = c;
    st.direction = j.direction;
    st.pivot_mm = j.pivot_mm;
    st.offset = j.offset;
    const Vec3& w = j.direction;
    st.wxx = w.x() * w.x();
    st.wxy = w.x() * w.y();
    st.wxz = w.x() * w.z();
    st.wyy = w.y() * w.y();
    st.wyz = w.y() * w.z();
    st.wzz = w.z() * w.z();
    steps_.push_back(st);
  };
  for (auto it = geometry_.head_chain.rbegin(); it != geometry_.head_chain.rend(); ++it) add_step(*it, false);
  for (int idx : geometry_.table_chain) add_step(idx, true);
  const auto& g = geometry_;
  tip_home_ = g.gauge_home_mm - g.tool_length_mm * g.tool_direction_home;
  // solve_for_rotaries' leading linear head steps do not depend on q: applied here, as it applies them.
  solve_t0_ = tip_home_;
  solve_A_ = Eigen::Matrix3d::Zero();
  for (solve_first_ = 0; solve_first_ < steps_.size(); ++solve_first_) {
    const Step& j = steps_[solve_first_];
    if (j.rotary || j.table) break;
    solve_t0_ += j.direction * j.offset;
    solve_A_.col(j.lin_col) += j.direction;
  }
}

Eigen::Matrix3d SerialKinematics::rotation(const Step& j, double angle) {
  // detail::axis_angle with w.x() * w.y() * v read as (w.x() * w.y()) * v, as C++ groups it.
  const double c = std::cos(angle), s = std::sin(angle), v = 1.0 - c;
  const Vec3& w = j.direction;
  Eigen::Matrix3d R;
  R << c + j.wxx * v, j.wxy * v - w.z() * s, j.wxz * v + w.y() * s,  //
      j.wxy * v + w.z() * s, c + j.wyy * v, j.wyz * v - w.x() * s,   //
      j.wxz * v - w.y() * s, j.wyz * v + w.x() * s, c + j.wzz * v;
  return R;
}

Posed SerialKinematics::forward(const Axes& q) const {
  // serial_forward<double>, step for step, written out in scalars: Eigen's small products, which the compiler left
  // as calls, sum each coefficient as (m0 x0 + m1 x1) + m2 x2, and so does this (no FMA contraction on this target
  // either way), so the numbers are serial_forward's to the bit (machine_test compares them).
  double tx = tip_home_.x(), ty = tip_home_.y(), tz = tip_home_.z();
  double ax = geometry_.tool_direction_home.x(), ay = geometry_.tool_direction_home.y(),
         az = geometry_.tool_direction_home.z();
  for (const Step& j : steps_) {
    const double v = q[j.axis] + j.offset;
    const Vec3& w = j.direction;
    if (!j.rotary) {
      const double dx = w.x() * v, dy = w.y() * v, dz = w.z() * v;
      if (j.table) {
        tx -= dx;
        ty -= dy;
        tz -= dz;
      } else {
        tx += dx;
        ty += dy;
        tz += dz;
      }
      continue;
    }
    // detail::axis_angle's matrix R (its direction products taken once), or R^T for a table joint (its inverse).
    // rotation() computes the same coefficients; building its Matrix3d here made the post's linearizer, three
    // forward() calls per CL segment, about 8 % slower (post_bench, 1 thread: 0.58 -> 0.63 s).
    const double c = std::cos(v), sn = std::sin(v), u = 1.0 - c;
    const double r00 = c + j.wxx * u, r01 = j.wxy * u - w.z() * sn, r02 = j.wxz * u + w.y() * sn;
    const double r10 = j.wxy * u + w.z() * sn, r11 = c + j.wyy * u, r12 = j.wyz * u - w.x() * sn;
    const double r20 = j.wxz * u - w.y() * sn, r21 = j.wyz * u + w.x() * sn, r22 = c + j.wzz * u;
    const bool t = j.table;
    const double m01 = t ? r10 : r01, m02 = t ? r20 : r02, m10 = t ? r01 : r10;
    const double m12 = t ? r21 : r12, m20 = t ? r02 : r20, m21 = t ? r12 : r21;
    const Vec3& p = j.pivot_mm;
    const double dx = tx - p.x(), dy = ty - p.y(), dz = tz - p.z();
    tx = ((r00 * dx + m01 * dy) + m02 * dz) + p.x();
    ty = ((m10 * dx + r11 * dy) + m12 * dz) + p.y();
    tz = ((m20 * dx + m21 * dy) + r22 * dz) + p.z();
    const double bx = ax, by = ay, bz = az;
    ax = (r00 * bx + m01 * by) + m02 * bz;
    ay = (m10 * bx + r11 * by) + m12 * bz;
    az = (m20 * bx + m21 * by) + r22 * bz;
  }
  const Vec3& o = geometry_.part_origin_home_mm;
  return Posed{Vec3(tx - o.x(), ty - o.y(), tz - o.z()), Vec3(ax, ay, az)};
}

Eigen::Vector3d SerialKinematics::axis_for_rotaries(double primary, double secondary) const {
  Eigen::Matrix3d R;
  Eigen::Vector3d v;
  axis_factors(primary, secondary, &R, &v);
  return R * v;
}

bool SerialKinematics::axis_factors(double primary, double secondary, Eigen::Matrix3d* R_primary,
                                    Eigen::Vector3d* v_secondary) const {
  const auto& j1 = geometry_.joints[static_cast<size_t>(rot_[0])];
  const auto& j2 = geometry_.joints[static_cast<size_t>(rot_[1])];
  if (R_primary) *R_primary = detail::axis_angle<double>(j1.direction, sign_[0] * (primary + j1.offset));
  if (v_secondary)
    *v_secondary =
        detail::axis_angle<double>(j2.direction, sign_[1] * (secondary + j2.offset)) * geometry_.tool_direction_home;
  return true;
}

void SerialKinematics::inverse_branches(const Posed& pose, const Axes* hint, std::vector<Solution>& out) const {
  out.clear();
  const auto& j1 = geometry_.joints[static_cast<size_t>(rot_[0])];
  const auto& j2 = geometry_.joints[static_cast<size_t>(rot_[1])];
  const Vec3& w1 = j1.direction;
  const Vec3& w2 = j2.direction;
  const Vec3 p = geometry_.tool_direction_home;
  const Vec3 q = pose.axis.normalized();
  // Paden-Kahan subproblem 2: Rot(w1, t1) Rot(w2, t2) p = q. The intermediate z = Rot(w2, t2) p satisfies
  // w2.z = w2.p and w1.z = w1.q; write z = a w1 + b w2 + c (w1 x w2).
  const double c12 = w1.dot(w2);
  const double den = c12 * c12 - 1.0;
  const double s2 = w2.dot(p);
  double a = (c12 * s2 - w1.dot(q)) / den;
  double b = (c12 * w1.dot(q) - s2) / den;
  const Vec3 w12 = w1.cross(w2);
  double g2 = (p.squaredNorm() - a * a - b * b - 2.0 * a * b * c12) / w12.squaredNorm();
  double axis_error = 0.0;
  if (g2 < 0.0) {
    // The cone of axes at q's angle from w1 misses the cone the secondary sweeps p over: q lies outside the band of
    // angles from w1 that the machine reaches. On an ideal trunnion that band is [0, pi]; tilt its axes by a few
    // hundred microradians (a calibrated machine) and a cone of that size about w1 becomes unreachable, with the
    // vertical tool axis on or near its edge; a nutating head's band ends at its widest tilt. The reachable axes
    // nearest q have the band's nearer end as angle from w1 and q's azimuth about it: z is the tangent point, in
    // the plane of w1 and w2 (c = 0), with w2.z = w2.p and |z| = |p|: a^2 (1 - c12^2) + (w2.p)^2 = |p|^2.
    const double span = std::sqrt(std::max(0.0, (p.squaredNorm() - s2 * s2) / (1.0 - c12 * c12)));
    const double w1z_hi = span * (1.0 - c12 * c12) + s2 * c12, w1z_lo = -span * (1.0 - c12 * c12) + s2 * c12;
    a = std::abs(w1.dot(q) - w1z_hi) <= std::abs(w1.dot(q) - w1z_lo) ? span : -span;
    b = s2 - a * c12;
    const Vec3 z = a * w1 + b * w2;
    // How far q is from the nearest reachable axis: the difference of the two angles from w1.
    axis_error = std::abs(std::atan2(w1.cross(q).norm(), w1.dot(q)) - std::atan2(w1.cross(z).norm(), w1.dot(z)));
    if (axis_error > tol::kReachSlackRad) return;  // unreachable, e.g. beyond a nutating head's cone
    g2 = 0.0;
  }
  const double g = std::sqrt(g2);
  const int nroots = g > 1e-12 ? 2 : 1;
  for (int r = 0; r < nroots; ++r) {
    const Vec3 z = a * w1 + b * w2 + (r == 0 ? g : -g) * w12;
    double t2 = 0.0, t1 = 0.0;
    if (!pk1(w2, p, z, t2)) t2 = 0.0;  // p on w2: the secondary does nothing to the axis
    Solution s;
    s.branch = r;
    s.axis_error_rad = axis_error;
    if (!pk1(w1, z, q, t1)) {
      // Tool axis parallel to the primary rotary: its angle is free; keep the previous one.
      s.singular = true;
      t1 = hint ? sign_[0] * ((*hint)[rot_[0]] + j1.offset) : 0.0;
    }
    s.axes[rot_[0]] = wrap_pi(sign_[0] * t1 - j1.offset);
    s.axes[rot_[1]] = wrap_pi(sign_[1] * t2 - j2.offset);
    if (!solve_for_rotaries(pose, s.axes)) continue;
    out.push_back(std::move(s));
  }
  // Singular: both roots collapse to z parallel to w1; the two branches differ only by how the
  // secondary got there. They are genuine distinct solutions (e.g. A=+0 vs the flipped one) only if
  // they differ; drop exact duplicates.
  if (out.size() == 2 && (out[0].axes - out[1].axes).norm() < 1e-12) out.pop_back();
  // The pole of a calibrated machine. On the ideal machine the home tool direction p lies along the primary (a
  // trunnion's C, a head's C), and a CL axis there (the vertical tool of every 3-axis stretch) leaves the primary
  // free. Tilt the primary by rho (tens to hundreds of microradians) and that axis is rho from the pole: its two
  // branches fix the primary to values unrelated to the path's, so a walk past the vertical swung C twice where the
  // ideal machine kept it, and a segment from the vertical to a tilted axis could need a flip against the secondary's
  // limit. Within rho of the pole the primary is free as on the ideal machine, within what the machine's own tilt
  // costs: one more branch, flagged singular, with the hint's primary and the secondary that brings the axis nearest
  // (at most about 2 rho off, axis_error_rad); the exact branches stay listed and the post or the planner chooses.
  if (std::any_of(out.begin(), out.end(), [](const Solution& s) { return s.singular; })) return;
  for (const double sign : {1.0, -1.0}) {
    const Vec3 pole = sign * w1;
    const double rho = std::atan2(p.cross(pole).norm(), p.dot(pole));
    if (rho > tol::kReachSlackRad || rho <= 0.0) continue;
    if (std::atan2(q.cross(pole).norm(), q.dot(pole)) > rho * (1.0 + 1e-9) + tol::kSingularRad) continue;
    Solution s;
    s.branch = static_cast<int>(out.size());
    s.singular = true;
    const double t1 = hint ? sign_[0] * ((*hint)[rot_[0]] + j1.offset) : 0.0;
    const Vec3 v = detail::axis_angle<double>(w1, -t1) * q;  // the axis the secondary must give
    double t2 = 0.0;
    if (!pk1(w2, p, v, t2)) t2 = 0.0;
    const Vec3 got = detail::axis_angle<double>(w1, t1) * (detail::axis_angle<double>(w2, t2) * p);
    s.axis_error_rad = std::atan2(got.cross(q).norm(), got.dot(q));
    s.axes[rot_[0]] = wrap_pi(sign_[0] * t1 - j1.offset);
    s.axes[rot_[1]] = wrap_pi(sign_[1] * t2 - j2.offset);
    if (s.axis_error_rad <= tol::kReachSlackRad && solve_for_rotaries(pose, s.axes)) out.push_back(std::move(s));
    return;
  }
}

void SerialKinematics::inverse_all(const Posed& pose, const Axes* hint, std::vector<Solution>& out) const {
  std::vector<Solution> base;
  inverse_branches(pose, hint, base);
  out.clear();
  // Windings change the rotaries by whole turns: the linear axes are unchanged, so nothing to redo.
  for (const Solution& s : base) expand_windings(s, out);
}

bool SerialKinematics::solve_for_rotaries(const Posed& pose, Axes& q) const {
  // With the rotaries fixed, the tip in the part frame is affine in the three linear axes:
  // tip(l) = t0 + A l. Build t0 and A in one pass over the chains with the rotations computed once
  // (this is the hot path of the post: one call per IK branch). The leading linear head steps are constants
  // (solve_t0_, solve_A_, applied in the constructor in this order).
  Vec3 t0 = solve_t0_;
  Eigen::Matrix3d A = solve_A_;  // column c: d tip / d l_c
  for (std::size_t k = solve_first_; k < steps_.size(); ++k) {
    const Step& j = steps_[k];
    if (!j.rotary) {
      if (j.table) {
        t0 -= j.direction * j.offset;
        A.col(j.lin_col) -= j.direction;
      } else {
        t0 += j.direction * j.offset;
        A.col(j.lin_col) += j.direction;
      }
    } else {
      // t0 = M (t0 - pivot) + pivot and A = M A with M = R (head) or R^T (table), summed as Eigen's small
      // products sum each coefficient: (m0 x0 + m1 x1) + m2 x2.
      const Eigen::Matrix3d R = rotation(j, q[j.axis] + j.offset);
      const Eigen::Matrix3d M = j.table ? Eigen::Matrix3d(R.transpose()) : R;
      const Vec3 d = t0 - j.pivot_mm;
      for (int i = 0; i < 3; ++i) t0[i] = ((M(i, 0) * d[0] + M(i, 1) * d[1]) + M(i, 2) * d[2]) + j.pivot_mm[i];
      const Eigen::Matrix3d B = A;
      for (int c = 0; c < 3; ++c)
        for (int i = 0; i < 3; ++i) A(i, c) = (M(i, 0) * B(0, c) + M(i, 1) * B(1, c)) + M(i, 2) * B(2, c);
    }
  }
  t0 -= geometry_.part_origin_home_mm;
  const double det = A.determinant();
  if (std::abs(det) < 1e-12) return false;
  const Vec3 l = A.inverse() * (pose.tip_mm - t0);
  for (int c = 0; c < 3; ++c) q[lin_[static_cast<size_t>(c)]] = l[c];
  return true;
}

std::array<SerialKinematics::Rigid, 5> SerialKinematics::joint_motions(const Axes& q) const {
  // The same joint motions as serial_forward, as rigid motions (x -> R (x - pivot) + pivot, or a shift), each
  // computed once for all the links that need it.
  std::array<Rigid, 5> J;
  for (std::size_t idx = 0; idx < J.size(); ++idx) {
    J[idx] = {Eigen::Matrix3d::Identity(), Eigen::Vector3d::Zero()};
    if (idx >= geometry_.joints.size()) continue;
    const auto& j = geometry_.joints[idx];
    const double v = q[static_cast<int>(idx)] + j.offset;
    if (j.type == AxisType::Linear) {
      J[idx].t = v * j.direction;
    } else {
      J[idx].R = detail::axis_angle<double>(j.direction, v);
      J[idx].t = j.pivot_mm - J[idx].R * j.pivot_mm;
    }
  }
  return J;
}

SerialKinematics::Rigid SerialKinematics::part_from_base(const std::array<Rigid, 5>& J) const {
  Rigid T{Eigen::Matrix3d::Identity(), Eigen::Vector3d::Zero()};  // undo the table chain from the base outward
  for (int idx : geometry_.table_chain) {
    const Rigid& j = J[static_cast<std::size_t>(idx)];
    // T <- j^-1 T, with j^-1 x = R^T (x - t)
    T = {j.R.transpose() * T.R, j.R.transpose() * (T.t - j.t)};
  }
  T.t -= geometry_.part_origin_home_mm;
  return T;
}

bool SerialKinematics::chain_link(int axis, const std::array<Rigid, 5>& J, const Rigid& part_from_base,
                                  Eigen::Isometry3d& T) const {
  const auto& g = geometry_;
  // The joints from the base up to and including `axis` on its chain move the link (none for the base).
  Rigid M = part_from_base;  // part <- base <- ... <- link
  if (axis >= 0) {
    const std::vector<int>* chain = nullptr;
    std::size_t upto = 0;
    for (const std::vector<int>* c : {&g.head_chain, &g.table_chain}) {
      const auto it = std::find(c->begin(), c->end(), axis);
      if (it != c->end()) {
        chain = c;
        upto = static_cast<std::size_t>(it - c->begin()) + 1;
      }
    }
    if (!chain) return false;
    for (std::size_t k = 0; k < upto; ++k) {
      const Rigid& j = J[static_cast<std::size_t>((*chain)[k])];
      M = {M.R * j.R, M.R * j.t + M.t};
    }
  }
  T.setIdentity();
  T.linear() = M.R;
  T.translation() = M.t;
  return true;
}

bool SerialKinematics::head_in_part(const Axes& q, Eigen::Isometry3d& T) const {
  // The outermost head link; with no head joint, the base.
  const auto J = joint_motions(q);
  return chain_link(geometry_.head_chain.empty() ? -1 : geometry_.head_chain.back(), J, part_from_base(J), T);
}

bool SerialKinematics::link_in_part(int axis, const Axes& q, Eigen::Isometry3d& T) const {
  const auto J = joint_motions(q);
  return chain_link(axis, J, part_from_base(J), T);
}

bool SerialKinematics::links_in_part(const Axes& q, int n, unsigned used, Eigen::Isometry3d* T) const {
  const auto J = joint_motions(q);
  const Rigid pfb = part_from_base(J);
  for (int l = 0; l < n; ++l)
    if (((used >> l) & 1u) && !chain_link(l - 1, J, pfb, T[l])) return false;
  return true;
}

bool SerialKinematics::motion_bound(const Axes& qa, const Axes& qb, MotionBound& out) const {
  const auto& g = geometry_;
  // The tip is carried through the same operations as in serial_forward, each a shift along a fixed direction
  // or a turn about a fixed axis, with joint values linear in t. For the point x before an operation keep bounds
  // over t in [0, 1]: S >= |x| (from the base origin), V >= |x'|, A >= |x''|. A turn x -> R(th)(x - c) + c with
  // rate w = |dth/dt| gives x' = w [n]x R (x - c) + R x' and x'' = w^2 [n]x^2 R (x - c) + 2 w [n]x R x' + R x'',
  // so with rho = S + |c| >= |x - c|: V += w rho, A += w^2 rho + 2 w V, and S <= rho + |c| afterwards. A shift
  // by d v(t) (|d| = 1) adds |v_b - v_a| to V and max(|v_a|, |v_b|) to S. Table joints enter inverted (R^T, -d):
  // the same bounds.
  double S = (g.gauge_home_mm - g.tool_length_mm * g.tool_direction_home).norm(), V = 0.0, A = 0.0, W = 0.0;
  auto step = [&](int idx) {
    const auto& j = g.joints[static_cast<size_t>(idx)];
    const double va = qa[idx] + j.offset, vb = qb[idx] + j.offset;
    if (j.type == AxisType::Linear) {
      S += std::max(std::abs(va), std::abs(vb));
      V += std::abs(vb - va);
    } else {
      const double w = std::abs(vb - va), c = j.pivot_mm.norm(), rho = S + c;
      A += w * w * rho + 2.0 * w * V;
      V += w * rho;
      S = rho + c;
      W += w;
    }
  };
  for (auto it = g.head_chain.rbegin(); it != g.head_chain.rend(); ++it) step(*it);
  for (int idx : g.table_chain) step(idx);
  out.tip_accel_mm = A;
  // The unit tool axis only turns: the same recursion with rho = 1 and no shifts gives W and W^2.
  out.axis_rate_rad = W;
  out.axis_accel = W * W;
  return std::isfinite(A);
}

}  // namespace cscam::kin
