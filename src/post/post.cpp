#include "cscam/post/post.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <ostream>
#include <sstream>
#include <string_view>

#include "blend.hpp"
#include "cscam/core/error.hpp"
#include "cscam/core/parallel.hpp"
#include "cscam/core/rotations.hpp"
#include "cscam/core/tolerances.hpp"
#include "cscam/core/units.hpp"
#include "cscam/kin/track.hpp"
#include "cscam/post/dialect.hpp"
#include "linearize.hpp"

// The post in three parts: the linearizer (linearize.cpp: where points must be inserted), the motion sequencer
// (this file: which blocks, in which order: rapids, retracts, flips, feeds, tool-tip control, clamps) and one
// formatter per dialect (dialects.cpp: how a controller family spells them).

namespace cscam::post {

namespace {

using Vec3 = Eigen::Vector3d;

/// The linearizer's settings for a program posted with `opt` on machine `m`.
Linearizer::Settings linearizer_settings(const machine::Machine& m, const Options& opt) {
  Linearizer::Settings s;
  s.tolerance_mm = opt.tolerance_mm > 0 ? opt.tolerance_mm : m.post.tolerance_mm;
  s.axis_tolerance_rad = deg2rad(opt.axis_tolerance_deg > 0 ? opt.axis_tolerance_deg : m.post.axis_tolerance_deg);
  s.control_offset_mm = opt.control_offset_mm;
  s.max_depth = opt.max_subdivision_depth;
  s.enabled = opt.linearise;
  s.planned = opt.strategy != "conventional";
  s.cone_rad = deg2rad(opt.cone_deg);
  return s;
}

// Feeds are printed rounded down. A feed that is a round number in exact arithmetic (the CL's F halved by the
// linearizer) comes out of FK-based timing a few ulps either side, and the side depends on a PKM's FK warm
// start, i.e. on which thread evaluated what: without this slack F1200.000 and F1199.999 alternated from run to
// run. A relative 1e-9 is far below any feed's meaning.
constexpr double kFeedFloorSlack = 1e-9;

// --- Cartesian (TCP) output --------------------------------------------------------------------
// Rotary words of the XMINI in Cartesian mode: the tool vector u (W) as the virtual wrist angles (C, A)
// of an untilted platform, u = (-sin A sin C, -sin A cos C, cos A) (docs/xmini.md with R_BP = I and
// nominal wrist): the two branches (C, A) and (C + 180 deg, -A); the one nearest to the machine's own
// wrist values q_c, q_a is taken, so branch and winding follow the chosen axis path. At A = 0, C = q_c.
std::array<double, 2> xmini_virtual_ca(const Vec3& u_W, double q_c, double q_a) {
  const Vec3 u = u_W.normalized();
  const double s = std::hypot(u.x(), u.y());
  if (s < tol::kSingularRad) return {q_c, u.z() >= 0 ? 0.0 : kPi};
  const double a = std::atan2(s, u.z());
  const double c = std::atan2(-u.x(), -u.y());
  std::array<double, 2> best{};
  double best_d = std::numeric_limits<double>::infinity();
  for (const auto& [cb, ab] : {std::pair{c, a}, std::pair{c + kPi, -a}}) {
    const double cw = cb + 2.0 * kPi * std::round((q_c - cb) / (2.0 * kPi));  // winding nearest to q_c
    const double d = std::abs(cw - q_c) + std::abs(ab - q_a);
    if (d < best_d) {
      best_d = d;
      best = {cw, ab};
    }
  }
  return best;
}

/// std::llround (half away from zero) without its libm call: the sequencer rounds every axis word of every block
/// several times. Below 2^52 the truncation and the fraction x - trunc(x) are exact, so the result is llround's.
long long round_half_away(double x) {
  if (!(std::abs(x) < 4503599627370496.0)) return std::llround(x);  // larger values are whole numbers; NaN
  const auto i = static_cast<long long>(x);
  const double frac = x - static_cast<double>(i);
  return frac >= 0.5 ? i + 1 : (frac <= -0.5 ? i - 1 : i);
}

/// Rotary changes between two CL points below this are taken as continuing the branch without a check.
constexpr double kFlipCheckRad = 0.5235987756;  // 30 deg

/// Feed for cutting moves without one (the CL reader refuses those unless a default is given).
constexpr double kFallbackFeedMmMin = 1000.0;

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

 public:
  Sequencer(std::ostream& out, const cl::Program& program, const machine::Machine& machine, const kin::Kinematics& kin,
            const Options& opt, Summary& summary)
      : out_(out),
        prog_(program),
        m_(machine),
        kin_(kin),
        traits_(kin.traits()),
        opt_(opt),
        sum_(summary),
        lin_(kin, linearizer_settings(machine, opt)) {
    const std::string dialect = opt.dialect.empty() ? machine.post.dialect : opt.dialect;
    tol_mm_ = opt.tolerance_mm > 0 ? opt.tolerance_mm : machine.post.tolerance_mm;
    tol_axis_rad_ = deg2rad(opt.axis_tolerance_deg > 0 ? opt.axis_tolerance_deg : machine.post.axis_tolerance_deg);
    cos_tol_axis_ = std::cos(tol_axis_rad_);
    cart_ = dialect_forces_tcp(dialect) || (opt.tcp ? *opt.tcp : m_.post.tcp);
    vectors_ = cart_ && m_.post.tcp_form == "vectors" &&
               traits_.tcp_rotary_words == kin::Traits::TcpRotaryWords::MachineAngles;
    const double to_inch = m_.post.inch ? 1.0 / kMmPerInch : 1.0;
    for (int i = 0; i < 5; ++i) {
      const auto& a = m_.axes[static_cast<size_t>(i)];
      const int d = a.rotary() ? m_.post.decimals_rotary : m_.post.decimals_linear;
      decimals_[static_cast<size_t>(i)] = d;
      scale_[static_cast<size_t>(i)] = std::pow(10.0, d);
      to_file_[static_cast<size_t>(i)] = a.rotary() ? 180.0 / kPi : to_inch;
      shortest_[static_cast<size_t>(i)] = a.rotary() && a.cyclic && m_.post.rotary_output == "shortest";
    }
    feed_to_file_ = to_inch;
    z_ = traits_.retract_axis;
    safe_z_ = m_.post.safe_z_mm;
    if (z_ >= 0 && std::isnan(safe_z_)) safe_z_ = m_.axes[static_cast<size_t>(z_)].max;
    info_.letters = m_.post.letters;
    if (cart_) {  // the tip's words are X Y Z, whatever the machine's linear axes are called
      int k = 0;
      for (size_t i = 0; i < 5; ++i)
        if (!m_.axes[i].rotary()) info_.letters[i] = std::string(1, "XYZ"[k++]);
    }
    // Without a Z axis (a PKM), or in Cartesian mode, safe_z_mm is a plane z = const of the part frame
    // and the retract moves the tip along the tool axis up to it.
    // With a Z axis under TCP, the tip leaves along the tool axis until the machine's Z reaches the safe Z.
    axis_retract_ = (z_ < 0 && std::isfinite(m_.post.safe_z_mm)) || (cart_ && (z_ >= 0 || std::isfinite(safe_z_)));
    info_.machine_name = m_.name;
    info_.program_name = m_.post.program_name;
    info_.program_number = m_.post.program_number;
    info_.source_name = opt.source_name;
    info_.strategy = opt.strategy;
    info_.tool_length_mm = opt.tool_length_mm;
    info_.tolerance_mm = tol_mm_;
    info_.tcp = cart_;
    info_.tcp_vectors = vectors_;
    info_.inch = m_.post.inch;
    info_.work_offset = m_.post.work_offset;
    info_.swivel_record = m_.post.swivel_record;
    for (size_t i = 0; i < 5; ++i) info_.rotary[i] = m_.axes[i].rotary();
    try {
      fmt_ = make_formatter(dialect, info_);
    } catch (const InputError& e) {
      if (!opt.dialect.empty()) throw InputError("--dialect: " + e.message());
      throw InputError(machine.where("post.dialect"), e.message());  // the machine file's value
    }
    fmt_->number_lines(m_.post.sequence_numbers, m_.post.sequence_step);
    mode_ = fmt_->blend_words();  // the header's (empty where the dialect writes none)
    for (auto& memo : fk_memo_) memo.first.setConstant(std::numeric_limits<double>::quiet_NaN());  // matches no q
    exact_words_ = fmt_->exact_path_words();
    bound_corners_ = fmt_->blends_parabolically() && !cart_ && !exact_words_.empty();
    for (std::size_t i = 0; i < 5; ++i) {
      const char letter = info_.letters[i].empty() ? 'X' : info_.letters[i][0];
      control_axes_.group[i] = std::string_view("UVW").find(letter) != std::string_view::npos   ? AxisGroup::Uvw
                               : std::string_view("ABC").find(letter) != std::string_view::npos ? AxisGroup::Abc
                                                                                                : AxisGroup::Xyz;
      control_axes_.to_program[i] = to_file_[i];
      control_axes_.accel[i] = m_.axes[i].max_accel * to_file_[i];
    }
    // Without max_accel in the machine file: every axis alike in program units (as LinuxCNC's sample configs).
    if (std::all_of(control_axes_.accel.begin(), control_axes_.accel.end(), [](double a) { return a <= 0; }))
      control_axes_.accel.fill(1.0);
    inverse_time_ = fmt_->has_inverse_time();
    for (const auto& [axis, codes] : m_.post.clamp) {
      const int i = m_.axis_index(axis);
      if (i >= 0) clamp_codes_[static_cast<size_t>(i)] = codes;
    }
    buf_.reserve(1 << 16);
    // Arcs: a dialect with I J K arcs, machine (not tool-tip) words, and linear axes lettered X, Y, Z.
    arcs_ = m_.post.arcs && fmt_->has_arcs() && !cart_;
    for (int k = 0; k < 3; ++k) {
      xyz_[static_cast<size_t>(k)] = -1;
      for (int i = 0; i < 5; ++i)
        if (!m_.axes[static_cast<size_t>(i)].rotary() &&
            m_.post.letters[static_cast<size_t>(i)] == std::string(1, "XYZ"[k]))
          xyz_[static_cast<size_t>(k)] = i;
      arcs_ = arcs_ && xyz_[static_cast<size_t>(k)] >= 0;
    }
    // Tilted work planes for 3+2 stretches: machine coordinates with a Z, linear axes X Y Z, a dialect that has them.
    const std::string work_plane = opt.work_plane.empty() ? m_.post.work_plane : opt.work_plane;
    if (work_plane == "tilted") {
      const bool xyz = std::all_of(xyz_.begin(), xyz_.end(), [](int s) { return s >= 0; });
      // Under tool-tip control the plane is written with TCP cancelled around it (switch_to_machine).
      if (fmt_->plane_form() == Formatter::PlaneForm::None || z_ < 0 || !xyz)
        sum_.warnings.push_back(fmt::format(
            "{}: dialect {} on machine {} has no tilted work plane: 3+2 stretches are "
            "written {}",
            prog_.file, fmt_->name(), m_.name, cart_ ? "under tool-tip control" : "in machine coordinates"));
      else
        planes_ = true;
    }
    tcp_program_ = cart_;
    tcp_vectors_ = vectors_;
    tcp_axis_retract_ = axis_retract_;
  }

  /// A tool-tip-control program whose every stretch gets a tilted work plane would cancel TCP for all of its motion:
  /// write_nc then posts it in machine coordinates (as with TCP off), without a TCP word or a Cartesian header.
  /// The stretches are decided where run() decides them: at the first move and at every rapid.
  [[nodiscard]] bool planes_only(const std::vector<kin::Axes>& axes) const {
    if (!tcp_program_ || !planes_ || prog_.moves.empty()) return false;
    for (size_t i = 0; i < prog_.moves.size(); ++i) {
      if (i > 0 && prog_.moves[i].kind != cl::MotionKind::Rapid) continue;
      if (const auto plane = plane_ahead(axes, i); plane && !*plane) return false;
    }
    return true;
  }

  void run(const std::vector<kin::Axes>& axes) {
    axes_ = &axes;
    sum_.cl_line_of_nc_line.assign(1, 0);
    sum_.cl_line_of_nc_line.reserve(prog_.moves.size() + prog_.events.size() + 1024);  // about a line a move
    fmt_->begin(buf_);
    map_lines(0);
    size_t ev = 0;
    const auto& moves = prog_.moves;
    for (size_t i = 0; i < moves.size(); ++i) {
      while (ev < prog_.events.size() && prog_.events[ev].before_move <= i) {
        event(prog_.events[ev]);
        map_lines(prog_.events[ev++].line);
      }
      const cl::Move& mv = moves[i];
      ++sum_.cl_points;
      check_limits(axes[i], mv);
      if (tcp_program_ && planes_ && (!have_state_ || mv.kind == cl::MotionKind::Rapid)) {
        // Under tool-tip control a 3+2 stretch that gets a plane, and the rapids to it, run with TCP cancelled,
        // everything else under TCP.
        if (const auto plane = plane_ahead(axes, i)) {
          if (*plane && cart_) switch_to_machine(mv.line);
          if (!*plane && !cart_) switch_to_tcp(mv.line);
        }
      }
      if (cart_) {
        if (!tcp_on_) tool_tip_control_on(mv.line);
        cartesian(mv, axes[i]);
      } else if (!have_state_ || mv.kind == cl::MotionKind::Rapid) {
        pending_plane_ = planes_ && fixed_from(axes, i) && !at_rotary_zero(axes[i]);
        rapid(axes[i], mv);
        pending_plane_ = false;
        if (indexed_from(axes, i)) clamp_rotaries();
      } else if (const std::size_t end = arc_end(axes, i); end > 0) {
        // One G2/G3 for the whole CIRCLE/: its points are checked, not written.
        for (std::size_t k = i + 1; k <= end; ++k) {
          ++sum_.cl_points;
          check_limits(axes[k], moves[k]);
        }
        i = end;
      } else {
        feed(moves[i - 1], axes[i - 1], mv, axes[i]);
      }
      map_lines(moves[i].line);
      if (buf_.size() > (1 << 15)) flush();
    }
    while (ev < prog_.events.size()) {
      event(prog_.events[ev]);
      map_lines(prog_.events[ev++].line);
    }
    footer();
    map_lines(0);
    flush(true);
    if (capped_blocks_ > 0)
      sum_.warnings.push_back(
          fmt::format("{}: {} feed block(s) slowed so that no axis exceeds its max_feed (first at NC line {})",
                      prog_.file, capped_blocks_, first_capped_line_));
    sum_.capped_blocks = capped_blocks_;
  }

 private:
  /// Writes the buffer out, but keeps the last feed block (stop_exactly_at_last_feed may still change it) unless
  /// `all`.
  void flush(bool all = false) {
    const std::size_t keep_from = all || !last_blk_.tracked() ? buf_.size() : std::min(last_blk_.at, buf_.size());
    out_.write(buf_.data(), static_cast<std::streamsize>(keep_from));
    buf_.erase(0, keep_from);
    scanned_ -= std::min(scanned_, keep_from);
    prev_blk_ = FeedBlock{};  // its corner was bounded when the last block was written
    if (all) {
      last_blk_ = FeedBlock{};
    } else if (last_blk_.tracked()) {
      last_blk_.at -= keep_from;
      last_blk_.end -= keep_from;
    }
  }

  /// Attributes the NC lines written since the last call to `cl_line` (for the gate's messages).
  void map_lines(int cl_line) {
    const char* const end = buf_.data() + buf_.size();
    for (const char* p = buf_.data() + scanned_;
         (p = static_cast<const char*>(std::memchr(p, '\n', static_cast<std::size_t>(end - p)))) != nullptr; ++p)
      sum_.cl_line_of_nc_line.push_back(cl_line);
    scanned_ = buf_.size();
  }

  /// The NC line the next line of text will be.
  [[nodiscard]] int next_nc_line() const {
    return static_cast<int>(
        sum_.cl_line_of_nc_line.size() +
        static_cast<size_t>(std::count(buf_.begin() + static_cast<std::ptrdiff_t>(scanned_), buf_.end(), '\n')));
  }

  // --- Program frame and CL records -----------------------------------------------------------------

  void tool_tip_control_on(int cl_line) {
    if (tool_h_ == 0 && !warned_h0_) {
      warned_h0_ = true;
      sum_.warnings.push_back(
          fmt::format("{}: tool-tip control with length offset register H0: H0 cancels the tool length on "
                      "most controls",
                      SourceLoc{prog_.file, cl_line, 0}.str()));
    }
    fmt_->tcp_on(buf_, tool_h_);
    tcp_on_ = true;
  }

  void footer() {
    exit_along_axis();
    work_plane_off();
    if (!cart_ && z_ >= 0 && have_state_) {
      emit_safe_z();
    } else if (have_state_) {
      axis_retract(SourceLoc{prog_.file});
    }
    unclamp_rotaries();
    if (tcp_on_) {
      fmt_->tcp_off(buf_);
      tcp_on_ = false;
    }
    // Rotaries home at the end (machine coordinates: a table turned back, a head upright), above the part.
    if (!cart_ && have_state_ && m_.post.home_rotaries && z_ >= 0) {
      kin::Axes home = cur_;
      for (int i : kin_.rotary_pair())  // a modulo rotary is home at any whole turn: the nearest one
        home[i] = shortest_[static_cast<size_t>(i)] ? 2.0 * kPi * std::round(cur_[i] / (2.0 * kPi)) : 0.0;
      if (kin_.check_limits(home).empty()) emit_g0(home);
    }
    fmt_->end(buf_);
  }

  void event(const cl::Event& e) {
    using K = cl::Event::Kind;
    switch (e.kind) {
      case K::ToolChange: {
        const bool known = e.tool_index >= 0 && static_cast<size_t>(e.tool_index) < prog_.tools.size();
        const int n = known ? prog_.tools[static_cast<size_t>(e.tool_index)].number : 0;
        // Retract before the change so the new tool does not come down into the part.
        exit_along_axis();
        work_plane_off();
        if (!cart_ && z_ >= 0 && have_state_)
          emit_safe_z();
        else if (have_state_)
          axis_retract(SourceLoc{prog_.file, e.line, 0});
        unclamp_rotaries();
        if (tcp_on_) {
          fmt_->tcp_off(buf_);
          tcp_on_ = false;
        }
        if (tcp_program_ && !cart_) restore_tcp_state();  // left a plane stretch: the new tool starts under TCP
        // The length offset register: LOAD/TOOL,n,ADJUST,h, else the tool's own number.
        tool_h_ = known && prog_.tools[static_cast<size_t>(e.tool_index)].length_register >= 0
                      ? prog_.tools[static_cast<size_t>(e.tool_index)].length_register
                      : n;
        if (tool_h_ == 0)
          sum_.warnings.push_back(
              fmt::format("{}: length offset register H0 (tool 0, or ADJUST,0): H0 cancels "
                          "the tool length on most controls",
                          SourceLoc{prog_.file, e.line, 0}.str()));
        fmt_->tool_change(
            buf_, n, tool_h_,
            known ? fmt::format("TOOL {}: {} D{:.3f}", n, prog_.tools[static_cast<size_t>(e.tool_index)].name,
                                prog_.tools[static_cast<size_t>(e.tool_index)].diameter_mm)
                  : std::string());
        // A tool whose first stretch is a tilted plane starts without TCP: switch_to_machine writes its plain length
        // offset there, rather than TCP on here and off again before any motion.
        if (cart_) {
          const auto plane = tcp_program_ && planes_ ? plane_ahead(*axes_, e.before_move) : std::nullopt;
          if (!plane.value_or(false)) tool_tip_control_on(e.line);
        }
        break;
      }
      case K::SpindleOn:
        fmt_->spindle(buf_, e.spindle_rpm, e.clockwise);
        break;
      case K::SpindleOff:
        exit_along_axis();  // leave the cut while the spindle still turns
        if (cart_ && have_state_) axis_retract(SourceLoc{prog_.file, e.line, 0});
        fmt_->spindle_off(buf_);
        break;
      case K::CoolantOn:
        fmt_->coolant(buf_, true, e.text == "MIST");
        break;
      case K::CoolantOff:
        fmt_->coolant(buf_, false, false);
        break;
      case K::Comment:
        if (!e.text.empty()) fmt_->comment(buf_, e.text);
        break;
      case K::OperationStart:
        fmt_->comment(buf_, "OPERATION " + e.text);
        break;
      case K::Stop:
        fmt_->stop(buf_, e.text.rfind("OPSTOP", 0) == 0);
        break;
      case K::Dwell:
        fmt_->dwell(buf_, e.seconds);
        break;
      case K::Insert:
        fmt_->insert(buf_, e.text);
        break;
    }
  }

  // --- Rotary clamps around indexed (3+2) stretches -----------------------------------------------------

  /// Whether the stretch of feed moves after the rapid at i keeps every rotary where the rapid put it (and clamp
  /// codes are given).
  bool indexed_from(const std::vector<kin::Axes>& axes, size_t i) const {
    if (std::all_of(clamp_codes_.begin(), clamp_codes_.end(), [](const auto& c) { return c[0].empty(); })) return false;
    return fixed_from(axes, i);
  }

  /// Whether the stretch of feed moves after the rapid at i keeps every rotary where the rapid put it (3+2).
  bool fixed_from(const std::vector<kin::Axes>& axes, size_t i) const {
    const auto rp = kin_.rotary_pair();
    size_t j = i + 1;
    for (; j < axes.size() && prog_.moves[j].kind == cl::MotionKind::Feed; ++j)
      for (int r : rp)
        if (rounded(r, axes[j][r]) != rounded(r, axes[i][r])) return false;
    return j > i + 1;
  }

  /// Every rotary at 0 as printed: machine and part frames agree, a plane would add nothing.
  bool at_rotary_zero(const kin::Axes& q) const {
    for (int r : kin_.rotary_pair())
      if (rounded(r, q[r]) != 0) return false;
    return true;
  }

  // --- Tool-tip control around tilted work planes --------------------------------------------------------
  // A control refuses a tilted plane under TCP (G68.2 in G43.4 mode, CYCLE800 under TRAORI): a TCP program
  // cancels TCP for each 3+2 stretch that gets a plane and writes that stretch exactly as the non-TCP program
  // does (safe Z, turn, clamp, plane, cut in plane words, plane off), then switches TCP on again.

  /// Whether the cut after the rapids from move i on (or after move i itself, the first) is a 3+2 stretch that gets
  /// a plane; nothing when no cut follows (the last rapids keep the mode they find).
  std::optional<bool> plane_ahead(const std::vector<kin::Axes>& axes, size_t i) const {
    const auto& moves = prog_.moves;
    size_t j = i;
    while (moves[j].kind == cl::MotionKind::Rapid && j + 1 < moves.size() && moves[j + 1].kind == cl::MotionKind::Rapid)
      ++j;
    if (j + 1 >= moves.size()) return std::nullopt;
    return fixed_from(axes, j) && !at_rotary_zero(axes[j]);
  }

  /// Into a 3+2 stretch: out along the tool axis under TCP (as before any rotary change of the TCP program), TCP
  /// off, the plain length offset, and machine words from here on.
  void switch_to_machine(int cl_line) {
    if (have_state_) axis_retract(SourceLoc{prog_.file, cl_line, 0});
    if (tcp_on_) {
      fmt_->tcp_off(buf_);
      tcp_on_ = false;
    }
    fmt_->length_on(buf_, tool_h_);
    cart_ = false;
    vectors_ = false;
    axis_retract_ = false;            // planes need a Z axis: machine Z retracts
    if (have_state_) cur_ = cart_q_;  // the machine axes where TCP left the tool
    forget_words();
    at_cut_ = false;
  }

  /// Out of a 3+2 stretch into a simultaneous one: out along the axis, the plane off, up to the safe Z, the clamps
  /// released, TCP on again; the TCP rapid that follows positions the tool.
  void switch_to_tcp(int cl_line) {
    exit_along_axis();
    work_plane_off();
    if (have_state_) emit_safe_z();
    unclamp_rotaries();
    restore_tcp_state();
    tool_tip_control_on(cl_line);
  }

  /// The TCP program's settings again, with its Cartesian state at the machine axes the tool is at.
  void restore_tcp_state() {
    cart_ = true;
    vectors_ = tcp_vectors_;
    axis_retract_ = tcp_axis_retract_;
    if (have_state_) {
      const kin::Posed here = kin_.forward(cur_);
      cart_q_ = ctrl_q_ = cur_;
      cart_tip_ = here.tip_mm;
      cart_axis_ = here.axis;
      cur_ = cartesian_words(here.tip_mm, here.axis, cur_);
    }
    forget_words();
  }

  /// The words change meaning (tip words <-> machine words): every word and the feed are written again.
  void forget_words() {
    have_word_.fill(false);
    last_feed_ = -1.0;
  }

  // --- Tilted work planes (3+2) ------------------------------------------------------------------------

  /// Switches the work plane of the rotaries in q on: its Z is the tool axis there (origin: the part's).
  void work_plane_on(const kin::Axes& q) {
    if (plane_active_) return;
    plane_R_ = fmt_->plane_on(buf_, rot::plane_for_tool_axis(kin_.forward(q).axis));
    plane_active_ = true;
    plane_words_ = fmt_->plane_form() == Formatter::PlaneForm::Rotated;
    plane_rot_ = {rounded(kin_.rotary_pair()[0], q[kin_.rotary_pair()[0]]),
                  rounded(kin_.rotary_pair()[1], q[kin_.rotary_pair()[1]])};
    for (int s : xyz_) have_word_[static_cast<size_t>(s)] = false;  // the words now mean plane coordinates
    ++sum_.work_planes;
  }

  void work_plane_off() {
    if (!plane_active_) return;
    fmt_->plane_off(buf_);
    plane_active_ = false;
    for (int s : xyz_) have_word_[static_cast<size_t>(s)] = false;  // machine coordinates again: all written
  }

  /// add_words in a work plane: the tip of q in the plane's X Y Z (all three whenever a linear word is asked
  /// for: one machine axis moves the tip along a tilted direction); the rotaries must not turn.
  bool add_plane_words(const kin::Axes& q, std::initializer_list<int> which, bool force) {
    bool linear = false;
    for (int i : which) {
      if (!m_.axes[static_cast<size_t>(i)].rotary()) {
        linear = true;
        continue;
      }
      const auto rp = kin_.rotary_pair();
      CSCAM_CHECK(rounded(i, q[i]) == plane_rot_[i == rp[0] ? 0 : 1], "a rotary turns inside a tilted work plane");
    }
    if (!linear) return false;
    const Vec3 p = plane_R_.transpose() * kin_.forward(q).tip_mm;
    bool any = false;
    for (int k = 0; k < 3; ++k) {
      const auto u = static_cast<size_t>(xyz_[static_cast<size_t>(k)]);
      const long long r = round_half_away(p[k] * to_file_[u] * scale_[u]);
      if (!force && have_word_[u] && r == last_[u]) continue;
      blk_.words.push_back({static_cast<int>(u), r, decimals_[u], false});
      last_[u] = r;
      written_[u] = p[k];
      have_word_[u] = true;
      any = true;
    }
    return any;
  }

  void clamp_rotaries() {
    for (int r : kin_.rotary_pair()) {
      const auto& c = clamp_codes_[static_cast<size_t>(r)];
      if (!c[0].empty() && !clamped_[static_cast<size_t>(r)]) {
        fmt_->clamp(buf_, c[0]);
        clamped_[static_cast<size_t>(r)] = true;
      }
    }
  }

  void unclamp_rotaries() {
    for (int r : kin_.rotary_pair()) {
      if (!clamped_[static_cast<size_t>(r)]) continue;
      fmt_->clamp(buf_, clamp_codes_[static_cast<size_t>(r)][1]);
      clamped_[static_cast<size_t>(r)] = false;
    }
  }

  // --- Words and blocks ----------------------------------------------------------------------------------

  long long rounded(int i, double v) const {
    double f = v * to_file_[static_cast<size_t>(i)];
    if (shortest_[static_cast<size_t>(i)]) f -= 360.0 * std::floor(f / 360.0);  // modulo output in [0, 360)
    long long r = round_half_away(f * scale_[static_cast<size_t>(i)]);
    if (shortest_[static_cast<size_t>(i)] && r == round_half_away(360.0 * scale_[static_cast<size_t>(i)])) r = 0;
    return r;
  }

  void check_limits(const kin::Axes& q, const cl::Move& mv) const {
    const std::string v = kin_.check_limits(q);
    if (!v.empty())
      throw InputError(SourceLoc{prog_.file, mv.line, 0},
                       fmt::format("the post refuses a block outside the limits: {}", v));
  }

  /// Starts a block of the given motion.
  void start(BlockSpec::Motion motion) {
    blk_.motion = motion;
    blk_.words.clear();
    blk_.tool_vector.reset();
    blk_.arc.reset();
    blk_.feed.reset();
    blk_.feed_mode = BlockSpec::FeedMode::Keep;
  }

  /// Adds the axis words of q that differ from the last written values.
  bool add_words(const kin::Axes& q, std::initializer_list<int> which, bool force = false) {
    if (plane_active_ && plane_words_) return add_plane_words(q, which, force);
    bool any = false;
    for (int i : which) {
      const long long r = rounded(i, q[i]);
      const auto u = static_cast<size_t>(i);
      if (!force && have_word_[u] && r == last_[u]) continue;
      // A modulo rotary is reached the short way: one block may not turn it half a turn or more.
      if (shortest_[u] && have_word_[u] && std::abs(q[i] - written_[u]) >= kPi - 1e-9)
        throw InputError(SourceLoc{prog_.file, cur_line_, 0},
                         fmt::format("axis {} would turn {:.3f} deg in one block, but with post.rotary_output "
                                     "'shortest' the control takes the short way",
                                     m_.axes[u].name, rad2deg(std::abs(q[i] - written_[u]))));
      if (!(vectors_ && m_.axes[u].rotary())) blk_.words.push_back({i, r, decimals_[u], shortest_[u]});
      last_[u] = r;
      written_[u] = q[i];
      have_word_[u] = true;
      any = true;
    }
    return any;
  }

  /// Writes the block started with start(); `feed` is per minute (G94) or inverse time (G93).
  void emit(std::optional<double> feed = std::nullopt) {
    for (const auto& w : blk_.words)
      if (m_.axes[static_cast<size_t>(w.slot)].rotary() && clamped_[static_cast<size_t>(w.slot)]) {
        unclamp_rotaries();  // a clamped rotary about to turn: released first, never turned against the brake
        break;
      }
    if (feed) {
      // Printed rounded down: a block is never faster than the time the sequencer gave it.
      // Slow per-minute feeds (a capped block that mostly turns a rotary) keep four decimals.
      blk_.feed_decimals = mode93_ ? 3 : (*feed < 100.0 ? 4 : 1);
      static constexpr double kPow10[] = {1.0, 10.0, 100.0, 1000.0, 10000.0};
      const double p = kPow10[blk_.feed_decimals];
      blk_.feed = std::max(std::floor(*feed * p * (1.0 + kFeedFloorSlack)) / p, 1.0 / p);
    }
    const std::size_t at = buf_.size();
    const bool follows_feed = last_blk_.tracked() && at == last_blk_.end;
    fmt_->block(buf_, blk_);
    ++sum_.blocks;
    corner_open_ = false;  // emit_timed opens it again for its own blocks
    if (blk_.motion == BlockSpec::Motion::Rapid) {
      resume_blend_ = exact_;  // away from the part: the next cut blends again (a turn's plunge resets this)
      prev_blk_ = FeedBlock{};
    } else {
      prev_blk_ = follows_feed ? std::move(last_blk_) : FeedBlock{};
      last_blk_ = FeedBlock{at, buf_.size(), mode_, mode_, {}};
      if (resume_blend_ && exact_) {  // the first cut after a plunge: blending again from here on
        set_mode(last_blk_, fmt_->blend_words());
        exact_ = resume_blend_ = false;
      }
    }
  }

  /// Makes the control stop exactly at the end of the last feed block written (the cut before a retract, whose
  /// blend mode was fixed when the control queued it) and at every block's after it, until resume_blend_.
  void stop_exactly_at_last_feed() {
    if (exact_words_.empty() || exact_ || !last_blk_.tracked()) return;
    exact_ = true;
    resume_blend_ = false;
    set_mode(last_blk_, exact_words_);
  }

  /// Gives a tracked feed block the blend mode `mode` (its words, when the mode in force before it differs). The
  /// block after the previous one is rewritten too: the mode before it changed. One word of the group per block: a
  /// block that asked for another mode is rewritten, never given a second word.
  void set_mode(FeedBlock& b, const std::string& mode) {
    CSCAM_CHECK(b.tracked() && (&b == &last_blk_ || &b == &prev_blk_), "set_mode: a tracked feed block");
    b.mode = mode;
    rewrite_words(b, b.mode == b.before ? std::string() : b.mode);
    if (&b == &prev_blk_ && last_blk_.tracked()) {
      last_blk_.before = mode;
      rewrite_words(last_blk_, last_blk_.mode == last_blk_.before ? std::string() : last_blk_.mode);
    } else if (&b == &last_blk_) {
      mode_ = mode;
    }
  }

  /// Replaces the words inserted at the start of a tracked block, and moves the offsets after them.
  void rewrite_words(FeedBlock& b, const std::string& words) {
    if (words == b.words) return;
    const std::size_t p = words_at(b.at);
    const std::string old = b.words.empty() ? std::string() : b.words + " ";
    const std::string now = words.empty() ? std::string() : words + " ";
    CSCAM_CHECK(buf_.compare(p, old.size(), old) == 0, "a tracked block starts with the words inserted there");
    buf_.replace(p, old.size(), now);
    auto move = [&](std::size_t& at) {
      if (at != std::string::npos && at > p) at = at + now.size() - old.size();
    };
    move(b.end);
    if (&b == &prev_blk_) {
      move(last_blk_.at);
      move(last_blk_.end);
    }
    if (scanned_ > p) scanned_ = scanned_ + now.size() - old.size();  // the words hold no newline
    b.words = words;
  }

  /// The tool at q, remembered for the last few q: neighbouring corners share two of their three points.
  kin::Posed pose_at(const kin::Axes& q) {
    for (const auto& [at, pose] : fk_memo_)
      if (at == q) return pose;
    auto& slot = fk_memo_[fk_memo_next_];
    fk_memo_next_ = (fk_memo_next_ + 1) % fk_memo_.size();
    slot = {q, kin_.forward(q)};
    return slot.second;
  }

  /// After the feed block q1 -> q2 that follows the feed block q0 -> q1 (both still in buf_): where the control
  /// blends their corner as parabolic_corner() models, the whole blend must keep the tip within the tolerance of the
  /// path, pass the corner's point within it, and keep the tool axis within the axis tolerance of the blocks' axes
  /// (CornerBlendCheck). If it would not, the first block gets a smaller blend tolerance (the reach shrinks with P
  /// where the turn lets P bound it) or exact path, and the second the post's own again.
  void bound_corner_blend(const kin::Axes& q0, const kin::Axes& q1, const kin::Axes& q2) {
    const double p = fmt_->tolerance_in_program_units();
    const auto c = parabolic_corner(q0, q1, q2, control_axes_, p);
    if (!c) return;
    const kin::Posed A = pose_at(q0), B = pose_at(q1), C = pose_at(q2);
    const CornerBlendCheck check(kin_, *c, q1, A, B, C, tol_mm_, tol_axis_rad_);
    const double worst = check.excess(c->reach);
    if (worst <= 1.0 + 1e-9) return;
    std::string words;
    if (std::isfinite(c->reach_per_p)) {
      // The deviation grows with the reach about linearly: aim at 90 % of the tolerance, then check.
      const double step = fmt_->blend_tolerance_resolution();
      double p_new = std::floor(0.9 * c->reach / worst / c->reach_per_p / step) * step;
      while (p_new >= step && check.excess(p_new * c->reach_per_p) > 1.0) p_new = std::floor(0.5 * p_new / step) * step;
      if (p_new >= step) words = fmt_->blend_within_words(p_new);
    }
    if (words.empty()) {
      words = exact_words_;
      if (words.empty()) return;
      ++sum_.exact_corners;
    } else {
      ++sum_.narrowed_corners;
    }
    set_mode(prev_blk_, words);
    set_mode(last_blk_, fmt_->blend_words());
  }

  /// Where the words of the block that begins at buf_[at] start (after its N number).
  [[nodiscard]] std::size_t words_at(std::size_t at) const {
    CSCAM_CHECK(at <= buf_.size(), "words_at: the block is still in the buffer");
    std::size_t p = at;
    if (p < buf_.size() && buf_[p] == 'N') {
      ++p;
      while (p < buf_.size() && std::isdigit(static_cast<unsigned char>(buf_[p])) != 0) ++p;
      if (p < buf_.size() && buf_[p] == ' ') ++p;
    }
    return p;
  }

  bool rotaries_differ(const kin::Axes& q) const {
    for (int i : kin_.rotary_pair())
      if (!have_word_[static_cast<size_t>(i)] || rounded(i, q[i]) != last_[static_cast<size_t>(i)]) return true;
    return false;
  }

  void set_mode94() {
    if (mode93_) {
      blk_.feed_mode = BlockSpec::FeedMode::PerMinute;
      mode93_ = false;
      last_feed_ = -1;
    }
  }

  void emit_safe_z() {
    kin::Axes q = cur_;
    q[z_] = safe_z_;
    start(BlockSpec::Motion::Rapid);
    if (add_words(q, {z_})) {
      set_mode94();
      emit();
    }
    cur_[z_] = safe_z_;
  }

  /// Rapid blocks that bring the rotaries written modulo 360 (reached the short way) to q's in steps of less
  /// than half a turn, every axis moving proportionally: the control then turns the way the model does.
  void turn_stepwise(const kin::Axes& q) {
    double worst = 0.0;
    for (int i = 0; i < 5; ++i)
      if (shortest_[static_cast<size_t>(i)] && have_word_[static_cast<size_t>(i)])
        worst = std::max(worst, std::abs(q[i] - written_[static_cast<size_t>(i)]));
    const int n = static_cast<int>(std::ceil(worst / deg2rad(170.0)));
    if (n <= 1) return;
    kin::Axes from = cur_;
    for (int i = 0; i < 5; ++i)
      if (have_word_[static_cast<size_t>(i)]) from[i] = written_[static_cast<size_t>(i)];
    for (int k = 1; k < n; ++k) {
      const kin::Axes mid = from + (static_cast<double>(k) / n) * (q - from);
      start(BlockSpec::Motion::Rapid);
      if (add_words(mid, {0, 1, 2, 3, 4})) {
        set_mode94();
        emit();
      }
    }
  }

  /// One rapid block to q (nothing when every word is unchanged).
  void emit_g0(const kin::Axes& q) {
    turn_stepwise(q);
    start(BlockSpec::Motion::Rapid);
    if (add_words(q, {0, 1, 2, 3, 4})) {
      set_mode94();
      emit();
    }
    cur_ = q;
  }

  /// Rapid positioning. With a rotary change: retract, rotate, position, plunge.
  void rapid(const kin::Axes& q, const cl::Move& mv) {
    cur_line_ = mv.line;
    const auto rp = kin_.rotary_pair();
    std::vector<int> lin;
    for (int i = 0; i < 5; ++i)
      if (i != rp[0] && i != rp[1]) lin.push_back(i);
    // Leaving a plane: before the rotaries turn, out along the tool axis (in the plane) first; a rapid that keeps
    // them (and no 3+2 stretch after it) just ends the plane, the same motion as in machine coordinates.
    if (plane_active_ && (rotaries_differ(q) || !pending_plane_)) {
      if (rotaries_differ(q)) exit_along_axis();
      work_plane_off();
    }
    if (pending_plane_ && !rotaries_differ(q)) work_plane_on(q);  // the rotaries are already there
    if (rotaries_differ(q) && z_ >= 0) {
      exit_along_axis();
      if (have_state_) emit_safe_z();
      kin::Axes at_safe = have_state_ ? cur_ : q;
      at_safe[z_] = safe_z_;
      at_safe[rp[0]] = q[rp[0]];
      at_safe[rp[1]] = q[rp[1]];
      check_limits(at_safe, mv);
      if (!have_state_) {  // the safe start: up first, wherever the tool is
        start(BlockSpec::Motion::Rapid);
        set_mode94();
        add_words(at_safe, {z_}, true);
        emit();
      }
      turn_stepwise(at_safe);
      start(BlockSpec::Motion::Rapid);
      set_mode94();
      if (add_words(at_safe, {rp[0], rp[1]})) emit();
      if (pending_plane_) work_plane_on(at_safe);  // positioned: the plane, then the approach in it
      kin::Axes above = q;
      above[z_] = safe_z_;
      start(BlockSpec::Motion::Rapid);
      bool any = false;
      for (int i : lin)
        if (i != z_) any = add_words(above, {i}, !have_word_[static_cast<size_t>(i)]) || any;
      if (any) emit();  // already above the point: no empty block (a control would still move)
    }
    if (rotaries_differ(q) && z_ < 0 && axis_retract_) pkm_reposition(q, mv);
    start(BlockSpec::Motion::Rapid);
    set_mode94();
    if (!add_words(q, {0, 1, 2, 3, 4})) add_words(q, {lin[0]}, true);
    emit();
    cur_ = q;
    have_state_ = true;
    at_cut_ = false;
  }

  /// After a cut, before a retract that is not along the tool axis (machine Z up, a tool change, the end):
  /// feed out post.singularity.retract_mm along the tool axis first, so that a tilted tool under an
  /// overhang does not drag through it on the way up.
  void exit_along_axis() {
    if (!at_cut_ || cart_ || axis_retract_) return;
    at_cut_ = false;
    stop_exactly_at_last_feed();
    // Along the machine's actual tool axis (a planned program may tilt away from the CL axis).
    const kin::Posed here = kin_.forward(cur_);
    cl::Move from = cut_move_, up = cut_move_;
    from.tip_in_part_mm = here.tip_mm;
    from.axis_in_part = here.axis;
    up.tip_in_part_mm = here.tip_mm + m_.post.singularity.retract_mm * here.axis;
    up.axis_in_part = here.axis;
    kin::Axes q_up;
    if (!kin::nearest_solution(kin_, kin::Posed{up.tip_in_part_mm, here.axis}, cur_, q_up) ||
        rotary_jump(q_up, cur_) > kFlipCheckRad)
      return;  // no room along the axis: the plain retract follows (and the gate checks it against the meshes)
    feed_linear(from, cur_, up, q_up);
  }

  // --- Branch flips and unwinds between two feed points ------------------------------------------

  /// Largest rotary change between two axis vectors (rad).
  double rotary_jump(const kin::Axes& a, const kin::Axes& b) const {
    const auto rp = kin_.rotary_pair();
    return std::max(std::abs(a[rp[0]] - b[rp[0]]), std::abs(a[rp[1]] - b[rp[1]]));
  }

  /// Whether q1 continues the solution branch of q0 (no flip, no change of winding). Small rotary
  /// changes always do; large ones are checked by tracking the pose continuously from q0.
  bool continues_branch(const kin::Posed& pose0, const kin::Axes& q0, const kin::Posed& pose1,
                        const kin::Axes& q1) const {
    if (rotary_jump(q0, q1) < kFlipCheckRad) return true;
    kin::Axes tracked;
    bool jumped = false;
    if (!kin::track_checked(kin_, q0, pose0, pose1, tracked, jumped)) return false;
    return !jumped && rotary_jump(tracked, q1) < 1e-6;
  }

  /// q0 (at m0) and q1 (at m1) lie on different branches or windings: a rotary limit or the branch rule
  /// forces a flip or an unwind. Turns to q1's branch at m0 and returns the axis values there, from which the feed to
  /// q1 continues. Where q1's branch cannot be followed back to m0 inside the limits (the limit that forces the turn
  /// is on q1's side of it), cuts to m1 on q0's branch and turns there; where neither can (an unwind forced between
  /// two points, each end's winding beyond a limit at the other), turns at m0 to a branch that runs to m1 inside the
  /// limits and again at m1. Returns nothing in those two cases (m1 is reached with q1).
  std::optional<kin::Axes> reconfigure(const kin::Posed& pose0, const kin::Axes& q0, const kin::Posed& pose1,
                                       const kin::Axes& q1, const cl::Move& m0, const cl::Move& m1,
                                       double feed_mm_min) {
    refuse_if_asked(q0, q1, m0, m1);
    // The branch that starts at qa on pose0 and runs continuously to pose1 inside the limits, there.
    auto runs_through = [&](const kin::Axes& qa, kin::Axes& qb) {
      bool jumped = false;
      return kin::track_checked(kin_, qa, pose0, pose1, qb, jumped) && !jumped && kin_.check_limits(qb).empty();
    };
    kin::Axes q0n;
    if (!branch_back(pose0, pose1, q1, q0n)) {
      kin::Axes q1p;
      if (runs_through(q0, q1p) && rotary_jump(q1p, q1) >= kFlipCheckRad) {
        feed_linear(m0, q0, m1, q1p);
        turn_at(m1, pose1, q1p, q1, m1, feed_mm_min);
        return std::nullopt;
      }
      std::vector<kin::Solution> sols;
      kin_.inverse_all(pose0, &q0, sols);
      std::sort(sols.begin(), sols.end(), [&](const kin::Solution& a, const kin::Solution& b) {
        return rotary_jump(q0, a.axes) < rotary_jump(q0, b.axes);
      });
      for (const kin::Solution& sol : sols) {
        if (!sol.feasible() || rotary_jump(q0, sol.axes) < kFlipCheckRad || !runs_through(sol.axes, q1p)) continue;
        turn_at(m0, pose0, q0, sol.axes, m1, feed_mm_min);
        feed_linear(m0, sol.axes, m1, q1p);
        if (rotary_jump(q1p, q1) >= kFlipCheckRad) turn_at(m1, pose1, q1p, q1, m1, feed_mm_min);
        return std::nullopt;
      }
      q0n = nearest_at_start(pose0, q0, q1, m0, m1);
    }
    if (rotary_jump(q0, q0n) < 1e-9) return q0;  // tracking stalled near a singularity: same branch after all
    turn_at(m0, pose0, q0, q0n, m1, feed_mm_min);
    return q0n;
  }

  /// An error when the machine file says the post must not flip (post.singularity.flip: refuse).
  void refuse_if_asked(const kin::Axes& q0, const kin::Axes& q1, const cl::Move& m0, const cl::Move& m1) const {
    if (m_.post.singularity.flip == "refuse")
      throw InputError(SourceLoc{prog_.file, m1.line, 0},
                       fmt::format("the rotaries must flip or unwind between CL lines {} and {} ({}): a rotary limit "
                                   "or the branch rule forces it, and post.singularity.flip is 'refuse'",
                                   m0.line, m1.line, rotary_change(kin_, q0, q1)));
  }

  /// q1's branch at pose0, in q0n: followed back from q1 (at pose1), so that the feed from pose0 to pose1 is
  /// continuous on it. False when it cannot get there inside the limits.
  bool branch_back(const kin::Posed& pose0, const kin::Posed& pose1, const kin::Axes& q1, kin::Axes& q0n) const {
    bool jumped = false;
    return kin::track_checked(kin_, q1, pose1, pose0, q0n, jumped) && !jumped;
  }

  /// The solution at pose0 (m0) nearest q1, for a turn made there when q1's branch cannot be followed back; an error
  /// when none is inside the limits.
  kin::Axes nearest_at_start(const kin::Posed& pose0, const kin::Axes& q0, const kin::Axes& q1, const cl::Move& m0,
                             const cl::Move& m1) const {
    kin::Axes q0n;
    std::string why;
    if (!kin::nearest_solution(kin_, pose0, q1, q0n, &why))
      throw InputError(
          SourceLoc{prog_.file, m1.line, 0},
          fmt::format("the rotaries must flip or unwind between CL lines {} and {} ({}) but no axis "
                      "values inside the limits hold the tool at CL line {}{}",
                      m0.line, m1.line, rotary_change(kin_, q0, q1), m0.line, why.empty() ? "" : ": " + why));
    return q0n;
  }

  /// Turns the rotaries from qa to qb (the same pose, another branch or winding) at the CL point m (pose): in place
  /// when the joint move keeps the tool pose within tolerance (at the singular point itself), else by retract along
  /// the tool axis, turn, plunge. `next` is the CL move the turn is made for (its line and feed).
  void turn_at(const cl::Move& m, const kin::Posed& pose, const kin::Axes& qa, const kin::Axes& qb,
               const cl::Move& next, double feed_mm_min) {
    const auto& pol = m_.post.singularity;
    const SourceLoc where{prog_.file, next.line, 0};
    // In place: the straight joint move qa -> qb keeps the tool pose (e.g. the primary turning while the
    // tool axis lies along it).
    if (pol.flip == "auto") {
      const Vec3 ctrl = pose.tip_mm + opt_.control_offset_mm * pose.axis;
      const int n = std::clamp(static_cast<int>(std::ceil(rad2deg(rotary_jump(qa, qb)))), 2, 720);
      bool held = true;
      for (int k = 1; k < n && held; ++k) {
        const kin::Axes q = qa + (static_cast<double>(k) / n) * (qb - qa);
        const kin::Posed p = kin_.forward(q);
        held = (p.tip_mm + opt_.control_offset_mm * p.axis - ctrl).norm() <= tol_mm_ &&
               p.axis.dot(pose.axis) >= cos_tol_axis_ && kin_.passive_violation(q).empty();
      }
      if (held) {
        check_limits(qb, next);
        emit_feed_to(qa, qb, 0.0, feed_mm_min);
        ++sum_.reorientations;
        sum_.warnings.push_back(fmt::format("{}: rotaries turned in place at CL line {} ({}), the tool held",
                                            where.str(), m.line, rotary_change(kin_, qa, qb)));
        return;
      }
    }
    // Retract along the tool axis, turn at the safe position, come back above the point, plunge.
    const double d = pol.retract_mm;
    kin::Axes up0, up1;
    cl::Move m_up = m;  // the point d above m along the CL tool axis, at next's feed
    m_up.tip_in_part_mm = pose.tip_mm + d * pose.axis;
    m_up.axis_in_part = pose.axis;
    m_up.feed_mm_per_min = feed_mm_min;
    m_up.line = next.line;
    const kin::Posed above{m_up.tip_in_part_mm, pose.axis};
    if (!kin::nearest_solution(kin_, above, qa, up0) || !kin::nearest_solution(kin_, above, qb, up1) ||
        rotary_jump(up0, qa) > kFlipCheckRad || rotary_jump(up1, qb) > kFlipCheckRad)
      throw InputError(where, fmt::format("the rotaries must flip or unwind at CL line {} ({}) but the tool cannot "
                                          "retract {:.1f} mm along its axis inside the limits "
                                          "(post.singularity.retract_mm)",
                                          m.line, rotary_change(kin_, qa, qb), d));
    stop_exactly_at_last_feed();    // no blend of the cut into the retract, nor of the plunge into the cut
    feed_linear(m, qa, m_up, up0);  // straight out along the tool axis (linearised: a PKM's joints are not)
    at_cut_ = false;                // already out
    rapid(up1, next);
    resume_blend_ = false;
    cl::Move m_back = m;
    m_back.feed_mm_per_min = feed_mm_min;
    m_back.line = next.line;
    feed_linear(m_up, up1, m_back, qb);  // and straight back in
    resume_blend_ = true;
    ++sum_.retracts;
    sum_.warnings.push_back(
        fmt::format("{}: rotaries flip or unwind at CL line {} ({}): retract {:.1f} mm along the "
                    "tool axis, turn, plunge",
                    where.str(), m.line, rotary_change(kin_, qa, qb), d));
  }

  void feed(const cl::Move& m0, const kin::Axes& q0_in, const cl::Move& m1, const kin::Axes& q1) {
    cur_line_ = m1.line;
    std::optional<kin::Axes> q0 = q0_in;
    const double fr = m1.feed_mm_per_min > 0 ? m1.feed_mm_per_min : kFallbackFeedMmMin;
    const kin::Posed pose0{m0.tip_in_part_mm, m0.axis_in_part.normalized()};
    const kin::Posed pose1{m1.tip_in_part_mm, m1.axis_in_part.normalized()};
    const bool turned = !continues_branch(pose0, q0_in, pose1, q1);
    if (turned) q0 = reconfigure(pose0, q0_in, pose1, q1, m0, m1, fr);
    if (q0) {  // else reconfigure reached m1 itself
      try {
        feed_linear(m0, *q0, m1, q1);
      } catch (const BranchChangeError&) {
        // continues_branch takes a small rotary change as continuous unchecked, but beside a singular orientation even
        // a small one can end on another branch (A changing sign): turned as for any flip. (The linearizer refuses
        // before it writes a block.)
        if (turned) throw;
        q0 = reconfigure(pose0, q0_in, pose1, q1, m0, m1, fr);
        if (q0) feed_linear(m0, *q0, m1, q1);
      }
    }
    at_cut_ = true;
    cut_move_ = m1;
    if (cut_move_.feed_mm_per_min <= 0) cut_move_.feed_mm_per_min = kFallbackFeedMmMin;
  }

  /// When moves[i] is the first point of a CL arc that can be one circular block (rotaries fixed over the whole
  /// arc, its machine-coordinate plane XY, ZX or YZ, no event inside), writes that block and returns the index
  /// of the arc's end move; else returns 0 and writes nothing. In a tilted work plane whose words are its
  /// coordinates (G68.2, CYCLE800) the arc is written in them when its normal is the plane's Z (G17 there, the
  /// plane's own XY); under Haas G254 the words stay machine words and so do the rules.
  std::size_t arc_end(const std::vector<kin::Axes>& axes, std::size_t i) {
    if (!arcs_ || i == 0) return 0;
    const bool in_plane = plane_active_ && plane_words_;
    const auto& moves = prog_.moves;
    const int a = moves[i].arc_index;
    if (a < 0 || moves[i - 1].arc_index == a || moves[i - 1].kind != cl::MotionKind::Feed) return 0;
    const cl::Arc& arc = prog_.arcs[static_cast<std::size_t>(a)];
    const std::size_t end = arc.end_move;
    if (end < i || end >= moves.size()) return 0;
    for (std::size_t k = i; k <= end; ++k)
      if (moves[k].arc_index != a || moves[k].kind != cl::MotionKind::Feed ||
          moves[k].feed_mm_per_min != moves[end].feed_mm_per_min || rotaries_differ(axes[k]))
        return 0;
    for (const cl::Event& e : prog_.events)
      if (e.before_move > i && e.before_move <= end) return 0;
    // The rotaries are fixed: the machine's linear axes follow the tip rigidly. Where do the centre and the
    // normal go?
    const kin::Axes& q0 = axes[i - 1];
    const Vec3 cl_axis = moves[i - 1].axis_in_part.normalized();
    const Vec3 lift = opt_.control_offset_mm * cl_axis;  // the controlled point (a ball centre) moves in parallel
    auto machine_xyz = [&](const Vec3& p, Vec3& out) {
      kin::Axes q = q0;
      if (!kin_.solve_for_rotaries(kin::Posed{p, cl_axis}, q)) return false;
      for (int k = 0; k < 3; ++k) out[k] = q[xyz_[static_cast<size_t>(k)]];
      return true;
    };
    // The X Y Z words of a tip p (part frame): the machine's linear axes, or in a plane its coordinates (the
    // frame of the printed angles, as add_plane_words writes them).
    auto word_xyz = [&](const Vec3& p, Vec3& out) {
      if (!in_plane) return machine_xyz(p, out);
      kin::Axes q = q0;
      if (!kin_.solve_for_rotaries(kin::Posed{p, cl_axis}, q)) return false;
      out = plane_R_.transpose() * kin_.forward(q).tip_mm;
      return true;
    };
    Vec3 c_m, cn_m;
    if (!word_xyz(arc.centre_in_part_mm + lift, c_m) ||
        !word_xyz(arc.centre_in_part_mm + lift + arc.normal_in_part, cn_m))
      return 0;
    const Vec3 n_m = cn_m - c_m;
    int w = -1;
    for (int k = 0; k < 3; ++k)
      if (std::abs(std::abs(n_m[k]) - 1.0) < 1e-9) w = k;
    if (w < 0 || std::abs(n_m.norm() - 1.0) > 1e-9) return 0;  // not a machine plane (or not a rigid map)
    if (in_plane && w != 2) return 0;                          // in a plane only its XY: other arcs are points
    // The machine's X Y Z per unit of each word (identity for machine words): the feed cap below.
    Eigen::Matrix3d word_to_machine = Eigen::Matrix3d::Identity();
    if (in_plane) {
      Vec3 at, step;
      if (!machine_xyz(arc.centre_in_part_mm + lift, at)) return 0;
      for (int j = 0; j < 3; ++j) {
        if (!machine_xyz(arc.centre_in_part_mm + lift + plane_R_.col(j), step)) return 0;
        word_to_machine.col(j) = step - at;
      }
    }
    const int plane = w == 2 ? 17 : (w == 1 ? 18 : 19);
    const int u = (w + 1) % 3, v = (w + 2) % 3;  // (X,Y) for G17, (Z,X) for G18, (Y,Z) for G19
    auto xyz_of = [&](const kin::Axes& q) {
      return in_plane ? Vec3(plane_R_.transpose() * kin_.forward(q).tip_mm) : Vec3(q[xyz_[0]], q[xyz_[1]], q[xyz_[2]]);
    };
    const Vec3 p0 = xyz_of(q0), p1 = xyz_of(axes[end]);
    const double r = arc.radius_mm;
    const double ccw_sign = n_m[w] > 0 ? 1.0 : -1.0;  // the CL's counter-clockwise, seen from +w
    const double sweep = ccw_sign * arc.sweep_rad;
    const double ang0 = std::atan2(p0[v] - c_m[v], p0[u] - c_m[u]);
    // Every CL point of the arc on the machine helix (else the map is not what we assumed: points).
    const double on_helix = 0.1 * tol_mm_;
    // In a plane its Z (from the printed angles) and the CL's normal differ by ~1e-7 rad: a helix' points project
    // some nm off, so the angle along the arc gets the slack of the distance check there.
    const double slack_rad = in_plane ? on_helix / r : 1e-9, t_slack = in_plane ? slack_rad / arc.sweep_rad : 1e-9;
    for (std::size_t k = i; k <= end; ++k) {
      const Vec3 p = xyz_of(axes[k]);
      const double rk = std::hypot(p[u] - c_m[u], p[v] - c_m[v]);
      double d = std::atan2(p[v] - c_m[v], p[u] - c_m[u]) - ang0;
      d = sweep > 0 ? std::fmod(d + 4 * kPi, 2 * kPi) : -std::fmod(-d + 4 * kPi, 2 * kPi);
      if (k == end && std::abs(d) < slack_rad) d = sweep;  // a full circle ends where it started
      const double t = d / sweep;
      if (std::abs(rk - r) > on_helix || t < -t_slack || t > 1 + t_slack ||
          std::abs(p[w] - (p0[w] + t * (p1[w] - p0[w]))) > on_helix)
        return 0;
    }
    // The centre relative to the printed start, as the control reads I J K; a short radius would be all rounding.
    const auto su = static_cast<size_t>(xyz_[static_cast<size_t>(u)]);
    if (r < 100.0 / scale_[su] || !have_word_[su]) return 0;
    BlockSpec::Arc words;
    words.clockwise = sweep < 0;
    words.plane = plane;
    words.decimals = decimals_[su];
    for (int k : {u, v}) {
      const auto s = static_cast<size_t>(xyz_[static_cast<size_t>(k)]);
      if (!have_word_[s]) return 0;
      words.ijk[static_cast<size_t>(k)] = round_half_away(c_m[k] * to_file_[s] * scale_[s]) - last_[s];
      words.write[static_cast<size_t>(k)] = true;
    }
    // Feed: the path's speed F; no machine axis exceeds max_feed (in the arc's plane each peaks at F r |sweep| / L,
    // times its share of the plane's two directions in a tilted plane).
    cur_line_ = arc.line;
    const double dw = p1[w] - p0[w];
    const double len = std::hypot(r * arc.sweep_rad, dw);
    double f_mm = moves[end].feed_mm_per_min > 0 ? moves[end].feed_mm_per_min : kFallbackFeedMmMin;
    const double programmed = f_mm;
    for (int k = 0; k < 3; ++k) {
      const double vmax = m_.axes[static_cast<size_t>(xyz_[static_cast<size_t>(k)])].max_feed;
      const double share = (r * arc.sweep_rad * std::hypot(word_to_machine(k, u), word_to_machine(k, v)) +
                            std::abs(dw * word_to_machine(k, w))) /
                           len;
      if (vmax > 0 && share > 0) f_mm = std::min(f_mm, vmax / share);
    }
    if (f_mm < programmed * (1.0 - 1e-9) && capped_blocks_++ == 0) first_capped_line_ = next_nc_line();
    start(BlockSpec::Motion::Linear);
    if (!add_words(axes[end], {0, 1, 2, 3, 4})) add_words(axes[end], {xyz_[static_cast<size_t>(u)]}, true);
    blk_.arc = words;
    set_mode94();
    std::optional<double> fw;
    const double f = f_mm * feed_to_file_;
    if (std::abs(f - last_feed_) > 1e-9) {
      fw = f;
      last_feed_ = f;
    }
    emit(fw);
    ++sum_.arc_blocks;
    cur_ = axes[end];
    at_cut_ = true;
    cut_move_ = moves[end];
    if (cut_move_.feed_mm_per_min <= 0) cut_move_.feed_mm_per_min = kFallbackFeedMmMin;
    return end;
  }

  /// The block time (minutes) for a move qa -> qb at the programmed feed, slowed so that no axis exceeds its
  /// max_feed; counts the blocks slowed so.
  double block_minutes(const kin::Axes& qa, const kin::Axes& qb, double programmed_minutes) {
    double minutes = programmed_minutes;
    for (int i = 0; i < 5; ++i) {
      const double vmax = m_.axes[static_cast<size_t>(i)].max_feed;
      if (vmax <= 0) continue;
      // The move as the control sees it is between the printed (rounded) words: a short block's rounding may
      // make it longer than the model's.
      const double f = to_file_[static_cast<size_t>(i)] * scale_[static_cast<size_t>(i)];
      const double printed = std::abs(static_cast<double>(round_half_away(qb[i] * f) - round_half_away(qa[i] * f))) / f;
      minutes = std::max(minutes, std::max(std::abs(qb[i] - qa[i]), printed) / vmax);
    }
    if (minutes > programmed_minutes * (1.0 + 1e-9) + 1e-12 && programmed_minutes > 0) {
      if (capped_blocks_++ == 0) first_capped_line_ = next_nc_line();
    }
    return std::max(minutes, 1e-6);
  }

  /// The length an RS274 control measures a G94 block by: the linear words' distance (file units), else the
  /// rotary words' angle (deg).
  [[nodiscard]] double word_length(const kin::Axes& wa, const kin::Axes& wb) const {
    double lin2 = 0.0, rot2 = 0.0;
    for (int i = 0; i < 5; ++i) {  // between the printed (rounded) words, as the control measures it
      const double f = to_file_[static_cast<size_t>(i)] * scale_[static_cast<size_t>(i)];
      const double d =
          static_cast<double>(round_half_away(wb[i] * f) - round_half_away(wa[i] * f)) / scale_[static_cast<size_t>(i)];
      (m_.axes[static_cast<size_t>(i)].rotary() ? rot2 : lin2) += d * d;
    }
    return lin2 > 1e-18 ? std::sqrt(lin2) : std::sqrt(rot2);
  }

  /// Feed from q0 (at m0) to q1 (at m1) on one branch, linearised so that the tip stays within the
  /// tolerance of the straight CL segment and the axis within its tolerance of the interpolated CL axis.
  void feed_linear(const cl::Move& m0, const kin::Axes& q0, const cl::Move& m1, const kin::Axes& q1) {
    const double feed_mm_min = m1.feed_mm_per_min > 0 ? m1.feed_mm_per_min : kFallbackFeedMmMin;
    Linearizer::Stats st;
    bool split = false;
    if (!rotaries_differ(q1) && traits_.parallel) {
      // A parallel machine's legs, moved linearly, move the tip straight only approximately (a 48 mm plunge on the
      // XMINI bows by 0.03 mm): one block where that is within the tolerance, else the linearizer's pieces.
      Linearizer::ClAxes ends;
      lin_.split(m0, q0, m1, q1, prog_.file, pieces_, st, cl_axes(m0, m1, ends));
      split = pieces_.size() > 1;
    }
    if (!rotaries_differ(q1) && !split) {
      // Pure linear motion: the machine moves straight, exactly the CL segment.
      start(BlockSpec::Motion::Linear);
      if (!add_words(q1, {0, 1, 2, 3, 4})) return;  // a repeated point: nothing to do
      set_mode94();
      const double len_mm = (q1 - q0).norm();  // linear axes only differ
      const double programmed = len_mm / feed_mm_min;
      const double minutes = block_minutes(q0, q1, programmed);
      const double f = (minutes > programmed * (1.0 + 1e-9) ? len_mm / minutes : feed_mm_min) * feed_to_file_;
      std::optional<double> fw;
      if (std::abs(f - last_feed_) > 1e-9) {
        fw = f;
        last_feed_ = f;
      }
      emit(fw);
      cur_ = q1;
      return;
    }
    if (!split && !split_ahead(m0, q0, m1, q1, st)) {
      Linearizer::ClAxes ends;
      lin_.split(m0, q0, m1, q1, prog_.file, pieces_, st, cl_axes(m0, m1, ends));
    }
    sum_.inserted_points += st.inserted_points;
    sum_.ik_calls += st.ik_calls;
    sum_.max_checked_tip_deviation_mm = std::max(sum_.max_checked_tip_deviation_mm, st.max_checked_tip_deviation_mm);
    for (auto& w : st.warnings) sum_.warnings.push_back(std::move(w));
    kin::Axes qa = q0;
    for (const auto& pc : pieces_) {
      emit_timed(qa, pc.q_end, pc.path_mm, feed_mm_min);
      qa = pc.q_end;
    }
    cur_ = q1;
  }

  /// The CL's own axes at the ends of the program's segment m0 -> m1 (both moves of prog_), in `ends`; null where
  /// no cone reference was given or the moves are not consecutive moves of the program.
  const Linearizer::ClAxes* cl_axes(const cl::Move& m0, const cl::Move& m1, Linearizer::ClAxes& ends) const {
    const cl::Program* ref = opt_.cone_reference;
    const auto& moves = prog_.moves;
    if (!ref || &m1 <= moves.data() || &m1 >= moves.data() + moves.size()) return nullptr;
    const auto i = static_cast<std::size_t>(&m1 - moves.data());
    if (&m0 != &moves[i - 1] || i >= ref->moves.size()) return nullptr;
    ends = {ref->moves[i - 1].axis_in_part, ref->moves[i].axis_in_part};
    return &ends;
  }

  /// One segment split ahead (split_ahead).
  struct Ahead {
    bool ready = false;
    std::vector<Linearizer::Piece> pieces;
    Linearizer::Stats stats;
  };

  /// The linearisation of a CL segment is a pure function of its ends and their axis values, and most of the
  /// post's time: the segments ahead (moves[i - 1] -> moves[i] at axes[i - 1], axes[i]) are split in parallel, a
  /// window at a time, and taken from there when the sequencer asks for exactly that segment. While the sequencer
  /// works through one window the next is split in the background, so the two overlap. A segment whose split
  /// throws, or one the sequencer asks for with other axis values (after a retract or flip), is split here as
  /// before, so the output and the errors are those of the sequential post. Not on models whose FK/IK depend on
  /// call order (the XMINI): there the numbers must come in order.
  bool split_ahead(const cl::Move& m0, const kin::Axes& q0, const cl::Move& m1, const kin::Axes& q1,
                   Linearizer::Stats& st) {
    if (!axes_ || traits_.forward_depends_on_call_order) return false;
    const auto& moves = prog_.moves;
    if (&m1 <= moves.data() || &m1 >= moves.data() + moves.size()) return false;
    const std::size_t i = static_cast<std::size_t>(&m1 - moves.data());
    const auto& axes = *axes_;
    if (&m0 != &moves[i - 1] || i >= axes.size() || q0 != axes[i - 1] || q1 != axes[i]) return false;
    if (i < ahead_begin_ || i >= ahead_begin_ + ahead_.size()) {
      if (next_pending_) {
        next_job_.wait();
        next_pending_ = false;
      }
      if (i >= next_begin_ && i < next_begin_ + next_.size()) {
        ahead_.swap(next_);
        ahead_begin_ = next_begin_;
      } else {
        ahead_begin_ = i;
        split_window(ahead_, i, std::min(moves.size(), i + kAheadWindow));
      }
      // The window after this one, beside the sequencer.
      const std::size_t begin = ahead_begin_ + ahead_.size();
      if (begin < moves.size()) {
        next_begin_ = begin;
        next_pending_ = true;
        next_job_.run(
            [this, begin, end = std::min(moves.size(), begin + kAheadWindow)] { split_window(next_, begin, end); });
      } else {
        next_.clear();
      }
    }
    Ahead& a = ahead_[i - ahead_begin_];
    if (!a.ready) return false;
    a.ready = false;
    pieces_.swap(a.pieces);
    st = std::move(a.stats);
    return true;
  }

  /// Splits the segments ending at moves [begin, end) into `window` (in parallel; reads only the program, the axes
  /// and lin_proto_, so it may run beside the sequencer).
  void split_window(std::vector<Ahead>& window, std::size_t begin, std::size_t end) const {
    const auto& moves = prog_.moves;
    const auto& axes = *axes_;
    window.assign(end - begin, Ahead{});
    parallel_range(begin, end, 64, [&](const tbb::blocked_range<std::size_t>& r) {
      Linearizer lin = lin_proto_;  // its scratch stack is per task
      for (std::size_t k = r.begin(); k != r.end(); ++k) {
        if (moves[k].kind == cl::MotionKind::Rapid || moves[k - 1].kind == cl::MotionKind::Rapid) continue;
        Ahead& a = window[k - begin];
        try {
          Linearizer::ClAxes ends;
          lin.split(moves[k - 1], axes[k - 1], moves[k], axes[k], prog_.file, a.pieces, a.stats,
                    cl_axes(moves[k - 1], moves[k], ends));
          a.ready = true;
        } catch (...) {  // split again in order, where it throws for the sequential post too
          a = Ahead{};
        }
      }
    });
  }

  /// A feed block qa -> qb that covers tip_len_mm of the CL path: inverse time (G93) where the dialect has it,
  /// else a per-minute F that gives the same block time by the control's own measure of the block length.
  void emit_timed(const kin::Axes& qa, const kin::Axes& qb, double tip_len_mm, double feed_mm_min) {
    const double minutes = block_minutes(qa, qb, tip_len_mm / feed_mm_min);
    start(BlockSpec::Motion::Linear);
    if (!add_words(qb, {0, 1, 2, 3, 4})) return;
    const bool after_straight_feed = corner_open_;  // emit() closes it
    if (inverse_time_) {
      if (!mode93_) {
        blk_.feed_mode = BlockSpec::FeedMode::InverseTime;
        mode93_ = true;
      }
      last_feed_ = -1;
      emit(std::min(1.0 / minutes, 999999.0));
    } else {
      const double f = word_length(qa, qb) / minutes;
      last_feed_ = f;
      emit(f);
    }
    // The corner with the block before, when that one was a straight feed block ending here and the control
    // blends it (not in exact path around a retract).
    if (bound_corners_ && after_straight_feed && prev_blk_.tracked() && !exact_ && prev_blk_.mode != exact_words_ &&
        qa == corner_q1_ && !(plane_active_ && plane_words_))
      bound_corner_blend(corner_q0_, qa, qb);
    corner_q0_ = qa;
    corner_q1_ = qb;
    corner_open_ = true;
  }

  void emit_feed_to(const kin::Axes& from, const kin::Axes& q, double tip_len_mm, double feed_mm_min) {
    emit_timed(from, q, tip_len_mm, feed_mm_min);
    cur_ = q;
  }

  // --- Retract along the tool axis (machines without a Z axis, e.g. the XMINI; Cartesian mode) -----

  /// The point where the tip, leaving along the tool axis (or vertically when the axis is nearly
  /// horizontal), reaches the plane z = safe_z_mm. False when the tip is already at or above it.
  bool retract_point(const Vec3& tip, const Vec3& axis, Vec3& up) const {
    return kin::axial_retract_point(tip, axis, m_.post.safe_z_mm, tol::kLimitSlackMm, up);
  }

  /// Under tool-tip control: the point up the tool axis from the tip (machine axes q there) where the machine's
  /// Z reaches the safe Z; on a machine without one, where the tip reaches the plane z = safe_z_mm. False when
  /// already there, or when the tool axis does not lift the machine's Z.
  bool tcp_retract_point(const Vec3& tip, const Vec3& axis, const kin::Axes& q, Vec3& up) const {
    if (z_ < 0) return retract_point(tip, axis, up);
    const Vec3 dir = axis.normalized();
    kin::Axes q1 = q;  // the same rotaries, the tip 1 mm up the axis: the linear axes are affine in it
    if (!kin_.solve_for_rotaries(kin::Posed{tip + dir, dir}, q1)) return false;
    const double slope = q1[z_] - q[z_];
    if (slope < kin::kMinRetractAxisZ) return false;
    const double d = (safe_z_ - q[z_]) / slope;
    if (d <= tol::kLimitSlackMm) return false;
    up = tip + d * dir;
    return true;
  }

  /// Joint values with the tip of q moved along its tool axis to the safe plane, the axis kept (by IK).
  kin::Axes pkm_retracted(const kin::Axes& q, const SourceLoc& where) {
    kin::Axes out;
    Vec3 up;
    if (!kin::retract_along_axis(kin_, q, m_.post.safe_z_mm, tol::kLimitSlackMm, out, &up))
      throw InputError(where, fmt::format("cannot retract the tool along its axis to the safe plane z = {:.3f} mm "
                                          "(post.safe_z_mm): no axis values inside the limits put the tip at "
                                          "({:.3f}, {:.3f}, {:.3f}) with this tool axis",
                                          m_.post.safe_z_mm, up.x(), up.y(), up.z()));
    return out;
  }

  /// Retract before a tool change and at the end of the program.
  void axis_retract(const SourceLoc& where) {
    if (!axis_retract_) return;
    if (cart_) {
      Vec3 up;
      if (!tcp_retract_point(cart_tip_, cart_axis_, cart_q_, up)) return;
      kin::Axes v = cur_;
      int k = 0;
      for (int i = 0; i < 5; ++i)
        if (!m_.axes[static_cast<size_t>(i)].rotary()) v[i] = up[k++];
      emit_g0(v);
      track_control(v, cart_axis_);
      cart_tip_ = up;
      kin::Axes q_up = cart_q_;
      if (kin_.solve_for_rotaries(kin::Posed{up, cart_axis_}, q_up)) cart_q_ = q_up;
      return;
    }
    emit_g0(pkm_retracted(cur_, where));
  }

  /// Joint-space rapid to q with a rotary change: retract along the current tool axis, turn to q's tool
  /// axis at the safe plane, go above q (along its axis); the caller then plunges to q.
  void pkm_reposition(const kin::Axes& q, const cl::Move& mv) {
    const SourceLoc where{prog_.file, mv.line, 0};
    if (!have_state_) {
      emit_g0(pkm_retracted(q, where));
      return;
    }
    kin::Axes up, turned, above;  // the planner's swept check sweeps the same moves
    if (!kin::reposition_at_plane(kin_, cur_, q, m_.post.safe_z_mm, tol::kLimitSlackMm, up, turned, above)) {
      // The retract that leaves the limits says so (the one above q first).
      (void)pkm_retracted(q, where);
      (void)pkm_retracted(cur_, where);
      CSCAM_CHECK(false, "reposition_at_plane failed where both retracts succeed");
    }
    emit_g0(up);
    emit_g0(turned);
    emit_g0(above);
  }

  // --- Cartesian mode: one block per CL point, the control interpolates ------------------------

  /// The words of a Cartesian block in the machine's axis slots: tip in the linear slots, in the
  /// rotary slots the machine's rotaries (serial: they alone set the tool vector) or, for a virtual-wrist
  /// model (the XMINI), the virtual wrist angles of the tool vector (xmini_virtual_ca).
  kin::Axes cartesian_words(const Vec3& tip, const Vec3& axis, const kin::Axes& q) const {
    kin::Axes v = q;
    int k = 0;
    for (int i = 0; i < 5; ++i)
      if (!m_.axes[static_cast<size_t>(i)].rotary()) v[i] = tip[k++];
    if (traits_.tcp_rotary_words == kin::Traits::TcpRotaryWords::VirtualWrist) {
      const auto rp = kin_.rotary_pair();
      const auto ca = xmini_virtual_ca(axis, q[rp[0]], q[rp[1]]);
      v[rp[0]] = ca[0];
      v[rp[1]] = ca[1];
    }
    return v;
  }

  /// Adds the tool vector to the block when the rotary state changed (vector form of tool-tip control).
  void add_vector(const Vec3& axis, bool rot_changed) {
    if (vectors_ && rot_changed) blk_.tool_vector = std::array<double, 3>{axis.x(), axis.y(), axis.z()};
  }

  void cartesian(const cl::Move& mv, const kin::Axes& q) {
    cur_line_ = mv.line;
    const Vec3 axis = mv.axis_in_part.normalized();
    const kin::Axes v = cartesian_words(mv.tip_in_part_mm, axis, q);
    if (!have_state_ || mv.kind == cl::MotionKind::Rapid) {
      if (axis_retract_ && rotaries_differ(v)) {
        if (have_state_) axis_retract(SourceLoc{prog_.file, mv.line, 0});
        Vec3 above;
        if (tcp_retract_point(mv.tip_in_part_mm, axis, q, above)) {
          kin::Axes va = v;
          int k = 0;
          for (int i = 0; i < 5; ++i)
            if (!m_.axes[static_cast<size_t>(i)].rotary()) va[i] = above[k++];
          turn_stepwise(va);
          const bool rot = rotaries_differ(va);
          start(BlockSpec::Motion::Rapid);
          if (add_words(va, {0, 1, 2, 3, 4})) {
            add_vector(axis, rot);
            set_mode94();
            emit();
          }
          cur_ = va;
          track_control(va, axis);
        }
      }
      turn_stepwise(v);
      const bool rot = rotaries_differ(v);
      start(BlockSpec::Motion::Rapid);
      if (add_words(v, {0, 1, 2, 3, 4})) {
        add_vector(axis, rot);
        set_mode94();
        emit();
      }
    } else {
      const double feed_mm_min = mv.feed_mm_per_min > 0 ? mv.feed_mm_per_min : kFallbackFeedMmMin;
      if (!vectors_ && traits_.tcp_rotary_words == kin::Traits::TcpRotaryWords::MachineAngles) {
        const kin::Posed pose0{cart_tip_, cart_axis_}, pose1{mv.tip_in_part_mm, axis};
        if (!continues_branch(pose0, cart_q_, pose1, q)) tcp_reconfigure(pose0, pose1, q, mv, feed_mm_min);
      }
      tcp_pieces(cart_move_, cart_q_, mv, q);
      for (const auto& pc : tcp_pieces_) emit_tcp_feed(pc.tip, pc.axis, pc.q, feed_mm_min);
    }
    if (!have_state_ || mv.kind == cl::MotionKind::Rapid) track_control(v, axis);
    cur_ = v;
    cart_q_ = q;
    cart_tip_ = mv.tip_in_part_mm;
    cart_axis_ = axis;
    cart_move_ = mv;
    have_state_ = true;
  }

  /// Under tool-tip control with the machine's rotary angles as words: the axis values at the last point (cart_q_,
  /// pose0) and q1 (at mv) lie on different branches or windings, and the words' linear interpolation would swing
  /// the tool through other orientations on the path. As reconfigure does in machine coordinates: retract along the
  /// tool axis, turn the rotary words there (a rapid; the control holds the tip), plunge back; cart_q_ is then q1's
  /// branch at pose0, from which the cut to mv continues.
  void tcp_reconfigure(const kin::Posed& pose0, const kin::Posed& pose1, const kin::Axes& q1, const cl::Move& mv,
                       double feed_mm_min) {
    const SourceLoc where{prog_.file, mv.line, 0};
    const kin::Axes q0 = cart_q_;
    refuse_if_asked(q0, q1, cart_move_, mv);
    kin::Axes q0n;
    if (!branch_back(pose0, pose1, q1, q0n)) q0n = nearest_at_start(pose0, q0, q1, cart_move_, mv);
    if (rotary_jump(q0, q0n) < 1e-9) return;  // tracking stalled near a singularity: same branch after all
    const double d = m_.post.singularity.retract_mm;
    const Vec3 up = pose0.tip_mm + d * pose0.axis;
    kin::Axes q_up = q0, qn_up = q0n;
    if (!kin_.solve_for_rotaries(kin::Posed{up, pose0.axis}, q_up) ||
        !kin_.solve_for_rotaries(kin::Posed{up, pose0.axis}, qn_up) || !kin_.check_limits(q_up).empty() ||
        !kin_.check_limits(qn_up).empty())
      throw InputError(where, fmt::format("the rotaries must flip or unwind before CL line {} ({}) but the tool cannot "
                                          "retract {:.1f} mm along its axis inside the limits "
                                          "(post.singularity.retract_mm)",
                                          mv.line, rotary_change(kin_, q0, q0n), d));
    stop_exactly_at_last_feed();
    emit_tcp_feed(up, pose0.axis, q_up, feed_mm_min);  // out along the tool axis
    const kin::Axes v = cartesian_words(up, pose0.axis, qn_up);
    emit_g0(v);
    track_control(v, pose0.axis);
    cart_q_ = qn_up;
    resume_blend_ = false;
    emit_tcp_feed(pose0.tip_mm, pose0.axis, q0n, feed_mm_min);  // and straight back in
    resume_blend_ = true;
    ++sum_.retracts;
    sum_.warnings.push_back(
        fmt::format("{}: rotaries flip or unwind before CL line {} ({}): retract {:.1f} mm along "
                    "the tool axis, turn, plunge",
                    where.str(), mv.line, rotary_change(kin_, q0, q0n), d));
  }

  /// The tool axis that the words v (tip + rotary words) give, as the control interpolates them.
  bool axis_of_words(const kin::Axes& v, Vec3& axis) const {
    const auto rp = kin_.rotary_pair();
    if (traits_.tcp_rotary_words == kin::Traits::TcpRotaryWords::VirtualWrist) {
      const double c = v[rp[0]], a = v[rp[1]];
      axis = Vec3(-std::sin(a) * std::sin(c), -std::sin(a) * std::cos(c), std::cos(a));
      return true;
    }
    Vec3 tip;
    int k = 0;
    for (int i = 0; i < 5; ++i)
      if (!m_.axes[static_cast<size_t>(i)].rotary()) tip[k++] = v[i];
    return kin_.tool_axis_at(v[rp[0]], v[rp[1]], tip, axis);
  }

  struct TcpPiece {
    Vec3 tip, axis;
    kin::Axes q;
  };

  /// The linearizer of tool-tip control: the control moves the tip straight (exactly the CL segment) and
  /// interpolates the rotary words linearly; where that turns the axis away from the CL's interpolated axis by
  /// more than the axis tolerance, points are inserted (tip on the segment, axis on the CL's great circle).
  void tcp_pieces(const cl::Move& m0, const kin::Axes& q0, const cl::Move& m1, const kin::Axes& q1) {
    tcp_pieces_.clear();
    const Vec3 P0 = m0.tip_in_part_mm, P1 = m1.tip_in_part_mm;
    const Slerp axis(m0.axis_in_part.normalized(), m1.axis_in_part.normalized());
    struct Span {
      double sa, sb;
      kin::Axes qa, qb;
      int depth;
    };
    std::vector<Span> stack{{0.0, 1.0, q0, q1, 0}};
    while (!stack.empty()) {
      const Span sp = stack.back();
      stack.pop_back();
      const Vec3 ta = P0 + sp.sa * (P1 - P0), tb = P0 + sp.sb * (P1 - P0);
      const kin::Axes wa = cartesian_words(ta, axis(sp.sa), sp.qa), wb = cartesian_words(tb, axis(sp.sb), sp.qb);
      bool bad = false;
      if (opt_.linearise && sp.depth < opt_.max_subdivision_depth) {
        const Vec3 ua = axis(sp.sa), ub = axis(sp.sb);
        for (double t : {0.5, 0.25, 0.75}) {
          Vec3 u;
          bool ok = true;
          if (vectors_) {  // the vector on the great circle, as the gate reads it (gnomonic coordinates)
            ok = ua.z() > 0 && ub.z() > 0;
            u = Vec3(ua.x() / ua.z() + t * (ub.x() / ub.z() - ua.x() / ua.z()),
                     ua.y() / ua.z() + t * (ub.y() / ub.z() - ua.y() / ua.z()), 1.0)
                    .normalized();
          } else {
            ok = axis_of_words(wa + t * (wb - wa), u);
          }
          if (!ok || u.dot(axis(sp.sa + t * (sp.sb - sp.sa))) < cos_tol_axis_) {
            bad = true;
            break;
          }
        }
      }
      if (bad) {
        const double sm = 0.5 * (sp.sa + sp.sb);
        const Vec3 um = axis(sm);
        kin::Axes qm;
        bool jumped = false;
        const kin::Posed from{ta, axis(sp.sa)}, to{P0 + sm * (P1 - P0), um};
        ++sum_.ik_calls;
        if (kin::track_checked(kin_, sp.qa, from, to, qm, jumped) && !jumped) {
          check_limits(qm, m1);
          ++sum_.inserted_points;
          stack.push_back({sm, sp.sb, qm, sp.qb, sp.depth + 1});
          stack.push_back({sp.sa, sm, sp.qa, qm, sp.depth + 1});
          continue;
        }
      }
      tcp_pieces_.push_back({tb, axis(sp.sb), sp.qb});
    }
  }

  /// The machine axes the control moves to for the tip words v (IK nearest to its previous axes, as the gate
  /// reads the program back).
  void track_control(const kin::Axes& v, const Vec3& cl_axis) {
    Vec3 tip, u = cl_axis;
    int k = 0;
    for (int i = 0; i < 5; ++i)
      if (!m_.axes[static_cast<size_t>(i)].rotary()) tip[k++] = v[i];
    if (!vectors_ && !axis_of_words(v, u)) return;
    kin::Axes sol;
    if (kin::nearest_solution(kin_, kin::Posed{tip, u}, ctrl_q_, sol)) ctrl_q_ = sol;
  }

  /// One tool-tip-control feed block to (tip, axis) with machine axes q there.
  void emit_tcp_feed(const Vec3& tip, const Vec3& axis, const kin::Axes& q, double feed_mm_min) {
    const kin::Axes v = cartesian_words(tip, axis, q);
    const bool rot = rotaries_differ(v);
    start(BlockSpec::Motion::Linear);
    if (add_words(v, {0, 1, 2, 3, 4})) {
      add_vector(axis, rot);
      set_mode94();
      // The control moves the tip at F; slowed so that no machine axis exceeds its max_feed.
      const double tip_mm = (tip - cart_tip_).norm();
      const double programmed = tip_mm / feed_mm_min;
      // Judged by the planned axes and by what the control computes from the words (its IK nearest to where it
      // is: near a singularity it may turn a rotary much more than the plan).
      const kin::Axes ctrl_before = ctrl_q_;
      track_control(v, axis);
      const double minutes =
          std::max(block_minutes(cart_q_, q, programmed), block_minutes(ctrl_before, ctrl_q_, programmed));
      const double f =
          minutes > programmed * (1.0 + 1e-9) ? word_length(cur_, v) / minutes : feed_mm_min * feed_to_file_;
      std::optional<double> fw;
      if (std::abs(f - last_feed_) > 1e-9) {
        fw = f;
        last_feed_ = f;
      }
      emit(fw);
    }
    cur_ = v;
    cart_q_ = q;
    cart_tip_ = tip;
    cart_axis_ = axis;
  }

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
  bool at_cut_ = false;      ///< the last motion was a feed: the tool may be in the material
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

}  // namespace

std::vector<std::string> dialects() { return dialect_names(); }

bool can_follow(const kin::Kinematics& kinematics, const machine::Machine& machine, const Options& options,
                const kin::Posed& p0, const kin::Axes& q0, const kin::Posed& p1, const kin::Axes& q1) {
  Linearizer lin(kinematics, linearizer_settings(machine, options));
  cl::Move m0, m1;
  m0.tip_in_part_mm = p0.tip_mm;
  m0.axis_in_part = p0.axis;
  m1.tip_in_part_mm = p1.tip_mm;
  m1.axis_in_part = p1.axis;
  std::vector<Linearizer::Piece> pieces;
  Linearizer::Stats stats;
  try {
    lin.split(m0, q0, m1, q1, std::string(), pieces, stats);
  } catch (const InputError&) {
    return false;  // where the post would refuse the segment (a flip, or the rotaries turning too fast)
  }
  return true;
}

namespace {

/// A std::ostringstream sink that nothing was written to yet (the CLI's, the benchmark's) gets room for the expected
/// text at once: it would otherwise double its buffer some twenty times for a million-block program, copying the text
/// and faulting in twice its size. Room never written costs no memory; a longer text regrows as before.
void reserve_text(std::ostream& out, std::size_t bytes) {
  auto* s = dynamic_cast<std::ostringstream*>(&out);
  if (s == nullptr || s->tellp() != std::streampos(0) || !s->view().empty()) return;
  std::string room;
  room.reserve(bytes);
  s->str(std::move(room));
}

}  // namespace

void write_nc(std::ostream& out, const cl::Program& program, const machine::Machine& machine,
              const kin::Kinematics& kinematics, const std::vector<kin::Axes>& axes, const Options& options,
              Summary& summary) {
  CSCAM_CHECK(axes.size() == program.moves.size(), "one axis vector per CL move");
  CSCAM_CHECK(!options.cone_reference || options.cone_reference->moves.size() == program.moves.size(),
              "the cone's reference CL has the program's moves");
  reserve_text(out, 96 * program.moves.size() + (std::size_t{1} << 16));  // ~50-65 bytes a block, a block a move
  {
    Summary probe;
    if (Sequencer(out, program, machine, kinematics, options, probe).planes_only(axes)) {
      Options machine_words = options;
      machine_words.tcp = false;
      Sequencer w(out, program, machine, kinematics, machine_words, summary);
      summary.warnings.push_back(
          fmt::format("{}: tool-tip control asked for, but every stretch is cut in a tilted work plane: written in "
                      "machine coordinates (TCP would be cancelled around every plane)",
                      program.file));
      w.run(axes);
      return;
    }
  }
  Sequencer w(out, program, machine, kinematics, options, summary);
  w.run(axes);
}

}  // namespace cscam::post
