#pragma once
/// @file
/// The safety gate: every NC program is read back from its text and checked before it may reach disk.
///
/// The check is independent of the code that produced the program: it parses the G-code with the NC
/// reader, rebuilds the tool pose by forward kinematics (or, for tool-tip-control programs, from the
/// tip and tool-vector words, as the control would), and checks
///  - every block's axis values against the axis limits (and a PKM's passive joints, sampled inside);
///  - every feed block's axis velocities against the machine file's `max_feed`;
///  - the tip and tool-axis deviation from the CL path, sampled inside every feed block;
///  - optionally, rapid and reorientation moves against the part/fixture (a caller-supplied check).
/// A program that fails is never written: write_checked() throws an InputError naming the NC block and,
/// where known, the CL line. There is no option to bypass it.
#include <functional>
#include <string>
#include <vector>

#include "cscam/cl/program.hpp"
#include "cscam/kin/kinematics.hpp"
#include "cscam/machine/machine.hpp"
#include "cscam/nc/reader.hpp"
#include "cscam/report/verify.hpp"

namespace cscam::gate {

/// What the gate allows. Build it with options_for() so that the tolerances follow the post's.
struct Options {
  double tip_tolerance_mm = 0.012;  ///< post tolerance + printing slack
  double axis_tolerance_deg = 0.31;
  bool ball_centre = false;   ///< compare ball centres (a planner that tilts a ball mill keeps those)
  int samples_per_block = 8;  ///< FK samples inside every feed block
  double feed_slack = 1e-3;   ///< relative slack on max_feed (printed F words are rounded)
  /// Largest joint step between collision samples inside every move (mm or deg).
  double collision_step = 0.5;
  /// A collision check of a machine configuration against the scene (part, fixture, the machine's own bodies):
  /// returns a description of the collision, or an empty string when free. `whole_tool`: inside a rapid move the
  /// cutting end counts too (a feed move's cutting end is in contact with the material by design).
  using CollisionCheck = std::function<std::string(const kin::Axes&, bool whole_tool)>;
  /// Inside a rapid, poses whose tip is within this distance of either end are checked as cuts (mm): there the
  /// tool leaves or reaches the material where the CL put it, and the rapid check bounds the cutting end by a
  /// cylinder, coarser than a ball.
  double rapid_contact_mm = 10.0;
  /// Optional: makes a collision check for one worker (each keeps its own query workspace, so that the moves are
  /// checked in parallel). Applied inside every move, rapid or feed.
  /// The argument is the tool in the spindle, as nc::Block::tool_changes counts it (0: before the first tool change;
  /// k: the tool the program's k-th change loads): a program with several tools is checked with each one's shape.
  std::function<CollisionCheck(int tool_changes)> make_collision;
};

/// Options for a program posted with `tolerance_mm` / `axis_tolerance_deg` (0: the machine file's)
/// and planned within a cone of `cone_deg` (0: the CL orientation exactly).
Options options_for(const machine::Machine& machine, double tolerance_mm, double axis_tolerance_deg, double cone_deg);

/// One broken rule.
struct Violation {
  enum class Kind { Limit, Velocity, Deviation, Coverage, Collision, Unreadable } kind = Kind::Limit;
  int nc_line = 0;  ///< 0 when not tied to one block
  int cl_line = 0;  ///< 0 when unknown
  std::string message;
};

/// The gate's verdict, with statistics (like a solver summary).
struct Summary {
  bool ok = false;
  std::string message;  ///< one line: "passed: ..." or the first violation
  std::vector<Violation> violations;
  bool tool_tip_control = false;  ///< the program was checked as TCP/Cartesian (tip words)
  std::size_t blocks = 0;
  std::size_t limit_checks = 0;
  double max_velocity_ratio = 0.0;  ///< largest axis velocity / max_feed over feed blocks
  int max_velocity_nc_line = 0;
  std::size_t collision_checks = 0;
  report::VerifyResult deviation;  ///< the tip/axis comparison with the CL path
};

/// Checks `nc_text` (named `nc_name` in messages) against the CL program and the machine.
/// `cl_line_of_nc_line`, when given, maps an NC line number (1-based index) to the CL line it came from.
/// `read_back`, when given, receives the program as the gate read it back (report::read_for_machine, with tool
/// vectors resolved), so that a caller wanting its statistics need not read a million blocks again; it is left
/// as it was when the text cannot be read.
Summary check(const std::string& nc_text, const std::string& nc_name, const cl::Program& cl,
              const machine::Machine& machine, const kin::Kinematics& kinematics, const Options& options,
              const std::vector<int>* cl_line_of_nc_line = nullptr, nc::Program* read_back = nullptr);

/// Checks, then writes `nc_text` to `path` atomically. Throws InputError naming the NC file, the block
/// and the CL line when the check fails; nothing is written then. `read_back` as for check().
Summary write_checked(const std::string& path, const std::string& nc_text, const cl::Program& cl,
                      const machine::Machine& machine, const kin::Kinematics& kinematics, const Options& options,
                      const std::vector<int>* cl_line_of_nc_line = nullptr, nc::Program* read_back = nullptr);

}  // namespace cscam::gate
