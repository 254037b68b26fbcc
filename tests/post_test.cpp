// The conventional post end to end: CL -> IK -> G-code, checked three independent ways:
//  1. LinuxCNC's own interpreter (rs274 -g) accepts the program and moves exactly to the axis values we meant;
//  2. back-simulation by FK inside every block stays within the tolerance of the CL path;
//  3. against NX's post for the same CL (the B/C angles NX chose are IK solutions of ours).
#include "cscam/post/post.hpp"

#include <fmt/format.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <limits>
#include <map>
#include <nlohmann/json.hpp>
#include <optional>
#include <random>
#include <regex>
#include <sstream>
#include <tuple>

#include "../src/post/linearize.hpp"
#include "cscam/cl/program.hpp"
#include "cscam/core/error.hpp"
#include "cscam/core/tolerances.hpp"
#include "cscam/core/units.hpp"
#include "cscam/gate/gate.hpp"
#include "cscam/kin/track.hpp"
#include "cscam/machine/machine.hpp"
#include "cscam/nc/reader.hpp"
#include "cscam/report/letters.hpp"
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

machine::Machine load_machine(const std::string& name) {
  return machine::load(test::source_path("machines/" + name + ".yaml"));
}

nc::AxisLetters letters_of(const machine::Machine& m) { return report::axis_letters(m); }

struct Posted {
  std::string text;
  post::Summary summary;
};

Posted post_program(const cl::Program& prog, const machine::Machine& m, const kin::Kinematics& k, bool linearise = true,
                    std::optional<bool> tcp = std::nullopt, const std::string& dialect = "") {
  const auto axes = post::conventional_axes(prog, m, k);
  std::ostringstream os;
  post::Options o;
  o.linearise = linearise;
  o.tcp = tcp;
  o.dialect = dialect;
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

// A path that runs along a rotary limit: the trunnion's A reaches +50 deg (its limit) at two points, whose tool vectors
// lie past it by `past_deg`, as a CL's rounded vector does. A point 3.4e-6 deg past the limit made the post retract and
// flip both rotaries half a turn, and back. Within tol::kLimitSnapDeg the point is cut at the limit, straight through;
// the control, 0.01 deg past, is beyond it and still flips (the machine cannot reach that axis on this branch).
TEST(Post, APointPastARotaryLimitByRoundingIsCutAtTheLimitNotFlipped) {
  const auto m = load_machine("trunnion-ac");
  const auto k = m.kinematics();
  for (const double past_deg : {3.4e-6, 5e-4, 0.01}) {
    std::ostringstream cl;
    cl.precision(12);
    cl << "UNITS/MM\nMULTAX\nCUTTER/10,0\nFEDRAT/MMPM,800\nRAPID\n";
    const std::array<double, 8> tilt_deg = {45, 47, 49, 50 + past_deg, 50 + past_deg, 49, 47, 45};
    for (std::size_t i = 0; i < tilt_deg.size(); ++i) {
      const double t = deg2rad(tilt_deg[i]);
      const Vec3 u(0.0, std::sin(t), std::cos(t));
      const Vec3 tip(-20.0 + 5.0 * static_cast<double>(i), 0.0, 60.0);
      if (i == 0)
        cl << "GOTO/" << tip.x() << "," << tip.y() + 20 * u.y() << "," << tip.z() + 20 * u.z() << ",0," << u.y() << ","
           << u.z() << "\n";
      cl << "GOTO/" << tip.x() << "," << tip.y() << "," << tip.z() << ",0," << u.y() << "," << u.z() << "\n";
    }
    const cl::Program prog = cl::read_text(cl.str(), "along_limit.cls");
    const Posted p = post_program(prog, m, *k);
    const bool snapped = past_deg <= tol::kLimitSnapDeg;
    EXPECT_EQ(p.summary.retracts, snapped ? 0u : 1u) << past_deg << "\n" << p.text;
    if (snapped) {
      EXPECT_NE(p.text.find("A50.0000"), std::string::npos) << p.text;
      EXPECT_EQ(p.text.find("A-"), std::string::npos) << p.text;  // never on the flipped branch
    }
    // The oracle: back-simulation of the text against the CL (tip and axis, every block sampled).
    const auto v = verify_text(p.text, prog, m, *k);
    EXPECT_TRUE(v.ok) << past_deg << ": " << v.message;
    EXPECT_LE(v.max_axis_deviation_deg, m.post.axis_tolerance_deg);
  }
}

// On a machine whose head carries a rotary, machine coordinates depend on the tool length: a second tool 60 mm longer
// was posted with the first one's length (its tip 60 mm away, and the gate, told one length, passed it). Tools of
// different lengths are refused without TCP, naming the tool change; one length, or TCP, is posted. The oracle for the
// posted one: FK with each tool's own length reaches its CL points.
TEST(Post, ToolsOfDifferentLengthsOnARotaryHeadNeedTcp) {
  const auto m = load_machine("head-head-ac");
  auto cl_text = [](double second_mm) {
    return fmt::format(
        "UNITS/MM\nMULTAX/ON\nTLDATA/MILL,10,0,80,0,0\nLOAD/TOOL,1\nFEDRAT/500,MMPM\nGOTO/0,0,10,0.5,0,0.8660254\n"
        "GOTO/20,0,10,0.5,0,0.8660254\nTLDATA/MILL,6,0,{},0,0\nLOAD/TOOL,2\nGOTO/0,10,10,0.5,0,0.8660254\n"
        "GOTO/20,10,10,0.5,0,0.8660254\n",
        second_mm);
  };
  auto post_with = [&](const cl::Program& prog, std::optional<bool> tcp) {
    std::string note;
    const double L = post::tool_length_for(m, 0, prog, note);
    const auto k = m.make_kinematics(L);
    post::Options o;
    o.tcp = tcp;
    o.tool_length_mm = L;
    post::Summary sum;
    std::ostringstream os;
    post::write_nc(os, prog, m, *k, post::conventional_axes(prog, m, *k), o, sum);
    return os.str();
  };
  const cl::Program mixed = cl::read_text(cl_text(140), "two.cls");
  try {
    post_with(mixed, false);
    FAIL() << "tools of 80 and 140 mm were posted in machine coordinates";
  } catch (const InputError& e) {
    EXPECT_EQ(e.where().line, 8) << e.what();
    EXPECT_NE(std::string(e.what()).find("--tcp"), std::string::npos) << e.what();
  }
  EXPECT_NO_THROW(post_with(mixed, true));
  const cl::Program same = cl::read_text(cl_text(80), "two.cls");
  const std::string text = post_with(same, false);
  const auto k80 = m.make_kinematics(80);
  const nc::Program nc = nc::read_text(text, "two.ngc", report::axis_letters(m));
  double worst = 0.0;
  for (const auto& mv : same.moves) {
    double best = std::numeric_limits<double>::infinity();
    for (const auto& b : nc.blocks) {
      kin::Axes q;
      for (int j = 0; j < 5; ++j) q[j] = b.axes[static_cast<size_t>(j)];
      best = std::min(best, (k80->forward(q).tip_mm - mv.tip_in_part_mm).norm());
    }
    worst = std::max(worst, best);
  }
  EXPECT_LT(worst, tol::kLinearisationMm) << text;
}

// A part taller than the machine file's safe Z (250 mm on the trunnion), cut at Z 270 from the CL's own clearance at
// 290: the post went down to "safe" Z 250 first and travelled there, through the part; between two cuts it "retracted"
// down to it. The tool now goes up to the safe Z, never down to it. The oracle: the Z word of every block, read back.
TEST(Post, APartTallerThanTheSafeZIsNeverEnteredByARetract) {
  const auto m = load_machine("trunnion-ac");
  const auto k = m.make_kinematics(0);
  std::string cl = "UNITS/MM\nMULTAX/ON\nFEDRAT/MMPM,800\n";
  for (const double y : {0.0, 20.0}) {
    cl += fmt::format("RAPID\nGOTO/-10,{0},290,0,0,1\nGOTO/-10,{0},270,0,0,1\nGOTO/10,{0},270,0,0,1\n", y);
    cl += fmt::format("RAPID\nGOTO/10,{},290,0,0,1\n", y);
  }
  const cl::Program prog = cl::read_text(cl, "tall.cls");
  post::Options o;
  post::Summary sum;
  std::ostringstream os;
  post::write_nc(os, prog, m, *k, post::conventional_axes(prog, m, *k), o, sum);
  const nc::Program nc = nc::read_text(os.str(), "tall.ngc", report::axis_letters(m));
  const int z = m.axis_index("z");
  double lowest = std::numeric_limits<double>::infinity();
  for (const auto& b : nc.blocks) lowest = std::min(lowest, b.axes[static_cast<size_t>(z)]);
  EXPECT_GE(lowest, 270.0 - 1e-9) << os.str();
}

// A reorientation at a fixed tip out of the vertical, with repeated CL points, on the 45-degree head under TCP: the
// linearizer's split tracked the midpoint from the vertical, where C turns freely, saw a jump, and wrote the whole
// turn as one block (0.67 deg off the CL's great circle); the gate refused the program. The midpoint is now tracked
// from the end's branch. The oracle: every block's axis, sampled through its rotary words, against the great circle
// between the CL axes (brute force), with and without TCP.
TEST(Post, AReorientationOutOfTheVerticalUnderTcpIsSplitOnTheEndsBranch) {
  const auto m = load_machine("head-table-bc45");
  const auto k = m.make_kinematics(post::tool_length_for(m, 0));
  const cl::Program prog = cl::read_text(
      "UNITS/MM\nMULTAX/ON\nFEDRAT/1200,MMPM\nRAPID\nGOTO/0,0,20,0,0,1\nGOTO/0,0,0,0,0,1\nGOTO/0,0,0,0,0,1\n"
      "GOTO/0,0,0,0.2955202,0,0.9553365\nGOTO/0,0,0,0.2955202,0,0.9553365\nGOTO/0,0,0,0.1596702,0.2486717,0.9553365\n",
      "turn.cls");
  std::vector<Eigen::Vector3d> arc;  // the CL axes' great circles, finely
  for (std::size_t i = 1; i < prog.moves.size(); ++i) {
    const Eigen::Vector3d a = prog.moves[i - 1].axis_in_part.normalized(), b = prog.moves[i].axis_in_part.normalized();
    const double th = std::acos(std::clamp(a.dot(b), -1.0, 1.0));
    for (int s = 0; s <= 2000; ++s) {
      const double t = s / 2000.0;
      arc.push_back(th < 1e-12 ? a : ((std::sin((1 - t) * th) * a + std::sin(t * th) * b) / std::sin(th)).normalized());
    }
  }
  for (const bool tcp : {false, true}) {
    post::Options o;
    o.tcp = tcp;
    post::Summary sum;
    std::ostringstream os;
    post::write_nc(os, prog, m, *k, post::conventional_axes(prog, m, *k), o, sum);
    const auto g =
        gate::check(os.str(), "turn.ngc", prog, m, *k, gate::options_for(m, 0, 0, 0), &sum.cl_line_of_nc_line);
    EXPECT_TRUE(g.ok) << (tcp ? "tcp: " : "") << g.message << "\n" << os.str();
    const nc::Program nc = nc::read_text(os.str(), "turn.ngc", report::axis_letters(m));
    const auto rp = k->rotary_pair();
    double worst = 0.0;
    for (std::size_t i = 1; i < nc.blocks.size(); ++i) {
      if (nc.blocks[i].motion != nc::Motion::Linear) continue;
      for (int s = 0; s <= 20; ++s) {
        kin::Axes q = kin::Axes::Zero();
        for (const int r : rp)
          q[r] = nc.blocks[i - 1].axes[static_cast<size_t>(r)] +
                 s / 20.0 * (nc.blocks[i].axes[static_cast<size_t>(r)] - nc.blocks[i - 1].axes[static_cast<size_t>(r)]);
        const Eigen::Vector3d u = k->forward(q).axis.normalized();
        double best = 180.0;
        for (const auto& c : arc) best = std::min(best, rad2deg(std::acos(std::clamp(c.dot(u), -1.0, 1.0))));
        worst = std::max(worst, best);
      }
    }
    EXPECT_LE(worst, gate::options_for(m, 0, 0, 0).axis_tolerance_deg) << (tcp ? "tcp\n" : "") << os.str();
  }
}

// Under TCP with angle words the control puts the rotaries at the words. The post (and the gate) took them to be the
// IK solution nearest the control's last state, which out of the vertical (C free) or after a flip is another winding:
// the first block was slowed 7 to 13 times for a swing that never happens (a dwell mark). The oracle: the machine axes
// from the words (rotaries as written, linear axes from the tip), and each block's F at least the programmed feed or
// the fastest one no axis's max_feed forbids, whichever is lower.
TEST(Post, TcpFeedsAreSlowedOnlyForTheMotionTheControlMakes) {
  std::string cl = "UNITS/INCHES\nMULTAX/ON\nFEDRAT/IPM,40\nRAPID\nGOTO/0,0,2,0,0,1\nGOTO/0,1,0.2,0,0,1\n";
  for (int k = 1; k <= 10; ++k) {
    const double th = deg2rad(0.51 * k);
    cl += fmt::format("GOTO/{},1,0.2,0,{},{}\n", 0.05 * k, -std::sin(th), std::cos(th));
  }
  const cl::Program prog = cl::read_text(cl, "tilt.cls");
  for (const std::string name : {"haas-umc750", "head-table-bc45"}) {
    const auto m = load_machine(name);
    const auto k = m.make_kinematics(post::tool_length_for(m, 0));
    post::Options o;
    o.tcp = true;
    o.dialect = "fanuc";
    post::Summary sum;
    std::ostringstream os;
    post::write_nc(os, prog, m, *k, post::conventional_axes(prog, m, *k), o, sum);
    const auto g = gate::check(os.str(), "t.ngc", prog, m, *k, gate::options_for(m, 0, 0, 0), &sum.cl_line_of_nc_line);
    EXPECT_TRUE(g.ok) << name << ": " << g.message;
    const nc::Program nc = nc::read_text(os.str(), "t.ngc", report::axis_letters(m));
    const auto rp = k->rotary_pair();
    auto joints = [&](const nc::Block& b) {
      kin::Axes q;
      for (int j = 0; j < 5; ++j) q[j] = b.axes[static_cast<size_t>(j)];
      Eigen::Vector3d tip, axis;
      int n = 0;
      for (int j = 0; j < 5; ++j)
        if (j != rp[0] && j != rp[1]) tip[n++] = q[j];
      EXPECT_TRUE(k->tool_axis_at(q[rp[0]], q[rp[1]], tip, axis));
      EXPECT_TRUE(k->solve_for_rotaries(kin::Posed{tip, axis}, q));
      return std::make_pair(q, tip);
    };
    for (std::size_t i = 1; i < nc.blocks.size(); ++i) {
      const auto& b = nc.blocks[i];
      if (b.motion != nc::Motion::Linear || !b.tcp || !nc.blocks[i - 1].tcp) continue;
      const auto [qa, ta] = joints(nc.blocks[i - 1]);
      const auto [qb, tb] = joints(b);
      const double len = (tb - ta).norm();
      if (len < 1e-6) continue;
      double need = std::numeric_limits<double>::infinity();
      for (int j = 0; j < 5; ++j) {
        const double d =
            m.axes[static_cast<size_t>(j)].rotary() ? rad2deg(std::abs(qb[j] - qa[j])) : std::abs(qb[j] - qa[j]);
        if (d > 1e-12) need = std::min(need, m.axes[static_cast<size_t>(j)].max_feed * len / d);
      }
      EXPECT_GE(b.feed, std::min(1016.0, need) * (1 - 1e-3)) << name << " NC line " << b.line << "\n" << os.str();
    }
  }
}

TEST(Post, APlannedSegmentBesideTheSingularAxisIsJudgedByItsConeNotByTheSlerpOfItsAxes) {
  // Planned (A, C) = (-2, 96) -> (+2, 78) deg on the trunnion: the machine's joint interpolation passes through the
  // vertical, while the slerp of the two planned axes (198 deg apart in azimuth) passes 0.31 deg beside it, just
  // beyond the 0.3 deg axis tolerance, where following it needs C to swing half a turn. Both lie within a 10 deg
  // cone of the CL's vertical axis. Found on NX's variable_axis path planned at cone 10 (CL lines 36-37).
  const auto m = load_machine("trunnion-ac");
  const auto k = m.kinematics();
  const auto rp = k->rotary_pair();
  const double ball_mm = 3.0;
  const std::array<Vec3, 2> centre = {Vec3(30, 10, 5), Vec3(31, 10, 5)};
  const std::array<std::array<double, 2>, 2> ac = {{{-2.0, 96.0}, {2.0, 78.0}}};
  cl::Program cl_prog, planned;
  cl_prog.file = planned.file = "beside_pole.cls";
  cl::Tool ball;
  ball.number = 1;
  ball.diameter_mm = 2 * ball_mm;
  ball.corner_radius_mm = ball_mm;
  cl_prog.tools = planned.tools = {ball};
  std::vector<kin::Axes> axes;
  for (int i = 0; i < 2; ++i) {
    kin::Axes q = kin::Axes::Zero();
    q[rp[0]] = deg2rad(ac[static_cast<size_t>(i)][1]);  // the primary rotary is C
    q[rp[1]] = deg2rad(ac[static_cast<size_t>(i)][0]);
    Vec3 u;
    ASSERT_TRUE(k->tool_axis_at(q[rp[0]], q[rp[1]], centre[static_cast<size_t>(i)], u));
    const Vec3 tip = centre[static_cast<size_t>(i)] - ball_mm * u;
    ASSERT_TRUE(k->solve_for_rotaries(kin::Posed{tip, u}, q));
    ASSERT_LT((k->forward(q).tip_mm - tip).norm(), 1e-9);
    cl::Move mv;
    mv.kind = i == 0 ? cl::MotionKind::Rapid : cl::MotionKind::Feed;
    mv.feed_mm_per_min = i == 0 ? 0.0 : 1000.0;
    mv.line = 36 + i;
    mv.tool_index = 0;
    mv.tip_in_part_mm = tip;
    mv.axis_in_part = u;
    planned.moves.push_back(mv);
    mv.tip_in_part_mm = centre[static_cast<size_t>(i)] - ball_mm * Vec3::UnitZ();
    mv.axis_in_part = Vec3::UnitZ();
    cl_prog.moves.push_back(mv);
    axes.push_back(q);
  }
  post::Options o;
  o.strategy = "cspace-planner";
  o.control_offset_mm = ball_mm;
  post::Summary sum;
  auto post = [&](const post::Options& opt) {
    std::ostringstream os;
    sum = post::Summary{};
    post::write_nc(os, planned, m, *k, axes, opt, sum);
    return os.str();
  };
  // The premise: judged by the slerp of the planned axes alone, the segment cannot be followed on one branch: the post
  // turns the rotaries with a retract (before it knew the rotaries must change branch there, it refused the cut).
  post(o);
  EXPECT_EQ(sum.retracts, 1u);
  o.cone_deg = 10.0;
  o.cone_reference = &cl_prog;
  const std::string text = post(o);
  EXPECT_EQ(sum.retracts, 0u);  // judged by its cone, it is cut straight through
  // The oracle: the independent back-simulation, against the CL within the cone (ball centre on the path).
  const nc::Program ncp = nc::read_text(text, "beside_pole.ngc", letters_of(m));
  const auto v = report::verify(ncp, cl_prog, *k, report::verify_options_for(m, 0.0, 0.0, o.cone_deg));
  EXPECT_TRUE(v.ok) << v.message << "\n" << text;
  EXPECT_LE(v.max_axis_deviation_deg, 2.0 + m.post.axis_tolerance_deg) << text;
  expect_rs274_agrees(text, m, "beside_pole");
}

TEST(Post, AnUnwindNeitherEndOfWhichReachesTheOtherTurnsAtBothPoints) {
  // The head's C has limits of +-360 deg. Between two points 42 deg of azimuth apart, the axes come at C 341 and at
  // C -337 (23 deg one turn down): q0's winding would pass +360 on the way to the second point and q1's winding
  // -360 on the way back to the first, so no single turn at either point can be followed by a continuous cut. The
  // post once turned to the nearest solution and then refused the cut ("the rotaries must change IK branch").
  const auto m = load_machine("head-head-ac");
  const auto k = m.kinematics();
  const auto rp = k->rotary_pair();
  const std::array<double, 2> c_deg = {341.0, -337.0};
  const std::array<Vec3, 2> tip = {Vec3(10, -8, 19), Vec3(11, -8, 19)};
  cl::Program prog;
  prog.file = "unwind.cls";
  std::vector<kin::Axes> axes;
  std::array<kin::Posed, 2> pose;
  for (std::size_t i = 0; i < 2; ++i) {
    kin::Axes q = kin::Axes::Zero();
    q[rp[0]] = deg2rad(c_deg[i]);
    q[rp[1]] = deg2rad(15.0);
    Vec3 u;
    ASSERT_TRUE(k->tool_axis_at(q[rp[0]], q[rp[1]], tip[i], u));
    ASSERT_TRUE(k->solve_for_rotaries(kin::Posed{tip[i], u}, q));
    ASSERT_TRUE(k->check_limits(q).empty()) << k->check_limits(q);
    pose[i] = kin::Posed{tip[i], u};
    cl::Move mv;
    mv.kind = i == 0 ? cl::MotionKind::Rapid : cl::MotionKind::Feed;
    mv.feed_mm_per_min = 1000.0;
    mv.line = 10 + static_cast<int>(i);
    mv.tip_in_part_mm = tip[i];
    mv.axis_in_part = u;
    prog.moves.push_back(mv);
    axes.push_back(q);
  }
  // The premise: neither winding runs to the other point inside the limits.
  kin::Axes tracked;
  bool jumped = false;
  EXPECT_TRUE(!kin::track_checked(*k, axes[0], pose[0], pose[1], tracked, jumped) || jumped);
  jumped = false;
  EXPECT_TRUE(!kin::track_checked(*k, axes[1], pose[1], pose[0], tracked, jumped) || jumped);
  std::ostringstream os;
  post::Summary sum;
  post::write_nc(os, prog, m, *k, axes, post::Options{}, sum);
  EXPECT_EQ(sum.retracts + sum.reorientations, 2u) << os.str();
  // The oracle: the back-simulation reaches both points on the path (the turns are retract, turn, plunge).
  const auto v = verify_text(os.str(), prog, m, *k);
  EXPECT_TRUE(v.ok) << v.message << "\n" << os.str();
  expect_rs274_agrees(os.str(), m, "unwind");
}

TEST(Post, SlerpBestDotIsTheNearestPointOfTheStretchOfTheArc) {
  // Oracle: the largest dot product over 20001 evenly spaced points of the stretch.
  std::mt19937_64 rng(test::kSeed);
  std::normal_distribution<double> g;
  std::uniform_real_distribution<double> uni(0.0, 1.0);
  auto unit = [&] { return Vec3(g(rng), g(rng), g(rng)).normalized(); };
  for (int trial = 0; trial < 200; ++trial) {
    const Vec3 a = unit(), u = unit();
    // Arcs from a fraction of a degree to nearly half a turn.
    const Vec3 b = trial % 2 ? (a + 0.01 * unit()).normalized() : unit();
    const post::Slerp arc(a, b);
    double lo = uni(rng), hi = uni(rng);
    if (lo > hi) std::swap(lo, hi);
    double best = -2.0;
    for (int i = 0; i <= 20000; ++i) best = std::max(best, u.dot(arc(lo + (hi - lo) * i / 20000.0)));
    EXPECT_NEAR(arc.best_dot(u, lo, hi), best, 1e-7) << "trial " << trial;
    EXPECT_GE(arc.best_dot(u, lo, hi), best - 1e-12) << "trial " << trial;
  }
}

// --- LinuxCNC ------------------------------------------------------------------------------------------

/// LinuxCNC's xyzac-trt-kins forward map (src/emc/kinematics/trtfuncs.c, xyzacKinematicsForward), written out
/// here as the oracle: joints (machine X Y Z, A C in degrees) to world coordinates, with the sample config's
/// pins y-offset 20, z-offset 10, rot-points 0 and tool-offset dt.
Vec3 linuxcnc_xyzac_world(const kin::Axes& j, double dt) {
  const double x_rot = 0, y_rot = 0, z_rot = 0, dy = 20, dz = 10 + dt;
  const double a = j[3], c = j[4];
  return {std::cos(c) * (j[0] - x_rot) + std::sin(c) * std::cos(a) * (j[1] - dy - y_rot) +
              std::sin(c) * std::sin(a) * (j[2] - dz - z_rot) + std::sin(c) * dy + x_rot,
          -std::sin(c) * (j[0] - x_rot) + std::cos(c) * std::cos(a) * (j[1] - dy - y_rot) +
              std::cos(c) * std::sin(a) * (j[2] - dz - z_rot) + std::cos(c) * dy + y_rot,
          -std::sin(a) * (j[1] - dy - y_rot) + std::cos(a) * (j[2] - dz - z_rot) + dz + z_rot};
}

TEST(PostLinuxcnc, TrunnionAcModelIsLinuxcncXyzacTrtKins) {
  // The TCP words are LinuxCNC's world coordinates only if our trunnion-ac model is its kinematics: the tip our
  // FK gives for random joints must be the world position of trtfuncs.c (tool offset 0: the tip is the gauge).
  const auto m = load_machine("trunnion-ac");
  const auto k = m.kinematics();
  std::mt19937 rng(42);
  std::uniform_real_distribution<double> lin(-200, 200), a(deg2rad(-100), deg2rad(50)), c(-7, 7);
  for (int i = 0; i < 200; ++i) {
    kin::Axes q;
    q << lin(rng), lin(rng), lin(rng), a(rng), c(rng);
    const Vec3 ours = k->forward(q).tip_mm;
    const Vec3 theirs = linuxcnc_xyzac_world(q, 0.0);
    ASSERT_LT((ours - theirs).norm(), 1e-9) << "joints " << q.transpose();
  }
}

TEST(PostLinuxcnc, MachineCoordinatesCarryG64PAtTheTolerance) {
  const auto m = load_machine("trunnion-ac");
  const auto k = m.kinematics();
  const cl::Program prog = cl::read_text(synthetic_cl(30.0, 4, 30, 10.0), "g64.cls");
  const Posted p = post_program(prog, m, *k, true, false);
  EXPECT_NE(p.text.find(fmt::format("G64 P{:.4f}\n", m.post.tolerance_mm)), std::string::npos) << p.text.substr(0, 400);
  EXPECT_EQ(p.text.find("M428"), std::string::npos);
  std::string log;
  const auto moves = rs274_moves(p.text, "g64", log);
  EXPECT_NE(log.find(fmt::format("SET_MOTION_CONTROL_MODE(CANON_CONTINUOUS, {:.6f})", m.post.tolerance_mm)),
            std::string::npos)
      << log.substr(0, 3000);
  expect_rs274_agrees(p.text, m, "g64");
}

TEST(PostLinuxcnc, TcpFormSwitchesTheTrunnionKinematicsAndVerifies) {
  const auto m = load_machine("trunnion-ac");
  const auto k = m.kinematics();
  const cl::Program prog = cl::read_text(synthetic_cl(30.0, 4, 30, 10.0), "tcp.cls");
  const Posted p = post_program(prog, m, *k, true, true);
  const size_t on = p.text.find("\nM428"), off = p.text.find("\nM429"), first_move = p.text.find("\nG0");
  ASSERT_NE(on, std::string::npos) << p.text.substr(0, 600);
  ASSERT_NE(off, std::string::npos);
  EXPECT_LT(on, first_move);  // world coordinates before the first move
  EXPECT_GT(off, p.text.rfind("\nG1"));
  EXPECT_EQ(p.text.find("G43.4"), std::string::npos) << "LinuxCNC's rs274 rejects G43.4";
  // rs274 with the M428/M429 remaps of the sample config accepts it and moves to our words.
  std::string log;
  rs274_moves(p.text, "tcp", log, "tests/data/linuxcnc");
  EXPECT_NE(log.find("SET_AUX_OUTPUT_VALUE(3,1.000000)"), std::string::npos) << log.substr(0, 3000);
  expect_rs274_agrees(p.text, m, "tcp", "tests/data/linuxcnc");
  // Every block's words are the tip (part frame) of the CL point: each CL point appears as a block.
  const nc::Program ncp = nc::read_text(p.text, "tcp.ngc", letters_of(m));
  EXPECT_TRUE(ncp.tcp);
  size_t found = 0;
  for (const auto& mv : prog.moves)
    for (const auto& b : ncp.blocks)
      if ((Vec3(b.axes[0], b.axes[1], b.axes[2]) - mv.tip_in_part_mm).norm() < 1e-4) {
        ++found;
        break;
      }
  EXPECT_EQ(found, prog.moves.size());
  // The safety gate reads it as TCP: IK of the tip and rotary words, limits, feeds and the path.
  const auto gs = gate::check(p.text, "tcp.ngc", prog, m, *k, gate::options_for(m, 0, 0, 0));
  EXPECT_TRUE(gs.ok) << gs.message;
  EXPECT_TRUE(gs.tool_tip_control);
}

// --- Dialects -----------------------------------------------------------------------------------------

namespace {

/// The machine file `name` with extra post settings appended under `post:` (same folder: relative paths hold).
machine::Machine machine_with_post(const std::string& name, const std::string& extra_post_lines) {
  std::ifstream in(test::source_path("machines/" + name + ".yaml"));
  std::stringstream ss;
  ss << in.rdbuf();
  std::string text = ss.str();
  const size_t p = text.find("\npost:\n");
  EXPECT_NE(p, std::string::npos);
  text.insert(p + 7, extra_post_lines);
  return machine::load_text(text, test::source_path("machines/" + name + "-variant.yaml"));
}

/// Every CL point is reached by some block: its words read back (FK of the machine axes, or the tip words and
/// tool vector under tool-tip control) give the CL tip and axis within the tolerance. Independent of verify.
void expect_every_cl_point_reached(const std::string& text, const cl::Program& prog, const machine::Machine& m,
                                   const kin::Kinematics& k, const std::string& tag) {
  nc::Program ncp = report::read_for_machine(text, tag, m);
  ASSERT_EQ(report::resolve_tool_vectors(ncp, k), "");
  const bool tcp = report::uses_tool_tip_control(text);
  ASSERT_EQ(tcp, ncp.tcp) << tag;
  std::vector<kin::Posed> poses;
  for (const auto& b : ncp.blocks) {
    if (!std::all_of(b.known.begin(), b.known.end(), [](bool x) { return x; })) continue;
    kin::Axes q;
    for (int i = 0; i < 5; ++i) q[i] = b.axes[static_cast<size_t>(i)];
    if (!tcp) {
      poses.push_back(k.forward(q));
      continue;
    }
    kin::Posed p;
    p.tip_mm = Vec3(q[0], q[1], q[2]);
    const auto rp = k.rotary_pair();
    if (b.has_vector)
      p.axis = Vec3(b.tool_vector[0], b.tool_vector[1], b.tool_vector[2]).normalized();
    else
      ASSERT_TRUE(k.tool_axis_at(q[rp[0]], q[rp[1]], p.tip_mm, p.axis));
    poses.push_back(p);
  }
  const double tol = m.post.tolerance_mm + 1e-3, cos_tol = std::cos(deg2rad(m.post.axis_tolerance_deg + 0.01));
  for (const auto& mv : prog.moves) {
    bool hit = false;
    for (const auto& p : poses)
      if ((p.tip_mm - mv.tip_in_part_mm).norm() <= tol && p.axis.dot(mv.axis_in_part.normalized()) >= cos_tol) {
        hit = true;
        break;
      }
    ASSERT_TRUE(hit) << tag << ": CL line " << mv.line << " is never reached";
  }
}

struct Case {
  std::string dialect;
  bool tcp;
  std::string tcp_form;
};

std::vector<Case> all_cases() {
  return {{"linuxcnc", false, "angles"}, {"linuxcnc", true, "angles"},    {"fanuc", false, "angles"},
          {"fanuc", true, "angles"},     {"fanuc", true, "vectors"},      {"haas", false, "angles"},
          {"haas", true, "angles"},      {"siemens", false, "angles"},    {"siemens", true, "angles"},
          {"siemens", true, "vectors"},  {"heidenhain", false, "angles"}, {"heidenhain", true, "angles"}};
}

std::string case_tag(const Case& c) {
  return c.dialect + (c.tcp ? "-tcp" : "") + (c.tcp_form == "vectors" ? "-vectors" : "");
}

}  // namespace

TEST(PostDialects, EveryDialectReadsBackReachesEveryClPointAndPassesTheGate) {
  for (const char* name : {"trunnion-ac", "haas-umc750", "head-head-ac"}) {
    const cl::Program prog = cl::read_text(synthetic_cl(25.0, 3, 25, 10.0), std::string(name) + ".cls");
    for (const Case& c : all_cases()) {
      const std::string tag = std::string(name) + "-" + case_tag(c);
      SCOPED_TRACE(tag);
      const auto m = machine_with_post(name, "  tcp_form: " + c.tcp_form + "\n");
      const auto k = m.kinematics();
      const Posted p = post_program(prog, m, *k, true, c.tcp, c.dialect);
      expect_every_cl_point_reached(p.text, prog, m, *k, tag);
      const auto gs = gate::check(p.text, tag, prog, m, *k, gate::options_for(m, 0, 0, 0));
      EXPECT_TRUE(gs.ok) << gs.message;
      EXPECT_EQ(gs.tool_tip_control, c.tcp);
    }
  }
}

TEST(PostDialects, EachControllerFamilySpellsItsOwnForms) {
  const cl::Program prog = cl::read_text(synthetic_cl(25.0, 2, 10, 10.0), "forms.cls");
  auto post_as = [&](const std::string& dialect, bool tcp, const std::string& form) {
    const auto m = machine_with_post("trunnion-ac", "  tcp_form: " + form + "\n  program_number: 42\n");
    const auto k = m.kinematics();
    return post_program(prog, m, *k, true, tcp, dialect).text;
  };
  auto has = [](const std::string& t, const std::string& w) { return t.find(w) != std::string::npos; };
  const std::string fa = post_as("fanuc", true, "angles");
  EXPECT_TRUE(has(fa, "O0042 (TRUNNION-AC)") && has(fa, "G43.4 H1\n") && has(fa, "\nG49\n") && has(fa, "\nM30\n"))
      << fa.substr(0, 800);
  const std::string fv = post_as("fanuc", true, "vectors");
  EXPECT_TRUE(has(fv, "G43.5 H1\n") && has(fv, " I-0.303731 J-0.274364 K0.912399")) << fv.substr(0, 800);
  EXPECT_FALSE(std::regex_search(fv, std::regex("\\nG[01][^\\n]* A-?[0-9]"))) << "no rotary words with vectors";
  const std::string fm = post_as("fanuc", false, "angles");
  EXPECT_TRUE(has(fm, "G43 H1\n") && !has(fm, "G43.4")) << fm.substr(0, 800);
  const std::string ha = post_as("haas", true, "angles");
  EXPECT_TRUE(has(ha, "O00042 (TRUNNION-AC)") && has(ha, "G234 H1\n") && has(ha, "\nG49\n")) << ha.substr(0, 800);
  const std::string sv = post_as("siemens", true, "vectors");
  EXPECT_TRUE(has(sv, "\nTRAORI\n") && has(sv, "ORIWKS ORIVECT") && has(sv, " A3=") && has(sv, " C3=") &&
              has(sv, "\nTRAFOOF\n") && has(sv, "G710 ") && has(sv, "\n; (cscam post: machine trunnion-ac"))
      << sv.substr(0, 800);
  const std::string hh = post_as("heidenhain", true, "angles");
  EXPECT_TRUE(has(hh, "0 BEGIN PGM TRUNNION_AC MM\n") && has(hh, "FUNCTION TCPM F TCP AXIS POS PATHCTRL AXIS") &&
              has(hh, " FMAX\n") && has(hh, "FUNCTION RESET TCPM") && has(hh, "END PGM TRUNNION_AC MM\n") &&
              std::regex_search(hh, std::regex("\\n[0-9]+ L X[+-][0-9.]+ Y[+-][0-9.]+")))
      << hh.substr(0, 800);
  EXPECT_FALSE(has(hh, "G93")) << "a TNC has no inverse-time feed";
  const std::string hm = post_as("heidenhain", false, "angles");
  EXPECT_FALSE(has(hm, "G93"));
}

TEST(PostDialects, FanucMachineCoordinatesAreAcceptedByRs274) {
  // Fanuc's machine-coordinate form is RS274 apart from the O-number line.
  const auto m = load_machine("trunnion-ac");
  const auto k = m.kinematics();
  const cl::Program prog = cl::read_text(synthetic_cl(25.0, 3, 25, 10.0), "fanuc.cls");
  std::string text = post_program(prog, m, *k, true, false, "fanuc").text;
  const size_t o = text.find("\nO0001");
  ASSERT_NE(o, std::string::npos);
  text.erase(o + 1, text.find('\n', o + 1) - o);
  expect_rs274_agrees(text, m, "fanuc");
}

TEST(PostDialects, UnknownDialectNamesTheKnownOnes) {
  const auto m = load_machine("trunnion-ac");
  const auto k = m.kinematics();
  const cl::Program prog = cl::read_text(synthetic_cl(10.0, 2, 5, 10.0), "x.cls");
  try {
    post_program(prog, m, *k, true, std::nullopt, "klingon");
    FAIL();
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("heidenhain"), std::string::npos) << e.what();
  }
}

// --- The program a machinist expects ----------------------------------------------------------------

TEST(PostProgram, SequenceNumbersInchWorkOffsetAndRotaryHome) {
  const auto m = machine_with_post("trunnion-ac",
                                   "  sequence_numbers: true\n  sequence_step: 5\n  inch: true\n"
                                   "  work_offset: g55\n");
  const auto k = m.kinematics();
  const cl::Program prog = cl::read_text(synthetic_cl(25.0, 3, 20, 10.0), "inch.cls");
  const Posted p = post_program(prog, m, *k);
  EXPECT_NE(p.text.find("N5 G20 G90 G94"), std::string::npos) << p.text.substr(0, 600);
  EXPECT_NE(p.text.find("N10 G55\n"), std::string::npos);
  // G64 P is a length in the program's units: 0.01 mm is 0.0004 inch.
  EXPECT_NE(p.text.find("G64 P0.0004\n"), std::string::npos) << p.text.substr(0, 600);
  // every block numbered, in steps of 5
  std::regex nword("^N([0-9]+) ");
  long long prev = 0;
  std::istringstream in(p.text);
  std::string line;
  int numbered = 0;
  while (std::getline(in, line)) {
    std::smatch mm;
    if (line.empty() || line[0] == '(' || line == "%") continue;
    ASSERT_TRUE(std::regex_search(line, mm, nword)) << line;
    const long long n = std::stoll(mm[1]);
    EXPECT_EQ(n, prev + 5);
    prev = n;
    ++numbered;
  }
  EXPECT_GT(numbered, 50);
  // the last move turns the rotaries home
  const nc::Program ncp = report::read_for_machine(p.text, "inch.ngc", m);
  ASSERT_FALSE(ncp.blocks.empty());
  EXPECT_NEAR(ncp.blocks.back().axes[3], 0.0, 1e-9);
  EXPECT_NEAR(ncp.blocks.back().axes[4], 0.0, 1e-9);
  // inch words read back in mm through the same path
  const auto gs = gate::check(p.text, "inch.ngc", prog, m, *k, gate::options_for(m, 0, 0, 0));
  EXPECT_TRUE(gs.ok) << gs.message;
}

TEST(PostProgram, FeedsAreCappedAtMaxFeedAndReported) {
  const auto m = load_machine("trunnion-ac");
  const auto k = m.kinematics();
  // 30 m/min asked, X may do 10 m/min
  const cl::Program prog = cl::read_text(
      "UNITS/MM\nMULTAX\nFEDRAT/MMPM,30000\nRAPID\nGOTO/0,0,5,0,0,1\nGOTO/100,0,5,0,0,1\n"
      "GOTO/110,10,5,0.2,0,0.9797959\n",
      "fast.cls");
  const Posted p = post_program(prog, m, *k);
  EXPECT_GT(p.summary.capped_blocks, 0u);
  EXPECT_NE(p.text.find("F10000.0"), std::string::npos) << p.text;
  bool warned = false;
  for (const auto& w : p.summary.warnings) warned |= w.find("max_feed") != std::string::npos;
  EXPECT_TRUE(warned);
  const auto gs = gate::check(p.text, "fast.ngc", prog, m, *k, gate::options_for(m, 0, 0, 0));
  EXPECT_TRUE(gs.ok) << gs.message;
  EXPECT_LE(gs.max_velocity_ratio, 1.0 + 1e-3);
}

TEST(PostProgram, ShortestWayRotaryIsWrittenModulo360AndReadBackUnwound) {
  // A spiral that winds C through 720 deg: modulo words, and the reader follows the short way.
  std::ostringstream cl;
  cl << "UNITS/MM\nMULTAX\nFEDRAT/MMPM,2000\nRAPID\n";
  for (int i = 0; i <= 240; ++i) {
    const double t = deg2rad(3.0 * i);
    const Vec3 u = Vec3(0.3 * std::cos(t), 0.3 * std::sin(t), 1.0).normalized();
    cl << "GOTO/" << 30 * std::cos(t) << "," << 30 * std::sin(t) << ",5," << u.x() << "," << u.y() << "," << u.z()
       << "\n";
  }
  const cl::Program prog = cl::read_text(cl.str(), "spiral.cls");
  for (const char* dialect : {"linuxcnc", "siemens"}) {
    SCOPED_TRACE(dialect);
    const auto m = machine_with_post("trunnion-ac", "  rotary_output: shortest\n");
    const auto k = m.kinematics();
    const Posted p = post_program(prog, m, *k, true, std::nullopt, dialect);
    std::smatch mm;
    std::string::const_iterator it = p.text.begin();
    const std::regex cword(dialect == std::string("siemens") ? "C=DC\\((-?[0-9.]+)\\)" : " C(-?[0-9.]+)");
    int n = 0;
    while (std::regex_search(it, p.text.cend(), mm, cword)) {
      const double c = std::stod(mm[1]);
      EXPECT_GE(c, 0.0);
      EXPECT_LT(c, 360.0);
      it = mm[0].second;
      ++n;
    }
    EXPECT_GT(n, 100);
    const nc::Program ncp = report::read_for_machine(p.text, "spiral.ngc", m);
    double cmax = 0;
    for (const auto& b : ncp.blocks) cmax = std::max(cmax, std::abs(b.axes[4]));
    EXPECT_GT(rad2deg(cmax), 600.0) << "read back the short way, the table winds on";
    const auto gs = gate::check(p.text, "spiral.ngc", prog, m, *k, gate::options_for(m, 0, 0, 0));
    EXPECT_TRUE(gs.ok) << gs.message;
    // LinuxCNC takes the short way only for a joint configured as wrapped: the post says so.
    const bool warned = std::any_of(p.summary.warnings.begin(), p.summary.warnings.end(), [](const std::string& w) {
      return w.find("[AXIS_C]WRAPPED_ROTARY = 1") != std::string::npos;
    });
    EXPECT_EQ(warned, dialect == std::string("linuxcnc"));
  }
}

TEST(PostProgram, RotariesClampedAroundIndexedStretches) {
  const auto m = machine_with_post("haas-umc750", "  clamp: {b: [M10, M11], c: [M12, M13]}\n");
  const auto k = m.kinematics();
  // two 3+2 faces: fixed tilt, then another fixed tilt; then a stretch that tilts B alone (C is clamped for it)
  const cl::Program prog = cl::read_text(
      "UNITS/MM\nMULTAX\nFEDRAT/MMPM,1000\nRAPID\nGOTO/0,0,20,0.3,0,0.9539392\nGOTO/20,0,20,0.3,0,0.9539392\n"
      "GOTO/20,20,20,0.3,0,0.9539392\nRAPID\nGOTO/0,60,20,0,0.3,0.9539392\nGOTO/-20,60,20,0,0.3,0.9539392\n"
      "RAPID\nGOTO/0,-60,20,0,0,1\nGOTO/10,-60,20,0.1,0,0.9949874\n",
      "faces.cls");
  const Posted p = post_program(prog, m, *k, true, std::nullopt, "haas");
  auto count = [&](const std::string& w) {
    size_t n = 0;
    for (size_t pos = p.text.find(w); pos != std::string::npos; pos = p.text.find(w, pos + 1)) ++n;
    return n;
  };
  EXPECT_EQ(count("\nM10\n"), 2u) << p.text;
  EXPECT_EQ(count("\nM12\n"), 3u);
  EXPECT_EQ(count("\nM11\n"), 2u);
  EXPECT_EQ(count("\nM13\n"), 3u);
  // no word of a rotary between its clamp and its unclamp, and the third stretch's B turns while C is clamped
  std::istringstream in(p.text);
  std::string line;
  bool b_clamped = false, c_clamped = false, b_turned_under_c_clamp = false;
  while (std::getline(in, line)) {
    if (line == "M10") b_clamped = true;
    if (line == "M11") b_clamped = false;
    if (line == "M12") c_clamped = true;
    if (line == "M13") c_clamped = false;
    if (b_clamped) EXPECT_FALSE(std::regex_search(line, std::regex(" B-?[0-9]"))) << line;
    if (c_clamped) EXPECT_FALSE(std::regex_search(line, std::regex(" C-?[0-9]"))) << line;
    b_turned_under_c_clamp |= c_clamped && line.rfind("G1", 0) == 0 && std::regex_search(line, std::regex(" B-?[0-9]"));
  }
  EXPECT_TRUE(b_turned_under_c_clamp) << p.text;
  const auto gs = gate::check(p.text, "faces.ngc", prog, m, *k, gate::options_for(m, 0, 0, 0));
  EXPECT_TRUE(gs.ok) << gs.message << "\n" << p.text;
}

TEST(PostProgram, OptionalStopAndToolZeroWarning) {
  const auto m = load_machine("trunnion-ac");
  const auto k = m.kinematics();
  const cl::Program prog = cl::read_text(
      "UNITS/MM\nMULTAX\nLOADTL/0\nFEDRAT/MMPM,1000\nRAPID\nGOTO/0,0,20,0,0,1\nOPSTOP\nGOTO/20,0,20,0,0,1\nSTOP\n"
      "GOTO/20,10,20,0,0,1\n",
      "stops.cls");
  const Posted p = post_program(prog, m, *k);
  EXPECT_NE(p.text.find("\nM1\n"), std::string::npos) << p.text;
  EXPECT_NE(p.text.find("\nM0\n"), std::string::npos) << p.text;
  bool warned = false;
  for (const auto& w : p.summary.warnings) warned |= w.find("H0") != std::string::npos;
  EXPECT_TRUE(warned);
}

TEST(PostProgram, MachineFileRejectsBadPostSettings) {
  for (const auto& [line, key] :
       std::vector<std::pair<std::string, std::string>>{{"  tcp_form: quaternions\n", "post.tcp_form"},
                                                        {"  work_offset: G99\n", "post.work_offset"},
                                                        {"  rotary_output: sideways\n", "post.rotary_output"},
                                                        {"  clamp: {x: [M10, M11]}\n", "post.clamp.x"},
                                                        {"  clamp: {a: [M10, Q11]}\n", "post.clamp.a"},
                                                        {"  program_number: -3\n", "post.program_number"}}) {
    SCOPED_TRACE(line);
    try {
      machine_with_post("trunnion-ac", line);
      FAIL() << "accepted";
    } catch (const InputError& e) {
      EXPECT_NE(std::string(e.what()).find(key), std::string::npos) << e.what();
      EXPECT_NE(std::string(e.what()).find("trunnion-ac-variant.yaml:"), std::string::npos) << e.what();
    }
  }
  // A safe Z beyond the Z travel (it was blamed on the CL file's first rapid), and a cyclic axis that cannot turn.
  std::ifstream in(test::source_path("machines/trunnion-ac.yaml"));
  const std::string text(std::istreambuf_iterator<char>(in), {});
  for (const auto& [from, to, what] : std::vector<std::tuple<std::string, std::string, std::string>>{
           {"safe_z_mm: 250", "safe_z_mm: 900", "'post.safe_z_mm': 900 mm is outside the travel of z"},
           {"name: a, type: rotary,", "name: a, type: rotary, cyclic: true,", "span less than one"}}) {
    const std::string bad = std::regex_replace(text, std::regex(from), to);
    ASSERT_NE(bad, text);
    try {
      (void)machine::load_text(bad, "bad.yaml");
      FAIL() << "accepted: " << to;
    } catch (const InputError& e) {
      EXPECT_NE(std::string(e.what()).find(what), std::string::npos) << e.what();
    }
  }
}

// --- Golden files: the groove and NX examples in every dialect ------------------------------------------
// A change to any of these files is a change of what the machines run: review the diff, then regenerate with
// CSCAM_UPDATE_GOLDEN=1 ctest -R PostGolden.

TEST(PostGolden, GrooveAndNxExamplesInEveryDialect) {
  const bool update = std::getenv("CSCAM_UPDATE_GOLDEN") != nullptr;
  struct Example {
    std::string cl, machine, stem;
  };
  for (const Example& ex : {Example{"examples/groove/groove.cls", "trunnion-ac", "groove"},
                            Example{"examples/nx-haas-umc750/variable_axis.cls", "haas-umc750", "nx"}}) {
    const cl::Program prog = cl::read_file(test::source_path(ex.cl));
    for (const Case& c : all_cases()) {
      const std::string tag = ex.stem + "-" + case_tag(c);
      SCOPED_TRACE(tag);
      const auto m = machine_with_post(ex.machine, "  tcp_form: " + c.tcp_form + "\n");
      const auto k = m.kinematics();
      const auto axes = post::conventional_axes(prog, m, *k);
      std::ostringstream os;
      post::Options o;
      o.tcp = c.tcp;
      o.dialect = c.dialect;
      o.source_name = fs::path(ex.cl).filename().string();
      post::Summary sum;
      post::write_nc(os, prog, m, *k, axes, o, sum);
      const std::string text = os.str();
      const auto gs = gate::check(text, tag, prog, m, *k, gate::options_for(m, 0, 0, 0));
      EXPECT_TRUE(gs.ok) << gs.message;
      const std::string path = test::source_path("tests/data/golden/" + tag + ".nc");
      if (update) {
        fs::create_directories(fs::path(path).parent_path());
        std::ofstream(path, std::ios::binary) << text;
        continue;
      }
      std::ifstream in(path, std::ios::binary);
      ASSERT_TRUE(in) << "missing golden file " << path << " (CSCAM_UPDATE_GOLDEN=1 writes it)";
      std::stringstream want;
      want << in.rdbuf();
      if (want.str() != text) {
        // the first differing line, for the review
        std::istringstream a(want.str()), b(text);
        std::string la, lb;
        int n = 0;
        while (true) {
          const bool ga = static_cast<bool>(std::getline(a, la)), gb = static_cast<bool>(std::getline(b, lb));
          ++n;
          if (!ga && !gb) break;
          if (!ga || !gb || la != lb) {
            ADD_FAILURE() << path << ":" << n << ": golden '" << la << "' now '" << lb << "'";
            break;
          }
        }
      }
    }
  }
}

TEST(PostCli, TcpFlagsAndVerifyAndStatsReadEveryDialect) {
  const fs::path dir = fs::temp_directory_path() / ("cscam_post_cli_" + std::to_string(::getpid()));
  fs::create_directories(dir);
  const std::string cl = test::source_path("examples/nx-haas-umc750/variable_axis.cls");
  for (const char* dialect : {"haas", "siemens", "heidenhain", "fanuc", "linuxcnc"}) {
    for (const char* tcp : {"--tcp", "--no-tcp"}) {
      SCOPED_TRACE(std::string(dialect) + " " + tcp);
      const std::string out = (dir / (std::string(dialect) + tcp + ".nc")).string();
      auto r = test::run_command(
          fmt::format("{} post {} --machine haas-umc750 --dialect {} {} -o {}", CSCAM_CLI, cl, dialect, tcp, out));
      ASSERT_EQ(r.status, 0) << r.output;
      r = test::run_command(fmt::format("{} verify {} --machine haas-umc750 --cl {}", CSCAM_CLI, out, cl));
      EXPECT_EQ(r.status, 0) << r.output;
      EXPECT_EQ(r.output.rfind("OK:", 0), 0u) << r.output;
      r = test::run_command(fmt::format("{} stats {} --machine haas-umc750", CSCAM_CLI, out));
      EXPECT_EQ(r.status, 0) << r.output;
      EXPECT_NE(r.output.find("cycle time (min)"), std::string::npos) << r.output;
    }
  }
  const auto r = test::run_command(
      fmt::format("{} post {} --machine haas-umc750 --tcp --no-tcp -o {}", CSCAM_CLI, cl, (dir / "x.nc").string()));
  EXPECT_NE(r.status, 0);
  EXPECT_FALSE(fs::exists(dir / "x.nc"));
  fs::remove_all(dir);
}

TEST(PostProgram, HeadRotaryToolLengthComesFromTheClNeverSilentlyTheDefault) {
  const auto hh = load_machine("head-head-ac");
  const auto tt = load_machine("trunnion-ac");
  const cl::Program with = cl::read_text("UNITS/MM\nTLDATA/MILL,6,3,75,0,0\nLOADTL/3\nGOTO/0,0,0\n", "with.cls");
  const cl::Program without = cl::read_text("UNITS/MM\nLOADTL/3\nGOTO/0,0,0\n", "without.cls");
  std::string note;
  EXPECT_DOUBLE_EQ(post::tool_length_for(hh, 0.0, with, note), 75.0);
  EXPECT_NE(note.find("from the CL"), std::string::npos) << note;
  EXPECT_DOUBLE_EQ(post::tool_length_for(hh, 0.0, without, note), hh.default_tool_length_mm);
  EXPECT_NE(note.find("default_tool_length_mm"), std::string::npos) << note;
  EXPECT_DOUBLE_EQ(post::tool_length_for(hh, 42.0, with, note), 42.0);
  EXPECT_TRUE(note.empty());
  EXPECT_DOUBLE_EQ(post::tool_length_for(tt, 0.0, with, note), tt.default_tool_length_mm);  // table rotaries only
  EXPECT_TRUE(note.empty());
}

TEST(PostProgram, DwellInsertAdjustRegisterAndCutcomPolicy) {
  const auto m = load_machine("trunnion-ac");
  const auto k = m.kinematics();
  const cl::Program prog = cl::read_text(
      "UNITS/MM\nMULTAX\nCUTTER/6\nLOAD/TOOL,7,ADJUST,27\nCUTCOM/LEFT\nFEDRAT/MMPM,1000\nRAPID\nGOTO/0,0,20,0,0,1\n"
      "DELAY/2.5\nINSERT/M100 P1\nGOTO/20,0,20,0,0,1\n",
      "records.cls");
  bool cutcom_warned = false;
  for (const auto& w : prog.warnings) cutcom_warned |= w.message.find("CUTCOM") != std::string::npos;
  EXPECT_TRUE(cutcom_warned);
  const Posted p = post_program(prog, m, *k);
  EXPECT_NE(p.text.find("T7 M6\nG43 H27\n"), std::string::npos) << p.text;
  EXPECT_NE(p.text.find("\nG4 P2.500\n"), std::string::npos) << p.text;
  EXPECT_NE(p.text.find("\nM100 P1\n"), std::string::npos) << p.text;
  const auto s = post_program(prog, m, *k, true, std::nullopt, "siemens").text;
  EXPECT_NE(s.find("\nG4 F2.500\n"), std::string::npos) << s;
  const auto h = post_program(prog, m, *k, true, std::nullopt, "heidenhain").text;
  EXPECT_NE(h.find(" CYCL DEF 9.1 DWELL 2.500\n"), std::string::npos) << h;
  // Fanuc: P in milliseconds, no decimal point; Haas: P with a decimal point is seconds.
  const auto f = post_program(prog, m, *k, true, std::nullopt, "fanuc").text;
  EXPECT_NE(f.find("\nG4 P2500\n"), std::string::npos) << f;
  const auto hs = post_program(prog, m, *k, true, std::nullopt, "haas").text;
  EXPECT_NE(hs.find("\nG4 P2.500\n"), std::string::npos) << hs;
  try {
    cl::read_text("UNITS/MM\nLOAD/TOOL,7,ADJUST,-2\nGOTO/0,0,0\n", "bad.cls");
    FAIL();
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("bad.cls:2:"), std::string::npos) << e.what();
  }
}

// A dwell read back in every dialect is the CL's DELAY: its time in the cycle estimate (stats), with Fanuc's P in
// milliseconds and the others' seconds, and a Sinumerik G4 F that does not become the feed of the moves after it.
TEST(PostProgram, DwellsReadBackInEveryDialectAreTheClDelays) {
  const auto m = load_machine("trunnion-ac");
  const auto k = m.kinematics();
  const cl::Program prog = cl::read_text(
      "UNITS/MM\nMULTAX\nCUTTER/6\nLOADTL/1\nFEDRAT/MMPM,1000\nRAPID\nGOTO/0,0,20,0,0,1\nGOTO/0,0,10,0,0,1\n"
      "DELAY/2.5\nGOTO/20,0,10,0,0,1\nDELAY/0.75\nGOTO/20,20,10,0,0,1\n",
      "dwell.cls");
  constexpr double kDwellS = 3.25;
  for (const char* dialect : {"linuxcnc", "fanuc", "haas", "siemens", "heidenhain"}) {
    SCOPED_TRACE(dialect);
    const std::string text = post_program(prog, m, *k, true, std::nullopt, dialect).text;
    const nc::Program nc = report::read_for_machine(text, "dwell.nc", m);
    EXPECT_EQ(nc.dwells, 2u);
    EXPECT_NEAR(nc.dwell_seconds, kDwellS, 1e-9);
    ASSERT_FALSE(nc.blocks.empty());
    for (const auto& b : nc.blocks)
      if (b.motion != nc::Motion::Rapid) EXPECT_DOUBLE_EQ(b.feed, 1000.0) << "line " << b.line;
    const report::Stats st = report::compute(nc, {"X", "Y", "Z", "A", "C"}, {false, false, false, true, true});
    EXPECT_NEAR(st.dwell_minutes, kDwellS / 60.0, 1e-12);
    EXPECT_NEAR(st.json()["cycle_minutes"].get<double>(), st.feed_minutes + st.dwell_minutes, 1e-4);
  }
}

// --- Tilted work planes (3+2) ---------------------------------------------------------------------------

namespace {

/// Two 3+2 faces, a simultaneous stretch, a third face between it and another simultaneous stretch.
std::string faces_between_simultaneous_cl() {
  return "UNITS/MM\nMULTAX\nFEDRAT/MMPM,1000\nRAPID\nGOTO/0,0,20,0.3,0,0.9539392\nGOTO/20,0,20,0.3,0,0.9539392\n"
         "GOTO/20,20,20,0.3,0,0.9539392\nRAPID\nGOTO/0,60,20,0,0.3,0.9539392\nGOTO/-20,60,20,0,0.3,0.9539392\n"
         "RAPID\nGOTO/0,-60,20,0,0,1\nGOTO/10,-60,20,0.1,0,0.9949874\nGOTO/20,-60,20,0.2,0,0.9797959\n"
         "RAPID\nGOTO/-30,-20,25,-0.2,0.25,0.9474704\nGOTO/-30,0,25,-0.2,0.25,0.9474704\n"
         "GOTO/-10,0,25,-0.2,0.25,0.9474704\nRAPID\nGOTO/0,0,25,-0.1,0.25,0.9630680\nGOTO/10,0,25,0,0.2,0.9797959\n"
         "GOTO/20,0,25,0.1,0.2,0.9746794\nFINI\n";
}

/// The CL program turned rigidly by R and moved by t (points, axes and arcs): a 3-axis program becomes 3+2.
cl::Program turned(cl::Program p, const Eigen::Matrix3d& R, const Vec3& t) {
  for (auto& mv : p.moves) {
    mv.tip_in_part_mm = R * mv.tip_in_part_mm + t;
    mv.axis_in_part = R * mv.axis_in_part;
  }
  for (auto& a : p.arcs) {
    a.centre_in_part_mm = R * a.centre_in_part_mm + t;
    a.normal_in_part = R * a.normal_in_part;
  }
  return p;
}

Posted post_with_plane(const cl::Program& prog, const machine::Machine& m, const kin::Kinematics& k,
                       const std::string& dialect, const std::string& work_plane) {
  const auto axes = post::conventional_axes(prog, m, k);
  std::ostringstream os;
  post::Options o;
  o.dialect = dialect;
  o.work_plane = work_plane;
  o.tcp = false;
  Posted p;
  post::write_nc(os, prog, m, k, axes, o, p.summary);
  p.text = os.str();
  return p;
}

/// The machine positions a program moves through, read back (work planes resolved), repeated positions dropped.
std::vector<kin::Axes> machine_path(const std::string& text, const machine::Machine& m, const std::string& tag) {
  const nc::Program ncp = report::read_for_machine(text, tag, m);
  std::vector<kin::Axes> out;
  for (const auto& b : ncp.blocks) {
    if (!std::all_of(b.known.begin(), b.known.end(), [](bool x) { return x; })) continue;
    kin::Axes q;
    for (int i = 0; i < 5; ++i) q[i] = b.axes[static_cast<size_t>(i)];
    if (!out.empty() && (q - out.back()).cwiseAbs().maxCoeff() < 1e-3) continue;
    out.push_back(q);
  }
  return out;
}

/// Oracle: the plane program, its words resolved into machine axes, moves through the same machine positions as
/// the machine-coordinate program of the same CL (whose words are the axes themselves), within the rounding of
/// the printed words (plane coordinates and angles: 1e-4 mm / deg at 4 decimals, through a rotation).
void expect_same_machine_path(const std::string& plane_text, const std::string& machine_text, const machine::Machine& m,
                              const std::string& tag) {
  const auto a = machine_path(plane_text, m, tag + "-plane"), b = machine_path(machine_text, m, tag + "-machine");
  for (size_t i = 0; i < std::min(a.size(), b.size()); ++i)
    if ((a[i] - b[i]).cwiseAbs().maxCoeff() > 2e-3) {
      ADD_FAILURE() << tag << ": position " << i << " differs: " << a[i].transpose() << " vs " << b[i].transpose();
      break;
    }
  ASSERT_EQ(a.size(), b.size()) << tag;
  double worst_mm = 0.0, worst_rad = 0.0;
  for (size_t i = 0; i < a.size(); ++i)
    for (int j = 0; j < 5; ++j)
      (m.axes[static_cast<size_t>(j)].rotary() ? worst_rad : worst_mm) =
          std::max(m.axes[static_cast<size_t>(j)].rotary() ? worst_rad : worst_mm, std::abs(a[i][j] - b[i][j]));
  EXPECT_LT(worst_mm, 2e-3) << tag;
  EXPECT_LT(worst_rad, 1e-9) << tag;  // the rotaries are the same words
}

size_t count_of(const std::string& text, const std::string& w) {
  size_t n = 0;
  for (size_t pos = text.find(w); pos != std::string::npos; pos = text.find(w, pos + 1)) ++n;
  return n;
}

const std::map<std::string, std::pair<std::string, std::string>>& plane_codes() {
  static const std::map<std::string, std::pair<std::string, std::string>> codes{
      {"fanuc", {"G68.2 ", "G69\n"}},
      {"haas", {"G254\n", "G255\n"}},
      {"siemens", {"CYCLE800(0,", "CYCLE800()\n"}},
      {"heidenhain", {"PLANE SPATIAL SPA", "PLANE RESET STAY\n"}}};
  return codes;
}

}  // namespace

TEST(PostWorkPlane, EachDialectWritesItsPlaneBetweenSimultaneousStretchesAndReadsBackToTheMachineProgram) {
  const cl::Program prog = cl::read_text(faces_between_simultaneous_cl(), "faces.cls");
  for (const char* name : {"haas-umc750", "trunnion-ac"}) {
    const auto m = load_machine(name);
    const auto k = m.kinematics();
    for (const auto& [dialect, codes] : plane_codes()) {
      const std::string tag = std::string(name) + "-" + dialect;
      SCOPED_TRACE(tag);
      const Posted p = post_with_plane(prog, m, *k, dialect, "tilted");
      const Posted q = post_with_plane(prog, m, *k, dialect, "machine");
      EXPECT_EQ(p.summary.work_planes, 3u);  // the three fixed faces; the simultaneous stretches stay outside
      EXPECT_EQ(count_of(p.text, codes.first), 3u) << p.text;
      EXPECT_EQ(count_of(p.text, codes.second), 3u) << p.text;
      EXPECT_EQ(count_of(q.text, codes.first), 0u);
      expect_every_cl_point_reached(p.text, prog, m, *k, tag);
      expect_same_machine_path(p.text, q.text, m, tag);
      const auto gs = gate::check(p.text, tag, prog, m, *k, gate::options_for(m, 0, 0, 0));
      EXPECT_TRUE(gs.ok) << gs.message << "\n" << p.text;
      // no rotary word while a plane is on
      std::istringstream in(p.text);
      std::string line;
      bool on = false;
      const std::string rot = "[" + m.post.letters[3] + m.post.letters[4] + "][-+]?[0-9]";
      while (std::getline(in, line)) {
        if (line.find(codes.first) != std::string::npos) on = true;
        if ((line + "\n").find(codes.second) != std::string::npos) on = false;
        if (on) EXPECT_FALSE(std::regex_search(line, std::regex(" " + rot))) << line;
      }
    }
  }
}

TEST(PostWorkPlane, SiemensNamesTheMachinesSwivelDataRecord) {
  const cl::Program prog = cl::read_text(faces_between_simultaneous_cl(), "faces.cls");
  const auto m = machine_with_post("trunnion-ac", "  swivel_record: TABLE_1\n");
  const auto k = m.kinematics();
  const Posted p = post_with_plane(prog, m, *k, "siemens", "tilted");
  EXPECT_EQ(count_of(p.text, "CYCLE800(0,\"TABLE_1\",0,57,"), 3u) << p.text;
  EXPECT_EQ(count_of(p.text, "\"TC1\""), 0u);
  const auto gs = gate::check(p.text, "faces", prog, m, *k, gate::options_for(m, 0, 0, 0));
  EXPECT_TRUE(gs.ok) << gs.message;
}

TEST(PostWorkPlane, NxZigzagTurnedIntoA3Plus2FaceRoundTripsInEveryDialect) {
  // NX's 3-axis zigzag, its part turned 25 deg about X and 10 deg about Z: one fixed orientation, a real 3+2 job.
  const cl::Program flat = cl::read_file(test::source_path("examples/nx-haas-umc750/zigzag_smoothed.cls"));
  const Eigen::Matrix3d R =
      (Eigen::AngleAxisd(deg2rad(10.0), Vec3::UnitZ()) * Eigen::AngleAxisd(deg2rad(25.0), Vec3::UnitX()))
          .toRotationMatrix();
  const cl::Program prog = turned(flat, R, Vec3(0, -40, -30));
  // CL arcs are points inside a plane: the machine program compared with has them as points too
  const auto m = machine_with_post("haas-umc750", "  arcs: false\n");
  const auto k = m.kinematics();
  for (const auto& [dialect, codes] : plane_codes()) {
    SCOPED_TRACE(dialect);
    const Posted p = post_with_plane(prog, m, *k, dialect, "tilted");
    const Posted q = post_with_plane(prog, m, *k, dialect, "machine");
    EXPECT_GE(p.summary.work_planes, 1u);
    EXPECT_EQ(count_of(p.text, codes.first), p.summary.work_planes);
    expect_every_cl_point_reached(p.text, prog, m, *k, "nx-" + dialect);
    expect_same_machine_path(p.text, q.text, m, "nx-" + dialect);
    const auto gs = gate::check(p.text, "nx-" + dialect, prog, m, *k, gate::options_for(m, 0, 0, 0));
    EXPECT_TRUE(gs.ok) << gs.message;
  }
}

TEST(PostWorkPlane, SimultaneousExamplesAndLinuxcncKeepMachineCoordinates) {
  // groove and NX's variable-axis job have no 3+2 stretch: a tilted setting writes the same program.
  for (const auto& [cl_path, name] :
       {std::pair<std::string, std::string>{"examples/groove/groove.cls", "trunnion-ac"},
        std::pair<std::string, std::string>{"examples/nx-haas-umc750/variable_axis.cls", "haas-umc750"}}) {
    const cl::Program prog = cl::read_file(test::source_path(cl_path));
    const auto m = load_machine(name);
    const auto k = m.kinematics();
    for (const auto& d : {"fanuc", "haas", "siemens", "heidenhain"}) {
      const Posted p = post_with_plane(prog, m, *k, d, "tilted");
      EXPECT_EQ(p.summary.work_planes, 0u) << cl_path << " " << d;
      EXPECT_EQ(p.text, post_with_plane(prog, m, *k, d, "machine").text) << cl_path << " " << d;
    }
  }
  // linuxcnc has no tilted plane: machine coordinates with a warning, and rs274 accepts them
  const cl::Program prog = cl::read_text(faces_between_simultaneous_cl(), "faces.cls");
  const auto m = load_machine("trunnion-ac");
  const auto k = m.kinematics();
  const Posted p = post_with_plane(prog, m, *k, "linuxcnc", "tilted");
  EXPECT_EQ(p.text, post_with_plane(prog, m, *k, "linuxcnc", "machine").text);
  EXPECT_EQ(p.summary.work_planes, 0u);
  ASSERT_FALSE(p.summary.warnings.empty());
  EXPECT_NE(p.summary.warnings.back().find("has no tilted work plane"), std::string::npos);
  expect_rs274_agrees(p.text, m, "linuxcnc-tilted");
}

TEST(PostWorkPlane, AWrongPlaneIsCaughtByTheGate) {
  const cl::Program prog = cl::read_text(faces_between_simultaneous_cl(), "faces.cls");
  const auto m = load_machine("haas-umc750");
  const auto k = m.kinematics();
  // One Euler angle changed by 0.1 deg: the plane no longer matches the rotaries positioned for it.
  std::string text = post_with_plane(prog, m, *k, "fanuc", "tilted").text;
  const std::regex j_word("J([0-9]+\\.[0-9]+)");
  std::smatch mt;
  ASSERT_TRUE(std::regex_search(text, mt, j_word));
  text.replace(static_cast<size_t>(mt.position(1)), static_cast<size_t>(mt.length(1)),
               fmt::format("{:.4f}", std::stod(mt.str(1)) + 0.1));
  const auto gs = gate::check(text, "bent.nc", prog, m, *k, gate::options_for(m, 0, 0, 0));
  EXPECT_FALSE(gs.ok);
  EXPECT_NE(gs.message.find("the Z axis of G68.2"), std::string::npos) << gs.message;
  // the machine file setting
  const auto bad = [&] {
    try {
      machine_with_post("haas-umc750", "  work_plane: rotated\n");
    } catch (const InputError& e) {
      return std::string(e.what());
    }
    return std::string();
  }();
  EXPECT_NE(bad.find("post.work_plane"), std::string::npos) << bad;
  EXPECT_EQ(machine_with_post("haas-umc750", "  work_plane: tilted\n").post.work_plane, "tilted");
}

// --- Tilted work planes under tool-tip control ------------------------------------------------------------

namespace {

/// The words each dialect with planes writes to switch tool-tip control on and off (dialects.cpp).
struct TcpWords {
  std::vector<std::string> on;
  std::string off;
};
const std::map<std::string, TcpWords>& tcp_words() {
  static const std::map<std::string, TcpWords> words{{"fanuc", {{"G43.4 H", "G43.5 H"}, "G49"}},
                                                     {"haas", {{"G234 H"}, "G49"}},
                                                     {"siemens", {{"TRAORI"}, "TRAFOOF"}},
                                                     {"heidenhain", {{"FUNCTION TCPM"}, "FUNCTION RESET TCPM"}}};
  return words;
}

/// One block of a program read back: the machine axes the control moves to and the pose there (part frame).
struct MachineBlock {
  kin::Axes q;
  kin::Posed pose;
  bool feed = false, tcp = false;
  int line = 0;
};

/// Oracle: the program read back (planes and TCP switching resolved by the reader), then per block the machine axes
/// the control moves to, found here without the post's code: machine words (kept by the reader) are the axes; tip
/// words in the angle form name the rotaries, the linear axes follow from the tip; in the vector form the control
/// takes the IK solution nearest to where it is.
std::vector<MachineBlock> machine_blocks(const std::string& text, const machine::Machine& m, const kin::Kinematics& k,
                                         const std::string& tag) {
  nc::Program ncp = report::read_for_machine(text, tag, m);
  EXPECT_EQ(report::resolve_tool_vectors(ncp, k), "") << tag;
  const auto view = report::tool_tip_kinematics(k, ncp.tcp_vectors);
  std::vector<MachineBlock> out;
  kin::Axes prev = kin::Axes::Zero();
  std::map<std::size_t, std::array<double, 5>> machine_words(ncp.machine_axes.begin(), ncp.machine_axes.end());
  for (std::size_t bi = 0; bi < ncp.blocks.size(); ++bi) {
    const nc::Block& b = ncp.blocks[bi];
    if (!std::all_of(b.known.begin(), b.known.end(), [](bool x) { return x; })) continue;
    MachineBlock mb;
    for (int i = 0; i < 5; ++i) mb.q[i] = b.axes[static_cast<size_t>(i)];
    mb.feed = b.motion != nc::Motion::Rapid;
    mb.tcp = ncp.tcp && !machine_words.count(bi);
    mb.line = b.line;
    if (machine_words.count(bi)) {
      for (int i = 0; i < 5; ++i) mb.q[i] = machine_words[bi][static_cast<size_t>(i)];
    } else if (ncp.tcp) {
      const kin::Posed words = view->forward(mb.q);
      kin::Axes q = mb.q;
      const bool ok = ncp.tcp_vectors ? kin::nearest_solution(k, words, prev, q) : k.solve_for_rotaries(words, q);
      EXPECT_TRUE(ok) << tag << " line " << b.line;
      mb.q = q;
    }
    mb.pose = k.forward(mb.q);
    prev = mb.q;
    out.push_back(mb);
  }
  return out;
}

/// Distance from p to the segment ab.
double segment_distance(const Vec3& p, const Vec3& a, const Vec3& b) {
  const Vec3 ab = b - a;
  const double t = ab.squaredNorm() > 0 ? std::clamp((p - a).dot(ab) / ab.squaredNorm(), 0.0, 1.0) : 0.0;
  return (a + t * ab - p).norm();
}

/// The tips a feed block passes through as the control interpolates it: the tip words straight under TCP, the
/// machine axes straight otherwise (FK of the joints).
std::vector<Vec3> feed_samples(const std::vector<MachineBlock>& blocks, const kin::Kinematics& k, int n) {
  std::vector<Vec3> out;
  for (size_t i = 1; i < blocks.size(); ++i) {
    if (!blocks[i].feed) continue;
    for (int s = 0; s <= n; ++s) {
      const double t = static_cast<double>(s) / n;
      out.push_back(blocks[i].tcp
                        ? Vec3(blocks[i - 1].pose.tip_mm + t * (blocks[i].pose.tip_mm - blocks[i - 1].pose.tip_mm))
                        : k.forward(blocks[i - 1].q + t * (blocks[i].q - blocks[i - 1].q)).tip_mm);
    }
  }
  return out;
}

/// The block whose tip is nearest to the CL point.
const MachineBlock& nearest_block(const std::vector<MachineBlock>& blocks, const Vec3& tip) {
  return *std::min_element(blocks.begin(), blocks.end(), [&](const MachineBlock& a, const MachineBlock& b) {
    return (a.pose.tip_mm - tip).norm() < (b.pose.tip_mm - tip).norm();
  });
}

/// (c) on the text alone: inside every plane no TCP word is in force (and Fanuc / Haas restore the plain length
/// offset G43 H before it), every feed block outside the planes runs under TCP. Returns the plane stretches seen.
int expect_tcp_off_exactly_in_planes(const std::string& text, const std::string& dialect, const std::string& tag) {
  const auto& words = tcp_words().at(dialect);
  const auto& plane = plane_codes().at(dialect);
  std::istringstream in(text);
  std::string line;
  bool tcp = false, in_plane = false, length = true;
  int planes = 0, tcp_feeds = 0, plane_feeds = 0;
  const std::regex feed_re(dialect == "heidenhain" ? "^[0-9]+ L .* F[0-9]|^[0-9]+ L [^F]*$" : "(^| )G1 ");
  while (std::getline(in, line)) {
    const std::string l = line + "\n";
    for (const auto& w : words.on)
      if (l.find(w) != std::string::npos) tcp = true;
    if (l.find(words.off) != std::string::npos && (dialect != "heidenhain" || l.find("RESET") != std::string::npos)) {
      tcp = false;
      length = dialect != "fanuc" && dialect != "haas";  // G49 cancels the length too
    }
    if (l.find("G43 H") != std::string::npos) length = true;
    if (l.find(plane.first) != std::string::npos) {
      EXPECT_FALSE(tcp) << tag << ": plane switched on under TCP: " << line;
      EXPECT_TRUE(length) << tag << ": plane without the length offset: " << line;
      in_plane = true;
      ++planes;
    }
    if (l.find(plane.second) != std::string::npos) in_plane = false;
    const bool feed = std::regex_search(line, feed_re) && line.find("FMAX") == std::string::npos;
    if (in_plane) EXPECT_FALSE(tcp) << tag << ": TCP in force inside a plane: " << line;
    if (feed && !in_plane) {
      EXPECT_TRUE(tcp) << tag << ": a feed block outside the planes without TCP: " << line;
      ++tcp_feeds;
    }
    if (feed && in_plane) ++plane_feeds;
  }
  EXPECT_GT(tcp_feeds, 0) << tag;
  EXPECT_GT(plane_feeds, 0) << tag;
  return planes;
}

/// (d): the first plane's angle word that tilts its Z changed by 0.1 deg (Fanuc J, Siemens CYCLE800 A, Heidenhain
/// SPA). Haas G254 has no angle word (the control carries the work offset with the rotaries): nothing to bend.
std::optional<std::string> bent_plane(std::string text, const std::string& dialect) {
  const std::map<std::string, std::string> patterns{{"fanuc", "G68\\.2 [^\\n]* J(-?[0-9]+\\.[0-9]+)"},
                                                    {"siemens", "CYCLE800\\(0,\"TC1\",0,57,0,0,0,(-?[0-9]+\\.[0-9]+)"},
                                                    {"heidenhain", "PLANE SPATIAL SPA([-+][0-9]+\\.[0-9]+)"}};
  const auto it = patterns.find(dialect);
  if (it == patterns.end()) return std::nullopt;
  std::smatch mt;
  if (!std::regex_search(text, mt, std::regex(it->second))) return std::nullopt;
  const double bent = std::stod(mt.str(1)) + 0.1;
  text.replace(static_cast<size_t>(mt.position(1)), static_cast<size_t>(mt.length(1)),
               dialect == "heidenhain" ? fmt::format("{:+.4f}", bent) : fmt::format("{:.4f}", bent));
  return text;
}

}  // namespace

TEST(PostWorkPlane, UnderTcpEachPlaneRunsWithTcpCancelledAndReadsBackToTheMachineProgram) {
  // The faces between simultaneous stretches posted under TCP with tilted planes: the simultaneous stretches under
  // TCP, each fixed face in the dialect's plane with TCP cancelled. Oracles: the safety gate; the tips of the
  // read-back axes (FK) against the machine-coordinate program of the same CL; the TCP words on the text; `cscam
  // verify` refuses a plane bent by 0.1 deg.
  const cl::Program prog = cl::read_text(faces_between_simultaneous_cl(), "faces.cls");
  const fs::path dir = fs::temp_directory_path() / ("cscam_tcp_plane_" + std::to_string(::getpid()));
  fs::create_directories(dir);
  const std::string cl_path = (dir / "faces.cls").string();
  std::ofstream(cl_path) << faces_between_simultaneous_cl();
  double worst_tip_mm = 0.0, worst_rot_rad = 0.0, worst_cl_mm = 0.0, worst_vector_rad = 0.0;
  for (const char* name : {"haas-umc750", "trunnion-ac"}) {
    for (const auto& [dialect, codes] : plane_codes()) {
      for (const std::string form : {"angles", "vectors"}) {
        if (form == "vectors" && dialect != "fanuc" && dialect != "siemens") continue;  // the others write angles
        const std::string tag = std::string(name) + "-" + dialect + "-" + form;
        SCOPED_TRACE(tag);
        const std::string extra = "  tcp_form: " + form + "\n";
        const auto m = machine_with_post(name, extra);
        const auto k = m.kinematics();
        post::Options o;
        o.dialect = dialect;
        o.work_plane = "tilted";
        o.tcp = true;
        Posted p;
        std::ostringstream os;
        post::write_nc(os, prog, m, *k, post::conventional_axes(prog, m, *k), o, p.summary);
        p.text = os.str();
        const Posted q = post_with_plane(prog, m, *k, dialect, "machine");  // machine coordinates, no TCP
        EXPECT_EQ(p.summary.work_planes, 3u);
        EXPECT_EQ(count_of(p.text, codes.first), 3u) << p.text;
        EXPECT_EQ(count_of(p.text, codes.second), 3u) << p.text;
        if (form == "vectors") EXPECT_NE(p.text.find(dialect == "fanuc" ? "G43.5 H" : "ORIVECT"), std::string::npos);
        // (a) the safety gate passes the program
        const auto gs = gate::check(p.text, tag, prog, m, *k, gate::options_for(m, 0, 0, 0));
        EXPECT_TRUE(gs.ok) << gs.message << "\n" << p.text;
        EXPECT_TRUE(gs.tool_tip_control);
        expect_every_cl_point_reached(p.text, prog, m, *k, tag);
        // (b) the tip path, read back, against the machine-coordinate program's: every feed sample within the post
        // tolerance of its feed path; at every CL point the same tip and the same rotaries
        const auto mixed = machine_blocks(p.text, m, *k, tag), machine = machine_blocks(q.text, m, *k, tag + "-m");
        const auto ours = feed_samples(mixed, *k, 16), theirs = feed_samples(machine, *k, 32);
        ASSERT_FALSE(ours.empty());
        ASSERT_GT(theirs.size(), 1u);
        double tip_mm = 0.0;
        for (const Vec3& s : ours) {
          double d = std::numeric_limits<double>::infinity();
          for (size_t j = 1; j < theirs.size(); ++j) d = std::min(d, segment_distance(s, theirs[j - 1], theirs[j]));
          tip_mm = std::max(tip_mm, d);
        }
        EXPECT_LE(tip_mm, m.post.tolerance_mm + tol::kVerifySlackMm) << tag;
        double rot_rad = 0.0, cl_mm = 0.0, vector_rad = 0.0;
        for (const auto& mv : prog.moves) {
          const MachineBlock &a = nearest_block(mixed, mv.tip_in_part_mm),
                             &b = nearest_block(machine, mv.tip_in_part_mm);
          cl_mm =
              std::max({cl_mm, (a.pose.tip_mm - mv.tip_in_part_mm).norm(), (b.pose.tip_mm - mv.tip_in_part_mm).norm()});
          if (form == "vectors" && a.tcp) {  // the control picks the rotaries of a vector (here a winding apart)
            vector_rad = std::max(vector_rad, std::acos(std::clamp(a.pose.axis.dot(b.pose.axis), -1.0, 1.0)));
            continue;
          }
          for (int r : k->rotary_pair()) rot_rad = std::max(rot_rad, std::abs(a.q[r] - b.q[r]));
        }
        EXPECT_LE(cl_mm, m.post.tolerance_mm) << tag;
        EXPECT_LE(rot_rad, 1e-9) << tag;  // the same rotary words (angles form; machine words in the planes)
        EXPECT_LE(vector_rad, deg2rad(1e-3)) << tag;  // 6-decimal vectors
        worst_tip_mm = std::max(worst_tip_mm, tip_mm);
        worst_rot_rad = std::max(worst_rot_rad, rot_rad);
        worst_cl_mm = std::max(worst_cl_mm, cl_mm);
        worst_vector_rad = std::max(worst_vector_rad, vector_rad);
        // (c) TCP cancelled exactly around the planes
        EXPECT_EQ(expect_tcp_off_exactly_in_planes(p.text, dialect, tag), 3);
        // (d) cscam verify reads the program, and refuses it with one plane angle bent by 0.1 deg
        const std::string machine_path = (dir / (tag + ".yaml")).string();
        {
          std::ifstream in(test::source_path(std::string("machines/") + name + ".yaml"));
          std::stringstream ss;
          ss << in.rdbuf();
          std::string y = ss.str();
          y.insert(y.find("\npost:\n") + 7, extra);
          std::ofstream(machine_path) << y;
        }
        const std::string good = (dir / (tag + ".nc")).string();
        std::ofstream(good) << p.text;
        auto r =
            test::run_command(fmt::format("{} verify {} --machine {} --cl {}", CSCAM_CLI, good, machine_path, cl_path));
        EXPECT_EQ(r.status, 0) << r.output;
        EXPECT_EQ(r.output.rfind("OK:", 0), 0u) << r.output;
        if (const auto bent = bent_plane(p.text, dialect)) {
          const std::string bad = (dir / (tag + "-bent.nc")).string();
          std::ofstream(bad) << *bent;
          r = test::run_command(
              fmt::format("{} verify {} --machine {} --cl {}", CSCAM_CLI, bad, machine_path, cl_path));
          EXPECT_NE(r.status, 0) << r.output;
          EXPECT_NE(r.output.find("the Z axis of"), std::string::npos) << r.output;
          EXPECT_FALSE(gate::check(*bent, tag + "-bent", prog, m, *k, gate::options_for(m, 0, 0, 0)).ok);
        } else {
          EXPECT_EQ(dialect, "haas");
        }
      }
    }
  }
  // The figures for the record: tip of the read-back TCP + plane program against the machine-coordinate program.
  std::cout << fmt::format(
      "[ figures  ] tcp+plane vs machine program: max tip deviation {:.5f} mm, max rotary "
      "difference {:.6f} deg (vector form under TCP: tool axis {:.6f} deg), max tip distance to "
      "a CL point {:.5f} mm\n",
      worst_tip_mm, rad2deg(worst_rot_rad), rad2deg(worst_vector_rad), worst_cl_mm);
  fs::remove_all(dir);
}

TEST(PostWorkPlane, APlaneWhileTcpIsOnIsNotRead) {
  // A control refuses a tilted plane under TCP: so does the reader (the post cancels TCP first).
  const cl::Program prog = cl::read_text(faces_between_simultaneous_cl(), "faces.cls");
  const auto m = load_machine("trunnion-ac");
  const auto k = m.kinematics();
  post::Options o;
  o.dialect = "fanuc";
  o.work_plane = "tilted";
  o.tcp = true;
  post::Summary sum;
  std::ostringstream os;
  post::write_nc(os, prog, m, *k, post::conventional_axes(prog, m, *k), o, sum);
  std::string text = os.str();
  // the TCP cancel (and the plain length after it) before the plane after the first simultaneous stretch
  const size_t g49 = text.find("G49\nG43 H");
  ASSERT_NE(g49, std::string::npos) << text;
  text.erase(g49, text.find('\n', g49 + 4) + 1 - g49);
  const auto gs = gate::check(text, "under-tcp.nc", prog, m, *k, gate::options_for(m, 0, 0, 0));
  EXPECT_FALSE(gs.ok);
  EXPECT_NE(gs.message.find("under tool-tip control is not read"), std::string::npos) << gs.message;
}

TEST(PostWorkPlane, LinuxcncUnderTcpKeepsItsTcpFormWithAWarning) {
  // linuxcnc has no tilted plane: under TCP every stretch stays under M428, the same bytes as without planes.
  const cl::Program prog = cl::read_text(faces_between_simultaneous_cl(), "faces.cls");
  const auto m = load_machine("trunnion-ac");
  const auto k = m.kinematics();
  std::string text[2];
  post::Summary sum[2];
  for (int i = 0; i < 2; ++i) {
    post::Options o;
    o.dialect = "linuxcnc";
    o.work_plane = i == 0 ? "tilted" : "machine";
    o.tcp = true;
    std::ostringstream os;
    post::write_nc(os, prog, m, *k, post::conventional_axes(prog, m, *k), o, sum[i]);
    text[i] = os.str();
  }
  EXPECT_EQ(text[0], text[1]);
  EXPECT_EQ(sum[0].work_planes, 0u);
  EXPECT_EQ(count_of(text[0], "M428"), 1u);
  EXPECT_EQ(std::count_if(sum[0].warnings.begin(), sum[0].warnings.end(),
                          [](const std::string& w) {
                            return w.find(
                                       "has no tilted work plane: 3+2 stretches are written under tool-tip "
                                       "control") != std::string::npos;
                          }),
            1);
  const auto gs = gate::check(text[0], "linuxcnc-tcp", prog, m, *k, gate::options_for(m, 0, 0, 0));
  EXPECT_TRUE(gs.ok) << gs.message;
}

TEST(PostWorkPlane, UnderTcpAJobOfPlanesOnlyIsThePlaneProgram) {
  // NX's zigzag turned into one 3+2 face: under TCP with planes every stretch would run with TCP cancelled, so the post
  // writes the non-TCP plane program itself, byte for byte (no TCP word switched on and off again before the first
  // motion, no Cartesian header that the program never uses), and says so in a warning.
  const cl::Program flat = cl::read_file(test::source_path("examples/nx-haas-umc750/zigzag_smoothed.cls"));
  const Eigen::Matrix3d R =
      (Eigen::AngleAxisd(deg2rad(10.0), Vec3::UnitZ()) * Eigen::AngleAxisd(deg2rad(25.0), Vec3::UnitX()))
          .toRotationMatrix();
  const cl::Program prog = turned(flat, R, Vec3(0, -40, -30));
  const auto m = machine_with_post("haas-umc750", "  arcs: false\n");
  const auto k = m.kinematics();
  for (const auto& [dialect, codes] : plane_codes()) {
    SCOPED_TRACE(dialect);
    post::Options o;
    o.dialect = dialect;
    o.work_plane = "tilted";
    o.tcp = true;
    post::Summary sum;
    std::ostringstream os;
    post::write_nc(os, prog, m, *k, post::conventional_axes(prog, m, *k), o, sum);
    const std::string text = os.str();
    const Posted q = post_with_plane(prog, m, *k, dialect, "tilted");
    EXPECT_GE(sum.work_planes, 1u);
    EXPECT_EQ(text, q.text);
    EXPECT_TRUE(std::any_of(sum.warnings.begin(), sum.warnings.end(), [](const std::string& w) {
      return w.find("every stretch is cut in a tilted work plane") != std::string::npos;
    }));
    const auto gs = gate::check(text, "nx-tcp-" + dialect, prog, m, *k, gate::options_for(m, 0, 0, 0));
    EXPECT_TRUE(gs.ok) << gs.message;
    EXPECT_FALSE(gs.tool_tip_control);
    expect_every_cl_point_reached(text, prog, m, *k, "nx-tcp-" + dialect);
  }
}

// --- CL arcs inside tilted work planes ----------------------------------------------------------------------

namespace {

/// Circles on a face tilted 25 deg about X and 10 deg about Z (3+2), between two simultaneous stretches. In the
/// face's own frame (R, t: part = R local + t): a quarter counter-clockwise about the origin (radius 10), a half
/// clockwise about (0, 15) (radius 5), a half helix down 1 mm counter-clockwise about (0, 10) (radius 10), all with
/// normals along the face's Z, then a half circle standing in the face's XZ plane about (-5, 0, -1) (normal along
/// its Y: no arc of the plane's XY). The path never runs back over itself (the gate follows the CL in order).
struct TiltedPocket {
  Eigen::Matrix3d R;
  Vec3 t;
  std::string cl;
};

TiltedPocket tilted_pocket() {
  TiltedPocket p;
  p.R = (Eigen::AngleAxisd(deg2rad(10.0), Vec3::UnitZ()) * Eigen::AngleAxisd(deg2rad(25.0), Vec3::UnitX()))
            .toRotationMatrix();
  p.t = Vec3(10, -20, 0);
  const Vec3 a = p.R * Vec3::UnitZ();
  const auto part = [&](const Vec3& local) { return Vec3(p.R * local + p.t); };
  const auto go = [&](const Vec3& local) {
    const Vec3 q = part(local);
    return fmt::format("GOTO/{:.7f},{:.7f},{:.7f},{:.7f},{:.7f},{:.7f}\n", q.x(), q.y(), q.z(), a.x(), a.y(), a.z());
  };
  // NX's CIRCLE/ runs clockwise about its i,j,k (cl reader): -Z of the face is counter-clockwise seen from its +Z.
  const auto circle = [&](const Vec3& centre_local, const Vec3& normal_local, double r) {
    const Vec3 c = part(centre_local), n = p.R * normal_local;
    return fmt::format("CIRCLE/{:.7f},{:.7f},{:.7f},{:.7f},{:.7f},{:.7f},{},0.01\n", c.x(), c.y(), c.z(), n.x(), n.y(),
                       n.z(), r);
  };
  p.cl =
      "UNITS/MM\nMULTAX\nFEDRAT/MMPM,800\nRAPID\nGOTO/0,-60,20,0,0,1\nGOTO/10,-60,20,0.1,0,0.9949874\n"
      "GOTO/20,-60,20,0.2,0,0.9797959\nRAPID\n" +
      go({10, 0, 5}) + go({10, 0, 0}) + circle({0, 0, 0}, {0, 0, -1}, 10) + go({0, 10, 0}) +
      circle({0, 15, 0}, {0, 0, 1}, 5) + go({0, 20, 0}) + circle({0, 10, 0}, {0, 0, -1}, 10) + go({0, 0, -1}) +
      circle({-5, 0, -1}, {0, 1, 0}, 5) + go({-10, 0, -1}) + go({-10, 0, 5}) +
      "RAPID\nGOTO/0,0,25,-0.1,0.25,0.9630680\nGOTO/10,0,25,0,0.2,0.9797959\nGOTO/20,0,25,0.1,0.2,0.9746794\n"
      "FINI\n";
  return p;
}

/// The lines of a program without sequence numbers (N10, Heidenhain's leading block numbers).
std::vector<std::string> unnumbered_lines(const std::string& text) {
  std::vector<std::string> out;
  std::istringstream in(text);
  for (std::string l; std::getline(in, l);) out.push_back(std::regex_replace(l, std::regex("^N?[0-9]+ "), ""));
  return out;
}

}  // namespace

TEST(PostWorkPlane, CirclesInAPlaneBecomeArcsInItsCoordinatesAndReadBackOnTheClCircle) {
  const TiltedPocket pocket = tilted_pocket();
  const cl::Program prog = cl::read_text(pocket.cl, "pocket.cls");
  ASSERT_EQ(prog.arcs.size(), 4u);
  const std::regex arc_block("(^| )G[23] ");
  double worst_mm = 0.0;
  for (const char* name : {"haas-umc750", "trunnion-ac"}) {
    const auto m = load_machine(name);
    const auto k = m.kinematics();
    const auto m_points = machine_with_post(name, "  arcs: false\n");
    for (const auto& [dialect, codes] : plane_codes()) {
      const std::string tag = std::string(name) + "-" + dialect;
      SCOPED_TRACE(tag);
      const Posted p = post_with_plane(prog, m, *k, dialect, "tilted");
      ASSERT_EQ(p.summary.work_planes, 1u) << p.text;
      // Heidenhain writes no arcs at all (its CC / C form is not written): points, in the plane as outside. Haas G254
      // keeps machine words, so the machine-coordinate rules: the arcs of the machine-word program (the standing half
      // circle too where the rotaries turn its plane into a machine plane).
      const std::size_t want = dialect == "heidenhain" ? 0u
                               : dialect == "haas" ? post_with_plane(prog, m, *k, dialect, "machine").summary.arc_blocks
                                                   : 3u;
      EXPECT_GE(want, dialect == "heidenhain" ? 0u : 3u);
      EXPECT_EQ(p.summary.arc_blocks, want) << p.text;
      // (a) the arc blocks are inside the plane stretch (and only there)
      const auto lines = unnumbered_lines(p.text);
      std::size_t on = lines.size(), off = lines.size(), inside = 0, outside = 0;
      for (std::size_t i = 0; i < lines.size(); ++i) {
        const std::string l = lines[i] + "\n";
        if (on == lines.size() && l.find(codes.first) != std::string::npos) on = i;
        if (on < lines.size() && off == lines.size() && l.find(codes.second) != std::string::npos) off = i;
        if (std::regex_search(lines[i], arc_block)) (on < i && off == lines.size() ? inside : outside) += 1;
      }
      ASSERT_LT(off, lines.size()) << p.text;
      EXPECT_EQ(inside, want) << p.text;
      EXPECT_EQ(outside, 0u) << p.text;
      if (dialect == "fanuc" || dialect == "siemens") {  // the plane's own XY
        EXPECT_NE(p.text.find("G17"), std::string::npos) << p.text;
      }
      // (e) outside the plane stretch the program is the one with arcs off
      const Posted q = post_with_plane(prog, m_points, *m_points.kinematics(), dialect, "tilted");
      const auto q_lines = unnumbered_lines(q.text);
      ASSERT_GE(q_lines.size(), lines.size() - off);
      EXPECT_TRUE(std::equal(lines.begin(), lines.begin() + static_cast<std::ptrdiff_t>(on + 1), q_lines.begin()));
      EXPECT_TRUE(std::equal(lines.begin() + static_cast<std::ptrdiff_t>(off), lines.end(),
                             q_lines.end() - static_cast<std::ptrdiff_t>(lines.size() - off)))
          << p.text << "\n----\n"
          << q.text;
      if (want == 0) EXPECT_EQ(p.text, q.text);
      // (b) the gate passes
      const auto gs = gate::check(p.text, tag, prog, m, *k, gate::options_for(m, 0, 0, 0));
      EXPECT_TRUE(gs.ok) << gs.message << "\n" << p.text;
      // (c) read back, the arcs sampled: each point on its CL circle, in the face's frame (the helix at the height
      // its angle gives). (d) the standing half circle is no arc block in plane coordinates.
      const nc::Program ncp = report::read_for_machine(p.text, tag, m);
      std::size_t n_arcs = 0;
      for (std::size_t bi = 1; bi < ncp.blocks.size(); ++bi) {
        const nc::Block& b = ncp.blocks[bi];
        if (!b.arc) continue;
        ASSERT_LT(n_arcs, 4u);
        for (int s = 0; s <= 64; ++s) {
          const auto a = nc::point_on(ncp.blocks[bi - 1].axes, b, s / 64.0);
          kin::Axes qa;
          for (int i = 0; i < 5; ++i) qa[i] = a[static_cast<size_t>(i)];
          const Vec3 local = pocket.R.transpose() * (k->forward(qa).tip_mm - pocket.t);
          double d = 0.0;
          if (n_arcs == 0) {
            d = std::hypot(std::hypot(local.x(), local.y()) - 10.0, local.z());
            EXPECT_GE(std::min(local.x(), local.y()), -1e-3);  // the first quadrant
          } else if (n_arcs == 1) {
            d = std::hypot(std::hypot(local.x(), local.y() - 15.0) - 5.0, local.z());
            EXPECT_LE(local.x(), 1e-3);  // clockwise from (0, 10): through (-5, 15)
          } else if (n_arcs == 2) {
            double ang = std::atan2(local.y() - 10.0, local.x());  // pi/2 .. 3 pi/2, counter-clockwise
            if (ang < 0.0) ang += 2.0 * kPi;
            d = std::hypot(std::hypot(local.x(), local.y() - 10.0) - 10.0, local.z() + (ang - 0.5 * kPi) / kPi);
            EXPECT_LE(local.x(), 1e-3);
          } else {  // Haas: the standing half circle in machine words
            const Vec3 c = local - Vec3(-5, 0, -1);
            d = std::hypot(std::hypot(c.x(), c.z()) - 5.0, c.y());
          }
          worst_mm = std::max(worst_mm, d);
          EXPECT_LT(d, m.post.tolerance_mm) << "arc " << n_arcs << " sample " << s << " at " << local.transpose();
        }
        ++n_arcs;
      }
      EXPECT_EQ(n_arcs, want);
      // the gate reads the arcs: a centre moved 0.1 mm along the plane's X inside it is refused
      if (want > 0) {
        const std::regex first_i(R"((\n[^\n]*G[23] [^\n]* I)(-?[0-9]+\.[0-9]+))");
        std::smatch mt;
        ASSERT_TRUE(std::regex_search(p.text, mt, first_i));
        std::string moved = p.text;
        moved.replace(static_cast<size_t>(mt.position(2)), static_cast<size_t>(mt.length(2)),
                      fmt::format("{:.4f}", std::stod(mt.str(2)) + 0.1));
        const auto ms = gate::check(moved, tag + "-moved", prog, m, *k, gate::options_for(m, 0, 0, 0));
        EXPECT_FALSE(ms.ok) << mt.str(0);
        EXPECT_NE(ms.message.find("tool tip leaves the CL path"), std::string::npos) << ms.message;
      }
      // the gate still refuses a plane bent by 0.1 deg with arcs in it
      if (const auto bent = bent_plane(p.text, dialect)) {
        const auto bs = gate::check(*bent, tag + "-bent", prog, m, *k, gate::options_for(m, 0, 0, 0));
        EXPECT_FALSE(bs.ok);
        EXPECT_NE(bs.message.find("the Z axis of"), std::string::npos) << bs.message;
      }
    }
  }
  std::cout << fmt::format("[ figures  ] arcs in tilted planes read back: max distance to the CL circle {:.6f} mm\n",
                           worst_mm);
}

// post::can_follow is the post's own rule, asked by the planner before it takes a jump. Beside the XMINI's singular
// orientation (tests/data/xmini_walk_singular.cls, CL lines 25 -> 26) tracking from the A > 0 branch lands on the A < 0
// one; the straight rotary move between those two leaves the axis tolerance (checked here in closed form: the tool axis
// of the interpolated rotaries against the slerp of the CL axes), so the post cannot follow it. The A < 0 branch at
// line 25 runs there continuously (C swings 166 deg while the tool stays within 0.6 deg of the singular direction).
// LinuxCNC's G64 P bounds the joint X Y Z of a blend only: it lifted Z into a retract while A and C still finished
// the cut (docs/linuxcnc.md). The post sets exact path (G61) on the last cut before every retract along the tool
// axis, keeps it through the turn and the plunge, and resumes G64 P on the first cut after; never two words of that
// modal group in one block, and rs274 reads the program as we do. Oracle: the blocks around each G61 and G64 P.
TEST(Post, LinuxcncStopsExactlyAroundARetractAndResumesBlendingAfterThePlunge) {
  const auto m = load_machine("trunnion-ac");
  const auto k = m.kinematics();
  const cl::Program prog = cl::read_file(test::source_path("tests/data/azimuth_turn_at_vertical.cls"));
  const Posted p = post_program(prog, m, *k);
  ASSERT_EQ(p.summary.retracts, 1u);
  std::vector<std::string> lines;
  std::istringstream in(p.text);
  for (std::string l; std::getline(in, l);) lines.push_back(l);
  std::vector<size_t> g61, g64;
  for (size_t i = 0; i < lines.size(); ++i) {
    EXPECT_FALSE(lines[i].find("G61") != std::string::npos && lines[i].find("G64") != std::string::npos) << lines[i];
    if (lines[i].find("G61") != std::string::npos) g61.push_back(i);
    // The post's own P; not where it follows a corner the post narrowed (Post.LinuxcncNarrows... checks those).
    if (lines[i].find(fmt::format("G64 P{:.4f}", m.post.tolerance_mm)) != std::string::npos &&
        (i == 0 || lines[i - 1].find("G64 P") == std::string::npos))
      g64.push_back(i);
  }
  // The flip's retract and the final one; the header's G64 P and the one after the plunge.
  ASSERT_EQ(g61.size(), 2u) << p.text;
  ASSERT_EQ(g64.size(), 2u) << p.text;
  EXPECT_LT(g64[0], g61[0]);
  EXPECT_TRUE(g61[0] < g64[1] && g64[1] < g61[1]);
  auto is_z_only_feed = [](const std::string& l) {
    return l.find("G1") != std::string::npos && l.find('Z') != std::string::npos && l.find('X') == std::string::npos &&
           l.find('Y') == std::string::npos && l.find('A') == std::string::npos && l.find('C') == std::string::npos;
  };
  for (size_t at : g61) {  // a cut, then the retract along the (here vertical) tool axis
    EXPECT_NE(lines[at].find("G1 X"), std::string::npos) << lines[at];
    ASSERT_LT(at + 1, lines.size());
    EXPECT_TRUE(is_z_only_feed(lines[at + 1])) << lines[at + 1];
  }
  // The block before the resumed G64 P is the plunge (a feed along Z), and rapids (the turn) come before it.
  EXPECT_TRUE(is_z_only_feed(lines[g64[1] - 1])) << lines[g64[1] - 1];
  EXPECT_NE(lines[g64[1] - 2].find("G0"), std::string::npos) << lines[g64[1] - 2];
  expect_rs274_agrees(p.text, m, "azimuth-flip");
  const auto v = verify_text(p.text, prog, m, *k);
  EXPECT_TRUE(v.ok) << v.message;
}

TEST(Post, CanFollowRefusesAJumpBesideASingularOrientation) {
  const auto m = load_machine("xmini");
  const auto kin = m.kinematics();
  cl::ReadOptions ro;
  const auto prog = cl::read_file(test::source_path("tests/data/xmini_walk_singular.cls"), ro);
  const cl::Move *m25 = nullptr, *m26 = nullptr;
  for (const auto& mv : prog.moves) {
    if (mv.line == 25) m25 = &mv;
    if (mv.line == 26) m26 = &mv;
  }
  ASSERT_TRUE(m25 && m26);
  const kin::Posed p0{m25->tip_in_part_mm, m25->axis_in_part.normalized()};
  const kin::Posed p1{m26->tip_in_part_mm, m26->axis_in_part.normalized()};
  const auto rp = kin->rotary_pair();
  auto branch = [&](const kin::Posed& p, double sign) {
    std::vector<kin::Solution> sols;
    kin->inverse_branches(p, nullptr, sols);
    for (const auto& s : sols)
      if (sign * s.axes[rp[1]] > 0 && s.feasible()) return s.axes;
    ADD_FAILURE() << "no branch with the secondary's sign " << sign;
    return kin::Axes(kin::Axes::Zero());
  };
  const kin::Axes a_pos = branch(p0, 1), a_neg = branch(p0, -1), b_neg = branch(p1, -1);
  post::Options po;
  po.strategy = "planned";
  const double tol_rad = deg2rad(m.post.axis_tolerance_deg);
  // The oracle: the straight rotary move's tool axis half way against the CL's.
  const kin::Axes mid = 0.5 * (a_pos + b_neg);
  Vec3 u_mid;
  ASSERT_TRUE(kin->tool_axis_at(mid[rp[0]], mid[rp[1]], 0.5 * (p0.tip_mm + p1.tip_mm), u_mid));
  const Vec3 slerp_mid = (p0.axis + p1.axis).normalized();
  EXPECT_GT(std::acos(std::clamp(u_mid.dot(slerp_mid), -1.0, 1.0)), 2.0 * tol_rad);
  EXPECT_FALSE(post::can_follow(*kin, m, po, p0, a_pos, p1, b_neg));
  EXPECT_TRUE(post::can_follow(*kin, m, po, p0, a_neg, p1, b_neg));

  // Given that jump to post (a plan made when no other path exists), the post turns the rotaries with a retract: the
  // rotary change is small (C 13 deg), so it had taken the two ends as one branch and refused the cut inside. The
  // oracle: the safety gate's back-simulation of what it wrote.
  cl::Program two = prog;
  two.moves = {*m25, *m26};
  two.moves[0].kind = cl::MotionKind::Rapid;
  two.moves[1].kind = cl::MotionKind::Feed;
  two.events.clear();
  std::ostringstream os;
  post::Summary sum;
  ASSERT_NO_THROW(post::write_nc(os, two, m, *kin, {a_pos, b_neg}, po, sum));
  EXPECT_EQ(sum.retracts, 1u);
  const auto gs = gate::check(os.str(), "jump.ngc", two, m, *kin, gate::options_for(m, 0, 0, 0));
  EXPECT_TRUE(gs.ok) << gs.message;
}

namespace {

/// The oracle of the corner tests: LinuxCNC's parabolic blend integrated in time (docs/linuxcnc.md), not sampled
/// from the post's closed form. At each corner between two straight G1 blocks the first decelerates to a stop at its
/// end at the acceleration its slowest axis allows, while the second accelerates from its start at its own; the blend
/// speed is the smaller of 2 sqrt(a P / sin(turn / 2)) (P: the first block's G64 P; none under G61, which stops) and
/// the speed that lets the first block use half its length. Returns the largest distance of the tip from the CL
/// polyline over all blends.
double worst_blend_deviation_mm(const std::string& text, const cl::Program& prog, const machine::Machine& m,
                                const kin::Kinematics& k, std::optional<double> force_p = std::nullopt) {
  const nc::Program ncp = nc::read_text(text, "blend.ngc", letters_of(m));
  std::vector<std::string> lines;
  std::istringstream in(text);
  for (std::string l; std::getline(in, l);) lines.push_back(l);
  std::vector<Vec3> cl_pts;
  for (const auto& mv : prog.moves) cl_pts.push_back(mv.tip_in_part_mm);
  auto cl_distance = [&](const Vec3& p) {
    double best = std::numeric_limits<double>::infinity();
    for (size_t i = 1; i < cl_pts.size(); ++i) {
      const Vec3 ab = cl_pts[i] - cl_pts[i - 1];
      const double t = std::clamp((p - cl_pts[i - 1]).dot(ab) / ab.squaredNorm(), 0.0, 1.0);
      best = std::min(best, (cl_pts[i - 1] + t * ab - p).norm());
    }
    return best;
  };
  // The blend mode each block was queued with.
  std::optional<double> p_mode;  // nullopt: G61
  std::vector<std::optional<double>> p_of(ncp.blocks.size());
  for (size_t b = 0, l = 0; b < ncp.blocks.size(); ++b) {
    for (; l < lines.size() && static_cast<int>(l) + 1 <= ncp.blocks[b].line; ++l) {
      if (lines[l].find("G61") != std::string::npos) p_mode.reset();
      if (const auto at = lines[l].find("G64 P"); at != std::string::npos) p_mode = std::stod(lines[l].substr(at + 5));
    }
    p_of[b] = force_p && p_mode ? force_p : p_mode;
  }
  auto q_of = [](const nc::Block& b) {
    kin::Axes q;
    for (int i = 0; i < 5; ++i) q[i] = b.axes[static_cast<size_t>(i)];
    return q;
  };
  // A segment's acceleration along its X Y Z length, as LinuxCNC's canon takes it from the axes' MAX_ACCELERATION
  // (the machine file's max_accel).
  auto accel_of = [&](const kin::Axes& w) {  // w: the move per mm of X Y Z, model units
    double slowest = 0.0;
    for (size_t i = 0; i < 5; ++i) slowest = std::max(slowest, std::abs(w[static_cast<int>(i)]) / m.axes[i].max_accel);
    return 1.0 / slowest;
  };
  double worst = 0.0;
  for (size_t b = 1; b + 1 < ncp.blocks.size(); ++b) {
    const auto &b0 = ncp.blocks[b - 1], &b1 = ncp.blocks[b], &b2 = ncp.blocks[b + 1];
    if (b1.motion != nc::Motion::Linear || b2.motion != nc::Motion::Linear || b1.arc || b2.arc || !p_of[b]) continue;
    const kin::Axes q0 = q_of(b0), q1 = q_of(b1), q2 = q_of(b2);
    const Vec3 d1 = (q1 - q0).head<3>(), d2 = (q2 - q1).head<3>();
    if (d1.norm() < 1e-9 || d2.norm() < 1e-9) continue;
    const kin::Axes w1 = (q1 - q0) / d1.norm(), w2 = (q2 - q1) / d2.norm();
    const double a1 = accel_of(w1), a2 = accel_of(w2);
    const double turn = std::acos(std::clamp(d1.normalized().dot(d2.normalized()), -1.0, 1.0));
    double v = std::sqrt(a1 * std::min(d1.norm(), d2.norm()));  // stops within half the shorter block
    if (turn > 2e-3) v = std::min(v, 2.0 * std::sqrt(a1 * *p_of[b] / std::sin(0.5 * turn)));
    const double T = v / a1;
    for (int s = 0; s <= 400; ++s) {
      const double t = T * s / 400.0;
      const double into_next = std::min(0.5 * a2 * t * t, d2.norm());
      const kin::Axes q = q1 - w1 * (0.5 * a1 * (T - t) * (T - t)) + w2 * into_next;
      worst = std::max(worst, cl_distance(k.forward(q).tip_mm));
    }
  }
  return worst;
}

// Ten points of a random walk (scripts/generate_cl.py seed 46) where C turns 8.6 deg per mm into a corner and 2.2 deg
// per mm out of it: LinuxCNC took the tip 0.064 mm off the path there (docs/linuxcnc.md).
constexpr const char* kRotaryRateJump =
    "UNITS/MM\nMULTAX/ON\nCUTTER/6,3\nLOADTL/1\nFEDRAT/MMPM,1500\n"
    "GOTO/8.3611,12.9081,0.0000,0.056679,0.192065,0.979744\n"
    "GOTO/8.4921,12.9934,0.0000,0.043465,0.195181,0.979804\n"
    "GOTO/8.4098,13.4683,0.0000,0.025003,0.200467,0.979381\n"
    "GOTO/8.7048,12.9524,0.0000,0.031392,0.188502,0.981571\n"
    "GOTO/8.2676,12.9359,0.0000,0.045166,0.188597,0.981015\n"
    "GOTO/8.7321,13.0664,0.0000,0.047454,0.206299,0.977338\n"
    "GOTO/8.1770,12.2077,0.0000,0.042328,0.199878,0.978906\n"
    "GOTO/8.6356,11.4962,0.0000,0.057184,0.190861,0.979950\n"
    "GOTO/8.0368,11.0023,0.0000,0.064907,0.187245,0.980166\n"
    "GOTO/8.8415,10.9874,0.0000,0.070063,0.176710,0.981766\n"
    "GOTO/10.0304,11.1023,0.0000,0.072205,0.184255,0.980223\n";

}  // namespace

TEST(Post, LinuxcncNarrowsTheBlendWhereTheRotaryRateJumps) {
  const auto m = load_machine("trunnion-ac");
  const auto k = m.kinematics();
  const cl::Program prog = cl::read_text(kRotaryRateJump, "rate_jump.cls");
  for (const auto& a : m.axes) ASSERT_GT(a.max_accel, 0.0) << a.name;  // the oracle's segment accelerations
  const Posted p = post_program(prog, m, *k);
  const double tol = m.post.tolerance_mm;
  EXPECT_GT(p.summary.narrowed_corners + p.summary.exact_corners, 0u) << p.text;
  // The negative control: every corner at the post's own P leaves the tolerance (the oracle can fail).
  EXPECT_GT(worst_blend_deviation_mm(p.text, prog, m, *k, tol), 1.5 * tol);
  // As posted, every blend stays within it (the post checks the middle; the oracle the whole blend).
  EXPECT_LE(worst_blend_deviation_mm(p.text, prog, m, *k), tol * (1.0 + 1e-3)) << p.text;
  // No block has two blend words, and the narrowed P holds for the narrowed corners only: as many feed blocks are
  // queued with a P below the post's as there are narrowed corners.
  std::istringstream in(p.text);
  std::optional<double> mode;
  size_t narrowed_blocks = 0;
  for (std::string l; std::getline(in, l);) {
    EXPECT_FALSE(l.find("G61") != std::string::npos && l.find("G64") != std::string::npos) << l;
    if (l.find("G61") != std::string::npos) mode.reset();
    if (const auto at = l.find("G64 P"); at != std::string::npos) mode = std::stod(l.substr(at + 5));
    if (l.find("G1 ") != std::string::npos && mode && *mode < tol - 1e-9) ++narrowed_blocks;
  }
  EXPECT_EQ(narrowed_blocks, p.summary.narrowed_corners);
  expect_rs274_agrees(p.text, m, "rate-jump");
  const auto v = verify_text(p.text, prog, m, *k);
  EXPECT_TRUE(v.ok) << v.message;
  // Under tool-tip control the tip is the X Y Z words, which P bounds: nothing to narrow.
  const Posted tcp = post_program(prog, m, *k, true, true);
  EXPECT_EQ(tcp.summary.narrowed_corners + tcp.summary.exact_corners, 0u);
}

TEST(Post, EveryNcLineIsAttributedOnceWhenBlendWordsAreInserted) {
  // The words of a corner or a retract are inserted into blocks already written: the CL line of each NC line (the
  // gate's messages; 1-based, entry 0 unused) must still count every line once.
  const auto m = load_machine("trunnion-ac");
  const auto k = m.kinematics();
  for (const char* text : {kRotaryRateJump}) {
    const cl::Program prog = cl::read_text(text, "rate_jump.cls");
    const Posted p = post_program(prog, m, *k);
    ASSERT_GT(p.summary.narrowed_corners, 0u);
    EXPECT_EQ(p.summary.cl_line_of_nc_line.size(),
              static_cast<size_t>(std::count(p.text.begin(), p.text.end(), '\n')) + 1);
  }
  const cl::Program flip = cl::read_file(test::source_path("tests/data/azimuth_turn_at_vertical.cls"));
  const Posted p = post_program(flip, m, *k);
  ASSERT_EQ(p.summary.retracts, 1u);
  EXPECT_EQ(p.summary.cl_line_of_nc_line.size(),
            static_cast<size_t>(std::count(p.text.begin(), p.text.end(), '\n')) + 1);
}

// What a control reads differently from what the gate reads, found by trying machine files the examples do not use.
TEST(PostProgram, ControlsReadEveryWordAsTheGateDoes) {
  const cl::Program prog = cl::read_text(synthetic_cl(25.0, 3, 40, 10.0), "words.cls");
  {
    // Fanuc and Haas read "X300" in input increments (0.3 mm): integers keep their point.
    std::ifstream in(test::source_path("machines/trunnion-ac.yaml"));
    std::string text(std::istreambuf_iterator<char>(in), {});
    text = std::regex_replace(text, std::regex("decimals_(linear|rotary): 4"), "decimals_$1: 0");
    // (Whole millimetres and degrees carry no finer tolerance: the post refuses one.)
    text = std::regex_replace(text, std::regex("tolerance_(mm|deg): [0-9.]+"), "tolerance_$1: 1");
    const auto m = machine::load_text(text, test::source_path("machines/trunnion-ac-integers.yaml"));
    const auto k = m.kinematics();
    for (const char* d : {"fanuc", "haas"}) {
      const Posted p = post_program(prog, m, *k, true, std::nullopt, d);
      EXPECT_NE(p.text.find(" Z250.\n"), std::string::npos) << d << "\n" << p.text.substr(0, 900);
      EXPECT_EQ(std::regex_search(p.text, std::regex(" [XYZAC]-?[0-9]+[ \n]")), false) << d;
    }
    // LinuxCNC reads integers as they are.
    const Posted l = post_program(prog, m, *k, true, std::nullopt, "linuxcnc");
    EXPECT_NE(l.text.find(" Z250\n"), std::string::npos) << l.text.substr(0, 900);
  }
  {
    // Sequence numbers stay within N99999 on Fanuc-family controls (numbering starts again).
    const auto m = machine_with_post("trunnion-ac", "  sequence_numbers: true\n  sequence_step: 1000\n");
    const auto k = m.kinematics();
    const Posted p = post_program(prog, m, *k, true, std::nullopt, "fanuc");
    EXPECT_EQ(std::regex_search(p.text, std::regex("\nN[0-9]{6}")), false);
    EXPECT_NE(p.text.find("\nN99000 "), std::string::npos);
  }
  {
    // A '%' in a comment would end the program on a Fanuc control as it loads.
    const cl::Program pct = cl::read_text("UNITS/MM\nPPRINT/50% STEPOVER\nFEDRAT/MMPM,500\nGOTO/0,0,10\n", "p.cls");
    const auto m = machine::load(test::source_path("machines/trunnion-ac.yaml"));
    const Posted p = post_program(pct, m, *m.kinematics(), true, std::nullopt, "fanuc");
    EXPECT_NE(p.text.find("(50_ STEPOVER)"), std::string::npos) << p.text;
    EXPECT_EQ(std::count(p.text.begin(), p.text.end(), '%'), 2) << p.text;  // the tape marks only
  }
  {
    // Siemens in inches: G700 (feeds in inches too), read back as inches by the gate.
    const auto m = machine_with_post("trunnion-ac", "  inch: true\n");
    const auto k = m.kinematics();
    const Posted p = post_program(prog, m, *k, true, std::nullopt, "siemens");
    EXPECT_NE(p.text.find("\nG700 G90"), std::string::npos) << p.text.substr(0, 600);
    const auto gs = gate::check(p.text, "si.mpf", prog, m, *k, gate::options_for(m, 0, 0, 0));
    EXPECT_TRUE(gs.ok) << gs.message;
  }
  {
    // G54.1 P<n> is not a LinuxCNC (or Sinumerik) work offset.
    const auto m = machine_with_post("trunnion-ac", "  work_offset: G54.1 P300\n");
    const auto k = m.kinematics();
    for (const char* d : {"linuxcnc", "siemens"}) {
      try {
        (void)post_program(prog, m, *k, true, std::nullopt, d);
        FAIL() << d << ": expected an error";
      } catch (const InputError& e) {
        EXPECT_NE(std::string(e.what()).find("post.work_offset G54.1 P300"), std::string::npos) << e.what();
      }
    }
    EXPECT_NE(post_program(prog, m, *k, true, std::nullopt, "fanuc").text.find("\nG54.1 P300\n"), std::string::npos);
  }
}

// Under tool-tip control the tool leaves along its axis up to the safe Z. With the head tilted 70 deg that point lies a
// metre out in X: the retract stops inside the travel (with a warning) instead of the program being refused.
TEST(PostProgram, ATcpRetractAlongASteepToolStopsAtTheTravel) {
  const std::string yaml =
      "name: ht-bc\nkinematics: serial\ntool_direction: [0, 0, 1]\nspindle_gauge_mm: [0, 0, 200]\n"
      "part_origin_mm: [0, 0, 0]\ndefault_tool_length_mm: 100\naxes:\n"
      "  - {name: x, type: linear, side: head, direction: [1, 0, 0], limits: [-500, 500], max_feed: 20000}\n"
      "  - {name: y, type: linear, side: head, direction: [0, 1, 0], limits: [-500, 500], max_feed: 20000}\n"
      "  - {name: z, type: linear, side: head, direction: [0, 0, 1], limits: [-400, 400], max_feed: 20000}\n"
      "  - {name: b, type: rotary, side: head, direction: [0, 1, 0], pivot_mm: [0, 0, 350], limits: [-100, 100], "
      "max_feed: 5000}\n"
      "  - {name: c, type: rotary, side: table, direction: [0, 0, -1], pivot_mm: [0, 0, 0], limits: [-360, 360], "
      "max_feed: 10000}\n"
      "chains:\n  table: [c]\n  head: [x, y, z, b]\npost:\n  dialect: linuxcnc\n  tcp: true\n"
      "  letters: {x: X, y: Y, z: Z, b: B, c: C}\n  safe_z_mm: 150\n  singularity: {flip: auto, retract_mm: 10}\n";
  const auto m = machine::load_text(yaml, test::source_path("machines/ht-bc.yaml"));
  const auto k = m.kinematics();
  std::ostringstream cl;
  cl << "UNITS/MM\nMULTAX/ON\nFEDRAT/MMPM,1000\n";
  for (int i = 0; i <= 20; ++i) {  // along a ring whose normal tilts 70 deg from Z
    const double c = deg2rad(3.0 * i), t = deg2rad(70.0);
    const Vec3 n(std::sin(t) * std::cos(c), std::sin(t) * std::sin(c), std::cos(t));
    cl << "GOTO/" << 30 * std::cos(c) << "," << 30 * std::sin(c) << ",0," << n.x() << "," << n.y() << "," << n.z()
       << "\n";
  }
  const cl::Program prog = cl::read_text(cl.str(), "ring.cls");
  for (const char* d : {"linuxcnc", "fanuc", "siemens", "heidenhain"}) {
    SCOPED_TRACE(d);
    const Posted p = post_program(prog, m, *k, true, true, d);
    const auto gs = gate::check(p.text, "ring.ngc", prog, m, *k, gate::options_for(m, 0, 0, 0));
    EXPECT_TRUE(gs.ok) << gs.message;
    const bool warned = std::any_of(p.summary.warnings.begin(), p.summary.warnings.end(), [](const std::string& w) {
      return w.find("stops at the machine's travel") != std::string::npos;
    });
    EXPECT_TRUE(warned);
  }
}

namespace {

/// machines/NAME.yaml with each (from, to) text replaced, as a calibration writes its corrected file.
machine::Machine machine_edited(const std::string& name,
                                const std::vector<std::pair<std::string, std::string>>& edits) {
  std::ifstream in(test::source_path("machines/" + name + ".yaml"));
  std::stringstream ss;
  ss << in.rdbuf();
  std::string text = ss.str();
  for (const auto& [from, to] : edits) {
    const size_t p = text.find(from);
    EXPECT_NE(p, std::string::npos) << from;
    if (p != std::string::npos) text.replace(p, from.size(), to);
  }
  return machine::load_text(text, test::source_path("machines/" + name + "-calibrated.yaml"));
}

}  // namespace

// The start of gen/hemi.cls (scripts/generate_cl.py): the tool normal to a sphere, from the vertical tilting away while
// its azimuth turns. On a trunnion whose C is tilted 0.5 mrad (and A 0.3 mrad), axes within about 0.4 mrad of C are
// out of reach, and the path from the first point to the second passes through them: "no inverse-kinematics solution"
// at the second point, where the nominal machine posts it. Now the machine takes the nearest axis there. The oracle is
// the safety gate's back-simulation (tip and axis within the tolerances of the CL path in every block).
TEST(Post, ACalibratedTrunnionPostsAPathThroughTheAxesItCannotReachExactly) {
  std::ostringstream cl;
  cl << "PARTNO HEMI\nUNITS/MM\nMULTAX/ON\nCUTTER/6,3\nLOADTL/1\nSPINDL/8000,CLW\nFEDRAT/MMPM,1500\nRAPID\n";
  for (int i = 0; i <= 80; ++i) {
    const double tilt = deg2rad(0.05 * i), az = 0.08 * i;
    const Vec3 n(std::sin(tilt) * std::cos(az), std::sin(tilt) * std::sin(az), std::cos(tilt));
    cl << fmt::format("GOTO/{:.4f},{:.4f},{:.4f},{:.6f},{:.6f},{:.6f}\n", 20 * n.x(), 20 * n.y(), 20 * n.z(), n.x(),
                      n.y(), n.z());
  }
  cl << "FINI\n";
  const auto prog = cl::read_text(cl.str(), "hemi.cls");
  const std::string c_nominal = "direction: [0, 0, 1], pivot_mm: [0, 0, 0]";
  const std::string a_nominal = "direction: [1, 0, 0], pivot_mm: [0, 20, 10]";
  const std::vector<std::vector<std::pair<std::string, std::string>>> variants = {
      {},
      {{c_nominal, "direction: [0.0004, -0.0003, 1], pivot_mm: [0.02, -0.01, 0]"}},
      {{c_nominal, "direction: [0.0004, -0.0003, 1], pivot_mm: [0.02, -0.01, 0]"},
       {a_nominal, "direction: [1, 0.0003, 0.0001], pivot_mm: [0.01, 20.03, 9.98]"}},
      {{c_nominal, "direction: [-0.00045, 0, 1], pivot_mm: [0, 0, 0]"}}};
  for (std::size_t v = 0; v < variants.size(); ++v) {
    SCOPED_TRACE(::testing::Message() << "variant " << v);
    const auto m = machine_edited("trunnion-ac", variants[v]);
    const auto k = m.kinematics();
    Posted p;
    ASSERT_NO_THROW(p = post_program(prog, m, *k));
    const auto gs = gate::check(p.text, "hemi.ngc", prog, m, *k, gate::options_for(m, 0, 0, 0));
    EXPECT_TRUE(gs.ok) << gs.message;
  }
}

// A path that tilts toward +X, stands vertical, then tilts toward +Y (a 3+2 face meeting a 5-axis flank, or
// gen/walk.cls passing the vertical). The ideal trunnion keeps C at the vertical and turns it once, a quarter turn.
// With C tilted 0.5 mrad the vertical fixed C to values of its own, and C swung there and back (the walks of
// scripts/generate_cl.py: 30-60 % more rotary travel on every calibrated serial machine). Now the calibrated machine
// turns C about as far as the ideal one, and as often; the oracle for the program is the gate.
TEST(Post, ACalibratedTrunnionTurnsCAtTheVerticalAsLittleAsTheIdealOne) {
  std::ostringstream cl;
  cl << "PARTNO VERTICAL\nUNITS/MM\nMULTAX/ON\nCUTTER/6,3\nLOADTL/1\nSPINDL/8000,CLW\nFEDRAT/MMPM,1500\nRAPID\n";
  for (int i = -20; i <= 20; ++i) {
    const double tilt = deg2rad(0.1 * std::abs(i));
    const Vec3 n = i < 0 ? Vec3(std::sin(tilt), 0, std::cos(tilt)) : Vec3(0, std::sin(tilt), std::cos(tilt));
    cl << fmt::format("GOTO/{:.4f},{:.4f},0,{:.6f},{:.6f},{:.6f}\n", 30.0 + 0.5 * std::min(i, 0),
                      -10.0 + 0.5 * std::max(i, 0), n.x(), n.y(), n.z());
  }
  cl << "FINI\n";
  const auto prog = cl::read_text(cl.str(), "vertical.cls");
  double nominal_travel = 0;
  std::size_t nominal_retracts = 0;
  for (const bool calibrated : {false, true}) {
    SCOPED_TRACE(calibrated ? "calibrated" : "nominal");
    const auto m = machine_edited(
        "trunnion-ac",
        calibrated
            ? std::vector<std::pair<std::string, std::string>>{{"direction: [0, 0, 1], pivot_mm: [0, 0, 0]",
                                                                "direction: [0.0004, -0.0003, 1], pivot_mm: [0.02, "
                                                                "-0.01, 0]"}}
            : std::vector<std::pair<std::string, std::string>>{});
    const auto k = m.kinematics();
    const int c = m.axis_index("c");
    const auto axes = post::conventional_axes(prog, m, *k);
    double travel = 0;
    for (std::size_t i = 1; i < axes.size(); ++i) travel += std::abs(axes[i][c] - axes[i - 1][c]);
    if (!calibrated) {
      nominal_travel = travel;
      EXPECT_NEAR(rad2deg(travel), 90.0, 1.0);
    } else {
      EXPECT_LT(travel, nominal_travel + deg2rad(10.0))
          << rad2deg(travel) << " deg against " << rad2deg(nominal_travel);
    }
    std::ostringstream os;
    post::Summary sum;
    ASSERT_NO_THROW(post::write_nc(os, prog, m, *k, axes, post::Options{}, sum));
    if (!calibrated) nominal_retracts = sum.retracts;  // the quarter turn away from the C axis: a retract
    EXPECT_EQ(sum.retracts, nominal_retracts);
    const auto gs = gate::check(os.str(), "vertical.ngc", prog, m, *k, gate::options_for(m, 0, 0, 0));
    EXPECT_TRUE(gs.ok) << gs.message;
  }
}

// A retract, turn and plunge at a point where the machine reaches the CL axis only approximately (C tilted 1.5 mrad:
// the vertical tool is 0.09 deg out of reach). The plunge ran along the CL axis, beside the tool's own, 0.015 mm off
// it over 10 mm, and the gate (rightly) measured it as a cut 10 mm off the path: the program was refused. Out and in
// now follow the axis the machine has at each end of the turn; the gate passes the program, as on the ideal machine.
TEST(Post, ARetractOnACalibratedMachineRunsAlongItsOwnToolAxis) {
  const auto prog = cl::read_text(
      "UNITS/MM\nMULTAX\nCUTTER/10,0\nFEDRAT/MMPM,1000\nRAPID\nGOTO/0,0,50,0,0,1\nGOTO/0,0,5,0,0,1\n"
      "GOTO/10,0,5,0,0,1\nGOTO/10,10,5,0,0,1\nGOTO/20,10,5,0.05,0,0.99875\nGOTO/30,10,5,0,0,1\n",
      "vertical.cls");
  for (const char* c :
       {"direction: [0, 0, 1], pivot_mm: [0, 0, 0]", "direction: [0.0015, 0, 1], pivot_mm: [0, 0, 0]",
        "direction: [-0.0015, 0, 1], pivot_mm: [0, 0, 0]", "direction: [0, 0.0015, 1], pivot_mm: [0, 0, 0]"}) {
    SCOPED_TRACE(c);
    const auto m = machine_edited("trunnion-ac", {{"direction: [0, 0, 1], pivot_mm: [0, 0, 0]", c}});
    const auto k = m.kinematics();
    Posted p;
    ASSERT_NO_THROW(p = post_program(prog, m, *k));
    const auto gs = gate::check(p.text, "vertical.ngc", prog, m, *k, gate::options_for(m, 0, 0, 0));
    EXPECT_TRUE(gs.ok) << gs.message;
  }
  // Tilted 3 mrad (beyond tol::kReachSlackRad), the axes between the vertical and the next point pass through the cone
  // about C that no rotary values reach. Both points are reachable: the error says so, and names the way between.
  const auto m = machine_edited(
      "trunnion-ac", {{"direction: [0, 0, 1], pivot_mm: [0, 0, 0]", "direction: [0.003, 0, 1], pivot_mm: [0, 0, 0]"}});
  try {
    (void)post::conventional_axes(prog, m, *m.kinematics());
    ADD_FAILURE() << "no error for a path through the unreachable cone";
  } catch (const InputError& e) {
    EXPECT_EQ(e.where().line, 10);
    EXPECT_NE(std::string(e.what()).find("from CL line 9"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("both points are reachable"), std::string::npos) << e.what();
  }
}

TEST(Post, AFeedMoveReachedFromOffThePathIsApproachedAlongItsAxis) {
  // The program's first motion a feed move, a tool change followed by one, and a spindle stop and start between two
  // cuts: the tool is away from the last CL point each time. It used to be a rapid straight onto the first point, and
  // after a tool change a feed from the safe Z diagonally to the next point, which the gate refused (220 mm off).
  const char* text = R"(PARTNO OFFPATH
UNITS/MM
MULTAX/ON
CUTTER/10,5
LOADTL/1
SPINDL/8000,CLW
FEDRAT/MMPM,1000
GOTO/10,0,5,0,0,1
GOTO/20,0,5,0,0.2,0.9797959
LOADTL/2
GOTO/40,10,5,0,0,1
GOTO/50,10,5,0,0,1
SPINDL/OFF
SPINDL/8000,CLW
GOTO/60,10,5,0.2,0,0.9797959
FINI
)";
  const cl::Program prog = cl::read_text(text, "offpath.cls");
  for (const char* name : {"trunnion-ac", "haas-umc750", "head-head-ac", "xmini"}) {
    const auto m = load_machine(name);
    const auto k = m.kinematics();
    for (const bool tcp : {false, true}) {
      const Posted p = post_program(prog, m, *k, true, tcp);
      const auto g =
          gate::check(p.text, "offpath.ngc", prog, m, *k, gate::options_for(m, 0, 0, 0), &p.summary.cl_line_of_nc_line);
      EXPECT_TRUE(g.ok) << name << " tcp " << tcp << ": " << g.message << "\n" << p.text;
      // Oracle: FK of every block end. A block that ends on a feed CL point is a feed block (G1), never a rapid.
      const nc::Program nc = nc::read_text(p.text, "offpath.ngc", report::axis_letters(m));
      if (tcp) continue;  // (the gate reads the TCP words; verify_text reads machine coordinates)
      const auto vo = verify_text(p.text, prog, m, *k);
      EXPECT_TRUE(vo.ok) << name << ": " << vo.message;
      std::size_t rapids_onto_cut = 0;
      for (const auto& b : nc.blocks) {
        if (b.motion != nc::Motion::Rapid) continue;
        kin::Axes q;
        for (int j = 0; j < 5; ++j) q[j] = b.axes[static_cast<size_t>(j)];
        const Eigen::Vector3d tip = k->forward(q).tip_mm;
        for (const auto& mv : prog.moves)
          if (mv.kind == cl::MotionKind::Feed && (tip - mv.tip_in_part_mm).norm() < 1e-3) ++rapids_onto_cut;
      }
      EXPECT_EQ(rapids_onto_cut, 0u) << name << "\n" << p.text;
    }
  }
}

// The post retracts by raising Z to the safe plane. On a horizontal spindle whose file calls the vertical axis `z`,
// that retract drags the tool sideways through the part: refused at the machine file's axis, not posted. The same
// machine described as ISO 841 has it (Z along the spindle, + away from the work) posts, and every retract it writes
// moves the tip straight back along the tool axis.
TEST(Post, ARetractAcrossTheSpindleIsRefusedAndOneAlongItRetracts) {
  auto machine_with = [](const std::string& z_dir, const std::string& y_dir) {
    const std::string yaml =
        "name: hor\nkinematics: serial\ntool_direction: [0, -1, 0]\nspindle_gauge_mm: [0, 300, 0]\n"
        "default_tool_length_mm: 100\naxes:\n"
        "  - {name: x, type: linear, side: head, direction: [1, 0, 0], limits: [-500, 500], max_feed: 30000}\n"
        "  - {name: y, type: linear, side: head, direction: " +
        y_dir +
        ", limits: [-500, 500], max_feed: 30000}\n"
        "  - {name: z, type: linear, side: head, direction: " +
        z_dir +
        ", limits: [-500, 500], max_feed: 30000}\n"
        "  - {name: a, type: rotary, side: table, direction: [1, 0, 0], pivot_mm: [0, 0, 0], limits: [-100, 100], "
        "max_feed: 3600}\n"
        "  - {name: b, type: rotary, side: table, direction: [0, 0, 1], pivot_mm: [0, 0, 0], limits: [-360, 360], "
        "max_feed: 7200}\n"
        "chains:\n  table: [a, b]\n  head: [x, y, z]\npost:\n  dialect: linuxcnc\n  safe_z_mm: 60\n"
        "  letters: {x: X, y: Y, z: Z, a: A, b: B}\n";
    return machine::load_text(yaml, test::source_path("machines/hor.yaml"));
  };
  // A path on the part's face toward the spindle (-Y): two cuts with a rapid between them.
  const cl::Program prog = cl::read_text(
      "UNITS/MM\nMULTAX/ON\nFEDRAT/MMPM,1000\nGOTO/0,0,0,0,-1,0\nGOTO/10,0,0,0,-1,0\nRAPID\nGOTO/10,0,20,0,-1,0\n"
      "GOTO/0,0,20,0,-1,0\n",
      "face.cls");
  {
    const auto m = machine_with("[0, 0, 1]", "[0, 1, 0]");  // z vertical: across the spindle
    try {
      (void)post_program(prog, m, *m.kinematics());
      ADD_FAILURE() << "posted with a sideways retract";
    } catch (const InputError& e) {
      EXPECT_NE(std::string(e.what()).find("axis 'z'"), std::string::npos) << e.what();
      EXPECT_NE(std::string(e.what()).find("sideways"), std::string::npos) << e.what();
      EXPECT_NE(std::string(e.what()).find("hor.yaml"), std::string::npos) << e.what();
    }
  }
  const auto m = machine_with("[0, -1, 0]", "[0, 0, 1]");  // ISO 841: Z along the spindle, + toward it
  const auto k = m.kinematics();
  const Posted p = post_program(prog, m, *k);
  const auto gs = gate::check(p.text, "face.ngc", prog, m, *k, gate::options_for(m, 0, 0, 0));
  EXPECT_TRUE(gs.ok) << gs.message;
  // Every block that moves Z alone (the retracts and plunges) moves the tip along the tool axis.
  const nc::Program nc = nc::read_text(p.text, "face.ngc", report::axis_letters(m));
  int along = 0;
  for (std::size_t i = 1; i < nc.blocks.size(); ++i) {
    const auto& b0 = nc.blocks[i - 1];
    if (!std::all_of(b0.known.begin(), b0.known.end(), [](bool x) { return x; })) continue;
    const kin::Axes q0 = Eigen::Map<const kin::Axes>(b0.axes.data()),
                    q1 = Eigen::Map<const kin::Axes>(nc.blocks[i].axes.data());
    const kin::Axes d = q1 - q0;
    if (std::abs(d[2]) < 1e-9 || d.cwiseAbs().sum() - std::abs(d[2]) > 1e-9) continue;
    const kin::Posed a = k->forward(q0), b = k->forward(q1);
    EXPECT_GT(std::abs((b.tip_mm - a.tip_mm).normalized().dot(a.axis)), 1 - 1e-9) << "NC block " << i;
    ++along;
  }
  EXPECT_GE(along, 2) << p.text;
}
