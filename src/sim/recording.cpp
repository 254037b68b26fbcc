#include "cscam/sim/recording.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cctype>
#include <charconv>
#include <cmath>
#include <fstream>
#include <limits>
#include <set>
#include <sstream>

#include "cscam/core/error.hpp"
#include "cscam/machine/machine.hpp"

namespace cscam::sim {

namespace {
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

/// Metadata keys of spec/recording.md that no plain comment starts with (not `machine` or `note`, which are words).
bool is_meta_key(const std::string& k) {
  static const std::set<std::string> keys{"kind", "tool_length", "spindle_rpm", "flutes"};
  return keys.count(k) > 0 || k.rfind("sigma.", 0) == 0;
}

std::string trim(std::string_view s) {
  size_t a = 0, b = s.size();
  while (a < b && (s[a] == ' ' || s[a] == '\t' || s[a] == '\r')) ++a;
  while (b > a && (s[b - 1] == ' ' || s[b - 1] == '\t' || s[b - 1] == '\r')) --b;
  return std::string(s.substr(a, b - a));
}
}  // namespace

constexpr double kMaxCellMagnitude = 1e9;

int Recording::column(const std::string& name) const {
  for (size_t i = 0; i < columns.size(); ++i)
    if (columns[i] == name) return static_cast<int>(i);
  return -1;
}

std::optional<std::string> Recording::meta_value(const std::string& key) const {
  for (const auto& [k, v] : meta)
    if (k == key) return v;
  return std::nullopt;
}

SourceLoc Recording::meta_loc(const std::string& key) const {
  for (size_t i = 0; i < meta.size(); ++i)
    if (meta[i].first == key)
      return SourceLoc{file, i < meta_line.size() ? meta_line[i] : 0, i < meta_col.size() ? meta_col[i] : 0};
  return SourceLoc{file};
}

std::optional<double> Recording::meta_number(const std::string& key, double lo, double hi) const {
  for (size_t i = 0; i < meta.size(); ++i) {
    if (meta[i].first != key) continue;
    const std::string& v = meta[i].second;
    double x = kNaN;
    const auto r = std::from_chars(v.data(), v.data() + v.size(), x);
    if (r.ec != std::errc() || r.ptr != v.data() + v.size() || !std::isfinite(x) || x < lo || x > hi)
      throw InputError(meta_loc(key),
                       fmt::format("metadata {}: expected a number in [{:g}, {:g}] (in the spec's unit, written "
                                   "without one), got '{}'",
                                   key, lo, hi, v));
    return x;
  }
  return std::nullopt;
}

void Recording::set_meta(const std::string& key, const std::string& value) {
  for (auto& [k, v] : meta)
    if (k == key) {
      v = value;
      return;
    }
  meta.emplace_back(key, value);
  meta_line.push_back(0);
  meta_col.push_back(0);
}

int Recording::add_column(const std::string& name, std::vector<double> values) {
  if (values.empty()) values.assign(rows(), kNaN);
  columns.push_back(name);
  data.push_back(std::move(values));
  return static_cast<int>(columns.size()) - 1;
}

Recording parse_recording(const std::string& text, const std::string& name) {
  Recording rec;
  rec.file = name;
  // A UTF-8 byte-order mark (spreadsheets write one) is not part of the first line.
  size_t pos = text.rfind("\xEF\xBB\xBF", 0) == 0 ? 3 : 0;
  int line = 0;
  bool header_seen = false;
  while (pos < text.size()) {
    size_t end = text.find('\n', pos);
    if (end == std::string::npos) end = text.size();
    std::string_view ln(text.data() + pos, end - pos);
    pos = end + 1;
    ++line;
    if (!ln.empty() && ln.back() == '\r') ln.remove_suffix(1);
    if (ln.find_first_not_of(" \t") == std::string_view::npos) continue;
    if (ln.front() == '#') {
      if (header_seen) continue;  // a comment after the header
      const auto body = ln.substr(1);
      const auto colon = body.find(':');
      if (colon == std::string_view::npos) {
        // A plain comment, unless it starts with a metadata key: a forgotten colon must not drop the entry.
        const std::string t = trim(body);
        const std::string first = t.substr(0, t.find_first_of(" \t="));
        if (is_meta_key(first))
          throw InputError(SourceLoc{name, line, static_cast<int>(ln.find(first)) + 1 + static_cast<int>(first.size())},
                           fmt::format("metadata '{}': expected '# {}: value' (a colon after the key)", first, first));
        continue;
      }
      const std::string key = trim(body.substr(0, colon));
      if (key.empty())
        throw InputError(SourceLoc{name, line, 2}, "metadata line without a key: expected '# key: value'");
      for (size_t i = 0; i < rec.meta.size(); ++i)
        if (rec.meta[i].first == key)
          throw InputError(SourceLoc{name, line, static_cast<int>(ln.find(key)) + 1},
                           fmt::format("metadata '{}' given twice (first on line {})", key, rec.meta_line[i]));
      const auto vpos = body.find_first_not_of(" \t", colon + 1);
      rec.meta.emplace_back(key, trim(body.substr(colon + 1)));
      rec.meta_line.push_back(line);
      rec.meta_col.push_back(vpos == std::string_view::npos ? static_cast<int>(ln.size()) + 1
                                                            : static_cast<int>(vpos) + 2);  // +1 for '#', 1-based
      continue;
    }
    if (!header_seen) {
      header_seen = true;
      rec.header_line = line;
      if (ln.find(',') == std::string_view::npos && ln.find(';') != std::string_view::npos)
        throw InputError(SourceLoc{name, line, static_cast<int>(ln.find(';')) + 1},
                         "the header's columns are separated by ';': a recording separates them by ',' and writes "
                         "decimals with '.' (shared/spec/recording.md)");
      size_t a = 0;
      std::set<std::string> seen;
      while (true) {
        const size_t b = ln.find(',', a);
        const std::string col = trim(ln.substr(a, b == std::string_view::npos ? std::string_view::npos : b - a));
        if (col.empty())
          throw InputError(SourceLoc{name, line, static_cast<int>(a) + 1}, "empty column name in the header");
        if (!seen.insert(col).second)
          throw InputError(SourceLoc{name, line, static_cast<int>(a) + 1}, fmt::format("duplicate column '{}'", col));
        rec.columns.push_back(col);
        if (b == std::string_view::npos) break;
        a = b + 1;
      }
      rec.data.assign(rec.columns.size(), {});
      continue;
    }
    size_t a = 0, c = 0;
    while (true) {
      const size_t b = ln.find(',', a);
      const size_t e = b == std::string_view::npos ? ln.size() : b;
      if (c >= rec.columns.size())
        throw InputError(SourceLoc{name, line, static_cast<int>(a) + 1},
                         fmt::format("too many cells (the header has {} columns)", rec.columns.size()));
      size_t s0 = a, s1 = e;
      while (s0 < s1 && (ln[s0] == ' ' || ln[s0] == '\t')) ++s0;
      while (s1 > s0 && (ln[s1 - 1] == ' ' || ln[s1 - 1] == '\t')) --s1;
      double v = kNaN;
      if (s1 > s0) {
        const char* first = ln.data() + s0;
        if (*first == '+') ++first;
        const auto [ptr, ec] = std::from_chars(first, ln.data() + s1, v);
        if (ec != std::errc() || ptr != ln.data() + s1 || !std::isfinite(v))
          throw InputError(SourceLoc{name, line, static_cast<int>(s0) + 1},
                           fmt::format("column {}: expected a number, got '{}'", rec.columns[c],
                                       std::string(ln.substr(s0, s1 - s0))));
        // Squares of larger values overflow the fits; no position, time or acceleration of a machine comes near.
        if (std::abs(v) > kMaxCellMagnitude)
          throw InputError(SourceLoc{name, line, static_cast<int>(s0) + 1},
                           fmt::format("column {}: {} is out of range (at most {:g} in magnitude)", rec.columns[c],
                                       std::string(ln.substr(s0, s1 - s0)), kMaxCellMagnitude));
      }
      rec.data[c].push_back(v);
      ++c;
      if (b == std::string_view::npos) break;
      a = b + 1;
    }
    if (c != rec.columns.size())
      throw InputError(SourceLoc{name, line},
                       fmt::format("expected {} cells, got {} (missing cells must be left empty between commas)",
                                   rec.columns.size(), c));
    rec.row_line.push_back(line);
  }
  if (!header_seen) throw InputError(SourceLoc{name}, "no header row (expected e.g. t,cmd.x,...,tip.x,tip.y,tip.z)");
  const int tc = rec.column("t");
  const auto kind = rec.meta_value("kind");
  if (kind && *kind != "trajectory" && *kind != "static")
    throw InputError(rec.meta_loc("kind"),
                     fmt::format("metadata kind: expected trajectory or static, got '{}'", *kind));
  if (tc < 0 && (!kind || *kind == "trajectory")) {
    // Column names are case-sensitive (spec/recording.md): say so where the header would match in lower case.
    bool other_case = false;
    for (const auto& col : rec.columns) {
      std::string lower = col;
      std::transform(lower.begin(), lower.end(), lower.begin(), [](unsigned char ch) { return std::tolower(ch); });
      other_case |= lower != col && (lower == "t" || lower.rfind("cmd.", 0) == 0 || lower.rfind("tip.", 0) == 0);
    }
    throw InputError(SourceLoc{name, rec.header_line},
                     other_case ? "a trajectory recording needs a time column 't': column names are lower case (t, "
                                  "cmd.x, tip.x, ...), and this header's are not"
                                : "a trajectory recording needs a time column 't'");
  }
  if (tc >= 0) {
    const auto& t = rec.data[static_cast<size_t>(tc)];
    for (size_t i = 0; i < t.size(); ++i) {
      if (std::isnan(t[i]))
        throw InputError(SourceLoc{name, rec.row_line[i]}, fmt::format("row {}: time 't' is empty", i + 1));
      if (i > 0 && !(t[i] > t[i - 1]))
        throw InputError(
            SourceLoc{name, rec.row_line[i]},
            fmt::format("row {}: time is not strictly increasing (t = {} after {})", i + 1, t[i], t[i - 1]));
    }
  }
  return rec;
}

Recording read_recording(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw InputError(SourceLoc{path}, "cannot open the recording");
  std::stringstream ss;
  ss << in.rdbuf();
  return parse_recording(ss.str(), path);
}

void write_recording(std::ostream& os, const Recording& rec, int decimals) {
  for (const auto& [k, v] : rec.meta) os << "# " << k << ": " << v << "\n";
  for (size_t c = 0; c < rec.columns.size(); ++c) os << (c ? "," : "") << rec.columns[c];
  os << "\n";
  const size_t n = rec.rows();
  std::string line;
  for (size_t i = 0; i < n; ++i) {
    line.clear();
    for (size_t c = 0; c < rec.columns.size(); ++c) {
      if (c) line += ',';
      const double v = rec.data[c][i];
      if (std::isnan(v)) continue;
      const int d = rec.columns[c] == "t" ? 6 : decimals;
      fmt::format_to(std::back_inserter(line), "{:.{}f}", v == 0.0 ? 0.0 : v, d);
    }
    line += '\n';
    os << line;
  }
}

void validate_against(Recording& rec, const machine::Machine& m) {
  for (const auto& ax : m.axes)
    if (rec.column("cmd." + ax.name) < 0)
      throw InputError(SourceLoc{rec.file, rec.header_line},
                       fmt::format("missing column 'cmd.{}' (machine {} has axis {}; every machine axis needs its "
                                   "commanded position)",
                                   ax.name, m.name, ax.name));
  for (const auto& col : rec.columns) {
    if (col == "t") continue;
    const auto dot = col.find('.');
    const std::string group = dot == std::string::npos ? col : col.substr(0, dot);
    const std::string rest = dot == std::string::npos ? "" : col.substr(dot + 1);
    const bool xyz = rest == "x" || rest == "y" || rest == "z";
    if (group == "cmd" || group == "enc") {
      if (m.axis_index(rest) < 0) {
        if (group == "enc")
          throw InputError(SourceLoc{rec.file}, fmt::format("column '{}': machine {} has no axis '{}', so it cannot "
                                                            "predict this channel",
                                                            col, m.name, rest));
        rec.warnings.push_back(
            fmt::format("{}: column '{}' ignored (machine {} has no axis '{}')", rec.file, col, m.name, rest));
      }
    } else if ((group == "tip" || group == "ptip" || group == "dir" || group == "acc") && xyz) {
    } else if (group == "len") {
      throw InputError(SourceLoc{rec.file}, fmt::format("column '{}': machine {} defines no passive link '{}', so "
                                                        "it cannot predict this channel",
                                                        col, m.name, rest));
    } else if (group == "temp") {
    } else {
      rec.warnings.push_back(fmt::format("{}: unknown column '{}' ignored", rec.file, col));
    }
  }
}

}  // namespace cscam::sim
