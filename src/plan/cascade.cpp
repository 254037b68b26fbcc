// The tier cascade of one segment, and its re-run when moves between the chosen cells collide.
#include <fmt/format.h>

#include "cscam/core/error.hpp"
#include "detail/search.hpp"

namespace cscam::plan::detail {

Cascade run_cascade(const SegmentView& v, SegmentCells& d, std::size_t& points_beyond_cap) {
  Cascade c;
  TierOutcome t;
  if (tier_fixed(v, d, t)) {
    c.tier = Tier::Fixed2;
  } else {
    c.failures.push_back(t.failure);
    if (!v.exact && !d.listed) list_layers(v, d);
    d.listed = true;
    check_points(v, d, points_beyond_cap);
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
  geom::QueryWorkspace ws;
  for (int round = 0; round < 4; ++round) {
    std::vector<std::size_t> bad, free_into;
    for (std::size_t k = 0; k + 1 < c.path.size(); ++k) {
      const auto st =
          v.space.swept(c.path[k]->axes, c.path[k + 1]->axes, cspace::SweepMode::Cutting, ws, d.counters).status;
      if (st == cspace::SweepStatus::Collides) bad.push_back(k + 1);
      if (st == cspace::SweepStatus::Free) free_into.push_back(k + 1);
    }
    if (bad.empty()) {
      // The final check need not repeat these (unless an approach/retract moves an end).
      for (std::size_t k : free_into) swept_ok[d.layers[k].move] = 1;
      return;
    }
    // Keep the current answer: if nothing is left without those cells, it stands (with its warning).
    kept.clear();
    for (const Cell* cell : c.path) kept.push_back(*cell);
    Cascade before = c;
    for (std::size_t k : bad) {
      Cell* cell = const_cast<Cell*>(c.path[k]);  // the layers own the cells; the path points into them
      cell->status = Status::Collision;
      cell->detail = "the move into it from the previous point collides (swept)";
    }
    try {
      c = run_cascade(v, d, points_beyond_cap);
    } catch (const InputError&) {
      c = std::move(before);
      for (std::size_t k = 0; k < kept.size(); ++k) c.path[k] = &kept[k];
      return;
    }
  }
}

}  // namespace cscam::plan::detail
