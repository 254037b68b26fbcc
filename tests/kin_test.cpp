// Serial kinematics: IK -> FK round trips, the LinuxCNC xyzac-trt closed form as an independent oracle,
// singularity handling and winding enumeration.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <tuple>

#include "cscam/core/units.hpp"
#include "cscam/kin/serial.hpp"
#include "cscam/kin/track.hpp"
#include "test_support.hpp"

using namespace cscam;
using namespace cscam::kin;
using Vec3 = Eigen::Vector3d;

namespace {

AxisInfo lin(const char* n, double lo, double hi) { return {n, AxisType::Linear, lo, hi, false, 0}; }
AxisInfo rot(const char* n, double lo_deg, double hi_deg, bool cyc = false) {
  return {n, AxisType::Rotary, deg2rad(lo_deg), deg2rad(hi_deg), cyc, 0};
}

JointGeometry<double> J(AxisType t, Side s, Vec3 d, Vec3 p = Vec3::Zero()) {
  JointGeometry<double> j;
  j.type = t;
  j.side = s;
  j.direction = d.normalized();
  j.pivot_mm = p;
  return j;
}

/// The joints of the A/C trunnion of LinuxCNC's xyzac-trt sim: A about +X through (y, z), C about +Z.
SerialGeometry<double> trunnion_ac_geometry(double y_off = 20, double z_off = 10) {
  SerialGeometry<double> g;
  g.joints = {J(AxisType::Linear, Side::Head, Vec3::UnitX()), J(AxisType::Linear, Side::Head, Vec3::UnitY()),
              J(AxisType::Linear, Side::Head, Vec3::UnitZ()),
              J(AxisType::Rotary, Side::Table, Vec3::UnitX(), Vec3(0, y_off, z_off)),
              J(AxisType::Rotary, Side::Table, Vec3::UnitZ())};
  g.table_chain = {3, 4};
  g.head_chain = {0, 1, 2};
  return g;
}

/// That trunnion with the sim's limits.
SerialKinematics trunnion_ac(double y_off = 20, double z_off = 10) {
  const SerialGeometry<double> g = trunnion_ac_geometry(y_off, z_off);
  return SerialKinematics(g, {lin("x", -1e4, 1e4), lin("y", -1e4, 1e4), lin("z", -1e4, 1e4), rot("a", -100, 50),
                              rot("c", -36000, 36000, true)});
}

/// LinuxCNC xyzac-trt-kins forward map written from its published equations (rot points 0, tool offset 0):
/// the part-frame position of the tool tip for joints (x, y, z, a, c), and the tool axis.
Vec3 linuxcnc_xyzac_forward(double jx, double jy, double jz, double a, double c, double dy, double dz) {
  const double ca = std::cos(a), sa = std::sin(a), cc = std::cos(c), sc = std::sin(c);
  const double ty = jy - dy, tz = jz - dz;
  return {cc * jx + sc * ca * ty + sc * sa * tz + sc * dy, -sc * jx + cc * ca * ty + cc * sa * tz + cc * dy,
          -sa * ty + ca * tz + dz};
}

Vec3 random_unit_in_cone(std::mt19937_64& rng, double max_tilt_rad) {
  std::uniform_real_distribution<double> U(0, 1);
  const double tilt = max_tilt_rad * std::sqrt(U(rng));
  const double az = 2 * kPi * U(rng);
  return {std::sin(tilt) * std::cos(az), std::sin(tilt) * std::sin(az), std::cos(tilt)};
}

}  // namespace

TEST(SerialKinematics, MatchesLinuxcncXyzacTrtForward) {
  const auto k = trunnion_ac();
  auto rng = test::rng(1);
  std::uniform_real_distribution<double> U(-200, 200), A(deg2rad(-100.0), deg2rad(50.0)), C(-10, 10);
  for (int i = 0; i < 1000; ++i) {
    Axes q;
    q << U(rng), U(rng), U(rng), A(rng), C(rng);
    const Posed p = k.forward(q);
    const Vec3 oracle = linuxcnc_xyzac_forward(q[0], q[1], q[2], q[3], q[4], 20, 10);
    EXPECT_LT((p.tip_mm - oracle).norm(), tol::kRoundTripMm) << "sample " << i;
    // The tool axis is the image of +Z under the same rotation (no translation).
    const Vec3 axis_oracle = linuxcnc_xyzac_forward(0, 0, 1, q[3], q[4], 0, 0);
    EXPECT_LT((p.axis - axis_oracle).norm(), tol::kRoundTripRad);
  }
}

TEST(SerialKinematics, IkThenFkRoundTripTrunnion) {
  const auto k = trunnion_ac();
  auto rng = test::rng(2);
  std::uniform_real_distribution<double> U(-150, 150);
  std::vector<Solution> sols;
  int checked = 0;
  for (int i = 0; i < 2000; ++i) {
    const Posed target{Vec3(U(rng), U(rng), U(rng)), random_unit_in_cone(rng, deg2rad(89.0))};
    k.inverse_branches(target, nullptr, sols);
    ASSERT_FALSE(sols.empty());
    for (const auto& s : sols) {
      const Posed p = k.forward(s.axes);
      EXPECT_LT((p.tip_mm - target.tip_mm).norm(), tol::kRoundTripMm);
      EXPECT_LT((p.axis - target.axis).norm(), tol::kRoundTripRad);
      ++checked;
    }
  }
  EXPECT_GT(checked, 3000);  // two branches almost everywhere
}

TEST(SerialKinematics, InverseMatchesLinuxcncLinearAxes) {
  // For given rotaries, LinuxCNC's inverse is the unique joint position whose forward image is the pose.
  const auto k = trunnion_ac();
  auto rng = test::rng(3);
  std::uniform_real_distribution<double> U(-150, 150);
  std::vector<Solution> sols;
  for (int i = 0; i < 200; ++i) {
    const Posed target{Vec3(U(rng), U(rng), U(rng)), random_unit_in_cone(rng, deg2rad(80.0))};
    k.inverse_branches(target, nullptr, sols);
    for (const auto& s : sols) {
      const Vec3 world = linuxcnc_xyzac_forward(s.axes[0], s.axes[1], s.axes[2], s.axes[3], s.axes[4], 20, 10);
      EXPECT_LT((world - target.tip_mm).norm(), tol::kRoundTripMm);
    }
  }
}

TEST(SerialKinematics, AllWindingsInsideLimits) {
  const auto k = trunnion_ac();
  std::vector<Solution> all;
  const Posed target{Vec3(10, 20, 5), Vec3(0.3, 0.2, 0.9).normalized()};
  k.inverse_all(target, nullptr, all);
  // C spans +-36000 deg: 200 windings per branch; A has one winding in [-100, 50].
  int feasible = 0;
  for (const auto& s : all) feasible += s.feasible();
  EXPECT_GE(feasible, 200);
  EXPECT_LE(feasible, 2 * 201);
  for (const auto& s : all)
    if (s.feasible()) {
      EXPECT_GE(s.axes[4], deg2rad(-36000.0) - 1e-9);
      EXPECT_LE(s.axes[4], deg2rad(36000.0) + 1e-9);
      EXPECT_LT((k.forward(s.axes).tip_mm - target.tip_mm).norm(), tol::kRoundTripMm);
    }
}

TEST(SerialKinematics, SingularityKeepsThePreviousPrimaryAngle) {
  const auto k = trunnion_ac();
  std::vector<Solution> sols;
  Axes hint = Axes::Zero();
  hint[4] = deg2rad(37.0);
  const Posed vertical{Vec3(5, 6, 7), Vec3::UnitZ()};
  k.inverse_branches(vertical, &hint, sols);
  ASSERT_FALSE(sols.empty());
  EXPECT_TRUE(sols[0].singular);
  EXPECT_NEAR(sols[0].axes[4], deg2rad(37.0), 1e-12);
  EXPECT_NEAR(sols[0].axes[3], 0.0, 1e-12);
  EXPECT_LT((k.forward(sols[0].axes).tip_mm - vertical.tip_mm).norm(), tol::kRoundTripMm);
}

TEST(SerialKinematics, LimitsAreReported) {
  const auto k = trunnion_ac();
  Axes q = Axes::Zero();
  q[3] = deg2rad(60.0);
  const std::string v = k.check_limits(q);
  EXPECT_NE(v.find("a = 60.0000 deg"), std::string::npos) << v;
  EXPECT_NE(v.find("[-100.0000, 50.0000]"), std::string::npos) << v;
}

TEST(SerialKinematics, NonOrthogonalHeadRoundTrip) {
  // 45-degree nutating B head on X/Y/Z, C table: reachable tilts 0..90 deg.
  SerialGeometry<double> g;
  g.joints = {J(AxisType::Linear, Side::Head, Vec3::UnitX()), J(AxisType::Linear, Side::Head, Vec3::UnitY()),
              J(AxisType::Linear, Side::Head, Vec3::UnitZ()),
              J(AxisType::Rotary, Side::Head, Vec3(0, -1, 1), Vec3(0, 0, 450)),
              J(AxisType::Rotary, Side::Table, -Vec3::UnitZ())};
  g.table_chain = {4};
  g.head_chain = {0, 1, 2, 3};
  g.gauge_home_mm = Vec3(0, 0, 300);
  g.tool_length_mm = 100;
  const SerialKinematics k(
      g, {lin("x", -1e4, 1e4), lin("y", -1e4, 1e4), lin("z", -1e4, 1e4), rot("b", -5, 185), rot("c", -1e5, 1e5, true)});
  auto rng = test::rng(4);
  std::uniform_real_distribution<double> U(-100, 100);
  std::vector<Solution> sols;
  int n = 0;
  for (int i = 0; i < 1000; ++i) {
    const Posed target{Vec3(U(rng), U(rng), U(rng)), random_unit_in_cone(rng, deg2rad(89.0))};
    k.inverse_branches(target, nullptr, sols);
    ASSERT_FALSE(sols.empty()) << "tilts up to 90 deg are reachable";
    for (const auto& s : sols) {
      const Posed p = k.forward(s.axes);
      EXPECT_LT((p.tip_mm - target.tip_mm).norm(), tol::kRoundTripMm);
      EXPECT_LT((p.axis - target.axis).norm(), tol::kRoundTripRad);
      ++n;
    }
  }
  EXPECT_GT(n, 1000);
  // Beyond the head's cone (tool pointing down-ish) there is no solution.
  k.inverse_branches(Posed{Vec3::Zero(), Vec3(0, 0, -1)}, nullptr, sols);
  EXPECT_TRUE(sols.empty());
}

TEST(Track, ALimitMetBetweenTwoNearbyPosesIsAJump) {
  // The trunnion with C limited to +-360 deg. From C 359.6 the tool axis turns 0.6 deg further in azimuth: on this
  // winding C would pass its limit, and the nearest solution inside the limits is the other branch (A negated, C half
  // a turn away). Halving the pose step must keep seeing that jump; it once stopped where the two halves' axes were
  // about 1e-8 rad apart (acos of their dot product is 0 there) and reported a continuous motion.
  SerialGeometry<double> g = trunnion_ac_geometry();
  const SerialKinematics k(
      g, {lin("x", -1e4, 1e4), lin("y", -1e4, 1e4), lin("z", -1e4, 1e4), rot("a", -100, 100), rot("c", -360, 360)});
  auto pose_at = [&](double a_deg, double c_deg) {
    Axes q = Axes::Zero();
    q[3] = deg2rad(a_deg);
    q[4] = deg2rad(c_deg);
    return std::pair<Axes, Posed>(q, k.forward(q));
  };
  const auto [q0, p0] = pose_at(-45.0, 359.6);
  for (const double c1_deg : {359.9, 360.2}) {
    SCOPED_TRACE(c1_deg);
    const Posed p1{p0.tip_mm, pose_at(-45.0, c1_deg).second.axis};
    Axes out;
    bool jumped = false;
    const bool tracked = track_checked(k, q0, p0, p1, out, jumped);
    if (c1_deg < 360.0) {  // the control: inside the limit the motion is continuous and lands on C1
      ASSERT_TRUE(tracked);
      EXPECT_FALSE(jumped);
      EXPECT_NEAR(rad2deg(out[4]), c1_deg, 1e-6);
    } else {
      EXPECT_TRUE(!tracked || jumped) << "C " << rad2deg(out[4]) << " A " << rad2deg(out[3]);
    }
  }
}

// A pose no branch reaches is reported by the branch that misses its limits by least: A needs 60 deg, or -60 deg with
// C turned half a turn; whichever of the two misses its limit by 10 deg (the other by 30) is named. The first branch's
// miss was reported, whichever it was.
TEST(Track, AnUnreachablePoseNamesTheBranchThatMissesByLeast) {
  const SerialGeometry<double> g = trunnion_ac_geometry();
  for (const auto& [a_min, a_max, named] :
       {std::tuple{-30.0, 50.0, "a = 60.0000 deg"}, std::tuple{-50.0, 30.0, "a = -60.0000 deg"}}) {
    const SerialKinematics k(g, {lin("x", -1e4, 1e4), lin("y", -1e4, 1e4), lin("z", -1e4, 1e4), rot("a", a_min, a_max),
                                 rot("c", -36000, 36000, true)});
    for (const double c_deg : {0.0, 180.0, 90.0}) {
      Axes q = Axes::Zero();
      q[3] = deg2rad(60.0);
      q[4] = deg2rad(c_deg);
      Axes out;
      std::string violation;
      EXPECT_FALSE(nearest_solution(k, k.forward(q), Axes::Zero(), out, &violation));
      EXPECT_NE(violation.find(named), std::string::npos) << violation;
    }
  }
}

// --- Calibrated (slightly non-ideal) serial machines ----------------------------------------------------------------

namespace {

/// The four serial layouts of machines/: trunnion A/C, Haas B/C table-table, head-head C/A, 45-degree nutating B head
/// with a C table. Axis order x y z r1 r2 as in the machine files.
SerialGeometry<double> layout_geometry(int layout) {
  SerialGeometry<double> g;
  const Vec3 X = Vec3::UnitX(), Y = Vec3::UnitY(), Z = Vec3::UnitZ();
  const auto L = [](const Vec3& d) { return J(AxisType::Linear, Side::Head, d); };
  g.head_chain = {0, 1, 2};
  switch (layout) {
    case 0:  // trunnion-ac
      return trunnion_ac_geometry();
    case 1:  // haas-umc750: B about -Y under C about -Z
      g.joints = {L(X), L(Y), L(Z), J(AxisType::Rotary, Side::Table, -Y, Vec3(0, 0, -50.8)),
                  J(AxisType::Rotary, Side::Table, -Z)};
      g.table_chain = {3, 4};
      return g;
    case 2:  // head-head-ac: the gantry carries C, C carries A
      g.joints = {L(X), L(Y), L(Z), J(AxisType::Rotary, Side::Head, X, Vec3(0, 0, 780)),
                  J(AxisType::Rotary, Side::Head, Z, Vec3(0, 0, 780))};
      g.head_chain = {0, 1, 2, 4, 3};
      g.gauge_home_mm = Vec3(0, 0, 600);
      g.tool_length_mm = 120;
      return g;
    default:  // head-table-bc45
      g.joints = {L(X), L(Y), L(Z), J(AxisType::Rotary, Side::Head, Vec3(0, -1, 1), Vec3(0, 0, 450)),
                  J(AxisType::Rotary, Side::Table, -Z)};
      g.head_chain = {0, 1, 2, 3};
      g.table_chain = {4};
      g.gauge_home_mm = Vec3(0, 0, 300);
      g.tool_length_mm = 100;
      return g;
  }
}

Vec3 tilted(const Vec3& d, double angle, std::mt19937_64& rng) {
  std::normal_distribution<double> N;
  Vec3 r;
  do r = d.cross(Vec3(N(rng), N(rng), N(rng)));
  while (r.norm() < 1e-3);
  return (std::cos(angle) * d + std::sin(angle) * r.normalized()).normalized();
}

/// `g` as a calibration writes it (ISO 230-1 location errors): rotary directions tilted 20-500 urad, pivots moved
/// 5-50 um, Y and Z out of square with X by 20-200 urad.
SerialGeometry<double> calibrated(SerialGeometry<double> g, std::mt19937_64& rng) {
  std::uniform_real_distribution<double> rot_tilt(20e-6, 500e-6), pivot(0.005, 0.050), lin_tilt(20e-6, 200e-6);
  std::normal_distribution<double> N;
  for (std::size_t i = 0; i < 5; ++i) {
    auto& j = g.joints[i];
    if (j.type == AxisType::Rotary) {
      j.direction = tilted(j.direction, rot_tilt(rng), rng);
      j.pivot_mm += pivot(rng) * Vec3(N(rng), N(rng), N(rng)).normalized();
    } else if (i > 0) {
      j.direction = tilted(j.direction, lin_tilt(rng), rng);
    }
  }
  return g;
}

SerialKinematics layout_kinematics(const SerialGeometry<double>& g) {
  return SerialKinematics(g, {lin("x", -1e4, 1e4), lin("y", -1e4, 1e4), lin("z", -1e4, 1e4),
                              rot("r1", -36000, 36000, true), rot("r2", -36000, 36000, true)});
}

/// body(k) for `per_layout` randomly calibrated machines of each of the four serial layouts (traced).
template <typename Body>
void for_calibrated_machines(int per_layout, std::mt19937_64& rng, Body body) {
  for (int layout = 0; layout < 4; ++layout)
    for (int n = 0; n < per_layout; ++n) {
      SCOPED_TRACE(::testing::Message() << "layout " << layout << " machine " << n);
      body(layout_kinematics(calibrated(layout_geometry(layout), rng)));
    }
}

double angle_between(const Vec3& a, const Vec3& b) { return std::atan2(a.cross(b).norm(), a.dot(b)); }

/// The oracle for how near the machine's tool axis comes to `u`: the least angle over both rotaries, by a 3-degree
/// grid and then a pattern search, from FK alone (no IK).
double nearest_reachable_angle(const SerialKinematics& k, const Vec3& u) {
  const auto rp = k.rotary_pair();
  auto f = [&](double r1, double r2) {
    Axes q = Axes::Zero();
    q[rp[0]] = r1;
    q[rp[1]] = r2;
    return angle_between(k.forward(q).axis, u);
  };
  double b1 = 0, b2 = 0, best = f(0, 0);
  for (int i = -60; i < 60; ++i)
    for (int j = -60; j < 60; ++j)
      if (const double v = f(deg2rad(3.0 * i), deg2rad(3.0 * j)); v < best)
        std::tie(best, b1, b2) = std::tuple(v, deg2rad(3.0 * i), deg2rad(3.0 * j));
  for (double h = deg2rad(3.0); h > 1e-13; h *= 0.5)
    for (bool moved = true; moved;) {
      moved = false;
      for (const auto& [d1, d2] : {std::pair(h, 0.0), std::pair(-h, 0.0), std::pair(0.0, h), std::pair(0.0, -h),
                                   std::pair(h, h), std::pair(-h, -h), std::pair(h, -h), std::pair(-h, h)})
        if (const double v = f(b1 + d1, b2 + d2); v < best) {
          std::tie(best, b1, b2) = std::tuple(v, b1 + d1, b2 + d2);
          moved = true;
        }
    }
  return best;
}

}  // namespace

// A calibrated machine's tilted rotaries leave a cone of tool axes about the primary unreachable, as wide as the tilts
// (here up to about 1 mrad), with the vertical tool on or beside its edge. A CL path beside the vertical crosses it
// (gen/hemi.cls on a trunnion with C tilted 0.5 mrad: "no inverse-kinematics solution" at its second point, found
// half way from the first). The IK now returns the nearest reachable axis there, exact tip, and says how far off it
// is. Oracles: FK of every solution, and the least angle to the requested axis found by searching FK alone.
TEST(SerialKinematics, CalibratedMachinesReachAxesBesideThePrimaryAsNearlyAsTheyCan) {
  auto rng = test::rng(11);
  std::uniform_real_distribution<double> U(-100, 100), R(0, 1), Az(-kPi, kPi);
  std::vector<Solution> sols;
  int inside_cones = 0;
  for_calibrated_machines(5, rng, [&](const SerialKinematics& k) {
    const Vec3 w1 = k.geometry().joints[static_cast<std::size_t>(k.rotary_pair()[0])].direction;
    for (int i = 0; i < 10; ++i) {
      // Within 1.5 mrad of either pole of the primary.
      const Vec3 pole = (i % 2 ? -1.0 : 1.0) * w1;
      const Vec3 u = tilted(pole, 1.5e-3 * R(rng), rng);
      const Posed target{Vec3(U(rng), U(rng), U(rng)), u};
      const double oracle = nearest_reachable_angle(k, u);
      k.inverse_branches(target, nullptr, sols);
      if (oracle > tol::kReachSlackRad) {  // a pole outside the band (the nutating head's downward axis)
        EXPECT_TRUE(sols.empty());
        continue;
      }
      inside_cones += oracle > 1e-7;
      ASSERT_FALSE(sols.empty()) << "axis " << u.transpose() << " is " << oracle << " rad from the reachable ones";
      int nearest = 0;
      for (const auto& s : sols) {
        const Posed p = k.forward(s.axes);
        EXPECT_LT((p.tip_mm - target.tip_mm).norm(), tol::kRoundTripMm);
        EXPECT_NEAR(angle_between(p.axis, u), s.axis_error_rad, 1e-8);
        if (s.singular) continue;  // the free primary of the pole (CalibratedMachinesKeepThePrimaryFreeAtTheVertical)
        ++nearest;
        EXPECT_NEAR(s.axis_error_rad, oracle, 1e-8);
      }
      EXPECT_GE(nearest, 1);
    }
  });
  EXPECT_GT(inside_cones, 20);  // the requested axes inside an unreachable cone, not only beside it
}

// Every branch, near the singular direction too: FK of axis values whose secondary is within 3 mrad of 0 or of half a
// turn (the tool axis within a few mrad of the primary, where the two branches approach each other) gives a pose whose
// IK lists those axis values (one of its branches, modulo whole turns), and every branch it lists is exact (the pole's
// free-primary branch to within its axis_error_rad).
TEST(SerialKinematics, CalibratedMachinesListEveryBranchBesideThePrimary) {
  auto rng = test::rng(12);
  std::uniform_real_distribution<double> U(-100, 100), Near(-3e-3, 3e-3), Az(-kPi, kPi);
  std::vector<Solution> sols;
  for_calibrated_machines(6, rng, [&](const SerialKinematics& k) {
    const auto rp = k.rotary_pair();
    for (int i = 0; i < 40; ++i) {
      Axes q;
      q << U(rng), U(rng), U(rng), 0, 0;
      q[rp[0]] = Az(rng);
      q[rp[1]] = (i % 2 ? kPi : 0.0) + Near(rng);
      const Posed target = k.forward(q);
      k.inverse_branches(target, nullptr, sols);
      ASSERT_FALSE(sols.empty());
      double nearest = std::numeric_limits<double>::infinity();
      for (const auto& s : sols) {
        const Posed p = k.forward(s.axes);
        EXPECT_LT((p.tip_mm - target.tip_mm).norm(), tol::kRoundTripMm);
        // The pole's free-primary branch is the nearest axis at the hint's primary, off by axis_error_rad.
        EXPECT_LT(angle_between(p.axis, target.axis), s.singular ? s.axis_error_rad + 1e-12 : tol::kRoundTripRad);
        double d = 0;
        for (const int r : rp) d += std::abs(std::remainder(s.axes[r] - q[r], 2 * kPi));
        nearest = std::min(nearest, d);
      }
      EXPECT_LT(nearest, 1e-6) << "the branch of " << q.transpose() << " is missing";
    }
  });
}

// On the ideal machine the vertical tool (the home tool direction) lies along the primary, which is then free (kept
// from the hint). A calibrated machine's primary is tilted rho from it; its exact branches there fix the primary to
// values unrelated to the path's, so a walk past the vertical swung C about twice as far as on the ideal machine.
// Within rho of its pole the IK now also lists a singular branch with the hint's primary and the secondary that brings
// the axis nearest (the exact branches stay listed). Oracles: FK, and the least angle over the secondary at that
// primary found by searching FK alone; the deviation is at most 2 rho.
TEST(SerialKinematics, CalibratedMachinesKeepThePrimaryFreeAtTheVertical) {
  auto rng = test::rng(13);
  std::uniform_real_distribution<double> U(-100, 100), Az(-kPi, kPi);
  std::vector<Solution> sols;
  for_calibrated_machines(6, rng, [&](const SerialKinematics& k) {
    const auto rp = k.rotary_pair();
    const Vec3 w1 = k.geometry().joints[static_cast<std::size_t>(rp[0])].direction;
    const Vec3 vertical = k.forward(Axes::Zero()).axis;
    const double rho = std::min(angle_between(vertical, w1), angle_between(vertical, -w1));
    ASSERT_GT(rho, 1e-6);
    for (int i = 0; i < 5; ++i) {
      Axes hint = Axes::Zero();
      hint[rp[0]] = Az(rng);
      const Posed target{Vec3(U(rng), U(rng), U(rng)), vertical};
      k.inverse_branches(target, &hint, sols);
      int exact = 0, singular = 0;
      for (const auto& s : sols) {
        const Posed p = k.forward(s.axes);
        EXPECT_LT((p.tip_mm - target.tip_mm).norm(), tol::kRoundTripMm);
        if (!s.singular) {
          ++exact;
          EXPECT_LT(angle_between(p.axis, vertical), tol::kRoundTripRad);
          continue;
        }
        ++singular;
        EXPECT_NEAR(std::remainder(s.axes[rp[0]] - hint[rp[0]], 2 * kPi), 0.0, 1e-12);
        EXPECT_NEAR(angle_between(p.axis, vertical), s.axis_error_rad, 1e-12);
        EXPECT_LE(s.axis_error_rad, 2 * rho + 1e-12);
        double best = std::numeric_limits<double>::infinity();  // the oracle: every secondary at this primary
        Axes q = s.axes;
        for (int j = 0; j < 3600; ++j) {
          q[rp[1]] = deg2rad(0.1 * j);
          best = std::min(best, angle_between(k.forward(q).axis, vertical));
        }
        EXPECT_LE(s.axis_error_rad, best + 1e-9);
      }
      EXPECT_GE(exact, 1);
      EXPECT_EQ(singular, 1);
    }
  });
}
