#include "cscam/kin/track.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

#include "cscam/core/tolerances.hpp"
#include "cscam/core/units.hpp"

namespace cscam::kin {

namespace {
double rotary_distance(const Kinematics& k, const Axes& a, const Axes& b) {
  const auto rp = k.rotary_pair();
  return std::abs(a[rp[0]] - b[rp[0]]) + std::abs(a[rp[1]] - b[rp[1]]);
}

/// `p1_branches`: the IK branches of p1, if computed beforehand (see track.hpp), else nullptr.
bool track_rec(const Kinematics& k, const Axes& prev, const Posed& p0, const Posed& p1, int depth, Axes& out,
               std::string* violation, bool* singular, double max_step, bool* jumped = nullptr,
               const std::vector<Solution>* p1_branches = nullptr) {
  if (!(p1_branches ? nearest_solution(k, *p1_branches, prev, out, violation, singular)
                    : nearest_solution(k, p1, prev, out, violation, singular)))
    return false;
  if (rotary_distance(k, out, prev) <= max_step) return true;
  if (depth >= 20) {
    if (jumped) *jumped = true;
    return true;
  }
  // The angle from the cross product: acos of the dot product is 0 below about 1e-8 rad, which would end the
  // halving early and hide a jump (a limit met between two poses a fraction of a degree apart).
  const double ang = std::atan2(p0.axis.cross(p1.axis).norm(), p0.axis.dot(p1.axis));
  if (ang < 1e-12) return true;
  const Eigen::Vector3d mid_axis = (std::sin(0.5 * ang) / std::sin(ang) * (p0.axis + p1.axis)).normalized();
  const Posed mid{0.5 * (p0.tip_mm + p1.tip_mm), mid_axis};
  Axes qm;
  if (!track_rec(k, prev, p0, mid, depth + 1, qm, violation, nullptr, max_step, jumped)) return false;
  return track_rec(k, qm, mid, p1, depth + 1, out, violation, singular, max_step, jumped, p1_branches);
}

/// Takes a solution past a rotary limit by at most tol::kLimitSnapDeg to the limit, with the other axes solved again
/// for the same tip. False (q unchanged) when nothing is that near or the snapped values break a limit.
bool snap_rotaries_to_limits(const Kinematics& k, Axes& q) {
  const double eps = deg2rad(tol::kLimitSnapDeg);
  Axes s = q;
  bool moved = false;
  for (std::size_t i = 0; i < k.axes().size(); ++i) {
    const auto& a = k.axes()[i];
    double& v = s[static_cast<int>(i)];
    if (!a.rotary()) continue;
    if (v > a.max && v <= a.max + eps) {
      v = a.max;
      moved = true;
    } else if (v < a.min && v >= a.min - eps) {
      v = a.min;
      moved = true;
    }
  }
  if (!moved) return false;
  const Posed pose = k.forward(q);
  if (!k.solve_for_rotaries(pose, s) || !k.check_limits(s).empty()) return false;
  q = s;
  return true;
}

/// The choice of nearest_solution among `sols` (modified: windings adjusted to `near`).
bool choose_nearest(const Kinematics& k, std::vector<Solution>& sols, const Axes& near, Axes& out,
                    std::string* violation, bool* singular, const std::function<double(const Axes&)>& extra_cost) {
  double best = std::numeric_limits<double>::infinity();
  // Of the branches that break a limit, the one that misses by least is the one to name (the first may be a flipped
  // branch 180 deg away while the nearest misses by one degree).
  double least_miss = std::numeric_limits<double>::infinity();
  bool named_here = false;  // a violation named by an earlier call (another pose of the same track) is kept
  for (Solution& s : sols) {
    k.nearest_winding(s.axes, near);
    // Axis limits after the winding choice, then the limits the axis values do not show (a PKM's passive joints).
    std::string v = k.check_limits(s.axes);
    if (!v.empty() && snap_rotaries_to_limits(k, s.axes)) v.clear();
    const bool passive = v.empty();
    if (passive) v = k.passive_violation(s.axes);
    if (!v.empty()) {
      double miss = 0.0;  // mm, or deg for a rotary
      for (std::size_t i = 0; i < k.axes().size(); ++i) {
        const auto& a = k.axes()[i];
        const double q = s.axes[static_cast<int>(i)];
        miss += std::max({0.0, a.min - q, q - a.max}) * (a.rotary() ? 180.0 / kPi : 1.0);
      }
      if (passive) miss = std::numeric_limits<double>::max();  // a passive joint: named only when nothing else is
      if (violation && (violation->empty() || (named_here && miss < least_miss))) {
        *violation = v;
        named_here = true;
      }
      least_miss = std::min(least_miss, miss);
      continue;
    }
    const double d = rotary_distance(k, s.axes, near) + (extra_cost ? extra_cost(s.axes) : 0.0);
    if (d < best) {
      best = d;
      out = s.axes;
      if (singular) *singular = s.singular;
    }
  }
  return std::isfinite(best);
}
}  // namespace

bool nearest_solution(const Kinematics& k, const Posed& pose, const Axes& near, Axes& out, std::string* violation,
                      bool* singular, const std::function<double(const Axes&)>& extra_cost) {
  thread_local std::vector<Solution> sols;
  k.inverse_branches(pose, &near, sols);
  return choose_nearest(k, sols, near, out, violation, singular, extra_cost);
}

bool nearest_solution(const Kinematics& k, const std::vector<Solution>& branches, const Axes& near, Axes& out,
                      std::string* violation, bool* singular, const std::function<double(const Axes&)>& extra_cost) {
  thread_local std::vector<Solution> sols;
  sols = branches;
  return choose_nearest(k, sols, near, out, violation, singular, extra_cost);
}

bool track(const Kinematics& k, const Axes& from, const Posed& p0, const Posed& p1,
           const std::vector<Solution>& p1_branches, Axes& out, std::string* violation, bool* singular,
           double max_step_rad) {
  return track_rec(k, from, p0, p1, 0, out, violation, singular, max_step_rad, nullptr, &p1_branches);
}

bool track(const Kinematics& k, const Axes& from, const Posed& p0, const Posed& p1, Axes& out, std::string* violation,
           bool* singular, double max_step_rad) {
  return track_rec(k, from, p0, p1, 0, out, violation, singular, max_step_rad);
}

bool track_checked(const Kinematics& k, const Axes& from, const Posed& p0, const Posed& p1, Axes& out, bool& jumped,
                   std::string* violation, double max_step_rad) {
  jumped = false;
  return track_rec(k, from, p0, p1, 0, out, violation, nullptr, max_step_rad, &jumped);
}

bool axial_retract_point(const Eigen::Vector3d& tip_mm, const Eigen::Vector3d& axis, double plane_z_mm, double slack_mm,
                         Eigen::Vector3d& up_mm) {
  if (tip_mm.z() >= plane_z_mm - slack_mm) return false;
  const Eigen::Vector3d dir =
      axis.z() >= kMinRetractAxisZ ? Eigen::Vector3d(axis.normalized()) : Eigen::Vector3d::UnitZ();
  up_mm = tip_mm + (plane_z_mm - tip_mm.z()) / dir.z() * dir;
  return true;
}

bool retract_along_axis(const Kinematics& k, const Axes& q, double plane_z_mm, double slack_mm, Axes& out,
                        Eigen::Vector3d* up_mm) {
  const Posed p = k.forward(q);
  Eigen::Vector3d up;
  if (!axial_retract_point(p.tip_mm, p.axis, plane_z_mm, slack_mm, up)) {
    out = q;
    if (up_mm) *up_mm = p.tip_mm;
    return true;
  }
  if (up_mm) *up_mm = up;
  return nearest_solution(k, Posed{up, p.axis}, q, out);
}

bool reposition_at_plane(const Kinematics& k, const Axes& q_from, const Axes& q_to, double plane_z_mm, double slack_mm,
                         Axes& up, Axes& turned, Axes& above) {
  if (!retract_along_axis(k, q_to, plane_z_mm, slack_mm, above) ||
      !retract_along_axis(k, q_from, plane_z_mm, slack_mm, up))
    return false;
  turned = up;
  if (!nearest_solution(k, Posed{k.forward(up).tip_mm, k.forward(q_to).axis}, above, turned)) turned = up;
  return true;
}

}  // namespace cscam::kin
