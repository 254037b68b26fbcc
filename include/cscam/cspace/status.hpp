#pragma once
/// @file
/// Why a C-space cell is (in)feasible, and the sampled C-space of a planned segment (for pictures). Header only,
/// without geometry: reports that draw the C-space need not link the collision libraries.
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <utility>
#include <vector>

namespace cscam::cspace {

/// Why a cell is (in)feasible.
enum class Status : std::uint8_t { Unknown, Feasible, Orientation, Stroke, Collision };

inline const char* to_string(Status s) {
  switch (s) {
    case Status::Unknown:
      return "unknown";
    case Status::Feasible:
      return "feasible";
    case Status::Orientation:
      return "orientation";
    case Status::Stroke:
      return "stroke";
    case Status::Collision:
      return "collision";
  }
  return "?";
}

}  // namespace cscam::cspace

namespace cscam::plan {

/// For the pictures: the C-space of one segment at a few of its CL points (panels), on a common window of the two
/// rotaries, with the planned path.
struct SegmentSpace {
  std::size_t segment = 0;
  int first_line = 0, last_line = 0;  ///< CL lines of the segment
  std::size_t points = 0;             ///< CL points in the segment
  /// The window, in picture cells: cell (i1, i2) is centred on rotaries (i1 * resolution1_rad, i2 * resolution2_rad).
  int i1_min = 0, i1_max = 0, i2_min = 0, i2_max = 0;
  double resolution1_rad = 0.0, resolution2_rad = 0.0;  ///< picture cell size per rotary (at least the planner's)
  double cone_rad = 0.0;                                ///< the planner's cone
  /// One sampled CL point: why each cell of the window is (in)feasible there.
  struct Panel {
    std::size_t point = 0;                       ///< index of the point in the segment
    int line = 0;                                ///< its CL line
    std::vector<cspace::Status> status;          ///< per cell, at (i2 - i2_min) * width() + (i1 - i1_min)
    std::pair<double, double> chosen{0.0, 0.0};  ///< the plan's rotaries at this point, rad
    /// The plan's own cell evaluated at this point (the picture cell holding it shows this status).
    cspace::Status chosen_status = cspace::Status::Unknown;
  };
  std::vector<Panel> panels;
  std::vector<std::pair<double, double>> path;  ///< the plan's (r1, r2) at every point of the segment, rad
  [[nodiscard]] int width() const { return i1_max - i1_min + 1; }
  [[nodiscard]] int height() const { return i2_max - i2_min + 1; }
  /// The picture cell holding rotaries (r1, r2).
  [[nodiscard]] int i1_of(double r1) const { return static_cast<int>(std::lround(r1 / resolution1_rad)); }
  [[nodiscard]] int i2_of(double r2) const { return static_cast<int>(std::lround(r2 / resolution2_rad)); }
};

}  // namespace cscam::plan
