// `cscam trace SAMPLES --machine M --cl CL`: FK of every servo cycle LinuxCNC's motion controller commanded
// (halsampler output of scripts/linuxcnc/run_program.py) and the tip's deviation from the CL path.
#include "trace_cmd.hpp"

#include <iostream>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>

#include "cscam/cl/program.hpp"
#include "cscam/core/error.hpp"
#include "cscam/machine/machine.hpp"
#include "cscam/nc/reader.hpp"
#include "cscam/report/letters.hpp"
#include "cscam/report/trace.hpp"
#include "cscam/report/verify.hpp"
#include "plan_cmd.hpp"
#include "validators.hpp"

namespace cscam::cli {

namespace {

struct TraceArgs {
  std::string samples, machine, cl, nc, units;
  double tolerance = 0, axis_tolerance = 0, tool_length = -1;
  bool json = false;
};

int cmd_trace(const TraceArgs& a) {
  const machine::Machine m = machine::load(resolve_machine(a.machine));
  double L = a.tool_length;
  std::optional<nc::Program> ncp;
  if (!a.nc.empty()) {
    // The program that ran: its header names the machine, the tool length and the CL unit it was posted for.
    ncp = nc::read_file(a.nc, report::axis_letters(m));
    if (auto mismatch = report::check_machine_of(*ncp, m)) throw *mismatch;
    if (L < 0 && ncp->tool_length_mm) L = *ncp->tool_length_mm;
  }
  const cl::Program prog = read_cl_as_posted(a.cl, a.units, ncp ? ncp->header_cl_units : std::nullopt, a.nc);
  if (L < 0) L = m.default_tool_length_mm;
  const auto kin = m.make_kinematics(L);
  if (ncp)  // tilted-plane words as the machine axes they move
    if (const std::string why = report::resolve_work_planes(*ncp, *kin); !why.empty()) throw InputError(why);
  std::array<bool, 5> rotary{};
  for (size_t i = 0; i < 5; ++i) rotary[i] = m.axes[i].rotary();
  const report::Trace trace = report::read_halsampler(a.samples, rotary);
  // The post's tolerances plus the slack for printed decimals, as verify; explicit values are the limit itself.
  const report::VerifyOptions vo = report::verify_options_for(m);
  report::TraceCheckOptions to;
  to.tip_tolerance_mm = a.tolerance > 0 ? a.tolerance : vo.tip_tolerance_mm;
  to.axis_tolerance_deg = a.axis_tolerance > 0 ? a.axis_tolerance : vo.axis_tolerance_deg;
  const report::TraceCheckResult r = report::check_trace(trace, prog, *kin, to, ncp ? &*ncp : nullptr);
  if (a.json)
    std::cout << r.json().dump(2) << "\n";
  else {
    std::cout << r.message << "\n";
    for (const auto& b : r.worst_blocks)
      std::cout << "  NC line " << b.nc_line << ": " << b.max_tip_deviation_mm << " mm over " << b.samples
                << " samples\n";
  }
  return r.ok ? 0 : 1;
}

}  // namespace

std::function<int()> add_trace_commands(CLI::App& app) {
  auto a = std::make_shared<TraceArgs>();
  auto* cmd = app.add_subcommand(
      "trace", "Compare a servo trace from LinuxCNC's motion controller (scripts/linuxcnc) with the CL path");
  cmd->add_option("samples", a->samples, "halsampler -t output of scripts/linuxcnc/run_program.py")->required();
  cmd->add_option("-m,--machine", a->machine, "machine file or bundled machine name")->required();
  cmd->add_option("--cl", a->cl, "the CL file the program was posted from")->required();
  cmd->add_option("--nc", a->nc,
                  "the program that ran: its header gives machine and tool length; its retracts and plunges along "
                  "the tool axis off the CL path are not compared");
  cmd->add_option("--units", a->units, "force the CL units (mm or inch)");
  cmd->add_option("--tolerance", a->tolerance, "allowed tip deviation, mm (default: the post's tolerance + slack)")
      ->check(cli::kPositive);
  cmd->add_option("--axis-tolerance", a->axis_tolerance, "allowed tool-axis deviation, deg")->check(cli::kPositive);
  cmd->add_option("--tool-length", a->tool_length, "tool length, mm (default: NC header, else machine file)")
      ->check(cli::kNonNegative);
  cmd->add_flag("--json", a->json, "print the result as JSON");
  return [cmd, a]() { return *cmd ? cmd_trace(*a) : -1; };
}

}  // namespace cscam::cli
