// Counted axes (Options::monotone_axes, e.g. a parallel machine's actuated legs): where the tiers' path reverses
// one, the segment is re-planned inside the cone so that they move monotonically, if it can be.
#include <fmt/format.h>

#include <algorithm>
#include <cmath>

#include "cscam/core/error.hpp"
#include "cscam/core/units.hpp"
#include "detail/search.hpp"

namespace cscam::plan::detail {

namespace {

constexpr double kLegHyst = 1e-4;  // mm: far below a lost motion, far above round-off

/// Which of the counted axes reverse along `path`, and the first point where one does (path.size(): none).
std::vector<int> reversals(const std::vector<int>& axes, const std::vector<const Cell*>& path, std::size_t& where) {
  std::vector<int> which;
  where = path.size();
  for (int ax : axes) {
    int d = 0;
    double ext = path[0]->axes[ax];
    for (std::size_t k = 1; k < path.size(); ++k) {
      const double v = path[k]->axes[ax];
      if (d == 0) {
        if (std::abs(v - ext) > kLegHyst) d = v > ext ? 1 : -1, ext = v;
      } else if (d * (v - ext) > 0) {
        ext = v;
      } else if (std::abs(v - ext) > kLegHyst) {
        which.push_back(ax);
        where = std::min(where, k - 1);
        break;
      }
    }
  }
  return which;
}

/// Exact orientation (cone 0): re-plans so that the axes in `axes` never reverse (beyond `hyst`): the shared DP over
/// the IK cells with transitions that keep every such axis moving in its chosen direction (all direction
/// combinations tried).
bool legs_monotone(const SegmentView& v, SegmentCells& d, const std::vector<int>& axes, double hyst,
                   std::vector<const Cell*>& path, std::size_t& fail_layer, std::string& why) {
  CSCAM_CHECK(v.exact, "the exact-orientation leg re-plan runs on IK cells (grid cells use legs_tilt)");
  const std::size_t combos = std::size_t{1} << axes.size();
  std::size_t worst = 0;
  for (std::size_t m = 0; m < combos; ++m) {
    auto dir = [&](std::size_t j) { return (m >> j) & 1u ? -1.0 : 1.0; };
    auto mono = [&](const Cell& a, const Cell& b) {
      for (std::size_t j = 0; j < axes.size(); ++j)
        if (dir(j) * (b.axes[axes[j]] - a.axes[axes[j]]) < -hyst) return false;
      return true;
    };
    std::size_t fl = 0;
    Why w;
    if (dp_exact(v, d, mono, path, fl, w)) return true;
    if (fl >= worst) {
      worst = fl;
      why = w.text();
    }
  }
  fail_layer = worst;
  return false;
}

/// Continuous refinement inside the cone for the counted axes: instead of the rotary grid (degenerate near
/// the singularity, where the cone covers every primary angle), grid the tool tilt itself around each CL
/// axis (a disc of radius cone, step `tilt_step`), solve the IK nearest the current path there, and run the
/// DP with transitions that keep the counted axes monotonic. The new cells are stored in the layers.
bool legs_tilt(const SegmentView& v, SegmentCells& d, const std::vector<int>& axes, double hyst, double tilt_step,
               const std::vector<const Cell*>& current, std::vector<const Cell*>& path, std::size_t& fail_layer,
               std::string& why) {
  auto& L = d.layers;
  const std::size_t n = L.size();
  const auto& sp = v.space;
  const double cone = sp.options().cone_rad;
  if (cone <= 0 || tilt_step <= 0) return false;
  const int R = static_cast<int>(std::floor(cone / tilt_step + 1e-9));
  const auto& k = sp.kinematics();
  const auto rp = k.rotary_pair();
  const double rb = sp.options().ball_radius_mm;
  // Per layer: states on the tilt disc (index (ti, tj) -> cell in a per-layer store).
  std::vector<std::vector<Cell>> S(n);
  std::vector<std::unordered_map<std::uint64_t, int>> at(n);
  for (std::size_t l = 0; l < n; ++l) {
    const Eigen::Vector3d u = L[l].cl.axis;
    const Eigen::Vector3d e1 = u.unitOrthogonal(), e2 = u.cross(e1);
    const Eigen::Vector3d centre = L[l].cl.tip_mm + rb * u;
    for (int tj = -R; tj <= R; ++tj)
      for (int ti = -R; ti <= R; ++ti) {
        const double tx = ti * tilt_step, ty = tj * tilt_step, t = std::hypot(tx, ty);
        if (t > cone + 1e-12 || t < sp.options().min_tilt_rad - 1e-12) continue;
        const Eigen::Vector3d a = (u + std::tan(tx) * e1 + std::tan(ty) * e2).normalized();
        const kin::Posed pose{rb > 0 ? Eigen::Vector3d(centre - rb * a) : L[l].cl.tip_mm, a};
        kin::Axes q;
        ++d.counters.ik;
        if (!kin::nearest_solution(k, pose, current[l]->axes, q) || !retracts(v, L[l], q)) continue;
        ++d.counters.stroke;
        Cell c;
        c.r1 = q[rp[0]];
        c.r2 = q[rp[1]];
        c.i1 = ti;
        c.i2 = tj;
        c.orient_err = static_cast<float>(t);
        c.axes = q;
        if (!sp.collision_at_axes(q, d.ws, d.counters).empty()) continue;  // tool, head and machine bodies
        c.status = Status::Feasible;
        at[l].emplace(key(ti, tj), static_cast<int>(S[l].size()));
        S[l].push_back(c);
      }
  }
  const std::size_t combos = std::size_t{1} << axes.size();
  const int W = std::max(1, static_cast<int>(v.options.leg_step_cells));
  const Options& opt = v.options;
  std::size_t worst = 0;
  for (std::size_t m = 0; m < combos; ++m) {
    auto dir = [&](std::size_t j) { return (m >> j) & 1u ? -1.0 : 1.0; };
    LayeredDp<CostNode> dp;
    const std::size_t built =
        dp.forward(n, [&](std::size_t l, const std::vector<CostNode>& prev, std::vector<CostNode>& cur) {
          cur.assign(S[l].size(), CostNode{});
          bool any = false;
          for (std::size_t j = 0; j < S[l].size(); ++j) {
            const Cell& b = S[l][j];
            if (l == 0) {
              cur[j].cost = opt.orientation_weight * b.orient_err;
              any = true;
              continue;
            }
            for (int d2 = -W; d2 <= W; ++d2)
              for (int d1 = -W; d1 <= W; ++d1) {
                auto it = at[l - 1].find(key(b.i1 + d1, b.i2 + d2));
                if (it == at[l - 1].end()) continue;
                const std::size_t i = static_cast<std::size_t>(it->second);
                if (!std::isfinite(prev[i].cost)) continue;
                const Cell& a = S[l - 1][i];
                bool ok = true;
                for (std::size_t x = 0; x < axes.size() && ok; ++x)
                  ok = dir(x) * (b.axes[axes[x]] - a.axes[axes[x]]) >= -hyst;
                if (!ok) continue;
                // Rotary travel, plus the change of tilt and the tilt itself: the smallest, smoothest deviation
                // from the CL axis that keeps the legs monotonic.
                const double val = prev[i].cost + opt.weight_primary * std::abs(b.r1 - a.r1) +
                                   opt.weight_secondary * std::abs(b.r2 - a.r2) +
                                   tilt_step * (std::hypot(b.i1 - a.i1, b.i2 - a.i2) + 0.05 * std::hypot(b.i1, b.i2));
                if (val < cur[j].cost) {
                  cur[j] = {val, static_cast<int>(i)};
                  any = true;
                }
              }
          }
          return any;
        });
    if (built < n) {
      if (built >= worst) worst = built;
      continue;
    }
    // Keep the chosen cells alive in the layers (their `extra` store) and return pointers to them.
    const std::vector<int> idx = dp.backtrack(dp.cheapest_last());
    path.assign(n, nullptr);
    for (std::size_t kk = n; kk-- > 0;) {
      const Cell& c = S[kk][static_cast<size_t>(idx[kk])];
      const std::uint64_t slot = key(std::numeric_limits<int>::min() + static_cast<int>(kk), idx[kk]);
      path[kk] = &L[kk].extra.insert_or_assign(slot, c).first->second;
    }
    return true;
  }
  fail_layer = worst;
  why = fmt::format("no tilt within the cone (step {:.3f} deg) keeps it monotonic", rad2deg(tilt_step));
  return false;
}

}  // namespace

LegReport replan_legs(const SegmentView& v, SegmentCells& d, std::vector<const Cell*>& path, Tier& tier,
                      std::string& description) {
  LegReport rep;
  const auto& axes = v.options.monotone_axes;
  std::size_t where = 0;
  const std::vector<int> rev = reversals(axes, path, where);
  if (rev.empty()) {
    rep.state = Legs::Monotonic;
    return rep;
  }
  for (int ax : rev) rep.axes += (rep.axes.empty() ? "" : ", ") + v.kinematics->axes()[static_cast<size_t>(ax)].name;
  const cl::Move& at = v.program.moves[d.layers[where].move];
  rep.line = at.line;
  rep.tip_mm = at.tip_in_part_mm;
  std::vector<const Cell*> mono;
  std::size_t fl = 0;
  const double tilt_step = v.options.tilt_step_rad > 0 ? v.options.tilt_step_rad : v.space.options().resolution_rad;
  // A pinned first point (windowed planning) must keep its rotaries.
  auto keeps_pin = [&] { return !d.layers[0].pinned || (mono[0]->r1 == path[0]->r1 && mono[0]->r2 == path[0]->r2); };
  if (!v.exact && legs_tilt(v, d, rev, kLegHyst, tilt_step, path, mono, fl, rep.why) && keeps_pin()) {
    path = mono;
    for (const Cell* c : mono) rep.max_tilt_rad = std::max(rep.max_tilt_rad, static_cast<double>(c->orient_err));
    rep.state = Legs::TiltedMonotonic;
    rep.why.clear();
    tier = Tier::Shortest;  // the rotaries now follow the tilt refinement
    description = "re-planned inside the cone for monotonic legs (" + description + " before)";
  } else if (v.exact && legs_monotone(v, d, rev, kLegHyst, mono, fl, rep.why) && keeps_pin()) {
    path = mono;
    rep.state = Legs::ReversalRemoved;
    rep.why.clear();
  } else {
    rep.state = Legs::Reverses;
    rep.blocked_line = v.program.moves[d.layers[fl].move].line;
  }
  return rep;
}

}  // namespace cscam::plan::detail
