// Calibration benchmarks: seed 001's parallel CMM (26 parameters, 45 poses, passive link + probe tip)
// and the XMINI with every parameter a candidate (38), 500 laser-tracker poses, identifiability
// analysis included. Targets: < 100 ms and < 2 s.
#include <benchmark/benchmark.h>

#include <algorithm>
#include <random>

#include "cscam/calib/calibrate.hpp"

using namespace cscam;

namespace {

std::vector<double> perturb(const calib::Model& m, double amp, unsigned seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(-amp, amp);
  std::vector<double> p = m.nominal();
  for (double& v : p) v += u(rng);
  return p;
}

void BM_Seed001Pcmm26Params45Poses(benchmark::State& state) {
  const auto m = calib::load_model(std::string(CSCAM_SOURCE_DIR) + "/machines/pcmm.yaml");
  std::vector<double> truth = perturb(*m, 0.5, 5);
  truth[m->index("ths1")] = m->nominal()[m->index("ths1")];
  calib::Sigmas s;
  s.tip_mm = s.len_mm = 0.0005;
  const calib::Dataset d = calib::simulate(*m, truth, m->random_poses(45, 11), {"len", "tip"}, s, 1);
  calib::Options o;  // every parameter a candidate: the analysis fixes the stage frame's convention
  for (auto _ : state) {
    const calib::Result r = calib::calibrate(*m, d, o);
    benchmark::DoNotOptimize(r.estimate.data());
    state.counters["iterations"] = r.summary.iterations;
  }
}
BENCHMARK(BM_Seed001Pcmm26Params45Poses)->Unit(benchmark::kMillisecond);

void BM_XminiAllParams500Poses(benchmark::State& state) {
  const auto m = calib::load_model(std::string(CSCAM_SOURCE_DIR) + "/machines/xmini.yaml");
  std::vector<double> truth = perturb(*m, 0.2, 9);
  calib::Sigmas s;
  s.tip_mm = 0.002;
  const calib::Dataset d = calib::simulate(*m, truth, m->random_poses(500, 21), {"tip"}, s, 2);
  calib::Options o;
  for (auto _ : state) {
    const calib::Result r = calib::calibrate(*m, d, o);  // includes the identifiability analysis
    benchmark::DoNotOptimize(r.estimate.data());
    state.counters["iterations"] = r.summary.iterations;
    state.counters["rank"] = r.ident.rank;
  }
}
BENCHMARK(BM_XminiAllParams500Poses)->Unit(benchmark::kMillisecond);

void BM_XminiIdentifiabilityOnly500Poses(benchmark::State& state) {
  const auto m = calib::load_model(std::string(CSCAM_SOURCE_DIR) + "/machines/xmini.yaml");
  calib::Sigmas s;
  const calib::Dataset d = calib::simulate(*m, m->nominal(), m->random_poses(500, 21), {"tip"}, s, 2);
  for (auto _ : state) {
    const calib::Identifiability id = calib::analyse(*m, d, m->nominal(), calib::Options{});
    benchmark::DoNotOptimize(id.rank);
  }
}
BENCHMARK(BM_XminiIdentifiabilityOnly500Poses)->Unit(benchmark::kMillisecond);

}  // namespace

BENCHMARK_MAIN();
