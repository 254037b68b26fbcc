#include "cscam/diagnose/diagnose.hpp"

#include <ceres/ceres.h>
#include <fftw3.h>
#include <fmt/format.h>
#include <fmt/ranges.h>

#include <Eigen/Dense>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <complex>
#include <mutex>
#include <nlohmann/json.hpp>
#include <numeric>
#include <sstream>
#include <thread>

#include "cscam/calib/model.hpp"
#include "cscam/core/error.hpp"
#include "cscam/core/threads.hpp"
#include "cscam/core/units.hpp"
#include "cscam/sim/simulate.hpp"

namespace cscam::diagnose {

namespace {

/// f(w) for w = 0 .. nt-1 on nt threads (each worker's share is fixed, so the results do not depend on scheduling);
/// the first exception a worker throws is rethrown here, after every worker has joined.
template <class F>
void on_workers(size_t nt, const F& f) {
  std::vector<std::thread> th;
  std::vector<std::exception_ptr> err(nt);
  for (size_t w = 0; w < nt; ++w)
    th.emplace_back([&, w] {
      try {
        f(w);
      } catch (...) {
        err[w] = std::current_exception();
      }
    });
  for (auto& t : th) t.join();
  for (auto& e : err)
    if (e) std::rethrow_exception(e);
}

using sim::Context;
using sim::Effect;
using sim::Scope;
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
/// A noise estimate is lowered after a finding only when it falls by more than this factor (not for the spread of
/// the estimate itself).
constexpr double kNoiseRefit = 0.9;
/// A channel's constant offset is reported when it exceeds this many noise sigmas.
constexpr double kOffsetNoted = 5.0;
/// No measurement system resolves below this (mm or deg): the floor of the noise estimate.
constexpr double kNoiseFloor = 2e-5;
/// A thermal drift's time constant stays above this share of the run (see the fit's bounds).
constexpr double kThermalDriftMinTau = 0.05;
/// The same for a tool direction (a unit vector: radians): 0.2 urad. The floor in mm hid a 25 urad drift of `dir` under
/// a noise "estimate" of 20 urad per component.
constexpr double kNoiseFloorDir = 2e-7;

enum class Kind { Tip, PTip, Dir, Enc, Acc };

struct Comp {
  std::string name, group;
  Kind kind = Kind::Tip;
  int idx = 0;  ///< xyz component or axis index
  int col = -1;
  double sigma = kNoiseFloor;
  bool fit = true;
  std::vector<double> res_full;  ///< measured - predicted at every row
  std::vector<double> res;       ///< at the analysis samples
};

struct Peak {
  double f = 0, amp = 0;
};

double floor_of(const Comp& c) { return c.kind == Kind::Dir ? kNoiseFloorDir : kNoiseFloor; }

using Clock = std::chrono::steady_clock;
double secs(Clock::time_point a) { return std::chrono::duration<double>(Clock::now() - a).count(); }

/// Periodogram |X_k|^2 of x (mean removed) with FFTW; frequencies k * fs / n.
std::vector<double> periodogram(const std::vector<double>& x) {
  const size_t n = x.size();
  if (n < 8) return {};
  double mean = 0;
  for (double v : x) mean += v;
  mean /= static_cast<double>(n);
  static std::mutex plan_mutex;  // FFTW planning is not thread-safe
  double* in = fftw_alloc_real(n);
  fftw_complex* out = fftw_alloc_complex(n / 2 + 1);
  fftw_plan p;
  {
    std::lock_guard<std::mutex> lk(plan_mutex);
    p = fftw_plan_dft_r2c_1d(static_cast<int>(n), in, out, FFTW_ESTIMATE);
  }
  for (size_t i = 0; i < n; ++i) in[i] = x[i] - mean;
  fftw_execute(p);
  std::vector<double> P(n / 2 + 1);
  for (size_t k = 0; k <= n / 2; ++k) P[k] = out[k][0] * out[k][0] + out[k][1] * out[k][1];
  {
    std::lock_guard<std::mutex> lk(plan_mutex);
    fftw_destroy_plan(p);
  }
  fftw_free(in);
  fftw_free(out);
  return P;
}

double median(std::vector<double> v) {
  if (v.empty()) return 0;
  auto mid = v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2);
  std::nth_element(v.begin(), mid, v.end());
  return *mid;
}

/// The recording's sampling clock. A control logs on a fixed clock; a recording with rows missing (a logger that
/// stalls, a dropped packet) keeps the others on that clock. The spectra are taken on that regular grid, each sample
/// in its own slot and the missing slots left out (zero once the mean is removed, as a missing cell is): the FFT then
/// sees a vibration at its true frequency and phase, where the mean rate (rows / duration) put 47 Hz at 45.4 Hz. Not a
/// Lomb-Scargle periodogram: that costs rows x frequencies (10^9 for a 10^5-row recording over its whole band); not
/// interpolation across the gaps, which smears a vibration that the gap interrupts.
struct TimeGrid {
  double dt = 0;                 ///< the sampling interval: the median time step
  size_t slots = 0;              ///< length of the regular grid
  std::vector<size_t> slot;      ///< grid slot of every row (kNoSlot: outside the analysed stretch)
  size_t gaps = 0, missing = 0;  ///< time steps longer than 1.5 intervals, and the rows they leave out
  double largest_gap_s = 0, largest_gap_at_s = 0;
  size_t off_grid = 0;        ///< rows more than a quarter interval off their slot (jittered stamps)
  double scatter_s = 0;       ///< robust RMS of the stamps about their slots (1.4826 x the median |offset|), s
  bool stretch_only = false;  ///< the grid would be mostly empty: only the longest stretch without a gap is used
  static constexpr size_t kNoSlot = std::numeric_limits<size_t>::max();
};

TimeGrid time_grid(const std::vector<double>& t) {
  TimeGrid g;
  const size_t n = t.size();
  g.slot.assign(n, TimeGrid::kNoSlot);
  if (n < 2) return g;
  std::vector<double> d(n - 1);
  for (size_t i = 1; i < n; ++i) d[i - 1] = t[i] - t[i - 1];
  std::vector<double> ds = d;
  std::nth_element(ds.begin(), ds.begin() + static_cast<std::ptrdiff_t>(ds.size() / 2), ds.end());
  g.dt = ds[ds.size() / 2];
  if (!(g.dt > 0)) return g;
  size_t run_a = 0, best_a = 0, best_b = n;  // the longest stretch without a gap: rows [best_a, best_b)
  size_t best_len = 0;
  for (size_t i = 1; i <= n; ++i) {
    const bool gap = i < n && d[i - 1] > 1.5 * g.dt;
    if (i < n && gap) {
      ++g.gaps;
      g.missing += static_cast<size_t>(std::max(0.0, std::round(d[i - 1] / g.dt) - 1));
      if (d[i - 1] > g.largest_gap_s) g.largest_gap_s = d[i - 1], g.largest_gap_at_s = t[i - 1];
    }
    if (i == n || gap) {
      if (i - run_a > best_len) best_len = i - run_a, best_a = run_a, best_b = i;
      run_a = i;
    }
  }
  // The median step is the clock's interval rounded as the file prints it (0.002857 for 1/350 s): over 13000 rows
  // that rounding adds up to more than an interval. The mean step of the longest stretch without a gap is exact to
  // the rounding over its length; the whole span in those steps, rounded to whole intervals, then fixes it.
  if (best_len >= 2) g.dt = (t[best_b - 1] - t[best_a]) / static_cast<double>(best_len - 1);
  const double whole = std::round((t.back() - t.front()) / g.dt);
  if (whole >= 1) g.dt = (t.back() - t.front()) / whole;
  const double span = (t.back() - t.front()) / g.dt;
  // A grid mostly empty (gaps longer than the data between them) has a spectral window of many side lobes: the
  // longest regular stretch tells the frequencies better then.
  size_t a = 0, b = n;
  if (span > 4.0 * static_cast<double>(n) && best_len >= 64) a = best_a, b = best_b, g.stretch_only = true;
  // The scatter about the clock's phase (the circular mean of the stamps' fractional positions: the first stamp's own
  // offset must not bias every other).
  double sum_c = 0.0, sum_s = 0.0;
  for (size_t i = a; i < b; ++i) {
    const double x = (t[i] - t[a]) / g.dt;
    g.slot[i] = static_cast<size_t>(std::llround(x));
    if (std::abs(x - static_cast<double>(g.slot[i])) > 0.25) ++g.off_grid;
    sum_c += std::cos(2.0 * kPi * x), sum_s += std::sin(2.0 * kPi * x);
  }
  const double phase = std::atan2(sum_s, sum_c) / (2.0 * kPi);
  std::vector<double> off;
  off.reserve(b - a);
  for (size_t i = a; i < b; ++i) {
    const double x = (t[i] - t[a]) / g.dt - phase;
    off.push_back(std::abs(x - std::round(x)));
  }
  g.scatter_s = 1.4826 * median(std::move(off)) * g.dt;
  g.slots = g.slot[b - 1] + 1;
  return g;
}

/// A residual on the grid: mean of the samples present removed, missing slots 0; `present` counts the samples.
std::vector<double> on_grid(const std::vector<double>& x, const TimeGrid& g, size_t& present) {
  std::vector<double> y(g.slots, 0.0);
  std::vector<unsigned> cnt(g.slots, 0);
  double mean = 0;
  present = 0;
  for (size_t i = 0; i < x.size(); ++i)
    if (g.slot[i] != TimeGrid::kNoSlot && !std::isnan(x[i])) mean += x[i], ++present;
  if (present == 0) return y;
  mean /= static_cast<double>(present);
  for (size_t i = 0; i < x.size(); ++i)
    if (g.slot[i] != TimeGrid::kNoSlot && !std::isnan(x[i])) y[g.slot[i]] += x[i] - mean, ++cnt[g.slot[i]];
  size_t used = 0;
  for (size_t k = 0; k < g.slots; ++k)
    if (cnt[k] > 1) y[k] /= cnt[k];  // two stamps rounded to one slot (jitter): their mean
  for (size_t k = 0; k < g.slots; ++k) used += cnt[k] > 0;
  present = used;
  return y;
}

/// White noise of variance s^2 gives E|X_k|^2 = n s^2 and a median of n s^2 ln 2: the noise from the
/// median of the upper half of the band (smooth effects live at low frequencies, peaks are few).
double noise_from_spectrum(const std::vector<double>& P, size_t n, double floor = kNoiseFloor) {
  if (P.size() < 8) return floor;
  std::vector<double> hi(P.begin() + static_cast<std::ptrdiff_t>(P.size() / 2), P.end() - 1);
  return std::max(floor, std::sqrt(median(hi) / (static_cast<double>(n) * std::log(2.0))));
}

/// The frequency (in bins of the length-n grid, fractional) where the periodogram of `y` peaks near bin `k_bin`: the
/// maximum of |X(w)|^2, X(w) = sum y_k e^{-iwk}, within a bin of `k_bin`. That maximum is the least-squares frequency
/// of one sinusoid in white noise; an interpolation between FFT bins is off by up to a tenth of a bin, which over a run
/// of 20 s drifts the fitted sinusoid's phase by 30 deg or more (the frequency is not refitted: the fits subsample in
/// time). |X|^2 is first scanned on a fine grid over +-1 bin, then Newton's method polishes the best point of the
/// scan within one scan step. The scan is what makes this hold for a recording with gaps: there the periodogram is
/// fringed (the spectral window of two stretches of data has side lobes about a bin apart), so Newton from a
/// parabolic guess between bins can start in a trough or on the slope of the wrong fringe and stop there (it ran
/// only while the curvature is negative, and was clamped to half a bin of the FFT's bin).
double refine_peak(const std::vector<double>& y, double k_bin) {
  const auto n = static_cast<double>(y.size());
  double mean = 0;
  for (double v : y) mean += v;
  mean /= n;
  // |X|^2 and its first two derivatives in w (sums of y_k (-ik)^j e^{-iwk}, j = 0, 1, 2); the phasor e^{-iwk} by
  // rotation, renormalised now and then against the rounding's drift.
  auto eval = [&](double ww, double& q, double& dq, double& ddq) {
    std::complex<double> x0, x1, x2;
    const std::complex<double> step = std::polar(1.0, -ww);
    std::complex<double> e = 1.0;
    for (size_t k = 0; k < y.size(); ++k) {
      if ((k & 1023) == 0) e = std::polar(1.0, -ww * static_cast<double>(k));
      const double kk = static_cast<double>(k);
      const std::complex<double> v = (y[k] - mean) * e;
      x0 += v;
      x1 += std::complex<double>(0.0, -kk) * v;
      x2 += -kk * kk * v;
      e *= step;
    }
    q = std::norm(x0);
    dq = 2.0 * std::real(x1 * std::conj(x0));
    ddq = 2.0 * (std::norm(x1) + std::real(x2 * std::conj(x0)));
  };
  // |X|^2 alone, for the scan.
  auto power = [&](double ww) {
    std::complex<double> x0;
    const std::complex<double> step = std::polar(1.0, -ww);
    std::complex<double> e = 1.0;
    for (size_t k = 0; k < y.size(); ++k) {
      if ((k & 1023) == 0) e = std::polar(1.0, -ww * static_cast<double>(k));
      x0 += (y[k] - mean) * e;
      e *= step;
    }
    return std::norm(x0);
  };
  constexpr int kScan = 16;  // steps per bin: a fringe of a gapped recording is at least a bin wide
  const double dw = 2.0 * kPi / n / kScan;
  double w = 2.0 * kPi * k_bin / n, best = -1;
  for (int j = -kScan; j <= kScan; ++j) {
    const double wj = 2.0 * kPi * k_bin / n + j * dw;
    const double qj = power(wj);
    if (qj > best) w = wj, best = qj;
  }
  double q = 0, dq = 0, ddq = 0;
  eval(w, q, dq, ddq);
  const double w_lo = w - dw, w_hi = w + dw;
  for (int it = 0; it < 8 && ddq < 0.0; ++it) {
    const double wn = std::clamp(w - dq / ddq, w_lo, w_hi);
    double qn = 0, dqn = 0, ddqn = 0;
    eval(wn, qn, dqn, ddqn);
    if (!(qn >= q)) break;  // Newton overshot where the peak is not a parabola: keep the better point
    const bool done = std::abs(wn - w) < 1e-6 / n;
    w = wn, q = qn, dq = dqn, ddq = ddqn;
    if (done) break;
  }
  return w * n / (2.0 * kPi);
}

/// Spectral peaks: local maxima far above the local median level, at least a few cycles per run.
/// `n`: the grid's length (frequency k fs / n); `present`: the samples on it (the amplitude: 2 |X_k| / present);
/// `y`: the series on the grid (for the peaks' exact frequencies).
std::vector<Peak> find_peaks(const std::vector<double>& P, const std::vector<double>& y, size_t n, size_t present,
                             double fs, double duration, const std::vector<double>& known = {}) {
  std::vector<Peak> out;
  if (P.size() < 16) return out;
  const double gmed = median(std::vector<double>(P.begin() + 1, P.end()));
  std::vector<size_t> cand;
  const double fmin = std::max(1.0, 5.0 / std::max(duration, 1e-9));
  for (size_t k = 2; k + 1 < P.size(); ++k) {
    const double f = static_cast<double>(k) * fs / static_cast<double>(n);
    if (f < fmin) continue;
    if (!(P[k] > P[k - 1] && P[k] >= P[k + 1] && P[k] > 40 * gmed)) continue;
    // A frequency already known (a peak found before): not searched again.
    if (std::any_of(known.begin(), known.end(),
                    [&](double fk) { return std::abs(fk - f) < 3 * fs / static_cast<double>(n); }))
      continue;
    cand.push_back(k);
  }
  std::sort(cand.begin(), cand.end(), [&](size_t a, size_t b) { return P[a] > P[b]; });
  if (cand.size() > 60) cand.resize(60);
  for (size_t k : cand) {
    const size_t w = std::max<size_t>(20, k / 10);
    const size_t a = k > w ? k - w : 1, b = std::min(P.size() - 1, k + w);
    std::vector<double> loc(P.begin() + static_cast<std::ptrdiff_t>(a), P.begin() + static_cast<std::ptrdiff_t>(b));
    if (P[k] < 40 * median(loc)) continue;
    Peak pk;
    pk.f = refine_peak(y, static_cast<double>(k)) * fs / static_cast<double>(n);
    pk.amp = 2.0 * std::sqrt(P[k]) / static_cast<double>(std::max<size_t>(present, 1));
    bool dup = false;
    for (const auto& q : out) dup |= std::abs(q.f - pk.f) < 3 * fs / static_cast<double>(n);
    if (!dup) out.push_back(pk);
    if (out.size() >= 4) break;
  }
  return out;
}

std::string fmt_um(double mm) { return fmt::format("{:.1f} um", mm * 1000); }

/// A residual of channel group `g` in its own unit: a rotary encoder's in degrees, a direction's (a unit vector's
/// difference, i.e. radians) in microradians, a length in micrometres.
std::string fmt_group(const machine::Machine& m, const std::string& g, double v) {
  if (g == "dir") return fmt::format("{:.1f} urad", v * 1e6);
  if (g.rfind("enc.", 0) == 0)
    for (const auto& a : m.axes)
      if (g == "enc." + a.name && a.rotary()) return fmt::format("{:.4f} deg", v);
  return fmt_um(v);
}

std::string fmt_value(const std::string& unit_group, double v) {
  return unit_group == "deg" ? fmt::format("{:.4f} deg", v) : fmt_um(v);
}

/// Samples far off both neighbours (a tracker's beam break, a dropped bit): one such sample of 3 mm raised the noise
/// estimate of the whole channel 40-fold (the spectrum of a spike is flat) and hid a 10 um lost motion. A sample is
/// left out (made missing, with a warning) when it stands more than kGlitchScales robust difference scales (1.4826 MAD
/// of the first differences) from both neighbours on the same side; not within 3 samples of a reversal of any axis,
/// where a real spike (stick-slip) lives.
void drop_glitches(std::vector<Comp>& comps, const std::vector<kin::Axes>& cmd, const std::vector<double>& t,
                   std::vector<std::string>& warnings) {
  constexpr double kGlitchScales = 50.0;
  const std::size_t n = cmd.size();
  if (n < 5) return;
  std::vector<char> near_reversal(n, 0);
  for (int a = 0; a < 5; ++a) {
    double dir = 0;
    for (std::size_t i = 1; i < n; ++i) {
      const double dq = cmd[i][a] - cmd[i - 1][a];
      if (std::abs(dq) <= 1e-12) continue;
      const double nd = dq > 0 ? 1 : -1;
      if (dir != 0 && nd != dir)
        for (std::size_t j = i > 3 ? i - 3 : 0; j < std::min(n, i + 4); ++j) near_reversal[j] = 1;
      dir = nd;
    }
  }
  for (auto& c : comps) {
    auto& r = c.res_full;
    std::vector<double> d;
    d.reserve(n);
    for (std::size_t i = 1; i < n; ++i)
      if (!std::isnan(r[i]) && !std::isnan(r[i - 1])) d.push_back(std::abs(r[i] - r[i - 1]));
    if (d.size() < 4) continue;
    std::nth_element(d.begin(), d.begin() + static_cast<std::ptrdiff_t>(d.size() / 2), d.end());
    const double scale = 1.4826 * d[d.size() / 2];  // |d| of a zero-median difference: its median is the MAD
    if (!(scale > 0)) continue;
    std::vector<std::size_t> dropped;
    for (std::size_t i = 1; i + 1 < n; ++i) {
      if (near_reversal[i] || std::isnan(r[i]) || std::isnan(r[i - 1]) || std::isnan(r[i + 1])) continue;
      const double a = r[i] - r[i - 1], b = r[i] - r[i + 1];
      if (a * b > 0 && std::min(std::abs(a), std::abs(b)) > kGlitchScales * scale) dropped.push_back(i);
    }
    const double first_off =
        dropped.empty() ? 0.0 : r[dropped.front()] - 0.5 * (r[dropped.front() - 1] + r[dropped.front() + 1]);
    for (const std::size_t i : dropped) r[i] = std::numeric_limits<double>::quiet_NaN();
    if (!dropped.empty())
      warnings.push_back(fmt::format(
          "{}: {} isolated sample(s) more than {:.0f} noise scales off both neighbours left out as glitches (a beam "
          "break, a dropped bit), the first at t = {:.4f} s ({:.4g} off)",
          c.name, dropped.size(), kGlitchScales, t[dropped.front()], first_off));
  }
}

/// Everything the fits need, at the analysis samples.
struct Fit {
  const Context* ctx = nullptr;
  std::vector<Comp>* comps = nullptr;
  std::vector<int> fitc;                       ///< indices of fitted components
  std::vector<Eigen::Matrix<double, 9, 5>> J;  ///< FK Jacobian per analysis sample
  std::vector<Eigen::Matrix3d> Rpw;            ///< machine frame -> part frame per analysis sample (tool.* effects)
  std::vector<char> held;                      ///< held-out flag per analysis sample
  std::vector<double> off;                     ///< offset per component (index into comps)
  double sample_s = 0.0;                       ///< the recording's sample interval (what a transient must outlast)

  [[nodiscard]] double sens(const Comp& c, const Effect& e, size_t k) const {
    if (e.scope() == Scope::Channel) {
      if (e.channel.rfind("tool.", 0) != 0) return c.name == e.channel ? 1.0 : 0.0;
      const int w = e.channel.back() - 'x';  // the tool point moves along W's axis w: in tip as it is, in ptip turned
      if (c.kind == Kind::Tip) return c.idx == w ? 1.0 : 0.0;
      if (c.kind == Kind::PTip) return Rpw[k](c.idx, w);
      return 0.0;
    }
    if (e.scope() == Scope::Geometric) {
      const auto& g = (*e.geo_sens)[k];
      switch (c.kind) {
        case Kind::Tip:
          return g[static_cast<size_t>(c.idx)];
        case Kind::PTip:
          return g[3 + static_cast<size_t>(c.idx)];
        case Kind::Dir:
          return g[6 + static_cast<size_t>(c.idx)];
        default:
          return 0.0;
      }
    }
    switch (c.kind) {
      case Kind::Tip:
        return J[k](c.idx, e.axis);
      case Kind::PTip:
        return J[k](3 + c.idx, e.axis);
      case Kind::Dir:
        return J[k](6 + c.idx, e.axis);
      case Kind::Enc:
        return (c.idx == e.axis && e.enc_visible) ? 1.0 : 0.0;
      case Kind::Acc:
        return 0.0;
    }
    return 0.0;
  }
  /// Does effect e reach component c at all?
  [[nodiscard]] bool reaches(const Comp& c, const Effect& e) const {
    if (e.scope() == Scope::Channel)
      return e.channel.rfind("tool.", 0) == 0 ? (c.kind == Kind::Tip || c.kind == Kind::PTip) : c.name == e.channel;
    if (c.kind == Kind::Enc) return e.scope() == Scope::Axis && c.idx == e.axis && e.enc_visible;
    return c.kind != Kind::Acc;
  }
};

/// Residual after the model at analysis sample k for component c.
double model_residual(const Fit& f, const std::vector<const Effect*>& fx, int ci, size_t k) {
  const Comp& c = (*f.comps)[static_cast<size_t>(ci)];
  double r = c.res[k] - f.off[static_cast<size_t>(ci)];
  for (const Effect* e : fx)
    if (f.reaches(c, *e)) r -= f.sens(c, *e, k) * e->value(*f.ctx, k, e->p.data());
  return r;
}

/// Noise-weighted mean square on the held-out (held = 1) or training (held = 0) samples.
double weighted_ms(const Fit& f, const std::vector<const Effect*>& fx, bool held) {
  double s = 0;
  size_t cnt = 0;
  for (int ci : f.fitc) {
    const Comp& c = (*f.comps)[static_cast<size_t>(ci)];
    for (size_t k = 0; k < f.ctx->size(); ++k) {
      if (static_cast<bool>(f.held[k]) != held || std::isnan(c.res[k])) continue;
      const double r = model_residual(f, fx, ci, k) / c.sigma;
      s += r * r;
      ++cnt;
    }
  }
  return cnt ? s / static_cast<double>(cnt) : 0.0;
}

/// The noise level of a component's residual under a model, from the spectrum of the analysis samples (missing
/// cells as zeros). Compared only with itself under another model: the analysis samples may be strided, so their
/// upper band is not the full recording's.
double analysis_noise(const Fit& f, const std::vector<const Effect*>& fx, int ci) {
  const Comp& c = (*f.comps)[static_cast<size_t>(ci)];
  std::vector<double> r(f.ctx->size(), 0.0);
  for (size_t k = 0; k < r.size(); ++k)
    if (!std::isnan(c.res[k])) r[k] = model_residual(f, fx, ci, k);
  return noise_from_spectrum(periodogram(r), r.size(), floor_of(c));
}

/// Held-out RMS of a channel group (vector RMS for tip/ptip/dir) under a model.
/// `mask` (optional) restricts it to the samples where an effect acts.
double group_rms(const Fit& f, const std::vector<const Effect*>& fx, const std::string& group, bool held,
                 const std::vector<char>* mask = nullptr) {
  double s = 0;
  std::vector<char> any(f.ctx->size(), 0);
  for (int ci : f.fitc) {
    const Comp& c = (*f.comps)[static_cast<size_t>(ci)];
    if (c.group != group) continue;
    for (size_t k = 0; k < f.ctx->size(); ++k) {
      if (static_cast<bool>(f.held[k]) != held || std::isnan(c.res[k])) continue;
      if (mask && !(*mask)[k]) continue;
      const double r = model_residual(f, fx, ci, k);
      s += r * r;
      any[k] = 1;
    }
  }
  const auto cnt = static_cast<double>(std::count(any.begin(), any.end(), 1));
  return cnt > 0 ? std::sqrt(s / cnt) : 0.0;
}

/// Ceres cost over a chunk of training samples: weighted residuals of every fitted component.
class ChunkCost final : public ceres::CostFunction {
 public:
  ChunkCost(const Fit& f, const std::vector<Effect*>& fx, std::vector<size_t> samples)
      : f_(f), fx_(fx), s_(std::move(samples)) {
    set_num_residuals(static_cast<int>(s_.size() * f_.fitc.size()));
    for (const Effect* e : fx_) mutable_parameter_block_sizes()->push_back(static_cast<int>(e->p.size()));
    mutable_parameter_block_sizes()->push_back(static_cast<int>(f_.comps->size()));
  }
  bool Evaluate(double const* const* params, double* residuals, double** jac) const override {
    const size_t E = fx_.size(), nc = f_.fitc.size();
    const size_t ncomp = f_.comps->size();
    std::vector<double> val(E);
    std::vector<std::array<double, 4>> grad(E);
    const int nres = num_residuals();
    if (jac)
      for (size_t e = 0; e <= E; ++e)
        if (jac[e]) {
          const size_t w = e < E ? fx_[e]->p.size() : ncomp;
          std::fill(jac[e], jac[e] + static_cast<size_t>(nres) * w, 0.0);
        }
    for (size_t si = 0; si < s_.size(); ++si) {
      const size_t k = s_[si];
      for (size_t e = 0; e < E; ++e) {
        if (jac)
          val[e] = fx_[e]->value_grad(*f_.ctx, k, params[e], grad[e].data());
        else
          val[e] = fx_[e]->value(*f_.ctx, k, params[e]);
      }
      for (size_t j = 0; j < nc; ++j) {
        const int ci = f_.fitc[j];
        const Comp& c = (*f_.comps)[static_cast<size_t>(ci)];
        const size_t row = si * nc + j;
        if (std::isnan(c.res[k])) {
          residuals[row] = 0;
          continue;
        }
        const double w = 1.0 / c.sigma;
        double r = c.res[k] - params[E][ci];
        for (size_t e = 0; e < E; ++e) {
          if (!f_.reaches(c, *fx_[e])) continue;
          const double s = f_.sens(c, *fx_[e], k);
          r -= s * val[e];
          if (jac && jac[e]) {
            const size_t np = fx_[e]->p.size();
            for (size_t q = 0; q < np; ++q) jac[e][row * np + q] = -w * s * grad[e][q];
          }
        }
        residuals[row] = w * r;
        if (jac && jac[E]) jac[E][row * ncomp + static_cast<size_t>(ci)] = -w;
      }
    }
    return true;
  }

 private:
  const Fit& f_;
  std::vector<Effect*> fx_;
  std::vector<size_t> s_;
};

/// thermal_scale's shortest time constant, as a share of the recording's duration.
constexpr double kThermalScaleMinTau = 0.1;

/// Joint refit of all effects and the offsets on the training samples.
void joint_fit(Fit& f, const std::vector<Effect*>& fx, size_t stride = 1) {
  ceres::Problem::Options po;
  po.cost_function_ownership = ceres::TAKE_OWNERSHIP;
  ceres::Problem prob(po);
  std::vector<size_t> train;
  for (size_t k = 0; k < f.ctx->size(); k += stride)
    if (!f.held[k]) train.push_back(k);
  std::vector<double*> blocks;
  for (Effect* e : fx) blocks.push_back(e->p.data());
  blocks.push_back(f.off.data());
  const size_t chunk = 256;
  for (size_t a = 0; a < train.size(); a += chunk) {
    std::vector<size_t> s(train.begin() + static_cast<std::ptrdiff_t>(a),
                          train.begin() + static_cast<std::ptrdiff_t>(std::min(train.size(), a + chunk)));
    prob.AddResidualBlock(new ChunkCost(f, fx, std::move(s)), nullptr, blocks);
  }
  for (Effect* e : fx) {
    const auto names = e->internal_names();
    if (e->name() == "vibration") {  // the frequency comes from the spectrum (the fit subsamples in time)
      prob.SetManifold(e->p.data(), new ceres::SubsetManifold(3, {0}));
    }
    if (e->name() == "step") {  // the time of the jump comes from the residual (no derivative)
      prob.SetManifold(e->p.data(), new ceres::SubsetManifold(2, {1}));
    }
    for (size_t q = 0; q < names.size(); ++q) {
      if (names[q] == "apex") {
        // Within a travel of the second axis's recorded range: an apex far beyond it is a tilted line (squareness or
        // scale), which the curvature would then fit only as a large, meaningless product.
        const auto [lo, hi] = f.ctx->range(static_cast<size_t>(e->axis2));
        const double span = std::max(hi - lo, 1.0);
        prob.SetParameterLowerBound(e->p.data(), static_cast<int>(q), std::min(e->p[q], lo - span));
        prob.SetParameterUpperBound(e->p.data(), static_cast<int>(q), std::max(e->p[q], hi + span));
      }
      if (names[q] == "tau_s" || names[q] == "decay_s" || names[q] == "period") {
        // A screw that reaches its growth within a tenth of the run is a constant scale error to this recording:
        // thermal_scale keeps its time constant above that, so the two stay apart (the scale has one parameter less).
        // A drift that completes within a twentieth of the run is a constant to this recording (with the tool point's
        // drift turned with the table, a constant it shares with a rotary axis's offset centre).
        const double floor = e->name() == "thermal_scale"   ? std::min(e->p[q], kThermalScaleMinTau * f.ctx->duration)
                             : e->name() == "thermal_drift" ? std::min(e->p[q], kThermalDriftMinTau * f.ctx->duration)
                                                            : 0.0;
        prob.SetParameterLowerBound(e->p.data(), static_cast<int>(q), std::max(e->p[q] * 0.05, floor));
        prob.SetParameterUpperBound(
            e->p.data(), static_cast<int>(q),
            names[q] == "decay_s" ? std::max(e->p[q], std::min(e->p[q] * 20, 1.0)) : e->p[q] * 20);
      }
    }
  }
  ceres::Solver::Options so;
  so.linear_solver_type = ceres::DENSE_QR;
  so.max_num_iterations = 40;
  so.num_threads = static_cast<int>(worker_threads());
  so.logging_type = ceres::SILENT;
  ceres::Solver::Summary sum;
  ceres::Solve(so, &prob, &sum);
}

/// The recording's sample interval, s (the median step of its time column; 0 with fewer than two rows).
double sample_interval(const Context& c) {
  if (c.t_full.size() < 2) return 0.0;
  std::vector<double> dt(c.t_full.size() - 1);
  for (size_t i = 1; i < c.t_full.size(); ++i) dt[i - 1] = c.t_full[i] - c.t_full[i - 1];
  std::nth_element(dt.begin(), dt.begin() + static_cast<std::ptrdiff_t>(dt.size() / 2), dt.end());
  return dt[dt.size() / 2];
}

/// Physical plausibility: an explanation that needs, e.g., a 0.3 % scale error or a friction spike that decays
/// over seconds is another effect in disguise (or one outside the library), not a finding. And resolution: the
/// recording is sampled every `sample_s` seconds, from `t_first` to `t_last`.
bool plausible(const Effect& e, double sample_s, double t_first, double t_last) {
  const std::string n = e.name();
  // A spike that decays within one sample interval shows at one sample per reversal at most, where it cannot be told
  // from where the reversal fell between two samples (it would absorb the misfit of a lost motion taken up there).
  if (n == "friction_spike" && e.p[1] < sample_s) return false;
  // Likewise a first-order lag whose time constant is shorter than a sample interval is a plain lag to the recording.
  if (n == "servo_lag_1st" && e.p[1] < sample_s) return false;
  const double a = std::abs(e.p[0]);
  if (n == "scale") return a <= 1000;                                         // ppm
  if (n == "thermal_scale") return a <= 1000 && e.p[1] > 0;                   // ppm at the end of the run
  if (n == "squareness") return a <= 5000;                                    // urad
  if (n == "straightness") return a <= 100;                                   // mm/m^2: 1 mm at 100 mm from the apex
  if (n == "servo_lag") return a <= 0.5;                                      // s
  if (n == "servo_lag_1st") return a <= 0.5 && e.p[1] > 0 && e.p[1] <= 1.0;   // s: steady lag, time constant
  if (n == "backlash") return a <= 1.0 && e.p[1] >= 0 && e.p[1] <= 1.0;       // width, take-up: mm or deg
  if (n == "friction_spike") return e.p[1] > 0 && e.p[1] <= 1.0 && a <= 1.0;  // decay, s; peak, mm or deg
  if (n == "thermal_drift") return e.p[1] > 0 && a <= 1.0;                    // mm over the run (a wrong machine: 28)
  if (n == "thermal_growth") return a <= 0.1;                                 // mm/degC (steel: 0.012 per metre)
  if (n == "thermal_expansion") return a <= 100;                              // ppm/degC (steel 12, aluminium 23)
  if (n == "step") {  // mm; and samples on both sides: at a run's first or last few it is an outlier, not a step
    const double edge = std::max(10.0 * sample_s, 0.01 * (t_last - t_first));
    return a <= 1.0 && e.p[1] >= t_first + edge && e.p[1] <= t_last - edge;
  }
  if (n == "vibration") return std::hypot(e.p[1], e.p[2]) <= 1.0;  // mm amplitude
  if (n == "geometric") return a <= 1.0;  // mm or deg: linearised at nominal, valid for tens of micrometres
  if (n == "cyclic") return std::hypot(e.p[1], e.p[2]) <= 1.0;  // mm or deg amplitude
  return true;
}

struct Candidate {
  std::unique_ptr<Effect> e;
  double gain = 0;
  /// The best grid point among those whose fitted effect acts only on training samples (a transient at the one
  /// reversal of a run, in a training block): the held-out blocks cannot judge it, its training gain can.
  std::unique_ptr<Effect> event;
  double event_train_gain = 0;
};

/// Below this held-out prediction (sum of squares, in noise variances) an effect does not reach the held-out blocks.
constexpr double kHeldReach = 1.0;

/// Screens one effect over its grid against the current residual: best grid point with its linear
/// parameters fitted (offsets refitted: columns centred on the training samples); gain on held-out.
Candidate screen(const Fit& f, const Effect& proto, const std::vector<size_t>& screen_idx,
                 const std::vector<std::vector<double>>& cur, const sim::GridHints& hints) {
  Candidate best;
  const double sample_s = f.sample_s;
  const auto lin = proto.linear();
  std::vector<int> L;
  for (size_t q = 0; q < lin.size(); ++q)
    if (lin[q]) L.push_back(static_cast<int>(q));
  const size_t nl = L.size(), np = lin.size();
  std::vector<int> comps;
  for (int ci : f.fitc)
    if (f.reaches((*f.comps)[static_cast<size_t>(ci)], proto)) comps.push_back(ci);
  if (comps.empty()) return best;
  const size_t ms = screen_idx.size();
  std::vector<double> G(ms * nl), grad(np);
  for (const auto& g : proto.grid(*f.ctx, hints)) {
    for (size_t s = 0; s < ms; ++s) {
      proto.value_grad(*f.ctx, screen_idx[s], g.data(), grad.data());
      for (size_t l = 0; l < nl; ++l) G[s * nl + l] = grad[static_cast<size_t>(L[l])];
    }
    Eigen::MatrixXd A = Eigen::MatrixXd::Zero(static_cast<Eigen::Index>(nl), static_cast<Eigen::Index>(nl));
    Eigen::VectorXd b = Eigen::VectorXd::Zero(static_cast<Eigen::Index>(nl));
    // Per component: training means of columns and target (the offset refit), then normal equations.
    std::vector<std::vector<double>> mcol(comps.size(), std::vector<double>(nl, 0.0));
    std::vector<double> mr(comps.size(), 0.0);
    for (size_t j = 0; j < comps.size(); ++j) {
      const Comp& c = (*f.comps)[static_cast<size_t>(comps[j])];
      const auto& cr = cur[static_cast<size_t>(comps[j])];
      size_t cnt = 0;
      for (size_t s = 0; s < ms; ++s) {
        const size_t k = screen_idx[s];
        if (f.held[k] || std::isnan(c.res[k])) continue;
        const double sv = f.sens(c, proto, k);
        for (size_t l = 0; l < nl; ++l) mcol[j][l] += sv * G[s * nl + l];
        mr[j] += cr[s];
        ++cnt;
      }
      if (cnt)
        for (size_t l = 0; l < nl; ++l) mcol[j][l] /= static_cast<double>(cnt);
      if (cnt) mr[j] /= static_cast<double>(cnt);
      const double w2 = 1.0 / (c.sigma * c.sigma);
      for (size_t s = 0; s < ms; ++s) {
        const size_t k = screen_idx[s];
        if (f.held[k] || std::isnan(c.res[k])) continue;
        const double sv = f.sens(c, proto, k);
        double col[4];
        for (size_t l = 0; l < nl; ++l) col[l] = sv * G[s * nl + l] - mcol[j][l];
        for (size_t l = 0; l < nl; ++l) {
          b(static_cast<Eigen::Index>(l)) += w2 * col[l] * (cr[s] - mr[j]);
          for (size_t m2 = 0; m2 < nl; ++m2)
            A(static_cast<Eigen::Index>(l), static_cast<Eigen::Index>(m2)) += w2 * col[l] * col[m2];
        }
      }
    }
    if (A.trace() <= 0) continue;
    A.diagonal().array() += 1e-12 * A.trace();
    const Eigen::VectorXd x = A.ldlt().solve(b);
    // Held-out gain (normalised by noise), counted over every fitted component's held-out values; the training
    // gain and what the effect predicts on the held-out values (its own contribution, not centred) beside it.
    double before = 0, after = 0, train_before = 0, train_after = 0, held_pred = 0;
    for (size_t j = 0; j < comps.size(); ++j) {
      const Comp& c = (*f.comps)[static_cast<size_t>(comps[j])];
      const auto& cr = cur[static_cast<size_t>(comps[j])];
      for (size_t s = 0; s < ms; ++s) {
        const size_t k = screen_idx[s];
        if (std::isnan(c.res[k])) continue;
        const double sv = f.sens(c, proto, k);
        double m = 0, own = 0;
        for (size_t l = 0; l < nl; ++l) {
          m += x(static_cast<Eigen::Index>(l)) * (sv * G[s * nl + l] - mcol[j][l]);
          own += x(static_cast<Eigen::Index>(l)) * sv * G[s * nl + l];
        }
        const double r0 = (cr[s] - mr[j]) / c.sigma, r1 = (cr[s] - mr[j] - m) / c.sigma;
        if (f.held[k]) {
          before += r0 * r0;
          after += r1 * r1;
          held_pred += own * own / (c.sigma * c.sigma);
        } else {
          train_before += r0 * r0;
          train_after += r1 * r1;
        }
      }
    }
    const double gain = before - after;  // summed; normalised by the caller
    const bool event = held_pred < kHeldReach;
    if (!best.e || gain > best.gain || (event && train_before - train_after > best.event_train_gain)) {
      auto cand = proto.clone();
      cand->p = g;
      for (size_t l = 0; l < nl; ++l) cand->p[static_cast<size_t>(L[l])] = x(static_cast<Eigen::Index>(l));
      if (!plausible(*cand, sample_s, f.ctx->t_full.front(), f.ctx->t_full.back())) continue;
      if (event && train_before - train_after > best.event_train_gain) {
        best.event = cand->clone();
        best.event_train_gain = train_before - train_after;
      }
      if (!best.e || gain > best.gain) {
        best.e = std::move(cand);
        best.gain = gain;
      }
    }
  }
  return best;
}

/// Where a frequency f lands when sampled at sample_hz (0: not sampled).
double aliased(double f, double sample_hz) {
  return sample_hz > 0 && f > 0.5 * sample_hz ? std::abs(f - sample_hz * std::round(f / sample_hz)) : f;
}

/// What a vibration at f comes from, given the spindle speed and flutes; sampled at sample_hz, a source above the
/// Nyquist frequency is recognised where it aliases to.
std::string source_of(double f, double rpm, int flutes, double sample_hz = 0) {
  if (!(rpm > 0)) return "structural";
  const double fs = aliased(rpm / 60.0, sample_hz), ft = flutes > 0 ? aliased(rpm / 60.0 * flutes, sample_hz) : 0;
  auto near = [&](double base) {
    if (!(base > 0)) return 0;
    const double h = std::round(f / base);
    return (h >= 1 && h <= 5 && std::abs(f - h * base) < std::max(0.02 * base, 0.5)) ? static_cast<int>(h) : 0;
  };
  if (near(ft) == 1) return "tooth_passing";
  if (near(ft) > 1) return "tooth_passing";  // a harmonic of it
  if (near(fs)) return "spindle";
  return "structural";
}

/// A following error: servo_lag or servo_lag_1st.
bool is_lag(const Effect& e) { return e.name() == "servo_lag" || e.name() == "servo_lag_1st"; }

/// The steady following error per unit velocity of a lag effect, s.
double steady_lag_s(const Effect& e) {
  const auto rep = e.reported();
  return e.name() == "servo_lag_1st" ? rep[1].second : rep[0].second;
}

std::string explain(const Effect& e, const std::string& dom) {
  const auto rep = e.reported();
  const std::string u = e.rotary ? "deg" : "mm";
  const std::string n = e.name();
  if (n == "backlash")
    return fmt::format("step in {} at every reversal of {} (lost motion of {})", dom, e.target,
                       fmt_value(u, rep[0].second));
  if (n == "servo_lag")
    return fmt::format("{} follows the velocity of {}: following error = velocity x {:.4f} s", dom, e.target,
                       rep[0].second);
  if (n == "servo_lag_1st")
    return fmt::format(
        "{} follows {} as a first-order loop: the following error builds up and dies away with a time constant of "
        "{:.4f} s and settles at velocity x {:.4f} s",
        dom, e.target, rep[0].second, rep[1].second);
  if (n == "thermal_drift")
    return fmt::format("{} drifts by {} over the run (time constant {:.0f} s)", dom, fmt_um(rep[0].second),
                       rep[1].second);
  if (n == "step")
    return fmt::format("{} jumps by {} at t = {:.3f} s and stays", dom, fmt_um(rep[0].second), rep[1].second);
  if (n == "thermal_growth")
    return fmt::format("{} follows temperature temp.{}: {} per degree C", dom, e.note, fmt_um(rep[0].second));
  if (n == "thermal_expansion")
    return fmt::format(
        "error in {} growing with the position of {} and with temperature temp.{} ({:.2f} ppm per degree C)", dom,
        e.target, e.note, rep[0].second);
  if (n == "vibration")
    return fmt::format("sinusoid of {} at {:.1f} Hz in {}{}", fmt_um(rep[1].second), rep[0].second, dom,
                       e.note.empty() ? "" : " (" + e.note + ")");
  if (n == "scale")
    return fmt::format("error in {} growing with the position of {} ({:.1f} ppm)", dom, e.target, rep[0].second);
  if (n == "squareness")
    return fmt::format("error in {} proportional to the position of the second axis of {} ({:.1f} urad)", dom, e.target,
                       rep[0].second);
  if (n == "straightness")
    return fmt::format(
        "error in {} growing with the square of the position of the second axis of {} ({:.4g} mm/m^2, apex at {:.1f} "
        "mm)",
        dom, e.target, rep[0].second, rep[1].second);
  if (n == "cyclic")
    return fmt::format("error in {} periodic in the position of {} (period {:.3f} {}, amplitude {})", dom, e.target,
                       rep[0].second, u, fmt_value(u, rep[1].second));
  if (n == "friction_spike")
    return fmt::format("spike in {} after every reversal of {} (peak {}, decay {:.3f} s)", dom, e.target,
                       fmt_value(u, rep[0].second), rep[1].second);
  if (n == "compliance") return fmt::format("deflection in {} proportional to the acceleration of {}", dom, e.target);
  if (n == "thermal_scale")
    return fmt::format(
        "error in {} growing with the position of {} and with time ({:.1f} ppm at the end, time "
        "constant {:.0f} s)",
        dom, e.target, rep[0].second, rep[1].second);
  if (n == "cross_compliance")
    return fmt::format(
        "deflection in {} proportional to the acceleration of the second axis of {} ({:.3g} mm per m/s^2)", dom,
        e.target, rep[0].second);
  if (n == "geometric")
    return fmt::format("position-dependent error in {} reproduced by machine parameter {} off nominal by {:.6g} {}",
                       dom, e.target, e.p[0], e.unit);
  return e.signature();
}

std::string describe(const Effect& e) {
  const auto rep = e.reported();
  const std::string u = e.rotary ? "deg" : "mm";
  const std::string n = e.name();
  if (n == "backlash")
    return fmt::format("lost motion of {} on {} at each {} reversal", fmt_value(u, rep[0].second), e.target, e.target);
  if (n == "servo_lag") return fmt::format("servo lag of {:.2f} ms on {}", rep[0].second * 1000, e.target);
  if (n == "servo_lag_1st")
    return fmt::format("first-order servo lag on {}: time constant {:.2f} ms (steady lag {:.2f} ms)", e.target,
                       rep[0].second * 1000, rep[1].second * 1000);
  // A direction (a unit vector) drifts in microradians.
  auto in_channel = [&](double v) {
    return e.channel.rfind("dir.", 0) == 0 ? fmt::format("{:.1f} urad", v * 1e6) : fmt_um(v);
  };
  if (n == "thermal_drift")
    return fmt::format("thermal drift of {} in {} (time constant {:.0f} s)", in_channel(rep[0].second), e.target,
                       rep[1].second);
  if (n == "step")
    return fmt::format("a permanent step of {} in {} at t = {:.3f} s (knocked, re-seated or slipped)",
                       in_channel(rep[0].second), e.target, rep[1].second);
  if (n == "thermal_growth")
    return fmt::format("thermal growth of {} per degree C of temp.{} in {}", in_channel(rep[0].second), e.note,
                       e.target);
  if (n == "thermal_expansion")
    return fmt::format("thermal expansion of {}'s screw: {:.2f} ppm per degree C of temp.{}", e.target, rep[0].second,
                       e.note);
  if (n == "vibration")
    return fmt::format("vibration of {} at {:.1f} Hz in {}{}", in_channel(rep[1].second), rep[0].second, e.target,
                       e.note.empty() ? "" : " (" + e.note + ")");
  if (n == "scale") return fmt::format("scale error of {:.1f} ppm on {}", rep[0].second, e.target);
  if (n == "thermal_scale")
    return fmt::format("thermal growth of {}'s screw: a scale error rising to {:.1f} ppm (time constant {:.0f} s)",
                       e.target, rep[0].second, rep[1].second);
  if (n == "squareness") return fmt::format("squareness error of {:.1f} urad between {}", rep[0].second, e.target);
  if (n == "straightness") {
    // The bow over 100 mm either side of the apex says more to a machinist than the curvature.
    const auto comma = e.target.find(',');
    return fmt::format("straightness error of {} along {}: {} at 100 mm from the apex ({} = {:.1f} mm)",
                       e.target.substr(0, comma), e.target.substr(comma + 1), fmt_um(rep[0].second * 0.01),
                       e.target.substr(comma + 1), rep[1].second);
  }
  if (n == "cyclic")
    return fmt::format("cyclic error of {} (period {:.3f} {}) on {}", fmt_value(u, rep[1].second), rep[0].second, u,
                       e.target);
  if (n == "friction_spike")
    return fmt::format("reversal spike of {} decaying in {:.0f} ms on {}", fmt_value(u, rep[0].second),
                       rep[1].second * 1000, e.target);
  if (n == "compliance") return fmt::format("compliance {:.3g} {} on {}", rep[0].second, rep[0].first, e.target);
  if (n == "cross_compliance") {
    const auto comma = e.target.find(',');
    return fmt::format("cross compliance: {} deflects {} per m/s^2 of {}'s acceleration", e.target.substr(0, comma),
                       fmt_um(rep[0].second), e.target.substr(comma + 1));
  }
  if (n == "geometric")
    return fmt::format("geometry: {} is {:.6g} {} instead of {:.6g}", e.target, e.nominal + e.p[0], e.unit, e.nominal);
  return n + " on " + e.target;
}

}  // namespace

Report diagnose(sim::Recording& rec, const machine::Machine& m, const std::vector<const sim::Effect*>& known,
                const Options& o) {
  Report R;
  auto tstage = Clock::now();
  R.recording = rec.file;
  R.machine = m.file;
  sim::validate_against(rec, m);
  R.warnings = rec.warnings;
  const size_t n = rec.rows();
  R.samples = n;
  const size_t kMinSamples = 120;
  if (n < kMinSamples)
    throw InputError(
        SourceLoc{rec.file},
        fmt::format("too little data to hold any out: {} samples, diagnosis needs at least {} ({} more) so "
                    "that every one of {} time blocks has 10",
                    n, kMinSamples, kMinSamples - n, o.time_blocks));
  const int tcol = rec.column("t");
  if (tcol < 0) throw InputError(SourceLoc{rec.file}, "diagnose needs a trajectory recording with a time column 't'");
  const auto& t = rec.data[static_cast<size_t>(tcol)];
  std::vector<kin::Axes> cmd(n);
  for (int j = 0; j < 5; ++j) {
    const auto& name = m.axes[static_cast<size_t>(j)].name;
    const auto& col = rec.data[static_cast<size_t>(rec.column("cmd." + name))];
    for (size_t i = 0; i < n; ++i) {
      if (std::isnan(col[i]))
        throw InputError(SourceLoc{rec.file, rec.row_line[i]},
                         fmt::format("row {}: column 'cmd.{}' is empty", i + 1, name));
      cmd[i][j] = col[i];
    }
    // A control may record a rotary modulo 360 deg (a cyclic table's 359.9 then 0.1). No axis turns half a turn
    // between two samples: such a step is a wrap, unwound here so that velocities and reversals stay physical.
    if (m.axes[static_cast<size_t>(j)].rotary())
      for (size_t i = 1; i < n; ++i) {
        double prev = cmd[i - 1][j], &q = cmd[i][j];
        q -= 360.0 * std::round((q - prev) / 360.0);
      }
  }
  // A tool length past 10 m or a spindle past 10^6 rpm is a broken file, not a machine.
  const double L = rec.meta_number("tool_length", 0.0, 1e4).value_or(m.default_tool_length_mm);
  const double rpm = rec.meta_number("spindle_rpm", 0.0, 1e6).value_or(0.0);
  const int flutes = static_cast<int>(rec.meta_number("flutes", 0.0, 1000.0).value_or(0.0));

  // ---- 1. simulate and subtract -------------------------------------------------------------------
  std::vector<Comp> comps;
  const char* xyz = "xyz";
  std::vector<std::string> groups;
  auto add_group = [&](const std::string& g, Kind kind) {
    bool any = false;
    for (int c = 0; c < 3; ++c) {
      const int col = rec.column(g + "." + xyz[c]);
      if (col < 0) continue;
      Comp cp;
      cp.name = g + "." + xyz[c];
      cp.group = g;
      cp.kind = kind;
      cp.idx = c;
      cp.col = col;
      cp.fit = kind != Kind::Acc;
      comps.push_back(cp);
      any = true;
    }
    if (any) groups.push_back(g);
  };
  add_group("tip", Kind::Tip);
  add_group("ptip", Kind::PTip);
  add_group("dir", Kind::Dir);
  for (int j = 0; j < 5; ++j) {
    const std::string nm = "enc." + m.axes[static_cast<size_t>(j)].name;
    const int col = rec.column(nm);
    if (col < 0) continue;
    Comp cp;
    cp.name = cp.group = nm;
    cp.kind = Kind::Enc;
    cp.idx = j;
    cp.col = col;
    comps.push_back(cp);
    groups.push_back(nm);
  }
  add_group("acc", Kind::Acc);
  if (comps.empty())
    throw InputError(SourceLoc{rec.file},
                     "no measured channel to compare with the model (tip.*, ptip.*, dir.*, enc.*, acc.*)");
  if (std::all_of(comps.begin(), comps.end(), [&](const Comp& c) {
        const auto& col = rec.data[static_cast<size_t>(c.col)];
        return std::all_of(col.begin(), col.end(), [](double v) { return std::isnan(v); });
      }))
    throw InputError(SourceLoc{rec.file}, "every cell of the measured channels is empty: nothing to compare");
  sim::Trajectory traj{t, cmd};
  sim::SimulateOptions so;
  for (const auto& g : {"tip", "ptip", "dir", "acc"})
    if (std::find(groups.begin(), groups.end(), g) != groups.end()) so.channels.emplace_back(g);
  so.channels.erase(so.channels.begin(), so.channels.begin() + 2);  // drop the defaults ("tip", "enc")
  so.channels.emplace_back("enc");
  so.tool_length_mm = L;
  // The recording's own temperatures, for known effects that follow one (thermal_growth, thermal_expansion).
  for (std::size_t col = 0; col < rec.columns.size(); ++col) {
    if (rec.columns[col].rfind("temp.", 0) != 0) continue;
    sim::SimulateOptions::Temperature tp;
    tp.sensor = rec.columns[col].substr(5);
    for (std::size_t r = 0; r < n; ++r)
      if (std::isfinite(rec.data[col][r])) tp.t.push_back(t[r]), tp.deg_c.push_back(rec.data[col][r]);
    if (!tp.t.empty()) so.temperatures.push_back(std::move(tp));
  }
  for (const sim::Effect* e : known)
    if (e->follows_temperature() &&
        std::none_of(so.temperatures.begin(), so.temperatures.end(),
                     [&](const sim::SimulateOptions::Temperature& tp) { return tp.sensor == e->note; }))
      throw InputError(SourceLoc{rec.file},
                       fmt::format("the machine's {} on {} follows temperature temp.{}, which this recording has no "
                                   "readings of: record that column, or diagnose against the machine without it",
                                   e->name(), e->target, e->note));
  const sim::Recording pred = sim::simulate(traj, m, known, so);
  for (auto& c : comps) {
    const auto& meas = rec.data[static_cast<size_t>(c.col)];
    const auto& p = pred.data[static_cast<size_t>(pred.column(c.name))];
    c.res_full.resize(n);
    for (size_t i = 0; i < n; ++i) c.res_full[i] = meas[i] - p[i];
    if (c.kind == Kind::Enc && m.axes[static_cast<size_t>(c.idx)].rotary())  // a wrapped encoder against the unwound
      for (double& r : c.res_full) r = std::remainder(r, 360.0);
  }
  drop_glitches(comps, cmd, t, R.warnings);
  for (const auto& g : groups) {
    double s = 0;
    size_t cnt = 0;
    std::vector<double> acc(n, 0.0);
    std::vector<char> has(n, 0);
    for (const auto& c : comps)
      if (c.group == g)
        for (size_t i = 0; i < n; ++i)
          if (!std::isnan(c.res_full[i])) acc[i] += c.res_full[i] * c.res_full[i], has[i] = 1;
    for (size_t i = 0; i < n; ++i)
      if (has[i]) s += acc[i], ++cnt;
    R.rms_before.emplace_back(g, cnt ? std::sqrt(s / static_cast<double>(cnt)) : 0.0);
  }
  R.seconds.emplace_back("simulate_and_subtract", secs(tstage));
  // The sampling rate is the clock's, not rows / duration: with rows missing, the mean rate is lower.
  const TimeGrid tg = time_grid(t);
  const double sample_hz = tg.dt > 0 ? 1.0 / tg.dt : static_cast<double>(n - 1) / std::max(t.back() - t.front(), 1e-12);
  if (tg.gaps > 0)
    R.warnings.push_back(fmt::format(
        "time stamps are uneven: {} gap(s) in t where about {} row(s) are missing, the largest {:.4g} s ({:.0f} "
        "sampling intervals of {:.4g} s) after t = {:.4f} s; spectra are taken on the regular {:.4g} s grid {}",
        tg.gaps, tg.missing, tg.largest_gap_s, tg.largest_gap_s / tg.dt, tg.dt, tg.largest_gap_at_s, tg.dt,
        tg.stretch_only ? "of the longest stretch without a gap (the gaps are longer than the data between them)"
                        : "with the missing rows left out"));
  if (tg.off_grid > n / 100)
    R.warnings.push_back(fmt::format(
        "time stamps are uneven: {} row(s) lie more than a quarter of the {:.4g} s sampling interval off a regular "
        "clock; spectral frequencies near the Nyquist frequency are blurred",
        tg.off_grid, tg.dt));
  if (rpm > 0)
    for (const auto& [what, f] : std::vector<std::pair<std::string, double>>{
             {"spindle", rpm / 60.0}, {"tooth-passing", flutes > 0 ? rpm / 60.0 * flutes : 0.0}})
      if (f > 0.5 * sample_hz)
        R.warnings.push_back(fmt::format(
            "the {} frequency {:.1f} Hz is above the Nyquist frequency {:.1f} Hz of this recording ({:.1f} samples/s): "
            "a vibration there shows aliased at {:.1f} Hz (record faster than {:.0f} samples/s to see it as it is)",
            what, f, 0.5 * sample_hz, sample_hz, aliased(f, sample_hz), 2.0 * f));
  tstage = Clock::now();

  // ---- 2. noise first; spectra --------------------------------------------------------------------
  const double duration = t.back() - t.front();
  const double fs = sample_hz;
  const size_t ngrid = tg.slots;
  std::vector<std::vector<Peak>> peaks(comps.size());
  std::vector<std::vector<double>> spectra(comps.size());
  std::vector<size_t> spectrum_n(comps.size(), 0);  // samples behind each spectrum (its amplitude scale)
  {
    const size_t nt = worker_threads();
    on_workers(nt, [&](size_t w) {
      for (size_t ci = w; ci < comps.size(); ci += nt) {
        size_t present = 0;
        const std::vector<double> y = on_grid(comps[ci].res_full, tg, present);
        auto P = periodogram(y);
        comps[ci].sigma = noise_from_spectrum(P, std::max<size_t>(present, 1), floor_of(comps[ci]));
        peaks[ci] = find_peaks(P, y, ngrid, present, fs, duration);
        spectrum_n[ci] = present;
        if (o.keep_plot_data) spectra[ci] = std::move(P);
      }
    });
  }
  for (const auto& g : groups) {
    double s = 0;
    for (const auto& c : comps)
      if (c.group == g) s += c.sigma * c.sigma;
    R.noise.emplace_back(g, std::sqrt(s));
  }
  // A time column in another unit than seconds: the commanded speeds come out a thousand (milliseconds) or sixty
  // (minutes) times off, far beyond the axes' max_feed or far below any feed, and every effect that depends on time
  // is fitted to nonsense.
  if (n > 2) {
    double peak_ratio = 0.0;  // the largest commanded speed / max_feed over the slides with a max_feed
    std::string fastest;
    for (int j = 0; j < 5; ++j) {
      const auto& ax = m.axes[static_cast<size_t>(j)];
      if (ax.rotary() || !(ax.max_feed > 0)) continue;
      double peak = 0.0;
      for (size_t i = 1; i < n; ++i)
        peak = std::max(peak, std::abs(cmd[i][j] - cmd[i - 1][j]) / std::max(t[i] - t[i - 1], 1e-12) * 60.0);
      if (peak / ax.max_feed > peak_ratio) peak_ratio = peak / ax.max_feed, fastest = ax.name;
    }
    const double dt_s = tg.dt > 0 ? tg.dt : (t.back() - t.front()) / static_cast<double>(n - 1);
    if (peak_ratio > 2.0)
      R.warnings.push_back(fmt::format(
          "the command moves {} at up to {:.3g} times its max_feed: is t in seconds (spec/recording.md)? A time in "
          "minutes makes every speed 60 times too high",
          fastest, peak_ratio));
    else if (peak_ratio > 0 && peak_ratio < 1e-3 && dt_s >= 0.5)
      R.warnings.push_back(fmt::format(
          "the slides move at most {:.2g} of their max_feed, sampled every {:.4g} s: is t in seconds "
          "(spec/recording.md)? A time in milliseconds makes every speed 1000 times too low and every time-dependent "
          "finding meaningless",
          peak_ratio, dt_s));
  }
  // Stamps that scatter about a regular clock, where the samples themselves were taken on it (a logger that stamps
  // late by a varying delay), move each sample along the path by its speed times the scatter: white noise that grows
  // with speed, which speed-dependent effects (lags, compliance) and steps then partly fit. Told where it reaches a
  // third of the noise at the program's speeds (the slides' RMS speed, the fastest slide's).
  if (tg.scatter_s > 0 && n > 2) {
    double v_rms = 0.0;
    for (int j = 0; j < 5; ++j) {
      if (m.axes[static_cast<size_t>(j)].rotary()) continue;
      double s2 = 0.0;
      for (size_t i = 1; i < n; ++i) {
        const double v = (cmd[i][j] - cmd[i - 1][j]) / std::max(t[i] - t[i - 1], 1e-12);
        s2 += v * v;
      }
      v_rms = std::max(v_rms, std::sqrt(s2 / static_cast<double>(n - 1)));
    }
    double noise_mm = 0.0;
    for (const auto& [g, v] : R.noise)
      if (g == "tip" || g == "ptip") noise_mm = std::max(noise_mm, v);
    const double moved_mm = v_rms * tg.scatter_s;
    if (noise_mm > 0 && moved_mm > noise_mm / 3.0)
      R.warnings.push_back(fmt::format(
          "time stamps scatter by {:.3g} ms RMS about a regular {:.4g} s clock ({:.1f} % of the interval): if the "
          "samples were taken on the clock and only their stamps scatter, each moves along the path by its speed "
          "times the scatter, {:.2f} um RMS at this program's speeds (noise {:.2f} um); speed-dependent findings "
          "(servo "
          "lag, compliance) and steps may then be the clock's",
          1e3 * tg.scatter_s, tg.dt, 100.0 * tg.scatter_s / tg.dt, 1e3 * moved_mm, 1e3 * noise_mm));
  }
  R.seconds.emplace_back("noise_and_spectra", secs(tstage));
  tstage = Clock::now();

  // ---- analysis samples, Jacobians, time blocks ---------------------------------------------------
  std::array<bool, 5> rot{};
  for (int j = 0; j < 5; ++j) rot[j] = m.axes[static_cast<size_t>(j)].rotary();
  const size_t stride = std::max<size_t>(1, (n + o.max_fit_samples - 1) / o.max_fit_samples);
  const Context ctx = [&] {
    Context c = sim::make_context(t, cmd, rot, stride);
    // The recorded temperatures' rise since the start at every analysis sample (thermal_growth, thermal_expansion),
    // for each sensor whose reading changes.
    for (const auto& tp : so.temperatures) {
      std::vector<double> rise = sim::temperature_at(tp, c.t);
      const double t0 = rise.front();
      for (double& x : rise) x -= t0;
      if (std::any_of(rise.begin(), rise.end(), [](double x) { return x != 0.0; }))
        c.temp_rise.emplace_back(tp.sensor, std::move(rise));
    }
    return c;
  }();
  const double sample_s = sample_interval(ctx);
  const size_t ma = ctx.size();
  for (auto& c : comps) {
    c.res.resize(ma);
    for (size_t k = 0; k < ma; ++k) c.res[k] = c.res_full[ctx.index[k]];
  }
  Fit F;
  F.ctx = &ctx;
  F.comps = &comps;
  F.sample_s = sample_s;
  for (size_t ci = 0; ci < comps.size(); ++ci)
    if (comps[ci].fit) F.fitc.push_back(static_cast<int>(ci));
  const bool need_j =
      std::any_of(comps.begin(), comps.end(), [](const Comp& c) { return c.kind != Kind::Enc && c.kind != Kind::Acc; });
  F.J.assign(ma, Eigen::Matrix<double, 9, 5>::Zero());
  F.Rpw.assign(ma, Eigen::Matrix3d::Identity());
  const sim::Predictor P(m, L);
  if (need_j) {
    const size_t nt = worker_threads();
    on_workers(nt, [&](size_t w) {
      for (size_t k = ma * w / nt; k < ma * (w + 1) / nt; ++k) {
        P.jacobian(cmd[ctx.index[k]], F.J[k]);
        F.Rpw[k] = P.part_from_machine(cmd[ctx.index[k]]);
      }
    });
  }
  F.held.resize(ma);
  const int K = std::max(3, o.time_blocks);
  for (size_t k = 0; k < ma; ++k) {
    const int b = std::min(K - 1, static_cast<int>((ctx.t[k] - ctx.t0) / std::max(duration, 1e-12) * K));
    F.held[k] = static_cast<char>(b % 3 == 1);
  }
  F.off.assign(comps.size(), 0.0);
  for (int ci : F.fitc) {  // offsets: training mean
    double s = 0;
    size_t cnt = 0;
    for (size_t k = 0; k < ma; ++k)
      if (!F.held[k] && !std::isnan(comps[static_cast<size_t>(ci)].res[k]))
        s += comps[static_cast<size_t>(ci)].res[k], ++cnt;
    F.off[static_cast<size_t>(ci)] = cnt ? s / static_cast<double>(cnt) : 0.0;
  }
  size_t n_held_values = 0, n_train_values = 0;
  for (int ci : F.fitc)
    for (size_t k = 0; k < ma; ++k)
      if (!std::isnan(comps[static_cast<size_t>(ci)].res[k])) ++(F.held[k] ? n_held_values : n_train_values);
  R.seconds.emplace_back("jacobians", secs(tstage));
  tstage = Clock::now();

  // ---- 3. explain: greedy selection on held-out time blocks, joint refit ---------------------------
  const size_t sstride = std::max<size_t>(1, (ma + o.max_screen_samples - 1) / o.max_screen_samples);
  std::vector<size_t> sidx;
  for (size_t k = 0; k < ma; k += sstride) sidx.push_back(k);
  size_t n_held_screen = 0;
  for (int ci : F.fitc)
    for (size_t k : sidx)
      if (F.held[k] && !std::isnan(comps[static_cast<size_t>(ci)].res[k])) ++n_held_screen;
  // Thresholds on the held-out mean square (noise variance = 1): a gain of min_gain_sum noise variances in
  // total (a localised effect, e.g. spikes at a few reversals, is significant when it stands out that much),
  // and at least min_gain of the noise variance per held-out value.
  const double thr = std::max(o.min_gain_sum, o.min_gain * static_cast<double>(n_held_values)) /
                     std::max<double>(1.0, static_cast<double>(n_held_values));
  const double thr_screen = std::max(o.min_gain_sum, o.min_gain * static_cast<double>(n_held_screen)) /
                            std::max<double>(1.0, static_cast<double>(n_held_screen));

  // Candidate prototypes.
  std::vector<std::unique_ptr<Effect>> protos;
  auto has_enc = [&](int j) {
    return std::any_of(comps.begin(), comps.end(), [&](const Comp& c) { return c.kind == Kind::Enc && c.idx == j; });
  };
  // A following error that the axis's own recorded encoder does not see.
  auto unseen_lag = [&](const Effect& e) { return is_lag(e) && !e.enc_visible && has_enc(e.axis); };
  const bool has_geom_channel = std::any_of(comps.begin(), comps.end(), [](const Comp& c) {
    return c.kind == Kind::Tip || c.kind == Kind::PTip || c.kind == Kind::Dir;
  });
  // An axis that never moves (or never reverses) in the recording holds no effect that depends on its motion (or
  // its reversals): there such an effect is a constant shift of the axis, which the channel offsets and the
  // geometric zero offsets describe, and its fit to the noise would be reported as lost motion that nothing shows.
  std::array<bool, 5> moves{}, reverses{};
  for (int j = 0; j < 5; ++j) {
    moves[static_cast<size_t>(j)] = ctx.range(static_cast<size_t>(j)).travel() > 1e-9;
    const auto& since = ctx.since_rev[static_cast<size_t>(j)];
    reverses[static_cast<size_t>(j)] =
        moves[static_cast<size_t>(j)] &&
        std::any_of(since.begin(), since.end(), [](double s) { return std::isfinite(s); });
  }
  for (int j = 0; j < 5; ++j) {
    const std::string ax = m.axes[static_cast<size_t>(j)].name;
    // A slide's growth with a recorded temperature: one candidate per sensor (the loop below takes them one by one).
    std::vector<std::string> names{"backlash", "servo_lag",      "servo_lag_1st", "scale",
                                   "cyclic",   "friction_spike", "compliance",    "thermal_scale"};
    std::vector<std::string> sensors(names.size());
    for (const auto& [sensor, rise] : ctx.temp_rise) {
      names.emplace_back("thermal_expansion");
      sensors.push_back(sensor);
    }
    for (std::size_t ni = 0; ni < names.size(); ++ni) {
      if (!moves[static_cast<size_t>(j)]) break;
      const std::string& n = names[ni];
      if ((n == "backlash" || n == "friction_spike") && !reverses[static_cast<size_t>(j)]) continue;
      if ((n == "thermal_scale" || n == "thermal_expansion") && rot[static_cast<size_t>(j)]) continue;  // a screw's
      auto e = sim::make_effect(n, ax, m);
      e->note = sensors[ni];
      std::vector<std::unique_ptr<Effect>> variants;
      if (has_enc(j)) {
        if (has_geom_channel) {
          auto e2 = e->clone();
          e2->enc_visible = !e->enc_visible;
          variants.push_back(std::move(e2));
        } else {
          e->enc_visible = true;
        }
      } else if (!has_geom_channel) {
        continue;
      }
      variants.push_back(std::move(e));
      for (auto& v : variants) {
        // Lost motion: the axis may also start the recording against its first move (it last moved the other way).
        if (n == "backlash") {
          auto v2 = v->clone();
          const auto keys = v->reported();
          v2->set_reported({{keys[0].first, 0.0}, {keys[1].first, 0.0}, {"start_opposite", 1.0}});
          protos.push_back(std::move(v2));
        }
        protos.push_back(std::move(v));
      }
    }
  }
  // Squareness is a property of Cartesian slides; between the legs of a parallel machine it means nothing. Both
  // orders: "z += g x" (X tilted toward Z) and "x += g z" (Z tilted toward X) differ in the machine frame; a circle
  // in the XY plane sees only the first.
  // Straightness: each linear axis bowing along each (itself included: a lead error that grows quadratically).
  // Cross compliance: each linear axis deflecting with another's acceleration (one's own is `compliance`).
  if (has_geom_channel && m.kind == machine::ModelKind::Serial)
    for (int i = 0; i < 5; ++i)
      for (int j = 0; j < 5; ++j) {
        if (rot[i] || rot[j] || !moves[static_cast<size_t>(j)]) continue;
        const std::string pair = m.axes[static_cast<size_t>(i)].name + "," + m.axes[static_cast<size_t>(j)].name;
        if (i != j) protos.push_back(sim::make_effect("squareness", pair, m));
        if (i != j) protos.push_back(sim::make_effect("cross_compliance", pair, m));
        protos.push_back(sim::make_effect("straightness", pair, m));
      }
  std::vector<sim::GridHints> hints(comps.size());
  // Growth that follows a recorded temperature, on every fitted channel, per sensor whose reading changes.
  auto growth = [&](const std::string& channel) {
    for (const auto& [sensor, rise] : ctx.temp_rise) {
      auto e = sim::make_effect("thermal_growth", channel, m);
      e->note = sensor;
      protos.push_back(std::move(e));
    }
  };
  for (int ci : F.fitc) {
    const Comp& c = comps[static_cast<size_t>(ci)];
    if (c.kind == Kind::Tip || c.kind == Kind::PTip) growth(c.name);
    protos.push_back(sim::make_effect("thermal_drift", comps[static_cast<size_t>(ci)].name, m));
    protos.push_back(sim::make_effect("step", comps[static_cast<size_t>(ci)].name, m));
    for (const auto& pk : peaks[static_cast<size_t>(ci)]) hints[static_cast<size_t>(ci)].frequencies_hz.push_back(pk.f);
    if (!hints[static_cast<size_t>(ci)].frequencies_hz.empty())
      protos.push_back(sim::make_effect("vibration", comps[static_cast<size_t>(ci)].name, m));
  }
  // Spectral peaks for a tool-point vibration along W's axis w: those of tip.w and of every ptip component.
  const auto tool_hints = [&](char w) {
    sim::GridHints h;
    for (int ci : F.fitc) {
      const Comp& c = comps[static_cast<size_t>(ci)];
      if ((c.kind == Kind::Tip && c.idx == w - 'x') || c.kind == Kind::PTip)
        for (double f : hints[static_cast<size_t>(ci)].frequencies_hz) h.frequencies_hz.push_back(f);
    }
    return h;
  };
  // The tool point itself drifting or vibrating (a spindle growing with heat): one effect that tip and ptip both see.
  // Only where it differs from a channel's own: both groups recorded, or ptip alone on a machine whose table turns
  // (there a drift fixed in W turns in the part frame).
  const auto fitted = [&](Kind k) {
    return std::any_of(F.fitc.begin(), F.fitc.end(), [&](int ci) { return comps[static_cast<size_t>(ci)].kind == k; });
  };
  const bool table_turns =
      m.serial && std::any_of(m.serial->table_chain.begin(), m.serial->table_chain.end(), [&](int j) {
        return m.serial->joints[static_cast<size_t>(j)].type == kin::AxisType::Rotary;
      });
  const bool tool_candidates = fitted(Kind::PTip) && (fitted(Kind::Tip) || table_turns);
  if (tool_candidates)
    for (const char* c : {"tool.x", "tool.y", "tool.z"}) {
      protos.push_back(sim::make_effect("thermal_drift", c, m));
      growth(c);
      if (!tool_hints(std::string(c).back()).frequencies_hz.empty())
        protos.push_back(sim::make_effect("vibration", c, m));
    }

  // Geometric candidates: one per machine-file parameter of the calibration model, with the channels'
  // sensitivity to it (forward differences at anchor samples, interpolated between them).
  if (has_geom_channel) {
    std::shared_ptr<calib::Model> cm;
    try {
      cm = calib::load_model(m.file);
    } catch (const std::exception& ex) {
      R.warnings.push_back(fmt::format("geometric effects not tried: {}", ex.what()));
    }
    if (cm) {
      cm->set_tool_length_mm(L);
      const size_t np = cm->size(), nch = 9 + cm->links().size();
      const auto p0 = cm->nominal();
      const size_t astep = std::max<size_t>(1, ma / 1500);
      std::vector<size_t> anchors;
      for (size_t k = 0; k < ma; k += astep) anchors.push_back(k);
      if (anchors.back() != ma - 1) anchors.push_back(ma - 1);
      std::vector<std::vector<std::array<double, 9>>> at(np, std::vector<std::array<double, 9>>(anchors.size()));
      const size_t nt = worker_threads();
      on_workers(nt, [&](size_t w) {
        auto scratch = cm->make_scratch();
        std::vector<double> base(nch), pert(nch), p = p0;
        for (size_t a = w; a < anchors.size(); a += nt) {
          const kin::Axes& q = cmd[ctx.index[anchors[a]]];
          cm->predict_channels(q.data(), p.data(), base.data(), scratch.get());
          for (size_t j = 0; j < np; ++j) {
            const double h = 1e-5;
            p[j] += h;
            cm->predict_channels(q.data(), p.data(), pert.data(), scratch.get());
            p[j] = p0[j];
            auto& o = at[j][a];
            for (int c = 0; c < 3; ++c) {  // calib order: tip, dir, ptip -> ours: tip, ptip, dir
              o[static_cast<size_t>(c)] = (pert[static_cast<size_t>(c)] - base[static_cast<size_t>(c)]) / h;
              o[3 + static_cast<size_t>(c)] = (pert[6 + static_cast<size_t>(c)] - base[6 + static_cast<size_t>(c)]) / h;
              o[6 + static_cast<size_t>(c)] = (pert[3 + static_cast<size_t>(c)] - base[3 + static_cast<size_t>(c)]) / h;
            }
          }
        }
      });
      for (size_t j = 0; j < np; ++j) {
        auto tab = std::make_shared<std::vector<std::array<double, 9>>>(ma);
        double mag = 0;
        size_t a = 0;
        for (size_t k = 0; k < ma; ++k) {
          while (a + 1 < anchors.size() && anchors[a + 1] <= k) ++a;
          const size_t b = std::min(a + 1, anchors.size() - 1);
          const double f =
              b > a ? static_cast<double>(k - anchors[a]) / static_cast<double>(anchors[b] - anchors[a]) : 0.0;
          for (size_t r = 0; r < 9; ++r) {
            (*tab)[k][r] = (1 - f) * at[j][a][r] + f * at[j][b][r];
            mag = std::max(mag, std::abs((*tab)[k][r]));
          }
        }
        if (!(mag > 1e-9) || !std::isfinite(mag)) continue;  // the channels do not see this parameter
        // Seen only as a constant shift of every fitted channel (the part origin, measured from the part): the
        // channel offsets hold that already, and the fit would blow the parameter up to kilometres to follow the
        // round-off of its sensitivity.
        double varying = 0.0;
        for (int ci : F.fitc) {
          const Comp& c = comps[static_cast<size_t>(ci)];
          if (c.kind != Kind::Tip && c.kind != Kind::PTip && c.kind != Kind::Dir) continue;
          const size_t r = static_cast<size_t>(c.idx) + (c.kind == Kind::Tip ? 0 : c.kind == Kind::PTip ? 3 : 6);
          double sum = 0.0, sq = 0.0;
          for (size_t k = 0; k < ma; ++k) sum += (*tab)[k][r], sq += (*tab)[k][r] * (*tab)[k][r];
          varying = std::max(varying, std::sqrt(std::max(0.0, sq / static_cast<double>(ma) -
                                                                  std::pow(sum / static_cast<double>(ma), 2))));
        }
        if (!(varying > 1e-6 * mag)) continue;
        const auto& pi = cm->params()[j];
        auto e = sim::make_geometric(pi.name, pi.unit, pi.nominal, 0.0);
        e->geo_sens = tab;
        protos.push_back(std::move(e));
      }
    }
  }

  std::vector<std::unique_ptr<Effect>> model;
  auto view = [](const std::vector<std::unique_ptr<Effect>>& v) {
    std::vector<const Effect*> r;
    for (const auto& e : v) r.push_back(e.get());
    return r;
  };
  auto fit_view = [](std::vector<std::unique_ptr<Effect>>& v) {  // what joint_fit adjusts
    std::vector<Effect*> r;
    r.reserve(v.size());
    for (auto& e : v) r.push_back(e.get());
    return r;
  };
  // A copy of the accepted model with one candidate more.
  auto model_with = [&](std::unique_ptr<Effect> extra) {
    std::vector<std::unique_ptr<Effect>> t;
    t.reserve(model.size() + 1);
    for (const auto& e : model) t.push_back(e->clone());
    t.push_back(std::move(extra));
    return t;
  };
  // A large effect with sharp steps (lost motion) leaks into the upper band and raises the noise estimate, which
  // would then hide a small effect beside it. Once effects are modelled, the estimate is lowered by the factor by
  // which the analysis samples' own noise level fell (never raised: the first estimate used every sample).
  std::vector<double> noise0_analysis(comps.size(), 0.0), noise0(comps.size(), 0.0);
  for (int ci : F.fitc) {
    noise0_analysis[static_cast<size_t>(ci)] = analysis_noise(F, {}, ci);
    noise0[static_cast<size_t>(ci)] = comps[static_cast<size_t>(ci)].sigma;
  }
  auto renoise = [&](const std::vector<const Effect*>& fx) {
    bool changed = false;
    for (int ci : F.fitc) {
      auto& c = comps[static_cast<size_t>(ci)];
      const double a0 = noise0_analysis[static_cast<size_t>(ci)];
      if (!(a0 > floor_of(c))) continue;
      const double lowered = std::max(floor_of(c), noise0[static_cast<size_t>(ci)] * analysis_noise(F, fx, ci) / a0);
      if (lowered < kNoiseRefit * c.sigma) c.sigma = lowered, changed = true;
    }
    return changed;
  };
  // Axis effects enter the fits through the Jacobian, linear in the deviation. Where a deviation is large (a lag at a
  // rapid's speed, lost motion of a rotary far from its axis) the machine's curvature shows: FK(q + dq) - FK(q) - J dq,
  // 1.4 um in the XMINI's tip for a 3 ms lag on a leg at a rapid's speed, which a "step" then fitted. That term, for
  // the accepted effects' current values, is taken out of the geometric channels' residuals as known (the fits stay
  // linear in it; it is recomputed as the effects change). Returns the largest correction, in noise units.
  std::vector<std::vector<double>> res_linear(comps.size());
  for (int ci : F.fitc) res_linear[static_cast<size_t>(ci)] = comps[static_cast<size_t>(ci)].res;
  // Below these deviations the curvature term is under 1 % of a 0.5 um noise (dq^2 / 2R for a path radius R above
  // 40 mm; r theta^2 / 2 for a tool point within 500 mm of a rotary axis), and two FKs per sample (the XMINI's are
  // iterative) are not worth it.
  constexpr double kCurvedMm = 0.02, kCurvedDeg = 0.01;
  auto curved = [&](const kin::Axes& dq) {
    for (int j = 0; j < 5; ++j)
      if (std::abs(dq[j]) > (rot[static_cast<size_t>(j)] ? kCurvedDeg : kCurvedMm)) return true;
    return false;
  };
  auto relinearise = [&](const std::vector<const Effect*>& fx) {
    if (!need_j) return 0.0;
    std::vector<const Effect*> ax;
    for (const Effect* e : fx)
      if (e->scope() == Scope::Axis) ax.push_back(e);
    const size_t nt = worker_threads();
    std::vector<double> worst(nt, 0.0);
    on_workers(nt, [&](size_t w) {
      for (size_t k = ma * w / nt; k < ma * (w + 1) / nt; ++k) {
        kin::Axes dq = kin::Axes::Zero();
        for (const Effect* e : ax) dq[e->axis] += e->value(ctx, k, e->p.data());
        Eigen::Matrix<double, 9, 1> d = Eigen::Matrix<double, 9, 1>::Zero();
        if (curved(dq)) {
          const kin::Axes& q = cmd[ctx.index[k]];
          Eigen::Vector3d t0, p0, u0, t1, p1, u1;
          P.fk(q, t0, p0, u0);
          P.fk(q + dq, t1, p1, u1);
          d << t1 - t0, p1 - p0, u1 - u0;
          d -= F.J[k] * dq;
        }
        for (int ci : F.fitc) {
          Comp& c = comps[static_cast<size_t>(ci)];
          const int row = c.kind == Kind::Tip    ? c.idx
                          : c.kind == Kind::PTip ? 3 + c.idx
                          : c.kind == Kind::Dir  ? 6 + c.idx
                                                 : -1;
          if (row < 0) continue;
          c.res[k] = res_linear[static_cast<size_t>(ci)][k] - d[row];
          if (!std::isnan(c.res[k])) worst[w] = std::max(worst[w], std::abs(d[row]) / c.sigma);
        }
      }
    });
    return *std::max_element(worst.begin(), worst.end());
  };
  // Spectral peaks of the residual under the model accepted so far. The first search, on the residual before any
  // effect, misses a vibration that a large broadband effect hides (a 3 um vibration at 100 Hz beside the following
  // error of a 10 ms lag on an XMINI leg): the lag's spectrum raises the local level around the peak. Searched again
  // after each acceptance, new frequencies join the channel's vibration hints (and a vibration candidate is added
  // where the channel had none), so the next step can screen them; the acceptance thresholds still decide. The
  // spectrum is taken at full rate, on the regular grid as the first one: at an analysis stride of 1 the model's
  // residual is there at every row; with a stride, the model's prediction between analysis samples is interpolated
  // (a modelled vibration evaluated at every row, as it is faster than the stride), which never puts a frequency
  // above the analysis samples' Nyquist frequency at its alias.
  auto late_peaks = [&](const std::vector<const Effect*>& fx) {
    std::vector<const Effect*> slow, vib;
    for (const Effect* e : fx) (e->name() == "vibration" ? vib : slow).push_back(e);
    Context tctx;  // time only: all a vibration reads
    if (stride > 1 && !vib.empty()) tctx.t = t;
    std::vector<std::vector<Peak>> found(comps.size());
    const size_t nt = worker_threads();
    on_workers(nt, [&](size_t w) {
      for (size_t fi = w; fi < F.fitc.size(); fi += nt) {
        const int ci = F.fitc[fi];
        const Comp& c = comps[static_cast<size_t>(ci)];
        std::vector<double> r(n, kNaN);
        if (stride == 1) {
          for (size_t k = 0; k < ma; ++k)
            if (!std::isnan(c.res[k])) r[ctx.index[k]] = model_residual(F, fx, ci, k);
        } else {
          // The slow part of the prediction (offset, curvature term included) at the analysis samples.
          std::vector<double> pred(ma, kNaN), sv(ma * vib.size(), 0.0);
          for (size_t k = 0; k < ma; ++k) {
            if (!std::isnan(c.res[k])) pred[k] = c.res_full[ctx.index[k]] - model_residual(F, slow, ci, k);
            for (size_t v = 0; v < vib.size(); ++v)
              if (F.reaches(c, *vib[v])) sv[k * vib.size() + v] = F.sens(c, *vib[v], k);
          }
          for (size_t k = 0; k < ma; ++k) {
            const size_t a = ctx.index[k], b = k + 1 < ma ? ctx.index[k + 1] : n;
            for (size_t i = a; i < b; ++i) {
              if (std::isnan(c.res_full[i])) continue;
              const double f = k + 1 < ma ? static_cast<double>(i - a) / static_cast<double>(b - a) : 0.0;
              const double pa = pred[k], pb = k + 1 < ma ? pred[k + 1] : pa;
              const double pi = std::isnan(pa) ? pb : std::isnan(pb) ? pa : (1 - f) * pa + f * pb;
              if (std::isnan(pi)) continue;
              double x = c.res_full[i] - pi;
              for (size_t v = 0; v < vib.size(); ++v) {
                const double sa = sv[k * vib.size() + v], sb = k + 1 < ma ? sv[(k + 1) * vib.size() + v] : sa;
                x -= ((1 - f) * sa + f * sb) * vib[v]->value(tctx, i, vib[v]->p.data());
              }
              r[i] = x;
            }
          }
        }
        size_t present = 0;
        const std::vector<double> y = on_grid(r, tg, present);
        const auto P = periodogram(y);
        found[static_cast<size_t>(ci)] =
            find_peaks(P, y, ngrid, present, fs, duration, hints[static_cast<size_t>(ci)].frequencies_hz);
      }
    });
    bool added = false;
    for (int ci : F.fitc) {
      const auto& fk = found[static_cast<size_t>(ci)];
      if (fk.empty()) continue;
      added = true;
      auto& h = hints[static_cast<size_t>(ci)].frequencies_hz;
      if (h.empty()) protos.push_back(sim::make_effect("vibration", comps[static_cast<size_t>(ci)].name, m));
      for (const auto& pk : fk) h.push_back(pk.f);
    }
    if (tool_candidates)
      for (const char* c : {"tool.x", "tool.y", "tool.z"})
        if (!tool_hints(std::string(c).back()).frequencies_hz.empty() &&
            std::none_of(protos.begin(), protos.end(), [&](const auto& e) {
              return e->name() == "vibration" && e->scope() == Scope::Channel && e->channel == c;
            }))
          protos.push_back(sim::make_effect("vibration", c, m));
    return added;
  };
  // Searched when the greedy steps would stop (nothing else explains enough), once per model: a spectrum of every
  // fitted channel at full rate costs about as much as a step on a long recording, and a hidden vibration is found
  // as well last as in between.
  std::size_t peaks_searched_at = 0;  // the model size of the last late search (0: none)
  auto search_again = [&]() {
    if (model.empty() || peaks_searched_at == model.size()) return false;
    peaks_searched_at = model.size();
    return late_peaks(view(model));
  };
  double held_ms = weighted_ms(F, {}, true);
  const double held_ms_start = held_ms;
  std::vector<char> event_only;  // per accepted effect: judged on the training blocks (try_event)
  // Per accepted effect: others that explain as well, by identity (name, target) and description.
  struct Alternative {
    std::string name, target, what;
  };
  std::vector<std::vector<Alternative>> alternatives;
  std::vector<std::vector<double>> cur(comps.size());
  for (int step = 0; step < o.max_effects; ++step) {
    // The curvature term of the effects accepted so far; where it is more than a tenth of the noise, the effects
    // are refitted against the corrected residual (once: the term then changes by far less).
    if (!model.empty() && relinearise(view(model)) > 0.1) {
      joint_fit(F, fit_view(model));
      relinearise(view(model));
      held_ms = weighted_ms(F, view(model), true);
    }
    const auto fx = view(model);
    for (int ci : F.fitc) {
      auto& v = cur[static_cast<size_t>(ci)];
      v.resize(sidx.size());
      for (size_t s = 0; s < sidx.size(); ++s) v[s] = model_residual(F, fx, ci, sidx[s]);
    }
    // Where each channel's residual under the current model jumps most: the split of the analysis samples into a
    // before and an after whose means differ most for their counts (k (n - k) / n (mean_a - mean_b)^2, the
    // likelihood of one mean shift in white noise). A step's time is the middle of that split.
    std::vector<double> step_at(comps.size(), kNaN);
    for (int ci : F.fitc) {
      std::vector<double> r, tt;
      for (size_t k = 0; k < ma; ++k)
        if (!std::isnan(comps[static_cast<size_t>(ci)].res[k]))
          r.push_back(model_residual(F, fx, ci, k)), tt.push_back(ctx.t[k]);
      const size_t nr = r.size();
      if (nr < 4) continue;
      const double total = std::accumulate(r.begin(), r.end(), 0.0);
      double cum = 0, best = -1;
      for (size_t k = 1; k < nr; ++k) {
        cum += r[k - 1];
        const double nk = static_cast<double>(k), nn = static_cast<double>(nr);
        const double d = cum - nk / nn * total, stat = d * d * nn / (nk * (nn - nk));
        if (stat > best) best = stat, step_at[static_cast<size_t>(ci)] = 0.5 * (tt[k - 1] + tt[k]);
      }
    }
    std::vector<Candidate> res(protos.size());
    {
      const size_t nt = worker_threads();
      on_workers(nt, [&](size_t w) {
        for (size_t pi = w; pi < protos.size(); pi += nt) {
          const Effect& pr = *protos[pi];
          sim::GridHints h;
          for (size_t ci = 0; ci < comps.size(); ++ci)
            if (pr.scope() == Scope::Channel && comps[ci].name == pr.channel) {
              h = hints[ci];
              if (!std::isnan(step_at[ci])) h.step_times_s = {step_at[ci]};
            }
          if (pr.scope() == Scope::Channel && pr.channel.rfind("tool.", 0) == 0) h = tool_hints(pr.channel.back());
          res[pi] = screen(F, pr, sidx, cur, h);
        }
      });
    }
    // A named effect of the library is the more specific explanation: a geometric parameter that explains
    // the same (e.g. an axis direction vs squareness) must do clearly better (by 3 %) to be chosen.
    auto score = [&](size_t pi) { return res[pi].gain * (res[pi].e->scope() == Scope::Geometric ? 0.97 : 1.0); };
    // The best few by screening (each alone against the current residual) are refitted jointly with the
    // effects already accepted (on the screening samples), and the one that leaves the smallest held-out
    // residual wins: an effect that was partly absorbed by an earlier one gets its chance.
    std::vector<size_t> order;
    for (size_t pi = 0; pi < res.size(); ++pi)
      if (res[pi].e && score(pi) / std::max<double>(1.0, static_cast<double>(n_held_screen)) > thr_screen) {
        bool dup = false;
        for (const auto& e : model) dup |= e->name() == res[pi].e->name() && e->target == res[pi].e->target;
        if (!dup) order.push_back(pi);
      }
    // A transient the held-out blocks do not reach (a reversal spike at the one reversal of an out-and-back cut):
    // tried only when no effect passes the held-out test, and judged on the training blocks, with twice the
    // threshold on the sum (the held-out share of the test is missing) and no loss on the held-out blocks.
    auto try_event = [&]() {
      size_t ei = res.size();
      for (size_t pi = 0; pi < res.size(); ++pi) {
        if (!res[pi].event || res[pi].event_train_gain <= 2.0 * o.min_gain_sum) continue;
        bool dup = false;
        for (const auto& e : model) dup |= e->name() == res[pi].event->name() && e->target == res[pi].event->target;
        if (!dup && (ei == res.size() || res[pi].event_train_gain > res[ei].event_train_gain)) ei = pi;
      }
      if (ei == res.size()) return false;
      const auto off_save = F.off;
      const double train_ms = weighted_ms(F, view(model), false);
      auto trial = model_with(std::move(res[ei].event));
      joint_fit(F, fit_view(trial));
      const double new_train = weighted_ms(F, view(trial), false), new_held = weighted_ms(F, view(trial), true);
      const bool ok = std::all_of(trial.begin(), trial.end(),
                                  [&](const auto& e) { return plausible(*e, sample_s, t.front(), t.back()); });
      if (!ok || (train_ms - new_train) * static_cast<double>(n_train_values) <= 2.0 * o.min_gain_sum ||
          new_held > held_ms + 0.5 * thr) {
        F.off = off_save;
        return false;
      }
      held_ms = new_held;
      model = std::move(trial);
      event_only.push_back(1);
      if (renoise(view(model))) held_ms = weighted_ms(F, view(model), true);
      return true;
    };
    if (order.empty()) {
      if (search_again() || try_event()) continue;
      break;
    }
    std::sort(order.begin(), order.end(), [&](size_t a, size_t b) { return score(a) > score(b); });
    if (order.size() > 4) order.resize(4);
    const auto off_save = F.off;
    size_t bi = order.front();
    // Each of the best few refitted jointly: (candidate, its held-out mean square, what it says).
    std::vector<std::tuple<size_t, double, std::string>> refits;
    if (order.size() > 1) {
      double best_ms = std::numeric_limits<double>::infinity();
      for (size_t pi : order) {
        auto tr = model_with(res[pi].e->clone());
        joint_fit(F, fit_view(tr), sstride);
        const bool ok = std::all_of(tr.begin(), tr.end(),
                                    [&](const auto& e) { return plausible(*e, sample_s, t.front(), t.back()); });
        const double raw_ms = weighted_ms(F, view(tr), true);
        const double ms = raw_ms * (res[pi].e->scope() == Scope::Geometric ? 1.03 : 1.0);
        F.off = off_save;
        if (ok) refits.emplace_back(pi, raw_ms, describe(*tr.back()));
        if (ok && ms < best_ms) best_ms = ms, bi = pi;
      }
    }
    // Parsimony on one target: an effect with more parameters must explain what an effect must explain to count beyond
    // one with fewer, or the simpler is named (a first-order lag whose time constant is too short to show is the plain
    // lag; a straightness whose apex lies far outside the travel bends too little to show and is a squareness).
    {
      double ms_best = 0.0;
      for (const auto& [pi, ms, what] : refits)
        if (pi == bi) ms_best = ms;
      const Effect& eb = *res[bi].e;
      size_t fewest = eb.p.size();
      for (const auto& [pi, ms, what] : refits) {
        const Effect& e = *res[pi].e;
        if (pi == bi || e.scope() == Scope::Geometric || eb.scope() == Scope::Geometric || e.target != eb.target ||
            e.enc_visible != eb.enc_visible || e.p.size() >= fewest || ms - ms_best > thr)
          continue;
        fewest = e.p.size();
        bi = pi;
      }
    }
    // The others that leave a held-out residual larger by less than an effect must explain to count: the recording
    // cannot tell them from the one chosen.
    std::vector<Alternative> same;
    double chosen_ms = 0.0;
    for (const auto& [pi, ms, what] : refits)
      if (pi == bi) chosen_ms = ms;
    // (Not the chosen effect's own twin, seen or not by the encoder, nor a plain lag's first-order form, which only
    // generalises it; one line per explanation.)
    const auto lag = [](const std::string& n) { return n == "servo_lag" || n == "servo_lag_1st"; };
    for (const auto& [pi, ms, what] : refits) {
      const std::string& says = what;  // (a structured binding cannot be captured before C++20 in clang)
      if (pi != bi && ms - chosen_ms <= thr && held_ms - chosen_ms > thr &&
          (res[pi].e->name() != res[bi].e->name() || res[pi].e->target != res[bi].e->target) &&
          !(lag(res[pi].e->name()) && lag(res[bi].e->name()) && res[pi].e->target == res[bi].e->target) &&
          std::none_of(same.begin(), same.end(), [&](const Alternative& a) { return a.what == says; }))
        same.push_back({res[pi].e->name(), res[pi].e->target, says});
    }
    auto trial = model_with(std::move(res[bi].e));
    joint_fit(F, fit_view(trial));
    const double new_ms = weighted_ms(F, view(trial), true);
    const bool ok = std::all_of(trial.begin(), trial.end(),
                                [&](const auto& e) { return plausible(*e, sample_s, t.front(), t.back()); });
    if (!ok || held_ms - new_ms <= thr) {
      F.off = off_save;
      if (search_again() || try_event()) continue;
      break;
    }
    held_ms = new_ms;
    model = std::move(trial);
    event_only.push_back(0);
    alternatives.resize(model.size());
    alternatives.back() = std::move(same);
    if (renoise(view(model))) held_ms = weighted_ms(F, view(model), true);
  }
  if (!model.empty()) relinearise(view(model));  // the last accepted effect's curvature term too
  // The groups' noise as the findings left it (lowered where modelled steps had raised it).
  for (auto& [g, v] : R.noise) {
    double s = 0;
    for (const auto& c : comps)
      if (c.group == g) s += c.sigma * c.sigma;
    v = std::sqrt(s);
  }
  R.seconds.emplace_back("explain", secs(tstage));
  tstage = Clock::now();

  // ---- 4. findings, ranked by the held-out residual they explain ----------------------------------
  const auto fx_all = view(model);
  double total_gain = 0;
  for (size_t i = 0; i < model.size(); ++i) {
    std::vector<const Effect*> others;
    for (size_t j = 0; j < model.size(); ++j)
      if (j != i) others.push_back(model[j].get());
    Finding fd;
    fd.effect = model[i]->clone();
    // An effect the held-out blocks do not reach is judged, and its figures taken, on the training blocks.
    fd.judged_on_training = event_only[i] != 0;
    // An alternative that is itself in the model (accepted before or after this one) is no alternative: the
    // recording told it apart, as a finding of its own. (A plain lag and its first-order form are one effect.)
    if (i < alternatives.size())
      for (const auto& a : alternatives[i]) {
        const bool accepted = std::any_of(model.begin(), model.end(), [&](const auto& e) {
          return e->target == a.target &&
                 (e->name() == a.name || (is_lag(*e) && (a.name == "servo_lag" || a.name == "servo_lag_1st")));
        });
        if (!accepted) fd.alternatives.push_back(a.what);
      }
    const bool on_held = !fd.judged_on_training;
    if (fd.effect->name() == "vibration") fd.effect->note = source_of(fd.effect->p[0], rpm, flutes, sample_hz);
    // The group where it matters most, and its dominant component. Before/after are judged where the effect
    // acts (its contribution above half the noise), so that a localised effect (spikes at reversals) is judged
    // on the samples it explains, not diluted by the rest of the run.
    double best = -1;
    for (const auto& g : groups) {
      std::vector<char> mask(ma, 0);
      double sig = 0;
      for (int ci : F.fitc)
        if (comps[static_cast<size_t>(ci)].group == g) sig += std::pow(comps[static_cast<size_t>(ci)].sigma, 2);
      sig = std::sqrt(sig);
      size_t nmask = 0;
      for (size_t k = 0; k < ma; ++k) {
        double v2 = 0;
        for (int ci : F.fitc) {
          const Comp& c = comps[static_cast<size_t>(ci)];
          if (c.group != g || !F.reaches(c, *model[i])) continue;
          const double v = F.sens(c, *model[i], k) * model[i]->value(ctx, k, model[i]->p.data());
          v2 += v * v;
        }
        if (std::sqrt(v2) > 0.5 * sig && static_cast<bool>(F.held[k]) == on_held) mask[k] = 1, ++nmask;
      }
      const std::vector<char>* mp = nmask >= 5 ? &mask : nullptr;
      const double b = group_rms(F, others, g, on_held, mp), a = group_rms(F, fx_all, g, on_held, mp);
      const double bw = group_rms(F, others, g, on_held), aw = group_rms(F, fx_all, g, on_held);
      if (bw * bw - aw * aw > best)
        best = bw * bw - aw * aw, fd.group = g, fd.heldout_rms_before = b, fd.heldout_rms_after = a;
    }
    std::string dom = fd.group;
    double domv = -1;
    for (int ci : F.fitc) {
      const Comp& c = comps[static_cast<size_t>(ci)];
      if (!F.reaches(c, *model[i])) continue;
      double s = 0;
      for (size_t k = 0; k < ma; k += sstride) {
        const double v = F.sens(c, *model[i], k) * model[i]->value(ctx, k, model[i]->p.data()) / c.sigma;
        s += v * v;
      }
      if (s > domv) domv = s, dom = c.name;
    }
    fd.explains = explain(*fd.effect, dom);
    if (unseen_lag(*fd.effect))
      fd.explains += fmt::format(
          "; enc.{} does not see it: the lag lies between the axis's scale and the tool, or in the measurement itself",
          fd.effect->target);
    if (fd.effect->name() == "cyclic") {
      // A period longer than the travel recorded is a curve the recording cannot close: it stands in for a slope or
      // a bow over that travel as much as for a periodic error.
      const double travel = ctx.range(static_cast<size_t>(fd.effect->axis)).travel();
      if (fd.effect->p[0] > travel) {
        const std::string u = fd.effect->rotary ? "deg" : "mm";
        const std::string why = fmt::format(
            "the period of the cyclic error on {} ({:.1f} {}) is longer than its recorded travel ({:.1f} {}): not "
            "resolved; a recording over a whole period would tell",
            fd.effect->target, fd.effect->p[0], u, travel, u);
        fd.explains += "; " + why;
        R.warnings.push_back(why);
      }
    }
    fd.share = on_held ? weighted_ms(F, others, true) - held_ms
                       : weighted_ms(F, others, false) - weighted_ms(F, fx_all, false);
    total_gain += std::max(0.0, fd.share);
    R.findings.push_back(std::move(fd));
  }
  for (auto& fd : R.findings) fd.share = total_gain > 0 ? std::max(0.0, fd.share) / total_gain : 0;
  std::stable_sort(R.findings.begin(), R.findings.end(),
                   [](const Finding& a, const Finding& b) { return a.share > b.share; });
  R.heldout_rms_before = std::sqrt(held_ms_start);
  R.heldout_rms_after = std::sqrt(held_ms);
  R.heldout_values = n_held_values;

  // ---- 5. localisation ------------------------------------------------------------------------------
  std::vector<std::vector<double>> rev_times(5);
  for (int j = 0; j < 5; ++j) {
    double dir = 0;  // reversal: the direction of motion changes (full-rate commanded positions)
    for (size_t i = 1; i < n; ++i) {
      const double dq = cmd[i][j] - cmd[i - 1][j];
      if (std::abs(dq) > 1e-12) {
        const double nd = dq > 0 ? 1 : -1;
        if (dir != 0 && nd != dir) rev_times[static_cast<size_t>(j)].push_back(t[i - 1]);
        dir = nd;
      }
    }
  }
  for (size_t ci = 0; ci < comps.size(); ++ci) {
    const Comp& c = comps[ci];
    double mean = 0, cnt = 0;
    for (double v : c.res_full)
      if (!std::isnan(v)) mean += v, cnt += 1;
    if (cnt == 0) continue;
    mean /= cnt;
    double ms = 0;
    for (double v : c.res_full)
      if (!std::isnan(v)) ms += (v - mean) * (v - mean);
    const double rms = std::sqrt(ms / cnt);
    if (rms < 1.5 * c.sigma) continue;  // nothing beyond noise in this channel
    // Windows in time where the residual is large.
    const int W = 40;
    std::vector<double> wr(W, 0.0), wc(W, 0.0);
    for (size_t i = 0; i < n; ++i) {
      if (std::isnan(c.res_full[i])) continue;
      const int w = std::min(W - 1, static_cast<int>((t[i] - t.front()) / std::max(duration, 1e-12) * W));
      wr[static_cast<size_t>(w)] += (c.res_full[i] - mean) * (c.res_full[i] - mean);
      wc[static_cast<size_t>(w)] += 1;
    }
    for (int w = 0; w < W; ++w)
      wr[static_cast<size_t>(w)] =
          wc[static_cast<size_t>(w)] > 0 ? std::sqrt(wr[static_cast<size_t>(w)] / wc[static_cast<size_t>(w)]) : 0;
    const double wmed = median(wr);
    int emitted = 0;
    for (int w = 0; w < W && emitted < 3; ++w) {
      if (!(wr[static_cast<size_t>(w)] > 2.0 * wmed && wr[static_cast<size_t>(w)] > 3 * c.sigma)) continue;
      int w2 = w;
      double peak = wr[static_cast<size_t>(w)];
      while (w2 + 1 < W && wr[static_cast<size_t>(w2 + 1)] > 2.0 * wmed)
        peak = std::max(peak, wr[static_cast<size_t>(++w2)]);
      Localization l;
      l.channel = c.name;
      l.t_start = t.front() + duration * w / W;
      l.t_end = t.front() + duration * (w2 + 1) / W;
      l.rms = peak;
      std::string with;
      for (int j = 0; j < 5; ++j)
        for (double tr : rev_times[static_cast<size_t>(j)])
          if (tr >= l.t_start - duration / W && tr <= l.t_end + duration / W) {
            with += (with.empty() ? "reversal of " : ", ") + m.axes[static_cast<size_t>(j)].name;
            break;
          }
      l.coincides_with = with.empty() ? "" : with;  // no reversal: filled with the best feature below
      R.localization.push_back(l);
      ++emitted;
      w = w2;
    }
    // Correlation with features of the motion over the whole run.
    std::string best_feat;
    double best_r2 = 0;
    auto corr = [&](const std::vector<double>& f, const std::string& name) {
      double sx = 0, sy = 0, sxx = 0, syy = 0, sxy = 0, k = 0;
      for (size_t a = 0; a < ma; ++a) {
        const double y = c.res[a];
        if (std::isnan(y)) continue;
        sx += f[a], sy += y, sxx += f[a] * f[a], syy += y * y, sxy += f[a] * y, k += 1;
      }
      const double vx = sxx - sx * sx / k, vy = syy - sy * sy / k, cxy = sxy - sx * sy / k;
      if (vx <= 1e-300 || vy <= 1e-300) return;
      const double r2 = cxy * cxy / (vx * vy);
      if (r2 > best_r2) best_r2 = r2, best_feat = name;
    };
    corr(ctx.t, "elapsed time");
    for (int j = 0; j < 5; ++j) {
      const auto& an = m.axes[static_cast<size_t>(j)].name;
      corr(ctx.q[static_cast<size_t>(j)], "position along " + an);
      corr(ctx.v[static_cast<size_t>(j)], "velocity of " + an);
      corr(ctx.a[static_cast<size_t>(j)], "acceleration of " + an);
      corr(ctx.dir[static_cast<size_t>(j)], "direction of motion of " + an + " (reversals)");
    }
    for (auto& l : R.localization)
      if (l.channel == c.name && l.coincides_with.empty())
        l.coincides_with = best_r2 > 0.2 ? fmt::format("no reversal there; the channel follows the {}", best_feat)
                                         : "elapsed time (no reversal there)";
    if (best_r2 > 0.2) {
      Localization l;
      l.channel = c.name;
      l.t_start = t.front();
      l.t_end = t.back();
      l.rms = rms;
      l.coincides_with = fmt::format("{} (R^2 = {:.2f})", best_feat, best_r2);
      R.localization.push_back(l);
    }
    for (const auto& pk : peaks[ci]) {
      Localization l;
      l.channel = c.name;
      l.t_start = t.front();
      l.t_end = t.back();
      l.rms = pk.amp / std::sqrt(2.0);
      const std::string src = source_of(pk.f, rpm, flutes, sample_hz);
      std::string rel =
          src == "tooth_passing"
              ? fmt::format(" = tooth passing ({} rpm x {} flutes / 60 = {:.1f} Hz{})", rpm, flutes, rpm * flutes / 60,
                            std::round(pk.f / (rpm * flutes / 60)) > 1 ? ", harmonic" : "")
          : src == "spindle" ? fmt::format(" = spindle rotation ({} rpm / 60 = {:.1f} Hz)", rpm, rpm / 60)
                             : " (not related to the spindle)";
      l.coincides_with = fmt::format("spectral peak at {:.1f} Hz{}", pk.f, rel);
      R.localization.push_back(l);
    }
  }
  R.seconds.emplace_back("localise_and_report", secs(tstage));

  // Constant offsets well above the noise of their component (5 sigma; a mean of many samples is known far better,
  // but a sub-noise zero shift is nothing to act on).
  for (int ci : F.fitc) {
    const Comp& c = comps[static_cast<size_t>(ci)];
    const double off = F.off[static_cast<size_t>(ci)];
    if (std::abs(off) > kOffsetNoted * c.sigma) R.offsets.emplace_back(c.name, off);
  }

  // ---- 6. verdict ------------------------------------------------------------------------------------
  std::string fitted_groups;
  double noise_total = 0;
  for (const auto& [g, v] : R.noise)
    if (g != "acc") noise_total = std::max(noise_total, v);
  // What the findings leave: per channel group, the held-out RMS against the noise. A mean square above the noise
  // variance by more than its own sampling spread (8 sigma of a chi-square mean, at least 20 %) is physics the
  // library does not model, or models only in part; the verdict must not call that noise.
  std::string left;
  for (size_t gi = 0; gi < R.noise.size(); ++gi) {
    const std::string& g = R.noise[gi].first;
    if (g == "acc" || !(R.noise[gi].second > 0)) continue;
    std::vector<char> any(ma, 0);
    for (int ci : F.fitc)
      if (comps[static_cast<size_t>(ci)].group == g)
        for (size_t k = 0; k < ma; ++k)
          if (F.held[k] && !std::isnan(comps[static_cast<size_t>(ci)].res[k])) any[k] = 1;
    const auto cnt = static_cast<double>(std::count(any.begin(), any.end(), 1));
    if (cnt < 10) continue;
    const double rms = group_rms(F, fx_all, g, true), ratio2 = std::pow(rms / R.noise[gi].second, 2);
    if (ratio2 > 1.0 + std::max(0.2, 8.0 * std::sqrt(2.0 / cnt)))
      left += fmt::format("{}{} {} RMS held out vs noise {}", left.empty() ? "" : ", ", g, fmt_group(m, g, rms),
                          fmt_group(m, g, R.noise[gi].second));
  }
  // Acceleration channels give spectra but are not fitted: a residual there far above the noise is not noise either.
  std::string acc_left;
  for (size_t gi = 0; gi < R.noise.size(); ++gi)
    if (R.noise[gi].first == "acc" && R.noise[gi].second > 0 && R.rms_before[gi].second > 2.0 * R.noise[gi].second)
      acc_left = fmt::format("acc {:.4g} RMS vs noise {:.4g}", R.rms_before[gi].second, R.noise[gi].second);
  R.residual_above_noise = !left.empty();
  if (R.findings.empty() && left.empty() && !acc_left.empty()) {
    R.residual_above_noise = true;
    R.verdict = fmt::format(
        "unexplained: the acceleration residual is above the measurement noise ({}); acceleration channels are not "
        "fitted to the effect library{}: record tip, ptip or enc channels as well to name the cause",
        acc_left, F.fitc.empty() ? " and the recording has no other" : "");
  } else if (R.findings.empty() && R.residual_above_noise) {
    R.verdict = fmt::format(
        "unexplained: the residual is above the measurement noise ({}), but no effect of the library explains it; {}",
        left,
        R.localization.empty() ? "it is spread over the run and follows none of the features tried (axis positions, "
                                 "velocities, accelerations, directions of motion, time)"
                               : "see where it is large and what it follows");
  } else if (R.findings.empty()) {
    // The held-out RMS once the constant offsets are removed (the raw RMS holds them; they are listed apart).
    std::string parts;
    for (size_t i = 0; i < R.noise.size(); ++i)
      if (R.noise[i].first != "acc")
        parts += fmt::format("{}{} {} RMS held out vs noise {}", parts.empty() ? "" : ", ", R.noise[i].first,
                             fmt_group(m, R.noise[i].first, group_rms(F, fx_all, R.noise[i].first, true)),
                             fmt_group(m, R.noise[i].first, R.noise[i].second));
    R.verdict =
        fmt::format("no missing physics found: the residual is consistent with measurement noise alone ({})", parts);
  } else {
    std::string parts;
    for (const auto& fd : R.findings) {
      parts += (parts.empty() ? "" : "; ") + describe(*fd.effect);
      if (!fd.alternatives.empty())
        parts += fmt::format(" (or as well: {}; this recording cannot tell them apart)",
                             fmt::join(fd.alternatives, "; or "));
    }
    // The same lag on several axes that their encoders do not see is most likely one delay of the measurement (a
    // tracker's or a probe's latency against the command's clock), not as many servos lagging alike.
    std::string latency;
    std::vector<const Finding*> lags;
    for (const auto& fd : R.findings)
      if (unseen_lag(*fd.effect)) lags.push_back(&fd);
    if (lags.size() >= 2) {
      double lo = std::numeric_limits<double>::infinity(), hi = 0;
      std::string axes;
      for (const Finding* fd : lags) {
        const double lag_s = steady_lag_s(*fd->effect);
        lo = std::min(lo, lag_s);
        hi = std::max(hi, lag_s);
        axes += (axes.empty() ? "" : ", ") + fd->effect->target;
      }
      if (lo > 0 && hi <= 1.1 * lo)
        latency = fmt::format(
            "; the same lag of {:.2f} ms on {}, which their encoders do not see: most likely the measurement itself "
            "runs {:.2f} ms late (a latency of the tracker or probe against the command), not the servos",
            0.5 * (lo + hi) * 1000, axes, 0.5 * (lo + hi) * 1000);
    }
    const auto& top = R.findings.front();
    R.verdict =
        fmt::format("missing physics: {}; modelled, the {} RMS of {} falls from {} to {}", parts,
                    top.judged_on_training ? "training-block" : "held-out", top.group,
                    fmt_group(m, top.group, top.heldout_rms_before), fmt_group(m, top.group, top.heldout_rms_after));
    R.verdict += latency;
    if (R.residual_above_noise)
      R.verdict += fmt::format(
          "; what is left is still above the noise ({}): an effect outside the library, or one modelled only in part",
          left);
  }
  if (!R.offsets.empty()) {
    std::string offs;
    for (const auto& off : R.offsets) {  // (no structured binding: a lambda captures it)
      const auto& c = *std::find_if(comps.begin(), comps.end(), [&](const Comp& x) { return x.name == off.first; });
      offs += fmt::format("{}{} {}", offs.empty() ? "" : ", ", off.first, fmt_group(m, c.group, off.second));
    }
    R.verdict += fmt::format(
        "; constant offsets (a zero or reference shift, or an effect this motion shows only as a constant, such as "
        "lost motion on an axis that never reverses): {}",
        offs);
  }

  // ---- plot data ---------------------------------------------------------------------------------------
  if (o.keep_plot_data) {
    int mci = F.fitc.empty() ? 0 : F.fitc.front();
    double best = -1;
    for (int ci : F.fitc) {
      double s = 0;
      for (size_t k = 0; k < ma; ++k)
        if (!std::isnan(comps[static_cast<size_t>(ci)].res[k]))
          s += std::pow((comps[static_cast<size_t>(ci)].res[k] - F.off[static_cast<size_t>(ci)]) /
                            comps[static_cast<size_t>(ci)].sigma,
                        2);
      if (s > best) best = s, mci = ci;
    }
    const Comp& c = comps[static_cast<size_t>(mci)];
    R.main_channel = c.name;
    Series before{"before", {}, {}}, after{"after", {}, {}};
    const size_t ps = std::max<size_t>(1, ma / 1500);
    for (size_t k = 0; k < ma; k += ps) {
      if (std::isnan(c.res[k])) continue;
      before.x.push_back(ctx.t[k]);
      before.y.push_back(c.res[k] - F.off[static_cast<size_t>(mci)]);
      after.x.push_back(ctx.t[k]);
      after.y.push_back(model_residual(F, fx_all, mci, k));
    }
    R.plots_time = {before, after};
    // Feature: the axis position the residual correlates with best (or time).
    R.feature_name = "elapsed time, s";
    std::vector<double> feat = ctx.t;
    if (!R.findings.empty() && R.findings.front().effect->axis >= 0) {
      const int ax =
          R.findings.front().effect->axis2 >= 0 ? R.findings.front().effect->axis2 : R.findings.front().effect->axis;
      feat = ctx.q[static_cast<size_t>(ax)];
      R.feature_name = "position of " + m.axes[static_cast<size_t>(ax)].name;
    }
    Series fb{"before", {}, {}}, fa{"after", {}, {}};
    for (size_t k = 0; k < ma; k += ps) {
      if (std::isnan(c.res[k])) continue;
      fb.x.push_back(feat[k]);
      fb.y.push_back(c.res[k] - F.off[static_cast<size_t>(mci)]);
      fa.x.push_back(feat[k]);
      fa.y.push_back(model_residual(F, fx_all, mci, k));
    }
    R.plots_feature = {fb, fa};
    // Spectrum of the main channel (amplitude, mm) on a thinned frequency axis.
    const auto& P = spectra[static_cast<size_t>(mci)];
    Series sp{c.name, {}, {}};
    const size_t fstep = std::max<size_t>(1, P.size() / 4000);
    for (size_t k = 1; k < P.size(); k += fstep) {
      double mx = 0;
      for (size_t q = k; q < std::min(P.size(), k + fstep); ++q) mx = std::max(mx, P[q]);
      sp.x.push_back(static_cast<double>(k) * fs / static_cast<double>(ngrid));
      sp.y.push_back(2.0 * std::sqrt(mx) /
                     static_cast<double>(std::max<size_t>(spectrum_n[static_cast<size_t>(mci)], 1)));
    }
    R.plots_spectrum = {sp};
    for (const auto& pk : peaks[static_cast<size_t>(mci)]) R.peak_freqs.push_back(pk.f);
  }
  return R;
}

std::string Report::to_json() const {
  nlohmann::ordered_json j;
  j["recording"] = recording;
  j["machine"] = machine;
  j["samples"] = samples;
  j["rms_before"] = nlohmann::ordered_json::object();
  for (const auto& [k, v] : rms_before) j["rms_before"][k] = v;
  j["noise"] = nlohmann::ordered_json::object();
  for (const auto& [k, v] : noise) j["noise"][k] = v;
  j["localization"] = nlohmann::ordered_json::array();
  for (const auto& l : localization)
    j["localization"].push_back({{"channel", l.channel},
                                 {"t_start", l.t_start},
                                 {"t_end", l.t_end},
                                 {"rms", l.rms},
                                 {"coincides_with", l.coincides_with}});
  j["findings"] = nlohmann::ordered_json::array();
  // recording.md: one `geometric` finding whose target lists the parameters that moved (comma-separated),
  // one key per parameter. It takes the place of the largest geometric finding; its share is their sum and
  // its held-out figures the conservative ones (largest before, largest after).
  int geo_at = -1;
  for (const auto& f : findings) {
    if (f.effect->name() == "geometric") {
      if (geo_at < 0) {
        geo_at = static_cast<int>(j["findings"].size());
        nlohmann::ordered_json fj;
        fj["effect"] = "geometric";
        fj["target"] = f.effect->target;
        fj["parameters"] = nlohmann::ordered_json::object();
        fj["explains"] = f.explains;
        fj["channel"] = f.group;
        fj["share"] = 0.0;
        fj["heldout_rms_before"] = f.heldout_rms_before;
        fj["heldout_rms_after"] = f.heldout_rms_after;
        j["findings"].push_back(fj);
      } else {
        auto& g = j["findings"][static_cast<size_t>(geo_at)];
        g["target"] = g["target"].get<std::string>() + "," + f.effect->target;
        g["explains"] = g["explains"].get<std::string>() + "; " + f.explains;
        g["heldout_rms_before"] = std::max(g["heldout_rms_before"].get<double>(), f.heldout_rms_before);
        g["heldout_rms_after"] = std::max(g["heldout_rms_after"].get<double>(), f.heldout_rms_after);
      }
      auto& g = j["findings"][static_cast<size_t>(geo_at)];
      for (const auto& [k, v] : f.effect->reported()) g["parameters"][k] = v;
      g["share"] = g["share"].get<double>() + f.share;
      continue;
    }
    nlohmann::ordered_json p = nlohmann::ordered_json::object();
    for (const auto& [k, v] : f.effect->reported()) p[k] = v;
    if (f.effect->name() == "vibration" && !f.effect->note.empty()) p["source"] = f.effect->note;
    if (f.effect->follows_temperature()) p["sensor"] = "temp." + f.effect->note;
    nlohmann::ordered_json fj;
    fj["effect"] = f.effect->name();
    fj["target"] = f.effect->target;
    fj["parameters"] = p;
    fj["explains"] = f.explains;
    fj["channel"] = f.group;
    fj["share"] = f.share;
    fj["heldout_rms_before"] = f.heldout_rms_before;
    fj["heldout_rms_after"] = f.heldout_rms_after;
    if (f.judged_on_training) fj["judged_on"] = "training blocks (no held-out block holds the samples where it acts)";
    if (!f.alternatives.empty()) fj["equally_explained_by"] = f.alternatives;
    j["findings"].push_back(fj);
  }
  j["heldout_residual"] = {{"values", heldout_values},
                           {"rms_before_noise_units", heldout_rms_before},
                           {"rms_after_noise_units", heldout_rms_after},
                           {"above_noise", residual_above_noise}};
  j["offsets"] = nlohmann::ordered_json::object();
  for (const auto& [k, v] : offsets) j["offsets"][k] = v;
  j["verdict"] = verdict;
  j["seconds"] = nlohmann::ordered_json::object();
  for (const auto& [k, v] : seconds) j["seconds"][k] = v;
  if (!warnings.empty()) j["warnings"] = warnings;
  return j.dump(2);
}

std::string Report::text() const {
  std::ostringstream os;
  os << fmt::format("recording {} ({} samples), machine {}\n", recording, samples, machine);
  for (size_t i = 0; i < rms_before.size(); ++i)
    os << fmt::format("  {:<10} residual RMS {:>10.4f}   noise {:>10.4f}\n", rms_before[i].first, rms_before[i].second,
                      noise[i].second);
  if (!localization.empty()) os << "where:\n";
  for (const auto& l : localization)
    os << fmt::format("  {:<8} t {:8.3f} .. {:8.3f} s  rms {:.4f}  {}\n", l.channel, l.t_start, l.t_end, l.rms,
                      l.coincides_with);
  if (!findings.empty()) os << "findings (largest share first; held-out RMS of the channel group before -> after):\n";
  for (const auto& f : findings) {
    std::string ps;
    for (const auto& [k, v] : f.effect->reported()) ps += fmt::format(" {}={:.6g}", k, v);
    os << fmt::format("  {:>3.0f}%  {} {}:{}\n        {}; {} {:.4f} -> {:.4f}{}\n", 100 * f.share, f.effect->name(),
                      f.effect->target, ps, f.explains, f.group, f.heldout_rms_before, f.heldout_rms_after,
                      f.judged_on_training ? " (training blocks: it acts where no held-out block is)" : "");
    for (const auto& a : f.alternatives)
      os << fmt::format("        as well explained by: {} (this recording cannot tell them apart)\n", a);
  }
  os << "verdict: " << verdict << "\n";
  return os.str();
}

std::string model_yaml(const std::string& text, const std::vector<const sim::Effect*>& effects) {
  // Drop an old top-level effects: block (its line and the indented/list lines that follow).
  std::istringstream in(text);
  std::string line, out;
  bool skipping = false;
  while (std::getline(in, line)) {
    if (line.rfind("effects:", 0) == 0) {
      skipping = true;
      continue;
    }
    if (skipping && (line.empty() || line[0] == ' ' || line[0] == '-' || line[0] == '#')) continue;
    skipping = false;
    out += line + "\n";
  }
  out += "# Identified by cscam diagnose: applied by cscam simulate, part of the model in cscam diagnose.\n";
  out += sim::effects_yaml(effects);
  return out;
}

std::string linuxcnc_ini(const machine::Machine& m, const std::vector<const sim::Effect*>& effects,
                         const std::string& comp_prefix, std::map<std::string, std::string>& comp_files) {
  std::string ini = "# LinuxCNC compensation from cscam diagnose (joint numbers in the machine file's axis order)\n";
  for (int j = 0; j < 5; ++j) {
    double backlash = 0;
    std::vector<const sim::Effect*> table;
    for (const auto* e : effects) {
      // (Errors that follow another axis's position cannot go into this axis's table.)
      if (e->scope() != sim::Scope::Axis || e->axis != j || (e->axis2 >= 0 && e->axis2 != j)) continue;
      if (e->name() == "backlash") backlash += e->p[0];
      if (e->name() == "scale" || e->name() == "cyclic" || e->name() == "straightness") table.push_back(e);
    }
    if (backlash == 0 && table.empty()) continue;
    const auto& ax = m.axes[static_cast<size_t>(j)];
    ini += fmt::format("[JOINT_{}]\n# axis {}\n", j, ax.name);
    if (table.empty()) {
      ini += fmt::format("BACKLASH = {:.6f}\n", backlash);
      continue;
    }
    // COMP_FILE_TYPE 0: nominal, position while moving forward, position while moving in reverse.
    const std::string file = fmt::format("{}.joint{}.comp", comp_prefix, j);
    const double lo = ax.rotary() ? ax.min * 180 / 3.14159265358979323846 : ax.min;
    const double hi = ax.rotary() ? ax.max * 180 / 3.14159265358979323846 : ax.max;
    const double span = std::min(hi - lo, ax.rotary() ? 720.0 : 2000.0);
    double step = span / 256;
    for (const auto* e : table)
      if (e->name() == "cyclic") step = std::min(step, e->p[0] / 8);
    std::string tab = fmt::format("# {} {}: nominal forward reverse (COMP_FILE_TYPE 0)\n", m.name, ax.name);
    const double c0 = std::max(lo, -span / 2), c1 = std::min(hi, span / 2);
    sim::Context ctx;
    for (double x = c0; x <= c1 + 1e-9; x += step) {
      double dev = 0;
      for (const auto* e : table) {
        if (e->name() == "scale") dev += x * 1e-6 * e->p[0];
        if (e->name() == "straightness") dev += e->p[0] * std::pow((x - e->p[1]) * 1e-3, 2);
        if (e->name() == "cyclic") {
          const double ph = 2 * 3.14159265358979323846 * x / e->p[0];
          dev += e->p[1] * std::sin(ph) + e->p[2] * std::cos(ph);
        }
      }
      tab += fmt::format("{:.6f} {:.6f} {:.6f}\n", x, x + dev - backlash / 2, x + dev + backlash / 2);
      if (tab.size() > 2'000'000) break;
    }
    comp_files[file] = tab;
    ini += fmt::format("COMP_FILE = {}\nCOMP_FILE_TYPE = 0\n", file);
    if (backlash != 0) ini += "# backlash is included in the table (BACKLASH must stay 0 with a COMP_FILE)\n";
  }
  return ini;
}

namespace {
std::string svg_plot(const std::string& title, const std::string& xlabel, const std::string& ylabel,
                     const std::vector<Series>& series, bool points, const std::vector<double>& marks = {}) {
  const double W = 800, H = 360, ml = 70, mr = 20, mt = 30, mb = 45;
  double x0 = 1e300, x1 = -1e300, y0 = 1e300, y1 = -1e300;
  for (const auto& s : series)
    for (size_t i = 0; i < s.x.size(); ++i)
      x0 = std::min(x0, s.x[i]), x1 = std::max(x1, s.x[i]), y0 = std::min(y0, s.y[i]), y1 = std::max(y1, s.y[i]);
  if (!(x1 > x0)) x1 = x0 + 1;
  if (!(y1 > y0)) y1 = y0 + 1e-6;
  auto X = [&](double x) { return ml + (x - x0) / (x1 - x0) * (W - ml - mr); };
  auto Y = [&](double y) { return H - mb - (y - y0) / (y1 - y0) * (H - mt - mb); };
  std::string s = fmt::format(
      "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{}\" height=\"{}\" font-family=\"sans-serif\" "
      "font-size=\"12\">\n",
      W, H);
  s += fmt::format("<rect x=\"{}\" y=\"{}\" width=\"{}\" height=\"{}\" fill=\"none\" stroke=\"#444\"/>\n", ml, mt,
                   W - ml - mr, H - mt - mb);
  s += fmt::format("<text x=\"{}\" y=\"20\" font-size=\"14\">{}</text>\n", ml, title);
  s += fmt::format("<text x=\"{}\" y=\"{}\" text-anchor=\"middle\">{}</text>\n", (W + ml) / 2, H - 8, xlabel);
  s += fmt::format("<text x=\"14\" y=\"{}\" transform=\"rotate(-90 14 {})\" text-anchor=\"middle\">{}</text>\n", H / 2,
                   H / 2, ylabel);
  for (int i = 0; i <= 4; ++i) {
    const double xv = x0 + (x1 - x0) * i / 4, yv = y0 + (y1 - y0) * i / 4;
    s += fmt::format("<text x=\"{:.1f}\" y=\"{}\" text-anchor=\"middle\">{:.4g}</text>\n", X(xv), H - mb + 15, xv);
    s += fmt::format("<text x=\"{}\" y=\"{:.1f}\" text-anchor=\"end\">{:.4g}</text>\n", ml - 4, Y(yv) + 4, yv);
  }
  const char* colors[] = {"#c0392b", "#2471a3", "#229954", "#7d3c98"};
  for (size_t k = 0; k < series.size(); ++k) {
    const auto& se = series[k];
    if (points) {
      for (size_t i = 0; i < se.x.size(); ++i)
        s += fmt::format("<circle cx=\"{:.1f}\" cy=\"{:.1f}\" r=\"1.2\" fill=\"{}\"/>\n", X(se.x[i]), Y(se.y[i]),
                         colors[k % 4]);
    } else {
      s += fmt::format("<polyline fill=\"none\" stroke=\"{}\" stroke-width=\"1\" points=\"", colors[k % 4]);
      for (size_t i = 0; i < se.x.size(); ++i) s += fmt::format("{:.1f},{:.1f} ", X(se.x[i]), Y(se.y[i]));
      s += "\"/>\n";
    }
    s += fmt::format("<text x=\"{}\" y=\"{}\" fill=\"{}\">{}</text>\n", W - mr - 120, mt + 16 + 14 * k, colors[k % 4],
                     se.name);
  }
  for (double mk : marks)
    s += fmt::format(
        "<line x1=\"{0:.1f}\" x2=\"{0:.1f}\" y1=\"{1}\" y2=\"{2}\" stroke=\"#e67e22\" stroke-dasharray=\"4 3\"/>"
        "<text x=\"{0:.1f}\" y=\"{3}\" fill=\"#e67e22\">{4:.1f} Hz</text>\n",
        X(mk), mt, H - mb, mt + 12, mk);
  s += "</svg>\n";
  return s;
}
}  // namespace

std::map<std::string, std::string> svg_pictures(const Report& r) {
  std::map<std::string, std::string> out;
  if (r.plots_time.empty()) return out;
  out["residual_time.svg"] = svg_plot("residual of " + r.main_channel + " before and after the identified effects",
                                      "time, s", r.main_channel + " residual", r.plots_time, false);
  out["residual_feature.svg"] = svg_plot("residual of " + r.main_channel + " against " + r.feature_name, r.feature_name,
                                         r.main_channel + " residual", r.plots_feature, true);
  out["spectrum.svg"] = svg_plot("amplitude spectrum of the " + r.main_channel + " residual (identified peaks dashed)",
                                 "frequency, Hz", "amplitude", r.plots_spectrum, false, r.peak_freqs);
  return out;
}

}  // namespace cscam::diagnose
