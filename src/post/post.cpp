#include "cscam/post/post.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <charconv>
#include <cmath>
#include <ostream>

#include "cscam/core/error.hpp"
#include "cscam/core/tolerances.hpp"
#include "cscam/core/units.hpp"

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
};

Dialect make_dialect(const std::string& name) {
  if (name == "linuxcnc") return {name, false};
  if (name == "fanuc") return {name, true};
  throw InputError(fmt::format("unknown post dialect '{}' (known: linuxcnc, fanuc)", name));
}

std::string sanitize_comment(std::string s) {
  for (char& c : s)
    if (c == '(' || c == ')') c = '_';
  return s;
}

/// Writes blocks with modal suppression of unchanged axis words.
class Writer {
 public:
  Writer(std::ostream& out, const cl::Program& program, const machine::Machine& machine,
         const kin::Kinematics& kin, const Options& opt, Summary& summary)
      : out_(out), prog_(program), m_(machine), kin_(kin), opt_(opt), sum_(summary) {
    dialect_ = make_dialect(opt.dialect.empty() ? machine.post.dialect : opt.dialect);
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
    buf_.reserve(1 << 16);
  }

  void run(const std::vector<kin::Axes>& axes) {
    header();
    size_t ev = 0;
    const auto& moves = prog_.moves;
    for (size_t i = 0; i < moves.size(); ++i) {
      while (ev < prog_.events.size() && prog_.events[ev].before_move <= i) event(prog_.events[ev++]);
      const cl::Move& mv = moves[i];
      ++sum_.cl_points;
      check_limits(axes[i], mv);
      if (!have_state_ || mv.kind == cl::MotionKind::Rapid) {
        rapid(axes[i], mv);
      } else {
        feed(moves[i - 1], axes[i - 1], mv, axes[i]);
      }
      if (buf_.size() > (1 << 15)) flush();
    }
    while (ev < prog_.events.size()) event(prog_.events[ev++]);
    footer();
    flush();
  }

 private:
  void flush() {
    out_.write(buf_.data(), static_cast<std::streamsize>(buf_.size()));
    buf_.clear();
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
    fmt::format_to(std::back_inserter(buf_), "(cscam post: machine {} dialect {} strategy {})\n", sanitize_comment(m_.name),
                   dialect_.name, sanitize_comment(opt_.strategy));
    if (!opt_.source_name.empty()) fmt::format_to(std::back_inserter(buf_), "(source: {})\n", sanitize_comment(opt_.source_name));
    fmt::format_to(std::back_inserter(buf_), "(cscam tool_length_mm={:.4f} tolerance_mm={:.4f})\n",
                   opt_.tool_length_mm, tol_mm_);
    line("G21 G90 G94 G17 G40 G49 G80");
    mode93_ = false;
  }

  void footer() {
    if (z_ >= 0 && have_state_) {
      fmt::format_to(std::back_inserter(buf_), "G0 {}{}\n", m_.post.letters[static_cast<size_t>(z_)], fmt_axis(z_, safe_z_));
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
        if (z_ >= 0 && have_state_) emit_safe_z();
        fmt::format_to(std::back_inserter(buf_), "T{} M6\nG43 H{}\n", n, n);
        break;
      }
      case K::SpindleOn:
        fmt::format_to(std::back_inserter(buf_), "S{:.0f} {}\n", e.spindle_rpm, e.clockwise ? "M3" : "M4");
        break;
      case K::SpindleOff:
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
      throw InputError(SourceLoc{prog_.file, mv.line, 0}, fmt::format("the post refuses a block outside the limits: {}", v));
  }

  /// Appends the axis words of q that differ from the last written values.
  bool append_words(const kin::Axes& q, std::initializer_list<int> which, bool force = false) {
    bool any = false;
    for (int i : which) {
      const long long r = rounded(i, q[i]);
      if (!force && have_word_[static_cast<size_t>(i)] && r == last_[static_cast<size_t>(i)]) continue;
      buf_.push_back(' ');
      buf_.append(m_.post.letters[static_cast<size_t>(i)]);
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
      buf_.append("\nG0");
      kin::Axes above = q;
      above[z_] = safe_z_;
      std::vector<int> xy;
      for (int i : lin)
        if (i != z_) xy.push_back(i);
      for (int i : xy) append_words(above, {i}, !have_word_[static_cast<size_t>(i)]);
      buf_.push_back('\n');
      sum_.blocks += 3;
    }
    set_mode94();
    buf_.append("G0");
    if (!append_words(q, {0, 1, 2, 3, 4})) buf_.append(fmt::format(" {}{}", m_.post.letters[static_cast<size_t>(lin[0])], fmt_axis(lin[0], q[lin[0]])));
    buf_.push_back('\n');
    ++sum_.blocks;
    cur_ = q;
    have_state_ = true;
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
      const double dtip = point_segment_distance(p.tip_mm, P0, P1);
      sum_.max_checked_tip_deviation_mm = std::max(sum_.max_checked_tip_deviation_mm, dtip);
      if (dtip > tol_mm_ || p.axis.dot(axis(sa + t * (sb - sa))) < cos_tol_axis_) {
        bad = true;
        break;
      }
    }
    return bad;
  }

  void feed(const cl::Move& m0, const kin::Axes& q0, const cl::Move& m1, const kin::Axes& q1) {
    const auto rp = kin_.rotary_pair();
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
    const Vec3 &P0 = m0.tip_in_part_mm, &P1 = m1.tip_in_part_mm;
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
        const kin::Posed target{P0 + sm * (P1 - P0), axis(sm)};
        const kin::Axes guess = 0.5 * (pc.qa + pc.qb);
        kin_.inverse_branches(target, &guess, sols_);
        ++sum_.ik_calls;
        double best = 1e300;
        kin::Axes qm = guess;
        for (auto& s : sols_) {
          kin_.nearest_winding(s.axes, guess);
          const double d = std::abs(s.axes[rp[0]] - guess[rp[0]]) + std::abs(s.axes[rp[1]] - guess[rp[1]]);
          if (d < best) {
            best = d;
            qm = s.axes;
          }
        }
        if (sols_.empty()) {
          sum_.warnings.push_back(fmt::format("{}: no IK solution while linearising", SourceLoc{prog_.file, m1.line, 0}.str()));
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
  bool have_state_ = false;
  bool mode93_ = false;
  double last_feed_ = -1.0;
  kin::Axes cur_ = kin::Axes::Zero();
  std::string buf_;
  std::vector<kin::Solution> sols_;
  std::vector<Piece> stack_;
};

}  // namespace

std::vector<std::string> dialects() { return {"linuxcnc", "fanuc"}; }

void write_nc(std::ostream& out, const cl::Program& program, const machine::Machine& machine,
              const kin::Kinematics& kinematics, const std::vector<kin::Axes>& axes, const Options& options,
              Summary& summary) {
  CSCAM_CHECK(axes.size() == program.moves.size(), "one axis vector per CL move");
  Writer w(out, program, machine, kinematics, options, summary);
  w.run(axes);
}

}  // namespace cscam::post
