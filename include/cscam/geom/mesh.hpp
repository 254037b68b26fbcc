#pragma once
/// @file
/// Triangle meshes: loading (assimp), closedness checks, transforms, binary STL output.
///
/// All coordinates are in millimetres, in whatever frame the mesh was given in (normally the part
/// frame). Triangles are wound counter-clockwise seen from outside (outward normals), which the
/// closedness check verifies as "consistently oriented"; signed_volume_mm3() > 0 then tells that
/// the orientation is outward rather than inward.
#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstddef>
#include <string>
#include <vector>

namespace cscam::geom {

/// An indexed triangle mesh in millimetres.
struct Mesh {
  std::vector<Eigen::Vector3d> vertices_mm;  ///< vertex positions, mm
  std::vector<Eigen::Vector3i> triangles;    ///< indices into vertices_mm, counter-clockwise seen from outside
  std::string source;                        ///< where it came from (file path or generator name), for messages
  /// Triangles the loader dropped because two of their corners are one vertex (after welding): counted, so that the
  /// check's report says so (check_and_repair).
  std::size_t collapsed_at_load = 0;

  /// Number of triangles.
  [[nodiscard]] std::size_t triangle_count() const { return triangles.size(); }

  /// Axis-aligned bounding box of the vertices (empty box for an empty mesh).
  [[nodiscard]] Eigen::AlignedBox3d bounding_box() const;

  /// True when every edge is shared by exactly two triangles that traverse it in opposite
  /// directions (a closed, consistently oriented 2-manifold surface).
  /// @param why if not null and the mesh is not closed, receives a one-line explanation: the counts of
  ///            boundary, non-manifold and inconsistently oriented edges and one example edge with its
  ///            end-point coordinates.
  [[nodiscard]] bool is_closed(std::string* why = nullptr) const;

  /// Signed enclosed volume (mm^3) by the divergence theorem. Positive for a closed mesh with outward
  /// normals; meaningless for an open mesh.
  [[nodiscard]] double signed_volume_mm3() const;

  /// Total surface area, mm^2.
  [[nodiscard]] double area_mm2() const;

  /// Applies `x -> T * x` to every vertex (T maps the current frame to the new one, in mm).
  void transform(const Eigen::Isometry3d& T);

  /// Appends another mesh (vertices are not welded).
  void append(const Mesh& other);
};

/// Loads a triangle mesh with assimp (STL ASCII/binary, OBJ, PLY, OFF, 3MF, ... whatever assimp reads).
///
/// All meshes of the file's scene are merged, each with its node's accumulated transform; polygons are
/// triangulated; coincident vertices are welded (assimp's JoinIdenticalVertices after dropping
/// normals/UVs, then a position weld with a tolerance of 1e-7 of the bounding-box diagonal across
/// sub-meshes); triangles that became degenerate by welding are dropped; points and lines are ignored.
///
/// @param path          file to read
/// @param scale_to_mm   multiply the file's coordinates by this (e.g. 25.4 for a file in inches)
/// @param require_closed reject meshes that are not closed (see Mesh::is_closed) — obstacle meshes must
///                      be closed for the collision checker to mean what it says
/// @throws InputError   "path: ..." when the file cannot be opened, assimp fails (its error string is
///                      included), the file holds no triangles, or (require_closed) the mesh is open,
///                      non-manifold or inconsistently oriented.
[[nodiscard]] Mesh load_mesh(const std::string& path, double scale_to_mm = 1.0, bool require_closed = true);

/// A closed, outward-oriented box mesh of the axis-aligned box [min_mm, max_mm] (12 triangles).
/// @throws InputError when a side is not positive (names `source`).
[[nodiscard]] Mesh box_mesh(const Eigen::Vector3d& min_mm, const Eigen::Vector3d& max_mm,
                            const std::string& source = "box");

/// A closed, outward-oriented prism that contains the cylinder of diameter `diameter_mm` between the centres
/// of its end faces `from_mm` and `to_mm`: a regular polygon with `sides` sides circumscribed about the
/// circle (its vertices lie at radius r / cos(pi / sides)), so a collision test against it is conservative
/// by at most r (1 / cos(pi / sides) - 1) (0.5 % of r with 32 sides).
/// @throws InputError for a non-positive diameter or length or fewer than 3 sides (names `source`).
[[nodiscard]] Mesh cylinder_mesh(const Eigen::Vector3d& from_mm, const Eigen::Vector3d& to_mm, double diameter_mm,
                                 int sides = 32, const std::string& source = "cylinder");

/// Writes a binary STL (little endian), atomically: nothing is left at `path` if writing fails.
/// Coordinates are written in mm as 32-bit floats. Does not require the mesh to be closed.
/// @throws InputError "path: ..." when the directory does not exist or the file cannot be written.
void save_stl(const Mesh& mesh, const std::string& path);

}  // namespace cscam::geom
