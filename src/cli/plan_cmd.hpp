#pragma once
// The planner's subcommands: `cscam plan` and `cscam compare`.
#include <CLI/CLI.hpp>
#include <functional>
#include <string>
#include <vector>

namespace cscam::cli {

/// Adds `plan` and `compare` to the app; returns a runner that executes whichever was chosen (or null).
std::function<int()> add_plan_commands(CLI::App& app);

/// A machine by path or by bundled name (shared with main.cpp).
std::string resolve_machine(const std::string& arg);

}  // namespace cscam::cli
