#pragma once
// `cscam trace`: a servo trace recorded in LinuxCNC's motion controller (scripts/linuxcnc) against the CL path.
#include <CLI/CLI.hpp>
#include <functional>

namespace cscam::cli {

/// Adds `trace` to the app; returns a runner that executes it if it was chosen (-1 if not).
std::function<int()> add_trace_commands(CLI::App& app);

}  // namespace cscam::cli
