#include "cscam/machine/machine.hpp"

#include <fmt/format.h>
#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <set>
#include <sstream>

#include "cscam/core/error.hpp"
#include "cscam/core/units.hpp"

namespace cscam::machine {

// Defined in xmini_loader.cpp: fills a Machine of kind xmini from the file's root node.
void load_xmini(const YAML::Node& root, const std::string& file, Machine& m);

namespace {

/// Reads a YAML node with the file name at hand, so every error can say file:line: key: what.
class Reader {
 public:
  explicit Reader(std::string file) : file_(std::move(file)) {}

  [[noreturn]] void fail(const YAML::Node& n, const std::string& key, const std::string& what) const {
    SourceLoc where{file_, 0, 0};
    if (n.IsDefined() && n.Mark().line >= 0) {
      where.line = n.Mark().line + 1;
      where.column = n.Mark().column + 1;
    }
    throw InputError(where, key.empty() ? what : fmt::format("'{}': {}", key, what));
  }

  /// Rejects keys that are not in `allowed` (a typo must not silently fall back to a default).
  void only_keys(const YAML::Node& map, const std::string& where, std::initializer_list<const char*> allowed) const {
    if (!map.IsMap()) fail(map, where, "expected a mapping");
    std::set<std::string> ok(allowed.begin(), allowed.end());
    for (const auto& kv : map) {
      const auto k = kv.first.as<std::string>();
      if (!ok.count(k)) {
        std::string list;
        for (const auto& a : allowed) list += (list.empty() ? "" : ", ") + std::string(a);
        fail(kv.first, where.empty() ? k : where + "." + k, fmt::format("unknown key (expected one of: {})", list));
      }
    }
  }

  YAML::Node required(const YAML::Node& map, const char* key, const std::string& path) const {
    const YAML::Node n = map[key];
    if (!n.IsDefined() || n.IsNull()) fail(map, path.empty() ? key : path + "." + key, "required key is missing");
    return n;
  }

  double number(const YAML::Node& n, const std::string& key) const {
    if (!n.IsScalar()) fail(n, key, "expected a number");
    try {
      const double v = n.as<double>();
      if (!std::isfinite(v)) fail(n, key, "expected a finite number");
      return v;
    } catch (const YAML::Exception&) {
      fail(n, key, fmt::format("expected a number, got '{}'", n.Scalar()));
    }
  }

  std::string string(const YAML::Node& n, const std::string& key) const {
    if (!n.IsScalar()) fail(n, key, "expected a string");
    return n.as<std::string>();
  }

  bool boolean(const YAML::Node& n, const std::string& key) const {
    try {
      return n.as<bool>();
    } catch (const YAML::Exception&) {
      fail(n, key, fmt::format("expected true or false, got '{}'", n.Scalar()));
    }
  }

  template <int N>
  Eigen::Matrix<double, N, 1> vec(const YAML::Node& n, const std::string& key) const {
    if (!n.IsSequence() || n.size() != N) fail(n, key, fmt::format("expected a list of {} numbers", N));
    Eigen::Matrix<double, N, 1> v;
    for (int i = 0; i < N; ++i) v[i] = number(n[static_cast<size_t>(i)], key);
    return v;
  }

  Eigen::Vector3d unit(const YAML::Node& n, const std::string& key) const {
    Eigen::Vector3d v = vec<3>(n, key);
    if (v.norm() < 1e-9) fail(n, key, "direction must not be the zero vector");
    return v.normalized();
  }

  [[nodiscard]] const std::string& file() const { return file_; }

 private:
  std::string file_;
};

std::mutex& registry_mutex() {
  static std::mutex m;
  return m;
}
std::map<std::string, ModelLoader>& registry() {
  static std::map<std::string, ModelLoader> r;
  return r;
}

void load_post(const Reader& r, const YAML::Node& n, Machine& m) {
  r.only_keys(n, "post",
              {"dialect",
               "tcp",
               "letters",
               "decimals_linear",
               "decimals_rotary",
               "tolerance_mm",
               "axis_tolerance_deg",
               "safe_z_mm",
               "start_branch",
               "branch_rule",
               "program_name",
               "singularity",
               "tcp_form",
               "work_offset",
               "program_number",
               "sequence_numbers",
               "sequence_step",
               "inch",
               "clamp",
               "rotary_output",
               "home_rotaries",
               "arcs",
               "work_plane",
               "swivel_record"});
  PostSettings& p = m.post;
  if (n["dialect"]) p.dialect = r.string(n["dialect"], "post.dialect");
  if (n["tcp"]) p.tcp = r.boolean(n["tcp"], "post.tcp");
  if (n["decimals_linear"])
    p.decimals_linear = static_cast<int>(r.number(n["decimals_linear"], "post.decimals_linear"));
  if (n["decimals_rotary"])
    p.decimals_rotary = static_cast<int>(r.number(n["decimals_rotary"], "post.decimals_rotary"));
  if (p.decimals_linear < 0 || p.decimals_linear > 9)
    r.fail(n["decimals_linear"], "post.decimals_linear", "must be 0..9");
  if (p.decimals_rotary < 0 || p.decimals_rotary > 9)
    r.fail(n["decimals_rotary"], "post.decimals_rotary", "must be 0..9");
  if (n["tolerance_mm"]) p.tolerance_mm = r.number(n["tolerance_mm"], "post.tolerance_mm");
  if (!(p.tolerance_mm > 0))
    r.fail(n["tolerance_mm"], "post.tolerance_mm", fmt::format("must be positive (got {})", p.tolerance_mm));
  if (n["axis_tolerance_deg"]) p.axis_tolerance_deg = r.number(n["axis_tolerance_deg"], "post.axis_tolerance_deg");
  if (!(p.axis_tolerance_deg > 0))
    r.fail(n["axis_tolerance_deg"], "post.axis_tolerance_deg",
           fmt::format("must be positive (got {})", p.axis_tolerance_deg));
  if (n["safe_z_mm"]) p.safe_z_mm = r.number(n["safe_z_mm"], "post.safe_z_mm");
  if (n["program_name"]) p.program_name = r.string(n["program_name"], "post.program_name");
  if (n["tcp_form"]) {
    p.tcp_form = r.string(n["tcp_form"], "post.tcp_form");
    if (p.tcp_form != "angles" && p.tcp_form != "vectors")
      r.fail(n["tcp_form"], "post.tcp_form", fmt::format("expected angles or vectors, got '{}'", p.tcp_form));
  }
  if (n["work_offset"]) {
    std::string w = r.string(n["work_offset"], "post.work_offset");
    for (char& c : w) c = static_cast<char>(std::toupper(static_cast<unsigned char>(c)));
    const bool g5x = w.size() == 3 && w.rfind("G5", 0) == 0 && w[2] >= '4' && w[2] <= '9';
    const bool g541 = w.rfind("G54.1 P", 0) == 0 && w.size() > 7 && std::all_of(w.begin() + 7, w.end(), [](char c) {
                        return std::isdigit(static_cast<unsigned char>(c));
                      });
    if (w == "NONE")
      w.clear();
    else if (!g5x && !g541)
      r.fail(n["work_offset"], "post.work_offset", fmt::format("expected G54..G59, G54.1 P<n> or none, got '{}'", w));
    p.work_offset = w;
  }
  if (n["program_number"]) {
    const double v = r.number(n["program_number"], "post.program_number");
    if (!(v >= 0 && v <= 99999 && v == std::floor(v)))
      r.fail(n["program_number"], "post.program_number", "must be an integer 0..99999");
    p.program_number = static_cast<int>(v);
  }
  if (n["sequence_numbers"]) p.sequence_numbers = r.boolean(n["sequence_numbers"], "post.sequence_numbers");
  if (n["sequence_step"]) {
    const double v = r.number(n["sequence_step"], "post.sequence_step");
    if (!(v >= 1 && v <= 1000 && v == std::floor(v)))
      r.fail(n["sequence_step"], "post.sequence_step", "must be an integer 1..1000");
    p.sequence_step = static_cast<int>(v);
  }
  if (n["inch"]) p.inch = r.boolean(n["inch"], "post.inch");
  if (n["home_rotaries"]) p.home_rotaries = r.boolean(n["home_rotaries"], "post.home_rotaries");
  if (n["arcs"]) p.arcs = r.boolean(n["arcs"], "post.arcs");
  if (n["work_plane"]) {
    p.work_plane = r.string(n["work_plane"], "post.work_plane");
    if (p.work_plane != "tilted" && p.work_plane != "machine")
      r.fail(n["work_plane"], "post.work_plane", fmt::format("expected tilted or machine, got '{}'", p.work_plane));
  }
  if (n["swivel_record"]) {
    p.swivel_record = r.string(n["swivel_record"], "post.swivel_record");
    // Written inside a quoted string in CYCLE800: a name, no quote or control character, as the control allows.
    const bool ok =
        !p.swivel_record.empty() && p.swivel_record.size() <= 32 &&
        std::all_of(p.swivel_record.begin(), p.swivel_record.end(), [](char ch) {
          return (ch >= 'A' && ch <= 'Z') || (ch >= 'a' && ch <= 'z') || (ch >= '0' && ch <= '9') || ch == '_';
        });
    if (!ok)
      r.fail(n["swivel_record"], "post.swivel_record",
             fmt::format("expected a name of 1-32 letters, digits or '_', got '{}'", p.swivel_record));
  }
  if (n["rotary_output"]) {
    p.rotary_output = r.string(n["rotary_output"], "post.rotary_output");
    if (p.rotary_output != "absolute" && p.rotary_output != "shortest")
      r.fail(n["rotary_output"], "post.rotary_output",
             fmt::format("expected absolute or shortest, got '{}'", p.rotary_output));
  }
  if (const YAML::Node cl = n["clamp"]) {
    if (!cl.IsMap()) r.fail(cl, "post.clamp", "expected a mapping axis: [clamp M-code, unclamp M-code]");
    for (const auto& kv : cl) {
      const auto ax = kv.first.as<std::string>();
      const int i = m.axis_index(ax);
      if (i < 0 || !m.axes[static_cast<size_t>(i)].rotary())
        r.fail(kv.first, "post.clamp." + ax, "not a rotary axis of this machine");
      if (!kv.second.IsSequence() || kv.second.size() != 2)
        r.fail(kv.second, "post.clamp." + ax, "expected [clamp M-code, unclamp M-code], e.g. [M10, M11]");
      std::array<std::string, 2> codes{r.string(kv.second[0], "post.clamp." + ax),
                                       r.string(kv.second[1], "post.clamp." + ax)};
      for (const auto& c : codes)
        if (c.size() < 2 || (c[0] != 'M' && c[0] != 'm') ||
            !std::all_of(c.begin() + 1, c.end(), [](char d) { return std::isdigit(static_cast<unsigned char>(d)); }))
          r.fail(kv.second, "post.clamp." + ax, fmt::format("'{}' is not an M-code", c));
      p.clamp[ax] = codes;
    }
  }
  if (const YAML::Node sg = n["singularity"]) {
    if (!sg.IsMap()) r.fail(sg, "post.singularity", "expected a mapping with flip and retract_mm");
    r.only_keys(sg, "post.singularity", {"flip", "retract_mm"});
    auto& q = p.singularity;
    if (sg["flip"]) {
      q.flip = r.string(sg["flip"], "post.singularity.flip");
      if (q.flip != "auto" && q.flip != "retract" && q.flip != "refuse")
        r.fail(sg["flip"], "post.singularity.flip", fmt::format("expected auto, retract or refuse, got '{}'", q.flip));
    }
    if (sg["retract_mm"]) {
      q.retract_mm = r.number(sg["retract_mm"], "post.singularity.retract_mm");
      if (!(q.retract_mm > 0))
        r.fail(sg["retract_mm"], "post.singularity.retract_mm", fmt::format("must be positive (got {})", q.retract_mm));
    }
  }
  if (n["branch_rule"]) {
    p.branch_rule = r.string(n["branch_rule"], "post.branch_rule");
    if (p.branch_rule != "start" && p.branch_rule != "always")
      r.fail(n["branch_rule"], "post.branch_rule", fmt::format("expected start or always, got '{}'", p.branch_rule));
  }
  if (n["start_branch"]) {
    p.start_branch = r.string(n["start_branch"], "post.start_branch");
    const auto& s = p.start_branch;
    bool ok = s == "nearest_home";
    for (const char* pre : {"positive:", "negative:"}) {
      if (s.rfind(pre, 0) == 0) {
        const std::string ax = s.substr(std::string(pre).size());
        const int i = m.axis_index(ax);
        if (i < 0 || !m.axes[static_cast<size_t>(i)].rotary())
          r.fail(n["start_branch"], "post.start_branch", fmt::format("'{}' is not a rotary axis of this machine", ax));
        ok = true;
      }
    }
    if (!ok)
      r.fail(n["start_branch"], "post.start_branch", "expected nearest_home, positive:<axis> or negative:<axis>");
  }
  if (n["letters"]) {
    const YAML::Node l = n["letters"];
    if (!l.IsMap()) r.fail(l, "post.letters", "expected a mapping axis: letter");
    for (const auto& kv : l) {
      const auto ax = kv.first.as<std::string>();
      const int i = m.axis_index(ax);
      if (i < 0) r.fail(kv.first, "post.letters." + ax, "no such axis in this machine");
      const auto letter = r.string(kv.second, "post.letters." + ax);
      if (letter.size() != 1 || !std::isalpha(static_cast<unsigned char>(letter[0])))
        r.fail(kv.second, "post.letters." + ax, "expected a single letter");
      p.letters[static_cast<size_t>(i)] = std::string(1, static_cast<char>(std::toupper(letter[0])));
    }
  }
}

SourceLoc loc(const Reader& r, const YAML::Node& n) {
  SourceLoc where{r.file()};
  if (n.IsDefined() && n.Mark().line >= 0) {
    where.line = n.Mark().line + 1;
    where.column = n.Mark().column + 1;
  }
  return where;
}

void load_bodies(const Reader& r, const YAML::Node& list, Machine& m) {
  if (!list.IsSequence()) r.fail(list, "geometry.bodies", "expected a list of bodies");
  const std::filesystem::path dir = std::filesystem::path(r.file()).parent_path();
  std::set<std::string> names;
  for (std::size_t i = 0; i < list.size(); ++i) {
    const YAML::Node n = list[i];
    const std::string key = fmt::format("geometry.bodies[{}]", i);
    r.only_keys(n, key, {"name", "attach", "box", "cylinder", "mesh", "source"});
    MachineBody b;
    b.where = loc(r, n);
    b.name = r.string(r.required(n, "name", key), key + ".name");
    if (b.name.empty() || !names.insert(b.name).second)
      r.fail(n["name"], key + ".name", fmt::format("body name '{}' is empty or used twice", b.name));
    // Provenance is required: a dimension nobody can trace is a collision answer nobody can trust.
    b.source = r.string(r.required(n, "source", key), key + ".source");
    if (b.source.empty()) r.fail(n["source"], key + ".source", "say where the dimensions come from");
    const std::string attach = r.string(r.required(n, "attach", key), key + ".attach");
    if (attach != "base") {
      b.axis = m.axis_index(attach);
      if (b.axis < 0)
        r.fail(n["attach"], key + ".attach", fmt::format("no axis '{}' in this machine (or 'base')", attach));
    }
    if (!m.serial) r.fail(n, key, "machine bodies are supported on serial kinematics only");
    const auto& g = *m.serial;
    auto in = [&](const std::vector<int>& chain) {
      return std::find(chain.begin(), chain.end(), b.axis) != chain.end();
    };
    b.side = b.axis < 0 ? BodySide::Base : in(g.head_chain) ? BodySide::Head : BodySide::Table;
    if (b.axis >= 0 && !in(g.head_chain) && !in(g.table_chain))
      r.fail(n["attach"], key + ".attach", fmt::format("axis '{}' is in neither chain", attach));
    const int shapes = (n["box"] ? 1 : 0) + (n["cylinder"] ? 1 : 0) + (n["mesh"] ? 1 : 0);
    if (shapes != 1) r.fail(n, key, "give exactly one of box, cylinder, mesh");
    if (const YAML::Node box = n["box"]) {
      r.only_keys(box, key + ".box", {"min_mm", "max_mm"});
      b.shape = BodyShape::Box;
      b.min_mm = r.vec<3>(r.required(box, "min_mm", key + ".box"), key + ".box.min_mm");
      b.max_mm = r.vec<3>(r.required(box, "max_mm", key + ".box"), key + ".box.max_mm");
      if (!((b.max_mm - b.min_mm).array() > 0.0).all())
        r.fail(box, key + ".box", "min_mm must be below max_mm on every axis");
    } else if (const YAML::Node cyl = n["cylinder"]) {
      r.only_keys(cyl, key + ".cylinder", {"from_mm", "to_mm", "diameter_mm"});
      b.shape = BodyShape::Cylinder;
      b.from_mm = r.vec<3>(r.required(cyl, "from_mm", key + ".cylinder"), key + ".cylinder.from_mm");
      b.to_mm = r.vec<3>(r.required(cyl, "to_mm", key + ".cylinder"), key + ".cylinder.to_mm");
      b.diameter_mm = r.number(r.required(cyl, "diameter_mm", key + ".cylinder"), key + ".cylinder.diameter_mm");
      if (!(b.diameter_mm > 0.0)) r.fail(cyl["diameter_mm"], key + ".cylinder.diameter_mm", "must be positive");
      if ((b.to_mm - b.from_mm).norm() <= 0.0) r.fail(cyl, key + ".cylinder", "from_mm and to_mm must differ");
    } else {
      const YAML::Node mesh = n["mesh"];
      r.only_keys(mesh, key + ".mesh", {"file", "scale"});
      b.shape = BodyShape::Mesh;
      std::filesystem::path p = r.string(r.required(mesh, "file", key + ".mesh"), key + ".mesh.file");
      if (p.is_relative()) p = dir / p;
      if (!std::filesystem::exists(p))
        r.fail(mesh["file"], key + ".mesh.file", fmt::format("mesh file '{}' not found", p.string()));
      b.mesh = p.string();
      if (mesh["scale"]) {
        b.mesh_scale = r.number(mesh["scale"], key + ".mesh.scale");
        if (!(b.mesh_scale > 0.0)) r.fail(mesh["scale"], key + ".mesh.scale", "must be positive");
      }
    }
    m.geometry.bodies.push_back(std::move(b));
  }
}

void load_geometry(const Reader& r, const YAML::Node& n, Machine& m) {
  r.only_keys(n, "geometry",
              {"bodies", "head_mesh", "table_mesh", "holder_diameter_mm", "holder_length_mm", "spindle_diameter_mm",
               "spindle_length_mm"});
  if (n["bodies"]) load_bodies(r, n["bodies"], m);
  const std::filesystem::path dir = std::filesystem::path(r.file()).parent_path();
  auto mesh = [&](const char* key, std::string& out) {
    if (!n[key]) return;
    std::filesystem::path p = r.string(n[key], std::string("geometry.") + key);
    if (p.is_relative()) p = dir / p;
    if (!std::filesystem::exists(p))
      r.fail(n[key], std::string("geometry.") + key, fmt::format("mesh file '{}' not found", p.string()));
    out = p.string();
  };
  mesh("head_mesh", m.geometry.head_mesh);
  mesh("table_mesh", m.geometry.table_mesh);
  auto num = [&](const char* key, double& out) {
    if (!n[key]) return;
    out = r.number(n[key], std::string("geometry.") + key);
    if (out < 0) r.fail(n[key], std::string("geometry.") + key, "must not be negative");
  };
  num("holder_diameter_mm", m.geometry.holder_diameter_mm);
  num("holder_length_mm", m.geometry.holder_length_mm);
  num("spindle_diameter_mm", m.geometry.spindle_diameter_mm);
  num("spindle_length_mm", m.geometry.spindle_length_mm);
}

void load_serial(const Reader& r, const YAML::Node& root, Machine& m) {
  kin::SerialGeometry<double> g;
  const YAML::Node axes = r.required(root, "axes", "");
  if (!axes.IsSequence() || axes.size() != 5) r.fail(axes, "axes", "expected a list of exactly 5 axes");
  for (size_t i = 0; i < 5; ++i) {
    const YAML::Node a = axes[i];
    const std::string path = fmt::format("axes[{}]", i);
    r.only_keys(a, path,
                {"name", "type", "side", "direction", "pivot_mm", "limits", "max_feed", "max_accel", "cyclic", "prefer",
                 "offset"});
    kin::AxisInfo info;
    info.name = r.string(r.required(a, "name", path), path + ".name");
    for (auto& ch : info.name) ch = static_cast<char>(std::tolower(static_cast<unsigned char>(ch)));
    if (m.axis_index(info.name) >= 0)
      r.fail(a["name"], path + ".name", fmt::format("axis '{}' is defined twice", info.name));
    const std::string type = r.string(r.required(a, "type", path), path + ".type");
    if (type == "linear")
      info.type = kin::AxisType::Linear;
    else if (type == "rotary")
      info.type = kin::AxisType::Rotary;
    else
      r.fail(a["type"], path + ".type", fmt::format("expected linear or rotary, got '{}'", type));
    const double scale = info.rotary() ? kPi / 180.0 : 1.0;
    const Eigen::Vector2d lim = r.vec<2>(r.required(a, "limits", path), path + ".limits");
    if (!(lim[0] < lim[1])) r.fail(a["limits"], path + ".limits", "expected [min, max] with min < max");
    info.min = lim[0] * scale;
    info.max = lim[1] * scale;
    if (a["max_feed"]) {
      info.max_feed = r.number(a["max_feed"], path + ".max_feed") * scale;
      if (!(info.max_feed > 0))
        r.fail(a["max_feed"], path + ".max_feed", fmt::format("must be positive (got {})", a["max_feed"].Scalar()));
    }
    if (a["max_accel"]) {
      info.max_accel = r.number(a["max_accel"], path + ".max_accel") * scale;
      if (!(info.max_accel > 0))
        r.fail(a["max_accel"], path + ".max_accel", fmt::format("must be positive (got {})", a["max_accel"].Scalar()));
    }
    if (a["cyclic"]) info.cyclic = r.boolean(a["cyclic"], path + ".cyclic");
    if (info.cyclic && !info.rotary()) r.fail(a["cyclic"], path + ".cyclic", "only a rotary axis can be cyclic");
    if (info.cyclic && info.max - info.min < 2.0 * kPi - 1e-9)
      r.fail(a["cyclic"], path + ".cyclic",
             fmt::format("a cyclic axis turns on through whole turns, but its limits [{}, {}] deg span less than one",
                         lim[0], lim[1]));

    kin::JointGeometry<double>& j = g.joints[i];
    j.type = info.type;
    j.direction = r.unit(r.required(a, "direction", path), path + ".direction");
    if (a["pivot_mm"]) {
      if (!info.rotary()) r.fail(a["pivot_mm"], path + ".pivot_mm", "only a rotary axis has a pivot");
      j.pivot_mm = r.vec<3>(a["pivot_mm"], path + ".pivot_mm");
    } else if (info.rotary()) {
      // No silent origin: a wrong pivot moves the tip by the pivot's distance from it.
      r.fail(a, path + ".pivot_mm", "required key is missing (a rotary axis needs the point its axis passes through)");
    }
    if (a["offset"]) j.offset = r.number(a["offset"], path + ".offset") * scale;
    const std::string side = r.string(r.required(a, "side", path), path + ".side");
    if (side == "table")
      j.side = kin::Side::Table;
    else if (side == "head")
      j.side = kin::Side::Head;
    else
      r.fail(a["side"], path + ".side", fmt::format("expected table or head, got '{}'", side));
    if (a["prefer"]) {
      const std::string pref = r.string(a["prefer"], path + ".prefer");
      if (pref != "positive" && pref != "negative")
        r.fail(a["prefer"], path + ".prefer", "expected positive or negative");
      m.preferred_sign[info.name] = pref == "positive" ? 1 : -1;
    }
    m.axes.push_back(info);
  }
  // Chains: from the base outward. Both are required: the order of the axes on a side decides the kinematics, so
  // it is not guessed from the file order.
  const YAML::Node chains = root["chains"];
  if (!chains || chains.IsNull())
    r.fail(root, "chains",
           "required key is missing (expected chains: {table: [...], head: [...]}, each axis on its side, from the "
           "machine base outward)");
  r.only_keys(chains, "chains", {"table", "head"});
  for (const char* key : {"table", "head"})
    if (!chains[key]) r.fail(chains, std::string("chains.") + key, "required key is missing (use [] for no axes)");
  auto chain = [&](const char* key, kin::Side side, std::vector<int>& out) {
    if (root["chains"] && root["chains"][key]) {
      const YAML::Node c = root["chains"][key];
      if (!c.IsSequence()) r.fail(c, std::string("chains.") + key, "expected a list of axis names");
      for (const auto& e : c) {
        const std::string nm = r.string(e, std::string("chains.") + key);
        const int idx = m.axis_index(nm);
        if (idx < 0) r.fail(e, std::string("chains.") + key, fmt::format("no axis named '{}'", nm));
        if (g.joints[static_cast<size_t>(idx)].side != side)
          r.fail(e, std::string("chains.") + key, fmt::format("axis '{}' is declared on the other side", nm));
        out.push_back(idx);
      }
    } else {
      for (int i = 0; i < 5; ++i)
        if (g.joints[static_cast<size_t>(i)].side == side) out.push_back(i);
    }
  };
  chain("table", kin::Side::Table, g.table_chain);
  chain("head", kin::Side::Head, g.head_chain);
  if (g.table_chain.size() + g.head_chain.size() != 5)
    r.fail(root["chains"], "chains", "every axis must appear exactly once in chains.table or chains.head");
  if (root["tool_direction"]) g.tool_direction_home = r.unit(root["tool_direction"], "tool_direction");
  if (root["spindle_gauge_mm"]) g.gauge_home_mm = r.vec<3>(root["spindle_gauge_mm"], "spindle_gauge_mm");
  if (root["part_origin_mm"]) g.part_origin_home_mm = r.vec<3>(root["part_origin_mm"], "part_origin_mm");
  try {
    // Validate once now so that a bad file fails at load time, not at first use.
    kin::SerialKinematics probe(g, m.axes);
  } catch (const std::invalid_argument& e) {
    r.fail(axes, "axes", e.what());
  }
  m.serial = g;
  const auto axes_copy = m.axes;
  m.make_kinematics = [g, axes_copy](double tool_length_mm) -> std::shared_ptr<const kin::Kinematics> {
    kin::SerialGeometry<double> gg = g;
    gg.tool_length_mm = tool_length_mm;
    return std::make_shared<kin::SerialKinematics>(gg, axes_copy);
  };
}

/// yaml-cpp keeps every pair of a mapping but `map[key]` finds only the first: a repeated key would be silently
/// ignored (e.g. a second `tolerance_mm:` that the author thinks is in force). Every mapping is checked.
void reject_duplicate_keys(const Reader& r, const YAML::Node& n, const std::string& path) {
  if (n.IsMap()) {
    std::map<std::string, int> seen;  // key -> 1-based line of its first use
    for (const auto& kv : n) {
      if (!kv.first.IsScalar()) continue;
      const std::string k = kv.first.Scalar();
      const std::string key = path.empty() ? k : path + "." + k;
      const auto [it, fresh] = seen.emplace(k, kv.first.Mark().line + 1);
      if (!fresh) r.fail(kv.first, key, fmt::format("duplicate key (already given at line {})", it->second));
      reject_duplicate_keys(r, kv.second, key);
    }
  } else if (n.IsSequence()) {
    for (std::size_t i = 0; i < n.size(); ++i) reject_duplicate_keys(r, n[i], fmt::format("{}[{}]", path, i));
  }
}

/// Every axis needs its own letter, and a letter that G-code reads as an axis: a second 'A' would command two
/// axes with one word, and 'F' or 'S' would be read as a feed or a spindle speed.
void check_letters(const Reader& r, const YAML::Node& root, const Machine& m) {
  const YAML::Node post = root["post"];
  const YAML::Node letters = post && post.IsMap() ? post["letters"] : YAML::Node(YAML::NodeType::Undefined);
  const bool given = letters.IsDefined() && letters.IsMap();
  auto node_of = [&](std::size_t i) {
    if (given && letters[m.axes[i].name]) return letters[m.axes[i].name];
    if (given) return letters;
    const YAML::Node axes = root["axes"];
    return axes && axes.IsSequence() && i < axes.size() ? axes[i] : root;
  };
  for (std::size_t i = 0; i < m.axes.size() && i < 5; ++i) {
    const std::string& l = m.post.letters[i];
    const std::string key = "post.letters." + m.axes[i].name;
    if (l.size() != 1 || std::string_view("XYZABCUVW").find(l[0]) == std::string_view::npos)
      r.fail(node_of(i), key,
             fmt::format("letter '{}' of axis '{}' is not an axis word (expected one of X Y Z A B C U V W{})", l,
                         m.axes[i].name, given ? "" : "; give post.letters"));
    for (std::size_t j = 0; j < i; ++j)
      if (m.post.letters[j] == l)
        r.fail(node_of(i), key,
               fmt::format("duplicate axis letter '{}': axes '{}' and '{}' would share it (expected one letter per "
                           "axis{})",
                           l, m.axes[j].name, m.axes[i].name, given ? "" : "; give post.letters"));
  }
}

/// Remembers where every key of the file is, so that later errors about a machine-file value (a dialect the post
/// does not know, a safe plane the tool cannot reach) can name the machine file's line.
void record_locations(const std::string& file, const YAML::Node& n, const std::string& path,
                      std::map<std::string, SourceLoc>& out) {
  if (n.IsMap()) {
    for (const auto& kv : n) {
      if (!kv.first.IsScalar()) continue;
      const std::string key = path.empty() ? kv.first.Scalar() : path + "." + kv.first.Scalar();
      out.emplace(key, SourceLoc{file, kv.first.Mark().line + 1, kv.first.Mark().column + 1});
      record_locations(file, kv.second, key, out);
    }
  } else if (n.IsSequence()) {
    for (std::size_t i = 0; i < n.size(); ++i) {
      const std::string key = fmt::format("{}[{}]", path, i);
      out.emplace(key, SourceLoc{file, n[i].Mark().line + 1, n[i].Mark().column + 1});
      record_locations(file, n[i], key, out);
    }
  }
}

Machine load_node(const YAML::Node& root, const std::string& name) {
  const Reader r(name);
  if (!root.IsMap()) r.fail(root, "", "a machine file must be a YAML mapping");
  if (root["kinematics"] && root["kinematics"].IsScalar() && root["kinematics"].Scalar() == "pcmm")
    r.fail(root["kinematics"], "kinematics",
           "a 'pcmm' file describes seed 001's parallel coordinate-measuring machine: `cscam calibrate` reads it, "
           "but it has no 5-axis machine-tool kinematics to post, plan, verify or simulate with");
  r.only_keys(root, "",
              {"name", "description", "kinematics", "axes", "chains", "tool_direction", "spindle_gauge_mm",
               "part_origin_mm", "default_tool_length_mm", "post", "geometry", "xmini",
               "effects"});  // effects: identified by `cscam diagnose`, parsed and applied by the sim module
  Machine m;
  m.file = name;
  m.name = r.string(r.required(root, "name", ""), "name");
  if (root["description"]) m.description = r.string(root["description"], "description");
  const std::string kind = root["kinematics"] ? r.string(root["kinematics"], "kinematics") : "serial";
  if (root["default_tool_length_mm"]) {
    m.default_tool_length_mm = r.number(root["default_tool_length_mm"], "default_tool_length_mm");
    if (m.default_tool_length_mm < 0)
      r.fail(root["default_tool_length_mm"], "default_tool_length_mm", "must not be negative");
  }
  if (kind == "serial") {
    m.kind = ModelKind::Serial;
    load_serial(r, root, m);
  } else if (kind == "xmini") {
    m.kind = ModelKind::Xmini;
    load_xmini(root, name, m);
  } else {
    ModelLoader loader;
    {
      std::lock_guard<std::mutex> lock(registry_mutex());
      auto it = registry().find(kind);
      if (it != registry().end()) loader = it->second;
    }
    if (!loader)
      r.fail(root["kinematics"], "kinematics",
             fmt::format("unknown kinematics '{}' (expected serial, xmini or a registered kind)", kind));
    try {
      loader(&root, m);
    } catch (const InputError& e) {
      if (!e.where().file.empty()) throw;
      r.fail(root["kinematics"], "", e.what());
    }
  }
  for (size_t i = 0; i < 5; ++i)
    if (m.post.letters[i].empty()) {
      std::string l = m.axes[i].name.substr(0, 1);
      l[0] = static_cast<char>(std::toupper(static_cast<unsigned char>(l[0])));
      m.post.letters[i] = l;
    }
  if (root["post"]) load_post(r, root["post"], m);
  // The safe Z of a machine with a Z slide is a value of that slide (a PKM's is a plane of the part frame).
  if (kind == "serial" && std::isfinite(m.post.safe_z_mm))
    for (const auto& a : m.axes)
      if (!a.rotary() && a.name == "z" && (m.post.safe_z_mm < a.min || m.post.safe_z_mm > a.max))
        r.fail(root["post"]["safe_z_mm"], "post.safe_z_mm",
               fmt::format("{} mm is outside the travel of z [{}, {}] mm", m.post.safe_z_mm, a.min, a.max));
  // The machines we post for; a registered model (a measuring machine, say) may not write G-code at all.
  if (kind == "serial" || kind == "xmini") check_letters(r, root, m);
  if (root["geometry"]) load_geometry(r, root["geometry"], m);
  record_locations(name, root, "", m.key_locations);
  return m;
}

}  // namespace

SourceLoc Machine::where(const std::string& key) const {
  const auto it = key_locations.find(key);
  return it != key_locations.end() ? it->second : SourceLoc{file};
}

int Machine::axis_index(const std::string& axis_name) const {
  for (size_t i = 0; i < axes.size(); ++i)
    if (axes[i].name == axis_name) return static_cast<int>(i);
  return -1;
}

Machine load_text(const std::string& yaml, const std::string& name) {
  // One machine file at a time in the process: ThreadSanitizer reports a race inside yaml-cpp 0.7's
  // convert<bool>::decode when two threads convert at once (batch jobs loading their machines). Loading is rare and
  // takes milliseconds, so a lock costs nothing.
  static std::mutex yaml_mu;
  const std::lock_guard<std::mutex> yaml_lock(yaml_mu);
  YAML::Node root;
  try {
    root = YAML::Load(yaml);
  } catch (const YAML::ParserException& e) {
    throw InputError(SourceLoc{name, e.mark.line + 1, e.mark.column + 1}, "YAML syntax error: " + e.msg);
  }
  // Any YAML value of the wrong shape that a specific check did not catch (e.g. a mapping key that is a
  // sequence) still becomes an error with the file, line and column (found by fuzz/machine_fuzz).
  try {
    reject_duplicate_keys(Reader(name), root, "");
    return load_node(root, name);
  } catch (const YAML::Exception& e) {
    throw InputError(SourceLoc{name, e.mark.line + 1, e.mark.column + 1},
                     "unexpected YAML value: " + (e.msg.empty() ? std::string(e.what()) : e.msg));
  }
}

Machine load(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw InputError(SourceLoc{path}, "cannot open machine file");
  std::stringstream ss;
  ss << in.rdbuf();
  return load_text(ss.str(), path);
}

void register_model(const std::string& kind, ModelLoader loader) {
  std::lock_guard<std::mutex> lock(registry_mutex());
  registry()[kind] = std::move(loader);
}

}  // namespace cscam::machine
