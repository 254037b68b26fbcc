#include "cscam/plan/swept.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>

#include "cscam/core/error.hpp"
#include "cscam/core/tolerances.hpp"
#include "cscam/kin/track.hpp"

namespace cscam::plan {

double safe_z_of(const machine::Machine& m) {
  const int z = m.axis_index("z");
  if (z < 0) return std::numeric_limits<double>::quiet_NaN();
  return std::isnan(m.post.safe_z_mm) ? m.axes[static_cast<size_t>(z)].max : m.post.safe_z_mm;
}

SweptSummary check_program(const cspace::Space& space, const machine::Machine& machine, const cl::Program& program,
                           const std::vector<kin::Axes>& axes, cspace::Counters& counters,
                           const std::vector<char>* certified) {
  CSCAM_CHECK(axes.size() == program.moves.size(), "one axis vector per CL move");
  SweptSummary out;
  if (!space.checks_collision()) return out;
  geom::QueryWorkspace ws;
  const auto rp = space.kinematics().rotary_pair();
  const int z = machine.axis_index("z");
  const double safe_z = safe_z_of(machine);
  auto check = [&](std::size_t move, const kin::Axes& qa, const kin::Axes& qb, cspace::SweepMode mode, bool reo,
                   std::uint64_t budget = 0) {
    ++out.moves;
    cspace::SweptResult r = space.swept(qa, qb, mode, ws, counters, budget);
    if (r.status == cspace::SweepStatus::Free) return;
    (r.status == cspace::SweepStatus::Collides ? out.collisions : out.uncertified)++;
    out.hits.push_back({move, program.moves[move].line, reo, std::move(r)});
  };
  const auto& mv = program.moves;
  for (std::size_t i = 1; i < mv.size(); ++i) {
    const kin::Axes& from = axes[i - 1];
    const kin::Axes& to = axes[i];
    const bool from_cut = mv[i - 1].kind != cl::MotionKind::Rapid, to_cut = mv[i].kind != cl::MotionKind::Rapid;
    const auto direct = from_cut || to_cut ? cspace::SweepMode::Cutting : cspace::SweepMode::Rapid;
    const bool turns = std::abs(from[rp[0]] - to[rp[0]]) > 1e-9 || std::abs(from[rp[1]] - to[rp[1]]) > 1e-9;
    // The post's reorientation between points whose rotaries differ: up, turn, across, down. With a Z axis:
    // retract Z to the safe plane, rotate there, position above, plunge. Without one (the XMINI): retract along the
    // tool axis to the safe plane, turn there, move above the next point, plunge along its axis
    // (kin::reposition_at_plane, as the post writes it).
    kin::Axes up = from, turned = from, above = to;
    bool reorients = false;
    std::uint64_t cut_budget = 0;  // queries for a leg out of or into a cut (0: the default)
    if (mv[i].kind == cl::MotionKind::Rapid && turns && z >= 0 && !std::isnan(safe_z)) {
      up[z] = turned[z] = above[z] = std::max({safe_z, from[z], to[z]});  // never down to it (as the post)
      turned[rp[0]] = to[rp[0]];
      turned[rp[1]] = to[rp[1]];
      reorients = true;
    } else if (mv[i].kind == cl::MotionKind::Rapid && turns && z < 0 && std::isfinite(machine.post.safe_z_mm)) {
      // (No retract inside the limits: the post refuses the program; the direct move is checked meanwhile.)
      reorients = kin::reposition_at_plane(space.kinematics(), from, to, machine.post.safe_z_mm, tol::kLimitSlackMm, up,
                                           turned, above);
      // A retract out of a cut keeps its cutting end excluded (Cutting mode, small margins): through the XMINI's
      // joint motion that takes about 2,000 queries per 50 mm, so it gets a larger budget.
      cut_budget = 8192;
    }
    if (reorients) {
      const std::array<std::pair<kin::Axes, kin::Axes>, 4> legs = {
          {{from, up}, {up, turned}, {turned, above}, {above, to}}};
      for (std::size_t l = 0; l < legs.size(); ++l) {
        const bool cut = (l == 0 && from_cut) || (l == 3 && to_cut);
        check(i, legs[l].first, legs[l].second, cut ? cspace::SweepMode::Cutting : cspace::SweepMode::Rapid, true,
              cut ? cut_budget : 0);
      }
      continue;
    }
    if (certified && (*certified)[i]) {
      ++out.moves;
      continue;
    }
    check(i, from, to, direct, false);
  }
  return out;
}

}  // namespace cscam::plan
