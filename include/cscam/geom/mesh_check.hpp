#pragma once
/// @file
/// Validation and safe repair of obstacle meshes (CGAL Polygon Mesh Processing).
///
/// Part, fixture and machine meshes exported by CAM systems are often open (unstitched seams), hold
/// duplicated vertices and zero-area triangles, are inconsistently or inward oriented, or cross
/// themselves. The collision checker works on triangle surfaces, so such a mesh gives answers that look
/// right and are not (a tool inside an open solid, an "outward" test that is inverted). check_and_repair()
/// fixes what can be fixed without guessing geometry and says what it did; what cannot be trusted
/// afterwards is an error naming the file.
///
/// Repairs (in this order): merge vertices at identical positions; drop triangles with a repeated vertex
/// and duplicated triangles; orient the triangles consistently (a non-manifold vertex is split); stitch
/// coincident border edges; remove zero-area triangles (edge collapse / flip, so no hole is left); orient
/// every closed component outward (nested shells bound the volume between them).
///
/// Untrusted (MeshCheckReport::error is set): a mesh still open after repair when a closed solid is
/// needed (MeshUse::Solid), and a connected component whose triangles cross each other. Separate closed
/// components that overlap (an assembly of solids) are kept with a warning: their union is still a
/// correct obstacle for the surface-based checker.
#include <cstddef>
#include <limits>
#include <string>
#include <vector>

#include "cscam/geom/mesh.hpp"

namespace cscam::geom {

/// What the mesh is used for.
enum class MeshUse {
  Solid,    ///< a collision obstacle: must be closed after repair
  Surface,  ///< an open surface is acceptable (reported as a warning)
};

/// How to check a mesh.
struct MeshCheckOptions {
  MeshUse use = MeshUse::Solid;
  bool repair = true;  ///< false: a mesh that would need a repair is an error (diagnose only)
};

/// What check_and_repair() found and did. Counts refer to triangles and vertices of the mesh.
struct MeshCheckReport {
  std::string source;  ///< the mesh's source (file path), for messages
  std::size_t vertices_in = 0, triangles_in = 0;
  std::size_t vertices_out = 0, triangles_out = 0;

  // Repairs made.
  std::size_t duplicate_vertices_merged = 0;    ///< vertices at the same position as an earlier one
  std::size_t repeated_index_faces_removed = 0; ///< triangles naming one vertex twice
  std::size_t duplicate_faces_removed = 0;      ///< triangles over the same three vertices as another
  std::size_t non_manifold_vertices_split = 0;  ///< vertices duplicated to make the surface orientable
  std::size_t border_edges_stitched = 0;        ///< pairs of coincident border edges joined
  std::size_t degenerate_faces_removed = 0;     ///< zero-area triangles removed (collapsed or flipped away)
  std::size_t faces_reoriented = 0;             ///< triangles whose winding was reversed (net, vs the input)

  // State after repair.
  bool closed = false;                  ///< no border edge
  std::size_t border_edges = 0;         ///< edges with a triangle on one side only
  std::size_t components = 0;           ///< connected components (by shared edges)
  std::size_t self_intersections = 0;   ///< pairs of crossing triangles within one component
  std::size_t component_overlaps = 0;   ///< pairs of crossing triangles of different components
  std::size_t degenerate_faces_left = 0;
  double volume_mm3 = std::numeric_limits<double>::quiet_NaN();  ///< enclosed volume when closed (>0: outward)

  std::vector<std::string> repairs;   ///< one line per kind of repair made, for the user
  std::vector<std::string> warnings;  ///< tolerated defects
  std::string error;                  ///< why the mesh cannot be trusted; empty when it can

  [[nodiscard]] bool trusted() const { return error.empty(); }
  [[nodiscard]] bool repaired() const { return !repairs.empty(); }
};

/// Validates `mesh` and repairs it in place (unless options.repair is false). Never throws for a bad mesh:
/// the verdict is in the report (error). Cost: O(n log n); measured 0.27 s for 20k and 3.2 s for 200k
/// triangles (the benchmark part) on the shared 2-core sandbox under load.
/// @throws InputError only for a vertex index out of range or a non-finite vertex (names mesh.source).
[[nodiscard]] MeshCheckReport check_and_repair(Mesh& mesh, const MeshCheckOptions& options = {});

/// check_and_repair(), then throws InputError("source: error") when the mesh cannot be trusted.
MeshCheckReport require_trusted(Mesh& mesh, const MeshCheckOptions& options = {});

/// Loads a mesh (load_mesh in its child process, without its closedness test) and require_trusted() it.
/// @param report if not null, receives the report (also on success, to show the repairs as warnings)
/// @throws InputError from loading, or "path: ..." when the mesh cannot be trusted.
[[nodiscard]] Mesh load_checked_mesh(const std::string& path, double scale_to_mm = 1.0,
                                     const MeshCheckOptions& options = {}, MeshCheckReport* report = nullptr);

}  // namespace cscam::geom
