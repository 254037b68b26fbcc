#include "cscam/nc/reader.hpp"

#include <fmt/format.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cctype>
#include <charconv>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <fstream>
#include <functional>
#include <optional>
#include <set>
#include <sstream>

#include "cscam/core/error.hpp"
#include "cscam/core/numparse.hpp"
#include "cscam/core/parallel.hpp"
#include "cscam/core/rotations.hpp"
#include "cscam/core/units.hpp"

namespace cscam::nc {

// A million-block program is a million of these: the pages the reader fills are most of its cost.
static_assert(sizeof(Block) <= 128, "nc::Block grew: keep rare members out of line");

namespace {

/// A move of the rotary axes alone (no linear axis, nor the tip under TCP, changes; nor an arc).
bool rotary_only(const Block& from, const Block& to, const AxisLetters& letters) {
  if (to.arc) return false;
  bool rotary_moves = false;
  for (std::size_t a = 0; a < 5; ++a) {
    const bool moved = std::abs(to.axes[a] - from.axes[a]) > 1e-12;
    if (moved && !letters.rotary[a]) return false;
    rotary_moves |= moved;
  }
  return rotary_moves;
}

/// "cone_deg=X" and "cl_units=U" in our header comment (the rest of the line from "cscam tool_length_mm="): a planned
/// program's cone, and the unit the CL was read in.
void read_header_cone(std::string_view rest, Program& prog) {
  constexpr std::string_view kKey = " cone_deg=", kUnits = " cl_units=";
  if (const auto p = rest.find(kKey); p != std::string_view::npos) {
    const auto v = rest.substr(p + kKey.size());
    double c = 0;
    if (std::from_chars(v.data(), v.data() + v.size(), c).ec == std::errc() && std::isfinite(c) && c > 0 && c <= 90)
      prog.header_cone_deg = c;
  }
  if (const auto p = rest.find(kUnits); p != std::string_view::npos) {
    const auto v = rest.substr(p + kUnits.size());
    if (v.substr(0, 4) == "inch")
      prog.header_cl_units = LengthUnit::Inch;
    else if (v.substr(0, 2) == "mm")
      prog.header_cl_units = LengthUnit::Millimetre;
  }
}

// Character classes of the "C" locale (cscam never sets another), inline: the reader asks them for every
// character of a program that may have millions of lines.
constexpr bool is_space(char c) { return c == ' ' || (c >= '\t' && c <= '\r'); }
constexpr bool is_digit(char c) { return c >= '0' && c <= '9'; }
constexpr bool is_alpha(char c) { return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z'); }
constexpr bool is_alnum(char c) { return is_digit(c) || is_alpha(c); }
constexpr char to_upper(char c) { return c >= 'a' && c <= 'z' ? static_cast<char>(c - 'a' + 'A') : c; }

std::string_view trim(std::string_view s) {
  while (!s.empty() && (is_space(s.front()) || s.front() == '\xEF' || s.front() == '\xBB' || s.front() == '\xBF'))
    s.remove_prefix(1);
  while (!s.empty() && is_space(s.back())) s.remove_suffix(1);
  return s;
}

/// The G-code number `num` (an optional sign, then digits and points: "-1.5", "+.5", "3.", "-.5"), which
/// from_chars alone does not take (a '+', no digit before or after the point). False if it is not a number.
/// In a buffer on the stack: this runs for every word of a million-block program.
bool gcode_number(std::string_view num, double& v) {
  if (!num.empty() && num[0] == '+') num.remove_prefix(1);
  if (num.empty()) return false;
  // Nearly every word is a plain "-12.345": read in place when that takes the whole word.
  if (num[0] != '.' && num.back() != '.' && !(num.size() > 1 && num[0] == '-' && num[1] == '.')) {
    const auto r = decimal_from_chars(num.data(), num.data() + num.size(), v);
    return r.ec == std::errc() && r.ptr == num.data() + num.size();
  }
  char small[64];
  std::string big;  // only for absurdly long words
  char* fixed = small;
  if (num.size() + 3 > sizeof small) {
    big.resize(num.size() + 3);
    fixed = big.data();
  }
  size_t n = 0;
  if (num[0] == '.') fixed[n++] = '0';  // ".5"
  for (size_t i = 0; i < num.size(); ++i) {
    fixed[n++] = num[i];
    if (i == 0 && num[0] == '-' && num.size() > 1 && num[1] == '.') fixed[n++] = '0';  // "-.5"
  }
  if (num.back() == '.') fixed[n++] = '0';  // "3."
  const auto r = std::from_chars(fixed, fixed + n, v);
  return r.ec == std::errc() && r.ptr == fixed + n;
}

/// One letter-number word of a block: its letter (upper case), its 1-based column and value.
struct Word {
  char letter = 0;
  int column = 0;
  double value = 0.0;
};

/// The words of a line made only of letter-number words ("G1 X1.5 Y-2 F100", with blanks, '%', comments in
/// parentheses, a leading '/' and a ';' tail around them), appended to `out` exactly as read_text's character
/// loop reads them. False for any other line (an 'O' word, an identifier, '=', a letter without a number, a
/// malformed number, ...): read_text's loop reads, or refuses, that one itself.
bool simple_words(std::string_view s, std::vector<Word>& out) {
  size_t i = 0;
  while (i < s.size()) {
    const char c = s[i];
    if (is_space(c) || c == '%') {
      ++i;
      continue;
    }
    if (c == '(') {
      const size_t e = s.find(')', i);
      i = e == std::string_view::npos ? s.size() : e + 1;
      continue;
    }
    if (c == ';') break;
    if (c == '/' && i == 0) {
      ++i;
      continue;
    }
    if (!is_alpha(c) || i + 1 >= s.size()) return false;
    const char L = to_upper(c);
    const char n = s[i + 1];
    if (L == 'O' || !(is_digit(n) || n == '-' || n == '+' || n == '.')) return false;
    size_t e = i + 1;  // Sinumerik "R1=...", "A3=...": not a word
    while (e < s.size() && is_digit(s[e])) ++e;
    if (e > i + 1 && e < s.size() && s[e] == '=') return false;
    size_t k = i + 1;
    if (s[k] == '-' || s[k] == '+') ++k;
    while (k < s.size() && (is_digit(s[k]) || s[k] == '.')) ++k;
    double v = 0;
    if (!gcode_number(s.substr(i + 1, k - i - 1), v)) return false;
    out.push_back({L, static_cast<int>(i) + 1, v});
    i = k;
  }
  return true;
}

/// A number at s[k] ("-1.5", "+.5", "3."); advances k past it.
std::optional<double> parse_number(std::string_view s, size_t& k) {
  while (k < s.size() && s[k] == ' ') ++k;
  const size_t j = k;
  if (k < s.size() && (s[k] == '-' || s[k] == '+')) ++k;
  while (k < s.size() && (is_digit(s[k]) || s[k] == '.')) ++k;
  double v = 0;
  if (!gcode_number(s.substr(j, k - j), v)) return std::nullopt;
  return v;
}

/// Past an identifier's argument: a parenthesised list "(...)" or "=value" (up to the next blank).
size_t skip_argument(std::string_view s, size_t e) {
  while (e < s.size() && s[e] == ' ') ++e;
  if (e < s.size() && s[e] == '(') {
    int depth = 0;
    for (; e < s.size(); ++e) {
      if (s[e] == '(') ++depth;
      if (s[e] == ')' && --depth == 0) return e + 1;
    }
    return s.size();
  }
  if (e < s.size() && s[e] == '=') {
    ++e;
    int depth = 0;
    bool quoted = false;
    for (; e < s.size(); ++e) {
      if (s[e] == '"') quoted = !quoted;
      if (quoted) continue;
      if (s[e] == '(' || s[e] == '[') ++depth;
      if (s[e] == ')' || s[e] == ']') --depth;
      if (depth <= 0 && (s[e] == ' ' || s[e] == ';')) break;
    }
  }
  return e;
}

/// The arguments of "CYCLE800(...)" (s[open] is '('), split at commas; empty ones stay empty.
std::vector<std::string_view> call_arguments(std::string_view s, size_t open) {
  std::vector<std::string_view> args;
  size_t start = open + 1;
  bool quoted = false;
  for (size_t k = open + 1; k < s.size(); ++k) {
    if (s[k] == '"') quoted = !quoted;
    if (quoted) continue;
    if (s[k] == ',' || s[k] == ')') {
      args.push_back(trim(s.substr(start, k - start)));
      start = k + 1;
      if (s[k] == ')') break;
    }
  }
  if (args.size() == 1 && args[0].empty()) args.clear();  // "CYCLE800()"
  return args;
}

/// Siemens CYCLE800(_FR, _TC, _ST, _MODE, _X0, _Y0, _Z0, _A, _B, _C, _X1, _Y1, _Z1, _DIR, ...): the swivelled
/// frame (origin X0 + R X1) for mode 57 (axis by axis X, Y, Z), or nothing for CYCLE800() (reset). Other modes
/// and kinematics-dependent forms (direct rotary angles) are refused: the reader cannot compute their frame.
std::optional<WorkPlane> cycle800(std::string_view s, size_t open, double scale,
                                  const std::function<void(size_t, const std::string&)>& fail) {
  const auto args = call_arguments(s, open);
  if (args.empty()) return std::nullopt;
  auto num = [&](size_t k) {
    if (k >= args.size() || args[k].empty()) return 0.0;
    size_t j = 0;
    const auto v = parse_number(args[k], j);
    if (!v || j != args[k].size())
      fail(static_cast<size_t>(args[k].data() - s.data()),
           fmt::format("CYCLE800: argument {} '{}' is not a number", k + 1, std::string(args[k])));
    return *v;
  };
  const double mode = num(3);
  if (mode != 57)
    fail(open, fmt::format("CYCLE800 mode {} is not read: only mode 57 (axis by axis about X, Y, Z) is", mode));
  WorkPlane w;
  w.R_part_plane = rot::from_axis_by_axis_xyz(deg2rad(num(7)), deg2rad(num(8)), deg2rad(num(9)));
  const Eigen::Vector3d x0(num(4), num(5), num(6)), x1(num(10), num(11), num(12));
  w.origin_in_part_mm = scale * (x0 + w.R_part_plane * x1);
  w.form = "CYCLE800";
  return w;
}

/// A Heidenhain conversational program starts with "[n] BEGIN PGM name MM|INCH".
bool is_heidenhain(const std::string& text) {
  std::string_view all(text);
  size_t pos = 0;
  while (pos < all.size()) {
    size_t nl = all.find('\n', pos);
    if (nl == std::string_view::npos) nl = all.size();
    std::string_view l = trim(all.substr(pos, nl - pos));
    pos = nl + 1;
    if (l.empty()) continue;
    while (!l.empty() && is_digit(l.front())) l.remove_prefix(1);
    return trim(l).rfind("BEGIN PGM", 0) == 0;
  }
  return false;
}

/// Follows M3 / M4 / M5 into Program::spindle_stops. An M5 takes effect after its block's motion (RS274, Fanuc,
/// TNC): the stop opens at the next line.
class SpindleState {
 public:
  /// An M word of line `lineno`, read before the line's block (if any) is stored. M3 / M4 act before the motion.
  void word(int m, int lineno, Program& p) {
    if (m == 3 || m == 4) {
      ran_ = true;
      pending_ = 0;
      if (open_) p.spindle_stops.back().end_block = p.blocks.size();
      open_ = false;
    } else if ((m == 5 || m == 6) && ran_) {  // a tool change stops the spindle too (M6; TOOL CALL n on a TNC)
      pending_ = lineno;
      pending_what_ = m == 5 ? "M5" : "the tool change (M6)";
    }
  }
  /// At the start of every line: an M5 of an earlier line opens its stop here.
  void line(Program& p) {
    if (pending_ && !open_) {
      p.spindle_stops.push_back({pending_, p.blocks.size(), p.blocks.size(), pending_what_});
      open_ = true;
    }
    pending_ = 0;
  }
  void finish(Program& p) {
    line(p);
    if (open_) p.spindle_stops.back().end_block = p.blocks.size();
  }

 private:
  bool ran_ = false, open_ = false;
  int pending_ = 0;
  const char* pending_what_ = "M5";
};

/// Heidenhain conversational: "n L X+1.5 Y-2 Z+0 A+0 C+90 R0 F1500 M3" (FMAX: rapid), M128 / FUNCTION TCPM
/// switch tool-tip control on; TOOL CALL, CYCL DEF, PLANE and the rest carry no position and are skipped.
Program read_heidenhain(const std::string& text, const std::string& name, const AxisLetters& letters) {
  Program prog;
  prog.file = name;
  for (int a = 0; a < 5; ++a)
    for (int k = 0; k < 3; ++k)
      if (!letters.rotary[static_cast<size_t>(a)] && letters.letter[static_cast<size_t>(a)] == "XYZ"[k])
        prog.xyz_slots[static_cast<size_t>(k)] = a;
  std::shared_ptr<const WorkPlane> plane;  // the tilted work plane in force (shared by its blocks)
  Block state;
  bool inch = false;
  bool tcp_on = false;  // tool-tip control in force (FUNCTION TCPM / M128 ... FUNCTION RESET TCPM / M129)
  SpindleState spindle;
  double feed = 0.0;
  std::string_view all(text);
  size_t pos = 0;
  int lineno = 0;
  while (pos <= all.size()) {
    size_t nl = all.find('\n', pos);
    if (nl == std::string_view::npos) nl = all.size();
    const std::string_view raw = all.substr(pos, nl - pos);
    pos = nl + 1;
    ++lineno;
    spindle.line(prog);
    std::string_view s = trim(raw);
    const auto fail = [&](std::string_view at, const std::string& what) {
      throw InputError(SourceLoc{name, lineno, static_cast<int>(at.data() - raw.data()) + 1}, what);
    };
    while (!s.empty() && is_digit(s.front())) s.remove_prefix(1);  // block number
    s = trim(s);
    if (s.empty()) continue;
    // Comments ("; ..." and "* - ..."), with our header's tool length and machine in them.
    if (s.front() == ';' || s.front() == '*') {
      if (auto p = s.find("cscam tool_length_mm="); p != std::string_view::npos) {
        const auto v = s.substr(p + 21);
        double L = 0;
        if (std::from_chars(v.data(), v.data() + v.size(), L).ec == std::errc()) prog.tool_length_mm = L;
        read_header_cone(s.substr(p), prog);
      }
      constexpr std::string_view kHeader = "cscam post: machine ";
      if (const auto p = s.find(kHeader); !prog.header_machine && p != std::string_view::npos) {
        const auto rest = s.substr(p + kHeader.size());
        const auto end = rest.find(" dialect ");
        if (end != std::string_view::npos) {
          prog.header_machine = std::string(rest.substr(0, end));
          prog.header_line = lineno;
        }
      }
      continue;
    }
    if (s.rfind("BEGIN PGM", 0) == 0) {
      inch = s.find(" INCH") != std::string_view::npos;
      continue;
    }
    if (s.rfind("TOOL CALL", 0) == 0) {
      // A tool number or name loads a tool; "TOOL CALL Z S..." alone changes the spindle speed.
      const std::string_view rest = trim(s.substr(9));
      if (!rest.empty() && (is_digit(rest.front()) || rest.front() == '"' || rest.front() == '\'') &&
          state.tool_changes < UINT16_MAX) {
        ++state.tool_changes;
        spindle.word(6, lineno, prog);
      }
    }
    if (s.rfind("END PGM", 0) == 0) break;
    if (s.rfind("FUNCTION TCPM", 0) == 0) {
      prog.tcp = prog.tcp_words = tcp_on = true;
      continue;
    }
    if (s.rfind("FUNCTION RESET TCPM", 0) == 0) {
      tcp_on = false;
      continue;
    }
    // PLANE SPATIAL SPA SPB SPC (spatial angles about the fixed X, Y, Z) ... STAY|TURN|MOVE; PLANE RESET.
    if (s.rfind("PLANE ", 0) == 0) {
      const std::string_view rest = trim(s.substr(6));
      if (rest.rfind("RESET", 0) == 0) {
        plane.reset();
        continue;
      }
      if (rest.rfind("SPATIAL", 0) != 0)
        fail(rest, fmt::format("'PLANE {}' is not read: only PLANE SPATIAL and PLANE RESET are",
                               std::string(rest.substr(0, rest.find(' ')))));
      std::array<double, 3> ang{};
      std::array<bool, 3> got{};
      for (int k = 0; k < 3; ++k) {
        const std::string key = std::string(" SP") + "ABC"[k];  // not the SPA of SPATIAL
        const auto p = rest.find(key);
        if (p == std::string_view::npos) continue;
        size_t j = p + 4;
        const auto v = parse_number(rest, j);
        if (!v) fail(rest.substr(p), fmt::format("malformed number after '{}'", key));
        ang[static_cast<size_t>(k)] = *v;
        got[static_cast<size_t>(k)] = true;
      }
      if (!got[0] || !got[1] || !got[2]) fail(rest, "PLANE SPATIAL needs SPA, SPB and SPC");
      WorkPlane w;
      w.R_part_plane = rot::from_spatial(deg2rad(ang[0]), deg2rad(ang[1]), deg2rad(ang[2]));
      w.form = "PLANE SPATIAL";
      w.line = lineno;
      if (w.R_part_plane.isIdentity(1e-15)) {
        plane.reset();  // the identity frame changes nothing
      } else {
        plane = std::make_shared<const WorkPlane>(std::move(w));
        prog.work_planes = true;
      }
      continue;
    }
    const bool is_l = s.size() >= 2 && s[0] == 'L' && s[1] == ' ';
    // A comment after the block.
    if (const auto sc = s.find(';'); sc != std::string_view::npos) s = trim(s.substr(0, sc));
    // Coordinate transformations the reader does not model: datum shift (cycle 7, TRANS DATUM), mirror (8), rotation
    // (10), scaling (11, 26), and the TRANS forms of the newer controls. (Their resets, "TRANS ... RESET", are what
    // the reader assumes anyway.)
    if (!is_l) {
      constexpr std::string_view kCycl = "CYCL DEF ";
      if (s.rfind(kCycl, 0) == 0) {
        // The cycle's number; its definition opens with "n" or "n.0" (n.1, n.2 ... carry its values).
        int n = 0;
        const auto r = std::from_chars(s.data() + kCycl.size(), s.data() + s.size(), n);
        const std::string_view after(r.ptr, static_cast<size_t>(s.data() + s.size() - r.ptr));
        const bool opens = after.empty() || after.front() == ' ' || after.rfind(".0", 0) == 0;
        if (r.ec == std::errc() && opens && (n == 7 || n == 8 || n == 10 || n == 11 || n == 26))
          prog.unmodelled.push_back(
              {lineno, fmt::format("CYCL DEF {} transforms the coordinates", n), prog.blocks.size()});
      }
      // Cycle 9's value line: "CYCL DEF 9.1 DWELL 2.5" (seconds).
      if (constexpr std::string_view kDwell = "CYCL DEF 9.1 DWELL"; s.rfind(kDwell, 0) == 0) {
        double t = 0;
        std::string_view v = trim(s.substr(kDwell.size()));
        if (!v.empty() && v.front() == '+') v.remove_prefix(1);
        const auto r = std::from_chars(v.data(), v.data() + v.size(), t);
        if (r.ec != std::errc()) fail(v, "CYCL DEF 9.1 DWELL without a time in seconds");
        ++prog.dwells;
        prog.dwell_seconds += std::max(0.0, t);
      }
      if (s.rfind("TRANS ", 0) == 0 && s.find("RESET") == std::string_view::npos)
        prog.unmodelled.push_back({lineno, fmt::format("{} transforms the coordinates", s), prog.blocks.size()});
    }
    if (!is_l && (s.rfind("CALL LBL", 0) == 0 || s.rfind("CALL PGM", 0) == 0 || s.rfind("CYCL CALL", 0) == 0))
      prog.unmodelled.push_back({lineno, fmt::format("{} calls a subprogram or cycle", s), prog.blocks.size()});
    if (!is_l) {  // M functions on their own line (M128 / M129, the spindle's)
      for (std::size_t a = 0; a < s.size();) {
        const std::size_t e = std::min(s.find(' ', a), s.size());
        if (const std::string_view tok = s.substr(a, e - a); tok == "M3" || tok == "M4" || tok == "M5")
          spindle.word(tok[1] - '0', lineno, prog);
        a = e + 1;
      }
      for (size_t p = s.find("M128"); p != std::string_view::npos; p = s.find("M128", p + 1))
        prog.tcp = prog.tcp_words = tcp_on = true;
      if (s.find("M129") != std::string_view::npos) tcp_on = false;
      continue;
    }
    Block b = state;
    b.words = {};
    bool rapid = false, any = false, machine_coords = false;
    size_t i = 1;
    while (i < s.size()) {
      if (s[i] == ' ') {
        ++i;
        continue;
      }
      const size_t start = i;
      while (i < s.size() && s[i] != ' ') ++i;
      const std::string_view tok = s.substr(start, i - start);
      if (tok == "FMAX" || tok == "FAUTO") {
        rapid = tok == "FMAX";
        continue;
      }
      if (tok == "R0" || tok == "RL" || tok == "RR" || tok == "R+" || tok == "R-") continue;
      const char L = tok[0];
      if (L == 'M') {
        if (tok == "M128") prog.tcp = prog.tcp_words = tcp_on = true;
        if (tok == "M129") tcp_on = false;
        if (tok == "M3" || tok == "M4" || tok == "M5") spindle.word(tok[1] - '0', lineno, prog);
        if (tok == "M91" || tok == "M92") machine_coords = true;  // machine datum: not a work position
        continue;
      }
      size_t k = 1;
      const auto v = parse_number(tok, k);
      if (!v || k != tok.size()) fail(tok, fmt::format("malformed word '{}'", std::string(tok)));
      if (L == 'F') {
        feed = inch ? *v * kMmPerInch : *v;
        continue;
      }
      for (int a = 0; a < 5; ++a) {
        if (letters.letter[static_cast<size_t>(a)] != L) continue;
        double x = *v;
        if (letters.rotary[static_cast<size_t>(a)]) {
          x = deg2rad(x);
          if (letters.modulo[static_cast<size_t>(a)] && b.known[static_cast<size_t>(a)])
            x = b.axes[static_cast<size_t>(a)] + std::remainder(x - b.axes[static_cast<size_t>(a)], 2.0 * kPi);
        } else if (inch) {
          x *= kMmPerInch;
        }
        b.axes[static_cast<size_t>(a)] = x;
        b.known[static_cast<size_t>(a)] = true;
        b.words[static_cast<size_t>(a)] = true;
        any = true;
      }
      if (std::string_view("XYZABCUVW").find(L) != std::string_view::npos &&
          std::none_of(letters.letter.begin(), letters.letter.end(), [L](char c) { return c == L; }) &&
          std::none_of(prog.foreign_axis_words.begin(), prog.foreign_axis_words.end(),
                       [L](const Program::ForeignWord& f) { return f.letter == L; }))
        prog.foreign_axis_words.push_back({L, lineno, static_cast<int>(tok.data() - raw.data()) + 1});
    }
    if (!any) continue;
    if (machine_coords) {
      prog.notes.push_back(fmt::format("{}:{}: M91/M92 block not taken as a position", name, lineno));
      continue;
    }
    b.plane = plane;
    b.tcp = tcp_on;
    if (plane && tcp_on)  // a TNC cancels TCPM before it tilts (our post does: FUNCTION RESET TCPM, PLANE SPATIAL)
      fail(s, "a tilted work plane (PLANE SPATIAL) under tool-tip control is not read");
    b.line = lineno;
    b.motion = rapid ? Motion::Rapid : Motion::Linear;
    b.inverse_time = false;
    // A rotary-only move's F is deg/min in inch programs too (the F word was converted as inch/min).
    b.feed = inch && rotary_only(state, b, letters) ? feed / kMmPerInch : feed;
    prog.blocks.push_back(b);
    state = b;
  }
  spindle.finish(prog);
  return prog;
}

}  // namespace

const Program::Unmodelled* first_unmodelled_before_motion(const Program& p) {
  for (const auto& u : p.unmodelled)
    if (u.blocks_before < p.blocks.size()) return &u;
  return nullptr;
}

Program read_text(const std::string& text, const std::string& name, const AxisLetters& letters) {
  if (is_heidenhain(text)) return read_heidenhain(text, name, letters);
  Program prog;
  prog.file = name;
  // Lines before the first lone '%' are a listing header (NX writes one); skip them when a '%' exists.
  std::vector<std::string_view> lines;
  {
    std::string_view all(text);
    // A UTF-8 byte-order mark (an editor on Windows writes one) is not part of the first line.
    if (all.size() >= 3 && all.substr(0, 3) == "\xEF\xBB\xBF") all.remove_prefix(3);
    // Counted first (memchr): a million-line program's list is then filled without regrowing.
    std::size_t newlines = 0;
    for (const char *p = all.data(), *end = p + all.size();
         (p = static_cast<const char*>(std::memchr(p, '\n', static_cast<size_t>(end - p)))) != nullptr; ++p)
      ++newlines;
    lines.reserve(newlines + 1);
    size_t pos = 0;
    while (pos <= all.size()) {
      size_t nl = all.find('\n', pos);
      if (nl == std::string_view::npos) nl = all.size();
      lines.push_back(all.substr(pos, nl - pos));
      pos = nl + 1;
    }
  }
  size_t first = 0;
  for (size_t i = 0; i < lines.size(); ++i)
    if (trim(lines[i]) == "%") {
      first = i;
      break;
    }

  prog.blocks.reserve(lines.size() - first);  // at most one block a line: no regrowth of a large program
  Block state;
  Motion motion = Motion::Rapid;
  bool inch = false, absolute = true, g93 = false, g435 = false;
  int ended_line = 0, ended_word = 0;  // the program's end (M2 / M30), if read: -1 once a move after it was told
  // Per axis: the line and G word (28, 30, 53) that last moved it home or in machine coordinates (0: none since).
  std::array<std::pair<int, int>, 5> left_at{};
  bool tcp_on =
      false;  // tool-tip control in force: G43.4/G43.5/G234 ... G49 (or G43), M428 ... M429, TRAORI ... TRAFOOF
  int plane = 17;
  // The machine's X, Y and Z slots (arcs are in their planes).
  std::array<int, 3> xyz{-1, -1, -1};
  for (int a = 0; a < 5; ++a)
    for (int k = 0; k < 3; ++k)
      if (!letters.rotary[static_cast<size_t>(a)] && letters.letter[static_cast<size_t>(a)] == "XYZ"[k])
        xyz[static_cast<size_t>(k)] = a;
  prog.xyz_slots = xyz;
  std::shared_ptr<const WorkPlane> work_plane;  // the tilted work plane in force (shared by its blocks)
  std::array<bool, 3> plane_given{};            // X, Y, Z given in it: the modal values are plane coordinates
  double feed = 0.0;
  // What the reader does not model (Program::unmodelled): the work offset selected first, the length offset register
  // in force (-1 none, -2 one without H) and where it was lost (a G49 or a tool change) before the next motion.
  bool p_in_seconds = false;  // G4 P: seconds in a LinuxCNC program
  SpindleState spindle;
  int work_offset = 0;
  int tlo_h = -1;
  bool uses_length_offset = false;
  int tlo_lost_line = 0;
  std::string tlo_lost_why;
  // Tokenising is most of the reading and needs no modal state: the lines ahead are tokenised in parallel, a
  // window at a time (fixed chunks), and read in order below; the window after the one being read is tokenised
  // in the background meanwhile.
  static constexpr std::size_t kWindow = 1 << 15, kChunk = 1 << 10;
  struct LineWords {
    std::uint32_t first = 0, count = 0;
    bool simple = false;
  };
  struct TokenWindow {
    std::size_t begin = 0, end = 0;
    std::vector<std::vector<Word>> chunk_words;
    std::vector<LineWords> line_words;
  };
  auto tokenise = [&lines](TokenWindow& w, std::size_t begin, std::size_t end) {
    w.begin = begin;
    w.end = end;
    const std::size_t chunks = (end - begin + kChunk - 1) / kChunk;
    w.chunk_words.resize(chunks);
    w.line_words.assign(end - begin, LineWords{});
    parallel_range(0, chunks, 1, [&](const tbb::blocked_range<std::size_t>& r) {
      for (std::size_t c = r.begin(); c != r.end(); ++c) {
        auto& words = w.chunk_words[c];
        words.clear();
        const std::size_t l0 = begin + c * kChunk, l1 = std::min(end, l0 + kChunk);
        for (std::size_t l = l0; l < l1; ++l) {
          LineWords& lw = w.line_words[l - begin];
          lw.first = static_cast<std::uint32_t>(words.size());
          lw.simple = simple_words(lines[l], words);
          if (!lw.simple) words.resize(lw.first);
          lw.count = static_cast<std::uint32_t>(words.size() - lw.first);
        }
      }
    });
  };
  TokenWindow window, next;
  bool next_pending = false;
  Background next_job;  // after the windows it writes: joined first when leaving (a throw, the closing '%')
  std::size_t tn = 0;
  auto tokens_for = [&](std::size_t li, std::size_t& count) -> const Word* {
    if (li >= window.end) {
      if (next_pending) {
        next_job.wait();
        next_pending = false;
      }
      if (li >= next.begin && li < next.end)
        std::swap(window, next);
      else
        tokenise(window, li, std::min(lines.size(), li + kWindow));
      if (window.end < lines.size()) {
        next_pending = true;
        next_job.run(
            [&tokenise, &next, &lines, b = window.end] { tokenise(next, b, std::min(lines.size(), b + kWindow)); });
      }
    }
    const LineWords& lw = window.line_words[li - window.begin];
    count = lw.count;
    return lw.simple ? window.chunk_words[(li - window.begin) / kChunk].data() + lw.first : nullptr;
  };
  for (size_t li = first; li < lines.size(); ++li) {
    const std::string_view raw = lines[li];
    const int lineno = static_cast<int>(li) + 1;
    // The closing '%' ends the program; NX appends a listing trailer after it.
    if (li > first && trim(raw) == "%" && trim(lines[first]) == "%") break;
    std::string_view s = raw;
    // Header comment carrying the tool length our post used.
    if (auto p = s.find("cscam tool_length_mm="); p != std::string_view::npos) {
      const auto v = s.substr(p + 21);
      double L = 0;
      auto r = std::from_chars(v.data(), v.data() + v.size(), L);
      if (r.ec == std::errc()) prog.tool_length_mm = L;
      read_header_cone(s.substr(p), prog);
    }
    // Our post's header names the machine the program was written for.
    if (!prog.header_machine) {
      constexpr std::string_view kHeader = "(cscam post: machine ";
      if (const auto p = s.find(kHeader); p != std::string_view::npos) {
        const auto rest = s.substr(p + kHeader.size());
        auto end = rest.find(" dialect ");
        if (end == std::string_view::npos) end = rest.find(')');
        if (end != std::string_view::npos) {
          prog.header_machine = std::string(rest.substr(0, end));
          prog.header_line = lineno;
        }
      }
    }
    spindle.line(prog);
    // Our header names the dialect: a LinuxCNC G4 P is seconds with or without a decimal point.
    if (lineno == prog.header_line && s.find(" dialect linuxcnc") != std::string_view::npos) p_in_seconds = true;
    bool non_modal_skip = false, tcp_word = false, vector_words = false;
    bool plane_def = false, plane_cancel = false;
    bool dwell = false;
    std::optional<double> dwell_s;  // from P, X, U (ISO) or F (Sinumerik) in a G4 block
    bool dwell_revolutions = false;
    std::optional<double> f_word;
    int offset_word = 0;  // G54 ... G59.3, G500 (x10) in this block
    bool length_offset = false, length_cancel = false, tool_change = false;
    int home_word = 0;  // G28 / G30 (to home, through an intermediate point) or G53 (machine coordinates) in this block
    std::optional<double> h_word;
    auto unmodelled = [&](std::string what) {
      prog.unmodelled.push_back({lineno, std::move(what), prog.blocks.size()});
    };
    std::optional<WorkPlane> cycle_plane;
    bool cycle_seen = false;
    Block b = state;
    b.words = {};
    size_t i = 0;
    auto fail = [&](size_t col, const std::string& what) {
      throw InputError(SourceLoc{name, lineno, static_cast<int>(col) + 1}, what);
    };
    std::array<double, 5> word_val{};
    std::array<bool, 5> word_short{};
    std::array<double, 3> ijk{};
    std::array<bool, 3> ijk_given{};
    std::optional<double> r_word;
    int ijk_column = 0;
    // An axis word: the machine's letter, or a letter it lacks (noted once).
    auto axis_word_value = [&](char L, double v, bool short_way, int word_column) {
      bool axis_word = false;
      for (int a = 0; a < 5; ++a)
        if (letters.letter[static_cast<size_t>(a)] == L) {
          b.words[static_cast<size_t>(a)] = true;
          word_val[static_cast<size_t>(a)] = v;
          word_short[static_cast<size_t>(a)] = short_way;
          axis_word = true;
        }
      if (!axis_word && std::string_view("XYZABCUVW").find(L) != std::string_view::npos &&
          std::none_of(prog.foreign_axis_words.begin(), prog.foreign_axis_words.end(),
                       [L](const Program::ForeignWord& f) { return f.letter == L; }))
        prog.foreign_axis_words.push_back({L, lineno, word_column});
      return axis_word;
    };
    // One word (letter, value, 1-based column) of the block: its meaning for the modal state and the block.
    auto on_word = [&](const char L, const double v, const int word_column) {
      if (L == 'G') {
        const int g10 = static_cast<int>(std::lround(v * 10));
        switch (g10) {
          case 0:
            motion = Motion::Rapid;
            break;
          case 10:
            motion = Motion::Linear;
            break;
          case 20:
            motion = Motion::ArcCW;
            break;
          case 30:
            motion = Motion::ArcCCW;
            break;
          case 170:
          case 180:
          case 190:
            plane = g10 / 10;
            break;
          case 200:
          case 700:   // Sinumerik G70 (and older ISO milling controls): inch
          case 7000:  // Sinumerik G700: inch, feeds too
            inch = true;
            break;
          case 210:
          case 710:
          case 7100:
            inch = false;
            break;
          case 900:
            absolute = true;
            break;
          case 910:
            absolute = false;
            break;
          case 930:
            g93 = true;
            break;
          case 940:
            g93 = false;
            break;
          case 682:  // G68.2 X Y Z I J K: a tilted work plane (ZXZ Euler angles) about the origin X Y Z
            plane_def = true;
            break;
          case 531:  // G53.1: tool axis to the plane (the rotaries positioned before it; see resolve_work_planes)
            break;
          case 690:
            plane_cancel = true;
            break;
          case 2540:  // Haas G254 / G255 dynamic work offset on / off: the control carries the work offset with the
          case 2550:  // rotaries; the words stay the post's machine coordinates (Haas mill manual, G254)
            break;
          case 280:
          case 300:
            home_word = g10 / 10;
            non_modal_skip = true;
            break;
          case 530:
            home_word = 53;
            non_modal_skip = true;
            break;
          case 410:
          case 420:
            unmodelled(
                fmt::format("G{} offsets the tool from the programmed path by its radius (cutter "
                            "compensation)",
                            g10 / 10));
            break;
          case 650:
          case 660:
            non_modal_skip = true;  // its words are the macro's arguments
            unmodelled(fmt::format("G{} calls a macro", g10 / 10));
            break;
          case 730:
          case 740:
          case 760:
          case 810:
          case 820:
          case 830:
          case 840:
          case 850:
          case 860:
          case 870:
          case 880:
          case 890:
            non_modal_skip = true;  // its words are the cycle's (depth, R plane, peck), not a position
            unmodelled(fmt::format("G{} is a canned cycle (its moves are the control's)", g10 / 10));
            break;
          case 40:  // dwell: its P, X, U (or F) words are its time, not a position or a feed
            dwell = true;
            non_modal_skip = true;
            break;
          case 100:
            non_modal_skip = true;
            unmodelled("G10 writes offset or tool data");
            break;
          case 920:
          case 923:  // G92.3 restores a saved shift
            non_modal_skip = true;
            unmodelled(fmt::format("G{:g} shifts the coordinate system", v));
            break;
          case 921:  // G92.1 / G92.2 cancel a shift: what the reader assumes anyway
          case 922:
            non_modal_skip = true;
            break;
          case 520:
            non_modal_skip = true;  // its words are the shift, not a position
            unmodelled("G52 shifts the coordinate system (local coordinates)");
            break;
          case 680:
            non_modal_skip = true;  // X Y R: the centre and angle of the rotation
            unmodelled("G68 rotates the coordinate system");
            break;
          case 510:
          case 511:
            non_modal_skip = true;
            unmodelled(g10 == 510 ? "G51 scales the coordinates" : "G51.1 mirrors the coordinates");
            break;
          case 540:
          case 541:
          case 550:
          case 560:
          case 570:
          case 580:
          case 590:
          case 591:
          case 592:
          case 593:
          case 5000:  // Sinumerik G500: no settable offset
            offset_word = g10;
            break;
          case 434:
          case 2340:
            tcp_word = tcp_on = true;
            length_offset = true;  // with its H word
            break;
          case 435:  // Fanuc tool-tip control with the tool vector I J K
            tcp_word = tcp_on = true;
            g435 = true;
            length_offset = true;
            break;
          case 430:  // plain length offset: the same modal group, so tool-tip control ends
          case 440:
          case 490:
            g435 = false;
            tcp_on = false;
            (g10 == 490 ? length_cancel : length_offset) = true;
            break;
          default:
            break;
        }
        return;
      }
      if (L == 'F') {
        f_word = v;  // the feed, unless this is a dwell (applied after the block's words)
        return;
      }
      if (dwell && (L == 'P' || L == 'X' || L == 'U' || L == 'S')) {
        // The dwell's time (G4 after its words is not read as one: rare). A P without a decimal point is
        // milliseconds on Fanuc and Haas; X and U are seconds; S (Sinumerik) is spindle revolutions.
        if (L == 'S') {
          dwell_revolutions = true;
          return;
        }
        bool decimal = L != 'P' || p_in_seconds;
        for (std::size_t k = static_cast<std::size_t>(word_column); k < s.size() && !decimal; ++k) {
          if (s[k] == '.') decimal = true;
          if (!is_digit(s[k]) && s[k] != '.' && s[k] != '+' && s[k] != '-' && s[k] != ' ') break;
        }
        dwell_s = decimal ? v : v / 1000.0;
        return;
      }
      if (L == 'H') {
        h_word = v;
        return;
      }
      // Sinumerik "L100": a subprogram call (G10's L is its data form, already not modelled).
      if (L == 'L' && !non_modal_skip) {
        unmodelled(fmt::format("L{:g} calls a subprogram", v));
        return;
      }
      if (L == 'M') {
        if (v == 6.0) {
          tool_change = true;
          spindle.word(6, lineno, prog);
        }
        if (v == 98.0 || v == 97.0) unmodelled(fmt::format("M{:g} calls a subprogram", v));
        if (v == 99.0) unmodelled("M99 returns from a subprogram (or loops the program)");
        if ((v == 2.0 || v == 30.0) && !ended_line) ended_line = lineno, ended_word = static_cast<int>(v);
        if (v == 3.0 || v == 4.0 || v == 5.0) spindle.word(static_cast<int>(v), lineno, prog);
        // LinuxCNC's switchable trunnion kinematics: M428 world (TCP) coordinates, M429 identity (joints).
        if (std::lround(v) == 428) tcp_word = tcp_on = true;
        if (std::lround(v) == 429) tcp_on = false;
        return;
      }
      if (!plane_def && g435 && (L == 'I' || L == 'J' || L == 'K')) {
        b.tool_vector[static_cast<size_t>(L - 'I')] = v;
        vector_words = true;
        return;
      }
      if (L == 'I' || L == 'J' || L == 'K') {  // arc centre, incremental from the start (G91.1, the default)
        ijk[static_cast<size_t>(L - 'I')] = v;
        ijk_given[static_cast<size_t>(L - 'I')] = true;
        ijk_column = word_column;
        return;
      }
      if (L == 'R') {
        r_word = v;
        ijk_column = word_column;
        return;
      }
      axis_word_value(L, v, false, word_column);
    };
    // Lines of letter-number words only (nearly all of a posted program) come tokenised from the parallel
    // pass (tokens_for); any other line is read here character by character.
    if (const Word* tw = tokens_for(li, tn)) {
      for (std::size_t t = 0; t < tn; ++t) on_word(tw[t].letter, tw[t].value, tw[t].column);
      i = s.size();
    }
    while (i < s.size()) {
      const char c = s[i];
      if (is_space(c) || c == '%') {
        ++i;
        continue;
      }
      if (c == '(') {
        const size_t e = s.find(')', i);
        i = e == std::string_view::npos ? s.size() : e + 1;
        continue;
      }
      if (c == ';') break;
      if (c == '/' && i == 0) {  // block delete: still a valid block for reading
        ++i;
        continue;
      }
      if (!is_alpha(c)) {
        const auto byte = static_cast<unsigned char>(c);
        fail(i, byte >= 0x20 && byte < 0x7f
                    ? fmt::format("unexpected character '{}'", c)
                    : fmt::format("unexpected byte 0x{:02X} (not G-code text{})", byte,
                                  byte == 0xEF && i == 0 ? ": a UTF-8 byte-order mark? save the file without it" : ""));
      }
      const char L = to_upper(c);
      const int word_column = static_cast<int>(i) + 1;
      if (L == 'O') {  // program number/name ("O2021-11-28_part"): not a block; LinuxCNC's o-word flow control is
        std::size_t e = i + 1;
        while (e < s.size() && (is_alnum(s[e]) || s[e] == '<' || s[e] == '>' || s[e] == '_')) ++e;
        while (e < s.size() && s[e] == ' ') ++e;
        std::size_t k = e;
        while (k < s.size() && is_alpha(s[k])) ++k;
        std::string kw(s.substr(e, k - e));
        for (char& ch : kw) ch = static_cast<char>(std::tolower(static_cast<unsigned char>(ch)));
        static const std::set<std::string> flow{"call",   "sub",    "endsub",    "return", "if",
                                                "elseif", "else",   "endif",     "while",  "endwhile",
                                                "do",     "repeat", "endrepeat", "break",  "continue"};
        if (flow.count(kw))
          unmodelled(fmt::format("o-word '{}' (LinuxCNC flow control: a subroutine, loop or condition)", kw));
        break;
      }
      // Sinumerik identifiers (TRAORI, TRAFOOF, ORIWKS, CYCLE800(...), MCALL ...): skipped, TRAORI noted.
      if (i + 1 < s.size() && (is_alpha(s[i + 1]) || s[i + 1] == '_')) {
        size_t e = i;
        while (e < s.size() && (is_alnum(s[e]) || s[e] == '_')) ++e;
        std::string id(s.substr(i, e - i));
        for (char& ch : id) ch = to_upper(ch);
        if (id == "TRAORI") tcp_word = tcp_on = true;
        if (id == "TRAFOOF") tcp_on = false;
        if (id == "SUPA") non_modal_skip = true;  // machine coordinates: every frame suppressed for this block
        if (id == "CALL" || id == "PCALL" || id == "MCALL" || id == "EXTCALL")
          unmodelled(fmt::format("{} calls a subprogram or cycle", id));
        if (id == "TRANS" || id == "ATRANS" || id == "CTRANS" || id == "ROT" || id == "AROT" || id == "CROT" ||
            id == "ROTS" || id == "AROTS" || id == "SCALE" || id == "ASCALE" || id == "MIRROR" || id == "AMIRROR") {
          // Alone it resets that part of the frame (what the reader assumes anyway); with words it sets one.
          const auto rest = s.substr(e);
          const auto first = rest.find_first_not_of(' ');
          if (first != std::string_view::npos && rest[first] != ';')
            unmodelled(fmt::format("{} changes the programmable frame", id));
          i = s.size();  // its words are the frame's, not a position
          continue;
        }
        if (id == "CYCLE800") {
          size_t open = e;
          while (open < s.size() && s[open] == ' ') ++open;
          if (open >= s.size() || s[open] != '(') fail(e, "CYCLE800 without its argument list");
          cycle_seen = true;
          cycle_plane = cycle800(s, open, inch ? kMmPerInch : 1.0, fail);
        }
        i = skip_argument(s, e);
        continue;
      }
      // Sinumerik "A3=0.5" (tool vector) or "R1=..." (parameter): a letter, digits, '='.
      {
        size_t e = i + 1;
        while (e < s.size() && is_digit(s[e])) ++e;
        if (e > i + 1 && e < s.size() && s[e] == '=') {
          const std::string_view ext = s.substr(i + 1, e - i - 1);
          size_t k = e + 1;
          if (ext == "3" && (L == 'A' || L == 'B' || L == 'C')) {
            const auto val = parse_number(s, k);
            if (!val) fail(k, fmt::format("malformed number after '{}3='", L));
            b.tool_vector[static_cast<size_t>(L - 'A')] = *val;
            vector_words = true;
            i = k;
          } else {
            i = skip_argument(s, e);
          }
          continue;
        }
      }
      // Sinumerik "X=10", "C=DC(45)", "C=ACP(45)", "T=\"name\"": the value after '=', maybe in a function.
      bool short_way = false;
      size_t j = i + 1;
      while (j < s.size() && s[j] == ' ') ++j;
      if (j < s.size() && s[j] == '=') {
        ++j;
        if (j < s.size() && s[j] == '"') {  // T="name"
          const size_t q = s.find('"', j + 1);
          i = q == std::string_view::npos ? s.size() : q + 1;
          continue;
        }
        if (j < s.size() && is_alpha(s[j])) {
          size_t e = j;
          while (e < s.size() && is_alpha(s[e])) ++e;
          std::string fn(s.substr(j, e - j));
          for (char& ch : fn) ch = to_upper(ch);
          if (e >= s.size() || s[e] != '(') fail(j, fmt::format("expected a number or a function after '{}='", L));
          short_way = fn == "DC";
          if (fn != "DC" && fn != "AC" && fn != "ACP" && fn != "ACN")
            fail(j, fmt::format("'{}={}()' is not an absolute position this reader knows (DC, AC, ACP, ACN)", L, fn));
          size_t k = e + 1;
          const auto val = parse_number(s, k);
          if (!val || k >= s.size() || s[k] != ')') fail(e + 1, fmt::format("malformed number in '{}={}()'", L, fn));
          i = k + 1;
          if (!axis_word_value(L, *val, short_way, word_column)) continue;
          continue;
        }
      }
      size_t k = j;
      if (k < s.size() && (s[k] == '-' || s[k] == '+')) ++k;
      while (k < s.size() && (is_digit(s[k]) || s[k] == '.')) ++k;
      double v = 0;
      // "X-.5" and "X3." are valid G-code numbers; from_chars wants a digit before/after the point.
      if (!gcode_number(s.substr(j, k - j), v))
        fail(j, fmt::format("malformed number after '{}': '{}'", L, std::string(s.substr(j, k - j))));
      i = k;
      on_word(L, v, word_column);
    }
    if (tcp_word) prog.tcp = prog.tcp_words = true;
    bool any_axis = false;
    for (bool w : b.words) any_axis |= w;
    if (plane_def || cycle_seen) {
      if (cycle_seen && !cycle_plane) {
        work_plane.reset();  // CYCLE800(): the swivelled frame reset
      } else {
        WorkPlane w;
        if (cycle_plane) {
          w = *cycle_plane;
        } else if (plane_def) {
          w.R_part_plane = rot::from_euler_zxz(deg2rad(ijk[0]), deg2rad(ijk[1]), deg2rad(ijk[2]));
          for (int k = 0; k < 3; ++k) {
            const int slot = xyz[static_cast<size_t>(k)];
            if (slot >= 0 && b.words[static_cast<size_t>(slot)])
              w.origin_in_part_mm[k] = word_val[static_cast<size_t>(slot)] * (inch ? kMmPerInch : 1.0);
          }
          w.form = "G68.2";
        }
        if (!plane_def && any_axis) fail(0, fmt::format("{} with axis words is not read", w.form));
        w.line = lineno;
        // The identity frame (no rotation, no offset: e.g. CYCLE800 to the basic position) changes nothing.
        if (w.R_part_plane.isIdentity(1e-15) && w.origin_in_part_mm.isZero(0.0)) {
          work_plane.reset();
        } else {
          work_plane = std::make_shared<const WorkPlane>(std::move(w));
          prog.work_planes = true;
        }
      }
      continue;  // the plane's words (G68.2 X Y Z I J K) are its origin and angles, not a position
    }
    if (plane_cancel) work_plane.reset();
    if (work_plane && (any_axis || vector_words)) {
      if (!absolute)
        fail(0, fmt::format("incremental (G91) words in a tilted work plane ({}) are not read", work_plane->form));
      if (vector_words || g435 || tcp_on)  // a control refuses it too: TCP is cancelled before the plane
        fail(0, fmt::format("a tilted work plane ({}) under tool-tip control is not read", work_plane->form));
    }
    if (work_plane != state.plane) plane_given = {};  // a new plane (or none): its coordinates start unknown
    b.plane = work_plane;
    b.tcp = tcp_on;
    if (vector_words) {
      prog.tcp_vectors = true;
      b.has_vector = true;
      any_axis = true;  // a change of orientation alone is a move
    }
    if (dwell) {
      ++prog.dwells;
      if (!dwell_s && f_word && !dwell_revolutions) dwell_s = *f_word;  // Sinumerik G4 F: seconds
      if (dwell_s && !dwell_revolutions) prog.dwell_seconds += std::max(0.0, *dwell_s);
    } else if (f_word) {
      feed = *f_word;
    }
    if (offset_word) {
      auto offset_name = [](int g) {
        return g % 10 ? fmt::format("G{}.{}", g / 10, g % 10) : fmt::format("G{}", g / 10);
      };
      if (work_offset && offset_word != work_offset)
        unmodelled(
            fmt::format("the work offset changes from {} to {}", offset_name(work_offset), offset_name(offset_word)));
      work_offset = offset_word;
    }
    if (tool_change && state.tool_changes < UINT16_MAX)  // (a block without a position leaves `state` as is)
      ++state.tool_changes, ++b.tool_changes;
    if (tool_change && uses_length_offset) {
      tlo_lost_line = lineno;
      tlo_lost_why = "a tool change (M6) without a new tool length offset (G43 H) before the next move";
    }
    if (length_offset) {
      uses_length_offset = true;
      const int h = h_word ? static_cast<int>(std::lround(*h_word)) : -2;
      if (!tlo_lost_line && tlo_h >= 0 && h >= 0 && h != tlo_h)
        unmodelled(fmt::format("the tool length offset changes from H{} to H{} without a tool change", tlo_h, h));
      tlo_h = h;
      tlo_lost_line = 0;
    } else if (length_cancel && tlo_h != -1) {
      tlo_h = -1;
      tlo_lost_line = lineno;
      tlo_lost_why = "G49 cancels the tool length offset before more moves";
    }
    // A Z word from here is off by the tool length (a move of the other axes alone keeps Z where it is).
    if (tlo_lost_line && xyz[2] >= 0 && b.words[static_cast<size_t>(xyz[2])] && !non_modal_skip) {
      prog.unmodelled.push_back({tlo_lost_line, tlo_lost_why, prog.blocks.size()});
      tlo_lost_line = 0;
    }
    if ((home_word == 28 || home_word == 30) && !any_axis) {
      // Without words every axis goes to the stored home position.
      for (int a = 0; a < 5; ++a) left_at[static_cast<size_t>(a)] = {lineno, home_word};
    }
    if (home_word && any_axis) {
      // G28 / G30 go home through the words' point: in G90 a point of the work coordinates (G28 Z0 dips to the part's
      // zero on its way up), in G91 one that far from here (zero: straight home).
      bool via = home_word != 53 && absolute;
      for (int a = 0; a < 5; ++a)
        if (home_word != 53 && b.words[static_cast<size_t>(a)] && word_val[static_cast<size_t>(a)] != 0.0) via = true;
      if (via) unmodelled(fmt::format("G{} goes home through an intermediate point", home_word));
      // Where the axes it moves end, in the program's coordinates, the read-back does not know: a feed must not
      // start there (a rapid may: the program positions them again before it cuts).
      for (int a = 0; a < 5; ++a)
        if (b.words[static_cast<size_t>(a)]) left_at[static_cast<size_t>(a)] = {lineno, home_word};
    }
    if (non_modal_skip) {
      if (any_axis)
        prog.notes.push_back(
            fmt::format("{}:{}: G28/G30/G53/G10/G92 or SUPA block not taken as a position", name, lineno));
      continue;
    }
    if (!any_axis) continue;
    if (ended_line > 0) {
      unmodelled(fmt::format("a move after the program's end (M{} at line {}): the control never runs it", ended_word,
                             ended_line));
      ended_line = -1;  // said once
    }
    if (motion != Motion::Rapid)
      for (int a = 0; a < 5; ++a) {
        auto& [at, by] = left_at[static_cast<size_t>(a)];
        if (at > 0 && !b.words[static_cast<size_t>(a)]) {
          unmodelled(
              fmt::format("the move starts where G{} at line {} left axis {} (at machine home or in machine "
                          "coordinates)",
                          by, at, letters.letter[static_cast<size_t>(a)]));
          left_at.fill({0, 0});
          break;
        }
      }
    for (int a = 0; a < 5; ++a)
      if (b.words[static_cast<size_t>(a)]) left_at[static_cast<size_t>(a)] = {0, 0};
    for (int a = 0; a < 5; ++a) {
      if (!b.words[static_cast<size_t>(a)]) continue;
      double v = word_val[static_cast<size_t>(a)];
      if (letters.rotary[static_cast<size_t>(a)])
        v = deg2rad(v);
      else if (inch)
        v *= kMmPerInch;
      const bool unwrap = letters.rotary[static_cast<size_t>(a)] && absolute &&
                          (letters.modulo[static_cast<size_t>(a)] || word_short[static_cast<size_t>(a)]) &&
                          b.known[static_cast<size_t>(a)];
      if (unwrap) {  // the short way from where the axis is
        const double prev = b.axes[static_cast<size_t>(a)];
        v = prev + std::remainder(v - prev, 2.0 * kPi);
      }
      b.axes[static_cast<size_t>(a)] = absolute ? v : b.axes[static_cast<size_t>(a)] + v;
      b.known[static_cast<size_t>(a)] = true;
    }
    b.arc.reset();
    if (motion == Motion::ArcCW || motion == Motion::ArcCCW) {
      ArcGeometry g;
      g.plane = plane;
      const std::array<int, 3> uvw = plane == 17   ? std::array<int, 3>{0, 1, 2}
                                     : plane == 18 ? std::array<int, 3>{2, 0, 1}
                                                   : std::array<int, 3>{1, 2, 0};
      for (int k = 0; k < 3; ++k)
        g.slot[static_cast<size_t>(k)] = xyz[static_cast<size_t>(uvw[static_cast<size_t>(k)])];
      if (g.slot[0] < 0 || g.slot[1] < 0 || g.slot[2] < 0)
        fail(0, fmt::format("G{} arc in the G{} plane, but this machine lacks one of its axes X, Y, Z",
                            motion == Motion::ArcCW ? 2 : 3, plane));
      const auto su = static_cast<size_t>(g.slot[0]), sv = static_cast<size_t>(g.slot[1]);
      if (!state.known[su] || !state.known[sv])
        fail(0, "arc before its plane's axes have a position: its start is unknown");
      // In a tilted work plane the arc is in its coordinates (G17: the plane's XY; report::resolve_work_planes
      // turns it into machine axes): its start must be given in them, not the machine position before the plane.
      if (work_plane && (!plane_given[static_cast<size_t>(uvw[0])] || !plane_given[static_cast<size_t>(uvw[1])]))
        fail(0, fmt::format("arc in a tilted work plane ({}) before its plane's axes are given in it: its start is "
                            "unknown",
                            work_plane->form));
      const double scale = inch ? kMmPerInch : 1.0;
      const double u0 = state.axes[su], v0 = state.axes[sv], u1 = b.axes[su], v1 = b.axes[sv];
      const bool cw = motion == Motion::ArcCW;
      if (ijk_given[static_cast<size_t>(uvw[0])] || ijk_given[static_cast<size_t>(uvw[1])]) {
        if (r_word) fail(static_cast<size_t>(ijk_column - 1), "arc with both I J K and R");
        g.centre_u = u0 + scale * ijk[static_cast<size_t>(uvw[0])];
        g.centre_v = v0 + scale * ijk[static_cast<size_t>(uvw[1])];
      } else if (r_word) {
        const double R = *r_word * scale, du = u1 - u0, dv = v1 - v0, d = std::hypot(du, dv);
        if (d < 1e-9) fail(static_cast<size_t>(ijk_column - 1), "R arc with its end at its start");
        if (std::abs(R) < 0.5 * d - 1e-6)
          fail(static_cast<size_t>(ijk_column - 1),
               fmt::format("arc radius R{} is less than half the distance to its end ({:.4f} mm)", *r_word, 0.5 * d));
        const double h = std::sqrt(std::max(0.0, R * R - 0.25 * d * d));
        // Left of the chord for a counter-clockwise short arc; R < 0 asks for the long arc.
        const double side = (cw ? -1.0 : 1.0) * (R < 0 ? -1.0 : 1.0);
        g.centre_u = 0.5 * (u0 + u1) - side * h * dv / d;
        g.centre_v = 0.5 * (v0 + v1) + side * h * du / d;
      } else {
        fail(0, fmt::format("G{} arc without a centre (I J K in its plane) or a radius (R)", cw ? 2 : 3));
      }
      g.start_radius_mm = std::hypot(u0 - g.centre_u, v0 - g.centre_v);
      g.end_radius_mm = std::hypot(u1 - g.centre_u, v1 - g.centre_v);
      if (g.start_radius_mm < 1e-9 || g.end_radius_mm < 1e-9) fail(0, "arc with its start or end at its centre");
      g.start_angle_rad = std::atan2(v0 - g.centre_v, u0 - g.centre_u);
      const double a1 = std::atan2(v1 - g.centre_v, u1 - g.centre_u);
      double ccw = std::fmod(a1 - g.start_angle_rad + 4.0 * kPi, 2.0 * kPi);  // [0, 2 pi)
      double cwa = std::fmod(g.start_angle_rad - a1 + 4.0 * kPi, 2.0 * kPi);
      if (ccw < 1e-12) ccw = 2.0 * kPi;  // end = start: a full circle
      if (cwa < 1e-12) cwa = 2.0 * kPi;
      g.sweep_rad = cw ? -cwa : ccw;
      b.arc = std::make_shared<const ArcGeometry>(g);
    }
    if (work_plane)
      for (int k = 0; k < 3; ++k)
        if (xyz[static_cast<size_t>(k)] >= 0 && b.words[static_cast<size_t>(xyz[static_cast<size_t>(k)])])
          plane_given[static_cast<size_t>(k)] = true;
    b.line = lineno;
    b.motion = motion;
    b.inverse_time = g93;
    // In inch, F is inch/min, except for a move of the rotaries alone, whose F is deg/min (G20 or not).
    b.feed = inch && !g93 && !rotary_only(state, b, letters) ? feed * kMmPerInch : feed;
    prog.blocks.push_back(b);
    state = b;
  }
  spindle.finish(prog);
  return prog;
}

namespace {

Eigen::Vector3d xyz_of(const std::array<double, 5>& q, const ArcGeometry& g) {
  return {q[static_cast<size_t>(g.slot[0])], q[static_cast<size_t>(g.slot[1])], q[static_cast<size_t>(g.slot[2])]};
}

}  // namespace

std::array<double, 5> point_on(const std::array<double, 5>& start, const Block& b, double t) {
  std::array<double, 5> q{};
  for (size_t a = 0; a < 5; ++a) q[a] = start[a] + t * (b.axes[a] - start[a]);
  if (b.arc) {
    const ArcGeometry& g = *b.arc;
    const double ang = g.start_angle_rad + t * g.sweep_rad;
    const double r = g.start_radius_mm + t * (g.end_radius_mm - g.start_radius_mm);
    if (g.tilted) {  // the chord's point moved within the tilted plane onto the circle; along the normal it stays
      const ArcGeometry::Tilted& c = *g.tilted;
      const Eigen::Vector3d n = c.u.cross(c.v);
      const Eigen::Vector3d p =
          c.centre_mm + n.dot(xyz_of(q, g) - c.centre_mm) * n + r * std::cos(ang) * c.u + r * std::sin(ang) * c.v;
      for (int k = 0; k < 3; ++k) q[static_cast<size_t>(g.slot[static_cast<size_t>(k)])] = p[k];
    } else {
      q[static_cast<size_t>(g.slot[0])] = g.centre_u + r * std::cos(ang);
      q[static_cast<size_t>(g.slot[1])] = g.centre_v + r * std::sin(ang);
    }
  }
  return q;
}

double linear_path_mm(const std::array<double, 5>& start, const Block& b, const std::array<bool, 5>& rotary) {
  double lin2 = 0.0;
  const bool tilted = b.arc && b.arc->tilted;
  for (size_t a = 0; a < 5; ++a)
    if (!rotary[a] && !(b.arc && (static_cast<int>(a) == b.arc->slot[0] || static_cast<int>(a) == b.arc->slot[1] ||
                                  (tilted && static_cast<int>(a) == b.arc->slot[2]))))
      lin2 += (b.axes[a] - start[a]) * (b.axes[a] - start[a]);
  if (b.arc) {
    const double in_plane = 0.5 * (b.arc->start_radius_mm + b.arc->end_radius_mm) * std::abs(b.arc->sweep_rad);
    lin2 += in_plane * in_plane;
  }
  if (tilted) {  // the helix' rise along the tilted normal
    const ArcGeometry::Tilted& c = *b.arc->tilted;
    const double rise = c.u.cross(c.v).dot(xyz_of(b.axes, *b.arc) - xyz_of(start, *b.arc));
    lin2 += rise * rise;
  }
  return std::sqrt(lin2);
}

std::array<double, 5> arc_axis_travel(const std::array<double, 5>& start, const Block& b) {
  std::array<double, 5> d{};
  for (size_t a = 0; a < 5; ++a) d[a] = std::abs(b.axes[a] - start[a]);
  if (!b.arc) return d;
  const ArcGeometry& g = *b.arc;
  const double in_plane = 0.5 * (g.start_radius_mm + g.end_radius_mm) * std::abs(g.sweep_rad);
  if (!g.tilted) {
    d[static_cast<size_t>(g.slot[0])] = d[static_cast<size_t>(g.slot[1])] = in_plane;
    return d;
  }
  const ArcGeometry::Tilted& c = *g.tilted;
  const Eigen::Vector3d n = c.u.cross(c.v);
  const double rise = std::abs(n.dot(xyz_of(b.axes, g) - xyz_of(start, g)));
  for (int k = 0; k < 3; ++k)
    d[static_cast<size_t>(g.slot[static_cast<size_t>(k)])] =
        in_plane * std::hypot(c.u[k], c.v[k]) + rise * std::abs(n[k]);
  return d;
}

Program read_file(const std::string& path, const AxisLetters& letters) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw InputError(SourceLoc{path}, "cannot open NC file");
  std::stringstream ss;
  ss << in.rdbuf();
  return read_text(ss.str(), path, letters);
}

}  // namespace cscam::nc
