// A segment's points and their cells: building the layers, lazy cell access, and the per-point feasibility check
// that runs before the tiers that move the rotaries.
#include <fmt/format.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <numbers>
#include <utility>

#include "cscam/core/error.hpp"
#include "cscam/core/tolerances.hpp"
#include "cscam/core/units.hpp"
#include "detail/search.hpp"

namespace cscam::plan::detail {

std::string SegmentView::n1() const {
  return space.kinematics().axes()[static_cast<size_t>(space.kinematics().rotary_pair()[0])].name;
}
std::array<double, 2> SegmentView::entry_rotaries() const {
  const auto rp = space.kinematics().rotary_pair();
  return prefer ? std::array<double, 2>{(*prefer)[rp[0]], (*prefer)[rp[1]]} : std::array<double, 2>{0.0, 0.0};
}

std::string SegmentView::n2() const {
  return space.kinematics().axes()[static_cast<size_t>(space.kinematics().rotary_pair()[1])].name;
}

bool retracts(const SegmentView& v, const Layer& l, const kin::Axes& q) {
  kin::Axes up;
  return !l.retract_end ||
         kin::retract_along_axis(v.space.kinematics(), q, v.retract_plane_z_mm, tol::kLimitSlackMm, up);
}

void mark_retract(const SegmentView& v, const Layer& l, Cell& c) {
  if (!l.retract_end || c.status != Status::Unknown) return;
  const kin::Kinematics& kin = v.space.kinematics();
  const auto rp = kin.rotary_pair();
  kin::Axes q = kin::Axes::Zero();
  q[rp[0]] = c.r1;
  q[rp[1]] = c.r2;
  // A cell out of reach is left to Space::evaluate, which says which limit it breaks.
  if (!kin.solve_for_rotaries(v.space.tool_pose(l.cl, c.r1, c.r2), q) || !kin.check_limits(q).empty() ||
      !kin.passive_violation(q).empty() || retracts(v, l, q))
    return;
  c.status = Status::Stroke;
  c.detail = fmt::format(
      "the tool cannot retract from here along its axis to the safe plane z = {:.3f} mm (post.safe_z_mm) inside the "
      "limits",
      v.retract_plane_z_mm);
}

void enumerate_layer(const SegmentView& v, Layer& l, std::size_t cap, cspace::Counters& counters) {
  v.space.enumerate(l.cl, l.cells, cap, counters);
  if (l.retract_end)
    for (Cell& c : l.cells) mark_retract(v, l, c);
  l.grid_order.clear();
  l.row_starts.clear();
  l.truncated = l.cells.size() >= cap;
  l.index.clear();
  l.index.reserve(l.cells.size());
  if (v.exact)
    for (Cell& c : l.cells) {
      c.i1 = static_cast<int>(std::lround(c.r1 / kExactKeyRad));
      c.i2 = static_cast<int>(std::lround(c.r2 / kExactKeyRad));
    }
  for (std::size_t j = 0; j < l.cells.size(); ++j)
    l.index.emplace(key(l.cells[j].i1, l.cells[j].i2), static_cast<int>(j));
}

namespace {

/// At a singular point the primary rotary is free: offer every primary that the nearest regular point on either side
/// uses, so that continuous (flip-free) paths can pass straight through the singularity. Every point of a run of
/// singular points gets the same primaries (those of the regular points around the run), so that the path can hold
/// one primary across the whole run. Where the axis's azimuth is not the primary itself (a 45-degree head: the tilt
/// direction turns with the secondary), the primary that the machine reaches at the singular point is not the
/// regular point's: tracking from its cells to the singular pose finds it (1.1 deg further on the 45-degree head from
/// a point 4.4 deg off the vertical), and both are offered.
void expand_singular(const SegmentView& v, std::vector<Layer>& layers) {
  const auto regular = [&](std::size_t kk) {
    const auto& cells = layers[kk].cells;
    return std::any_of(cells.begin(), cells.end(), [](const Cell& c) { return !c.singular; });
  };
  const kin::Kinematics& kin = v.space.kinematics();
  const auto rp = kin.rotary_pair();
  for (std::size_t k = 0; k < layers.size(); ++k) {
    auto& cells = layers[k].cells;
    if (std::none_of(cells.begin(), cells.end(), [](const Cell& c) { return c.singular; })) continue;
    std::vector<double> primaries;
    const auto take = [&](std::size_t kk) {
      for (const Cell& c : layers[kk].cells) {
        if (c.singular) continue;
        primaries.push_back(c.r1);
        kin::Axes q = kin::Axes::Zero(), out;
        q[rp[0]] = c.r1;
        q[rp[1]] = c.r2;
        const kin::Posed from = v.space.tool_pose(layers[kk].cl, c.r1, c.r2);
        // (At cone 0 the singular point's tool pose is its CL pose.)
        if (kin.solve_for_rotaries(from, q) && kin::track(kin, q, from, layers[k].cl, out) &&
            std::abs(out[rp[0]] - c.r1) > 1e-9)
          primaries.push_back(out[rp[0]]);
      }
    };
    for (std::size_t kk = k; kk-- > 0;)
      if (regular(kk)) {
        take(kk);
        break;
      }
    for (std::size_t kk = k + 1; kk < layers.size(); ++kk)
      if (regular(kk)) {
        take(kk);
        break;
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
        n.detail.clear();
        mark_retract(v, layers[k], n);
        if (std::none_of(out.begin(), out.end(), [&](const Cell& o) { return o.i1 == n.i1 && o.i2 == n.i2; }))
          out.push_back(n);
      }
    }
    cells = std::move(out);
    layers[k].grid_order.clear();
    layers[k].row_starts.clear();
    layers[k].index.clear();
    for (std::size_t j = 0; j < cells.size(); ++j)
      layers[k].index.emplace(key(cells[j].i1, cells[j].i2), static_cast<int>(j));
  }
}

/// Puts cells evaluated before a re-listing back: into the list where they are in it, else among the extras.
void restore(Layer& l, std::unordered_map<std::uint64_t, Cell>& keep) {
  for (auto& [kk, c] : keep) {
    if (const int at = l.index.find(kk); at >= 0) {
      if (c.status != Status::Orientation) l.cells[static_cast<size_t>(at)] = c;
    } else {
      l.extra.emplace(kk, std::move(c));
    }
  }
}

}  // namespace

SegmentCells make_cells(const SegmentView& v, std::size_t first, std::size_t last, cspace::Counters& counters) {
  SegmentCells d(counters, v.space);
  d.layers.resize(last - first + 1);
  const auto& moves = v.program.moves;
  // Windowed planning: the program's last move is not its segment's end (the next window continues it).
  const bool open_end = v.options.continues && last + 1 == moves.size();
  if (std::isfinite(v.retract_plane_z_mm)) {
    // The post retracts along the tool axis at both ends of a segment, and approaches the first point the same way
    // (replace_approach_retract's cases: a window that joins or continues has no such end). Where the CL approach
    // (retract) runs along the axis of the point after (before) it, it is re-placed on that point's chosen axis and
    // retracts on the same line: that point is marked too.
    const std::size_t n = last - first + 1;
    const bool join = first == 0 && v.options.start_rotaries.has_value();
    if (!join) {
      d.layers[0].retract_end = true;
      if (n > 1 && is_axial_approach(v.program, first, first + 1)) d.layers[1].retract_end = true;
    }
    if (!open_end) {
      d.layers[n - 1].retract_end = true;
      if (n > 2 && moves[last].kind != cl::MotionKind::Rapid && is_axial_approach(v.program, last, last - 1))
        d.layers[n - 2].retract_end = true;
    }
  }
  const std::optional<std::array<double, 2>> pinned_to = first == 0 && v.options.start_rotaries
                                                             ? v.options.start_rotaries
                                                         : open_end ? v.options.open_segment_rotaries
                                                                    : std::nullopt;
  // Only the first point's cells are needed by tier 1 (the others are tested cell by cell); the rest
  // are enumerated when a later tier needs them, or for the per-point feasibility check in exact mode.
  for (std::size_t k = 0; k < d.layers.size(); ++k) {
    Layer& l = d.layers[k];
    l.move = first + k;
    l.cl = {moves[first + k].tip_in_part_mm, moves[first + k].axis_in_part.normalized()};
    // Tier 1 takes its candidates from the first point: give it a much larger share.
    const bool pin = k == 0 && pinned_to;
    if ((k == 0 && !pin) || v.exact)
      enumerate_layer(v, l, k == 0 ? 64 * v.options.max_cells_per_point : v.options.max_cells_per_point, counters);
  }
  if (v.exact) expand_singular(v, d.layers);
  if (pinned_to) {
    // Windowed planning: the first point keeps the rotaries the previous window ended at, or those found for the
    // whole of a segment that runs on into the next window, as its only cell.
    Layer& l = d.layers[0];
    const double kr = v.exact ? kExactKeyRad : v.space.options().resolution_rad;
    Cell c;
    c.r1 = (*pinned_to)[0];
    c.r2 = (*pinned_to)[1];
    c.i1 = static_cast<int>(std::lround(c.r1 / kr));
    c.i2 = static_cast<int>(std::lround(c.r2 / kr));
    (void)v.space.in_cone(l.cl, c.r1, c.r2, &c.orient_err);
    l.cells.assign(1, c);
    l.grid_order.clear();
    l.row_starts.clear();
    l.index.clear();
    l.index.emplace(key(c.i1, c.i2), 0);
    l.extra.clear();
    l.truncated = false;
    l.pinned = true;
  }
  return d;
}

void extend_layer(const SegmentView& v, SegmentCells& d, std::size_t k) {
  d.last_shortest.reset();  // its states point into the old list
  Layer& l = d.layers[k];
  std::unordered_map<std::uint64_t, Cell> keep;
  keep.swap(l.extra);
  for (Cell& c : l.cells)
    if (c.status != Status::Unknown) keep.insert_or_assign(key(c.i1, c.i2), std::move(c));
  enumerate_layer(v, l, std::numeric_limits<std::size_t>::max(), d.counters);
  restore(l, keep);
}

void list_layers(const SegmentView& v, SegmentCells& d) {
  d.last_shortest.reset();
  // Every layer on its own (in parallel): the same lists, counters summed.
  parallel_items(d.layers.size() - 1, d.counters, [&](std::size_t i, geom::QueryWorkspace&, cspace::Counters& cc) {
    Layer& l = d.layers[i + 1];
    // Keep what tier 1 already evaluated (the cache) when the full cell list arrives.
    std::unordered_map<std::uint64_t, Cell> keep;
    keep.swap(l.extra);
    enumerate_layer(v, l, v.options.max_cells_per_point, cc);
    restore(l, keep);
  });
}

Cell* cell_at(const SegmentView& v, SegmentCells& d, std::size_t k, int i1, int i2) {
  Layer& l = d.layers[k];
  const auto kk = key(i1, i2);
  if (const int at = l.index.find(kk); at >= 0) return &l.cells[static_cast<size_t>(at)];
  if (auto it = l.extra.find(kk); it != l.extra.end())
    return it->second.status == Status::Orientation ? nullptr : &it->second;
  if (v.exact || l.pinned) return nullptr;  // exact cells are all enumerated; a pinned layer has its one cell
  Cell c;
  c.i1 = i1;
  c.i2 = i2;
  c.r1 = v.space.r1_of(i1);
  c.r2 = v.space.r2_of(i2);
  if (!v.space.in_cone(l.cl, c.r1, c.r2, &c.orient_err)) c.status = Status::Orientation;
  mark_retract(v, l, c);
  auto& slot = l.extra.emplace(kk, c).first->second;
  return slot.status == Status::Orientation ? nullptr : &slot;
}

namespace {
/// Grid cells per whole turn (0: a turn is no whole number of cells).
long cells_per_turn(const cspace::Space& sp) {
  const double turn_cells = 2.0 * kPi / sp.options().resolution_rad;
  const long per_turn = std::lround(turn_cells);
  return std::abs(turn_cells - static_cast<double>(per_turn)) > 1e-6 ? 0 : per_turn;
}
/// The whole turns t (t_lo <= t <= t_hi; none when t_lo > t_hi) that keep grid indices [lo, hi] of rotary j (0:
/// primary) on the grid when shifted by t turns.
std::pair<long, long> turns_on_grid(const cspace::Space& sp, int j, int lo, int hi, long per_turn) {
  const int g_lo = j == 0 ? sp.i1_min() : sp.i2_min(), g_hi = j == 0 ? sp.i1_max() : sp.i2_max();
  const auto n = static_cast<double>(per_turn);
  return {static_cast<long>(std::ceil(static_cast<double>(g_lo - lo) / n)),
          static_cast<long>(std::floor(static_cast<double>(g_hi - hi) / n))};
}
}  // namespace

PathCost path_cost(const SegmentView& v, const std::vector<const Cell*>& path) {
  PathCost c;
  if (path.empty()) return c;
  const double w1 = v.options.weight_primary, w2 = v.options.weight_secondary;
  for (std::size_t k = 1; k < path.size(); ++k)
    c.travel += w1 * std::abs(path[k]->r1 - path[k - 1]->r1) + w2 * std::abs(path[k]->r2 - path[k - 1]->r2);
  const auto [p1, p2] = v.entry_rotaries();
  c.entry = w1 * std::abs(path.front()->r1 - p1) + w2 * std::abs(path.front()->r2 - p2);
  return c;
}

double whole_turns_rad(const cspace::Space& sp, int j, int i, double from_rad) {
  const long per_turn = cells_per_turn(sp);
  if (per_turn <= 0) return 0.0;
  const double r = j == 0 ? sp.r1_of(i) : sp.r2_of(i);
  double best = std::abs(r - from_rad);
  // The windings of the same angle on the grid: i + t per_turn.
  const auto [t_lo, t_hi] = turns_on_grid(sp, j, i, i, per_turn);
  for (long t = t_lo; t <= t_hi; ++t)
    best = std::min(best, std::abs(r + 2.0 * kPi * static_cast<double>(t) - from_rad));
  return std::abs(r - from_rad) - best;
}

void rewind_to_entry(const SegmentView& v, SegmentCells& d, std::vector<const Cell*>& path) {
  if (v.exact || path.empty() || d.layers.front().pinned) return;
  const auto& sp = v.space;
  const auto& kin = sp.kinematics();
  const auto rp = kin.rotary_pair();
  const long per_turn = cells_per_turn(sp);
  if (per_turn <= 0) return;
  const auto entry = v.entry_rotaries();
  // Any rotary whose grid holds more than a turn (a cyclic axis, or limits wider than a turn): a turn is no motion.
  for (int j = 0; j < 2; ++j) {
    const auto axis = static_cast<std::size_t>(rp[static_cast<std::size_t>(j)]);
    auto idx = [j](const Cell* c) { return j == 0 ? c->i1 : c->i2; };
    int lo = idx(path.front()), hi = lo;
    for (const Cell* c : path) lo = std::min(lo, idx(c)), hi = std::max(hi, idx(c));
    const auto [t_lo, t_hi] = turns_on_grid(sp, j, lo, hi, per_turn);
    if (t_lo > t_hi) continue;  // t = 0 leaves the grid already (cannot be: the path is on it); no turn fits
    const double r0 = j == 0 ? path.front()->r1 : path.front()->r2;
    const long t = std::clamp(std::lround((entry[static_cast<std::size_t>(j)] - r0) / (2.0 * kPi)), t_lo, t_hi);
    if (t == 0) continue;
    // All or nothing: every shifted cell must be on the grid and within the axis limits.
    std::vector<Cell*> moved(path.size(), nullptr);
    bool ok = true;
    for (std::size_t k = 0; k < path.size() && ok; ++k) {
      const Cell& c = *path[k];
      if (c.status != Status::Feasible) {
        ok = false;
        break;
      }
      const int s = static_cast<int>(t * per_turn);
      Cell* to = j == 0 ? cell_at(v, d, k, c.i1 + s, c.i2) : cell_at(v, d, k, c.i1, c.i2 + s);
      if (!to || (to->status != Status::Unknown && to->status != Status::Feasible)) {
        ok = false;
        break;
      }
      if (to->status == Status::Unknown) {
        kin::Axes q = c.axes;
        q[axis] = j == 0 ? to->r1 : to->r2;
        if (!kin.check_limits(q).empty() || !kin.passive_violation(q).empty()) {
          ok = false;
          break;
        }
        to->axes = q;
        to->status = Status::Feasible;
        to->clearance_mm = c.clearance_mm;
      }
      moved[k] = to;
    }
    if (!ok) continue;
    for (std::size_t k = 0; k < path.size(); ++k) path[k] = moved[k];
  }
}

bool feasible(const SegmentView& v, SegmentCells& d, std::size_t k, Cell& c, cspace::Certificate* cert) {
  if (cert || v.exact) {
    v.space.evaluate(d.layers[k].cl, c, d.ws, d.counters, cert);
  } else {
    // Tiers 2 and 3 walk the same grid cells point after point, as tier 4's beam does: the segment's clearance
    // certificates spare the queries (same answers: a certified pose is free).
    d.certs.reserve();
    d.certs.evaluate(d.layers[k].cl, c, d.ws, d.counters);
  }
  return c.status == Status::Feasible;
}

bool steps_within_bound(const SegmentView& v, const std::vector<const Cell*>& path, Why& why, std::size_t& at) {
  const double bound = max_rotary_step(v);
  for (std::size_t k = 1; k < path.size(); ++k) {
    const double d1 = std::abs(path[k]->r1 - path[k - 1]->r1), d2 = std::abs(path[k]->r2 - path[k - 1]->r2);
    if (d1 <= bound + 1e-12 && d2 <= bound + 1e-12) continue;
    at = k;
    why = {FailureCause::Transition,
           fmt::format("its rotaries would jump by {:.3f} deg ({}) and {:.3f} deg ({}) from the previous point, beyond "
                       "the step bound of {:.2f} deg",
                       rad2deg(d1), v.n1(), rad2deg(d2), v.n2(), rad2deg(bound))};
    return false;
  }
  return true;
}

double room(const SegmentView& v, SegmentCells& d, const std::vector<const Cell*>& p) {
  const std::size_t n = p.size();
  double r = 0.0;
  for (double m : {0.5, 1.0, 2.0, 4.0, 8.0, 16.0}) {
    for (std::size_t k : {std::size_t{0}, n / 2, n - 1})
      if (!v.space.free_with_margin(d.layers[k].cl, *p[k], m, d.ws, d.counters)) return r;
    r = m;
  }
  return r;
}

namespace {

/// The primary is free at a singular point: the IK offers one value (and its neighbours' primaries), but a table or
/// head body may stand in the way of that one while another turn of the primary is clear (a vertical tool over a part
/// beside the trunnion's support). Offers every singular point of the segment the primary on a grid over a whole turn
/// about its own value, inside the primary's limits; returns whether any cell was added.
bool turn_singular_primaries(const SegmentView& v, SegmentCells& d) {
  const kin::Kinematics& kin = v.space.kinematics();
  const int p = kin.rotary_pair()[0];
  const auto& axis = kin.axes()[static_cast<std::size_t>(p)];
  // 5 degrees: 72 cells per point where the IK offered one (a body's edge moves by millimetres per step at most).
  const double step = std::max(v.space.options().resolution_rad, deg2rad(5.0));
  const int n = static_cast<int>(std::lround(std::numbers::pi / step));
  bool added = false;
  for (Layer& l : d.layers) {
    if (l.pinned || l.cells.empty() ||
        !std::all_of(l.cells.begin(), l.cells.end(), [](const Cell& c) { return c.singular; }))
      continue;
    const std::vector<Cell> own = l.cells;
    for (const Cell& c : own)
      for (int j = -n; j < n; ++j) {
        if (j == 0) continue;
        Cell t = c;
        t.r1 = c.r1 + j * step;
        if (t.r1 < axis.min - 1e-9 || t.r1 > axis.max + 1e-9) continue;
        t.i1 = static_cast<int>(std::lround(t.r1 / kExactKeyRad));
        if (l.index.find(key(t.i1, t.i2)) >= 0) continue;
        t.status = Status::Unknown;
        t.detail.clear();
        mark_retract(v, l, t);
        l.index.emplace(key(t.i1, t.i2), static_cast<int>(l.cells.size()));
        l.cells.push_back(std::move(t));
        added = true;
      }
  }
  return added;
}

}  // namespace

bool check_points(const SegmentView& v, SegmentCells& d, std::size_t& points_beyond_cap) {
  auto& layers = d.layers;
  const auto& space = v.space;
  // Every point needs at least one feasible cell; otherwise say which constraint emptied it. A point is
  // called infeasible only once every cell of its cone has been shown infeasible: a truncated list whose
  // cells all fail is first extended to the whole cone.
  // In parallel first, in fixed runs of points (the same cells evaluated at any thread count): a point tries the
  // cell found feasible at the point before it (neighbouring points mostly share one), then that cell's
  // neighbourhood, and only a run's first point scans its cells nearest first. Where the cells nearest the CL axis
  // collide (a wall or lip beside the path) a scan passes hundreds of colliding cells: long runs, few scans.
  // The hint carries a clearance certificate: while it holds (same cell, tool moved less than its margin) the hint
  // needs no query at all, and its margin probe halves while it fails so that a tight hint costs one query, not two.
  constexpr std::size_t kRun = 256;
  constexpr int kRing = 3;
  const std::size_t runs = (layers.size() + kRun - 1) / kRun;
  std::vector<char> found_at(layers.size(), 0);
  parallel_items(runs, d.counters, [&](std::size_t r, geom::QueryWorkspace& ws, cspace::Counters& c) {
    const Cell* hint = nullptr;
    cspace::Certificate cert;
    std::vector<std::pair<double, Cell*>> by_angle;
    auto try_cell = [&](const Layer& l, Cell& cell) {
      if (cell.status == Status::Unknown) space.evaluate(l.cl, cell, ws, c);
      return cell.status == Status::Feasible;
    };
    for (std::size_t k = r * kRun; k < std::min(layers.size(), (r + 1) * kRun); ++k) {
      Layer& l = layers[k];
      if (hint) {
        if (const int at = l.index.find(key(hint->i1, hint->i2)); at >= 0) {
          Cell& cell = l.cells[static_cast<std::size_t>(at)];
          if (cell.status == Status::Unknown) {
            const bool probe = cert.valid || cert.probe_mm >= cspace::CertificateStore::kMinProbeMm;
            space.evaluate(l.cl, cell, ws, c, probe ? &cert : nullptr);
            if (probe && cell.status == Status::Feasible && !cert.valid) cert.probe_mm *= 0.5;
          }
          if (cell.status == Status::Feasible) {
            hint = &cell;
            found_at[k] = 1;
            continue;
          }
        }
      }
      const Cell* found = nullptr;
      if (hint) {
        // The free region moves little from point to point: look around the old hint, first ring by ring on the grid,
        // then through the cells by the angle between their tool axis and the hint's (near the singular axis many
        // grid steps of the primary are a small turn), rather than from the CL axis outward, where a wall or lip
        // beside the path makes the nearest cells collide.
        const int h1 = hint->i1, h2 = hint->i2;
        for (int rad = 1; rad <= kRing && !found; ++rad)
          for (int a = -rad; a <= rad && !found; ++a)
            for (int b = -rad; b <= rad && !found; ++b) {
              if (std::max(std::abs(a), std::abs(b)) != rad) continue;
              if (const int at = l.index.find(key(h1 + a, h2 + b)); at >= 0) {
                Cell& cell = l.cells[static_cast<std::size_t>(at)];
                if (try_cell(l, cell)) found = &cell;
              }
            }
        if (!found) {
          const Eigen::Vector3d hint_axis = space.axis_of(hint->r1, hint->r2);
          by_angle.clear();
          for (Cell& cell : l.cells)
            if (cell.status == Status::Unknown || cell.status == Status::Feasible)
              by_angle.emplace_back(-space.axis_of(cell.r1, cell.r2).dot(hint_axis), &cell);
          std::sort(by_angle.begin(), by_angle.end(), [](const auto& x, const auto& y) {
            return x.first != y.first ? x.first < y.first
                                      : key(x.second->i1, x.second->i2) < key(y.second->i1, y.second->i2);
          });
          for (auto& [dot, cell] : by_angle)
            if (try_cell(l, *cell)) {
              found = cell;
              break;
            }
        }
      } else {
        for (Cell& cell : l.cells)
          if (try_cell(l, cell)) {
            found = &cell;
            break;
          }
      }
      hint = found;
      found_at[k] = found != nullptr;
      cert = {};
    }
  });
  for (std::size_t k = 0; k < layers.size(); ++k) {
    if (found_at[k]) continue;
    bool any = false;
    int n_stroke = 0, n_coll = 0;
    std::string example;
    for (bool extended = false;;) {
      n_stroke = n_coll = 0;
      for (Cell& c : layers[k].cells) {
        if (feasible(v, d, k, c)) {
          any = true;
          break;
        }
        (c.status == Status::Stroke ? n_stroke : n_coll)++;
        if (example.empty()) example = c.detail;
      }
      if (any || extended || !layers[k].truncated) break;
      extend_layer(v, d, k);
      ++points_beyond_cap;
      extended = true;
      // The whole cone, nearest first, in parallel blocks; stop after the first block holding a feasible cell.
      auto& cells = layers[k].cells;
      constexpr std::size_t kBlock = 1024;
      for (std::size_t b = 0; b < cells.size(); b += kBlock) {
        const std::size_t e = std::min(cells.size(), b + kBlock);
        parallel_items(e - b, d.counters, [&](std::size_t i, geom::QueryWorkspace& ws, cspace::Counters& c) {
          space.evaluate(layers[k].cl, cells[b + i], ws, c);
        });
        if (std::any_of(cells.begin() + static_cast<std::ptrdiff_t>(b), cells.begin() + static_cast<std::ptrdiff_t>(e),
                        [](const Cell& x) { return x.status == Status::Feasible; }))
          break;
      }
    }
    if (any) continue;
    if (v.exact && !d.singular_turned && !layers[k].cells.empty() &&
        std::all_of(layers[k].cells.begin(), layers[k].cells.end(), [](const Cell& c) { return c.singular; })) {
      d.singular_turned = true;
      if (turn_singular_primaries(v, d)) {
        d.last_shortest.reset();
        return true;
      }
    }
    const cl::Move& mv = v.program.moves[layers[k].move];
    std::string why;
    if (layers[k].cells.empty())
      why = "orientation: no rotary cell gives a tool axis within the cone (the machine cannot reach this axis" +
            std::string(v.exact ? ")" : "; try a finer --resolution or a larger --cone)");
    else if (n_coll == 0)
      why = fmt::format("stroke: all {} cells in the cone break a limit (e.g. {})", n_stroke, example);
    else if (n_stroke == 0)
      why = fmt::format("collision: all {} cells in the cone collide (e.g. {})", n_coll, example);
    else
      why = fmt::format("stroke ({} cells) and collision ({} cells), e.g. {}", n_stroke, n_coll, example);
    // The nearest feasible cell beyond the cone, for the user to decide.
    // (Each wider cone lists at most its kWideCells cells nearest the CL axis beyond what was searched: past that,
    // the claim covers only the angle they reach.)
    constexpr std::size_t kWideCells = 20000;
    double covered_deg = space.options().cone_rad > 0 ? rad2deg(space.options().cone_rad) : 0.0;
    std::string nearest;
    for (double cone_deg : {5.0, 15.0, 45.0, 90.0}) {
      cspace::Options wider = space.options();
      if (wider.cone_rad >= deg2rad(cone_deg)) continue;
      wider.cone_rad = deg2rad(cone_deg);
      wider.min_tilt_rad = deg2rad(covered_deg);  // (what is nearer failed already)
      wider.resolution_rad = std::max(wider.resolution_rad, deg2rad(1.0));
      const cspace::Space wide(v.kinematics, nullptr, nullptr, wider);
      std::vector<Cell> cells;
      cspace::Counters dummy;
      wide.enumerate(layers[k].cl, cells, kWideCells, dummy);
      geom::QueryWorkspace ws;
      bool found = false;
      for (Cell& c : cells) {
        // Re-check with the real space (collision included) on the wider grid, and the retract at a segment end.
        mark_retract(v, layers[k], c);
        space.evaluate(layers[k].cl, c, ws, d.counters);
        if (c.status == Status::Feasible) {
          nearest = fmt::format("({:.3f}, {:.3f}) deg, {:.2f} deg from the CL axis", rad2deg(c.r1), rad2deg(c.r2),
                                rad2deg(c.orient_err));
          found = true;
          break;
        }
      }
      if (found) break;
      // Sorted nearest first: a full list covers the angle of its last cell only (the next cone goes on from there).
      covered_deg = cells.size() >= kWideCells ? rad2deg(cells.back().orient_err) : cone_deg;
    }
    if (nearest.empty())
      nearest = fmt::format("none found within {:.1f} deg of the CL axis{}", covered_deg,
                            covered_deg < 90.0 - 1e-9 ? " (the cells searched nearest the axis reach no farther)" : "");
    throw InputError(SourceLoc{v.program.file, mv.line, 0},
                     fmt::format("no feasible orientation at CL point ({:.4f}, {:.4f}, {:.4f}) axis ({:.5f}, {:.5f}, "
                                 "{:.5f}): {}; nearest feasible cell: {}",
                                 mv.tip_in_part_mm.x(), mv.tip_in_part_mm.y(), mv.tip_in_part_mm.z(),
                                 mv.axis_in_part.x(), mv.axis_in_part.y(), mv.axis_in_part.z(), why, nearest));
  }
  return false;
}

}  // namespace cscam::plan::detail
