#include "cscam/post/post.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <charconv>
#include <cmath>
#include <limits>
#include <ostream>

#include "cscam/core/error.hpp"
#include "cscam/core/tolerances.hpp"
#include "cscam/core/units.hpp"
#include "cscam/kin/track.hpp"

namespace cscam::post {

namespace {

using Vec3 = Eigen::Vector3d;

/// Spherical interpolation of the CL tool axis between two points (angle computed once per segment).
class Slerp {
 public:
  Slerp(const Vec3& a, const Vec3& b) : a_(a), b_(b), th_(std::acos(std::clamp(a.dot(b), -1.0, 1.0))) {
    sn_ = std::sin(th_);
  }
  Vec3 operator()(double s) const {
    if (th_ < 1e-9) return ((1 - s) * a_ + s * b_).normalized();
    return (std::sin((1 - s) * th_) / sn_ * a_ + std::sin(s * th_) / sn_ * b_).normalized();
  }

 private:
  Vec3 a_, b_;
  double th_, sn_ = 0.0;
};

double point_segment_distance(const Vec3& p, const Vec3& a, const Vec3& b) {
  const Vec3 ab = b - a;
  const double L2 = ab.squaredNorm();
  const double t = L2 > 0 ? std::clamp((p - a).dot(ab) / L2, 0.0, 1.0) : 0.0;
  return (a + t * ab - p).norm();
}

/// A piece [sa, sb] of a CL segment (parameter s in [0,1]) with the axis values at its ends.
struct Piece {
  double sa, sb;
  kin::Axes qa, qb;
  int depth;
};

struct Dialect {
  std::string name;
  bool fanuc = false;
  bool cartesian = false;  ///< tip X Y Z + tool-vector rotaries; the control does the kinematics
};

Dialect make_dialect(const std::string& name) {
  if (name == "linuxcnc") return {name, false, false};
  if (name == "fanuc") return {name, true, false};
  // The XMINI (PKM): joint space is the linuxcnc output with the machine's letters (legs + wrist);
  // Cartesian mode is for a control that runs the PKM transformation itself.
  if (name == "xmini-joint") return {name, false, false};
  if (name == "xmini-cartesian") return {name, false, true};
  throw InputError(
      fmt::format("unknown post dialect '{}' (known: linuxcnc, fanuc, xmini-joint, xmini-cartesian)", name));
}

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

/// Rotary changes between two CL points below this are taken as continuing the branch without a check.
constexpr double kFlipCheckRad = 0.5235987756;  // 30 deg

/// A retract target counts only if the tool axis points up at least this much (cos of the tilt).
constexpr double kMinRetractAxisZ = 0.1;

std::string sanitize_comment(std::string s) {
  for (char& c : s)
    if (c == '(' || c == ')') c = '_';
  return s;
}

/// Writes blocks with modal suppression of unchanged axis words.
class Writer {
 public:
  Writer(std::ostream& out, const cl::Program& program, const machine::Machine& machine, const kin::Kinematics& kin,
         const Options& opt, Summary& summary)
      : out_(out), prog_(program), m_(machine), kin_(kin), opt_(opt), sum_(summary) {
    try {
      dialect_ = make_dialect(opt.dialect.empty() ? machine.post.dialect : opt.dialect);
    } catch (const InputError& e) {
      if (!opt.dialect.empty()) throw InputError("--dialect: " + e.message());
      throw InputError(machine.where("post.dialect"), e.message());  // the machine file's value
    }
    tol_mm_ = opt.tolerance_mm > 0 ? opt.tolerance_mm : machine.post.tolerance_mm;
    tol_axis_rad_ = deg2rad(opt.axis_tolerance_deg > 0 ? opt.axis_tolerance_deg : machine.post.axis_tolerance_deg);
    cos_tol_axis_ = std::cos(tol_axis_rad_);
    for (int i = 0; i < 5; ++i) {
      const auto& a = m_.axes[static_cast<size_t>(i)];
      const int d = a.rotary() ? m_.post.decimals_rotary : m_.post.decimals_linear;
      decimals_[static_cast<size_t>(i)] = d;
      scale_[static_cast<size_t>(i)] = std::pow(10.0, d);
      to_file_[static_cast<size_t>(i)] = a.rotary() ? 180.0 / kPi : 1.0;
    }
    z_ = m_.axis_index("z");
    safe_z_ = m_.post.safe_z_mm;
    if (z_ >= 0 && std::isnan(safe_z_)) safe_z_ = m_.axes[static_cast<size_t>(z_)].max;
    letters_ = m_.post.letters;
    cart_ = dialect_.cartesian || m_.post.tcp;
    if (cart_) {  // the tip's words are X Y Z, whatever the machine's linear axes are called
      int k = 0;
      for (size_t i = 0; i < 5; ++i)
        if (!m_.axes[i].rotary()) letters_[i] = std::string(1, "XYZ"[k++]);
    }
    // Without a Z axis (a PKM), or in Cartesian mode, safe_z_mm is a plane z = const of the part frame
    // and the retract moves the tip along the tool axis up to it.
    axis_retract_ = (cart_ || z_ < 0) && std::isfinite(m_.post.safe_z_mm);
    buf_.reserve(1 << 16);
  }

  void run(const std::vector<kin::Axes>& axes) {
    sum_.cl_line_of_nc_line.assign(1, 0);
    header();
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
      if (cart_) {
        cartesian(mv, axes[i]);
      } else if (!have_state_ || mv.kind == cl::MotionKind::Rapid) {
        rapid(axes[i], mv);
      } else {
        feed(moves[i - 1], axes[i - 1], mv, axes[i]);
      }
      map_lines(mv.line);
      if (buf_.size() > (1 << 15)) flush();
    }
    while (ev < prog_.events.size()) {
      event(prog_.events[ev]);
      map_lines(prog_.events[ev++].line);
    }
    footer();
    map_lines(0);
    flush();
  }

 private:
  void flush() {
    out_.write(buf_.data(), static_cast<std::streamsize>(buf_.size()));
    buf_.clear();
    scanned_ = 0;
  }

  /// Attributes the NC lines written since the last call to `cl_line` (for the gate's messages).
  void map_lines(int cl_line) {
    for (; scanned_ < buf_.size(); ++scanned_)
      if (buf_[scanned_] == '\n') sum_.cl_line_of_nc_line.push_back(cl_line);
  }

  void line(std::string_view s) {
    buf_.append(s);
    buf_.push_back('\n');
  }

  void header() {
    if (dialect_.fanuc) {
      line("%");
      fmt::format_to(std::back_inserter(buf_), "O{:04d} ({})\n", 1, sanitize_comment(m_.post.program_name));
    } else {
      line("%");
      fmt::format_to(std::back_inserter(buf_), "({})\n", sanitize_comment(m_.post.program_name));
    }
    fmt::format_to(std::back_inserter(buf_), "(cscam post: machine {} dialect {} strategy {})\n",
                   sanitize_comment(m_.name), dialect_.name, sanitize_comment(opt_.strategy));
    if (!opt_.source_name.empty())
      fmt::format_to(std::back_inserter(buf_), "(source: {})\n", sanitize_comment(opt_.source_name));
    fmt::format_to(std::back_inserter(buf_), "(cscam tool_length_mm={:.4f} tolerance_mm={:.4f})\n", opt_.tool_length_mm,
                   tol_mm_);
    if (cart_)
      fmt::format_to(std::back_inserter(buf_),
                     "(cartesian: X Y Z = tool tip, {} {} = tool vector; the control runs the kinematics)\n",
                     letters_[static_cast<size_t>(kin_.rotary_pair()[0])],
                     letters_[static_cast<size_t>(kin_.rotary_pair()[1])]);
    line("G21 G90 G94 G17 G40 G49 G80");
    mode93_ = false;
  }

  void footer() {
    exit_along_axis();
    if (!cart_ && z_ >= 0 && have_state_) {
      fmt::format_to(std::back_inserter(buf_), "G0 {}{}\n", letters_[static_cast<size_t>(z_)], fmt_axis(z_, safe_z_));
    } else if (have_state_) {
      axis_retract(SourceLoc{prog_.file});
    }
    line("M5");
    line("M9");
    line(dialect_.fanuc ? "M30" : "M2");
    line("%");
  }

  void event(const cl::Event& e) {
    using K = cl::Event::Kind;
    switch (e.kind) {
      case K::ToolChange: {
        const int n = (e.tool_index >= 0 && static_cast<size_t>(e.tool_index) < prog_.tools.size())
                          ? prog_.tools[static_cast<size_t>(e.tool_index)].number
                          : 0;
        if (e.tool_index >= 0 && static_cast<size_t>(e.tool_index) < prog_.tools.size())
          fmt::format_to(std::back_inserter(buf_), "(TOOL {}: {} D{:.3f})\n", n,
                         sanitize_comment(prog_.tools[static_cast<size_t>(e.tool_index)].name),
                         prog_.tools[static_cast<size_t>(e.tool_index)].diameter_mm);
        // Retract before the change so the new tool does not come down into the part.
        exit_along_axis();
        if (!cart_ && z_ >= 0 && have_state_)
          emit_safe_z();
        else if (have_state_)
          axis_retract(SourceLoc{prog_.file, e.line, 0});
        // TCP on a serial machine: G43.4 (LinuxCNC, Fanuc). The XMINI's control runs its own transformation.
        const bool g434 = cart_ && m_.kind != machine::ModelKind::Xmini;
        fmt::format_to(std::back_inserter(buf_), "T{} M6\n{} H{}\n", n, g434 ? "G43.4" : "G43", n);
        break;
      }
      case K::SpindleOn:
        fmt::format_to(std::back_inserter(buf_), "S{:.0f} {}\n", e.spindle_rpm, e.clockwise ? "M3" : "M4");
        break;
      case K::SpindleOff:
        exit_along_axis();  // leave the cut while the spindle still turns
        line("M5");
        break;
      case K::CoolantOn:
        line(e.text == "MIST" ? "M7" : "M8");
        break;
      case K::CoolantOff:
        line("M9");
        break;
      case K::Comment:
        if (!e.text.empty()) fmt::format_to(std::back_inserter(buf_), "({})\n", sanitize_comment(e.text));
        break;
      case K::OperationStart:
        fmt::format_to(std::back_inserter(buf_), "(OPERATION {})\n", sanitize_comment(e.text));
        break;
      case K::Stop:
        line("M0");
        break;
    }
  }

  std::string fmt_axis(int i, double v) const {
    return fmt::format("{:.{}f}", v * to_file_[static_cast<size_t>(i)], decimals_[static_cast<size_t>(i)]);
  }

  long long rounded(int i, double v) const {
    return std::llround(v * to_file_[static_cast<size_t>(i)] * scale_[static_cast<size_t>(i)]);
  }

  void check_limits(const kin::Axes& q, const cl::Move& mv) const {
    const std::string v = kin_.check_limits(q);
    if (!v.empty())
      throw InputError(SourceLoc{prog_.file, mv.line, 0},
                       fmt::format("the post refuses a block outside the limits: {}", v));
  }

  /// Appends the axis words of q that differ from the last written values.
  bool append_words(const kin::Axes& q, std::initializer_list<int> which, bool force = false) {
    bool any = false;
    for (int i : which) {
      const long long r = rounded(i, q[i]);
      if (!force && have_word_[static_cast<size_t>(i)] && r == last_[static_cast<size_t>(i)]) continue;
      buf_.push_back(' ');
      buf_.append(letters_[static_cast<size_t>(i)]);
      append_fixed(r, decimals_[static_cast<size_t>(i)]);
      last_[static_cast<size_t>(i)] = r;
      have_word_[static_cast<size_t>(i)] = true;
      any = true;
    }
    return any;
  }

  /// Writes r / 10^d with exactly d decimals (the value is already rounded: no float formatting needed).
  void append_fixed(long long r, int d) {
    if (r < 0) {
      buf_.push_back('-');
      r = -r;
    }
    long long p = 1;
    for (int k = 0; k < d; ++k) p *= 10;
    char tmp[32];
    auto res = std::to_chars(tmp, tmp + sizeof tmp, r / p);
    buf_.append(tmp, res.ptr);
    if (d > 0) {
      buf_.push_back('.');
      res = std::to_chars(tmp, tmp + sizeof tmp, r % p);
      const auto len = res.ptr - tmp;
      buf_.append(static_cast<size_t>(d - len), '0');
      buf_.append(tmp, res.ptr);
    }
  }

  bool rotaries_differ(const kin::Axes& q) const {
    for (int i : kin_.rotary_pair())
      if (!have_word_[static_cast<size_t>(i)] || rounded(i, q[i]) != last_[static_cast<size_t>(i)]) return true;
    return false;
  }

  void set_mode94() {
    if (mode93_) {
      buf_.append("G94 ");
      mode93_ = false;
      last_feed_ = -1;
    }
  }

  void emit_safe_z() {
    set_mode94();
    kin::Axes q = cur_;
    q[z_] = safe_z_;
    buf_.append("G0");
    append_words(q, {z_});
    buf_.push_back('\n');
    cur_[z_] = safe_z_;
    ++sum_.blocks;
  }

  /// Rapid positioning. With a rotary change: retract, rotate, position, plunge.
  void rapid(const kin::Axes& q, const cl::Move& mv) {
    const auto rp = kin_.rotary_pair();
    std::vector<int> lin;
    for (int i = 0; i < 5; ++i)
      if (i != rp[0] && i != rp[1]) lin.push_back(i);
    if (rotaries_differ(q) && z_ >= 0) {
      exit_along_axis();
      if (have_state_) emit_safe_z();
      kin::Axes at_safe = have_state_ ? cur_ : q;
      at_safe[z_] = safe_z_;
      at_safe[rp[0]] = q[rp[0]];
      at_safe[rp[1]] = q[rp[1]];
      check_limits(at_safe, mv);
      set_mode94();
      buf_.append("G0");
      if (!have_state_) {
        append_words(at_safe, {z_}, true);
        buf_.append("\nG0");
      }
      append_words(at_safe, {rp[0], rp[1]});
      const size_t mark = buf_.size();
      buf_.append("\nG0");
      kin::Axes above = q;
      above[z_] = safe_z_;
      std::vector<int> xy;
      for (int i : lin)
        if (i != z_) xy.push_back(i);
      bool any = false;
      for (int i : xy) any = append_words(above, {i}, !have_word_[static_cast<size_t>(i)]) || any;
      if (!any) buf_.resize(mark);  // already above the point: no empty block (a control would still move)
      buf_.push_back('\n');
      sum_.blocks += any ? 3 : 2;
    }
    if (rotaries_differ(q) && z_ < 0 && axis_retract_) pkm_reposition(q, mv);
    set_mode94();
    buf_.append("G0");
    if (!append_words(q, {0, 1, 2, 3, 4}))
      buf_.append(fmt::format(" {}{}", letters_[static_cast<size_t>(lin[0])], fmt_axis(lin[0], q[lin[0]])));
    buf_.push_back('\n');
    ++sum_.blocks;
    cur_ = q;
    have_state_ = true;
    at_cut_ = false;
  }

  /// The largest normalised deviation (1 = at tolerance) of the machine's straight joint-space move
  /// qa->qb from the CL segment P0P1 (tip) and from the interpolated CL axis.
  /// Whether the machine's straight joint-space move qa->qb leaves the tolerance of the CL segment P0P1
  /// (tip) or of the interpolated CL axis, sampled at a quarter, half and three quarters.
  bool exceeds(const kin::Axes& qa, const kin::Axes& qb, double sa, double sb, const Vec3& P0, const Vec3& P1,
               const Slerp& axis) {
    bool bad = false;
    for (double t : {0.5, 0.25, 0.75}) {
      const kin::Posed p = kin_.forward(qa + t * (qb - qa));
      const double dtip = point_segment_distance(p.tip_mm + opt_.control_offset_mm * p.axis, P0, P1);
      sum_.max_checked_tip_deviation_mm = std::max(sum_.max_checked_tip_deviation_mm, dtip);
      if (dtip > tol_mm_ || p.axis.dot(axis(sa + t * (sb - sa))) < cos_tol_axis_) {
        bad = true;
        break;
      }
    }
    return bad;
  }

  /// After a cut, before a retract that is not along the tool axis (machine Z up, a tool change, the end):
  /// feed out post.singularity.retract_mm along the tool axis first, so that a tilted tool under an
  /// overhang does not drag through it on the way up.
  void exit_along_axis() {
    if (!at_cut_ || cart_ || axis_retract_) return;
    at_cut_ = false;
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

  /// One feed block to q at a tip speed of feed_mm_min (an axis never faster than its max_feed).
  void emit_feed_to(const kin::Axes& from, const kin::Axes& q, double tip_len_mm, double feed_mm_min) {
    emit_inverse_time(from, q, tip_len_mm, feed_mm_min);
    cur_ = q;
  }

  /// q0 (at m0) and q1 (at m1) lie on different branches or windings: a rotary limit or the branch rule
  /// forces a flip or an unwind. Turns to q1's branch at m0, in place when the joint move keeps the tool
  /// pose within tolerance (at the singular point itself), else by retract along the tool axis, turn,
  /// plunge. Returns the axis values at m0 on the new branch, from which the feed to q1 continues.
  kin::Axes reconfigure(const kin::Posed& pose0, const kin::Axes& q0, const kin::Posed& pose1, const kin::Axes& q1,
                        const cl::Move& m0, const cl::Move& m1, double feed_mm_min) {
    const auto& pol = m_.post.singularity;
    const SourceLoc where{prog_.file, m1.line, 0};
    const auto rp = kin_.rotary_pair();
    auto describe = [&] {
      return fmt::format("{} {:.3f} -> {:.3f} deg, {} {:.3f} -> {:.3f} deg", m_.axes[static_cast<size_t>(rp[0])].name,
                         rad2deg(q0[rp[0]]), rad2deg(q1[rp[0]]), m_.axes[static_cast<size_t>(rp[1])].name,
                         rad2deg(q0[rp[1]]), rad2deg(q1[rp[1]]));
    };
    if (pol.flip == "refuse")
      throw InputError(where, fmt::format("the rotaries must flip or unwind between CL lines {} and {} ({}): a rotary "
                                          "limit or the branch rule forces it, and post.singularity.flip is 'refuse'",
                                          m0.line, m1.line, describe()));
    // q1's branch at m0's pose: track back from q1 so that the feed m0 -> m1 is continuous on it.
    kin::Axes q0n;
    bool jumped = false;
    if (!kin::track_checked(kin_, q1, pose1, pose0, q0n, jumped) || jumped) {
      std::string why;
      if (!kin::nearest_solution(kin_, pose0, q1, q0n, &why))
        throw InputError(where, fmt::format("the rotaries must flip or unwind between CL lines {} and {} ({}) but no "
                                            "axis values inside the limits hold the tool at CL line {}{}",
                                            m0.line, m1.line, describe(), m0.line, why.empty() ? "" : ": " + why));
    }
    if (rotary_jump(q0, q0n) < 1e-9) return q0;  // tracking stalled near a singularity: same branch after all
    // In place: the straight joint move q0 -> q0n keeps the tool pose (e.g. the primary turning while the
    // tool axis lies along it).
    if (pol.flip == "auto") {
      const Vec3 ctrl0 = pose0.tip_mm + opt_.control_offset_mm * pose0.axis;
      const int n = std::clamp(static_cast<int>(std::ceil(rad2deg(rotary_jump(q0, q0n)))), 2, 720);
      bool held = true;
      for (int k = 1; k < n && held; ++k) {
        const kin::Axes q = q0 + (static_cast<double>(k) / n) * (q0n - q0);
        const kin::Posed p = kin_.forward(q);
        held = (p.tip_mm + opt_.control_offset_mm * p.axis - ctrl0).norm() <= tol_mm_ &&
               p.axis.dot(pose0.axis) >= cos_tol_axis_ && kin_.passive_violation(q).empty();
      }
      if (held) {
        check_limits(q0n, m1);
        emit_feed_to(q0, q0n, 0.0, feed_mm_min);
        ++sum_.reorientations;
        sum_.warnings.push_back(fmt::format(
            "{}: rotaries turned in place at CL line {} ({} {:.3f} -> {:.3f} deg, {} {:.3f} -> {:.3f} deg), the tool "
            "held",
            where.str(), m0.line, m_.axes[static_cast<size_t>(rp[0])].name, rad2deg(q0[rp[0]]), rad2deg(q0n[rp[0]]),
            m_.axes[static_cast<size_t>(rp[1])].name, rad2deg(q0[rp[1]]), rad2deg(q0n[rp[1]])));
        return q0n;
      }
    }
    // Retract along the tool axis, turn at the safe position, come back above the point, plunge.
    const double d = pol.retract_mm;
    kin::Axes up0, up1;
    cl::Move m_up = m0;  // the point d above m0 along the CL tool axis, at m1's feed
    m_up.tip_in_part_mm = pose0.tip_mm + d * pose0.axis;
    m_up.axis_in_part = pose0.axis;
    m_up.feed_mm_per_min = feed_mm_min;
    m_up.line = m1.line;
    const kin::Posed above{m_up.tip_in_part_mm, pose0.axis};
    if (!kin::nearest_solution(kin_, above, q0, up0) || !kin::nearest_solution(kin_, above, q0n, up1) ||
        rotary_jump(up0, q0) > kFlipCheckRad || rotary_jump(up1, q0n) > kFlipCheckRad)
      throw InputError(where, fmt::format("the rotaries must flip or unwind between CL lines {} and {} ({}) but the "
                                          "tool cannot retract {:.1f} mm along its axis inside the limits "
                                          "(post.singularity.retract_mm)",
                                          m0.line, m1.line, describe(), d));
    feed_linear(m0, q0, m_up, up0);  // straight out along the tool axis (linearised: a PKM's joints are not)
    at_cut_ = false;                 // already out
    rapid(up1, m1);
    cl::Move m_back = m0;
    m_back.feed_mm_per_min = feed_mm_min;
    m_back.line = m1.line;
    feed_linear(m_up, up1, m_back, q0n);  // and straight back in
    ++sum_.retracts;
    sum_.warnings.push_back(
        fmt::format("{}: rotaries flip or unwind at CL line {} ({}): retract {:.1f} mm along the "
                    "tool axis, turn, plunge",
                    where.str(), m0.line, describe(), d));
    return q0n;
  }

  void feed(const cl::Move& m0, const kin::Axes& q0_in, const cl::Move& m1, const kin::Axes& q1) {
    kin::Axes q0 = q0_in;
    {
      const double fr = m1.feed_mm_per_min > 0 ? m1.feed_mm_per_min : 1000.0;
      const kin::Posed pose0{m0.tip_in_part_mm, m0.axis_in_part.normalized()};
      const kin::Posed pose1{m1.tip_in_part_mm, m1.axis_in_part.normalized()};
      if (!continues_branch(pose0, q0, pose1, q1)) q0 = reconfigure(pose0, q0, pose1, q1, m0, m1, fr);
    }
    feed_linear(m0, q0, m1, q1);
    at_cut_ = true;
    cut_move_ = m1;
    if (cut_move_.feed_mm_per_min <= 0) cut_move_.feed_mm_per_min = 1000.0;
  }

  /// Feed from q0 (at m0) to q1 (at m1) on one branch, linearised so that the tip stays within the
  /// tolerance of the straight CL segment and the axis within its tolerance of the interpolated CL axis.
  void feed_linear(const cl::Move& m0, const kin::Axes& q0, const cl::Move& m1, const kin::Axes& q1) {
    const bool rot_moves = rotaries_differ(q1);
    const double feed_mm_min = m1.feed_mm_per_min > 0 ? m1.feed_mm_per_min : 1000.0;
    if (!rot_moves) {
      // Pure linear motion: the machine moves straight, exactly the CL segment.
      set_mode94();
      buf_.append("G1");
      const bool any = append_words(q1, {0, 1, 2, 3, 4});
      if (!any) {  // a repeated point: nothing to do
        buf_.resize(buf_.size() - 2);
        if (buf_.size() >= 4 && buf_.compare(buf_.size() - 4, 4, "G94 ") == 0) buf_.resize(buf_.size() - 4);
        return;
      }
      if (std::abs(feed_mm_min - last_feed_) > 1e-9) {
        fmt::format_to(std::back_inserter(buf_), " F{:.1f}", feed_mm_min);
        last_feed_ = feed_mm_min;
      }
      buf_.push_back('\n');
      ++sum_.blocks;
      cur_ = q1;
      return;
    }
    // The controlled points: tips, or ball centres when the plan keeps those on the CL path.
    const Vec3 P0 = m0.tip_in_part_mm + opt_.control_offset_mm * m0.axis_in_part.normalized();
    const Vec3 P1 = m1.tip_in_part_mm + opt_.control_offset_mm * m1.axis_in_part.normalized();
    const Slerp axis(m0.axis_in_part.normalized(), m1.axis_in_part.normalized());
    // Explicit stack of pieces [sa, sb] with their axis values; emits pieces in order.
    stack_.clear();
    stack_.push_back({0.0, 1.0, q0, q1, 0});
    while (!stack_.empty()) {
      Piece pc = stack_.back();
      stack_.pop_back();
      if (opt_.linearise && pc.depth < opt_.max_subdivision_depth &&
          exceeds(pc.qa, pc.qb, pc.sa, pc.sb, P0, P1, axis)) {
        const double sm = 0.5 * (pc.sa + pc.sb);
        const Vec3 axis_m = axis(sm);
        const kin::Posed target{P0 + sm * (P1 - P0) - opt_.control_offset_mm * axis_m, axis_m};
        const kin::Axes guess = 0.5 * (pc.qa + pc.qb);
        // First keep the rotaries the machine would pass through anyway and only correct the linear axes:
        // near the singularity a fresh IK of the interpolated axis is ill-conditioned (its azimuth is
        // arbitrary) while the interpolated rotaries already give an axis within tolerance.
        kin::Axes qm = guess;
        {
          // The axis the interpolated rotaries give; the controlled point (tip, or ball centre) is put exactly
          // on the path with that axis, so only the axis error is left to judge.
          Vec3 a_int;
          const auto rp = kin_.rotary_pair();
          const Vec3 ctrl = P0 + sm * (P1 - P0);
          if (kin_.tool_axis_at(qm[rp[0]], qm[rp[1]], target.tip_mm, a_int) &&
              a_int.dot(target.axis) >= cos_tol_axis_ &&
              kin_.solve_for_rotaries(kin::Posed{ctrl - opt_.control_offset_mm * a_int, a_int}, qm) &&
              kin_.forward(qm).axis.dot(target.axis) >= cos_tol_axis_) {
            check_limits(qm, m1);
            ++sum_.inserted_points;
            stack_.push_back({sm, pc.sb, qm, pc.qb, pc.depth + 1});
            stack_.push_back({pc.sa, sm, pc.qa, qm, pc.depth + 1});
            continue;
          }
        }
        // Otherwise continue the solution branch from the piece's start (no flips), as the conventional
        // strategy does between CL points.
        const Vec3 axis_a = axis(pc.sa);
        const kin::Posed from{P0 + pc.sa * (P1 - P0) - opt_.control_offset_mm * axis_a, axis_a};
        ++sum_.ik_calls;
        bool jumped = false;
        std::string why;
        const bool tracked = kin::track_checked(kin_, pc.qa, from, target, qm, jumped, &why);
        if (tracked && jumped)
          throw InputError(SourceLoc{prog_.file, m1.line, 0},
                           fmt::format("the machine cannot follow the CL segment from line {} to line {} "
                                       "continuously: inside it a limit{} forces the rotaries to flip (the "
                                       "tool would leave the path); split the segment or plan it with a cone",
                                       m0.line, m1.line, why.empty() ? "" : " (" + why + ")"));
        if (!tracked) {
          sum_.warnings.push_back(
              fmt::format("{}: no IK solution while linearising", SourceLoc{prog_.file, m1.line, 0}.str()));
        } else {
          check_limits(qm, m1);
          ++sum_.inserted_points;
          stack_.push_back({sm, pc.sb, qm, pc.qb, pc.depth + 1});
          stack_.push_back({pc.sa, sm, pc.qa, qm, pc.depth + 1});
          continue;
        }
      } else if (opt_.linearise && pc.depth >= opt_.max_subdivision_depth &&
                 exceeds(pc.qa, pc.qb, pc.sa, pc.sb, P0, P1, axis)) {
        sum_.warnings.push_back(fmt::format("{}: tolerance not reached after {} subdivisions (singular region?)",
                                            SourceLoc{prog_.file, m1.line, 0}.str(), opt_.max_subdivision_depth));
      }
      emit_inverse_time(pc.qa, pc.qb, (pc.sb - pc.sa) * (P1 - P0).norm(), feed_mm_min);
    }
    cur_ = q1;
  }

  void emit_inverse_time(const kin::Axes& qa, const kin::Axes& qb, double tip_len_mm, double feed_mm_min) {
    // Block time: the tip at the programmed feed, but no axis faster than its maximum feed.
    double minutes = tip_len_mm / feed_mm_min;
    for (int i = 0; i < 5; ++i) {
      const double vmax = m_.axes[static_cast<size_t>(i)].max_feed;
      if (vmax > 0) minutes = std::max(minutes, std::abs(qb[i] - qa[i]) / vmax);
    }
    minutes = std::max(minutes, 1e-6);
    if (!mode93_) {
      buf_.append("G93 ");
      mode93_ = true;
    }
    buf_.append("G1");
    if (!append_words(qb, {0, 1, 2, 3, 4})) {
      buf_.resize(buf_.size() - 2);
      return;
    }
    fmt::format_to(std::back_inserter(buf_), " F{:.3f}\n", std::min(1.0 / minutes, 999999.0));
    ++sum_.blocks;
  }

  // --- Retract along the tool axis (machines without a Z axis, e.g. the XMINI; Cartesian mode) -----

  /// The point where the tip, leaving along the tool axis (or vertically when the axis is nearly
  /// horizontal), reaches the plane z = safe_z_mm. False when the tip is already at or above it.
  bool retract_point(const Vec3& tip, const Vec3& axis, Vec3& up) const {
    const double safe = m_.post.safe_z_mm;
    if (tip.z() >= safe - tol::kLimitSlackMm) return false;
    const Vec3 dir = axis.z() >= kMinRetractAxisZ ? Vec3(axis.normalized()) : Vec3::UnitZ();
    up = tip + (safe - tip.z()) / dir.z() * dir;
    return true;
  }

  /// Joint values with the tip of q moved along its tool axis to the safe plane, the axis kept (by IK).
  kin::Axes pkm_retracted(const kin::Axes& q, const SourceLoc& where) {
    const kin::Posed p = kin_.forward(q);
    Vec3 up;
    if (!retract_point(p.tip_mm, p.axis, up)) return q;
    kin::Axes out;
    if (!kin::nearest_solution(kin_, kin::Posed{up, p.axis}, q, out))
      throw InputError(where, fmt::format("cannot retract the tool along its axis to the safe plane z = {:.3f} mm "
                                          "(post.safe_z_mm): no axis values inside the limits put the tip at "
                                          "({:.3f}, {:.3f}, {:.3f}) with this tool axis",
                                          m_.post.safe_z_mm, up.x(), up.y(), up.z()));
    return out;
  }

  /// One rapid block to q (nothing when every word is unchanged).
  void emit_g0(const kin::Axes& q) {
    const size_t mark = buf_.size();
    const bool mode93 = mode93_;
    const double last_feed = last_feed_;
    set_mode94();
    buf_.append("G0");
    if (append_words(q, {0, 1, 2, 3, 4})) {
      buf_.push_back('\n');
      ++sum_.blocks;
    } else {  // nothing moves: no block, and the feed mode stays as it was
      buf_.resize(mark);
      mode93_ = mode93;
      last_feed_ = last_feed;
    }
    cur_ = q;
  }

  /// Retract before a tool change and at the end of the program.
  void axis_retract(const SourceLoc& where) {
    if (!axis_retract_) return;
    if (cart_) {
      Vec3 up;
      if (!retract_point(cart_tip_, cart_axis_, up)) return;
      kin::Axes v = cur_;
      int k = 0;
      for (int i = 0; i < 5; ++i)
        if (!m_.axes[static_cast<size_t>(i)].rotary()) v[i] = up[k++];
      emit_g0(v);
      cart_tip_ = up;
      return;
    }
    emit_g0(pkm_retracted(cur_, where));
  }

  /// Joint-space rapid to q with a rotary change: retract along the current tool axis, turn to q's tool
  /// axis at the safe plane, go above q (along its axis); the caller then plunges to q.
  void pkm_reposition(const kin::Axes& q, const cl::Move& mv) {
    const SourceLoc where{prog_.file, mv.line, 0};
    const kin::Axes above = pkm_retracted(q, where);
    if (have_state_) {
      const kin::Axes up = pkm_retracted(cur_, where);
      const kin::Posed at_up = kin_.forward(up), target = kin_.forward(q);
      kin::Axes turned = up;  // if the new axis cannot be had there, turn on the way to the point above q
      if (!kin::nearest_solution(kin_, kin::Posed{at_up.tip_mm, target.axis}, above, turned)) turned = up;
      emit_g0(up);
      emit_g0(turned);
    }
    emit_g0(above);
  }

  // --- Cartesian mode: one block per CL point, the control interpolates ------------------------

  /// The words of a Cartesian block in the machine's axis slots: tip in the linear slots, in the
  /// rotary slots the machine's rotaries (serial: they alone set the tool vector) or, for the XMINI,
  /// the virtual wrist angles of the tool vector (xmini_virtual_ca).
  kin::Axes cartesian_words(const Vec3& tip, const Vec3& axis, const kin::Axes& q) const {
    kin::Axes v = q;
    int k = 0;
    for (int i = 0; i < 5; ++i)
      if (!m_.axes[static_cast<size_t>(i)].rotary()) v[i] = tip[k++];
    if (m_.kind == machine::ModelKind::Xmini) {
      const auto rp = kin_.rotary_pair();
      const auto ca = xmini_virtual_ca(axis, q[rp[0]], q[rp[1]]);
      v[rp[0]] = ca[0];
      v[rp[1]] = ca[1];
    }
    return v;
  }

  void cartesian(const cl::Move& mv, const kin::Axes& q) {
    const Vec3 axis = mv.axis_in_part.normalized();
    const kin::Axes v = cartesian_words(mv.tip_in_part_mm, axis, q);
    if (!have_state_ || mv.kind == cl::MotionKind::Rapid) {
      if (axis_retract_ && rotaries_differ(v)) {
        if (have_state_) axis_retract(SourceLoc{prog_.file, mv.line, 0});
        Vec3 above;
        if (retract_point(mv.tip_in_part_mm, axis, above)) {
          kin::Axes va = v;
          int k = 0;
          for (int i = 0; i < 5; ++i)
            if (!m_.axes[static_cast<size_t>(i)].rotary()) va[i] = above[k++];
          emit_g0(va);
        }
      }
      emit_g0(v);
    } else {
      const double feed_mm_min = mv.feed_mm_per_min > 0 ? mv.feed_mm_per_min : 1000.0;
      set_mode94();
      buf_.append("G1");
      if (!append_words(v, {0, 1, 2, 3, 4})) {
        buf_.resize(buf_.size() - 2);
      } else {
        if (std::abs(feed_mm_min - last_feed_) > 1e-9) {
          fmt::format_to(std::back_inserter(buf_), " F{:.1f}", feed_mm_min);
          last_feed_ = feed_mm_min;
        }
        buf_.push_back('\n');
        ++sum_.blocks;
      }
    }
    cur_ = v;
    cart_tip_ = mv.tip_in_part_mm;
    cart_axis_ = axis;
    have_state_ = true;
  }

  std::ostream& out_;
  const cl::Program& prog_;
  const machine::Machine& m_;
  const kin::Kinematics& kin_;
  const Options& opt_;
  Summary& sum_;
  Dialect dialect_;
  double tol_mm_ = 0.01, tol_axis_rad_ = 0.005, cos_tol_axis_ = 1.0;
  std::array<int, 5> decimals_{};
  std::array<double, 5> scale_{}, to_file_{};
  std::array<long long, 5> last_{};
  std::array<bool, 5> have_word_{};
  int z_ = -1;
  double safe_z_ = 0.0;
  std::array<std::string, 5> letters_;  ///< word letter per axis slot (X Y Z for the tip in Cartesian mode)
  bool cart_ = false;                   ///< Cartesian (TCP) output: slots hold tip + tool-vector rotaries
  bool axis_retract_ = false;           ///< retract along the tool axis to z = safe_z_mm (no Z axis, or Cartesian)
  Vec3 cart_tip_ = Vec3::Zero(), cart_axis_ = Vec3::UnitZ();  ///< last Cartesian position (part frame)
  bool have_state_ = false;
  bool at_cut_ = false;  ///< the last motion was a feed: the tool may be in the material
  cl::Move cut_move_;    ///< the CL point that feed ended at
  bool mode93_ = false;
  double last_feed_ = -1.0;
  kin::Axes cur_ = kin::Axes::Zero();
  std::string buf_;
  size_t scanned_ = 0;  ///< bytes of buf_ already attributed to a CL line
  std::vector<Piece> stack_;
};

}  // namespace

std::vector<std::string> dialects() { return {"linuxcnc", "fanuc", "xmini-joint", "xmini-cartesian"}; }

void write_nc(std::ostream& out, const cl::Program& program, const machine::Machine& machine,
              const kin::Kinematics& kinematics, const std::vector<kin::Axes>& axes, const Options& options,
              Summary& summary) {
  CSCAM_CHECK(axes.size() == program.moves.size(), "one axis vector per CL move");
  Writer w(out, program, machine, kinematics, options, summary);
  w.run(axes);
}

}  // namespace cscam::post
