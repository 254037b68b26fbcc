#pragma once
// Private to src/plan: what the tiers of the planner share. A segment's search is split as Pinocchio splits a
// model from its data: SegmentView holds what does not change during the search (the C-space, the options, the
// program, where the previous segment ended), SegmentCells the per-point cells, evaluated lazily, the counters and
// a query workspace. Each tier is a free function of the two; the layered dynamic programme (forward pass over the
// points, backtrack from the cheapest end) is written once, in LayeredDp, and the exact-orientation search on it
// (dp_exact) serves every tier at cone 0.
#include <fmt/format.h>

#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <tuple>
#include <unordered_map>
#include <utility>
#include <vector>

#include "../parallel.hpp"  // parallel_items, parallel_indices: a kept arena, per-thread query workspaces
#include "cscam/cspace/certificates.hpp"
#include "cscam/kin/track.hpp"
#include "cscam/plan/plan.hpp"

namespace cscam::plan::detail {

using cspace::Cell;
using cspace::Status;
inline constexpr double kInf = std::numeric_limits<double>::infinity();
/// Exact-orientation (cone 0) cells are keyed on a 1e-6 rad lattice so that "the same cell" and
/// "monotonic" mean the same thing as on the grid.
inline constexpr double kExactKeyRad = 1e-6;

inline std::uint64_t key(int i1, int i2) {
  return (static_cast<std::uint64_t>(static_cast<std::uint32_t>(i1)) << 32) | static_cast<std::uint32_t>(i2);
}

/// (i1, i2) key -> position in a layer's cell list, by open addressing in one array: a layer lists thousands of cells
/// near a singular axis, and a node-based map made one allocation per cell (which dominated listing the layers).
class CellIndex {
 public:
  void clear() {
    slots_.clear();
    size_ = 0;
  }
  void reserve(std::size_t n) {
    if (2 * n > slots_.size()) rehash(2 * n);
  }
  /// Adds k -> v unless k is present (as std::unordered_map::emplace).
  void emplace(std::uint64_t k, int v) {
    if (2 * (size_ + 1) > slots_.size()) rehash(2 * (size_ + 1));
    for (std::size_t i = hash(k) & (slots_.size() - 1);; i = (i + 1) & (slots_.size() - 1)) {
      if (slots_[i].value < 0) {
        slots_[i] = {k, v};
        ++size_;
        return;
      }
      if (slots_[i].key == k) return;
    }
  }
  /// The position of k, or -1.
  [[nodiscard]] int find(std::uint64_t k) const {
    if (slots_.empty()) return -1;
    for (std::size_t i = hash(k) & (slots_.size() - 1);; i = (i + 1) & (slots_.size() - 1)) {
      if (slots_[i].value < 0) return -1;
      if (slots_[i].key == k) return slots_[i].value;
    }
  }
  [[nodiscard]] bool contains(std::uint64_t k) const { return find(k) >= 0; }
  [[nodiscard]] std::size_t size() const { return size_; }

 private:
  struct Slot {
    std::uint64_t key = 0;
    int value = -1;  // -1: empty
  };
  static std::size_t hash(std::uint64_t k) {  // a 64-bit finaliser (MurmurHash3's): neighbouring cells spread out
    k ^= k >> 33;
    k *= 0xff51afd7ed558ccdULL;
    k ^= k >> 33;
    return static_cast<std::size_t>(k);
  }
  void rehash(std::size_t want) {
    std::size_t cap = 16;
    while (cap < want) cap *= 2;
    std::vector<Slot> old(cap);
    old.swap(slots_);
    size_ = 0;
    for (const Slot& sl : old)
      if (sl.value >= 0) emplace(sl.key, sl.value);
  }
  std::vector<Slot> slots_;
  std::size_t size_ = 0;
};

/// One CL point of a segment and its orientation cells.
struct Layer {
  std::size_t move = 0;
  kin::Posed cl;
  std::vector<Cell> cells;                        ///< orientation cells, closest first (capped)
  CellIndex index;                                ///< (i1,i2) -> position in cells
  std::unordered_map<std::uint64_t, Cell> extra;  ///< evaluated cells outside the cap
  bool truncated = false;                         ///< `cells` stopped at the cap: the cone holds more
  bool pinned = false;                            ///< Options::start_rotaries: `cells` is that one cell, no other
  /// The post retracts from (approaches) this point along the tool axis to the safe plane (a PKM's segment ends): a
  /// cell from which that retract leaves the machine's reach is out of stroke here.
  bool retract_end = false;
  /// Positions in `cells` by (i2, i1), and where each i2 row starts (plus cells.size()): tier 3's walk, built when
  /// first needed, cleared whenever `cells` is rebuilt.
  std::vector<std::uint32_t> grid_order, row_starts;
};

/// A state of tier 4's beam: a feasible cell, the cost of the best path to it and its predecessor's index.
struct ShortestState {
  Cell* cell;
  double cost;
  int pred;
};

/// What does not change while a segment is searched.
struct SegmentView {
  const cspace::Space& space;
  const Options& options;
  const cl::Program& program;
  const std::shared_ptr<const kin::Kinematics>& kinematics;
  bool exact = false;                 ///< cone 0: the cells are the exact IK solutions
  const kin::Axes* prefer = nullptr;  ///< rotaries the previous segment ended at (tie-break); null: home
  /// The plane z (part frame, mm) a machine without a Z axis retracts to along the tool axis at segment ends
  /// (post.safe_z_mm); NaN when the post retracts along a machine axis instead.
  double retract_plane_z_mm = std::numeric_limits<double>::quiet_NaN();
  /// Names of the primary and secondary rotaries, for reports.
  [[nodiscard]] std::string n1() const;
  [[nodiscard]] std::string n2() const;
  /// The primary and secondary rotary values the segment is entered from: where the previous segment ended, or home.
  [[nodiscard]] std::array<double, 2> entry_rotaries() const;
};

/// The cells of a segment's points as the search evaluates them, its counters and its query workspace.
struct SegmentCells {
  std::vector<Layer> layers;
  cspace::Counters& counters;
  geom::QueryWorkspace ws;
  /// Clearance certificates per grid cell, across this segment's points (tier 4's beam revisits the same cells).
  cspace::CertificateStore certs;
  /// The full (capped) cell lists of the points after the first are in the layers (tier 1 needs only the first's).
  bool listed = false;
  /// Per layer: an earlier answer's move into this point collided between the points, so tier 4 takes every
  /// transition into it only after a swept check (avoid_swept_collisions sets these).
  std::vector<char> swept_layers;
  /// Swept checks of moves into those layers, across the re-searches: (layer, from cell, into cell) -> status.
  std::map<std::tuple<std::size_t, std::uint64_t, std::uint64_t>, cspace::SweepStatus> sweeps;
  /// Tier 4's last forward pass, for a re-search after avoid_swept_collisions flagged more layers: the layers before
  /// the first newly flagged one come out the same (their cells are evaluated already and keep their status), so the
  /// pass resumes there. Valid while the cell lists stay as they were (any re-listing clears it).
  struct ShortestPass {
    std::vector<std::vector<ShortestState>> nodes;  ///< per layer, as LayeredDp leaves them
    std::vector<char> swept_layers;                 ///< the flags the pass ran with
    std::size_t beam_at = 0;                        ///< the beam it kept (its index in tier 4's beam widths)
  };
  std::optional<ShortestPass> last_shortest;
  /// At cone 0, the points along the primary axis were offered the whole turn of the primary (check_points).
  bool singular_turned = false;
  SegmentCells(cspace::Counters& c, const cspace::Space& space) : counters(c), certs(space) {}
};

/// The layers of the moves [first, last]: every point's pose; the first point's cells (a large share: tier 1 takes its
/// candidates there) and, at cone 0, every point's IK cells, singular points offered their neighbours' primaries.
/// With Options::start_rotaries, the program's first point (first == 0) has that one cell only (pinned).
SegmentCells make_cells(const SegmentView& v, std::size_t first, std::size_t last, cspace::Counters& counters);
/// Whether the post can retract from axis values q at layer l along the tool axis to the safe plane (true where
/// it need not: Layer::retract_end unset).
bool retracts(const SegmentView& v, const Layer& l, const kin::Axes& q);
/// For a layer at a segment end (Layer::retract_end): marks an unevaluated cell out of stroke when the tool cannot
/// retract from its pose along the tool axis to the safe plane (kin::retract_along_axis, as the post does).
void mark_retract(const SegmentView& v, const Layer& l, Cell& c);
/// Lists point k's cells afresh, at most `cap` of them.
void enumerate_layer(const SegmentView& v, Layer& l, std::size_t cap, cspace::Counters& counters);
/// Replaces a truncated cell list with every cell of the cone, keeping what was evaluated already.
void extend_layer(const SegmentView& v, SegmentCells& d, std::size_t k);
/// The capped cell lists of every point after the first (in parallel), keeping what tier 1 evaluated.
void list_layers(const SegmentView& v, SegmentCells& d);
/// Every point needs at least one feasible cell: a truncated list whose cells all fail is first extended to the
/// whole cone (counted in `points_beyond_cap`). At cone 0, a point along the primary axis whose cells all fail first
/// gets the whole turn of the primary (every singular point of the segment does, so that one primary can hold across
/// them): returns true then, and the tiers must start again. Throws InputError naming the CL line, the constraint that
/// emptied the cone and the nearest feasible cell beyond it.
bool check_points(const SegmentView& v, SegmentCells& d, std::size_t& points_beyond_cap);

/// The cell (i1, i2) at layer k, created (with its orientation test) if needed; null if outside the cone.
Cell* cell_at(const SegmentView& v, SegmentCells& d, std::size_t k, int i1, int i2);
/// A grid path of a cyclic rotary can be shifted by whole turns without changing a pose or its travel: the shift
/// whose first cell lies nearest where the segment is entered from (the previous segment's end, or home), within the
/// grid and the axis limits. The shifted cells take the originals' collision status (the same physical poses).
void rewind_to_entry(const SegmentView& v, SegmentCells& d, std::vector<const Cell*>& path);
/// Weighted rotary travel along a path, and into its first cell from where the segment is entered (the previous
/// segment's end, or home): how tiers that find several answers of one kind choose between them.
struct PathCost {
  double travel = 0.0, entry = 0.0;
  /// Less travel first; about equal travel (1e-9), then the shorter entry.
  [[nodiscard]] bool better_than(const PathCost& o) const {
    return travel < o.travel - 1e-9 || (travel <= o.travel + 1e-9 && entry < o.entry - 1e-9);
  }
};
PathCost path_cost(const SegmentView& v, const std::vector<const Cell*>& path);
/// Rotary travel into grid index `i` of rotary `j` (0: primary, 1: secondary) from `from_rad` beyond the travel into
/// the nearest winding of the same angle on the grid (whole turns for nothing), rad; 0 where the grid holds no whole
/// turn.
double whole_turns_rad(const cspace::Space& sp, int j, int i, double from_rad);
/// Stroke and collision of a cell of layer k (cached in the cell).
bool feasible(const SegmentView& v, SegmentCells& d, std::size_t k, Cell& c, cspace::Certificate* cert = nullptr);
/// CL line of layer k.
inline int line_of(const SegmentView& v, const SegmentCells& d, std::size_t k) {
  return v.program.moves[d.layers[k].move].line;
}
/// Extra clearance (mm, coarse steps) a path keeps at its first, middle and last points.
double room(const SegmentView& v, SegmentCells& d, const std::vector<const Cell*>& path);

/// The layered dynamic programme. Node is a state of one layer with at least `double cost` (cost of the best path
/// to it) and `int pred` (its predecessor's index in the previous layer, -1 at the first layer).
template <typename Node>
struct LayeredDp {
  std::vector<std::vector<Node>> nodes;  ///< per layer

  /// Forward pass: `build(k, prev, cur)` fills layer k (`cur`, empty on entry) from layer k - 1 (`prev`, empty at
  /// k = 0) and returns whether any of its states is reachable. Stops at the first layer without one. Returns the
  /// number of layers built before that: n when the pass went through.
  template <typename Build>
  std::size_t forward(std::size_t n, Build&& build) {
    return forward_from(0, n, std::forward<Build>(build));
  }
  /// The same pass from layer `k0` on, layers [0, k0) kept as they are (built by an earlier pass that would build them
  /// the same way now).
  template <typename Build>
  std::size_t forward_from(std::size_t k0, std::size_t n, Build&& build) {
    static const std::vector<Node> none;
    nodes.resize(n);
    for (std::size_t k = k0; k < n; ++k) nodes[k].clear();
    for (std::size_t k = k0; k < n; ++k)
      if (!build(k, k ? nodes[k - 1] : none, nodes[k])) return k;
    return n;
  }
  /// forward_from, rejoining the pass the layers still hold: once a layer k >= rejoin_from comes out as that pass's
  /// (the same states by `same`, the same predecessors, every cost shifted by one amount), the layers after it would
  /// too: they are kept, their costs shifted. (A pass re-run for a detour around a colliding move mostly rejoins the
  /// old path a few points later.) Layers [k0, n) must hold the earlier pass's states, built the same way.
  template <typename Build, typename Same>
  std::size_t forward_rejoin(std::size_t k0, std::size_t rejoin_from, std::size_t n, Build&& build, Same&& same) {
    static const std::vector<Node> none;
    nodes.resize(n);
    std::vector<Node> was;
    for (std::size_t k = k0; k < n; ++k) {
      was.swap(nodes[k]);
      nodes[k].clear();
      if (!build(k, k ? nodes[k - 1] : none, nodes[k])) {
        for (std::size_t j = k + 1; j < n; ++j) nodes[j].clear();
        return k;
      }
      const auto& now = nodes[k];
      if (k < rejoin_from || was.empty() || was.size() != now.size()) continue;
      const double delta = now[0].cost - was[0].cost;
      bool joined = true;
      for (std::size_t i = 0; i < now.size() && joined; ++i)
        joined = same(was[i], now[i]) && was[i].pred == now[i].pred &&
                 std::abs(now[i].cost - was[i].cost - delta) <= 1e-9 * (1.0 + std::abs(was[i].cost));
      if (!joined) continue;
      for (std::size_t j = k + 1; j < n; ++j)
        for (Node& s : nodes[j]) s.cost += delta;
      return n;
    }
    return n;
  }
  /// The cheapest state of the last layer (the first of equals).
  [[nodiscard]] int cheapest_last() const {
    const auto& last = nodes.back();
    std::size_t best = 0;
    for (std::size_t j = 1; j < last.size(); ++j)
      if (last[j].cost < last[best].cost) best = j;
    return static_cast<int>(best);
  }
  /// Backtrack: the state index per layer of the path that ends at state `last` of the last layer.
  [[nodiscard]] std::vector<int> backtrack(int last) const {
    std::vector<int> idx(nodes.size(), -1);
    for (std::size_t k = nodes.size(); k-- > 0;) {
      idx[k] = last;
      last = nodes[k][static_cast<std::size_t>(last)].pred;
    }
    return idx;
  }
};

/// The cause of a failed cell.
inline FailureCause cause_of(Status s) {
  return s == Status::Stroke      ? FailureCause::Stroke
         : s == Status::Collision ? FailureCause::Collision
                                  : FailureCause::Orientation;
}

/// Why a search stopped: a cause and its detail (TierFailure's text without the place).
struct Why {
  FailureCause cause = FailureCause::Transition;
  std::string detail;
  [[nodiscard]] std::string text() const { return failure_text(cause, detail); }
};

/// The largest rotary step a path may take from one point to the next (Options::max_step_rad; by default 20 grid
/// steps, and no bound at cone 0, where the exact orientations must turn fast near the singularity).
inline double max_rotary_step(const SegmentView& v) {
  if (v.options.max_step_rad > 0) return v.options.max_step_rad;
  return v.exact ? kPi : 20.0 * v.space.options().resolution_rad;
}
/// Whether every step of `path` stays within max_rotary_step; if not, `why` says where the first one leaves it.
/// Tiers 2 and 3 only ask for monotonic rotaries: a monotonic path may still jump (unwind a turn, or flip) between
/// two points, which is the sudden rotary change the planner is there to avoid; such an answer is not taken.
bool steps_within_bound(const SegmentView& v, const std::vector<const Cell*>& path, Why& why, std::size_t& at);

/// A state of a DP over a layer's own cell list: cost and predecessor per cell (kInf / -1: unreachable).
struct CostNode {
  double cost = kInf;
  int pred = -1;
};

/// Exact orientations (cone 0): a layered DP over the IK cells where a transition must satisfy `allowed`
/// and be continuously trackable (following the CL pose from one cell reaches the other without a
/// flip). Least L1 rotary travel. Returns false with the first layer that no allowed path reaches.
/// On failure `why` holds the last infeasible cell's cause (a flip-free transition missing when every cell was
/// feasible).
template <typename Allowed>
bool dp_exact(const SegmentView& v, SegmentCells& d, Allowed&& allowed, std::vector<const Cell*>& path,
              std::size_t& fail_layer, Why& why) {
  auto& L = d.layers;
  const std::size_t n = L.size();
  const auto& sp = v.space;
  const auto rp = sp.kinematics().rotary_pair();
  LayeredDp<CostNode> dp;
  // First only the jumps the post can bridge (no retract and turn on the part); if that finds no path and refused one,
  // again with every jump, where the post then turns the rotaries with a retract.
  bool strict = static_cast<bool>(v.options.can_bridge);
  std::size_t bridge_refusals = 0;
  const auto forward = [&] {
    return dp.forward(n, [&](std::size_t k, const std::vector<CostNode>& prev, std::vector<CostNode>& cur) {
      auto& cells = L[k].cells;
      cur.assign(cells.size(), CostNode{});
      bool any = false;
      for (std::size_t j = 0; j < cells.size(); ++j) {
        if (!feasible(v, d, k, cells[j])) {
          why = {cause_of(cells[j].status), cells[j].detail};
          continue;
        }
        if (k == 0) {
          // Ties (windings of a cyclic axis) go to the start nearest the previous segment's rotaries (or home).
          const auto [r1, r2] = v.entry_rotaries();
          cur[j].cost = 1e-9 * (std::abs(cells[j].r1 - r1) + std::abs(cells[j].r2 - r2));
          any = true;
          continue;
        }
        for (std::size_t i = 0; i < L[k - 1].cells.size(); ++i) {
          if (!std::isfinite(prev[i].cost)) continue;
          const Cell& a = L[k - 1].cells[i];
          const Cell& b = cells[j];
          if (!allowed(a, b)) continue;
          const double val = prev[i].cost + v.options.weight_primary * std::abs(b.r1 - a.r1) +
                             v.options.weight_secondary * std::abs(b.r2 - a.r2);
          if (val >= cur[j].cost) continue;
          // Between two singular points the tool axis is the same whatever the primary: it may turn there (the
          // linear axes keep the tip on the path), where the azimuth of the path through the singular axis changes.
          const bool in_place = a.singular && b.singular && std::abs(a.r2 - b.r2) < 1e-9;
          if (!in_place) {
            kin::Axes out;
            bool jumped = false;
            const kin::Posed pa = sp.tool_pose(L[k - 1].cl, a.r1, a.r2), pb = sp.tool_pose(L[k].cl, b.r1, b.r2);
            // A primary that swings on leaving the singular axis (a step that does not shrink with the pose's) is a
            // flip too: the post could not follow it on the path. (Near the axis, not on it, a fast swing is
            // continuous and the post follows it.)
            if (!kin::track_checked(sp.kinematics(), a.axes, pa, pb, out, jumped) || (jumped && a.singular)) continue;
            if (jumped && strict) {
              // Tracking cannot follow the pose here (beside a singular orientation the primary would have to swing,
              // or a limit is in the way): without a retract the post follows only where it can bridge the move
              // within its tolerances (interpolated rotaries), into any cell that allows that, not only where
              // tracking landed.
              if (!v.options.can_bridge(a.axes, pa, b.axes, pb)) {
                ++bridge_refusals;
                continue;
              }
            } else {
              // Arriving at a singular point, the primary may turn there in place before the path goes on.
              const double primary_off = b.singular ? 0.0 : std::abs(out[rp[0]] - b.r1);
              if (primary_off + std::abs(out[rp[1]] - b.r2) > 1e-6) continue;  // would flip
            }
          }
          cur[j] = {val, static_cast<int>(i)};
          any = true;
        }
      }
      return any;
    });
  };
  std::size_t built = forward();
  if (built < n && strict && bridge_refusals > 0) {
    strict = false;
    built = forward();
  }
  if (built < n) {
    fail_layer = built;
    if (why.cause == FailureCause::Transition && why.detail.empty())
      why.detail = "no continuous (flip-free) transition from the previous point";
    return false;
  }
  const std::vector<int> idx = dp.backtrack(dp.cheapest_last());
  path.assign(n, nullptr);
  for (std::size_t k = 0; k < n; ++k) path[k] = &L[k].cells[static_cast<std::size_t>(idx[k])];
  return true;
}

/// What a tier found: the cell per point, its description, or why it failed.
struct TierOutcome {
  std::vector<const Cell*> path;
  std::string description;
  TierFailure failure;
};

/// Cone 0, tiers 2 and 3: dp_exact under each of several transition rules (fixed axis or directions). Keeps the path
/// of least travel (then the shortest entry: the other branch of a tilt can need half a turn of the primary to get
/// there) and, while none is found, the failure that got furthest.
struct ExactChoice {
  bool found = false;
  PathCost best;
  std::size_t worst = 0;
  Why why;
  /// One rule's result (`ok`, its path `p`, or where it failed, `fail_layer` and `w`). Returns whether `p` is now
  /// the best (moved into `out.path`; the caller describes it).
  bool offer(const SegmentView& v, bool ok, std::vector<const Cell*>& p, std::size_t fail_layer, const Why& w,
             TierOutcome& out) {
    if (!ok) {
      if (fail_layer >= worst) worst = fail_layer, why = w;
      return false;
    }
    const PathCost cost = path_cost(v, p);
    if (found && !cost.better_than(best)) return false;
    found = true;
    best = cost;
    out.path = std::move(p);
    return true;
  }
  /// After the last rule: true with the best path, or false with the furthest failure in `out`.
  bool finish(const SegmentView& v, const SegmentCells& d, Tier tier, TierOutcome& out) const {
    if (found) return true;
    out.failure = {tier, d.layers[worst].move, line_of(v, d, worst), why.cause, why.detail};
    return false;
  }
};

/// Tier 1 (tier_fixed.cpp): one cell feasible at every point (3+2); ties broken by clearance, then by nearness to
/// the previous segment's rotaries.
bool tier_fixed(const SegmentView& v, SegmentCells& d, TierOutcome& out);
/// Tier 2 (tier_one_fixed.cpp): one rotary fixed, the other monotonic.
bool tier_one_fixed(const SegmentView& v, SegmentCells& d, TierOutcome& out);
/// Tier 3 (tier_monotonic.cpp): both rotaries monotonic (reachability through Pareto staircases).
bool tier_monotonic(const SegmentView& v, SegmentCells& d, TierOutcome& out);
/// Tier 4 (tier_shortest.cpp): least weighted rotary travel, bounded step per point.
bool tier_shortest(const SegmentView& v, SegmentCells& d, TierOutcome& out);

/// The answer of the tier cascade for a segment.
struct Cascade {
  Tier tier = Tier::Shortest;
  std::vector<TierFailure> failures;  ///< one per tier tried before the one reached
  std::string description;
  std::vector<const Cell*> path;
};
/// Runs the tiers in order (cascade.cpp); between tier 1 and 2 the points' cell lists are completed and every point
/// is checked for a feasible cell. Before tier 4 gives up, truncated cell lists are extended to the whole cone.
/// Throws InputError when no tier finds a path.
Cascade run_cascade(const SegmentView& v, SegmentCells& d, std::size_t& points_beyond_cap);
/// Between the points: a move whose sweep collides is ruled out and the search runs again, until no chosen move
/// collides (a few rounds at most). A tier 4 answer is re-searched with every transition into those points swept
/// first (SegmentCells::swept_layers); an answer of tiers 1-3 loses the cell the move led into (conservative:
/// that cell might be fine from another predecessor) and the cascade runs again. `kept` holds
/// the cells of an answer that stands when nothing is left without them (c.path may then point into it). Moves
/// certified free are flagged in `swept_ok`.
void avoid_swept_collisions(const SegmentView& v, SegmentCells& d, Cascade& c, std::vector<Cell>& kept,
                            std::vector<char>& swept_ok, std::size_t& points_beyond_cap);

/// With Options::monotone_axes (legs.cpp): the counted axes' reversals along `path`; a reversing path is re-planned
/// inside the cone so that they move monotonically, if it can be. May replace `path`, the tier and the description.
LegReport replan_legs(const SegmentView& v, SegmentCells& d, std::vector<const Cell*>& path, Tier& tier,
                      std::string& description);

/// Whether CL move m lies on CL move ref's axis, with ref's axis (an approach into or retract out of ref).
bool is_axial_approach(const cl::Program& cl, std::size_t m, std::size_t ref);
/// Re-places move m (an approach into, or retract out of, move ref along ref's CL axis; approach.cpp) along ref's
/// chosen axis at the same distance, with ref's rotaries. False (nothing changed) when m is not such a move or the
/// re-placed point breaks a limit.
bool along_chosen_axis(const kin::Kinematics& kin, const cl::Program& cl, Plan& plan, std::size_t m, std::size_t ref);

}  // namespace cscam::plan::detail
