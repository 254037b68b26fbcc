#include "cscam/geom/groove.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>

#include "cscam/core/error.hpp"

namespace cscam::geom {

namespace {

struct Pt2 {
  double y, z;
};

[[noreturn]] void bad(const std::string& msg) { throw InputError(SourceLoc{"groove"}, msg); }

/// The right wall as points from the floor corner (k = 0) to the lip (k = n), on the analytic profile.
std::vector<Pt2> wall_points(const GrooveParams& p, const GrooveProfile& g) {
  const int n = p.wall_segments;
  std::vector<Pt2> w(static_cast<std::size_t>(n) + 1);
  if (g.radius_mm <= 0.0) {
    for (int k = 0; k <= n; ++k) {
      const double t = static_cast<double>(k) / n;
      w[static_cast<std::size_t>(k)] = {g.floor_corner_y_mm + t * (g.lip_y_mm - g.floor_corner_y_mm), t * g.lip_z_mm};
    }
  } else {
    const double a0 = std::atan2(0.0 - g.centre_z_mm, g.floor_corner_y_mm - g.centre_y_mm);
    const double a1 = std::atan2(g.lip_z_mm - g.centre_z_mm, g.lip_y_mm - g.centre_y_mm);
    for (int k = 0; k <= n; ++k) {
      const double a = a0 + (a1 - a0) * static_cast<double>(k) / n;
      w[static_cast<std::size_t>(k)] = {g.centre_y_mm + g.radius_mm * std::cos(a),
                                        g.centre_z_mm + g.radius_mm * std::sin(a)};
    }
  }
  // End points exactly as specified (no trigonometric round-off at the lip and the floor corner).
  w.front() = {g.floor_corner_y_mm, 0.0};
  w.back() = {g.lip_y_mm, g.lip_z_mm};
  return w;
}

}  // namespace

GrooveProfile groove_profile(const GrooveParams& p) {
  auto positive = [](double v, const char* what) {
    if (!(v > 0.0) || !std::isfinite(v)) bad(fmt::format("{} must be positive, got {}", what, v));
  };
  positive(p.length_mm, "length");
  positive(p.floor_width_mm, "floor width");
  positive(p.mouth_width_mm, "mouth width");
  positive(p.depth_mm, "depth");
  positive(p.block_width_mm, "block width");
  positive(p.floor_thickness_mm, "floor thickness");
  if (!(p.wall_radius_mm >= 0.0)) bad(fmt::format("wall radius must be >= 0 (0: straight), got {}", p.wall_radius_mm));
  if (p.wall_segments < 1 || p.floor_segments < 1 || p.length_segments < 1)
    bad(fmt::format("segment counts must be >= 1, got wall {}, floor {}, length {}", p.wall_segments, p.floor_segments,
                    p.length_segments));

  GrooveProfile g;
  g.floor_corner_y_mm = 0.5 * p.floor_width_mm;
  g.lip_y_mm = 0.5 * p.mouth_width_mm;
  g.lip_z_mm = p.depth_mm;
  g.max_half_width_mm = std::max(g.floor_corner_y_mm, g.lip_y_mm);
  if (p.wall_radius_mm > 0.0) {
    // Chord from the floor corner A to the lip B; the centre lies on the cavity side (toward -y), so the
    // arc bulges outward into the material.
    const double ay = g.floor_corner_y_mm, az = 0.0, by = g.lip_y_mm, bz = g.lip_z_mm;
    const double cy = by - ay, cz = bz - az;
    const double len = std::hypot(cy, cz);
    const double half = 0.5 * len;
    if (p.wall_radius_mm < half)
      bad(fmt::format("wall radius {} mm is smaller than half the wall chord ({:.6g} mm)", p.wall_radius_mm, half));
    const double h = std::sqrt(p.wall_radius_mm * p.wall_radius_mm - half * half);
    // Unit normal to the chord pointing to -y (cz > 0, so (-cz, cy) / len has a negative y component).
    const double ny = -cz / len, nz = cy / len;
    g.radius_mm = p.wall_radius_mm;
    g.centre_y_mm = 0.5 * (ay + by) + h * ny;
    g.centre_z_mm = 0.5 * (az + bz) + h * nz;
    // z must rise monotonically along the arc (no bending over itself): both end angles inside (-90, 90) deg.
    const double a0 = std::atan2(az - g.centre_z_mm, ay - g.centre_y_mm);
    const double a1 = std::atan2(bz - g.centre_z_mm, by - g.centre_y_mm);
    const double lim = 0.5 * std::numbers::pi;
    if (!(a0 > -lim && a1 < lim && a0 < a1))
      bad(fmt::format("wall radius {} mm is too small: the wall arc would bend over itself", p.wall_radius_mm));
    if (a0 < 0.0 && a1 > 0.0) g.max_half_width_mm = g.centre_y_mm + g.radius_mm;
  }
  if (g.max_half_width_mm >= 0.5 * p.block_width_mm)
    bad(fmt::format("the groove (half width up to {:.6g} mm) does not fit in the block (half width {:.6g} mm)",
                    g.max_half_width_mm, 0.5 * p.block_width_mm));
  return g;
}

double groove_half_width_at(const GrooveParams& p, double z_mm) {
  const GrooveProfile g = groove_profile(p);
  if (!(z_mm >= 0.0 && z_mm <= p.depth_mm))
    bad(fmt::format("height {} mm is outside the groove [0, {}]", z_mm, p.depth_mm));
  if (g.radius_mm <= 0.0) return g.floor_corner_y_mm + (g.lip_y_mm - g.floor_corner_y_mm) * z_mm / p.depth_mm;
  const double dz = z_mm - g.centre_z_mm;
  return g.centre_y_mm + std::sqrt(std::max(0.0, g.radius_mm * g.radius_mm - dz * dz));
}

Mesh make_groove(const GrooveParams& p) {
  const GrooveProfile g = groove_profile(p);
  const int n = p.wall_segments, m = p.floor_segments, nx = p.length_segments;
  const double W2 = 0.5 * p.block_width_mm, zb = -p.floor_thickness_mm;
  const std::vector<Pt2> wall = wall_points(p, g);

  // The cross-section boundary, counter-clockwise in the (y, z) plane (material on the left), with the
  // indices of the named points kept for the structured cap triangulation.
  std::vector<Pt2> poly;
  // Top line of the slab below the floor: -W/2, floor points (-wf/2 .. wf/2), +W/2.
  std::vector<double> slab_y;
  slab_y.push_back(-W2);
  for (int j = 0; j <= m; ++j) slab_y.push_back(-g.floor_corner_y_mm + 2.0 * g.floor_corner_y_mm * j / m);
  slab_y.push_back(W2);
  const int S = static_cast<int>(slab_y.size());  // m + 3
  // Bottom, left to right.
  const int i_bottom = 0;
  for (double y : slab_y) poly.push_back({y, zb});
  // Right outer side, upward at the wall heights: O_k = (W/2, z_k).
  const int i_outer_r = static_cast<int>(poly.size());
  for (int k = 0; k <= n; ++k) poly.push_back({W2, k == 0 ? 0.0 : wall[static_cast<std::size_t>(k)].z});
  // Right wall, downward from the lip: W_n .. W_1 (W_0 starts the floor).
  const int i_wall_r = static_cast<int>(poly.size());  // holds W_n
  for (int k = n; k >= 1; --k) poly.push_back(wall[static_cast<std::size_t>(k)]);
  // Floor, right to left: F_m (= W_0 right) .. F_0 (= W_0 left).
  const int i_floor = static_cast<int>(poly.size());  // holds the right floor corner
  for (int j = m; j >= 0; --j) poly.push_back({slab_y[static_cast<std::size_t>(j + 1)], 0.0});
  // Left wall, upward: W_1 .. W_n mirrored.
  const int i_wall_l = static_cast<int>(poly.size());  // holds W_1 left
  for (int k = 1; k <= n; ++k)
    poly.push_back({-wall[static_cast<std::size_t>(k)].y, wall[static_cast<std::size_t>(k)].z});
  // Left outer side, downward: O_n .. O_0 mirrored.
  const int i_outer_l = static_cast<int>(poly.size());  // holds O_n left
  for (int k = n; k >= 0; --k) poly.push_back({-W2, k == 0 ? 0.0 : wall[static_cast<std::size_t>(k)].z});
  const int K = static_cast<int>(poly.size());
  CSCAM_CHECK(K == 2 * m + 4 * n + 6, "groove cross-section vertex count");

  // Index helpers into poly for the named points.
  auto bottom = [&](int j) { return i_bottom + j; };    // j = 0..S-1
  auto outer_r = [&](int k) { return i_outer_r + k; };  // k = 0..n
  auto wall_r = [&](int k) { return k == 0 ? i_floor : i_wall_r + (n - k); };
  auto wall_l = [&](int k) { return k == 0 ? i_floor + m : i_wall_l + (k - 1); };
  auto outer_l = [&](int k) { return i_outer_l + (n - k); };
  auto slab_top = [&](int j) {  // j = 0..S-1 along slab_y
    if (j == 0) return outer_l(0);
    if (j == S - 1) return outer_r(0);
    return i_floor + (m - (j - 1));
  };

  // Cap triangulation (in cross-section indices), counter-clockwise in (y, z).
  std::vector<Eigen::Vector3i> cap;
  auto quad = [&](int a, int b, int c, int e) {  // a, b, c, e counter-clockwise
    cap.emplace_back(a, b, c);
    cap.emplace_back(a, c, e);
  };
  for (int j = 0; j + 1 < S; ++j) quad(bottom(j), bottom(j + 1), slab_top(j + 1), slab_top(j));
  for (int k = 0; k < n; ++k) {
    quad(wall_r(k), outer_r(k), outer_r(k + 1), wall_r(k + 1));
    quad(outer_l(k), wall_l(k), wall_l(k + 1), outer_l(k + 1));
  }
  for (const auto& t : cap) {  // every cap triangle must be counter-clockwise and non-degenerate
    const Pt2 &a = poly[static_cast<std::size_t>(t[0])], &b = poly[static_cast<std::size_t>(t[1])],
              &c = poly[static_cast<std::size_t>(t[2])];
    const double area2 = (b.y - a.y) * (c.z - a.z) - (b.z - a.z) * (c.y - a.y);
    CSCAM_CHECK(area2 > 0.0, "groove cap triangle is not counter-clockwise");
  }

  Mesh mesh;
  mesh.source = "groove";
  mesh.vertices_mm.reserve(static_cast<std::size_t>(K) * static_cast<std::size_t>(nx + 1));
  for (int i = 0; i <= nx; ++i) {
    const double x = i == nx ? 0.5 * p.length_mm : -0.5 * p.length_mm + p.length_mm * i / nx;
    for (const Pt2& q : poly) mesh.vertices_mm.emplace_back(x, q.y, q.z);
  }
  auto vid = [&](int i, int k) { return i * K + k; };
  mesh.triangles.reserve(static_cast<std::size_t>(2 * K * nx) + 2 * cap.size());
  // Side faces: edge k -> k+1 of the counter-clockwise boundary, between x levels i and i+1.
  for (int i = 0; i < nx; ++i)
    for (int k = 0; k < K; ++k) {
      const int k1 = (k + 1) % K;
      mesh.triangles.emplace_back(vid(i, k), vid(i, k1), vid(i + 1, k1));
      mesh.triangles.emplace_back(vid(i, k), vid(i + 1, k1), vid(i + 1, k));
    }
  // Caps: +x end counter-clockwise in (y, z) (normal +x); -x end reversed.
  for (const auto& t : cap) {
    mesh.triangles.emplace_back(vid(nx, t[0]), vid(nx, t[1]), vid(nx, t[2]));
    mesh.triangles.emplace_back(vid(0, t[0]), vid(0, t[2]), vid(0, t[1]));
  }
  return mesh;
}

Mesh make_benchmark_part(std::size_t target_triangles, GrooveParams p) {
  // Keep the cross-section reasonably fine and put the rest of the budget along X.
  p.wall_segments = 64;
  p.floor_segments = 32;
  const auto K = static_cast<double>(2 * p.floor_segments + 4 * p.wall_segments + 6);
  const double caps = 8.0 * p.wall_segments + 4.0 * p.floor_segments + 8.0;
  p.length_segments =
      std::max(1, static_cast<int>(std::lround((static_cast<double>(target_triangles) - caps) / (2.0 * K))));
  Mesh mesh = make_groove(p);
  mesh.source = fmt::format("groove benchmark part ({} triangles)", mesh.triangles.size());
  return mesh;
}

}  // namespace cscam::geom
