#include "cscam/plan/plan.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <deque>
#include <limits>
#include <numeric>
#include <unordered_map>
#include <utility>

#include <sys/resource.h>
#include <tbb/blocked_range.h>
#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include "cscam/core/error.hpp"
#include "cscam/core/threads.hpp"
#include "cscam/core/units.hpp"
#include "cscam/cspace/certificates.hpp"
#include "cscam/kin/track.hpp"
#include "parallel.hpp"

namespace cscam::plan {

const char* to_string(Tier t) {
  switch (t) {
    case Tier::Fixed2:
      return "fixed 2 axes + simultaneous 3 axes";
    case Tier::Fixed1:
      return "fixed 1 axis + simultaneous 4 axes (monotonic)";
    case Tier::Monotonic:
      return "simultaneous 5 axes, both rotaries monotonic";
    case Tier::Shortest:
      return "simultaneous 5 axes, shortest rotary path";
  }
  return "?";
}

namespace {

// The parallel loops (a kept arena, per-thread workspaces): src/plan/parallel.hpp.
using detail::parallel_indices;
using detail::parallel_items;

using cspace::Cell;
using cspace::Status;
constexpr double kInf = std::numeric_limits<double>::infinity();
/// Exact-orientation (cone 0) cells are keyed on a 1e-6 rad lattice so that "the same cell" and
/// "monotonic" mean the same thing as on the grid.
constexpr double kExactKeyRad = 1e-6;

std::uint64_t key(int i1, int i2) {
  return (static_cast<std::uint64_t>(static_cast<std::uint32_t>(i1)) << 32) | static_cast<std::uint32_t>(i2);
}

struct Layer {
  std::size_t move = 0;
  kin::Posed cl;
  std::vector<Cell> cells;                        ///< orientation cells, closest first (capped)
  std::unordered_map<std::uint64_t, int> index;   ///< (i1,i2) -> position in cells
  std::unordered_map<std::uint64_t, Cell> extra;  ///< evaluated cells outside the cap
  bool truncated = false;                         ///< `cells` stopped at the cap: the cone holds more
  bool pinned = false;                            ///< Options::start_rotaries: `cells` is that one cell, no other
};

/// The search over one segment's layers. Owns the per-thread query workspace.
class Search {
 public:
  Search(const cspace::Space& sp, const Options& opt, std::vector<Layer>& layers, cspace::Counters& c,
         const cl::Program& prog)
      : sp_(sp), opt_(opt), L_(layers), c_(c), prog_(prog), exact_(sp.options().cone_rad <= 0), certs_(sp) {}

  /// The cell (i1, i2) at layer k, created (with its orientation test) if needed; null if outside the cone.
  Cell* cell(std::size_t k, int i1, int i2) {
    Layer& l = L_[k];
    const auto kk = key(i1, i2);
    if (auto it = l.index.find(kk); it != l.index.end()) return &l.cells[static_cast<size_t>(it->second)];
    if (auto it = l.extra.find(kk); it != l.extra.end())
      return it->second.status == Status::Orientation ? nullptr : &it->second;
    if (exact_ || l.pinned) return nullptr;  // exact cells are all enumerated; a pinned layer has its one cell
    Cell c;
    c.i1 = i1;
    c.i2 = i2;
    c.r1 = sp_.r1_of(i1);
    c.r2 = sp_.r2_of(i2);
    if (!sp_.in_cone(l.cl, c.r1, c.r2, &c.orient_err)) c.status = Status::Orientation;
    auto& slot = l.extra.emplace(kk, c).first->second;
    return slot.status == Status::Orientation ? nullptr : &slot;
  }

  bool feasible(std::size_t k, Cell& c, cspace::Certificate* cert = nullptr) {
    sp_.evaluate(L_[k].cl, c, ws_, c_, cert);
    return c.status == Status::Feasible;
  }

  int line(std::size_t k) const { return prog_.moves[L_[k].move].line; }
  /// The rotaries the previous segment ended at (tie-break between equally good starts); null: home.
  void prefer(const kin::Axes* q) { prefer_ = q; }
  /// Names of the primary and secondary rotaries, for reports.
  std::string n1() const {
    return sp_.kinematics().axes()[static_cast<size_t>(sp_.kinematics().rotary_pair()[0])].name;
  }
  std::string n2() const {
    return sp_.kinematics().axes()[static_cast<size_t>(sp_.kinematics().rotary_pair()[1])].name;
  }

  /// Exact orientations (cone 0): a layered DP over the IK cells where a transition must satisfy `allowed`
  /// and be continuously trackable (following the CL pose from one cell reaches the other without a
  /// flip). Least L1 rotary travel. Returns false with the first layer that no allowed path reaches.
  template <typename Allowed>
  bool dp_exact(Allowed&& allowed, std::vector<const Cell*>& path, std::size_t& fail_layer, std::string& why) {
    const std::size_t n = L_.size();
    const auto rp = sp_.kinematics().rotary_pair();
    std::vector<std::vector<double>> cost(n);
    std::vector<std::vector<int>> pred(n);
    for (std::size_t k = 0; k < n; ++k) {
      auto& cells = L_[k].cells;
      cost[k].assign(cells.size(), kInf);
      pred[k].assign(cells.size(), -1);
      bool any = false;
      for (std::size_t j = 0; j < cells.size(); ++j) {
        if (!feasible(k, cells[j])) {
          why = fmt::format("{}: {}", to_string(cells[j].status), cells[j].detail);
          continue;
        }
        if (k == 0) {
          // Ties (windings of a cyclic axis) go to the start nearest the previous segment's rotaries (or home).
          const double r1 = prefer_ ? (*prefer_)[rp[0]] : 0.0, r2 = prefer_ ? (*prefer_)[rp[1]] : 0.0;
          cost[0][j] = 1e-9 * (std::abs(cells[j].r1 - r1) + std::abs(cells[j].r2 - r2));
          any = true;
          continue;
        }
        for (std::size_t i = 0; i < L_[k - 1].cells.size(); ++i) {
          if (!std::isfinite(cost[k - 1][i])) continue;
          const Cell& a = L_[k - 1].cells[i];
          const Cell& b = cells[j];
          if (!allowed(a, b)) continue;
          const double v = cost[k - 1][i] + opt_.weight_primary * std::abs(b.r1 - a.r1) +
                           opt_.weight_secondary * std::abs(b.r2 - a.r2);
          if (v >= cost[k][j]) continue;
          kin::Axes out;
          const kin::Posed pa = sp_.tool_pose(L_[k - 1].cl, a.r1, a.r2), pb = sp_.tool_pose(L_[k].cl, b.r1, b.r2);
          if (!kin::track(sp_.kinematics(), a.axes, pa, pb, out)) continue;
          if (std::abs(out[rp[0]] - b.r1) + std::abs(out[rp[1]] - b.r2) > 1e-6) continue;  // would flip
          cost[k][j] = v;
          pred[k][j] = static_cast<int>(i);
          any = true;
        }
      }
      if (!any) {
        fail_layer = k;
        if (why.empty()) why = "no continuous (flip-free) transition from the previous point";
        return false;
      }
    }
    std::size_t best = 0;
    for (std::size_t j = 1; j < cost[n - 1].size(); ++j)
      if (cost[n - 1][j] < cost[n - 1][best]) best = j;
    path.assign(n, nullptr);
    int idx = static_cast<int>(best);
    for (std::size_t k = n; k-- > 0;) {
      path[k] = &L_[k].cells[static_cast<size_t>(idx)];
      idx = pred[k][static_cast<size_t>(idx)];
    }
    return true;
  }

  /// Exact orientation (cone 0): re-plans so that the axes in `axes` never reverse (beyond `hyst`): a DP over the IK
  /// cells whose transitions keep every such axis moving in its chosen direction (all direction combinations tried).
  bool legs_monotone(const std::vector<int>& axes, double hyst, std::vector<const Cell*>& path, std::size_t& fail_layer,
                     std::string& why) {
    CSCAM_CHECK(exact_, "the exact-orientation leg re-plan runs on IK cells (grid cells use legs_tilt)");
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
      std::string w;
      const bool ok = dp_exact(mono, path, fl, w);
      if (ok) return true;
      if (fl >= worst) {
        worst = fl;
        why = w;
      }
    }
    fail_layer = worst;
    return false;
  }

  /// Continuous refinement inside the cone for the counted axes: instead of the rotary grid (degenerate near
  /// the singularity, where the cone covers every primary angle), grid the tool tilt itself around each CL
  /// axis (a disc of radius cone, step `tilt_step`), solve the IK nearest the current path there, and run a
  /// DP whose transitions keep the counted axes monotonic. The new cells are stored in the layers.
  bool legs_tilt(const std::vector<int>& axes, double hyst, double tilt_step, const std::vector<const Cell*>& current,
                 std::vector<const Cell*>& path, std::size_t& fail_layer, std::string& why) {
    const std::size_t n = L_.size();
    const double cone = sp_.options().cone_rad;
    if (cone <= 0 || tilt_step <= 0) return false;
    const int R = static_cast<int>(std::floor(cone / tilt_step + 1e-9));
    const auto& k = sp_.kinematics();
    const auto rp = k.rotary_pair();
    const double rb = sp_.options().ball_radius_mm;
    // Per layer: states on the tilt disc (index (ti, tj) -> cell in a per-layer store).
    std::vector<std::vector<Cell>> S(n);
    std::vector<std::unordered_map<std::uint64_t, int>> at(n);
    for (std::size_t l = 0; l < n; ++l) {
      const Eigen::Vector3d u = L_[l].cl.axis;
      const Eigen::Vector3d e1 = u.unitOrthogonal(), e2 = u.cross(e1);
      const Eigen::Vector3d centre = L_[l].cl.tip_mm + rb * u;
      for (int tj = -R; tj <= R; ++tj)
        for (int ti = -R; ti <= R; ++ti) {
          const double tx = ti * tilt_step, ty = tj * tilt_step, t = std::hypot(tx, ty);
          if (t > cone + 1e-12 || t < sp_.options().min_tilt_rad - 1e-12) continue;
          const Eigen::Vector3d a = (u + std::tan(tx) * e1 + std::tan(ty) * e2).normalized();
          const kin::Posed pose{rb > 0 ? Eigen::Vector3d(centre - rb * a) : L_[l].cl.tip_mm, a};
          kin::Axes q;
          ++c_.ik;
          if (!kin::nearest_solution(k, pose, current[l]->axes, q)) continue;
          ++c_.stroke;
          Cell c;
          c.r1 = q[rp[0]];
          c.r2 = q[rp[1]];
          c.i1 = ti;
          c.i2 = tj;
          c.orient_err = static_cast<float>(t);
          c.axes = q;
          if (!sp_.collision_at_axes(q, ws_, c_).empty()) continue;  // tool, head and machine bodies
          c.status = Status::Feasible;
          at[l].emplace(key(ti, tj), static_cast<int>(S[l].size()));
          S[l].push_back(c);
        }
    }
    const std::size_t combos = std::size_t{1} << axes.size();
    const int W = std::max(1, static_cast<int>(opt_.leg_step_cells));
    std::size_t worst = 0;
    for (std::size_t m = 0; m < combos; ++m) {
      auto dir = [&](std::size_t j) { return (m >> j) & 1u ? -1.0 : 1.0; };
      std::vector<std::vector<double>> cost(n);
      std::vector<std::vector<int>> pred(n);
      std::size_t l = 0;
      for (; l < n; ++l) {
        cost[l].assign(S[l].size(), kInf);
        pred[l].assign(S[l].size(), -1);
        bool any = false;
        for (std::size_t j = 0; j < S[l].size(); ++j) {
          const Cell& b = S[l][j];
          if (l == 0) {
            cost[0][j] = opt_.orientation_weight * b.orient_err;
            any = true;
            continue;
          }
          for (int d2 = -W; d2 <= W; ++d2)
            for (int d1 = -W; d1 <= W; ++d1) {
              auto it = at[l - 1].find(key(b.i1 + d1, b.i2 + d2));
              if (it == at[l - 1].end()) continue;
              const std::size_t i = static_cast<std::size_t>(it->second);
              if (!std::isfinite(cost[l - 1][i])) continue;
              const Cell& a = S[l - 1][i];
              bool ok = true;
              for (std::size_t x = 0; x < axes.size() && ok; ++x)
                ok = dir(x) * (b.axes[axes[x]] - a.axes[axes[x]]) >= -hyst;
              if (!ok) continue;
              // Rotary travel, plus the change of tilt and the tilt itself: the smallest, smoothest deviation
              // from the CL axis that keeps the legs monotonic.
              const double v = cost[l - 1][i] + opt_.weight_primary * std::abs(b.r1 - a.r1) +
                               opt_.weight_secondary * std::abs(b.r2 - a.r2) +
                               tilt_step * (std::hypot(b.i1 - a.i1, b.i2 - a.i2) + 0.05 * std::hypot(b.i1, b.i2));
              if (v < cost[l][j]) {
                cost[l][j] = v;
                pred[l][j] = static_cast<int>(i);
                any = true;
              }
            }
        }
        if (!any) break;
      }
      if (l < n) {
        if (l >= worst) worst = l;
        continue;
      }
      std::size_t best = 0;
      for (std::size_t j = 1; j < cost[n - 1].size(); ++j)
        if (cost[n - 1][j] < cost[n - 1][best]) best = j;
      // Keep the chosen cells alive in the layers (their `extra` store) and return pointers to them.
      path.assign(n, nullptr);
      int idx = static_cast<int>(best);
      for (std::size_t kk = n; kk-- > 0;) {
        Cell c = S[kk][static_cast<size_t>(idx)];
        const std::uint64_t slot = key(std::numeric_limits<int>::min() + static_cast<int>(kk), idx);
        path[kk] = &L_[kk].extra.insert_or_assign(slot, c).first->second;
        idx = pred[kk][static_cast<size_t>(idx)];
      }
      return true;
    }
    fail_layer = worst;
    why = fmt::format("no tilt within the cone (step {:.3f} deg) keeps it monotonic", rad2deg(tilt_step));
    return false;
  }

  /// Extra clearance (mm, coarse steps) a path keeps at its first, middle and last points.
  double room(const std::vector<const Cell*>& p) {
    const std::size_t n = p.size();
    double r = 0.0;
    for (double m : {0.5, 1.0, 2.0, 4.0, 8.0, 16.0}) {
      for (std::size_t k : {std::size_t{0}, n / 2, n - 1})
        if (!sp_.free_with_margin(L_[k].cl, *p[k], m, ws_, c_)) return r;
      r = m;
    }
    return r;
  }

  // ---- tier 1: one cell feasible at every point ----
  bool fixed2(std::vector<const Cell*>& path, TierFailure& fail, const kin::Axes* prefer) {
    const std::size_t n = L_.size();
    struct Cand {
      int i1, i2;
      double score, home;
    };
    std::vector<Cand> cands;
    std::size_t furthest = 0;
    const auto rp = sp_.kinematics().rotary_pair();
    // Orientation only (cheap): no cell is materialised until a candidate survives every point. The point
    // that rejected the previous candidate is tested first (move-to-front), so most candidates cost O(1).
    std::vector<std::size_t> oorder;
    for (std::size_t k = 1; k < n; ++k) oorder.push_back(k);
    for (const Cell& c0 : L_[0].cells) {
      double score = c0.orient_err;
      bool ok = true;
      double min_dot = 1.0;  // the worst point's cosine: one arc cosine per candidate, not one per point
      for (std::size_t oi = 0; oi < oorder.size() && ok; ++oi) {
        const std::size_t k = oorder[oi];
        double dot = 1.0;
        const bool in = exact_ ? L_[k].index.count(key(c0.i1, c0.i2)) > 0 : sp_.in_cone_cos(L_[k].cl, c0.r1, c0.r2, dot);
        if (!in) {
          furthest = std::max(furthest, k);
          ok = false;
          std::rotate(oorder.begin(), oorder.begin() + static_cast<std::ptrdiff_t>(oi),
                      oorder.begin() + static_cast<std::ptrdiff_t>(oi) + 1);
        } else {
          min_dot = std::min(min_dot, dot);
        }
      }
      if (ok && !exact_ && oorder.size()) score = std::max(score, static_cast<double>(static_cast<float>(std::acos(min_dot))));
      // Among equally good orientations prefer the winding nearest the previous segment (or home).
      const double home = prefer ? std::abs(c0.r1 - (*prefer)[rp[0]]) + std::abs(c0.r2 - (*prefer)[rp[1]])
                                 : std::abs(c0.r1) + std::abs(c0.r2);
      if (ok) cands.push_back({c0.i1, c0.i2, score, home});
    }
    if (cands.empty()) {
      fail = {Tier::Fixed2, L_[furthest].move, line(furthest),
              fmt::format("orientation: no single orientation stays within the cone from the segment start to this "
                          "point")};
      return false;
    }
    // Orientation closeness first (to 1e-6 rad: windings tie exactly), then nearness to the previous rotaries.
    std::stable_sort(cands.begin(), cands.end(), [](const Cand& a, const Cand& b) {
      if (std::abs(a.score - b.score) > 1e-6) return a.score < b.score;
      return a.home < b.home;
    });
    // Feasibility along the segment, candidates in order. The point that rejected the last candidate is
    // tried first for the next one (move-to-front): neighbouring candidates tend to fail at the same place,
    // so most rejections cost one query instead of a walk along the segment.
    std::vector<std::size_t> order(n);
    std::iota(order.begin(), order.end(), std::size_t{0});
    std::size_t best_reach = 0;
    std::string best_reason;
    for (const Cand& cd : cands) {
      path.assign(n, nullptr);
      std::size_t failed_at = n;
      cspace::Certificate cert;  // one fixed orientation along the segment: neighbours certify each other
      for (std::size_t oi = 0; oi < n; ++oi) {
        const std::size_t k = order[oi];
        Cell* c = cell(k, cd.i1, cd.i2);
        if (!c || !feasible(k, *c, &cert)) {
          failed_at = k;
          std::rotate(order.begin(), order.begin() + static_cast<std::ptrdiff_t>(oi),
                      order.begin() + static_cast<std::ptrdiff_t>(oi) + 1);
          break;
        }
        path[k] = c;
      }
      if (failed_at == n) {
        if (!sp_.options().check_collision) return true;
        // Ties in orientation are broken by clearance: among the candidates about as close to the CL axis
        // (within 0.1 deg) that are feasible everywhere, keep the one with the most room around it.
        // Room is probed at three points per alternative; only the winner is then validated everywhere.
        const double room0 = room(path);
        const Cand* winner = nullptr;
        double best_room = room0;
        int tried = 0;
        for (const Cand* nx = &cd + 1; nx < cands.data() + cands.size() && tried < 8; ++nx) {
          if (nx->score > cd.score + deg2rad(0.1)) break;
          ++tried;
          std::vector<const Cell*> probe(n, nullptr);
          bool ok = true;
          for (std::size_t kk : {std::size_t{0}, n / 2, n - 1}) {
            Cell* c = cell(kk, nx->i1, nx->i2);
            ok = ok && c && feasible(kk, *c);
            if (ok) probe[kk] = c;
          }
          if (!ok) continue;
          const double r = room(probe);
          if (r > best_room) {
            best_room = r;
            winner = nx;
          }
        }
        std::vector<const Cell*> best_path = path;
        if (winner) {
          std::vector<const Cell*> alt(n, nullptr);
          cspace::Certificate cert2;
          bool ok = true;
          for (std::size_t kk = 0; kk < n && ok; ++kk) {
            Cell* c = cell(kk, winner->i1, winner->i2);
            ok = c && feasible(kk, *c, &cert2);
            if (ok) alt[kk] = c;
          }
          if (ok) best_path = alt;
        }
        path = best_path;
        return true;
      }
      // Report the failure of the candidate that got furthest from the segment start (in point order).
      std::size_t reach = 0;
      while (reach < n && path[reach]) ++reach;
      if (reach >= best_reach) {
        Cell* c = cell(failed_at, cd.i1, cd.i2);
        best_reach = failed_at;
        best_reason =
            fmt::format("{}: {} (best fixed orientation {:.3f}, {:.3f} deg)", c ? to_string(c->status) : "orientation",
                        c ? c->detail : "", rad2deg(sp_.r1_of(cd.i1)), rad2deg(sp_.r2_of(cd.i2)));
      }
    }
    fail = {Tier::Fixed2, L_[best_reach].move, line(best_reach), best_reason};
    return false;
  }

  // ---- tier 2: one rotary fixed, the other monotonic ----
  bool fixed1(std::vector<const Cell*>& path, TierFailure& fail, std::string& desc) {
    const std::size_t n = L_.size();
    if (exact_) {
      std::size_t worst = 0;
      std::string why;
      for (int f = 1; f >= 0; --f)
        for (int dir : {+1, -1}) {
          std::size_t fl = 0;
          std::string w;
          auto allowed = [&](const Cell& a, const Cell& b) {
            const long long fa = f == 0 ? a.i1 : a.i2, fb = f == 0 ? b.i1 : b.i2;
            const long long ma = f == 0 ? a.i2 : a.i1, mb = f == 0 ? b.i2 : b.i1;
            return fa == fb && dir * (mb - ma) >= 0;
          };
          if (dp_exact(allowed, path, fl, w)) {
            desc = fmt::format("{} fixed at {:.3f} deg, the other {}", f == 0 ? n1() : n2(),
                               rad2deg(f == 0 ? path[0]->r1 : path[0]->r2), dir > 0 ? "rising" : "falling");
            return true;
          }
          if (fl >= worst) {
            worst = fl;
            why = w;
          }
        }
      fail = {Tier::Fixed1, L_[worst].move, line(worst), why};
      return false;
    }
    std::size_t furthest = 0;
    std::string furthest_reason = "orientation";
    double best_travel = kInf;
    std::vector<const Cell*> best;
    for (int f = 1; f >= 0; --f) {  // fix the secondary first (e.g. the tilt), then the primary
      // Candidate fixed values: present at the first point, closest orientation first. Later points are
      // scanned lazily along the moving axis (no per-point cell lists, so no cap can hide a cell).
      std::unordered_map<int, double> first_err;
      for (const Cell& c : L_[0].cells) {
        const int v = f == 0 ? c.i1 : c.i2;
        auto it = first_err.find(v);
        if (it == first_err.end() || c.orient_err < it->second) first_err[v] = c.orient_err;
      }
      std::vector<std::pair<double, int>> vals;
      for (const auto& [v, e] : first_err) vals.emplace_back(e, v);
      std::sort(vals.begin(), vals.end());
      if (vals.size() > static_cast<size_t>(opt_.max_fixed_candidates))
        vals.resize(static_cast<size_t>(opt_.max_fixed_candidates));
      const int mlo = f == 0 ? sp_.i2_min() : sp_.i1_min(), mhi = f == 0 ? sp_.i2_max() : sp_.i1_max();
      for (const auto& [e0, v] : vals) {
        for (int dir : {+1, -1}) {
          std::vector<const Cell*> p(n, nullptr);
          int prev = dir > 0 ? mlo : mhi;
          std::size_t k = 0;
          std::string why = "orientation";
          for (; k < n; ++k) {
            Cell* chosen = nullptr;
            bool entered = false;
            for (int m = prev; m >= mlo && m <= mhi; m += dir) {
              Cell* c = f == 0 ? cell(k, v, m) : cell(k, m, v);
              if (!c) {
                if (entered || k > 0) {
                  if (entered) break;  // left the cone's run along the moving axis
                  // before entering: keep scanning, but only within a turn of the previous value
                  if (std::abs(m - prev) * sp_.options().resolution_rad > 2 * kPi) break;
                }
                continue;
              }
              entered = true;
              if (feasible(k, *c)) {
                chosen = c;
                break;
              }
              why = fmt::format("{}: {}", to_string(c->status), c->detail);
            }
            if (!chosen) break;
            p[k] = chosen;
            prev = f == 0 ? chosen->i2 : chosen->i1;
          }
          if (k < n) {
            if (k >= furthest) {
              furthest = k;
              furthest_reason = why;
            }
            continue;
          }
          const double travel = std::abs((f == 0 ? p[n - 1]->r2 - p[0]->r2 : p[n - 1]->r1 - p[0]->r1));
          if (travel < best_travel - 1e-12) {
            best_travel = travel;
            best = p;
            desc = fmt::format("{} fixed at {:.3f} deg, {} {} by {:.3f} deg", f == 0 ? n1() : n2(),
                               rad2deg(f == 0 ? p[0]->r1 : p[0]->r2), f == 0 ? n2() : n1(),
                               dir > 0 ? "rising" : "falling", rad2deg(travel));
          }
        }
        if (!best.empty()) break;  // candidates are in order of orientation closeness
      }
    }
    if (!best.empty()) {
      path = best;
      return true;
    }
    fail = {Tier::Fixed1, L_[furthest].move, line(furthest), furthest_reason};
    return false;
  }

  // ---- tier 3: both rotaries monotonic (reachability through Pareto staircases) ----
  bool monotonic(std::vector<const Cell*>& path, TierFailure& fail, std::string& desc) {
    const std::size_t n = L_.size();
    if (exact_) {
      std::size_t worst = 0;
      std::string why;
      for (int d1 : {+1, -1})
        for (int d2 : {+1, -1}) {
          std::size_t fl = 0;
          std::string w;
          auto allowed = [&](const Cell& a, const Cell& b) {
            return d1 * (static_cast<long long>(b.i1) - a.i1) >= 0 && d2 * (static_cast<long long>(b.i2) - a.i2) >= 0;
          };
          if (dp_exact(allowed, path, fl, w)) {
            desc =
                fmt::format("{} {}, {} {}", n1(), d1 > 0 ? "rising" : "falling", n2(), d2 > 0 ? "rising" : "falling");
            return true;
          }
          if (fl >= worst) {
            worst = fl;
            why = w;
          }
        }
      fail = {Tier::Monotonic, L_[worst].move, line(worst), why};
      return false;
    }
    std::size_t furthest = 0;
    std::string furthest_reason = "orientation";
    double best_travel = kInf;
    for (int d1 : {+1, -1})
      for (int d2 : {+1, -1}) {
        struct Step {
          long long a, b;
          Cell* cell;
          int pred;  // index into the previous staircase
        };
        std::vector<std::vector<Step>> stair(n);
        std::size_t k = 0;
        std::string why = "orientation";
        for (; k < n; ++k) {
          // Rows by b (ascending), a ascending inside a row.
          std::vector<std::pair<std::pair<long long, long long>, Cell*>> cells;
          cells.reserve(L_[k].cells.size());
          for (Cell& c : L_[k].cells)
            cells.push_back({{static_cast<long long>(d2) * c.i2, static_cast<long long>(d1) * c.i1}, &c});
          std::sort(cells.begin(), cells.end(), [](const auto& x, const auto& y) { return x.first < y.first; });
          const auto& prev = k ? stair[k - 1] : std::vector<Step>{};
          std::size_t pi = 0;
          long long lb = std::numeric_limits<long long>::max();  // min a over prev staircase with b' <= b
          int lb_idx = -1;
          long long cur_min_a = std::numeric_limits<long long>::max();
          for (std::size_t i = 0; i < cells.size();) {
            const long long b = cells[i].first.first;
            std::size_t j = i;
            while (j < cells.size() && cells[j].first.first == b) ++j;
            while (pi < prev.size() && prev[pi].b <= b) {
              if (prev[pi].a < lb) {
                lb = prev[pi].a;
                lb_idx = static_cast<int>(pi);
              }
              ++pi;
            }
            if (k == 0) lb = std::numeric_limits<long long>::min();
            if (k == 0 || lb_idx >= 0) {
              for (std::size_t t = i; t < j; ++t) {
                const long long a = cells[t].first.second;
                if (a < lb) continue;
                if (a >= cur_min_a) break;  // dominated by a reachable cell of a lower row
                if (feasible(k, *cells[t].second)) {
                  stair[k].push_back({a, b, cells[t].second, lb_idx});
                  cur_min_a = a;
                  break;
                }
                why = fmt::format("{}: {}", to_string(cells[t].second->status), cells[t].second->detail);
              }
            }
            i = j;
          }
          if (stair[k].empty()) break;
        }
        if (k < n) {
          if (k >= furthest) {
            furthest = k;
            furthest_reason = why;
          }
          continue;
        }
        // Any final staircase cell is reachable; take the one with the least travel.
        for (std::size_t e = 0; e < stair[n - 1].size(); ++e) {
          std::vector<const Cell*> p(n);
          int idx = static_cast<int>(e);
          for (std::size_t kk = n; kk-- > 0;) {
            p[kk] = stair[kk][static_cast<size_t>(idx)].cell;
            idx = stair[kk][static_cast<size_t>(idx)].pred;
          }
          const double travel = opt_.weight_primary * std::abs(p[n - 1]->r1 - p[0]->r1) +
                                opt_.weight_secondary * std::abs(p[n - 1]->r2 - p[0]->r2);
          if (travel < best_travel - 1e-12) {
            best_travel = travel;
            path = p;
            desc = fmt::format("{} {} by {:.3f} deg, {} {} by {:.3f} deg", n1(), d1 > 0 ? "rising" : "falling",
                               rad2deg(std::abs(p[n - 1]->r1 - p[0]->r1)), n2(), d2 > 0 ? "rising" : "falling",
                               rad2deg(std::abs(p[n - 1]->r2 - p[0]->r2)));
          }
        }
      }
    if (std::isfinite(best_travel)) return true;
    fail = {Tier::Monotonic, L_[furthest].move, line(furthest), furthest_reason};
    return false;
  }

  // ---- tier 4: least weighted rotary travel, bounded step per point ----
  bool shortest(std::vector<const Cell*>& path, TierFailure& fail, std::string& desc) {
    const std::size_t n = L_.size();
    const double res = sp_.options().resolution_rad;
    // Exact orientations (cone 0) must be free to turn fast near the singularity: no default bound there.
    const double max_step = opt_.max_step_rad > 0 ? opt_.max_step_rad : exact_ ? kPi : 20.0 * res;
    const std::size_t beam = 256;
    if (exact_) {
      std::size_t fl = 0;
      std::string w;
      auto allowed = [&](const Cell& a, const Cell& b) {
        return std::abs(b.r1 - a.r1) <= max_step + 1e-12 && std::abs(b.r2 - a.r2) <= max_step + 1e-12;
      };
      if (!dp_exact(allowed, path, fl, w)) {
        fail = {Tier::Shortest, L_[fl].move, line(fl), w};
        return false;
      }
      double travel = 0;
      for (std::size_t k = 1; k < n; ++k)
        travel += std::abs(path[k]->r1 - path[k - 1]->r1) + std::abs(path[k]->r2 - path[k - 1]->r2);
      desc = fmt::format("rotary travel {:.3f} deg along continuous IK branches", rad2deg(travel));
      return true;
    }
    struct State {
      Cell* cell;
      double cost;
      int pred;
    };
    std::vector<std::vector<State>> S(n);
    for (std::size_t k = 0; k < n; ++k) {
      std::vector<std::pair<double, std::pair<Cell*, int>>> tent;  // tentative cost, cell, pred
      tent.reserve(L_[k].cells.size());
      if (k == 0) {
        for (Cell& c : L_[0].cells) tent.push_back({opt_.orientation_weight * c.orient_err, {&c, -1}});
      } else if (exact_ || S[k - 1].size() * L_[k].cells.size() <= 200000) {
        // Each cell's best predecessor on its own (in parallel), then collected in cell order.
        auto& cells = L_[k].cells;
        std::vector<std::pair<double, int>> best(cells.size(), {kInf, -1});
        const auto& prev = S[k - 1];
        parallel_indices(cells.size(), [&](std::size_t j) {
          const Cell& c = cells[j];
          for (std::size_t p = 0; p < prev.size(); ++p) {
            const Cell* pc = prev[p].cell;
            const double d1 = std::abs(c.r1 - pc->r1), d2 = std::abs(c.r2 - pc->r2);
            if (d1 > max_step + 1e-12 || d2 > max_step + 1e-12) continue;
            const double v = prev[p].cost + opt_.weight_primary * d1 + opt_.weight_secondary * d2;
            if (v < best[j].first) best[j] = {v, static_cast<int>(p)};
          }
        });
        for (std::size_t j = 0; j < cells.size(); ++j)
          if (best[j].second >= 0)
            tent.push_back({best[j].first + opt_.orientation_weight * cells[j].orient_err, {&cells[j], best[j].second}});
      } else {
        distance_transform(S[k - 1], L_[k], max_step, res, tent);
      }
      std::sort(tent.begin(), tent.end(), [](const auto& x, const auto& y) { return x.first < y.first; });
      // The beam: the cheapest feasible cells. Evaluated in parallel blocks of exactly as many cells as the beam
      // still lacks, so the cells evaluated (and the counters) are those of a serial scan, at any thread count.
      for (std::size_t next = 0; next < tent.size() && S[k].size() < beam;) {
        const std::size_t b = next, e = std::min(tent.size(), next + (beam - S[k].size()));
        // The beam revisits the same cells point after point: their clearance certificates spare most queries.
        certs_.reserve();
        parallel_items(e - b, c_, [&](std::size_t i, geom::QueryWorkspace& ws, cspace::Counters& cc) {
          certs_.evaluate(L_[k].cl, *tent[b + i].second.first, ws, cc);
        });
        for (std::size_t i = b; i < e; ++i)
          if (tent[i].second.first->status == Status::Feasible) S[k].push_back({tent[i].second.first, tent[i].first, tent[i].second.second});
        next = e;
      }
      if (S[k].empty()) {
        fail = {Tier::Shortest, L_[k].move, line(k),
                fmt::format("no feasible cell within a rotary step of {:.2f} deg of the previous point",
                            rad2deg(max_step))};
        return false;
      }
    }
    int idx = 0;
    for (std::size_t e = 1; e < S[n - 1].size(); ++e)
      if (S[n - 1][e].cost < S[n - 1][static_cast<size_t>(idx)].cost) idx = static_cast<int>(e);
    path.assign(n, nullptr);
    for (std::size_t k = n; k-- > 0;) {
      path[k] = S[k][static_cast<size_t>(idx)].cell;
      idx = S[k][static_cast<size_t>(idx)].pred;
    }
    double travel = 0;
    for (std::size_t k = 1; k < n; ++k)
      travel += std::abs(path[k]->r1 - path[k - 1]->r1) + std::abs(path[k]->r2 - path[k - 1]->r2);
    desc = fmt::format("rotary travel {:.3f} deg (steps bounded by {:.2f} deg)", rad2deg(travel), rad2deg(max_step));
    return true;
  }

 private:
  /// Windowed L1 distance transform of the previous states' costs onto the grid, separable in the two
  /// rotaries: D(c) = min over |di1|,|di2| <= W of cost(p) + w1 |dr1| + w2 |dr2|.
  template <typename PrevStates>
  void distance_transform(const PrevStates& prev, Layer& cur, double max_step, double res,
                          std::vector<std::pair<double, std::pair<Cell*, int>>>& tent) {
    int lo1 = std::numeric_limits<int>::max(), hi1 = std::numeric_limits<int>::min();
    int lo2 = lo1, hi2 = hi1;
    for (const Cell& c : cur.cells) {
      lo1 = std::min(lo1, c.i1);
      hi1 = std::max(hi1, c.i1);
      lo2 = std::min(lo2, c.i2);
      hi2 = std::max(hi2, c.i2);
    }
    const int W = static_cast<int>(std::floor(max_step / res + 1e-9));
    lo1 -= W;
    hi1 += W;
    lo2 -= W;
    hi2 += W;
    const int n1 = hi1 - lo1 + 1, n2 = hi2 - lo2 + 1;
    std::vector<double> f(static_cast<size_t>(n1) * n2, kInf);
    std::vector<int> src(static_cast<size_t>(n1) * n2, -1);
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
    // 1-D windowed min of g(j) + w |i - j| along a line, via two monotone deques.
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
      std::vector<double> out(static_cast<size_t>(len), kInf);
      std::vector<int> arg(static_cast<size_t>(len), -1);
      std::deque<int> dq;
      for (int i = lo; i <= hi; ++i) {  // from the left: min_{i-W<=j<=i} g(j) - w j, + w i
        const double gi = get(i) - w * i;
        while (!dq.empty() && get(dq.back()) - w * dq.back() >= gi) dq.pop_back();
        dq.push_back(i);
        while (dq.front() < i - W) dq.pop_front();
        const double v = get(dq.front()) - w * dq.front() + w * i;
        if (v < out[static_cast<size_t>(i)]) {
          out[static_cast<size_t>(i)] = v;
          arg[static_cast<size_t>(i)] = dq.front();
        }
      }
      dq.clear();
      for (int i = hi; i >= lo; --i) {  // from the right: min_{i<=j<=i+W} g(j) + w j, - w i
        const double gi = get(i) + w * i;
        while (!dq.empty() && get(dq.back()) + w * dq.back() >= gi) dq.pop_back();
        dq.push_back(i);
        while (dq.front() > i + W) dq.pop_front();
        const double v = get(dq.front()) + w * dq.front() - w * i;
        if (v < out[static_cast<size_t>(i)]) {
          out[static_cast<size_t>(i)] = v;
          arg[static_cast<size_t>(i)] = dq.front();
        }
      }
      for (int i = lo; i <= hi; ++i)
        put(i, out[static_cast<size_t>(i)],
            arg[static_cast<size_t>(i)] >= 0 ? get_src(arg[static_cast<size_t>(i)]) : -1);
    };
    const double w1 = opt_.weight_primary * res, w2 = opt_.weight_secondary * res;
    std::vector<double> g(f.size(), kInf);
    std::vector<int> gsrc(f.size(), -1);
    // Rows, then columns: each line is independent (in parallel).
    parallel_indices(static_cast<std::size_t>(n2), [&](std::size_t bi) {
      const int b = static_cast<int>(bi);
      pass(
          n1, [&](int a) { return f[at(a, b)]; }, [&](int a) { return src[at(a, b)]; },
          [&](int a, double v, int s) {
            g[at(a, b)] = v;
            gsrc[at(a, b)] = s;
          },
          w1);
    });
    std::vector<double> D(f.size(), kInf);
    std::vector<int> dsrc(f.size(), -1);
    parallel_indices(static_cast<std::size_t>(n1), [&](std::size_t ai) {
      const int a = static_cast<int>(ai);
      pass(
          n2, [&](int b) { return g[at(a, b)]; }, [&](int b) { return gsrc[at(a, b)]; },
          [&](int b, double v, int s) {
            D[at(a, b)] = v;
            dsrc[at(a, b)] = s;
          },
          w2);
    });
    for (Cell& c : cur.cells) {
      const size_t i = at(c.i1 - lo1, c.i2 - lo2);
      if (std::isfinite(D[i]) && dsrc[i] >= 0)
        tent.push_back({D[i] + opt_.orientation_weight * c.orient_err, {&c, dsrc[i]}});
    }
  }

  const cspace::Space& sp_;
  const Options& opt_;
  std::vector<Layer>& L_;
  cspace::Counters& c_;
  const cl::Program& prog_;
  bool exact_;
  const kin::Axes* prefer_ = nullptr;
  geom::QueryWorkspace ws_;
  cspace::CertificateStore certs_;  ///< per grid cell, across this segment's points (tier 4's beam)
};

}  // namespace

const char* to_string(Reorientation r) {
  switch (r) {
    case Reorientation::None:
      return "none";
    case Reorientation::Clear:
      return "clear";
    case Reorientation::Collides:
      return "collides";
    case Reorientation::Uncertified:
      return "uncertified";
  }
  return "?";
}

std::string Plan::summary() const {
  std::string s;
  for (std::size_t i = 0; i < segments.size(); ++i) {
    const auto& g = segments[i];
    std::string reo;
    if (g.reorientation != Reorientation::None)
      reo = std::string("; reorientation into it: ") + to_string(g.reorientation) +
            (g.reorientation_detail.empty() ? "" : ": " + g.reorientation_detail);
    s += fmt::format("segment {} (CL lines {}-{}): {} — {}{}\n", i + 1, g.first_line, g.last_line, to_string(g.tier),
                     g.description, reo);
    for (const auto& f : g.failures)
      s += fmt::format("    tier {} failed at CL line {}: {}\n", static_cast<int>(f.tier), f.line, f.reason);
    if (!g.legs.empty()) s += "    legs: " + g.legs + "\n";
    if (g.approach_moves_replaced)
      s += fmt::format("    approach/retract: {} move(s) along the chosen tool axis\n", g.approach_moves_replaced);
    if (g.swept_collisions || g.swept_uncertified)
      s += fmt::format("    swept: {} move(s) collide, {} uncertified (first into CL line {}: {})\n", g.swept_collisions,
                       g.swept_uncertified, g.swept_first_line, g.swept_first_detail);
  }
  if (points_beyond_cap)
    s += fmt::format("{} point(s) needed cells beyond the first cells per point: searched their whole cone\n",
                     points_beyond_cap);
  for (const auto& w : warnings) s += "warning: " + w + "\n";
  return s;
}

Planner::Planner(const machine::Machine& machine, std::shared_ptr<const kin::Kinematics> kinematics,
                 const geom::Scene* scene, const geom::ToolShape* tool, Options options, const geom::Scene* head)
    : machine_(machine),
      kin_(kinematics),
      space_(kinematics, scene, tool, options.cspace, head),
      opt_(std::move(options)) {}

bool Planner::along_chosen_axis(const cl::Program& cl, Plan& plan, std::size_t m, std::size_t ref) const {
  // The CL values decide whether `m` is an approach (retract) along the axis of `ref`.
  const cl::Move& orig_m = cl.moves[m];
  const Eigen::Vector3d cl_ref_tip = cl.moves[ref].tip_in_part_mm, cl_ref_axis = cl.moves[ref].axis_in_part.normalized();
  const Eigen::Vector3d d = orig_m.tip_in_part_mm - cl_ref_tip;
  const double len = d.norm();
  constexpr double kAxialRad = 1e-3;  // CL files print 4-5 decimals: far below this
  if (len < 1e-6 || d.dot(cl_ref_axis) < len * std::cos(kAxialRad)) return false;
  if (orig_m.axis_in_part.normalized().dot(cl_ref_axis) < std::cos(kAxialRad)) return false;
  const kin::Posed ref_pose = kin_->forward(plan.axes[ref]);
  if (ref_pose.axis.dot(cl_ref_axis) > 1.0 - 1e-12 && (ref_pose.tip_mm - cl_ref_tip).norm() < 1e-9) return false;
  kin::Axes q = plan.axes[ref];
  const kin::Posed target{ref_pose.tip_mm + len * ref_pose.axis, ref_pose.axis};
  if (!kin_->solve_for_rotaries(target, q) || !kin_->check_limits(q).empty() || !kin_->passive_violation(q).empty())
    return false;
  plan.axes[m] = q;
  const kin::Posed tp = kin_->forward(q);
  plan.program.moves[m].tip_in_part_mm = tp.tip_mm;
  plan.program.moves[m].axis_in_part = tp.axis;
  plan.replaced_moves.push_back(m);
  return true;
}


Plan Planner::run(const cl::Program& program) const {
  const auto t0 = std::chrono::steady_clock::now();
  Plan plan;
  plan.program = program;
  plan.axes.assign(program.moves.size(), kin::Axes::Zero());
  const auto& moves = program.moves;
  const bool exact = space_.options().cone_rad <= 0;
  // Segments: a rapid (or the first move) starts one; the feed moves after it continue it.
  std::vector<std::pair<std::size_t, std::size_t>> segs;
  for (std::size_t i = 0; i < moves.size(); ++i) {
    if (i == 0 || moves[i].kind == cl::MotionKind::Rapid)
      segs.emplace_back(i, i);
    else
      segs.back().second = i;
  }
  std::vector<char> swept_ok(moves.size(), 0);  // moves certified free by a segment's own swept check
  for (const auto& [s, e] : segs) {
    std::vector<Layer> layers(e - s + 1);
    // Only the first point's cells are needed by tier 1 (the others are tested cell by cell); the rest
    // are enumerated when a later tier needs them, or for the per-point feasibility check in exact mode.
    auto enumerate_layer = [&](std::size_t k, std::size_t cap, cspace::Counters& counters) {
      Layer& l = layers[k];
      space_.enumerate(l.cl, l.cells, cap, counters);
      l.truncated = l.cells.size() >= cap;
      l.index.clear();
      if (exact)
        for (Cell& c : l.cells) {
          c.i1 = static_cast<int>(std::lround(c.r1 / kExactKeyRad));
          c.i2 = static_cast<int>(std::lround(c.r2 / kExactKeyRad));
        }
      for (std::size_t j = 0; j < l.cells.size(); ++j)
        l.index.emplace(key(l.cells[j].i1, l.cells[j].i2), static_cast<int>(j));
    };
    for (std::size_t k = 0; k < layers.size(); ++k) {
      layers[k].move = s + k;
      layers[k].cl = {moves[s + k].tip_in_part_mm, moves[s + k].axis_in_part.normalized()};
      // Tier 1 takes its candidates from the first point: give it a much larger share.
      const bool pin = k == 0 && s == 0 && opt_.start_rotaries.has_value();
      if ((k == 0 && !pin) || exact)
        enumerate_layer(k, k == 0 ? 64 * opt_.max_cells_per_point : opt_.max_cells_per_point, plan.counters);
    }
    if (exact) {
      // At a singular point the primary rotary is free: offer every primary that a neighbouring regular
      // point uses, so that continuous (flip-free) paths can pass straight through the singularity.
      for (std::size_t k = 0; k < layers.size(); ++k) {
        auto& cells = layers[k].cells;
        if (std::none_of(cells.begin(), cells.end(), [](const Cell& c) { return c.singular; })) continue;
        std::vector<double> primaries;
        for (long d = 1; d < static_cast<long>(layers.size()) && primaries.size() < 64; ++d)
          for (long kk : {static_cast<long>(k) - d, static_cast<long>(k) + d}) {
            if (kk < 0 || kk >= static_cast<long>(layers.size())) continue;
            bool regular = false;
            for (const Cell& c : layers[static_cast<size_t>(kk)].cells)
              if (!c.singular) {
                primaries.push_back(c.r1);
                regular = true;
              }
            if (regular && d > 1) d = static_cast<long>(layers.size());  // nearest regular layers on each side only
          }
        std::vector<Cell> out;
        for (const Cell& c : cells) {
          // No regular neighbour (e.g. a whole segment along the primary axis): the IK's own choice stands.
          if (!c.singular || primaries.empty()) {
            out.push_back(c);
            continue;
          }
          for (double r1 : primaries) {
            Cell n = c;
            n.r1 = r1;
            n.i1 = static_cast<int>(std::lround(r1 / kExactKeyRad));
            n.status = Status::Unknown;
            if (std::none_of(out.begin(), out.end(), [&](const Cell& o) { return o.i1 == n.i1 && o.i2 == n.i2; }))
              out.push_back(n);
          }
        }
        cells = std::move(out);
        layers[k].index.clear();
        for (std::size_t j = 0; j < cells.size(); ++j)
          layers[k].index.emplace(key(cells[j].i1, cells[j].i2), static_cast<int>(j));
      }
    }
    if (s == 0 && opt_.start_rotaries) {
      // Windowed planning: the first point keeps the rotaries the previous window ended at, as its only cell.
      Layer& l = layers[0];
      const double kr = exact ? kExactKeyRad : space_.options().resolution_rad;
      Cell c;
      c.r1 = (*opt_.start_rotaries)[0];
      c.r2 = (*opt_.start_rotaries)[1];
      c.i1 = static_cast<int>(std::lround(c.r1 / kr));
      c.i2 = static_cast<int>(std::lround(c.r2 / kr));
      (void)space_.in_cone(l.cl, c.r1, c.r2, &c.orient_err);
      l.cells.assign(1, c);
      l.index.clear();
      l.index.emplace(key(c.i1, c.i2), 0);
      l.extra.clear();
      l.truncated = false;
      l.pinned = true;
    }
    // Replaces a truncated cell list with every cell of the cone, keeping what was evaluated already.
    auto extend_layer = [&](std::size_t k) {
      Layer& l = layers[k];
      std::unordered_map<std::uint64_t, Cell> keep;
      keep.swap(l.extra);
      for (Cell& c : l.cells)
        if (c.status != Status::Unknown) keep.insert_or_assign(key(c.i1, c.i2), std::move(c));
      enumerate_layer(k, std::numeric_limits<std::size_t>::max(), plan.counters);
      for (auto& [kk, c] : keep) {
        if (auto it = l.index.find(kk); it != l.index.end()) {
          if (c.status != Status::Orientation) l.cells[static_cast<size_t>(it->second)] = c;
        } else {
          l.extra.emplace(kk, std::move(c));
        }
      }
    };
    Search search(space_, opt_, layers, plan.counters, program);
    auto check_points = [&]() {
      // Every point needs at least one feasible cell; otherwise say which constraint emptied it. A point is
      // called infeasible only once every cell of its cone has been shown infeasible: a truncated list whose
      // cells all fail is first extended to the whole cone.
      // In parallel first: each point's cells in order up to its first feasible one (what the loop below needs).
      parallel_items(layers.size(), plan.counters, [&](std::size_t k, geom::QueryWorkspace& ws, cspace::Counters& c) {
        for (Cell& cell : layers[k].cells) {
          space_.evaluate(layers[k].cl, cell, ws, c);
          if (cell.status == Status::Feasible) break;
        }
      });
      for (std::size_t k = 0; k < layers.size(); ++k) {
        bool any = false;
        int n_stroke = 0, n_coll = 0;
        std::string example;
        for (bool extended = false;;) {
          n_stroke = n_coll = 0;
          for (Cell& c : layers[k].cells) {
            if (search.feasible(k, c)) {
              any = true;
              break;
            }
            (c.status == Status::Stroke ? n_stroke : n_coll)++;
            if (example.empty()) example = c.detail;
          }
          if (any || extended || !layers[k].truncated) break;
          extend_layer(k);
          ++plan.points_beyond_cap;
          extended = true;
          // The whole cone, nearest first, in parallel blocks; stop after the first block holding a feasible cell.
          auto& cells = layers[k].cells;
          constexpr std::size_t kBlock = 1024;
          for (std::size_t b = 0; b < cells.size(); b += kBlock) {
            const std::size_t e = std::min(cells.size(), b + kBlock);
            parallel_items(e - b, plan.counters, [&](std::size_t i, geom::QueryWorkspace& ws, cspace::Counters& c) {
              space_.evaluate(layers[k].cl, cells[b + i], ws, c);
            });
            if (std::any_of(cells.begin() + static_cast<std::ptrdiff_t>(b), cells.begin() + static_cast<std::ptrdiff_t>(e),
                            [](const Cell& x) { return x.status == Status::Feasible; }))
              break;
          }
        }
        if (any) continue;
        const cl::Move& mv = moves[layers[k].move];
        std::string why;
        if (layers[k].cells.empty())
          why = "orientation: no rotary cell gives a tool axis within the cone (the machine cannot reach this axis" +
                std::string(exact ? ")" : "; try a finer --resolution or a larger --cone)");
        else if (n_coll == 0)
          why = fmt::format("stroke: all {} cells in the cone break a limit (e.g. {})", n_stroke, example);
        else if (n_stroke == 0)
          why = fmt::format("collision: all {} cells in the cone collide (e.g. {})", n_coll, example);
        else
          why = fmt::format("stroke ({} cells) and collision ({} cells), e.g. {}", n_stroke, n_coll, example);
        // The nearest feasible cell beyond the cone, for the user to decide.
        std::string nearest = "none found within 90 deg";
        for (double cone_deg : {5.0, 15.0, 45.0, 90.0}) {
          cspace::Options wider = space_.options();
          if (wider.cone_rad >= deg2rad(cone_deg)) continue;
          wider.cone_rad = deg2rad(cone_deg);
          wider.min_tilt_rad = 0;
          wider.resolution_rad = std::max(wider.resolution_rad, deg2rad(1.0));
          const cspace::Space wide(kin_, nullptr, nullptr, wider);
          std::vector<Cell> cells;
          cspace::Counters dummy;
          wide.enumerate(layers[k].cl, cells, 20000, dummy);
          geom::QueryWorkspace ws;
          bool found = false;
          for (Cell& c : cells) {
            // Re-check with the real space (collision included) on the wider grid.
            space_.evaluate(layers[k].cl, c, ws, plan.counters);
            if (c.status == Status::Feasible) {
              nearest = fmt::format("({:.3f}, {:.3f}) deg, {:.2f} deg from the CL axis", rad2deg(c.r1), rad2deg(c.r2),
                                    rad2deg(c.orient_err));
              found = true;
              break;
            }
          }
          if (found) break;
        }
        throw InputError(
            SourceLoc{program.file, mv.line, 0},
            fmt::format("no feasible orientation at CL point ({:.4f}, {:.4f}, {:.4f}) axis ({:.5f}, {:.5f}, "
                        "{:.5f}): {}; nearest feasible cell: {}",
                        mv.tip_in_part_mm.x(), mv.tip_in_part_mm.y(), mv.tip_in_part_mm.z(), mv.axis_in_part.x(),
                        mv.axis_in_part.y(), mv.axis_in_part.z(), why, nearest));
      }
    };
    SegmentReport rep;
    rep.first_move = s;
    rep.last_move = e;
    rep.first_line = moves[s].line;
    rep.last_line = moves[e].line;
    std::vector<const Cell*> path;
    TierFailure f;
    std::string desc;
    const kin::Axes* prefer = plan.segments.empty() ? nullptr : &plan.axes[segs[plan.segments.size() - 1].second];
    search.prefer(prefer);
    bool listed = false;  // the full (capped) cell lists of points after the first are in the layers
    auto cascade = [&]() {
    rep.failures.clear();
    desc.clear();
    if (search.fixed2(path, f, prefer)) {
      rep.tier = Tier::Fixed2;
      desc = fmt::format("rotaries fixed at {} = {:.3f} deg, {} = {:.3f} deg", search.n1(), rad2deg(path[0]->r1),
                         search.n2(), rad2deg(path[0]->r2));
    } else {
      rep.failures.push_back(f);
      if (!exact && !listed)
        // Every layer on its own (in parallel): the same lists, counters summed.
        parallel_items(layers.size() - 1, plan.counters, [&](std::size_t i, geom::QueryWorkspace&, cspace::Counters& cc) {
          const std::size_t k = i + 1;
          // Keep what tier 1 already evaluated (the cache) when the full cell list arrives.
          std::unordered_map<std::uint64_t, Cell> keep;
          keep.swap(layers[k].extra);
          enumerate_layer(k, opt_.max_cells_per_point, cc);
          for (auto& [kk, c] : keep) {
            if (auto it = layers[k].index.find(kk); it != layers[k].index.end()) {
              if (c.status != Status::Orientation) layers[k].cells[static_cast<size_t>(it->second)] = c;
            } else {
              layers[k].extra.emplace(kk, std::move(c));
            }
          }
        });
      listed = true;
      check_points();
      if (search.fixed1(path, f, desc)) {
        rep.tier = Tier::Fixed1;
      } else {
        rep.failures.push_back(f);
        if (search.monotonic(path, f, desc)) {
          rep.tier = Tier::Monotonic;
        } else {
          rep.failures.push_back(f);
          bool found = search.shortest(path, f, desc);
          if (!found && !exact) {
            // The tiers searched truncated cell lists: search the whole cones before giving up.
            std::size_t n_ext = 0;
            for (std::size_t k = 0; k < layers.size(); ++k)
              if (layers[k].truncated) {
                extend_layer(k);
                ++n_ext;
              }
            plan.points_beyond_cap += n_ext;
            if (n_ext) found = search.shortest(path, f, desc);
          }
          if (!found) {
            throw InputError(SourceLoc{program.file, f.line, 0},
                             fmt::format("no rotary path through the feasible cells of segment CL lines {}-{}: {}",
                                         rep.first_line, rep.last_line, f.reason));
          }
          rep.tier = Tier::Shortest;
        }
      }
    }
    };
    cascade();
    // Between the points: a move whose sweep collides rules out the cell it leads into (conservative: that cell
    // might be fine from another predecessor), and the tiers run again on what is left. A few rounds at most;
    // what remains is reported by the final swept check.
    std::vector<Cell> kept;  // outlives `path` when it points here
    if (space_.checks_collision() && path.size() > 1) {
      geom::QueryWorkspace ws;
      for (int round = 0; round < 4; ++round) {
        std::vector<std::size_t> bad, free_into;
        for (std::size_t k = 0; k + 1 < path.size(); ++k) {
          const auto st =
              space_.swept(path[k]->axes, path[k + 1]->axes, cspace::SweepMode::Cutting, ws, plan.counters).status;
          if (st == cspace::SweepStatus::Collides) bad.push_back(k + 1);
          if (st == cspace::SweepStatus::Free) free_into.push_back(k + 1);
        }
        if (bad.empty()) {
          // The final check need not repeat these (unless an approach/retract below moves an end).
          for (std::size_t k : free_into) swept_ok[layers[k].move] = 1;
          break;
        }
        // Keep the current answer: if nothing is left without those cells, it stands (with its warning).
        kept.clear();
        for (const Cell* c : path) kept.push_back(*c);
        const Tier kept_tier = rep.tier;
        const std::vector<TierFailure> kept_failures = rep.failures;
        const std::string kept_desc = desc;
        for (std::size_t k : bad) {
          Cell* c = const_cast<Cell*>(path[k]);  // the layers own the cells; the path points into them
          c->status = Status::Collision;
          c->detail = "the move into it from the previous point collides (swept)";
        }
        try {
          cascade();
        } catch (const InputError&) {
          for (std::size_t k = 0; k < kept.size(); ++k) path[k] = &kept[k];
          rep.tier = kept_tier;
          rep.failures = kept_failures;
          desc = kept_desc;
          break;
        }
      }
    }
    rep.description = desc;
    if (!opt_.monotone_axes.empty() && layers.size() > 2) {
      // Which of the counted axes reverse along the chosen path, and where first?
      constexpr double kLegHyst = 1e-4;  // mm: far below a lost motion, far above round-off
      auto reversals = [&](const std::vector<const Cell*>& pth, std::vector<int>& which, std::size_t& where) {
        which.clear();
        where = pth.size();
        for (int ax : opt_.monotone_axes) {
          int d = 0;
          double ext = pth[0]->axes[ax];
          for (std::size_t k = 1; k < pth.size(); ++k) {
            const double v = pth[k]->axes[ax];
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
      };
      std::vector<int> rev;
      std::size_t where = 0;
      reversals(path, rev, where);
      if (rev.empty()) {
        rep.legs = "monotonic";
      } else {
        std::vector<const Cell*> mono;
        std::size_t fl = 0;
        std::string why;
        std::string names;
        for (int ax : rev) names += (names.empty() ? "" : ", ") + kin_->axes()[static_cast<size_t>(ax)].name;
        const cl::Move& at = moves[layers[where].move];
        // A pinned first point (windowed planning) must keep its rotaries.
        auto keeps_pin = [&] {
          return !layers[0].pinned || (mono[0]->r1 == path[0]->r1 && mono[0]->r2 == path[0]->r2);
        };
        if (!exact &&
            search.legs_tilt(rev, kLegHyst,
                             opt_.tilt_step_rad > 0 ? opt_.tilt_step_rad : space_.options().resolution_rad, path, mono,
                             fl, why) &&
            keeps_pin()) {
          path = mono;
          double max_tilt = 0;
          for (const Cell* c : mono) max_tilt = std::max(max_tilt, static_cast<double>(c->orient_err));
          rep.legs = fmt::format("monotonic: the reversal of {} at CL line {} removed by tilting at most {:.3f} deg",
                                 names, at.line, rad2deg(max_tilt));
          rep.tier = Tier::Shortest;  // the rotaries now follow the tilt refinement
          rep.description = "re-planned inside the cone for monotonic legs (" + rep.description + " before)";
        } else if (exact && search.legs_monotone(rev, kLegHyst, mono, fl, why) && keeps_pin()) {
          path = mono;
          rep.legs = fmt::format("monotonic: the reversal of {} at CL line {} removed", names, at.line);
        } else {
          rep.legs = fmt::format(
              "{} reverses at CL line {} ({:.4f}, {:.4f}, {:.4f}); it cannot be avoided at this cone "
              "(no monotonic path beyond CL line {}: {})",
              names, at.line, at.tip_in_part_mm.x(), at.tip_in_part_mm.y(), at.tip_in_part_mm.z(),
              moves[layers[fl].move].line, why);
        }
      }
    }
    for (std::size_t k = 0; k < layers.size(); ++k) {
      const Cell* c = path[k];
      const std::size_t m = layers[k].move;
      plan.axes[m] = c->axes;
      const kin::Posed tp = kin_->forward(c->axes);
      plan.program.moves[m].tip_in_part_mm = tp.tip_mm;
      plan.program.moves[m].axis_in_part = tp.axis;
    }
    // Approach and retract run along the tool axis: a CL approach (retract) along the CL axis of the point it
    // leads into (out of) follows the chosen axis instead, at the same distance, with that point's rotaries;
    // otherwise the new tilt would be dragged along the old approach line (through the material beside it).
    const bool pinned0 =
        s == 0 && opt_.start_rotaries.has_value() && opt_.start_is_join;  // windowed: move 0 is the previous window's
    const bool open_end = opt_.continues && e + 1 == moves.size();   // windowed: the next window continues it
    if (e > s && !pinned0 && moves[s].kind == cl::MotionKind::Rapid && along_chosen_axis(program, plan, s, s + 1)) {
      ++rep.approach_moves_replaced;
      swept_ok[s + 1] = 0;
    }
    if (e > s + 1 && !open_end && moves[e].kind != cl::MotionKind::Rapid &&
        along_chosen_axis(program, plan, e, e - 1)) {
      ++rep.approach_moves_replaced;
      swept_ok[e] = 0;
    }
    if (e == s && s > 0 && moves[s].kind == cl::MotionKind::Rapid && along_chosen_axis(program, plan, s, s - 1))
      ++rep.approach_moves_replaced;
    plan.segments.push_back(std::move(rep));
  }
  // Every move between points, checked swept: feed blocks, approach and retract, and the reorientation into each
  // segment as the post performs it.
  plan.swept = check_program(space_, machine_, plan.program, plan.axes, plan.counters, &swept_ok);
  std::size_t g = 0;
  for (const SweptHit& h : plan.swept.hits) {
    while (g + 1 < plan.segments.size() && plan.segments[g].last_move < h.move) ++g;
    SegmentReport& rep = plan.segments[g];
    const bool collides = h.result.status == cspace::SweepStatus::Collides;
    if (h.reorientation) {
      if (rep.reorientation == Reorientation::Collides) continue;
      rep.reorientation = collides ? Reorientation::Collides : Reorientation::Uncertified;
      rep.reorientation_detail = h.result.detail;
      plan.warnings.push_back(fmt::format("{}: the reorientation into the segment starting here {} ({})",
                                          SourceLoc{program.file, rep.first_line, 0}.str(),
                                          collides ? "collides" : "cannot be certified free", h.result.detail));
      continue;
    }
    (collides ? rep.swept_collisions : rep.swept_uncertified)++;
    if (rep.swept_collisions + rep.swept_uncertified == 1) {
      rep.swept_first_line = h.line;
      rep.swept_first_detail = h.result.detail;
      plan.warnings.push_back(fmt::format("{}: the move into this point {} between CL points ({}, at {:.0f} % of the move)",
                                          SourceLoc{program.file, h.line, 0}.str(),
                                          collides ? "collides" : "cannot be certified free", h.result.detail,
                                          100.0 * h.result.t));
    }
  }
  if (space_.checks_collision()) {
    const auto rp = kin_->rotary_pair();
    for (std::size_t i = 1; i < plan.segments.size(); ++i) {
      auto& rep = plan.segments[i];
      const kin::Axes &from = plan.axes[plan.segments[i - 1].last_move], &to = plan.axes[rep.first_move];
      if (rep.reorientation == Reorientation::None &&
          (std::abs(from[rp[0]] - to[rp[0]]) > 1e-9 || std::abs(from[rp[1]] - to[rp[1]]) > 1e-9))
        rep.reorientation = Reorientation::Clear;
    }
  }
  plan.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  rusage ru{};
  if (getrusage(RUSAGE_SELF, &ru) == 0) plan.peak_memory_mb = static_cast<double>(ru.ru_maxrss) / 1024.0;
  return plan;
}

SegmentSpace Planner::sample_segment(const cl::Program& program, const Plan& plan, std::size_t segment,
                                     std::size_t max_points) const {
  CSCAM_CHECK(segment < plan.segments.size(), "segment index in range");
  const SegmentReport& rep = plan.segments[segment];
  SegmentSpace out;
  out.segment = segment;
  out.resolution_rad = space_.options().resolution_rad;
  const auto rp = kin_->rotary_pair();
  // The window: the planned path's bounding box, padded, clipped to the grid.
  double lo1 = kInf, hi1 = -kInf, lo2 = kInf, hi2 = -kInf;
  for (std::size_t m = rep.first_move; m <= rep.last_move; ++m) {
    lo1 = std::min(lo1, plan.axes[m][rp[0]]);
    hi1 = std::max(hi1, plan.axes[m][rp[0]]);
    lo2 = std::min(lo2, plan.axes[m][rp[1]]);
    hi2 = std::max(hi2, plan.axes[m][rp[1]]);
    out.path.emplace_back(plan.axes[m][rp[0]], plan.axes[m][rp[1]]);
  }
  const double res = std::max(out.resolution_rad, deg2rad(0.5));
  out.resolution_rad = res;
  const double pad = deg2rad(40.0);
  out.i1_min = std::max(static_cast<int>(std::floor((lo1 - pad) / res)),
                        static_cast<int>(std::ceil(space_.i1_min() * space_.options().resolution_rad / res)));
  out.i1_max = std::min(static_cast<int>(std::ceil((hi1 + pad) / res)),
                        static_cast<int>(std::floor(space_.i1_max() * space_.options().resolution_rad / res)));
  out.i2_min = std::max(static_cast<int>(std::floor((lo2 - pad) / res)),
                        static_cast<int>(std::ceil(space_.i2_min() * space_.options().resolution_rad / res)));
  out.i2_max = std::min(static_cast<int>(std::ceil((hi2 + pad) / res)),
                        static_cast<int>(std::floor(space_.i2_max() * space_.options().resolution_rad / res)));
  const int n1 = out.i1_max - out.i1_min + 1, n2 = out.i2_max - out.i2_min + 1;
  out.status.assign(static_cast<size_t>(std::max(0, n1 * n2)), Status::Feasible);
  // Orientation is judged with at least half a picture cell of slack so the picture is readable at cone 0.
  cspace::Options o = space_.options();
  o.cone_rad = std::max(o.cone_rad, 0.75 * res);
  const cspace::Space pic(kin_, nullptr, nullptr, o);
  geom::QueryWorkspace ws;
  cspace::Counters dummy;
  const std::size_t npts = rep.last_move - rep.first_move + 1;
  const std::size_t step = std::max<std::size_t>(1, npts / std::max<std::size_t>(1, max_points));
  for (std::size_t m = rep.first_move; m <= rep.last_move; m += step) {
    const kin::Posed cl{program.moves[m].tip_in_part_mm, program.moves[m].axis_in_part.normalized()};
    for (int b = 0; b < n2; ++b)
      for (int a = 0; a < n1; ++a) {
        auto& st = out.status[static_cast<size_t>(b) * static_cast<size_t>(n1) + static_cast<size_t>(a)];
        if (st != Status::Feasible) continue;
        Cell c;
        c.r1 = (out.i1_min + a) * res;
        c.r2 = (out.i2_min + b) * res;
        if (!pic.in_cone(cl, c.r1, c.r2, &c.orient_err)) {
          st = Status::Orientation;
          continue;
        }
        space_.evaluate(cl, c, ws, dummy);
        st = c.status;
      }
  }
  return out;
}

}  // namespace cscam::plan
