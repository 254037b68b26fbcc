// The conventional post end to end: CL -> IK -> G-code, checked three independent ways:
//  1. LinuxCNC's own interpreter (rs274 -g) accepts the program and moves exactly to the axis values we meant;
//  2. back-simulation by FK inside every block stays within the tolerance of the CL path;
//  3. against NX's post for the same CL (the B/C angles NX chose are IK solutions of ours).
#include "cscam/post/post.hpp"

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <regex>
#include <sstream>

#include "cscam/cl/program.hpp"
#include "cscam/core/error.hpp"
#include "cscam/core/units.hpp"
#include "cscam/machine/machine.hpp"
#include "cscam/nc/reader.hpp"
#include "cscam/report/verify.hpp"
#include "rs274_support.hpp"
#include "test_support.hpp"

using namespace cscam;
using cscam::test::expect_rs274_agrees;
using cscam::test::rs274_moves;
namespace fs = std::filesystem;
using Vec3 = Eigen::Vector3d;

namespace {

machine::Machine load_machine(const std::string& name) {
  return machine::load(test::source_path("machines/" + name + ".yaml"));
}

nc::AxisLetters letters_of(const machine::Machine& m) { return report::axis_letters(m); }

struct Posted {
  std::string text;
  post::Summary summary;
};

Posted post_program(const cl::Program& prog, const machine::Machine& m, const kin::Kinematics& k,
                    bool linearise = true) {
  const auto axes = post::conventional_axes(prog, m, k);
  std::ostringstream os;
  post::Options o;
  o.linearise = linearise;
  Posted p;
  post::write_nc(os, prog, m, k, axes, o, p.summary);
  p.text = os.str();
  return p;
}

report::VerifyResult verify_text(const std::string& text, const cl::Program& prog, const machine::Machine& m,
                                 const kin::Kinematics& k) {
  const nc::Program ncp = nc::read_text(text, "posted.ngc", letters_of(m));
  report::VerifyOptions vo;
  vo.tip_tolerance_mm = m.post.tolerance_mm + 0.002;  // printed decimals add a little rounding
  vo.axis_tolerance_deg = m.post.axis_tolerance_deg + 0.01;
  vo.samples_per_block = 16;
  return report::verify(ncp, prog, k, vo);
}

/// A smooth variable-axis raster over a saddle; tool axis tilts up to `max_tilt_deg` from +Z.
std::string synthetic_cl(double max_tilt_deg, int rows, int cols, double z0) {
  std::ostringstream o;
  o << "PARTNO SYNTH\nUNITS/MM\nMULTAX/ON\nCUTTER/6,3\nLOADTL/1\nSPINDL/6000,CLW\nCOOLNT/ON\nFEDRAT/MMPM,1500\n";
  const double t = deg2rad(max_tilt_deg);
  for (int r = 0; r < rows; ++r) {
    o << "RAPID\n";
    for (int c = 0; c < cols; ++c) {
      const int cc = r % 2 ? cols - 1 - c : c;
      const double u = -1.0 + 2.0 * cc / (cols - 1), v = -1.0 + 2.0 * r / std::max(1, rows - 1);
      const double x = 40 * u, y = 40 * v, z = z0 + 5 * (u * u - v * v);
      const double ti = std::sin(t * u), tj = std::sin(0.7 * t * v);
      const Vec3 n = Vec3(ti, tj, 1.0).normalized();
      o << "GOTO/" << x << "," << y << "," << z << "," << n.x() << "," << n.y() << "," << n.z() << "\n";
    }
  }
  o << "COOLNT/OFF\nSPINDL/OFF\nFINI\n";
  return o.str();
}

}  // namespace

TEST(Post, EveryMachineSyntheticPathIsAcceptedByRs274AndVerifies) {
  for (const char* name : {"trunnion-ac", "haas-umc750", "head-table-bc45", "head-head-ac"}) {
    SCOPED_TRACE(name);
    const auto m = load_machine(name);
    const auto k = m.kinematics();
    const cl::Program prog = cl::read_text(synthetic_cl(30.0, 6, 40, 10.0), std::string(name) + ".cls");
    const Posted p = post_program(prog, m, *k);
    expect_rs274_agrees(p.text, m, name);
    const auto v = verify_text(p.text, prog, m, *k);
    EXPECT_TRUE(v.ok) << v.message;
    EXPECT_LE(p.summary.max_checked_tip_deviation_mm, 1e9);
  }
}

TEST(Post, LinearisationIsWhatKeepsTheTipOnTheCLPath) {
  const auto m = load_machine("trunnion-ac");
  const auto k = m.kinematics();
  // Far from the rotary centre, a 30-degree swing between two CL points throws the tip off the chord.
  const cl::Program prog = cl::read_text(
      "UNITS/MM\nMULTAX\nFEDRAT/MMPM,1000\nRAPID\nGOTO/100,50,20,0,0,1\nGOTO/110,50,20,0.5,0,0.8660254\n"
      "GOTO/120,50,20,0,0.5,0.8660254\n",
      "swing.cls");
  const Posted with = post_program(prog, m, *k, true);
  const Posted without = post_program(prog, m, *k, false);
  EXPECT_GT(with.summary.inserted_points, 5u);
  const auto good = verify_text(with.text, prog, m, *k);
  EXPECT_TRUE(good.ok) << good.message;
  const auto bad = verify_text(without.text, prog, m, *k);
  EXPECT_FALSE(bad.ok) << "without linearisation the tip must leave the tolerance: " << bad.message;
  EXPECT_GT(bad.max_tip_deviation_mm, 1.0);
  expect_rs274_agrees(with.text, m, "swing");
}

TEST(Post, RealNxFilesConvertAndVerifyOnHaas) {
  const auto m = load_machine("haas-umc750");
  const auto k = m.kinematics();
  for (const char* f : {"variable_axis.cls", "zigzag_smoothed.cls"}) {
    SCOPED_TRACE(f);
    const cl::Program prog = cl::read_file(test::source_path(std::string("examples/nx-haas-umc750/") + f));
    const Posted p = post_program(prog, m, *k);
    expect_rs274_agrees(p.text, m, f);
    const auto v = verify_text(p.text, prog, m, *k);
    EXPECT_TRUE(v.ok) << v.message;
  }
}

TEST(Post, HaasAxisSensesReproduceNxPostAngles) {
  // NX's HAAS_UMC750 post printed "B-22.201 C1.05" for the first CL axis (-0.3778015,-0.0069217,0.9258607),
  // and B/C for the following points. Our IK must have these among its solutions (C modulo 360).
  const auto m = load_machine("haas-umc750");
  const auto k = m.kinematics();
  const cl::Program prog = cl::read_file(test::source_path("examples/nx-haas-umc750/variable_axis.cls"));
  const nc::Program nx =
      nc::read_file(test::source_path("examples/nx-haas-umc750/variable_axis.nx-post.nc"), letters_of(m));
  // Pair CL points and NX blocks by their (part-frame, TCPC) tip positions.
  int matched = 0;
  std::vector<kin::Solution> sols;
  for (const auto& b : nx.blocks) {
    const Vec3 tip(b.axes[0], b.axes[1], b.axes[2]);
    for (const auto& mv : prog.moves) {
      if ((mv.tip_in_part_mm - tip).norm() > 1e-3) continue;
      k->inverse_branches(kin::Posed{mv.tip_in_part_mm, mv.axis_in_part}, nullptr, sols);
      bool found = false;
      for (const auto& s : sols) {
        const double db = rad2deg(s.axes[3]) - rad2deg(b.axes[3]);
        const double dc = std::remainder(rad2deg(s.axes[4]) - rad2deg(b.axes[4]), 360.0);
        // NX prints 3 decimals of degrees.
        found |= std::abs(db) < 2e-3 && std::abs(dc) < 2e-3 + (std::abs(s.axes[3]) < 0.02 ? 1.0 : 0.0);
      }
      EXPECT_TRUE(found) << "NX line " << b.line;
      ++matched;
      break;
    }
  }
  EXPECT_GT(matched, 200);
}

TEST(Post, PointOutsideTheLimitsNamesTheClLine) {
  const auto m = load_machine("trunnion-ac");
  const auto k = m.kinematics();
  // A tool axis tilted 80 deg toward -Y needs A beyond its +50 deg limit on one branch and beyond -100 on none;
  // 2000 mm out in X is beyond the X stroke on every branch.
  const cl::Program prog = cl::read_text("UNITS/MM\nMULTAX\nGOTO/0,0,0,0,0,1\nGOTO/2000,0,0,0,0,1\n", "far.cls");
  try {
    post::conventional_axes(prog, m, *k);
    FAIL() << "expected an InputError";
  } catch (const InputError& e) {
    const std::string msg = e.what();
    EXPECT_NE(msg.find("far.cls:4"), std::string::npos) << msg;
    EXPECT_NE(msg.find("x = "), std::string::npos) << msg;
  }
}
