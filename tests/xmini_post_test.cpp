// The XMINI behind the generic interface, its machine file, its posts and the backlash simulation.
// Oracles: IK -> FK round trips; LinuxCNC's own interpreter (rs274 -g) on the programs; FK inside every
// block (report::verify); the analytic XMINI Jacobian; hand-computed play on a linear machine.
#include <fmt/format.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <array>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <regex>
#include <sstream>
#include <thread>
#include <tuple>

#include "cscam/cl/program.hpp"
#include "cscam/core/error.hpp"
#include "cscam/core/units.hpp"
#include "cscam/gate/gate.hpp"
#include "cscam/kin/xmini_kinematics.hpp"
#include "cscam/machine/machine.hpp"
#include "cscam/nc/reader.hpp"
#include "cscam/post/post.hpp"
#include "cscam/report/backlash.hpp"
#include "cscam/report/stats.hpp"
#include "cscam/report/verify.hpp"
#include "rs274_support.hpp"
#include "test_support.hpp"

using namespace cscam;
using cscam::test::expect_rs274_agrees;
using cscam::test::rs274_moves;
namespace fs = std::filesystem;
using Vec3 = Eigen::Vector3d;

namespace {

// The working volume of docs/xmini.md: a cylinder of diameter 300, z -100..100, tilt up to 30 deg.
constexpr double kVolumeRadiusMm = 150.0;
constexpr double kVolumeZMm = 100.0;
constexpr double kMaxTiltDeg = 30.0;
constexpr int kRandomPoses = 500;
/// 5 printed decimals of legs (mm) and angles (deg): < 1e-5 mm at the tip each; allowance on top of
/// the post's tolerance when reading a program back.
constexpr double kPrintedRoundingMm = 1e-4;
constexpr double kPrintedRoundingDeg = 1e-3;
/// rs274 prints 4 decimals: agreement to half a unit in the last place.
constexpr double kRs274Half = cscam::test::kRs274HalfUnit;
/// Home of the spec, printed with 6 decimals.
constexpr double kHomeMm = 1e-5;

double angle_between(const Vec3& a, const Vec3& b) { return std::atan2(a.cross(b).norm(), a.dot(b)); }

std::string read_text_file(const std::string& path) {
  std::ifstream in(path);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

machine::Machine xmini_machine() { return machine::load(test::source_path("machines/xmini.yaml")); }

/// machines/xmini.yaml with other text for one line (e.g. letters X Y Z for rs274, or tcp).
machine::Machine xmini_variant(const std::string& from, const std::string& to) {
  std::string text = read_text_file(test::source_path("machines/xmini.yaml"));
  const auto at = text.find(from);
  if (at == std::string::npos) throw std::runtime_error("machines/xmini.yaml has no '" + from + "'");
  text.replace(at, from.size(), to);
  return machine::load_text(text, test::source_path("machines/xmini-variant.yaml"));
}

/// rs274 knows X Y Z A B C only: the legs lettered X Y Z.
machine::Machine xmini_xyz() {
  return xmini_variant("letters: {q1: U, q2: V, q3: W, c: C, a: A}", "letters: {q1: X, q2: Y, q3: Z, c: C, a: A}");
}

nc::AxisLetters letters_of(const machine::Machine& m) { return report::axis_letters(m); }

std::string post_text(const cl::Program& prog, const machine::Machine& m, const kin::Kinematics& k,
                      const std::string& dialect = "", post::Summary* summary = nullptr) {
  const auto axes = post::conventional_axes(prog, m, k);
  std::ostringstream os;
  post::Options o;
  o.dialect = dialect;
  o.tool_length_mm = m.default_tool_length_mm;
  post::Summary s;
  post::write_nc(os, prog, m, k, axes, o, s);
  if (summary) *summary = s;
  return os.str();
}

report::VerifyResult verify_text(const std::string& text, const cl::Program& prog, const machine::Machine& m,
                                 const kin::Kinematics& k) {
  const nc::Program ncp = nc::read_text(text, "posted.ngc", letters_of(m));
  report::VerifyOptions vo;
  vo.tip_tolerance_mm = m.post.tolerance_mm + kPrintedRoundingMm;
  vo.axis_tolerance_deg = m.post.axis_tolerance_deg + kPrintedRoundingDeg;
  vo.samples_per_block = 16;
  return report::verify(ncp, prog, k, vo);
}

/// A smooth variable-axis raster inside the working volume; the tool tilts up to `max_tilt_deg`, away
/// from the vertical (so the wrist stays clear of its singularity).
std::string raster_cl(double max_tilt_deg, int rows, int cols, double z0) {
  std::ostringstream o;
  o << "PARTNO XRASTER\nUNITS/MM\nMULTAX/ON\nCUTTER/6,3\nLOADTL/1\nSPINDL/6000,CLW\nFEDRAT/MMPM,1500\n";
  const double t = deg2rad(max_tilt_deg);
  for (int r = 0; r < rows; ++r) {
    o << "RAPID\n";
    for (int c = 0; c < cols; ++c) {
      const int cc = r % 2 ? cols - 1 - c : c;
      const double u = -1.0 + 2.0 * cc / (cols - 1), v = -1.0 + 2.0 * r / std::max(1, rows - 1);
      const double x = 60 * u, y = 60 * v, z = z0 + 5 * (u * u - v * v);
      const Vec3 n = Vec3(std::sin(t * (0.6 + 0.4 * u)), std::sin(0.5 * t * v), 1.0).normalized();
      o << "GOTO/" << x << "," << y << "," << z << "," << n.x() << "," << n.y() << "," << n.z() << "\n";
    }
  }
  o << "SPINDL/OFF\nFINI\n";
  return o.str();
}

cl::Program seed_cut(const std::string& file = "seed000_x_cut.cls") {
  return cl::read_file(test::source_path("examples/xmini/" + file));
}

struct RandomPose {
  Vec3 tip, u;
};
std::vector<RandomPose> random_poses(int n, unsigned salt) {
  auto rng = test::rng(salt);
  std::uniform_real_distribution<double> U(0.0, 1.0);
  const double cos_max = std::cos(deg2rad(kMaxTiltDeg));
  std::vector<RandomPose> out;
  for (int i = 0; i < n; ++i) {
    const double r = kVolumeRadiusMm * std::sqrt(U(rng)), th = 2 * kPi * U(rng), z = kVolumeZMm * (2 * U(rng) - 1);
    const double ct = 1.0 - (1.0 - cos_max) * U(rng), st = std::sqrt(1 - ct * ct), ph = 2 * kPi * U(rng);
    out.push_back({Vec3(r * std::cos(th), r * std::sin(th), z), Vec3(st * std::cos(ph), st * std::sin(ph), ct)});
  }
  return out;
}

/// The axis values of the feed blocks of a program (and the point each cut starts from).
std::vector<kin::Axes> feed_path(const nc::Program& p) {
  std::vector<kin::Axes> out;
  for (size_t i = 1; i < p.blocks.size(); ++i) {
    if (p.blocks[i].motion == nc::Motion::Rapid) continue;
    if (out.empty() || p.blocks[i - 1].motion == nc::Motion::Rapid) {
      kin::Axes q;
      for (int a = 0; a < 5; ++a) q[a] = p.blocks[i - 1].axes[static_cast<size_t>(a)];
      out.push_back(q);
    }
    kin::Axes q;
    for (int a = 0; a < 5; ++a) q[a] = p.blocks[i].axes[static_cast<size_t>(a)];
    out.push_back(q);
  }
  return out;
}

report::Stats cut_stats(const nc::Program& p) {
  const auto path = feed_path(p);
  return report::compute(path, std::vector<bool>(path.size(), false), {"q1", "q2", "q3", "c", "a"},
                         {false, false, false, true, true});
}

}  // namespace

// ------------------------------------------------------------------------------------------------
// XminiKinematics
// ------------------------------------------------------------------------------------------------

TEST(XminiKinematics, AxesRotaryPairAndHome) {
  const kin::XminiKinematics k{kin::XminiModel()};
  ASSERT_EQ(k.axes().size(), 5u);
  for (size_t i = 0; i < 5; ++i) EXPECT_EQ(k.axes()[i].name, kin::kXminiAxisNames[i]);
  EXPECT_FALSE(k.axes()[2].rotary());
  EXPECT_TRUE(k.axes()[3].rotary());
  EXPECT_EQ(k.rotary_pair()[0], 3);
  EXPECT_EQ(k.rotary_pair()[1], 4);
  EXPECT_NEAR(k.axes()[3].max, deg2rad(270.0), 1e-12);
  EXPECT_NEAR(k.axes()[4].min, deg2rad(-50.0), 1e-12);
  kin::Axes home;
  home << 154.669331, 158.276253, 154.669331, 0.0, 0.0;
  const kin::Posed p = k.forward(home);
  EXPECT_NEAR(p.tip_mm.norm(), 0.0, kHomeMm);
  EXPECT_NEAR(angle_between(p.axis, Vec3::UnitZ()), 0.0, 1e-7);
}

TEST(XminiKinematics, EverySolutionRoundTripsThroughForward) {
  const kin::XminiKinematics k{kin::XminiModel()};
  std::vector<kin::Solution> all, principal;
  int poses = 0, solutions = 0;
  for (const RandomPose& rp : random_poses(kRandomPoses, 1)) {
    const kin::Posed pose{rp.tip, rp.u};
    k.inverse_all(pose, nullptr, all);
    k.inverse_branches(pose, nullptr, principal);
    ASSERT_EQ(principal.size(), 2u) << "both wrist branches";
    EXPECT_NE(principal[0].branch, principal[1].branch);
    for (const kin::Solution& s : principal) {
      EXPECT_GT(s.axes[3], -kPi - 1e-12);
      EXPECT_LE(s.axes[3], kPi + 1e-12);
    }
    // Every winding inside +-270 deg: a principal c in (-90, 90) has one, the others two.
    size_t expected = 0;
    for (const kin::Solution& s : principal) expected += std::abs(s.axes[3]) < kPi / 2 ? 1 : 2;
    EXPECT_EQ(all.size(), expected);
    for (const kin::Solution& s : all) {
      const kin::Posed f = k.forward(s.axes);
      ASSERT_LT((f.tip_mm - rp.tip).norm(), tol::kRoundTripMm) << "tip " << rp.tip.transpose();
      ASSERT_LT(angle_between(f.axis, rp.u), tol::kRoundTripRad);
      ++solutions;
    }
    ++poses;
  }
  EXPECT_EQ(poses, kRandomPoses);
  EXPECT_GE(solutions, 2 * kRandomPoses);
}

TEST(XminiKinematics, PassiveJointLimitIsReportedAndBlocksSolveForRotaries) {
  kin::XminiLimits lim;
  lim.alpha_max_rad = deg2rad(5.0);  // a vertical tool at y = 100 needs alpha = atan(100/750) = 7.6 deg
  const kin::XminiKinematics k{kin::XminiModel(kin::XminiParams<double>::nominal(), lim)};
  const kin::Posed pose{Vec3(0, 100, 0), Vec3::UnitZ()};
  std::vector<kin::Solution> sols;
  k.inverse_branches(pose, nullptr, sols);
  ASSERT_FALSE(sols.empty());
  for (const auto& s : sols) {
    EXPECT_FALSE(s.feasible());
    EXPECT_NE(s.violation.find("alpha"), std::string::npos) << s.violation;
    EXPECT_TRUE(k.check_limits(s.axes).empty()) << "strokes, C and A are fine: only the passive joint breaks";
    EXPECT_NE(k.passive_violation(s.axes).find("alpha"), std::string::npos);
    kin::Axes q = s.axes;
    EXPECT_FALSE(k.solve_for_rotaries(pose, q));
    Vec3 axis;
    EXPECT_FALSE(k.tool_axis_at(s.axes[3], s.axes[4], pose.tip_mm, axis));
  }
  const kin::XminiKinematics nominal{kin::XminiModel()};
  nominal.inverse_branches(pose, nullptr, sols);
  for (const auto& s : sols) EXPECT_TRUE(s.feasible()) << s.violation;
}

TEST(XminiKinematics, SolveForRotariesPlacesTheTipAndTheAxisFollowsTheParasiticTilt) {
  const kin::XminiKinematics k{kin::XminiModel()};
  std::vector<kin::Solution> sols;
  for (const RandomPose& rp : random_poses(100, 2)) {
    const kin::Posed pose{rp.tip, rp.u};
    k.inverse_branches(pose, nullptr, sols);
    ASSERT_FALSE(sols.empty());
    const kin::Axes q_ik = sols[0].axes;
    // Same rotaries: the legs of the IK solution come back, and the axis is the pose's.
    kin::Axes q = q_ik;
    q.head<3>().setConstant(100.0);
    ASSERT_TRUE(k.solve_for_rotaries(pose, q));
    EXPECT_LT((q.head<3>() - q_ik.head<3>()).cwiseAbs().maxCoeff(), tol::kRoundTripMm * 10);
    Vec3 axis;
    ASSERT_TRUE(k.tool_axis_at(q_ik[3], q_ik[4], rp.tip, axis));
    EXPECT_LT(angle_between(axis, rp.u), tol::kRoundTripRad * 10);
    // Other rotaries: the tip still lands, and the axis is whatever FK says, as tool_axis_at reports.
    kin::Axes q2 = q_ik;
    q2[3] += deg2rad(20.0);
    q2[4] = std::clamp(q2[4] + deg2rad(5.0), deg2rad(-45.0), deg2rad(45.0));
    ASSERT_TRUE(k.solve_for_rotaries(pose, q2));
    const kin::Posed f = k.forward(q2);
    EXPECT_LT((f.tip_mm - rp.tip).norm(), tol::kRoundTripMm);
    ASSERT_TRUE(k.tool_axis_at(q2[3], q2[4], rp.tip, axis));
    EXPECT_LT(angle_between(axis, f.axis), tol::kRoundTripRad);
  }
  // Parasitic motion: away from the centre, a = 0 does not give a vertical tool (docs/xmini.md). With
  // a = c = 0 the tool lies along the platform's z axis, which passes through the wrist centre; both lie
  // in the plane of legs 1 and 3, which contains x_B. So the tool line meets the base axis x_B, 900 mm
  // above the tip: the tilt is atan(100 / 900) at y = 100.
  Vec3 axis;
  ASSERT_TRUE(k.tool_axis_at(0.0, 0.0, Vec3(0, 100, 0), axis));
  EXPECT_NEAR(rad2deg(angle_between(axis, Vec3::UnitZ())), rad2deg(std::atan2(100.0, 900.0)), 1e-9);
}

TEST(XminiKinematics, ForwardIsThreadSafeWithItsWarmStart) {
  const kin::XminiKinematics k{kin::XminiModel()};
  std::vector<kin::Axes> qs;
  std::vector<kin::Solution> sols;
  for (const RandomPose& rp : random_poses(400, 3)) {
    k.inverse_branches({rp.tip, rp.u}, nullptr, sols);
    qs.push_back(sols[0].axes);
  }
  std::vector<kin::Posed> expected;
  for (const auto& q : qs) expected.push_back(k.forward(q));
  std::vector<double> worst(4, 0.0);
  std::vector<std::thread> threads;
  for (int t = 0; t < 4; ++t)
    threads.emplace_back([&, t] {
      for (int rep = 0; rep < 5; ++rep)
        for (size_t i = 0; i < qs.size(); ++i) {
          const size_t j = (i * (2 * static_cast<size_t>(t) + 1) + static_cast<size_t>(rep)) % qs.size();
          const kin::Posed p = k.forward(qs[j]);
          worst[static_cast<size_t>(t)] =
              std::max(worst[static_cast<size_t>(t)], (p.tip_mm - expected[j].tip_mm).norm());
        }
    });
  for (auto& th : threads) th.join();
  for (double w : worst) EXPECT_LT(w, tol::kRoundTripMm);
}

TEST(XminiKinematics, LegsWithoutAnAssemblyGiveAnInfiniteTip) {
  const kin::XminiKinematics k{kin::XminiModel()};
  kin::Axes q;
  q << -440.0, -440.0, -440.0, 0.0, 0.0;  // 10 mm legs cannot span the joints
  const kin::Posed p = k.forward(q);
  EXPECT_TRUE(std::isinf(p.tip_mm.x()));
  // And the workspace recovers for the next, valid call.
  q << 154.669331, 158.276253, 154.669331, 0.0, 0.0;
  EXPECT_NEAR(k.forward(q).tip_mm.norm(), 0.0, kHomeMm);
}

// ------------------------------------------------------------------------------------------------
// Machine file
// ------------------------------------------------------------------------------------------------

TEST(XminiMachine, FileHasTheSpecsNominalMachineAndPostDefaults) {
  const machine::Machine m = xmini_machine();
  EXPECT_EQ(m.kind, machine::ModelKind::Xmini);
  ASSERT_EQ(m.axes.size(), 5u);
  EXPECT_EQ(m.axes[0].name, "q1");
  EXPECT_EQ(m.axes[4].name, "a");
  EXPECT_NEAR(m.axes[1].max, 350.0, 1e-12);
  EXPECT_NEAR(m.axes[3].min, deg2rad(-270.0), 1e-12);
  EXPECT_NEAR(m.axes[3].max_feed, deg2rad(5400.0), 1e-9);
  const std::array<std::string, 5> letters{"U", "V", "W", "C", "A"};
  EXPECT_EQ(m.post.letters, letters);
  EXPECT_EQ(m.post.dialect, "xmini-joint");
  EXPECT_EQ(m.post.start_branch, "positive:a");
  EXPECT_DOUBLE_EQ(m.post.tolerance_mm, 0.001);
  EXPECT_DOUBLE_EQ(m.default_tool_length_mm, 50.0);
  const auto k = m.kinematics();
  const auto* xk = dynamic_cast<const kin::XminiKinematics*>(k.get());
  ASSERT_NE(xk, nullptr);
  const auto nominal = kin::XminiParams<double>::nominal();
  for (size_t i = 0; i < kin::kXminiParamCount; ++i) EXPECT_DOUBLE_EQ(xk->model().params()[i], nominal[i]);
  kin::Axes home;
  home << 154.669331, 158.276253, 154.669331, 0.0, 0.0;
  EXPECT_NEAR(k->forward(home).tip_mm.norm(), 0.0, kHomeMm);
  // Another tool length (the post's --tool-length) moves the tip along the tool.
  const auto k80 = m.make_kinematics(80.0);
  EXPECT_NEAR((k80->forward(home).tip_mm - Vec3(0, 0, -30)).norm(), 0.0, kHomeMm);
}

TEST(XminiMachine, ParametersLimitsAndFeedsComeFromTheFile) {
  const machine::Machine m = machine::load_text(
      "name: x2\nkinematics: xmini\nxmini:\n  tool_length_mm: 60\n  parameters: {theta0: 0.02, L02: 449.7, gz: 100.2}\n"
      "  limits: {strokes_mm: [[0, 300], [10, 340], [0, 350]], alpha_deg: 20, beta_deg: 22, a_deg: [-40, 45], "
      "c_deg: [-200, 190]}\n  max_feed: {q2: 9000, a: 3600}\npost: {letters: {q1: X, q2: Y, q3: Z}}\n",
      "x2.yaml");
  const auto k = m.kinematics();
  const auto& xk = dynamic_cast<const kin::XminiKinematics&>(*k);
  EXPECT_NEAR(xk.model().params().get("theta0"), 0.02, 1e-12);
  EXPECT_NEAR(xk.model().params().L02, 449.7, 1e-12);
  EXPECT_NEAR(xk.model().tool_length_mm(), 60.0, 1e-12);
  EXPECT_NEAR(xk.model().limits().q_min_mm[1], 10.0, 1e-12);
  EXPECT_NEAR(xk.model().limits().q_max_mm[0], 300.0, 1e-12);
  EXPECT_NEAR(rad2deg(xk.model().limits().beta_max_rad), 22.0, 1e-9);
  EXPECT_NEAR(rad2deg(m.axes[3].max), 190.0, 1e-9);
  EXPECT_NEAR(rad2deg(m.axes[4].min), -40.0, 1e-9);
  EXPECT_NEAR(m.axes[1].max_feed, 9000.0, 1e-9);
  EXPECT_NEAR(m.axes[0].max_feed, 0.0, 1e-9);
  EXPECT_EQ(m.post.letters[0], "X");
  EXPECT_EQ(m.post.letters[3], "C");  // the XMINI default survives a partial letters map
  EXPECT_DOUBLE_EQ(m.default_tool_length_mm, 60.0);
}

TEST(XminiMachine, BadInputNamesTheKeyAndTheLine) {
  auto expect_error = [](const std::string& yaml, const std::vector<std::string>& needles) {
    try {
      machine::load_text(yaml, "bad.yaml");
      ADD_FAILURE() << "expected an InputError for:\n" << yaml;
    } catch (const InputError& e) {
      const std::string msg = e.what();
      for (const auto& n : needles) EXPECT_NE(msg.find(n), std::string::npos) << msg;
    }
  };
  const std::string head = "name: x\nkinematics: xmini\n";
  expect_error(head + "xmini:\n  parameters:\n    A1x: -150\n    A9x: 3\n",
               {"bad.yaml:6", "xmini.parameters.A9x", "unknown XMINI parameter"});
  expect_error(head + "xmini:\n  parameters: {L01: abc}\n", {"bad.yaml:4", "xmini.parameters.L01", "number"});
  expect_error(head + "xmini:\n  limits:\n    strokes_mm: [350, 0]\n", {"bad.yaml:5", "strokes_mm", "min < max"});
  expect_error(head + "xmini:\n  limits:\n    gamma_deg: 3\n", {"bad.yaml:5", "xmini.limits.gamma_deg", "unknown key"});
  expect_error(head + "xmini:\n  limits: {alpha_deg: 95}\n", {"bad.yaml:4", "alpha_deg"});
  expect_error(head + "default_tool_length_mm: 40\nxmini:\n  tool_length_mm: 50\n", {"bad.yaml:5", "give it once"});
  expect_error(head + "xmini:\n  max_feed: {q4: 10}\n", {"bad.yaml:4", "xmini.max_feed.q4"});
  expect_error(head + "axes: []\n", {"bad.yaml:3", "'axes'", "xmini"});
  expect_error(head + "xmini:\n  parameters: {psi: 90}\n", {"bad.yaml", "psi"});
  expect_error(head + "post: {start_branch: positive:q1}\n", {"bad.yaml:3", "not a rotary"});
}

// ------------------------------------------------------------------------------------------------
// Posts
// ------------------------------------------------------------------------------------------------

TEST(XminiPost, JointProgramsGoThroughRs274AndStayWithinTheTolerance) {
  const machine::Machine m = xmini_xyz();
  const auto k = m.kinematics();
  const cl::Program raster = cl::read_text(raster_cl(20.0, 5, 30, -30.0), "raster.cls");
  for (const cl::Program* prog : {&raster}) {
    post::Summary sum;
    const std::string text = post_text(*prog, m, *k, "", &sum);
    EXPECT_GT(sum.inserted_points, 10u) << "joint-space lines are curves: the post must subdivide";
    EXPECT_TRUE(sum.warnings.empty()) << sum.warnings.front();
    expect_rs274_agrees(text, m, "raster");
    const auto v = verify_text(text, *prog, m, *k);
    EXPECT_TRUE(v.ok) << v.message;
    EXPECT_LE(v.max_tip_deviation_mm, 0.001 + kPrintedRoundingMm);
  }
  for (const char* f : {"seed000_x_cut.cls", "seed000_x_cut_offset.cls"}) {
    SCOPED_TRACE(f);
    const cl::Program prog = seed_cut(f);
    post::Summary sum;
    const std::string text = post_text(prog, m, *k, "", &sum);
    expect_rs274_agrees(text, m, f);
    const auto v = verify_text(text, prog, m, *k);
    // The conventional post keeps a >= 0 at every point, so at the singularity (x = 0, a = 0) C must turn
    // 180 deg. Once it swung C and a sign of a together inside one feed block (0.07 mm off the path); now it
    // turns C alone at a = 0, where the tool does not move, and the whole cut stays within the tolerance.
    EXPECT_TRUE(v.ok) << v.message;
    EXPECT_EQ(sum.reorientations, std::string(f) == "seed000_x_cut.cls" ? 1u : 0u);
    EXPECT_EQ(sum.retracts, 0u);
  }
}

TEST(XminiPost, ASwingBesideTheSingularityInsideASegmentIsFollowed) {
  // NX's zigzag passes close to the wrist singularity inside the long cut from CL line 149 to 151 (a = 0.37 deg at
  // line 149): the branch the post keeps swings C by 120 deg there. Once the post wrote that segment as one block
  // with a warning and only the gate stopped it (the joint move sweeps the tip by a millimetre); then the post refused
  // it naming the segment ("IK branch"); now it follows the swing with CL points inserted along it, and the safety
  // gate and FK of every block agree that the program stays within the tolerances.
  const machine::Machine m = xmini_machine();
  const auto k = m.kinematics();
  const cl::Program prog = cl::read_file(test::source_path("examples/nx-haas-umc750/zigzag_smoothed.cls"));
  post::Summary sum;
  const std::string nc = post_text(prog, m, *k, "", &sum);
  const auto swing = std::find_if(sum.warnings.begin(), sum.warnings.end(), [](const std::string& w) {
    return w.find("swing beside a singular orientation between CL lines 149 and 151") != std::string::npos;
  });
  EXPECT_NE(swing, sum.warnings.end());
  const auto gs = gate::check(nc, "zigzag.ngc", prog, m, *k, gate::options_for(m, 0, 0, 0), &sum.cl_line_of_nc_line);
  EXPECT_TRUE(gs.ok) << gs.message;
  const auto v = verify_text(nc, prog, m, *k);
  EXPECT_TRUE(v.ok) << v.message;
  EXPECT_LE(v.max_tip_deviation_mm, m.post.tolerance_mm + kPrintedRoundingMm);
}

// A calibrated XMINI: the C axis tilted by a few thousandths of a degree (gC1, gC2), as `cscam calibrate` finds
// them. The vertical is then no longer exactly singular: ISO/CATIA's ramp (CL lines 19 -> 20) tilts the tool past
// the C axis at a fraction of a thousandth of a degree, where the wrist branch the post keeps (A >= 0) swings C half
// a turn over 1e-4 of the segment. The linearizer's halving crossed there holding C, on the other branch, and the
// post refused the program (nominal: retract and flip at line 19). The swing is now followed with CL points inserted
// along it. Oracles: the safety gate, and FK of every block against the CL path within the post's tolerances.
TEST(XminiPost, APassBesideTheWristSingularityOfACalibratedMachineIsFollowed) {
  auto rng = test::rng(2024);
  std::uniform_real_distribution<double> mag(0.0005, 0.003);  // deg, the size of calibrated wrist tilts
  std::bernoulli_distribution sign(0.5);
  // The nominal machine, the reported case, then seeded ones.
  std::vector<std::array<double, 2>> tilts{{0.0, 0.0}, {0.002, 0.0}};
  for (int i = 0; i < 4; ++i) tilts.push_back({(sign(rng) ? 1 : -1) * mag(rng), (sign(rng) ? 1 : -1) * mag(rng)});
  for (const auto& [g1, g2] : tilts) {
    std::string text = read_text_file(test::source_path("machines/xmini.yaml"));
    text.replace(text.find("    gC1: 0\n"), 11, fmt::format("    gC1: {}\n", g1));
    text.replace(text.find("    gC2: 0\n"), 11, fmt::format("    gC2: {}\n", g2));
    const machine::Machine m = machine::load_text(text, test::source_path("machines/xmini-calibrated.yaml"));
    const auto k = m.kinematics();
    for (const char* f :
         {"examples/cl/iso_catia.cls", "examples/cl/points_csv.cls", "examples/xmini/seed000_x_cut.cls"}) {
      SCOPED_TRACE(fmt::format("gC1 {} gC2 {} {}", g1, g2, f));
      const cl::Program prog = cl::read_file(test::source_path(f));
      post::Summary sum;
      std::string nc;
      ASSERT_NO_THROW(nc = post_text(prog, m, *k, "", &sum));
      const auto gs =
          gate::check(nc, "calibrated.ngc", prog, m, *k, gate::options_for(m, 0, 0, 0), &sum.cl_line_of_nc_line);
      EXPECT_TRUE(gs.ok) << gs.message;
      const auto v = verify_text(nc, prog, m, *k);
      EXPECT_TRUE(v.ok) << v.message;
      EXPECT_LE(v.max_tip_deviation_mm, m.post.tolerance_mm + kPrintedRoundingMm);
    }
  }
}

/// machines/xmini.yaml with one parameter's value replaced (a calibrated machine is slightly off nominal).
machine::Machine xmini_with(const std::string& name, double value) {
  return xmini_variant(fmt::format("    {}: {}\n", name, name == "gz" ? "100" : "0"),
                       fmt::format("    {}: {}\n", name, value));
}

// A calibrated wrist (psi or gx off nominal) cannot reach the tool axes at and around the vertical exactly (psi:
// every direction within |psi| of the C axis; gx: the tip swings with C about the pole). The IK then returns the
// nearest reachable axis, flagged with the angle it is off; the tip stays exact. Oracle: forward kinematics.
TEST(XminiKinematics, NearThePoleOfACalibratedWristTheNearestAxisIsReturnedWithItsError) {
  auto rng = test::rng(77);
  std::uniform_real_distribution<double> z(-50.0, 50.0), tilt(0.0, 1.0), az(-kPi, kPi);
  const double psi_deg = 0.003;
  for (const auto& [name, value, bound_rad] : std::vector<std::tuple<std::string, double, double>>{
           {"psi", psi_deg, deg2rad(psi_deg)}, {"gx", 0.1, tol::kReachSlackRad}}) {
    const machine::Machine m = xmini_with(name, value);
    const auto k = m.kinematics();
    std::vector<kin::Solution> all;
    int inexact = 0;
    for (int i = 0; i < 40; ++i) {
      // Vertical, or tilted less than |psi| off it (the unreachable cone).
      const double t = i % 2 == 0 ? 0.0 : 0.9 * tilt(rng) * deg2rad(psi_deg), phi = az(rng);
      const Vec3 u(std::sin(t) * std::cos(phi), std::sin(t) * std::sin(phi), std::cos(t));
      // On the machine's centre line, where the platform is untilted and the C axis vertical (elsewhere the platform's
      // tilt moves the unreachable cone off the vertical).
      const kin::Posed pose{Vec3(0.0, 0.0, z(rng)), u};
      SCOPED_TRACE(fmt::format("{} {} tip {} {} {}", name, value, pose.tip_mm.x(), pose.tip_mm.y(), pose.tip_mm.z()));
      k->inverse_all(pose, nullptr, all);
      ASSERT_FALSE(all.empty()) << "the nearest reachable axis is a solution";
      for (const kin::Solution& s : all) {
        const kin::Posed f = k->forward(s.axes);
        EXPECT_LT((f.tip_mm - pose.tip_mm).norm(), 1e-6) << "the tip is exact";
        const double err = std::atan2(f.axis.cross(u).norm(), f.axis.dot(u));
        EXPECT_NEAR(err, s.axis_error_rad, 1e-9) << "the flag says what FK measures";
        EXPECT_LE(err, bound_rad + 1e-9);
        inexact += s.exact() ? 0 : 1;
      }
    }
    EXPECT_GT(inexact, 0) << name << ": the vertical is unreachable exactly";
  }
  // Nominal: every solution exact.
  const auto k = xmini_machine().kinematics();
  std::vector<kin::Solution> all;
  k->inverse_all(kin::Posed{Vec3(0, 0, 50), Vec3::UnitZ()}, nullptr, all);
  ASSERT_FALSE(all.empty());
  for (const kin::Solution& s : all) EXPECT_TRUE(s.exact());
}

// ISO/CATIA's vertical passes on an XMINI whose wrist twist psi is 0.003 deg (calibration size): the post takes the
// nearest reachable axes and the gate passes the program, with the deviation measured inside the tolerance (it said
// "no inverse-kinematics solution" at CL line 14). A twist beyond the tolerance is refused by the gate.
TEST(XminiPost, ACalibratedWristTwistPostsTheVerticalWithinTheAxisTolerance) {
  const cl::Program prog = cl::read_file(test::source_path("examples/cl/iso_catia.cls"));
  {
    const machine::Machine m = xmini_with("psi", 0.003);
    const auto k = m.kinematics();
    const std::string nc = post_text(prog, m, *k);
    const auto gs = gate::check(nc, "psi.ngc", prog, m, *k, gate::options_for(m, 0, 0, 0));
    EXPECT_TRUE(gs.ok) << gs.message;
    const auto v = verify_text(nc, prog, m, *k);
    EXPECT_TRUE(v.ok) << v.message;
    EXPECT_LE(v.max_axis_deviation_deg, m.post.axis_tolerance_deg);
    EXPECT_GE(v.max_axis_deviation_deg, 0.0029) << "the deviation is measured, not assumed";
  }
  {
    const machine::Machine m = xmini_with("psi", 0.03);  // 3 x the axis tolerance, inside the IK's reach
    const auto k = m.kinematics();
    try {
      const std::string nc = post_text(prog, m, *k);
      const auto gs = gate::check(nc, "psi.ngc", prog, m, *k, gate::options_for(m, 0, 0, 0));
      EXPECT_FALSE(gs.ok);
      EXPECT_NE(gs.message.find("axis"), std::string::npos) << gs.message;
    } catch (const InputError& e) {  // or the linearizer refuses first
      SUCCEED() << e.what();
    }
  }
}

TEST(XminiPost, WithoutLinearisationTheTipLeavesTheTolerance) {
  // The oracle is able to fail: the same raster without subdivision is off by more than the tolerance.
  const machine::Machine m = xmini_machine();
  const auto k = m.kinematics();
  const cl::Program prog = cl::read_text(raster_cl(20.0, 3, 8, -30.0), "coarse.cls");
  const auto axes = post::conventional_axes(prog, m, *k);
  std::ostringstream os;
  post::Options o;
  o.linearise = false;
  post::Summary s;
  post::write_nc(os, prog, m, *k, axes, o, s);
  const auto v = verify_text(os.str(), prog, m, *k);
  EXPECT_FALSE(v.ok) << v.message;
  EXPECT_GT(v.max_tip_deviation_mm, 0.01);
}

TEST(XminiPost, CartesianModeWritesTheTipAndTheToolVector) {
  const machine::Machine m = xmini_machine();
  const auto k = m.kinematics();
  const cl::Program prog = cl::read_text(raster_cl(20.0, 3, 12, -30.0), "cart.cls");
  for (const machine::Machine& mm :
       {m, xmini_variant("  dialect: xmini-joint\n", "  dialect: xmini-joint\n  tcp: true\n")}) {
    post::Summary sum;
    const std::string text = post_text(prog, mm, *k, mm.post.tcp ? "" : "xmini-cartesian", &sum);
    // The control moves the tip straight and interpolates the wrist words: points are inserted only where that
    // interpolation would turn the tool axis beyond the axis tolerance; read back through the control's view,
    // the program stays within the tolerance.
    {
      nc::Program ncp = report::read_for_machine(text, "cart.ngc", mm);
      ASSERT_TRUE(ncp.tcp);
      const auto view = report::tool_tip_kinematics(*k);
      const auto v = report::verify(ncp, prog, *view, report::verify_options_for(mm));
      EXPECT_TRUE(v.ok) << v.message;
      EXPECT_LT(sum.inserted_points, prog.moves.size());
    }
    // rs274 reads X Y Z C A: the Cartesian letters.
    std::string log;
    const auto moves = rs274_moves(text, "cart", log);
    EXPECT_EQ(log.find("rror"), std::string::npos) << log.substr(0, 2000);
    EXPECT_EQ(log.find("Unknown"), std::string::npos) << log.substr(0, 2000);
    // Every feed point of the CL appears as a block: tip = X Y Z, u from the virtual (C, A).
    size_t matched = 0;
    for (const auto& mv : prog.moves) {
      for (const auto& b : moves) {
        const Vec3 tip(b[0], b[1], b[2]);
        if ((tip - mv.tip_in_part_mm).cwiseAbs().maxCoeff() > kRs274Half) continue;
        const double A = deg2rad(b[3]), C = deg2rad(b[5]);
        const Vec3 u(-std::sin(A) * std::sin(C), -std::sin(A) * std::cos(C), std::cos(A));
        EXPECT_LT(rad2deg(angle_between(u, mv.axis_in_part.normalized())), 1e-3);
        ++matched;
        break;
      }
    }
    EXPECT_EQ(matched, prog.moves.size());
  }
}

TEST(XminiPost, RetractsAlongTheToolAxisToTheSafePlane) {
  // Two cuts with different tool axes: retract, turn at the safe plane, above the next point, plunge.
  const machine::Machine m = xmini_machine();
  const auto k = m.kinematics();
  const Vec3 u2 = Vec3(0.3, -0.2, 1.0).normalized();
  std::ostringstream cl;
  cl << "UNITS/MM\nMULTAX/ON\nFEDRAT/MMPM,500\nRAPID\nGOTO/-30,20,-40,0,0,1\nGOTO/30,20,-40,0,0,1\nRAPID\nGOTO/"
        "30,-20,-40,"
     << u2.x() << "," << u2.y() << "," << u2.z() << "\nGOTO/-30,-20,-40," << u2.x() << "," << u2.y() << "," << u2.z()
     << "\n";
  const cl::Program prog = cl::read_text(cl.str(), "two_cuts.cls");
  const std::string text = post_text(prog, m, *k);
  const nc::Program ncp = nc::read_text(text, "two_cuts.ngc", letters_of(m));
  std::vector<kin::Posed> rapid_tips;
  for (const auto& b : ncp.blocks) {
    kin::Axes q;
    for (int a = 0; a < 5; ++a) q[a] = b.axes[static_cast<size_t>(a)];
    if (b.motion == nc::Motion::Rapid) rapid_tips.push_back(k->forward(q));
  }
  // first: above the start, the plunge; then: up, turn, above, plunge; at the end: up.
  ASSERT_EQ(rapid_tips.size(), 7u) << text;
  const double safe = m.post.safe_z_mm;
  EXPECT_NEAR(rapid_tips[0].tip_mm.z(), safe, kPrintedRoundingMm);
  EXPECT_NEAR((rapid_tips[1].tip_mm - Vec3(-30, 20, -40)).norm(), 0.0, kPrintedRoundingMm);
  // Up along the vertical tool from (30, 20, -40).
  EXPECT_NEAR((rapid_tips[2].tip_mm - Vec3(30, 20, safe)).norm(), 0.0, kPrintedRoundingMm);
  EXPECT_NEAR(rad2deg(angle_between(rapid_tips[2].axis, Vec3::UnitZ())), 0.0, 1e-3);
  // Turned in place at the safe plane: same tip, the new tool axis.
  EXPECT_NEAR((rapid_tips[3].tip_mm - rapid_tips[2].tip_mm).norm(), 0.0, kPrintedRoundingMm);
  EXPECT_NEAR(rad2deg(angle_between(rapid_tips[3].axis, u2)), 0.0, 1e-3);
  // Above the next point along its tool axis.
  const Vec3 above = Vec3(30, -20, -40) + (safe + 40) / u2.z() * u2;
  EXPECT_NEAR((rapid_tips[4].tip_mm - above).norm(), 0.0, kPrintedRoundingMm);
  EXPECT_NEAR(rad2deg(angle_between(rapid_tips[4].axis, u2)), 0.0, 1e-3);
  EXPECT_NEAR((rapid_tips[5].tip_mm - Vec3(30, -20, -40)).norm(), 0.0, kPrintedRoundingMm);
  // The end: up along u2 from (-30, -20, -40).
  EXPECT_NEAR((rapid_tips[6].tip_mm - (Vec3(-30, -20, -40) + (safe + 40) / u2.z() * u2)).norm(), 0.0,
              kPrintedRoundingMm);
  const machine::Machine mx = xmini_xyz();
  expect_rs274_agrees(post_text(prog, mx, *mx.kinematics()), mx, "two_cuts");
}

// ------------------------------------------------------------------------------------------------
// Seed 000: the cut along X
// ------------------------------------------------------------------------------------------------

TEST(XminiSeed000, TheLineCrossesTheSingularityWhereQ2HasItsMinimum) {
  const machine::Machine m = xmini_machine();
  const auto k = m.kinematics();
  std::vector<kin::Solution> sols;
  auto principal_branch0 = [&](double x) {
    k->inverse_branches({Vec3(x, 0, 0), Vec3::UnitZ()}, nullptr, sols);
    for (const auto& s : sols)
      if (s.branch == 0) return s.axes;
    return kin::Axes(kin::Axes::Constant(std::nan("")));
  };
  // Scan x at 0.01 mm: the wrist angle |a| and q2 are both smallest at x = 0.
  double x_amin = 1e9, amin = 1e9, x_q2min = 1e9, q2min = 1e9;
  for (int i = -2000; i <= 2000; ++i) {
    const double x = 0.01 * i;
    const kin::Axes q = principal_branch0(x);
    if (std::abs(q[4]) < amin) amin = std::abs(q[4]), x_amin = x;
    if (q[1] < q2min) q2min = q[1], x_q2min = x;
  }
  EXPECT_NEAR(x_amin, 0.0, 1e-9);
  EXPECT_LT(amin, 1e-9);
  EXPECT_NEAR(x_q2min, 0.0, 1e-9);
  EXPECT_GT(principal_branch0(-20)[1] - q2min, 0.2) << "q2 reverses by a fraction of a mm";
  // 0.05 mm off the singular line, a vertical tool needs a != 0 everywhere (parasitic tilt).
  double amin_off = 1e9;
  for (int i = -200; i <= 200; ++i) {
    k->inverse_branches({Vec3(0.01 * i, 0.05, 0), Vec3::UnitZ()}, nullptr, sols);
    amin_off = std::min(amin_off, std::abs(sols[0].axes[4]));
  }
  EXPECT_NEAR(rad2deg(amin_off), rad2deg(std::atan2(0.05, 750.0)), 1e-6);
}

TEST(XminiSeed000, ConventionalPostStats) {
  const machine::Machine m = xmini_machine();
  const auto k = m.kinematics();
  // On the line: q2 reverses once inside the cut; the post keeps a >= 0 at every point (machine file:
  // branch_rule always), so A comes down to 0 and goes up again (a reversal) while C flips by 180 deg.
  {
    const cl::Program prog = seed_cut();
    const nc::Program ncp = nc::read_text(post_text(prog, m, *k), "exact.ngc", letters_of(m));
    const report::Stats s = cut_stats(ncp);
    EXPECT_EQ(s.axes[1].reversals, 1);
    EXPECT_EQ(s.axes[0].reversals, 0);
    EXPECT_EQ(s.axes[2].reversals, 0);
    EXPECT_EQ(s.axes[4].reversals, 1);
    EXPECT_NEAR(s.axes[3].travel, 180.0, 1e-6);
    // At CL points a >= 0; inside the flip the post's subdivision follows the branch through a = 0 and
    // dips below it by less than a tenth of a degree before the flip completes.
    EXPECT_GE(s.axes[4].min, -0.1);
  }
  // 0.05 mm off: every exact-orientation path turns C by 180 deg; A (kept >= 0) reverses near x = 0.
  {
    const cl::Program prog = seed_cut("seed000_x_cut_offset.cls");
    const nc::Program ncp = nc::read_text(post_text(prog, m, *k), "offset.ngc", letters_of(m));
    const report::Stats s = cut_stats(ncp);
    EXPECT_GE(s.axes[1].reversals, 1);
    EXPECT_EQ(s.axes[4].reversals, 1);
    EXPECT_GE(s.axes[4].min, 0.0);
    EXPECT_NEAR(s.axes[3].travel, 180.0, 1.0);
    EXPECT_EQ(s.axes[3].reversals, 0);
  }
}

// ------------------------------------------------------------------------------------------------
// Backlash
// ------------------------------------------------------------------------------------------------

TEST(Backlash, PlayOperatorHandComputed) {
  // Width 0.01; engaged upward (first motion); the command turns at 2 and must come down 0.01 first.
  const std::vector<double> cmd{0, 1, 2, 1.995, 1.99, 1.985, 1.98, 1.5, 1.0, 1.004, 1.02};
  const std::vector<double> want{0, 1, 2, 2, 2, 1.995, 1.99, 1.51, 1.01, 1.01, 1.02};
  const auto out = report::apply_play(cmd, 0.01);
  ASSERT_EQ(out.size(), want.size());
  for (size_t i = 0; i < want.size(); ++i) EXPECT_NEAR(out[i], want[i], 1e-12) << i;
  // Engaged downward first: the mirror image.
  std::vector<double> neg(cmd.size()), want_neg(cmd.size());
  for (size_t i = 0; i < cmd.size(); ++i) neg[i] = -cmd[i], want_neg[i] = -want[i];
  const auto out_neg = report::apply_play(neg, 0.01);
  for (size_t i = 0; i < want.size(); ++i) EXPECT_NEAR(out_neg[i], want_neg[i], 1e-12) << i;
  EXPECT_EQ(report::apply_play(cmd, 0.0), cmd);
  EXPECT_THROW(report::apply_play(cmd, -1.0), std::invalid_argument);
}

TEST(Backlash, OnALinearAxisTheTipStepEqualsTheWidth) {
  // trunnion-ac with A = C = 0: the tip is x, y, z plus a constant, so the step is exactly the play.
  const machine::Machine m = machine::load(test::source_path("machines/trunnion-ac.yaml"));
  const auto k = m.kinematics();
  const nc::Program ncp =
      nc::read_text("G0 X0 Y5 Z3 A0 C0\nG1 X10 F100\nG1 X4\nG1 X6\nG0 X50\n", "lin.ngc", letters_of(m));
  const report::SampledPath path = report::sample_nc(ncp, 0, 0.001);
  const report::BacklashResult r = report::simulate_backlash(path, *k, 0, 0.01);
  ASSERT_EQ(r.reversals.size(), 2u);
  EXPECT_TRUE(r.reversals[0].in_feed);
  EXPECT_NEAR(r.reversals[0].tip_mm.x() - r.tip_commanded_mm[0].x(), 10.0, 1e-9);
  EXPECT_NEAR(r.reversals[0].step_mm.x(), 0.01, 1e-9);   // turning down: the output lags above
  EXPECT_NEAR(r.reversals[1].step_mm.x(), -0.01, 1e-9);  // turning up again: back on the command
  EXPECT_NEAR(r.reversals[0].step_mm.y(), 0.0, 1e-12);
  EXPECT_NEAR(r.max_abs_step_mm.x(), 0.01, 1e-9);
  EXPECT_NEAR(r.max_abs_step_mm.z(), 0.0, 1e-12);
  EXPECT_NEAR(r.max_abs_deviation_mm.x(), 0.01, 1e-9);
  EXPECT_EQ(r.max_deviation_nc_line[0], 3);
}

TEST(Backlash, OnTheXminiSeedCutTheQ2StepIsTheJacobianColumnMostlyInY) {
  const machine::Machine m = xmini_machine();
  const auto k = m.kinematics();
  const auto& xk = dynamic_cast<const kin::XminiKinematics&>(*k);
  const nc::Program ncp = nc::read_text(post_text(seed_cut(), m, *k), "seed.ngc", letters_of(m));
  const double w = 0.010;
  const report::BacklashResult r = report::simulate_backlash(report::sample_nc(ncp, 1, w / 10), *k, 1, w);
  std::vector<report::BacklashReversal> cutting;
  for (const auto& v : r.reversals)
    if (v.in_feed) cutting.push_back(v);
  ASSERT_EQ(cutting.size(), 1u);
  const auto& v = cutting[0];
  EXPECT_NEAR(v.tip_mm.x(), 0.0, 0.02) << "the q2 reversal is at the minimum, x = 0";
  // Oracle: the analytic Jacobian. The drive was engaged downward (plunge up, then the cut down), so at
  // the minimum the output jumps from w above the command back onto it: step = -w dtip/dq2.
  kin::XminiWorkspace ws;
  const report::SampledPath path = report::sample_nc(ncp, 1, w / 10);
  const Eigen::Matrix<double, 6, 5> Jt = xk.model().jacobian(path.q[v.begin_sample], ws);
  const Vec3 expected = -w * Jt.block<3, 1>(0, 1);
  EXPECT_NEAR(v.step_mm.y(), expected.y(), 0.02 * std::abs(expected.y()));
  EXPECT_GT(std::abs(v.step_mm.y()), 4.0 * w) << "the PKM amplifies the leg's play at the tip";
  EXPECT_LT(std::abs(v.step_mm.x()), 0.01 * std::abs(v.step_mm.y()));
  EXPECT_LT(std::abs(v.step_mm.z()), 0.01 * std::abs(v.step_mm.y()));
}

TEST(Backlash, CliReportsTheStepPerComponent) {
  const fs::path dir = fs::temp_directory_path() / ("cscam_xmini_backlash_cli_" + std::to_string(::getpid()));
  fs::create_directories(dir);
  const std::string cli = CSCAM_CLI;
  const std::string nc = (dir / "seed.ngc").string();
  const std::string cl = test::source_path("examples/xmini/seed000_x_cut.cls");
  auto r = test::run_command(cli + " post " + cl + " --machine xmini -o " + nc);
  ASSERT_EQ(r.status, 0) << r.output;
  r = test::run_command(cli + " backlash " + nc + " --machine xmini --axis q2 --width-mm 0.010");
  ASSERT_EQ(r.status, 0) << r.output;
  EXPECT_NE(r.output.find("max |step y|"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("max |dz|"), std::string::npos) << r.output;
  r = test::run_command(cli + " backlash " + nc + " --machine xmini --axis q2 --width-mm 0.010 --json");
  ASSERT_EQ(r.status, 0) << r.output;
  EXPECT_NE(r.output.find("\"max_abs_step_mm\""), std::string::npos) << r.output;
  r = test::run_command(cli + " backlash " + nc + " --machine xmini --axis c --width-mm 0.010");
  EXPECT_EQ(r.status, 2) << r.output;
  EXPECT_NE(r.output.find("--width-deg"), std::string::npos) << r.output;
  r = test::run_command(cli + " backlash " + nc + " --machine xmini --axis q9 --width-mm 0.010");
  EXPECT_EQ(r.status, 2) << r.output;
  fs::remove_all(dir);
}

TEST(XminiPost, AVerticalPlungeIsSplitWhereTheLegsWouldBowThePath) {
  // With the wrist fixed a serial machine moves the tip straight; the XMINI's legs, moved linearly, do not. A 48 mm
  // plunge was written as one block and the gate refused it (0.028 mm off the path, 0.003 allowed).
  const auto m = xmini_machine();
  const auto k = m.make_kinematics(m.default_tool_length_mm);
  const cl::Program prog = cl::read_text(
      "UNITS/MM\nMULTAX/ON\nFEDRAT/MMPM,1200\nRAPID\nGOTO/0,0,50,0,0,1\nGOTO/0,0,2,0,0,1\nGOTO/5,0,2,0,0,1\n",
      "plunge.cls");
  // The premise: the joint-space midpoint of the plunge is off the straight path by more than the tolerance.
  const auto axes = post::conventional_axes(prog, m, *k);
  const Vec3 mid = k->forward(0.5 * (axes[0] + axes[1])).tip_mm;
  ASSERT_GT(std::hypot(mid.x(), mid.y()), m.post.tolerance_mm);
  post::Summary sum;
  const std::string text = post_text(prog, m, *k, "", &sum);
  EXPECT_GT(sum.inserted_points, 0u);
  const auto v = verify_text(text, prog, m, *k);
  EXPECT_TRUE(v.ok) << v.message << "\n" << text;
}

// A flip on the XMINI is a retract along the tool axis, a turn and a plunge, each written in pieces (its legs move
// the tip straight only piece by piece). On this random walk (robustness seed 38) the retract from CL line 15 rises
// past other CL points whose axes point elsewhere, and the gate judged its later pieces, which have neither end on
// the path, against those: "below" them, so a cut leaving the path by 2.98 mm, and it refused the program. Every
// piece is now judged against the CL point the retract left from. The oracle, independent of verify: every feed
// block that is off the CL path lies on the tool-axis line of a CL point and above it, and the gate passes.
TEST(XminiPost, APieceWiseRetractIsJudgedFromThePointItLeft) {
  const auto m = machine::load(test::source_path("machines/xmini.yaml"));
  const auto k = m.kinematics();
  cl::ReadOptions ro;
  const auto prog = cl::read_file(test::source_path("tests/data/xmini_random_flip.cls"), ro);
  const auto axes = post::conventional_axes(prog, m, *k);
  std::ostringstream os;
  post::Summary sum;
  post::write_nc(os, prog, m, *k, axes, post::Options{}, sum);
  ASSERT_GE(sum.retracts, 1u);
  const auto ncp = report::read_for_machine(os.str(), "flip.ngc", m);
  int off_path = 0;
  for (std::size_t bi = 1; bi < ncp.blocks.size(); ++bi) {
    const auto& b = ncp.blocks[bi];
    if (b.motion == nc::Motion::Rapid) continue;
    kin::Axes q;
    for (int i = 0; i < 5; ++i) q[i] = b.axes[static_cast<std::size_t>(i)];
    const kin::Posed p = k->forward(q);
    double nearest = 1e9;
    bool on_an_axis_line = false;
    for (std::size_t i = 0; i < prog.moves.size(); ++i) {
      const auto& mv = prog.moves[i];
      const Vec3 d = p.tip_mm - mv.tip_in_part_mm;
      const Vec3 u = mv.axis_in_part.normalized();
      on_an_axis_line = on_an_axis_line || (d.cross(u).norm() < 2e-3 && d.dot(u) > -2e-3 && p.axis.dot(u) > 1 - 1e-8);
      if (i == 0) continue;
      const Vec3 a = prog.moves[i - 1].tip_in_part_mm, ab = mv.tip_in_part_mm - a;
      const double t = ab.squaredNorm() > 0 ? std::clamp((p.tip_mm - a).dot(ab) / ab.squaredNorm(), 0.0, 1.0) : 0.0;
      nearest = std::min(nearest, (a + t * ab - p.tip_mm).norm());
    }
    if (nearest < 0.01) continue;  // on the CL path
    ++off_path;
    EXPECT_TRUE(on_an_axis_line) << "NC line " << b.line << " is off the CL path and on no CL point's axis line";
  }
  EXPECT_GE(off_path, 4);  // the retract and the plunge, in pieces
  const auto gs =
      gate::check(os.str(), "flip.ngc", prog, m, *k, gate::options_for(m, 0, 0, 0), &sum.cl_line_of_nc_line);
  EXPECT_TRUE(gs.ok) << gs.message;
}
