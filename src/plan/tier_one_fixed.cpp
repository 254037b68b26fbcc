// Tier 2: one rotary fixed along the segment, the other monotonic.
#include <fmt/format.h>

#include <algorithm>
#include <cmath>

#include "cscam/core/units.hpp"
#include "detail/search.hpp"

namespace cscam::plan::detail {

namespace {
/// Cone 0: the exact IK cells, through the shared DP with a transition rule per (fixed axis, direction).
bool exact_one_fixed(const SegmentView& v, SegmentCells& d, TierOutcome& out) {
  ExactChoice choice;  // every (fixed axis, direction) that has a path: the least travel
  for (int f = 1; f >= 0; --f)
    for (int dir : {+1, -1}) {
      std::size_t fl = 0;
      Why w;
      auto allowed = [&](const Cell& a, const Cell& b) {
        const long long fa = f == 0 ? a.i1 : a.i2, fb = f == 0 ? b.i1 : b.i2;
        const long long ma = f == 0 ? a.i2 : a.i1, mb = f == 0 ? b.i2 : b.i1;
        return fa == fb && dir * (mb - ma) >= 0;
      };
      std::vector<const Cell*> p;
      const bool ok = dp_exact(v, d, allowed, p, fl, w);
      if (choice.offer(v, ok, p, fl, w, out))
        out.description =
            fmt::format("{} fixed at {:.3f} deg, the other {}", f == 0 ? v.n1() : v.n2(),
                        rad2deg(f == 0 ? out.path[0]->r1 : out.path[0]->r2), dir > 0 ? "rising" : "falling");
    }
  return choice.finish(v, d, Tier::Fixed1, out);
}
}  // namespace

bool tier_one_fixed(const SegmentView& v, SegmentCells& d, TierOutcome& out) {
  if (v.exact) return exact_one_fixed(v, d, out);
  const std::size_t n = d.layers.size();
  const auto& sp = v.space;
  std::size_t furthest = 0;
  Why furthest_why{FailureCause::Orientation, ""};
  double best_travel = kInf;
  bool jumped = false;  // some candidate had a whole monotonic path, but one that jumps
  std::vector<const Cell*> best;
  int best_f = 0, best_dir = 0;
  for (int f = 1; f >= 0; --f) {  // fix the secondary first (e.g. the tilt), then the primary
    // Candidate fixed values: present at the first point, closest orientation first. Later points are
    // scanned lazily along the moving axis (no per-point cell lists, so no cap can hide a cell).
    std::unordered_map<int, double> first_err;
    for (const Cell& c : d.layers[0].cells) {
      const int val = f == 0 ? c.i1 : c.i2;
      auto it = first_err.find(val);
      if (it == first_err.end() || c.orient_err < it->second) first_err[val] = c.orient_err;
    }
    std::vector<std::pair<double, int>> vals;
    vals.reserve(first_err.size());
    for (const auto& [val, e] : first_err) vals.emplace_back(e, val);
    std::sort(vals.begin(), vals.end());
    if (vals.size() > static_cast<size_t>(v.options.max_fixed_candidates))
      vals.resize(static_cast<size_t>(v.options.max_fixed_candidates));
    const int mlo = f == 0 ? sp.i2_min() : sp.i1_min(), mhi = f == 0 ? sp.i2_max() : sp.i1_max();
    for (const auto& [e0, val] : vals) {
      for (int dir : {+1, -1}) {
        std::vector<const Cell*> p(n, nullptr);
        int prev = dir > 0 ? mlo : mhi;
        std::size_t k = 0;
        Why why{FailureCause::Orientation, ""};
        for (; k < n; ++k) {
          Cell* chosen = nullptr;
          bool entered = false;
          for (int m = prev; m >= mlo && m <= mhi; m += dir) {
            Cell* c = f == 0 ? cell_at(v, d, k, val, m) : cell_at(v, d, k, m, val);
            if (!c) {
              if (entered || k > 0) {
                if (entered) break;  // left the cone's run along the moving axis
                // before entering: keep scanning, but only within a turn of the previous value
                if (std::abs(m - prev) * sp.options().resolution_rad > 2 * kPi) break;
              }
              continue;
            }
            entered = true;
            if (feasible(v, d, k, *c)) {
              chosen = c;
              break;
            }
            why = {cause_of(c->status), c->detail};
          }
          if (!chosen) break;
          p[k] = chosen;
          prev = f == 0 ? chosen->i2 : chosen->i1;
        }
        if (k == n && !steps_within_bound(v, p, why, k)) {
          // A monotonic path exists but jumps: that, not a shorter failure elsewhere, is why this tier gives none.
          if (!jumped) furthest = k, furthest_why = why;
          jumped = true;
          continue;
        }
        if (k < n) {
          if (!jumped && k >= furthest) {
            furthest = k;
            furthest_why = why;
          }
          continue;
        }
        const double travel = std::abs((f == 0 ? p[n - 1]->r2 - p[0]->r2 : p[n - 1]->r1 - p[0]->r1));
        if (travel < best_travel - 1e-12) {
          best_travel = travel;
          best = p;
          best_f = f;
          best_dir = dir;
        }
      }
      if (!best.empty()) break;  // candidates are in order of orientation closeness
    }
  }
  if (!best.empty()) {
    rewind_to_entry(v, d, best);
    const Cell& c0 = *best.front();
    out.description = fmt::format("{} fixed at {:.3f} deg, {} {} by {:.3f} deg", best_f == 0 ? v.n1() : v.n2(),
                                  rad2deg(best_f == 0 ? c0.r1 : c0.r2), best_f == 0 ? v.n2() : v.n1(),
                                  best_dir > 0 ? "rising" : "falling", rad2deg(best_travel));
    out.path = std::move(best);
    return true;
  }
  out.failure = {Tier::Fixed1, d.layers[furthest].move, line_of(v, d, furthest), furthest_why.cause,
                 furthest_why.detail};
  return false;
}

}  // namespace cscam::plan::detail
