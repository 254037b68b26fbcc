#pragma once
// The calibration subcommand: `cscam calibrate`.
#include <CLI/CLI.hpp>
#include <functional>

namespace cscam::cli {

/// Adds `calibrate` to the app; returns a runner that executes it if chosen (-1 if not).
std::function<int()> add_calib_commands(CLI::App& app);

}  // namespace cscam::cli
