#pragma once
/// @file
/// Why a C-space cell is (in)feasible, and the sampled C-space of a planned segment (for pictures). Header only,
/// without geometry: reports that draw the C-space need not link the collision libraries.
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

/// For the pictures: the C-space of one segment (cells feasible at every point, and why the others failed).
struct SegmentSpace {
  std::size_t segment = 0;
  int i1_min = 0, i1_max = 0, i2_min = 0, i2_max = 0;
  double resolution_rad = 0.0;
  /// status per cell over the whole segment: Feasible only if feasible at every point; otherwise the
  /// first reason found (Orientation < Stroke < Collision by first failing point).
  std::vector<cspace::Status> status;           ///< (i2 - i2_min) * (i1_max - i1_min + 1) + (i1 - i1_min)
  std::vector<std::pair<double, double>> path;  ///< chosen (r1, r2) per point
};

}  // namespace cscam::plan
