// The cscam command-line program: batch CL-to-NC conversion, verification and statistics.
#include <fmt/format.h>
#include <tbb/global_control.h>
#include <tbb/task_arena.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <nlohmann/json.hpp>
#include <optional>
#include <sstream>

#include "batch_cmd.hpp"
#include "calib_cmd.hpp"
#include "cscam/cl/program.hpp"
#include "cscam/core/atomic_file.hpp"
#include "cscam/core/error.hpp"
#include "cscam/core/threads.hpp"
#include "cscam/gate/gate.hpp"
#include "cscam/machine/machine.hpp"
#include "cscam/nc/reader.hpp"
#include "cscam/post/post.hpp"
#include "cscam/report/backlash.hpp"
#include "cscam/report/letters.hpp"
#include "cscam/report/stats.hpp"
#include "cscam/report/verify.hpp"
#include "plan_cmd.hpp"
#include "sim_cmd.hpp"
#include "trace_cmd.hpp"
#include "validators.hpp"

namespace fs = std::filesystem;
using namespace cscam;

namespace {

using cli::read_cl_as_posted;
using cli::resolve_machine;

}  // namespace

namespace cscam::cli {
std::optional<LengthUnit> parse_units(const std::string& s) {
  if (s.empty()) return std::nullopt;
  if (s == "mm") return LengthUnit::Millimetre;
  if (s == "inch" || s == "in") return LengthUnit::Inch;
  throw InputError(fmt::format("--units: expected mm or inch, got '{}'", s));
}

cl::Program read_cl_as_posted(const std::string& cl_path, const std::string& units_arg,
                              const std::optional<LengthUnit>& header_units, const std::string& nc_path) {
  cl::ReadOptions ro;
  ro.units = parse_units(units_arg);
  cl::Program prog = cl::read_file(cl_path, ro);
  if (!ro.units && header_units && *header_units != prog.source_units) {
    ro.units = header_units;
    prog = cl::read_file(cl_path, ro);
    std::cerr << fmt::format("note: {} was posted from {} read in {} (its header; --units to say otherwise)\n", nc_path,
                             cl_path, *ro.units == LengthUnit::Inch ? "inch" : "mm");
  }
  return prog;
}

/// A machine may be named by path or by its name in the bundled machines/ folder.
std::string resolve_machine(const std::string& arg) {
  if (fs::exists(arg)) return arg;
  for (const std::string& dir : {std::string(CSCAM_MACHINES_DIR), std::string(CSCAM_INSTALLED_MACHINES_DIR)}) {
    const fs::path p = fs::path(dir) / (arg + ".yaml");
    if (fs::exists(p)) return p.string();
  }
  throw InputError(SourceLoc{arg}, fmt::format("machine file not found (neither a path nor a bundled machine in {})",
                                               CSCAM_MACHINES_DIR));
}

std::string resolve_recorded_machine(const std::string& recording_file, const std::string& named) {
  // The spec's order: beside the recording, then the working directory (or a bundled name).
  const fs::path beside = fs::path(recording_file).parent_path() / named;
  if (fs::exists(beside)) return beside.string();
  if (fs::exists(named) || fs::path(named).is_absolute() || fs::path(named).extension() != ".yaml")
    return resolve_machine(named);
  // A path relative to a project root (`machines/xmini.yaml`, written where the recording was made) read from
  // elsewhere: relative to a folder above the recording's, else the bundled machine of that file name.
  std::error_code ec;
  for (fs::path dir = fs::absolute(recording_file, ec).parent_path(); !ec && dir.has_relative_path();
       dir = dir.parent_path())
    if (const fs::path up = dir / named; fs::exists(up)) return up.string();
  for (const std::string& d : {std::string(CSCAM_MACHINES_DIR), std::string(CSCAM_INSTALLED_MACHINES_DIR)})
    if (const fs::path bundled = fs::path(d) / fs::path(named).filename(); fs::exists(bundled)) return bundled.string();
  return resolve_machine(named);
}
}  // namespace cscam::cli

namespace {

std::array<std::string, 5> names_of(const machine::Machine& m, bool use_letters) {
  std::array<std::string, 5> n;
  for (size_t i = 0; i < 5; ++i) n[i] = use_letters ? m.post.letters[i] : m.axes[i].name;
  return n;
}

std::array<bool, 5> rotary_of(const machine::Machine& m) {
  std::array<bool, 5> r{};
  for (size_t i = 0; i < 5; ++i) r[i] = m.axes[i].rotary();
  return r;
}

struct PostArgs {
  std::vector<std::string> cl;
  std::string machine, out, dialect, units, work_plane;
  std::vector<std::string> parts, fixtures;  ///< meshes the gate checks every move against
  double tolerance = 0, axis_tolerance = 0, tool_length = 0;
  double default_feed = 0;  ///< mm/min for feed moves without a feed rate; 0: such a CL file is an error
  bool json = false, no_linearise = false, tcp = false, no_tcp = false;
};

cli::PostJob job_of(const PostArgs& a, const std::string& cl, const std::string& out) {
  cli::PostJob j;
  j.cl = cl;
  j.machine = a.machine;
  j.out = out;
  j.dialect = a.dialect;
  j.units = a.units;
  j.tolerance_mm = a.tolerance;
  j.axis_tolerance_deg = a.axis_tolerance;
  j.tool_length_mm = a.tool_length;
  j.default_feed_mm_per_min = a.default_feed;
  j.linearise = !a.no_linearise;
  if (a.tcp || a.no_tcp) j.tcp = a.tcp;
  j.work_plane = a.work_plane;
  j.parts = a.parts;
  j.fixtures = a.fixtures;
  return j;
}

int cmd_post(const PostArgs& a) {
  // Several files, or an output that names a directory: the batch form, every file a job of its own.
  const bool to_dir = !a.out.empty() && (a.out.back() == '/' || fs::is_directory(a.out));
  if (a.cl.size() > 1 || to_dir) {
    if (a.out.empty())
      throw InputError(fmt::format("post: {} CL files need an output directory: -o DIR/", a.cl.size()));
    if (!to_dir)
      throw InputError(SourceLoc{a.out}, fmt::format("post: {} CL files need an output directory, and this is a "
                                                     "file (end it with / to create the directory)",
                                                     a.cl.size()));
    cli::make_output_dir(a.out);
    std::vector<cli::PostJob> jobs;
    for (const auto& cl : a.cl)
      jobs.push_back(job_of(a, cl, (fs::path(a.out) / (fs::path(cl).stem().string() + ".ngc")).string()));
    return cli::run_jobs(jobs, a.json);
  }
  const std::string& cl = a.cl.front();
  const std::string out = a.out.empty() ? fs::path(cl).stem().string() + ".ngc" : a.out;  // in the working dir
  const cli::PostJob job = job_of(a, cl, out);
  cli::JobResult r;
  // CSCAM_THREADS sets the gate's parallel loops' threads (TBB's pool alone would follow the hardware).
  const tbb::global_control pool(tbb::global_control::max_allowed_parallelism, worker_threads());
  tbb::task_arena arena(static_cast<int>(worker_threads()));
  arena.execute([&] { cli::run_job(job, r); });
  if (a.json) {
    nlohmann::json j;
    j["nc"] = out;
    j["machine"] = r.machine_name;
    cli::add_written_json(j, r);
    j["warnings"] = r.warnings;
    j["seconds"] = r.seconds;
    std::cout << j.dump() << "\n";
  } else {
    for (const auto& w : r.warnings) std::cerr << "warning: " << w << "\n";
    std::cout << fmt::format(
        "wrote {} ({} CL points -> {} blocks, {} points inserted by linearisation{}{}) for machine {} in {:.3f} s\n"
        "gate {}\n",
        out, r.cl_points, r.blocks, r.inserted_points,
        r.reorientations + r.retracts
            ? fmt::format(", {} reorientations in place, {} retracts", r.reorientations, r.retracts)
            : std::string(),
        r.narrowed_corners + r.exact_corners
            ? fmt::format(", {} corners given a smaller blend tolerance and {} exact stops so that the control's "
                          "blending keeps the tolerance",
                          r.narrowed_corners, r.exact_corners)
            : std::string(),
        r.machine_name, r.seconds, r.message);
  }
  return 0;
}

struct VerifyArgs {
  std::string nc, machine, cl, units;
  double tolerance = 0, axis_tolerance = 0, tool_length = -1;
  std::optional<double> cone;  // none: the cone a cscam-planned program's header states, else 0
  std::optional<int> samples;  // none: adaptive (a proven bound between samples); N: N fixed samples per block
  bool json = false;
};

int cmd_verify(const VerifyArgs& a) {
  const machine::Machine m = machine::load(resolve_machine(a.machine));
  // Tool-tip-control programs are read with the tip words X Y Z and compared through the control's view.
  nc::Program ncp = report::read_file_for_machine(a.nc, m);
  const cl::Program prog = read_cl_as_posted(a.cl, a.units, ncp.header_cl_units, a.nc);
  // Another machine's program would be verified against the wrong kinematics: an error, not a verdict.
  if (auto mismatch = report::check_machine_of(ncp, m)) throw *mismatch;
  const double L = a.tool_length >= 0 ? a.tool_length : ncp.tool_length_mm.value_or(m.default_tool_length_mm);
  const auto kin = m.make_kinematics(L);
  // The post's tolerances plus the slack for printed decimals (one place: report::verify_options_for); an explicit
  // --tolerance / --axis-tolerance is the allowed deviation itself. A planned program may tilt within a cone: then
  // the axis may deviate by the cone and a ball mill's centre (not its tip) is what stays on the CL path.
  // A program planned by `cscam plan` states its cone in the header: compared as planned unless --cone says otherwise.
  const double cone = a.cone.value_or(ncp.header_cone_deg.value_or(0.0));
  if (!a.cone && cone > 0)
    std::cerr << fmt::format(
        "note: {} was planned with a {:g} deg cone (its header): the tool axis may deviate by that much and ball "
        "centres are compared (--cone to say otherwise)\n",
        a.nc, cone);
  report::VerifyOptions vo = report::verify_options_for(m, 0.0, 0.0, cone);
  if (a.tolerance > 0) vo.tip_tolerance_mm = a.tolerance;
  if (a.axis_tolerance > 0) vo.axis_tolerance_deg = a.axis_tolerance + cone;
  if (a.samples) {  // asked for: exactly that many samples in every block, nothing added
    vo.samples_per_block = *a.samples;
    vo.adaptive_samples = false;
  }
  if (const std::string why = report::resolve_tool_vectors(ncp, *kin); !why.empty()) throw InputError(why);
  const auto tip_view = report::tool_tip_kinematics(*kin, ncp.tcp_vectors);
  auto r = report::verify(ncp, prog, ncp.tcp ? *tip_view : *kin, vo);
  // The machine's own rules as the safety gate applies them before a file is written: every block inside the axis
  // limits (a PKM's passive joints sampled inside the moves) and no axis above its max_feed. A file edited by hand, or
  // written by another post, can follow the CL path and still break them.
  std::vector<gate::Violation> broken;
  {
    std::ifstream in(a.nc, std::ios::binary);
    std::stringstream text;
    text << in.rdbuf();
    gate::Options go = gate::options_for(m, 0.0, 0.0, cone);
    go.tip_tolerance_mm = vo.tip_tolerance_mm;
    go.axis_tolerance_deg = vo.axis_tolerance_deg;
    const gate::Summary gs = gate::check(text.str(), a.nc, prog, m, *kin, go);
    for (const auto& v : gs.violations)
      if (v.kind == gate::Violation::Kind::Limit || v.kind == gate::Violation::Kind::Velocity) broken.push_back(v);
  }
  if (!broken.empty()) {
    if (r.ok) r.message = "FAILED:";
    r.ok = false;
    r.message += fmt::format(" {} at NC line {}", broken.front().message, broken.front().nc_line);
    if (broken.size() > 1) r.message += fmt::format(" ({} more limit or feed violation(s))", broken.size() - 1);
    r.message += ";";
  }
  if (a.json) {
    nlohmann::json j = r.json();
    nlohmann::json v = nlohmann::json::array();
    for (const auto& b : broken)
      v.push_back({{"kind", b.kind == gate::Violation::Kind::Limit ? "limit" : "feed"},
                   {"nc_line", b.nc_line},
                   {"message", b.message}});
    j["limit_and_feed_violations"] = std::move(v);
    std::cout << j.dump(2) << "\n";
  } else {
    std::cout << r.message << "\n";
  }
  return r.ok ? 0 : 1;
}

int cmd_stats(const std::vector<std::string>& files, const std::string& machine_arg, bool json) {
  const machine::Machine m = machine::load(resolve_machine(machine_arg));
  std::vector<report::Stats> cols;
  std::vector<std::string> headers;
  std::vector<std::vector<std::string>> warnings;
  for (const auto& f : files) {
    const nc::Program p = report::read_file_for_machine(f, m);
    // Statistics count axis words: a letter the machine lacks is an error, another machine's header a warning.
    warnings.emplace_back();
    if (const auto mismatch = report::check_machine_of(p, m)) {
      std::cerr << "warning: " << mismatch->what() << "\n";
      warnings.back().push_back(mismatch->what());
    }
    std::array<double, 5> vmax{};  // mm/min, deg/min: the rapids of the cycle-time estimate
    for (size_t i = 0; i < 5; ++i) vmax[i] = m.axes[i].rotary() ? rad2deg(m.axes[i].max_feed) : m.axes[i].max_feed;
    cols.push_back(report::compute(p, names_of(m, true), rotary_of(m), &vmax));
    headers.push_back(fs::path(f).filename().string());
  }
  if (json) {
    nlohmann::json all = nlohmann::json::array();
    for (std::size_t i = 0; i < cols.size(); ++i) {
      nlohmann::json c = cols[i].json();
      c["warnings"] = warnings[i];  // what went to stderr, also in the document
      all.push_back(std::move(c));
    }
    std::cout << all.dump(2) << "\n";
  } else {
    std::cout << report::table(cols, headers);
  }
  return 0;
}

// --- backlash: simulate a lost motion on one axis and show what it does to the tip -------------------
struct BacklashArgs {
  std::vector<std::string> nc;
  std::string machine, axis;
  double width_mm = -1, width_deg = -1, tool_length = -1, max_step = 0;
  bool json = false;
};

int cmd_backlash(const BacklashArgs& a) {
  const machine::Machine m = machine::load(resolve_machine(a.machine));
  const int axis = m.axis_index(a.axis);
  if (axis < 0) throw InputError(fmt::format("--axis: machine {} has no axis '{}'", m.name, a.axis));
  const bool rotary = m.axes[static_cast<size_t>(axis)].rotary();
  if ((a.width_mm >= 0) == (a.width_deg >= 0))
    throw InputError("backlash: give exactly one of --width-mm and --width-deg");
  if (rotary != (a.width_deg >= 0))
    throw InputError(fmt::format("backlash: axis '{}' is {}: give its width with {}", a.axis,
                                 rotary ? "rotary" : "linear", rotary ? "--width-deg" : "--width-mm"));
  const double width = rotary ? deg2rad(a.width_deg) : a.width_mm;
  // Fine enough that the play acts within a tenth of its width (default), whatever the block lengths.
  const double step = a.max_step > 0 ? (rotary ? deg2rad(a.max_step) : a.max_step) : (width > 0 ? width / 10 : 0.001);
  std::vector<report::BacklashResult> results;
  for (const auto& f : a.nc) {
    nc::Program ncp = nc::read_file(f, report::axis_letters(m));
    if (const auto mismatch = report::check_machine_of(ncp, m)) throw *mismatch;
    report::resolve_work_planes(ncp, m);  // tilted-plane words as the machine axes they move
    if (const nc::Program::Unmodelled* u = nc::first_unmodelled_before_motion(ncp))
      throw InputError(
          SourceLoc{f, u->line, 0},
          fmt::format("{}, which backlash does not model: the moves after it go where it does not look", u->what));
    if (ncp.tcp) {
      int at = 0;
      for (const auto& b : ncp.blocks)
        if (b.tcp) {
          at = b.line;
          break;
        }
      throw InputError(SourceLoc{f, at, 0},
                       "this program runs under tool-tip control (G43.4, G43.5, G234, M428, TRAORI, TCPM or M128): its "
                       "words are the tip in the part frame, not machine axes; backlash simulates machine-coordinate "
                       "programs (post with --no-tcp)");
    }
    const double L = a.tool_length >= 0 ? a.tool_length : ncp.tool_length_mm.value_or(m.default_tool_length_mm);
    const auto kin = m.make_kinematics(L);
    results.push_back(report::simulate_backlash(report::sample_nc(ncp, axis, step), *kin, axis, width));
  }
  if (a.json) {
    nlohmann::json all = nlohmann::json::array();
    for (size_t i = 0; i < results.size(); ++i) all.push_back({{"nc", a.nc[i]}, {"result", results[i].json()}});
    std::cout << all.dump(2) << "\n";
    return 0;
  }
  for (size_t i = 0; i < results.size(); ++i)
    std::cout << fs::path(a.nc[i]).filename().string() << ": " << results[i].text();
  if (results.size() > 1) {  // side by side: the step at feed reversals is what marks the surface
    size_t w = 14;
    for (const auto& f : a.nc) w = std::max(w, fs::path(f).filename().string().size() + 2);
    std::cout << fmt::format("\n{:<36}", "");
    for (const auto& f : a.nc) std::cout << fmt::format("{:>{}}", fs::path(f).filename().string(), w);
    std::cout << "\n";
    auto row = [&](const std::string& label, auto&& cell) {
      std::cout << fmt::format("{:<36}", label);
      for (const auto& r : results) std::cout << fmt::format("{:>{}}", cell(r), w);
      std::cout << "\n";
    };
    row(a.axis + " reversals while cutting", [](const report::BacklashResult& r) {
      return fmt::format(
          "{}", std::count_if(r.reversals.begin(), r.reversals.end(), [](const auto& v) { return v.in_feed; }));
    });
    for (int c = 0; c < 3; ++c) {
      const char comp = "xyz"[c];
      row(fmt::format("max |step {}| at those (um)", comp),
          [c](const report::BacklashResult& r) { return fmt::format("{:.3f}", 1000.0 * r.max_abs_step_mm[c]); });
    }
    for (int c = 0; c < 3; ++c) {
      const char comp = "xyz"[c];
      row(fmt::format("max |d{}| over feed (um)", comp),
          [c](const report::BacklashResult& r) { return fmt::format("{:.3f}", 1000.0 * r.max_abs_deviation_mm[c]); });
    }
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"cscam: 5-axis CAM post-processor with a configuration-space tool-orientation planner"};
  app.require_subcommand(1);
  app.set_version_flag("--version", std::string("cscam ") + CSCAM_VERSION);
  // Every option's default is shown in --help ("0" for a tolerance means "the machine file's").
  app.option_defaults()->always_capture_default();

  PostArgs pa;
  auto* post_cmd = app.add_subcommand(
      "post", "Convert CL files to NC with the conventional (nearest-solution) strategy; several in parallel");
  post_cmd->add_option("cl", pa.cl, "CL file(s) (APT/CLDATA, NX CLSF, CSV); several are converted in parallel")
      ->required();
  post_cmd->add_option("-m,--machine", pa.machine, "machine file or bundled machine name")->required();
  post_cmd->add_option("-o,--output", pa.out,
                       "NC file to write, or a directory (ending in /) for several CL files "
                       "(default: CL name with .ngc, in the working directory)");
  post_cmd->add_option("--dialect", pa.dialect,
                       "override the machine's dialect (linuxcnc, fanuc, haas, siemens, heidenhain, xmini-joint, "
                       "xmini-cartesian)");
  post_cmd->add_option("--units", pa.units, "force the CL units (mm or inch)");
  post_cmd->add_option("--tolerance", pa.tolerance, "linearisation tolerance of the tip, mm (0: the machine file's)")
      ->check(cli::kNonNegative);
  post_cmd
      ->add_option("--axis-tolerance", pa.axis_tolerance,
                   "linearisation tolerance of the tool axis, deg (0: the machine file's)")
      ->check(cli::kNonNegative);
  post_cmd->add_option("--tool-length", pa.tool_length, "gauge-to-tip tool length, mm (0: the machine file's)")
      ->check(cli::kNonNegative);
  post_cmd
      ->add_option("--default-feed", pa.default_feed,
                   "feed, mm/min, for cutting moves the CL gives no feed rate for (default: such a CL is an error)")
      ->check(cli::kPositive);
  post_cmd->add_flag("--no-linearise", pa.no_linearise, "do not insert points between CL points");
  post_cmd->add_option("--part", pa.parts,
                       "part mesh(es) (STL, OBJ, PLY, ...): the safety gate checks every move against them, as it "
                       "checks the machine file's bodies");
  post_cmd->add_option("--fixture", pa.fixtures, "fixture mesh(es), checked as --part");
  auto* tcp_flag = post_cmd->add_flag("--tcp", pa.tcp, "tool-tip control on (default: the machine's post.tcp)");
  post_cmd->add_flag("--no-tcp", pa.no_tcp, "tool-tip control off: machine coordinates")->excludes(tcp_flag);
  post_cmd
      ->add_option("--work-plane", pa.work_plane,
                   "3+2 stretches: tilted (G68.2, G254, CYCLE800, PLANE SPATIAL) or machine coordinates (default: "
                   "the machine's post.work_plane)")
      ->check(CLI::IsMember({"tilted", "machine"}));
  post_cmd->add_flag("--json", pa.json, "print a JSON summary");

  VerifyArgs va;
  auto* verify_cmd = app.add_subcommand("verify", "Back-simulate an NC file by FK and compare it with the CL path");
  verify_cmd->add_option("nc", va.nc, "NC file")->required();
  verify_cmd->add_option("-m,--machine", va.machine, "machine file or bundled machine name")->required();
  verify_cmd->add_option("--cl", va.cl, "the CL file the NC was made from")->required();
  verify_cmd->add_option("--units", va.units, "force the CL units (mm or inch)");
  verify_cmd->add_option("--tolerance", va.tolerance, "allowed tip deviation, mm")->check(cli::kPositive);
  verify_cmd->add_option("--axis-tolerance", va.axis_tolerance, "allowed tool-axis deviation, deg")
      ->check(cli::kPositive);
  verify_cmd->add_option("--tool-length", va.tool_length, "tool length, mm (default: from the NC header)")
      ->check(cli::kPositive);
  verify_cmd
      ->add_option(
          "--cone", va.cone,
          "the program was planned with this cone, deg: compare ball centres, allow the cone (default: the cone a "
          "cscam-planned program's header states, else 0)")
      ->check(CLI::Range(0.0, 90.0));
  verify_cmd
      ->add_option("--samples", va.samples,
                   "FK samples inside every block, fixed (default: as few as a proven bound on the path between "
                   "samples allows, the bound added to the deviation; 8 where the kinematics has no such bound)")
      ->check(CLI::Range(1, 10000));
  verify_cmd->add_flag("--json", va.json, "print the result as JSON");

  std::vector<std::string> stat_files;
  std::string stat_machine;
  bool stat_json = false;
  auto* stats_cmd = app.add_subcommand("stats", "Axis travel, reversals, steps and simultaneous axes of NC files");
  stats_cmd->add_option("nc", stat_files, "one or more NC files (shown side by side)")->required();
  stats_cmd->add_option("-m,--machine", stat_machine, "machine file or bundled machine name")->required();
  stats_cmd->add_flag("--json", stat_json, "print JSON");

  BacklashArgs ba;
  auto* backlash_cmd = app.add_subcommand(
      "backlash", "Simulate a lost motion (backlash) on one axis of NC files and report the tip deviation");
  backlash_cmd->add_option("nc", ba.nc, "one or more NC files (compared side by side)")->required();
  backlash_cmd->add_option("-m,--machine", ba.machine, "machine file or bundled machine name")->required();
  backlash_cmd->add_option("--axis", ba.axis, "axis with the play, by its machine-file name (e.g. q2)")->required();
  backlash_cmd->add_option("--width-mm", ba.width_mm, "full lost-motion width of a linear axis, mm")
      ->check(cli::kPositive);
  backlash_cmd->add_option("--width-deg", ba.width_deg, "full lost-motion width of a rotary axis, deg")
      ->check(cli::kPositive);
  backlash_cmd->add_option("--tool-length", ba.tool_length, "tool length, mm (default: from the NC header)")
      ->check(cli::kPositive);
  backlash_cmd
      ->add_option("--max-step", ba.max_step, "largest axis step between samples, mm or deg (default: width/10)")
      ->check(cli::kPositive);
  backlash_cmd->add_flag("--json", ba.json, "print JSON");

  auto run_plan_commands = cli::add_plan_commands(app);
  auto run_sim_commands = cli::add_sim_commands(app);
  auto run_calib_commands = cli::add_calib_commands(app);
  auto run_trace_commands = cli::add_trace_commands(app);
  auto run_batch_command = cli::add_batch_command(app);

  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    // Help and version exit 0; a bad argument is bad input, as everywhere else: exit 2.
    return app.exit(e) == 0 ? 0 : 2;
  }
  try {
    if (*post_cmd) return cmd_post(pa);
    if (*verify_cmd) return cmd_verify(va);
    if (*stats_cmd) return cmd_stats(stat_files, stat_machine, stat_json);
    if (*backlash_cmd) return cmd_backlash(ba);
    if (const int rc = run_plan_commands(); rc >= 0) return rc;
    if (const int rc = run_sim_commands(); rc >= 0) return rc;
    if (const int rc = run_calib_commands(); rc >= 0) return rc;
    if (const int rc = run_trace_commands(); rc >= 0) return rc;
    if (const int rc = run_batch_command(); rc >= 0) return rc;
  } catch (const InputError& e) {
    std::cerr << "error: " << e.what() << "\n";
    return 2;
  } catch (const std::exception& e) {
    std::cerr << "internal error: " << e.what() << "\n";
    return 3;
  }
  return 0;
}
