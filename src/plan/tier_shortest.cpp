// Tier 4: least weighted rotary travel along the segment, with a bounded rotary step per point.
#include <fmt/format.h>
#include <fmt/ranges.h>

#include <algorithm>
#include <array>
#include <cmath>

#include "cscam/core/units.hpp"
#include "detail/search.hpp"

namespace cscam::plan::detail {

namespace {
using State = ShortestState;
/// Tentative states of a layer before the beam is filled: cost, cell, predecessor.
using Tentative = std::vector<std::pair<double, std::pair<Cell*, int>>>;

/// Windowed L1 distance transform of the previous states' costs onto the grid, separable in the two
/// rotaries: D(c) = min over |di1|,|di2| <= W of cost(p) + w1 |dr1| + w2 |dr2|.
void distance_transform(const Options& opt, const std::vector<State>& prev, Layer& cur, double max_step, double res,
                        Tentative& tent) {
  int lo1 = std::numeric_limits<int>::max(), hi1 = std::numeric_limits<int>::min();
  int lo2 = lo1, hi2 = hi1;
  for (const Cell& c : cur.cells) {
    lo1 = std::min(lo1, c.i1);
    hi1 = std::max(hi1, c.i1);
    lo2 = std::min(lo2, c.i2);
    hi2 = std::max(hi2, c.i2);
  }
  const int W = static_cast<int>(std::floor(max_step / res + 1e-9));
  // The grid need only hold the cells a previous state reaches (within W of one) and the states within W of those:
  // near a singular axis the layer spans every primary angle, while the beam before it sits in a small patch.
  int plo1 = std::numeric_limits<int>::max(), phi1 = std::numeric_limits<int>::min();
  int plo2 = plo1, phi2 = phi1;
  for (const State& st : prev) {
    plo1 = std::min(plo1, st.cell->i1);
    phi1 = std::max(phi1, st.cell->i1);
    plo2 = std::min(plo2, st.cell->i2);
    phi2 = std::max(phi2, st.cell->i2);
  }
  auto crop = [&](int& lo, int& hi, int plo, int phi) {
    const int tlo = std::max(lo, plo - W), thi = std::min(hi, phi + W);  // reachable cells
    if (tlo > thi) return false;
    lo = std::min(tlo, std::max(plo, tlo - W));  // and the states that reach them
    hi = std::max(thi, std::min(phi, thi + W));
    return true;
  };
  if (prev.empty() || !crop(lo1, hi1, plo1, phi1) || !crop(lo2, hi2, plo2, phi2)) return;
  const int n1 = hi1 - lo1 + 1, n2 = hi2 - lo2 + 1;
  // Scratch grids reused layer after layer (fresh ones cost page faults on every layer).
  // (References: the row and column passes run on other threads, which must see this thread's grids.)
  thread_local std::vector<double> tl_f, tl_g, tl_d;
  thread_local std::vector<int> tl_src, tl_gsrc, tl_dsrc;
  std::vector<double>&f = tl_f, &g = tl_g, &D = tl_d;
  std::vector<int>&src = tl_src, &gsrc = tl_gsrc, &dsrc = tl_dsrc;
  const std::size_t cells = static_cast<size_t>(n1) * n2;
  f.assign(cells, kInf);
  src.assign(cells, -1);
  auto at = [&](int a, int b) { return static_cast<size_t>(b) * n1 + a; };
  for (std::size_t p = 0; p < prev.size(); ++p) {
    const Cell* c = prev[p].cell;
    const int a = c->i1 - lo1, b = c->i2 - lo2;
    if (a < 0 || a >= n1 || b < 0 || b >= n2) continue;
    if (prev[p].cost < f[at(a, b)]) {
      f[at(a, b)] = prev[p].cost;
      src[at(a, b)] = static_cast<int>(p);
    }
  }
  // 1-D windowed min of g(j) + w |i - j| along a line, via two monotone queues.
  // Only the span within W of the line's finite entries can change: the rest stays infinite (no source), as the
  // outputs start, so a line without a finite entry is skipped.
  auto pass = [&](int len, auto&& get, auto&& get_src, auto&& put, double w) {
    int first = -1, last = -1;
    for (int i = 0; i < len; ++i)
      if (get(i) < kInf) {
        if (first < 0) first = i;
        last = i;
      }
    if (first < 0) return;
    const int lo = std::max(0, first - W), hi = std::min(len - 1, last + W);
    // Per-thread scratch (the rows run in parallel): the monotone queue is a plain array with two ends.
    thread_local std::vector<double> out;
    thread_local std::vector<int> arg, dq;
    out.assign(static_cast<size_t>(len), kInf);
    arg.assign(static_cast<size_t>(len), -1);
    dq.resize(static_cast<size_t>(len));
    int head = 0, tail = 0;  // dq[head, tail)
    // Costs are compared and summed through index differences (exact integers), so that the answers do not depend
    // on where the grid starts.
    for (int i = lo; i <= hi; ++i) {  // from the left: min_{i-W<=j<=i} g(j) + w (i - j)
      const double gi = get(i);
      while (tail > head && get(dq[tail - 1]) + w * (i - dq[tail - 1]) >= gi) --tail;
      dq[tail++] = i;
      while (dq[head] < i - W) ++head;
      const double val = get(dq[head]) + w * (i - dq[head]);
      if (val < out[static_cast<size_t>(i)]) {
        out[static_cast<size_t>(i)] = val;
        arg[static_cast<size_t>(i)] = dq[head];
      }
    }
    head = tail = 0;
    for (int i = hi; i >= lo; --i) {  // from the right: min_{i<=j<=i+W} g(j) + w (j - i)
      const double gi = get(i);
      while (tail > head && get(dq[tail - 1]) + w * (dq[tail - 1] - i) >= gi) --tail;
      dq[tail++] = i;
      while (dq[head] > i + W) ++head;
      const double val = get(dq[head]) + w * (dq[head] - i);
      if (val < out[static_cast<size_t>(i)]) {
        out[static_cast<size_t>(i)] = val;
        arg[static_cast<size_t>(i)] = dq[head];
      }
    }
    for (int i = lo; i <= hi; ++i)
      put(i, out[static_cast<size_t>(i)], arg[static_cast<size_t>(i)] >= 0 ? get_src(arg[static_cast<size_t>(i)]) : -1);
  };
  const double w1 = opt.weight_primary * res, w2 = opt.weight_secondary * res;
  g.assign(cells, kInf);
  gsrc.assign(cells, -1);
  // Rows, then columns: each line is independent (in parallel).
  parallel_indices(static_cast<std::size_t>(n2), [&](std::size_t bi) {
    const int b = static_cast<int>(bi);
    pass(
        n1, [&](int a) { return f[at(a, b)]; }, [&](int a) { return src[at(a, b)]; },
        [&](int a, double val, int s) {
          g[at(a, b)] = val;
          gsrc[at(a, b)] = s;
        },
        w1);
  });
  D.assign(cells, kInf);
  dsrc.assign(cells, -1);
  parallel_indices(static_cast<std::size_t>(n1), [&](std::size_t ai) {
    const int a = static_cast<int>(ai);
    pass(
        n2, [&](int b) { return g[at(a, b)]; }, [&](int b) { return gsrc[at(a, b)]; },
        [&](int b, double val, int s) {
          D[at(a, b)] = val;
          dsrc[at(a, b)] = s;
        },
        w2);
  });
  for (Cell& c : cur.cells) {
    if (c.i1 < lo1 || c.i1 > hi1 || c.i2 < lo2 || c.i2 > hi2) continue;  // beyond reach of every state
    const size_t i = at(c.i1 - lo1, c.i2 - lo2);
    if (std::isfinite(D[i]) && dsrc[i] >= 0)
      tent.push_back({D[i] + opt.orientation_weight * c.orient_err, {&c, dsrc[i]}});
  }
}

/// A layer whose incoming move collided between the points in an earlier answer: its states in order of cost,
/// each with the cheapest predecessor whose swept move into it is certified free. Sweeps cost far more than a
/// cell, so this layer keeps a smaller beam and tries a few predecessors per cell; the answer through it can then
/// not repeat a colliding move.
bool swept_layer(const SegmentView& v, SegmentCells& d, const std::vector<State>& prev, std::size_t k, double max_step,
                 std::vector<State>& S) {
  constexpr std::size_t kSweptBeam = 32;        // states kept at such a layer
  constexpr std::size_t kSweptTries = 16;       // predecessors swept per cell, cheapest first
  constexpr std::size_t kSweepsPerLayer = 512;  // sweeps at most per layer
  // A move that needs more queries than this skims the part: passed over here (the final check's budget is larger).
  constexpr std::uint64_t kSweptBudget = 200;
  const Options& opt = v.options;
  auto& cells = d.layers[k].cells;
  struct Candidate {
    double cost;  // of the cheapest predecessor, orientation error included
    std::size_t cell;
    std::vector<std::pair<double, int>> preds;  // (cost through it, index in prev), cheapest first
  };
  std::vector<Candidate> cand;
  for (std::size_t j = 0; j < cells.size(); ++j) {
    const Cell& c = cells[j];
    if (c.status != Status::Unknown && c.status != Status::Feasible) continue;
    Candidate cd{kInf, j, {}};
    for (std::size_t p = 0; p < prev.size(); ++p) {
      const Cell* pc = prev[p].cell;
      const double d1 = std::abs(c.r1 - pc->r1), d2 = std::abs(c.r2 - pc->r2);
      if (d1 > max_step + 1e-12 || d2 > max_step + 1e-12) continue;
      cd.preds.push_back({prev[p].cost + opt.weight_primary * d1 + opt.weight_secondary * d2, static_cast<int>(p)});
    }
    if (cd.preds.empty()) continue;
    std::stable_sort(cd.preds.begin(), cd.preds.end(), [](const auto& a, const auto& b) { return a.first < b.first; });
    cd.cost = cd.preds.front().first + opt.orientation_weight * c.orient_err;
    cand.push_back(std::move(cd));
  }
  std::stable_sort(cand.begin(), cand.end(), [](const Candidate& a, const Candidate& b) { return a.cost < b.cost; });
  // Moves that skim the part (not certified within the budget, no hit found) are kept aside: taken only if no
  // certified move reaches this point, so that a path still exists (the final check then warns about them).
  std::vector<State> skimming;
  std::size_t sweeps = 0;
  // Candidates in blocks of a fixed size, in parallel: each evaluates its cell and sweeps its predecessors, cheapest
  // first, up to the first free move. The block is then replayed in order under the serial rules (beam, sweep
  // budget), so the states, the sweep cache and the answer are those of a serial scan at any thread count; sweeps past
  // where the serial scan stops are wasted work (counted).
  constexpr std::size_t kBlock = 2;
  std::vector<std::vector<std::pair<cspace::SweepStatus, bool>>> tried;  // per candidate: (status, swept now)
  for (std::size_t b = 0; b < cand.size(); b += kBlock) {
    if (S.size() >= kSweptBeam || sweeps >= kSweepsPerLayer) break;
    const std::size_t e = std::min(cand.size(), b + kBlock);
    tried.assign(e - b, {});
    d.certs.reserve();
    parallel_items(e - b, d.counters, [&](std::size_t i, geom::QueryWorkspace& ws, cspace::Counters& cc) {
      const Candidate& cd = cand[b + i];
      Cell& c = cells[cd.cell];
      d.certs.evaluate(d.layers[k].cl, c, ws, cc);
      if (c.status != Status::Feasible) return;
      for (std::size_t t = 0; t < cd.preds.size() && t < kSweptTries; ++t) {
        const State& from = prev[static_cast<std::size_t>(cd.preds[t].second)];
        const auto it = d.sweeps.find(std::make_tuple(k, key(from.cell->i1, from.cell->i2), key(c.i1, c.i2)));
        const bool now = it == d.sweeps.end();  // the cache is only read inside the block
        const cspace::SweepStatus st =
            now ? v.space.swept(from.cell->axes, c.axes, cspace::SweepMode::Cutting, ws, cc, kSweptBudget).status
                : it->second;
        tried[i].push_back({st, now});
        if (st == cspace::SweepStatus::Free) break;
      }
    });
    for (std::size_t i = 0; i < e - b && S.size() < kSweptBeam && sweeps < kSweepsPerLayer; ++i) {
      const Candidate& cd = cand[b + i];
      Cell& c = cells[cd.cell];
      if (c.status != Status::Feasible) continue;
      const double orient = opt.orientation_weight * c.orient_err;
      for (std::size_t t = 0; t < tried[i].size() && sweeps < kSweepsPerLayer; ++t) {
        const auto [st, now] = tried[i][t];
        const State& from = prev[static_cast<std::size_t>(cd.preds[t].second)];
        if (now && d.sweeps.emplace(std::make_tuple(k, key(from.cell->i1, from.cell->i2), key(c.i1, c.i2)), st).second)
          ++sweeps;
        if (st == cspace::SweepStatus::Free) {
          S.push_back({&c, cd.preds[t].first + orient, cd.preds[t].second});
          break;
        }
        if (st == cspace::SweepStatus::Uncertified && skimming.size() < kSweptBeam)
          skimming.push_back({&c, cd.preds[t].first + orient, cd.preds[t].second});
      }
    }
  }
  if (S.empty()) S = std::move(skimming);
  return !S.empty();
}

/// Each cell's cheapest predecessor among `prev`, by a scan of every pair (in parallel over the cells), with steps
/// within `max_step` (infinite: any step); appended to `tent` in cell order.
void scan_predecessors(const Options& opt, const std::vector<State>& prev, std::vector<Cell>& cells, double max_step,
                       Tentative& tent) {
  std::vector<std::pair<double, int>> best(cells.size(), {kInf, -1});
  parallel_indices(cells.size(), [&](std::size_t j) {
    const Cell& c = cells[j];
    for (std::size_t p = 0; p < prev.size(); ++p) {
      const Cell* pc = prev[p].cell;
      const double d1 = std::abs(c.r1 - pc->r1), d2 = std::abs(c.r2 - pc->r2);
      if (d1 > max_step + 1e-12 || d2 > max_step + 1e-12) continue;
      const double val = prev[p].cost + opt.weight_primary * d1 + opt.weight_secondary * d2;
      if (val < best[j].first) best[j] = {val, static_cast<int>(p)};
    }
  });
  for (std::size_t j = 0; j < cells.size(); ++j)
    if (best[j].second >= 0)
      tent.push_back({best[j].first + opt.orientation_weight * cells[j].orient_err, {&cells[j], best[j].second}});
}

/// Layer k of the forward pass: its states from the previous layer's (`prev`), at most `beam` of them, the cheapest
/// feasible cells within the step bound; with `may_jump` (the widest beam, the default bound), where none is within
/// the bound, the cheapest step however large. Returns whether the layer has a state.
bool beam_layer(const SegmentView& v, SegmentCells& d, const std::vector<State>& prev, std::size_t k, double max_step,
                std::size_t beam, bool may_jump, std::vector<State>& S) {
  auto& L = d.layers;
  const Options& opt = v.options;
  // No swept-free (or skimming) move into a flagged point: it is searched as any other (its collision stays
  // reported) rather than failing the whole path.
  if (k > 0 && k < d.swept_layers.size() && d.swept_layers[k] && swept_layer(v, d, prev, k, max_step, S)) return true;
  // The beam from candidates (cost, cell, predecessor): the cheapest feasible ones, cheapest first, ties by grid
  // position (a total order: any sort gives the same sequence). It fills from the front, usually within a few hundred
  // of the thousands of cells near a singular axis: sorted a chunk at a time, as far as the beam reaches. Evaluated in
  // parallel blocks of as many cells as the beam still lacks, and at least kMinFillBlock (a parallel loop per cell or
  // two, as the beam's last places fill, cost more than the spare evaluations): the cells evaluated (and the counters)
  // do not depend on the thread count.
  constexpr std::size_t kMinFillBlock = 16;
  auto fill = [&](Tentative& tent) {
    auto cheaper = [](const auto& x, const auto& y) {
      if (x.first != y.first) return x.first < y.first;
      const Cell &a = *x.second.first, &b = *y.second.first;
      return a.i2 != b.i2 ? a.i2 < b.i2 : a.i1 < b.i1;
    };
    std::size_t sorted = 0;
    auto sort_to = [&](std::size_t e) {
      if (e <= sorted) return;
      e = std::max(e, std::min(tent.size(), sorted + 2 * beam));
      const auto first = tent.begin() + static_cast<std::ptrdiff_t>(sorted), last = tent.end();
      const auto mid = tent.begin() + static_cast<std::ptrdiff_t>(e);
      if (mid < last) std::nth_element(first, mid, last, cheaper);
      std::sort(first, mid, cheaper);
      sorted = e;
    };
    for (std::size_t next = 0; next < tent.size() && S.size() < beam;) {
      const std::size_t b = next, e = std::min(tent.size(), next + std::max(beam - S.size(), kMinFillBlock));
      sort_to(e);
      // The beam revisits the same cells point after point: their clearance certificates spare most queries.
      d.certs.reserve();
      parallel_items(e - b, d.counters, [&](std::size_t i, geom::QueryWorkspace& ws, cspace::Counters& cc) {
        d.certs.evaluate(L[k].cl, *tent[b + i].second.first, ws, cc);
      });
      for (next = b; next < e && S.size() < beam; ++next)
        if (tent[next].second.first->status == Status::Feasible)
          S.push_back({tent[next].second.first, tent[next].first, tent[next].second.second});
    }
  };
  Tentative tent;
  tent.reserve(L[k].cells.size());
  if (k == 0) {
    // The segment is entered from where the previous one ended (or from home). Whole turns of a rotary on the way
    // in are travel for nothing (the windings of an angle cost the same along the segment): they count in full.
    // The rest of the entry reorientation is a rapid, not a cut: a tie-break only, so it never bends the cut
    // toward it.
    const auto [p1, p2] = v.entry_rotaries();
    for (Cell& c : L[0].cells) {
      const double entry = opt.weight_primary * std::abs(c.r1 - p1) + opt.weight_secondary * std::abs(c.r2 - p2);
      const double whole_turns = opt.weight_primary * whole_turns_rad(v.space, 0, c.i1, p1) +
                                 opt.weight_secondary * whole_turns_rad(v.space, 1, c.i2, p2);
      tent.push_back({opt.orientation_weight * c.orient_err + whole_turns + 1e-9 * entry, {&c, -1}});
    }
  } else if (prev.size() * L[k].cells.size() <= 200000) {
    scan_predecessors(opt, prev, L[k].cells, max_step, tent);
  } else {
    distance_transform(opt, prev, L[k], max_step, v.space.options().resolution_rad, tent);
  }
  fill(tent);
  if (S.empty() && k > 0 && may_jump) {
    // No feasible cell within the default step bound of any state: the CL axis itself turns faster here (every
    // point has a feasible cell, check_points made sure). The bound is a preference, not the machine's limit: the
    // cheapest step, however large, is taken (the description names where). A bound the user set stays hard.
    tent.clear();
    scan_predecessors(opt, prev, L[k].cells, kInf, tent);
    fill(tent);
  }
  return !S.empty();
}

double rotary_travel(const std::vector<const Cell*>& path) {
  double travel = 0;
  for (std::size_t k = 1; k < path.size(); ++k)
    travel += std::abs(path[k]->r1 - path[k - 1]->r1) + std::abs(path[k]->r2 - path[k - 1]->r2);
  return travel;
}
}  // namespace

bool tier_shortest(const SegmentView& v, SegmentCells& d, TierOutcome& out) {
  auto& L = d.layers;
  const std::size_t n = L.size();
  const Options& opt = v.options;
  // Exact orientations (cone 0) must be free to turn fast near the singularity: no default bound there.
  const double max_step = max_rotary_step(v);  // the bound tiers 2 and 3 hold too
  // The beam: states kept per point. Where it dead-ends within the step bound it is widened (a bounded path can run
  // through states a narrow beam dropped: NX's path on the 45-degree head needs 1024); only the widest beam may step
  // beyond the bound (below).
  std::vector<std::size_t> beams{std::clamp<std::size_t>(opt.beam_states, 1, Options::kWidestBeam)};
  while (beams.back() < Options::kWidestBeam) beams.push_back(std::min(Options::kWidestBeam, 4 * beams.back()));
  if (v.exact) {
    std::size_t fl = 0;
    Why w;
    auto allowed = [&](const Cell& a, const Cell& b) {
      return std::abs(b.r1 - a.r1) <= max_step + 1e-12 && std::abs(b.r2 - a.r2) <= max_step + 1e-12;
    };
    if (!dp_exact(v, d, allowed, out.path, fl, w)) {
      out.failure = {Tier::Shortest, L[fl].move, line_of(v, d, fl), w.cause, w.detail};
      return false;
    }
    out.description =
        fmt::format("rotary travel {:.3f} deg along continuous IK branches", rad2deg(rotary_travel(out.path)));
    return true;
  }
  LayeredDp<State> dp;
  std::size_t beam_at = 0;  // index in beams
  // Resume where the swept flags first differ from the last pass's (a pass that went through, on the same lists).
  std::size_t k0 = 0;
  std::size_t rejoin_from = n;  // past the last layer whose flag changed, the old pass may be rejoined
  if (d.last_shortest && d.last_shortest->nodes.size() == n) {
    const auto& was = d.last_shortest->swept_layers;
    auto flag = [](const std::vector<char>& f, std::size_t k) { return k < f.size() && f[k]; };
    while (k0 < n && flag(was, k0) == flag(d.swept_layers, k0)) ++k0;
    if (k0 == n) k0 = n - 1;  // nothing changed: the last layer again (cheap)
    rejoin_from = k0 + 1;
    for (std::size_t k = n; k-- > k0;)
      if (flag(was, k) != flag(d.swept_layers, k)) {
        rejoin_from = k + 1;
        break;
      }
    dp.nodes = std::move(d.last_shortest->nodes);
    beam_at = d.last_shortest->beam_at;
  }
  d.last_shortest.reset();
  std::size_t built = 0;
  for (;; ++beam_at, k0 = 0, rejoin_from = n) {
    const bool widest = beam_at + 1 >= beams.size();
    built = dp.forward_rejoin(
        k0, rejoin_from, n,
        [&](std::size_t k, const auto& prev, std::vector<State>& S) {
          return beam_layer(v, d, prev, k, max_step, beams[std::min(beam_at, beams.size() - 1)],
                            widest && opt.max_step_rad <= 0, S);
        },
        [](const State& a, const State& b) { return a.cell == b.cell; });
    if (built == n || widest) break;
  }
  if (built < n) {
    out.failure = {
        Tier::Shortest, L[built].move, line_of(v, d, built), FailureCause::Transition,
        fmt::format(
            "no feasible cell within a rotary step of {:.2f} deg of the previous point (the step bound set in the "
            "options; the default bound gives way where no cell within it follows the CL axis)",
            rad2deg(max_step))};
    return false;
  }
  const std::vector<int> idx = dp.backtrack(dp.cheapest_last());
  d.last_shortest = SegmentCells::ShortestPass{std::move(dp.nodes), d.swept_layers, beam_at};
  const auto& nodes = d.last_shortest->nodes;
  out.path.assign(n, nullptr);
  for (std::size_t k = 0; k < n; ++k) out.path[k] = nodes[k][static_cast<size_t>(idx[k])].cell;
  rewind_to_entry(v, d, out.path);
  // Steps beyond the bound (beam_layer's may_jump): named in the description.
  std::vector<int> beyond;
  double largest = 0.0;
  for (std::size_t k = 1; k < n; ++k) {
    const double step =
        std::max(std::abs(out.path[k]->r1 - out.path[k - 1]->r1), std::abs(out.path[k]->r2 - out.path[k - 1]->r2));
    if (step <= max_step + 1e-12) continue;
    beyond.push_back(line_of(v, d, k));
    largest = std::max(largest, step);
  }
  if (beyond.empty()) {
    out.description = fmt::format("rotary travel {:.3f} deg (steps bounded by {:.2f} deg)",
                                  rad2deg(rotary_travel(out.path)), rad2deg(max_step));
  } else {
    const std::size_t shown = std::min<std::size_t>(beyond.size(), 5);
    out.description = fmt::format(
        "rotary travel {:.3f} deg (steps bounded by {:.2f} deg except into {} point(s), CL line(s) {}{}, up to {:.2f} "
        "deg: no cell within the bound follows the CL axis there)",
        rad2deg(rotary_travel(out.path)), rad2deg(max_step), beyond.size(),
        fmt::join(beyond.begin(), beyond.begin() + static_cast<std::ptrdiff_t>(shown), ", "),
        beyond.size() > shown ? ", ..." : "", rad2deg(largest));
  }
  return true;
}

}  // namespace cscam::plan::detail
