#pragma once
/// @file
/// Reads NC programs back into axis values per motion block: ISO G-code (ours; Fanuc, Haas, LinuxCNC), Siemens
/// Sinumerik (identifiers such as TRAORI, `X=`, `C=DC()`, A3/B3/C3 vectors, `;` comments) and Heidenhain
/// conversational (`L X+1 Y-2 FMAX`, detected by its BEGIN PGM line). Tilted work planes (G68.2 / G69, CYCLE800,
/// PLANE SPATIAL / PLANE RESET) are read as frames (Block::plane); their words become machine axis values with the
/// kinematics (report::resolve_work_planes). Haas G254 / G255 (dynamic work offset) keep the words as they are.
#include <Eigen/Core>
#include <array>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "cscam/core/units.hpp"

namespace cscam::nc {

/// What the reader needs to know about the machine's axes (letters and which ones are rotary).
struct AxisLetters {
  std::array<char, 5> letter{};
  std::array<bool, 5> rotary{};
  /// Rotary written modulo 360 and reached the short way (Siemens =DC() says so itself): the value read is
  /// the one nearest to the previous.
  std::array<bool, 5> modulo{};
};

enum class Motion { Rapid, Linear, ArcCW, ArcCCW };

/// The circle of a G2/G3 block, in machine coordinates (mm). The plane's axes (u, v) and its normal w are
/// (X, Y, Z) for G17, (Z, X, Y) for G18 and (Y, Z, X) for G19 (RS274: counter-clockwise seen from +w); the
/// motion along w and of every other axis is linear (a helix).
struct ArcGeometry {
  int plane = 17;             ///< 17, 18 or 19
  std::array<int, 3> slot{};  ///< axis slots of u, v, w
  double centre_u = 0.0, centre_v = 0.0;
  double start_angle_rad = 0.0;                       ///< of the start point about the centre, from +u toward +v
  double sweep_rad = 0.0;                             ///< signed: > 0 counter-clockwise (G3), < 0 clockwise (G2)
  double start_radius_mm = 0.0, end_radius_mm = 0.0;  ///< unequal for a malformed arc: read as a spiral
  /// An arc of a tilted work plane resolved into machine axes (report::resolve_work_planes): its plane is no machine
  /// plane. Its circle is centre + r (cos a u + sin a v) in the machine's X Y Z (slot = the X, Y, Z slots;
  /// centre_u/v unused); motion along u x v and of every other axis is linear.
  struct Tilted {
    Eigen::Vector3d centre_mm = Eigen::Vector3d::Zero();                         ///< machine X Y Z, on the arc's axis
    Eigen::Vector3d u = Eigen::Vector3d::UnitX(), v = Eigen::Vector3d::UnitY();  ///< unit, machine X Y Z
  };
  std::optional<Tilted> tilted;
};

/// A tilted work plane in force: the linear words of a block in it are the tip in this frame (part frame:
/// origin + R_part_plane * words), the rotaries stay where they were positioned before it.
struct WorkPlane {
  Eigen::Matrix3d R_part_plane = Eigen::Matrix3d::Identity();  ///< columns: the plane's X, Y, Z in the part frame
  Eigen::Vector3d origin_in_part_mm = Eigen::Vector3d::Zero();
  int line = 0;      ///< where it was switched on (a new plane, even an equal one, starts a new frame)
  std::string form;  ///< "G68.2", "CYCLE800", "PLANE SPATIAL" (for messages)
};

/// One motion block with the full modal axis state after it. Linear axes in mm, rotary in radians.
/// Kept small (128 bytes): a million-block program is a million of these, so the rare parts (an arc, a tilted
/// work plane) are shared, immutable and out of line, and the members are ordered to pack.
struct Block {
  int line = 0;
  Motion motion = Motion::Linear;
  double feed = 0.0;  ///< F word in force (mm/min, or 1/min in G93)
  std::array<double, 5> axes{};
  /// Tool vector (part frame) of tool-tip control in vector form (G43.5 I J K, Siemens A3 B3 C3), modal.
  std::array<double, 3> tool_vector{0.0, 0.0, 1.0};
  std::shared_ptr<const ArcGeometry> arc;  ///< G2/G3: the circle from the previous block's position to this one's
  /// The work plane in force (one object for every block in it): the linear slots whose `words` are set hold the
  /// plane coordinates (mm) until report::resolve_work_planes replaces them by machine values and clears this.
  std::shared_ptr<const WorkPlane> plane;
  std::array<bool, 5> known{};  ///< the axis has been programmed at least once so far
  std::array<bool, 5> words{};  ///< the axis word appears in this block
  bool inverse_time = false;    ///< G93 active
  bool has_vector = false;      ///< a tool vector has been programmed so far
  /// Written while tool-tip control was on (G43.4 ... G49, TRAORI ... TRAFOOF, ...): its linear words are the tip
  /// in the part frame. A program that switches TCP off for tilted planes has both kinds; report::resolve_work_planes
  /// turns the machine-word blocks into tip words.
  bool tcp = false;
  /// Tool changes (M6, TOOL CALL) at or before this block: which of the program's tools is in the spindle, counted in
  /// the order the program loads them (0: before the first change).
  std::uint16_t tool_changes = 0;  ///< (16 bits: Block stays within two cache lines; saturates at 65535)
};

/// The axis values at parameter t in [0, 1] of block `b` travelled from `start` (the previous block's axes):
/// along its arc for G2/G3, else straight.
std::array<double, 5> point_on(const std::array<double, 5>& start, const Block& b, double t);
/// The length of the linear axes' path of block `b` from `start` (mm): the helix of an arc, else the chord.
double linear_path_mm(const std::array<double, 5>& start, const Block& b, const std::array<bool, 5>& rotary);
/// How far each axis moves at most, as the control's speed sees it, on arc block `b` from `start`: for the axes of
/// the arc's plane its length in that plane (times the axis' share of the plane's two directions in a tilted plane),
/// plus their share of the motion along the normal there; the chord for every other axis.
std::array<double, 5> arc_axis_travel(const std::array<double, 5>& start, const Block& b);

struct Program {
  std::string file;
  std::vector<Block> blocks;
  std::optional<double> tool_length_mm;   ///< from a "(cscam tool_length_mm=...)" header comment
  std::optional<double> header_cone_deg;  ///< "cone_deg=..." in that comment: the cone the program was planned with
  /// "cl_units=mm|inch" in that comment: the unit the post read the CL in (a --units override included).
  std::optional<LengthUnit> header_cl_units;
  bool tcp = false;  ///< G43.4/G43.5/G234/M428/TRAORI/TCPM/M128 seen: axis values are part coordinates (Block::tcp)
  bool tcp_words = false;          ///< a word switched tool-tip control on (Block::tcp follows it; not a header alone)
  bool tcp_vectors = false;        ///< the tool orientation is given as vectors (Block::tool_vector)
  std::vector<std::string> notes;  ///< things skipped on purpose (G28/G53, SUPA, M91/M92 blocks)
  bool work_planes = false;        ///< some block is in a tilted work plane (Block::plane)
  /// A TCP program that cancels TCP for its tilted planes: the machine axes of its blocks written without TCP (block
  /// index, axes; in order), kept by report::resolve_work_planes when it turns their words into tip words.
  std::vector<std::pair<std::size_t, std::array<double, 5>>> machine_axes;
  std::array<int, 3> xyz_slots{-1, -1, -1};  ///< the slots lettered X, Y, Z (the plane words' axes)
  /// The machine named by our post's header comment "(cscam post: machine NAME dialect ...)", if present.
  std::optional<std::string> header_machine;
  int header_line = 0;  ///< the line of that comment
  /// Axis words (X Y Z A B C U V W) whose letter is none of the machine's: each letter once, where it first
  /// appears (line, column). Such a program was written for another machine; the reader ignores these words.
  struct ForeignWord {
    char letter = 0;
    int line = 0;
    int column = 0;
  };
  std::vector<ForeignWord> foreign_axis_words;
  /// A state change the reader does not model: a coordinate shift, rotation, scaling or mirror (G92, G52, G68, G51,
  /// TRANS, CYCL DEF 7 ...), offset data written (G10), a change of work offset, or a tool length offset that is
  /// cancelled, changed or lost at a tool change. The blocks after it are not where the reader puts them.
  struct Unmodelled {
    int line = 0;
    std::string what;
    std::size_t blocks_before = 0;  ///< motion blocks read before it: it matters when more follow
  };
  std::vector<Unmodelled> unmodelled;
  /// Dwells (G4 P / X / U, Sinumerik G4 F, Heidenhain cycle 9): their number and total time, s. ISO G4 P is seconds
  /// with a decimal point and milliseconds without one (Fanuc, Haas), except in a LinuxCNC program (ours), where it
  /// is always seconds. A dwell given in spindle revolutions (Sinumerik G4 S) is counted, not timed.
  std::size_t dwells = 0;
  double dwell_seconds = 0.0;
  /// Where the spindle is stopped (M5) after it has run (M3 / M4): the M5's line and the motion blocks read until it
  /// runs again, [first_block, end_block).
  struct SpindleStop {
    int line = 0;
    std::size_t first_block = 0, end_block = 0;
    const char* what = "M5";  ///< what stopped it: M5, or a tool change
  };
  std::vector<SpindleStop> spindle_stops;
};

/// The first unmodelled state change that some motion block follows (nullptr if none): a program with one cannot be
/// checked by reading it back, so it may not be verified or written.
const Program::Unmodelled* first_unmodelled_before_motion(const Program& p);

/// Reads an NC file. Throws InputError with file:line:column on a malformed word.
Program read_file(const std::string& path, const AxisLetters& letters);
Program read_text(const std::string& text, const std::string& name, const AxisLetters& letters);

}  // namespace cscam::nc
