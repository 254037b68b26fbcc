#pragma once
/// @file
/// The C-space tool-orientation planner (seed 002). For every continuous cutting segment it searches,
/// in this order: both rotaries fixed (3+2); one fixed and the other monotonic; both monotonic; and
/// finally the shortest path (least weighted rotary travel, bounded step per point).
#include <array>
#include <cstdint>
#include <functional>
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
  double max_step_rad = 0.0;         ///< tier 4 bound on the rotary step per point; 0: 20 x resolution
  double orientation_weight = 1e-3;  ///< tier 4: cost per rad of orientation error (tie-break only)
  /// Tier 4: states its beam keeps per point at first. Where that beam dead-ends within the step bound, the search
  /// runs again with four times as many, up to kWidestBeam (only the widest may then step beyond the default bound).
  /// The cost is about proportional to the width; a narrower beam drops states that a shorter path needed (64 instead
  /// of 256: the hard benchmark 30 % faster with 0.8 % more rotary travel, but short random walks up to 10 % more).
  std::size_t beam_states = 256;
  static constexpr std::size_t kWidestBeam = 1024;
  int max_fixed_candidates = 256;  ///< tier 2: fixed values tried per axis
  /// Weights of the two rotaries' travel (tier 4 cost), per rad.
  double weight_primary = 1.0, weight_secondary = 1.0;
  /// Further axes whose reversals count (e.g. a PKM's actuated legs: on a parallel machine every Cartesian
  /// move moves every leg, and a leg reversal leaves a mark). After the tier search, a segment whose path
  /// reverses one of these is re-planned, if the cone allows, so that they move monotonically.
  std::vector<int> monotone_axes;
  double leg_step_cells = 4;   ///< largest per-point change of tilt (in tilt steps) of that re-plan
  double tilt_step_rad = 0.0;  ///< tilt grid of that re-plan (a disc of radius cone around the CL axis); 0: resolution
  /// Cone 0: whether the post can follow a transition that tracking cannot (a jump beside a singular orientation, or a
  /// limit in the way) from axis values q0 at pose p0 to q1 at p1. The CLI passes the post's own rule
  /// (post::can_follow), so that a plan never holds a move its post refuses. Unset: a jump is taken where tracking
  /// lands, and the gate judges the program.
  std::function<bool(const kin::Axes& q0, const kin::Posed& p0, const kin::Axes& q1, const kin::Posed& p1)> can_bridge;
  /// Windowed planning (plan_windowed): move 0 keeps exactly these rotary values (primary, secondary, rad), where
  /// the previous window ended, so that the windows join without a rotary jump. Move 0 is then never re-placed as
  /// an approach, and the re-plans that could move it (leg re-plan) keep it.
  std::optional<std::array<double, 2>> start_rotaries;
  /// Windowed planning, with `continues`: the program's last segment starts in this window and runs on into the
  /// next. Its first point takes these rotary values (primary, secondary, rad), an orientation plan_windowed found
  /// feasible along the whole segment, so that the windows can keep it fixed.
  std::optional<std::array<double, 2>> open_segment_rotaries;
  /// Windowed planning: the program's last move is not the end of its segment (the next window continues it), so
  /// it is not re-placed as a retract.
  bool continues = false;
};

/// The reorientation into a segment.
enum class Reorientation : std::uint8_t { None, Clear, Collides, Uncertified };
const char* to_string(Reorientation r);

/// What made a tier impossible at a point.
enum class FailureCause : std::uint8_t {
  Orientation,  ///< no cell of the tier's shape within the cone
  Stroke,       ///< the cells it needed break a limit
  Collision,    ///< the cells it needed collide (at the point, or on the move into it)
  Transition,   ///< feasible cells, but no allowed step (flip-free, within the step bound) from the previous point
};
const char* to_string(FailureCause c);
/// A cause and its detail as reports print them: "collision: holder hits part" (the cell causes), the detail alone
/// (Transition).
std::string failure_text(FailureCause cause, const std::string& detail);

/// Why an earlier tier failed on a segment: the first point at which it became impossible.
struct TierFailure {
  Tier tier = Tier::Fixed2;
  std::size_t move = 0;  ///< index into Program::moves
  int line = 0;          ///< CL line of that point
  FailureCause cause = FailureCause::Orientation;
  std::string detail;  ///< the broken limit, what collides, the best candidate
  [[nodiscard]] std::string reason() const { return failure_text(cause, detail); }
};

/// Whether the counted axes (Options::monotone_axes) move monotonically along a segment.
enum class Legs : std::uint8_t {
  NotCounted,       ///< no counted axes, or a segment of two points or fewer
  Monotonic,        ///< the tiers' path keeps them monotonic
  ReversalRemoved,  ///< cone 0: other IK branches remove the reversal
  TiltedMonotonic,  ///< a re-plan on a tilt grid inside the cone removes it
  Reverses,         ///< they reverse and no path within the cone avoids it
};
const char* to_string(Legs l);

struct LegReport {
  Legs state = Legs::NotCounted;
  std::string axes;  ///< names of the counted axes that reversed on the tiers' path ("U, V")
  int line = 0;      ///< CL line of the first reversal
  Eigen::Vector3d tip_mm = Eigen::Vector3d::Zero();  ///< tip of that CL point
  double max_tilt_rad = 0.0;  ///< TiltedMonotonic: largest tilt of the re-planned path from the CL axis
  int blocked_line = 0;       ///< Reverses: no monotonic path goes beyond this CL line
  std::string why;            ///< Reverses: what stops it there
  [[nodiscard]] bool monotonic() const {
    return state == Legs::Monotonic || state == Legs::ReversalRemoved || state == Legs::TiltedMonotonic;
  }
  /// The report text ("" when not counted).
  [[nodiscard]] std::string text() const;
};

struct SegmentReport {
  std::size_t first_move = 0, last_move = 0;
  int first_line = 0, last_line = 0;
  Tier tier = Tier::Shortest;
  /// Every move of the segment is a rapid (a retract, a traverse or an approach between cuts): it positions the tool
  /// and cuts nothing, so its tier says little (reported as positioning, not counted with the cutting segments).
  bool positioning = false;
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
  /// With Options::monotone_axes: monotonic, or which axis still reverses, where, and why it cannot be avoided.
  LegReport legs;
};

/// The plan: axis values for every CL move, and a CL program whose tips/axes are the planned ones
/// (ball-end: the ball centre is the CL's; the tip and axis follow the chosen orientation).
struct Plan {
  std::vector<kin::Axes> axes;
  cl::Program program;
  std::vector<SegmentReport> segments;
  cspace::Counters counters;
  SweptSummary swept;                       ///< the swept check of the planned program
  std::size_t points_beyond_cap = 0;        ///< points whose cells beyond max_cells_per_point had to be searched
  std::vector<std::size_t> replaced_moves;  ///< approach/retract moves re-placed along the chosen tool axis
  double seconds = 0.0;
  double peak_memory_mb = 0.0;  ///< the process's peak resident memory when the plan was done
  std::size_t windows = 1;      ///< windows the program was planned in (plan_windowed)
  std::string window_rule;      ///< how the windows were cut (empty: one window)
  std::vector<std::string> warnings;
  std::string summary() const;
  /// What a program posted from this plan is judged against: the CL `cl` it was planned from (whose axes the cone
  /// is around), with the approach/retract moves re-placed along the chosen axis taken from the plan.
  [[nodiscard]] cl::Program reference(const cl::Program& cl) const;
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
  /// The C-space of one planned segment at up to `max_panels` evenly spaced CL points (the first and the last
  /// included), each cell of a window around the planned path evaluated there, and the plan's own cell (for
  /// pictures; costs many queries, not counted in the plan's).
  SegmentSpace sample_segment(const cl::Program& program, const Plan& plan, std::size_t segment,
                              std::size_t max_panels = 12) const;

 private:
  const machine::Machine& machine_;
  std::shared_ptr<const kin::Kinematics> kin_;
  cspace::Space space_;
  Options opt_;
};

}  // namespace cscam::plan
