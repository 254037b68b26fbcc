#pragma once
/// @file
/// Machine definition files (YAML): the kinematic model, axis limits and feeds, post settings, geometry.
#include <array>
#include <functional>
#include <limits>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "cscam/core/error.hpp"
#include "cscam/kin/kinematics.hpp"
#include "cscam/kin/serial.hpp"

namespace cscam::machine {

/// How the post writes programs for this machine.
struct PostSettings {
  std::string dialect = "linuxcnc";    ///< linuxcnc | fanuc | xmini-joint | ...
  bool tcp = false;                    ///< true: the control does the kinematics (G43.4 / TCPM)
  std::array<std::string, 5> letters;  ///< G-code word letter of each axis
  int decimals_linear = 4;
  int decimals_rotary = 4;
  double tolerance_mm = 0.01;       ///< linearisation chord tolerance of the tip
  double axis_tolerance_deg = 0.3;  ///< linearisation tolerance of the tool axis
  double safe_z_mm =
      std::numeric_limits<double>::quiet_NaN();  ///< machine Z of the safe retract plane; NaN: the Z limit
  std::string start_branch = "nearest_home";     ///< nearest_home | positive:<axis> | negative:<axis>
  /// start: the start_branch preference picks the first solution, then the nearest one is followed;
  /// always: the preference applies at every point (what simple posts do: they flip at the singularity).
  std::string branch_rule = "start";
  /// What the post does where the tool axis passes through or near the singular direction (parallel to
  /// the primary rotary) and where a branch rule or a rotary limit forces a flip or an unwind.
  struct Singularity {
    /// auto: turn in place when the joint move keeps the tip and axis within tolerance (at the singular
    /// point itself), else retract along the tool axis, turn and plunge; retract: always the latter;
    /// refuse: an error naming the CL point.
    std::string flip = "auto";
    double retract_mm = 10.0;  ///< how far the tip leaves along the tool axis before turning
  } singularity;
  std::string program_name = "CSCAM";
  /// Tool-tip control form: angles (rotary words: G43.4, G234, TRAORI ORIAXES, TCPM) or vectors (G43.5 I J K,
  /// Siemens A3 B3 C3).
  std::string tcp_form = "angles";
  std::string work_offset = "G54";  ///< G54..G59 or G54.1 Pn; empty ("none" in the file): none written
  int program_number = 1;           ///< O-number (fanuc, haas)
  bool sequence_numbers = false;    ///< N words on every block
  int sequence_step = 10;
  bool inch = false;  ///< G20 output: linear words and feeds in inches
  /// Rotary clamp / unclamp M-codes per rotary axis name (e.g. a: [M10, M11]), written around indexed (3+2)
  /// moves: clamped once positioned for a stretch of feed moves in which the axis does not turn.
  std::map<std::string, std::array<std::string, 2>> clamp;
  /// absolute: rotary words are the axis positions; shortest: cyclic rotaries are written modulo 360 in
  /// [0, 360) and the control takes the short way (Siemens writes =DC()).
  std::string rotary_output = "absolute";
  bool home_rotaries = true;  ///< the end block turns the rotaries back to 0
  /// CL CIRCLE/ records as G2/G3 where the rotaries stay fixed and the arc lies in a machine XY, ZX or YZ plane
  /// (dialects with I J K arcs); false, another dialect or another arc: its points as linear blocks.
  bool arcs = true;
  /// machine: 3+2 stretches in machine coordinates (today's output); tilted: each stretch whose feeds keep the
  /// rotaries fixed (and not all at 0) is written in a tilted work plane (G68.2 / G254 / CYCLE800 / PLANE
  /// SPATIAL) whose Z is the tool axis; linuxcnc has none and keeps machine coordinates (docs/posts.md).
  std::string work_plane = "machine";
  /// Siemens CYCLE800's swivel data record (_TC): the name the control's kinematics for tilted planes is set up
  /// under (machine-specific; "TC1" is Siemens' usual first record).
  std::string swivel_record = "TC1";
};

/// Where a machine body sits in the kinematic structure.
enum class BodySide {
  Base,   ///< fixed to the machine frame (bed, column, trunnion supports)
  Table,  ///< carried by a table-side joint (cradle, platter): moves with the part's chain
  Head,   ///< carried by a head-side joint (spindle housing, fork): moves with the tool
};

/// The shape of a machine body.
enum class BodyShape { Box, Cylinder, Mesh };

/// A rigid piece of the machine (given in the machine frame with every axis at 0) for collision checking:
/// the tool, holder and head bodies are checked against the part, fixture and base/table bodies.
struct MachineBody {
  std::string name;
  int axis = -1;  ///< the joint whose link carries the body (index into Machine::axes); -1: the base
  BodySide side = BodySide::Base;
  BodyShape shape = BodyShape::Box;
  Eigen::Vector3d min_mm = Eigen::Vector3d::Zero(), max_mm = Eigen::Vector3d::Zero();  ///< Box
  Eigen::Vector3d from_mm = Eigen::Vector3d::Zero(), to_mm = Eigen::Vector3d::Zero();  ///< Cylinder end centres
  double diameter_mm = 0.0;                                                            ///< Cylinder
  std::string mesh;         ///< Mesh: absolute path (resolved against the machine file)
  double mesh_scale = 1.0;  ///< Mesh: multiply the file's coordinates by this to get mm
  std::string source;       ///< where the dimensions come from (data sheet, drawing, "estimated: why")
  SourceLoc where;          ///< the body's entry in the machine file, for messages
};

/// Optional meshes and tool-holder shapes used by collision checking.
struct GeometrySettings {
  std::vector<MachineBody> bodies;  ///< geometry.bodies
  std::string head_mesh;            ///< absolute path (resolved against the machine file)
  std::string table_mesh;
  double holder_diameter_mm = 0.0;
  double holder_length_mm = 0.0;
  double spindle_diameter_mm = 0.0;
  double spindle_length_mm = 0.0;
};

/// The kinds of kinematic model a machine file can name.
enum class ModelKind { Serial, Xmini };

/// A machine definition. Immutable once loaded; cheap to copy (shares the kinematics).
struct Machine {
  std::string name;
  std::string file;  ///< the file it was read from
  std::string description;
  ModelKind kind = ModelKind::Serial;
  std::vector<kin::AxisInfo> axes;
  PostSettings post;
  GeometrySettings geometry;
  double default_tool_length_mm = 0.0;
  std::map<std::string, int> preferred_sign;          ///< per rotary axis name: +1 / -1 branch preference
  std::optional<kin::SerialGeometry<double>> serial;  ///< the serial model's parameters (kind Serial)
  /// Builds the model for a given tool length (gauge point to tip, mm). Other kinds plug in here.
  std::function<std::shared_ptr<const kin::Kinematics>(double)> make_kinematics;

  /// Where each key of the machine file is: "post.safe_z_mm", "axes[3].limits", ... -> file:line:column.
  std::map<std::string, SourceLoc> key_locations;

  /// Kinematics for the default tool length.
  [[nodiscard]] std::shared_ptr<const kin::Kinematics> kinematics() const {
    return make_kinematics(default_tool_length_mm);
  }
  [[nodiscard]] int axis_index(const std::string& axis_name) const;  ///< -1 if none
  /// The machine file's location of `key` (as in key_locations), or just the file when the key is not in it
  /// (a default). Errors about a machine-file value name this, not the CL file.
  [[nodiscard]] SourceLoc where(const std::string& key) const;
};

/// Reads and validates a machine file. Throws InputError naming the file, line and key on bad input.
Machine load(const std::string& path);
/// The same from text; `name` is used in messages and to resolve relative mesh paths.
Machine load_text(const std::string& yaml, const std::string& name);

/// Registers a loader for a `kinematics:` kind other than serial (e.g. the XMINI). The hook receives the
/// YAML root node (as an opaque pointer to YAML::Node) and fills the machine.
using ModelLoader = std::function<void(const void* yaml_root, Machine& m)>;
void register_model(const std::string& kind, ModelLoader loader);

}  // namespace cscam::machine
