#pragma once
/// @file
/// Pictures generated from the same data as the JSON reports: the C-space of a segment with the chosen
/// path, and axis-value plots of two strategies.
#include <array>
#include <string>
#include <vector>

#include "cscam/cspace/status.hpp"
#include "cscam/kin/types.hpp"

namespace cscam::report {

/// The C-space of one segment, one panel per sampled CL point (labelled with its CL line): which cells are
/// feasible (green), outside stroke (orange), colliding (red) or outside the cone (grey) there, the planned path
/// over it and the plan's cell at that point outlined; a legend and a summary line.
std::string cspace_svg(const plan::SegmentSpace& space, const std::string& primary_name,
                       const std::string& secondary_name, const std::string& title);

/// One plot per rotary axis: axis value (deg) against CL point index for each strategy.
std::string axis_plot_svg(const std::vector<std::vector<kin::Axes>>& paths, const std::vector<std::string>& labels,
                          const std::array<int, 2>& rotaries, const std::array<std::string, 2>& names,
                          std::size_t first, std::size_t last, const std::string& title);

}  // namespace cscam::report
