#pragma once
// The planner's subcommands: `cscam plan` and `cscam compare`.
#include <CLI/CLI.hpp>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "cscam/cl/program.hpp"
#include "cscam/core/units.hpp"
#include "cscam/gate/gate.hpp"
#include "cscam/plan/plan.hpp"
#include "cscam/post/post.hpp"

namespace cscam::cli {

/// The options of `plan` and `compare` (also what a batch job with the planner strategy sets).
struct PlanArgs {
  std::string cl, machine, out, dialect, units, svg_dir, json_out;
  std::vector<std::string> parts, fixtures;
  double cone_deg = 0, min_tilt_deg = 0, resolution_deg = 1.0, clearance_mm = 0.5, tool_length = 0, tolerance = 0;
  double max_step_deg = 0, mesh_scale = 1.0, tilt_step_deg = 0;
  double default_feed = 0;  ///< mm/min for feed moves without a feed rate; 0: such a CL file is an error
  bool no_collision = false, json = false;
  bool no_machine_geometry = false;  ///< leave the machine file's bodies out of the scene
  std::optional<bool> tcp;           ///< tool-tip control on/off; unset: the machine's post.tcp
  std::string work_plane;            ///< tilted | machine for 3+2 segments; empty: the machine's post.work_plane
  std::size_t window = 0;            ///< plan in windows of this many moves; 0: automatic (above 50,000 moves)
  std::size_t beam = plan::Options{}.beam_states;  ///< tier 4's first beam width (states per point)
};

/// What plan_and_write did.
struct PlanWritten {
  std::string machine_name;
  std::string nc_text;  ///< the program written
  post::Summary post;
  gate::Summary gate;
  std::vector<std::string> warnings;  ///< CL reader and post warnings (not printed)
};

/// Plans `a.cl`, posts it and writes `out` through the safety gate, printing nothing (the batch form of
/// `cscam plan`: the same program byte for byte). Throws InputError on bad input or a refused program.
PlanWritten plan_and_write(const PlanArgs& a, const std::string& out);

/// The safety gate's collision check for a conventional post (gate::Options::make_collision): the moves against the
/// machine file's bodies and meshes, and `a.parts` / `a.fixtures`, with the machine's holder and the cutter in the
/// spindle: the CL's first cutter before any tool change, after the k-th change the cutter of `prog`'s k-th tool
/// change. Empty when there is nothing to check against, or no cutter size (then a warning).
std::function<gate::Options::CollisionCheck(int)> collision_for_post(const machine::Machine& m,
                                                                     const std::shared_ptr<const kin::Kinematics>& kin,
                                                                     double tool_length, const cl::Program& prog,
                                                                     const PlanArgs& a,
                                                                     std::vector<std::string>& warnings);

/// Adds `plan` and `compare` to the app; returns a runner that executes whichever was chosen (or null).
std::function<int()> add_plan_commands(CLI::App& app);

/// The --units option: empty (decide from the CL file), mm or inch; anything else is an InputError.
std::optional<LengthUnit> parse_units(const std::string& s);

/// The CL an NC program was posted from, read as the post read it: in the --units given, else in the unit the
/// program's header records (a note on stderr when that differs from the CL's own), else as the CL declares.
cl::Program read_cl_as_posted(const std::string& cl_path, const std::string& units_arg,
                              const std::optional<LengthUnit>& header_units, const std::string& nc_path);

/// A machine by path or by bundled name (shared with main.cpp).
std::string resolve_machine(const std::string& arg);
/// The machine a recording names (`# machine:`): beside the recording, in the working directory, in a folder above the
/// recording's (a project-relative path such as machines/xmini.yaml read from elsewhere), else the bundled machine of
/// that file name. Throws InputError naming it when none holds it.
std::string resolve_recorded_machine(const std::string& recording_file, const std::string& named);

}  // namespace cscam::cli
