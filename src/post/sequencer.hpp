#pragma once
// The post's motion sequencer (private to the post module): turns CL moves and their axis values into motion blocks
// for a dialect's formatter. post.cpp's write_nc runs it; its member functions are defined by concern in
// sequencer.cpp (construction, the run over the program, CL events, the end, the buffer, word emission),
// sequencer_modes.cpp (tool-tip control, tilted work planes, rotary clamps, blend modes and corner bounds),
// sequencer_rapid.cpp (rapids, retracts, flips and unwinds, PKM repositioning), sequencer_feed.cpp (feeds, arcs,
// linearised feeds and their timing, the splits ahead) and sequencer_tcp.cpp (Cartesian blocks under tool-tip
// control).
#include <Eigen/Core>
#include <algorithm>
#include <array>
#include <cmath>
#include <cstddef>
#include <initializer_list>
#include <memory>
#include <optional>
#include <ostream>
#include <string>
#include <utility>
#include <vector>

#include "blend.hpp"
#include "cscam/cl/program.hpp"
#include "cscam/core/parallel.hpp"
#include "cscam/kin/kinematics.hpp"
#include "cscam/machine/machine.hpp"
#include "cscam/post/dialect.hpp"
#include "cscam/post/post.hpp"
#include "linearize.hpp"

namespace cscam::post::detail {

using Vec3 = Eigen::Vector3d;

/// The linearizer's settings for a program posted with `opt` on machine `m` (the sequencer's, can_follow's).
Linearizer::Settings linearizer_settings(const machine::Machine& m, const Options& opt);

/// std::llround (half away from zero) without its libm call: the sequencer rounds every axis word of every block
/// several times. Below 2^52 the truncation and the fraction x - trunc(x) are exact, so the result is llround's.
inline long long round_half_away(double x) {
  if (!(std::abs(x) < 4503599627370496.0)) return std::llround(x);  // larger values are whole numbers; NaN
  const auto i = static_cast<long long>(x);
  const double frac = x - static_cast<double>(i);
  return frac >= 0.5 ? i + 1 : (frac <= -0.5 ? i - 1 : i);
}

/// Feed for cutting moves without one (the CL reader refuses those unless a default is given).
inline constexpr double kFallbackFeedMmMin = 1000.0;
/// Rotary changes between two CL points below this are taken as continuing the branch without a check.
inline constexpr double kFlipCheckRad = 0.5235987756;  // 30 deg
/// How far inside a linear axis's limit a retract that the travel stops ends, mm.
inline constexpr double kRetractLimitMarginMm = 1.0;

/// The motion sequencer: turns CL moves and their axis values into motion blocks for a formatter, with modal
/// suppression of unchanged axis words.
class Sequencer {
  /// A feed block still in buf_ whose blend mode may change: where it starts and ends, the mode in force before it
  /// and the one it asks for; its inserted words are the latter where the two differ.
  struct FeedBlock {
    std::size_t at = std::string::npos, end = std::string::npos;
    std::string before, mode, words;
    [[nodiscard]] bool tracked() const { return at != std::string::npos; }
  };

  /// One segment split ahead (split_ahead).
  struct Ahead {
    bool ready = false;
    std::vector<Linearizer::Piece> pieces;
    Linearizer::Stats stats;
  };

  /// A piece of a feed under tool-tip control: its end tip and axis, and the machine axes there.
  struct TcpPiece {
    Vec3 tip, axis;
    kin::Axes q;
  };

 public:
  /// Takes the post's settings (tolerances, units, letters, TCP, planes, arcs, clamps) and the dialect's formatter.
  Sequencer(std::ostream& out, const cl::Program& program, const machine::Machine& machine, const kin::Kinematics& kin,
            const Options& opt, Summary& summary);

  /// Whether a TCP program would cancel TCP for all its motion (every stretch a plane): then posted without TCP.
  [[nodiscard]] bool planes_only(const std::vector<kin::Axes>& axes) const;

  /// Posts the program (one axis vector per CL move): events, rapids, feeds, arcs, tool-tip control, the footer.
  void run(const std::vector<kin::Axes>& axes);

 private:
  /// Throws InputError where the CL's tools differ in length on a machine whose head carries a rotary, without TCP.
  void warn_tcp_without_trunnion_kinematics(const std::string& dialect);
  void refuse_mixed_tool_lengths() const;
  /// The spindle as the CL last set it (restarted after a tool change, which stops it).
  struct Spindle {
    bool on = false;
    double rpm = 0.0;
    bool clockwise = true;
  } spindle_;
  void refuse_a_sideways_retract() const;
  // --- sequencer.cpp: the program frame, CL events, the buffer, words and blocks -----------------------------

  /// Writes the buffer out; keeps the last feed block (its blend mode may still change) unless `all`.
  void flush(bool all = false);

  /// Attributes the NC lines written since the last call to `cl_line` (for the gate's messages).
  void map_lines(int cl_line);

  /// The NC line the next line of text will be.
  [[nodiscard]] int next_nc_line() const;

  /// The program's end: out of the cut, plane off, retract, clamps released, TCP off, rotaries home.
  void footer();

  /// Writes a CL event: a tool change (with the retract before it), spindle, coolant, comment, stop, dwell, insert.
  void event(const cl::Event& e);

  /// Axis value v of slot i as printed: in file units and decimals (modulo 360 for a shortest-way rotary).
  long long rounded(int i, double v) const {
    double f = v * to_file_[static_cast<size_t>(i)];
    if (shortest_[static_cast<size_t>(i)]) f -= 360.0 * std::floor(f / 360.0);  // modulo output in [0, 360)
    long long r = round_half_away(f * scale_[static_cast<size_t>(i)]);
    if (shortest_[static_cast<size_t>(i)] && r == round_half_away(360.0 * scale_[static_cast<size_t>(i)])) r = 0;
    return r;
  }

  /// Refuses a block at q outside the machine's limits (an InputError at mv's CL line).
  void check_limits(const kin::Axes& q, const cl::Move& mv) const;

  /// Starts a block of the given motion.
  void start(BlockSpec::Motion motion) {
    blk_.motion = motion;
    blk_.words.clear();
    blk_.tool_vector.reset();
    blk_.arc.reset();
    blk_.feed.reset();
    blk_.feed_mode = BlockSpec::FeedMode::Keep;
  }

  /// Adds the axis words of q (slots `which`) that differ from the last written values; false when none does.
  bool add_words(const kin::Axes& q, std::initializer_list<int> which, bool force = false);

  /// Writes the block started with start(), `feed` per minute or inverse time; tracks feed blocks' blend modes.
  void emit(std::optional<double> feed = std::nullopt);
  /// emit() of a per-minute feed block (program units), its F word written only where the feed changes.
  void emit_per_minute(double f);

  /// Whether a rotary word of q differs from (or was never) written.
  bool rotaries_differ(const kin::Axes& q) const {
    for (int i : kin_.rotary_pair())
      if (!have_word_[static_cast<size_t>(i)] || rounded(i, q[i]) != last_[static_cast<size_t>(i)]) return true;
    return false;
  }

  /// Back to feed per minute (G94) after inverse time.
  void set_mode94() {
    if (mode93_) {
      blk_.feed_mode = BlockSpec::FeedMode::PerMinute;
      mode93_ = false;
      last_feed_ = -1;
    }
  }

  // --- sequencer_modes.cpp: tool-tip control, tilted work planes, rotary clamps, blend modes -----------------

  /// Switches tool-tip control on for the loaded tool (a warning, once, for length register H0).
  void tool_tip_control_on(int cl_line);

  /// The rotaries that have clamp codes and that the feed moves after the rapid at i keep where the rapid put them:
  /// clamped for that stretch (both in 3+2, one where only the other turns). Bit r: rotary slot r.
  unsigned indexed_from(const std::vector<kin::Axes>& axes, size_t i) const;

  /// Whether the feed moves after the rapid at i keep every rotary where the rapid put it (3+2).
  bool fixed_from(const std::vector<kin::Axes>& axes, size_t i) const;

  /// Whether every rotary of q is at 0 as printed (a plane would add nothing).
  bool at_rotary_zero(const kin::Axes& q) const;

  /// Whether the cut after the rapids from move i on is a 3+2 stretch that gets a plane; nothing when no cut follows.
  std::optional<bool> plane_ahead(const std::vector<kin::Axes>& axes, size_t i) const;

  /// Into a 3+2 stretch of a TCP program: out along the tool axis, TCP off, machine words from here on.
  void switch_to_machine(int cl_line);

  /// Out of a 3+2 stretch of a TCP program: out, plane off, safe Z, clamps released, TCP on again.
  void switch_to_tcp(int cl_line);

  /// The TCP program's settings again, with its Cartesian state at the machine axes the tool is at.
  void restore_tcp_state();

  /// Every word and the feed are written again (the words change meaning).
  void forget_words();

  /// Switches on the tilted work plane of q's rotaries (its Z the tool axis there).
  void work_plane_on(const kin::Axes& q);

  /// Switches the tilted work plane off: the linear words are machine coordinates again.
  void work_plane_off();

  /// add_words inside a tilted work plane: the tip in the plane's X Y Z; the rotaries must not turn.
  bool add_plane_words(const kin::Axes& q, std::initializer_list<int> which, bool force);

  /// Clamps the rotaries of `which` (bit r: slot r) that have clamp codes.
  void clamp_rotaries(unsigned which);

  /// Releases the clamped rotaries (before a rotary turns, a tool change, the end).
  void unclamp_rotaries();

  /// Exact stop at the end of the last feed block and at every block after it until resume_blend_ (around a retract).
  void stop_exactly_at_last_feed();

  /// Gives a tracked feed block the blend mode `mode`, rewriting its words and those of the block after it.
  void set_mode(FeedBlock& b, const std::string& mode);

  /// Replaces the words inserted at the start of a tracked block in buf_ and moves the offsets after them.
  void rewrite_words(FeedBlock& b, const std::string& words);

  /// The tool pose at q, remembered for the last few q (neighbouring corners share two of their three points).
  kin::Posed pose_at(const kin::Axes& q);

  /// Narrows the blend at the corner q0 -> q1 -> q2 (or stops exactly) where the control's would leave the tolerances.
  void bound_corner_blend(const kin::Axes& q0, const kin::Axes& q1, const kin::Axes& q2);

  /// Where the words of the block that begins at buf_[at] start (after its N number).
  [[nodiscard]] std::size_t words_at(std::size_t at) const;

  // --- sequencer_rapid.cpp: rapids, retracts, flips and unwinds, PKM repositioning ---------------------------

  /// A rapid of the machine's Z up to the safe Z.
  void emit_safe_z();

  /// Rapids that bring the modulo-360 rotaries to q's in steps under half a turn (the control turns the model's way).
  void turn_stepwise(const kin::Axes& q);

  /// One rapid block to q (nothing when every word is unchanged).
  void emit_g0(const kin::Axes& q);

  /// Rapid positioning to q; with a rotary change: retract, turn, position, plunge.
  void rapid(const kin::Axes& q, const cl::Move& mv);
  /// A feed move reached from off the CL path (the program's first motion, or after a tool change): rapid to
  /// post.singularity.retract_mm above it along the tool axis, then fed along the axis into it.
  void approach(const kin::Axes& q, const cl::Move& mv);

  /// After a cut, before a retract that is not along the tool axis: feeds out along the tool axis first.
  void exit_along_axis();

  /// Largest rotary change between two axis vectors (rad).
  double rotary_jump(const kin::Axes& a, const kin::Axes& b) const {
    const auto rp = kin_.rotary_pair();
    return std::max(std::abs(a[rp[0]] - b[rp[0]]), std::abs(a[rp[1]] - b[rp[1]]));
  }

  /// Whether q1 continues q0's solution branch (no flip, no change of winding).
  bool continues_branch(const kin::Posed& pose0, const kin::Axes& q0, const kin::Posed& pose1,
                        const kin::Axes& q1) const;

  /// How a flip or unwind between pose0 (q0) and pose1 (q1) is made, by both reconfigure and tcp_reconfigure.
  struct Turns {
    enum class Kind {
      None,         ///< tracking stalled near a singularity: the same branch after all
      AtStart,      ///< turn at pose0 to `start` (q1's branch there), then the feed to q1
      CutThenTurn,  ///< feed to pose1 on q0's branch (arriving at `end`), turn there to q1
      BothEnds,     ///< turn at pose0 to `start`, feed to pose1 (arriving at `end`), turn there to q1 if it differs
    };
    Kind kind = Kind::None;
    kin::Axes start, end;
    bool turn_at_end = false;
  };
  /// The turns for a flip or unwind between m0 and m1 (errors: the machine file refuses flips, or no axis values
  /// inside the limits hold the tool at m0). Where q1's branch runs back to m0 inside the limits, turns there; where
  /// it cannot (the limit that forces the turn is on q1's side), cuts to m1 on q0's branch and turns there; where
  /// neither can (an unwind forced between two points, each end's winding beyond a limit at the other), turns at m0
  /// to a branch that runs to m1 inside the limits and again at m1.
  Turns plan_turns(const kin::Posed& pose0, const kin::Axes& q0, const kin::Posed& pose1, const kin::Axes& q1,
                   const cl::Move& m0, const cl::Move& m1) const;

  /// A flip or unwind between m0 and m1: turns to q1's branch; returns the axes the feed to m1 continues from.
  std::optional<kin::Axes> reconfigure(const kin::Posed& pose0, const kin::Axes& q0, const kin::Posed& pose1,
                                       const kin::Axes& q1, const cl::Move& m0, const cl::Move& m1, double feed_mm_min);

  /// An error when the machine file says the post must not flip (post.singularity.flip: refuse).
  void refuse_if_asked(const kin::Axes& q0, const kin::Axes& q1, const cl::Move& m0, const cl::Move& m1) const;

  /// q1's branch followed back to pose0, in q0n; false when it cannot get there inside the limits.
  bool branch_back(const kin::Posed& pose0, const kin::Posed& pose1, const kin::Axes& q1, kin::Axes& q0n) const;

  /// The solution at pose0 nearest q1, for a turn made there; an error when none is inside the limits.
  kin::Axes nearest_at_start(const kin::Posed& pose0, const kin::Axes& q0, const kin::Axes& q1, const cl::Move& m0,
                             const cl::Move& m1) const;

  /// Turns the rotaries qa -> qb at the CL point m: in place where the tool holds, else retract, turn, plunge.
  void turn_at(const cl::Move& m, const kin::Posed& pose, const kin::Axes& qa, const kin::Axes& qb,
               const cl::Move& next, double feed_mm_min);

  /// Where the tip, leaving along the tool axis, reaches the plane z = safe_z_mm; false when at or above it.
  bool retract_point(const Vec3& tip, const Vec3& axis, Vec3& up) const;

  /// Under TCP: the point up the tool axis where the machine's Z (or the tip) reaches the safe height.
  bool tcp_retract_point(const Vec3& tip, const Vec3& axis, const kin::Axes& q, Vec3& up) const;
  /// A retract stopped short of the safe Z by the travel was reported (once per program).
  mutable bool retract_short_warned_ = false;

  /// The axis values with q's tip moved along its tool axis to the safe plane (an error when out of the limits).
  kin::Axes pkm_retracted(const kin::Axes& q, const SourceLoc& where);

  /// The retract along the tool axis before a tool change and at the end (no Z axis, or Cartesian).
  void axis_retract(const SourceLoc& where);

  /// A rapid with a rotary change without a Z axis: retract, turn at the safe plane, go above q.
  void pkm_reposition(const kin::Axes& q, const cl::Move& mv);

  // --- sequencer_feed.cpp: feeds, arcs, linearised feeds and their timing, the splits ahead ------------------

  /// The feed move m0 -> m1: a flip or unwind first where the branch changes (reconfigure), then feed_linear.
  void feed(const cl::Move& m0, const kin::Axes& q0_in, const cl::Move& m1, const kin::Axes& q1);

  /// Writes one G2/G3 block for the CL arc starting at moves[i] where it can be one; returns its end move, else 0.
  std::size_t arc_end(const std::vector<kin::Axes>& axes, std::size_t i);

  /// The block time qa -> qb at the programmed feed, slowed so that no axis exceeds its max_feed.
  double block_minutes(const kin::Axes& qa, const kin::Axes& qb, double programmed_minutes);

  /// The length a control measures a G94 block by, between the printed words.
  [[nodiscard]] double word_length(const kin::Axes& wa, const kin::Axes& wb) const;

  /// Where the linearizer refused q0 -> q1: the branch tracked from q0 with CL points inserted along a swing of the
  /// rotaries beside a singular orientation; false (nothing written) where that does not reach q1 either.
  bool follow_swing(const cl::Move& m0, const kin::Axes& q0, const cl::Move& m1, const kin::Axes& q1);
  /// The IK branch (Solution::branch) that q takes at pose, or -1 when no solution is q.
  [[nodiscard]] int branch_of(const kin::Posed& pose, const kin::Axes& q) const;

  /// Feed q0 -> q1 on one branch, linearised within the tip and axis tolerances.
  void feed_linear(const cl::Move& m0, const kin::Axes& q0, const cl::Move& m1, const kin::Axes& q1);

  /// The cone reference's CL axes at the ends of m0 -> m1, in `ends`; null where there are none.
  const Linearizer::ClAxes* cl_axes(const cl::Move& m0, const cl::Move& m1, Linearizer::ClAxes& ends) const;

  /// The linearisation of m0 -> m1 from the windows split in parallel ahead; false when it must be split here.
  bool split_ahead(const cl::Move& m0, const kin::Axes& q0, const cl::Move& m1, const kin::Axes& q1,
                   Linearizer::Stats& st);

  /// Splits the segments ending at moves [begin, end) into `window`, in parallel.
  void split_window(std::vector<Ahead>& window, std::size_t begin, std::size_t end) const;

  /// A feed block qa -> qb timed for tip_len_mm at the feed (G93, or a per-minute F); bounds its corner blend.
  void emit_timed(const kin::Axes& qa, const kin::Axes& qb, double tip_len_mm, double feed_mm_min);

  /// emit_timed from `from` to q; the tool is then at q.
  void emit_feed_to(const kin::Axes& from, const kin::Axes& q, double tip_len_mm, double feed_mm_min);

  // --- sequencer_tcp.cpp: Cartesian blocks under tool-tip control --------------------------------------------

  /// The words of a Cartesian block: the tip in the linear slots, rotary (or virtual wrist) angles in the rotary ones.
  kin::Axes cartesian_words(const Vec3& tip, const Vec3& axis, const kin::Axes& q) const;

  /// Adds the tool vector to the block when the rotary state changed (vector form of tool-tip control).
  void add_vector(const Vec3& axis, bool rot_changed) {
    if (vectors_ && rot_changed) blk_.tool_vector = std::array<double, 3>{axis.x(), axis.y(), axis.z()};
  }

  /// Posts one CL point under tool-tip control: a rapid (retract, turn, approach) or a feed (flip, pieces).
  void cartesian(const cl::Move& mv, const kin::Axes& q);

  /// Under TCP with machine angles as words: a flip or unwind before (or at) mv by retract, turn, plunge; true when it
  /// cut to mv itself.
  bool tcp_reconfigure(const kin::Posed& pose0, const kin::Posed& pose1, const kin::Axes& q1, const cl::Move& mv,
                       double feed_mm_min);
  /// Retract along the tool axis, turn from qa to qb, plunge, at `pose` (tool-tip control).
  void tcp_turn_at(const kin::Posed& pose, const kin::Axes& qa, const kin::Axes& qb, const cl::Move& mv,
                   double feed_mm_min);
  /// The feed m0 -> m1 under tool-tip control, split by tcp_pieces.
  void tcp_feed(const cl::Move& m0, const kin::Axes& q0, const cl::Move& m1, const kin::Axes& q1, double feed_mm_min,
                const Linearizer::ClAxes* cl);

  /// The tool axis that the words v give, as the control interpolates them.
  bool axis_of_words(const kin::Axes& v, Vec3& axis) const;

  /// The pieces of m0 -> m1 under TCP: points inserted where the interpolated words turn the axis out of tolerance.
  /// The cone reference's CL axes at the ends of the TCP segment into m1 (null: none).
  const Linearizer::ClAxes* tcp_cl_axes(const cl::Move& m1, Linearizer::ClAxes& ends) const;
  /// Whether the words' interpolation between the two poses keeps the tool within the cone of the CL axes `cl`.
  bool words_in_cone(const kin::Posed& pose0, const kin::Axes& q0, const kin::Posed& pose1, const kin::Axes& q1,
                     const Linearizer::ClAxes& cl) const;
  /// With `cl` (a planned program's CL axes at the ends), axes within the cone of the CL's are accepted too.
  void tcp_pieces(const cl::Move& m0, const kin::Axes& q0, const cl::Move& m1, const kin::Axes& q1,
                  const Linearizer::ClAxes* cl = nullptr);

  /// The machine axes the control moves to for the words v (its IK nearest its previous axes, as the gate reads it).
  void track_control(const kin::Axes& v, const Vec3& cl_axis);

  /// One tool-tip-control feed block to (tip, axis) with machine axes q there, slowed to the axes' max_feed.
  void emit_tcp_feed(const Vec3& tip, const Vec3& axis, const kin::Axes& q, double feed_mm_min);

  // --- State -------------------------------------------------------------------------------------------------

  std::ostream& out_;
  const cl::Program& prog_;
  const machine::Machine& m_;
  const kin::Kinematics& kin_;
  const kin::Traits traits_;
  const Options& opt_;
  Summary& sum_;
  Linearizer lin_;
  std::vector<Linearizer::Piece> pieces_;
  const std::vector<kin::Axes>* axes_ = nullptr;  ///< the axis values run() was given
  static constexpr std::size_t kAheadWindow = 4096;
  const Linearizer lin_proto_{lin_};  ///< untouched by the sequencer: copied by the splits ahead
  std::vector<Ahead> ahead_;          ///< split_ahead's window: segments ahead_begin_ ...
  std::size_t ahead_begin_ = 0;
  std::vector<Ahead> next_;  ///< the window after it, split in the background (next_job_)
  std::size_t next_begin_ = 0;
  bool next_pending_ = false;
  Background next_job_;  ///< declared after what it writes: destroyed (joined) first
  ProgramInfo info_;
  std::unique_ptr<Formatter> fmt_;
  BlockSpec blk_;
  bool inverse_time_ = true;
  bool arcs_ = false;         ///< CL arcs may become G2/G3
  std::array<int, 3> xyz_{};  ///< slots of the machine's X, Y, Z
  // Tilted work planes (3+2).
  bool planes_ = false;         ///< 3+2 stretches in a tilted work plane
  bool pending_plane_ = false;  ///< the rapid being written starts a 3+2 stretch that gets a plane
  bool plane_active_ = false;
  bool plane_words_ = false;  ///< in the plane the linear words are its coordinates (not Haas G254's machine words)
  Eigen::Matrix3d plane_R_ = Eigen::Matrix3d::Identity();  ///< the plane as printed (columns: its axes, part frame)
  std::array<long long, 2> plane_rot_{};                   ///< the rotaries (printed) the plane was switched on at
  double tol_mm_ = 0.01, tol_axis_rad_ = 0.005, cos_tol_axis_ = 1.0;
  std::array<int, 5> decimals_{};
  std::array<double, 5> scale_{}, to_file_{};
  std::array<bool, 5> shortest_{};  ///< cyclic rotary written modulo 360, reached the short way
  double feed_to_file_ = 1.0;       ///< mm/min to the file's feed unit
  std::array<long long, 5> last_{};
  std::array<double, 5> written_{};  ///< the (unwrapped) value last written per axis
  std::array<bool, 5> have_word_{};
  std::array<std::array<std::string, 2>, 5> clamp_codes_{};
  std::array<bool, 5> clamped_{};
  int z_ = -1;
  double safe_z_ = 0.0;
  bool cart_ = false;              ///< Cartesian (TCP) output: slots hold tip + tool-vector rotaries (now)
  bool vectors_ = false;           ///< TCP with the tool vector instead of rotary words (now)
  bool tcp_program_ = false;       ///< the program is a TCP program (cart_ is false only inside plane stretches)
  bool tcp_vectors_ = false;       ///< vectors_ of the TCP program
  bool tcp_axis_retract_ = false;  ///< axis_retract_ of the TCP program
  bool tcp_on_ = false;            ///< tool-tip control switched on in the program
  int tool_h_ = 0;                 ///< length offset register of the loaded tool
  bool warned_h0_ = false;
  bool axis_retract_ = false;  ///< retract along the tool axis to z = safe_z_mm (no Z axis, or Cartesian)
  Vec3 cart_tip_ = Vec3::Zero(), cart_axis_ = Vec3::UnitZ();  ///< last Cartesian position (part frame)
  kin::Axes cart_q_ = kin::Axes::Zero();                      ///< the machine axes there
  kin::Axes ctrl_q_ = kin::Axes::Zero();  ///< the machine axes a TCP control reaches (IK nearest, like the gate)
  cl::Move cart_move_;                    ///< the last CL point posted in Cartesian mode
  std::vector<TcpPiece> tcp_pieces_;
  bool have_state_ = false;
  bool at_cut_ = false;  ///< the last motion was a feed: the tool may be in the material
  /// The tool left the last CL point by a move the CL did not ask for (up to the safe Z before a tool change, out
  /// along the axis when the spindle stops): a feed move that follows must be approached, not fed from here.
  bool off_path_ = false;
  FeedBlock prev_blk_;       ///< the feed block right before last_blk_ (nothing between them), while its corner is open
  FeedBlock last_blk_;       ///< the last feed block written
  std::string mode_;         ///< the blend mode in force after the last block (its words; the header sets the first)
  bool exact_ = false;       ///< exact path (Formatter::exact_path_words) is on: around a retract, turn and plunge
  std::string exact_words_;  ///< Formatter::exact_path_words(), once (the corner check asks at every block)
  bool resume_blend_ = false;   ///< the plunge is written: the next feed block resumes blending
  bool bound_corners_ = false;  ///< the control blends rotaries past its tolerance: bound_corner_blend at each corner
  ControlAxes control_axes_;    ///< the axis slots as the control's planner sees them
  bool corner_open_ = false;    ///< the last block written is a straight feed block corner_q0_ -> corner_q1_
  kin::Axes corner_q0_ = kin::Axes::Zero(), corner_q1_ = kin::Axes::Zero();
  std::array<std::pair<kin::Axes, kin::Posed>, 3> fk_memo_{};  ///< pose_at's memory (NaN axes: empty)
  std::size_t fk_memo_next_ = 0;
  cl::Move cut_move_;  ///< the CL point that feed ended at
  bool mode93_ = false;
  double last_feed_ = -1.0;
  kin::Axes cur_ = kin::Axes::Zero();
  int cur_line_ = 0;  ///< the CL line being posted (for messages)
  std::size_t capped_blocks_ = 0;
  int first_capped_line_ = 0;
  std::string buf_;
  size_t scanned_ = 0;  ///< bytes of buf_ already attributed to a CL line
};

}  // namespace cscam::post::detail
