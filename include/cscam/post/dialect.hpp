#pragma once
/// @file
/// Dialects: how one controller family spells a program. The post's sequencer decides what moves (which axis
/// values, which feed, when to switch tool-tip control on); a dialect only writes it down: the program frame
/// (number, name, safe start block, end), tool changes, tool-tip control on/off and the syntax of one block.
/// One small class per controller family; its settings come from the machine file's `post:` section.
#include <Eigen/Core>
#include <array>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "cscam/core/units.hpp"
#include "cscam/machine/machine.hpp"

namespace cscam::post {

/// Everything a dialect may print in the program frame.
struct ProgramInfo {
  std::string machine_name;
  std::string program_name;
  int program_number = 1;
  std::string source_name;  ///< the CL file, shown in a comment
  std::string strategy;
  double tool_length_mm = 0.0;
  double tolerance_mm = 0.01;
  double cone_deg = 0.0;     ///< a planned program's cone (header comment: verify compares ball centres within it)
  std::string cl_units;      ///< the unit the CL was read in, "mm" or "inch" (header comment: verify reads it so)
  bool tcp = false;          ///< tool-tip control: linear words are the tip in the part frame
  bool tcp_vectors = false;  ///< the tool orientation as a vector (G43.5 I J K, Siemens A3 B3 C3), not angles
  bool inch = false;         ///< G20 / MM->INCH output
  std::string work_offset;   ///< "G54", ...; empty: none
  std::string swivel_record = "TC1";   ///< Siemens CYCLE800 _TC (machine file post.swivel_record)
  std::array<std::string, 5> letters;  ///< word letter per axis slot
  std::array<bool, 5> rotary{};
  std::array<double, 5> home{};  ///< values the end block returns the rotaries to (rad)
};

/// One motion block as the sequencer means it. Words are already rounded and modally reduced.
struct BlockSpec {
  enum class Motion { Rapid, Linear } motion = Motion::Linear;
  enum class FeedMode { Keep, PerMinute, InverseTime } feed_mode = FeedMode::Keep;  ///< a change to announce
  struct Word {
    int slot = 0;      ///< axis slot 0..4
    long long scaled;  ///< value * 10^decimals, in file units (mm/inch/deg)
    int decimals = 4;
    bool shortest = false;  ///< a rotary to be reached the short way (modulo output)
  };
  std::vector<Word> words;
  std::optional<std::array<double, 3>> tool_vector;  ///< unit tool vector (TCP vector form)
  std::optional<double> feed;                        ///< F value to print (already in the file's units)
  int feed_decimals = 1;
  /// A circular (G2/G3) feed block instead of G1: its plane and its centre relative to the start (I J K).
  struct Arc {
    bool clockwise = false;
    int plane = 17;                  ///< 17 (XY), 18 (ZX), 19 (YZ)
    std::array<long long, 3> ijk{};  ///< centre - start per X, Y, Z, scaled like the linear words
    std::array<bool, 3> write{};     ///< which of I J K the plane needs
    int decimals = 4;
  };
  std::optional<Arc> arc;
};

/// A controller family.
class Formatter {
 public:
  explicit Formatter(const ProgramInfo& info) : info_(info) {}
  virtual ~Formatter() = default;
  [[nodiscard]] virtual std::string name() const = 0;
  /// Inverse-time feed (G93) exists; otherwise the sequencer converts each block's time to a per-minute F.
  [[nodiscard]] virtual bool has_inverse_time() const { return true; }
  /// Circular blocks (G2/G3 with an incremental centre I J K in the G17/G18/G19 planes) exist.
  [[nodiscard]] virtual bool has_arcs() const { return true; }
  /// Words that make the control reach the end of the block they start exactly, and every block's after them: so
  /// that it cannot start a retract while the rotaries still finish the cut before it. Empty where the dialect's
  /// blending has not been measured (LinuxCNC's was: docs/linuxcnc.md).
  [[nodiscard]] virtual std::string exact_path_words() const { return {}; }
  /// Words that resume blending within the post's tolerance after exact_path_words().
  [[nodiscard]] std::string blend_words() const { return blend_within_words(tolerance_in_program_units()); }
  /// Words that make the control blend corners within `p` (program units: mm, or inch under G20); empty where the
  /// dialect has none.
  [[nodiscard]] virtual std::string blend_within_words(double /*p*/) const { return {}; }
  /// The smallest step of the P that blend_within_words() prints.
  [[nodiscard]] virtual double blend_tolerance_resolution() const { return 1e-4; }
  /// The control blends straight blocks that turn a rotary as post/blend.hpp's parabolic_corner() models, with its
  /// blend tolerance bounding the linear axes only: the sequencer then bounds each corner's blend itself
  /// (blend_within_words() with a smaller P, or exact_path_words()).
  [[nodiscard]] virtual bool blends_parabolically() const { return false; }
  /// The post's tolerance in program units.
  [[nodiscard]] double tolerance_in_program_units() const {
    return info_.inch ? info_.tolerance_mm / kMmPerInch : info_.tolerance_mm;
  }

  /// Tilted work planes for 3+2 stretches (rotaries fixed; docs/posts.md): none (machine coordinates: linuxcnc),
  /// a rotated frame whose Z is the tool axis (G68.2, CYCLE800, PLANE SPATIAL; origin: the part's), or a work
  /// offset the control carries with the rotaries while the words stay machine coordinates (Haas G254 DWO).
  enum class PlaneForm { None, Rotated, WorkOffset };
  [[nodiscard]] virtual PlaneForm plane_form() const { return PlaneForm::None; }
  /// Switches the work plane with axes R_part_plane (columns, part frame) on, after the rotaries are positioned.
  /// Returns the rotation the printed words define (angles rounded as printed): the linear words that follow are
  /// the tip in that frame (WorkOffset: machine coordinates, the return value unused).
  virtual Eigen::Matrix3d plane_on(std::string& out, const Eigen::Matrix3d& R_part_plane);
  /// Cancels the work plane (before the rotaries turn again, a tool change, the end).
  virtual void plane_off(std::string& out);

  /// Program start: '%', number and name, the header comments, the safe start block, the work offset.
  virtual void begin(std::string& out);
  /// After the last move: tool-tip control off, spindle and coolant off, end of program.
  virtual void end(std::string& out);
  /// Tool change to tool `tool` with length offset register `h`; switches tool-tip control on when asked.
  virtual void tool_change(std::string& out, int tool, int h, const std::string& description);
  /// Tool-tip control off (before a tool change and at the end) and on (after it), where the dialect needs it.
  virtual void tcp_on(std::string& out, int h);
  virtual void tcp_off(std::string& out);
  /// Plain tool-length compensation after tool-tip control was cancelled for a tilted work plane, where cancelling
  /// TCP cancels the length too (fanuc, haas: G43 H; elsewhere the length stays active: nothing).
  virtual void length_on(std::string& out, int h);
  /// Rotary clamp / unclamp (M-codes from the machine file) around indexed (3+2) positioning.
  virtual void clamp(std::string& out, const std::string& code);
  virtual void spindle(std::string& out, double rpm, bool clockwise);
  virtual void spindle_off(std::string& out);
  virtual void coolant(std::string& out, bool on, bool mist);
  virtual void stop(std::string& out, bool optional);
  virtual void dwell(std::string& out, double seconds);
  virtual void comment(std::string& out, const std::string& text);
  /// A CL INSERT record's text, passed through as a block of its own.
  virtual void insert(std::string& out, const std::string& text);
  /// A motion block.
  virtual void block(std::string& out, const BlockSpec& b);

  /// Appends "N<n> " when sequence numbers are on (every dialect numbers its blocks the same way).
  void number_lines(bool on, int step) {
    numbers_ = on;
    step_ = step;
  }

 protected:
  void line_start(std::string& out);
  /// The comments every dialect writes first: name, "cscam post: machine ...", source, tool length, TCP.
  void header_comments(std::string& out, bool with_name);
  /// The ISO safe start block (units, absolute, feed per minute, XY plane, no compensation) and work offset.
  void start_block(std::string& out);
  /// r / 10^d with d decimals (and a trailing point for d = 0 where integer_point_).
  void append_fixed(std::string& out, long long r, int d, bool plus_sign = false) const;
  /// "G0", "G1" or "G2"/"G3" (after a plane word when the plane changes).
  void motion_word(std::string& out, const BlockSpec& b);
  /// " I.. J.." of an arc block.
  void arc_centre_words(std::string& out, const BlockSpec& b) const;
  int plane_ = 17;  ///< the plane the start block selected
  const ProgramInfo& info_;
  bool tcp_active_ = false;
  /// Axis words without decimals still get a point ("X300."): a Fanuc-family control reads "X300" in its least
  /// input increment (0.3 mm).
  bool integer_point_ = false;
  /// The largest sequence number the control reads (0: no limit); numbering starts again past it.
  long long max_sequence_number_ = 0;

 private:
  bool numbers_ = false;
  int step_ = 10;
  long long n_ = 0;
};

/// The dialects this build knows: linuxcnc, fanuc, haas, siemens, heidenhain, xmini-joint, xmini-cartesian.
std::vector<std::string> dialect_names();
/// Whether the dialect always writes tool-tip (Cartesian) words (xmini-cartesian).
bool dialect_forces_tcp(const std::string& name);
/// Makes the dialect `name`; throws InputError naming the known ones.
std::unique_ptr<Formatter> make_formatter(const std::string& name, const ProgramInfo& info);

}  // namespace cscam::post
