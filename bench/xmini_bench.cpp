// XMINI kinematics throughput. Target: >= 200,000 IK poses/s on one core, every branch and winding.
// Poses are random over the working volume (cylinder d 300, z -100..100, tilt <= 30 deg).
#include <benchmark/benchmark.h>

#include <cmath>
#include <random>
#include <vector>

#include "cscam/core/units.hpp"
#include "cscam/kin/xmini.hpp"

namespace {

using cscam::kPi;
using namespace cscam::kin;
using Vec3 = Eigen::Vector3d;

struct Pose {
  Vec3 tip, u;
};

std::vector<Pose> poses(std::size_t n) {
  std::mt19937_64 rng(20261122u);
  std::uniform_real_distribution<double> U(0.0, 1.0);
  const double cos_max = std::cos(cscam::deg2rad(30.0));
  std::vector<Pose> out;
  for (std::size_t i = 0; i < n; ++i) {
    const double r = 150.0 * std::sqrt(U(rng)), th = 2 * kPi * U(rng), z = -100.0 + 200.0 * U(rng);
    const double ct = 1.0 - (1.0 - cos_max) * U(rng), st = std::sqrt(1 - ct * ct), ph = 2 * kPi * U(rng);
    out.push_back({Vec3(r * std::cos(th), r * std::sin(th), z), Vec3(st * std::cos(ph), st * std::sin(ph), ct)});
  }
  return out;
}

/// The perturbed parameter set of tests/data/xmini-vectors.csv (every wrist offset non-zero, so
/// both wrist branches need their own Newton solve).
XminiParams<double> perturbed() {
  XminiParams<double> p = XminiParams<double>::nominal();
  const std::pair<const char*, double> kv[] = {
      {"theta0", 0.02}, {"eps_y", -0.015}, {"A1x", -150.3}, {"A3x", 149.8}, {"l1", 0.2},   {"l3", -0.15},
      {"A2x", 0.4},     {"A2y", 200.3},    {"A2z", -0.25},  {"b1x", -75.2}, {"b1z", 0.1},  {"b3x", 75.15},
      {"b3z", -0.2},    {"c2x", 0.3},      {"c2y", 99.8},   {"c2z", 0.2},   {"phi", 0.3},  {"chi", -0.2},
      {"L01", 450.4},   {"L02", 449.7},    {"L03", 450.2},  {"sCx", 0.2},   {"sCy", -0.1}, {"sCz", 150.3},
      {"gC1", 0.01},    {"gC2", -0.02},    {"c0", 0.05},    {"e", 0.1},     {"f", -0.15},  {"psi", 0.03},
      {"a0", -0.04},    {"gx", 0.05},      {"gy", -0.05},   {"gz", 100.2}};
  for (const auto& [name, value] : kv) p.set(name, value);
  return p;
}

void run_ik(benchmark::State& state, const XminiModel& model) {
  const std::vector<Pose> ps = poses(4096);
  std::vector<XminiIkSolution> out;
  out.reserve(16);
  std::size_t i = 0, solutions = 0, newton = 0;
  for (auto _ : state) {
    const Pose& p = ps[i++ & 4095];
    model.inverse(p.tip, p.u, out);
    solutions += out.size();
    for (const auto& s : out) newton += static_cast<std::size_t>(s.winding == 0 ? s.iterations : 0);
    benchmark::DoNotOptimize(out.data());
  }
  const double n = static_cast<double>(state.iterations());
  state.counters["poses/s"] = benchmark::Counter(n, benchmark::Counter::kIsRate);
  state.counters["solutions/pose"] = static_cast<double>(solutions) / n;
  state.counters["newton_it/pose"] = static_cast<double>(newton) / n;
}

void BM_XminiIkNominal(benchmark::State& state) { run_ik(state, XminiModel()); }
void BM_XminiIkPerturbed(benchmark::State& state) { run_ik(state, XminiModel(perturbed())); }

/// FK of joint vectors along a path (warm start from the previous point, the post's use) or shuffled
/// (range(0) = 1: cold start from home every time).
void BM_XminiFk(benchmark::State& state) {
  const XminiModel model(perturbed());
  const bool cold = state.range(0) != 0;
  std::vector<XminiJoints<double>> qs;
  for (const Pose& p : poses(4096)) qs.push_back(model.inverse(p.tip, p.u).front().joints());
  if (!cold) {  // a smooth path: small steps between consecutive joint vectors
    const XminiJoints<double> q0 = qs[0];
    for (std::size_t k = 0; k < qs.size(); ++k) {
      const double t = static_cast<double>(k) / static_cast<double>(qs.size());
      qs[k] = q0 + XminiJoints<double>(20 * t, -15 * t, 10 * t, 0.5 * t, 0.2 * t);
    }
  }
  XminiWorkspace ws;
  std::size_t i = 0, iterations = 0;
  for (auto _ : state) {
    if (cold) ws.reset();
    const auto fk = model.forward(qs[i++ & 4095], ws);
    iterations += static_cast<std::size_t>(fk.summary.iterations);
    benchmark::DoNotOptimize(fk.pose.tip_in_W_mm.data());
  }
  const double n = static_cast<double>(state.iterations());
  state.counters["fk/s"] = benchmark::Counter(n, benchmark::Counter::kIsRate);
  state.counters["newton_it"] = static_cast<double>(iterations) / n;
}

void BM_XminiJacobian(benchmark::State& state) {
  const XminiModel model(perturbed());
  std::vector<std::pair<XminiJoints<double>, XminiState<double>>> qs;
  for (const Pose& p : poses(1024)) {
    const XminiIkSolution s = model.inverse(p.tip, p.u).front();
    qs.emplace_back(s.joints(), s.state());
  }
  std::size_t i = 0;
  for (auto _ : state) {
    const auto& [q, x] = qs[i++ & 1023];
    const auto J = xmini_jacobian(model.geometry(), x, q, model.tool_length_mm());
    benchmark::DoNotOptimize(J.data());
  }
}

}  // namespace

BENCHMARK(BM_XminiIkNominal);
BENCHMARK(BM_XminiIkPerturbed);
BENCHMARK(BM_XminiFk)->Arg(0)->Arg(1);
BENCHMARK(BM_XminiJacobian);
