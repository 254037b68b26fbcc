// Axis statistics against hand-computed values, and verification catching a deviating program.
#include <gtest/gtest.h>

#include "cscam/core/units.hpp"
#include "cscam/report/backlash.hpp"
#include "cscam/report/json.hpp"
#include "cscam/report/stats.hpp"
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
