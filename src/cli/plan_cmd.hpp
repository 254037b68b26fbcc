#pragma once
// The planner's subcommands: `cscam plan` and `cscam compare`.
#include <CLI/CLI.hpp>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "cscam/core/units.hpp"

namespace cscam::cli {

/// Adds `plan` and `compare` to the app; returns a runner that executes whichever was chosen (or null).
std::function<int()> add_plan_commands(CLI::App& app);

/// The --units option: empty (decide from the CL file), mm or inch; anything else is an InputError.
std::optional<LengthUnit> parse_units(const std::string& s);

/// A machine by path or by bundled name (shared with main.cpp).
std::string resolve_machine(const std::string& arg);

}  // namespace cscam::cli
