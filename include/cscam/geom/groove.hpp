#pragma once
/// @file
/// The seed-002 test part: a block with a straight groove whose two side walls are curved overhangs.
///
/// Part frame (mm):
/// - the groove runs along X, through the whole block: x in [-length/2, +length/2];
/// - it is centred on y = 0;
/// - the groove floor is flat, at z = 0, for y in [-floor_width/2, +floor_width/2];
/// - the block top surface is at z = depth; the groove mouth there spans y in [-mouth_width/2, +mouth_width/2];
/// - the block spans y in [-block_width/2, +block_width/2] and z in [-floor_thickness, depth].
///
/// Cross-section (plane x = const), right half (the left is its mirror image in y):
/// @verbatim
///   z=depth  ______________lip (mouth_width/2, depth)            ____________  (block_width/2, depth)
///                            \      <- right wall: circular arc of radius wall_radius,
///                             )        bulging outward into the material (the cavity stays convex)
///   z=0     floor ___________/  floor corner (floor_width/2, 0)
///   z=-floor_thickness ____________________________________________________ block bottom
/// @endverbatim
/// With mouth_width < floor_width the walls overhang the floor: a ball mill on the floor centre line
/// (tip at (x, 0, 0), axis (0, 0, 1)) is free, while tilting it sideways far enough makes its cylinder hit
/// the lip edge, the line (x, +-mouth_width/2, depth). A CL path along the floor centre is (x, 0, 0) for x in
/// (-length/2, length/2) with surface normal (0, 0, 1).
///
/// The cross-section polygon is inscribed in the analytic profile (arc chords), so the mesh cavity is
/// the convex polygon through the profile points; the lips and floor corners are exact vertices.
#include <cstddef>

#include "cscam/geom/mesh.hpp"

namespace cscam::geom {

/// Dimensions of the groove block (mm) and its tessellation.
struct GrooveParams {
  double length_mm = 100.0;          ///< along X (groove and block)
  double floor_width_mm = 30.0;      ///< groove width at the floor (z = 0)
  double mouth_width_mm = 20.0;      ///< groove width at the top surface (z = depth); < floor width: overhang
  double depth_mm = 20.0;            ///< floor to top surface
  double wall_radius_mm = 25.0;      ///< radius of the wall arcs; 0 = straight (planar) walls
  double block_width_mm = 60.0;      ///< along Y
  double floor_thickness_mm = 10.0;  ///< material below the floor
  int wall_segments = 24;            ///< chords per wall arc
  int floor_segments = 8;            ///< segments across the floor
  int length_segments = 8;           ///< segments along X
};

/// The analytic right wall (the left is mirrored, y -> -y): a circular arc from the floor corner to the lip.
struct GrooveProfile {
  double centre_y_mm = 0.0, centre_z_mm = 0.0;  ///< arc centre (on the cavity side); meaningless for straight walls
  double radius_mm = 0.0;                       ///< 0 for straight walls
  double floor_corner_y_mm = 0.0;               ///< = floor_width/2 (z = 0)
  double lip_y_mm = 0.0, lip_z_mm = 0.0;        ///< = (mouth_width/2, depth)
  double max_half_width_mm = 0.0;               ///< widest point of the cavity (the bulge), >= floor/mouth half widths
};

/// Validates the parameters and computes the analytic right-wall profile.
/// @throws InputError when the dimensions are inconsistent (non-positive sizes, an arc radius smaller than
///         half the wall chord, a wall reaching the block side or bending over itself, too few segments).
[[nodiscard]] GrooveProfile groove_profile(const GrooveParams& params);

/// Half width (mm) of the analytic cavity at height z in [0, depth] (the right wall's y at z).
/// @throws InputError for z outside [0, depth] or invalid params.
[[nodiscard]] double groove_half_width_at(const GrooveParams& params, double z_mm);

/// Generates the groove block as a closed, outward-oriented triangle mesh (source "groove").
/// Triangle count: 2 K length_segments + 8 wall_segments + 4 floor_segments + 8, where
/// K = 2 floor_segments + 4 wall_segments + 6 is the number of cross-section vertices.
/// @throws InputError as groove_profile().
[[nodiscard]] Mesh make_groove(const GrooveParams& params = {});

/// The groove with its tessellation raised so that the mesh has about `target_triangles` triangles
/// (within 1 %, for targets >= 10,000): the benchmark part (default ~200,000 triangles).
[[nodiscard]] Mesh make_benchmark_part(std::size_t target_triangles = 200000, GrooveParams params = {});

}  // namespace cscam::geom
