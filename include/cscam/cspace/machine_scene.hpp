#pragma once
/// @file
/// The machine in the collision scene: the bodies of a machine file (geometry.bodies, head_mesh,
/// table_mesh) as obstacles placed per axis configuration.
///
/// Bodies are given in the machine frame with every axis at 0. A body on the base or a table-side link goes
/// into the fixed scene (checked against the tool and the head bodies); a body on a head-side link goes into
/// the head scene (checked against the part, the fixtures and the fixed machine bodies). Each gets the link
/// of its joint (0: base, 1 + axis index), which cspace::Space places with Kinematics::link_in_part.
#include <string>
#include <vector>

#include "cscam/geom/mesh.hpp"
#include "cscam/geom/mesh_check.hpp"
#include "cscam/geom/scene.hpp"
#include "cscam/machine/machine.hpp"

namespace cscam::cspace {

/// The geom::Scene link of a body: 0 for the base, 1 + axis index otherwise.
[[nodiscard]] int link_of(const machine::MachineBody& body);

/// The body's surface in the machine frame at home: a box, a circumscribed 32-sided prism for a cylinder
/// (conservative), or the mesh file loaded, validated and repaired (its report in `report` if not null).
/// @throws InputError naming the machine file and body, or the mesh file, when the body cannot be trusted.
[[nodiscard]] geom::Mesh body_mesh(const machine::MachineBody& body, geom::MeshCheckReport* report = nullptr);

/// What add_machine_bodies() added.
struct MachineBodiesSummary {
  std::size_t fixed_bodies = 0;                     ///< base and table-side bodies added to the fixed scene
  std::size_t head_bodies = 0;                      ///< head-side bodies added to the head scene
  std::vector<geom::MeshCheckReport> mesh_reports;  ///< one per mesh body
};

/// Adds the machine's bodies (geometry.bodies) to the scenes (before they are built): base and table side
/// to `fixed`, head side to `head`, named "machine <name>". Head-side bodies are lifted by `head_lift_mm`
/// along the home tool direction: the holder of the checked tool shape ends that far above the kinematic
/// gauge point (see docs/machine-geometry.md).
/// The checked tool of a cutter (diameter, corner radius, flute length, mm) on this machine: shank by default, holder
/// and spindle nose from the machine file's geometry where it gives them.
[[nodiscard]] geom::ToolShape tool_on_machine(const machine::Machine& machine, double diameter_mm,
                                              double corner_radius_mm, double flute_length_mm);

MachineBodiesSummary add_machine_bodies(const machine::Machine& machine, double head_lift_mm, geom::Scene& fixed,
                                        geom::Scene& head);

}  // namespace cscam::cspace
