// The `xmini:` section of a machine file (kinematics: xmini): parameters of docs/xmini.md, limits,
// axis feeds and the tool length. The common keys (name, post, geometry, ...) are read by machine.cpp,
// which applies `post:` after this function, so the XMINI's post defaults set here can be overridden.
#include <fmt/format.h>
#include <yaml-cpp/yaml.h>

#include <array>
#include <cmath>
#include <initializer_list>
#include <optional>
#include <set>

#include "cscam/core/error.hpp"
#include "cscam/core/units.hpp"
#include "cscam/kin/xmini_kinematics.hpp"
#include "cscam/machine/machine.hpp"

namespace cscam::machine {

namespace {

/// Tool length (gauge point to tip) when neither the machine file nor the post names one: the spec's.
constexpr double kXminiDefaultToolLengthMm = 50.0;

class XminiReader {
 public:
  explicit XminiReader(const std::string& file) : file_(file) {}

  [[noreturn]] void fail(const YAML::Node& n, const std::string& key, const std::string& what) const {
    SourceLoc where{file_, 0, 0};
    if (n.IsDefined() && n.Mark().line >= 0) {
      where.line = n.Mark().line + 1;
      where.column = n.Mark().column + 1;
    }
    throw InputError(where, fmt::format("'{}': {}", key, what));
  }

  void only_keys(const YAML::Node& map, const std::string& path, std::initializer_list<const char*> allowed) const {
    if (!map.IsMap()) fail(map, path, "expected a mapping");
    const std::set<std::string> ok(allowed.begin(), allowed.end());
    for (const auto& kv : map) {
      const auto k = kv.first.as<std::string>();
      if (ok.count(k)) continue;
      std::string list;
      for (const char* a : allowed) list += (list.empty() ? "" : ", ") + std::string(a);
      fail(kv.first, path + "." + k, fmt::format("unknown key (expected one of: {})", list));
    }
  }

  double number(const YAML::Node& n, const std::string& key) const {
    if (!n.IsScalar()) fail(n, key, "expected a number");
    double v = 0;
    try {
      v = n.as<double>();
    } catch (const YAML::Exception&) {
      fail(n, key, fmt::format("expected a number, got '{}'", n.Scalar()));
    }
    if (!std::isfinite(v)) fail(n, key, "expected a finite number");
    return v;
  }

  /// [min, max] with min < max.
  std::pair<double, double> range(const YAML::Node& n, const std::string& key) const {
    if (!n.IsSequence() || n.size() != 2) fail(n, key, "expected [min, max]");
    const double lo = number(n[0], key), hi = number(n[1], key);
    if (!(lo < hi)) fail(n, key, "expected [min, max] with min < max");
    return {lo, hi};
  }

 private:
  std::string file_;
};

void read_parameters(const XminiReader& r, const YAML::Node& n, kin::XminiParams<double>& p) {
  if (!n.IsMap()) r.fail(n, "xmini.parameters", "expected a mapping name: value (mm, deg)");
  for (const auto& kv : n) {
    const auto name = kv.first.as<std::string>();
    const std::string key = "xmini.parameters." + name;
    const double v = r.number(kv.second, key);
    try {
      p.set(name, v);
    } catch (const InputError& e) {
      r.fail(kv.first, key, e.message());
    }
  }
}

void read_limits(const XminiReader& r, const YAML::Node& n, kin::XminiLimits& lim) {
  r.only_keys(n, "xmini.limits", {"strokes_mm", "alpha_deg", "beta_deg", "a_deg", "c_deg"});
  if (const YAML::Node s = n["strokes_mm"]) {
    // One [min, max] for every leg, or a list of three.
    if (s.IsSequence() && s.size() == 3 && s[0].IsSequence()) {
      for (std::size_t i = 0; i < 3; ++i) {
        const auto [lo, hi] = r.range(s[i], fmt::format("xmini.limits.strokes_mm[{}]", i));
        lim.q_min_mm[i] = lo;
        lim.q_max_mm[i] = hi;
      }
    } else {
      const auto [lo, hi] = r.range(s, "xmini.limits.strokes_mm");
      lim.q_min_mm = {lo, lo, lo};
      lim.q_max_mm = {hi, hi, hi};
    }
  }
  auto half_range = [&](const char* key, double& out_rad) {
    if (!n[key]) return;
    const double v = r.number(n[key], std::string("xmini.limits.") + key);
    if (!(v > 0 && v < 90))
      r.fail(n[key], std::string("xmini.limits.") + key, "expected the largest |angle| in deg, 0 < v < 90");
    out_rad = deg2rad(v);
  };
  half_range("alpha_deg", lim.alpha_max_rad);
  half_range("beta_deg", lim.beta_max_rad);
  if (n["a_deg"]) {
    const auto [lo, hi] = r.range(n["a_deg"], "xmini.limits.a_deg");
    lim.a_min_rad = deg2rad(lo);
    lim.a_max_rad = deg2rad(hi);
  }
  if (n["c_deg"]) {
    const auto [lo, hi] = r.range(n["c_deg"], "xmini.limits.c_deg");
    lim.c_min_rad = deg2rad(lo);
    lim.c_max_rad = deg2rad(hi);
  }
}

/// Axis feeds: q1..q3 in mm/min, c and a in deg/min.
void read_max_feed(const XminiReader& r, const YAML::Node& n, std::array<double, 5>& feed) {
  r.only_keys(n, "xmini.max_feed", {"q1", "q2", "q3", "c", "a"});
  for (std::size_t i = 0; i < 5; ++i) {
    const char* name = kin::kXminiAxisNames[i];
    if (!n[name]) continue;
    const std::string key = std::string("xmini.max_feed.") + name;
    const double v = r.number(n[name], key);
    if (!(v > 0)) r.fail(n[name], key, "must be positive");
    feed[i] = i >= 3 ? deg2rad(v) : v;
  }
}

}  // namespace

void load_xmini(const YAML::Node& root, const std::string& file, Machine& m) {
  const XminiReader r(file);
  kin::XminiParams<double> params = kin::XminiParams<double>::nominal();
  kin::XminiLimits limits;
  std::array<double, 5> max_feed{};
  double tool_length_mm = root["default_tool_length_mm"] ? m.default_tool_length_mm : kXminiDefaultToolLengthMm;

  const YAML::Node x = root["xmini"];
  if (x && !x.IsNull()) {
    r.only_keys(x, "xmini", {"parameters", "limits", "max_feed", "tool_length_mm"});
    if (x["parameters"]) read_parameters(r, x["parameters"], params);
    if (x["limits"]) read_limits(r, x["limits"], limits);
    if (x["max_feed"]) read_max_feed(r, x["max_feed"], max_feed);
    if (x["tool_length_mm"]) {
      if (root["default_tool_length_mm"])
        r.fail(x["tool_length_mm"], "xmini.tool_length_mm",
               "the tool length is also given by default_tool_length_mm: give it once");
      tool_length_mm = r.number(x["tool_length_mm"], "xmini.tool_length_mm");
      if (tool_length_mm < 0) r.fail(x["tool_length_mm"], "xmini.tool_length_mm", "must not be negative");
    }
  }
  for (const auto& key : {"axes", "chains", "tool_direction", "spindle_gauge_mm", "part_origin_mm"})
    if (root[key]) r.fail(root[key], key, "not used by kinematics 'xmini' (its geometry is in the 'xmini:' section)");

  // Validate the whole model once now, so a bad file fails at load time.
  std::optional<kin::XminiModel> model;
  try {
    model.emplace(params, limits, tool_length_mm);
  } catch (const InputError& e) {
    r.fail(x ? x : root, "xmini", e.message());
  }

  m.axes = kin::XminiKinematics::axes_for(limits, max_feed);
  m.default_tool_length_mm = tool_length_mm;
  // The XMINI's post defaults; the file's `post:` section is applied afterwards and may change them.
  m.post.dialect = "xmini-joint";
  m.post.letters = {"U", "V", "W", "C", "A"};
  m.post.decimals_linear = 5;
  m.post.decimals_rotary = 5;
  m.post.tolerance_mm = 0.001;
  m.post.axis_tolerance_deg = 0.01;
  m.post.start_branch = "positive:a";
  m.post.program_name = "XMINI";
  const auto axes = m.axes;
  m.make_kinematics = [params, limits, axes](double L) -> std::shared_ptr<const kin::Kinematics> {
    return std::make_shared<kin::XminiKinematics>(kin::XminiModel(params, limits, L), axes);
  };
}

}  // namespace cscam::machine
