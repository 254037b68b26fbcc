// geom: mesh I/O (assimp), closedness, the groove test part, tool shapes, FCL collision and distance queries.
// The oracles are analytic (box and groove geometry computed by hand), not FCL.
#include <gtest/gtest.h>
#include <unistd.h>

#include <array>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <set>
#include <thread>

#include "cscam/core/error.hpp"
#include "cscam/core/units.hpp"
#include "cscam/geom/groove.hpp"
#include "cscam/geom/mesh.hpp"
#include "cscam/geom/mesh_check.hpp"
#include "cscam/geom/scene.hpp"
#include "test_support.hpp"

using namespace cscam;
using namespace cscam::geom;
namespace fs = std::filesystem;

namespace {

/// One folder per test process, removed when the process ends (ctest runs every test in a process of its own, and
/// each used to leave its folder behind).
fs::path temp_dir() {
  struct Folder {
    fs::path path;
    ~Folder() {
      std::error_code ec;
      fs::remove_all(path, ec);
    }
  };
  static const Folder folder{[] {
    const fs::path d = fs::temp_directory_path() / ("cscam_geom_test_" + std::to_string(::getpid()));
    fs::create_directories(d);
    return d;
  }()};
  return folder.path;
}

/// Axis-aligned box [lo, hi] as a closed, outward-oriented 12-triangle mesh.
Mesh make_box(const Eigen::Vector3d& lo, const Eigen::Vector3d& hi) {
  Mesh m;
  m.source = "box";
  for (int i = 0; i < 8; ++i)
    m.vertices_mm.emplace_back(i & 1 ? hi.x() : lo.x(), i & 2 ? hi.y() : lo.y(), i & 4 ? hi.z() : lo.z());
  // Faces as quads (counter-clockwise seen from outside), split into two triangles each.
  const int q[6][4] = {{0, 2, 3, 1}, {4, 5, 7, 6}, {0, 1, 5, 4}, {2, 6, 7, 3}, {0, 4, 6, 2}, {1, 3, 7, 5}};
  for (const auto& f : q) {
    m.triangles.emplace_back(f[0], f[1], f[2]);
    m.triangles.emplace_back(f[0], f[2], f[3]);
  }
  return m;
}

std::string message_of(const std::function<void()>& f) {
  try {
    f();
  } catch (const InputError& e) {
    return e.what();
  }
  return "<no InputError thrown>";
}

kin::Posed pose(const Eigen::Vector3d& tip, const Eigen::Vector3d& axis) { return {tip, axis.normalized()}; }

}  // namespace

// ---------------------------------------------------------------------------------------------------
// Meshes
// ---------------------------------------------------------------------------------------------------

TEST(GeomMesh, BoxIsClosedWithOutwardVolume) {
  const Mesh box = make_box({0, 0, 0}, {10, 20, 30});
  std::string why;
  EXPECT_TRUE(box.is_closed(&why)) << why;
  EXPECT_NEAR(box.signed_volume_mm3(), 6000.0, 1e-9);
  EXPECT_NEAR(box.area_mm2(), 2 * (200 + 300 + 600), 1e-9);
  const auto bb = box.bounding_box();
  EXPECT_TRUE(bb.min().isApprox(Eigen::Vector3d(0, 0, 0)));
  EXPECT_TRUE(bb.max().isApprox(Eigen::Vector3d(10, 20, 30)));
}

TEST(GeomMesh, IsClosedReportsBoundaryFlippedAndNonManifold) {
  Mesh open = make_box({0, 0, 0}, {1, 1, 1});
  open.triangles.resize(10);  // drop the last face (x = hi): a square hole of 4 boundary edges
  std::string why;
  EXPECT_FALSE(open.is_closed(&why));
  EXPECT_NE(why.find("4 boundary edge(s)"), std::string::npos) << why;
  EXPECT_NE(why.find("e.g. boundary edge ("), std::string::npos) << why;

  Mesh flipped = make_box({0, 0, 0}, {1, 1, 1});
  std::swap(flipped.triangles[0][1], flipped.triangles[0][2]);
  EXPECT_FALSE(flipped.is_closed(&why));
  EXPECT_NE(why.find("3 inconsistently oriented edge(s)"), std::string::npos) << why;

  Mesh nm = make_box({0, 0, 0}, {1, 1, 1});
  nm.triangles.push_back(nm.triangles[0]);  // a duplicated triangle: its three edges are used three times
  nm.triangles.push_back(Eigen::Vector3i(nm.triangles[0][0], nm.triangles[0][2], nm.triangles[0][1]));
  EXPECT_FALSE(nm.is_closed(&why));
  EXPECT_NE(why.find("3 non-manifold edge(s)"), std::string::npos) << why;

  EXPECT_FALSE(Mesh{}.is_closed(&why));
}

TEST(GeomMesh, StlRoundTripKeepsTrianglesAndBox) {
  const fs::path dir = temp_dir();
  const Mesh box = make_box({-1.5, 2.25, -3}, {4, 7.75, 0.5});
  const std::string path = (dir / "box.stl").string();
  save_stl(box, path);
  EXPECT_EQ(fs::file_size(path), 84u + 50u * 12u);
  const Mesh back = load_mesh(path);
  EXPECT_EQ(back.triangle_count(), 12u);
  EXPECT_EQ(back.vertices_mm.size(), 8u);  // welded across faces
  EXPECT_EQ(back.source, path);
  EXPECT_TRUE(back.bounding_box().min().isApprox(box.bounding_box().min(), 1e-7));
  EXPECT_TRUE(back.bounding_box().max().isApprox(box.bounding_box().max(), 1e-7));
  EXPECT_NEAR(back.signed_volume_mm3(), box.signed_volume_mm3(), 1e-6);  // orientation kept

  // A larger, curved mesh: the groove.
  GrooveParams gp;
  gp.length_segments = 3;
  const Mesh g = make_groove(gp);
  const std::string gpath = (dir / "groove.stl").string();
  save_stl(g, gpath);
  const Mesh gb = load_mesh(gpath);
  EXPECT_EQ(gb.triangle_count(), g.triangle_count());
  EXPECT_EQ(gb.vertices_mm.size(), g.vertices_mm.size());
  EXPECT_LT((gb.bounding_box().min() - g.bounding_box().min()).norm(), 1e-5);
  EXPECT_LT((gb.bounding_box().max() - g.bounding_box().max()).norm(), 1e-5);
  EXPECT_NEAR(gb.signed_volume_mm3(), g.signed_volume_mm3(), 1e-6 * g.signed_volume_mm3());

  // Scale to mm (a file in inches).
  const Mesh inch = load_mesh(path, 25.4);
  EXPECT_NEAR(inch.bounding_box().max().x(), 4 * 25.4, 1e-4);
}

TEST(GeomMesh, ObjQuadsAreTriangulatedAndMultipleObjectsMerged) {
  const fs::path dir = temp_dir();
  const std::string path = (dir / "two_cubes.obj").string();
  std::ofstream out(path);
  // Two unit cubes as quads, in two objects; the second offset by 3 in x. Outward winding.
  for (int c = 0; c < 2; ++c) {
    out << "o cube" << c << "\n";
    for (int i = 0; i < 8; ++i)
      out << "v " << ((i & 1) + 3 * c) << " " << ((i >> 1) & 1) << " " << ((i >> 2) & 1) << "\n";
    const int q[6][4] = {{0, 2, 3, 1}, {4, 5, 7, 6}, {0, 1, 5, 4}, {2, 6, 7, 3}, {0, 4, 6, 2}, {1, 3, 7, 5}};
    for (const auto& f : q)
      out << "f " << f[0] + 1 + 8 * c << " " << f[1] + 1 + 8 * c << " " << f[2] + 1 + 8 * c << " " << f[3] + 1 + 8 * c
          << "\n";
  }
  out.close();
  const Mesh m = load_mesh(path);
  EXPECT_EQ(m.triangle_count(), 24u);
  EXPECT_NEAR(m.signed_volume_mm3(), 2.0, 1e-9);
  EXPECT_NEAR(m.bounding_box().max().x(), 4.0, 1e-12);
}

TEST(GeomMesh, OpenMeshesAreRejectedNamingTheFile) {
  const fs::path dir = temp_dir();
  Mesh tri;
  tri.vertices_mm = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}};
  tri.triangles = {{0, 1, 2}};
  const std::string p1 = (dir / "one_triangle.stl").string();
  save_stl(tri, p1);
  std::string msg = message_of([&] { (void)load_mesh(p1); });
  EXPECT_EQ(msg.rfind(p1 + ": ", 0), 0u) << msg;
  EXPECT_NE(msg.find("3 boundary edge(s)"), std::string::npos) << msg;

  Mesh open = make_box({0, 0, 0}, {2, 2, 2});
  open.triangles.resize(10);
  const std::string p2 = (dir / "open_box.stl").string();
  save_stl(open, p2);
  msg = message_of([&] { (void)load_mesh(p2); });
  EXPECT_EQ(msg.rfind(p2 + ": ", 0), 0u) << msg;
  EXPECT_NE(msg.find("4 boundary edge(s)"), std::string::npos) << msg;
  EXPECT_NE(msg.find("(2, "), std::string::npos) << msg;  // the example edge lies on the removed face x = 2

  // Allowed when closedness is not required.
  EXPECT_EQ(load_mesh(p2, 1.0, /*require_closed=*/false).triangle_count(), 10u);
}

TEST(GeomMesh, MissingAndGarbageFilesAreInputErrorsNamingTheFile) {
  const fs::path dir = temp_dir();
  const std::string missing = (dir / "no_such_part.stl").string();
  std::string msg = message_of([&] { (void)load_mesh(missing); });
  EXPECT_EQ(msg, missing + ": cannot open mesh file");

  const std::string garbage = (dir / "garbage.ply").string();
  std::ofstream(garbage) << "this is not a PLY file\n\x01\x02\x03";
  msg = message_of([&] { (void)load_mesh(garbage); });
  EXPECT_EQ(msg.rfind(garbage + ": ", 0), 0u) << msg;

  EXPECT_THROW((void)load_mesh(missing, -1.0), InputError);
  EXPECT_THROW(save_stl(make_box({0, 0, 0}, {1, 1, 1}), (dir / "no_dir" / "x.stl").string()), InputError);
}

// ---------------------------------------------------------------------------------------------------
// The groove test part
// ---------------------------------------------------------------------------------------------------

TEST(GeomGroove, ClosedOutwardWithAnalyticVolumeAndBox) {
  const GrooveParams p;  // L 100, floor 30, mouth 20, depth 20, R 25, block 60, thickness 10
  const Mesh g = make_groove(p);
  std::string why;
  ASSERT_TRUE(g.is_closed(&why)) << why;
  const int K = 2 * p.floor_segments + 4 * p.wall_segments + 6;
  EXPECT_EQ(g.triangle_count(),
            static_cast<std::size_t>(2 * K * p.length_segments + 8 * p.wall_segments + 4 * p.floor_segments + 8));

  const auto bb = g.bounding_box();
  EXPECT_TRUE(bb.min().isApprox(Eigen::Vector3d(-50, -30, -10), 1e-12));
  EXPECT_TRUE(bb.max().isApprox(Eigen::Vector3d(50, 30, 20), 1e-12));

  // Cross-section area, by hand: block minus cavity; cavity = trapezoid under the chords + 2 arc segments.
  // Wall chord from (15, 0) to (10, 20): length sqrt(425); central angle alpha = 2 asin(len / 2R).
  const double R = 25.0, len = std::sqrt(425.0), alpha = 2.0 * std::asin(len / (2.0 * R));
  const double trapezoid = 0.5 * (30.0 + 20.0) * 20.0;
  const double exact_segment = 0.5 * R * R * (alpha - std::sin(alpha));  // circle segment beyond the chord
  const int n = p.wall_segments;
  const double poly_segment = 0.5 * R * R * (n * std::sin(alpha / n) - std::sin(alpha));  // inscribed polygon
  const double block = 60.0 * 30.0;
  EXPECT_NEAR(g.signed_volume_mm3(), 100.0 * (block - trapezoid - 2 * poly_segment), 1e-6);
  // Against the true arcs the chords cut off R^2/2 (alpha - n sin(alpha/n)) ~ R^2 alpha^3 / (12 n^2) per wall.
  const double chord_loss = 100.0 * 2.0 * R * R * alpha * alpha * alpha / (12.0 * n * n);
  EXPECT_NEAR(g.signed_volume_mm3() - 100.0 * (block - trapezoid - 2 * exact_segment), chord_loss, 0.01 * chord_loss);

  // The profile: overhang (floor wider than mouth) and the bulge.
  const GrooveProfile prof = groove_profile(p);
  EXPECT_NEAR(groove_half_width_at(p, 0.0), 15.0, 1e-12);
  EXPECT_NEAR(groove_half_width_at(p, 20.0), 10.0, 1e-12);
  EXPECT_GT(prof.max_half_width_mm, 15.0);
  EXPECT_NEAR(std::hypot(15.0 - prof.centre_y_mm, 0.0 - prof.centre_z_mm), 25.0, 1e-12);
  EXPECT_NEAR(std::hypot(10.0 - prof.centre_y_mm, 20.0 - prof.centre_z_mm), 25.0, 1e-12);
  // Every wall vertex is on the analytic arc (checked through the half-width function).
  for (const auto& v : g.vertices_mm)
    if (v.z() > 0.0 && v.z() < 20.0 && std::abs(v.y()) < 29.0)
      EXPECT_NEAR(std::abs(v.y()), groove_half_width_at(p, v.z()), 1e-9) << v.transpose();
}

TEST(GeomGroove, ParameterErrorsAndStraightWalls) {
  GrooveParams p;
  p.wall_radius_mm = 5.0;  // smaller than half the chord (10.3)
  EXPECT_THROW((void)make_groove(p), InputError);
  p = GrooveParams{};
  p.block_width_mm = 30.6;  // the bulge reaches |y| = 15.37 (> floor half width 15)
  EXPECT_THROW((void)make_groove(p), InputError);
  p = GrooveParams{};
  p.depth_mm = -1;
  EXPECT_THROW((void)make_groove(p), InputError);
  p = GrooveParams{};
  p.wall_radius_mm = 0.0;  // straight dovetail
  const Mesh g = make_groove(p);
  EXPECT_TRUE(g.is_closed());
  EXPECT_NEAR(g.signed_volume_mm3(), 100.0 * (60.0 * 30.0 - 0.5 * (30.0 + 20.0) * 20.0), 1e-6);
  EXPECT_NEAR(groove_half_width_at(p, 10.0), 12.5, 1e-12);
}

TEST(GeomGroove, BenchmarkPartHasAbout200kTrianglesAndIsClosed) {
  const Mesh m = make_benchmark_part(200000);
  EXPECT_NEAR(static_cast<double>(m.triangle_count()), 200000.0, 2000.0);
  EXPECT_TRUE(m.is_closed());
  EXPECT_GT(m.signed_volume_mm3(), 0.0);
}

// ---------------------------------------------------------------------------------------------------
// Tool shapes
// ---------------------------------------------------------------------------------------------------

TEST(GeomTool, FromCutterDefaultsAndValidation) {
  const ToolShape t = ToolShape::from_cutter(6.0, 3.0, 18.0);
  EXPECT_TRUE(t.is_ball());
  EXPECT_DOUBLE_EQ(t.shank.diameter_mm, 6.0);
  EXPECT_DOUBLE_EQ(t.shank.length_mm, 12.0);
  EXPECT_DOUBLE_EQ(t.holder.diameter_mm, 15.0);
  EXPECT_DOUBLE_EQ(t.holder.length_mm, 40.0);
  EXPECT_FALSE(t.spindle.present());
  EXPECT_DOUBLE_EQ(t.gauge_length_mm(), 18.0 + 12.0 + 40.0);
  const auto segs = t.segments();
  ASSERT_EQ(segs.size(), 3u);
  EXPECT_EQ(segs[2].part, ToolPart::Holder);
  EXPECT_DOUBLE_EQ(segs[2].z0_mm, 30.0);
  EXPECT_DOUBLE_EQ(segs[2].z1_mm, 70.0);

  EXPECT_THROW((void)ToolShape::from_cutter(6.0, 3.5, 18.0), InputError);
  EXPECT_THROW((void)ToolShape::from_cutter(0.0, 0.0, 18.0), InputError);
  EXPECT_THROW((void)ToolShape::from_cutter(6.0, 0.0, -1.0), InputError);
}

TEST(GeomTool, CheckedSegmentsExcludeTheCuttingEndAndInflate) {
  ToolDefaults d;
  d.spindle = {60.0, 30.0};
  const ToolShape ball = ToolShape::from_cutter(6.0, 3.0, 18.0, d);
  CheckOptions o;
  o.clearance_mm = 1.0;
  auto s = checked_segments(ball, o);
  ASSERT_EQ(s.size(), 4u);
  EXPECT_EQ(s[0].part, ToolPart::CutterBody);
  EXPECT_DOUBLE_EQ(s[0].z0_mm, 3.0 + 0.6);  // ball radius + 0.2 r relief
  EXPECT_DOUBLE_EQ(s[0].radius_mm, 3.0);    // cutter clearance 0
  EXPECT_DOUBLE_EQ(s[1].z0_mm, 18.0);       // shank not extended into the flutes
  EXPECT_DOUBLE_EQ(s[1].radius_mm, 4.0);
  EXPECT_DOUBLE_EQ(s[2].z0_mm, 30.0 - 1.0);  // holder bottom face is exposed
  EXPECT_DOUBLE_EQ(s[2].z1_mm, 70.0);        // covered by the wider spindle above
  EXPECT_DOUBLE_EQ(s[2].radius_mm, 8.5);
  EXPECT_DOUBLE_EQ(s[3].z1_mm, 100.0 + 1.0);

  const ToolShape flat = ToolShape::from_cutter(10.0, 0.0, 20.0);
  s = checked_segments(flat, {});
  EXPECT_DOUBLE_EQ(s[0].z0_mm, 0.5);
  o = {};
  o.check_cutter_body = false;
  EXPECT_EQ(checked_segments(flat, o).front().part, ToolPart::Shank);
}

// ---------------------------------------------------------------------------------------------------
// Collision and distance queries against analytic geometry
// ---------------------------------------------------------------------------------------------------

namespace {

/// A box with its top face at z = 0 and its side face y = 0 toward the tool: [0,100] x [0,100] x [-50,0].
Scene box_scene() {
  Scene s;
  s.add("box", ObstacleRole::Part, make_box({0, 0, -50}, {100, 100, 0}));
  s.build();
  return s;
}

}  // namespace

TEST(GeomQuery, HolderEntersBoxExactlyAtTheAnalyticHeight) {
  const Scene scene = box_scene();
  QueryWorkspace ws;
  // Ball mill D6, flutes 15, shank 12 -> holder (D15 -> radius 7.5) from 27 mm above the tip.
  const ToolShape tool = ToolShape::from_cutter(6.0, 3.0, 15.0);
  CheckOptions o;
  o.clearance_mm = 1.0;  // holder: radius 8.5, bottom face at tip + 26; shank radius 4
  // Axis at y = -5: cutter and shank stay 1 mm off the side face y = 0; the holder overhangs the box.
  const double y = -5.0, boundary_tip_z = -(27.0 - 1.0);
  for (double dz : {50.0, 10.0, 1.0, 0.1, 0.01}) {
    const auto r = check(scene, tool, pose({50, y, boundary_tip_z + dz}, {0, 0, 1}), o, ws);
    EXPECT_FALSE(r.collides) << "dz = " << dz;
    EXPECT_EQ(r.obstacle, -1);
  }
  for (double dz : {-0.01, -0.1, -1.0, -10.0}) {
    const auto r = check(scene, tool, pose({50, y, boundary_tip_z + dz}, {0, 0, 1}), o, ws);
    EXPECT_TRUE(r.collides) << "dz = " << dz;
    EXPECT_EQ(r.part, ToolPart::Holder) << "dz = " << dz;
    EXPECT_EQ(r.obstacle, 0);
  }
  // Without the clearance the boundary is 1 mm lower.
  CheckOptions o0;
  EXPECT_FALSE(check(scene, tool, pose({50, y, -27.0 + 0.01}, {0, 0, 1}), o0, ws).collides);
  EXPECT_TRUE(check(scene, tool, pose({50, y, -27.0 - 0.01}, {0, 0, 1}), o0, ws).collides);

  // Sideways: the holder (radius 8.5 with clearance) beside the face y = 0, holder well below the top.
  for (double dy : {0.01, -0.01}) {
    const auto r = check(scene, tool, pose({50, -(8.5 + dy), -40.0}, {0, 0, 1}), o, ws);
    EXPECT_EQ(r.collides, dy < 0) << "dy = " << dy;
    if (r.collides) EXPECT_EQ(r.part, ToolPart::Holder);
  }
  EXPECT_EQ(ws.stats.collision_queries, 13u);
  EXPECT_GT(ws.stats.fcl_collide_calls, 0u);
}

TEST(GeomQuery, BallContactAtTheSurfaceIsNotACollision) {
  const Scene scene = box_scene();
  QueryWorkspace ws;
  const ToolShape ball = ToolShape::from_cutter(6.0, 3.0, 15.0);
  // Tip on the top face, vertical and tilted by up to 60 deg about the ball centre (tip = C - r a).
  for (double deg : {0.0, 15.0, 30.0, 45.0, 60.0}) {
    const double t = deg2rad(deg);
    const Eigen::Vector3d a(std::sin(t), 0.0, std::cos(t)), C(50, 50, 3.0);
    EXPECT_FALSE(check(scene, ball, pose(C - 3.0 * a, a), {}, ws).collides) << deg;
  }
  // Even 2 mm deep (a gouge of the ball itself is the CL path's business, not the checker's)...
  EXPECT_FALSE(check(scene, ball, pose({50, 50, -2.0}, {0, 0, 1}), {}, ws).collides);
  // ...but the cylinder above the ball counts: start at 3.6 mm above the tip.
  EXPECT_FALSE(check(scene, ball, pose({50, 50, -3.59}, {0, 0, 1}), {}, ws).collides);
  EXPECT_TRUE(check(scene, ball, pose({50, 50, -3.61}, {0, 0, 1}), {}, ws).collides);

  // Flat mill: only the bottom 0.5 mm relief is excluded.
  const ToolShape flat = ToolShape::from_cutter(6.0, 0.0, 15.0);
  EXPECT_FALSE(check(scene, flat, pose({50, 50, 0.0}, {0, 0, 1}), {}, ws).collides);
  EXPECT_FALSE(check(scene, flat, pose({50, 50, -0.49}, {0, 0, 1}), {}, ws).collides);
  EXPECT_TRUE(check(scene, flat, pose({50, 50, -0.51}, {0, 0, 1}), {}, ws).collides);
  // A flat mill tilted about its tip on the surface digs its rim in: rim at 0.5 along the axis, 3 aside;
  // the rim's lowest point is 0.5 cos t - 3 sin t, negative beyond atan(1/6) = 9.46 deg.
  const double t_flat = std::atan(0.5 / 3.0);
  for (double d : {-0.2, 0.2}) {
    const double t = t_flat + deg2rad(d);
    EXPECT_EQ(check(scene, flat, pose({50, 50, 0}, {std::sin(t), 0, std::cos(t)}), {}, ws).collides, d > 0) << d;
  }
  // Without the cutter body check, nothing below the shank counts.
  CheckOptions no_cutter;
  no_cutter.check_cutter_body = false;
  EXPECT_FALSE(check(scene, flat, pose({50, 50, -10.0}, {0, 0, 1}), no_cutter, ws).collides);
  EXPECT_TRUE(check(scene, flat, pose({50, 50, -15.01}, {0, 0, 1}), no_cutter, ws).collides);
}

TEST(GeomQuery, DistanceMatchesAnalyticCylinderToBox) {
  const Scene scene = box_scene();
  QueryWorkspace ws;
  const ToolShape flat = ToolShape::from_cutter(6.0, 0.0, 15.0);  // checked cutter body from 0.5 above the tip
  for (double h : {0.3, 1.0, 5.0, 17.25}) {
    const double d = clearance(scene, flat, pose({50, 50, h}, {0, 0, 1}), {}, ws);
    EXPECT_NEAR(d, h + 0.5, 1e-6) << "h = " << h;
  }
  // Beside the side face y = 0 (axis at y = -12), tip at z = -40: the holder (radius 7.5, from 27 above the
  // tip) is beside the face, 12 - 7.5 = 4.5 mm away; flat cylinder side against a flat face.
  EXPECT_NEAR(clearance(scene, flat, pose({50, -12.0, -40.0}, {0, 0, 1}), {}, ws), 4.5, 1e-6);
  // With a long shank the holder is far up: the nearest is the cutter/shank side (radius 3), 9 mm away.
  ToolDefaults long_shank;
  long_shank.shank_length_mm = 60.0;
  const ToolShape flat_long = ToolShape::from_cutter(6.0, 0.0, 15.0, long_shank);
  EXPECT_NEAR(clearance(scene, flat_long, pose({50, -12.0, -20.0}, {0, 0, 1}), {}, ws), 9.0, 1e-6);
  // Tip at z = -20: the holder's bottom rim (y = -4.5, z = 7) is nearest to the box's top edge (y = 0, z = 0):
  // hypot(4.5, 7) < 9 (a circle against an edge).
  EXPECT_NEAR(clearance(scene, flat, pose({50, -12.0, -20.0}, {0, 0, 1}), {}, ws), std::hypot(4.5, 7.0), 1e-6);
  // Tilted over the top face: the lowest rim point of the checked body (0.5 up the axis, radius 3) is at
  // h + 0.5 cos t - 3 sin t.
  for (double deg : {10.0, 30.0}) {
    const double t = deg2rad(deg), h = 2.0;
    EXPECT_NEAR(clearance(scene, flat, pose({50, 50, h}, {std::sin(t), 0, std::cos(t)}), {}, ws),
                h + 0.5 * std::cos(t) - 3.0 * std::sin(t), 1e-6)
        << deg;
  }

  // check() with compute_distance agrees and names the nearest part.
  CheckOptions o;
  o.compute_distance = true;
  const auto r = check(scene, flat, pose({50, 50, 5.0}, {0, 0, 1}), o, ws);
  EXPECT_FALSE(r.collides);
  EXPECT_NEAR(r.min_distance_mm, 5.5, 1e-6);
  EXPECT_EQ(r.nearest_part, ToolPart::CutterBody);
  EXPECT_EQ(r.nearest_obstacle, 0);
  // Colliding: distance 0.
  EXPECT_EQ(clearance(scene, flat, pose({50, 50, -5.0}, {0, 0, 1}), {}, ws), 0.0);
  const auto rc = check(scene, flat, pose({50, 50, -5.0}, {0, 0, 1}), o, ws);
  EXPECT_TRUE(rc.collides);
  EXPECT_EQ(rc.min_distance_mm, 0.0);
  // Not asked: NaN.
  EXPECT_TRUE(std::isnan(check(scene, flat, pose({50, 50, 5.0}, {0, 0, 1}), {}, ws).min_distance_mm));

  EXPECT_EQ(ws.stats.distance_queries, 10u + 2u);
  EXPECT_EQ(ws.stats.collision_queries, 3u);
  EXPECT_GT(ws.stats.fcl_distance_calls, 0u);
}

namespace {

/// Tool for the groove: ball D6, flutes 25, shank 20, holder D15 x 40 (from 45 mm above the tip).
ToolShape groove_tool() {
  ToolDefaults d;
  d.shank_length_mm = 20.0;
  return ToolShape::from_cutter(6.0, 3.0, 25.0, d);
}

/// Ball tool on the groove floor at (0, 0, 0), tilted by t toward +y (sign > 0) or -y about the ball centre.
kin::Posed tilted(double t, double sign) {
  const Eigen::Vector3d a(0.0, sign * std::sin(t), std::cos(t)), C(0.0, 0.0, 3.0);
  return {C - 3.0 * a, a};
}

}  // namespace

TEST(GeomQuery, TiltedToolInTheGrooveHitsTheOverhangAtTheAnalyticAngle) {
  const GrooveParams p;  // mouth half width 10 at depth 20
  Scene scene;
  scene.add("groove", ObstacleRole::Part, make_groove(p));
  scene.build();
  QueryWorkspace ws;
  const ToolShape tool = groove_tool();

  // The groove is an extrusion along X, so in the section x = 0 the tool is a band of half width rho = 3 around
  // its axis line through the ball centre C = (0, 3). The cavity is convex, so the band leaves it through the
  // mouth until its side touches the lip (10, 20): A cos t - B sin t = rho with A = 10, B = 20 - 3.
  const double A = 10.0, B = 17.0, rho = 3.0;
  const double t_star = std::acos(rho / std::hypot(A, B)) - std::atan2(B, A);  // ~21.7 deg
  ASSERT_GT(t_star, deg2rad(15.0));
  ASSERT_LT(t_star, deg2rad(30.0));
  // The lip meets the tool at (P - C).a + r from the tip, inside the flutes (25).
  const double s_star = A * std::sin(t_star) + B * std::cos(t_star) + 3.0;
  ASSERT_LT(s_star, 25.0);

  EXPECT_FALSE(check(scene, tool, tilted(0.0, 1.0), {}, ws).collides);  // vertical on the floor centre
  for (double sign : {1.0, -1.0}) {
    EXPECT_FALSE(check(scene, tool, tilted(t_star - deg2rad(0.001), sign), {}, ws).collides) << sign;
    const auto hit = check(scene, tool, tilted(t_star + deg2rad(0.001), sign), {}, ws);
    EXPECT_TRUE(hit.collides) << sign;
    EXPECT_EQ(hit.part, ToolPart::CutterBody) << sign;
    EXPECT_TRUE(check(scene, tool, tilted(deg2rad(40.0), sign), {}, ws).collides) << sign;
  }
  // Tilting along the groove (toward +x) is free far beyond t_star: the band in y stays within the mouth.
  const Eigen::Vector3d ax(std::sin(deg2rad(40.0)), 0.0, std::cos(deg2rad(40.0)));
  EXPECT_FALSE(check(scene, tool, pose(Eigen::Vector3d(0, 0, 3.0) - 3.0 * ax, ax), {}, ws).collides);

  // Distance below the threshold: from the lip edge to the cylinder side, A cos t - B sin t - rho.
  for (double below : {1.0, 5.0}) {
    const double t = t_star - deg2rad(below);
    EXPECT_NEAR(clearance(scene, tool, tilted(t, 1.0), {}, ws), A * std::cos(t) - B * std::sin(t) - rho, 1e-6);
  }
}

TEST(GeomQuery, RolesAndMachineObstaclePlacement) {
  Scene scene;
  scene.add("part", ObstacleRole::Part, make_box({-10, -10, -10}, {10, 10, 0}));
  // A fixture clamp 30 mm to the side, and a machine-frame obstacle that is placed per query.
  scene.add("clamp", ObstacleRole::Fixture, make_box({30, -5, -10}, {40, 5, 20}));
  scene.add("column", ObstacleRole::Machine, make_box({-5, -5, 0}, {5, 5, 10}));
  EXPECT_THROW(scene.add("empty", ObstacleRole::Part, Mesh{}), InputError);
  scene.build();
  EXPECT_THROW(scene.add("late", ObstacleRole::Part, make_box({0, 0, 0}, {1, 1, 1})), std::logic_error);
  EXPECT_EQ(scene.obstacle_count(), 3u);
  EXPECT_EQ(scene.triangle_count(), 36u);
  EXPECT_EQ(scene.obstacle_name(1), "clamp");
  EXPECT_EQ(scene.obstacle_role(2), ObstacleRole::Machine);

  QueryWorkspace ws;
  const ToolShape tool = ToolShape::from_cutter(10.0, 0.0, 20.0);  // holder D25 from 40 to 80
  CheckOptions o;
  o.machine_in_part = Eigen::Translation3d(500, 500, 500) * Eigen::Isometry3d::Identity();  // far away
  // Tool tilted 60 deg toward the clamp, 5 mm above the part: the shank (radius 5) crosses x = 30..40 at z ~ 20.
  const double t = deg2rad(60.0);
  const kin::Posed p = pose({5, 0, 5}, {std::sin(t), 0, std::cos(t)});
  auto r = check(scene, tool, p, o, ws);
  EXPECT_TRUE(r.collides);
  EXPECT_EQ(r.obstacle, 1);
  o.roles = static_cast<unsigned>(ObstacleRole::Part);
  EXPECT_FALSE(check(scene, tool, p, o, ws).collides);

  // The machine obstacle moved onto the tool's shank: collides only when placed there and selected.
  o.roles = kAllRoles;
  const kin::Posed v = pose({0, 0, 0.1}, {0, 0, 1});
  EXPECT_FALSE(check(scene, tool, v, o, ws).collides);
  o.machine_in_part = Eigen::Translation3d(0, 0, 25) * Eigen::Isometry3d::Identity();
  r = check(scene, tool, v, o, ws);
  EXPECT_TRUE(r.collides);
  EXPECT_EQ(r.obstacle, 2);
  o.roles = static_cast<unsigned>(ObstacleRole::Part) | static_cast<unsigned>(ObstacleRole::Fixture);
  EXPECT_FALSE(check(scene, tool, v, o, ws).collides);
}

TEST(GeomQuery, SceneWithoutDistanceSupportStillChecksCollisions) {
  Scene scene;
  scene.add("box", ObstacleRole::Part, make_box({0, 0, -50}, {100, 100, 0}));
  scene.build(/*with_distance=*/false);
  EXPECT_FALSE(scene.supports_distance());
  QueryWorkspace ws;
  const ToolShape flat = ToolShape::from_cutter(6.0, 0.0, 15.0);
  EXPECT_TRUE(check(scene, flat, pose({50, 50, -0.51}, {0, 0, 1}), {}, ws).collides);
  EXPECT_THROW((void)clearance(scene, flat, pose({50, 50, 1.0}, {0, 0, 1}), {}, ws), std::logic_error);
  Scene unbuilt;
  unbuilt.add("box", ObstacleRole::Part, make_box({0, 0, -50}, {100, 100, 0}));
  EXPECT_THROW((void)check(unbuilt, flat, pose({50, 50, 1.0}, {0, 0, 1}), {}, ws), std::logic_error);
  // A zero axis is a caller bug.
  EXPECT_THROW((void)check(scene, flat, kin::Posed{{50, 50, 1.0}, {0, 0, 0}}, {}, ws), std::logic_error);
}

TEST(GeomQuery, ConcurrentQueriesWithPerThreadWorkspacesAgreeWithSerial) {
  Scene scene;
  GrooveParams gp;
  gp.length_segments = 20;
  scene.add("groove", ObstacleRole::Part, make_groove(gp));
  scene.build();
  const ToolShape tool = groove_tool();
  auto rng = test::rng(7);
  std::uniform_real_distribution<double> ux(-40, 40), ut(0, deg2rad(45.0)), uphi(0, 2 * kPi);
  std::vector<kin::Posed> poses;
  for (int i = 0; i < 400; ++i) {
    const double t = ut(rng), ph = uphi(rng);
    const Eigen::Vector3d a(std::sin(t) * std::cos(ph), std::sin(t) * std::sin(ph), std::cos(t));
    poses.push_back({Eigen::Vector3d(ux(rng), 0, 3) - 3.0 * a, a});
  }
  QueryWorkspace serial_ws;
  std::vector<int> serial(poses.size());
  for (std::size_t i = 0; i < poses.size(); ++i) serial[i] = check(scene, tool, poses[i], {}, serial_ws).collides;
  const auto hits = std::count(serial.begin(), serial.end(), 1);
  EXPECT_GT(hits, 20);  // a mix of free and colliding poses
  EXPECT_LT(hits, 380);

  std::vector<int> par(poses.size(), -1);
  std::vector<QueryWorkspace> wss(2);
  std::vector<std::thread> th;
  for (int k = 0; k < 2; ++k)
    th.emplace_back([&, k] {
      for (std::size_t i = static_cast<std::size_t>(k); i < poses.size(); i += 2)
        par[i] = check(scene, tool, poses[i], {}, wss[static_cast<std::size_t>(k)]).collides;
    });
  for (auto& t : th) t.join();
  EXPECT_EQ(par, serial);
  QueryStats total = wss[0].stats;
  total += wss[1].stats;
  EXPECT_EQ(total.collision_queries, poses.size());
}

// Inputs found by fuzz/mesh_fuzz (tests/data/fuzz-regressions): assimp 5.2 hung on the first, aborted on the
// second and the last, and tried to allocate tens of GB for the huge-count headers. The loader must answer each
// with an InputError naming the file.
TEST(MeshFuzzRegressions, MalformedPlyAndOffAreInputErrors) {
  namespace fs = std::filesystem;
  // The third hangs assimp itself: the loader's child process is stopped at the time limit.
  ::setenv("CSCAM_MESH_TIMEOUT_S", "3", 1);
  const std::pair<const char*, const char*> cases[] = {
      {"mesh-ply-no-end-header.bin", ".ply"},        {"mesh-off-binary-bytes.bin", ".off"},
      {"mesh-ply-end-header-in-token.bin", ".ply"},  {"mesh-off-huge-count.bin", ".off"},
      {"mesh-ply-huge-count.bin", ".ply"},           {"mesh-off-triangulate-abort.bin", ".off"},
      {"mesh-off-no-keyword-huge-count.bin", ".off"}};
  for (const auto& [file, ext] : cases) {
    SCOPED_TRACE(file);
    std::ifstream in(test::source_path(std::string("tests/data/fuzz-regressions/") + file), std::ios::binary);
    ASSERT_TRUE(in);
    std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    const fs::path p =
        fs::temp_directory_path() / (std::string("cscam_fuzz_regression_") + std::to_string(::getpid()) + ext);
    std::ofstream(p, std::ios::binary) << bytes.substr(1);  // the fuzzer's first byte chose the extension
    try {
      (void)geom::load_mesh(p.string(), 1.0, false);
      ADD_FAILURE() << "a malformed mesh was accepted";
    } catch (const InputError& e) {
      EXPECT_NE(std::string(e.what()).find(p.filename().string()), std::string::npos) << e.what();
    }
    fs::remove(p);
  }
  ::unsetenv("CSCAM_MESH_TIMEOUT_S");
}

// ---------------------------------------------------------------------------------------------------
// Mesh validation and repair (CGAL). Oracles independent of CGAL: the divergence-theorem volume,
// the Euler characteristic from our own edge count, Mesh::is_closed and FCL queries.
// ---------------------------------------------------------------------------------------------------

namespace {

/// V - E + F over the vertices that triangles use (2 for a closed genus-0 surface).
long euler_characteristic(const Mesh& m) {
  std::set<std::pair<int, int>> edges;
  std::set<int> used;
  for (const auto& t : m.triangles)
    for (int k = 0; k < 3; ++k) {
      const int a = t[k], b = t[(k + 1) % 3];
      edges.insert({std::min(a, b), std::max(a, b)});
      used.insert(a);
    }
  return static_cast<long>(used.size()) - static_cast<long>(edges.size()) + static_cast<long>(m.triangles.size());
}

/// The box as an unwelded triangle soup: every triangle has its own three vertices (what STL stores).
Mesh soup_of(const Mesh& m) {
  Mesh s;
  s.source = m.source;
  for (const auto& t : m.triangles) {
    const int base = static_cast<int>(s.vertices_mm.size());
    for (int k = 0; k < 3; ++k) s.vertices_mm.push_back(m.vertices_mm[static_cast<std::size_t>(t[k])]);
    s.triangles.emplace_back(base, base + 1, base + 2);
  }
  return s;
}

void flip(Mesh& m, std::size_t t) { std::swap(m.triangles[t][1], m.triangles[t][2]); }

}  // namespace

TEST(GeomMeshCheck, CleanBoxIsTrustedAndUnchanged) {
  Mesh box = make_box({0, 0, 0}, {10, 20, 30});
  const Mesh before = box;
  const MeshCheckReport r = check_and_repair(box);
  EXPECT_TRUE(r.trusted()) << r.error;
  EXPECT_FALSE(r.repaired());
  EXPECT_TRUE(r.closed);
  EXPECT_EQ(r.components, 1u);
  EXPECT_EQ(r.self_intersections, 0u);
  EXPECT_NEAR(r.volume_mm3, 6000.0, 1e-9);
  EXPECT_EQ(box.triangle_count(), before.triangle_count());
  EXPECT_NEAR(box.signed_volume_mm3(), 6000.0, 1e-9);
  EXPECT_TRUE(box.is_closed());
}

TEST(GeomMeshCheck, DuplicatedVerticesAreMergedIntoAClosedGenusZeroSurface) {
  Mesh soup = soup_of(make_box({-1, -2, -3}, {4, 5, 6}));
  ASSERT_EQ(soup.vertices_mm.size(), 36u);
  ASSERT_FALSE(soup.is_closed());  // unwelded: every edge is a boundary edge
  const MeshCheckReport r = check_and_repair(soup);
  ASSERT_TRUE(r.trusted()) << r.error;
  EXPECT_EQ(r.duplicate_vertices_merged, 28u);
  EXPECT_EQ(soup.vertices_mm.size(), 8u);
  EXPECT_EQ(soup.triangle_count(), 12u);
  std::string why;
  EXPECT_TRUE(soup.is_closed(&why)) << why;
  EXPECT_EQ(euler_characteristic(soup), 2);
  EXPECT_NEAR(soup.signed_volume_mm3(), 5.0 * 7.0 * 9.0, 1e-9);
  ASSERT_FALSE(r.repairs.empty());
  EXPECT_NE(r.repairs[0].find("merged 28 duplicate vertices"), std::string::npos) << r.repairs[0];
}

TEST(GeomMeshCheck, FlippedAndInvertedFacesAreOrientedOutward) {
  Mesh some = make_box({0, 0, 0}, {2, 3, 4});
  for (std::size_t t : {1u, 4u, 9u}) flip(some, t);
  ASSERT_FALSE(some.is_closed());
  MeshCheckReport r = check_and_repair(some);
  ASSERT_TRUE(r.trusted()) << r.error;
  EXPECT_EQ(r.faces_reoriented, 3u);
  EXPECT_TRUE(some.is_closed());
  EXPECT_NEAR(some.signed_volume_mm3(), 24.0, 1e-9);

  Mesh inverted = make_box({0, 0, 0}, {2, 3, 4});
  for (std::size_t t = 0; t < inverted.triangle_count(); ++t) flip(inverted, t);
  ASSERT_TRUE(inverted.is_closed());  // consistent, but inward
  ASSERT_NEAR(inverted.signed_volume_mm3(), -24.0, 1e-9);
  r = check_and_repair(inverted);
  ASSERT_TRUE(r.trusted()) << r.error;
  EXPECT_EQ(r.faces_reoriented, 12u);
  EXPECT_NEAR(inverted.signed_volume_mm3(), 24.0, 1e-9);
  EXPECT_NEAR(r.volume_mm3, 24.0, 1e-9);

  // A hollow solid (outer shell and a cavity): the cavity must face inward, so the volume is the difference.
  Mesh hollow = make_box({0, 0, 0}, {10, 10, 10});
  hollow.append(make_box({2, 2, 2}, {8, 8, 8}));  // wrongly outward, as a careless exporter writes it
  r = check_and_repair(hollow);
  ASSERT_TRUE(r.trusted()) << r.error;
  EXPECT_EQ(r.components, 2u);
  EXPECT_EQ(r.faces_reoriented, 12u);
  EXPECT_NEAR(hollow.signed_volume_mm3(), 1000.0 - 216.0, 1e-9);
}

TEST(GeomMeshCheck, OpenBoxIsUntrustedAsASolidNamingTheFile) {
  Mesh open = make_box({0, 0, 0}, {2, 2, 2});
  open.source = "fixture_open.stl";
  open.triangles.resize(10);  // the face x = 2 is missing
  Mesh copy = open;
  const MeshCheckReport r = check_and_repair(copy);
  EXPECT_FALSE(r.trusted());
  EXPECT_EQ(r.border_edges, 4u);
  EXPECT_NE(r.error.find("open after repair: 4 border edges"), std::string::npos) << r.error;
  EXPECT_EQ(copy.triangle_count(), 10u);  // an untrusted mesh is left as it was
  const std::string msg = message_of([&] { (void)require_trusted(open); });
  EXPECT_EQ(msg.rfind("fixture_open.stl: ", 0), 0u) << msg;

  // As a surface it is accepted with a warning.
  const MeshCheckReport s = check_and_repair(open, {MeshUse::Surface, true});
  EXPECT_TRUE(s.trusted()) << s.error;
  ASSERT_FALSE(s.warnings.empty());
  EXPECT_NE(s.warnings.back().find("open surface: 4 border edges"), std::string::npos);
}

// A file triangle whose two corners are one point is dropped by the loader (after welding, it names one vertex twice):
// it was dropped with no word, and the check reported one triangle fewer in and nothing removed. The loader counts it
// (through the reader's child process) and the check reports it with the other repairs.
TEST(GeomMeshCheck, ATriangleCollapsedAtLoadIsReported) {
  const auto dir = std::filesystem::temp_directory_path() / ("cscam_geom_collapsed_" + std::to_string(::getpid()));
  std::filesystem::create_directories(dir);
  Mesh box = make_box({0, 0, 0}, {4, 2, 2});
  box.triangles.emplace_back(0, 0, 6);  // two corners at one point
  const std::string path = (dir / "box.stl").string();
  save_stl(box, path);
  Mesh m = load_mesh(path);
  EXPECT_EQ(m.triangle_count(), 12u);
  EXPECT_EQ(m.collapsed_at_load, 1u);
  const MeshCheckReport r = check_and_repair(m);
  EXPECT_EQ(r.triangles_in, 13u);
  EXPECT_EQ(r.repeated_index_faces_removed, 1u);
  EXPECT_TRUE(std::any_of(r.repairs.begin(), r.repairs.end(),
                          [](const std::string& s) { return s.find("name one vertex twice") != std::string::npos; }));
  std::filesystem::remove_all(dir);
}

TEST(GeomMeshCheck, DegenerateTrianglesAreRemovedWithoutOpeningTheSurface) {
  // A box whose front face has a vertex m in the middle of edge 0-1 (a T-junction), closed by the zero-area
  // triangle (0, 1, m), plus a triangle that names a vertex twice.
  Mesh m = make_box({0, 0, 0}, {4, 2, 2});
  const int mid = static_cast<int>(m.vertices_mm.size());
  m.vertices_mm.emplace_back(2, 0, 0);
  bool replaced = false;
  for (auto& t : m.triangles)
    if (t == Eigen::Vector3i(0, 1, 5)) {
      t = Eigen::Vector3i(0, mid, 5);
      replaced = true;
    }
  ASSERT_TRUE(replaced);
  m.triangles.emplace_back(mid, 1, 5);
  m.triangles.emplace_back(0, 1, mid);  // zero area
  m.triangles.emplace_back(3, 3, 7);    // repeated index
  const double volume = 16.0;
  ASSERT_NEAR(m.signed_volume_mm3(), volume, 1e-12);
  const MeshCheckReport r = check_and_repair(m);
  ASSERT_TRUE(r.trusted()) << r.error;
  EXPECT_EQ(r.repeated_index_faces_removed, 1u);
  EXPECT_GE(r.degenerate_faces_removed, 1u);
  EXPECT_EQ(r.degenerate_faces_left, 0u);
  std::string why;
  EXPECT_TRUE(m.is_closed(&why)) << why;
  EXPECT_EQ(euler_characteristic(m), 2);
  EXPECT_NEAR(m.signed_volume_mm3(), volume, 1e-9);
  for (const auto& t : m.triangles) {
    const Eigen::Vector3d a = m.vertices_mm[static_cast<std::size_t>(t[0])];
    EXPECT_GT((m.vertices_mm[static_cast<std::size_t>(t[1])] - a)
                  .cross(m.vertices_mm[static_cast<std::size_t>(t[2])] - a)
                  .norm(),
              1e-9);
  }
}

TEST(GeomMeshCheck, SelfIntersectingSolidIsUntrustedButOverlappingSolidsAreKept) {
  // One vertex of the top pushed through the bottom: the top triangles cross the bottom ones.
  Mesh crossed = make_box({0, 0, 0}, {10, 10, 10});
  crossed.source = "crossed.stl";
  crossed.vertices_mm[7] = Eigen::Vector3d(10, 10, -5);
  const MeshCheckReport r = check_and_repair(crossed);
  EXPECT_FALSE(r.trusted());
  EXPECT_GT(r.self_intersections, 0u);
  EXPECT_NE(r.error.find("crosses itself"), std::string::npos) << r.error;
  EXPECT_THROW((void)require_trusted(crossed), InputError);

  // Two closed boxes overlapping (a bolt through a plate): a union the checker handles; warned.
  Mesh pair = make_box({0, 0, 0}, {10, 10, 2});
  pair.append(make_box({4, 4, -3}, {6, 6, 5}));
  for (std::size_t t = 0; t < 12; ++t) flip(pair, 12 + t);  // and the bolt inward
  const MeshCheckReport p = check_and_repair(pair);
  ASSERT_TRUE(p.trusted()) << p.error;
  EXPECT_EQ(p.components, 2u);
  EXPECT_GT(p.component_overlaps, 0u);
  EXPECT_EQ(p.faces_reoriented, 12u);
  ASSERT_FALSE(p.warnings.empty());
  EXPECT_NE(p.warnings[0].find("overlap"), std::string::npos);
  EXPECT_NEAR(pair.signed_volume_mm3(), 200.0 + 32.0, 1e-9);  // each solid counted outward
}

TEST(GeomMeshCheck, RepairOffMakesANeededRepairAnError) {
  Mesh soup = soup_of(make_box({0, 0, 0}, {1, 1, 1}));
  const MeshCheckReport r = check_and_repair(soup, {MeshUse::Solid, /*repair=*/false});
  EXPECT_FALSE(r.trusted());
  EXPECT_NE(r.error.find("repair is off"), std::string::npos) << r.error;
  EXPECT_EQ(soup.vertices_mm.size(), 36u);
}

TEST(GeomMeshCheck, LoadCheckedRepairsAFlippedStlThatTheLoaderRejects) {
  const fs::path dir = temp_dir();
  Mesh box = make_box({0, 0, 0}, {20, 20, 20});
  for (std::size_t t : {0u, 5u}) flip(box, t);
  const std::string path = (dir / "flipped.stl").string();
  save_stl(box, path);
  EXPECT_THROW((void)load_mesh(path), InputError);  // the strict loader: inconsistently oriented
  MeshCheckReport report;
  const Mesh m = load_checked_mesh(path, 1.0, {}, &report);
  EXPECT_EQ(report.faces_reoriented, 2u);
  EXPECT_EQ(report.source, path);
  EXPECT_TRUE(m.is_closed());
  EXPECT_NEAR(m.signed_volume_mm3(), 8000.0, 1e-6);

  // FCL oracle: a tool plunged into the top face hits, one beside the box does not, as for the clean box.
  Scene scene;
  scene.add("box", ObstacleRole::Part, m);
  scene.build(false);
  QueryWorkspace ws;
  const ToolShape tool = ToolShape::from_cutter(6, 3, 18);
  CheckOptions o;
  EXPECT_TRUE(check(scene, tool, pose({10, 10, 10}, {0, 0, 1}), o, ws).collides);
  EXPECT_FALSE(check(scene, tool, pose({40, 10, 10}, {0, 0, 1}), o, ws).collides);

  Mesh open = make_box({0, 0, 0}, {2, 2, 2});
  open.triangles.resize(10);
  const std::string p2 = (dir / "open_for_check.stl").string();
  save_stl(open, p2);
  const std::string msg = message_of([&] { (void)load_checked_mesh(p2); });
  EXPECT_EQ(msg.rfind(p2 + ": ", 0), 0u) << msg;
  EXPECT_NE(msg.find("open after repair"), std::string::npos) << msg;
}

// ---------------------------------------------------------------------------------------------------
// Primitives for machine bodies, and obstacles placed per machine link
// ---------------------------------------------------------------------------------------------------

TEST(GeomPrimitives, CylinderPrismIsClosedOutwardAndCircumscribed) {
  const Eigen::Vector3d a(10, -5, 3), b(40, 15, 63);
  const double d = 50.0, L = (b - a).norm();
  const int n = 32;
  const Mesh c = cylinder_mesh(a, b, d, n);
  std::string why;
  EXPECT_TRUE(c.is_closed(&why)) << why;
  EXPECT_EQ(euler_characteristic(c), 2);
  // Volume of the circumscribed regular n-gon prism: n rc^2 sin(2 pi / n) / 2 * L, rc = r / cos(pi / n).
  const double pi = 3.14159265358979323846, rc = 0.5 * d / std::cos(pi / n);
  EXPECT_NEAR(c.signed_volume_mm3(), 0.5 * n * rc * rc * std::sin(2 * pi / n) * L, 1e-6 * L * d * d);
  // Every point of the true cylinder's rim is inside: its distance to the axis is below the polygon's
  // inradius, which is the cylinder radius itself (tangent sides).
  const Eigen::Vector3d w = (b - a) / L;
  for (const auto& v : c.vertices_mm) {
    const Eigen::Vector3d r = (v - a) - (v - a).dot(w) * w;
    if (r.norm() > 1e-9) EXPECT_NEAR(r.norm(), rc, 1e-9);
  }
  EXPECT_THROW((void)cylinder_mesh(a, a, d), InputError);
  EXPECT_THROW((void)box_mesh({0, 0, 0}, {1, 0, 1}), InputError);
  EXPECT_NEAR(box_mesh({0, 0, 0}, {1, 2, 3}).signed_volume_mm3(), 6.0, 1e-12);
}

TEST(GeomQuery, LinkedMachineObstaclesArePlacedByTheirLinkPose) {
  // A 20 mm cube given at the origin of its link; the tool stands at x = 100. Link pose: shift by +100 in x
  // -> the cube surrounds the tool; identity -> far away. Without link poses the obstacle is not tested.
  Scene scene;
  scene.add("cube", ObstacleRole::Machine, make_box({-10, -10, -10}, {10, 10, 10}), /*link=*/1);
  scene.build(false);
  EXPECT_EQ(scene.link_count(), 2);
  EXPECT_EQ(scene.obstacle_link(0), 1);
  const ToolShape tool = ToolShape::from_cutter(6, 0, 18);
  QueryWorkspace ws;
  std::array<Eigen::Isometry3d, 2> links{Eigen::Isometry3d::Identity(), Eigen::Isometry3d::Identity()};
  CheckOptions o;
  o.links_in_part = links.data();
  const kin::Posed p = pose({100, 0, -30}, {0, 0, 1});
  EXPECT_FALSE(check(scene, tool, p, o, ws).collides);
  links[1].translation() = Eigen::Vector3d(100, 0, 0);
  EXPECT_TRUE(check(scene, tool, p, o, ws).collides);
  o.machine_in_part.translation() = Eigen::Vector3d(100, 0, 0);  // not used for a linked obstacle
  links[1].translation() = Eigen::Vector3d(-100, 0, 0);
  EXPECT_FALSE(check(scene, tool, p, o, ws).collides);
  o.links_in_part = nullptr;
  EXPECT_FALSE(check(scene, tool, p, o, ws).collides);

  // Head side: a moving scene's linked obstacle uses the link pose, not moving_in_part.
  Scene head;
  head.add("nose", ObstacleRole::Machine, make_box({-5, -5, 0}, {5, 5, 10}), /*link=*/0);
  head.build(false);
  std::array<Eigen::Isometry3d, 2> hl{Eigen::Isometry3d::Identity(), Eigen::Isometry3d::Identity()};
  hl[0].translation() = Eigen::Vector3d(100, 0, 5);  // the nose box (z 5..15) now straddles the cube's top face
  links[1].translation() = Eigen::Vector3d(100, 0, 0);
  // Both scenes read the same array: link 0 for the nose, link 1 for the cube.
  std::array<Eigen::Isometry3d, 2> both{hl[0], links[1]};
  o.links_in_part = both.data();
  int which = -1;
  const CollisionResult r = check_meshes(head, Eigen::Isometry3d::Identity(), scene, o, ws, &which);
  EXPECT_TRUE(r.collides);
  EXPECT_EQ(which, 0);
  both[0].translation() = Eigen::Vector3d(100, 0, 50);
  EXPECT_FALSE(check_meshes(head, Eigen::Isometry3d::Identity(), scene, o, ws).collides);
}

// CheckOptions::erosion_mm against plain checks: whenever the tool eroded by m hits the groove at a pose, the whole
// tool hits it at every pose whose points all lie within m of their place there (random shifts of the tip and turns
// of the axis with |shift| + reach * |axis change| < m). The planner's hit certificates rest on this.
TEST(GeomQuery, AnErodedHitMeansEveryPoseWithinTheErosionHits) {
  Scene scene;
  scene.add("groove", ObstacleRole::Part, load_mesh(test::source_path("examples/groove/groove.stl")));
  scene.build(false);
  const ToolShape tool = ToolShape::from_cutter(10, 5, 30);
  double reach = 0;  // the farthest checked point from the tip
  for (const ToolSegment& s : tool.segments()) reach = std::max(reach, std::hypot(s.z1_mm, s.radius_mm));
  QueryWorkspace ws;
  auto rng = test::rng(41);
  std::uniform_real_distribution<double> U(-1.0, 1.0);
  auto unit = [&] {
    Eigen::Vector3d v;
    do v = Eigen::Vector3d(U(rng), U(rng), U(rng));
    while (v.norm() < 0.1 || v.norm() > 1.0);
    return v.normalized();
  };
  int eroded_hits = 0, checked = 0;
  for (int trial = 0; trial < 400; ++trial) {
    // Along the groove, tilted up to about 35 deg toward its walls.
    const kin::Posed p{Eigen::Vector3d(40 * U(rng), 6 * U(rng), 2 + 4 * U(rng)),
                       (Eigen::Vector3d::UnitZ() + 0.7 * Eigen::Vector3d(U(rng), U(rng), 0)).normalized()};
    CheckOptions eroded;
    eroded.erosion_mm = 0.25 + 0.75 * (0.5 + 0.5 * U(rng));
    if (!check(scene, tool, p, eroded, ws).collides) continue;
    ++eroded_hits;
    for (int k = 0; k < 10; ++k) {
      // Split the budget between a shift and a turn about the tip.
      const double share = 0.5 + 0.5 * U(rng), budget = 0.999 * eroded.erosion_mm;
      const Eigen::Vector3d shift = share * budget * unit();
      const double chord = (1 - share) * budget / reach, angle = 2 * std::asin(0.5 * chord);
      const Eigen::Vector3d turned = Eigen::AngleAxisd(angle, p.axis.cross(unit()).normalized()) * p.axis;
      const kin::Posed q{p.tip_mm + shift, turned};
      ++checked;
      EXPECT_TRUE(check(scene, tool, q, CheckOptions{}, ws).collides)
          << "trial " << trial << ": the eroded tool hits, a pose within the erosion does not";
    }
  }
  EXPECT_GE(eroded_hits, 40);
  EXPECT_GE(checked, 400);
}

// The planner re-tests a colliding cell's previous contact at the next CL point before it queries (check_witness).
// Oracle: the full query. At the pose that found it the witness must hold; at a moved pose a witness that holds
// must be a hit the full query sees too (with and without erosion), and it must be the usual case for small moves.
TEST(GeomQuery, AWitnessThatHoldsIsAHitTheFullQuerySees) {
  Scene scene;
  scene.add("groove", ObstacleRole::Part, load_mesh(test::source_path("examples/groove/groove.stl")));
  scene.build(false);
  const ToolShape tool = ToolShape::from_cutter(10, 5, 30);
  QueryWorkspace ws;
  auto rng = test::rng(43);
  std::uniform_real_distribution<double> U(-1.0, 1.0);
  int hits = 0, held = 0, moved = 0;
  for (int trial = 0; trial < 400; ++trial) {
    const kin::Posed p{Eigen::Vector3d(40 * U(rng), 6 * U(rng), 2 + 4 * U(rng)),
                       (Eigen::Vector3d::UnitZ() + 0.7 * Eigen::Vector3d(U(rng), U(rng), 0)).normalized()};
    CheckOptions o;
    o.erosion_mm = trial % 2 ? 0.0 : 0.3;
    const CollisionResult r = check(scene, tool, p, o, ws);
    if (!r.collides) continue;
    ++hits;
    const Witness w{r.segment, r.obstacle, r.triangle};
    ASSERT_TRUE(w.valid());
    const CollisionResult again = check_witness(scene, tool, p, o, ws, w);
    EXPECT_TRUE(again.collides) << "trial " << trial;
    EXPECT_EQ(again.part, r.part);
    for (int k = 0; k < 5; ++k) {
      const kin::Posed q{p.tip_mm + 0.05 * Eigen::Vector3d(U(rng), U(rng), U(rng)), p.axis};
      if (!check_witness(scene, tool, q, o, ws, w).collides) continue;
      ++held;
      EXPECT_TRUE(check(scene, tool, q, o, ws).collides) << "trial " << trial << ": witness holds, query is free";
    }
    moved += 5;
  }
  EXPECT_GE(hits, 40);
  EXPECT_GT(held, moved / 2);  // the common case after a small move: the same contact
  EXPECT_FALSE(check_witness(scene, tool, {Eigen::Vector3d(0, 0, 50), Eigen::Vector3d::UnitZ()}, {}, ws, {}).collides);
}
