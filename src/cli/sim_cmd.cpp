// `cscam simulate` (program + machine + injected effects -> recording) and `cscam diagnose` (recording ->
// findings, report, machine file with effects, LinuxCNC compensation).
#include "sim_cmd.hpp"

#include <fmt/format.h>
#include <fmt/ranges.h>
#include <yaml-cpp/yaml.h>

#include <cctype>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <memory>
#include <sstream>
#include <string_view>

#include "cscam/calib/model.hpp"
#include "cscam/core/atomic_file.hpp"
#include "cscam/core/error.hpp"
#include "cscam/diagnose/diagnose.hpp"
#include "cscam/machine/machine.hpp"
#include "cscam/nc/reader.hpp"
#include "cscam/report/letters.hpp"
#include "cscam/report/verify.hpp"
#include "cscam/sim/simulate.hpp"
#include "plan_cmd.hpp"
#include "validators.hpp"

namespace fs = std::filesystem;

namespace cscam::cli {

namespace {

struct SimArgs {
  std::string program, machine, out, channels, note;  // channels: empty for the machine's default
  double rate = 1000, accel = 2000, tool_length = -1, rpm = 0;
  int flutes = 0, decimals = 6;
  unsigned seed = 1;
  std::vector<std::string> inject, noise;
  std::string temperatures;
};

struct DiagArgs {
  std::string rec, machine, svg, write_model;
  bool json = false;
  std::size_t max_fit = 60000;
};

std::vector<std::string> split(const std::string& s, char sep) {
  std::vector<std::string> out;
  std::stringstream ss(s);
  std::string item;
  while (std::getline(ss, item, sep))
    if (!item.empty()) out.push_back(item);
  return out;
}

/// Whether `path` holds NC (G-code) rather than CL data. By the extension where it is one of the usual ones; otherwise
/// (a Siemens .mpf, a Heidenhain .h, a .txt) by the first statement: a CL file's are `KEYWORD/...`, `$$` comments or
/// bare keywords such as MULTAX and FINI, and anything else is taken for NC, whose reader names any line it cannot
/// read.
bool is_nc(const std::string& path) {
  std::string ext = fs::path(path).extension().string();
  for (auto& c : ext) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  if (ext == ".ngc" || ext == ".nc" || ext == ".tap" || ext == ".gcode" || ext == ".cnc") return true;
  if (ext == ".cls" || ext == ".cl" || ext == ".apt" || ext == ".aptsource" || ext == ".clsf") return false;
  std::ifstream in(path);
  std::string line;
  for (int n = 0; n < 200 && std::getline(in, line); ++n) {
    const std::size_t b = line.find_first_not_of(" \t\r");
    if (b == std::string::npos) continue;
    const std::string_view st = std::string_view(line).substr(b);
    if (st.rfind("$$", 0) == 0) return false;
    std::size_t k = 0;
    while (k < st.size() && (std::isalpha(static_cast<unsigned char>(st[k])) != 0 || st[k] == '_')) ++k;
    if (k == 0) return true;  // '%', ';', '(', a digit: G-code
    std::size_t after = k;
    while (after < st.size() && (st[after] == ' ' || st[after] == '\t')) ++after;
    if (after < st.size() && st[after] == '/') return false;  // GOTO/, TLDATA/, TOOL PATH/ (after its first word)
    std::string word(st.substr(0, k));
    for (auto& c : word) c = static_cast<char>(std::toupper(static_cast<unsigned char>(c)));
    if (word == "TOOL") return st.find("PATH/") == std::string_view::npos;  // NX's TOOL PATH/; Heidenhain's TOOL CALL
    return !(word == "MULTAX" || word == "FINI" || word == "PARTNO" || word == "RAPID" || word == "PPRINT");
  }
  return true;
}

std::string read_text(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw InputError(SourceLoc{path}, "cannot open");
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

/// Whether the machine file is seed 001's parallel CMM (`kinematics: pcmm`), which only the calibration model knows.
bool is_pcmm_file(const std::string& path) {
  try {
    const YAML::Node root = YAML::LoadFile(path);
    return root.IsMap() && root["kinematics"] && root["kinematics"].IsScalar() && root["kinematics"].Scalar() == "pcmm";
  } catch (const YAML::Exception&) {
    return false;  // machine::load names what is wrong
  }
}

std::vector<sim::NoiseSpec> parse_noise(const std::vector<std::string>& specs) {
  std::vector<sim::NoiseSpec> out;
  for (const auto& s : specs) {
    const auto c = s.find(':');
    if (c == std::string::npos) throw InputError(fmt::format("--noise '{}': expected GROUP:SIGMA, e.g. tip:0.001", s));
    sim::NoiseSpec ns;
    ns.group = s.substr(0, c);
    try {
      size_t used = 0;
      ns.sigma = std::stod(s.substr(c + 1), &used);
      if (used != s.size() - c - 1) throw std::invalid_argument(s);
    } catch (const std::exception&) {
      throw InputError(fmt::format("--noise '{}': expected a number after the colon", s));
    }
    if (!(ns.sigma >= 0) || !std::isfinite(ns.sigma))
      throw InputError(fmt::format("--noise '{}': sigma must be a finite number, not negative", s));
    out.push_back(ns);
  }
  return out;
}

/// The parallel CMM: a static pose list measured with its calibration model (geometric deviations only).
int simulate_pcmm(const SimArgs& a, const std::string& mpath) {
  const auto model = calib::load_model(mpath);
  std::string ext = fs::path(a.program).extension().string();
  for (auto& c : ext) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  if (ext != ".csv")
    throw InputError(
        SourceLoc{a.program},
        "machine '" + mpath +
            "' is a parallel coordinate-measuring machine (kinematics: pcmm): it measures static poses, so "
            "give a static pose list (e.g. from `cscam calibrate --design N --machine pcmm`), not a program");
  std::vector<std::pair<std::string, double>> values;
  for (const auto& s : a.inject) {
    if (s.rfind("geometric:", 0) != 0)
      throw InputError(
          fmt::format("--inject '{}': a static measurement of the parallel CMM shows geometric deviations "
                      "only (geometric:NAME=VALUE, e.g. geometric:l2=350.05)",
                      s));
    for (auto& kv : sim::parse_geometric_values(s)) {
      (void)model->index(kv.first);  // an unknown name is an error listing the model's parameters
      values.push_back(std::move(kv));
    }
  }
  if (!a.temperatures.empty()) throw InputError("--temperatures: a static measurement has no time to follow");
  const sim::Recording poses = sim::read_recording(a.program);
  if (poses.meta_value("kind").value_or("") != "static")
    throw InputError(poses.meta_value("kind") ? poses.meta_loc("kind") : SourceLoc{a.program, 1, 0},
                     "a CSV input must be a static pose list ('# kind: static' with cmd.<axis> columns)");
  const auto& axes = model->axis_names();
  std::vector<int> col(axes.size());
  for (std::size_t j = 0; j < axes.size(); ++j) {
    col[j] = poses.column("cmd." + axes[j]);
    if (col[j] < 0)
      throw InputError(SourceLoc{a.program, poses.header_line, 0},
                       fmt::format("missing column cmd.{} for axis {} of machine {}", axes[j], axes[j], mpath));
  }
  std::vector<std::vector<double>> q(poses.rows(), std::vector<double>(axes.size()));
  for (std::size_t i = 0; i < poses.rows(); ++i)
    for (std::size_t j = 0; j < axes.size(); ++j) {
      q[i][j] = poses.data[static_cast<std::size_t>(col[j])][i];
      if (!std::isfinite(q[i][j]))
        throw InputError(SourceLoc{a.program, poses.row_line[i], 0},
                         fmt::format("cmd.{} is empty: every pose needs every axis", axes[j]));
    }
  if (q.empty()) throw InputError(SourceLoc{a.program}, "no poses in the file");
  sim::SimulateOptions so;
  // The CMM's own groups: the probe tip and the passive link's gauge (the default tip,enc has no encoders here).
  so.channels = a.channels.empty() ? std::vector<std::string>{"tip", "len"} : split(a.channels, ',');
  so.noise = parse_noise(a.noise);
  so.seed = a.seed;
  so.note = a.note;
  so.machine_ref = a.machine;
  sim::Recording rec;
  try {
    rec = sim::simulate_static(*model, q, values, so);
  } catch (const InputError& e) {
    throw InputError(SourceLoc{a.program}, e.what());
  }
  const std::string out = a.out.empty() ? fs::path(a.program).stem().string() + ".rec.csv" : a.out;
  write_file_atomically(out, [&](std::ostream& os) { sim::write_recording(os, rec, a.decimals); });
  std::cout << fmt::format("wrote {} ({} static poses, channels {}, {} geometric deviation(s))\n", out, rec.rows(),
                           fmt::join(so.channels, ","), values.size());
  return 0;
}

int cmd_simulate(const SimArgs& a) {
  const std::string mpath = resolve_machine(a.machine);
  if (is_pcmm_file(mpath)) return simulate_pcmm(a, mpath);
  const machine::Machine m = machine::load(mpath);
  auto machine_fx = sim::load_machine_effects(mpath, m);
  std::vector<std::unique_ptr<sim::Effect>> injected;
  for (const auto& s : a.inject)
    for (auto& e : sim::parse_effects(s, m)) injected.push_back(std::move(e));
  std::vector<const sim::Effect*> fx;
  for (const auto& e : machine_fx) fx.push_back(e.get());
  for (const auto& e : injected) fx.push_back(e.get());

  sim::SimulateOptions so;
  const std::string channels = a.channels.empty() ? "tip,enc" : a.channels;
  so.channels = split(channels, ',');
  so.noise = parse_noise(a.noise);
  so.seed = a.seed;
  so.spindle_rpm = a.rpm;
  so.flutes = a.flutes;
  so.note = a.note;
  so.machine_ref = a.machine;
  if (!a.temperatures.empty()) {
    // Any recording-style CSV with t and temp.<sensor> columns (a real run's, to replay its temperatures).
    const sim::Recording tr = sim::read_recording(a.temperatures);
    const int tc = tr.column("t");
    if (tc < 0) throw InputError(SourceLoc{a.temperatures}, "--temperatures: the file has no 't' column");
    for (std::size_t c = 0; c < tr.columns.size(); ++c) {
      if (tr.columns[c].rfind("temp.", 0) != 0) continue;
      sim::SimulateOptions::Temperature tp;
      tp.sensor = tr.columns[c].substr(5);
      for (std::size_t r = 0; r < tr.rows(); ++r) {
        const double tv = tr.data[static_cast<std::size_t>(tc)][r], v = tr.data[c][r];
        if (std::isnan(tv) || std::isnan(v)) continue;  // not measured at that row
        tp.t.push_back(tv);
        tp.deg_c.push_back(v);
      }
      if (tp.t.empty())
        throw InputError(SourceLoc{a.temperatures},
                         fmt::format("--temperatures: column {} has no readings", tr.columns[c]));
      so.temperatures.push_back(std::move(tp));
    }
    if (so.temperatures.empty())
      throw InputError(SourceLoc{a.temperatures}, "--temperatures: the file has no temp.<sensor> column");
  }
  sim::ProfileOptions po;
  po.rate_hz = a.rate;
  po.accel = a.accel;
  double L = a.tool_length >= 0 ? a.tool_length : m.default_tool_length_mm;
  std::string ext = fs::path(a.program).extension().string();
  for (auto& c : ext) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  if (ext == ".csv") {
    // A static pose list (e.g. from `cscam calibrate --design`): measure every pose on the simulated
    // machine (its effects, geometric deviations included) and write a static recording.
    sim::Recording poses = sim::read_recording(a.program);
    if (poses.meta_value("kind").value_or("") != "static")
      throw InputError(poses.meta_value("kind") ? poses.meta_loc("kind") : SourceLoc{a.program, 1, 0},
                       "a CSV input must be a static pose list ('# kind: static' with cmd.<axis> columns)");
    sim::Trajectory tr;
    const auto kin = m.kinematics();
    std::vector<int> col(5);
    for (size_t j = 0; j < 5; ++j) {
      col[j] = poses.column("cmd." + m.axes[j].name);
      if (col[j] < 0)
        throw InputError(
            SourceLoc{a.program, poses.header_line, 0},
            fmt::format("missing column cmd.{} for axis {} of machine {}", m.axes[j].name, m.axes[j].name, m.name));
    }
    for (size_t i = 0; i < poses.rows(); ++i) {
      kin::Axes q;
      for (size_t j = 0; j < 5; ++j) {
        q[static_cast<int>(j)] = poses.data[static_cast<size_t>(col[j])][i];
        if (!std::isfinite(q[static_cast<int>(j)]))
          throw InputError(SourceLoc{a.program, poses.row_line[i], 0},
                           fmt::format("cmd.{} is empty: every pose needs every axis", m.axes[j].name));
      }
      // A pose beyond a stroke cannot be measured: simulating it anyway would hand calibration a pose that no
      // machine of this file can take.
      kin::Axes q_model = q;
      for (int j = 0; j < 5; ++j)
        if (m.axes[static_cast<std::size_t>(j)].rotary()) q_model[j] = deg2rad(q[j]);
      if (const std::string beyond = kin->check_limits(q_model); !beyond.empty())
        throw InputError(SourceLoc{a.program, poses.row_line[i], 0},
                         fmt::format("pose {} is beyond the machine's limits: {}", i + 1, beyond));
      tr.t.push_back(static_cast<double>(i));
      tr.cmd.push_back(q);
    }
    if (tr.t.empty()) throw InputError(SourceLoc{a.program}, "no poses in the file");
    if (a.tool_length < 0) L = poses.meta_number("tool_length", 0.0, 1e4).value_or(L);
    so.tool_length_mm = L;
    sim::Recording rec = sim::simulate(tr, m, fx, so);
    rec.set_meta("kind", "static");
    if (const int tc = rec.column("t"); tc >= 0) {  // poses have no time
      rec.columns.erase(rec.columns.begin() + tc);
      rec.data.erase(rec.data.begin() + tc);
    }
    const std::string out = a.out.empty() ? fs::path(a.program).stem().string() + ".rec.csv" : a.out;
    write_file_atomically(out, [&](std::ostream& os) { sim::write_recording(os, rec, a.decimals); });
    std::cout << fmt::format("wrote {} ({} static poses, channels {}, {} effect(s))\n", out, rec.rows(), channels,
                             fx.size());
    return 0;
  }
  std::vector<sim::Block> blocks;
  if (is_nc(a.program)) {
    nc::Program p = nc::read_file(a.program, report::axis_letters(m));
    // Axis words the machine lacks would be misread: an error (as in verify). A header naming another machine is a
    // warning here: a calibrated copy of the machine file simulates the program it was posted for.
    if (auto other = report::check_machine_of(p, m)) std::cerr << "warning: " << other->what() << "\n";
    report::resolve_work_planes(p, m);  // tilted-plane words as the machine axes they move
    if (p.tcp)
      throw InputError(SourceLoc{a.program}, "this program uses TCP: simulate needs machine-coordinate axis values");
    if (a.tool_length < 0 && p.tool_length_mm) L = *p.tool_length_mm;
    blocks = sim::blocks_from_nc(p, m);
  } else {
    blocks = sim::blocks_from_cl(a.program, m, L);
  }
  so.tool_length_mm = L;
  const sim::Trajectory tr = sim::profile(blocks, po);
  const sim::Recording rec = sim::simulate(tr, m, fx, so);
  const std::string out = a.out.empty() ? fs::path(a.program).stem().string() + ".rec.csv" : a.out;
  write_file_atomically(out, [&](std::ostream& os) { sim::write_recording(os, rec, a.decimals); });
  std::cout << fmt::format("wrote {} ({} samples at {} Hz, {:.3f} s, channels {}, {} effect(s))\n", out, rec.rows(),
                           a.rate, tr.t.empty() ? 0.0 : tr.t.back(), channels, fx.size());
  return 0;
}

std::string machine_for_recording(const sim::Recording& rec, const std::string& opt) {
  if (!opt.empty()) return resolve_machine(opt);
  const auto mm = rec.meta_value("machine");
  if (!mm) throw InputError(SourceLoc{rec.file}, "the recording names no machine (# machine: ...): give --machine");
  return resolve_recorded_machine(rec.file, *mm);
}

int cmd_diagnose(const DiagArgs& a) {
  const auto t0 = std::chrono::steady_clock::now();
  sim::Recording rec = sim::read_recording(a.rec);
  const double t_read = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const std::string mpath = machine_for_recording(rec, a.machine);
  const machine::Machine m = machine::load(mpath);
  auto known = sim::load_machine_effects(mpath, m);
  std::vector<const sim::Effect*> kv;
  for (const auto& e : known) kv.push_back(e.get());
  diagnose::Options o;
  o.keep_plot_data = !a.svg.empty();
  o.max_fit_samples = a.max_fit;
  diagnose::Report r = diagnose::diagnose(rec, m, kv, o);
  r.seconds.insert(r.seconds.begin(), {"read", t_read});
  // --machine over the recording's own: a calibrated copy is expected (same machine name); another machine's model
  // explains nothing, and its misfit would be read as missing physics.
  if (const auto mm = rec.meta_value("machine"); mm && !a.machine.empty()) {
    const std::string stem = fs::path(*mm).stem().string();
    if (stem != m.name && stem != fs::path(a.machine).stem().string())
      r.warnings.insert(r.warnings.begin(),
                        fmt::format("the recording was made on machine '{}' (its metadata), but --machine gives '{}': "
                                    "the findings describe the difference between the two machines",
                                    *mm, m.name));
  }
  for (const auto& w : r.warnings) std::cerr << "warning: " << w << "\n";
  if (!a.svg.empty()) {
    fs::create_directories(a.svg);
    for (const auto& pic : diagnose::svg_pictures(r))  // (clang 14 cannot capture structured bindings)
      write_file_atomically((fs::path(a.svg) / pic.first).string(), [&](std::ostream& os) { os << pic.second; });
  }
  if (!a.write_model.empty()) {
    std::vector<const sim::Effect*> all = kv;
    for (const auto& f : r.findings) all.push_back(f.effect.get());
    const std::string yaml = diagnose::model_yaml(read_text(mpath), all);
    const fs::path outp(a.write_model);
    const std::string prefix = (outp.parent_path() / outp.stem()).string();
    std::map<std::string, std::string> comp;
    const std::string ini = diagnose::linuxcnc_ini(m, all, fs::path(prefix).filename().string(), comp);
    // Relative mesh paths in the machine file must still resolve from the new file's folder: the written
    // file is meant to sit beside the original or be given by absolute path.
    write_file_atomically(a.write_model, [&](std::ostream& os) { os << yaml; });
    write_file_atomically(prefix + ".linuxcnc.ini", [&](std::ostream& os) { os << ini; });
    for (const auto& table : comp)
      write_file_atomically((outp.parent_path() / table.first).string(), [&](std::ostream& os) { os << table.second; });
  }
  if (a.json)
    std::cout << r.to_json() << "\n";
  else
    std::cout << r.text();
  return 0;
}

}  // namespace

std::function<int()> add_sim_commands(CLI::App& app) {
  auto sa = std::make_shared<SimArgs>();
  auto* sim_cmd =
      app.add_subcommand("simulate", "Simulate a program on a machine with injected effects: write a recording");
  sim_cmd
      ->add_option(
          "program", sa->program,
          "NC file (.ngc, .nc, .tap; other extensions such as .mpf or .h are told from CL by their content), CL "
          "file (posted with the conventional strategy), or a static pose list "
          "(.csv, kind: static) to measure")
      ->required();
  sim_cmd->add_option("-m,--machine", sa->machine, "machine file or bundled machine name")->required();
  sim_cmd->add_option("-o,--output", sa->out, "recording to write (CSV, spec/recording.md)");
  sim_cmd->add_option("--rate", sa->rate, "sample rate, Hz (default 1000)");
  sim_cmd->add_option("--accel", sa->accel, "path acceleration of the trapezoidal profile, mm/s^2 (default 2000)");
  sim_cmd->add_option("--channels", sa->channels,
                      "channel groups: tip,ptip,enc,acc,dir (default tip,enc; the parallel CMM: tip,len, with len its "
                      "passive link's gauge)");
  sim_cmd->add_option("--inject", sa->inject,
                      "EFFECT:TARGET:PARAMS, e.g. backlash:q2:0.012 or vibration:tip.z:166.7:0.00322");
  sim_cmd->add_option("--noise", sa->noise,
                      "GROUP:SIGMA white measurement noise, e.g. tip:0.001 (dir: sigma per component of the tool-axis "
                      "vector, which is then normalised to unit length)");
  sim_cmd->add_option("--seed", sa->seed, "random seed of the noise");
  sim_cmd->add_option("--temperatures", sa->temperatures,
                      "CSV with columns t and temp.<sensor> (e.g. a real run's recording): recorded in the output, "
                      "and followed by thermal_growth effects (thermal_growth:tip.z:mm_per_degC=0.002,sensor=spindle)");
  sim_cmd->add_option("--tool-length", sa->tool_length, "tool length, mm (default: NC header or machine)")
      ->check(cli::kNonNegative);
  sim_cmd->add_option("--spindle-rpm", sa->rpm, "spindle speed to record in the metadata");
  sim_cmd->add_option("--flutes", sa->flutes, "cutter flutes to record in the metadata");
  sim_cmd->add_option("--note", sa->note, "free text for the metadata");
  sim_cmd->add_option("--decimals", sa->decimals, "decimals of the written values (default 6)")
      ->check(CLI::Range(3, 12));

  auto da = std::make_shared<DiagArgs>();
  auto* diag_cmd =
      app.add_subcommand("diagnose", "Find where a recording departs from the model and which physics is missing");
  diag_cmd->add_option("recording", da->rec, "recording (CSV, spec/recording.md)")->required();
  diag_cmd->add_option("-m,--machine", da->machine, "machine file or bundled name (default: the recording's metadata)");
  diag_cmd->add_flag("--json", da->json, "print the report as JSON");
  diag_cmd->add_option("--svg", da->svg, "folder for pictures: residual vs time and feature, spectrum");
  diag_cmd->add_option(
      "--write-model", da->write_model,
      "machine file to write with the identified effects (+ LinuxCNC .ini lines and COMP_FILE tables)");
  diag_cmd->add_option("--max-fit-samples", da->max_fit, "samples used by the fits (default 60000)");
  return [sim_cmd, diag_cmd, sa, da]() -> int {
    if (*sim_cmd) return cmd_simulate(*sa);
    if (*diag_cmd) return cmd_diagnose(*da);
    return -1;
  };
}

}  // namespace cscam::cli
