// Axis statistics against hand-computed values, and verification catching a deviating program.
#include <fmt/format.h>
#include <gtest/gtest.h>

#include "cscam/cl/program.hpp"
#include "cscam/core/error.hpp"
#include "cscam/core/units.hpp"
#include "cscam/kin/track.hpp"
#include "cscam/machine/machine.hpp"
#include "cscam/nc/reader.hpp"
#include "cscam/report/backlash.hpp"
#include "cscam/report/json.hpp"
#include "cscam/report/letters.hpp"
#include "cscam/report/stats.hpp"
#include "cscam/report/trace.hpp"
#include "cscam/report/verify.hpp"
#include "test_support.hpp"

using namespace cscam;

TEST(Stats, TravelReversalsStepsAndSimultaneity) {
  // X: 0 -> 10 -> 5 -> 5.001 (noise) -> 8 : travel 10+5+0.001+2.999 = 18, one reversal (10 -> 5, then 5 -> 8 is a
  // second).
  std::vector<kin::Axes> path;
  auto P = [&](double x, double b_deg) {
    kin::Axes q = kin::Axes::Zero();
    q[0] = x;
    q[3] = deg2rad(b_deg);
    path.push_back(q);
  };
  P(0, 0);
  P(10, 0);
  P(5, 10);
  P(5.001, 10);  // below the hysteresis: not a reversal
  P(8, 10);
  P(8, -20);
  const std::vector<bool> rapid = {true, false, false, false, false, false};
  const auto st = report::compute(path, rapid, {"x", "y", "z", "b", "c"}, {false, false, false, true, true});
  EXPECT_NEAR(st.axes[0].travel, 18.0, 1e-9);
  EXPECT_EQ(st.axes[0].reversals, 2);  // 10 -> 5 and 5 -> 8
  EXPECT_NEAR(st.axes[3].travel, 40.0, 1e-9);
  EXPECT_EQ(st.axes[3].reversals, 1);
  EXPECT_NEAR(st.axes[3].largest_step, 30.0, 1e-9);
  ASSERT_EQ(st.segments.size(), 1u);
  EXPECT_EQ(st.segments[0].moving_rotaries, 1);
  EXPECT_EQ(st.segments[0].max_simultaneous, 2);
  EXPECT_EQ(st.blocks_by_simultaneous[1], 4);
  EXPECT_EQ(st.blocks_by_simultaneous[2], 1);
  const auto j = nlohmann::json::parse(st.to_json());
  EXPECT_EQ(j["axes"][0]["reversals"], 2);
  EXPECT_EQ(j["axes"][0]["travel"], 18.0);
  EXPECT_EQ(j["axes"][3]["unit"], "deg");
  EXPECT_EQ(j["feed_blocks_by_simultaneous_axes"][1], 4);
}

// Reports are JSON through a library: a path or a message with quotes, backslashes or control characters stays
// valid JSON and parses back to the same text.
TEST(ReportJson, QuotesAndBackslashesSurvive) {
  const std::string nasty = "C:\\cam\\\"part\" 1\\x.ngc\ttab\nline";
  report::Stats st;
  st.source = nasty;
  st.axes[0].name = "x\"";
  auto j = nlohmann::json::parse(st.to_json());
  EXPECT_EQ(j["source"], nasty);
  EXPECT_EQ(j["axes"][0]["name"], "x\"");
  report::VerifyResult v;
  v.message = "FAILED: \"tip\" \\ deviation";
  v.max_tip_deviation_mm = std::numeric_limits<double>::quiet_NaN();  // not a number: null, not "nan"
  j = nlohmann::json::parse(v.to_json());
  EXPECT_EQ(j["message"], v.message);
  EXPECT_TRUE(j["max_tip_deviation_mm"].is_null());
  EXPECT_EQ(j["ok"], false);
  report::BacklashResult b;
  b.axis_name = "q\\2\"";
  b.width = 0.01;
  b.reversals.push_back({});
  j = nlohmann::json::parse(b.to_json());
  EXPECT_EQ(j["axis"], b.axis_name);
  EXPECT_EQ(j["width_mm"], 0.01);
  ASSERT_EQ(j["reversals"].size(), 1u);
  EXPECT_EQ(j["reversals"][0]["tip_mm"].size(), 3u);
}

// ---- Servo traces (LinuxCNC's motion controller via halsampler) against the CL path ----

namespace {

// A trace that follows the CL path exactly: IK at 20 points along every feed segment (tip interpolated
// linearly, axis by slerp), written as halsampler -t text (degrees, 6 decimals) and read back.
struct TraceFixture {
  machine::Machine m = machine::load(test::source_path("machines/trunnion-ac.yaml"));
  std::shared_ptr<const kin::Kinematics> kin = m.make_kinematics(0.0);
  cl::Program cl = cl::read_file(test::source_path("examples/groove/groove.cls"));
  std::array<bool, 5> rotary{false, false, false, true, true};

  std::vector<report::TraceSample> exact() const {
    std::vector<report::TraceSample> out;
    kin::Axes near = kin::Axes::Zero();
    for (size_t i = 1; i < cl.moves.size(); ++i) {
      const auto& a = cl.moves[i - 1];
      const auto& b = cl.moves[i];
      const bool last = i + 1 == cl.moves.size();
      for (int k = 0; k <= (last ? 20 : 19); ++k) {  // the last segment up to its end point
        const double s = k / 20.0;
        kin::Posed p;
        p.tip_mm = (1 - s) * a.tip_in_part_mm + s * b.tip_in_part_mm;
        const Eigen::Vector3d ua = a.axis_in_part.normalized(), ub = b.axis_in_part.normalized();
        p.axis = ((1 - s) * ua + s * ub).normalized();  // on the great circle between them, as slerp
        kin::Axes q;
        EXPECT_TRUE(kin::nearest_solution(*kin, p, near, q));
        near = q;
        report::TraceSample smp;
        smp.index = static_cast<long>(out.size());
        smp.joints = q;
        smp.nc_line = 100 + static_cast<int>(i);
        smp.motion = b.kind == cl::MotionKind::Feed ? report::TraceMotion::Feed : report::TraceMotion::Rapid;
        out.push_back(smp);
      }
    }
    return out;
  }

  static std::string to_text(const std::vector<report::TraceSample>& samples) {
    std::string t;
    for (const auto& s : samples) {
      // Joint mode: the controller's world position is the joints themselves.
      t += fmt::format(
          "{0} {1:.6f} {2:.6f} {3:.6f} {4:.6f} {5:.6f} {1:.6f} {2:.6f} {3:.6f} {4:.6f} {5:.6f} {6} {7} 1.0 0\n",
          s.index, s.joints[0], s.joints[1], s.joints[2], rad2deg(s.joints[3]), rad2deg(s.joints[4]), s.nc_line,
          s.motion == report::TraceMotion::Feed ? 2 : 1);
    }
    return t;
  }
};

}  // namespace

TEST(Trace, ExactPathPassesThroughTheHalsamplerFormat) {
  TraceFixture f;
  const auto samples = f.exact();
  const report::Trace tr = report::read_halsampler_text(TraceFixture::to_text(samples), "exact.txt", f.rotary);
  ASSERT_EQ(tr.samples.size(), samples.size());
  const auto r = report::check_trace(tr, f.cl, *f.kin, report::TraceCheckOptions{});
  EXPECT_TRUE(r.ok) << r.message;
  // 6 printed decimals (1e-6 mm, 1e-6 deg at < 100 mm from the pivots) are all that separates it from the path.
  EXPECT_LT(r.max_tip_deviation_mm, 1e-5);
  EXPECT_LT(r.max_uncovered_cl_mm, 1e-5);
  EXPECT_GT(r.feed_samples, 3000u);
  EXPECT_LT(r.max_world_mismatch_mm, 1e-9);
  EXPECT_EQ(r.world_lag_samples, 0);
  EXPECT_EQ(r.tcp_samples, 0u);
}

// In TCP mode the controller's world X Y Z is the tip in the part frame: a world column that is our FK tip two
// cycles late matches at lag 2; one that is off by 0.03 mm (another pivot in the controller) shows 0.03 mm.
TEST(Trace, WorldPositionAgainstOurKinematics) {
  TraceFixture f;
  report::Trace tr;
  tr.file = "tcp";
  tr.samples = f.exact();
  for (size_t i = 0; i < tr.samples.size(); ++i) {
    tr.samples[i].kinematics = 1;
    tr.samples[i].world_mm = f.kin->forward(tr.samples[std::min(i + 2, tr.samples.size() - 1)].joints).tip_mm;
  }
  auto r = report::check_trace(tr, f.cl, *f.kin, report::TraceCheckOptions{});
  EXPECT_TRUE(r.ok) << r.message;
  EXPECT_EQ(r.world_lag_samples, 2);
  EXPECT_EQ(r.tcp_samples, tr.samples.size());
  EXPECT_LT(r.max_world_mismatch_tcp_mm, 1e-9);
  for (auto& s : tr.samples) s.world_mm.y() += 0.03;
  r = report::check_trace(tr, f.cl, *f.kin, report::TraceCheckOptions{});
  EXPECT_NEAR(r.max_world_mismatch_tcp_mm, 0.03, 1e-9);
}

TEST(Trace, OffsetInOneBlockIsFoundWithItsLine) {
  TraceFixture f;
  auto samples = f.exact();
  // A 0.05 mm excursion of X in the samples of one block: the tip leaves the path by 0.05 mm there.
  const int bad_line = 100 + 80;
  // Oracle: machine X turned into the part frame by the table, less its part along the (straight) CL segment.
  const Eigen::Vector3d dir = (f.cl.moves[80].tip_in_part_mm - f.cl.moves[79].tip_in_part_mm).normalized();
  double expected = 0.0;
  for (auto& s : samples)
    if (s.nc_line == bad_line) {
      const Eigen::Vector3d before = f.kin->forward(s.joints).tip_mm;
      s.joints[0] += 0.05;
      const Eigen::Vector3d delta = f.kin->forward(s.joints).tip_mm - before;
      expected = std::max(expected, (delta - delta.dot(dir) * dir).norm());
    }
  ASSERT_GT(expected, 0.015);
  report::Trace tr;
  tr.file = "offset";
  tr.samples = samples;
  report::TraceCheckOptions o;
  o.tip_tolerance_mm = 0.012;
  const auto r = report::check_trace(tr, f.cl, *f.kin, o);
  EXPECT_FALSE(r.ok);
  EXPECT_EQ(r.max_tip_nc_line, bad_line);
  EXPECT_NEAR(r.max_tip_deviation_mm, expected, 1e-4);
  ASSERT_FALSE(r.worst_blocks.empty());
  EXPECT_EQ(r.worst_blocks.front().nc_line, bad_line);
  // Rapid samples are not compared: the same excursion in a rapid passes.
  for (auto& s : tr.samples)
    if (s.nc_line == bad_line) s.motion = report::TraceMotion::Rapid;
  const auto r2 = report::check_trace(tr, f.cl, *f.kin, o);
  EXPECT_TRUE(r2.ok) << r2.message;
}

TEST(Trace, TruncatedRunFailsCoverage) {
  TraceFixture f;
  auto samples = f.exact();
  samples.resize(samples.size() / 2);  // the controller stopped half-way: every sample is on the path
  report::Trace tr;
  tr.file = "half";
  tr.samples = samples;
  const auto r = report::check_trace(tr, f.cl, *f.kin, report::TraceCheckOptions{});
  EXPECT_LT(r.max_tip_deviation_mm, 1e-9);
  EXPECT_FALSE(r.ok);
  EXPECT_GT(r.max_uncovered_cl_mm, 10.0);
}

// LinuxCNC labels a sample with the NC line the motion controller has queued, which runs ahead of the motion: a
// plunge blended into the first cuts was labelled with a cut's line while the tool was still above the CL point.
// A sample is matched to a retract or plunge by where it is (on its line, with its axis), not by its label. Oracle:
// the same samples moved 0.05 mm off the plunge line fail.
TEST(Trace, APlungeLabelledWithTheNextLineIsMatchedByWhereItIs) {
  TraceFixture f;
  kin::Axes q_cl, q_up;
  ASSERT_TRUE(kin::nearest_solution(*f.kin, {f.cl.moves[0].tip_in_part_mm, f.cl.moves[0].axis_in_part.normalized()},
                                    kin::Axes::Zero(), q_cl));
  const kin::Posed above{f.cl.moves[0].tip_in_part_mm + 10.0 * f.cl.moves[0].axis_in_part.normalized(),
                         f.cl.moves[0].axis_in_part.normalized()};
  ASSERT_TRUE(kin::nearest_solution(*f.kin, above, q_cl, q_up));
  auto word = [](const kin::Axes& q) {
    return fmt::format("X{:.6f} Y{:.6f} Z{:.6f} A{:.6f} C{:.6f}", q[0], q[1], q[2], rad2deg(q[3]), rad2deg(q[4]));
  };
  const std::string text =
      "G21 G90 G94\nG0 " + word(q_up) + "\nG1 " + word(q_cl) + " F500\nG1 " + word(q_cl) + "\nM2\n";
  const nc::Program nc = nc::read_text(text, "plunge.ngc", report::axis_letters(f.m));
  auto samples_with = [&](double sideways_mm) {
    std::vector<report::TraceSample> out;
    for (int k = 0; k <= 50; ++k) {  // the plunge, labelled with line 4 (the next block) as the controller did
      kin::Posed p = above;
      p.tip_mm += (k / 50.0) * (f.cl.moves[0].tip_in_part_mm - above.tip_mm);
      p.tip_mm += sideways_mm * p.axis.unitOrthogonal();
      report::TraceSample smp;
      smp.index = static_cast<long>(out.size());
      EXPECT_TRUE(kin::nearest_solution(*f.kin, p, q_cl, smp.joints));
      smp.nc_line = 4;
      smp.motion = report::TraceMotion::Feed;
      out.push_back(smp);
    }
    for (auto s : f.exact()) {
      s.index = static_cast<long>(out.size());
      out.push_back(s);
    }
    return out;
  };
  report::Trace tr;
  tr.file = "plunge";
  tr.samples = samples_with(0.0);
  const auto r = report::check_trace(tr, f.cl, *f.kin, report::TraceCheckOptions{}, &nc);
  EXPECT_TRUE(r.ok) << r.message;
  EXPECT_EQ(r.departure_blocks, 1U);
  EXPECT_GE(r.departure_samples, 45U) << r.message;
  tr.samples = samples_with(0.05);
  const auto off = report::check_trace(tr, f.cl, *f.kin, report::TraceCheckOptions{}, &nc);
  EXPECT_FALSE(off.ok) << off.message;
  EXPECT_LT(off.departure_samples, 5U) << off.message;  // the plunge's 51 samples are not on its line
}

// A path that doubles back along itself with another orientation: a sample on the way back is as near the way out,
// whose axis differs by up to 20 deg there. It is judged at the pose of the path it can be at, as the gate does; a
// sample whose axis matches neither still fails.
TEST(Trace, OnAPathThatDoublesBackTheAxisIsJudgedWhereTheSampleCanBe) {
  TraceFixture f;
  const cl::Program cl = cl::read_text(
      "UNITS/MM\nMULTAX/ON\nRAPID\nGOTO/0,0,5,0,0,1\nFEDRAT/MMPM,500\nGOTO/0,0,0,0,0,1\n"
      "GOTO/10,0,0,0.342020143,0,0.939692621\nGOTO/0,0,0,0,-0.342020143,0.939692621\n",
      "back.cls");
  auto run_with = [&](double extra_deg) {
    report::Trace tr;
    tr.file = "back";
    kin::Axes near = kin::Axes::Zero();
    for (size_t i = 1; i < cl.moves.size(); ++i)
      for (int k = 0; k <= 40; ++k) {
        const double s = k / 40.0;
        const auto& a = cl.moves[i - 1];
        const auto& b = cl.moves[i];
        kin::Posed p;
        p.tip_mm = (1 - s) * a.tip_in_part_mm + s * b.tip_in_part_mm;
        const Eigen::Vector3d ua = a.axis_in_part.normalized(), ub = b.axis_in_part.normalized();
        const double th = std::acos(std::clamp(ua.dot(ub), -1.0, 1.0));
        p.axis = th < 1e-12 ? ua : ((std::sin((1 - s) * th) * ua + std::sin(s * th) * ub) / std::sin(th)).normalized();
        p.axis = (Eigen::AngleAxisd(deg2rad(extra_deg), Eigen::Vector3d::UnitY()) * p.axis).normalized();
        report::TraceSample smp;
        smp.index = static_cast<long>(tr.samples.size());
        EXPECT_TRUE(kin::nearest_solution(*f.kin, p, near, smp.joints));
        near = smp.joints;
        smp.nc_line = static_cast<int>(i);
        smp.motion = i == 1 ? report::TraceMotion::Rapid : report::TraceMotion::Feed;
        smp.world_mm = Eigen::Vector3d(smp.joints[0], smp.joints[1], smp.joints[2]);
        tr.samples.push_back(smp);
      }
    return report::check_trace(tr, cl, *f.kin, report::TraceCheckOptions{});
  };
  const auto r = run_with(0.0);
  EXPECT_TRUE(r.ok) << r.message;
  EXPECT_LT(r.max_axis_deviation_deg, 0.01) << r.message;
  const auto bad = run_with(1.0);
  EXPECT_FALSE(bad.ok) << bad.message;
  EXPECT_NEAR(bad.max_axis_deviation_deg, 1.0, 0.05) << bad.message;
}

// A path that crosses itself: a sample that leaves its own pass right at the crossing is within the tolerance of the
// other pass. With the program known, each sample is judged against the CL segments its block runs along, so it fails
// by its distance from its own pass. Oracle: the 0.05 mm shift put into that one sample.
TEST(Trace, ASampleOffItsOwnPassFailsWhereAnotherPassCrossesIt) {
  TraceFixture f;
  std::string cls = "UNITS/MM\nMULTAX/ON\nRAPID\nGOTO/-10,0,0,0,0,1\nFEDRAT/MMPM,500\n";
  for (int x = -8; x <= 10; x += 2) cls += fmt::format("GOTO/{},0,0,0,0,1\n", x);   // pass 1 along X
  for (int y = -10; y <= 10; y += 2) cls += fmt::format("GOTO/0,{},0,0,0,1\n", y);  // pass 2 along Y, over pass 1
  const cl::Program cl = cl::read_text(cls, "cross.cls");
  // One block per CL move (move i on NC line i + 2), at the IK of its point.
  std::vector<kin::Axes> q(cl.moves.size());
  kin::Axes near = kin::Axes::Zero();
  for (size_t i = 0; i < cl.moves.size(); ++i) {
    ASSERT_TRUE(
        kin::nearest_solution(*f.kin, {cl.moves[i].tip_in_part_mm, cl.moves[i].axis_in_part.normalized()}, near, q[i]));
    near = q[i];
  }
  auto word = [](const kin::Axes& a) {
    return fmt::format("X{:.6f} Y{:.6f} Z{:.6f} A{:.6f} C{:.6f}", a[0], a[1], a[2], rad2deg(a[3]), rad2deg(a[4]));
  };
  std::string ngc = "G21 G90 G94\nG0 " + word(q[0]) + "\n";
  for (size_t i = 1; i < q.size(); ++i) ngc += "G1 " + word(q[i]) + (i == 1 ? " F500\n" : "\n");
  ngc += "M2\n";
  const nc::Program nc = nc::read_text(ngc, "cross.ngc", report::axis_letters(f.m));
  const size_t crossing = 10 + 1 + 5;  // pass 2's point (0, 0): pass 1 runs through it too
  ASSERT_LT((cl.moves[crossing].tip_in_part_mm - Eigen::Vector3d::Zero()).norm(), 1e-12);
  auto run_with = [&](double shift_mm) {
    report::Trace tr;
    tr.file = "cross";
    for (size_t i = 1; i < cl.moves.size(); ++i)
      for (int k = 0; k < (i + 1 == cl.moves.size() ? 41 : 40); ++k) {  // the last segment up to its end point
        kin::Posed p{
            cl.moves[i - 1].tip_in_part_mm + (k / 40.0) * (cl.moves[i].tip_in_part_mm - cl.moves[i - 1].tip_in_part_mm),
            Eigen::Vector3d::UnitZ()};
        if (i == crossing + 1 && k == 0) p.tip_mm.x() += shift_mm;  // the sample at the crossing, off pass 2
        report::TraceSample smp;
        smp.index = static_cast<long>(tr.samples.size());
        EXPECT_TRUE(kin::nearest_solution(*f.kin, p, q[i], smp.joints));
        smp.nc_line = static_cast<int>(i) + 2;
        smp.motion = report::TraceMotion::Feed;
        smp.world_mm = Eigen::Vector3d(smp.joints[0], smp.joints[1], smp.joints[2]);
        tr.samples.push_back(smp);
      }
    return report::check_trace(tr, cl, *f.kin, report::TraceCheckOptions{}, &nc);
  };
  const auto r = run_with(0.0);
  EXPECT_TRUE(r.ok) << r.message;
  EXPECT_LT(r.max_tip_deviation_mm, 1e-5) << r.message;
  const auto bad = run_with(0.05);
  EXPECT_FALSE(bad.ok) << bad.message;
  EXPECT_NEAR(bad.max_tip_deviation_mm, 0.05, 1e-5) << bad.message;
  EXPECT_EQ(bad.max_tip_nc_line, static_cast<int>(crossing) + 3) << bad.message;
}

TEST(Trace, ReaderRejectsLostSamplesAndBadLines) {
  const std::array<bool, 5> rot{false, false, false, true, true};
  const std::string ok = "0 1 2 3 4 5 6 7 8 9 10 7 2 1.5 0\n1 1 2 3 4 5 6 7 8 9 10 7 2 1.5 1\n";
  const auto tr = report::read_halsampler_text(ok, "ok.txt", rot);
  ASSERT_EQ(tr.samples.size(), 2u);
  EXPECT_DOUBLE_EQ(tr.samples[0].joints[2], 3.0);
  EXPECT_NEAR(tr.samples[0].joints[3], deg2rad(4.0), 1e-15);
  EXPECT_EQ(tr.samples[1].nc_line, 7);
  EXPECT_EQ(tr.samples[1].motion, report::TraceMotion::Feed);
  EXPECT_EQ(tr.samples[1].kinematics, 1);
  EXPECT_DOUBLE_EQ(tr.samples[0].world_mm.x(), 6.0);
  auto message_of = [&](const std::string& text) {
    try {
      report::read_halsampler_text(text, "s.txt", rot);
    } catch (const InputError& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  EXPECT_NE(message_of("0 1 2 3 4 5 6 7 8 9 10 7 2 1.5 0\n2 1 2 3 4 5 6 7 8 9 10 7 2 1.5 0\n").find("s.txt:2"),
            std::string::npos);
  EXPECT_NE(message_of("0 1 2 3 4 5 6 7 8 9 10 7 2 1.5 0\noverrun\n").find("overran"), std::string::npos);
  EXPECT_NE(message_of("0 1 2 3 4 5 6 7 8 9 10 7 2 1.5 0\n1 1 2 x 4 5 6 7 8 9 10 7 2 1.5 0\n").find("s.txt:2:"),
            std::string::npos);
  EXPECT_NE(message_of("0 1 2 3\n").find("s.txt:1"), std::string::npos);
  EXPECT_NE(message_of("").find("no samples"), std::string::npos);
  // The sample number and the program line are whole numbers (a sample 1e30 read as a negative index, 2.7 as 3).
  EXPECT_NE(message_of("0 1 2 3 4 5 6 7 8 9 10 7 2 1.5 0\n1e30 1 2 3 4 5 6 7 8 9 10 7 2 1.5 0\n")
                .find("s.txt:2: column 1 (the sample number) is 1e+30"),
            std::string::npos);
  EXPECT_NE(message_of("0.5 1 2 3 4 5 6 7 8 9 10 7 2 1.5 0\n").find("s.txt:1: column 1 (the sample number) is 0.5"),
            std::string::npos);
  EXPECT_NE(message_of("0 1 2 3 4 5 6 7 8 9 10 1e20 2 1.5 0\n").find("column 12 (the program line"), std::string::npos);
  EXPECT_EQ(message_of("0 1 2 3 4 5 6 7 8 9 10 -1 2 1.5 0\n"), "no error");  // an s32 pin: -1 is a state
}

TEST(Stats, CycleTimeByHand) {
  // G0 from (0,0,0) to X100: X at 10000 mm/min -> 0.01 min; G1 X200 F1000 -> 0.1 min; G93 G1 B90 F20 -> 0.05 min;
  // G94 G1 B0 (rotary only) F900 deg/min -> 0.1 min. Rapid to Z50 at 5000 -> 0.01 min.
  nc::AxisLetters l;
  l.letter = {'X', 'Y', 'Z', 'B', 'C'};
  l.rotary = {false, false, false, true, true};
  const nc::Program p =
      nc::read_text("G0 X0 Y0 Z0 B0 C0\nG0 X100\nG1 X200 F1000\nG93 G1 B90 F20\nG94 G1 B0 F900\nG0 Z50\n", "t.ngc", l);
  const std::array<double, 5> vmax{10000, 10000, 5000, 3600, 3600};
  const auto st = report::compute(p, {"X", "Y", "Z", "B", "C"}, l.rotary, &vmax);
  EXPECT_TRUE(st.rapid_time_known);
  EXPECT_NEAR(st.feed_minutes, 0.1 + 0.05 + 0.1, 1e-12);
  EXPECT_NEAR(st.rapid_minutes, 0.01 + 0.01, 1e-12);
  const auto no_rates = report::compute(p, {"X", "Y", "Z", "B", "C"}, l.rotary);
  EXPECT_FALSE(no_rates.rapid_time_known);
  EXPECT_NE(report::table({st}, {"t"}).find("cycle time (min)"), std::string::npos);
}

namespace {

/// Angle (rad) from unit vector u to the great-circle arc from a to b (unit, less than a half turn apart).
double angle_to_arc(const Eigen::Vector3d& u, const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  auto ang = [](const Eigen::Vector3d& x, const Eigen::Vector3d& y) {
    return std::acos(std::clamp(x.dot(y), -1.0, 1.0));
  };
  double best = std::min(ang(u, a), ang(u, b));
  const Eigen::Vector3d nrm = a.cross(b);
  if (nrm.norm() < 1e-12) return best;
  const Eigen::Vector3d n = nrm.normalized();
  const Eigen::Vector3d in_plane = u - u.dot(n) * n;
  if (in_plane.norm() < 1e-12) return best;
  const Eigen::Vector3d f = in_plane.normalized();  // u's foot on the great circle: on the arc?
  if (a.cross(f).dot(n) >= 0 && f.cross(b).dot(n) >= 0) best = std::min(best, ang(u, f));
  return best;
}

}  // namespace

// verify's sparse, bounded sampling against dense sampling: random joint moves on every bundled serial machine,
// the CL path through their ends (so the moves bulge away from it between them). The reported tip and axis
// deviations must bound the largest over 1000 FK samples per block of the exact distance to the CL polyline and
// the exact angle to the CL orientations (the arcs between its points' axes), with far fewer samples.
TEST(Verify, SparseBoundedSamplingBoundsDenseDeviation) {
  auto rng = test::rng(91);
  std::uniform_real_distribution<double> u01(0.0, 1.0);
  constexpr int kDense = 1000, kBlocks = 40;
  int sampling_alone_misses = 0;
  for (const char* name : {"haas-umc750", "trunnion-ac", "head-table-bc45", "head-head-ac"}) {
    const auto m = machine::load(test::source_path(std::string("machines/") + name + ".yaml"));
    const auto k = m.kinematics();
    for (double scale : {2e-4, 2e-3, 2e-2}) {  // fraction of each stroke per block
      nc::Program nc;
      cl::Program cl;
      kin::Axes q;
      for (int i = 0; i < 5; ++i) {
        const auto& a = m.axes[static_cast<size_t>(i)];
        q[i] = 0.5 * (std::max(a.min, -kPi) + std::min(a.max, kPi));
      }
      std::vector<kin::Axes> qs;
      for (int b = 0; b <= kBlocks; ++b) {
        if (b > 0)
          for (int i = 0; i < 5; ++i) {
            const auto& a = m.axes[static_cast<size_t>(i)];
            const double lo = a.rotary() ? std::max(a.min, -kPi) : a.min,
                         hi = a.rotary() ? std::min(a.max, kPi) : a.max;
            q[i] = std::clamp(q[i] + scale * (hi - lo) * (2.0 * u01(rng) - 1.0), lo, hi);
          }
        qs.push_back(q);
        nc::Block blk;
        blk.line = b + 1;
        blk.motion = b == 0 ? nc::Motion::Rapid : nc::Motion::Linear;
        blk.feed = 1000;
        for (int i = 0; i < 5; ++i) blk.axes[static_cast<size_t>(i)] = q[i];
        blk.known.fill(true);
        blk.words.fill(true);
        nc.blocks.push_back(blk);
        const kin::Posed p = k->forward(q);
        cl::Move mv;
        mv.tip_in_part_mm = p.tip_mm;
        mv.axis_in_part = p.axis;
        mv.kind = b == 0 ? cl::MotionKind::Rapid : cl::MotionKind::Feed;
        mv.line = b + 1;
        cl.moves.push_back(mv);
      }
      report::VerifyOptions vo;
      vo.tip_tolerance_mm = 1e6;  // nothing is refused: the numbers are compared
      vo.axis_tolerance_deg = 180;
      const auto r = report::verify(nc, cl, *k, vo);
      // The same budget with tolerances of a real post: the number of samples it would take.
      double dense_tip = 0.0, dense_axis = 0.0;
      for (int b = 1; b <= kBlocks; ++b)
        for (int j = 0; j <= kDense; ++j) {
          const auto& qa = qs[static_cast<size_t>(b) - 1];
          const auto& qb = qs[static_cast<size_t>(b)];
          const kin::Posed p = k->forward(qa + (double(j) / kDense) * (qb - qa));
          double d = std::numeric_limits<double>::infinity(), a = d;
          for (size_t s = 1; s < cl.moves.size(); ++s) {
            const auto& c0 = cl.moves[s - 1];
            const auto& c1 = cl.moves[s];
            const Eigen::Vector3d ab = c1.tip_in_part_mm - c0.tip_in_part_mm;
            const double t = ab.squaredNorm() > 0
                                 ? std::clamp((p.tip_mm - c0.tip_in_part_mm).dot(ab) / ab.squaredNorm(), 0.0, 1.0)
                                 : 0.0;
            d = std::min(d, (c0.tip_in_part_mm + t * ab - p.tip_mm).norm());
            a = std::min(a, angle_to_arc(p.axis, c0.axis_in_part.normalized(), c1.axis_in_part.normalized()));
          }
          dense_tip = std::max(dense_tip, d);
          dense_axis = std::max(dense_axis, rad2deg(a));
        }
      EXPECT_LE(dense_tip, r.max_tip_deviation_mm + 1e-9) << name << " scale " << scale;
      EXPECT_LE(dense_axis, r.max_axis_deviation_deg + 1e-6) << name << " scale " << scale;
      EXPECT_GT(dense_tip, 0.0) << name;
      report::VerifyOptions unbounded = vo;  // the same two samples per block without the bound
      unbounded.adaptive_samples = false;
      unbounded.samples_per_block = 2;
      if (report::verify(nc, cl, *k, unbounded).max_tip_deviation_mm < dense_tip) ++sampling_alone_misses;
      EXPECT_LT(r.samples, static_cast<size_t>(kBlocks) * 5000u) << name;
    }
  }
  EXPECT_GE(sampling_alone_misses, 2);  // the test can fail: the samples alone understate the deviation
}

// With a real post's tolerances the bound costs few samples: small moves get the minimum of two per block.
TEST(Verify, BoundedSamplingTakesTwoSamplesForShortBlocks) {
  const auto m = machine::load(test::source_path("machines/trunnion-ac.yaml"));
  const auto k = m.kinematics();
  nc::Program nc;
  cl::Program cl;
  for (int b = 0; b <= 100; ++b) {
    kin::Axes q;
    q << 10.0 + 0.1 * b, 5.0, -20.0, deg2rad(20.0 + 0.01 * b), deg2rad(30.0 + 0.02 * b);
    nc::Block blk;
    blk.line = b + 1;
    blk.motion = b == 0 ? nc::Motion::Rapid : nc::Motion::Linear;
    blk.feed = 1000;
    for (int i = 0; i < 5; ++i) blk.axes[static_cast<size_t>(i)] = q[i];
    blk.known.fill(true);
    nc.blocks.push_back(blk);
    const kin::Posed p = k->forward(q);
    cl::Move mv;
    mv.tip_in_part_mm = p.tip_mm;
    mv.axis_in_part = p.axis;
    mv.kind = b == 0 ? cl::MotionKind::Rapid : cl::MotionKind::Feed;
    mv.line = b + 1;
    cl.moves.push_back(mv);
  }
  report::VerifyOptions vo = report::verify_options_for(m);
  const auto r = report::verify(nc, cl, *k, vo);
  EXPECT_TRUE(r.ok) << r.message;
  EXPECT_EQ(r.samples, 1u + 100u * 2u) << r.message;  // the first point, then two per block
  vo.adaptive_samples = false;
  const auto fixed = report::verify(nc, cl, *k, vo);
  EXPECT_EQ(fixed.samples, 1u + 100u * 8u);
  // The bound is added: never below the fixed sampling's own figure by more than what sampling can miss.
  EXPECT_GE(r.max_tip_deviation_mm + 1e-9, 0.0);
  EXPECT_LE(r.max_tip_deviation_mm, vo.tip_tolerance_mm / 16 + fixed.max_tip_deviation_mm + 1e-9);
}

TEST(Verify, ATcpProgramThatSwitchesTcpOffIsReadAsTipWordsWithTheMachineAxesKept) {
  // G43.4 ... G49 G43 ... G43.4: the machine-word block in between becomes the tip words of its axes (FK), a word it
  // does not give is where the TCP block left the machine (IK), and the TCP block after it continues from its tip.
  const machine::Machine m = machine::load(test::source_path("machines/trunnion-ac.yaml"));
  const auto k = m.kinematics();
  const nc::Program p = report::read_for_machine(
      "%\n(cscam tool_length_mm=0.0000 tolerance_mm=0.0100)\nG43.4 H1\nG0 X10 Y5 Z50 A20 C30\nG49\nG43 H1\nG0 Z100\n"
      "G43.4 H1\nG0 X20\nM30\n%\n",
      "mixed.nc", m);
  ASSERT_EQ(p.blocks.size(), 3u);
  EXPECT_TRUE(p.blocks[0].tcp);
  EXPECT_FALSE(p.blocks[1].tcp);
  ASSERT_EQ(p.machine_axes.size(), 1u);
  EXPECT_EQ(p.machine_axes[0].first, 1u);
  // the machine where the TCP block put the tip (10, 5, 50) at A20 C30, then its Z at 100
  kin::Axes at_tip = kin::Axes::Zero();
  at_tip[3] = deg2rad(20.0);
  at_tip[4] = deg2rad(30.0);
  Eigen::Vector3d axis;
  ASSERT_TRUE(k->tool_axis_at(at_tip[3], at_tip[4], Eigen::Vector3d(10, 5, 50), axis));
  ASSERT_TRUE(k->solve_for_rotaries(kin::Posed{Eigen::Vector3d(10, 5, 50), axis}, at_tip));
  kin::Axes up = at_tip;
  up[2] = 100.0;
  for (int i = 0; i < 5; ++i) EXPECT_NEAR(p.machine_axes[0].second[static_cast<size_t>(i)], up[i], 1e-9) << i;
  const Eigen::Vector3d tip_up = k->forward(up).tip_mm;
  for (int c = 0; c < 3; ++c) EXPECT_NEAR(p.blocks[1].axes[static_cast<size_t>(c)], tip_up[c], 1e-9) << c;
  EXPECT_DOUBLE_EQ(p.blocks[1].axes[3], deg2rad(20.0));  // the rotary words stay
  // the TCP block after it: X given, Y and Z from the machine block's tip
  EXPECT_DOUBLE_EQ(p.blocks[2].axes[0], 20.0);
  EXPECT_NEAR(p.blocks[2].axes[1], tip_up.y(), 1e-9);
  EXPECT_NEAR(p.blocks[2].axes[2], tip_up.z(), 1e-9);
}

TEST(Verify, ArcsInATiltedPlaneBecomeCirclesOfTheMachineAxes) {
  // G68.2 tilted 30 deg about X on the trunnion, A positioned for it: a quarter circle and a quarter helix (down 1 mm)
  // in the plane's XY. Oracle by hand: the plane is Rx(J) about the part origin; sampled along each arc, FK of the
  // machine axes put back into the plane lies on the circle about its origin, radius 10, at the height the helix has
  // reached; the path length is the helix' (stats, the gate's feed check).
  const machine::Machine m = machine::load(test::source_path("machines/trunnion-ac.yaml"));
  const auto k = m.kinematics();
  Eigen::Vector3d axis;
  const auto rp = k->rotary_pair();  // A at -30, C at 0
  ASSERT_TRUE(k->tool_axis_at(rp[0] == 3 ? deg2rad(-30.0) : 0.0, rp[0] == 3 ? 0.0 : deg2rad(-30.0),
                              Eigen::Vector3d::Zero(), axis));
  const double j_deg = rad2deg(std::atan2(-axis.y(), axis.z()));  // Rx(J) e_z = (0, -sin J, cos J)
  ASSERT_NEAR(std::abs(j_deg), 30.0, 1e-9);
  const nc::Program p = report::read_for_machine(
      fmt::format(
          "%\n(cscam tool_length_mm=0.0000 tolerance_mm=0.0100)\nG0 X0 Y0 Z100 A-30 C0\nG68.2 X0 Y0 Z0 I0 J{:.4f} "
          "K0\nG53.1\nG0 X10 Y0 Z5\nG1 Z0 F500\nG17 G3 X0 Y10 I-10 J0\nG2 X10 Y0 Z-1 R10\nG69\nG0 Z100\nM30\n%\n",
          j_deg),
      "arcs.nc", m);
  const Eigen::Matrix3d R = Eigen::AngleAxisd(deg2rad(j_deg), Eigen::Vector3d::UnitX()).toRotationMatrix();
  std::size_t arcs = 0;
  for (std::size_t bi = 1; bi < p.blocks.size(); ++bi) {
    const nc::Block& b = p.blocks[bi];
    EXPECT_EQ(b.plane, nullptr);  // resolved into machine axes
    if (!b.arc) continue;
    ASSERT_TRUE(b.arc->tilted);
    for (int s = 0; s <= 32; ++s) {
      const auto a = nc::point_on(p.blocks[bi - 1].axes, b, s / 32.0);
      kin::Axes q;
      for (int i = 0; i < 5; ++i) q[i] = a[static_cast<size_t>(i)];
      const Eigen::Vector3d in_plane = R.transpose() * k->forward(q).tip_mm;
      const double z = arcs == 0 ? 0.0 : -s / 32.0;
      EXPECT_NEAR(std::hypot(in_plane.x(), in_plane.y()), 10.0, 1e-9) << arcs << " " << s;
      EXPECT_NEAR(in_plane.z(), z, 1e-9) << arcs << " " << s;
      const double ang = std::atan2(in_plane.y(), in_plane.x());
      EXPECT_NEAR(ang, arcs == 0 ? s / 32.0 * 0.5 * kPi : (1.0 - s / 32.0) * 0.5 * kPi, 1e-9);
    }
    const double quarter = 0.5 * kPi * 10.0;
    EXPECT_NEAR(nc::linear_path_mm(p.blocks[bi - 1].axes, b, {false, false, false, true, true}),
                arcs == 0 ? quarter : std::hypot(quarter, 1.0), 1e-9);
    ++arcs;
  }
  EXPECT_EQ(arcs, 2u);
  // a program that switches tool-tip control is not read with arcs in its planes (the post writes none there)
  try {
    report::read_for_machine(
        fmt::format("%\nG43.4 H1\nG0 X0 Y0 Z100 A-30 C0\nG49\nG43 H1\nG68.2 X0 Y0 Z0 I0 J{:.4f} K0\nG53.1\n"
                    "G0 X10 Y0 Z5\nG1 Z0 F500\nG3 X0 Y10 I-10 J0\nG69\nM30\n%\n",
                    j_deg),
        "mixed.nc", m);
    ADD_FAILURE() << "read";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("mixed.nc:10: an arc in the tilted work plane G68.2"), std::string::npos)
        << e.what();
  }
}

TEST(Verify, APathOutAndBackOverItselfThenOnIsFollowedInOrder) {
  // 40 segments out along Y, the same 40 back, then 20 mm on along X: the samples at the turning point tie between
  // the first visit and the return; the walk snapped back to the first visit and the last cut, more than the search
  // window past it, read as 20 mm off the path. Oracle: the NC blocks are the CL points themselves (IK of each), so
  // the true deviation is 0; the negative control moves the last cut 1 mm in Y, which must be refused.
  const auto m = machine::load(test::source_path("machines/trunnion-ac.yaml"));
  const auto k = m.kinematics();
  std::vector<Eigen::Vector3d> tips{{20, 0, 60}};
  for (int i = 0; i <= 40; ++i) tips.emplace_back(20, 0.625 * i, 30);
  for (int i = 39; i >= 0; --i) tips.emplace_back(20, 0.625 * i, 30);
  tips.emplace_back(40, 0, 30);
  for (const double shift : {0.0, 1.0}) {
    nc::Program nc;
    cl::Program cl;
    for (std::size_t b = 0; b < tips.size(); ++b) {
      cl::Move mv;
      mv.tip_in_part_mm = tips[b];
      mv.axis_in_part = Eigen::Vector3d::UnitZ();
      mv.kind = b == 0 ? cl::MotionKind::Rapid : cl::MotionKind::Feed;
      mv.line = static_cast<int>(b) + 1;
      cl.moves.push_back(mv);
      kin::Axes q;
      ASSERT_TRUE(kin::nearest_solution(*k, kin::Posed{tips[b], Eigen::Vector3d::UnitZ()}, kin::Axes::Zero(), q));
      if (b + 1 == tips.size()) q[1] += shift;  // Y of a table machine at A = C = 0
      nc::Block blk;
      blk.line = static_cast<int>(b) + 1;
      blk.motion = b == 0 ? nc::Motion::Rapid : nc::Motion::Linear;
      blk.feed = 600;
      for (int i = 0; i < 5; ++i) blk.axes[static_cast<size_t>(i)] = q[i];
      blk.known.fill(true);
      nc.blocks.push_back(blk);
    }
    const auto r = report::verify(nc, cl, *k, report::verify_options_for(m));
    if (shift == 0.0) {
      EXPECT_TRUE(r.ok) << r.message;
      EXPECT_LT(r.max_tip_deviation_mm, 1e-6) << r.message;
    } else {
      EXPECT_FALSE(r.ok) << r.message;
      EXPECT_GT(r.max_tip_deviation_mm, 0.5) << r.message;
    }
  }
}
