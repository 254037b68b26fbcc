// Tier 1: both rotaries fixed along the segment (3+2).
#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <numeric>

#include "cscam/core/units.hpp"
#include "detail/search.hpp"

namespace cscam::plan::detail {

namespace {
struct Candidate {
  int i1, i2;
  double score, home;
};

/// The cells of the first point whose orientation stays within the cone at every point, closest first (to 1e-6
/// rad: windings tie exactly), then nearest the previous segment's rotaries (or home). `furthest`: the latest point
/// that rejected a candidate.
std::vector<Candidate> candidates(const SegmentView& v, SegmentCells& d, std::size_t& furthest) {
  const auto& L = d.layers;
  const std::size_t n = L.size();
  std::vector<Candidate> cands;
  const auto entry = v.entry_rotaries();
  // Orientation only (cheap): no cell is materialised until a candidate survives every point. The point
  // that rejected the previous candidate is tested first (move-to-front), so most candidates cost O(1).
  std::vector<std::size_t> oorder;
  for (std::size_t k = 1; k < n; ++k) oorder.push_back(k);
  for (const Cell& c0 : L[0].cells) {
    double score = c0.orient_err;
    bool ok = true;
    double min_dot = 1.0;  // the worst point's cosine: one arc cosine per candidate, not one per point
    for (std::size_t oi = 0; oi < oorder.size() && ok; ++oi) {
      const std::size_t k = oorder[oi];
      double dot = 1.0;
      const bool in =
          v.exact ? L[k].index.contains(key(c0.i1, c0.i2)) : v.space.in_cone_cos(L[k].cl, c0.r1, c0.r2, dot);
      if (!in) {
        furthest = std::max(furthest, k);
        ok = false;
        std::rotate(oorder.begin(), oorder.begin() + static_cast<std::ptrdiff_t>(oi),
                    oorder.begin() + static_cast<std::ptrdiff_t>(oi) + 1);
      } else {
        min_dot = std::min(min_dot, dot);
      }
    }
    if (ok && !v.exact && oorder.size())
      score = std::max(score, static_cast<double>(static_cast<float>(std::acos(min_dot))));
    // Among equally good orientations prefer the winding nearest the previous segment (or home).
    const double home = std::abs(c0.r1 - entry[0]) + std::abs(c0.r2 - entry[1]);
    if (ok) cands.push_back({c0.i1, c0.i2, score, home});
  }
  std::stable_sort(cands.begin(), cands.end(), [](const Candidate& a, const Candidate& b) {
    if (std::abs(a.score - b.score) > 1e-6) return a.score < b.score;
    return a.home < b.home;
  });
  return cands;
}

/// Among the candidates after `cd` about as close to the CL axis (within 0.1 deg) and feasible at the first, middle
/// and last points, the one with the most room (more than `path` keeps), validated at every point; else `path`.
std::vector<const Cell*> roomiest(const SegmentView& v, SegmentCells& d, const std::vector<Candidate>& cands,
                                  const Candidate& cd, const std::vector<const Cell*>& path) {
  const std::size_t n = d.layers.size();
  // Room is probed at three points per alternative; only the winner is then validated everywhere.
  const double room0 = room(v, d, path);
  const Candidate* winner = nullptr;
  double best_room = room0;
  int tried = 0;
  for (const Candidate* nx = &cd + 1; nx < cands.data() + cands.size() && tried < 8; ++nx) {
    if (nx->score > cd.score + deg2rad(0.1)) break;
    ++tried;
    std::vector<const Cell*> probe(n, nullptr);
    bool ok = true;
    for (std::size_t kk : {std::size_t{0}, n / 2, n - 1}) {
      Cell* c = cell_at(v, d, kk, nx->i1, nx->i2);
      ok = ok && c && feasible(v, d, kk, *c);
      if (ok) probe[kk] = c;
    }
    if (!ok) continue;
    const double r = room(v, d, probe);
    if (r > best_room) {
      best_room = r;
      winner = nx;
    }
  }
  if (winner) {
    std::vector<const Cell*> alt(n, nullptr);
    cspace::Certificate cert2;
    bool ok = true;
    for (std::size_t kk = 0; kk < n && ok; ++kk) {
      Cell* c = cell_at(v, d, kk, winner->i1, winner->i2);
      ok = c && feasible(v, d, kk, *c, &cert2);
      if (ok) alt[kk] = c;
    }
    if (ok) return alt;
  }
  return path;
}
}  // namespace

bool tier_fixed(const SegmentView& v, SegmentCells& d, TierOutcome& out) {
  const std::size_t n = d.layers.size();
  std::size_t furthest = 0;
  const std::vector<Candidate> cands = candidates(v, d, furthest);
  if (cands.empty()) {
    out.failure = {Tier::Fixed2, d.layers[furthest].move, line_of(v, d, furthest), FailureCause::Orientation,
                   "no single orientation stays within the cone from the segment start to this point"};
    return false;
  }
  // Feasibility along the segment, candidates in order. The point that rejected the last candidate is
  // tried first for the next one (move-to-front): neighbouring candidates tend to fail at the same place,
  // so most rejections cost one query instead of a walk along the segment.
  std::vector<std::size_t> order(n);
  std::iota(order.begin(), order.end(), std::size_t{0});
  std::size_t best_reach = 0;
  FailureCause best_cause = FailureCause::Orientation;
  std::string best_detail;
  auto& path = out.path;
  for (const Candidate& cd : cands) {
    path.assign(n, nullptr);
    std::size_t failed_at = n;
    cspace::Certificate cert;  // one fixed orientation along the segment: neighbours certify each other
    for (std::size_t oi = 0; oi < n; ++oi) {
      const std::size_t k = order[oi];
      Cell* c = cell_at(v, d, k, cd.i1, cd.i2);
      if (!c || !feasible(v, d, k, *c, &cert)) {
        failed_at = k;
        std::rotate(order.begin(), order.begin() + static_cast<std::ptrdiff_t>(oi),
                    order.begin() + static_cast<std::ptrdiff_t>(oi) + 1);
        break;
      }
      path[k] = c;
    }
    if (failed_at == n) {
      // Ties in orientation are broken by clearance: among the candidates about as close to the CL axis that are
      // feasible everywhere, keep the one with the most room around it.
      if (v.space.options().check_collision) path = roomiest(v, d, cands, cd, path);
      out.description = fmt::format("rotaries fixed at {} = {:.3f} deg, {} = {:.3f} deg", v.n1(), rad2deg(path[0]->r1),
                                    v.n2(), rad2deg(path[0]->r2));
      return true;
    }
    // Report the failure of the candidate that got furthest from the segment start (in point order).
    std::size_t reach = 0;
    while (reach < n && path[reach]) ++reach;
    if (reach >= best_reach) {
      Cell* c = cell_at(v, d, failed_at, cd.i1, cd.i2);
      best_reach = failed_at;
      best_cause = c ? cause_of(c->status) : FailureCause::Orientation;
      best_detail = fmt::format("{} (best fixed orientation {:.3f}, {:.3f} deg)", c ? c->detail : "",
                                rad2deg(v.space.r1_of(cd.i1)), rad2deg(v.space.r2_of(cd.i2)));
    }
  }
  out.failure = {Tier::Fixed2, d.layers[best_reach].move, line_of(v, d, best_reach), best_cause, best_detail};
  return false;
}

}  // namespace cscam::plan::detail
