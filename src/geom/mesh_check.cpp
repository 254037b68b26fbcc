// The only translation unit that includes CGAL (its headers cost ~30 s of compile time each).
#include "cscam/geom/mesh_check.hpp"

#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <CGAL/Polygon_mesh_processing/connected_components.h>
#include <CGAL/Polygon_mesh_processing/orient_polygon_soup.h>
#include <CGAL/Polygon_mesh_processing/orientation.h>
#include <CGAL/Polygon_mesh_processing/polygon_soup_to_polygon_mesh.h>
#include <CGAL/Polygon_mesh_processing/repair_degeneracies.h>
#include <CGAL/Polygon_mesh_processing/repair_polygon_soup.h>
#include <CGAL/Polygon_mesh_processing/self_intersections.h>
#include <CGAL/Polygon_mesh_processing/shape_predicates.h>
#include <CGAL/Polygon_mesh_processing/stitch_borders.h>
#include <CGAL/Surface_mesh.h>
#include <fmt/format.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <map>
#include <set>

#include "cscam/core/error.hpp"

namespace cscam::geom {

namespace {

namespace PMP = CGAL::Polygon_mesh_processing;
using Kernel = CGAL::Exact_predicates_inexact_constructions_kernel;
using Point = Kernel::Point_3;
using SurfaceMesh = CGAL::Surface_mesh<Point>;
using Face = SurfaceMesh::Face_index;
using Polygon = std::vector<std::size_t>;

std::string fmt_point(const Point& p) { return fmt::format("({:.6g}, {:.6g}, {:.6g})", p.x(), p.y(), p.z()); }

/// A triangle keyed by its three positions in lexicographic order, with the parity of the sorting
/// permutation: two windings of the same three points have opposite parities.
using TriKey = std::array<double, 9>;
TriKey tri_key(std::array<Point, 3> p, bool& odd) {
  odd = false;
  // Three-element bubble sort, counting swaps.
  for (int pass = 0; pass < 2; ++pass)
    for (int i = 0; i + 1 < 3 - pass; ++i)
      if (p[static_cast<std::size_t>(i + 1)] < p[static_cast<std::size_t>(i)]) {
        std::swap(p[static_cast<std::size_t>(i)], p[static_cast<std::size_t>(i + 1)]);
        odd = !odd;
      }
  TriKey k{};
  for (std::size_t i = 0; i < 3; ++i)
    for (int c = 0; c < 3; ++c) k[3 * i + static_cast<std::size_t>(c)] = p[i][c];
  return k;
}

std::array<Point, 3> face_points(const SurfaceMesh& sm, Face f) {
  std::array<Point, 3> p;
  std::size_t i = 0;
  for (auto v : CGAL::vertices_around_face(sm.halfedge(f), sm)) {
    if (i < 3) p[i] = sm.point(v);
    ++i;
  }
  return p;
}

std::string fmt_face(const SurfaceMesh& sm, Face f) {
  const auto p = face_points(sm, f);
  return fmt::format("{} {} {}", fmt_point(p[0]), fmt_point(p[1]), fmt_point(p[2]));
}

/// Signed volume (x6) of the faces of one component, about a reference point (divergence theorem).
double six_volume(const SurfaceMesh& sm, const std::vector<Face>& faces, const Point& o) {
  double v = 0.0;
  for (Face f : faces) {
    const auto p = face_points(sm, f);
    const Kernel::Vector_3 a = p[0] - o, b = p[1] - o, c = p[2] - o;
    v += a * CGAL::cross_product(b, c);
  }
  return v;
}

}  // namespace

MeshCheckReport check_and_repair(Mesh& mesh, const MeshCheckOptions& options) {
  MeshCheckReport r;
  r.source = mesh.source;
  r.vertices_in = mesh.vertices_mm.size();
  // Triangles that name one vertex twice once welded were dropped at load: reported here with the others.
  r.triangles_in = mesh.triangles.size() + mesh.collapsed_at_load;
  r.repeated_index_faces_removed = mesh.collapsed_at_load;
  const SourceLoc where{mesh.source.empty() ? std::string("mesh") : mesh.source};
  if (mesh.triangles.empty()) {
    r.error = "mesh has no triangles";
    return r;
  }

  // Polygon soup, validated.
  std::vector<Point> points;
  points.reserve(mesh.vertices_mm.size());
  for (const auto& v : mesh.vertices_mm) {
    if (!v.allFinite()) throw InputError(where, "mesh has a non-finite vertex");
    points.emplace_back(v.x(), v.y(), v.z());
  }
  std::vector<Polygon> polygons;
  polygons.reserve(mesh.triangles.size());
  for (std::size_t t = 0; t < mesh.triangles.size(); ++t) {
    const auto& tri = mesh.triangles[t];
    for (int k = 0; k < 3; ++k)
      if (tri[k] < 0 || static_cast<std::size_t>(tri[k]) >= points.size())
        throw InputError(where,
                         fmt::format("triangle {} has vertex index {} out of range [0, {})", t, tri[k], points.size()));
    polygons.push_back(
        {static_cast<std::size_t>(tri[0]), static_cast<std::size_t>(tri[1]), static_cast<std::size_t>(tri[2])});
  }
  // The input windings, to count the triangles the repair reversed.
  std::map<TriKey, bool> input_winding;
  for (const Polygon& p : polygons) {
    bool odd = false;
    const TriKey k = tri_key({points[p[0]], points[p[1]], points[p[2]]}, odd);
    input_winding.emplace(k, odd);
  }

  // 1. Vertices at identical positions (the loader already welds within 1e-7 of the diagonal).
  r.duplicate_vertices_merged = PMP::merge_duplicate_points_in_polygon_soup(points, polygons);
  // 2. Triangles naming a vertex twice, and the same triangle twice.
  {
    std::vector<Polygon> kept;
    kept.reserve(polygons.size());
    std::set<std::array<std::size_t, 3>> seen;
    for (const Polygon& p : polygons) {
      if (p[0] == p[1] || p[1] == p[2] || p[0] == p[2]) {
        ++r.repeated_index_faces_removed;
        continue;
      }
      std::array<std::size_t, 3> s{p[0], p[1], p[2]};
      std::sort(s.begin(), s.end());
      if (!seen.insert(s).second) {
        ++r.duplicate_faces_removed;
        continue;
      }
      kept.push_back(p);
    }
    polygons = std::move(kept);
  }
  if (polygons.empty()) {
    r.error = "mesh has no triangle of non-zero size";
    return r;
  }
  // 3. Consistent orientation; a vertex where the surface is not a disc is duplicated.
  const std::size_t n_points = points.size();
  PMP::orient_polygon_soup(points, polygons);
  r.non_manifold_vertices_split = points.size() - n_points;

  SurfaceMesh sm;
  PMP::polygon_soup_to_polygon_mesh(points, polygons, sm);
  // 4. Seams: border edges with coincident end points.
  r.border_edges_stitched = PMP::stitch_borders(sm);
  // 5. Zero-area triangles, removed by collapsing or flipping edges (leaves no hole).
  std::size_t degenerate = 0;
  for (Face f : sm.faces())
    if (PMP::is_degenerate_triangle_face(f, sm)) ++degenerate;
  if (degenerate > 0) {
    PMP::remove_degenerate_faces(sm);
    sm.collect_garbage();
    for (Face f : sm.faces())
      if (PMP::is_degenerate_triangle_face(f, sm)) ++r.degenerate_faces_left;
    // Counted as the degenerate triangles that are gone: an edge flip repairs one without changing the count.
    r.degenerate_faces_removed = degenerate - std::min(degenerate, r.degenerate_faces_left);
  }
  sm.collect_garbage();

  // State: borders, components, self-intersections.
  std::string border_example;
  for (auto h : sm.halfedges())
    if (sm.is_border(h)) {
      ++r.border_edges;
      if (border_example.empty())
        border_example = fmt::format("{} - {}", fmt_point(sm.point(sm.source(h))), fmt_point(sm.point(sm.target(h))));
    }
  r.closed = r.border_edges == 0;
  auto component = sm.add_property_map<Face, std::size_t>("f:cscam_component", 0).first;
  r.components = PMP::connected_components(sm, component);
  std::vector<std::pair<Face, Face>> crossings;
  PMP::self_intersections(sm.faces(), sm, std::back_inserter(crossings));
  std::string crossing_example;
  for (const auto& [f, g] : crossings) {
    if (f == g) continue;  // a degenerate face, counted above
    if (component[f] == component[g]) {
      if (r.self_intersections++ == 0) crossing_example = fmt::format("{} and {}", fmt_face(sm, f), fmt_face(sm, g));
    } else {
      ++r.component_overlaps;
    }
  }

  // 6. Outward orientation of closed components (nested shells: the outer outward, a cavity inward).
  if (r.closed && r.self_intersections == 0) {
    if (r.component_overlaps == 0) {
      PMP::orient_to_bound_a_volume(sm);
    } else {
      // Overlapping solids: no nesting to respect, each component outward on its own.
      std::vector<std::vector<Face>> by_component(r.components);
      for (Face f : sm.faces()) by_component[component[f]].push_back(f);
      const Point o = sm.point(*sm.vertices().begin());
      for (const auto& faces : by_component)
        if (six_volume(sm, faces, o) < 0.0) PMP::reverse_face_orientations(faces, sm);
    }
  }

  // Back to a Mesh (only the vertices still used).
  Mesh out;
  out.source = mesh.source;
  std::vector<int> index(sm.number_of_vertices() + sm.number_of_removed_vertices(), -1);
  for (auto v : sm.vertices()) {
    if (sm.is_isolated(v)) continue;
    index[v.idx()] = static_cast<int>(out.vertices_mm.size());
    const Point& p = sm.point(v);
    out.vertices_mm.emplace_back(p.x(), p.y(), p.z());
  }
  out.triangles.reserve(sm.number_of_faces());
  for (Face f : sm.faces()) {
    std::array<int, 3> t{};
    std::size_t i = 0;
    for (auto v : CGAL::vertices_around_face(sm.halfedge(f), sm))
      if (i < 3) t[i++] = index[v.idx()];
    out.triangles.emplace_back(t[0], t[1], t[2]);
    bool odd = false;
    const auto it = input_winding.find(tri_key(face_points(sm, f), odd));
    if (it != input_winding.end() && it->second != odd) ++r.faces_reoriented;
  }
  r.vertices_out = out.vertices_mm.size();
  r.triangles_out = out.triangles.size();
  if (r.closed) r.volume_mm3 = out.signed_volume_mm3();

  // What was done, and the verdict.
  if (r.duplicate_vertices_merged)
    r.repairs.push_back(fmt::format("merged {} duplicate vertices", r.duplicate_vertices_merged));
  if (r.repeated_index_faces_removed)
    r.repairs.push_back(fmt::format("removed {} triangles that name one vertex twice", r.repeated_index_faces_removed));
  if (r.duplicate_faces_removed)
    r.repairs.push_back(fmt::format("removed {} duplicated triangles", r.duplicate_faces_removed));
  if (r.non_manifold_vertices_split)
    r.repairs.push_back(fmt::format("split {} non-manifold vertices", r.non_manifold_vertices_split));
  if (r.border_edges_stitched)
    r.repairs.push_back(fmt::format("stitched {} pairs of border edges", r.border_edges_stitched));
  if (r.degenerate_faces_removed)
    r.repairs.push_back(
        fmt::format("removed {} zero-area triangles (edge collapse or flip)", r.degenerate_faces_removed));
  if (r.faces_reoriented)
    r.repairs.push_back(fmt::format("reversed the winding of {} of {} triangles (consistent, outward orientation)",
                                    r.faces_reoriented, r.triangles_out));
  if (r.degenerate_faces_left)
    r.warnings.push_back(fmt::format("{} zero-area triangles could not be removed", r.degenerate_faces_left));
  if (r.component_overlaps)
    r.warnings.push_back(fmt::format("{} separate solids overlap ({} pairs of crossing triangles); kept as a union",
                                     r.components, r.component_overlaps));

  if (r.self_intersections > 0) {
    r.error = fmt::format(
        "the surface crosses itself: {} pairs of triangles of one connected piece intersect "
        "(e.g. {}), so inside and outside are undefined",
        r.self_intersections, crossing_example);
  } else if (!r.closed && options.use == MeshUse::Solid) {
    r.error = fmt::format(
        "the mesh is open after repair: {} border edges (e.g. edge {}); a collision obstacle "
        "must be a closed solid",
        r.border_edges, border_example);
  } else if (!options.repair && r.repaired()) {
    std::string what;
    for (const auto& s : r.repairs) what += (what.empty() ? "" : "; ") + s;
    r.error = fmt::format("the mesh needs repair ({}) and repair is off", what);
  } else if (r.closed && !(r.volume_mm3 > 0.0)) {
    r.error = fmt::format("the closed mesh encloses no positive volume ({:.6g} mm^3)", r.volume_mm3);
  }
  if (!r.closed && options.use == MeshUse::Surface)
    r.warnings.push_back(fmt::format("open surface: {} border edges", r.border_edges));

  if (options.repair && r.trusted()) mesh = std::move(out);
  return r;
}

MeshCheckReport require_trusted(Mesh& mesh, const MeshCheckOptions& options) {
  MeshCheckReport r = check_and_repair(mesh, options);
  if (!r.trusted()) throw InputError(SourceLoc{mesh.source.empty() ? std::string("mesh") : mesh.source}, r.error);
  return r;
}

Mesh load_checked_mesh(const std::string& path, double scale_to_mm, const MeshCheckOptions& options,
                       MeshCheckReport* report) {
  Mesh mesh = load_mesh(path, scale_to_mm, /*require_closed=*/false);
  mesh.source = path;
  MeshCheckReport r = require_trusted(mesh, options);
  if (report) *report = std::move(r);
  return mesh;
}

}  // namespace cscam::geom
