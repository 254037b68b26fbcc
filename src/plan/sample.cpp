// The C-space of a planned segment at a few of its CL points, for pictures.
#include <algorithm>
#include <cmath>
#include <limits>

#include "cscam/core/error.hpp"
#include "cscam/core/units.hpp"
#include "detail/search.hpp"

namespace cscam::plan {

SegmentSpace Planner::sample_segment(const cl::Program& program, const Plan& plan, std::size_t segment,
                                     std::size_t max_panels) const {
  CSCAM_CHECK(segment < plan.segments.size(), "segment index in range");
  CSCAM_CHECK(plan.axes.size() == program.moves.size(), "the plan is of this program");
  const SegmentReport& rep = plan.segments[segment];
  SegmentSpace out;
  out.segment = segment;
  out.first_line = rep.first_line;
  out.last_line = rep.last_line;
  out.points = rep.last_move - rep.first_move + 1;
  out.cone_rad = space_.options().cone_rad;
  const auto rp = kin_->rotary_pair();
  for (std::size_t m = rep.first_move; m <= rep.last_move; ++m)
    out.path.emplace_back(plan.axes[m][rp[0]], plan.axes[m][rp[1]]);
  // Evenly spaced points, the first and the last included.
  const std::size_t npanels = std::min(std::max<std::size_t>(1, max_panels), out.points);
  for (std::size_t i = 0; i < npanels; ++i) {
    SegmentSpace::Panel p;
    p.point = npanels == 1 ? 0
                           : static_cast<std::size_t>(std::lround(static_cast<double>(i) * (out.points - 1) /
                                                                  static_cast<double>(npanels - 1)));
    p.line = program.moves[rep.first_move + p.point].line;
    p.chosen = out.path[p.point];
    out.panels.push_back(std::move(p));
  }
  auto pose_of = [&](std::size_t point) {
    const cl::Move& mv = program.moves[rep.first_move + point];
    return kin::Posed{mv.tip_in_part_mm, mv.axis_in_part.normalized()};
  };
  // The window: the planned path and the cones of the shown points (orientation only, cheap), the cones at most
  // kReach beyond the path, clipped to the grid.
  constexpr double kInf = std::numeric_limits<double>::infinity();
  const double kReach = deg2rad(60.0), kPad = deg2rad(2.0);
  double plo[2] = {kInf, kInf}, phi[2] = {-kInf, -kInf};
  for (const auto& [r1, r2] : out.path) {
    plo[0] = std::min(plo[0], r1);
    phi[0] = std::max(phi[0], r1);
    plo[1] = std::min(plo[1], r2);
    phi[1] = std::max(phi[1], r2);
  }
  double lo[2] = {plo[0] - kPad, plo[1] - kPad}, hi[2] = {phi[0] + kPad, phi[1] + kPad};
  const double grid = space_.options().resolution_rad;
  {
    cspace::Options o = space_.options();
    o.resolution_rad = std::max(grid, deg2rad(0.5));
    o.cone_rad = std::max(o.cone_rad, 0.75 * o.resolution_rad);
    const cspace::Space cones(kin_, nullptr, nullptr, o);
    cspace::Counters ignored;
    for (const auto& p : out.panels) {
      std::vector<cspace::Cell> cells;
      cones.enumerate(pose_of(p.point), cells, 200000, ignored);
      for (const cspace::Cell& c : cells) {
        const double r[2] = {c.r1, c.r2};
        for (int x = 0; x < 2; ++x) {
          lo[x] = std::min(lo[x], std::max(r[x], plo[x] - kReach));
          hi[x] = std::max(hi[x], std::min(r[x], phi[x] + kReach));
        }
      }
    }
  }
  // Picture cells per rotary: the planner's resolution, at least 0.5 deg, coarser where the window would need more
  // than kMaxCells (the file stays small; a panel is a picture, not the planner's data).
  constexpr int kMaxCells = 64;
  const double res1 = std::max({grid, deg2rad(0.5), (hi[0] - lo[0]) / kMaxCells});
  const double res2 = std::max({grid, deg2rad(0.5), (hi[1] - lo[1]) / kMaxCells});
  out.resolution1_rad = res1;
  out.resolution2_rad = res2;
  out.i1_min =
      std::max(static_cast<int>(std::floor(lo[0] / res1)), static_cast<int>(std::ceil(space_.i1_min() * grid / res1)));
  out.i1_max =
      std::min(static_cast<int>(std::ceil(hi[0] / res1)), static_cast<int>(std::floor(space_.i1_max() * grid / res1)));
  out.i2_min =
      std::max(static_cast<int>(std::floor(lo[1] / res2)), static_cast<int>(std::ceil(space_.i2_min() * grid / res2)));
  out.i2_max =
      std::min(static_cast<int>(std::ceil(hi[1] / res2)), static_cast<int>(std::floor(space_.i2_max() * grid / res2)));
  const int n1 = std::max(0, out.width()), n2 = std::max(0, out.height());
  // Orientation is judged with at least 0.75 picture cells of slack so the picture is readable at cone 0.
  cspace::Options o = space_.options();
  o.cone_rad = std::max(o.cone_rad, 0.75 * std::max(res1, res2));
  const cspace::Space pic(kin_, nullptr, nullptr, o);
  cspace::Counters ignored;  // pictures are not part of the plan's counts
  detail::parallel_items(out.panels.size(), ignored, [&](std::size_t i, geom::QueryWorkspace& ws, cspace::Counters& c) {
    SegmentSpace::Panel& p = out.panels[i];
    const kin::Posed cl = pose_of(p.point);
    p.status.assign(static_cast<std::size_t>(n1) * static_cast<std::size_t>(n2), cspace::Status::Orientation);
    for (int b = 0; b < n2; ++b)
      for (int a = 0; a < n1; ++a) {
        cspace::Cell cell;
        cell.r1 = (out.i1_min + a) * res1;
        cell.r2 = (out.i2_min + b) * res2;
        if (!pic.in_cone(cl, cell.r1, cell.r2, &cell.orient_err)) continue;
        space_.evaluate(cl, cell, ws, c);
        p.status[static_cast<std::size_t>(b) * static_cast<std::size_t>(n1) + static_cast<std::size_t>(a)] =
            cell.status;
      }
    // The plan's own cell, evaluated where it is (not at the picture cell's centre): the picture cell holding it
    // shows what the plan met there.
    cspace::Cell chosen;
    chosen.r1 = p.chosen.first;
    chosen.r2 = p.chosen.second;
    if (pic.in_cone(cl, chosen.r1, chosen.r2, &chosen.orient_err))
      space_.evaluate(cl, chosen, ws, c);
    else
      chosen.status = cspace::Status::Orientation;
    p.chosen_status = chosen.status;
    const int a = out.i1_of(chosen.r1) - out.i1_min, b = out.i2_of(chosen.r2) - out.i2_min;
    if (a >= 0 && a < n1 && b >= 0 && b < n2)
      p.status[static_cast<std::size_t>(b) * static_cast<std::size_t>(n1) + static_cast<std::size_t>(a)] =
          chosen.status;
  });
  return out;
}

}  // namespace cscam::plan
