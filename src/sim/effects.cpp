#include "cscam/sim/effects.hpp"

#include <ceres/jet.h>
#include <fmt/format.h>
#include <yaml-cpp/yaml.h>

#include <array>
#include <atomic>
#include <cmath>
#include <functional>
#include <map>
#include <mutex>
#include <numbers>

#include "cscam/calib/model.hpp"
#include "cscam/core/error.hpp"
#include "cscam/machine/machine.hpp"

namespace cscam::sim {

namespace {
constexpr double kPi = std::numbers::pi;
constexpr double kInf = std::numeric_limits<double>::infinity();
}  // namespace

Context::Range Context::range(size_t j) const {
  Range r{kInf, -kInf};
  for (const double x : q[j]) r.lo = std::min(r.lo, x), r.hi = std::max(r.hi, x);
  return r;
}

Context make_context(const std::vector<double>& t, const std::vector<kin::Axes>& cmd, const std::array<bool, 5>& rotary,
                     size_t stride) {
  Context c;
  const size_t n = t.size();
  CSCAM_CHECK(cmd.size() == n, "make_context: t and cmd differ in length");
  if (stride < 1) stride = 1;
  c.rotary = rotary;
  static std::atomic<std::uint64_t> next_id{1};
  c.id = next_id++;
  c.t_full = t;
  c.t0 = n ? t.front() : 0;
  c.duration = n ? t.back() - t.front() : 0;
  const size_t m = n ? (n - 1) / stride + 1 : 0;
  c.t.reserve(m);
  c.index.reserve(m);
  for (size_t i = 0; i < n; i += stride) {
    c.t.push_back(t[i]);
    c.index.push_back(i);
  }
  for (int ax = 0; ax < 5; ++ax) {
    auto& q = c.q[ax];
    auto& v = c.v[ax];
    auto& a = c.a[ax];
    auto& d = c.dir[ax];
    auto& s = c.since_rev[ax];
    auto& ts = c.travel_since_rev[ax];
    auto& tr = c.travel[ax];
    q.reserve(m), v.reserve(m), a.reserve(m), d.reserve(m), s.reserve(m), ts.reserve(m), tr.reserve(m);
    auto& vf = c.v_full[ax];
    vf.resize(n);
    // Direction of the last motion (initially that of the first motion) and time of the last reversal.
    double dir = 0;
    for (size_t i = 1; i < n && dir == 0; ++i) {
      const double dq = cmd[i][ax] - cmd[i - 1][ax];
      if (std::abs(dq) > 1e-12) dir = dq > 0 ? 1 : -1;
    }
    if (dir == 0) dir = 1;
    double t_rev = -kInf, moved = 0.0, moved_since_rev = kInf;
    for (size_t i = 0; i < n; ++i) {
      if (i > 0) {
        const double dq = cmd[i][ax] - cmd[i - 1][ax];
        if (std::abs(dq) > 1e-12) {
          const double nd = dq > 0 ? 1 : -1;
          if (nd != dir) t_rev = t[i - 1], moved_since_rev = 0.0;
          dir = nd;
        }
        moved += std::abs(dq);
        moved_since_rev += std::abs(dq);
      }
      // Velocity by central differences (one-sided at the ends), at every row.
      const size_t i0 = i > 0 ? i - 1 : i, i1 = i + 1 < n ? i + 1 : i;
      vf[i] = i1 > i0 ? (cmd[i1][ax] - cmd[i0][ax]) / (t[i1] - t[i0]) : 0.0;
      if (i % stride) continue;
      q.push_back(cmd[i][ax]);
      d.push_back(dir);
      s.push_back(t[i] - t_rev);
      ts.push_back(moved_since_rev);
      tr.push_back(moved);
      // Acceleration by central differences over the actual steps.
      v.push_back(vf[i]);
      if (i > 0 && i + 1 < n) {
        const double h0 = t[i] - t[i - 1], h1 = t[i + 1] - t[i];
        a.push_back(2.0 * ((cmd[i + 1][ax] - cmd[i][ax]) / h1 - (cmd[i][ax] - cmd[i - 1][ax]) / h0) / (h0 + h1));
      } else {
        a.push_back(0.0);
      }
    }
  }
  return c;
}

std::vector<std::vector<double>> Effect::grid(const Context&, const GridHints&) const {
  return {std::vector<double>(p.size(), 0.0)};
}

namespace {

/// The one place each effect is written: Derived provides
///   static constexpr int N; names, linear flags, signature; template <class T> T eval(ctx, i, p) const.
template <class Derived, int N>
class EffectImpl : public Effect {
 public:
  EffectImpl() { p.assign(N, 0.0); }
  double value(const Context& ctx, size_t i, const double* pp) const override {
    return static_cast<const Derived*>(this)->template eval<double>(ctx, i, pp);
  }
  double value_grad(const Context& ctx, size_t i, const double* pp, double* g) const override {
    using J = ceres::Jet<double, N>;
    std::array<J, N> pj;
    for (int k = 0; k < N; ++k) pj[k] = J(pp[k], k);
    const J v = static_cast<const Derived*>(this)->template eval<J>(ctx, i, pj.data());
    for (int k = 0; k < N; ++k) g[k] = v.v[k];
    return v.a;
  }
  std::unique_ptr<Effect> clone() const override {
    return std::make_unique<Derived>(*static_cast<const Derived*>(this));
  }
};

std::string unit_of(bool rotary) { return rotary ? "deg" : "mm"; }

double get(const std::vector<std::pair<std::string, double>>& kv, const std::string& key, const std::string& effect,
           std::optional<double> def = std::nullopt) {
  for (const auto& [k, v] : kv)
    if (k == key) return v;
  if (def) return *def;
  throw InputError(fmt::format("effect {}: parameter '{}' is missing", effect, key));
}

// ---- axis effects -------------------------------------------------------------------------------------

class Backlash : public EffectImpl<Backlash, 2> {
 public:
  std::string name() const override { return "backlash"; }
  Scope scope() const override { return Scope::Axis; }
  std::vector<std::string> internal_names() const override { return {"width", "take_up"}; }
  std::vector<bool> linear() const override { return {true, false}; }
  std::string signature() const override {
    return fmt::format("step in the channels {} moves at every reversal of {}", target, target);
  }
  /// Lost motion of full width b: the axis trails the command by b/2 against its direction of motion. After a
  /// reversal it crosses the gap while the command travels `take_up` (the play of a screw whose axis waits until the
  /// nut meets the other flank: take_up = b; longer where the drive winds up first; 0: at once). An axis that starts
  /// the recording against its first move (`start_opposite`) crosses the gap on that move.
  template <class T>
  T eval(const Context& c, size_t i, const T* pp) const {
    const double s = std::isfinite(c.travel_since_rev[axis][i]) ? c.travel_since_rev[axis][i]
                     : start_opposite                           ? c.travel[axis][i]
                                                                : kInf;
    T f = T(-0.5);
    if (std::isfinite(s) && pp[1] > T(0.0)) {
      const T r = T(1.0) - s / pp[1];
      if (r > T(0.0)) f = f + r;
    }
    return c.dir[axis][i] * pp[0] * f;
  }
  std::vector<std::pair<std::string, double>> reported() const override {
    const std::string u = unit_of(rotary);
    return {{"magnitude_" + u, p[0]}, {"take_up_" + u, p[1]}, {"start_opposite", start_opposite ? 1.0 : 0.0}};
  }
  void set_reported(const std::vector<std::pair<std::string, double>>& kv) override {
    const std::string u = unit_of(rotary);
    p[0] = get(kv, "magnitude_" + u, name());
    p[1] = get(kv, "take_up_" + u, name(), std::abs(p[0]));
    if (!(p[1] >= 0)) throw InputError(fmt::format("effect backlash: take_up_{} must not be negative", u));
    const double so = get(kv, "start_opposite", name(), 0.0);
    if (so != 0.0 && so != 1.0) throw InputError("effect backlash: start_opposite must be 0 or 1");
    start_opposite = so == 1.0;
  }
  std::vector<std::vector<double>> grid(const Context&, const GridHints&) const override {
    std::vector<std::vector<double>> g;
    for (double u : {0.0, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1}) g.push_back({0, u});
    return g;
  }
  bool start_opposite = false;
};

class ServoLag : public EffectImpl<ServoLag, 1> {
 public:
  std::string name() const override { return "servo_lag"; }
  Scope scope() const override { return Scope::Axis; }
  std::vector<std::string> internal_names() const override { return {"lag_s"}; }
  std::vector<bool> linear() const override { return {true}; }
  std::string signature() const override {
    return fmt::format("following error proportional to the velocity of {}", target);
  }
  template <class T>
  T eval(const Context& c, size_t i, const T* pp) const {
    return -c.v[axis][i] * pp[0];
  }
  std::vector<std::pair<std::string, double>> reported() const override { return {{"lag_s", p[0]}}; }
  void set_reported(const std::vector<std::pair<std::string, double>>& kv) override { p[0] = get(kv, "lag_s", name()); }
};

/// The following error of a first-order servo loop of time constant tau over the commanded velocity v at every row:
/// de/dt = v - e/tau, at rest (or settled, e = tau v) at the first row. Exact for v linear between rows: over a step
/// h with a = exp(-h/tau), e1 = a e0 + tau (1 - a) v1 - (v1 - v0) (tau^2 (1 - a) / h - tau a). One pass over the
/// rows, whatever the analysis stride (a strided filter would miss the speed changes between its samples).
template <class T>
std::vector<T> first_order_following_error(const std::vector<double>& t, const std::vector<double>& v, const T& tau) {
  using std::exp, std::expm1;
  std::vector<T> e(t.size());
  if (t.empty()) return e;
  e[0] = tau * v[0];
  // The coefficients depend on the step only. A regular clock printed to a few decimals alternates between two or three
  // steps (17 and 18 us at 57 kHz with 6 decimals): the last few steps' coefficients are kept, so that the exponentials
  // (a Jet's too) are computed once per distinct step, not at every row.
  constexpr std::size_t kSlots = 4;
  std::array<double, kSlots> hs;
  hs.fill(-1.0);
  std::array<std::array<T, 3>, kSlots> coef{};
  std::size_t next_slot = 0;
  T a{}, c_v{}, c_dv{};
  for (size_t k = 1; k < t.size(); ++k) {
    const double h = t[k] - t[k - 1];
    std::size_t at = 0;
    // (Steps of one printed value differ in their last bits after the subtraction: equal within 1e-9 is one step.)
    while (at < kSlots && std::abs(hs[at] - h) > 1e-9 * h) ++at;
    if (at == kSlots) {
      at = next_slot;
      next_slot = (next_slot + 1) % kSlots;
      const T x = -h / tau;
      const T ax = exp(x);
      const T one_minus_a = -expm1(x);  // 1 - a without cancellation for h << tau
      coef[at] = {ax, tau * one_minus_a, tau * tau * one_minus_a / h - tau * ax};
      hs[at] = h;
    }
    a = coef[at][0], c_v = coef[at][1], c_dv = coef[at][2];
    e[k] = a * e[k - 1] + c_v * v[k] - (v[k] - v[k - 1]) * c_dv;
  }
  return e;
}

/// The series a ServoLag1st last computed, per scalar type (double to inject and evaluate, Jet to fit): the fit calls
/// the effect once per sample with the same parameters, so the filter runs once per parameter value (O(n) per
/// evaluation, not O(n^2)). Shared by the threads of one fit (a mutex); a copy of the effect starts empty.
template <class T>
struct SeriesSlot {
  std::uint64_t ctx = 0;
  T tau{};
  std::shared_ptr<const std::vector<T>> e;
};
inline bool same(double a, double b) { return a == b; }
template <int N>
bool same(const ceres::Jet<double, N>& a, const ceres::Jet<double, N>& b) {
  return a.a == b.a && a.v == b.v;
}
struct LagCache {
  std::mutex m;
  SeriesSlot<double> d;
  SeriesSlot<ceres::Jet<double, 2>> j;
  SeriesSlot<double>& slot(double*) { return d; }
  SeriesSlot<ceres::Jet<double, 2>>& slot(ceres::Jet<double, 2>*) { return j; }
};
struct LagCacheHolder {
  std::unique_ptr<LagCache> c = std::make_unique<LagCache>();
  LagCacheHolder() = default;
  LagCacheHolder(const LagCacheHolder&) : c(std::make_unique<LagCache>()) {}
  LagCacheHolder& operator=(const LagCacheHolder&) {
    c = std::make_unique<LagCache>();
    return *this;
  }
  LagCacheHolder(LagCacheHolder&&) noexcept = default;
  LagCacheHolder& operator=(LagCacheHolder&&) noexcept = default;
  ~LagCacheHolder() = default;
};

/// A first-order servo: the axis follows its command as a first-order system of time constant tau_s, trailing by the
/// following error e (de/dt = v - e/tau): e settles at tau v at a constant speed (servo_lag's steady state) and takes
/// about tau to build up after a start and to die away after a stop. lag_s scales it: a plain loop has lag_s =
/// tau_s; velocity feed-forward k lowers the steady error to (1 - k) tau v. Deviation -(lag_s / tau_s) e.
class ServoLag1st : public EffectImpl<ServoLag1st, 2> {
 public:
  std::string name() const override { return "servo_lag_1st"; }
  Scope scope() const override { return Scope::Axis; }
  std::vector<std::string> internal_names() const override { return {"lag_s", "tau_s"}; }
  std::vector<bool> linear() const override { return {true, false}; }
  std::string signature() const override {
    return fmt::format(
        "following error of {} that builds up over a time constant after each change of speed (a first-order loop)",
        target);
  }
  template <class T>
  T eval(const Context& c, size_t i, const T* pp) const {
    const auto e = series<T>(c, pp[1]);
    return -(pp[0] / pp[1]) * (*e)[c.index[i]];
  }
  std::vector<std::pair<std::string, double>> reported() const override { return {{"tau_s", p[1]}, {"lag_s", p[0]}}; }
  void set_reported(const std::vector<std::pair<std::string, double>>& kv) override {
    p[1] = get(kv, "tau_s", name());
    if (!(p[1] > 0)) throw InputError("effect servo_lag_1st: tau_s must be positive");
    p[0] = get(kv, "lag_s", name(), p[1]);
  }
  std::vector<std::vector<double>> grid(const Context&, const GridHints&) const override {
    std::vector<std::vector<double>> g;
    for (double tau : {0.001, 0.002, 0.004, 0.008, 0.015, 0.03, 0.06, 0.12, 0.25}) g.push_back({0, tau});
    return g;
  }

 private:
  template <class T>
  std::shared_ptr<const std::vector<T>> series(const Context& c, const T& tau) const {
    CSCAM_CHECK(c.t_full.size() == c.v_full[axis].size() && !c.index.empty() && c.index.back() < c.t_full.size(),
                "servo_lag_1st: the context has no full-rate velocity (made without make_context)");
    LagCache& lc = *cache_.c;
    std::lock_guard<std::mutex> lk(lc.m);
    auto& s = lc.slot(static_cast<T*>(nullptr));
    if (!s.e || s.ctx != c.id || c.id == 0 || !same(s.tau, tau)) {
      s.e = std::make_shared<const std::vector<T>>(first_order_following_error(c.t_full, c.v_full[axis], tau));
      s.ctx = c.id;
      s.tau = tau;
    }
    return s.e;
  }
  LagCacheHolder cache_;
};

class Scale : public EffectImpl<Scale, 1> {
 public:
  std::string name() const override { return "scale"; }
  Scope scope() const override { return Scope::Axis; }
  std::vector<std::string> internal_names() const override { return {"ppm"}; }
  std::vector<bool> linear() const override { return {true}; }
  std::string signature() const override { return fmt::format("error proportional to the position of {}", target); }
  template <class T>
  T eval(const Context& c, size_t i, const T* pp) const {
    return c.q[axis][i] * 1e-6 * pp[0];
  }
  std::vector<std::pair<std::string, double>> reported() const override { return {{"ppm", p[0]}}; }
  void set_reported(const std::vector<std::pair<std::string, double>>& kv) override { p[0] = get(kv, "ppm", name()); }
};

class Squareness : public EffectImpl<Squareness, 1> {
 public:
  std::string name() const override { return "squareness"; }
  Scope scope() const override { return Scope::Axis; }
  std::vector<std::string> internal_names() const override { return {"angle_urad"}; }
  std::vector<bool> linear() const override { return {true}; }
  std::string signature() const override {
    return fmt::format("error of the first axis proportional to the position of the second ({})", target);
  }
  template <class T>
  T eval(const Context& c, size_t i, const T* pp) const {
    return c.q[axis2][i] * 1e-6 * pp[0];
  }
  std::vector<std::pair<std::string, double>> reported() const override { return {{"angle_urad", p[0]}}; }
  void set_reported(const std::vector<std::pair<std::string, double>>& kv) override {
    p[0] = get(kv, "angle_urad", name());
  }
};

/// Straightness: the first axis bows with the position of the second (a sagging or curved guideway; the same axis
/// twice is a lead error that grows with the square of the distance from a point). A parabola k ((q - apex) / 1 m)^2
/// with its apex free: the constant it adds is a channel offset, and the slope is part of the bow (a tilted line alone
/// is squareness or scale).
class Straightness : public EffectImpl<Straightness, 2> {
 public:
  std::string name() const override { return "straightness"; }
  Scope scope() const override { return Scope::Axis; }
  std::vector<std::string> internal_names() const override { return {"mm_per_m2", "apex"}; }
  std::vector<bool> linear() const override { return {true, false}; }
  std::string signature() const override {
    return fmt::format("error of the first axis growing with the square of the position of the second ({})", target);
  }
  template <class T>
  T eval(const Context& c, size_t i, const T* pp) const {
    const T u = (c.q[axis2][i] - pp[1]) * 1e-3;  // m from the apex
    return pp[0] * u * u;
  }
  std::vector<std::pair<std::string, double>> reported() const override {
    return {{"mm_per_m2", p[0]}, {"apex_mm", p[1]}};
  }
  void set_reported(const std::vector<std::pair<std::string, double>>& kv) override {
    p[0] = get(kv, "mm_per_m2", name());
    p[1] = get(kv, "apex_mm", name(), 0.0);
  }
  /// The apex at five places along the second axis's travel (and a little beyond its ends).
  std::vector<std::vector<double>> grid(const Context& c, const GridHints&) const override {
    const auto [lo, hi] = c.range(axis2);
    if (!(hi > lo)) return {{0, lo}};
    std::vector<std::vector<double>> g;
    for (double f : {-0.25, 0.0, 0.25, 0.5, 0.75, 1.0, 1.25}) g.push_back({0, lo + f * (hi - lo)});
    return g;
  }
};

class Cyclic : public EffectImpl<Cyclic, 3> {
 public:
  std::string name() const override { return "cyclic"; }
  Scope scope() const override { return Scope::Axis; }
  std::vector<std::string> internal_names() const override { return {"period", "a_sin", "a_cos"}; }
  std::vector<bool> linear() const override { return {false, true, true}; }
  std::string signature() const override {
    return fmt::format("error periodic in the position of {} (screw pitch, encoder interpolation)", target);
  }
  template <class T>
  T eval(const Context& c, size_t i, const T* pp) const {
    using std::cos, std::sin;
    const T ph = 2.0 * kPi * c.q[axis][i] / pp[0];
    return pp[1] * sin(ph) + pp[2] * cos(ph);
  }
  std::vector<std::pair<std::string, double>> reported() const override {
    const std::string u = unit_of(rotary);
    return {{"period_" + u, p[0]},
            {"amplitude_" + u, std::hypot(p[1], p[2])},
            {"phase_deg", std::atan2(p[2], p[1]) * 180 / kPi}};
  }
  void set_reported(const std::vector<std::pair<std::string, double>>& kv) override {
    const std::string u = unit_of(rotary);
    p[0] = get(kv, "period_" + u, name());
    if (!(p[0] > 0)) throw InputError("effect cyclic: period must be positive");
    const double amp = get(kv, "amplitude_" + u, name()), ph = get(kv, "phase_deg", name(), 0.0) * kPi / 180;
    p[1] = amp * std::cos(ph);
    p[2] = amp * std::sin(ph);
  }
  std::vector<std::vector<double>> grid(const Context& c, const GridHints&) const override {
    std::vector<std::vector<double>> g;
    const double span = c.range(axis).travel();
    // A rotary's errors once, twice and three times per revolution (eccentricity, an oval bearing, a worm gear's
    // tooth count) need only one period seen: a whole turn shows them apart from an offset, and most of one (0.9)
    // still names them (the finding then says the period is not resolved) where the alternative is a wrong effect.
    const std::vector<double> periods =
        rotary ? std::vector<double>{1, 2, 3, 4, 5, 6, 8, 10, 12, 15, 20, 30, 45, 60, 90, 120, 180, 360}
               : std::vector<double>{0.5, 1, 2, 2.5, 3, 4, 5, 6, 8, 10, 12, 16, 20, 25, 32, 40};
    for (double per : periods)
      if (span >= (rotary && per >= 120 ? 0.9 : 1.5) * per - 1e-9) g.push_back({per, 0, 0});  // 1.5 periods seen
    return g;
  }
};

class FrictionSpike : public EffectImpl<FrictionSpike, 2> {
 public:
  std::string name() const override { return "friction_spike"; }
  Scope scope() const override { return Scope::Axis; }
  std::vector<std::string> internal_names() const override { return {"peak", "decay_s"}; }
  std::vector<bool> linear() const override { return {true, false}; }
  std::string signature() const override {
    return fmt::format("spike decaying after every reversal of {} (stick-slip, quadrant glitch)", target);
  }
  /// The axis lags by `peak` just after a reversal; the lag decays with time constant `decay_s`.
  template <class T>
  T eval(const Context& c, size_t i, const T* pp) const {
    using std::exp;
    const double s = c.since_rev[axis][i];
    if (!std::isfinite(s)) return T(0.0);
    return -c.dir[axis][i] * pp[0] * exp(-s / pp[1]);
  }
  std::vector<std::pair<std::string, double>> reported() const override {
    return {{"peak_" + unit_of(rotary), p[0]}, {"decay_s", p[1]}};
  }
  void set_reported(const std::vector<std::pair<std::string, double>>& kv) override {
    p[0] = get(kv, "peak_" + unit_of(rotary), name());
    p[1] = get(kv, "decay_s", name());
    if (!(p[1] > 0)) throw InputError("effect friction_spike: decay_s must be positive");
  }
  std::vector<std::vector<double>> grid(const Context&, const GridHints&) const override {
    return {{0, 0.003}, {0, 0.01}, {0, 0.02}, {0, 0.05}, {0, 0.1}, {0, 0.2}, {0, 0.5}};
  }
};

class Compliance : public EffectImpl<Compliance, 1> {
 public:
  std::string name() const override { return "compliance"; }
  Scope scope() const override { return Scope::Axis; }
  std::vector<std::string> internal_names() const override { return {"k"}; }
  std::vector<bool> linear() const override { return {true}; }
  std::string signature() const override {
    return fmt::format("deflection proportional to the commanded acceleration of {} (inertial load)", target);
  }
  /// Deflection against the acceleration: -k a, a in m/s^2 (linear) or deg/s^2 (rotary).
  template <class T>
  T eval(const Context& c, size_t i, const T* pp) const {
    return -(rotary ? c.a[axis][i] : c.a[axis][i] * 1e-3) * pp[0];
  }
  std::vector<std::pair<std::string, double>> reported() const override {
    return {{rotary ? "deg_per_deg_s2" : "mm_per_m_s2", p[0]}};
  }
  void set_reported(const std::vector<std::pair<std::string, double>>& kv) override {
    p[0] = get(kv, rotary ? "deg_per_deg_s2" : "mm_per_m_s2", name());
  }
};

/// Cross compliance: the first axis deflects against the commanded acceleration of the second (a column that leans
/// when the saddle under it accelerates, a ram that dips as the table starts). Both linear slides of a serial
/// machine; the deflection is in the structure, so the first axis's encoder does not see it.
class CrossCompliance : public EffectImpl<CrossCompliance, 1> {
 public:
  std::string name() const override { return "cross_compliance"; }
  Scope scope() const override { return Scope::Axis; }
  std::vector<std::string> internal_names() const override { return {"k"}; }
  std::vector<bool> linear() const override { return {true}; }
  std::string signature() const override {
    return fmt::format("deflection of the first axis proportional to the commanded acceleration of the second ({})",
                       target);
  }
  template <class T>
  T eval(const Context& c, size_t i, const T* pp) const {
    return -(c.a[axis2][i] * 1e-3) * pp[0];  // a in m/s^2
  }
  std::vector<std::pair<std::string, double>> reported() const override { return {{"mm_per_m_s2", p[0]}}; }
  void set_reported(const std::vector<std::pair<std::string, double>>& kv) override {
    p[0] = get(kv, "mm_per_m_s2", name());
  }
};

/// Thermal scale: a lead screw that warms during the run and grows; the scale error rises from 0 at the start to
/// `ppm` at the end as thermal_drift's profile does (time constant tau): q ppm 1e-6 (1 - e^(-t/tau)) / (1 -
/// e^(-T/tau)). In the screw, so the axis's encoder on the motor does not see it.
class ThermalScale : public EffectImpl<ThermalScale, 2> {
 public:
  std::string name() const override { return "thermal_scale"; }
  Scope scope() const override { return Scope::Axis; }
  std::vector<std::string> internal_names() const override { return {"ppm", "tau_s"}; }
  std::vector<bool> linear() const override { return {true, false}; }
  std::string signature() const override {
    return fmt::format("error proportional to the position of {} growing with elapsed time (a warming screw)", target);
  }
  template <class T>
  T eval(const Context& c, size_t i, const T* pp) const {
    using std::exp;
    const double T_run = std::max(c.duration, 1e-9);
    return c.q[axis][i] * 1e-6 * pp[0] * (1.0 - exp(-(c.t[i] - c.t0) / pp[1])) / (1.0 - exp(-T_run / pp[1]));
  }
  std::vector<std::pair<std::string, double>> reported() const override {
    return {{"ppm", p[0]}, {"time_constant_s", p[1]}};
  }
  void set_reported(const std::vector<std::pair<std::string, double>>& kv) override {
    p[0] = get(kv, "ppm", name());
    p[1] = get(kv, "time_constant_s", name());
    if (!(p[1] > 0)) throw InputError("effect thermal_scale: time_constant_s must be positive");
  }
  std::vector<std::vector<double>> grid(const Context& c, const GridHints&) const override {
    std::vector<std::vector<double>> g;
    for (double f : {0.1, 0.2, 0.35, 0.5, 1.0, 2.0, 5.0}) g.push_back({0, f * std::max(c.duration, 1e-3)});
    return g;
  }
};

/// A lead screw (or the slide's structure) that expands with a recorded temperature: the error grows with the
/// position and with the rise of sensor `note` since the start, q ppm_per_degC 1e-6 (T(t) - T(t0)). thermal_scale's
/// warming in time, where the temperature was recorded: it follows a run that warms and cools.
class ThermalExpansion : public EffectImpl<ThermalExpansion, 1> {
 public:
  std::string name() const override { return "thermal_expansion"; }
  Scope scope() const override { return Scope::Axis; }
  std::vector<std::string> internal_names() const override { return {"ppm_per_degC"}; }
  std::vector<bool> linear() const override { return {true}; }
  std::string signature() const override {
    return fmt::format("error proportional to the position of {} and to the rise of temp.{}", target, note);
  }
  template <class T>
  T eval(const Context& c, size_t i, const T* pp) const {
    const std::vector<double>* rise = c.temperature(note);
    return rise && i < rise->size() ? c.q[axis][i] * 1e-6 * pp[0] * (*rise)[i] : T(0.0);
  }
  std::vector<std::pair<std::string, double>> reported() const override { return {{"ppm_per_degC", p[0]}}; }
  void set_reported(const std::vector<std::pair<std::string, double>>& kv) override {
    p[0] = get(kv, "ppm_per_degC", name());
  }
  std::vector<std::vector<double>> grid(const Context&, const GridHints&) const override { return {{0.0}}; }
  std::string source() const override { return note.empty() ? std::string() : "temp." + note; }
  bool follows_temperature() const override { return true; }
};

// ---- channel effects ----------------------------------------------------------------------------------

class ThermalDrift : public EffectImpl<ThermalDrift, 2> {
 public:
  std::string name() const override { return "thermal_drift"; }
  Scope scope() const override { return Scope::Channel; }
  std::vector<std::string> internal_names() const override { return {"drift", "tau_s"}; }
  std::vector<bool> linear() const override { return {true, false}; }
  std::string signature() const override { return fmt::format("slow monotonic drift of {} with elapsed time", target); }
  /// drift (1 - exp(-(t - t0)/tau)) / (1 - exp(-T/tau)): zero at the start, `drift` at the end of the run.
  template <class T>
  T eval(const Context& c, size_t i, const T* pp) const {
    using std::exp;
    const double T_run = std::max(c.duration, 1e-9);
    return pp[0] * (1.0 - exp(-(c.t[i] - c.t0) / pp[1])) / (1.0 - exp(-T_run / pp[1]));
  }
  std::vector<std::pair<std::string, double>> reported() const override {
    return {{"drift_mm", p[0]}, {"time_constant_s", p[1]}};
  }
  void set_reported(const std::vector<std::pair<std::string, double>>& kv) override {
    p[0] = get(kv, "drift_mm", name());
    p[1] = get(kv, "time_constant_s", name());
    if (!(p[1] > 0)) throw InputError("effect thermal_drift: time_constant_s must be positive");
  }
  std::vector<std::vector<double>> grid(const Context& c, const GridHints&) const override {
    std::vector<std::vector<double>> g;
    for (double f : {0.05, 0.1, 0.2, 0.35, 0.5, 1.0, 2.0, 5.0}) g.push_back({0, f * std::max(c.duration, 1e-3)});
    return g;
  }
};

/// A permanent step: the channel jumps once, by step_mm at t_s, and stays (a knocked tracker, a re-seated probe, a
/// slip). Not a drift: nothing before t_s, all of it at once. t_s enters only through the jump, so its derivative is
/// zero: the fit holds it where the grid put it (the largest jump of the residual).
class Step : public EffectImpl<Step, 2> {
 public:
  std::string name() const override { return "step"; }
  Scope scope() const override { return Scope::Channel; }
  std::vector<std::string> internal_names() const override { return {"step", "t_s"}; }
  std::vector<bool> linear() const override { return {true, false}; }
  std::string signature() const override {
    return fmt::format("{} jumps once and stays (a knocked tracker, a re-seated probe)", target);
  }
  template <class T>
  T eval(const Context& c, size_t i, const T* pp) const {
    return c.t[i] >= pp[1] ? pp[0] : T(0.0);
  }
  std::vector<std::pair<std::string, double>> reported() const override { return {{"step_mm", p[0]}, {"t_s", p[1]}}; }
  void set_reported(const std::vector<std::pair<std::string, double>>& kv) override {
    p[0] = get(kv, "step_mm", name());
    p[1] = get(kv, "t_s", name());
    if (!std::isfinite(p[1])) throw InputError("effect step: t_s must be a finite time");
  }
  /// The times of the residual's largest jumps (hints), or nine times across the run.
  std::vector<std::vector<double>> grid(const Context& c, const GridHints& h) const override {
    std::vector<std::vector<double>> g;
    for (double ts : h.step_times_s) g.push_back({0, ts});
    if (g.empty())
      for (int k = 1; k <= 9; ++k) g.push_back({0, c.t0 + 0.1 * k * c.duration});
    return g;
  }
};

/// Thermal growth that follows a recorded temperature: k (mm per degC) times the rise of sensor `note` since the start
/// (a spindle that grows as it warms and shrinks as it cools, a column in the sun). Unlike thermal_drift it need not
/// be monotonic in time: it goes where the temperature goes. Needs the recording's temp.<sensor> column.
class ThermalGrowth : public EffectImpl<ThermalGrowth, 1> {
 public:
  std::string name() const override { return "thermal_growth"; }
  Scope scope() const override { return Scope::Channel; }
  std::vector<std::string> internal_names() const override { return {"mm_per_degC"}; }
  std::vector<bool> linear() const override { return {true}; }
  std::string signature() const override {
    return fmt::format("{} follows the temperature temp.{} (growth per degree)", target, note);
  }
  template <class T>
  T eval(const Context& c, size_t i, const T* pp) const {
    const std::vector<double>* rise = c.temperature(note);
    return rise && i < rise->size() ? pp[0] * (*rise)[i] : T(0.0);
  }
  std::vector<std::pair<std::string, double>> reported() const override { return {{"mm_per_degC", p[0]}}; }
  void set_reported(const std::vector<std::pair<std::string, double>>& kv) override {
    p[0] = get(kv, "mm_per_degC", name());
  }
  /// Linear in its one parameter: a single start.
  std::vector<std::vector<double>> grid(const Context&, const GridHints&) const override { return {{0.0}}; }
  std::string source() const override { return note.empty() ? std::string() : "temp." + note; }
  bool follows_temperature() const override { return true; }
};

class Vibration : public EffectImpl<Vibration, 3> {
 public:
  std::string name() const override { return "vibration"; }
  Scope scope() const override { return Scope::Channel; }
  std::vector<std::string> internal_names() const override { return {"frequency_hz", "a_sin", "a_cos"}; }
  std::vector<bool> linear() const override { return {false, true, true}; }
  std::string signature() const override {
    return fmt::format("sinusoid in {} at a fixed frequency (a spectral peak)", target);
  }
  template <class T>
  T eval(const Context& c, size_t i, const T* pp) const {
    using std::cos, std::sin;
    const T ph = 2.0 * kPi * pp[0] * c.t[i];
    return pp[1] * sin(ph) + pp[2] * cos(ph);
  }
  std::vector<std::pair<std::string, double>> reported() const override {
    return {{"frequency_hz", p[0]},
            {"amplitude_mm", std::hypot(p[1], p[2])},
            {"phase_deg", std::atan2(p[2], p[1]) * 180 / kPi}};
  }
  void set_reported(const std::vector<std::pair<std::string, double>>& kv) override {
    p[0] = get(kv, "frequency_hz", name());
    if (!(p[0] > 0)) throw InputError("effect vibration: frequency_hz must be positive");
    const double amp = get(kv, "amplitude_mm", name()), ph = get(kv, "phase_deg", name(), 0.0) * kPi / 180;
    p[1] = amp * std::cos(ph);
    p[2] = amp * std::sin(ph);
  }
  std::vector<std::vector<double>> grid(const Context&, const GridHints& h) const override {
    std::vector<std::vector<double>> g;
    for (double f : h.frequencies_hz) g.push_back({f, 0, 0});
    return g;
  }
  std::string source() const override { return note; }
};

class Geometric : public EffectImpl<Geometric, 1> {
 public:
  std::string name() const override { return "geometric"; }
  Scope scope() const override { return Scope::Geometric; }
  std::vector<std::string> internal_names() const override { return {"deviation"}; }
  std::vector<bool> linear() const override { return {true}; }
  std::string signature() const override {
    return fmt::format("position-dependent error of the tip that a change of machine parameter {} reproduces", target);
  }
  template <class T>
  T eval(const Context&, size_t, const T* pp) const {
    return pp[0];
  }
  std::vector<std::pair<std::string, double>> reported() const override { return {{target + "_" + unit, p[0]}}; }
  void set_reported(const std::vector<std::pair<std::string, double>>& kv) override {
    p[0] = get(kv, target + "_" + unit, name());
  }
};

using Factory = std::function<std::unique_ptr<Effect>()>;
const std::vector<std::pair<std::string, Factory>>& library() {
  static const std::vector<std::pair<std::string, Factory>> lib{
      {"backlash", [] { return std::make_unique<Backlash>(); }},
      {"servo_lag", [] { return std::make_unique<ServoLag>(); }},
      {"servo_lag_1st", [] { return std::make_unique<ServoLag1st>(); }},
      {"thermal_drift", [] { return std::make_unique<ThermalDrift>(); }},
      {"thermal_growth", [] { return std::make_unique<ThermalGrowth>(); }},
      {"step", [] { return std::make_unique<Step>(); }},
      {"vibration", [] { return std::make_unique<Vibration>(); }},
      {"scale", [] { return std::make_unique<Scale>(); }},
      {"squareness", [] { return std::make_unique<Squareness>(); }},
      {"straightness", [] { return std::make_unique<Straightness>(); }},
      {"cyclic", [] { return std::make_unique<Cyclic>(); }},
      {"friction_spike", [] { return std::make_unique<FrictionSpike>(); }},
      {"compliance", [] { return std::make_unique<Compliance>(); }},
      {"cross_compliance", [] { return std::make_unique<CrossCompliance>(); }},
      {"thermal_scale", [] { return std::make_unique<ThermalScale>(); }},
      {"thermal_expansion", [] { return std::make_unique<ThermalExpansion>(); }},
  };
  return lib;
}

bool valid_channel(const std::string& ch, const machine::Machine& m) {
  const auto dot = ch.find('.');
  if (dot == std::string::npos) return false;
  const std::string g = ch.substr(0, dot), r = ch.substr(dot + 1);
  // tool.*: the tool point itself moves (along x, y or z of the machine frame W): tip sees it, and so does ptip,
  // turned into the part frame (a spindle that grows with heat).
  if (g == "tip" || g == "ptip" || g == "dir" || g == "acc" || g == "tool") return r == "x" || r == "y" || r == "z";
  if (g == "enc") return m.axis_index(r) >= 0;
  return false;
}

}  // namespace

std::unique_ptr<Effect> make_geometric(const std::string& name, const std::string& unit, double nominal, double dev) {
  auto e = std::make_unique<Geometric>();
  e->target = name;
  e->unit = unit;
  e->nominal = nominal;
  e->p[0] = dev;
  e->enc_visible = false;
  return e;
}

std::vector<std::string> effect_names() {
  std::vector<std::string> n;
  for (const auto& [k, f] : library()) n.push_back(k);
  n.emplace_back("geometric");
  return n;
}

std::unique_ptr<Effect> make_effect(const std::string& name, const std::string& target, const machine::Machine& m) {
  for (const auto& [k, f] : library()) {
    if (k != name) continue;
    auto e = f();
    e->target = target;
    if (e->scope() == Scope::Channel) {
      if (!valid_channel(target, m))
        throw InputError(
            fmt::format("effect {}: '{}' is not a channel of machine {} (expected tip.x|y|z, ptip.*, "
                        "dir.*, acc.*, enc.<axis>, or tool.x|y|z for the tool point in tip and ptip)",
                        name, target, m.name));
      e->channel = target;
      return e;
    }
    if (name == "squareness" || name == "straightness" || name == "cross_compliance") {
      const auto comma = target.find(',');
      if (comma == std::string::npos)
        throw InputError(fmt::format("effect {}: target must be an axis pair like {}, got '{}'", name,
                                     name == "squareness" ? "x,y" : "z,x", target));
      e->axis = m.axis_index(target.substr(0, comma));
      e->axis2 = m.axis_index(target.substr(comma + 1));
      // Straightness of an axis along itself is a lead error that bows with the position; an axis's compliance to
      // its own acceleration is `compliance`.
      if (e->axis < 0 || e->axis2 < 0 || (e->axis == e->axis2 && name != "straightness"))
        throw InputError(fmt::format("effect {}: '{}' is not a pair of axes of machine {}", name, target, m.name));
      // A property of Cartesian slides: between a parallel machine's legs, or with a rotary, it means nothing.
      if (m.kind != machine::ModelKind::Serial)
        throw InputError(
            fmt::format("effect {}: machine {} is a parallel-link machine; {} is a property of linear slides, which "
                        "its legs are not",
                        name, m.name, name));
      if (m.axes[static_cast<size_t>(e->axis)].rotary() || m.axes[static_cast<size_t>(e->axis2)].rotary())
        throw InputError(
            fmt::format("effect {}: '{}' of machine {}: both axes must be linear slides", name, target, m.name));
      e->enc_visible = false;
    } else {
      e->axis = m.axis_index(target);
      if (e->axis < 0) throw InputError(fmt::format("effect {}: machine {} has no axis '{}'", name, m.name, target));
      // Errors of the encoder's own scale or of the structure are invisible to the axis's encoder.
      e->enc_visible = !(name == "scale" || name == "cyclic" || name == "thermal_scale" || name == "thermal_expansion");
      if ((name == "thermal_scale" || name == "thermal_expansion") && m.axes[static_cast<size_t>(e->axis)].rotary())
        throw InputError(fmt::format("effect {}: '{}' of machine {} is a rotary; {} is the growth of a linear slide",
                                     name, target, m.name, name));
    }
    e->rotary = m.axes[static_cast<size_t>(e->axis)].rotary();
    return e;
  }
  if (name == "geometric")
    throw InputError("effect geometric: give it as geometric:PARAM=VALUE (absolute value in the machine file's units)");
  std::string list;
  for (const auto& n : effect_names()) list += (list.empty() ? "" : ", ") + n;
  throw InputError(fmt::format("unknown effect '{}' (known: {})", name, list));
}

namespace {
/// geometric:NAME=VALUE[,NAME=VALUE...] (absolute values, file units) -> one effect per parameter.
std::unique_ptr<Effect> geometric_from(const std::string& name, double value, bool absolute,
                                       const machine::Machine& m) {
  const auto model = calib::load_model(m.file);
  const size_t i = model->index(name);
  const auto& pi = model->params()[i];
  return make_geometric(pi.name, pi.unit, pi.nominal, absolute ? value - pi.nominal : value);
}
}  // namespace

std::vector<std::pair<std::string, double>> parse_geometric_values(const std::string& spec) {
  std::vector<std::pair<std::string, double>> out;
  if (spec.rfind("geometric:", 0) != 0)
    throw InputError(fmt::format("--inject '{}': expected geometric:PARAM=VALUE (e.g. geometric:A1x=-150.06)", spec));
  const std::string rest = spec.substr(10);
  size_t a = 0;
  while (a < rest.size()) {
    size_t b = rest.find_first_of(",:", a);
    if (b == std::string::npos) b = rest.size();
    const std::string item = rest.substr(a, b - a);
    const auto eq = item.find('=');
    if (eq == std::string::npos)
      throw InputError(fmt::format("--inject '{}': expected geometric:PARAM=VALUE (e.g. geometric:A1x=-150.06)", spec));
    double v = 0;
    try {
      size_t used = 0;
      v = std::stod(item.substr(eq + 1), &used);
      if (used != item.size() - eq - 1 || !std::isfinite(v)) throw std::invalid_argument(item);
    } catch (const std::exception&) {
      throw InputError(fmt::format("--inject '{}': expected a finite number after '{}='", spec, item.substr(0, eq)));
    }
    out.emplace_back(item.substr(0, eq), v);
    a = b + 1;
  }
  if (out.empty()) throw InputError(fmt::format("--inject '{}': no PARAM=VALUE after 'geometric:'", spec));
  return out;
}

std::vector<std::unique_ptr<Effect>> parse_effects(const std::string& spec, const machine::Machine& m) {
  std::vector<std::unique_ptr<Effect>> out;
  if (spec.rfind("geometric:", 0) == 0) {
    for (const auto& [name, value] : parse_geometric_values(spec)) out.push_back(geometric_from(name, value, true, m));
    return out;
  }
  out.push_back(parse_effect(spec, m));
  return out;
}

std::unique_ptr<Effect> parse_effect(const std::string& spec, const machine::Machine& m) {
  const auto c1 = spec.find(':');
  if (c1 == std::string::npos)
    throw InputError(fmt::format("--inject '{}': expected EFFECT:TARGET:PARAMS, e.g. backlash:q2:0.012", spec));
  const std::string name = spec.substr(0, c1);
  const auto c2 = spec.find(':', c1 + 1);
  const std::string target = spec.substr(c1 + 1, c2 == std::string::npos ? std::string::npos : c2 - c1 - 1);
  const std::string rest = c2 == std::string::npos ? "" : spec.substr(c2 + 1);
  auto e = make_effect(name, target, m);
  const auto keys = e->reported();
  std::vector<std::pair<std::string, double>> kv;
  auto number = [&](const std::string& s) {
    try {
      size_t used = 0;
      const double v = std::stod(s, &used);
      if (used != s.size() || !std::isfinite(v)) throw std::invalid_argument(s);
      return v;
    } catch (const std::exception&) {
      throw InputError(fmt::format("--inject '{}': expected a finite number, got '{}'", spec, s));
    }
  };
  if (rest.find('=') != std::string::npos) {
    size_t a = 0;
    while (a <= rest.size()) {
      size_t b = rest.find_first_of(",:", a);
      if (b == std::string::npos) b = rest.size();
      const std::string item = rest.substr(a, b - a);
      const auto eq = item.find('=');
      if (eq == std::string::npos)
        throw InputError(
            fmt::format("--inject '{}': expected key=value, got '{}' (the parameters are all given in "
                        "order, {}:{}:VALUE:..., or all as key=value)",
                        spec, item, name, target));
      const std::string key = item.substr(0, eq);
      if (key == "sensor" && e->follows_temperature()) {  // the one text parameter: the temp.<sensor> it follows
        e->note = item.substr(eq + 1);
        a = b + 1;
        continue;
      }
      bool known = false;
      for (const auto& [k, v] : keys) known |= k == key;
      if (!known) {
        std::string list;
        for (const auto& [k, v] : keys) list += (list.empty() ? "" : ", ") + k;
        throw InputError(fmt::format("--inject '{}': {} has no parameter '{}' (expected {})", spec, name, key, list));
      }
      kv.emplace_back(key, number(item.substr(eq + 1)));
      a = b + 1;
    }
  } else {
    size_t a = 0, k = 0;
    while (!rest.empty() && a <= rest.size()) {
      size_t b = rest.find(':', a);
      if (b == std::string::npos) b = rest.size();
      if (k >= keys.size())
        throw InputError(fmt::format("--inject '{}': {} takes at most {} values", spec, name, keys.size()));
      kv.emplace_back(keys[k++].first, number(rest.substr(a, b - a)));
      a = b + 1;
    }
  }
  e->set_reported(kv);
  return e;
}

std::vector<std::unique_ptr<Effect>> load_machine_effects(const std::string& machine_file, const machine::Machine& m) {
  std::vector<std::unique_ptr<Effect>> out;
  YAML::Node root;
  try {
    root = YAML::LoadFile(machine_file);
  } catch (const YAML::Exception& ex) {
    throw InputError(SourceLoc{machine_file, ex.mark.line + 1}, ex.what());
  }
  const YAML::Node fx = root["effects"];
  if (!fx) return out;
  if (!fx.IsSequence())
    throw InputError(SourceLoc{machine_file, fx.Mark().line + 1},
                     "effects: expected a list of {effect, target, parameters}");
  for (const auto& item : fx) {
    const SourceLoc where{machine_file, item.Mark().line + 1};
    if (!item.IsMap() || !item["effect"] || !item["target"])
      throw InputError(where, "effects: every entry needs 'effect' and 'target'");
    std::unique_ptr<Effect> e;
    try {
      if (item["effect"].as<std::string>() == "geometric") {
        const std::string name = item["target"].as<std::string>();
        double dev = 0;
        if (item["parameters"])
          for (const auto& p : item["parameters"]) dev = p.second.as<double>();
        out.push_back(geometric_from(name, dev, false, m));
        continue;
      }
      e = make_effect(item["effect"].as<std::string>(), item["target"].as<std::string>(), m);
      std::vector<std::pair<std::string, double>> kv;
      if (item["parameters"])
        for (const auto& p : item["parameters"]) kv.emplace_back(p.first.as<std::string>(), p.second.as<double>());
      e->set_reported(kv);
      if (item["enc_visible"]) e->enc_visible = item["enc_visible"].as<bool>();
      if (e->follows_temperature()) {
        if (!item["sensor"])
          throw InputError(fmt::format("effects: {} needs 'sensor' (the temp.<sensor> column it follows)", e->name()));
        e->note = item["sensor"].as<std::string>();
      }
    } catch (const InputError& ex) {
      throw InputError(where, ex.message());
    } catch (const YAML::Exception& ex) {
      throw InputError(where, std::string("effects: ") + ex.what());
    }
    out.push_back(std::move(e));
  }
  return out;
}

std::string effects_yaml(const std::vector<const Effect*>& effects) {
  std::string s = "effects:\n";
  for (const Effect* e : effects) {
    s += fmt::format("  - effect: {}\n    target: \"{}\"\n", e->name(), e->target);
    if (e->scope() == Scope::Axis) s += fmt::format("    enc_visible: {}\n", e->enc_visible ? "true" : "false");
    if (e->follows_temperature()) s += fmt::format("    sensor: \"{}\"\n", e->note);
    if (e->scope() == Scope::Geometric)
      s += fmt::format("    # deviation from the nominal {} {} (the corrected value is {:.9g})\n", e->nominal, e->unit,
                       e->nominal + e->p[0]);
    s += "    parameters: {";
    bool first = true;
    for (const auto& [k, v] : e->reported()) {
      s += fmt::format("{}{}: {:.9g}", first ? "" : ", ", k, v);
      first = false;
    }
    s += "}\n";
  }
  return s;
}

}  // namespace cscam::sim
