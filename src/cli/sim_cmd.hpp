#pragma once
// The diagnosis subcommands: `cscam simulate` and `cscam diagnose`.
#include <CLI/CLI.hpp>
#include <functional>

namespace cscam::cli {

/// Adds `simulate` and `diagnose` to the app; returns a runner that executes whichever was chosen (-1 if none).
std::function<int()> add_sim_commands(CLI::App& app);

}  // namespace cscam::cli
