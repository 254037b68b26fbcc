#pragma once
/// @file
/// JSON for reports: nlohmann::json (strings escaped, NaN and infinities written as null), and numbers rounded to
/// the decimals a report means, so that 0.1235 is written as 0.1235 and not 0.12349999999999999.
#include <cmath>
#include <nlohmann/json.hpp>

namespace cscam::report {

/// `v` rounded to `decimals` decimal places; non-finite values unchanged (JSON null).
inline double rounded(double v, int decimals) {
  if (!std::isfinite(v)) return v;
  const double scale = std::pow(10.0, decimals);
  const double r = std::round(v * scale) / scale;
  return std::isfinite(r) ? r : v;
}

}  // namespace cscam::report
