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
  ExactChoice choice;  // every direction pair that has a path: the least travel
  for (int d1 : {+1, -1})
    for (int d2 : {+1, -1}) {
      std::size_t fl = 0;
      Why w;
      auto allowed = [&](const Cell& a, const Cell& b) {
        return d1 * (static_cast<long long>(b.i1) - a.i1) >= 0 && d2 * (static_cast<long long>(b.i2) - a.i2) >= 0;
      };
      std::vector<const Cell*> p;
      const bool ok = dp_exact(v, d, allowed, p, fl, w);
      if (choice.offer(v, ok, p, fl, w, out))
        out.description =
            fmt::format("{} {}, {} {}", v.n1(), d1 > 0 ? "rising" : "falling", v.n2(), d2 > 0 ? "rising" : "falling");
    }
  return choice.finish(v, d, Tier::Monotonic, out);
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

/// Both rotaries monotonic, every step within the bound: the exact search, for a direction pair whose staircase path
/// jumps. The states of a point are all its feasible cells that a state of the point before reaches with a step in
/// [0, W] grid steps on both directed axes; each keeps the least weighted travel to it and its predecessor. The reach
/// is a one-sided sliding minimum over W steps, along the rows and then the columns of the previous states' box.
/// Costlier than the staircase (it evaluates every reachable cell), so only run where the staircase's answer jumped,
/// and within kBoundedSearchCells cell evaluations (`stopped` then says so; the tier reports it).
constexpr std::size_t kBoundedSearchCells = 50000;
bool bounded_monotonic(const SegmentView& v, SegmentCells& d, int d1, int d2, std::vector<const Cell*>& path,
                       bool& stopped) {
  std::size_t evaluated = 0;
  auto reachable_and_feasible = [&](std::size_t k, Cell& c) {
    if (c.status == Status::Unknown && ++evaluated > kBoundedSearchCells) stopped = true;
    return !stopped && feasible(v, d, k, c);
  };
  const std::size_t n = d.layers.size();
  const double res = v.space.options().resolution_rad;
  const auto W = static_cast<long long>(std::floor(max_rotary_step(v) / res + 1e-9));
  const double w1 = v.options.weight_primary * res, w2 = v.options.weight_secondary * res;
  struct State {
    Cell* cell;
    long long a, b;  // directed grid coordinates
    double cost;
    int pred;
  };
  std::vector<std::vector<State>> states(n);
  for (Cell& c : d.layers[0].cells)
    if (reachable_and_feasible(0, c))
      states[0].push_back({&c, d1 * static_cast<long long>(c.i1), d2 * static_cast<long long>(c.i2), 0.0, -1});
  std::vector<double> g, h;
  std::vector<int> g_src, h_src;
  std::vector<long long> dq;
  // out[i] = min over i - W <= j <= i of in[j], along a line of `len` entries `stride` apart from `start`.
  auto sliding_min = [&](const std::vector<double>& in, const std::vector<int>& in_src, std::vector<double>& out,
                         std::vector<int>& out_src, std::size_t start, std::size_t stride, long long len) {
    dq.clear();
    std::size_t head = 0;
    for (long long i = 0; i < len; ++i) {
      const std::size_t at = start + static_cast<std::size_t>(i) * stride;
      while (dq.size() > head && in[start + static_cast<std::size_t>(dq.back()) * stride] >= in[at]) dq.pop_back();
      dq.push_back(i);
      while (dq[head] < i - W) ++head;
      const std::size_t best = start + static_cast<std::size_t>(dq[head]) * stride;
      out[at] = in[best];
      out_src[at] = in_src[best];
    }
  };
  for (std::size_t k = 1; k < n && !stopped && !states[k - 1].empty(); ++k) {
    const auto& prev = states[k - 1];
    long long a0 = prev.front().a, a1 = a0, b0 = prev.front().b, b1 = b0;
    for (const State& s : prev) {
      a0 = std::min(a0, s.a);
      a1 = std::max(a1, s.a);
      b0 = std::min(b0, s.b);
      b1 = std::max(b1, s.b);
    }
    a1 += W;
    b1 += W;
    const long long na = a1 - a0 + 1, nb = b1 - b0 + 1;
    const auto cells = static_cast<std::size_t>(na * nb);
    // Costs relative to the box's corner: cost(p) - w1 (a_p - a0) - w2 (b_p - b0), so that a cell's cost is the
    // minimum over its reach plus w1 (a - a0) + w2 (b - b0) (a monotone path's travel telescopes).
    g.assign(cells, kInf);
    g_src.assign(cells, -1);
    for (std::size_t p = 0; p < prev.size(); ++p) {
      const auto at = static_cast<std::size_t>((prev[p].b - b0) * na + (prev[p].a - a0));
      const double val =
          prev[p].cost - w1 * static_cast<double>(prev[p].a - a0) - w2 * static_cast<double>(prev[p].b - b0);
      if (val < g[at]) {
        g[at] = val;
        g_src[at] = static_cast<int>(p);
      }
    }
    h.assign(cells, kInf);
    h_src.assign(cells, -1);
    for (long long b = 0; b < nb; ++b) sliding_min(g, g_src, h, h_src, static_cast<std::size_t>(b * na), 1, na);
    for (long long a = 0; a < na; ++a)
      sliding_min(h, h_src, g, g_src, static_cast<std::size_t>(a), static_cast<std::size_t>(na), nb);
    for (Cell& c : d.layers[k].cells) {
      const long long a = d1 * static_cast<long long>(c.i1), b = d2 * static_cast<long long>(c.i2);
      if (a < a0 || a > a1 || b < b0 || b > b1) continue;
      const auto at = static_cast<std::size_t>((b - b0) * na + (a - a0));
      if (g_src[at] < 0 || !reachable_and_feasible(k, c)) continue;
      states[k].push_back(
          {&c, a, b, g[at] + w1 * static_cast<double>(a - a0) + w2 * static_cast<double>(b - b0), g_src[at]});
    }
  }
  if (stopped || states[n - 1].empty()) return false;
  std::size_t at = 0;
  for (std::size_t e = 1; e < states[n - 1].size(); ++e)
    if (states[n - 1][e].cost < states[n - 1][at].cost) at = e;
  path.assign(n, nullptr);
  for (std::size_t k = n; k-- > 0;) {
    const State& s = states[k][at];
    path[k] = s.cell;
    at = static_cast<std::size_t>(s.pred);
  }
  return true;
}
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
      // Any final staircase cell is reachable; take the one with the least travel. Where every such path jumps beyond
      // the step bound, the exact bounded search (bounded_monotonic) gives this direction pair's answer, if any.
      std::vector<std::vector<const Cell*>> paths;
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
        paths.push_back(std::move(p));
      }
      if (paths.empty()) {
        std::vector<const Cell*> p;
        bool stopped = false;
        if (bounded_monotonic(v, d, d1, d2, p, stopped)) paths.push_back(std::move(p));
        if (stopped)
          furthest_why.detail +=
              fmt::format("; the exact search within the step bound stopped after {} cells", kBoundedSearchCells);
      }
      for (const auto& p : paths) {
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
  if (std::isfinite(best_travel)) {
    rewind_to_entry(v, d, out.path);  // the description gives travels only: unchanged
    return true;
  }
  out.failure = {Tier::Monotonic, L[furthest].move, line_of(v, d, furthest), furthest_why.cause, furthest_why.detail};
  return false;
}

}  // namespace cscam::plan::detail
