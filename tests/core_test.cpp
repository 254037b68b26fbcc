// Core: error locations, angle helpers, and atomic file writing.
#include <gtest/gtest.h>
#include <unistd.h>

#include <charconv>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <random>
#include <vector>

#include "cscam/core/atomic_file.hpp"
#include "cscam/core/error.hpp"
#include "cscam/core/numparse.hpp"
#include "cscam/core/rotations.hpp"
#include "cscam/core/tolerances.hpp"
#include "cscam/core/units.hpp"

using namespace cscam;
namespace fs = std::filesystem;

TEST(Core, ErrorsCarryFileLineColumn) {
  const InputError e(SourceLoc{"a.cls", 12, 7}, "bad number");
  EXPECT_STREQ(e.what(), "a.cls:12:7: bad number");
  EXPECT_EQ(e.message(), "bad number");
  EXPECT_STREQ(InputError(SourceLoc{"a.cls", 3, 0}, "x").what(), "a.cls:3: x");
  EXPECT_STREQ(InputError("plain").what(), "plain");
}

TEST(Core, WrapPi) {
  EXPECT_NEAR(wrap_pi(3 * kPi), kPi, 1e-12);
  EXPECT_NEAR(wrap_pi(-kPi), kPi, 1e-12);
  EXPECT_NEAR(wrap_pi(0.5), 0.5, 1e-15);
  EXPECT_NEAR(rad2deg(deg2rad(123.25)), 123.25, 1e-12);
}

TEST(Core, WrapPiIsRemaindersToTheBit) {
  // The fast path for angles already in (-pi, pi] returns what std::remainder does there (the angle itself).
  auto reference = [](double a) {
    a = std::remainder(a, 2.0 * kPi);
    return a <= -kPi ? a + 2.0 * kPi : a;
  };
  std::mt19937_64 rng(3);
  std::uniform_real_distribution<double> U(-20.0, 20.0);
  std::vector<double> angles = {0.0,
                                -0.0,
                                kPi,
                                -kPi,
                                std::nextafter(kPi, 0.0),
                                std::nextafter(kPi, 4.0),
                                std::nextafter(-kPi, 0.0),
                                std::nextafter(-kPi, -4.0),
                                2 * kPi,
                                -2 * kPi};
  for (int i = 0; i < 100000; ++i) angles.push_back(U(rng));
  for (const double a : angles) {
    const double w = wrap_pi(a), r = reference(a);
    EXPECT_EQ(std::memcmp(&w, &r, sizeof w), 0) << a;
  }
}

TEST(Core, PendingFileIsInPlaceOnlyAfterCommit) {
  const fs::path dir = fs::temp_directory_path() / ("cscam_core_pending_" + std::to_string(::getpid()));
  fs::create_directories(dir);
  const std::string target = (dir / "out.txt").string();
  {
    PendingFile f(target);
    f.write([](std::ostream& os) { os << "text"; });
    EXPECT_FALSE(fs::exists(target));
  }  // not committed: the temporary goes
  EXPECT_TRUE(fs::is_empty(dir));
  {
    PendingFile f(target);
    f.write([](std::ostream& os) { os << "text"; });
    f.commit();
  }
  std::ifstream in(target);
  EXPECT_EQ(std::string((std::istreambuf_iterator<char>(in)), {}), "text");
  std::size_t n = 0;
  for ([[maybe_unused]] const auto& e : fs::directory_iterator(dir)) ++n;
  EXPECT_EQ(n, 1u);
  fs::remove_all(dir);
}

TEST(Core, AtomicWriteLeavesNothingOnError) {
  const fs::path dir = fs::temp_directory_path() / ("cscam_core_test_" + std::to_string(::getpid()));
  fs::create_directories(dir);
  const std::string target = (dir / "out.txt").string();
  std::ofstream(target) << "old";
  EXPECT_THROW(write_file_atomically(target,
                                     [](std::ostream& os) {
                                       os << "partial";
                                       throw InputError("boom");
                                     }),
               InputError);
  std::ifstream in(target);
  std::string s((std::istreambuf_iterator<char>(in)), {});
  EXPECT_EQ(s, "old");
  size_t n = 0;
  for ([[maybe_unused]] const auto& e : fs::directory_iterator(dir)) ++n;
  EXPECT_EQ(n, 1u);
  write_file_atomically(target, [](std::ostream& os) { os << "new"; });
  std::ifstream in2(target);
  std::string s2((std::istreambuf_iterator<char>(in2)), {});
  EXPECT_EQ(s2, "new");
  EXPECT_THROW(write_file_atomically("/nonexistent-dir/x.txt", [](std::ostream&) {}), InputError);
  fs::remove_all(dir);
}

TEST(Core, WholeDegreesDoNotTruncate) {
  EXPECT_NEAR(deg2rad(5), 5.0 * kPi / 180.0, 1e-15);
  EXPECT_NEAR(rad2deg(1), 180.0 / kPi, 1e-12);
}

// Work-plane rotations against closed-form matrices written out by hand (not through Eigen's AngleAxis).
namespace {
Eigen::Matrix3d closed_rx(double a) {
  Eigen::Matrix3d m;
  m << 1, 0, 0, 0, std::cos(a), -std::sin(a), 0, std::sin(a), std::cos(a);
  return m;
}
Eigen::Matrix3d closed_ry(double a) {
  Eigen::Matrix3d m;
  m << std::cos(a), 0, std::sin(a), 0, 1, 0, -std::sin(a), 0, std::cos(a);
  return m;
}
Eigen::Matrix3d closed_rz(double a) {
  Eigen::Matrix3d m;
  m << std::cos(a), -std::sin(a), 0, std::sin(a), std::cos(a), 0, 0, 0, 1;
  return m;
}
}  // namespace

TEST(Rotations, ConventionsMatchClosedFormProductsAndDecomposeBack) {
  std::mt19937_64 g(20261125u);
  std::uniform_real_distribution<double> ang(-kPi, kPi), half(-0.5 * kPi + 1e-3, 0.5 * kPi - 1e-3),
      pos(1e-3, kPi - 1e-3);
  for (int n = 0; n < 200; ++n) {
    const double a = ang(g), b = pos(g), c = ang(g), bh = half(g);
    // ZXZ Euler (G68.2 I J K): moving axes Z, X', Z''
    const Eigen::Matrix3d zxz = closed_rz(a) * closed_rx(b) * closed_rz(c);
    EXPECT_LT((rot::from_euler_zxz(a, b, c) - zxz).norm(), tol::kRoundTripRad);
    const auto e = rot::euler_zxz(zxz);
    EXPECT_LT((rot::from_euler_zxz(e[0], e[1], e[2]) - zxz).norm(), 1e-9);
    EXPECT_NEAR(e[1], b, 1e-9);
    // spatial angles (PLANE SPATIAL): fixed X, then Y, then Z
    const Eigen::Matrix3d sp = closed_rz(c) * closed_ry(bh) * closed_rx(a);
    EXPECT_LT((rot::from_spatial(a, bh, c) - sp).norm(), tol::kRoundTripRad);
    const auto s = rot::spatial(sp);
    EXPECT_NEAR(s[0], a, 1e-9);
    EXPECT_NEAR(s[1], bh, 1e-9);
    EXPECT_NEAR(s[2], c, 1e-9);
    // axis by axis X Y Z (CYCLE800 mode 57)
    const Eigen::Matrix3d xyz = closed_rx(a) * closed_ry(bh) * closed_rz(c);
    EXPECT_LT((rot::from_axis_by_axis_xyz(a, bh, c) - xyz).norm(), tol::kRoundTripRad);
    const auto x = rot::axis_by_axis_xyz(xyz);
    EXPECT_NEAR(x[0], a, 1e-9);
    EXPECT_NEAR(x[1], bh, 1e-9);
    EXPECT_NEAR(x[2], c, 1e-9);
  }
  // gimbal lock: the turn about Z (or the shared axis) goes into the first angle, the result is the same matrix
  for (const Eigen::Matrix3d& R :
       {Eigen::Matrix3d(closed_rz(0.7)), Eigen::Matrix3d(closed_rz(0.7) * closed_rx(kPi) * closed_rz(0.2))}) {
    const auto e = rot::euler_zxz(R);
    EXPECT_LT((rot::from_euler_zxz(e[0], e[1], e[2]) - R).norm(), 1e-9);
  }
  for (double sb : {1.0, -1.0}) {
    const Eigen::Matrix3d R = closed_rz(0.3) * closed_ry(sb * 0.5 * kPi) * closed_rx(0.4);
    const auto s = rot::spatial(R);
    EXPECT_LT((rot::from_spatial(s[0], s[1], s[2]) - R).norm(), 1e-9);
    const auto x = rot::axis_by_axis_xyz(R.transpose());
    EXPECT_LT((rot::from_axis_by_axis_xyz(x[0], x[1], x[2]) - R.transpose()).norm(), 1e-9);
  }
}

TEST(Rotations, PlaneOfAToolAxisHasItAsZAndMapsPointsBothWays) {
  // 30 deg about X: the tool axis (0, -sin 30, cos 30); the plane is Rx(30 deg)
  const Eigen::Vector3d u(0, -0.5, std::sqrt(3.0) / 2);
  const Eigen::Matrix3d R = rot::plane_for_tool_axis(u);
  EXPECT_LT((R - closed_rx(deg2rad(30.0))).norm(), 1e-12);
  const auto e = rot::euler_zxz(R);
  EXPECT_NEAR(e[0], 0.0, 1e-12);
  EXPECT_NEAR(rad2deg(e[1]), 30.0, 1e-12);
  // a tool along +X: beta 90 deg, alpha 90 deg (the plane's X is the part's Y)
  const Eigen::Matrix3d Rx = rot::plane_for_tool_axis(Eigen::Vector3d::UnitX());
  EXPECT_LT((Rx.col(2) - Eigen::Vector3d::UnitX()).norm(), 1e-12);
  EXPECT_LT((Rx.col(0) - Eigen::Vector3d::UnitY()).norm(), 1e-12);
  EXPECT_LT((rot::plane_for_tool_axis(Eigen::Vector3d::UnitZ()) - Eigen::Matrix3d::Identity()).norm(), 1e-15);
  // a point 10 mm up the tool axis from the origin is (0, 0, 10) in the plane
  const Eigen::Vector3d o(5, -2, 1);
  const Eigen::Vector3d p = o + 10 * u;
  EXPECT_LT((rot::to_plane(R, o, p) - Eigen::Vector3d(0, 0, 10)).norm(), 1e-12);
  EXPECT_LT((rot::from_plane(R, o, rot::to_plane(R, o, p)) - p).norm(), 1e-12);
}

// decimal_from_chars must be std::from_chars exactly (value bits, end pointer, error): the readers' numbers, and
// so every program the gate reads back, depend on it.
TEST(Core, DecimalFromCharsIsFromChars) {
  std::mt19937_64 g(7);
  auto same = [](const std::string& s) {
    double a = 1.5, b = 1.5;
    const auto ra = decimal_from_chars(s.data(), s.data() + s.size(), a);
    const auto rb = std::from_chars(s.data(), s.data() + s.size(), b);
    EXPECT_EQ(ra.ptr, rb.ptr) << s;
    EXPECT_TRUE(ra.ec == rb.ec) << s;
    EXPECT_EQ(std::memcmp(&a, &b, sizeof a), 0) << s << ": " << a << " vs " << b;
  };
  for (const char* s : {"0",
                        "-0",
                        "-0.0",
                        "12.3456",
                        "-12.3456",
                        "0.1",
                        "1.",
                        ".5",
                        "-.5",
                        "1e5",
                        "1.5E-3",
                        "-",
                        "",
                        "+1",
                        "inf",
                        "nan",
                        "1..2",
                        "1.2.3",
                        "9007199254740992",
                        "9007199254740993",
                        "9007199254740992.5",
                        "123456789012345678901234",
                        "0.0000000000000000000001",
                        "0.00000000000000000000001",
                        "0.12345678901234567890",
                        "12,5",
                        "7 "})
    same(s);
  const char alphabet[] = "0123456789.-+eE ";
  for (int i = 0; i < 200000; ++i) {
    std::string s;
    const int len = 1 + static_cast<int>(g() % 24);
    for (int k = 0; k < len; ++k) s += alphabet[g() % (g() % 4 == 0 ? 16 : 10)];
    same(s);
    char buf[64];
    const double x = static_cast<double>(static_cast<long long>(g() % 2000000000000ULL) - 1000000000000LL) /
                     std::pow(10.0, static_cast<double>(g() % 12));
    std::snprintf(buf, sizeof buf, "%.*f", static_cast<int>(g() % 18), x);
    same(buf);
  }
}
