#include <fmt/format.h>

#include <algorithm>
#include <limits>

#include "cscam/core/error.hpp"
#include "cscam/core/units.hpp"
#include "cscam/kin/track.hpp"
#include "cscam/post/post.hpp"

namespace cscam::post {

namespace {

/// Rotary travel from a to b, the measure a typical post minimises.
double rotary_distance(const kin::Kinematics& k, const kin::Axes& a, const kin::Axes& b) {
  const auto rp = k.rotary_pair();
  return std::abs(a[rp[0]] - b[rp[0]]) + std::abs(a[rp[1]] - b[rp[1]]);
}

/// Score of a candidate at the start of a program: smaller is preferred.
double start_score(const machine::Machine& m, const kin::Kinematics& k, const kin::Axes& q) {
  const auto& rule = m.post.start_branch;
  double score = rotary_distance(k, q, kin::Axes::Zero());  // nearest to home
  for (const char* pre : {"positive:", "negative:"}) {
    if (rule.rfind(pre, 0) != 0) continue;
    const int i = m.axis_index(rule.substr(std::string(pre).size()));
    const double sign = pre[0] == 'p' ? 1.0 : -1.0;
    if (i >= 0 && sign * q[i] < -1e-9) score += 1e6;  // wrong side: only if nothing else exists
  }
  return score;
}

/// At a singular point (tool axis along the primary rotary) the primary angle is free. A post that keeps
/// the previous angle there forces a large primary rotation right after it, while the tool is on the
/// part; looking ahead to the next non-singular point and turning the primary now costs nothing.
void resolve_singular(const kin::Kinematics& k, const cl::Program& prog, size_t i, kin::Axes& q,
                      std::vector<kin::Solution>& sols) {
  const int p = k.rotary_pair()[0];
  for (size_t j = i + 1; j < prog.moves.size(); ++j) {
    const kin::Posed pose{prog.moves[j].tip_in_part_mm, prog.moves[j].axis_in_part.normalized()};
    k.inverse_branches(pose, &q, sols);
    if (sols.empty()) return;
    if (sols[0].singular) continue;
    double best = std::numeric_limits<double>::infinity();
    kin::Axes pick = q;
    for (kin::Solution& s : sols) {
      k.nearest_winding(s.axes, q);
      if (!k.check_limits(s.axes).empty()) continue;
      const double d = std::abs(s.axes[p] - q[p]) + std::abs(s.axes[k.rotary_pair()[1]] - q[k.rotary_pair()[1]]);
      if (d < best) {
        best = d;
        pick = s.axes;
      }
    }
    if (!std::isfinite(best)) return;
    kin::Axes trial = q;
    trial[p] = pick[p];
    const kin::Posed here{prog.moves[i].tip_in_part_mm, prog.moves[i].axis_in_part.normalized()};
    if (k.solve_for_rotaries(here, trial) && k.check_limits(trial).empty()) q = trial;
    return;
  }
}

}  // namespace

std::vector<kin::Axes> conventional_axes(const cl::Program& program, const machine::Machine& machine,
                                         const kin::Kinematics& kinematics) {
  std::vector<kin::Axes> out;
  out.reserve(program.moves.size());
  std::vector<kin::Solution> sols;
  kin::Axes prev = kin::Axes::Zero();
  bool have_prev = false;
  kin::Posed prev_pose;
  int always_axis = -1;
  double always_sign = 0.0;
  if (machine.post.branch_rule == "always")
    for (const char* pre : {"positive:", "negative:"})
      if (machine.post.start_branch.rfind(pre, 0) == 0) {
        always_axis = machine.axis_index(machine.post.start_branch.substr(std::string(pre).size()));
        always_sign = always_axis >= 0 ? (pre[0] == 'p' ? 1.0 : -1.0) : 0.0;
      }
  for (const cl::Move& mv : program.moves) {
    const kin::Posed pose{mv.tip_in_part_mm, mv.axis_in_part.normalized()};
    kin::Axes chosen = kin::Axes::Zero();
    std::string first_violation;
    bool ok = false, singular = false;
    if (have_prev && always_sign != 0) {
      // A simple post: the preferred sign of one rotary at every point, else the nearest solution.
      kinematics.inverse_branches(pose, &prev, sols);
      double best = std::numeric_limits<double>::infinity();
      for (kin::Solution& s : sols) {
        kinematics.nearest_winding(s.axes, prev);
        std::string v = kinematics.check_limits(s.axes);
        if (v.empty()) v = kinematics.passive_violation(s.axes);
        if (!v.empty()) {
          if (first_violation.empty()) first_violation = v;
          continue;
        }
        const bool wrong_side = always_sign * s.axes[always_axis] < -1e-12;
        const double score = rotary_distance(kinematics, s.axes, prev) + (wrong_side ? 1e6 : 0.0);
        if (score < best) {
          best = score;
          chosen = s.axes;
          singular = s.singular;
        }
      }
      ok = std::isfinite(best);
    } else if (have_prev) {
      ok = kin::track(kinematics, prev, prev_pose, pose, chosen, &first_violation, &singular);
    } else {
      kinematics.inverse_branches(pose, nullptr, sols);
      double best = std::numeric_limits<double>::infinity();
      for (kin::Solution& s : sols) {
        kinematics.nearest_winding(s.axes, kin::Axes::Zero());
        const std::string v = kinematics.check_limits(s.axes);
        if (!v.empty()) {
          if (first_violation.empty()) first_violation = v;
          continue;
        }
        const double score = start_score(machine, kinematics, s.axes);
        if (score < best) {
          best = score;
          chosen = s.axes;
          singular = s.singular;
        }
      }
      ok = std::isfinite(best);
    }
    if (!ok) {
      const auto& t = mv.tip_in_part_mm;
      const auto& u = mv.axis_in_part;
      throw InputError(
          SourceLoc{program.file, mv.line, 0},
          fmt::format("CL point ({:.4f}, {:.4f}, {:.4f}) axis ({:.5f}, {:.5f}, {:.5f}) cannot be reached "
                      "on machine '{}': {}",
                      t.x(), t.y(), t.z(), u.x(), u.y(), u.z(), machine.name,
                      first_violation.empty() ? std::string("no inverse-kinematics solution for this tool axis")
                                              : first_violation));
    }
    if (singular && always_sign == 0)
      resolve_singular(kinematics, program, static_cast<size_t>(&mv - program.moves.data()), chosen, sols);
    prev_pose = pose;
    out.push_back(chosen);
    prev = chosen;
    have_prev = true;
  }
  return out;
}

double tool_length_for(const machine::Machine& machine, double option_mm) {
  return option_mm > 0 ? option_mm : machine.default_tool_length_mm;
}

}  // namespace cscam::post
