// The motion sequencer (sequencer.hpp): construction from the machine and the options, the run over the program,
// CL events, the program's end, the buffer and its NC line map, and the words and blocks themselves.
#include "sequencer.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <string_view>

#include "cscam/core/error.hpp"
#include "cscam/core/units.hpp"

namespace cscam::post::detail {

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

void Sequencer::warn_tcp_without_trunnion_kinematics(const std::string& dialect) {
  // LinuxCNC's M428 is the remap of its sample configurations' switchable trunnion kinematics (xyzac-trt /
  // xyzbc-trt): both rotaries in the table, the outer one tilting about X (A) or Y (B), the inner one turning the part
  // about Z (C), the spindle along Z. Another machine needs switchable kinematics of its own behind M428 (a control
  // without any stops at the unknown M-code). (Within a degree: a calibrated machine's axes are a little off.)
  const double near = std::cos(deg2rad(1.0));
  auto along = [&](const Vec3& d, int k) { return std::abs(d[k]) >= near * d.norm(); };
  bool trunnion = false;
  if (m_.serial) {
    const auto& g = *m_.serial;
    std::vector<int> rot;
    for (int j : g.table_chain)
      if (g.joints[static_cast<size_t>(j)].type == kin::AxisType::Rotary) rot.push_back(j);
    if (rot.size() == 2) {
      const Vec3 outer = g.joints[static_cast<size_t>(rot[0])].direction;
      const Vec3 inner = g.joints[static_cast<size_t>(rot[1])].direction;
      trunnion = (along(outer, 0) || along(outer, 1)) && along(inner, 2) && along(g.tool_direction_home, 2);
    }
  }
  if (!trunnion)
    sum_.warnings.push_back(fmt::format(
        "{}: dialect '{}' with tool-tip control writes M428, which LinuxCNC's sample configurations map to the "
        "switchable trunnion kinematics (xyzac-trt / xyzbc-trt: A or B tilting the table, C turning on it); machine "
        "'{}' is not built that way: run the program only on a LinuxCNC whose M428 switches to this machine's own "
        "tool-tip kinematics, or post it without TCP (--no-tcp)",
        m_.file, dialect, m_.name));
}

void Sequencer::refuse_mixed_tool_lengths() const {
  // A rotary in the head turns the tool about the gauge point: in machine coordinates every tool length gives other
  // axis words, and the program is computed for one. (Under TCP the control applies each tool's own length.)
  if (cart_ || !m_.serial) return;
  const bool head_rotary = std::any_of(m_.serial->joints.begin(), m_.serial->joints.end(), [](const auto& j) {
    return j.type == kin::AxisType::Rotary && j.side == kin::Side::Head;
  });
  if (!head_rotary) return;
  const cl::Tool* first = nullptr;
  int first_line = 0;
  for (const cl::Event& e : prog_.events) {
    if (e.kind != cl::Event::Kind::ToolChange || e.tool_index < 0) continue;
    const cl::Tool& t = prog_.tools[static_cast<size_t>(e.tool_index)];
    if (!(t.length_mm > 0)) continue;
    if (!first) {
      first = &t, first_line = e.line;
    } else if (std::abs(t.length_mm - first->length_mm) > 1e-6) {
      throw InputError(
          SourceLoc{prog_.file, e.line, 0},
          fmt::format(
              "tool {} is {:.3f} mm long and tool {} (line {}) {:.3f} mm: on machine '{}', whose head carries a "
              "rotary, the machine coordinates depend on the tool length and a program without TCP is "
              "computed for one length ({:.3f} mm); post each tool's operations separately with its "
              "--tool-length, or with tool-tip control (--tcp)",
              t.number, t.length_mm, first->number, first_line, first->length_mm, m_.name,
              opt_.tool_length_mm > 0 ? opt_.tool_length_mm : m_.default_tool_length_mm));
    }
  }
}

/// The post retracts by raising the machine's Z to the safe plane: that is away from the part only if +Z moves the tool
/// back along its own axis (ISO 841: Z is the spindle's axis, + away from the work). A machine file whose `z` runs
/// across the spindle (a horizontal spindle with a vertical `z`) would have every retract drag the tool sideways
/// through the part: refused, naming the axis. Judged at home, where the file gives the tool's direction.
void Sequencer::refuse_a_sideways_retract() const {
  const kin::Axes home = kin::Axes::Zero();
  kin::Axes up = home;
  up[z_] += 1.0;  // mm
  const kin::Posed p0 = kin_.forward(home), p1 = kin_.forward(up);
  const Vec3 moved = p1.tip_mm - p0.tip_mm;  // the tip's motion relative to the part
  const double along = moved.norm() > 0 ? moved.normalized().dot(p0.axis) : 0.0;
  if (along > std::cos(deg2rad(1.0))) return;
  const auto& a = m_.axes[static_cast<size_t>(z_)];
  throw InputError(
      m_.where(fmt::format("axes[{}]", z_)),
      fmt::format("axis '{}': the post retracts by raising it to post.safe_z_mm, but +{} moves the tool along ({:.3f}, "
                  "{:.3f}, {:.3f}) while the tool points along ({:.3f}, {:.3f}, {:.3f}) (tip to spindle) at home: the "
                  "retract would {}. Name the linear axis that runs along the spindle '{}' with + away from the work "
                  "(ISO 841)",
                  a.name, a.name, moved.x(), moved.y(), moved.z(), p0.axis.x(), p0.axis.y(), p0.axis.z(),
                  along < -std::cos(deg2rad(1.0)) ? "plunge the tool into the part" : "drag the tool sideways",
                  a.name));
}

Sequencer::Sequencer(std::ostream& out, const cl::Program& program, const machine::Machine& machine,
                     const kin::Kinematics& kin, const Options& opt, Summary& summary)
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
  vectors_ =
      cart_ && m_.post.tcp_form == "vectors" && traits_.tcp_rotary_words == kin::Traits::TcpRotaryWords::MachineAngles;
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
  if (cart_ && dialect == "linuxcnc") warn_tcp_without_trunnion_kinematics(dialect);
  refuse_mixed_tool_lengths();
  z_ = traits_.retract_axis;
  if (z_ >= 0) refuse_a_sideways_retract();
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
  info_.cone_deg = opt.cone_deg;
  info_.cl_units = program.source_units == LengthUnit::Inch ? "inch" : "mm";
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
  // Modulo words (C359.5 then C0.2) mean "the short way" only where the control wraps that axis; LinuxCNC does so
  // for a joint configured as wrapped, and otherwise turns 359 deg inside the block.
  if (fmt_->name() == "linuxcnc")
    for (std::size_t i = 0; i < 5; ++i)
      if (shortest_[i])
        sum_.warnings.push_back(fmt::format(
            "{}: rotary_output shortest writes {} modulo 360 deg: LinuxCNC turns it the short way only with "
            "[AXIS_{}]WRAPPED_ROTARY = 1 in its configuration (without it, the long way inside a block)",
            machine.file, info_.letters[i], info_.letters[i]));
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
      sum_.warnings.push_back(
          fmt::format("{}: dialect {} on machine {} has no tilted work plane: 3+2 stretches are "
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
bool Sequencer::planes_only(const std::vector<kin::Axes>& axes) const {
  if (!tcp_program_ || !planes_ || prog_.moves.empty()) return false;
  for (size_t i = 0; i < prog_.moves.size(); ++i) {
    if (i > 0 && prog_.moves[i].kind != cl::MotionKind::Rapid) continue;
    if (const auto plane = plane_ahead(axes, i); plane && !*plane) return false;
  }
  return true;
}

void Sequencer::run(const std::vector<kin::Axes>& axes) {
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
    } else if (!have_state_ || off_path_ || mv.kind == cl::MotionKind::Rapid) {
      pending_plane_ = planes_ && fixed_from(axes, i) && !at_rotary_zero(axes[i]);
      if (mv.kind == cl::MotionKind::Rapid)
        rapid(axes[i], mv);
      else
        approach(axes[i], mv);
      pending_plane_ = false;
      if (const unsigned still = indexed_from(axes, i)) clamp_rotaries(still);
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

/// Writes the buffer out, but keeps the last feed block (stop_exactly_at_last_feed may still change it) unless
/// `all`.
void Sequencer::flush(bool all) {
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
void Sequencer::map_lines(int cl_line) {
  const char* const end = buf_.data() + buf_.size();
  for (const char* p = buf_.data() + scanned_;
       (p = static_cast<const char*>(std::memchr(p, '\n', static_cast<std::size_t>(end - p)))) != nullptr; ++p)
    sum_.cl_line_of_nc_line.push_back(cl_line);
  scanned_ = buf_.size();
}

/// The NC line the next line of text will be.
int Sequencer::next_nc_line() const {
  return static_cast<int>(
      sum_.cl_line_of_nc_line.size() +
      static_cast<size_t>(std::count(buf_.begin() + static_cast<std::ptrdiff_t>(scanned_), buf_.end(), '\n')));
}

// --- Program frame and CL records -----------------------------------------------------------------

void Sequencer::footer() {
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

void Sequencer::event(const cl::Event& e) {
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
      fmt_->tool_change(buf_, n, tool_h_,
                        known
                            ? fmt::format("TOOL {}: {} D{:.3f}", n, prog_.tools[static_cast<size_t>(e.tool_index)].name,
                                          prog_.tools[static_cast<size_t>(e.tool_index)].diameter_mm)
                            : std::string());
      // A tool whose first stretch is a tilted plane starts without TCP: switch_to_machine writes its plain length
      // offset there, rather than TCP on here and off again before any motion.
      if (cart_) {
        const auto plane = tcp_program_ && planes_ ? plane_ahead(*axes_, e.before_move) : std::nullopt;
        if (!plane.value_or(false)) tool_tip_control_on(e.line);
      }
      // M6 stops the spindle (LinuxCNC's interpreter, Fanuc, Haas; TOOL CALL on a TNC): where the CL had it on before
      // the change and does not switch it on again itself, it is restarted as it was.
      if (spindle_.on) {
        bool set_again = false;  // the CL switches it on (or off) itself before the next move
        const auto& ev = prog_.events;
        if (&e >= ev.data() && &e < ev.data() + ev.size())
          for (const cl::Event* x = &e + 1; x < ev.data() + ev.size() && x->before_move == e.before_move; ++x)
            set_again |= x->kind == K::SpindleOn || x->kind == K::SpindleOff;
        if (!set_again) fmt_->spindle(buf_, spindle_.rpm, spindle_.clockwise);
      }
      break;
    }
    case K::SpindleOn:
      fmt_->spindle(buf_, e.spindle_rpm, e.clockwise);
      spindle_ = Spindle{true, e.spindle_rpm, e.clockwise};
      break;
    case K::SpindleOff:
      exit_along_axis();  // leave the cut while the spindle still turns
      if (cart_ && have_state_) axis_retract(SourceLoc{prog_.file, e.line, 0});
      fmt_->spindle_off(buf_);
      spindle_.on = false;
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

// --- Words and blocks ----------------------------------------------------------------------------------

void Sequencer::check_limits(const kin::Axes& q, const cl::Move& mv) const {
  const std::string v = kin_.check_limits(q);
  if (!v.empty())
    throw InputError(SourceLoc{prog_.file, mv.line, 0},
                     fmt::format("the post refuses a block outside the limits: {}", v));
}

/// Adds the axis words of q that differ from the last written values.
bool Sequencer::add_words(const kin::Axes& q, std::initializer_list<int> which, bool force) {
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
void Sequencer::emit_per_minute(double f) {
  std::optional<double> word;
  if (std::abs(f - last_feed_) > 1e-9) {  // F is modal: written where it changes
    word = f;
    last_feed_ = f;
  }
  emit(word);
}

void Sequencer::emit(std::optional<double> feed) {
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

}  // namespace cscam::post::detail
