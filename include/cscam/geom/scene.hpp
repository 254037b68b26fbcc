#pragma once
/// @file
/// Tool shapes, the obstacle scene (FCL bounding-volume hierarchies) and collision / distance queries.
///
/// Frames and units: every query takes the tool pose in the part frame (kin::Posed: tool tip in mm and
/// the unit tool axis pointing from the tip toward the spindle). Obstacle meshes are given in the part
/// frame, except obstacles with ObstacleRole::Machine, which are given in a machine frame and placed
/// per query by CheckOptions::machine_in_part.
///
/// Threading (Pinocchio Model/Data pattern): a Scene is filled, then build() once, and is immutable
/// afterwards, so any number of threads may query it concurrently. Everything that changes during a
/// query (FCL tool shapes, scratch, counters) lives in a QueryWorkspace, one per thread.
#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include "cscam/geom/mesh.hpp"
#include "cscam/kin/types.hpp"

namespace cscam::geom {

// ---------------------------------------------------------------------------------------------------
// Tool shape
// ---------------------------------------------------------------------------------------------------

/// The parts of a tool assembly, from the tip upward.
enum class ToolPart { CutterBody, Shank, Holder, Holder2, Spindle };

/// "cutter_body", "shank", "holder", "holder2", "spindle".
[[nodiscard]] const char* to_string(ToolPart part);

/// The cutting part. corner_radius_mm = 0: flat end mill; = diameter/2: ball end mill; between: bull nose.
struct CutterShape {
  double diameter_mm = 0.0;
  double corner_radius_mm = 0.0;
  double flute_length_mm = 0.0;  ///< from the tip, along the axis
  bool operator==(const CutterShape&) const = default;
};

/// A cylindrical stage of the tool assembly. A stage with zero diameter or zero length is absent.
struct CylinderStage {
  double diameter_mm = 0.0;
  double length_mm = 0.0;
  [[nodiscard]] bool present() const { return diameter_mm > 0.0 && length_mm > 0.0; }
  bool operator==(const CylinderStage&) const = default;
};

/// Axial extent and radius of one tool part, measured along the tool axis from the tip (mm).
struct ToolSegment {
  ToolPart part = ToolPart::CutterBody;
  double z0_mm = 0.0;  ///< lower end, distance from the tip along the axis
  double z1_mm = 0.0;  ///< upper end
  double radius_mm = 0.0;
};

/// Defaults used by ToolShape::from_cutter for what the CL file does not say (typically supplied by the
/// machine file). A negative value means "derive from the cutter diameter D" as documented per field.
struct ToolDefaults {
  double shank_diameter_mm = -1.0;   ///< < 0: D
  double shank_length_mm = -1.0;     ///< stick-out between flutes and holder; < 0: 2 D
  double holder_diameter_mm = -1.0;  ///< < 0: 2.5 D
  double holder_length_mm = 40.0;
  CylinderStage holder2{};  ///< optional second holder stage (absent by default)
  CylinderStage spindle{};  ///< spindle nose (absent by default: the machine file should give it)
};

/// A tool assembly described along its axis from the tip upward, stacked without gaps:
/// cutter [0, flute], shank, holder, optional second holder stage, spindle nose.
struct ToolShape {
  CutterShape cutter;
  CylinderStage shank;
  CylinderStage holder;
  CylinderStage holder2;  ///< optional
  CylinderStage spindle;  ///< optional

  /// A tool from the cutter data of a CL file (CUTTER/D,R) plus defaults for the rest.
  /// @throws InputError when the resulting shape is invalid (see validate()).
  [[nodiscard]] static ToolShape from_cutter(double diameter_mm, double corner_radius_mm, double flute_length_mm,
                                             const ToolDefaults& defaults = {});

  /// @throws InputError for a non-positive cutter diameter or flute length, a corner radius outside
  ///         [0, D/2], or a negative stage dimension.
  void validate() const;

  /// True when the corner radius equals the cutter radius (within 1e-9 mm).
  [[nodiscard]] bool is_ball() const;

  /// Tip to the top of the holder stages (the spindle nose face), mm.
  [[nodiscard]] double gauge_length_mm() const;

  /// The present parts as stacked cylinders (the cutter as the full cylinder [0, flute]).
  [[nodiscard]] std::vector<ToolSegment> segments() const;

  bool operator==(const ToolShape&) const = default;
};

// ---------------------------------------------------------------------------------------------------
// Scene
// ---------------------------------------------------------------------------------------------------

/// What an obstacle is. Roles are bit flags so that CheckOptions::roles can select several.
enum class ObstacleRole : unsigned { Part = 1u, Fixture = 2u, Machine = 4u };
inline constexpr unsigned kAllRoles = 7u;

/// "part", "fixture", "machine".
[[nodiscard]] const char* to_string(ObstacleRole role);

/// A set of obstacle meshes with FCL bounding-volume hierarchies: an OBB tree per obstacle for collision
/// and, unless disabled, an RSS tree for distance (FCL has no distance traversal on OBB trees, and OBBRSS
/// answers collision queries 3-4x slower than OBB with cylinder tools). Immutable and thread-safe after
/// build().
class Scene {
 public:
  Scene();
  ~Scene();
  Scene(Scene&&) noexcept;
  Scene& operator=(Scene&&) noexcept;
  Scene(const Scene&) = delete;
  Scene& operator=(const Scene&) = delete;

  /// Adds an obstacle (before build()). Returns its index.
  /// @param link for ObstacleRole::Machine: the machine link the mesh moves with (an index into
  ///        CheckOptions::links_in_part, e.g. 0 for the base and 1 + axis index for the link an axis drives);
  ///        -1: placed by CheckOptions::machine_in_part. Ignored for other roles.
  /// @throws InputError for a mesh without triangles or with out-of-range indices (names mesh.source);
  ///         std::logic_error when called after build().
  std::size_t add(std::string name, ObstacleRole role, Mesh mesh, int link = -1);

  /// Builds the bounding-volume hierarchies. Call once; queries require it. Further calls do nothing.
  /// @param with_distance also build the distance hierarchies (about doubles build time and memory);
  ///        without them clearance() and CheckOptions::compute_distance are invariant violations.
  void build(bool with_distance = true);
  [[nodiscard]] bool built() const;
  [[nodiscard]] bool supports_distance() const;

  [[nodiscard]] std::size_t obstacle_count() const;
  [[nodiscard]] const std::string& obstacle_name(std::size_t i) const;
  [[nodiscard]] ObstacleRole obstacle_role(std::size_t i) const;
  /// The machine link of obstacle i (-1: none, see add()).
  [[nodiscard]] int obstacle_link(std::size_t i) const;
  /// 1 + the largest link of any obstacle (0 when no obstacle has a link): the size CheckOptions::links_in_part
  /// must have.
  [[nodiscard]] int link_count() const;
  [[nodiscard]] const Mesh& obstacle_mesh(std::size_t i) const;
  /// Bounding box of obstacle i in its own frame (part frame, or machine frame for Machine obstacles).
  [[nodiscard]] const Eigen::AlignedBox3d& obstacle_bounds(std::size_t i) const;
  /// Total number of triangles over all obstacles.
  [[nodiscard]] std::size_t triangle_count() const;
  /// Wall-clock seconds build() took.
  [[nodiscard]] double build_seconds() const;

  struct Impl;
  [[nodiscard]] const Impl& impl() const { return *impl_; }

 private:
  std::unique_ptr<Impl> impl_;
};

// ---------------------------------------------------------------------------------------------------
// Queries
// ---------------------------------------------------------------------------------------------------

/// Counters of one workspace. Add workspaces' stats together for a run total.
struct QueryStats {
  std::uint64_t collision_queries = 0;   ///< check() calls
  std::uint64_t distance_queries = 0;    ///< clearance() calls and check() calls with compute_distance
  std::uint64_t fcl_collide_calls = 0;   ///< narrow FCL collide() calls (tool segment x obstacle)
  std::uint64_t fcl_distance_calls = 0;  ///< narrow FCL distance() calls
  std::uint64_t aabb_rejects = 0;        ///< segment x obstacle pairs settled by bounding boxes alone
  std::uint64_t witness_tests = 0;       ///< witness_holds() calls (one triangle each)
  QueryStats& operator+=(const QueryStats& o);
};

/// Per-thread scratch for queries: the FCL tool shapes (rebuilt only when the tool or the inflation
/// changes) and the counters. Not thread-safe; use one per thread.
class QueryWorkspace {
 public:
  QueryWorkspace();
  ~QueryWorkspace();
  QueryWorkspace(QueryWorkspace&&) noexcept;
  QueryWorkspace& operator=(QueryWorkspace&&) noexcept;
  QueryWorkspace(const QueryWorkspace&) = delete;
  QueryWorkspace& operator=(const QueryWorkspace&) = delete;

  QueryStats stats;

  struct Impl;
  [[nodiscard]] Impl& impl() { return *impl_; }

 private:
  std::unique_ptr<Impl> impl_;
};

/// How to check a tool pose.
///
/// The cutting end is in contact with the machined surface by design and never counts: the checked
/// cutter body is the cylinder of radius D/2 (+ cutter_clearance_mm) from `corner_radius + relief`
/// above the tip to the end of the flutes. For a ball mill this excludes the whole ball plus `relief`;
/// for a flat mill only the bottom `relief`. Shank, holder(s) and spindle nose are checked whole,
/// inflated by clearance_mm in radius and at their exposed end faces (a conservative superset of "closer
/// than clearance_mm": the inflated cylinder also covers the corners of the Minkowski sum).
///
/// Obstacles are triangle surfaces (FCL): a tool part lying entirely inside a closed obstacle without
/// touching its surface is not detected. A tool whose spindle side is outside the part always crosses
/// the surface, so this only matters for axes pointing into the material, which the caller should
/// reject first (axis . surface normal <= 0).
struct CheckOptions {
  double clearance_mm = 0.0;         ///< safety margin around shank, holder(s), spindle nose
  double cutter_clearance_mm = 0.0;  ///< margin around the checked cutter body (radius only)
  bool check_cutter_body = true;     ///< false: ignore the flutes entirely
  double relief_mm = -1.0;           ///< < 0: 0.2 x corner radius, or 0.5 mm for a flat mill
  /// Shrinks every checked segment (after the clearances) by this much in radius and at both ends: a pose whose
  /// eroded tool touches an obstacle collides whatever pose within this distance the tool takes (the eroded body
  /// plus the distance lies inside the body there). Segments that vanish are not checked.
  double erosion_mm = 0.0;
  bool compute_distance = false;  ///< check(): also fill min_distance_mm when free (needs distance support)
  unsigned roles = kAllRoles;     ///< which obstacle roles to test (bit or of ObstacleRole)
  /// Pose of the machine frame in the part frame, applied to ObstacleRole::Machine obstacles.
  Eigen::Isometry3d machine_in_part = Eigen::Isometry3d::Identity();
  /// Poses of the machine links in the part frame, indexed by link (Scene::add), for Machine obstacles that
  /// have a link, in check() and on both sides of check_meshes(). Not owned; must hold Scene::link_count()
  /// entries. Null: obstacles with a link are not tested (their pose is unknown without axis values).
  const Eigen::Isometry3d* links_in_part = nullptr;
};

/// Outcome of check().
struct CollisionResult {
  bool collides = false;
  ToolPart part = ToolPart::CutterBody;  ///< the tool part that hit (valid when collides)
  int obstacle = -1;                     ///< index of the obstacle hit in the Scene, -1 when free
  /// With CheckOptions::compute_distance: smallest distance (mm) between the checked, inflated tool
  /// parts and the obstacles; 0 when colliding; +inf when nothing is in range. NaN when not requested.
  double min_distance_mm = std::numeric_limits<double>::quiet_NaN();
  ToolPart nearest_part = ToolPart::CutterBody;  ///< part realising min_distance_mm (when computed)
  int nearest_obstacle = -1;                     ///< obstacle realising min_distance_mm (when computed)
  /// The contact that proved the hit (valid when collides): the checked tool segment (index into
  /// checked_segments()) and the obstacle's triangle. witness_holds() tests it again at another pose.
  int segment = -1;
  int triangle = -1;
};

/// A contact found by check(): tool segment, obstacle and triangle.
struct Witness {
  int segment = -1, obstacle = -1, triangle = -1;
  [[nodiscard]] bool valid() const { return segment >= 0 && obstacle >= 0 && triangle >= 0; }
};

/// Whether the witness's tool segment at `tool_pose_in_part` still intersects the witness's triangle, with
/// FCL's narrow phase (the leaf test of check()). A hit proves that check() with the same options collides and
/// is returned as check() would describe it; no hit proves nothing (another triangle may be hit). One triangle
/// test instead of a tree traversal: a cell that collided at one CL point usually still collides, by the same
/// contact, at the next.
[[nodiscard]] CollisionResult check_witness(const Scene& scene, const ToolShape& tool,
                                            const kin::Posed& tool_pose_in_part, const CheckOptions& options,
                                            QueryWorkspace& ws, const Witness& witness);

/// The tool segments check() actually tests for this tool and these options (after the cutting-end
/// exclusion and the inflation), from the tip upward.
[[nodiscard]] std::vector<ToolSegment> checked_segments(const ToolShape& tool, const CheckOptions& options);

/// Does the tool at `tool_pose_in_part` (tip in mm, unit axis tip -> spindle, part frame) collide with
/// the scene? Stops at the first hit (parts in order tip upward, obstacles in insertion order).
/// Counts one collision query (and one distance query with compute_distance).
/// @pre scene.built(); tool_pose_in_part.axis non-zero (it is normalised).
[[nodiscard]] CollisionResult check(const Scene& scene, const ToolShape& tool, const kin::Posed& tool_pose_in_part,
                                    const CheckOptions& options, QueryWorkspace& workspace);

/// Smallest distance (mm) between the checked tool parts (as in check()) and the scene; 0 when they
/// collide; +inf when the scene has no obstacle of the selected roles. FCL GJK distance (its own GJK):
/// agrees with analytic distances to < 1e-7 mm in the tests, flat and curved contacts alike.
/// Cost: ~1 ms on the 200k-triangle benchmark part (about 70x a collision query): FCL visits every
/// triangle within the distance. For a cheap "at least d mm of room" test use check() with
/// CheckOptions::clearance_mm = d instead. Counts one distance query.
/// @pre scene.built() with distance support.
[[nodiscard]] double clearance(const Scene& scene, const ToolShape& tool, const kin::Posed& tool_pose_in_part,
                               const CheckOptions& options, QueryWorkspace& workspace);

/// Collision between two sets of meshes: every obstacle of `moving` (e.g. a machine head that moves with
/// the tool), placed in the part frame by `moving_in_part` (or by options.links_in_part for one with a
/// link), against the obstacles of `fixed` selected by `options.roles` (Machine-role obstacles of `fixed`
/// placed as in check()). CollisionResult::part is Spindle; `moving_obstacle` receives the index of the moving
/// obstacle that hit, if not null.
/// Meshes are surfaces: a part wholly inside another is not seen. Counts one collision query.
[[nodiscard]] CollisionResult check_meshes(const Scene& moving, const Eigen::Isometry3d& moving_in_part,
                                           const Scene& fixed, const CheckOptions& options, QueryWorkspace& workspace,
                                           int* moving_obstacle = nullptr);

/// Whether every obstacle of `moving` (placed as in check_meshes()) stays clear of the selected obstacles of `fixed`
/// under any translation shorter than `margin_mm`: their bounding boxes, the moving one grown by the margin, are
/// disjoint. A cheap, conservative certificate (false does not mean a collision). A moving obstacle with a link is
/// placed by options.links_in_part (not certified, false, without them). Counts no query.
[[nodiscard]] bool meshes_apart(const Scene& moving, const Eigen::Isometry3d& moving_in_part, const Scene& fixed,
                                const CheckOptions& options, double margin_mm);

}  // namespace cscam::geom
