// Diagnosis benchmark: a 1,000,000-sample XMINI recording (tip + encoders; seed 000's X cut at ~57 kHz with
// lost motion on q2, a tooth-passing vibration and noise) written to disk, then read and diagnosed.
// Prints the time of every stage. Target: under 10 s on 2 cores.
#include <fmt/format.h>

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>

#include "cscam/core/atomic_file.hpp"
#include "cscam/diagnose/diagnose.hpp"
#include "cscam/sim/simulate.hpp"

using namespace cscam;
using Clock = std::chrono::steady_clock;

int main(int argc, char** argv) {
  const std::string src = CSCAM_SOURCE_DIR;
  const size_t target = argc > 1 ? static_cast<size_t>(std::stoul(argv[1])) : 1'000'000;
  const auto m = machine::load(src + "/machines/xmini.yaml");
  const auto blocks = sim::blocks_from_cl(src + "/examples/xmini/seed000_x_cut.cls", m, 50);
  sim::ProfileOptions po;
  po.rate_hz = 1000;
  const double T = sim::profile(blocks, po).t.back();
  po.rate_hz = static_cast<double>(target - 1) / T;
  auto t0 = Clock::now();
  const auto tr = sim::profile(blocks, po);
  auto b = sim::parse_effect("backlash:q2:0.015", m);
  auto v = sim::parse_effect("vibration:tip.z:166.67:0.00322", m);
  sim::SimulateOptions so;
  so.channels = {"tip", "enc"};
  so.noise = {{"tip", 0.001}, {"enc", 0.0002}};
  so.tool_length_mm = 50;
  so.spindle_rpm = 5000;
  so.flutes = 2;
  so.machine_ref = src + "/machines/xmini.yaml";
  const auto rec0 = sim::simulate(tr, m, {b.get(), v.get()}, so);
  const std::string path = (std::filesystem::temp_directory_path() / "cscam_diagnose_bench.csv").string();
  write_file_atomically(path, [&](std::ostream& os) { sim::write_recording(os, rec0); });
  const double t_make = std::chrono::duration<double>(Clock::now() - t0).count();
  std::cout << fmt::format("made {} samples at {:.0f} Hz ({} MB) in {:.2f} s (not part of the diagnosis)\n",
                           rec0.rows(), po.rate_hz, std::filesystem::file_size(path) >> 20, t_make);

  t0 = Clock::now();
  auto rec = sim::read_recording(path);
  const double t_read = std::chrono::duration<double>(Clock::now() - t0).count();
  const auto r = diagnose::diagnose(rec, m, {});
  const double total = std::chrono::duration<double>(Clock::now() - t0).count();
  std::cout << fmt::format("  {:<24} {:8.3f} s\n", "read", t_read);
  for (const auto& [k, s] : r.seconds) std::cout << fmt::format("  {:<24} {:8.3f} s\n", k, s);
  std::cout << fmt::format("  {:<24} {:8.3f} s  (target < 10 s on 2 cores)\n", "total", total);
  for (const auto& f : r.findings) {
    std::string ps;
    for (const auto& [k, x] : f.effect->reported()) ps += fmt::format(" {}={:.6g}", k, x);
    std::cout << fmt::format("  finding: {} {}:{}\n", f.effect->name(), f.effect->target, ps);
  }
  std::remove(path.c_str());
  return total < 10 ? 0 : 1;
}
