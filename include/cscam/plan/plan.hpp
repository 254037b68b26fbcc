#pragma once
/// @file
/// The C-space tool-orientation planner (seed 002). For every continuous cutting segment it searches,
/// in this order: both rotaries fixed (3+2); one fixed and the other monotonic; both monotonic; and
/// finally the shortest path (least weighted rotary travel, bounded step per point).
#include <array>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "cscam/cl/program.hpp"
#include "cscam/cspace/cspace.hpp"
#include "cscam/machine/machine.hpp"
#include "cscam/plan/swept.hpp"

namespace cscam::plan {

enum class Tier { Fixed2 = 1, Fixed1 = 2, Monotonic = 3, Shortest = 4 };
const char* to_string(Tier t);

struct Options {
  cspace::Options cspace;
  /// Orientation cells the tiers search per point (closest to the CL axis first). A point whose kept cells are all
  /// infeasible gets every cell of its cone (never called infeasible on a truncated list); the summary counts
  /// those points.
  std::size_t max_cells_per_point = 4096;
  double max_step_rad = 0.0;               ///< tier 4 bound on the rotary step per point; 0: 20 x resolution
  double orientation_weight = 1e-3;        ///< tier 4: cost per rad of orientation error (tie-break only)
  int max_fixed_candidates = 256;          ///< tier 2: fixed values tried per axis
  /// Weights of the two rotaries' travel (tier 4 cost), per rad.
  double weight_primary = 1.0, weight_secondary = 1.0;
  /// Further axes whose reversals count (e.g. a PKM's actuated legs: on a parallel machine every Cartesian
  /// move moves every leg, and a leg reversal leaves a mark). After the tier search, a segment whose path
  /// reverses one of these is re-planned, if the cone allows, so that they move monotonically.
  std::vector<int> monotone_axes;
  double leg_step_cells = 4;   ///< largest per-point change of tilt (in tilt steps) of that re-plan
  double tilt_step_rad = 0.0;  ///< tilt grid of that re-plan (a disc of radius cone around the CL axis); 0: resolution
  /// Windowed planning (plan_windowed): move 0 keeps exactly these rotary values (primary, secondary, rad), where
  /// the previous window ended, so that the windows join without a rotary jump. Move 0 is then never re-placed as
  /// an approach, and the re-plans that could move it (leg re-plan) keep it.
  std::optional<std::array<double, 2>> start_rotaries;
  /// With start_rotaries: move 0 is the previous window's last move, already planned and never re-placed. False for
  /// the first window, where start_rotaries is an orientation chosen for the whole first segment (plan_windowed).
  bool start_is_join = true;
  /// Windowed planning: the program's last move is not the end of its segment (the next window continues it), so
  /// it is not re-placed as a retract.
  bool continues = false;
};

/// The reorientation into a segment.
enum class Reorientation : std::uint8_t { None, Clear, Collides, Uncertified };
const char* to_string(Reorientation r);

/// Why an earlier tier failed on a segment: the first point at which it became impossible.
struct TierFailure {
  Tier tier = Tier::Fixed2;
  std::size_t move = 0;  ///< index into Program::moves
  int line = 0;          ///< CL line of that point
  std::string reason;    ///< "orientation", "stroke", "collision" and details
};

struct SegmentReport {
  std::size_t first_move = 0, last_move = 0;
  int first_line = 0, last_line = 0;
  Tier tier = Tier::Shortest;
  std::vector<TierFailure> failures;  ///< one per tier tried before the one reached
  std::string description;            ///< e.g. "fixed B=-22.0 C=1.0"
  /// The reorientation into this segment (retract to the safe plane, rotate, position, plunge), as the post
  /// performs it, checked swept.
  Reorientation reorientation = Reorientation::None;
  std::string reorientation_detail;  ///< what collides (Reorientation::Collides / Uncertified)
  /// Moves of this segment (CL moves into its points, approach and retract included) that the swept check
  /// found colliding or could not certify; the first of them.
  std::size_t swept_collisions = 0, swept_uncertified = 0;
  int swept_first_line = 0;
  std::string swept_first_detail;
  /// Approach / retract moves re-placed along the chosen tool axis (the CL's ran along the CL axis).
  int approach_moves_replaced = 0;
  /// With Options::monotone_axes: "monotonic", or which axis still reverses, where, and why it cannot be avoided.
  std::string legs;
};

/// The plan: axis values for every CL move, and a CL program whose tips/axes are the planned ones
/// (ball-end: the ball centre is the CL's; the tip and axis follow the chosen orientation).
struct Plan {
  std::vector<kin::Axes> axes;
  cl::Program program;
  std::vector<SegmentReport> segments;
  cspace::Counters counters;
  SweptSummary swept;                   ///< the swept check of the planned program
  std::size_t points_beyond_cap = 0;    ///< points whose cells beyond max_cells_per_point had to be searched
  std::vector<std::size_t> replaced_moves;  ///< approach/retract moves re-placed along the chosen tool axis
  double seconds = 0.0;
  double peak_memory_mb = 0.0;  ///< the process's peak resident memory when the plan was done
  std::vector<std::string> warnings;
  std::string summary() const;
};

class Planner {
 public:
  /// `scene`/`tool` may be null (no collision checking); `head`: machine meshes moving with the spindle.
  /// All must outlive the planner.
  Planner(const machine::Machine& machine, std::shared_ptr<const kin::Kinematics> kinematics, const geom::Scene* scene,
          const geom::ToolShape* tool, Options options, const geom::Scene* head = nullptr);
  /// Plans a whole program. Throws InputError (CL line, point, the constraint that emptied the cells and
  /// the nearest feasible cell) when a point has no feasible cell.
  Plan run(const cl::Program& program) const;
  /// Samples the C-space of one planned segment on the full grid (for pictures; costs many queries).
  SegmentSpace sample_segment(const cl::Program& program, const Plan& plan, std::size_t segment,
                              std::size_t max_points = 24) const;

 private:
  /// Re-places move m (an approach into, or retract out of, move ref along ref's CL axis) along ref's chosen
  /// axis at the same distance, with ref's rotaries. False (nothing changed) when m is not such a move or the
  /// re-placed point breaks a limit.
  bool along_chosen_axis(const cl::Program& cl, Plan& plan, std::size_t m, std::size_t ref) const;

  const machine::Machine& machine_;
  std::shared_ptr<const kin::Kinematics> kin_;
  cspace::Space space_;
  Options opt_;
};

}  // namespace cscam::plan
