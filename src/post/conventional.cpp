#include <fmt/format.h>

#include <limits>

#include "cscam/core/error.hpp"
#include "cscam/core/units.hpp"
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

}  // namespace

std::vector<kin::Axes> conventional_axes(const cl::Program& program, const machine::Machine& machine,
                                         const kin::Kinematics& kinematics) {
  std::vector<kin::Axes> out;
  out.reserve(program.moves.size());
  std::vector<kin::Solution> sols;
  kin::Axes prev = kin::Axes::Zero();
  bool have_prev = false;
  for (const cl::Move& mv : program.moves) {
    const kin::Posed pose{mv.tip_in_part_mm, mv.axis_in_part};
    kinematics.inverse_branches(pose, have_prev ? &prev : nullptr, sols);
    double best = std::numeric_limits<double>::infinity();
    kin::Axes chosen = kin::Axes::Zero();
    std::string first_violation;
    for (kin::Solution& s : sols) {
      if (have_prev) {
        kinematics.nearest_winding(s.axes, prev);
      } else {
        kinematics.nearest_winding(s.axes, kin::Axes::Zero());
      }
      const std::string v = kinematics.check_limits(s.axes);
      if (!v.empty()) {
        if (first_violation.empty()) first_violation = v;
        continue;
      }
      const double score = have_prev ? rotary_distance(kinematics, s.axes, prev) : start_score(machine, kinematics, s.axes);
      if (score < best) {
        best = score;
        chosen = s.axes;
      }
    }
    if (!std::isfinite(best)) {
      const auto& t = mv.tip_in_part_mm;
      const auto& u = mv.axis_in_part;
      throw InputError(SourceLoc{program.file, mv.line, 0},
                       fmt::format("CL point ({:.4f}, {:.4f}, {:.4f}) axis ({:.5f}, {:.5f}, {:.5f}) cannot be reached "
                                   "on machine '{}': {}",
                                   t.x(), t.y(), t.z(), u.x(), u.y(), u.z(), machine.name,
                                   sols.empty() ? std::string("no inverse-kinematics solution for this tool axis")
                                                : first_violation));
    }
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
