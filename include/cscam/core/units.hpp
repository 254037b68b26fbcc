#pragma once
/// @file
/// Units and angle helpers. Internally cscam works in mm and radians; files and G-code use degrees.
#include <cmath>
#include <numbers>

namespace cscam {

inline constexpr double kMmPerInch = 25.4;
inline constexpr double kPi = std::numbers::pi;

template <typename T>
constexpr T deg2rad(T deg) {
  return deg * T(kPi / 180.0);
}
template <typename T>
constexpr T rad2deg(T rad) {
  return rad * T(180.0 / kPi);
}
// Whole degrees must not truncate to an integer number of radians: deg2rad(5) is 0.0873, not 0.
constexpr double deg2rad(int deg) { return deg * (kPi / 180.0); }
constexpr double rad2deg(int rad) { return rad * (180.0 / kPi); }

/// Wrap an angle to (-pi, pi].
inline double wrap_pi(double a) {
  // Already inside (IK angles from atan2 nearly always are): remainder would return a itself (its quotient rounds
  // to 0), without its libm call.
  if (a > -kPi && a <= kPi) return a;
  a = std::remainder(a, 2.0 * kPi);
  return a <= -kPi ? a + 2.0 * kPi : a;
}

enum class LengthUnit { Millimetre, Inch };

inline double to_mm(double v, LengthUnit u) { return u == LengthUnit::Inch ? v * kMmPerInch : v; }

}  // namespace cscam
