// The recording reader of spec/recording.md (shared by calibrate and, later, diagnose).
#include "cscam/calib/recording.hpp"

#include <fmt/format.h>

#include <cerrno>
#include <charconv>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <set>
#include <sstream>

#include "cscam/core/error.hpp"
#include "cscam/sim/recording.hpp"

namespace cscam::calib {

namespace fs = std::filesystem;

std::string Recording::kind() const {
  auto it = meta.find("kind");
  return it == meta.end() ? std::string() : it->second;
}

std::optional<double> Recording::tool_length_mm() const { return meta_number("tool_length", true); }

SourceLoc Recording::meta_loc(const std::string& key) const {
  const auto it = meta_at.find(key);
  return it == meta_at.end() ? SourceLoc{file} : it->second;
}

std::optional<double> Recording::meta_number(const std::string& key, bool zero_ok) const {
  const auto it = meta.find(key);
  if (it == meta.end()) return std::nullopt;
  const std::string& v = it->second;
  double x = 0;
  const char* b = v.data();
  if (!v.empty() && *b == '+') ++b;
  const auto r = std::from_chars(b, v.data() + v.size(), x);
  // std::stod read "0.5um" as 0.5 (mm): a unit or any trailing text is an error, not ignored.
  if (r.ec != std::errc() || r.ptr != v.data() + v.size() || !std::isfinite(x))
    throw InputError(meta_loc(key),
                     fmt::format("metadata '{}': expected a plain number{}, got '{}'", key,
                                 key == "sigma.dir" ? " (unit-vector components)" : " in mm (no unit)", v));
  if (zero_ok ? !(x >= 0) : !(x > 0))
    throw InputError(meta_loc(key),
                     fmt::format("metadata '{}': must be {}, got '{}'", key, zero_ok ? ">= 0" : "positive", v));
  return x;
}

int Recording::column(const std::string& name) const {
  for (std::size_t i = 0; i < columns.size(); ++i)
    if (columns[i] == name) return static_cast<int>(i);
  return -1;
}

namespace {

std::string trim(std::string s) {
  const auto b = s.find_first_not_of(" \t\r");
  if (b == std::string::npos) return {};
  const auto e = s.find_last_not_of(" \t\r");
  return s.substr(b, e - b + 1);
}

/// Splits a CSV line at commas; `starts` receives the 1-based column of each cell.
std::vector<std::string> split(const std::string& line, std::vector<int>& starts) {
  std::vector<std::string> cells;
  starts.clear();
  std::size_t b = 0;
  while (true) {
    const std::size_t e = line.find(',', b);
    starts.push_back(static_cast<int>(b) + 1);
    cells.push_back(trim(line.substr(b, e == std::string::npos ? std::string::npos : e - b)));
    if (e == std::string::npos) break;
    b = e + 1;
  }
  return cells;
}

bool known_column(const std::string& c) {
  if (c == "t") return true;
  static const std::set<std::string> vec{"tip.x", "tip.y", "tip.z", "ptip.x", "ptip.y", "ptip.z",
                                         "dir.x", "dir.y", "dir.z", "acc.x",  "acc.y",  "acc.z"};
  if (vec.count(c)) return true;
  for (const char* p : {"cmd.", "enc.", "len.", "temp."}) {
    const std::string pre(p);
    if (c.size() > pre.size() && c.compare(0, pre.size(), pre) == 0) return true;
  }
  return false;
}

}  // namespace

Recording parse_recording(const std::string& text, const std::string& name) {
  // The sim module's reader parses (one reader for the project); this adds the calibration view: an
  // Eigen matrix, the header line, and unknown column families as errors (a typo in a calibration
  // channel must not silently drop measurements).
  const sim::Recording s = sim::parse_recording(text, name);
  Recording rec;
  rec.file = name;
  for (const auto& [k, v] : s.meta) {
    rec.meta[k] = v;
    rec.meta_at[k] = s.meta_loc(k);
  }
  rec.columns = s.columns;
  rec.line_of_row = s.row_line;
  {
    std::istringstream in(text);
    std::string line;
    int ln = 0;
    while (std::getline(in, line)) {
      ++ln;
      const std::string t = trim(line);
      if (t.empty() || t[0] == '#') continue;
      rec.header_line = ln;
      std::vector<int> starts;
      split(line, starts);
      for (std::size_t i = 0; i < rec.columns.size() && i < starts.size(); ++i)
        if (!known_column(rec.columns[i]))
          throw InputError(SourceLoc{name, ln, starts[i]},
                           fmt::format("unknown column '{}' (expected t, cmd.<axis>, enc.<axis>, tip.x|y|z, "
                                       "ptip.x|y|z, dir.x|y|z, len.<link>, acc.x|y|z or temp.<sensor>)",
                                       rec.columns[i]));
      break;
    }
  }
  (void)rec.tool_length_mm();  // a malformed value is an error here, at its line
  const auto rows = static_cast<Eigen::Index>(s.rows());
  rec.data.resize(rows, static_cast<Eigen::Index>(rec.columns.size()));
  for (std::size_t c = 0; c < rec.columns.size(); ++c)
    for (Eigen::Index r = 0; r < rows; ++r)
      rec.data(r, static_cast<Eigen::Index>(c)) = s.data[c][static_cast<std::size_t>(r)];
  return rec;
}

Recording read_recording(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw InputError(SourceLoc{path}, "cannot open recording");
  std::stringstream ss;
  ss << in.rdbuf();
  return parse_recording(ss.str(), path);
}

void check_axes(const Recording& rec, const std::vector<std::string>& axes, const std::vector<std::string>& links) {
  std::string list;
  for (const auto& a : axes) list += (list.empty() ? "" : ", ") + a;
  // Column positions on the header line (1-based), for messages.
  auto where = [&](std::size_t i) {
    int col = 1;
    for (std::size_t k = 0; k < i; ++k) col += static_cast<int>(rec.columns[k].size()) + 1;
    return SourceLoc{rec.file, rec.header_line, col};
  };
  for (std::size_t i = 0; i < rec.columns.size(); ++i) {
    const std::string& c = rec.columns[i];
    for (const char* p : {"cmd.", "enc."}) {
      const std::string pre(p);
      if (c.compare(0, pre.size(), pre) != 0) continue;
      const std::string ax = c.substr(pre.size());
      if (std::find(axes.begin(), axes.end(), ax) == axes.end())
        throw InputError(where(i), fmt::format("column '{}' names no axis of the machine (its axes: {})", c, list));
    }
    if (c.compare(0, 4, "len.") == 0) {
      const std::string l = c.substr(4);
      if (std::find(links.begin(), links.end(), l) == links.end()) {
        std::string ll;
        for (const auto& x : links) ll += (ll.empty() ? "" : ", ") + x;
        throw InputError(where(i), fmt::format("column '{}' names no passive link of the machine (its links: {})", c,
                                               ll.empty() ? "none" : ll));
      }
    }
  }
  for (const auto& a : axes)
    if (!rec.has("cmd." + a))
      throw InputError(SourceLoc{rec.file, rec.header_line, 0},
                       fmt::format("no column 'cmd.{}': every machine axis ({}) needs its commanded value", a, list));
  for (Eigen::Index r = 0; r < rec.rows(); ++r)
    for (const auto& a : axes) {
      const int c = rec.column("cmd." + a);
      if (std::isnan(rec.data(r, c)))
        throw InputError(SourceLoc{rec.file, rec.line_of_row[static_cast<std::size_t>(r)], 0},
                         fmt::format("column 'cmd.{}' is empty: every pose needs all commanded axes", a));
    }
}

std::string format_recording(const Recording& rec) {
  std::string out;
  for (const auto& [k, v] : rec.meta) out += fmt::format("# {}: {}\n", k, v);
  for (std::size_t i = 0; i < rec.columns.size(); ++i) out += (i ? "," : "") + rec.columns[i];
  out += "\n";
  for (Eigen::Index r = 0; r < rec.data.rows(); ++r) {
    for (Eigen::Index c = 0; c < rec.data.cols(); ++c) {
      if (c) out += ",";
      const double v = rec.data(r, c);
      if (!std::isnan(v)) out += fmt::format("{:.12g}", v);
    }
    out += "\n";
  }
  return out;
}

}  // namespace cscam::calib
