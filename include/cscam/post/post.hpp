#pragma once
/// @file
/// Posts: turn a CL program plus the chosen axis values per CL point into NC text for one machine.
/// The post linearises rotary motion (inserting points until the real tip path stays within the
/// tolerance of the straight CL segment), chooses G93/G94 feed modes, and refuses to leave the limits.
#include <iosfwd>
#include <optional>
#include <string>
#include <vector>

#include "cscam/cl/program.hpp"
#include "cscam/kin/kinematics.hpp"
#include "cscam/machine/machine.hpp"

namespace cscam::post {

/// Per-run options; unset fields fall back to the machine file's post settings.
struct Options {
  std::string dialect;              ///< empty: the machine's
  double tolerance_mm = 0.0;        ///< 0: the machine's
  double axis_tolerance_deg = 0.0;  ///< 0: the machine's
  bool linearise = true;
  std::optional<bool> tcp;         ///< tool-tip control on/off; unset: the machine's post.tcp
  std::string work_plane;          ///< "tilted" or "machine" for 3+2 stretches; empty: the machine's post.work_plane
  int max_subdivision_depth = 14;  ///< at most 2^depth pieces per CL segment
  std::string source_name;         ///< shown in the header comment
  std::string strategy = "conventional";
  double tool_length_mm = 0.0;  ///< recorded in the header so that verify can rebuild the same model
  /// The point whose path must stay within the tolerance: tip + control_offset_mm * axis. A planner that
  /// tilts a ball mill keeps the ball centre on the CL path, so it posts with the ball radius here.
  double control_offset_mm = 0.0;
  /// A planned program's cone (deg) and the CL its orientations were chosen from (the same moves, in the same
  /// order; the caller keeps it alive). Between two points the post then accepts any tool axis within the cone
  /// (plus the axis tolerance) of the CL's interpolated axis, as the gate does, besides one within the axis
  /// tolerance of the planned axes' interpolation.
  double cone_deg = 0.0;
  const cl::Program* cone_reference = nullptr;
};

/// What the post did.
struct Summary {
  size_t blocks = 0;  ///< motion blocks written
  size_t cl_points = 0;
  size_t inserted_points = 0;  ///< points added by linearisation
  size_t ik_calls = 0;
  double max_checked_tip_deviation_mm = 0.0;
  std::size_t reorientations = 0;  ///< branch flips or unwinds done with the tip held in place
  std::size_t retracts = 0;        ///< branch flips or unwinds done by retract, rotate and plunge
  std::size_t capped_blocks = 0;   ///< feed blocks slowed so that no axis exceeds its max_feed
  /// Corners where the control's blend would take the rotaries (and so the tip) past the tolerance: given a smaller
  /// blend tolerance, or exact path (LinuxCNC: docs/linuxcnc.md).
  std::size_t narrowed_corners = 0;
  std::size_t exact_corners = 0;
  std::size_t arc_blocks = 0;   ///< CL arcs written as one G2/G3 block
  std::size_t work_planes = 0;  ///< 3+2 stretches written in a tilted work plane (post.work_plane: tilted)
  std::vector<std::string> warnings;
  /// For every NC line (1-based index; index 0 unused) the CL line it came from (0: header, footer).
  std::vector<int> cl_line_of_nc_line;
};

/// The conventional strategy a typical post uses: the machine's preferred branch at the start, then
/// for every CL point the IK solution nearest (in rotary travel) to the previous one, within limits.
/// Throws InputError naming the CL line when a point has no solution inside the limits.
std::vector<kin::Axes> conventional_axes(const cl::Program& program, const machine::Machine& machine,
                                         const kin::Kinematics& kinematics);

/// Writes the NC program. `axes[i]` are the axis values chosen for `program.moves[i]`.
/// Throws InputError (naming the CL line) if any block would leave an axis limit.
void write_nc(std::ostream& out, const cl::Program& program, const machine::Machine& machine,
              const kin::Kinematics& kinematics, const std::vector<kin::Axes>& axes, const Options& options,
              Summary& summary);

/// Whether the post, writing with `options`, can follow the move from axis values q0 at pose p0 to q1 at p1 (one CL
/// segment) within its tolerances, by its own linearisation rule: interpolated rotaries where they keep the tool axis
/// within tolerance, else the IK branch followed without a flip. The planner asks it of a transition that tracking
/// cannot follow (plan::Options::can_bridge).
bool can_follow(const kin::Kinematics& kinematics, const machine::Machine& machine, const Options& options,
                const kin::Posed& p0, const kin::Axes& q0, const kin::Posed& p1, const kin::Axes& q1);

/// The dialects this build knows.
std::vector<std::string> dialects();

/// Tool length (gauge to tip, mm) to use for a program: the option if > 0, else the machine default.
double tool_length_for(const machine::Machine& machine, double option_mm);

/// The same for a CL program. On a machine whose head carries a rotary the tool length changes the kinematics:
/// without the option it comes from the CL (the first tool's TLDATA/CUTTER length) and `note` says so; when the CL
/// has none either, the machine default is used and `note` is a warning saying so (never silently).
double tool_length_for(const machine::Machine& machine, double option_mm, const cl::Program& program,
                       std::string& note);

}  // namespace cscam::post
