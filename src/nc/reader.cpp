#include "cscam/nc/reader.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cctype>
#include <charconv>
#include <cmath>
#include <fstream>
#include <sstream>

#include "cscam/core/error.hpp"
#include "cscam/core/units.hpp"

namespace cscam::nc {

namespace {

std::string_view trim(std::string_view s) {
  while (!s.empty() && (std::isspace(static_cast<unsigned char>(s.front())) || s.front() == '\xEF' ||
                        s.front() == '\xBB' || s.front() == '\xBF'))
    s.remove_prefix(1);
  while (!s.empty() && std::isspace(static_cast<unsigned char>(s.back()))) s.remove_suffix(1);
  return s;
}

}  // namespace

Program read_text(const std::string& text, const std::string& name, const AxisLetters& letters) {
  Program prog;
  prog.file = name;
  // Lines before the first lone '%' are a listing header (NX writes one); skip them when a '%' exists.
  std::vector<std::string_view> lines;
  {
    std::string_view all(text);
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

  Block state;
  Motion motion = Motion::Rapid;
  bool inch = false, absolute = true, g93 = false;
  double feed = 0.0;
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
    bool non_modal_skip = false, tcp_word = false;
    Block b = state;
    b.words = {};
    size_t i = 0;
    auto fail = [&](size_t col, const std::string& what) {
      throw InputError(SourceLoc{name, lineno, static_cast<int>(col) + 1}, what);
    };
    std::array<double, 5> word_val{};
    while (i < s.size()) {
      const char c = s[i];
      if (std::isspace(static_cast<unsigned char>(c)) || c == '%') {
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
      if (!std::isalpha(static_cast<unsigned char>(c))) fail(i, fmt::format("unexpected character '{}'", c));
      const char L = static_cast<char>(std::toupper(static_cast<unsigned char>(c)));
      const int word_column = static_cast<int>(i) + 1;
      size_t j = i + 1;
      while (j < s.size() && s[j] == ' ') ++j;
      size_t k = j;
      if (k < s.size() && (s[k] == '-' || s[k] == '+')) ++k;
      while (k < s.size() && (std::isdigit(static_cast<unsigned char>(s[k])) || s[k] == '.')) ++k;
      if (L == 'O') break;  // program number/name ("O2021-11-28_part"): not a block
      std::string num(s.substr(j, k - j));
      if (!num.empty() && num[0] == '+') num.erase(0, 1);
      double v = 0;
      // "X-.5" and "X3." are valid G-code numbers; from_chars wants a digit before/after the point.
      std::string fixed = num;
      if (!fixed.empty() && fixed.back() == '.') fixed.push_back('0');
      if (fixed.rfind("-.", 0) == 0) fixed.insert(1, "0");
      if (!fixed.empty() && fixed[0] == '.') fixed.insert(0, "0");
      auto r = std::from_chars(fixed.data(), fixed.data() + fixed.size(), v);
      if (num.empty() || r.ec != std::errc() || r.ptr != fixed.data() + fixed.size())
        fail(j, fmt::format("malformed number after '{}': '{}'", L, std::string(s.substr(j, k - j))));
      i = k;
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
          case 200:
            inch = true;
            break;
          case 210:
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
          case 280:
          case 300:
          case 530:
          case 100:
          case 920:
            non_modal_skip = true;
            break;
          case 434:
          case 2340:
            tcp_word = true;
            break;
          default:
            break;
        }
        continue;
      }
      if (L == 'F') {
        feed = v;
        continue;
      }
      bool axis_word = false;
      for (int a = 0; a < 5; ++a)
        if (letters.letter[static_cast<size_t>(a)] == L) {
          b.words[static_cast<size_t>(a)] = true;
          word_val[static_cast<size_t>(a)] = v;
          axis_word = true;
        }
      if (!axis_word && std::string_view("XYZABCUVW").find(L) != std::string_view::npos &&
          std::none_of(prog.foreign_axis_words.begin(), prog.foreign_axis_words.end(),
                       [L](const Program::ForeignWord& f) { return f.letter == L; }))
        prog.foreign_axis_words.push_back({L, lineno, word_column});
    }
    if (tcp_word) prog.tcp = true;
    bool any_axis = false;
    for (bool w : b.words) any_axis |= w;
    if (non_modal_skip) {
      if (any_axis)
        prog.notes.push_back(fmt::format("{}:{}: G28/G30/G53/G10/G92 block not taken as a position", name, lineno));
      continue;
    }
    if (!any_axis) continue;
    for (int a = 0; a < 5; ++a) {
      if (!b.words[static_cast<size_t>(a)]) continue;
      double v = word_val[static_cast<size_t>(a)];
      if (letters.rotary[static_cast<size_t>(a)])
        v = deg2rad(v);
      else if (inch)
        v *= kMmPerInch;
      b.axes[static_cast<size_t>(a)] = absolute ? v : b.axes[static_cast<size_t>(a)] + v;
      b.known[static_cast<size_t>(a)] = true;
    }
    if ((motion == Motion::ArcCW || motion == Motion::ArcCCW) && prog.notes.size() < 1000)
      prog.notes.push_back(fmt::format("{}:{}: arc taken as its chord for statistics", name, lineno));
    b.line = lineno;
    b.motion = motion;
    b.inverse_time = g93;
    b.feed = inch && !g93 ? feed * kMmPerInch : feed;
    prog.blocks.push_back(b);
    state = b;
  }
  return prog;
}

Program read_file(const std::string& path, const AxisLetters& letters) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw InputError(SourceLoc{path}, "cannot open NC file");
  std::stringstream ss;
  ss << in.rdbuf();
  return read_text(ss.str(), path, letters);
}

}  // namespace cscam::nc
