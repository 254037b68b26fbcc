#pragma once
/// @file
/// Rotation conventions of tilted work planes (3+2 machining). A work plane is a frame of the part: its
/// rotation R_part_plane (columns: the plane's X, Y, Z axes in the part frame) and its origin; a point with
/// coordinates p_plane in the plane is the part point origin + R_part_plane * p_plane. The tool axis of a
/// 3+2 stretch is the plane's Z axis.
///
/// - ZXZ Euler angles (Fanuc G68.2 I J K): R = Rz(alpha) Rx(beta) Rz(gamma), rotations about the frame's own
///   (moving) axes: Z, then the new X, then the new Z.
/// - Spatial angles (Heidenhain PLANE SPATIAL SPA SPB SPC): R = Rz(C) Ry(B) Rx(A): about the fixed (part) axes,
///   X first, then Y, then Z.
/// - Axis-by-axis X, Y, Z (Siemens CYCLE800 mode 57): R = Rx(A) Ry(B) Rz(C): X, then the new Y, then the new Z.
#include <Eigen/Core>
#include <Eigen/Geometry>
#include <algorithm>
#include <array>
#include <cmath>

namespace cscam::rot {

using Mat3 = Eigen::Matrix3d;
using Vec3 = Eigen::Vector3d;

inline Mat3 rx(double a) { return Eigen::AngleAxisd(a, Vec3::UnitX()).toRotationMatrix(); }
inline Mat3 ry(double a) { return Eigen::AngleAxisd(a, Vec3::UnitY()).toRotationMatrix(); }
inline Mat3 rz(double a) { return Eigen::AngleAxisd(a, Vec3::UnitZ()).toRotationMatrix(); }

/// Below this sin(beta) (or cos(B)) the first and last angles of a decomposition are one rotation: the last is 0.
inline constexpr double kGimbalLock = 1e-12;

/// R = Rz(alpha) Rx(beta) Rz(gamma).
inline Mat3 from_euler_zxz(double alpha, double beta, double gamma) { return rz(alpha) * rx(beta) * rz(gamma); }

/// {alpha, beta, gamma} with beta in [0, pi] and R = from_euler_zxz(...); gamma = 0 where beta is 0 or pi.
inline std::array<double, 3> euler_zxz(const Mat3& R) {
  const double beta = std::atan2(std::hypot(R(0, 2), R(1, 2)), R(2, 2));
  if (std::sin(beta) < kGimbalLock) {
    // R = Rz(alpha + gamma) or Rz(alpha - gamma) Rx(pi): the whole turn about Z goes into alpha.
    return {std::atan2(R(1, 0), R(0, 0)), beta, 0.0};
  }
  // Third column: (sin a sin b, -cos a sin b, cos b); third row: (sin b sin g, sin b cos g, cos b).
  return {std::atan2(R(0, 2), -R(1, 2)), beta, std::atan2(R(2, 0), R(2, 1))};
}

/// R = Rz(c) Ry(b) Rx(a) (spatial angles a, b, c about the fixed X, Y, Z).
inline Mat3 from_spatial(double a, double b, double c) { return rz(c) * ry(b) * rx(a); }

/// {a, b, c} with b in [-pi/2, pi/2] and R = from_spatial(...); c = 0 where cos b is 0.
inline std::array<double, 3> spatial(const Mat3& R) {
  const double b = std::atan2(-R(2, 0), std::hypot(R(0, 0), R(1, 0)));
  if (std::cos(b) < kGimbalLock) {
    // R = Ry(+-pi/2) with Rx(a) and Rz(c) about one axis: all of it in a.
    const double a = R(2, 0) < 0 ? std::atan2(R(0, 1), R(1, 1)) : std::atan2(-R(0, 1), R(1, 1));
    return {a, b, 0.0};
  }
  return {std::atan2(R(2, 1), R(2, 2)), b, std::atan2(R(1, 0), R(0, 0))};
}

/// R = Rx(a) Ry(b) Rz(c) (axis by axis about the moving X, then Y, then Z).
inline Mat3 from_axis_by_axis_xyz(double a, double b, double c) { return rx(a) * ry(b) * rz(c); }

/// {a, b, c} with b in [-pi/2, pi/2] and R = from_axis_by_axis_xyz(...); c = 0 where cos b is 0.
inline std::array<double, 3> axis_by_axis_xyz(const Mat3& R) {
  // R^T = Rz(-c) Ry(-b) Rx(-a): the spatial decomposition of the transpose, negated.
  const auto s = spatial(R.transpose());
  return {-s[0], -s[1], -s[2]};
}

/// The work plane whose Z is the tool axis `z_in_part` (unit) with gamma = 0 in ZXZ: its X axis is horizontal
/// in the part frame (along the part's X when the tool is vertical).
inline Mat3 plane_for_tool_axis(const Vec3& z_in_part) {
  const Vec3 u = z_in_part.normalized();
  const double beta = std::atan2(std::hypot(u.x(), u.y()), u.z());
  const double alpha = std::hypot(u.x(), u.y()) < kGimbalLock ? 0.0 : std::atan2(u.x(), -u.y());
  return from_euler_zxz(alpha, beta, 0.0);
}

/// The coordinates in the plane (R_part_plane, origin) of a part point.
inline Vec3 to_plane(const Mat3& R_part_plane, const Vec3& origin_in_part, const Vec3& p_in_part) {
  return R_part_plane.transpose() * (p_in_part - origin_in_part);
}

/// The part point with coordinates p_in_plane in the plane (R_part_plane, origin).
inline Vec3 from_plane(const Mat3& R_part_plane, const Vec3& origin_in_part, const Vec3& p_in_plane) {
  return origin_in_part + R_part_plane * p_in_plane;
}

/// The largest u . slerp(a, b, t) over t in [lo, hi] (0 <= lo <= hi <= 1) for unit vectors a, b and u, where th is
/// the angle from a to b and sin_th = sin(th) > 0: the dot product with the point of that stretch of the arc nearest
/// u. (In the arc's plane u's projection lies at an angle phi from a; along the arc the dot product is
/// |projection| cos(psi - phi).)
inline double arc_best_dot(const Vec3& a, const Vec3& b, double th, double sin_th, const Vec3& u, double lo,
                           double hi) {
  const Vec3 e2 = (b - std::cos(th) * a) / sin_th;
  const double x = u.dot(a), y = u.dot(e2);
  const double phi = std::atan2(y, x);
  if (phi >= lo * th && phi <= hi * th) return std::hypot(x, y);
  // Outside the stretch, the nearer end on the circle (phi is taken in (-pi, pi], not next to the stretch).
  return std::max(x * std::cos(lo * th) + y * std::sin(lo * th), x * std::cos(hi * th) + y * std::sin(hi * th));
}

}  // namespace cscam::rot
