#include "cscam/cspace/machine_scene.hpp"

#include <fmt/format.h>

#include "cscam/core/error.hpp"

namespace cscam::cspace {

geom::ToolShape tool_on_machine(const machine::Machine& machine, double diameter_mm, double corner_radius_mm,
                                double flute_length_mm) {
  geom::ToolDefaults d;
  const auto& g = machine.geometry;
  if (g.holder_diameter_mm > 0) d.holder_diameter_mm = g.holder_diameter_mm;
  if (g.holder_length_mm > 0) d.holder_length_mm = g.holder_length_mm;
  if (g.spindle_diameter_mm > 0) d.spindle = {g.spindle_diameter_mm, g.spindle_length_mm};
  return geom::ToolShape::from_cutter(diameter_mm, corner_radius_mm, flute_length_mm, d);
}

int link_of(const machine::MachineBody& body) { return body.axis < 0 ? 0 : 1 + body.axis; }

geom::Mesh body_mesh(const machine::MachineBody& body, geom::MeshCheckReport* report) {
  const std::string what = fmt::format("{}: machine body '{}'", body.where.str(), body.name);
  switch (body.shape) {
    case machine::BodyShape::Box:
      return geom::box_mesh(body.min_mm, body.max_mm, what);
    case machine::BodyShape::Cylinder:
      return geom::cylinder_mesh(body.from_mm, body.to_mm, body.diameter_mm, 32, what);
    case machine::BodyShape::Mesh:
      return geom::load_checked_mesh(body.mesh, body.mesh_scale, {}, report);
  }
  throw InputError(body.where, "unknown machine body shape");
}

MachineBodiesSummary add_machine_bodies(const machine::Machine& m, double head_lift_mm, geom::Scene& fixed,
                                        geom::Scene& head) {
  MachineBodiesSummary out;
  const Eigen::Vector3d up = m.serial ? m.serial->tool_direction_home.normalized() : Eigen::Vector3d::UnitZ();
  for (const machine::MachineBody& b : m.geometry.bodies) {
    geom::MeshCheckReport report;
    geom::Mesh mesh = body_mesh(b, &report);
    if (b.shape == machine::BodyShape::Mesh) out.mesh_reports.push_back(std::move(report));
    const std::string name = "machine " + b.name;
    if (b.side == machine::BodySide::Head) {
      Eigen::Isometry3d lift = Eigen::Isometry3d::Identity();
      lift.translation() = head_lift_mm * up;
      mesh.transform(lift);
      head.add(name, geom::ObstacleRole::Machine, std::move(mesh), link_of(b));
      ++out.head_bodies;
    } else {
      fixed.add(name, geom::ObstacleRole::Machine, std::move(mesh), link_of(b));
      ++out.fixed_bodies;
    }
  }
  return out;
}

}  // namespace cscam::cspace
