// The sim module: recordings (format, errors), the effect library (derivatives, parsing), motion profiles
// and the simulator.
#include <fmt/format.h>
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <sstream>

#include "cscam/core/error.hpp"
#include "cscam/core/tolerances.hpp"
#include "cscam/machine/machine.hpp"
#include "cscam/nc/reader.hpp"
#include "cscam/report/letters.hpp"
#include "cscam/sim/effects.hpp"
#include "cscam/sim/recording.hpp"
#include "cscam/sim/simulate.hpp"
#include "test_support.hpp"

using namespace cscam;

namespace {

machine::Machine trunnion() { return machine::load(std::string(CSCAM_SOURCE_DIR) + "/machines/trunnion-ac.yaml"); }

using test::error_of;

/// A square on the trunnion at 600 mm/min: every linear axis reverses.
sim::Trajectory square_path(const machine::Machine& m, double rate = 500) {
  const std::string nc =
      "G21 G90 G94\nG0 X0 Y0 Z0 A0 C0\nG1 X20 F600\nG1 Y20\nG1 X0\nG1 Y0\nG1 X20\nG1 Y20\nG1 X0\nG1 Y0\n";
  const auto p = nc::read_text(nc, "square.ngc", report::axis_letters(m));
  sim::ProfileOptions po;
  po.rate_hz = rate;
  return sim::profile(sim::blocks_from_nc(p, m), po);
}

}  // namespace

TEST(SimRecording, RoundTripKeepsMetadataColumnsAndEmptyCells) {
  sim::Recording r;
  r.set_meta("machine", "machines/xmini.yaml");
  r.set_meta("kind", "trajectory");
  r.add_column("t", {0.0, 0.001, 0.002});
  r.add_column("cmd.x", {1.0, 2.0, 3.0});
  r.add_column("tip.x", {0.5, std::nan(""), 0.25});
  std::ostringstream os;
  sim::write_recording(os, r);
  const auto back = sim::parse_recording(os.str(), "mem.csv");
  EXPECT_EQ(back.meta_value("machine").value(), "machines/xmini.yaml");
  ASSERT_EQ(back.columns.size(), 3u);
  ASSERT_EQ(back.rows(), 3u);
  EXPECT_DOUBLE_EQ(back.data[1][2], 3.0);
  EXPECT_TRUE(std::isnan(back.data[2][1]));
  EXPECT_EQ(back.row_line[0], 4);  // two metadata lines, the header, then the first row
}

TEST(SimRecording, ErrorsNameTheRowTheColumnOrTheCell) {
  EXPECT_NE(error_of([] {
              sim::parse_recording("t,cmd.x\n0,1\n0.2,1\n0.1,2\n", "r.csv");
            }).find("r.csv:4: row 3: time is not strictly increasing"),
            std::string::npos);
  EXPECT_NE(error_of([] { sim::parse_recording("t,cmd.x\n0,1\n0.1,abc\n", "r.csv"); }).find("r.csv:3:5: column cmd.x"),
            std::string::npos);
  EXPECT_NE(error_of([] { sim::parse_recording("t,cmd.x\n0,1,2\n", "r.csv"); }).find("too many cells"),
            std::string::npos);
  EXPECT_NE(error_of([] { sim::parse_recording("cmd.x\n1\n", "r.csv"); }).find("time column 't'"), std::string::npos);
  // A spreadsheet's byte-order mark is not part of the first metadata line; a ';'-separated file is named as such.
  const auto bom = sim::parse_recording("\xEF\xBB\xBF# machine: m\nt,tip.x\n0,1\n", "r.csv");
  ASSERT_EQ(bom.meta.size(), 1u);
  EXPECT_EQ(bom.meta[0].first, "machine");
  EXPECT_NE(error_of([] { sim::parse_recording("t;cmd.x\n0;1\n", "r.csv"); })
                .find("r.csv:1:2: the header's columns "
                      "are separated by ';'"),
            std::string::npos);
  EXPECT_NE(error_of([] {
              sim::parse_recording("t,tip.x\n0,1\n0.1,1e300\n", "r.csv");
            }).find("r.csv:3:5: column tip.x: 1e300 is out of range"),
            std::string::npos);
  // Numeric metadata: a finite number in range, at its line and the value's column.
  const auto meta = sim::parse_recording("# machine: m\n# tool_length: inf\nt,tip.x\n0,1\n", "r.csv");
  EXPECT_NE(error_of([&] { (void)meta.meta_number("tool_length", 0, 1e4); }).find("r.csv:2:16: metadata tool_length"),
            std::string::npos);
  EXPECT_FALSE(meta.meta_number("spindle_rpm", 0, 1e6).has_value());
  const auto m = trunnion();
  auto rec = sim::parse_recording("t,cmd.x,cmd.y,cmd.z,cmd.a,tip.x\n0,0,0,0,0,0\n", "r.csv");
  EXPECT_NE(error_of([&] { sim::validate_against(rec, m); }).find("missing column 'cmd.c'"), std::string::npos);
  auto rec2 = sim::parse_recording("t,cmd.x,cmd.y,cmd.z,cmd.a,cmd.c,len.bar\n0,0,0,0,0,0,1\n", "r.csv");
  EXPECT_NE(error_of([&] { sim::validate_against(rec2, m); }).find("column 'len.bar'"), std::string::npos);
  auto rec3 = sim::parse_recording("t,cmd.x,cmd.y,cmd.z,cmd.a,cmd.c,foo,temp.spindle\n0,0,0,0,0,0,1,20\n", "r.csv");
  sim::validate_against(rec3, m);
  ASSERT_EQ(rec3.warnings.size(), 1u);
  EXPECT_NE(rec3.warnings[0].find("unknown column 'foo'"), std::string::npos);
}

TEST(SimEffects, EveryEffectsAutodiffGradientMatchesFiniteDifferences) {
  const auto m = trunnion();
  const auto tr = square_path(m);
  const auto ctx = sim::make_context(tr.t, tr.cmd, {false, false, false, true, true});
  const std::vector<std::string> specs = {"backlash:x:0.01",
                                          "servo_lag:y:0.004",
                                          "scale:x:30",
                                          "squareness:x,y:50",
                                          "cyclic:x:5:0.002:30",
                                          "friction_spike:y:0.005:0.05",
                                          "compliance:x:0.001",
                                          "thermal_drift:tip.z:0.02:40",
                                          "vibration:tip.z:37.5:0.003:20",
                                          "straightness:z,x:0.8:7",
                                          "cross_compliance:z,x:0.004",
                                          "thermal_scale:x:ppm=40,time_constant_s=30",
                                          "servo_lag_1st:y:tau_s=0.01,lag_s=0.008",
                                          "step:tip.z:step_mm=0.01,t_s=1.2345"};
  std::mt19937 rng(7);
  for (const auto& s : specs) {
    auto e = sim::parse_effect(s, m);
    for (int trial = 0; trial < 20; ++trial) {
      const size_t i = std::uniform_int_distribution<size_t>(0, ctx.size() - 1)(rng);
      std::vector<double> g(e->p.size());
      const double v = e->value_grad(ctx, i, e->p.data(), g.data());
      EXPECT_NEAR(v, e->value(ctx, i, e->p.data()), 1e-15) << s;
      for (size_t k = 0; k < e->p.size(); ++k) {
        auto p1 = e->p, p0 = e->p;
        const double h = 1e-6 * std::max(1.0, std::abs(e->p[k]));
        p1[k] += h;
        p0[k] -= h;
        const double fd = (e->value(ctx, i, p1.data()) - e->value(ctx, i, p0.data())) / (2 * h);
        EXPECT_NEAR(g[k], fd, 1e-6 * std::max(1.0, std::abs(fd))) << s << " parameter " << k << " sample " << i;
      }
    }
  }
}

TEST(SimEffects, ParsingFollowsTheSpecKeysAndRejectsBadInput) {
  const auto m = trunnion();
  auto b = sim::parse_effect("backlash:x:0.012", m);
  ASSERT_EQ(b->reported().size(), 3u);
  EXPECT_EQ(b->reported()[0].first, "magnitude_mm");
  EXPECT_DOUBLE_EQ(b->reported()[0].second, 0.012);
  EXPECT_EQ(b->reported()[1].first, "take_up_mm");  // a screw's play by default: the gap crossed over its own width
  EXPECT_DOUBLE_EQ(b->reported()[1].second, 0.012);
  EXPECT_EQ(b->reported()[2].first, "start_opposite");
  EXPECT_DOUBLE_EQ(b->reported()[2].second, 0.0);
  EXPECT_NE(error_of([&] { sim::parse_effect("backlash:x:0.01:-0.01", m); }).find("must not be negative"),
            std::string::npos);
  EXPECT_NE(error_of([&] { sim::parse_effect("backlash:x:0.01:0.01:2", m); }).find("0 or 1"), std::string::npos);
  auto bc = sim::parse_effect("backlash:c:0.01", m);
  EXPECT_EQ(bc->reported()[0].first, "magnitude_deg");
  auto v = sim::parse_effect("vibration:tip.z:frequency_hz=166.7,amplitude_mm=0.00322", m);
  EXPECT_NEAR(v->reported()[1].second, 0.00322, 1e-12);
  EXPECT_NE(error_of([&] { sim::parse_effect("wobble:x:1", m); }).find("unknown effect 'wobble'"), std::string::npos);
  EXPECT_NE(error_of([&] { sim::parse_effect("backlash:q7:1", m); }).find("no axis 'q7'"), std::string::npos);
  EXPECT_NE(error_of([&] { sim::parse_effect("vibration:tip.w:1:1", m); }).find("not a channel"), std::string::npos);
  EXPECT_NE(error_of([&] { sim::parse_effect("servo_lag:x:lag=1", m); }).find("no parameter 'lag'"), std::string::npos);
  // Squareness is an angle between two linear slides: not between a slide and a rotary, nor between the legs of a
  // parallel machine.
  EXPECT_NE(error_of([&] { sim::parse_effect("squareness:x,c:100", m); }).find("both axes must be linear slides"),
            std::string::npos);
  const auto xmini = machine::load(std::string(CSCAM_SOURCE_DIR) + "/machines/xmini.yaml");
  EXPECT_NE(error_of([&] { sim::parse_effect("squareness:q1,q2:100", xmini); }).find("parallel-link machine"),
            std::string::npos);
  // Sign conventions of recording.md: scale actual = cmd (1 + ppm 1e-6); squareness first += gamma * second.
  const auto tr = square_path(m);
  const auto ctx = sim::make_context(tr.t, tr.cmd, {false, false, false, true, true});
  auto sc = sim::parse_effect("scale:x:100", m);
  auto sq = sim::parse_effect("squareness:x,y:100", m);
  // Straightness: first axis += k ((second - apex) / 1000)^2, k in mm/m^2.
  auto st = sim::parse_effect("straightness:z,x:mm_per_m2=2.5,apex_mm=12", m);
  EXPECT_EQ(st->axis, 2);
  EXPECT_EQ(st->axis2, 0);
  EXPECT_FALSE(st->enc_visible);
  for (size_t i = 0; i < ctx.size(); i += 97) {
    EXPECT_NEAR(sc->value(ctx, i, sc->p.data()), ctx.q[0][i] * 100e-6, 1e-15);
    EXPECT_NEAR(sq->value(ctx, i, sq->p.data()), ctx.q[1][i] * 100e-6, 1e-15);
    EXPECT_NEAR(st->value(ctx, i, st->p.data()), 2.5 * std::pow((ctx.q[0][i] - 12.0) / 1000.0, 2), 1e-15);
  }
}

TEST(SimEffects, StraightnessTakesTwoLinearSlidesOfASerialMachine) {
  const auto m = trunnion();
  EXPECT_EQ(sim::parse_effect("straightness:x,x:1", m)->axis2, 0);  // a lead error of X along itself
  EXPECT_NE(error_of([&] { sim::parse_effect("straightness:z:1", m); }).find("axis pair like z,x"), std::string::npos);
  EXPECT_NE(error_of([&] { sim::parse_effect("straightness:z,c:1", m); }).find("both axes must be linear slides"),
            std::string::npos);
  EXPECT_NE(error_of([&] { sim::parse_effect("squareness:x,x:1", m); }).find("not a pair of axes"), std::string::npos);
  const auto xmini = machine::load(std::string(CSCAM_SOURCE_DIR) + "/machines/xmini.yaml");
  EXPECT_NE(error_of([&] { sim::parse_effect("straightness:q1,q2:1", xmini); }).find("parallel-link machine"),
            std::string::npos);
}

TEST(SimProfile, TrapezoidReachesEveryBlockEndAtTheFeed) {
  const auto m = trunnion();
  const auto tr = square_path(m, 1000);
  // 8 sides of 20 mm at 10 mm/s, plus one acceleration time (5 ms at 2000 mm/s^2) per block.
  EXPECT_NEAR(tr.t.back(), 8 * (2.0 + 0.005), 0.01);
  double vmax = 0;
  for (size_t i = 1; i < tr.t.size(); ++i)
    vmax = std::max(vmax, (tr.cmd[i] - tr.cmd[i - 1]).norm() / (tr.t[i] - tr.t[i - 1]));
  EXPECT_NEAR(vmax, 10.0, 0.05);
  EXPECT_NEAR(tr.cmd.back()[0], 0.0, 1e-12);
  EXPECT_NEAR(tr.cmd.back()[1], 0.0, 1e-12);
}

TEST(SimSimulate, BacklashShowsInTheEncoderAndTheTipWithTheRightSign) {
  const auto m = trunnion();
  const auto tr = square_path(m);
  auto b = sim::parse_effect("backlash:x:0.02", m);
  sim::SimulateOptions so;
  so.channels = {"tip", "ptip", "enc"};
  const auto rec = sim::simulate(tr, m, {b.get()}, so);
  const auto& cx = rec.data[static_cast<size_t>(rec.column("cmd.x"))];
  const auto& ex = rec.data[static_cast<size_t>(rec.column("enc.x"))];
  const auto& tx = rec.data[static_cast<size_t>(rec.column("tip.x"))];
  // While x moves positive the axis trails by half the width, and the tip with it.
  const size_t i = static_cast<size_t>(0.5 * 500);  // mid first side (x increasing)
  EXPECT_NEAR(ex[i] - cx[i], -0.01, 1e-12);
  EXPECT_NEAR(tx[i] - cx[i], -0.01, 1e-9);
  // Noise is seeded: the same seed gives the same recording.
  so.noise = {{"tip", 0.001}};
  so.seed = 3;
  const auto r1 = sim::simulate(tr, m, {}, so), r2 = sim::simulate(tr, m, {}, so);
  EXPECT_EQ(r1.data[static_cast<size_t>(r1.column("tip.y"))], r2.data[static_cast<size_t>(r2.column("tip.y"))]);
}

// Lost motion is the play of a screw: the axis waits while the command crosses the gap after a reversal. The oracle is
// the play (hysteresis) operator run sample by sample: y = clamp(y, x - b/2, x + b/2). Moves are longer than the gap,
// where the effect's closed form (travel since the reversal) is exact. An axis that starts against its first move
// begins at the other flank.
TEST(SimEffects, BacklashIsThePlayOfAScrew) {
  const auto m = trunnion();
  const double b = 0.02;
  std::vector<double> t;
  std::vector<kin::Axes> cmd;
  const double legs[] = {0.0, 0.5, 0.1, 0.7, 0.3, 0.9};  // x: out and back, each leg longer than the gap
  for (std::size_t l = 1; l < std::size(legs); ++l)
    for (int k = 0; k < 200; ++k) {
      kin::Axes q = kin::Axes::Zero();
      q[0] = legs[l - 1] + (legs[l] - legs[l - 1]) * k / 200.0;
      t.push_back(static_cast<double>(t.size()) * 0.01);
      cmd.push_back(q);
    }
  const auto ctx = sim::make_context(t, cmd, {false, false, false, true, true});
  for (const bool opposite : {false, true}) {
    auto e = sim::parse_effect(fmt::format("backlash:x:{}:{}:{}", b, b, opposite ? 1 : 0), m);
    // The first move is positive: against it, the axis rests on the positive flank.
    double y = cmd[0][0] + (opposite ? 0.5 * b : -0.5 * b);
    for (std::size_t i = 0; i < cmd.size(); ++i) {
      const double x = cmd[i][0];
      y = std::clamp(y, x - 0.5 * b, x + 0.5 * b);
      if (i > 0) EXPECT_NEAR(e->value(ctx, i, e->p.data()), y - x, 1e-12) << "sample " << i << " opposite " << opposite;
    }
  }
}

// A drift of the tool point (tool.*) moves the tip in the machine frame and ptip by the same vector seen from the
// part: on the trunnion (A = 0) turned by -C about z. The oracle is that rotation written out.
TEST(SimSimulate, AToolPointDriftShowsInTipAndInPtipTurnedWithTheTable) {
  const auto m = trunnion();
  const std::string nc = "G21 G90 G94\nG0 X20 Y0 Z0 A0 C0\nG1 C90 X30 F600\nG1 C200 Y10\n";
  sim::ProfileOptions po;
  po.rate_hz = 100;
  const auto tr = sim::profile(sim::blocks_from_nc(nc::read_text(nc, "t.ngc", report::axis_letters(m)), m), po);
  auto e = sim::parse_effect("thermal_drift:tool.y:0.01:2", m);
  sim::SimulateOptions so;
  so.channels = {"tip", "ptip"};
  const auto clean = sim::simulate(tr, m, {}, so), drifted = sim::simulate(tr, m, {e.get()}, so);
  const auto col = [](const sim::Recording& r, const std::string& c) {
    return r.data[static_cast<size_t>(r.column(c))];
  };
  const auto& cc = col(clean, "cmd.c");
  const auto ctx = sim::make_context(tr.t, tr.cmd, {false, false, false, true, true});
  for (std::size_t i = 0; i < tr.t.size(); i += 17) {
    const double ctx_d = e->value(ctx, i, e->p.data());
    EXPECT_NEAR(col(drifted, "tip.y")[i] - col(clean, "tip.y")[i], ctx_d, 1e-12);
    EXPECT_NEAR(col(drifted, "tip.x")[i] - col(clean, "tip.x")[i], 0.0, 1e-12);
    const double c = cc[i] * 3.14159265358979323846 / 180.0;
    const double sgn = 1.0;  // machines/trunnion-ac.yaml: C turns about +z
    EXPECT_NEAR(col(drifted, "ptip.x")[i] - col(clean, "ptip.x")[i], ctx_d * std::sin(sgn * c), 1e-9) << i;
    EXPECT_NEAR(col(drifted, "ptip.y")[i] - col(clean, "ptip.y")[i], ctx_d * std::cos(sgn * c), 1e-9) << i;
  }
}

TEST(SimSimulate, XminiCutFromTheClFileFollowsTheFeed) {
  const auto m = machine::load(std::string(CSCAM_SOURCE_DIR) + "/machines/xmini.yaml");
  const auto blocks = sim::blocks_from_cl(std::string(CSCAM_SOURCE_DIR) + "/examples/xmini/seed000_x_cut.cls", m, 50.0);
  sim::ProfileOptions po;
  po.rate_hz = 200;
  const auto tr = sim::profile(blocks, po);
  sim::SimulateOptions so;
  so.channels = {"tip"};
  so.tool_length_mm = 50;
  const auto rec = sim::simulate(tr, m, {}, so);
  const auto& tx = rec.data[static_cast<size_t>(rec.column("tip.x"))];
  double lo = 1e9, hi = -1e9;
  for (double x : tx) lo = std::min(lo, x), hi = std::max(hi, x);
  EXPECT_NEAR(lo, -20.0, 1e-6);
  EXPECT_NEAR(hi, 20.0, 1e-6);
  EXPECT_GT(tr.t.back(), 40.0 / 2.5);  // 40 mm at 150 mm/min at least
}

// A first-order servo (de/dt = v - e/tau): the recursive filter against closed forms. Oracles: from rest under a
// constant acceleration A (v = A t, which the central differences give exactly), e = A tau (t - tau (1 - e^(-t/tau)));
// settled on a sine q = R sin(w t), the axis lags by e = tau v / (1 + i w tau) in complex amplitude. The axis trails:
// its deviation is -e (lag_s = tau_s). A strided context reads the same full-rate series at its rows.
TEST(SimEffects, AFirstOrderServoLagFollowsItsClosedForm) {
  const auto m = trunnion();
  const double tau = 0.02, A = 300.0, h = 0.002;
  std::vector<double> t;
  std::vector<kin::Axes> cmd;
  for (int k = 0; k <= 400; ++k) {
    t.push_back(k * h);
    kin::Axes q{};
    q[0] = 0.5 * A * t.back() * t.back();
    cmd.push_back(q);
  }
  auto e = sim::parse_effect("servo_lag_1st:x:0.02", m);
  EXPECT_EQ(e->reported()[0].first, "tau_s");
  EXPECT_DOUBLE_EQ(e->reported()[1].second, 0.02);  // lag_s = tau_s: a plain loop
  const auto ctx = sim::make_context(t, cmd, {false, false, false, true, true});
  // (The first row's one-sided velocity, A h / 2, starts a transient of its own: compared after 15 tau, e^-15 of it.)
  for (size_t i = 1; i + 1 < ctx.size(); ++i) {
    const double ti = ctx.t[i], truth = A * tau * (ti - tau * (1.0 - std::exp(-ti / tau)));
    if (ti < 15 * tau) continue;
    ASSERT_NEAR(-e->value(ctx, i, e->p.data()), truth, 1e-8 * std::max(1.0, truth)) << "t = " << ti;
  }
  // A sine of radius 10 mm at 2 Hz sampled at 1 kHz: after 10 tau the transient is e^-10 of it.
  const double R = 10.0, w = 2 * 3.14159265358979 * 2.0, h2 = 0.001;
  t.clear(), cmd.clear();
  for (int k = 0; k <= 2000; ++k) {
    t.push_back(k * h2);
    kin::Axes q{};
    q[1] = R * std::sin(w * t.back());
    cmd.push_back(q);
  }
  auto ey = sim::parse_effect("servo_lag_1st:y:tau_s=0.02", m);
  const auto c1 = sim::make_context(t, cmd, {false, false, false, true, true});
  const auto c5 = sim::make_context(t, cmd, {false, false, false, true, true}, 5);
  const double amp = R * w * tau / std::sqrt(1 + w * w * tau * tau), ph = std::atan(w * tau);
  for (size_t i = 0; i < c1.size(); ++i) {
    if (c1.t[i] < 10 * tau || i + 1 == c1.size()) continue;
    const double truth = amp * std::cos(w * c1.t[i] - ph);  // e = tau v / (1 + i w tau), v = R w cos(w t)
    ASSERT_NEAR(-ey->value(c1, i, ey->p.data()), truth, 1e-3 * amp) << "t = " << c1.t[i];
  }
  for (size_t k = 0; k < c5.size(); ++k)
    ASSERT_DOUBLE_EQ(ey->value(c5, k, ey->p.data()), ey->value(c1, 5 * k, ey->p.data())) << "row " << 5 * k;
  EXPECT_NE(error_of([&] { sim::parse_effect("servo_lag_1st:x:0", m); }).find("tau_s must be positive"),
            std::string::npos);
  EXPECT_NE(error_of([&] { sim::parse_effect("step:tip.z:step_mm=0.01", m); }).find("'t_s' is missing"),
            std::string::npos);
  EXPECT_NE(error_of([&] { sim::parse_effect("step:x:0.01:2", m); }).find("not a channel"), std::string::npos);
}
