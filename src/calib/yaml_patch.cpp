#include "yaml_patch.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>

namespace cscam::calib::detail {

std::string fmt_num(double v) {
  if (std::abs(v) < 5e-13) v = 0.0;
  std::string s = fmt::format("{:.10f}", v);
  while (!s.empty() && s.back() == '0') s.pop_back();
  if (!s.empty() && s.back() == '.') s.pop_back();
  if (s == "-0") s = "0";
  return s;
}

YamlPatcher::YamlPatcher(std::string text) : text_(std::move(text)) {}

std::size_t YamlPatcher::line_end(std::size_t pos) const {
  const std::size_t e = text_.find('\n', pos);
  return e == std::string::npos ? text_.size() : e;
}

std::size_t YamlPatcher::node_end(const YAML::Node& node) const {
  const std::size_t pos = static_cast<std::size_t>(node.Mark().pos);
  if (pos < text_.size() && (text_[pos] == '[' || text_[pos] == '{')) {
    int depth = 0;
    for (std::size_t i = pos; i < text_.size(); ++i) {
      if (text_[i] == '[' || text_[i] == '{') ++depth;
      if (text_[i] == ']' || text_[i] == '}') {
        if (--depth == 0) return i + 1;
      }
    }
    return text_.size();
  }
  // A plain or quoted scalar: up to a comma, closing bracket, comment or end of line.
  std::size_t i = pos;
  if (pos < text_.size() && (text_[pos] == '"' || text_[pos] == '\'')) {
    const std::size_t q = text_.find(text_[pos], pos + 1);
    return q == std::string::npos ? line_end(pos) : q + 1;
  }
  while (i < text_.size() && text_[i] != '\n' && text_[i] != ',' && text_[i] != ']' && text_[i] != '}' &&
         !(text_[i] == '#' && i > pos && text_[i - 1] == ' '))
    ++i;
  while (i > pos && text_[i - 1] == ' ') --i;
  return i;
}

void YamlPatcher::replace(const YAML::Node& node, const std::string& text, const std::string& comment) {
  const std::size_t pos = static_cast<std::size_t>(node.Mark().pos);
  const std::size_t end = node_end(node);
  edits_.push_back({pos, end - pos, text});
  if (!comment.empty()) comments_[line_end(pos)].push_back(comment);
}

void YamlPatcher::set(const YAML::Node& map, const std::string& key, const std::string& text,
                      const std::string& comment) {
  if (const YAML::Node v = map[key]; v.IsDefined() && !v.IsNull()) {
    replace(v, text, comment);
    return;
  }
  const std::size_t pos = static_cast<std::size_t>(map.Mark().pos);
  if (pos < text_.size() && text_[pos] == '{') {
    const std::size_t close = node_end(map) - 1;
    edits_.push_back({close, 0, fmt::format(", {}: {}", key, text)});
    if (!comment.empty()) comments_[line_end(close)].push_back(comment);
    return;
  }
  // Block mapping: a new line after the last entry, at the indentation of the first key.
  std::size_t last = pos;
  int indent = map.Mark().column;
  for (const auto& kv : map) last = std::max(last, node_end(kv.second.IsDefined() ? kv.second : kv.first));
  const std::size_t eol = line_end(last);
  edits_.push_back({eol, 0,
                    fmt::format("\n{}{}: {}{}", std::string(static_cast<std::size_t>(indent), ' '), key, text,
                                comment.empty() ? "" : "  # " + comment)});
}

std::string YamlPatcher::str() const {
  // Apply from the back so that earlier positions stay valid. Comments go at line ends.
  struct Op {
    std::size_t pos, len;
    std::string text;
    int order;
  };
  std::vector<Op> ops;
  for (const Edit& e : edits_) ops.push_back({e.pos, e.len, e.text, 0});
  for (const auto& [eol, list] : comments_) {
    std::string c;
    for (const auto& s : list) c += (c.empty() ? "" : "; ") + s;
    ops.push_back({eol, 0, "  # " + c, -1});
  }
  std::stable_sort(ops.begin(), ops.end(), [](const Op& a, const Op& b) {
    if (a.pos != b.pos) return a.pos > b.pos;
    return a.order > b.order;  // at the same position: the comment (order -1) ends up after the edit
  });
  std::string out = text_;
  for (const Op& o : ops) out.replace(o.pos, o.len, o.text);
  return out;
}

}  // namespace cscam::calib::detail
