#pragma once
/// @file
/// Windowed planning of long programs (issue 11, part 3): the program is planned in windows of N moves, each
/// window starting at the rotaries the previous one ended at (Options::start_rotaries), so that the planner's
/// per-point data (cell lists, caches) is bounded by the window and the result is continuous at the joins.
#include <cstddef>
#include <memory>

#include "cscam/cl/program.hpp"
#include "cscam/plan/plan.hpp"

namespace cscam::plan {

/// How plan_windowed cuts a program.
struct WindowOptions {
  /// Moves per window; 0: automatic: `auto_window` moves per window above `auto_above` moves; up to that, one window
  /// unless the points' cell lists together would exceed `cell_budget` cells, in which case windows holding at most
  /// that many (the lists are the planner's memory: about 150 bytes a cell, thousands per point near a singular axis
  /// with a wide cone).
  std::size_t window = 0;
  std::size_t auto_above = 50000;
  std::size_t auto_window = 1000;
  std::size_t cell_budget = 4000000;
};

/// The window size plan_windowed uses for a program of `moves` moves (0: one window, the planner as is).
[[nodiscard]] std::size_t effective_window(std::size_t moves, const WindowOptions& w);

/// The windows [first, last] (inclusive move indices) plan_windowed plans: consecutive windows share one move (the
/// last of one is the first of the next, pinned there). A cut falls, where one exists in the second half of a window,
/// at the end of a segment (the move before a rapid), so that whole segments stay in one window; otherwise inside a
/// segment at a feed move.
[[nodiscard]] std::vector<std::pair<std::size_t, std::size_t>> windows_of(const cl::Program& program,
                                                                          std::size_t window);

/// As windows_of, but each window holds moves whose costs (`cost[m]` for move m, the window's pinned first move not
/// counted) sum to at most `budget` (and at least one move after the pinned one); a segment end is preferred once
/// half the budget is used. windows_of(program, N) is this with every cost 1 and budget N.
[[nodiscard]] std::vector<std::pair<std::size_t, std::size_t>> windows_by_cost(const cl::Program& program,
                                                                               const std::vector<double>& cost,
                                                                               double budget);

/// The grid windows of the cyclic (or very wide) rotaries that `program` needs: its CL axes followed by the IK solution
/// nearest the last (every winding continuous, as a conventional post turns) give each such rotary's range; where
/// that range leaves the default +-cyclic_span_rad (twice that at cone 0), the window is the range widened by half a
/// turn and 20 deg each way (every primary angle a cone beside the singular axis can need), never narrower than the
/// default. Sets options.cyclic_window_rad for those axes only. Without it a
/// spiral that keeps turning C one way was unwound (retract, turn 720 deg, plunge) every second turn on a machine whose
/// C turns without end. plan_windowed plans again on these windows where its plan on the default grid unwinds a cyclic
/// rotary or finds no path, unless the caller set a window.
void fit_cyclic_windows(const kin::Kinematics& kin, const cl::Program& program, cspace::Options& options);

/// Plans `program` as Planner::run does, in windows of `w.window` moves (see WindowOptions). Each window is a
/// Planner::run on its moves; a window after the first starts with the previous window's last move pinned to the
/// rotaries chosen there, so no rotary jumps at a join, and every move between points is checked (swept) by exactly
/// one window. A segment split across windows is reported once, with the tier its stitched path actually satisfies
/// (both rotaries fixed, one fixed and the other monotonic, both monotonic, or shortest path). Counters, swept
/// results, warnings and replaced moves are merged; `seconds` and `peak_memory_mb` cover the whole run.
/// Throws InputError as Planner::run does (the CL line of the point that failed).
Plan plan_windowed(const machine::Machine& machine, const std::shared_ptr<const kin::Kinematics>& kinematics,
                   const geom::Scene* scene, const geom::ToolShape* tool, const Options& options,
                   const cl::Program& program, const WindowOptions& w = {}, const geom::Scene* head = nullptr);

}  // namespace cscam::plan
