// The tier cascade of one segment, and its re-run when moves between the chosen cells collide.
#include <fmt/format.h>

#include <algorithm>
#include <set>
#include <tuple>

#include "cscam/core/error.hpp"
#include "detail/search.hpp"

namespace cscam::plan::detail {

Cascade run_cascade(const SegmentView& v, SegmentCells& d, std::size_t& points_beyond_cap) {
  Cascade c;
  d.last_shortest.reset();  // cells may have been ruled out since: tier 4 searches afresh
  TierOutcome t;
  if (tier_fixed(v, d, t)) {
    c.tier = Tier::Fixed2;
  } else {
    c.failures.push_back(t.failure);
    if (!v.exact && !d.listed) list_layers(v, d);
    d.listed = true;
    // (Points along the primary axis offered the primary's whole turn: the tiers start again, 3+2 first.)
    if (check_points(v, d, points_beyond_cap)) return run_cascade(v, d, points_beyond_cap);
    if (t = {}; tier_one_fixed(v, d, t)) {
      c.tier = Tier::Fixed1;
    } else {
      c.failures.push_back(t.failure);
      if (t = {}; tier_monotonic(v, d, t)) {
        c.tier = Tier::Monotonic;
      } else {
        c.failures.push_back(t.failure);
        bool found = (t = {}, tier_shortest(v, d, t));
        if (!found && !v.exact) {
          // The tiers searched truncated cell lists: search the whole cones before giving up.
          std::size_t n_ext = 0;
          for (std::size_t k = 0; k < d.layers.size(); ++k)
            if (d.layers[k].truncated) {
              extend_layer(v, d, k);
              ++n_ext;
            }
          points_beyond_cap += n_ext;
          if (n_ext) found = (t = {}, tier_shortest(v, d, t));
        }
        if (!found) {
          const auto& moves = v.program.moves;
          throw InputError(
              SourceLoc{v.program.file, t.failure.line, 0},
              fmt::format("no rotary path through the feasible cells of segment CL lines {}-{}: {}",
                          moves[d.layers.front().move].line, moves[d.layers.back().move].line, t.failure.reason()));
        }
        c.tier = Tier::Shortest;
      }
    }
  }
  c.description = std::move(t.description);
  c.path = std::move(t.path);
  return c;
}

void avoid_swept_collisions(const SegmentView& v, SegmentCells& d, Cascade& c, std::vector<Cell>& kept,
                            std::vector<char>& swept_ok, std::size_t& points_beyond_cap) {
  if (!v.space.checks_collision() || c.path.size() <= 1) return;
  // Each round rules out what the last answer's moves hit; a tier 4 answer through swept-checked layers cannot
  // hit there again, so the rounds end when the colliding points run out (bounded: at most one round per point).
  const std::size_t max_rounds = std::max<std::size_t>(8, d.layers.size());
  // An approach into the first point and a retract out of the last along the CL axis are re-placed along the
  // chosen axis afterwards (replace_approach_retract, which the final check follows): not judged here.
  const auto& moves = v.program.moves;
  const std::size_t first = d.layers.front().move, last = d.layers.back().move;
  const bool pinned0 = first == 0 && v.options.start_rotaries.has_value();
  const bool open_end = v.options.continues && last + 1 == moves.size();
  const bool skip_first = d.layers.size() > 1 && !pinned0 && moves[first].kind == cl::MotionKind::Rapid &&
                          is_axial_approach(v.program, first, first + 1);
  const bool skip_last = d.layers.size() > 2 && !open_end && moves[last].kind != cl::MotionKind::Rapid &&
                         is_axial_approach(v.program, last, last - 1);
  // Moves found free in an earlier round (most of the path stays): (layer, from cell, into cell) on the grid.
  std::set<std::tuple<std::size_t, std::uint64_t, std::uint64_t>> known_free;
  for (std::size_t round = 0; round < max_rounds; ++round) {
    std::vector<std::size_t> bad, free_into;
    const bool searches_moves = c.tier == Tier::Shortest && !v.exact;
    // The moves to sweep (in parallel: each is its own question), then their verdicts in path order.
    std::vector<std::size_t> todo;
    for (std::size_t k = 0; k + 1 < c.path.size(); ++k) {
      if ((k == 0 && skip_first) || (k + 2 == c.path.size() && skip_last)) continue;
      const Cell &a = *c.path[k], &b = *c.path[k + 1];
      if (!v.exact && known_free.count(std::make_tuple(k + 1, key(a.i1, a.i2), key(b.i1, b.i2)))) {
        free_into.push_back(k + 1);
        continue;
      }
      todo.push_back(k);
    }
    std::vector<cspace::SweepStatus> status(todo.size());
    parallel_items(todo.size(), d.counters, [&](std::size_t i, geom::QueryWorkspace& wsi, cspace::Counters& cc) {
      const std::size_t k = todo[i];
      status[i] = v.space.swept(c.path[k]->axes, c.path[k + 1]->axes, cspace::SweepMode::Cutting, wsi, cc).status;
    });
    for (std::size_t i = 0; i < todo.size(); ++i) {
      const std::size_t k = todo[i];
      const Cell &a = *c.path[k], &b = *c.path[k + 1];
      const auto st = status[i];
      // A move that cannot be certified free (it skims the part) is avoided as a colliding one is where tier 4
      // can search around it move by move; a tier 1-3 answer is not given up for it (the final check warns).
      if (st == cspace::SweepStatus::Collides || (st == cspace::SweepStatus::Uncertified && searches_moves)) {
        bad.push_back(k + 1);
      } else if (st == cspace::SweepStatus::Free) {
        free_into.push_back(k + 1);
        known_free.insert(std::make_tuple(k + 1, key(a.i1, a.i2), key(b.i1, b.i2)));
      }
    }
    std::sort(free_into.begin(), free_into.end());
    if (bad.empty()) {
      // The final check need not repeat these (unless an approach/retract moves an end).
      for (std::size_t k : free_into) swept_ok[d.layers[k].move] = 1;
      return;
    }
    // Keep the current answer: if nothing is left without those moves, it stands (with its warning).
    kept.clear();
    for (const Cell* cell : c.path) kept.push_back(*cell);
    Cascade before = c;
    auto restore = [&] {
      c = std::move(before);
      for (std::size_t k = 0; k < kept.size(); ++k) c.path[k] = &kept[k];
    };
    if (searches_moves) {
      // Tiers 1-3 failed on cells that have only lost options since: search tier 4 again with the moves into
      // these points swept before they are taken.
      d.swept_layers.resize(d.layers.size(), 0);
      std::size_t added = 0;
      for (std::size_t k : bad) added += d.swept_layers[k] ? 0 : 1, d.swept_layers[k] = 1;
      if (added == 0) {  // the same layers again (a predecessor beyond the tries): keep the answer
        restore();
        return;
      }
      TierOutcome t;
      if (!tier_shortest(v, d, t)) {
        restore();
        return;
      }
      c.description = std::move(t.description);
      c.path = std::move(t.path);
      continue;
    }
    for (std::size_t k : bad) {
      Cell* cell = const_cast<Cell*>(c.path[k]);  // the layers own the cells; the path points into them
      cell->status = Status::Collision;
      cell->detail = "the move into it from the previous point collides (swept)";
    }
    try {
      c = run_cascade(v, d, points_beyond_cap);
    } catch (const InputError&) {
      restore();
      return;
    }
  }
}

}  // namespace cscam::plan::detail
