#include "cscam/geom/scene.hpp"

#include <fcl/geometry/bvh/BVH_model.h>
#include <fcl/geometry/shape/cylinder.h>
#include <fcl/math/bv/OBB.h>
#include <fcl/math/bv/RSS.h>
#include <fcl/narrowphase/collision.h>
#include <fcl/narrowphase/detail/gjk_solver_libccd.h>
#include <fcl/narrowphase/distance.h>
#include <fmt/format.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <optional>

#include "cscam/core/error.hpp"

namespace cscam::geom {

namespace {

// Two hierarchies per obstacle, both on FCL's const ("oriented") traversal path, so concurrent queries never
// modify the model (FCL's AABB path would re-transform the model's vertices in place):
// - collision: OBB. FCL computes the tool cylinder's OBB exactly (a specialisation), while for OBBRSS it fits
//   one to the cylinder's bound vertices by PCA on every query (heap allocation + eigen-solve, and a looser
//   box): on the 200k-triangle benchmark part OBB answers 3-4x faster than OBBRSS.
// - distance: RSS (OBB has no distance traversal in FCL; RSS builds faster than OBBRSS and queries as fast).
using CollideBvh = fcl::BVHModel<fcl::OBBd>;
using DistanceBvh = fcl::BVHModel<fcl::RSSd>;
constexpr double kInf = std::numeric_limits<double>::infinity();

/// Narrow phase. Collision: libccd (GJK/MPR), 3.5x faster than FCL's own GJK (GST_INDEP) on the benchmark.
/// Distance: GST_INDEP, ~10 % faster than libccd there, and exact on flat contacts (tests).
constexpr fcl::GJKSolverType kCollideSolver = fcl::GST_LIBCCD;
constexpr fcl::GJKSolverType kDistanceSolver = fcl::GST_INDEP;

template <typename Model>
std::shared_ptr<Model> make_bvh(const Mesh& mesh, const std::vector<fcl::Triangle>& tris, const std::string& name) {
  auto bvh = std::make_shared<Model>();
  int rc = bvh->beginModel(static_cast<int>(tris.size()), static_cast<int>(mesh.vertices_mm.size()));
  if (rc == fcl::BVH_OK) rc = bvh->addSubModel(mesh.vertices_mm, tris);
  if (rc == fcl::BVH_OK) rc = bvh->endModel();
  CSCAM_CHECK(rc == fcl::BVH_OK, fmt::format("FCL BVH build failed for obstacle '{}' (code {})", name, rc));
  bvh->computeLocalAABB();
  return bvh;
}

double aabb_gap(const Eigen::AlignedBox3d& a, const Eigen::AlignedBox3d& b) {
  const Eigen::Vector3d gap = (a.min() - b.max()).cwiseMax(b.min() - a.max()).cwiseMax(0.0);
  return gap.norm();
}

Eigen::AlignedBox3d transformed_box(const Eigen::AlignedBox3d& box, const Eigen::Isometry3d& T) {
  // Centre and half extents (|R| h): the same box as the eight transformed corners, without the eight products.
  if (box.isEmpty()) return box;
  const Eigen::Vector3d c = T * box.center();
  const Eigen::Vector3d h = T.linear().cwiseAbs() * (0.5 * box.sizes());
  return {c - h, c + h};
}

}  // namespace

// ---------------------------------------------------------------------------------------------------
// Tool shape
// ---------------------------------------------------------------------------------------------------

const char* to_string(ToolPart part) {
  switch (part) {
    case ToolPart::CutterBody:
      return "cutter_body";
    case ToolPart::Shank:
      return "shank";
    case ToolPart::Holder:
      return "holder";
    case ToolPart::Holder2:
      return "holder2";
    case ToolPart::Spindle:
      return "spindle";
  }
  return "?";
}

const char* to_string(ObstacleRole role) {
  switch (role) {
    case ObstacleRole::Part:
      return "part";
    case ObstacleRole::Fixture:
      return "fixture";
    case ObstacleRole::Machine:
      return "machine";
  }
  return "?";
}

ToolShape ToolShape::from_cutter(double diameter_mm, double corner_radius_mm, double flute_length_mm,
                                 const ToolDefaults& d) {
  ToolShape t;
  t.cutter = {diameter_mm, corner_radius_mm, flute_length_mm};
  t.shank = {d.shank_diameter_mm < 0.0 ? diameter_mm : d.shank_diameter_mm,
             d.shank_length_mm < 0.0 ? 2.0 * diameter_mm : d.shank_length_mm};
  t.holder = {d.holder_diameter_mm < 0.0 ? 2.5 * diameter_mm : d.holder_diameter_mm, d.holder_length_mm};
  t.holder2 = d.holder2;
  t.spindle = d.spindle;
  t.validate();
  return t;
}

void ToolShape::validate() const {
  const SourceLoc where{"tool"};
  const double D = cutter.diameter_mm, r = cutter.corner_radius_mm;
  if (!(D > 0.0) || !std::isfinite(D))
    throw InputError(where, fmt::format("cutter diameter must be positive, got {}", D));
  if (!(r >= 0.0 && r <= 0.5 * D + 1e-9))
    throw InputError(where, fmt::format("corner radius must be in [0, D/2 = {}], got {}", 0.5 * D, r));
  if (!(cutter.flute_length_mm > 0.0) || !std::isfinite(cutter.flute_length_mm))
    throw InputError(where, fmt::format("flute length must be positive, got {}", cutter.flute_length_mm));
  const std::pair<const char*, const CylinderStage*> stages[] = {
      {"shank", &shank}, {"holder", &holder}, {"holder2", &holder2}, {"spindle", &spindle}};
  for (const auto& [name, s] : stages)
    if (!(s->diameter_mm >= 0.0 && s->length_mm >= 0.0) || !std::isfinite(s->diameter_mm) ||
        !std::isfinite(s->length_mm))
      throw InputError(
          where, fmt::format("{} diameter and length must be >= 0, got {} and {}", name, s->diameter_mm, s->length_mm));
}

bool ToolShape::is_ball() const { return std::abs(cutter.corner_radius_mm - 0.5 * cutter.diameter_mm) <= 1e-9; }

double ToolShape::gauge_length_mm() const {
  double z = cutter.flute_length_mm;
  for (const CylinderStage* s : {&shank, &holder, &holder2})
    if (s->present()) z += s->length_mm;
  return z;
}

std::vector<ToolSegment> ToolShape::segments() const {
  std::vector<ToolSegment> out;
  out.push_back({ToolPart::CutterBody, 0.0, cutter.flute_length_mm, 0.5 * cutter.diameter_mm});
  double z = cutter.flute_length_mm;
  const std::pair<ToolPart, const CylinderStage*> stages[] = {{ToolPart::Shank, &shank},
                                                              {ToolPart::Holder, &holder},
                                                              {ToolPart::Holder2, &holder2},
                                                              {ToolPart::Spindle, &spindle}};
  for (const auto& [part, s] : stages) {
    if (!s->present()) continue;
    out.push_back({part, z, z + s->length_mm, 0.5 * s->diameter_mm});
    z += s->length_mm;
  }
  return out;
}

std::vector<ToolSegment> checked_segments(const ToolShape& tool, const CheckOptions& opt) {
  const double r = tool.cutter.corner_radius_mm;
  const double relief = opt.relief_mm >= 0.0 ? opt.relief_mm : (r > 0.0 ? 0.2 * r : 0.5);
  const double c = std::max(0.0, opt.clearance_mm);
  const std::vector<ToolSegment> all = tool.segments();
  std::vector<ToolSegment> out;
  const double e = std::max(0.0, opt.erosion_mm);
  auto keep = [&](ToolSegment s) {
    s.radius_mm -= e;
    s.z0_mm += e;
    s.z1_mm -= e;
    if (s.radius_mm > 1e-9 && s.z1_mm - s.z0_mm > 1e-9) out.push_back(s);
  };
  for (std::size_t i = 0; i < all.size(); ++i) {
    ToolSegment s = all[i];
    if (s.part == ToolPart::CutterBody) {
      if (!opt.check_cutter_body) continue;
      s.z0_mm = r + relief;
      s.radius_mm += std::max(0.0, opt.cutter_clearance_mm);
      // A cutter wider than the shank has an exposed top face: inflated upward too (a pose within the margin of
      // this one may lift that face by the margin).
      if (i + 1 < all.size() && all[i].radius_mm > all[i + 1].radius_mm)
        s.z1_mm += std::max(0.0, opt.cutter_clearance_mm);
      if (s.z1_mm - s.z0_mm <= 1e-9) continue;
      keep(s);
      continue;
    }
    // Inflate by the clearance; extend an end only where it is an exposed face (the neighbour is narrower or
    // absent), so that the inflated shank does not reach down into the cutting zone.
    const double below = i > 0 ? all[i - 1].radius_mm : 0.0;
    const double above = i + 1 < all.size() ? all[i + 1].radius_mm : 0.0;
    if (s.radius_mm > below) s.z0_mm -= c;
    if (s.radius_mm > above) s.z1_mm += c;
    s.radius_mm += c;
    keep(s);
  }
  return out;
}

// ---------------------------------------------------------------------------------------------------
// Scene
// ---------------------------------------------------------------------------------------------------

struct Obstacle {
  std::string name;
  ObstacleRole role = ObstacleRole::Part;
  int link = -1;  // Machine obstacles: index into CheckOptions::links_in_part
  Mesh mesh;
  Eigen::AlignedBox3d box;
  std::shared_ptr<CollideBvh> collide_bvh;
  std::shared_ptr<DistanceBvh> distance_bvh;  // null when built without distance support
};

struct Scene::Impl {
  std::vector<Obstacle> obstacles;
  bool built = false;
  bool distance = false;
  double build_seconds = 0.0;
  std::size_t triangles = 0;
};

Scene::Scene() : impl_(std::make_unique<Impl>()) {}
Scene::~Scene() = default;
Scene::Scene(Scene&&) noexcept = default;
Scene& Scene::operator=(Scene&&) noexcept = default;

std::size_t Scene::add(std::string name, ObstacleRole role, Mesh mesh, int link) {
  if (impl_->built) throw std::logic_error("geom::Scene::add after build()");
  const SourceLoc where{mesh.source.empty() ? name : mesh.source};
  if (mesh.triangles.empty()) throw InputError(where, fmt::format("obstacle '{}' has no triangles", name));
  const int nv = static_cast<int>(mesh.vertices_mm.size());
  for (const auto& t : mesh.triangles)
    if ((t.array() < 0).any() || (t.array() >= nv).any())
      throw InputError(where, fmt::format("obstacle '{}' has a vertex index out of range", name));
  for (const auto& v : mesh.vertices_mm)
    if (!v.allFinite()) throw InputError(where, fmt::format("obstacle '{}' has a non-finite vertex", name));
  Obstacle o;
  o.name = std::move(name);
  o.role = role;
  o.link = role == ObstacleRole::Machine ? std::max(link, -1) : -1;
  o.box = mesh.bounding_box();
  o.mesh = std::move(mesh);
  impl_->obstacles.push_back(std::move(o));
  return impl_->obstacles.size() - 1;
}

void Scene::build(bool with_distance) {
  if (impl_->built) return;
  const auto t0 = std::chrono::steady_clock::now();
  std::vector<fcl::Triangle> tris;
  std::size_t total = 0;
  for (Obstacle& o : impl_->obstacles) {
    tris.clear();
    tris.reserve(o.mesh.triangles.size());
    for (const auto& t : o.mesh.triangles)
      tris.emplace_back(static_cast<std::size_t>(t[0]), static_cast<std::size_t>(t[1]), static_cast<std::size_t>(t[2]));
    o.collide_bvh = make_bvh<CollideBvh>(o.mesh, tris, o.name);
    if (with_distance) o.distance_bvh = make_bvh<DistanceBvh>(o.mesh, tris, o.name);
    total += o.mesh.triangles.size();
  }
  impl_->triangles = total;
  impl_->built = true;
  impl_->distance = with_distance;
  impl_->build_seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

bool Scene::built() const { return impl_->built; }
bool Scene::supports_distance() const { return impl_->distance; }
std::size_t Scene::obstacle_count() const { return impl_->obstacles.size(); }
const std::string& Scene::obstacle_name(std::size_t i) const { return impl_->obstacles.at(i).name; }
ObstacleRole Scene::obstacle_role(std::size_t i) const { return impl_->obstacles.at(i).role; }
int Scene::obstacle_link(std::size_t i) const { return impl_->obstacles.at(i).link; }
int Scene::link_count() const {
  int n = 0;
  for (const auto& o : impl_->obstacles) n = std::max(n, o.link + 1);
  return n;
}
const Mesh& Scene::obstacle_mesh(std::size_t i) const { return impl_->obstacles.at(i).mesh; }
const Eigen::AlignedBox3d& Scene::obstacle_bounds(std::size_t i) const { return impl_->obstacles.at(i).box; }
std::size_t Scene::triangle_count() const {
  if (impl_->built) return impl_->triangles;
  std::size_t n = 0;
  for (const auto& o : impl_->obstacles) n += o.mesh.triangles.size();
  return n;
}
double Scene::build_seconds() const { return impl_->build_seconds; }

// ---------------------------------------------------------------------------------------------------
// Workspace
// ---------------------------------------------------------------------------------------------------

QueryStats& QueryStats::operator+=(const QueryStats& o) {
  collision_queries += o.collision_queries;
  distance_queries += o.distance_queries;
  fcl_collide_calls += o.fcl_collide_calls;
  fcl_distance_calls += o.fcl_distance_calls;
  aabb_rejects += o.aabb_rejects;
  witness_tests += o.witness_tests;
  return *this;
}

struct QueryWorkspace::Impl {
  struct Seg {
    ToolSegment seg;
    std::shared_ptr<fcl::Cylinderd> shape;
  };
  // Cache key: the tool and the options that change the shapes.
  std::optional<ToolShape> tool;
  double clearance = 0.0, cutter_clearance = 0.0, relief = 0.0, erosion = 0.0;
  bool check_cutter = true;
  std::vector<Seg> segs;

  // Per-query scratch.
  std::vector<Eigen::AlignedBox3d> boxes;      // obstacle boxes in the part frame
  std::vector<char> skip;                      // linked obstacle without link poses
  std::vector<Eigen::Isometry3d> obstacle_tf;  // obstacle pose in the part frame
  std::vector<Eigen::Isometry3d, Eigen::aligned_allocator<Eigen::Isometry3d>> seg_tf;
  std::vector<Eigen::AlignedBox3d> seg_box;

  fcl::CollisionRequestd creq;
  fcl::CollisionResultd cres;
  fcl::DistanceRequestd dreq;
  fcl::DistanceResultd dres;

  Impl() {
    creq.num_max_contacts = 1;
    creq.enable_contact = false;
    creq.gjk_solver_type = kCollideSolver;
    dreq.enable_nearest_points = false;
    dreq.enable_signed_distance = false;
    dreq.gjk_solver_type = kDistanceSolver;
  }

  void prepare(const ToolShape& t, const CheckOptions& o) {
    if (tool && *tool == t && clearance == o.clearance_mm && cutter_clearance == o.cutter_clearance_mm &&
        relief == o.relief_mm && check_cutter == o.check_cutter_body && erosion == o.erosion_mm)
      return;
    t.validate();
    segs.clear();
    for (const ToolSegment& s : checked_segments(t, o))
      segs.push_back({s, std::make_shared<fcl::Cylinderd>(s.radius_mm, s.z1_mm - s.z0_mm)});
    tool = t;
    clearance = o.clearance_mm;
    cutter_clearance = o.cutter_clearance_mm;
    relief = o.relief_mm;
    check_cutter = o.check_cutter_body;
    erosion = o.erosion_mm;
  }

  /// Places the segments and the obstacles for one query.
  void place(const Scene::Impl& scene, const kin::Posed& pose, const CheckOptions& o) {
    const double n = pose.axis.norm();
    CSCAM_CHECK(n > 0.0 && std::isfinite(n) && pose.tip_mm.allFinite(),
                "tool pose must be finite with a non-zero axis");
    const Eigen::Vector3d a = pose.axis / n;
    const Eigen::Matrix3d R = Eigen::Quaterniond::FromTwoVectors(Eigen::Vector3d::UnitZ(), a).toRotationMatrix();
    const Eigen::Vector3d abs_a = a.cwiseAbs();
    const Eigen::Vector3d perp = (Eigen::Vector3d::Ones() - a.cwiseProduct(a)).cwiseMax(0.0).cwiseSqrt();
    seg_tf.resize(segs.size());
    seg_box.resize(segs.size());
    for (std::size_t i = 0; i < segs.size(); ++i) {
      const ToolSegment& s = segs[i].seg;
      const double h = 0.5 * (s.z1_mm - s.z0_mm);
      const Eigen::Vector3d c = pose.tip_mm + (0.5 * (s.z0_mm + s.z1_mm)) * a;
      seg_tf[i].linear() = R;
      seg_tf[i].translation() = c;
      seg_tf[i].makeAffine();
      const Eigen::Vector3d ext = h * abs_a + s.radius_mm * perp;
      seg_box[i] = Eigen::AlignedBox3d(c - ext, c + ext);
    }
    boxes.resize(scene.obstacles.size());
    obstacle_tf.resize(scene.obstacles.size());
    skip.assign(scene.obstacles.size(), 0);
    for (std::size_t j = 0; j < scene.obstacles.size(); ++j) {
      const Obstacle& ob = scene.obstacles[j];
      if (ob.role == ObstacleRole::Machine) {
        skip[j] = ob.link >= 0 && !o.links_in_part;
        obstacle_tf[j] = ob.link >= 0 && o.links_in_part ? o.links_in_part[ob.link] : o.machine_in_part;
        boxes[j] = transformed_box(ob.box, obstacle_tf[j]);
      } else {
        obstacle_tf[j] = Eigen::Isometry3d::Identity();
        boxes[j] = ob.box;
      }
    }
  }
};

QueryWorkspace::QueryWorkspace() : impl_(std::make_unique<Impl>()) {}
QueryWorkspace::~QueryWorkspace() = default;
QueryWorkspace::QueryWorkspace(QueryWorkspace&&) noexcept = default;
QueryWorkspace& QueryWorkspace::operator=(QueryWorkspace&&) noexcept = default;

// ---------------------------------------------------------------------------------------------------
// Queries
// ---------------------------------------------------------------------------------------------------

namespace {

bool selected(const Obstacle& o, unsigned roles) { return (static_cast<unsigned>(o.role) & roles) != 0u; }

/// Pose of an obstacle in the part frame; false when it has a link and no link poses are given.
bool obstacle_pose(const Obstacle& o, const CheckOptions& opt, Eigen::Isometry3d& T) {
  if (o.role != ObstacleRole::Machine) {
    T.setIdentity();
    return true;
  }
  if (o.link < 0) {
    T = opt.machine_in_part;
    return true;
  }
  if (!opt.links_in_part) return false;
  T = opt.links_in_part[o.link];
  return true;
}

struct Nearest {
  double d = kInf;
  ToolPart part = ToolPart::CutterBody;
  int obstacle = -1;
};

/// Minimum distance over all segment x obstacle pairs; stops at the first contact (distance 0).
Nearest nearest(const Scene::Impl& scene, const CheckOptions& o, QueryWorkspace& ws) {
  auto& w = ws.impl();
  Nearest best;
  for (std::size_t i = 0; i < w.segs.size(); ++i) {
    for (std::size_t j = 0; j < scene.obstacles.size(); ++j) {
      const Obstacle& ob = scene.obstacles[j];
      if (!selected(ob, o.roles) || w.skip[j]) continue;
      if (aabb_gap(w.seg_box[i], w.boxes[j]) >= best.d) {  // a lower bound that cannot improve the best
        ++ws.stats.aabb_rejects;
        continue;
      }
      w.dres.clear();
      ++ws.stats.fcl_distance_calls;
      const double d =
          fcl::distance(ob.distance_bvh.get(), w.obstacle_tf[j], w.segs[i].shape.get(), w.seg_tf[i], w.dreq, w.dres);
      if (d < best.d) best = {std::max(d, 0.0), w.segs[i].seg.part, static_cast<int>(j)};
      if (best.d <= 0.0) return best;
    }
  }
  return best;
}

}  // namespace

CollisionResult check(const Scene& scene, const ToolShape& tool, const kin::Posed& pose, const CheckOptions& o,
                      QueryWorkspace& ws) {
  const Scene::Impl& sc = scene.impl();
  CSCAM_CHECK(sc.built, "geom::check() before Scene::build()");
  ++ws.stats.collision_queries;
  auto& w = ws.impl();
  w.prepare(tool, o);
  w.place(sc, pose, o);

  CollisionResult out;
  for (std::size_t i = 0; i < w.segs.size() && !out.collides; ++i) {
    for (std::size_t j = 0; j < sc.obstacles.size(); ++j) {
      const Obstacle& ob = sc.obstacles[j];
      if (!selected(ob, o.roles) || w.skip[j]) continue;
      if (!w.seg_box[i].intersects(w.boxes[j])) {
        ++ws.stats.aabb_rejects;
        continue;
      }
      w.cres.clear();
      ++ws.stats.fcl_collide_calls;
      fcl::collide(ob.collide_bvh.get(), w.obstacle_tf[j], w.segs[i].shape.get(), w.seg_tf[i], w.creq, w.cres);
      if (w.cres.isCollision()) {
        out.collides = true;
        out.part = w.segs[i].seg.part;
        out.obstacle = static_cast<int>(j);
        out.segment = static_cast<int>(i);
        if (w.cres.numContacts() > 0) out.triangle = w.cres.getContact(0).b1;  // o1 is the mesh
        break;
      }
    }
  }
  if (o.compute_distance) {
    CSCAM_CHECK(sc.distance, "geom::check(compute_distance) on a Scene built without distance support");
    ++ws.stats.distance_queries;
    if (out.collides) {
      out.min_distance_mm = 0.0;
      out.nearest_part = out.part;
      out.nearest_obstacle = out.obstacle;
    } else {
      const Nearest n = nearest(sc, o, ws);
      out.min_distance_mm = n.d;
      out.nearest_part = n.part;
      out.nearest_obstacle = n.obstacle;
    }
  }
  return out;
}

CollisionResult check_witness(const Scene& scene, const ToolShape& tool, const kin::Posed& pose, const CheckOptions& o,
                              QueryWorkspace& ws, const Witness& wit) {
  const Scene::Impl& sc = scene.impl();
  CSCAM_CHECK(sc.built, "geom::check_witness() before Scene::build()");
  CollisionResult out;
  if (!wit.valid() || static_cast<std::size_t>(wit.obstacle) >= sc.obstacles.size()) return out;
  const Obstacle& ob = sc.obstacles[static_cast<std::size_t>(wit.obstacle)];
  Eigen::Isometry3d T_part_obstacle;
  if (!selected(ob, o.roles) || !obstacle_pose(ob, o, T_part_obstacle)) return out;
  auto& w = ws.impl();
  w.prepare(tool, o);
  const auto si = static_cast<std::size_t>(wit.segment);
  const auto& bvh = *ob.collide_bvh;
  if (si >= w.segs.size() || wit.triangle >= bvh.num_tris) return out;
  const double n = pose.axis.norm();
  CSCAM_CHECK(n > 0.0 && std::isfinite(n) && pose.tip_mm.allFinite(), "tool pose must be finite with a non-zero axis");
  const Eigen::Vector3d a = pose.axis / n;
  const ToolSegment& s = w.segs[si].seg;
  // The segment placed as place() places it; the triangle as the leaf test of check() takes it.
  fcl::Transform3d T_part_seg = fcl::Transform3d::Identity();
  T_part_seg.linear() = Eigen::Quaterniond::FromTwoVectors(Eigen::Vector3d::UnitZ(), a).toRotationMatrix();
  T_part_seg.translation() = pose.tip_mm + (0.5 * (s.z0_mm + s.z1_mm)) * a;
  const fcl::Triangle& t = bvh.tri_indices[wit.triangle];
  ++ws.stats.witness_tests;
  const fcl::detail::GJKSolver_libccd<double> solver;  // (as fcl::collide makes one: default settings)
  if (solver.shapeTriangleIntersect(*w.segs[si].shape, T_part_seg, bvh.vertices[t[0]], bvh.vertices[t[1]],
                                    bvh.vertices[t[2]], fcl::Transform3d(T_part_obstacle.matrix()), nullptr, nullptr,
                                    nullptr)) {
    out.collides = true;
    out.part = s.part;
    out.obstacle = wit.obstacle;
    out.segment = wit.segment;
    out.triangle = wit.triangle;
  }
  return out;
}

double clearance(const Scene& scene, const ToolShape& tool, const kin::Posed& pose, const CheckOptions& o,
                 QueryWorkspace& ws) {
  const Scene::Impl& sc = scene.impl();
  CSCAM_CHECK(sc.built, "geom::clearance() before Scene::build()");
  CSCAM_CHECK(sc.distance, "geom::clearance() on a Scene built without distance support");
  ++ws.stats.distance_queries;
  auto& w = ws.impl();
  w.prepare(tool, o);
  w.place(sc, pose, o);
  return nearest(sc, o, ws).d;
}

CollisionResult check_meshes(const Scene& moving, const Eigen::Isometry3d& moving_in_part, const Scene& fixed,
                             const CheckOptions& o, QueryWorkspace& ws, int* moving_obstacle) {
  const Scene::Impl& mv = moving.impl();
  const Scene::Impl& fx = fixed.impl();
  CSCAM_CHECK(mv.built && fx.built, "geom::check_meshes() before Scene::build()");
  ++ws.stats.collision_queries;
  CollisionResult out;
  fcl::CollisionRequestd req(1, false);
  fcl::CollisionResultd res;
  // The fixed obstacles' poses and boxes once, not once per moving obstacle (per-thread scratch).
  struct Placed {
    bool used;
    Eigen::Isometry3d T;
    Eigen::AlignedBox3d box;
  };
  thread_local std::vector<Placed> placed;
  placed.resize(fx.obstacles.size());
  for (std::size_t j = 0; j < fx.obstacles.size(); ++j) {
    Placed& p = placed[j];
    p.used = selected(fx.obstacles[j], o.roles) && obstacle_pose(fx.obstacles[j], o, p.T);
    if (p.used) p.box = transformed_box(fx.obstacles[j].box, p.T);
  }
  for (std::size_t i = 0; i < mv.obstacles.size(); ++i) {
    const Obstacle& m = mv.obstacles[i];
    Eigen::Isometry3d Tm = moving_in_part;
    if (m.link >= 0) {
      if (!o.links_in_part) continue;
      Tm = o.links_in_part[m.link];
    }
    const Eigen::AlignedBox3d mbox = transformed_box(m.box, Tm);
    for (std::size_t j = 0; j < fx.obstacles.size(); ++j) {
      const Obstacle& f = fx.obstacles[j];
      if (!placed[j].used) continue;
      const Eigen::Isometry3d& Tf = placed[j].T;
      if (!mbox.intersects(placed[j].box)) {
        ++ws.stats.aabb_rejects;
        continue;
      }
      res.clear();
      ++ws.stats.fcl_collide_calls;
      fcl::collide(m.collide_bvh.get(), fcl::Transform3d(Tm.matrix()), f.collide_bvh.get(),
                   fcl::Transform3d(Tf.matrix()), req, res);
      if (res.isCollision()) {
        out.collides = true;
        out.part = ToolPart::Spindle;
        out.obstacle = static_cast<int>(j);
        if (moving_obstacle) *moving_obstacle = static_cast<int>(i);
        return out;
      }
    }
  }
  return out;
}

bool meshes_apart(const Scene& moving, const Eigen::Isometry3d& moving_in_part, const Scene& fixed,
                  const CheckOptions& o, double margin_mm) {
  const Scene::Impl& mv = moving.impl();
  const Scene::Impl& fx = fixed.impl();
  CSCAM_CHECK(mv.built && fx.built, "geom::meshes_apart() before Scene::build()");
  for (const Obstacle& m : mv.obstacles) {
    if (m.link >= 0 && !o.links_in_part) return false;
    Eigen::AlignedBox3d mbox = transformed_box(m.box, m.link >= 0 ? o.links_in_part[m.link] : moving_in_part);
    mbox.min().array() -= margin_mm;
    mbox.max().array() += margin_mm;
    for (const Obstacle& f : fx.obstacles) {
      Eigen::Isometry3d Tf;
      if (!selected(f, o.roles)) continue;
      if (!obstacle_pose(f, o, Tf) || mbox.intersects(transformed_box(f.box, Tf))) return false;
    }
  }
  return true;
}

}  // namespace cscam::geom
