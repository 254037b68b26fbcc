// Seed 001 (Oiwa & Shudo, parallel CMM calibrated with a redundant passive link), reproduced and extended:
//  A. passive-link lengths only: what the SVD says they cannot determine;
//  B. + probe-tip positions in W: Table 1 (given error / correction / difference for all 26 parameters,
//     noise-free), with the convergence history;
//  C. gauge noise 0.5 um: standard deviations and 100 seeded Monte-Carlo trials of 95 % coverage;
//  D. how many poses (and which) a target accuracy needs: D-optimal vs random poses.
// Usage: calib_seed001 [machines/pcmm.yaml]
#include <fmt/format.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <iostream>
#include <numeric>
#include <random>

#include "cscam/calib/calibrate.hpp"
#include "cscam/core/units.hpp"

using namespace cscam;

namespace {

/// The truth expressed in the convention ths1 = nominal (the stage frame's x axis is defined by joint 1).
std::vector<double> in_convention(const calib::Model& m, std::vector<double> t) {
  const double delta = t[m.index("ths1")] - m.nominal()[m.index("ths1")];
  for (const char* n : {"ths1", "ths2", "ths3"}) t[m.index(n)] -= delta;
  const double c = std::cos(deg2rad(-delta)), s = std::sin(deg2rad(-delta));
  const double sx = t[m.index("sx")], sy = t[m.index("sy")];
  t[m.index("sx")] = c * sx - s * sy;
  t[m.index("sy")] = s * sx + c * sy;
  return t;
}

}  // namespace

namespace {

int run(int argc, char** argv) {
  const std::string file = argc > 1 ? argv[1] : std::string(CSCAM_SOURCE_DIR) + "/machines/pcmm.yaml";
  const auto model = calib::load_model(file);
  const calib::Model& m = *model;
  const std::size_t n = m.size();
  std::mt19937_64 rng(2026);
  std::uniform_real_distribution<double> u(-0.5, 0.5);
  std::vector<double> truth = m.nominal();
  for (double& v : truth) v += u(rng);  // +-0.5 mm / +-0.5 deg on every parameter
  const auto poses = m.random_poses(45, 11);
  fmt::print("Seed 001 parallel CMM ({}), {} parameters, {} probe positions, errors up to +-0.5 mm / +-0.5 deg\n\n",
             file, n, poses.size());

  // ---- A. passive link only ----
  calib::Sigmas exact;
  exact.tip_mm = exact.len_mm = 0.0;
  calib::Dataset len = calib::simulate(m, truth, poses, {"len"}, exact, 1);
  len.sigma.len_mm = len.sigma.tip_mm = 0.001;
  const calib::Identifiability a = calib::analyse(m, len, m.nominal(), calib::Options{});
  fmt::print("A. passive-link lengths only: rank {} of {} (condition number of the identifiable subset {:.3g})\n",
             a.rank, n, a.condition_identified);
  for (const auto& msg : a.messages) fmt::print("   - {}\n", msg);
  fmt::print(
      "   The 7 null directions are the frames, which internal distances cannot see: the base may turn\n"
      "   about the passive link's base joint (3) and slide vertically with it (1); the stage frame may\n"
      "   slide (2) and turn (1) in its own plane.\n");
  {
    calib::Options oa;
    oa.max_iterations = 1000;  // the length-only subset is poorly conditioned: LM needs more steps
    const calib::Result r = calib::calibrate(m, len, oa);
    fmt::print(
        "   fit of the 19 identifiable combinations: {} after {} iterations ({}),\n   passive-link RMS {:.3e} -> "
        "{:.3e} mm\n\n",
        r.summary.termination, r.summary.iterations, r.summary.message, r.before.rms.at("len.link"),
        r.after.rms.at("len.link"));
  }

  // ---- B. passive link + probe tip (laser tracker or calibrated artefact): Table 1 ----
  calib::Dataset both = calib::simulate(m, truth, poses, {"len", "tip"}, exact, 1);
  both.sigma.len_mm = both.sigma.tip_mm = 0.001;
  const calib::Identifiability b = calib::analyse(m, both, m.nominal(), calib::Options{});
  fmt::print("B. + probe-tip positions in W: rank {} of {}\n", b.rank, n);
  for (const auto& c : b.combinations) fmt::print("   null space: {}\n", c);
  fmt::print(
      "   That is a naming convention, not geometry: ths1 defines the stage frame's x axis and stays at "
      "nominal.\n");
  calib::Options ob;
  ob.free = m.select({"all"});
  ob.free.erase(std::find(ob.free.begin(), ob.free.end(), m.index("ths1")));
  const auto t0 = std::chrono::steady_clock::now();
  const calib::Result rb = calib::calibrate(m, both, ob);
  const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  const std::vector<double> tc = in_convention(m, truth);
  fmt::print(
      "   {} after {} iterations, {:.1f} ms\n   convergence history (iteration: cost, largest correction step):\n",
      rb.summary.termination, rb.summary.iterations, ms);
  for (std::size_t i = 0; i < rb.summary.cost_history.size(); ++i)
    fmt::print("     {:2d}: {:.3e}  {:.3e}\n", i, rb.summary.cost_history[i], rb.summary.step_history[i]);
  fmt::print("\n   Table 1 (file units; the given error in the ths1 convention)\n");
  fmt::print("   {:<6} {:>14} {:>14} {:>12}\n", "param", "given error", "correction", "difference");
  double worst = 0;
  for (std::size_t i = 0; i < n; ++i) {
    const double given = tc[i] - m.nominal()[i], corr = rb.estimate[i] - m.nominal()[i];
    worst = std::max(worst, std::abs(given - corr));
    fmt::print("   {:<6} {:>+14.9f} {:>+14.9f} {:>12.1e}\n", m.params()[i].name, given, corr, given - corr);
  }
  fmt::print("   largest difference {:.2e} (target 1e-8)\n\n", worst);

  // ---- C. gauge noise 0.5 um: standard deviations, Monte-Carlo coverage ----
  calib::Sigmas noisy;
  noisy.len_mm = noisy.tip_mm = 0.0005;
  int inside = 0, total = 0;
  std::vector<double> sd(n, 0.0);
  double worst_ms = 0;
  for (int trial = 0; trial < 100; ++trial) {
    const calib::Dataset d =
        calib::simulate(m, truth, poses, {"len", "tip"}, noisy, 1000 + static_cast<unsigned>(trial));
    const auto s0 = std::chrono::steady_clock::now();
    const calib::Result r = calib::calibrate(m, d, ob);
    worst_ms =
        std::max(worst_ms, std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - s0).count());
    for (std::size_t i : ob.free) {
      ++total;
      if (std::abs(r.estimate[i] - tc[i]) <= 1.96 * r.stddev[i]) ++inside;
      if (trial == 0) sd[i] = r.stddev[i];
    }
  }
  fmt::print(
      "C. gauge noise sigma = 0.5 um (passive link and probe tip), 45 poses:\n   standard deviation per parameter:\n");
  for (std::size_t i : ob.free) fmt::print("     {:<6} {:.2e} {}\n", m.params()[i].name, sd[i], m.params()[i].unit);
  fmt::print(
      "   100 Monte-Carlo trials: the 95 % intervals cover the truth {:.1f} % of the time ({} of {}); slowest solve "
      "{:.1f} ms\n\n",
      100.0 * inside / total, inside, total, worst_ms);

  // ---- D. poses for a target accuracy ----
  // What a CMM needs is the probe tip: the true error of the calibrated model at 300 unseen positions.
  const double target_um = 0.3;
  const auto cand = m.random_poses(600, 5);
  const calib::Dataset unseen = calib::simulate(m, truth, m.random_poses(300, 123), {"tip"}, exact, 3);
  fmt::print(
      "D. poses needed for a probe-tip error (RMS over 300 unseen positions) <= {} um,\n"
      "   noise 0.5 um, passive link + tip (D-optimal from 600 candidates vs random):\n",
      target_um);
  fmt::print("   {:>5} {:>16} {:>16} {:>14} {:>14}\n", "poses", "D-opt tip um", "random tip um", "D-opt cond",
             "random cond");
  int need_d = -1, need_r = -1;
  std::vector<std::size_t> chosen_for_target;
  for (std::size_t N : {10, 15, 20, 30, 45, 60, 90}) {
    const auto idx = calib::select_poses(m, cand, {"len", "tip"}, ob.free, N);
    std::vector<std::vector<double>> dp, rp;
    for (std::size_t i : idx) dp.push_back(cand[i]);
    rp = m.random_poses(N, 99);
    auto tip_err = [&](const std::vector<std::vector<double>>& P, double& cond) {
      const calib::Dataset d = calib::simulate(m, truth, P, {"len", "tip"}, noisy, 7);
      calib::Options o = ob;
      o.rank_tolerance = 0;
      const calib::Result r = calib::calibrate(m, d, o);
      cond = r.ident.condition_identified;
      return 1000.0 * calib::residual_stats(m, unseen, r.estimate).rms.at("tip");
    };
    double cd = 0, cr = 0;
    const double ed = tip_err(dp, cd), er = tip_err(rp, cr);
    fmt::print("   {:>5} {:>16.3f} {:>16.3f} {:>14.3g} {:>14.3g}\n", N, ed, er, cd, cr);
    if (need_d < 0 && ed <= target_um) {
      need_d = static_cast<int>(N);
      chosen_for_target = idx;
    }
    if (need_r < 0 && er <= target_um) need_r = static_cast<int>(N);
  }
  fmt::print("   target reached with {} D-optimal poses, {} random poses\n",
             need_d < 0 ? std::string("> 90") : std::to_string(need_d),
             need_r < 0 ? std::string("> 90") : std::to_string(need_r));
  if (!chosen_for_target.empty()) {
    fmt::print("   the D-optimal poses (leg gauges q1, q2, q3 in mm; nominal tip in W, mm):\n");
    for (std::size_t i : chosen_for_target) {
      const auto p = m.predict(cand[i], m.nominal());
      fmt::print("     q = ({:8.3f}, {:8.3f}, {:8.3f})  tip = ({:8.2f}, {:8.2f}, {:8.2f})\n", cand[i][0], cand[i][1],
                 cand[i][2], p.tip.x(), p.tip.y(), p.tip.z());
    }
  }
  return worst <= 1e-8 ? 0 : 1;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc > 1 && (std::string(argv[1]) == "-h" || std::string(argv[1]) == "--help")) {
    fmt::print("usage: calib_seed001 [PCMM_MACHINE.yaml]  (default: machines/pcmm.yaml)\n");
    return 0;
  }
  try {
    return run(argc, argv);
  } catch (const std::exception& e) {
    fmt::print(stderr, "error: {}\n", e.what());
    return 2;
  }
}
