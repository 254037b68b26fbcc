#pragma once
/// @file
/// Continuous IK tracking: follow the tool pose from p0 to p1 (tip linear, axis along the great circle)
/// starting from a known solution, choosing at every small step the solution nearest the previous one.
/// This is how a solution branch is continued without flips; near the singularity the tilt azimuth turns
/// fast and a single "nearest solution" jump could land on a branch the motion cannot reach.
#include <functional>
#include <string>

#include "cscam/kin/kinematics.hpp"

namespace cscam::kin {

/// Tracks from `from` (a solution at p0) to p1. Returns false (and the first limit broken, if any) when
/// no solution inside the limits continues the motion. `max_step_rad` bounds the rotary change per step.
bool track(const Kinematics& k, const Axes& from, const Posed& p0, const Posed& p1, Axes& out,
           std::string* violation = nullptr, bool* singular = nullptr, double max_step_rad = 0.0872664626);

/// Tracking that also says whether it had to jump: `jumped` is set when no continuous motion inside the
/// limits exists (a limit or the branch structure forces a flip or an unwind, seen as a rotary step larger
/// than `max_step_rad` that does not shrink when the pose step does).
bool track_checked(const Kinematics& k, const Axes& from, const Posed& p0, const Posed& p1, Axes& out, bool& jumped,
                   std::string* violation = nullptr, double max_step_rad = 0.0872664626);

/// Among the IK solutions of `pose` (windings adjusted to `near`), the one nearest `near` in rotary
/// travel that lies inside every limit, the passive joints of a PKM included. `extra_cost`, when given,
/// is added to the rotary travel (e.g. a large penalty for the branch a post's rule avoids). This is the
/// one place where a solution is chosen by nearness: the post, the conventional strategy and tracking use it.
bool nearest_solution(const Kinematics& k, const Posed& pose, const Axes& near, Axes& out,
                      std::string* violation = nullptr, bool* singular = nullptr,
                      const std::function<double(const Axes&)>& extra_cost = {});

/// nearest_solution and track with the IK branches of the target pose computed beforehand (e.g. in parallel):
/// `branches` = inverse_branches(pose, hint) for a hint that does not matter, i.e. no branch is singular (the
/// hint only fills a singular branch's free angle). The same choice as without them.
bool nearest_solution(const Kinematics& k, const std::vector<Solution>& branches, const Axes& near, Axes& out,
                      std::string* violation = nullptr, bool* singular = nullptr,
                      const std::function<double(const Axes&)>& extra_cost = {});
bool track(const Kinematics& k, const Axes& from, const Posed& p0, const Posed& p1,
           const std::vector<Solution>& p1_branches, Axes& out, std::string* violation = nullptr,
           bool* singular = nullptr, double max_step_rad = 0.0872664626);

/// A retract direction counts as the tool axis only if the axis points up at least this much (cos of the tilt);
/// a flatter axis retracts straight up.
inline constexpr double kMinRetractAxisZ = 0.1;

/// Where a machine without a Z axis (a PKM) retracts to: the tip moved along the tool axis (straight up for an axis
/// flatter than kMinRetractAxisZ) up to the plane z = `plane_z_mm` of the part frame. False when the tip is there
/// already (within `slack_mm`).
bool axial_retract_point(const Eigen::Vector3d& tip_mm, const Eigen::Vector3d& axis, double plane_z_mm, double slack_mm,
                         Eigen::Vector3d& up_mm);

/// The axis values (nearest `q`, inside every limit) that put the tip of q at its axial_retract_point with q's tool
/// axis: `out` = q when no retract is needed. False when no such values exist. The post retracts and approaches
/// this way, and the planner keeps the ends of its segments where this succeeds (one rule for both).
bool retract_along_axis(const Kinematics& k, const Axes& q, double plane_z_mm, double slack_mm, Axes& out,
                        Eigen::Vector3d* up_mm = nullptr);

/// How a machine without a Z axis (the XMINI) turns its tool between two poses whose rotaries differ: retract along
/// the tool axis to the plane (`up` = retract_along_axis of q_from), turn there to the tool axis of q_to with the
/// tip kept (`turned`, nearest `above`; `up` itself where that axis cannot be had there: the turn then happens on
/// the way), move to above the target (`above` = retract_along_axis of q_to) and plunge. The post writes these
/// moves and the planner's swept check sweeps them. False when a retract leaves the limits.
bool reposition_at_plane(const Kinematics& k, const Axes& q_from, const Axes& q_to, double plane_z_mm, double slack_mm,
                         Axes& up, Axes& turned, Axes& above);

}  // namespace cscam::kin
