#pragma once
// Text-level edits of a YAML file that keep its comments and layout: replace a value node, add a key
// to a mapping, append a trailing comment to a line. Positions come from yaml-cpp's marks.
#include <yaml-cpp/yaml.h>

#include <map>
#include <string>
#include <vector>

namespace cscam::calib::detail {

class YamlPatcher {
 public:
  explicit YamlPatcher(std::string text);
  /// Replaces the text of a scalar or flow-sequence node by `text`; `comment` is appended to its line.
  void replace(const YAML::Node& node, const std::string& text, const std::string& comment);
  /// Sets `key: text` in mapping `map` (replacing the value if the key exists, else adding the key:
  /// inside the braces of a flow mapping, or on a new line after the mapping's last entry).
  void set(const YAML::Node& map, const std::string& key, const std::string& text, const std::string& comment);
  /// The edited text.
  [[nodiscard]] std::string str() const;

 private:
  struct Edit {
    std::size_t pos, len;
    std::string text;
  };
  std::size_t line_end(std::size_t pos) const;
  std::size_t node_end(const YAML::Node& node) const;
  std::string text_;
  std::vector<Edit> edits_;
  std::map<std::size_t, std::vector<std::string>> comments_;  // by end-of-line position
};

/// Formats a number with enough digits for calibration (no trailing zeros).
std::string fmt_num(double v);

}  // namespace cscam::calib::detail
