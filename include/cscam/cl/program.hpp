#pragma once
/// @file
/// A cutter-location program: what a CAM main processor asks the machine to do, independent of any machine.
#include <Eigen/Core>
#include <optional>
#include <string>
#include <vector>

#include "cscam/core/error.hpp"
#include "cscam/core/units.hpp"

namespace cscam::cl {

/// A cutting tool, from CUTTER/ or TLDATA/ (and LOADTL/ or LOAD/TOOL for the number).
struct Tool {
  int number = 0;
  std::string name;
  double diameter_mm = 0.0;
  double corner_radius_mm = 0.0;  ///< diameter/2 for a ball mill
  double length_mm = 0.0;         ///< flute/overall length as the CL gives it (0 if unknown)
  int length_register = -1;       ///< LOAD/TOOL,n,ADJUST,h: the length offset register (-1: the tool number)

  /// A ball-end mill: the corner radius equals the radius (then the ball centre is tip + r * axis).
  [[nodiscard]] bool is_ball() const {
    return diameter_mm > 0 && std::abs(corner_radius_mm - 0.5 * diameter_mm) < 1e-6 * diameter_mm;
  }
  /// The same cutting shape as `o` (diameter, corner radius, length): what a collision check or a planner sees.
  [[nodiscard]] bool same_shape(const Tool& o) const {
    return diameter_mm == o.diameter_mm && corner_radius_mm == o.corner_radius_mm && length_mm == o.length_mm;
  }
};

enum class MotionKind { Rapid, Feed };

/// One CL point. Positions are the tool tip in the part (CL) frame, in mm; the axis is a unit
/// vector from the tip toward the spindle.
struct Move {
  Eigen::Vector3d tip_in_part_mm = Eigen::Vector3d::Zero();
  Eigen::Vector3d axis_in_part = Eigen::Vector3d::UnitZ();
  MotionKind kind = MotionKind::Feed;
  double feed_mm_per_min = 0.0;  ///< 0 for rapids
  int line = 0;                  ///< CL line this point comes from (arc points: the CIRCLE/ line)
  int tool_index = -1;           ///< index into Program::tools, -1 before any tool
  bool from_arc = false;         ///< an intermediate point generated from a CIRCLE/ record
  int arc_index = -1;  ///< index into Program::arcs for the points of a CIRCLE/ and the GOTO that ends it; -1 else
};

/// A CIRCLE/ record as the CL gave it: the arc runs from the move before its first point to its end GOTO.
struct Arc {
  Eigen::Vector3d centre_in_part_mm = Eigen::Vector3d::Zero();
  Eigen::Vector3d normal_in_part = Eigen::Vector3d::UnitZ();  ///< unit; the motion is counter-clockwise about it
  double radius_mm = 0.0;
  double sweep_rad = 0.0;    ///< angle travelled, (0, 2 pi]
  int line = 0;              ///< the CIRCLE/ line
  std::size_t end_move = 0;  ///< index of the end GOTO in Program::moves (the start is the move before the first point)
};

/// A non-motion event, attached to the move that follows it.
struct Event {
  enum class Kind {
    ToolChange,
    SpindleOn,
    SpindleOff,
    CoolantOn,
    CoolantOff,
    Comment,
    OperationStart,
    Stop,   ///< STOP (text "STOP") or OPSTOP (text "OPSTOP")
    Dwell,  ///< DELAY/seconds
    Insert  ///< INSERT/text: passed to the NC program as it is
  };
  Kind kind = Kind::Comment;
  std::size_t before_move = 0;  ///< index of the first move after the event
  int line = 0;
  int tool_index = -1;       ///< ToolChange
  double spindle_rpm = 0.0;  ///< SpindleOn
  bool clockwise = true;     ///< SpindleOn
  std::string text;          ///< Comment / OperationStart name / coolant mode (FLOOD, MIST, ...) / Insert text
  double seconds = 0.0;      ///< Dwell
};

struct Warning {
  SourceLoc where;
  std::string message;
};

/// A whole CL file.
struct Program {
  std::string file;
  std::string part_name;  ///< PARTNO / TOOL PATH name
  LengthUnit source_units = LengthUnit::Millimetre;
  bool multax = false;                              ///< the file declared MULTAX or gave i,j,k on a GOTO
  std::optional<Eigen::Matrix<double, 3, 4>> msys;  ///< NX MSYS (origin, x axis, y axis), mm
  std::vector<Tool> tools;
  std::vector<Move> moves;
  std::vector<Arc> arcs;      ///< CIRCLE/ records turned into points (Move::arc_index)
  std::vector<Event> events;  ///< ordered by before_move, then by line
  std::vector<Warning> warnings;
};

/// Options of the reader.
struct ReadOptions {
  /// Forces the input unit. Unset: UNITS/ decides, else FEDRAT/IPM vs MMPM, else mm.
  std::optional<LengthUnit> units;
  /// Chord tolerance for turning CIRCLE/ records into points, mm.
  double arc_tolerance_mm = 0.001;
  /// Feed (mm/min) for feed moves that have no feed rate: none in the file, or before its first FEDRAT/.
  /// Applied with a warning; must be positive. The CLI's `--default-feed`.
  std::optional<double> default_feed_mm_per_min;
  /// A feed move without a feed rate (and no default_feed_mm_per_min) is an error naming its line. The commands
  /// that write NC turn this on; reading a CL file only to compare geometry with it (verify) does not need feeds.
  bool require_feed = false;
};

/// Reads APT/CLDATA (NX CLSF, ISO 4343, CATIA flavours) or the CSV form x,y,z,i,j,k[,feed].
/// The format is detected from the content. Throws InputError with file:line:column on malformed input, and
/// "no motion records" for an empty file, a binary file or a file without a single motion.
/// Warns (Program::warnings) when the length unit is assumed: no UNITS/, no FEDRAT/ naming IPM or MMPM, no
/// ReadOptions::units.
Program read_file(const std::string& path, const ReadOptions& options = {});
/// The same for text already in memory; `name` is used in messages.
Program read_text(const std::string& text, const std::string& name, const ReadOptions& options = {});

}  // namespace cscam::cl
