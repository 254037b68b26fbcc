#include <fmt/format.h>

#include <charconv>
#include <cmath>
#include <cstring>
#include <stdexcept>

#include "cscam/core/error.hpp"
#include "cscam/core/rotations.hpp"
#include "cscam/core/units.hpp"
#include "cscam/post/dialect.hpp"

namespace cscam::post {

namespace {

/// An angle (rad) as printed with 4 decimals in degrees, and back in radians: the plane the control reads.
double printed_deg(double rad) { return std::round(rad2deg(rad) * 1e4) / 1e4; }

/// "+12.5000" / "-3.0000" (Heidenhain) or "12.5000" (ISO, Siemens) for a printed angle.
std::string angle_word(double deg, bool plus_sign) {
  std::string s = fmt::format("{:.4f}", deg);
  if (s == "-0.0000") s = "0.0000";
  return plus_sign && s[0] != '-' ? "+" + s : s;
}

/// " F<feed>" with `decimals` decimals: the bytes fmt's "{:.Nf}" writes. The post rounds feeds to whole units of
/// the last decimal (k / 10^N, every block under inverse time): those are written from the integer k, for which
/// both roundings agree; any other value goes through fmt.
/// Writes u / 10^d with d decimals ("12.3400") backwards, ending at `end`; returns its first character. The
/// formatter runs once per block of a million-block program: digits into a stack buffer, one append per word.
char* fixed_backwards(char* end, unsigned long long u, int d) {
  char* p = end;
  for (int k = 0; k < d; ++k, u /= 10) *--p = static_cast<char>('0' + u % 10);
  if (d > 0) *--p = '.';
  do {
    *--p = static_cast<char>('0' + u % 10);
    u /= 10;
  } while (u != 0);
  return p;
}

void append_feed(std::string& out, double feed, int decimals) {
  double p = 1.0;
  for (int k = 0; k < decimals; ++k) p *= 10.0;
  const double scaled = feed * p;
  if (decimals >= 0 && decimals <= 9 && scaled >= 0.0 && scaled < 1e15) {
    const auto k = std::llround(scaled);
    if (static_cast<double>(k) / p == feed) {
      char tmp[48];
      char* const end = tmp + sizeof tmp;
      char* b = fixed_backwards(end, static_cast<unsigned long long>(k), decimals);
      *--b = 'F';
      *--b = ' ';
      out.append(b, static_cast<size_t>(end - b));
      return;
    }
  }
  fmt::format_to(std::back_inserter(out), " F{:.{}f}", feed, decimals);
}

/// Comment text that cannot end the comment early ( ')' ), open a nested one, or end the program on a control that
/// reads '%' as the end-of-program mark wherever it stands (Fanuc, Haas).
std::string sanitize_comment(std::string s) {
  for (char& c : s)
    if (c == '(' || c == ')' || c == '%') c = '_';
  return s;
}

}  // namespace

// --- ISO base (RS274/NGC spelling; LinuxCNC) ----------------------------------------------------------

void Formatter::line_start(std::string& out) {
  if (!numbers_) return;
  if (max_sequence_number_ > 0 && n_ + step_ > max_sequence_number_) n_ = 0;
  n_ += step_;
  char tmp[32];
  tmp[0] = 'N';
  char* e = std::to_chars(tmp + 1, tmp + sizeof tmp - 1, n_).ptr;
  *e++ = ' ';
  out.append(tmp, static_cast<size_t>(e - tmp));
}

void Formatter::append_fixed(std::string& out, long long r, int d, bool plus_sign) const {
  char tmp[48];
  char* const end = tmp + sizeof tmp;
  char* digits_end = end;
  if (d == 0 && integer_point_) *--digits_end = '.';
  // The magnitude as unsigned: -r overflows for the most negative value.
  const auto u = r < 0 ? 0ULL - static_cast<unsigned long long>(r) : static_cast<unsigned long long>(r);
  char* b = fixed_backwards(digits_end, u, d);
  if (r < 0)
    *--b = '-';
  else if (plus_sign)
    *--b = '+';
  out.append(b, static_cast<size_t>(end - b));
}

void Formatter::comment(std::string& out, const std::string& text) {
  fmt::format_to(std::back_inserter(out), "({})\n", sanitize_comment(text));
}

void Formatter::header_comments(std::string& out, bool with_name) {
  if (with_name) comment(out, info_.program_name);
  comment(out, fmt::format("cscam post: machine {} dialect {} strategy {}", sanitize_comment(info_.machine_name),
                           name(), sanitize_comment(info_.strategy)));
  if (!info_.source_name.empty()) comment(out, "source: " + info_.source_name);
  comment(out,
          fmt::format("cscam tool_length_mm={:.4f} tolerance_mm={:.4f}{}{}", info_.tool_length_mm, info_.tolerance_mm,
                      info_.cone_deg > 0 ? fmt::format(" cone_deg={:.4f}", info_.cone_deg) : std::string(),
                      info_.cl_units.empty() ? std::string() : " cl_units=" + info_.cl_units));
  if (info_.tcp) {
    std::string rot;
    for (size_t i = 0; i < 5; ++i)
      if (info_.rotary[i]) rot += (rot.empty() ? "" : " ") + info_.letters[i];
    comment(out, fmt::format("cartesian: X Y Z = tool tip, {} = tool vector; the control runs the kinematics",
                             info_.tcp_vectors ? std::string("vector words") : rot));
  }
}

void Formatter::start_block(std::string& out) {
  line_start(out);
  out += info_.inch ? "G20" : "G21";
  out += " G90 G94 G17 G40 G49 G80\n";
  if (!info_.work_offset.empty()) {
    line_start(out);
    out += info_.work_offset + "\n";
  }
}

void Formatter::begin(std::string& out) {
  out += "%\n";
  header_comments(out, true);
  start_block(out);
}

void Formatter::end(std::string& out) {
  line_start(out);
  out += "M5\n";
  line_start(out);
  out += "M9\n";
  line_start(out);
  out += "M2\n%\n";
}

void Formatter::tool_change(std::string& out, int tool, int h, const std::string& description) {
  if (!description.empty()) comment(out, description);
  line_start(out);
  fmt::format_to(std::back_inserter(out), "T{} M6\n", tool);
  line_start(out);
  fmt::format_to(std::back_inserter(out), "G43 H{}\n", h);
}

void Formatter::tcp_on(std::string& /*out*/, int /*h*/) { tcp_active_ = true; }
void Formatter::tcp_off(std::string& /*out*/) { tcp_active_ = false; }
void Formatter::length_on(std::string& /*out*/, int /*h*/) {}

Eigen::Matrix3d Formatter::plane_on(std::string& /*out*/, const Eigen::Matrix3d& /*R_part_plane*/) {
  throw std::logic_error("plane_on on a dialect without work planes");
}
void Formatter::plane_off(std::string& /*out*/) {}

void Formatter::clamp(std::string& out, const std::string& code) {
  line_start(out);
  out += code + "\n";
}

void Formatter::spindle(std::string& out, double rpm, bool clockwise) {
  line_start(out);
  fmt::format_to(std::back_inserter(out), "S{:.0f} {}\n", rpm, clockwise ? "M3" : "M4");
}

void Formatter::spindle_off(std::string& out) {
  line_start(out);
  out += "M5\n";
}

void Formatter::coolant(std::string& out, bool on, bool mist) {
  line_start(out);
  out += on ? (mist ? "M7\n" : "M8\n") : "M9\n";
}

void Formatter::stop(std::string& out, bool optional) {
  line_start(out);
  out += optional ? "M1\n" : "M0\n";
}

void Formatter::insert(std::string& out, const std::string& text) {
  line_start(out);
  out += text;
  out.push_back('\n');
}

void Formatter::dwell(std::string& out, double seconds) {
  line_start(out);
  fmt::format_to(std::back_inserter(out), "G4 P{:.3f}\n", seconds);
}

void Formatter::motion_word(std::string& out, const BlockSpec& b) {
  if (b.arc && b.arc->plane != plane_) {
    plane_ = b.arc->plane;
    fmt::format_to(std::back_inserter(out), "G{} ", plane_);
  }
  if (b.arc)
    out += b.arc->clockwise ? "G2" : "G3";
  else
    out += b.motion == BlockSpec::Motion::Rapid ? "G0" : "G1";
}

void Formatter::arc_centre_words(std::string& out, const BlockSpec& b) const {
  if (!b.arc) return;
  for (int k = 0; k < 3; ++k)
    if (b.arc->write[static_cast<size_t>(k)]) {
      out.push_back(' ');
      out.push_back("IJK"[k]);
      append_fixed(out, b.arc->ijk[static_cast<size_t>(k)], b.arc->decimals);
    }
}

void Formatter::block(std::string& out, const BlockSpec& b) {
  line_start(out);
  if (b.feed_mode == BlockSpec::FeedMode::InverseTime) out += "G93 ";
  if (b.feed_mode == BlockSpec::FeedMode::PerMinute) out += "G94 ";
  motion_word(out, b);
  for (const auto& w : b.words) {
    // " X-12.3456" built in one buffer, one append.
    const std::string& letter = info_.letters[static_cast<size_t>(w.slot)];
    char tmp[64];
    char* const end = tmp + sizeof tmp;
    char* digits_end = end;
    if (w.decimals == 0 && integer_point_) *--digits_end = '.';
    const auto u =
        w.scaled < 0 ? 0ULL - static_cast<unsigned long long>(w.scaled) : static_cast<unsigned long long>(w.scaled);
    char* p = fixed_backwards(digits_end, u, w.decimals);
    if (w.scaled < 0) *--p = '-';
    if (letter.size() < 16) {
      p -= letter.size();
      std::memcpy(p, letter.data(), letter.size());
      *--p = ' ';
    } else {
      out.push_back(' ');
      out += letter;
    }
    out.append(p, static_cast<size_t>(end - p));
  }
  arc_centre_words(out, b);
  if (b.tool_vector) {
    const auto& v = *b.tool_vector;
    fmt::format_to(std::back_inserter(out), " I{:.6f} J{:.6f} K{:.6f}", v[0], v[1], v[2]);
  }
  if (b.feed) append_feed(out, *b.feed, b.feed_decimals);
  out.push_back('\n');
}

namespace {

// --- LinuxCNC -----------------------------------------------------------------------------------------
class Linuxcnc : public Formatter {
 public:
  Linuxcnc(const ProgramInfo& info, std::string name, bool switchkins)
      : Formatter(info), name_(std::move(name)), switchkins_(switchkins) {
    if (info.work_offset.rfind("G54.1", 0) == 0)
      throw InputError(
          fmt::format("post.work_offset {}: LinuxCNC has the work offsets G54..G59 only (G54.1 P<n> is "
                      "a Fanuc and Haas form)",
                      info.work_offset));
  }
  [[nodiscard]] std::string name() const override { return name_; }
  // The XMINI's joint words are legs, not a Cartesian X Y Z: no arcs there.
  [[nodiscard]] bool has_arcs() const override { return switchkins_; }
  void begin(std::string& out) override {
    Formatter::begin(out);
    // The trajectory planner blends corners within G64 P: bounded by the linearisation tolerance, blending
    // cannot undo it (without P it rounds corners by as much as the accelerations allow).
    line_start(out);
    out += blend_words();
    out.push_back('\n');
  }
  // G64 P bounds the joint X Y Z of a blend only: LinuxCNC lifted Z into a retract while C was still 1.3 deg short of
  // the end of the cut (the tip 0.084 mm off the path). G61 (exact path) is set when a segment is queued.
  [[nodiscard]] std::string exact_path_words() const override { return "G61"; }
  [[nodiscard]] std::string blend_within_words(double p) const override { return fmt::format("G64 P{:.4f}", p); }
  // With A B C (or U V W) in a segment LinuxCNC blends parabolically, P bounding X Y Z only (docs/linuxcnc.md).
  [[nodiscard]] bool blends_parabolically() const override { return true; }
  // The switchable trunnion kinematics (xyzac-trt, xyzbc-trt sample configs): M428 selects the TCP (world)
  // kinematics, in which X Y Z are the tip in the table frame and the tool offset of G43 is taken into
  // account by the kinematics; M429 returns to identity (joint) kinematics.
  void tcp_on(std::string& out, int h) override {
    if (switchkins_ && !tcp_active_) {
      line_start(out);
      out += "M428 (TCP: world coordinates, the tip in the part frame)\n";
    }
    Formatter::tcp_on(out, h);
  }
  void tcp_off(std::string& out) override {
    if (switchkins_ && tcp_active_) {
      line_start(out);
      out += "M429\n";
    }
    Formatter::tcp_off(out);
  }

 private:
  std::string name_;
  bool switchkins_;
};

// --- Fanuc --------------------------------------------------------------------------------------------
class Fanuc : public Formatter {
 public:
  explicit Fanuc(const ProgramInfo& info) : Formatter(info) {
    integer_point_ = true;
    max_sequence_number_ = 99999;  // N1..N99999
  }
  [[nodiscard]] std::string name() const override { return "fanuc"; }
  // Fanuc's G04 P is milliseconds and takes no decimal point (P2.500 is an alarm or a 2 ms dwell).
  void dwell(std::string& out, double seconds) override {
    line_start(out);
    fmt::format_to(std::back_inserter(out), "G4 P{}\n", std::llround(seconds * 1000.0));
  }
  void begin(std::string& out) override {
    out += "%\n";
    fmt::format_to(std::back_inserter(out), "O{:0{}d} ({})\n", info_.program_number, program_number_digits(),
                   sanitize_comment(info_.program_name));
    header_comments(out, false);
    start_block(out);
  }
  void end(std::string& out) override {
    line_start(out);
    out += "M5\n";
    line_start(out);
    out += "M9\n";
    line_start(out);
    out += "M30\n%\n";
  }
  // G43.4: tool-tip control with rotary angles; G43.5: with the tool vector I J K. G49 cancels either.
  void tcp_on(std::string& out, int h) override {
    if (!tcp_active_) {
      line_start(out);
      fmt::format_to(std::back_inserter(out), "{} H{}\n", info_.tcp_vectors ? "G43.5" : "G43.4", h);
    }
    Formatter::tcp_on(out, h);
  }
  void tcp_off(std::string& out) override {
    if (tcp_active_) {
      line_start(out);
      out += "G49\n";
    }
    Formatter::tcp_off(out);
  }
  // G49 cancelled the length with TCP: G43 H as after a tool change without TCP (the machine words before and in
  // the plane are then the tip's, as in the non-TCP program).
  void length_on(std::string& out, int h) override {
    line_start(out);
    fmt::format_to(std::back_inserter(out), "G43 H{}\n", h);
  }
  // G68.2: the feature coordinate system by its origin and ZXZ Euler angles I J K; G53.1 turns the tool
  // perpendicular to it (the rotaries are there already: the sequencer positioned them); G69 cancels.
  [[nodiscard]] PlaneForm plane_form() const override { return PlaneForm::Rotated; }
  Eigen::Matrix3d plane_on(std::string& out, const Eigen::Matrix3d& R_part_plane) override {
    const auto e = rot::euler_zxz(R_part_plane);
    const double i = printed_deg(e[0]), j = printed_deg(e[1]), k = printed_deg(e[2]);
    line_start(out);
    fmt::format_to(std::back_inserter(out), "G68.2 X0. Y0. Z0. I{} J{} K{}\n", angle_word(i, false),
                   angle_word(j, false), angle_word(k, false));
    line_start(out);
    out += "G53.1\n";
    return rot::from_euler_zxz(deg2rad(i), deg2rad(j), deg2rad(k));
  }
  void plane_off(std::string& out) override {
    line_start(out);
    out += "G69\n";
  }
  void tool_change(std::string& out, int tool, int h, const std::string& description) override {
    if (!description.empty()) comment(out, description);
    line_start(out);
    fmt::format_to(std::back_inserter(out), "T{} M6\n", tool);
    if (!info_.tcp) {  // with tool-tip control, G43.4/G43.5 H is the length offset
      line_start(out);
      fmt::format_to(std::back_inserter(out), "G43 H{}\n", h);
    }
  }

 protected:
  /// Digits of the O number: Fanuc O0001, Haas (NGC) O00001.
  [[nodiscard]] virtual int program_number_digits() const { return 4; }
};

// --- Haas (NGC) ---------------------------------------------------------------------------------------
class Haas : public Fanuc {
 public:
  using Fanuc::Fanuc;
  [[nodiscard]] std::string name() const override { return "haas"; }
  // Haas reads a G04 P with a decimal point as seconds.
  void dwell(std::string& out, double seconds) override { Formatter::dwell(out, seconds); }
  [[nodiscard]] int program_number_digits() const override { return 5; }
  // G254 dynamic work offset (Haas mill manual): after the rotaries are positioned the control carries the work
  // offset with them; the words stay the machine coordinates of a part at the rotation centre, and X Y Z must all be
  // given again before cutting (the sequencer writes them). G255 cancels it before any rotary motion.
  [[nodiscard]] PlaneForm plane_form() const override { return PlaneForm::WorkOffset; }
  Eigen::Matrix3d plane_on(std::string& out, const Eigen::Matrix3d& /*R_part_plane*/) override {
    line_start(out);
    out += "G254\n";
    return Eigen::Matrix3d::Identity();
  }
  void plane_off(std::string& out) override {
    line_start(out);
    out += "G255\n";
  }
  // G234 TCPC (the vector form does not exist on a Haas: angles always); G49 cancels it.
  void tcp_on(std::string& out, int h) override {
    if (!tcp_active_) {
      line_start(out);
      fmt::format_to(std::back_inserter(out), "G234 H{}\n", h);
    }
    Formatter::tcp_on(out, h);
  }
};

// --- Siemens Sinumerik 840D ---------------------------------------------------------------------------
class Siemens : public Formatter {
 public:
  explicit Siemens(const ProgramInfo& info) : Formatter(info) {
    if (info.work_offset.rfind("G54.1", 0) == 0)
      throw InputError(
          fmt::format("post.work_offset {}: Sinumerik has no G54.1 P<n> (use G54..G57 or G505..G599 in "
                      "the control's own form)",
                      info.work_offset));
  }
  [[nodiscard]] std::string name() const override { return "siemens"; }
  void comment(std::string& out, const std::string& text) override {
    fmt::format_to(std::back_inserter(out), "; ({})\n", sanitize_comment(text));
  }
  void begin(std::string& out) override {
    // Sinumerik's own start block: G710 metric (G700 inch), TRAFOOF instead of G49, no canned cycles to cancel.
    // G710/G700 set the feed's unit too; G71/G70 would leave F in the control's basic system (an inch program on a
    // metric control would feed in mm/min).
    header_comments(out, true);
    line_start(out);
    out += info_.inch ? "G700" : "G710";
    out += " G90 G94 G17 G40 G64\n";
    line_start(out);
    out += "TRAFOOF\n";
    if (!info_.work_offset.empty()) {
      line_start(out);
      out += info_.work_offset + "\n";
    }
  }
  void end(std::string& out) override {
    line_start(out);
    out += "M5\n";
    line_start(out);
    out += "M9\n";
    line_start(out);
    out += "M30\n";
  }
  void tool_change(std::string& out, int tool, int h, const std::string& description) override {
    if (!description.empty()) comment(out, description);
    line_start(out);
    fmt::format_to(std::back_inserter(out), "T{}\n", tool);
    line_start(out);
    out += "M6\n";
    line_start(out);
    fmt::format_to(std::back_inserter(out), "D{}\n", h > 0 ? h : 1);
  }
  // TRAORI: the control's orientation transformation; ORIWKS: orientations in the workpiece frame; ORIAXES
  // interpolates the rotary angles linearly, ORIVECT the tool vector on a great circle (A3 B3 C3 words).
  void tcp_on(std::string& out, int h) override {
    if (!tcp_active_) {
      line_start(out);
      out += "TRAORI\n";
      line_start(out);
      out += info_.tcp_vectors ? "ORIWKS ORIVECT\n" : "ORIWKS ORIAXES\n";
    }
    Formatter::tcp_on(out, h);
  }
  void tcp_off(std::string& out) override {
    if (tcp_active_) {
      line_start(out);
      out += "TRAFOOF\n";
    }
    Formatter::tcp_off(out);
  }
  void dwell(std::string& out, double seconds) override {
    line_start(out);
    fmt::format_to(std::back_inserter(out), "G4 F{:.3f}\n", seconds);
  }
  // CYCLE800(_FR, _TC, _ST, _MODE, _X0, _Y0, _Z0, _A, _B, _C, _X1, _Y1, _Z1, _DIR, _FR_I): no retraction (the
  // sequencer retracted and positioned the rotaries), swivel data record (post.swivel_record, "TC1" by default), a new
  // frame, mode 57 = axis by axis X, Y, Z (bits 1-0, 3-2, 5-4 = 01, 10, 11; bits 7-6 = 00), no offsets, direction +.
  // CYCLE800() resets.
  [[nodiscard]] PlaneForm plane_form() const override { return PlaneForm::Rotated; }
  Eigen::Matrix3d plane_on(std::string& out, const Eigen::Matrix3d& R_part_plane) override {
    const auto e = rot::axis_by_axis_xyz(R_part_plane);
    const double a = printed_deg(e[0]), b = printed_deg(e[1]), c = printed_deg(e[2]);
    line_start(out);
    fmt::format_to(std::back_inserter(out), "CYCLE800(0,\"{}\",0,57,0,0,0,{},{},{},0,0,0,1,0)\n", info_.swivel_record,
                   angle_word(a, false), angle_word(b, false), angle_word(c, false));
    return rot::from_axis_by_axis_xyz(deg2rad(a), deg2rad(b), deg2rad(c));
  }
  void plane_off(std::string& out) override {
    line_start(out);
    out += "CYCLE800()\n";
  }
  void block(std::string& out, const BlockSpec& b) override {
    line_start(out);
    if (b.feed_mode == BlockSpec::FeedMode::InverseTime) out += "G93 ";
    if (b.feed_mode == BlockSpec::FeedMode::PerMinute) out += "G94 ";
    motion_word(out, b);  // Sinumerik: I J K incremental by default, as in ISO
    for (const auto& w : b.words) {
      out.push_back(' ');
      out += info_.letters[static_cast<size_t>(w.slot)];
      if (w.shortest) {  // a modulo rotary reached the short way
        out += "=DC(";
        append_fixed(out, w.scaled, w.decimals);
        out += ")";
      } else {
        append_fixed(out, w.scaled, w.decimals);
      }
    }
    arc_centre_words(out, b);
    if (b.tool_vector) {
      const auto& v = *b.tool_vector;
      fmt::format_to(std::back_inserter(out), " A3={:.6f} B3={:.6f} C3={:.6f}", v[0], v[1], v[2]);
    }
    if (b.feed) append_feed(out, *b.feed, b.feed_decimals);
    out.push_back('\n');
  }
};

// --- Heidenhain TNC (conversational) ------------------------------------------------------------------
class Heidenhain : public Formatter {
 public:
  using Formatter::Formatter;
  [[nodiscard]] std::string name() const override { return "heidenhain"; }
  [[nodiscard]] bool has_inverse_time() const override { return false; }
  // Conversational arcs (CC + C, helices with CP IPA) are not written: arcs stay G1-style L points.
  [[nodiscard]] bool has_arcs() const override { return false; }
  void comment(std::string& out, const std::string& text) override {
    number(out);
    fmt::format_to(std::back_inserter(out), "; ({})\n", sanitize_comment(text));
  }
  void begin(std::string& out) override {
    number(out);
    fmt::format_to(std::back_inserter(out), "BEGIN PGM {} {}\n", pgm(), info_.inch ? "INCH" : "MM");
    header_comments(out, true);
    // Datum from the preset table: the work offset's number (G54 -> preset 1).
    if (info_.work_offset.rfind("G5", 0) == 0 && info_.work_offset.size() == 3) {
      number(out);
      fmt::format_to(std::back_inserter(out), "CYCL DEF 247 DATUM SETTING ~\n  Q339=+{} ;DATUM NUMBER\n",
                     info_.work_offset[2] - '3');
    }
  }
  void end(std::string& out) override {
    number(out);
    out += "M5\n";
    number(out);
    out += "M9\n";
    number(out);
    out += "M30\n";
    number(out);
    fmt::format_to(std::back_inserter(out), "END PGM {} {}\n", pgm(), info_.inch ? "INCH" : "MM");
  }
  void tool_change(std::string& out, int tool, int /*h*/, const std::string& description) override {
    if (!description.empty()) comment(out, description);
    number(out);
    fmt::format_to(std::back_inserter(out), "TOOL CALL {} Z\n", tool);  // length from the tool table
  }
  // FUNCTION TCPM with the rotary words as axis angles, the tip path controlled (M128 on older TNCs).
  void tcp_on(std::string& out, int h) override {
    if (!tcp_active_) {
      number(out);
      out += "FUNCTION TCPM F TCP AXIS POS PATHCTRL AXIS\n";
    }
    Formatter::tcp_on(out, h);
  }
  void tcp_off(std::string& out) override {
    if (tcp_active_) {
      number(out);
      out += "FUNCTION RESET TCPM\n";
    }
    Formatter::tcp_off(out);
  }
  void clamp(std::string& out, const std::string& code) override {
    number(out);
    out += code + "\n";
  }
  // PLANE SPATIAL: spatial angles about the fixed X, Y, Z (in that order); STAY: the rotaries are already where
  // the plane needs them (the sequencer positioned them). PLANE RESET STAY cancels.
  [[nodiscard]] PlaneForm plane_form() const override { return PlaneForm::Rotated; }
  Eigen::Matrix3d plane_on(std::string& out, const Eigen::Matrix3d& R_part_plane) override {
    const auto e = rot::spatial(R_part_plane);
    const double a = printed_deg(e[0]), b = printed_deg(e[1]), c = printed_deg(e[2]);
    number(out);
    fmt::format_to(std::back_inserter(out), "PLANE SPATIAL SPA{} SPB{} SPC{} STAY\n", angle_word(a, true),
                   angle_word(b, true), angle_word(c, true));
    return rot::from_spatial(deg2rad(a), deg2rad(b), deg2rad(c));
  }
  void plane_off(std::string& out) override {
    number(out);
    out += "PLANE RESET STAY\n";
  }
  void spindle(std::string& out, double rpm, bool clockwise) override {
    number(out);
    fmt::format_to(std::back_inserter(out), "TOOL CALL Z S{:.0f}\n", rpm);
    number(out);
    out += clockwise ? "M3\n" : "M4\n";
  }
  void spindle_off(std::string& out) override {
    number(out);
    out += "M5\n";
  }
  void coolant(std::string& out, bool on, bool /*mist*/) override {
    number(out);
    out += on ? "M8\n" : "M9\n";
  }
  void stop(std::string& out, bool optional) override {
    number(out);
    out += optional ? "M1\n" : "STOP M0\n";
  }
  void insert(std::string& out, const std::string& text) override {
    number(out);
    out += text;
    out.push_back('\n');
  }
  void dwell(std::string& out, double seconds) override {
    number(out);
    out += "CYCL DEF 9.0 DWELL TIME\n";
    number(out);
    fmt::format_to(std::back_inserter(out), "CYCL DEF 9.1 DWELL {:.3f}\n", seconds);
  }
  void block(std::string& out, const BlockSpec& b) override {
    number(out);
    out += "L";
    for (const auto& w : b.words) {
      out.push_back(' ');
      out += info_.letters[static_cast<size_t>(w.slot)];
      append_fixed(out, w.scaled, w.decimals, true);
    }
    if (b.motion == BlockSpec::Motion::Rapid) {
      out += " R0 FMAX\n";
      return;
    }
    out += " R0";
    if (b.feed) append_feed(out, *b.feed, b.feed_decimals);
    out.push_back('\n');
  }

 private:
  /// Every conversational block carries its number, from 0.
  void number(std::string& out) { fmt::format_to(std::back_inserter(out), "{} ", block_no_++); }
  [[nodiscard]] std::string pgm() const {
    std::string s;
    for (char c : info_.program_name) s.push_back(std::isalnum(static_cast<unsigned char>(c)) ? c : '_');
    return s.empty() ? "CSCAM" : s;
  }
  long long block_no_ = 0;
};

}  // namespace

std::vector<std::string> dialect_names() {
  return {"linuxcnc", "fanuc", "haas", "siemens", "heidenhain", "xmini-joint", "xmini-cartesian"};
}

bool dialect_forces_tcp(const std::string& name) { return name == "xmini-cartesian"; }

std::unique_ptr<Formatter> make_formatter(const std::string& name, const ProgramInfo& info) {
  if (name == "linuxcnc") return std::make_unique<Linuxcnc>(info, name, true);
  // The XMINI (PKM): joint space is the linuxcnc output with the machine's letters (legs + wrist);
  // Cartesian mode is for a control that runs the PKM transformation itself.
  if (name == "xmini-joint" || name == "xmini-cartesian") return std::make_unique<Linuxcnc>(info, name, false);
  if (name == "fanuc") return std::make_unique<Fanuc>(info);
  if (name == "haas") return std::make_unique<Haas>(info);
  if (name == "siemens") return std::make_unique<Siemens>(info);
  if (name == "heidenhain") return std::make_unique<Heidenhain>(info);
  std::string known;
  for (const auto& n : dialect_names()) known += (known.empty() ? "" : ", ") + n;
  throw InputError(fmt::format("unknown post dialect '{}' (known: {})", name, known));
}

}  // namespace cscam::post
