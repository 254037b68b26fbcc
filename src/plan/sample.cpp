// The sampled C-space of a planned segment, for pictures.
#include <algorithm>
#include <cmath>
#include <limits>

#include "cscam/core/error.hpp"
#include "cscam/core/units.hpp"
#include "cscam/plan/plan.hpp"

namespace cscam::plan {

using cspace::Cell;
using cspace::Status;

SegmentSpace Planner::sample_segment(const cl::Program& program, const Plan& plan, std::size_t segment,
                                     std::size_t max_points) const {
  CSCAM_CHECK(segment < plan.segments.size(), "segment index in range");
  const SegmentReport& rep = plan.segments[segment];
  SegmentSpace out;
  out.segment = segment;
  out.resolution_rad = space_.options().resolution_rad;
  const auto rp = kin_->rotary_pair();
  // The window: the planned path's bounding box, padded, clipped to the grid.
  double lo1 = std::numeric_limits<double>::infinity(), hi1 = -std::numeric_limits<double>::infinity(),
         lo2 = std::numeric_limits<double>::infinity(), hi2 = -std::numeric_limits<double>::infinity();
  for (std::size_t m = rep.first_move; m <= rep.last_move; ++m) {
    lo1 = std::min(lo1, plan.axes[m][rp[0]]);
    hi1 = std::max(hi1, plan.axes[m][rp[0]]);
    lo2 = std::min(lo2, plan.axes[m][rp[1]]);
    hi2 = std::max(hi2, plan.axes[m][rp[1]]);
    out.path.emplace_back(plan.axes[m][rp[0]], plan.axes[m][rp[1]]);
  }
  const double res = std::max(out.resolution_rad, deg2rad(0.5));
  out.resolution_rad = res;
  const double pad = deg2rad(40.0);
  out.i1_min = std::max(static_cast<int>(std::floor((lo1 - pad) / res)),
                        static_cast<int>(std::ceil(space_.i1_min() * space_.options().resolution_rad / res)));
  out.i1_max = std::min(static_cast<int>(std::ceil((hi1 + pad) / res)),
                        static_cast<int>(std::floor(space_.i1_max() * space_.options().resolution_rad / res)));
  out.i2_min = std::max(static_cast<int>(std::floor((lo2 - pad) / res)),
                        static_cast<int>(std::ceil(space_.i2_min() * space_.options().resolution_rad / res)));
  out.i2_max = std::min(static_cast<int>(std::ceil((hi2 + pad) / res)),
                        static_cast<int>(std::floor(space_.i2_max() * space_.options().resolution_rad / res)));
  const int n1 = out.i1_max - out.i1_min + 1, n2 = out.i2_max - out.i2_min + 1;
  out.status.assign(static_cast<size_t>(std::max(0, n1 * n2)), Status::Feasible);
  // Orientation is judged with at least half a picture cell of slack so the picture is readable at cone 0.
  cspace::Options o = space_.options();
  o.cone_rad = std::max(o.cone_rad, 0.75 * res);
  const cspace::Space pic(kin_, nullptr, nullptr, o);
  geom::QueryWorkspace ws;
  cspace::Counters dummy;
  const std::size_t npts = rep.last_move - rep.first_move + 1;
  const std::size_t step = std::max<std::size_t>(1, npts / std::max<std::size_t>(1, max_points));
  for (std::size_t m = rep.first_move; m <= rep.last_move; m += step) {
    const kin::Posed cl{program.moves[m].tip_in_part_mm, program.moves[m].axis_in_part.normalized()};
    for (int b = 0; b < n2; ++b)
      for (int a = 0; a < n1; ++a) {
        auto& st = out.status[static_cast<size_t>(b) * static_cast<size_t>(n1) + static_cast<size_t>(a)];
        if (st != Status::Feasible) continue;
        Cell c;
        c.r1 = (out.i1_min + a) * res;
        c.r2 = (out.i2_min + b) * res;
        if (!pic.in_cone(cl, c.r1, c.r2, &c.orient_err)) {
          st = Status::Orientation;
          continue;
        }
        space_.evaluate(cl, c, ws, dummy);
        st = c.status;
      }
  }
  return out;
}

}  // namespace cscam::plan
