#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <limits>

#include "cscam/core/error.hpp"
#include "cscam/core/parallel.hpp"
#include "cscam/core/units.hpp"
#include "cscam/kin/track.hpp"
#include "cscam/post/post.hpp"

namespace cscam::post {

namespace {

/// Extra cost of a candidate at the start of a program: the start branch's wrong side is taken only if
/// nothing else exists (nearness to home is kin::nearest_solution's own measure).
double start_penalty(const machine::Machine& m, const kin::Axes& q) {
  const auto& rule = m.post.start_branch;
  for (const char* pre : {"positive:", "negative:"}) {
    if (rule.rfind(pre, 0) != 0) continue;
    const int i = m.axis_index(rule.substr(std::string(pre).size()));
    const double sign = pre[0] == 'p' ? 1.0 : -1.0;
    if (i >= 0 && sign * q[i] < -1e-9) return 1e6;
  }
  return 0.0;
}

/// At a singular point (tool axis along the primary rotary) the primary angle is free. A post that keeps
/// the previous angle there forces a large primary rotation right after it, while the tool is on the
/// part; looking ahead to the next non-singular point and turning the primary now costs nothing.
void resolve_singular(const kin::Kinematics& k, const cl::Program& prog, size_t i, kin::Axes& q) {
  const int p = k.rotary_pair()[0];
  for (size_t j = i + 1; j < prog.moves.size(); ++j) {
    const kin::Posed pose{prog.moves[j].tip_in_part_mm, prog.moves[j].axis_in_part.normalized()};
    kin::Axes pick;
    bool singular = false;
    if (!kin::nearest_solution(k, pose, q, pick, nullptr, &singular)) return;
    if (singular) continue;
    kin::Axes trial = q;
    trial[p] = pick[p];
    const kin::Posed here{prog.moves[i].tip_in_part_mm, prog.moves[i].axis_in_part.normalized()};
    // The singular solution with that primary (the hint): on a calibrated machine, whose pole is beside the tool axis,
    // the secondary that brings the axis nearest depends on the primary; on an ideal one it is the same secondary.
    kin::Axes turned;
    bool still_singular = false;
    if (kin::nearest_solution(k, here, trial, turned, nullptr, &still_singular) && still_singular &&
        std::abs(turned[p] - trial[p]) < 1e-9)
      q = turned;
    return;
  }
}

}  // namespace

std::vector<kin::Axes> conventional_axes(const cl::Program& program, const machine::Machine& machine,
                                         const kin::Kinematics& kinematics) {
  std::vector<kin::Axes> out;
  out.reserve(program.moves.size());
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
  // The rule's side of one rotary: only if nothing else exists.
  auto side_penalty = [&](const kin::Axes& q) {
    return always_axis >= 0 && always_sign * q[always_axis] < -1e-12 ? 1e6 : 0.0;
  };
  // The IK branches of every point do not depend on the previous point (only a singular branch's free angle
  // does): computed ahead in parallel, a window at a time, and used where no branch is singular; the window after
  // the one being walked is computed in the background meanwhile. Not on models whose numbers depend on call
  // order (the XMINI's warm-started solves).
  const bool ahead = !kinematics.traits().forward_depends_on_call_order;
  constexpr std::size_t kWindow = 4096;
  struct Window {
    std::size_t begin = 0;
    std::vector<std::vector<kin::Solution>> branches;
    std::vector<char> ok;  ///< no branch is singular
  };
  auto solve_window = [&program, &kinematics](Window& w, std::size_t begin, std::size_t end) {
    w.begin = begin;
    w.branches.resize(end - begin);
    w.ok.assign(end - begin, 0);
    parallel_range(begin, end, 256, [&](const tbb::blocked_range<std::size_t>& r) {
      for (std::size_t k = r.begin(); k != r.end(); ++k) {
        const cl::Move& m = program.moves[k];
        auto& b = w.branches[k - begin];
        kinematics.inverse_branches(kin::Posed{m.tip_in_part_mm, m.axis_in_part.normalized()}, nullptr, b);
        w.ok[k - begin] = std::none_of(b.begin(), b.end(), [](const kin::Solution& s) { return s.singular; });
      }
    });
  };
  Window window, next;
  bool next_pending = false;
  Background next_job;  // after the windows it writes: joined first when leaving (a throw)
  for (const cl::Move& mv : program.moves) {
    const kin::Posed pose{mv.tip_in_part_mm, mv.axis_in_part.normalized()};
    const std::size_t i = static_cast<std::size_t>(&mv - program.moves.data());
    if (ahead && (window.branches.empty() || i >= window.begin + window.branches.size())) {
      if (next_pending) {
        next_job.wait();
        next_pending = false;
      }
      if (!next.branches.empty() && i >= next.begin && i < next.begin + next.branches.size())
        std::swap(window, next);
      else
        solve_window(window, i, std::min(program.moves.size(), i + kWindow));
      const std::size_t b = window.begin + window.branches.size();
      if (b < program.moves.size()) {
        next_pending = true;
        next_job.run([&solve_window, &next, &program, b] {
          solve_window(next, b, std::min(program.moves.size(), b + kWindow));
        });
      }
    }
    const std::vector<kin::Solution>* given =
        ahead && window.ok[i - window.begin] ? &window.branches[i - window.begin] : nullptr;
    kin::Axes chosen = kin::Axes::Zero();
    std::string first_violation;
    bool ok = false, singular = false;
    if (have_prev && always_sign != 0) {
      // A simple post: the preferred sign of one rotary at every point, else the nearest solution.
      ok = given ? kin::nearest_solution(kinematics, *given, prev, chosen, &first_violation, &singular, side_penalty)
                 : kin::nearest_solution(kinematics, pose, prev, chosen, &first_violation, &singular, side_penalty);
    } else if (have_prev) {
      ok = given ? kin::track(kinematics, prev, prev_pose, pose, *given, chosen, &first_violation, &singular)
                 : kin::track(kinematics, prev, prev_pose, pose, chosen, &first_violation, &singular);
    } else {
      // The first point: nearest to home, on the start branch's side when there is one.
      ok = kin::nearest_solution(kinematics, pose, kin::Axes::Zero(), chosen, &first_violation, &singular,
                                 [&](const kin::Axes& q) { return start_penalty(machine, q); });
    }
    if (!ok) {
      const auto& t = mv.tip_in_part_mm;
      const auto& u = mv.axis_in_part;
      // Tracking fails without a broken limit either at the point itself or on the way to it: the tool axes
      // between two reachable CL axes can pass through a cone the machine cannot point into (about a calibrated
      // machine's tilted primary rotary), which is not the point's fault.
      kin::Axes alone;
      const bool reachable_alone =
          have_prev && first_violation.empty() && kin::nearest_solution(kinematics, pose, prev, alone);
      const std::size_t k = static_cast<std::size_t>(&mv - program.moves.data());
      throw InputError(
          SourceLoc{program.file, mv.line, 0},
          reachable_alone
              ? fmt::format("the tool axis from CL line {} to CL point ({:.4f}, {:.4f}, {:.4f}) axis ({:.5f}, "
                            "{:.5f}, {:.5f}) passes where machine '{}' has no inverse-kinematics solution (a cone of "
                            "tool axes no rotary values reach, e.g. about a slightly tilted rotary axis): both points "
                            "are reachable, but no continuous motion follows the CL path between them",
                            program.moves[k - 1].line, t.x(), t.y(), t.z(), u.x(), u.y(), u.z(), machine.name)
              : fmt::format("CL point ({:.4f}, {:.4f}, {:.4f}) axis ({:.5f}, {:.5f}, {:.5f}) cannot be reached "
                            "on machine '{}': {}",
                            t.x(), t.y(), t.z(), u.x(), u.y(), u.z(), machine.name,
                            first_violation.empty() ? std::string("no inverse-kinematics solution for this tool axis")
                                                    : first_violation));
    }
    if (singular && always_sign == 0)
      resolve_singular(kinematics, program, static_cast<size_t>(&mv - program.moves.data()), chosen);
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

double tool_length_for(const machine::Machine& machine, double option_mm, const cl::Program& program,
                       std::string& note) {
  note.clear();
  if (option_mm > 0) return option_mm;
  bool head_rotary = false;
  if (machine.serial)
    for (const auto& j : machine.serial->joints)
      head_rotary |= j.type == kin::AxisType::Rotary && j.side == kin::Side::Head;
  if (!head_rotary) return machine.default_tool_length_mm;
  for (const auto& t : program.tools)
    if (t.length_mm > 0) {
      note = fmt::format(
          "{}: tool length {:.3f} mm from the CL's tool {} (TLDATA/CUTTER): the head's rotaries turn "
          "about the gauge point, so it must be the gauge-to-tip length (--tool-length overrides)",
          program.file, t.length_mm, t.number);
      return t.length_mm;
    }
  note = fmt::format(
      "{}: machine '{}' has a rotary in the head and neither --tool-length nor the CL (TLDATA/CUTTER) "
      "gives the tool length: using the machine file's default_tool_length_mm {:.3f} mm",
      program.file, machine.name, machine.default_tool_length_mm);
  return machine.default_tool_length_mm;
}

}  // namespace cscam::post
