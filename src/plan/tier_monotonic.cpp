// Tier 3: both rotaries monotonic along the segment.
#include <fmt/format.h>

#include <algorithm>
#include <cmath>

#include "cscam/core/units.hpp"
#include "detail/search.hpp"

namespace cscam::plan::detail {

namespace {
/// Cone 0: the exact IK cells, through the shared DP with a transition rule per pair of directions.
bool exact_monotonic(const SegmentView& v, SegmentCells& d, TierOutcome& out) {
  std::size_t worst = 0;
  Why why;
  for (int d1 : {+1, -1})
    for (int d2 : {+1, -1}) {
      std::size_t fl = 0;
      Why w;
      auto allowed = [&](const Cell& a, const Cell& b) {
        return d1 * (static_cast<long long>(b.i1) - a.i1) >= 0 && d2 * (static_cast<long long>(b.i2) - a.i2) >= 0;
      };
      if (dp_exact(v, d, allowed, out.path, fl, w)) {
        out.description =
            fmt::format("{} {}, {} {}", v.n1(), d1 > 0 ? "rising" : "falling", v.n2(), d2 > 0 ? "rising" : "falling");
        return true;
      }
      if (fl >= worst) {
        worst = fl;
        why = w;
      }
    }
  out.failure = {Tier::Monotonic, d.layers[worst].move, line_of(v, d, worst), why.cause, why.detail};
  return false;
}

/// A state of the staircase DP: a cell, in the directed coordinates a (primary) and b (secondary), reachable
/// from the predecessor `pred` of the previous point's staircase. Only the Pareto front (least a for each b, a
/// falling as b rises) is kept: any cell it dominates is reachable from a front cell too.
struct Step {
  long long a, b;
  Cell* cell;
  int pred;
  double cost = 0.0;  // unused: any final step is reachable, the least travel picks one
};
}  // namespace

bool tier_monotonic(const SegmentView& v, SegmentCells& d, TierOutcome& out) {
  if (v.exact) return exact_monotonic(v, d, out);
  const std::size_t n = d.layers.size();
  auto& L = d.layers;
  std::size_t furthest = 0;
  Why furthest_why{FailureCause::Orientation, ""};
  double best_travel = kInf;
  bool jumped = false;  // some direction pair had a whole monotonic path, but one that jumps
  // Every layer's cells in grid order (rows by secondary, primary inside a row), sorted once per cell list (kept in
  // the layer across cascade re-runs) for the four direction pairs: each walks the rows and the cells inside a row
  // forward or backward.
  parallel_indices(n, [&](std::size_t k) {
    Layer& l = L[k];
    if (l.grid_order.size() == l.cells.size() && !l.row_starts.empty()) return;
    const auto& cells = l.cells;
    // Two stable counting passes (by i1, then by i2): linear in the cells, where a comparison sort of thousands of
    // cells per point was tier 3's largest cost.
    std::vector<std::uint32_t> by_i1(cells.size());
    l.grid_order.resize(cells.size());
    auto counting = [&](auto index_of, const std::vector<std::uint32_t>* in, std::vector<std::uint32_t>& out) {
      int lo = std::numeric_limits<int>::max(), hi = std::numeric_limits<int>::min();
      for (const Cell& c : cells) lo = std::min(lo, index_of(c)), hi = std::max(hi, index_of(c));
      std::vector<std::uint32_t> start(static_cast<std::size_t>(hi - lo) + 2, 0);
      for (const Cell& c : cells) ++start[static_cast<std::size_t>(index_of(c) - lo) + 1];
      for (std::size_t b = 1; b < start.size(); ++b) start[b] += start[b - 1];
      for (std::size_t i = 0; i < cells.size(); ++i) {
        const auto at = in ? (*in)[i] : static_cast<std::uint32_t>(i);
        out[start[static_cast<std::size_t>(index_of(cells[at]) - lo)]++] = at;
      }
    };
    if (!cells.empty()) {
      counting([](const Cell& c) { return c.i1; }, nullptr, by_i1);
      counting([](const Cell& c) { return c.i2; }, &by_i1, l.grid_order);
    }
    l.row_starts.clear();
    for (std::size_t i = 0; i < l.grid_order.size(); ++i)
      if (i == 0 || cells[l.grid_order[i]].i2 != cells[l.grid_order[i - 1]].i2)
        l.row_starts.push_back(static_cast<std::uint32_t>(i));
    l.row_starts.push_back(static_cast<std::uint32_t>(l.grid_order.size()));
  });
  for (int d1 : {+1, -1})
    for (int d2 : {+1, -1}) {
      Why why{FailureCause::Orientation, ""};
      LayeredDp<Step> dp;
      const std::size_t k_end =
          dp.forward(n, [&](std::size_t k, const std::vector<Step>& prev, std::vector<Step>& stair) {
            // Rows by b = d2 i2 ascending, a = d1 i1 ascending inside a row.
            Layer& l = L[k];
            const std::size_t n_rows = l.row_starts.size() - 1;
            std::size_t pi = 0;
            long long lb = std::numeric_limits<long long>::max();  // min a over prev staircase with b' <= b
            int lb_idx = -1;
            long long cur_min_a = std::numeric_limits<long long>::max();
            for (std::size_t ri = 0; ri < n_rows; ++ri) {
              const std::size_t row = d2 > 0 ? ri : n_rows - 1 - ri;
              const std::size_t i = l.row_starts[row], j = l.row_starts[row + 1];
              const long long b = static_cast<long long>(d2) * l.cells[l.grid_order[i]].i2;
              while (pi < prev.size() && prev[pi].b <= b) {
                if (prev[pi].a < lb) {
                  lb = prev[pi].a;
                  lb_idx = static_cast<int>(pi);
                }
                ++pi;
              }
              if (k == 0) lb = std::numeric_limits<long long>::min();
              if (k == 0 || lb_idx >= 0) {
                for (std::size_t u = 0; u < j - i; ++u) {
                  Cell* cell = &l.cells[l.grid_order[d1 > 0 ? i + u : j - 1 - u]];
                  const long long a = static_cast<long long>(d1) * cell->i1;
                  if (a < lb) continue;
                  if (a >= cur_min_a) break;  // dominated by a reachable cell of a lower row
                  if (feasible(v, d, k, *cell)) {
                    stair.push_back({a, b, cell, lb_idx});
                    cur_min_a = a;
                    break;
                  }
                  why = {cause_of(cell->status), cell->detail};
                }
              }
            }
            return !stair.empty();
          });
      if (k_end < n) {
        if (!jumped && k_end >= furthest) {
          furthest = k_end;
          furthest_why = why;
        }
        continue;
      }
      // Any final staircase cell is reachable; take the one with the least travel.
      for (std::size_t e = 0; e < dp.nodes[n - 1].size(); ++e) {
        const std::vector<int> idx = dp.backtrack(static_cast<int>(e));
        std::vector<const Cell*> p(n);
        for (std::size_t kk = 0; kk < n; ++kk) p[kk] = dp.nodes[kk][static_cast<size_t>(idx[kk])].cell;
        std::size_t jump = 0;
        if (Why w; !steps_within_bound(v, p, w, jump)) {
          // A monotonic path exists but jumps: that, not a shorter failure elsewhere, is why this tier gives none.
          if (!jumped) furthest = jump, furthest_why = w;
          jumped = true;
          continue;
        }
        const double travel = v.options.weight_primary * std::abs(p[n - 1]->r1 - p[0]->r1) +
                              v.options.weight_secondary * std::abs(p[n - 1]->r2 - p[0]->r2);
        if (travel < best_travel - 1e-12) {
          best_travel = travel;
          out.path = p;
          out.description =
              fmt::format("{} {} by {:.3f} deg, {} {} by {:.3f} deg", v.n1(), d1 > 0 ? "rising" : "falling",
                          rad2deg(std::abs(p[n - 1]->r1 - p[0]->r1)), v.n2(), d2 > 0 ? "rising" : "falling",
                          rad2deg(std::abs(p[n - 1]->r2 - p[0]->r2)));
        }
      }
    }
  if (std::isfinite(best_travel)) return true;
  out.failure = {Tier::Monotonic, L[furthest].move, line_of(v, d, furthest), furthest_why.cause, furthest_why.detail};
  return false;
}

}  // namespace cscam::plan::detail
