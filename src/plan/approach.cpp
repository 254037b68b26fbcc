// Approach and retract moves along the chosen tool axis.
#include "detail/search.hpp"

namespace cscam::plan::detail {

bool is_axial_approach(const cl::Program& cl, std::size_t m, std::size_t ref) {
  // The CL values decide whether `m` is an approach (retract) along the axis of `ref`.
  const cl::Move& orig_m = cl.moves[m];
  const Eigen::Vector3d cl_ref_tip = cl.moves[ref].tip_in_part_mm,
                        cl_ref_axis = cl.moves[ref].axis_in_part.normalized();
  const Eigen::Vector3d d = orig_m.tip_in_part_mm - cl_ref_tip;
  const double len = d.norm();
  constexpr double kAxialRad = 1e-3;  // CL files print 4-5 decimals: far below this
  if (len < 1e-6 || d.dot(cl_ref_axis) < len * std::cos(kAxialRad)) return false;
  return orig_m.axis_in_part.normalized().dot(cl_ref_axis) >= std::cos(kAxialRad);
}

bool along_chosen_axis(const kin::Kinematics& kin, const cl::Program& cl, Plan& plan, std::size_t m, std::size_t ref) {
  if (!is_axial_approach(cl, m, ref)) return false;
  const Eigen::Vector3d cl_ref_tip = cl.moves[ref].tip_in_part_mm,
                        cl_ref_axis = cl.moves[ref].axis_in_part.normalized();
  const double len = (cl.moves[m].tip_in_part_mm - cl_ref_tip).norm();
  const kin::Posed ref_pose = kin.forward(plan.axes[ref]);
  if (ref_pose.axis.dot(cl_ref_axis) > 1.0 - 1e-12 && (ref_pose.tip_mm - cl_ref_tip).norm() < 1e-9) return false;
  kin::Axes q = plan.axes[ref];
  const kin::Posed target{ref_pose.tip_mm + len * ref_pose.axis, ref_pose.axis};
  if (!kin.solve_for_rotaries(target, q) || !kin.check_limits(q).empty() || !kin.passive_violation(q).empty())
    return false;
  plan.axes[m] = q;
  const kin::Posed tp = kin.forward(q);
  plan.program.moves[m].tip_in_part_mm = tp.tip_mm;
  plan.program.moves[m].axis_in_part = tp.axis;
  plan.replaced_moves.push_back(m);
  return true;
}

}  // namespace cscam::plan::detail
