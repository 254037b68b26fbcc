// Reader of cutter-location files: APT/CLDATA (NX CLSF, ISO 4343, CATIA flavours) and a CSV form.
//
// Speed matters (a benchmark parses a million GOTO/ lines): the text is read in one go and split by hand with
// memchr, numbers go through decimal_from_chars (from_chars with a fast path), and per-statement buffers are reused
// instead of reallocated.
#include <fmt/format.h>
#include <tbb/task_arena.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cctype>
#include <charconv>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <fstream>
#include <iterator>
#include <optional>
#include <string_view>
#include <utility>

#include "cscam/cl/program.hpp"
#include "cscam/core/numparse.hpp"
#include "cscam/core/parallel.hpp"

#if defined(__unix__)
#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#endif

namespace cscam::cl {
namespace {

using Eigen::Vector3d;
using std::string_view;

/// Below this length a tool axis, a circle normal or an MSYS axis counts as zero.
constexpr double kMinVectorNorm = 1e-12;
/// An arc never advances more than this per generated point, so a coarse tolerance keeps the arc's shape.
constexpr double kMaxArcStepRad = kPi / 2;
/// Guards against a tiny tolerance on a huge arc exhausting memory.
constexpr int kMaxArcPoints = 1'000'000;
/// An end point at (nearly) the start angle means a full circle, as in APT.
constexpr double kFullCircleRad = 1e-12;
/// A CIRCLE/ whose start or end is farther than this from the circle is suspect (NX's printed rounding is ~1 um).
constexpr double kArcEndOffCircleMm = 0.01;
/// Beyond this the end points do not lie on the circle at all: the record is inconsistent, and drawing it anyway
/// would invent a path (rs274 likewise refuses an arc whose end is off its circle).
constexpr double kArcEndOffCircleErrorMm = 1.0;
/// No machine travels a circle larger than this; a larger radius is a corrupt record (and, expanded within the
/// tolerance, it would blow a few bytes up into a million points: fuzzing found it).
constexpr double kMaxArcRadiusMm = 1e5;
/// No machine travels a kilometre: a coordinate past it is a broken file (1e308 reached the planner's messages).
constexpr double kMaxCoordinateMm = 1e6;

bool is_space(char c) { return c == ' ' || c == '\t' || c == '\r' || c == '\f' || c == '\v'; }
char to_upper(char c) { return (c >= 'a' && c <= 'z') ? static_cast<char>(c - 'a' + 'A') : c; }
bool is_word_char(char c) {
  return (c >= 'A' && c <= 'Z') || (c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') || c == '_' || c == '-';
}

bool iequals(string_view a, string_view b) {
  if (a.size() != b.size()) return false;
  for (size_t i = 0; i < a.size(); ++i)
    if (to_upper(a[i]) != to_upper(b[i])) return false;
  return true;
}

string_view trim(string_view s) {
  size_t b = 0, e = s.size();
  while (b < e && is_space(s[b])) ++b;
  while (e > b && is_space(s[e - 1])) --e;
  return s.substr(b, e - b);
}

std::string upper_copy(string_view s) {
  std::string r(s);
  for (char& c : r) c = to_upper(c);
  return r;
}

// ---------------------------------------------------------------------------------------------------------------
// Numbers

enum class NumStatus { Ok, Malformed, NonFinite, OutOfRange };

/// Parses a whole field (no surrounding spaces) as a double; accepts a leading '+', "1.", "-.5", "1E-3".
NumStatus parse_number(string_view s, double& v) {
  const char* b = s.data();
  const char* e = b + s.size();
  if (b != e && *b == '+' && b + 1 != e && *(b + 1) != '-' && *(b + 1) != '+') ++b;
  if (b == e) return NumStatus::Malformed;
  const auto [ptr, ec] = decimal_from_chars(b, e, v);
  if (ec == std::errc::result_out_of_range) return NumStatus::OutOfRange;
  if (ec != std::errc() || ptr != e) return NumStatus::Malformed;
  return std::isfinite(v) ? NumStatus::Ok : NumStatus::NonFinite;
}

/// One comma-separated field of a statement.
struct Field {
  string_view text;   ///< trimmed
  size_t offset = 0;  ///< of the trimmed text in the statement
  NumStatus status = NumStatus::Malformed;
  double value = 0.0;
  [[nodiscard]] bool is_number() const { return status == NumStatus::Ok; }
  [[nodiscard]] bool is_word(string_view w) const { return iequals(text, w); }
};

// ---------------------------------------------------------------------------------------------------------------
// Statements: physical lines joined by `$` continuations, with `$$` comments split off.

struct Statement {
  struct Piece {
    size_t offset;  ///< text[offset] is at line:column
    int line;
    int column;
  };
  struct Comment {
    int line;
    int column;
    string_view text;
  };
  string_view text;  ///< the statement without comments and continuation marks
  int line = 0;      ///< its first physical line
  bool joined = false;
  std::vector<Piece> pieces;  ///< only for joined statements
  std::vector<Comment> comments;

  /// 1-based line and column of text[offset] in the original file.
  [[nodiscard]] std::pair<int, int> where(size_t offset) const {
    if (!joined) return {line, static_cast<int>(offset) + 1};
    const Piece* p = &pieces.front();
    for (const Piece& q : pieces)
      if (q.offset <= offset) p = &q;
    return {p->line, p->column + static_cast<int>(offset - p->offset)};
  }
};

/// Position of the `$$` that starts a comment in `line`, or npos.
size_t find_comment(string_view line) {
  const char* b = line.data();
  const char* e = b + line.size();
  const char* p = b;
  while (p < e) {
    p = static_cast<const char*>(std::memchr(p, '$', static_cast<size_t>(e - p)));
    if (!p) return string_view::npos;
    if (p + 1 < e && p[1] == '$') return static_cast<size_t>(p - b);
    p += 1;
  }
  return string_view::npos;
}

class Splitter {
 public:
  Splitter(string_view text, size_t pos, int first_line) : text_(text), pos_(pos), next_line_(first_line) {}

  /// The next non-blank statement; false at the end of the text. Views stay valid until the next call.
  bool next(Statement& st) {
    st.pieces.clear();
    st.comments.clear();
    st.joined = false;
    bool continuing = false;
    while (pos_ < text_.size()) {
      const char* nl = static_cast<const char*>(std::memchr(text_.data() + pos_, '\n', text_.size() - pos_));
      const size_t eol = nl ? static_cast<size_t>(nl - text_.data()) : text_.size();
      string_view line = text_.substr(pos_, eol - pos_);
      const int line_no = next_line_++;
      pos_ = eol + 1;
      const size_t cut = find_comment(line);
      string_view code = line;
      if (cut != string_view::npos) {
        st.comments.push_back({line_no, static_cast<int>(cut) + 1, trim(line.substr(cut + 2))});
        code = line.substr(0, cut);
      }
      size_t end = code.size();
      while (end > 0 && is_space(code[end - 1])) --end;
      const bool cont = end > 0 && code[end - 1] == '$';
      code = code.substr(0, cont ? end - 1 : end);
      if (!continuing) {
        if (!cont) {
          if (code.empty() && st.comments.empty()) continue;  // blank line
          st.text = code;
          st.line = line_no;
          return true;
        }
        continuing = true;
        st.joined = true;
        st.line = line_no;
        joined_.clear();
      }
      st.pieces.push_back({joined_.size(), line_no, 1});
      joined_.append(code);
      if (!cont) break;
    }
    if (!continuing) return false;
    st.text = joined_;
    return true;
  }

 private:
  string_view text_;
  size_t pos_;
  int next_line_;
  std::string joined_;
};

/// The record word of a statement and its arguments.
struct Head {
  string_view keyword;  ///< as written ("TOOL PATH" keeps its inner spaces)
  size_t keyword_offset = 0;
  char upper[24] = {};  ///< keyword upper-cased, truncated
  size_t upper_len = 0;
  bool listing_trailer = false;  ///< NX's "Tool Path Listing has N lines." trailer
  string_view args;              ///< after the '/' (or after the word when there is no '/')
  size_t args_offset = 0;

  [[nodiscard]] bool is(string_view kw) const { return kw == string_view(upper, upper_len); }
};

Head parse_head(string_view t) {
  Head h;
  size_t i = 0;
  while (i < t.size() && is_space(t[i])) ++i;
  h.keyword_offset = i;
  while (i < t.size() && is_word_char(t[i])) ++i;
  size_t kw_end = i;
  auto skip = [&] {
    while (i < t.size() && is_space(t[i])) ++i;
  };
  skip();
  // NX's "TOOL PATH/..." is the one record word with a space in it.
  const string_view first = t.substr(h.keyword_offset, kw_end - h.keyword_offset);
  if (iequals(first, "TOOL") && i < t.size() && t[i] != '/') {
    size_t j = i;
    while (j < t.size() && is_word_char(t[j])) ++j;
    if (iequals(t.substr(i, j - i), "PATH")) {
      kw_end = j;
      i = j;
      skip();
      size_t k = i;
      while (k < t.size() && is_word_char(t[k])) ++k;
      h.listing_trailer = iequals(t.substr(i, k - i), "LISTING");
    }
  }
  if (kw_end == h.keyword_offset) {  // no word: name the record by its first token
    kw_end = h.keyword_offset;
    while (kw_end < t.size() && !is_space(t[kw_end]) && t[kw_end] != '/' && kw_end - h.keyword_offset < 20) ++kw_end;
    i = kw_end;
    skip();
  }
  h.keyword = t.substr(h.keyword_offset, kw_end - h.keyword_offset);
  const size_t n = std::min(h.keyword.size(), sizeof(h.upper) - 1);
  for (size_t k = 0; k < n; ++k) h.upper[k] = to_upper(h.keyword[k]);
  h.upper_len = n;
  if (i < t.size() && t[i] == '/') ++i;
  h.args = t.substr(i);
  h.args_offset = i;
  return h;
}

std::optional<LengthUnit> unit_word(const Field& f) {
  if (f.is_word("MM") || f.is_word("MILLIMETERS") || f.is_word("MILLIMETRES") || f.is_word("METRIC"))
    return LengthUnit::Millimetre;
  if (f.is_word("INCHES") || f.is_word("INCH") || f.is_word("IN")) return LengthUnit::Inch;
  return std::nullopt;
}

void split_fields(string_view args, size_t base, std::vector<Field>& out) {
  out.clear();
  if (trim(args).empty()) return;
  size_t p = 0;
  while (true) {
    const size_t comma = args.find(',', p);
    const size_t end = comma == string_view::npos ? args.size() : comma;
    size_t b = p, e = end;
    while (b < e && is_space(args[b])) ++b;
    while (e > b && is_space(args[e - 1])) --e;
    Field f;
    f.text = args.substr(b, e - b);
    f.offset = base + b;
    if (!f.text.empty()) {
      const char c = f.text[0];
      if ((c >= '0' && c <= '9') || c == '.' || c == '-' || c == '+') f.status = parse_number(f.text, f.value);
    }
    out.push_back(f);
    if (comma == string_view::npos) break;
    p = comma + 1;
  }
}

/// Decides the file's unit before any position is converted: the first UNITS/, else the first FEDRAT/ that names
/// IPM or MMPM, else nothing. Only lines that start with U or F can hold either, so the rest are skipped cheaply.
std::optional<LengthUnit> scan_units(string_view text) {
  std::optional<LengthUnit> from_feed;
  Statement st;
  std::vector<Field> fields;
  size_t pos = 0;
  int line = 1;
  while (pos < text.size()) {
    const char* nl = static_cast<const char*>(std::memchr(text.data() + pos, '\n', text.size() - pos));
    const size_t eol = nl ? static_cast<size_t>(nl - text.data()) : text.size();
    size_t i = pos;
    while (i < eol && is_space(text[i])) ++i;
    const char c = i < eol ? to_upper(text[i]) : '\0';
    if (c == 'U' || (c == 'F' && !from_feed)) {
      Splitter sp(text, pos, line);
      if (sp.next(st)) {
        const Head h = parse_head(st.text);
        if (h.is("UNITS") || h.is("FEDRAT")) {
          split_fields(h.args, h.args_offset, fields);
          for (const Field& f : fields) {
            if (h.is("UNITS")) {
              if (auto u = unit_word(f)) return u;
            } else if (f.is_word("IPM") || f.is_word("IPR")) {
              from_feed = LengthUnit::Inch;
            } else if (f.is_word("MMPM") || f.is_word("MMPR")) {
              from_feed = LengthUnit::Millimetre;
            }
          }
        }
      }
    }
    pos = eol + 1;
    ++line;
  }
  return from_feed;
}

// ---------------------------------------------------------------------------------------------------------------
// The APT interpreter.

/// The numbers of a comma-separated list when every field is a plain finite number (AptReader::parse_numbers' path
/// without errors): their count, the first `cap` values and the offsets in s of the first cap + 1 fields; -1 for
/// anything parse_numbers would refuse (it then reads the list again to say why).
int scan_numbers(string_view s, double* v, size_t* offs, int cap) {
  int n = 0;
  size_t p = 0;
  const size_t size = s.size();
  if (trim(s).empty()) return 0;
  while (true) {
    while (p < size && is_space(s[p])) ++p;
    if (n <= cap) offs[n] = p;
    const char* b = s.data() + p;
    const char* e = s.data() + size;
    if (b != e && *b == '+' && b + 1 != e && (std::isdigit(static_cast<unsigned char>(b[1])) || b[1] == '.')) ++b;
    double x = 0.0;
    const auto [ptr, ec] = decimal_from_chars(b, e, x);
    if (ec != std::errc()) return -1;
    size_t q = static_cast<size_t>(ptr - s.data());
    while (q < size && is_space(s[q])) ++q;
    if ((q != size && s[q] != ',') || !std::isfinite(x)) return -1;
    if (n < cap) v[n] = x;
    ++n;
    if (q == size) return n;
    p = q + 1;
  }
}

/// The numbers of the GOTO/ lines ahead, read in parallel: converting them is most of reading a large CL file and
/// depends on nothing before them. The text is taken a window at a time (pieces of whole lines, in parallel), the
/// window after the one being read in the background meanwhile. A line is cut exactly as Splitter and parse_head
/// cut a one-line statement, so a statement's arguments are found here by their address and length in the text;
/// joined (continued) statements live elsewhere and are never found. Only lists scan_numbers accepts are kept:
/// the reader gets the same numbers as reading them itself, and reads anything else itself (errors included).
class GotoNumbers {
 public:
  static constexpr int kCap = 6;  ///< AptReader::motion's
  explicit GotoNumbers(string_view text) : text_(text) {}
  GotoNumbers(const GotoNumbers&) = delete;
  GotoNumbers& operator=(const GotoNumbers&) = delete;

  /// The numbers of `args` (parse_numbers with cap kCap) if they were read ahead; `args` come in text order.
  bool find(string_view args, double* v, size_t* offs, int& n) {
    const char* const a = args.data();
    if (a < text_.data() || a >= text_.data() + text_.size()) return false;
    while (a >= cur_.end) {
      if (!advance(a)) return false;
    }
    if (a < cur_.begin) return false;
    for (; piece_ < cur_.pieces.size(); ++piece_, entry_ = 0) {
      const auto& es = cur_.pieces[piece_];
      while (entry_ < es.size() && es[entry_].args < a) ++entry_;
      if (entry_ < es.size()) break;
    }
    if (piece_ >= cur_.pieces.size()) return false;
    const Entry& e = cur_.pieces[piece_][entry_];
    if (e.args != a || e.size != args.size()) return false;
    n = e.n;
    for (int k = 0; k < std::min(n, kCap); ++k) v[k] = e.v[k];
    for (int k = 0; k < std::min(n, kCap + 1); ++k) offs[k] = e.offs[k];
    return true;
  }

 private:
  struct Entry {
    const char* args;
    std::uint32_t size;
    int n;
    double v[kCap];
    std::uint32_t offs[kCap + 1];
  };
  struct Window {
    const char* begin = nullptr;
    const char* end = nullptr;
    std::vector<std::vector<Entry>> pieces;
  };
  static constexpr std::size_t kWindowBytes = std::size_t{1} << 20, kPieceBytes = std::size_t{1} << 16;

  /// Moves on to the window holding `a` (the one read ahead, else read now) and starts the one after it.
  bool advance(const char* a) {
    if (pending_) {
      job_.wait();
      pending_ = false;
    }
    if (next_.begin != nullptr && a >= next_.begin && a < next_.end)
      std::swap(cur_, next_);
    else
      read(cur_, line_start(a));
    piece_ = entry_ = 0;
    if (cur_.end < text_.data() + text_.size()) {
      pending_ = true;
      job_.run([this, b = cur_.end] { read(next_, b); });
    }
    return a >= cur_.begin && a < cur_.end;
  }

  [[nodiscard]] const char* line_start(const char* a) const {
    while (a > text_.data() && a[-1] != '\n') --a;
    return a;
  }
  /// Just past the end of the line holding a[-1] (or the text's end).
  [[nodiscard]] const char* line_end(const char* a) const {
    const char* const end = text_.data() + text_.size();
    if (a >= end) return end;
    const void* nl = std::memchr(a, '\n', static_cast<size_t>(end - a));
    return nl ? static_cast<const char*>(nl) + 1 : end;
  }

  void read(Window& w, const char* begin) const {
    const char* const text_end = text_.data() + text_.size();
    w.begin = begin;
    w.end = line_end(begin + std::min(kWindowBytes, static_cast<size_t>(text_end - begin)) - 1);
    std::vector<const char*> cuts{begin};
    while (cuts.back() < w.end)
      cuts.push_back(
          std::min(w.end, line_end(cuts.back() + std::min(kPieceBytes, static_cast<size_t>(w.end - cuts.back())) - 1)));
    w.pieces.resize(cuts.size() - 1);
    parallel_range(0, cuts.size() - 1, 1, [&](const tbb::blocked_range<std::size_t>& r) {
      for (std::size_t c = r.begin(); c != r.end(); ++c) {
        auto& out = w.pieces[c];
        out.clear();
        for (const char* p = cuts[c]; p < cuts[c + 1];) {
          const char* const nl = static_cast<const char*>(std::memchr(p, '\n', static_cast<size_t>(cuts[c + 1] - p)));
          const char* const eol = nl ? nl : cuts[c + 1];
          const string_view line(p, static_cast<size_t>(eol - p));
          p = eol + 1;
          // As Splitter::next: comment cut, trailing blanks, and not a continued line.
          const size_t cut = find_comment(line);
          string_view code = cut == string_view::npos ? line : line.substr(0, cut);
          size_t end = code.size();
          while (end > 0 && is_space(code[end - 1])) --end;
          if (end > 0 && code[end - 1] == '$') continue;
          code = code.substr(0, end);
          if (code.size() < 5) continue;
          const Head h = parse_head(code);
          if (!h.is("GOTO") || h.args.size() > UINT32_MAX) continue;  // offsets kept in 32 bits
          Entry e{};
          size_t offs[kCap + 1];
          e.n = scan_numbers(h.args, e.v, offs, kCap);
          if (e.n < 0) continue;
          e.args = h.args.data();
          e.size = static_cast<std::uint32_t>(h.args.size());
          for (int k = 0; k < std::min(e.n, kCap + 1); ++k) e.offs[k] = static_cast<std::uint32_t>(offs[k]);
          out.push_back(e);
        }
      }
    });
  }

  string_view text_;
  Window cur_, next_;
  std::size_t piece_ = 0, entry_ = 0;  ///< where find() stands in cur_
  bool pending_ = false;
  Background job_;  ///< declared last: joined before the windows go
};

class AptReader {
 public:
  AptReader(Program& prog, const ReadOptions& opt, LengthUnit unit, GotoNumbers* ahead = nullptr)
      : prog_(prog), opt_(opt), ahead_(ahead) {
    set_unit(unit);
  }

  /// Returns false after FINI.
  bool statement(const Statement& st);
  void finish();

 private:
  struct Circle {
    Vector3d centre_mm;
    Vector3d normal;
    double radius_mm;
    int line;
    int column;
  };
  /// A tool being defined by TLDATA/CUTTER/LOADTL/LOAD statements; it becomes current at the next motion.
  struct StagedTool {
    bool open = false;
    bool has_geometry = false;
    bool has_number = false;
    Tool tool;
    size_t event_index = 0;
  };

  [[noreturn]] void fail(const Statement& st, size_t offset, const std::string& msg) const {
    const auto [line, col] = st.where(offset);
    throw InputError(SourceLoc{prog_.file, line, col}, msg);
  }
  void warn(const Statement& st, size_t offset, std::string msg) {
    const auto [line, col] = st.where(offset);
    prog_.warnings.push_back({SourceLoc{prog_.file, line, col}, std::move(msg)});
  }
  void set_unit(LengthUnit u) { scale_ = u == LengthUnit::Inch ? kMmPerInch : 1.0; }

  int parse_numbers(const Statement& st, string_view args, size_t base, double* v, size_t* offs, int cap) const;
  double number(const Statement& st, const Field& f, const char* what) const;
  Vector3d unit_vector(const Statement& st, const double* v, size_t offset, const char* what) const;
  void push_event(Event::Kind kind, int line, std::string text = {});
  void motion(const Statement& st, const Head& h, MotionKind forced);
  void godlta(const Statement& st, const Head& h);
  void add_move(const Vector3d& tip_mm, const Vector3d& axis, int line, bool rapid);
  void emit_arc(const Circle& c, const Vector3d& end_mm, const Vector3d& end_axis, bool rapid);
  void stage_tool(int line);
  void commit_tool();
  void fedrat(const Statement& st, const Head& h);
  void spindl(const Statement& st, const Head& h);
  void tool_geometry(const Statement& st, const Head& h, bool tldata);
  void load_tool(const Statement& st, const Head& h);

  Program& prog_;
  const ReadOptions& opt_;
  GotoNumbers* ahead_ = nullptr;  ///< GOTO/ numbers read ahead (may be null)
  double scale_ = 1.0;            ///< file length unit -> mm
  std::vector<Field> fields_;
  Vector3d axis_ = Vector3d::UnitZ();
  std::optional<Vector3d> tlaxis_;  ///< the axis of the last TLAXIS/i,j,k (what MULTAX/OFF keeps)
  double feed_mm_per_min_ = 0.0;
  double feed_mm_per_rev_ = 0.0;  ///< the FEDRAT/ in force is per revolution (IPR/MMPR): recomputed at each SPINDL/
  double rpm_ = 0.0;
  bool clockwise_ = true;
  bool next_rapid_ = false;
  int current_tool_ = -1;
  std::string pending_tool_name_;
  StagedTool staged_;
  std::optional<Circle> circle_;
  bool arc_open_ = false;  ///< an arc recorded in prog_.arcs waits for its end GOTO
};

int AptReader::parse_numbers(const Statement& st, string_view s, size_t base, double* v, size_t* offs, int cap) const {
  if (ahead_ && cap == GotoNumbers::kCap) {
    int found = 0;
    if (ahead_->find(s, v, offs, found)) {
      for (int k = 0; k < std::min(found, cap + 1); ++k) offs[k] += base;
      return found;
    }
  }
  int n = 0;
  size_t p = 0;
  const size_t size = s.size();
  if (trim(s).empty()) return 0;
  while (true) {
    while (p < size && is_space(s[p])) ++p;
    if (n <= cap) offs[n] = base + p;
    // Fast path: from_chars straight on the text, then expect ',' or the end.
    const char* b = s.data() + p;
    const char* e = s.data() + size;
    if (b != e && *b == '+' && b + 1 != e && (std::isdigit(static_cast<unsigned char>(b[1])) || b[1] == '.')) ++b;
    double x = 0.0;
    const auto [ptr, ec] = decimal_from_chars(b, e, x);
    size_t q = static_cast<size_t>(ptr - s.data());
    bool ok = ec == std::errc();
    if (ok) {
      while (q < size && is_space(s[q])) ++q;
      ok = q == size || s[q] == ',';
    }
    if (!ok || !std::isfinite(x)) {
      size_t fe = s.find(',', p);
      if (fe == string_view::npos) fe = size;
      const string_view field = trim(s.substr(p, fe - p));
      if (ec == std::errc::result_out_of_range)
        fail(st, base + p, fmt::format("number out of range (expected a finite number, got '{}')", field));
      if (ok) fail(st, base + p, fmt::format("not a finite number (expected a finite number, got '{}')", field));
      fail(st, base + p, fmt::format("malformed number (expected a number, got '{}')", field));
    }
    if (n < cap) v[n] = x;
    ++n;
    if (q == size) return n;
    p = q + 1;
  }
}

double AptReader::number(const Statement& st, const Field& f, const char* what) const {
  switch (f.status) {
    case NumStatus::Ok:
      return f.value;
    case NumStatus::NonFinite:
      fail(st, f.offset, fmt::format("not a finite number (expected {}, got '{}')", what, f.text));
    case NumStatus::OutOfRange:
      fail(st, f.offset, fmt::format("number out of range (expected {}, got '{}')", what, f.text));
    case NumStatus::Malformed:
      break;
  }
  fail(st, f.offset, fmt::format("malformed number (expected {}, got '{}')", what, f.text));
}

Vector3d AptReader::unit_vector(const Statement& st, const double* v, size_t offset, const char* what) const {
  const Vector3d a(v[0], v[1], v[2]);
  const double norm = a.norm();
  if (!(norm > kMinVectorNorm) || !std::isfinite(norm))
    fail(st, offset, fmt::format("zero-length {} (expected a non-zero i,j,k, got {},{},{})", what, v[0], v[1], v[2]));
  return a / norm;
}

void AptReader::push_event(Event::Kind kind, int line, std::string text) {
  Event e;
  e.kind = kind;
  e.before_move = prog_.moves.size();
  e.line = line;
  e.text = std::move(text);
  if (kind == Event::Kind::SpindleOn) {
    e.spindle_rpm = rpm_;
    e.clockwise = clockwise_;
  }
  prog_.events.push_back(std::move(e));
}

void AptReader::stage_tool(int line) {
  if (staged_.open) return;
  staged_ = StagedTool{};
  staged_.open = true;
  staged_.tool.name = pending_tool_name_;
  staged_.event_index = prog_.events.size();
  push_event(Event::Kind::ToolChange, line);
}

// A tool statement only describes the tool; it takes effect (and merges with its neighbours, e.g. NX's TLDATA
// followed by LOAD/TOOL) at the next motion.
void AptReader::commit_tool() {
  if (!staged_.open) return;
  staged_.open = false;
  Tool t = staged_.tool;
  if (!staged_.has_number) t.number = current_tool_ >= 0 ? prog_.tools[static_cast<size_t>(current_tool_)].number : 0;
  if (!staged_.has_geometry) {  // a reload by number: reuse what is known about that tool
    for (auto it = prog_.tools.rbegin(); it != prog_.tools.rend(); ++it)
      if (it->number == t.number) {
        if (t.name.empty()) t.name = it->name;
        t.diameter_mm = it->diameter_mm;
        t.corner_radius_mm = it->corner_radius_mm;
        t.length_mm = it->length_mm;
        break;
      }
  }
  int index = -1;
  for (size_t i = 0; i < prog_.tools.size(); ++i) {
    const Tool& o = prog_.tools[i];
    if (o.number == t.number && o.name == t.name && o.diameter_mm == t.diameter_mm &&
        o.corner_radius_mm == t.corner_radius_mm && o.length_mm == t.length_mm) {
      index = static_cast<int>(i);
      break;
    }
  }
  pending_tool_name_.clear();  // a TOOL PATH/ name belongs to the tool defined right after it
  if (index < 0) {
    index = static_cast<int>(prog_.tools.size());
    prog_.tools.push_back(t);
  }
  if (index == current_tool_) {  // NX repeats the tool for every operation: no change, no event
    prog_.events.erase(prog_.events.begin() + static_cast<std::ptrdiff_t>(staged_.event_index));
    return;
  }
  current_tool_ = index;
  Event& e = prog_.events[staged_.event_index];
  e.tool_index = index;
  e.text = t.name;
}

void AptReader::add_move(const Vector3d& tip_mm, const Vector3d& axis, int line, bool rapid) {
  Move m;
  m.tip_in_part_mm = tip_mm;
  m.axis_in_part = axis;
  m.kind = rapid ? MotionKind::Rapid : MotionKind::Feed;
  m.feed_mm_per_min = rapid ? 0.0 : feed_mm_per_min_;
  m.line = line;
  m.tool_index = current_tool_;
  prog_.moves.push_back(m);
}

void AptReader::motion(const Statement& st, const Head& h, MotionKind forced) {
  double v[6];
  size_t offs[7];
  const int n = parse_numbers(st, h.args, h.args_offset, v, offs, 6);
  if (n != 3 && n != 6) {
    // Point at the field that breaks the pattern: the 4th of an incomplete axis, the 7th of too many, else the end.
    const size_t at = n > 6 ? offs[6] : (n > 3 ? offs[3] : h.args_offset + h.args.size());
    fail(st, at,
         fmt::format("wrong number of values on {}/ (expected 3 (x,y,z) or 6 (x,y,z,i,j,k), got {})", h.keyword, n));
  }
  if (n == 6) {
    axis_ = unit_vector(st, v + 3, offs[3], "tool axis");
    prog_.multax = true;
  }
  commit_tool();
  const Vector3d tip(v[0] * scale_, v[1] * scale_, v[2] * scale_);
  for (int k = 0; k < 3; ++k)
    if (std::abs(tip[k]) > kMaxCoordinateMm)
      fail(st, offs[k],
           fmt::format("coordinate {} mm is beyond any machine (at most {:g} mm)", tip[k], kMaxCoordinateMm));
  const bool rapid = forced == MotionKind::Rapid || next_rapid_;
  if (circle_) {
    if (prog_.moves.empty())
      prog_.warnings.push_back({SourceLoc{prog_.file, circle_->line, circle_->column},
                                "CIRCLE/ without a start point: moving straight to its end"});
    else
      emit_arc(*circle_, tip, axis_, rapid);
    circle_.reset();
  }
  add_move(tip, axis_, st.line, rapid);
  if (arc_open_) {
    prog_.arcs.back().end_move = prog_.moves.size() - 1;
    prog_.moves.back().arc_index = static_cast<int>(prog_.arcs.size()) - 1;
    arc_open_ = false;
  }
  next_rapid_ = false;
}

void AptReader::godlta(const Statement& st, const Head& h) {
  double v[3];
  size_t offs[4];
  const int n = parse_numbers(st, h.args, h.args_offset, v, offs, 3);
  if (n != 1 && n != 3)
    fail(st, n > 3 ? offs[3] : h.args_offset + h.args.size(),
         fmt::format("wrong number of values on GODLTA/ (expected 1 (along the axis) or 3 (dx,dy,dz), got {})", n));
  commit_tool();
  const Vector3d from = prog_.moves.empty() ? Vector3d::Zero() : prog_.moves.back().tip_in_part_mm;
  const Vector3d delta =
      n == 1 ? Vector3d(axis_ * v[0] * scale_) : Vector3d(v[0] * scale_, v[1] * scale_, v[2] * scale_);
  add_move(from + delta, axis_, st.line, next_rapid_);
  next_rapid_ = false;
}

// NX's CIRCLE/ runs CLOCKWISE about its (i,j,k): checked against NX's own post output of zigzag_smoothed.cls, whose
// arcs with k=-1 come out as G03 and those with k=+1 as G02 (both short corner arcs, not their 270-degree
// complements).
void AptReader::emit_arc(const Circle& c, const Vector3d& end_mm, const Vector3d& end_axis, bool rapid) {
  const Vector3d start = prog_.moves.back().tip_in_part_mm;
  const Vector3d start_axis = prog_.moves.back().axis_in_part;
  const Vector3d& n = c.normal;
  const Vector3d u = start - c.centre_mm, w = end_mm - c.centre_mm;
  const double h0 = u.dot(n), h1 = w.dot(n);
  const Vector3d up = u - h0 * n, wp = w - h1 * n;
  const double r = c.radius_mm;
  // (A start or end at the centre is r off the circle.)
  const double off_circle_mm = std::max(std::abs(up.norm() - r), std::abs(wp.norm() - r));
  if (off_circle_mm > kArcEndOffCircleErrorMm)
    throw InputError(SourceLoc{prog_.file, c.line, c.column},
                     fmt::format("CIRCLE/ start or end lies {:.4f} mm off the circle of radius {} mm (at most {} mm): "
                                 "the arc does not join its end points",
                                 off_circle_mm, r, kArcEndOffCircleErrorMm));
  if (up.norm() <= kMinVectorNorm || wp.norm() <= kMinVectorNorm) {
    prog_.warnings.push_back({SourceLoc{prog_.file, c.line, c.column},
                              "CIRCLE/ with its start or end at the centre: moving straight to its end"});
    return;
  }
  if (off_circle_mm > kArcEndOffCircleMm)
    prog_.warnings.push_back({SourceLoc{prog_.file, c.line, c.column},
                              fmt::format("CIRCLE/ start or end lies {:.4f} mm off the circle", off_circle_mm)});
  const Vector3d e1 = up.normalized();
  const Vector3d e2 = n.cross(e1);  // the counter-clockwise direction at the start
  const double phi = std::atan2(wp.dot(e2), wp.dot(e1));
  double sweep = -phi;  // clockwise angle from start to end
  if (std::abs(phi) < kFullCircleRad) sweep = 2 * kPi;
  if (sweep <= 0) sweep += 2 * kPi;
  const double tol = opt_.arc_tolerance_mm;
  // Sagitta of a step dtheta: r (1 - cos(dtheta/2)) <= tol.
  const double step = tol >= r ? kMaxArcStepRad : std::min(kMaxArcStepRad, 2.0 * std::acos(1.0 - tol / r));
  const int segments = static_cast<int>(std::min<double>(kMaxArcPoints, std::max(1.0, std::ceil(sweep / step))));
  const bool same_axis = (start_axis - end_axis).squaredNorm() < 1e-24;
  // The arc's identity (the GOTO that follows ends it): a post may write it as one G2/G3.
  prog_.arcs.push_back({c.centre_mm, -n, r, sweep, c.line, 0});
  arc_open_ = true;
  const int arc_index = static_cast<int>(prog_.arcs.size()) - 1;
  for (int k = 1; k < segments; ++k) {
    const double t = static_cast<double>(k) / segments;
    const double ang = -sweep * t;
    const Vector3d p = c.centre_mm + (h0 + (h1 - h0) * t) * n + r * (std::cos(ang) * e1 + std::sin(ang) * e2);
    Vector3d a = start_axis;
    if (!same_axis) {
      a = (1 - t) * start_axis + t * end_axis;
      a = a.norm() > kMinVectorNorm ? Vector3d(a.normalized()) : end_axis;
    }
    add_move(p, a, c.line, rapid);
    prog_.moves.back().from_arc = true;
    prog_.moves.back().arc_index = arc_index;
  }
}

void AptReader::fedrat(const Statement& st, const Head& h) {
  split_fields(h.args, h.args_offset, fields_);
  std::optional<double> value;
  double unit_scale = scale_;  // a bare feed is in the file's length unit per minute
  bool per_rev = false;
  for (const Field& f : fields_) {
    if (f.is_number() && !value) {
      value = f.value;
      if (!(*value > 0)) fail(st, f.offset, fmt::format("feed must be positive (got '{}')", f.text));
    } else if (f.is_word("IPM")) {
      unit_scale = kMmPerInch;
    } else if (f.is_word("MMPM")) {
      unit_scale = 1.0;
    } else if (f.is_word("IPR")) {
      unit_scale = kMmPerInch;
      per_rev = true;
    } else if (f.is_word("MMPR")) {
      unit_scale = 1.0;
      per_rev = true;
    } else if (!f.is_number()) {
      if (f.status != NumStatus::Malformed || (!f.text.empty() && !std::isalpha(static_cast<unsigned char>(f.text[0]))))
        number(st, f, "a feed");  // throws: a broken number, not a word
      warn(st, f.offset, fmt::format("FEDRAT/ modifier '{}' ignored", f.text));
    }
  }
  if (!value)
    fail(st, h.args_offset, fmt::format("FEDRAT/ without a feed (expected a number, got '{}')", trim(h.args)));
  double feed = *value * unit_scale;
  if (per_rev) {
    if (rpm_ <= 0)
      fail(st, h.keyword_offset,
           "feed per revolution (IPR/MMPR) before any spindle speed: it cannot be converted to a feed per minute "
           "(expected SPINDL/ with an RPM before it)");
    feed_mm_per_rev_ = feed;
    feed *= rpm_;
  } else {
    feed_mm_per_rev_ = 0.0;
  }
  feed_mm_per_min_ = feed;
}

void AptReader::spindl(const Statement& st, const Head& h) {
  split_fields(h.args, h.args_offset, fields_);
  // A surface speed (SFM/SMM) is not a spindle speed: keep the last rpm rather than misread it.
  const bool surface_speed =
      std::any_of(fields_.begin(), fields_.end(), [](const Field& f) { return f.is_word("SFM") || f.is_word("SMM"); });
  if (surface_speed)
    warn(st, h.keyword_offset, "SPINDL/ surface speed (SFM/SMM) not supported: spindle speed unchanged");
  bool off = false;
  for (const Field& f : fields_) {
    if (f.is_number()) {
      if (f.value < 0) fail(st, f.offset, fmt::format("negative spindle speed (expected rpm >= 0, got '{}')", f.text));
      if (!surface_speed) rpm_ = f.value;
    } else if (f.is_word("CLW")) {
      clockwise_ = true;
    } else if (f.is_word("CCLW")) {
      clockwise_ = false;
    } else if (f.is_word("OFF")) {
      off = true;
    } else if (f.is_word("ON") || f.is_word("RPM") || f.is_word("SFM") || f.is_word("SMM")) {
    } else if (f.status != NumStatus::Malformed ||
               (!f.text.empty() && !std::isalpha(static_cast<unsigned char>(f.text[0])))) {
      number(st, f, "a spindle speed");  // throws
    } else {
      warn(st, f.offset, fmt::format("SPINDL/ modifier '{}' ignored", f.text));
    }
  }
  // A feed per revolution follows the spindle: the same chip load at the new speed.
  if (feed_mm_per_rev_ > 0 && rpm_ > 0) feed_mm_per_min_ = feed_mm_per_rev_ * rpm_;
  push_event(off ? Event::Kind::SpindleOff : Event::Kind::SpindleOn, st.line);
}

// CUTTER/d[,r[,e,f,a,b,h]] (APT 7-parameter form: h is the height) and NX TLDATA/MILL,d,r,length,...
void AptReader::tool_geometry(const Statement& st, const Head& h, bool tldata) {
  split_fields(h.args, h.args_offset, fields_);
  size_t first = 0;
  bool drill = false;
  if (tldata && !fields_.empty() && !fields_[0].is_number() && fields_[0].status == NumStatus::Malformed &&
      !fields_[0].text.empty() && std::isalpha(static_cast<unsigned char>(fields_[0].text[0]))) {
    first = 1;  // the tool type: MILL, DRILL, ...
    // NX: TLDATA/MILL,d,r,length,... and TLDATA/DRILL,d,point angle,length,.... Other types are read as a mill's
    // first three numbers, with a warning: their other dimensions (a T-slot cutter's neck, a barrel's profile) are
    // not modelled.
    drill = fields_[0].is_word("DRILL");
    if (!drill && !fields_[0].is_word("MILL"))
      warn(st, fields_[0].offset,
           fmt::format("TLDATA/{} read as TLDATA/MILL,diameter,corner radius,length: the tool's other dimensions "
                       "are not modelled (collision checks use a cylinder with that corner)",
                       fields_[0].text));
  }
  if (fields_.size() <= first)
    fail(st, h.args_offset + h.args.size(), fmt::format("{}/ without a diameter (expected a number)", h.keyword));
  auto value = [&](size_t i) { return i < fields_.size() ? number(st, fields_[i], "a tool dimension") * scale_ : 0.0; };
  const double d = value(first);
  if (drill && fields_.size() > first + 1) {
    const double point_deg = number(st, fields_[first + 1], "a drill point angle");
    if (!(point_deg > 0 && point_deg <= 180))
      fail(st, fields_[first + 1].offset,
           fmt::format("drill point angle out of range (expected 0 < angle <= 180 deg, got '{}')",
                       fields_[first + 1].text));
  }
  const double r = drill ? 0.0 : value(first + 1);  // a drill's point is bounded by its flat end
  double len = 0.0;
  if (tldata) {
    len = value(first + 2);
  } else if (fields_.size() >= first + 7) {
    len = value(first + 6);
  }
  if (d <= 0)
    fail(st, fields_[first].offset, fmt::format("tool diameter must be positive (got '{}')", fields_[first].text));
  if (r < 0 || r > 0.5 * d + 1e-9)
    fail(st, fields_[first + 1].offset,
         fmt::format("corner radius out of range (expected 0 <= r <= d/2, got '{}')", fields_[first + 1].text));
  stage_tool(st.line);
  staged_.has_geometry = true;
  staged_.tool.diameter_mm = d;
  staged_.tool.corner_radius_mm = std::min(r, 0.5 * d);
  staged_.tool.length_mm = len;
}

// LOADTL/n[,...] and NX's LOAD/TOOL,n[,...].
void AptReader::load_tool(const Statement& st, const Head& h) {
  split_fields(h.args, h.args_offset, fields_);
  size_t i = 0;
  if (h.is("LOAD")) {
    if (fields_.empty() || !fields_[0].is_word("TOOL")) {
      warn(st, h.keyword_offset, fmt::format("unknown record '{}/{}' ignored", h.keyword, trim(h.args)));
      return;
    }
    i = 1;
  }
  if (i >= fields_.size())
    fail(st, h.args_offset + h.args.size(), fmt::format("{}/ without a tool number (expected a number)", h.keyword));
  const double num = number(st, fields_[i], "a tool number");
  if (num < 0 || num != std::floor(num) || num > 1e9)
    fail(st, fields_[i].offset, fmt::format("bad tool number (expected an integer >= 0, got '{}')", fields_[i].text));
  stage_tool(st.line);
  staged_.has_number = true;
  staged_.tool.number = static_cast<int>(num);
  // LOAD/TOOL,n,ADJUST,h: the length offset register h.
  for (size_t k = i + 1; k + 1 < fields_.size(); ++k)
    if (fields_[k].is_word("ADJUST")) {
      const double reg = number(st, fields_[k + 1], "a length offset register");
      if (reg < 0 || reg != std::floor(reg) || reg > 1e6)
        fail(st, fields_[k + 1].offset,
             fmt::format("bad ADJUST register (expected an integer >= 0, got '{}')", fields_[k + 1].text));
      staged_.tool.length_register = static_cast<int>(reg);
    }
}

bool AptReader::statement(const Statement& st) {
  const Head h = parse_head(st.text);
  if (h.is("GOTO")) {
    motion(st, h, MotionKind::Feed);
  } else if (h.keyword.empty()) {
    // a comment-only line
  } else if (h.is("RAPID")) {
    next_rapid_ = true;
  } else if (h.is("FEDRAT")) {
    fedrat(st, h);
  } else if (h.is("PAINT") || h.is("END-OF-PATH") || h.is("END") || h.is("TPRINT") || h.is("MACHIN") ||
             h.is("CLPRNT") || h.is("DISPLY") || h.is("SEQNO") || h.listing_trailer) {
    // known, nothing to do for a post
  } else if (h.is("CIRCLE")) {
    double v[7];
    size_t offs[8];
    const int n = parse_numbers(st, h.args, h.args_offset, v, offs, 7);
    if (n < 7)
      fail(st, h.args_offset + h.args.size(),
           fmt::format("too few values on CIRCLE/ (expected xc,yc,zc,i,j,k,r[,...], got {})", n));
    if (!(v[6] > 0)) fail(st, offs[6], fmt::format("circle radius must be positive (got {})", v[6]));
    if (v[6] * scale_ > kMaxArcRadiusMm)
      fail(st, offs[6],
           fmt::format("circle radius {} mm is beyond any machine (at most {} mm)", v[6] * scale_, kMaxArcRadiusMm));
    const auto [line, col] = st.where(h.keyword_offset);
    if (circle_)  // the first would be dropped: which arc was meant is not known
      fail(st, h.keyword_offset,
           fmt::format("CIRCLE/ follows the CIRCLE/ of line {} without the GOTO/ that ends that arc", circle_->line));
    circle_ = Circle{Vector3d(v[0], v[1], v[2]) * scale_, unit_vector(st, v + 3, offs[3], "circle axis"), v[6] * scale_,
                     line, col};
  } else if (h.is("FROM")) {
    motion(st, h, MotionKind::Rapid);
  } else if (h.is("GODLTA")) {
    godlta(st, h);
  } else if (h.is("TOOL PATH")) {
    split_fields(h.args, h.args_offset, fields_);
    const std::string op = fields_.empty() ? std::string() : std::string(fields_[0].text);
    for (size_t i = 1; i + 1 < fields_.size(); ++i)
      if (fields_[i].is_word("TOOL")) pending_tool_name_ = std::string(fields_[i + 1].text);
    if (staged_.open && staged_.tool.name.empty()) staged_.tool.name = pending_tool_name_;
    if (prog_.part_name.empty()) prog_.part_name = op;
    push_event(Event::Kind::OperationStart, st.line, op);
  } else if (h.is("TLDATA")) {
    tool_geometry(st, h, true);
  } else if (h.is("CUTTER")) {
    tool_geometry(st, h, false);
  } else if (h.is("LOADTL") || h.is("LOAD")) {
    load_tool(st, h);
  } else if (h.is("MSYS")) {
    double v[9];
    size_t offs[10];
    const int n = parse_numbers(st, h.args, h.args_offset, v, offs, 9);
    if (n != 9)
      fail(st, n > 9 ? offs[9] : h.args_offset + h.args.size(),
           fmt::format("wrong number of values on MSYS/ (expected 9 (origin, x axis, y axis), got {})", n));
    const Vector3d x = unit_vector(st, v + 3, offs[3], "MSYS x axis");
    const Vector3d y = unit_vector(st, v + 6, offs[6], "MSYS y axis");
    Eigen::Matrix<double, 3, 4> m;
    m.col(0) = Vector3d(v[0], v[1], v[2]) * scale_;
    m.col(1) = x;
    m.col(2) = y;
    m.col(3) = x.cross(y);
    prog_.msys = m;
  } else if (h.is("UNITS")) {
    split_fields(h.args, h.args_offset, fields_);
    const std::optional<LengthUnit> u = fields_.empty() ? std::nullopt : unit_word(fields_[0]);
    if (!u)
      fail(st, fields_.empty() ? h.args_offset : fields_[0].offset,
           fmt::format("unknown unit (expected MM or INCHES, got '{}')", trim(h.args)));
    if (!opt_.units) set_unit(*u);
  } else if (h.is("MULTAX")) {
    split_fields(h.args, h.args_offset, fields_);
    if (fields_.empty() || !fields_[0].is_word("OFF")) {
      prog_.multax = true;
    } else {
      // 3-axis mode: the GOTOs give no axis; it is the fixed one of the last TLAXIS/ (a 3+2 stretch), else +Z.
      axis_ = tlaxis_.value_or(Vector3d::UnitZ());
    }
  } else if (h.is("SPINDL")) {
    spindl(st, h);
  } else if (h.is("COOLNT")) {
    split_fields(h.args, h.args_offset, fields_);
    const std::string mode = fields_.empty() ? std::string("ON") : upper_copy(fields_[0].text);
    push_event(mode == "OFF" ? Event::Kind::CoolantOff : Event::Kind::CoolantOn, st.line, mode);
  } else if (h.is("PARTNO")) {
    prog_.part_name = std::string(trim(h.args));
  } else if (h.is("PPRINT")) {
    push_event(Event::Kind::Comment, st.line, std::string(trim(h.args)));
  } else if (h.is("STOP") || h.is("OPSTOP")) {
    push_event(Event::Kind::Stop, st.line, std::string(h.upper));
  } else if (h.is("DELAY")) {
    split_fields(h.args, h.args_offset, fields_);
    if (fields_.size() != 1)
      fail(st, h.args_offset, "DELAY/ expects one value, the dwell in seconds (DELAY/REV is not supported)");
    const double secs = number(st, fields_[0], "a dwell time in seconds");
    if (!(secs >= 0)) fail(st, fields_[0].offset, "negative DELAY/");
    push_event(Event::Kind::Dwell, st.line);
    prog_.events.back().seconds = secs;
  } else if (h.is("INSERT")) {
    push_event(Event::Kind::Insert, st.line, std::string(trim(h.args)));
  } else if (h.is("TLAXIS")) {
    // TLAXIS/i,j,k: the tool axis of the GOTOs that give none (3-axis and 3+2 stretches).
    split_fields(h.args, h.args_offset, fields_);
    const bool numbers =
        std::all_of(fields_.begin(), fields_.end(), [](const auto& f) { return f.status != NumStatus::Malformed; });
    double v[4];
    size_t offs[5];
    const int n = numbers ? parse_numbers(st, h.args, h.args_offset, v, offs, 4) : 0;
    if (n != 3)
      fail(st, h.args_offset,
           "TLAXIS/ is supported as TLAXIS/i,j,k only (a fixed tool axis); the other forms (NORMAL, ATANGL, ...) "
           "define the axis from geometry cscam does not have: output GOTO/x,y,z,i,j,k from the CAM system");
    axis_ = unit_vector(st, v, offs[0], "TLAXIS tool axis");
    tlaxis_ = axis_;
  } else if (h.is("CYCLE")) {
    // The GOTOs under a canned cycle are hole positions, not the tool path: posting them as moves would not drill.
    split_fields(h.args, h.args_offset, fields_);
    if (fields_.empty() || !fields_[0].is_word("OFF"))
      fail(st, h.keyword_offset,
           fmt::format("CYCLE/{}: canned cycles are not supported (the GOTOs that follow are hole positions, not "
                       "the tool path, and posting them as moves would not drill): output the cycle as explicit "
                       "motion from the CAM system",
                       trim(h.args)));
  } else if (h.is("TRACUT") || h.is("COPY") || h.is("INDEX") || h.is("ROTABL") || h.is("ROTATE") || h.is("ROTHED") ||
             h.is("GOHOME")) {
    // They move or repeat the motion around them; ignored, the program would cut somewhere else.
    split_fields(h.args, h.args_offset, fields_);
    if (!(h.is("TRACUT") && !fields_.empty() && fields_[0].is_word("NOMORE")))
      fail(st, h.keyword_offset,
           fmt::format("{}/ is not supported: it transforms, repeats or adds motion that the CL does not list, so "
                       "the program would not follow the part; output the motion itself from the CAM system",
                       h.keyword));
  } else if (h.is("RETRCT")) {
    // A retract to the clearance plane that the CL does not list (its plane is a CLEARP/CLRSRF the post would have to
    // interpret): ignored, the next move would run from the cut straight through the part.
    fail(st, h.keyword_offset,
         "RETRCT is not supported: it adds a retract the CL does not list (to a clearance plane set elsewhere), and "
         "without it the next move would leave the cut straight through the part; output the retract as GOTOs from the "
         "CAM system");
  } else if (h.is("MODE") || h.is("SET")) {
    // SET/MODE,INCR (MODE/INCR): the GOTOs that follow are increments, which cscam would read as positions.
    split_fields(h.args, h.args_offset, fields_);
    bool incremental = false;
    for (const auto& f : fields_) incremental = incremental || f.is_word("INCR");
    if (incremental)
      fail(st, h.keyword_offset,
           fmt::format("{}/{}: incremental CL coordinates are not supported (the GOTOs would be read as positions): "
                       "output absolute coordinates from the CAM system",
                       h.keyword, trim(h.args)));
    warn(st, h.keyword_offset, fmt::format("unknown record '{}/{}' ignored", h.keyword, trim(h.args)));
  } else if (h.is("ORIGIN")) {
    // ORIGIN/x,y,z moves the program's zero: the CL would be cut somewhere else, by a shift posts apply differently.
    split_fields(h.args, h.args_offset, fields_);
    double v[3];
    size_t offs[4];
    const bool numbers =
        std::all_of(fields_.begin(), fields_.end(), [](const auto& f) { return f.status != NumStatus::Malformed; });
    const int n = numbers ? parse_numbers(st, h.args, h.args_offset, v, offs, 3) : 0;
    if (!(n == 3 && v[0] == 0.0 && v[1] == 0.0 && v[2] == 0.0))
      fail(
          st, h.keyword_offset,
          fmt::format("ORIGIN/{} is not supported: it shifts the program's zero, which posts apply in different ways, "
                      "so the part would be cut somewhere else; output the CL in the part's coordinates (MSYS) and set "
                      "the work offset on the machine (post.work_offset)",
                      trim(h.args)));
  } else if (h.is("CUTCOM")) {
    // The CL is the tool path itself: the post writes it uncompensated (G40) and says so.
    warn(st, h.keyword_offset,
         "CUTCOM ignored: the CL points are the tool tip path, written without control-side "
         "cutter compensation (G40)");
  } else if (h.is("FINI")) {
    return false;
  } else {
    warn(st, h.keyword_offset, fmt::format("unknown record '{}' ignored", h.keyword));
  }
  for (const auto& c : st.comments) {
    Event e;
    e.kind = Event::Kind::Comment;
    e.before_move = prog_.moves.size();
    e.line = c.line;
    e.text = std::string(c.text);
    prog_.events.push_back(std::move(e));
  }
  return true;
}

void AptReader::finish() {
  if (circle_)
    prog_.warnings.push_back(
        {SourceLoc{prog_.file, circle_->line, circle_->column}, "CIRCLE/ without a following GOTO/ ignored"});
  commit_tool();
}

// ---------------------------------------------------------------------------------------------------------------
// CSV: x,y,z,i,j,k[,feed] per line, '#' comments, an optional header row.

/// True when every comma-separated field of `line` is a number (and there are at least 3).
bool numeric_row(string_view line) {
  if (line.find('/') != string_view::npos) return false;
  int n = 0;
  size_t p = 0;
  while (true) {
    const size_t comma = line.find(',', p);
    double v;
    if (parse_number(trim(line.substr(p, comma == string_view::npos ? string_view::npos : comma - p)), v) ==
        NumStatus::Malformed)
      return false;
    ++n;
    if (comma == string_view::npos) break;
    p = comma + 1;
  }
  return n >= 3;
}

/// A row of identifiers such as "x,y,z,i,j,k,feed".
bool header_row(string_view line) {
  if (line.find('/') != string_view::npos || line.find(',') == string_view::npos) return false;
  size_t p = 0;
  while (true) {
    const size_t comma = line.find(',', p);
    const string_view f = trim(line.substr(p, comma == string_view::npos ? string_view::npos : comma - p));
    if (f.empty() || !(std::isalpha(static_cast<unsigned char>(f[0])) || f[0] == '_')) return false;
    if (comma == string_view::npos) return true;
    p = comma + 1;
  }
}

/// The first two lines that are neither blank nor comments.
std::pair<string_view, string_view> first_content_lines(string_view text) {
  string_view found[2];
  int k = 0;
  size_t pos = 0;
  while (pos < text.size() && k < 2) {
    size_t eol = text.find('\n', pos);
    if (eol == string_view::npos) eol = text.size();
    const string_view line = trim(text.substr(pos, eol - pos));
    pos = eol + 1;
    if (line.empty() || line[0] == '#' || line.substr(0, 2) == "$$") continue;
    found[k++] = line;
  }
  return {found[0], found[1]};
}

bool looks_like_csv(string_view text) {
  const auto [first, second] = first_content_lines(text);
  if (numeric_row(first)) return true;
  return header_row(first) && numeric_row(second);
}

[[noreturn]] void csv_fail(const Program& prog, int line, size_t col0, const std::string& msg) {
  throw InputError(SourceLoc{prog.file, line, static_cast<int>(col0) + 1}, msg);
}

void read_csv(string_view text, Program& prog, const ReadOptions& opt) {
  const double scale = opt.units == LengthUnit::Inch ? kMmPerInch : 1.0;
  prog.source_units = opt.units.value_or(LengthUnit::Millimetre);
  prog.multax = true;
  double feed = 0.0;
  bool seen_data = false;
  size_t pos = 0;
  int line_no = 0;
  while (pos < text.size()) {
    const char* nl = static_cast<const char*>(std::memchr(text.data() + pos, '\n', text.size() - pos));
    const size_t eol = nl ? static_cast<size_t>(nl - text.data()) : text.size();
    const string_view line = text.substr(pos, eol - pos);
    pos = eol + 1;
    ++line_no;
    size_t b = 0;
    while (b < line.size() && is_space(line[b])) ++b;
    if (b == line.size()) continue;
    if (line[b] == '#') {
      Event e;
      e.kind = Event::Kind::Comment;
      e.before_move = prog.moves.size();
      e.line = line_no;
      e.text = std::string(trim(line.substr(b + 1)));
      prog.events.push_back(std::move(e));
      continue;
    }
    if (!seen_data && header_row(line)) {
      seen_data = true;
      continue;
    }
    seen_data = true;
    double v[7];
    size_t offs[8];
    int n = 0;
    size_t p = 0;
    while (true) {
      const size_t comma = line.find(',', p);
      const size_t end = comma == string_view::npos ? line.size() : comma;
      size_t fb = p, fe = end;
      while (fb < fe && is_space(line[fb])) ++fb;
      while (fe > fb && is_space(line[fe - 1])) --fe;
      if (n <= 7) offs[n] = fb;
      if (n < 7) {
        const string_view f = line.substr(fb, fe - fb);
        const NumStatus status = parse_number(f, v[n]);
        if (status == NumStatus::NonFinite)
          csv_fail(prog, line_no, fb, fmt::format("not a finite number (expected a finite number, got '{}')", f));
        if (status == NumStatus::OutOfRange)
          csv_fail(prog, line_no, fb, fmt::format("number out of range (expected a finite number, got '{}')", f));
        if (status == NumStatus::Malformed)
          csv_fail(prog, line_no, fb, fmt::format("malformed number (expected a number, got '{}')", f));
      }
      ++n;
      if (comma == string_view::npos) break;
      p = comma + 1;
    }
    if (n != 6 && n != 7)
      csv_fail(prog, line_no, n > 7 ? offs[7] : (n > 3 ? offs[3] : line.size()),
               fmt::format("wrong number of values (expected 6 (x,y,z,i,j,k) or 7 (x,y,z,i,j,k,feed), got {})", n));
    const Vector3d a(v[3], v[4], v[5]);
    if (!(a.norm() > kMinVectorNorm))
      csv_fail(prog, line_no, offs[3],
               fmt::format("zero-length tool axis (expected a non-zero i,j,k, got {},{},{})", v[3], v[4], v[5]));
    if (n == 7) {
      if (v[6] < 0) csv_fail(prog, line_no, offs[6], fmt::format("negative feed (expected a feed >= 0, got {})", v[6]));
      feed = v[6] * scale;
    }
    for (int k = 0; k < 3; ++k)
      if (std::abs(v[k] * scale) > kMaxCoordinateMm)
        csv_fail(
            prog, line_no, offs[k],
            fmt::format("coordinate {} mm is beyond any machine (at most {:g} mm)", v[k] * scale, kMaxCoordinateMm));
    Move m;
    m.tip_in_part_mm = Vector3d(v[0], v[1], v[2]) * scale;
    m.axis_in_part = a.normalized();
    m.feed_mm_per_min = feed;
    m.line = line_no;
    prog.moves.push_back(m);
  }
}

/// First-touch page faults are expensive (about 8 us each on a virtual machine, 80 ms per million moves): ask for
/// transparent huge pages on a large buffer, which cuts the faults 512-fold. Advice only: failure is harmless.
void advise_huge_pages([[maybe_unused]] const void* data, [[maybe_unused]] size_t bytes) {
#if defined(__linux__) && defined(MADV_HUGEPAGE)
  constexpr uintptr_t kHuge = uintptr_t{1} << 21;
  const auto begin = (reinterpret_cast<uintptr_t>(data) + kHuge - 1) & ~(kHuge - 1);
  const auto end = (reinterpret_cast<uintptr_t>(data) + bytes) & ~(kHuge - 1);
  if (end > begin) ::madvise(reinterpret_cast<void*>(begin), end - begin, MADV_HUGEPAGE);
#endif
}

/// Where `text` stops looking like text: the first NUL byte in its first 64 KiB, or the first control character
/// when more than 1 % of its first 4 KiB are control characters (other than tab, CR, LF, FF, VT, ^Z). CL files are
/// text, and reading a binary file as APT would only produce a flood of "unknown record" warnings.
std::optional<size_t> binary_offset(string_view text) {
  const string_view head = text.substr(0, size_t{1} << 16);
  if (const size_t nul = head.find('\0'); nul != string_view::npos) return nul;
  const string_view sample = text.substr(0, 4096);
  size_t controls = 0, first = string_view::npos;
  for (size_t i = 0; i < sample.size(); ++i) {
    const auto c = static_cast<unsigned char>(sample[i]);
    // (0x1A: the end-of-file mark of old DOS editors, harmless)
    if ((c < 0x20 && c != '\t' && c != '\n' && c != '\r' && c != '\f' && c != '\v' && c != 0x1A) || c == 0x7F) {
      ++controls;
      if (first == string_view::npos) first = i;
    }
  }
  if (controls * 100 > sample.size()) return first;
  return std::nullopt;
}

/// 1-based line and column of text[offset].
std::pair<int, int> line_column(string_view text, size_t offset) {
  const string_view before = text.substr(0, offset);
  const size_t nl = before.rfind('\n');
  const int line = 1 + static_cast<int>(std::count(before.begin(), before.end(), '\n'));
  const int col = 1 + static_cast<int>(nl == string_view::npos ? offset : offset - nl - 1);
  return {line, col};
}

/// Feed moves without a feed rate (none in the file, or before its first FEDRAT/): the default feed, or an error.
void settle_feeds(Program& prog, const ReadOptions& opt) {
  const auto unfed = [](const Move& m) { return m.kind == MotionKind::Feed && !(m.feed_mm_per_min > 0); };
  const auto first = std::find_if(prog.moves.begin(), prog.moves.end(), unfed);
  if (first == prog.moves.end()) return;
  const bool any_feed = std::any_of(prog.moves.begin(), prog.moves.end(),
                                    [](const Move& m) { return m.kind == MotionKind::Feed && m.feed_mm_per_min > 0; });
  const SourceLoc where{prog.file, first->line, 0};
  if (opt.default_feed_mm_per_min) {
    const double f = *opt.default_feed_mm_per_min;
    size_t n = 0;
    for (Move& m : prog.moves)
      if (unfed(m)) {
        m.feed_mm_per_min = f;
        ++n;
      }
    prog.warnings.push_back(
        {where, fmt::format("{} feed moves without a feed rate ({}): using the default feed {} mm/min", n,
                            any_feed ? "before the first FEDRAT/" : "no FEDRAT/ or CSV feed anywhere in the file", f)});
    return;
  }
  if (!opt.require_feed) return;
  if (any_feed)
    throw InputError(where,
                     "feed move before any feed rate (expected a FEDRAT/ before the first cutting move, "
                     "or a default feed: --default-feed F in mm/min)");
  throw InputError(where,
                   "no feed rate anywhere in the file (expected FEDRAT/ or a CSV feed column, or a default "
                   "feed: --default-feed F in mm/min)");
}

Program read_impl(string_view text, const std::string& name, const ReadOptions& opt) {
  if (!(opt.arc_tolerance_mm > 0) || !std::isfinite(opt.arc_tolerance_mm))
    throw InputError(fmt::format("arc tolerance must be a positive number of mm (got {})", opt.arc_tolerance_mm));
  if (opt.default_feed_mm_per_min &&
      (!(*opt.default_feed_mm_per_min > 0) || !std::isfinite(*opt.default_feed_mm_per_min)))
    throw InputError(
        fmt::format("default feed must be a positive number of mm/min (got {})", *opt.default_feed_mm_per_min));
  if (text.substr(0, 3) == "\xEF\xBB\xBF") text.remove_prefix(3);  // UTF-8 BOM
  if (text.find_first_not_of(" \t\r\n\f\v") == string_view::npos)
    throw InputError(SourceLoc{name, 1, 0},
                     "no motion records: the file is empty (expected APT/CLDATA or CSV x,y,z,i,j,k[,feed])");
  if (const auto at = binary_offset(text)) {
    const auto [line, col] = line_column(text, *at);
    throw InputError(SourceLoc{name, line, col},
                     fmt::format("no motion records: this is a binary file, not CL text (byte 0x{:02X}; expected "
                                 "APT/CLDATA or CSV x,y,z,i,j,k[,feed])",
                                 static_cast<unsigned>(static_cast<unsigned char>(text[*at]))));
  }
  Program prog;
  prog.file = name;
  // One move per line at most (arcs aside): reserving avoids regrowing a large vector.
  // Counted with memchr: std::count goes byte by byte (7 instructions a byte), a tenth of the reading.
  size_t newlines = 0;
  for (const char *p = text.data(), *end = p + text.size();
       (p = static_cast<const char*>(std::memchr(p, '\n', static_cast<size_t>(end - p)))) != nullptr; ++p)
    ++newlines;
  prog.moves.reserve(newlines + 1);
  advise_huge_pages(prog.moves.data(), prog.moves.capacity() * sizeof(Move));
  std::optional<LengthUnit> unit;
  if (looks_like_csv(text)) {
    unit = opt.units;
    read_csv(text, prog, opt);
  } else {
    unit = opt.units ? opt.units : scan_units(text);
    prog.source_units = unit.value_or(LengthUnit::Millimetre);
    // GOTO/ numbers read ahead in parallel, when there is more than one thread and enough text for it to pay.
    std::optional<GotoNumbers> ahead;
    if (tbb::this_task_arena::max_concurrency() > 1 && text.size() > (std::size_t{1} << 20)) ahead.emplace(text);
    AptReader reader(prog, opt, prog.source_units, ahead ? &*ahead : nullptr);
    Splitter sp(text, 0, 1);
    Statement st;
    while (sp.next(st))
      if (!reader.statement(st)) break;
    reader.finish();
  }
  if (prog.moves.empty()) {
    const int lines = static_cast<int>(std::count(text.begin(), text.end(), '\n')) + (text.back() == '\n' ? 0 : 1);
    throw InputError(SourceLoc{name, lines, 0},
                     "no motion records: the file ends without a GOTO/, FROM/ or GODLTA/ (expected at least one "
                     "tool position)");
  }
  if (!unit)
    prog.warnings.insert(prog.warnings.begin(),
                         {SourceLoc{name, prog.moves.front().line, 0},
                          "no UNITS/ and no FEDRAT/ naming IPM or MMPM: lengths are taken as mm (give --units inch "
                          "if they are inches)"});
  settle_feeds(prog, opt);
  return prog;
}

}  // namespace

Program read_text(const std::string& text, const std::string& name, const ReadOptions& options) {
  return read_impl(text, name, options);
}

Program read_file(const std::string& path, const ReadOptions& options) {
#if defined(__unix__)
  // mmap (pre-populated) instead of copying: no zero-fill and no page fault per 4 KiB of a large file.
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0)
    throw InputError(SourceLoc{path},
                     fmt::format("cannot open CL file: {} (expected a readable file)", std::strerror(errno)));
  struct Closer {
    int fd;
    ~Closer() { ::close(fd); }
  } closer{fd};
  struct stat info {};
  if (::fstat(fd, &info) != 0 || S_ISDIR(info.st_mode))
    throw InputError(SourceLoc{path}, "cannot read CL file (expected a regular file, got a directory)");
  if (S_ISREG(info.st_mode) && info.st_size > 0) {
    const auto size = static_cast<size_t>(info.st_size);
    void* p = ::mmap(nullptr, size, PROT_READ, MAP_PRIVATE | MAP_POPULATE, fd, 0);
    if (p != MAP_FAILED) {
      struct Unmapper {
        void* p;
        size_t n;
        ~Unmapper() { ::munmap(p, n); }
      } unmapper{p, size};
      return read_impl(string_view(static_cast<const char*>(p), size), path, options);
    }
  }
  std::string text;  // not mappable (a pipe, an empty file): read it
  char buf[1 << 16];
  for (ssize_t n; (n = ::read(fd, buf, sizeof buf)) != 0;) {
    if (n < 0) {
      if (errno == EINTR) continue;
      throw InputError(SourceLoc{path}, fmt::format("cannot read CL file: {}", std::strerror(errno)));
    }
    text.append(buf, static_cast<size_t>(n));
  }
  return read_impl(text, path, options);
#else
  std::ifstream in(path, std::ios::binary);
  if (!in) throw InputError(SourceLoc{path}, "cannot open CL file (expected a readable file)");
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  return read_impl(text, path, options);
#endif
}

}  // namespace cscam::cl
