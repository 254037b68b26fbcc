#pragma once
/// @file
/// Axis statistics of an NC program (or of a planned axis path): travel, reversals, steps, simultaneity.
#include <array>
#include <nlohmann/json_fwd.hpp>
#include <string>
#include <vector>

#include "cscam/kin/types.hpp"
#include "cscam/nc/reader.hpp"

namespace cscam::report {

struct AxisStat {
  std::string name;
  bool rotary = false;
  double travel = 0.0;        ///< mm or deg
  int reversals = 0;          ///< direction changes larger than the hysteresis
  double largest_step = 0.0;  ///< largest change in one feed block (mm or deg); rapids only reposition
  double min = 0.0, max = 0.0;
};

/// A continuous cutting segment (between rapids).
struct SegmentStat {
  int first_line = 0, last_line = 0;
  int blocks = 0;
  int moving_axes = 0;       ///< axes that move anywhere in the segment
  int moving_rotaries = 0;   ///< 0: 3+2 (fixed 2 axes), 1: fixed 1 axis + 4-axis, 2: simultaneous 5-axis
  int max_simultaneous = 0;  ///< most axes moving together in one block
};

struct Stats {
  std::string source;
  size_t motion_blocks = 0;
  size_t feed_blocks = 0;
  std::array<AxisStat, 5> axes;
  std::vector<SegmentStat> segments;
  std::array<int, 6> blocks_by_simultaneous{};  ///< feed blocks by number of moving axes (0..5)
  /// Cycle-time estimate (NC programs): feed blocks at their programmed rate (G93: 1/F; G94: length by the
  /// RS274 rule / F), rapids at the slowest axis' max_feed when the axis rates are known, and the dwells. No
  /// acceleration.
  double feed_minutes = 0.0;
  double rapid_minutes = 0.0;
  bool rapid_time_known = false;
  double dwell_minutes = 0.0;  ///< the program's dwells (nc::Program::dwell_seconds)

  [[nodiscard]] nlohmann::json json() const;
  [[nodiscard]] std::string to_json() const;  ///< json().dump()
};

/// Statistics of axis values read from an NC file. `max_feed` (mm/min, deg/min per axis; 0 unknown), when given,
/// times the rapids of the cycle-time estimate.
Stats compute(const nc::Program& program, const std::array<std::string, 5>& names, const std::array<bool, 5>& rotary,
              const std::array<double, 5>* max_feed = nullptr);

/// Statistics of an axis path (one entry per point; `rapid[i]` marks rapid points). Rotary in radians.
Stats compute(const std::vector<kin::Axes>& path, const std::vector<bool>& rapid,
              const std::array<std::string, 5>& names, const std::array<bool, 5>& rotary);

/// A side-by-side text table of several statistics (one column per source).
std::string table(const std::vector<Stats>& columns, const std::vector<std::string>& headers);

}  // namespace cscam::report
