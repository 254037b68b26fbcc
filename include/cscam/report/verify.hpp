#pragma once
/// @file
/// Back-simulation: read NC axis values, run forward kinematics inside every block, and compare the
/// tool tip and axis with the CL path.
#include <memory>
#include <nlohmann/json_fwd.hpp>
#include <string>

#include "cscam/cl/program.hpp"
#include "cscam/kin/kinematics.hpp"
#include "cscam/machine/machine.hpp"
#include "cscam/nc/reader.hpp"

namespace cscam::report {

struct VerifyOptions {
  double tip_tolerance_mm = 0.012;
  double axis_tolerance_deg = 0.35;
  /// Sample intervals per feed block (FK at k / n, k = 0..n) where the sampling is fixed: blocks on an arc, and
  /// kinematics without a motion bound (the XMINI's iterative FK, a PKM), or everywhere if !adaptive_samples.
  int samples_per_block = 8;
  /// Where the kinematics bounds a straight block's motion (kin::Kinematics::motion_bound), take as few sample
  /// intervals as keep that bound between samples within `bound_fraction` of each tolerance (at least 2, at most
  /// max_adaptive_samples), and add the bound to the reported deviations, so that they bound the whole
  /// interpolated move, not only its samples (docs/safety.md, "Sampling inside a block").
  bool adaptive_samples = true;
  double bound_fraction = 1.0 / 16;
  int max_adaptive_samples = 4096;
  /// Compare ball centres (tip + r axis) instead of tips when the CL tool is a ball mill: a planner that
  /// tilts a ball mill keeps the centre on the CL path and moves the tip.
  bool ball_centre = false;
  /// The cone (deg) a planned program's axes keep to the CL's. A CL feed move along its own tool axis (an approach or
  /// a retract) may then run along the planned axis instead, as the planner re-places it: its end point counts as
  /// reached within 2 d sin(cone / 2) more (d: the move's length).
  double cone_deg = 0.0;
};

struct VerifyResult {
  bool ok = false;
  std::string message;
  size_t feed_blocks = 0;
  size_t axial_blocks = 0;  ///< feed blocks that retract or plunge along the fixed tool axis (not compared)
  size_t samples = 0;
  double max_tip_deviation_mm = 0.0;
  int max_tip_nc_line = 0;
  int max_tip_cl_line = 0;
  double max_axis_deviation_deg = 0.0;
  int max_axis_nc_line = 0;
  /// Largest distance from a CL feed point to the NC path (beyond what the cone allows an axial approach or retract).
  double max_uncovered_cl_mm = 0.0;
  int max_uncovered_cl_line = 0;
  [[nodiscard]] nlohmann::json json() const;
  [[nodiscard]] std::string to_json() const;  ///< json().dump()
};

/// Verification options for a program posted with `tolerance_mm` / `axis_tolerance_deg` (0 or less: the
/// machine file's) and planned within a cone of `cone_deg` (0: the CL orientation): the post's tolerances
/// plus tol::kVerifySlackMm / kVerifySlackDeg; inside a cone the axis may deviate by the cone and a ball
/// mill's centre is what stays on the path.
VerifyOptions verify_options_for(const machine::Machine& machine, double tolerance_mm = 0.0,
                                 double axis_tolerance_deg = 0.0, double cone_deg = 0.0);

/// Whether an NC text uses tool-tip control (G43.4/G43.5, G234, M428, TRAORI, TCPM, M128, or our Cartesian
/// header): its linear words are then the tip in the part frame.
bool uses_tool_tip_control(const std::string& nc_text);

/// Reads an NC program for machine `m`: machine letters, or X Y Z for the tip under tool-tip control. Rotaries
/// written modulo 360 (post.rotary_output: shortest) are read the short way. Blocks in tilted work planes get
/// their machine axis values (resolve_work_planes, with the header's tool length); InputError where they cannot.
nc::Program read_for_machine(const std::string& nc_text, const std::string& name, const machine::Machine& m);
nc::Program read_file_for_machine(const std::string& path, const machine::Machine& m);

/// The view of a tool-tip-control program that verify needs: forward() maps the words (tip + rotary angles,
/// or a virtual wrist's, after kin::Traits) to the tool pose, as the control interpolates them. `vectors`: the
/// rotary slots hold a tool vector's gnomonic coordinates (resolve_tool_vectors).
std::unique_ptr<kin::Kinematics> tool_tip_kinematics(const kin::Kinematics& machine_kinematics, bool vectors = false);

/// Vector-form tool-tip control (G43.5 I J K, A3 B3 C3): puts into every block's rotary slots the tool vector's
/// gnomonic coordinates (x/z, y/z), in which the control's great-circle interpolation is a straight line.
/// Returns an empty string, or why a vector cannot be used (pointing down; `bad_line` set to its line).
std::string resolve_tool_vectors(nc::Program& nc, const kin::Kinematics& machine_kinematics, int* bad_line = nullptr);

/// Tilted work planes (nc::Block::plane: G68.2, CYCLE800, PLANE SPATIAL): replaces every plane block's
/// words by the machine axis values the control moves to. The rotaries are those positioned before the plane
/// (modal words); the tip is origin + R * words (a word not given keeps its plane coordinate, and at the plane's
/// start is where the machine is); the linear axes come from the kinematics at those rotaries. After a plane a
/// linear word not given keeps the machine position. Returns an empty string, or why a block cannot be resolved
/// (file:line: ..., `bad_line` set): the plane's Z is not the tool axis of the positioned rotaries (G53.1 / TURN
/// would turn them: not read), a rotary turns inside the plane, the position at the plane's start is unknown.
std::string resolve_work_planes(nc::Program& nc, const kin::Kinematics& machine_kinematics, int* bad_line = nullptr);
/// The same with machine `m`'s kinematics at the program's header tool length (else the machine default); throws
/// InputError where a block cannot be resolved. Nothing to do without work planes.
void resolve_work_planes(nc::Program& nc, const machine::Machine& m);

/// Compares the NC program (machine axis values) with the CL program through `kinematics`.
VerifyResult verify(const nc::Program& nc, const cl::Program& cl, const kin::Kinematics& kinematics,
                    const VerifyOptions& options);

}  // namespace cscam::report
