#pragma once
// Command-line number checks shared by the subcommands. CLI11's own (NonNegativeNumber, PositiveNumber) let NaN
// through and word their ranges in 300 digits.
#include <CLI/CLI.hpp>
#include <cmath>
#include <string>

namespace cscam::cli {

/// A validator for a finite number that `ok` accepts; `what` names the range in the message.
inline CLI::Validator finite_number(bool (*ok)(double), const std::string& what) {
  return CLI::Validator(
      [ok, what](std::string& s) -> std::string {
        double v = 0;
        try {
          std::size_t used = 0;
          v = std::stod(s, &used);
          if (used != s.size()) return "expected a number, got '" + s + "'";
        } catch (const std::exception&) {
          return "expected a number, got '" + s + "'";
        }
        return std::isfinite(v) && ok(v) ? std::string() : "must be a finite number " + what + ", got '" + s + "'";
      },
      "NUMBER " + what);
}

/// A finite number >= 0 (0 usually means: the machine file's value).
inline const CLI::Validator kNonNegative = finite_number([](double v) { return v >= 0; }, ">= 0");
/// A finite number > 0.
inline const CLI::Validator kPositive = finite_number([](double v) { return v > 0; }, "> 0");

}  // namespace cscam::cli
