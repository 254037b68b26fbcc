// Calibration models of the bundled machine kinds: serial (ISO 230-1 location errors of the rotary
// axes, squareness of the linear axes, gauge point, part origin), the XMINI (spec/xmini.md's vector)
// and the seed-001 parallel CMM (26 parameters). Every prediction runs the templated kinematics of
// the kin module; this file only maps a flat parameter vector onto their geometry structs.
#include "cscam/calib/model.hpp"

#include <ceres/jet.h>
#include <fmt/format.h>
#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <fstream>
#include <random>
#include <sstream>

#include "cscam/core/error.hpp"
#include "cscam/core/units.hpp"
#include "cscam/kin/pcmm.hpp"
#include "cscam/kin/serial.hpp"
#include "cscam/kin/xmini.hpp"
#include "cscam/kin/xmini_kinematics.hpp"
#include "cscam/machine/machine.hpp"
#include "yaml_patch.hpp"

namespace cscam::calib {

using detail::fmt_num;

namespace {
/// A machine file whose flat `parameters:` mapping (XMINI, PCMM) gets every value that moved, each marked
/// with the nominal it replaces.
std::string patch_flat_parameters(const std::string& text, const YAML::Node& parameters,
                                  const std::vector<ParamInfo>& info, const std::vector<double>& p) {
  detail::YamlPatcher patch(text);
  for (std::size_t i = 0; i < info.size(); ++i) {
    if (std::abs(p[i] - info[i].nominal) <= 1e-13) continue;
    patch.set(parameters, info[i].name, fmt_num(p[i]), "calibrated: was " + fmt_num(info[i].nominal));
  }
  return patch.str();
}
}  // namespace

// ---------------------------------------------------------------------------------------------------
// Model (common part)
// ---------------------------------------------------------------------------------------------------

std::vector<double> Model::nominal() const {
  std::vector<double> p;
  p.reserve(params_.size());
  for (const auto& i : params_) p.push_back(i.nominal);
  return p;
}

std::size_t Model::index(const std::string& name) const {
  for (std::size_t i = 0; i < params_.size(); ++i)
    if (params_[i].name == name) return i;
  std::string list;
  for (const auto& i : params_) list += (list.empty() ? "" : ", ") + i.name;
  throw InputError(fmt::format("unknown parameter '{}' (this {} machine has: {})", name, kind(), list));
}

std::vector<std::size_t> Model::select(const std::vector<std::string>& names_or_groups) const {
  std::vector<std::size_t> out;
  auto add = [&](std::size_t i) {
    if (std::find(out.begin(), out.end(), i) == out.end()) out.push_back(i);
  };
  for (const std::string& n : names_or_groups) {
    if (n.empty()) continue;
    if (n == "all") {
      for (std::size_t i = 0; i < params_.size(); ++i) add(i);
      continue;
    }
    bool group = false;
    for (std::size_t i = 0; i < params_.size(); ++i)
      if (params_[i].group == n) {
        add(i);
        group = true;
      }
    if (group) continue;
    bool found = false;
    for (std::size_t i = 0; i < params_.size(); ++i)
      if (params_[i].name == n) {
        add(i);
        found = true;
      }
    if (!found) {
      std::string groups, names;
      for (const auto& p : params_) {
        if (groups.find(p.group) == std::string::npos) groups += (groups.empty() ? "" : ", ") + p.group;
        names += (names.empty() ? "" : ", ") + p.name;
      }
      throw InputError(fmt::format("--free: '{}' is neither a parameter nor a group (groups: {}; parameters: {})", n,
                                   groups, names));
    }
  }
  std::sort(out.begin(), out.end());
  return out;
}

std::vector<std::string> Model::channel_names() const {
  std::vector<std::string> c{"tip.x", "tip.y", "tip.z", "dir.x", "dir.y", "dir.z", "ptip.x", "ptip.y", "ptip.z"};
  for (const auto& l : links_) c.push_back("len." + l);
  return c;
}

Prediction Model::predict(const std::vector<double>& q, const std::vector<double>& p, Scratch* scratch) const {
  if (q.size() != axes_.size())
    throw InputError(fmt::format("predict: expected {} axis values, got {}", axes_.size(), q.size()));
  if (p.size() != params_.size())
    throw InputError(fmt::format("predict: expected {} parameters, got {}", params_.size(), p.size()));
  std::unique_ptr<Scratch> own;
  if (!scratch) {
    own = make_scratch();
    scratch = own.get();
  }
  std::vector<double> out(9 + links_.size());
  predict_channels(q.data(), p.data(), out.data(), scratch);
  Prediction r;
  r.tip = Eigen::Vector3d(out[0], out[1], out[2]);
  r.dir = Eigen::Vector3d(out[3], out[4], out[5]);
  r.ptip = Eigen::Vector3d(out[6], out[7], out[8]);
  for (std::size_t i = 0; i < links_.size(); ++i) r.len[links_[i]] = out[9 + i];
  return r;
}

std::map<std::string, double> Model::deviations(const std::vector<double>& p, double eps) const {
  std::map<std::string, double> d;
  for (std::size_t i = 0; i < params_.size() && i < p.size(); ++i)
    if (std::abs(p[i] - params_[i].nominal) > eps) d[params_[i].name] = p[i] - params_[i].nominal;
  return d;
}

namespace {

std::string read_text(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw InputError(SourceLoc{path}, "cannot open machine file");
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

YAML::Node parse_yaml(const std::string& text, const std::string& path) {
  try {
    return YAML::Load(text);
  } catch (const YAML::ParserException& e) {
    throw InputError(SourceLoc{path, e.mark.line + 1, e.mark.column + 1}, "YAML syntax error: " + e.msg);
  }
}

template <typename T>
T to_internal(const T& v, bool angle) {
  return angle ? v * T(kPi / 180.0) : v;
}

// ---------------------------------------------------------------------------------------------------
// Serial machines
// ---------------------------------------------------------------------------------------------------

/// How one serial parameter changes the geometry.
enum class SerialOp { PivotShift, Tilt, Zero, Squareness, Gauge, PartOrigin, ToolTilt };

struct SerialParam {
  SerialOp op;
  int joint = -1;  ///< joint index (axis order), -1 for tool/part parameters
  int coord = 0;   ///< 0, 1, 2 = x, y, z (shift direction or rotation axis)
};

int dominant(const Eigen::Vector3d& d) {
  int k = 0;
  d.cwiseAbs().maxCoeff(&k);
  return k;
}

class SerialModel final : public Model {
 public:
  SerialModel(const machine::Machine& m, std::string text) : g0_(*m.serial), text_(std::move(text)) {
    file_ = m.file;
    tool_length_mm_ = m.default_tool_length_mm;
    for (const auto& a : m.axes) {
      axes_.push_back(a.name);
      rotary_.push_back(a.rotary());
      const double s = a.rotary() ? 180.0 / kPi : 1.0;
      // Poses for calibration: inside the limits, linear axes within +-200 mm, rotaries within one turn.
      const double cap = a.rotary() ? 180.0 : 200.0;
      lo_.push_back(std::max(a.min * s, -cap));
      hi_.push_back(std::min(a.max * s, cap));
    }
    static const char* kPos = "XYZ";
    static const char* kRot = "ABC";
    auto up = [](std::string s) {
      for (auto& c : s) c = static_cast<char>(std::toupper(static_cast<unsigned char>(c)));
      return s;
    };
    // Rotary axes: ISO 230-1 location errors (two offsets and two tilts of the axis line) + zero.
    for (int j = 0; j < 5; ++j) {
      if (!m.axes[static_cast<std::size_t>(j)].rotary()) continue;
      const std::string L = up(m.axes[static_cast<std::size_t>(j)].name);
      const std::string grp = "rotary_" + m.axes[static_cast<std::size_t>(j)].name;
      const int k = dominant(g0_.joints[static_cast<std::size_t>(j)].direction);
      for (int c = 0; c < 3; ++c)
        if (c != k)
          add(fmt::format("E{}0{}", kPos[c], L), grp, "mm", {SerialOp::PivotShift, j, c},
              fmt::format("position of the {} axis line in {}", L, kPos[c]));
      for (int c = 0; c < 3; ++c)
        if (c != k)
          add(fmt::format("E{}0{}", kRot[c], L), grp, "deg", {SerialOp::Tilt, j, c},
              fmt::format("tilt of the {} axis about {}", L, kPos[c]));
      add(fmt::format("E{}0{}", kRot[k], L), grp, "deg", {SerialOp::Zero, j, k},
          fmt::format("zero-point error of {}", L));
    }
    // Linear axes: squareness (ISO 230-1: the first linear axis is the reference).
    std::vector<int> lin;
    for (int j = 0; j < 5; ++j)
      if (!m.axes[static_cast<std::size_t>(j)].rotary()) lin.push_back(j);
    if (lin.size() == 3) {
      const int k0 = dominant(g0_.joints[static_cast<std::size_t>(lin[0])].direction);
      const int k1 = dominant(g0_.joints[static_cast<std::size_t>(lin[1])].direction);
      const int k2 = dominant(g0_.joints[static_cast<std::size_t>(lin[2])].direction);
      const std::string L1 = up(m.axes[static_cast<std::size_t>(lin[1])].name);
      const std::string L2 = up(m.axes[static_cast<std::size_t>(lin[2])].name);
      add(fmt::format("E{}0{}", kRot[k2], L1), "squareness", "deg", {SerialOp::Squareness, lin[1], k2},
          fmt::format("squareness of {} (rotation about {})", L1, kPos[k2]));
      add(fmt::format("E{}0{}", kRot[k0], L2), "squareness", "deg", {SerialOp::Squareness, lin[2], k0},
          fmt::format("squareness of {} (rotation about {})", L2, kPos[k0]));
      add(fmt::format("E{}0{}", kRot[k1], L2), "squareness", "deg", {SerialOp::Squareness, lin[2], k1},
          fmt::format("squareness of {} (rotation about {})", L2, kPos[k1]));
    }
    for (int c = 0; c < 3; ++c)
      add(fmt::format("gauge_{}", "xyz"[c]), "tool", "mm", {SerialOp::Gauge, -1, c},
          fmt::format("spindle gauge point at home, {}", kPos[c]));
    const int kt = dominant(g0_.tool_direction_home);
    for (int c = 0; c < 3; ++c)
      if (c != kt)
        add(fmt::format("tool_tilt_{}", "xyz"[c]), "tool", "deg", {SerialOp::ToolTilt, -1, c},
            fmt::format("tilt of the spindle axis about {}", kPos[c]));
    for (int c = 0; c < 3; ++c)
      add(fmt::format("part_{}", "xyz"[c]), "part", "mm", {SerialOp::PartOrigin, -1, c},
          fmt::format("part origin at home, {}", kPos[c]));
  }

  std::string kind() const override { return "serial"; }

  template <typename T>
  kin::SerialGeometry<T> geometry(const T* p) const {
    kin::SerialGeometry<T> g = g0_.template cast<T>();
    using V = Eigen::Matrix<T, 3, 1>;
    for (std::size_t i = 0; i < ops_.size(); ++i) {
      const SerialParam& o = ops_[i];
      const bool angle = params_[i].unit == "deg";
      const T v = to_internal(p[i], angle);
      V e = V::Zero();
      e[o.coord] = T(1);
      switch (o.op) {
        case SerialOp::PivotShift:
          g.joints[static_cast<std::size_t>(o.joint)].pivot_mm += e * v;
          break;
        case SerialOp::Tilt:
        case SerialOp::Squareness: {
          auto& d = g.joints[static_cast<std::size_t>(o.joint)].direction;
          d = kin::detail::axis_angle<T>(e, v) * d;
          break;
        }
        case SerialOp::Zero:
          g.joints[static_cast<std::size_t>(o.joint)].offset += v;
          break;
        case SerialOp::Gauge:
          g.gauge_home_mm += e * v;
          break;
        case SerialOp::PartOrigin:
          g.part_origin_home_mm += e * v;
          break;
        case SerialOp::ToolTilt:
          g.tool_direction_home = kin::detail::axis_angle<T>(e, v) * g.tool_direction_home;
          break;
      }
    }
    g.tool_length_mm = T(tool_length_mm_);
    return g;
  }

  template <typename T>
  void eval(const double* q, const T* p, T* out) const {
    kin::SerialGeometry<T> g = geometry(p);
    Eigen::Matrix<double, 5, 1> qi;
    for (int i = 0; i < 5; ++i) qi[i] = rotary_[static_cast<std::size_t>(i)] ? deg2rad(q[i]) : q[i];
    const kin::Pose<T> part = kin::serial_forward(g, qi);
    g.table_chain.clear();
    g.part_origin_home_mm.setZero();
    const kin::Pose<T> w = kin::serial_forward(g, qi);
    for (int c = 0; c < 3; ++c) {
      out[c] = w.tip_mm[c];
      out[3 + c] = w.axis[c];
      out[6 + c] = part.tip_mm[c];
    }
  }
  void predict_channels(const double* q, const double* p, double* out, Scratch*) const override { eval(q, p, out); }
  void predict_channels(const double* q, const Jet* p, Jet* out, Scratch*) const override { eval(q, p, out); }

  std::string corrected_yaml(const std::vector<double>& p) const override {
    const kin::SerialGeometry<double> g = geometry(p.data());
    const YAML::Node root = parse_yaml(text_, file_);
    detail::YamlPatcher patch(text_);
    auto vec = [](const Eigen::Vector3d& v) {
      return fmt::format("[{}, {}, {}]", fmt_num(v.x()), fmt_num(v.y()), fmt_num(v.z()));
    };
    auto changed = [](const Eigen::Vector3d& a, const Eigen::Vector3d& b) { return (a - b).norm() > 1e-12; };
    auto was = [](const YAML::Node& n) {
      if (!n.IsDefined()) return std::string("absent");
      YAML::Emitter e;
      e << YAML::Flow << n;
      return std::string(e.c_str());
    };
    const YAML::Node axes = root["axes"];
    for (std::size_t j = 0; j < 5; ++j) {
      const YAML::Node a = axes[j];
      const auto& n = g.joints[j];
      const auto& o = g0_.joints[j];
      if (changed(n.direction, o.direction))
        patch.set(a, "direction", vec(n.direction), "calibrated: direction was " + was(a["direction"]));
      if (rotary_[j] && changed(n.pivot_mm, o.pivot_mm))
        patch.set(a, "pivot_mm", vec(n.pivot_mm), "calibrated: pivot_mm was " + was(a["pivot_mm"]));
      if (std::abs(n.offset - o.offset) > 1e-15) {
        const double s = rotary_[j] ? 180.0 / kPi : 1.0;
        patch.set(a, "offset", fmt_num(n.offset * s), fmt::format("calibrated: offset was {}", fmt_num(o.offset * s)));
      }
    }
    auto top = [&](const char* key, const Eigen::Vector3d& nv, const Eigen::Vector3d& ov) {
      if (changed(nv, ov)) patch.set(root, key, vec(nv), fmt::format("calibrated: {} was {}", key, was(root[key])));
    };
    top("spindle_gauge_mm", g.gauge_home_mm, g0_.gauge_home_mm);
    top("tool_direction", g.tool_direction_home, g0_.tool_direction_home);
    top("part_origin_mm", g.part_origin_home_mm, g0_.part_origin_home_mm);
    return patch.str();
  }

 private:
  void add(std::string name, std::string group, std::string unit, SerialParam op, std::string desc) {
    params_.push_back({std::move(name), std::move(group), std::move(unit), 0.0, std::move(desc)});
    ops_.push_back(op);
  }
  kin::SerialGeometry<double> g0_;
  std::string text_;
  std::vector<SerialParam> ops_;
  std::vector<double> lo_, hi_;

 public:
  std::vector<std::vector<double>> random_poses(std::size_t n, std::uint64_t seed) const override {
    std::mt19937_64 rng(seed);
    std::vector<std::vector<double>> out;
    for (std::size_t k = 0; k < n; ++k) {
      std::vector<double> q(5);
      for (std::size_t i = 0; i < 5; ++i) q[i] = std::uniform_real_distribution<double>(lo_[i], hi_[i])(rng);
      out.push_back(q);
    }
    return out;
  }
};

// ---------------------------------------------------------------------------------------------------
// XMINI
// ---------------------------------------------------------------------------------------------------

const char* xmini_group(std::size_t i) {
  if (i < 6) return "base";
  if (i < 13) return "base_joints";
  if (i < 22) return "platform";
  if (i < 25) return "legs";
  if (i < 35) return "wrist";
  return "gauge";
}

struct XminiScratch final : Scratch {
  kin::XminiWorkspace ws;
};

class XminiCalModel final : public Model {
 public:
  XminiCalModel(const kin::XminiParams<double>& nominal, const kin::XminiLimits& limits, double tool_length_mm,
                std::string file, std::string text)
      : text_(std::move(text)), machine_(nominal, limits, tool_length_mm) {
    file_ = std::move(file);
    tool_length_mm_ = tool_length_mm;
    for (const char* a : kin::kXminiAxisNames) axes_.emplace_back(a);
    rotary_ = {false, false, false, true, true};
    const auto& info = kin::xmini_param_info();
    for (std::size_t i = 0; i < kin::kXminiParamCount; ++i) {
      const double v = info[i].angle() ? rad2deg(nominal[i]) : nominal[i];
      params_.push_back({std::string(info[i].name), xmini_group(i), std::string(info[i].unit), v,
                         "spec/xmini.md parameter " + std::string(info[i].name)});
    }
  }
  std::string kind() const override { return "xmini"; }
  std::unique_ptr<Scratch> make_scratch() const override { return std::make_unique<XminiScratch>(); }

  template <typename T>
  void eval(const double* q, const T* p, T* out, Scratch* s) const {
    XminiScratch local;
    auto* xs = s ? static_cast<XminiScratch*>(s) : &local;
    kin::XminiParams<T> xp;
    const auto& info = kin::xmini_param_info();
    for (std::size_t i = 0; i < kin::kXminiParamCount; ++i) xp[i] = to_internal(p[i], info[i].angle());
    kin::XminiJoints<T> qj;
    for (int i = 0; i < 5; ++i) qj[i] = T(i >= 3 ? deg2rad(q[i]) : q[i]);
    const kin::XminiFkResult<T> r = kin::xmini_forward(xp, qj, tool_length_mm_, xs->ws);
    const double nan = std::numeric_limits<double>::quiet_NaN();
    for (int c = 0; c < 3; ++c) {
      out[c] = r.summary.converged ? r.pose.tip_in_W_mm[c] : T(nan);
      out[3 + c] = r.summary.converged ? r.pose.u_in_W[c] : T(nan);
      out[6 + c] = out[c];
    }
  }
  void predict_channels(const double* q, const double* p, double* out, Scratch* s) const override {
    eval(q, p, out, s);
  }
  void predict_channels(const double* q, const Jet* p, Jet* out, Scratch* s) const override { eval(q, p, out, s); }

  std::string corrected_yaml(const std::vector<double>& p) const override {
    const YAML::Node root = parse_yaml(text_, file_);
    const YAML::Node x = root["xmini"];
    if (!x || !x["parameters"])
      throw InputError(SourceLoc{file_}, "cannot write the corrected file: it has no 'xmini.parameters' section");
    const YAML::Node ps = x["parameters"];
    return patch_flat_parameters(text_, ps, params_, p);
  }

 private:
  /// Tips in the spec's working volume (cylinder of diameter 300, z -100..100, tilt up to 30 deg),
  /// solved by the nominal machine's IK (first feasible solution).
  std::vector<std::vector<double>> random_poses(std::size_t n, std::uint64_t seed) const override {
    std::mt19937_64 rng(seed);
    std::uniform_real_distribution<double> u01(0.0, 1.0);
    std::vector<std::vector<double>> out;
    std::vector<kin::XminiIkSolution> sols;
    for (std::size_t tries = 0; out.size() < n && tries < 50 * n + 100; ++tries) {
      const double r = 150.0 * std::sqrt(u01(rng)), ph = 2 * kPi * u01(rng);
      const Eigen::Vector3d tip(r * std::cos(ph), r * std::sin(ph), -100.0 + 200.0 * u01(rng));
      const double tilt = std::acos(1.0 - u01(rng) * (1.0 - std::cos(deg2rad(30.0)))), az = 2 * kPi * u01(rng);
      const Eigen::Vector3d u(std::sin(tilt) * std::cos(az), std::sin(tilt) * std::sin(az), std::cos(tilt));
      machine_.inverse(tip, u, sols);
      for (const auto& s : sols) {
        if (!s.feasible()) continue;
        out.push_back({s.q1_mm, s.q2_mm, s.q3_mm, rad2deg(s.c_rad), rad2deg(s.a_rad)});
        break;
      }
    }
    return out;
  }

 private:
  std::string text_;
  kin::XminiModel machine_;
};

// ---------------------------------------------------------------------------------------------------
// Parallel CMM (seed 001)
// ---------------------------------------------------------------------------------------------------

struct PcmmScratch final : Scratch {
  kin::PcmmPose<double> ws = kin::pcmm_home_pose();
};

class PcmmCalModel final : public Model {
 public:
  PcmmCalModel(const std::vector<double>& nominal_file_units, const Eigen::Vector3d& tip_S, std::string file,
               std::string text, std::string link_name)
      : tip_S_(tip_S), text_(std::move(text)) {
    file_ = std::move(file);
    axes_ = {"q1", "q2", "q3"};
    rotary_ = {false, false, false};
    links_ = {std::move(link_name)};  // recordings give its gauge as len.<name>
    const auto& info = kin::pcmm_param_info();
    for (std::size_t i = 0; i < kin::kPcmmParamCount; ++i)
      params_.push_back({std::string(info[i].name), std::string(info[i].group), std::string(info[i].unit),
                         nominal_file_units[i], "seed 001 parameter " + std::string(info[i].name)});
    // A rotation of the stage frame about its normal turns every ths_i alike; joint 1 defines its x axis.
    params_[index("ths1")].gauge = true;
  }
  std::string kind() const override { return "pcmm"; }
  std::unique_ptr<Scratch> make_scratch() const override { return std::make_unique<PcmmScratch>(); }

  template <typename T>
  void eval(const double* q, const T* p, T* out, Scratch* s) const {
    PcmmScratch local;
    auto* ps = s ? static_cast<PcmmScratch*>(s) : &local;
    kin::PcmmParams<T> pp;
    const auto& info = kin::pcmm_param_info();
    for (std::size_t i = 0; i < kin::kPcmmParamCount; ++i) pp[i] = to_internal(p[i], info[i].angle());
    kin::PcmmPose<T> x;
    const Eigen::Vector3d qv(q[0], q[1], q[2]);
    if (!kin::pcmm_forward(pp, qv, ps->ws, x)) {
      for (int c = 0; c < 10; ++c) out[c] = T(std::numeric_limits<double>::quiet_NaN());
      return;
    }
    const Eigen::Matrix<T, 3, 1> tip = kin::pcmm_tip(x, tip_S_);
    const Eigen::Matrix<T, 3, 1> dir = x.R.col(2);
    for (int c = 0; c < 3; ++c) {
      out[c] = tip[c];
      out[3 + c] = dir[c];
      out[6 + c] = tip[c];
    }
    out[9] = kin::pcmm_link_reading(kin::PcmmGeometry<T>(pp), x);
  }
  void predict_channels(const double* q, const double* p, double* out, Scratch* s) const override {
    eval(q, p, out, s);
  }
  void predict_channels(const double* q, const Jet* p, Jet* out, Scratch* s) const override { eval(q, p, out, s); }

  std::string corrected_yaml(const std::vector<double>& p) const override {
    const YAML::Node root = parse_yaml(text_, file_);
    const YAML::Node ps = root["pcmm"]["parameters"];
    return patch_flat_parameters(text_, ps, params_, p);
  }

 private:
  /// Probe tips in a 200 x 200 x 120 mm box around the home tip, by IK of the nominal machine.
  std::vector<std::vector<double>> random_poses(std::size_t n, std::uint64_t seed) const override {
    std::mt19937_64 rng(seed);
    std::uniform_real_distribution<double> u(-1.0, 1.0);
    kin::PcmmParams<double> pp;
    const auto& info = kin::pcmm_param_info();
    for (std::size_t i = 0; i < kin::kPcmmParamCount; ++i) pp[i] = to_internal(params_[i].nominal, info[i].angle());
    kin::PcmmPose<double> home = kin::pcmm_home_pose();
    kin::PcmmPose<double> x0;
    kin::pcmm_forward<double>(
        pp,
        Eigen::Vector3d(sqrt(170.0 * 170.0 + 400.0 * 400.0) - 350.0, sqrt(170.0 * 170.0 + 400.0 * 400.0) - 350.0,
                        sqrt(170.0 * 170.0 + 400.0 * 400.0) - 350.0),
        home, x0);
    const Eigen::Vector3d c = kin::pcmm_tip(x0, tip_S_);
    std::vector<std::vector<double>> out;
    for (std::size_t tries = 0; out.size() < n && tries < 20 * n + 100; ++tries) {
      const Eigen::Vector3d tip = c + Eigen::Vector3d(100 * u(rng), 100 * u(rng), 60 * u(rng));
      Eigen::Vector3d q;
      if (kin::pcmm_inverse(pp, tip_S_, tip, q)) out.push_back({q[0], q[1], q[2]});
    }
    return out;
  }

 private:
  Eigen::Vector3d tip_S_;
  std::string text_;
};

[[noreturn]] void fail_at(const std::string& file, const YAML::Node& n, const std::string& what) {
  SourceLoc w{file, 0, 0};
  if (n.IsDefined() && n.Mark().line >= 0) {
    w.line = n.Mark().line + 1;
    w.column = n.Mark().column + 1;
  }
  throw InputError(w, what);
}

std::shared_ptr<Model> load_pcmm(const YAML::Node& root, const std::string& path, std::string text) {
  for (const auto& kv : root) {
    const auto k = kv.first.as<std::string>();
    if (k != "name" && k != "description" && k != "kinematics" && k != "pcmm")
      fail_at(path, kv.first,
              fmt::format("'{}': unknown key for kinematics 'pcmm' (expected name, description, kinematics, pcmm)", k));
  }
  const YAML::Node pc = root["pcmm"];
  if (!pc || !pc.IsMap()) fail_at(path, root, "'pcmm': missing section (parameters, tip_mm)");
  std::vector<double> nominal;
  for (const auto& i : kin::pcmm_param_info()) nominal.push_back(i.nominal);
  Eigen::Vector3d tip(0, 0, -100);
  std::string link_name = "link";
  // Every parameter and the probe tip are geometry: a missing one is an error, not a silent default (the link's
  // name alone has one).
  std::vector<bool> given(kin::kPcmmParamCount, false);
  bool tip_given = false, params_given = false;
  YAML::Node params_node;
  for (const auto& kv : pc) {
    const auto k = kv.first.as<std::string>();
    if (k == "parameters") {
      if (!kv.second.IsMap()) fail_at(path, kv.second, "'pcmm.parameters': expected a mapping name: value");
      params_node = kv.first;  // the `parameters:` line, for messages
      params_given = true;
      for (const auto& pv : kv.second) {
        const auto n = pv.first.as<std::string>();
        std::size_t idx = kin::kPcmmParamCount;
        for (std::size_t i = 0; i < kin::kPcmmParamCount; ++i)
          if (kin::pcmm_param_info()[i].name == n) idx = i;
        if (idx == kin::kPcmmParamCount)
          fail_at(path, pv.first, fmt::format("'pcmm.parameters.{}': unknown parameter", n));
        try {
          nominal[idx] = pv.second.as<double>();
        } catch (const YAML::Exception&) {
          fail_at(path, pv.second, fmt::format("'pcmm.parameters.{}': expected a number", n));
        }
        if (!std::isfinite(nominal[idx]))
          fail_at(path, pv.second, fmt::format("'pcmm.parameters.{}': expected a finite number", n));
        given[idx] = true;
      }
    } else if (k == "tip_mm") {
      if (!kv.second.IsSequence() || kv.second.size() != 3)
        fail_at(path, kv.second, "'pcmm.tip_mm': expected [x, y, z]");
      for (std::size_t c = 0; c < 3; ++c) {
        const YAML::Node v = kv.second[c];
        try {
          tip[static_cast<Eigen::Index>(c)] = v.as<double>();
        } catch (const YAML::Exception&) {
          fail_at(path, v, "'pcmm.tip_mm': expected [x, y, z] in mm");
        }
      }
      tip_given = true;
    } else if (k == "link") {
      // The passive link's name: the recording's column is len.<name> (a name as a column's suffix).
      const std::string name = kv.second.IsScalar() ? kv.second.as<std::string>() : std::string();
      const bool ok = !name.empty() && std::all_of(name.begin(), name.end(), [](char ch) {
        return std::isalnum(static_cast<unsigned char>(ch)) || ch == '_' || ch == '-';
      });
      if (!ok) fail_at(path, kv.second, "'pcmm.link': expected a name (letters, digits, '_' or '-')");
      link_name = name;
    } else if (k != "limits") {
      fail_at(path, kv.first, fmt::format("'pcmm.{}': unknown key (expected parameters, tip_mm, limits, link)", k));
    }
  }
  // Located at the line of the section the keys belong in: `pcmm:` or its `parameters:`.
  YAML::Node pcmm_key;
  for (const auto& kv : root)
    if (kv.first.as<std::string>() == "pcmm") pcmm_key = kv.first;
  if (!params_given)
    fail_at(path, pcmm_key, "'pcmm.parameters': missing section (the 26 parameters of the parallel CMM, bz ... gs3)");
  std::string missing;
  for (std::size_t i = 0; i < kin::kPcmmParamCount; ++i)
    if (!given[i]) missing += (missing.empty() ? "" : ", ") + std::string(kin::pcmm_param_info()[i].name);
  if (!missing.empty())
    fail_at(path, params_node,
            fmt::format("'pcmm.parameters': missing required parameter(s) {} (every one of the 26 must be given)",
                        missing));
  if (!tip_given) fail_at(path, pcmm_key, "'pcmm.tip_mm': missing (the probe tip in the stage frame, [x, y, z] mm)");
  return std::make_shared<PcmmCalModel>(nominal, tip, path, std::move(text), link_name);
}

}  // namespace

std::shared_ptr<Model> load_model(const std::string& path) {
  std::string text = read_text(path);
  const YAML::Node root = parse_yaml(text, path);
  if (!root.IsMap()) throw InputError(SourceLoc{path}, "a machine file must be a YAML mapping");
  const std::string kind = root["kinematics"] ? root["kinematics"].as<std::string>() : "serial";
  if (kind == "pcmm") return load_pcmm(root, path, std::move(text));
  const machine::Machine m = machine::load_text(text, path);
  if (m.kind == machine::ModelKind::Serial && m.serial) return std::make_shared<SerialModel>(m, std::move(text));
  if (m.kind == machine::ModelKind::Xmini) {
    const auto k = std::dynamic_pointer_cast<const kin::XminiKinematics>(m.kinematics());
    if (!k) throw InputError(SourceLoc{path}, "kinematics 'xmini': internal model is not an XminiKinematics");
    return std::make_shared<XminiCalModel>(k->model().params(), k->model().limits(), m.default_tool_length_mm, path,
                                           std::move(text));
  }
  throw InputError(SourceLoc{path}, fmt::format("calibration does not support kinematics '{}'", kind));
}

}  // namespace cscam::calib
