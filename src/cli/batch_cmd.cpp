#include "batch_cmd.hpp"

#include <fmt/format.h>
#include <tbb/blocked_range.h>
#include <tbb/global_control.h>
#include <tbb/task_arena.h>
#include <unistd.h>
#include <yaml-cpp/yaml.h>

#include <atomic>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <set>
#include <sstream>

#include "cscam/cl/program.hpp"
#include "cscam/core/parallel.hpp"
#include "cscam/core/threads.hpp"
#include "cscam/gate/gate.hpp"
#include "cscam/machine/machine.hpp"
#include "cscam/nc/reader.hpp"
#include "cscam/post/post.hpp"
#include "cscam/report/letters.hpp"
#include "cscam/report/stats.hpp"
#include "cscam/report/verify.hpp"
#include "plan_cmd.hpp"

namespace fs = std::filesystem;

namespace cscam::cli {

namespace {

/// Machines by resolved path, loaded once per process and shared read-only by every job that names them. Loaded
/// under the lock: two jobs naming one machine load it once, and yaml-cpp 0.7 is never run on two threads at once
/// (ThreadSanitizer reports a race inside its convert<bool>::decode when it is).
std::shared_ptr<const machine::Machine> machine_for(const std::string& arg) {
  static std::mutex mu;
  static std::map<std::string, std::shared_ptr<const machine::Machine>> cache;
  const std::string path = resolve_machine(arg);
  const std::lock_guard<std::mutex> lock(mu);
  if (const auto it = cache.find(path); it != cache.end()) return it->second;
  return cache.emplace(path, std::make_shared<const machine::Machine>(machine::load(path))).first->second;
}

/// Travel and reversals of a written program, as `cscam stats` reports them.
void add_stats(const nc::Program& ncp, const std::string& nc_name, const machine::Machine& m, JobResult& r) {
  std::array<std::string, 5> names;
  std::array<bool, 5> rotary{};
  for (std::size_t i = 0; i < 5; ++i) {
    names[i] = m.post.letters[i];
    rotary[i] = m.axes[i].rotary();
  }
  report::Stats st = report::compute(ncp, names, rotary);
  st.source = fs::path(nc_name).filename().string();
  for (const auto& a : st.axes) {
    (a.rotary ? r.travel_deg : r.travel_mm) += a.travel;
    r.reversals += a.reversals;
  }
  r.stats = st.json();
}

/// The same, read back from the program's text as `cscam stats` reads it.
void add_stats(const std::string& nc_text, const std::string& nc_name, const machine::Machine& m, JobResult& r) {
  nc::Program ncp;
  try {
    ncp = nc::read_text(nc_text, nc_name, report::axis_letters(m));
    report::resolve_work_planes(ncp, m);  // tilted-plane words as the machine axes they move
  } catch (const InputError& e) {         // the gate judges the program; the table just has no figures then
    r.warnings.push_back("no statistics: " + e.message());
    return;
  }
  add_stats(ncp, nc_name, m, r);
}

std::string status_name(JobStatus s) {
  switch (s) {
    case JobStatus::Ok:
      return "ok";
    case JobStatus::Failed:
      return "failed";
    case JobStatus::InternalError:
      return "internal-error";
  }
  return "?";
}

}  // namespace

void add_written_json(nlohmann::json& j, const JobResult& r) {
  j["cl_points"] = r.cl_points;
  j["blocks"] = r.blocks;
  j["inserted_points"] = r.inserted_points;
  j["reorientations"] = r.reorientations;
  j["retracts"] = r.retracts;
  j["narrowed_corners"] = r.narrowed_corners;
  j["exact_corners"] = r.exact_corners;
  j["travel_mm"] = r.travel_mm;
  j["travel_deg"] = r.travel_deg;
  j["reversals"] = r.reversals;
  j["gate"] = {{"ok", true},
               {"message", r.message},
               {"max_tip_deviation_mm", r.max_tip_deviation_mm},
               {"max_axis_deviation_deg", r.max_axis_deviation_deg},
               {"max_velocity_ratio", r.max_velocity_ratio}};
}

namespace {

nlohmann::json job_json(const PostJob& job, const JobResult& r) {
  nlohmann::json j;
  j["cl"] = job.cl;
  j["nc"] = job.out;
  j["status"] = status_name(r.status);
  j["message"] = r.message;
  j["machine"] = r.machine_name;
  j["strategy"] = job.strategy == Strategy::Planner ? "planner" : "conventional";
  if (r.status == JobStatus::Ok) {
    add_written_json(j, r);
    j["stats"] = r.stats;
  }
  j["warnings"] = r.warnings;
  j["seconds"] = r.seconds;
  return j;
}

/// "[#####.....] 12/200 files, 1 failed" on one rewritten stderr line; only on a terminal, so that logs and
/// pipes stay clean.
class Progress {
 public:
  explicit Progress(std::size_t total) : total_(total), on_(total > 1 && ::isatty(::fileno(stderr))) {}
  void done(bool failed) {
    const std::size_t n = ++done_;
    if (failed) ++failed_;
    if (!on_) return;
    const std::lock_guard<std::mutex> lock(mu_);
    constexpr std::size_t kWidth = 30;
    const std::size_t fill = total_ ? n * kWidth / total_ : kWidth;
    std::fprintf(stderr, "\r[%s%s] %zu/%zu files%s", std::string(fill, '#').c_str(),
                 std::string(kWidth - fill, '.').c_str(), n, total_,
                 failed_ ? fmt::format(", {} failed", failed_.load()).c_str() : "");
    std::fflush(stderr);
  }
  ~Progress() {
    if (on_ && done_) std::fputs("\r\033[K", stderr);
  }

 private:
  std::size_t total_;
  bool on_;
  std::atomic<std::size_t> done_{0}, failed_{0};
  std::mutex mu_;
};

void print_table(const std::vector<PostJob>& jobs, const std::vector<JobResult>& results, double wall_s,
                 std::size_t threads) {
  std::size_t w = 4;
  for (const auto& j : jobs) w = std::max(w, fs::path(j.cl).filename().string().size());
  w = std::min<std::size_t>(w + 2, 48);
  std::cout << fmt::format("{:<{}}{:<10}{:>10}{:>14}{:>14}{:>11}{:>9}\n", "file", w, "status", "blocks", "travel mm",
                           "travel deg", "reversals", "time s");
  std::size_t ok = 0;
  for (std::size_t i = 0; i < jobs.size(); ++i) {
    const JobResult& r = results[i];
    const std::string name = fs::path(jobs[i].cl).filename().string();
    if (r.status == JobStatus::Ok) {
      ++ok;
      std::cout << fmt::format("{:<{}}{:<10}{:>10}{:>14.3f}{:>14.3f}{:>11}{:>9.3f}\n", name, w, "ok", r.blocks,
                               r.travel_mm, r.travel_deg, r.reversals, r.seconds);
    } else {
      std::cout << fmt::format("{:<{}}{:<10}{:>10}{:>14}{:>14}{:>11}{:>9.3f}\n", name, w,
                               r.status == JobStatus::Failed ? "FAILED" : "INTERNAL", "-", "-", "-", "-", r.seconds);
    }
  }
  std::cout << fmt::format("{} of {} files converted in {:.3f} s on {} thread(s)\n", ok, jobs.size(), wall_s, threads);
  for (std::size_t i = 0; i < jobs.size(); ++i)
    if (results[i].status != JobStatus::Ok)
      std::cout << fmt::format("{}: {}\n", fs::path(jobs[i].cl).filename().string(), results[i].message);
}

/// The post's and the gate's figures of a written program, whichever strategy chose the axes.
void take_summaries(JobResult& r, const post::Summary& sum, const gate::Summary& gs) {
  r.cl_points = sum.cl_points;
  r.blocks = sum.blocks;
  r.inserted_points = sum.inserted_points;
  r.reorientations = sum.reorientations;
  r.retracts = sum.retracts;
  r.narrowed_corners = sum.narrowed_corners;
  r.exact_corners = sum.exact_corners;
  r.message = gs.message;
  r.max_tip_deviation_mm = gs.deviation.max_tip_deviation_mm;
  r.max_axis_deviation_deg = gs.deviation.max_axis_deviation_deg;
  r.max_velocity_ratio = gs.max_velocity_ratio;
}

}  // namespace

void make_output_dir(const std::string& dir) {
  if (dir.empty()) return;
  std::error_code ec;
  fs::create_directories(dir, ec);
  if (ec || !fs::is_directory(dir))
    throw InputError(SourceLoc{dir},
                     fmt::format("cannot create the output directory: {}", ec ? ec.message() : "not a directory"));
}

void run_job(const PostJob& job, JobResult& r) {
  const auto t0 = std::chrono::steady_clock::now();
  if (job.strategy == Strategy::Planner) {
    PlanArgs a;
    a.cl = job.cl;
    a.machine = job.machine;
    a.dialect = job.dialect;
    a.units = job.units;
    a.parts = job.parts;
    a.fixtures = job.fixtures;
    a.cone_deg = job.cone_deg;
    a.tool_length = job.tool_length_mm;
    a.tolerance = job.tolerance_mm;
    a.default_feed = job.default_feed_mm_per_min;
    a.tcp = job.tcp;
    a.work_plane = job.work_plane;
    PlanWritten w = plan_and_write(a, job.out);
    r.machine_name = w.machine_name;
    take_summaries(r, w.post, w.gate);
    r.warnings = std::move(w.warnings);
    add_stats(w.nc_text, job.out, *machine_for(job.machine), r);
  } else {
    const auto mp = machine_for(job.machine);
    const machine::Machine& m = *mp;
    cl::ReadOptions ro;
    ro.units = parse_units(job.units);
    ro.require_feed = true;
    if (job.default_feed_mm_per_min > 0) ro.default_feed_mm_per_min = job.default_feed_mm_per_min;
    const cl::Program prog = cl::read_file(job.cl, ro);
    for (const auto& w : prog.warnings) r.warnings.push_back(w.where.str() + ": " + w.message);
    std::string tool_note;  // head-side rotaries: where the tool length came from
    const double L = post::tool_length_for(m, job.tool_length_mm, prog, tool_note);
    if (!tool_note.empty()) r.warnings.push_back(tool_note);
    const std::shared_ptr<const kin::Kinematics> kin = m.make_kinematics(L);
    const auto axes = post::conventional_axes(prog, m, *kin);
    post::Options po;
    po.dialect = job.dialect;
    po.tolerance_mm = job.tolerance_mm;
    po.axis_tolerance_deg = job.axis_tolerance_deg;
    po.linearise = job.linearise;
    po.tcp = job.tcp;
    po.work_plane = job.work_plane;
    po.source_name = fs::path(job.cl).filename().string();
    po.tool_length_mm = L;
    post::Summary sum;
    std::ostringstream os;
    post::write_nc(os, prog, m, *kin, axes, po, sum);
    const std::string nc_text = std::move(os).str();
    for (const auto& w : sum.warnings) r.warnings.push_back(w);
    // No program reaches disk without passing the independent back-simulation (limits, feeds, tolerance).
    // Machine words: the statistics come from the program as the gate read it back (a second reading of a
    // million-block text cost about an eighth of the post). Tool-tip words are read as `cscam stats` reads them
    // (the gate reads them as tip coordinates), beside the gate (they are dropped if it refuses the program).
    gate::Summary gs;
    nc::Program read_back;
    const bool tip_words = report::uses_tool_tip_control(nc_text);
    // The moves are checked against the machine's own bodies (and the job's meshes), as a planned program's are.
    gate::Options go = gate::options_for(m, job.tolerance_mm, job.axis_tolerance_deg, 0.0);
    {
      PlanArgs scene_args;
      scene_args.cl = job.cl;
      scene_args.parts = job.parts;
      scene_args.fixtures = job.fixtures;
      go.make_collision = collision_for_post(m, kin, L, prog, scene_args, r.warnings);
    }
    auto gate_and_write = [&] {
      gs = gate::write_checked(job.out, nc_text, prog, m, *kin, go, &sum.cl_line_of_nc_line,
                               tip_words ? nullptr : &read_back);
    };
    auto stats = [&] { add_stats(nc_text, job.out, m, r); };
    if (!tip_words) {
      gate_and_write();
      if (read_back.tcp || read_back.tcp_vectors)  // not expected (the scan above saw no TCP word): read as stats does
        stats();
      else
        add_stats(read_back, job.out, m, r);
    } else if (kin->traits().forward_depends_on_call_order) {  // warm-started FK: the gate stays on this thread
      gate_and_write();
      stats();
    } else {
      cscam::parallel_invoke(gate_and_write, stats);
    }
    r.machine_name = m.name;
    take_summaries(r, sum, gs);
  }
  r.status = JobStatus::Ok;
  r.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

int run_jobs(const std::vector<PostJob>& jobs, bool json) {
  // Two jobs writing one file would race and one result would be lost: refused before anything runs.
  std::map<std::string, std::size_t> seen;
  for (std::size_t i = 0; i < jobs.size(); ++i) {
    const std::string key = fs::weakly_canonical(fs::absolute(jobs[i].out)).string();
    if (const auto [it, fresh] = seen.emplace(key, i); !fresh)
      throw InputError(jobs[i].entry.file.empty() ? SourceLoc{jobs[i].cl} : jobs[i].entry,
                       fmt::format("output {} is also the output of {}: give the files distinct names", jobs[i].out,
                                   jobs[it->second].cl));
  }
  // An output that is some job's CL input would replace that input, before or after the job reads it (which one
  // depends on the threads): refused before anything runs, as a job writing over its own input is.
  std::map<std::string, std::size_t> inputs;
  for (std::size_t i = 0; i < jobs.size(); ++i)
    inputs.emplace(fs::weakly_canonical(fs::absolute(jobs[i].cl)).string(), i);
  for (const auto& j : jobs)
    if (const auto it = inputs.find(fs::weakly_canonical(fs::absolute(j.out)).string()); it != inputs.end()) {
      const PostJob& reader = jobs[it->second];
      const std::string whose = &reader == &j ? std::string("its own CL input")
                                : reader.entry.line > 0
                                    ? fmt::format("the CL input of the job at line {}", reader.entry.line)
                                    : fmt::format("the CL input {}", reader.cl);
      throw InputError(j.entry.file.empty() ? SourceLoc{j.cl} : j.entry,
                       fmt::format("output {} is {}: it would be overwritten; give another output", j.out, whose));
    }
  const std::size_t threads = worker_threads();
  // TBB's own pool follows the hardware; CSCAM_THREADS may ask for more (or fewer) workers than cores.
  const tbb::global_control pool(tbb::global_control::max_allowed_parallelism, threads);
  std::vector<JobResult> results(jobs.size());
  const auto t0 = std::chrono::steady_clock::now();
  {
    Progress progress(jobs.size());
    tbb::task_arena arena(static_cast<int>(threads));
    arena.execute([&] {
      // One job per task: files differ widely in size, so let the scheduler balance them.
      parallel_range(0, jobs.size(), 1, [&](const tbb::blocked_range<std::size_t>& range) {
        for (std::size_t i = range.begin(); i != range.end(); ++i) {
          JobResult& r = results[i];
          const auto tj = std::chrono::steady_clock::now();
          try {
            // Isolated: while this job waits inside its own parallel loops, its thread does not pick up another
            // job (whose warm-started FK state would then leak into this one's figures).
            tbb::this_task_arena::isolate([&] { run_job(jobs[i], r); });
          } catch (const InputError& e) {
            r = JobResult{};
            r.status = JobStatus::Failed;
            r.message = e.what();
          } catch (const std::exception& e) {
            r = JobResult{};
            r.status = JobStatus::InternalError;
            r.message = std::string("internal error: ") + e.what();
          }
          if (r.status != JobStatus::Ok)
            r.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - tj).count();
          progress.done(r.status != JobStatus::Ok);
        }
      });
    });
  }
  const double wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  std::size_t failed = 0, internal = 0;
  for (const auto& r : results) {
    failed += r.status == JobStatus::Failed;
    internal += r.status == JobStatus::InternalError;
  }
  if (json) {
    nlohmann::json j;
    j["files"] = nlohmann::json::array();
    for (std::size_t i = 0; i < jobs.size(); ++i) j["files"].push_back(job_json(jobs[i], results[i]));
    j["converted"] = jobs.size() - failed - internal;
    j["failed"] = failed + internal;
    j["seconds"] = wall_s;
    j["threads"] = threads;
    std::cout << j.dump(2) << "\n";
  } else {
    print_table(jobs, results, wall_s, threads);
    for (std::size_t i = 0; i < jobs.size(); ++i)
      for (const auto& w : results[i].warnings)
        std::cerr << "warning: " << fs::path(jobs[i].cl).filename().string() << ": " << w << "\n";
  }
  return internal ? 3 : failed ? 2 : 0;
}

// --- the jobs file -----------------------------------------------------------------------------------------
namespace {

class JobsReader {
 public:
  explicit JobsReader(std::string file) : file_(std::move(file)), dir_(fs::path(file_).parent_path()) {}

  [[noreturn]] void fail(const YAML::Node& n, const std::string& key, const std::string& what) const {
    SourceLoc where{file_, 0, 0};
    if (n.IsDefined() && n.Mark().line >= 0) {
      where.line = n.Mark().line + 1;
      where.column = n.Mark().column + 1;
    }
    throw InputError(where, key.empty() ? what : fmt::format("'{}': {}", key, what));
  }

  SourceLoc loc(const YAML::Node& n) const { return {file_, n.Mark().line + 1, n.Mark().column + 1}; }

  /// A path in the jobs file is relative to the jobs file.
  std::string path(const YAML::Node& n, const std::string& key) const {
    const std::string s = str(n, key);
    if (s.empty()) fail(n, key, "empty path");
    const fs::path p(s);
    return (p.is_absolute() ? p : dir_ / p).lexically_normal().string();
  }

  std::string str(const YAML::Node& n, const std::string& key) const {
    if (!n.IsScalar()) fail(n, key, "expected a single value");
    return n.Scalar();
  }

  double number(const YAML::Node& n, const std::string& key, bool positive_only = false) const {
    if (!n.IsScalar()) fail(n, key, "expected a number");
    double v = 0;
    try {
      v = n.as<double>();
    } catch (const YAML::Exception&) {
      fail(n, key, fmt::format("expected a number, got '{}'", n.Scalar()));
    }
    if (!std::isfinite(v) || v < 0 || (positive_only && v <= 0))
      fail(n, key,
           fmt::format("expected a {} number, got '{}'", positive_only ? "positive" : "non-negative", n.Scalar()));
    return v;
  }

  bool boolean(const YAML::Node& n, const std::string& key) const {
    if (!n.IsScalar()) fail(n, key, "expected true or false");
    try {
      return n.as<bool>();
    } catch (const YAML::Exception&) {
      fail(n, key, fmt::format("expected true or false, got '{}'", n.Scalar()));
    }
  }

  std::vector<std::string> paths(const YAML::Node& n, const std::string& key) const {
    std::vector<std::string> out;
    if (n.IsScalar()) {
      out.push_back(path(n, key));
    } else if (n.IsSequence()) {
      for (const auto& e : n) out.push_back(path(e, key));
    } else {
      fail(n, key, "expected a path or a list of paths");
    }
    return out;
  }

  /// A machine: a file relative to the jobs file if there is one, else a bundled machine name.
  std::string machine(const YAML::Node& n, const std::string& key) const {
    const std::string s = str(n, key);
    const fs::path p = fs::path(s).is_absolute() ? fs::path(s) : dir_ / s;
    if (fs::exists(p)) return p.lexically_normal().string();
    try {
      return resolve_machine(s);
    } catch (const InputError& e) {
      fail(n, key, e.message() + fmt::format(" (looked for {} and for a bundled machine '{}')", p.string(), s));
    }
  }

  /// Applies one job-setting key (shared by `defaults:` and each job). Returns false for an unknown key.
  bool apply(const std::string& k, const YAML::Node& v, PostJob& j) const {
    if (k == "machine") {
      j.machine = machine(v, k);
    } else if (k == "dialect") {
      j.dialect = str(v, k);
      const auto ds = post::dialects();
      if (std::find(ds.begin(), ds.end(), j.dialect) == ds.end())
        fail(v, k, fmt::format("unknown dialect '{}' (known: {})", j.dialect, fmt::join(ds, ", ")));
    } else if (k == "units") {
      j.units = str(v, k);
      try {
        parse_units(j.units);
      } catch (const InputError&) {
        fail(v, k, fmt::format("expected mm or inch, got '{}'", j.units));
      }
    } else if (k == "strategy") {
      const std::string s = str(v, k);
      if (s == "conventional")
        j.strategy = Strategy::Conventional;
      else if (s == "planner" || s == "cspace")
        j.strategy = Strategy::Planner;
      else
        fail(v, k, fmt::format("unknown strategy '{}' (known: conventional, planner)", s));
    } else if (k == "tolerance") {
      j.tolerance_mm = number(v, k);
    } else if (k == "axis_tolerance") {
      j.axis_tolerance_deg = number(v, k);
    } else if (k == "tool_length") {
      j.tool_length_mm = number(v, k, true);
    } else if (k == "cone") {
      j.cone_deg = number(v, k);
    } else if (k == "default_feed") {
      j.default_feed_mm_per_min = number(v, k, true);
    } else if (k == "linearise") {
      j.linearise = boolean(v, k);
    } else if (k == "tcp") {
      j.tcp = boolean(v, k);
    } else if (k == "work_plane") {
      j.work_plane = str(v, k);
      if (j.work_plane != "tilted" && j.work_plane != "machine")
        fail(v, k, fmt::format("expected tilted or machine, got '{}'", j.work_plane));
    } else if (k == "part") {
      j.parts = paths(v, k);
    } else if (k == "fixture") {
      j.fixtures = paths(v, k);
    } else {
      return false;
    }
    return true;
  }

  [[nodiscard]] const fs::path& dir() const { return dir_; }

 private:
  std::string file_;
  fs::path dir_;
};

constexpr const char* kJobKeys =
    "cl, output, machine, dialect, units, strategy, tolerance, axis_tolerance, tool_length, cone, default_feed, "
    "linearise, tcp, work_plane, part, fixture";

}  // namespace

std::vector<PostJob> read_jobs_file(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw InputError(SourceLoc{path}, "cannot open jobs file");
  YAML::Node root;
  try {
    root = YAML::Load(in);
  } catch (const YAML::ParserException& e) {
    throw InputError(SourceLoc{path, e.mark.line + 1, e.mark.column + 1}, "YAML syntax error: " + e.msg);
  }
  const JobsReader r(path);
  if (!root.IsMap()) r.fail(root, "", "a jobs file is a mapping with a 'jobs:' list (see docs/batch.md)");
  std::set<std::string> top_seen;
  PostJob defaults;
  fs::path out_dir = r.dir();
  std::optional<YAML::Node> jobs_node;
  for (const auto& kv : root) {
    const std::string k = r.str(kv.first, "");
    if (!top_seen.insert(k).second) r.fail(kv.first, k, "duplicate key");
    if (k == "output_dir") {
      out_dir = r.path(kv.second, k);
    } else if (k == "defaults") {
      if (!kv.second.IsMap()) r.fail(kv.second, k, "expected a mapping of job settings");
      std::set<std::string> seen;
      for (const auto& d : kv.second) {
        const std::string dk = r.str(d.first, k);
        if (!seen.insert(dk).second) r.fail(d.first, "defaults." + dk, "duplicate key");
        if (dk == "cl" || dk == "output") r.fail(d.first, "defaults." + dk, "is per job, not a default");
        if (!r.apply(dk, d.second, defaults))
          r.fail(d.first, "defaults." + dk, fmt::format("unknown key (known: {})", kJobKeys));
      }
    } else if (k == "jobs") {
      jobs_node = kv.second;
    } else {
      r.fail(kv.first, k, "unknown key (known: output_dir, defaults, jobs)");
    }
  }
  if (!jobs_node) r.fail(root, "jobs", "missing: the list of CL files to convert");
  if (!jobs_node->IsSequence() || jobs_node->size() == 0) r.fail(*jobs_node, "jobs", "expected a non-empty list");
  std::vector<PostJob> jobs;
  for (const auto& e : *jobs_node) {
    PostJob j = defaults;
    j.entry = r.loc(e);
    std::optional<YAML::Node> out_node;
    if (e.IsScalar()) {  // shorthand: just the CL file
      j.cl = r.path(e, "cl");
    } else if (e.IsMap()) {
      std::set<std::string> seen;
      for (const auto& kv : e) {
        const std::string k = r.str(kv.first, "");
        if (!seen.insert(k).second) r.fail(kv.first, k, "duplicate key");
        if (k == "cl")
          j.cl = r.path(kv.second, k);
        else if (k == "output")
          out_node = kv.second;
        else if (!r.apply(k, kv.second, j))
          r.fail(kv.first, k, fmt::format("unknown key (known: {})", kJobKeys));
      }
      if (j.cl.empty()) r.fail(e, "cl", "missing: the CL file of this job");
    } else {
      r.fail(e, "jobs", "each job is a CL path or a mapping with 'cl:'");
    }
    if (j.machine.empty()) r.fail(e, "machine", "missing: give it in the job or under 'defaults:'");
    if (j.strategy == Strategy::Conventional && j.cone_deg > 0) r.fail(e, "strategy", "cone needs 'strategy: planner'");
    if (j.strategy == Strategy::Planner && (j.axis_tolerance_deg > 0 || !j.linearise))
      r.fail(e, "strategy", "axis_tolerance and linearise: false are settings of the conventional post only");
    const fs::path stem_out = out_dir / (fs::path(j.cl).stem().string() + ".ngc");
    if (out_node) {
      const fs::path o(r.str(*out_node, "output"));
      if (o.empty()) r.fail(*out_node, "output", "empty path");
      const fs::path at = (o.is_absolute() ? o : out_dir / o).lexically_normal();
      // A folder (written with a trailing slash, or one that exists): the job's file goes into it under its stem.
      const std::string raw = r.str(*out_node, "output");
      const bool folder = raw.back() == '/' || fs::is_directory(at);
      j.out = folder ? (at / stem_out.filename()).lexically_normal().string() : at.string();
    } else {
      j.out = stem_out.lexically_normal().string();
    }
    jobs.push_back(std::move(j));
  }
  // Two jobs writing one file: the second is named with its line.
  std::map<std::string, const PostJob*> outs;
  for (const auto& j : jobs)
    if (const auto [it, fresh] = outs.emplace(fs::absolute(j.out).lexically_normal().string(), &j); !fresh)
      throw InputError(j.entry, fmt::format("output {} is also the output of the job at line {}: give one of them "
                                            "'output:'",
                                            j.out, it->second->entry.line));
  return jobs;
}

std::function<int()> add_batch_command(CLI::App& app) {
  struct Args {
    std::string jobs_file;
    bool json = false;
  };
  auto a = std::make_shared<Args>();
  auto* cmd = app.add_subcommand(
      "batch",
      "Convert the CL files listed in a jobs file (per-file machine, tool length, tolerances, dialect, "
      "strategy), in parallel (CSCAM_THREADS threads)");
  cmd->add_option("jobs", a->jobs_file, "jobs file (YAML; paths relative to it; see docs/batch.md)")->required();
  cmd->add_flag("--json", a->json, "print the summary as JSON");
  return [a, cmd]() -> int {
    if (!*cmd) return -1;
    const auto jobs = read_jobs_file(a->jobs_file);
    std::set<std::string> dirs;
    for (const auto& j : jobs) dirs.insert(fs::path(j.out).parent_path().string());
    for (const auto& d : dirs) make_output_dir(d);
    return run_jobs(jobs, a->json);
  };
}

}  // namespace cscam::cli
