#pragma once
// Batch conversion: `cscam post A.cls B.cls ... -o DIR/` and `cscam batch JOBS.yaml`. Every file is one
// independent job (its own machine, tool length, tolerances, dialect, strategy); jobs run in parallel (TBB,
// CSCAM_THREADS) and a file that fails does not stop the others. A job writes exactly what a single
// `cscam post` / `cscam plan` run with the same settings writes, through the same safety gate.
#include <CLI/CLI.hpp>
#include <functional>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "cscam/core/error.hpp"

namespace cscam::cli {

/// How a job chooses the axis values: the conventional post or the C-space planner.
enum class Strategy { Conventional, Planner };

/// One CL file to convert and everything that decides its output.
struct PostJob {
  std::string cl;       ///< CL file path
  std::string machine;  ///< machine file path or bundled machine name
  std::string out;      ///< NC file to write
  std::string dialect, units;
  Strategy strategy = Strategy::Conventional;
  double tolerance_mm = 0, axis_tolerance_deg = 0, tool_length_mm = 0, default_feed_mm_per_min = 0;
  double cone_deg = 0;                       ///< planner only
  std::vector<std::string> parts, fixtures;  ///< meshes for collision checking (the planner's scene; the gate's)
  bool linearise = true;
  std::optional<bool> tcp;  ///< tool-tip control on/off; unset: the machine's post.tcp
  std::string work_plane;   ///< tilted | machine for 3+2 stretches; empty: the machine's post.work_plane
  SourceLoc entry;          ///< where the job was given (jobs file line); empty for the command line
};

enum class JobStatus { Ok, Failed, InternalError };

/// What one job did (like a solver summary: status, message, statistics).
struct JobResult {
  JobStatus status = JobStatus::Failed;
  std::string message;  ///< the gate's verdict when Ok, else the error (file:line: what)
  std::string machine_name;
  std::size_t cl_points = 0, blocks = 0, inserted_points = 0, reorientations = 0, retracts = 0;
  std::size_t narrowed_corners = 0, exact_corners = 0;  ///< corners whose control blend the post bounded
  double travel_mm = 0, travel_deg = 0;  ///< summed over the linear / rotary axes of the written program
  int reversals = 0;                     ///< direction changes, all axes
  double seconds = 0;
  double max_tip_deviation_mm = 0, max_axis_deviation_deg = 0, max_velocity_ratio = 0;
  std::vector<std::string> warnings;
  nlohmann::json stats;  ///< report::Stats of the written program
};

/// The figures of a written program (points, blocks, travel, reversals, the gate's verdict) into `j`: the same
/// fields for a single `post --json` and for each file of a batch.
void add_written_json(nlohmann::json& j, const JobResult& r);

/// Converts one file and writes its NC program through the safety gate. Throws InputError on bad input
/// (the caller decides whether that stops anything); fills `result` on success.
void run_job(const PostJob& job, JobResult& result);

/// Runs every job in parallel; prints a summary table (or JSON) on stdout and a progress line on stderr
/// when it is a terminal. Returns 0 when every job succeeded, 2 when any input was refused, 3 on an
/// internal error in any job.
int run_jobs(const std::vector<PostJob>& jobs, bool json);

/// Creates `dir` (and its parents) for outputs; an InputError naming it when that is impossible.
void make_output_dir(const std::string& dir);

/// Reads and validates a jobs file (paths relative to it); errors name the jobs file, line and key.
std::vector<PostJob> read_jobs_file(const std::string& path);

/// Adds `batch` to the app; returns a runner that executes it when chosen (-1 otherwise).
std::function<int()> add_batch_command(CLI::App& app);

}  // namespace cscam::cli
