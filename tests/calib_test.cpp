// Calibration: models, recordings, identifiability, recovery of injected errors, corrected files, CLI.
#include <ceres/jet.h>
#include <fmt/format.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iostream>
#include <nlohmann/json.hpp>
#include <random>
#include <sstream>

#include "cscam/calib/calibrate.hpp"
#include "cscam/calib/model.hpp"
#include "cscam/calib/recording.hpp"
#include "cscam/core/error.hpp"
#include "cscam/core/tolerances.hpp"
#include "cscam/kin/xmini.hpp"
#include "cscam/machine/machine.hpp"
#include "test_support.hpp"

using namespace cscam;
using calib::Dataset;
using calib::Model;
using test::source_path;

namespace {

// ---- Levels and tolerances of the write-safeguard, loader and recording tests (one place) ----
constexpr double kGaugeSigmaMm = 0.001;   // simulated probing noise, and the recording's sigma.ptip
constexpr double kOutlierMm = 0.06;       // one gross probing error (60 sigma): chi^2 ~ 3600 for ~90 dof
constexpr double kInjectedEX0CMm = 0.02;  // injected rotary-axis location errors (20 and 10 sigma-ish)
constexpr double kInjectedEZ0AMm = -0.01;
constexpr int kNoiseOnlyTrials = 40;       // seeded noise-only recordings of a perfect machine
constexpr int kNoiseOnlyMaxRewrites = 3;   // at level 0.01 (joint and Bonferroni tests) ~0.8 expected
constexpr double kChi2TailRel = 1e-10;     // chi^2 tail against its closed forms (dof 1 and 2)
constexpr double kUnitDirTol = 1e-9;       // |dir| of a simulated direction written with 12 decimals
constexpr double kNullRelationRel = 2e-3;  // |J v| / sum |v_i| |J_i| of a printed (4-digit) null relation

std::shared_ptr<Model> load(const std::string& name) {
  return calib::load_model(source_path("machines/" + name + ".yaml"));
}

/// Nominal plus uniform errors of up to +-amp (mm or deg) on the parameters `idx`.
std::vector<double> perturbed(const Model& m, const std::vector<std::size_t>& idx, double amp, unsigned salt) {
  auto rng = test::rng(salt);
  std::uniform_real_distribution<double> u(-amp, amp);
  std::vector<double> p = m.nominal();
  for (std::size_t i : idx) p[i] += u(rng);
  return p;
}

std::vector<std::size_t> all(const Model& m) {
  std::vector<std::size_t> v(m.size());
  for (std::size_t i = 0; i < v.size(); ++i) v[i] = i;
  return v;
}

/// Central finite differences of the weighted residuals vs the automatic Jacobian.
void expect_jacobian_matches(const Model& m, const Dataset& d, const std::vector<double>& p) {
  const Eigen::MatrixXd J = calib::jacobian(m, d, p, all(m));
  for (std::size_t j = 0; j < m.size(); ++j) {
    const double h = 1e-6;
    std::vector<double> pp = p, pm = p;
    pp[j] += h;
    pm[j] -= h;
    // Weighted residual = (meas - pred)/sigma: d/dp = -dpred/dp / sigma. Build it from predictions.
    Eigen::VectorXd col(J.rows());
    Eigen::Index r = 0;
    auto sp = m.make_scratch(), sm = m.make_scratch();
    std::vector<double> op(9 + m.links().size()), om(op.size());
    for (const auto& pose : d.poses) {
      m.predict_channels(pose.q.data(), pp.data(), op.data(), sp.get());
      m.predict_channels(pose.q.data(), pm.data(), om.data(), sm.get());
      for (std::size_t c = 0; c < op.size(); ++c) {
        if (std::isnan(pose.meas[c])) continue;
        const double s = c < 3 ? d.sigma.tip_mm : c < 6 ? d.sigma.dir : c < 9 ? d.sigma.ptip_mm : d.sigma.len_mm;
        col[r++] = -(op[c] - om[c]) / (2 * h) / s;
      }
    }
    ASSERT_EQ(r, J.rows());
    const double scale = std::max(1.0, J.col(static_cast<Eigen::Index>(j)).norm());
    EXPECT_LT((col - J.col(static_cast<Eigen::Index>(j))).norm() / scale, tol::kCalibJacobianRel) << m.params()[j].name;
  }
}

}  // namespace

// ---------------------------------------------------------------------------------------------------
// Models
// ---------------------------------------------------------------------------------------------------

TEST(CalibModel, SerialNominalMatchesMachineKinematics) {
  const auto m = load("trunnion-ac");
  EXPECT_EQ(m->kind(), "serial");
  for (const char* n : {"EX0C", "EY0C", "EA0C", "EB0C", "EC0C", "EY0A", "EZ0A", "EB0A", "EC0A", "EA0A"})
    EXPECT_NO_THROW((void)m->index(n)) << n;
  const machine::Machine mm = machine::load(source_path("machines/trunnion-ac.yaml"));
  const auto k = mm.make_kinematics(m->tool_length_mm());
  const std::vector<double> q{12.5, -30, 40, 20, 75};
  const auto pred = m->predict(q, m->nominal());
  kin::Axes qa;
  qa << 12.5, -30, 40, deg2rad(20.0), deg2rad(75.0);
  const kin::Posed pose = k->forward(qa);
  EXPECT_LT((pred.ptip - pose.tip_mm).norm(), 1e-12);
  // Tip in W: head side only.
  EXPECT_LT((pred.tip - Eigen::Vector3d(12.5, -30, 40)).norm(), 1e-12);
}

TEST(CalibModel, XminiHomeAndPerturbedVectorsMatchSpec) {
  const auto m = load("xmini");
  ASSERT_EQ(m->size(), kin::kXminiParamCount);
  EXPECT_EQ(m->params()[0].name, "pWB_x");
  const auto pred = m->predict({154.669331, 158.276253, 154.669331, 0, 0}, m->nominal());
  EXPECT_LT(pred.tip.norm(), 1e-5);
  EXPECT_LT((pred.dir - Eigen::Vector3d::UnitZ()).norm(), 1e-8);
  // The spec's reference vectors: FK of the listed joints gives the listed tip and direction.
  std::ifstream in(source_path("tests/data/xmini-vectors.csv"));
  ASSERT_TRUE(in);
  std::string line, header;
  std::vector<double> pert = m->nominal();
  int checked = 0;
  while (std::getline(in, line)) {
    if (line.rfind("# theta0=", 0) == 0) {
      std::stringstream ss(line.substr(2));
      std::string kv;
      while (std::getline(ss, kv, ';')) {
        const auto eq = kv.find('=');
        pert[m->index(kv.substr(0, eq))] = std::stod(kv.substr(eq + 1));
      }
      continue;
    }
    if (line.empty() || line[0] == '#' || line.rfind("case", 0) == 0) continue;
    std::vector<std::string> c;
    std::stringstream ss(line);
    std::string cell;
    while (std::getline(ss, cell, ',')) c.push_back(cell);
    const bool is_pert = c[1] == "perturbed";
    m->set_tool_length_mm(std::stod(c[2]));
    const std::vector<double> q{std::stod(c[10]), std::stod(c[11]), std::stod(c[12]), std::stod(c[13]),
                                std::stod(c[14])};
    const auto pr = m->predict(q, is_pert ? pert : m->nominal());
    EXPECT_LT((pr.tip - Eigen::Vector3d(std::stod(c[3]), std::stod(c[4]), std::stod(c[5]))).norm(), 1e-7) << line;
    EXPECT_LT((pr.dir - Eigen::Vector3d(std::stod(c[6]), std::stod(c[7]), std::stod(c[8]))).norm(), 1e-9) << line;
    ++checked;
  }
  EXPECT_GT(checked, 10);
}

TEST(CalibModel, JacobianMatchesFiniteDifferences) {
  calib::Sigmas s;
  for (const char* name : {"trunnion-ac", "xmini", "pcmm"}) {
    const auto m = load(name);
    const auto poses = m->random_poses(4, 7);
    ASSERT_EQ(poses.size(), 4u) << name;
    const std::vector<std::string> ch =
        m->kind() == "pcmm" ? std::vector<std::string>{"tip", "len"} : std::vector<std::string>{"tip", "dir", "ptip"};
    const Dataset d = calib::simulate(*m, m->nominal(), poses, ch, s, 1);
    SCOPED_TRACE(name);
    expect_jacobian_matches(*m, d, perturbed(*m, all(*m), 0.2, 3));
  }
}

TEST(CalibModel, SelectByNameAndGroup) {
  const auto m = load("xmini");
  EXPECT_EQ(m->select({"wrist"}).size(), 10u);
  EXPECT_EQ(m->select({"legs", "gz"}).size(), 4u);
  try {
    (void)m->select({"nonsense"});
    FAIL();
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("nonsense"), std::string::npos);
  }
}

// ---------------------------------------------------------------------------------------------------
// Recordings
// ---------------------------------------------------------------------------------------------------

TEST(CalibRecording, ParsesStaticAndTrajectory) {
  const auto r = calib::parse_recording(
      "# machine: machines/xmini.yaml\n# kind: static\n# tool_length: 50\n"
      "cmd.q1,cmd.q2,cmd.q3,cmd.c,cmd.a,tip.x,tip.y,tip.z\n"
      "1,2,3,4,5,0.1,,0.3\n# a comment\n6,7,8,9,10,1,2,3\n",
      "rec.csv");
  EXPECT_EQ(r.kind(), "static");
  EXPECT_EQ(r.rows(), 2);
  EXPECT_TRUE(std::isnan(r.data(0, 6)));
  EXPECT_EQ(r.line_of_row[1], 7);
  EXPECT_DOUBLE_EQ(*r.tool_length_mm(), 50.0);
  const auto t = calib::parse_recording("# kind: trajectory\nt,cmd.x,tip.x\n0,1,2\n0.1,1,2\n", "traj.csv");
  EXPECT_EQ(t.rows(), 2);
}

TEST(CalibRecording, ErrorsNameFileLineColumn) {
  try {
    (void)calib::parse_recording("# kind: static\ncmd.x,tip.x\n1,2\n1,abc\n", "bad.csv");
    FAIL();
  } catch (const InputError& e) {
    EXPECT_EQ(e.where().file, "bad.csv");
    EXPECT_EQ(e.where().line, 4);
    EXPECT_EQ(e.where().column, 3);
  }
  try {
    (void)calib::parse_recording("# kind: static\ncmd.x,tipp.x\n1,2\n", "bad.csv");
    FAIL();
  } catch (const InputError& e) {
    EXPECT_EQ(e.where().line, 2);
    EXPECT_EQ(e.where().column, 7);
    EXPECT_NE(std::string(e.what()).find("tipp.x"), std::string::npos);
  }
}

TEST(CalibRecording, ColumnNotMatchingAxesIsNamed) {
  const auto m = load("xmini");
  const auto r = calib::parse_recording(
      "# kind: static\ncmd.q1,cmd.q2,cmd.q3,cmd.c,cmd.b,tip.x,tip.y,tip.z\n1,2,3,4,5,0.1,0.2,0.3\n", "r.csv");
  try {
    (void)calib::dataset_from(r, *m);
    FAIL();
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("cmd.b"), std::string::npos) << e.what();
    EXPECT_EQ(e.where().line, 2);
    EXPECT_EQ(e.where().column, 28);
  }
}

TEST(CalibRecording, FewerMeasurementsThanParametersSaysHowMany) {
  const auto m = load("xmini");
  calib::Sigmas s;
  const Dataset d = calib::simulate(*m, m->nominal(), m->random_poses(5, 3), {"tip"}, s, 1);
  try {
    (void)calib::calibrate(*m, d, calib::Options{});
    FAIL();
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("15 independent measurements for 38 free parameters: at least 38"),
              std::string::npos)
        << e.what();
  }
}

// ---------------------------------------------------------------------------------------------------
// Identifiability and recovery
// ---------------------------------------------------------------------------------------------------

TEST(CalibIdent, PcmmPassiveLinkOnlyIsRankDeficientTipFixesIt) {
  const auto m = load("pcmm");
  const auto poses = m->random_poses(45, 11);
  ASSERT_EQ(poses.size(), 45u);
  calib::Sigmas s;
  const Dataset len = calib::simulate(*m, m->nominal(), poses, {"len"}, s, 1);
  const calib::Identifiability a = calib::analyse(*m, len, m->nominal(), calib::Options{});
  EXPECT_EQ(a.rank, 19);  // 26 - 7: base rotation (3) and height (1), stage frame in its plane (3)
  EXPECT_EQ(a.fixed.size(), 7u);
  EXPECT_EQ(a.combinations.size(), 7u);
  // Probe-tip positions in W pin the base frame and the stage frame's shifts; what remains is the
  // stage frame's rotation about the probe axis (a naming convention: the angles ths_i and (sx, sy)
  // turn together).
  const Dataset both = calib::simulate(*m, m->nominal(), poses, {"len", "tip"}, s, 1);
  const calib::Identifiability b = calib::analyse(*m, both, m->nominal(), calib::Options{});
  EXPECT_EQ(b.rank, 25);
  ASSERT_EQ(b.combinations.size(), 1u);
  for (const char* n : {"ths1", "ths2", "ths3"}) EXPECT_NE(b.combinations[0].find(n), std::string::npos) << n;
  calib::Options o;
  o.free = m->select({"all"});
  o.free.erase(std::find(o.free.begin(), o.free.end(), m->index("ths1")));
  const calib::Identifiability c = calib::analyse(*m, both, m->nominal(), o);
  EXPECT_EQ(c.rank, 25);
  EXPECT_TRUE(c.fixed.empty());
}

TEST(CalibIdent, PcmmTable1NoiseFreeRecoversAll26) {
  const auto m = load("pcmm");
  const std::vector<double> truth = perturbed(*m, all(*m), 0.5, 5);
  const auto poses = m->random_poses(45, 11);
  calib::Sigmas s;
  s.tip_mm = s.len_mm = 1e-20;  // noise-free data; weights equal
  Dataset d = calib::simulate(*m, truth, poses, {"len", "tip"}, s, 1);
  d.sigma.tip_mm = d.sigma.len_mm = 0.001;
  calib::Options o;
  o.free = m->select({"all"});
  o.free.erase(std::find(o.free.begin(), o.free.end(), m->index("ths1")));  // the stage frame's convention
  const calib::Result r = calib::calibrate(*m, d, o);
  ASSERT_TRUE(r.summary.converged) << r.summary.message;
  // The truth in the convention ths1 = nominal: turn the stage frame by -delta about its z axis.
  const double delta = truth[m->index("ths1")] - m->nominal()[m->index("ths1")];
  std::vector<double> t = truth;
  for (const char* n : {"ths1", "ths2", "ths3"}) t[m->index(n)] -= delta;
  const double c = std::cos(deg2rad(-delta)), sn = std::sin(deg2rad(-delta));
  t[m->index("sx")] = c * truth[m->index("sx")] - sn * truth[m->index("sy")];
  t[m->index("sy")] = sn * truth[m->index("sx")] + c * truth[m->index("sy")];
  for (std::size_t i = 0; i < m->size(); ++i)
    EXPECT_NEAR(r.estimate[i], t[i], tol::kCalibRecoveryNoiseFree) << m->params()[i].name;
}

TEST(CalibIdent, XminiNamesUnidentifiableAndPredictsHeldOutWithinNoise) {
  const auto m = load("xmini");
  // Truth: spec/xmini-vectors.csv's perturbed set.
  std::vector<double> truth = m->nominal();
  const std::map<std::string, double> pert{
      {"theta0", 0.02}, {"eps_y", -0.015}, {"A1x", -150.3}, {"A3x", 149.8}, {"l1", 0.2},   {"l3", -0.15},
      {"A2x", 0.4},     {"A2y", 200.3},    {"A2z", -0.25},  {"b1x", -75.2}, {"b1z", 0.1},  {"b3x", 75.15},
      {"b3z", -0.2},    {"c2x", 0.3},      {"c2y", 99.8},   {"c2z", 0.2},   {"phi", 0.3},  {"chi", -0.2},
      {"L01", 450.4},   {"L02", 449.7},    {"L03", 450.2},  {"sCx", 0.2},   {"sCy", -0.1}, {"sCz", 150.3},
      {"gC1", 0.01},    {"gC2", -0.02},    {"c0", 0.05},    {"e", 0.1},     {"f", -0.15},  {"psi", 0.03},
      {"a0", -0.04},    {"gx", 0.05},      {"gy", -0.05},   {"gz", 100.2}};
  for (const auto& [k, v] : pert) truth[m->index(k)] = v;
  calib::Sigmas s;
  s.tip_mm = 0.002;
  const Dataset fit = calib::simulate(*m, truth, m->random_poses(150, 21), {"tip"}, s, 2);
  const Dataset hold = calib::simulate(*m, truth, m->random_poses(60, 22), {"tip"}, s, 3);
  const calib::Result r = calib::calibrate(*m, fit, calib::Options{});
  ASSERT_TRUE(r.summary.converged) << r.summary.message;
  EXPECT_GT(r.ident.fixed.size(), 0u);
  EXPECT_FALSE(r.ident.messages.empty());
  const auto before = calib::residual_stats(*m, hold, m->nominal());
  const auto after = calib::residual_stats(*m, hold, r.estimate);
  const double noise = s.tip_mm * std::sqrt(3.0);  // RMS of a 3-vector of sigma-noise
  EXPECT_GT(before.rms.at("tip"), 100 * noise);
  EXPECT_LT(after.rms.at("tip"), 2 * noise);
}

TEST(CalibIdent, TrunnionRotaryLocationErrorsFromTableProbing) {
  const auto m = load("trunnion-ac");
  const std::vector<std::string> loc{"EX0C", "EY0C", "EA0C", "EB0C", "EY0A", "EZ0A", "EB0A", "EC0A"};
  std::vector<double> truth = m->nominal();
  const double errs[] = {0.02, -0.015, 0.01, -0.008, 0.03, -0.01, 0.005, 0.012};
  for (std::size_t i = 0; i < loc.size(); ++i) truth[m->index(loc[i])] = errs[i];
  calib::Sigmas s;
  s.ptip_mm = 0.0005;
  const Dataset d = calib::simulate(*m, truth, m->random_poses(60, 5), {"ptip"}, s, 4);
  calib::Options o;
  o.free = m->select({"rotary_a", "rotary_c"});
  const calib::Result r = calib::calibrate(*m, d, o);
  ASSERT_TRUE(r.summary.converged);
  for (std::size_t i = 0; i < loc.size(); ++i) {
    const std::size_t k = m->index(loc[i]);
    if (std::isnan(r.stddev[k])) continue;  // fixed: reported unidentifiable
    EXPECT_NEAR(r.estimate[k], truth[k], 5 * r.stddev[k] + 1e-9) << loc[i];
  }
}

TEST(CalibYaml, CorrectedFileRoundTripsAndMarksChanges) {
  for (const char* name : {"xmini", "trunnion-ac", "pcmm"}) {
    const auto m = load(name);
    std::vector<double> p = m->nominal();
    p[1] += 0.0123;
    p[m->size() - 2] -= 0.0456;
    const std::string text = m->corrected_yaml(p);
    EXPECT_NE(text.find("# calibrated:"), std::string::npos) << name;
    const std::string path = ::testing::TempDir() + std::string("/corrected-") + name + ".yaml";
    { std::ofstream(path) << text; }
    const auto m2 = calib::load_model(path);
    // The corrected file's nominal predicts like the original model with p.
    const auto poses = m->random_poses(3, 9);
    for (const auto& q : poses) {
      const auto a = m->predict(q, p);
      const auto b = m2->predict(q, m2->nominal());
      EXPECT_LT((a.ptip - b.ptip).norm(), 1e-8) << name << "\n" << text;
    }
  }
}

// ---------------------------------------------------------------------------------------------------
// Command line
// ---------------------------------------------------------------------------------------------------

namespace {

std::string tmp(const std::string& name) {
  const std::string dir = ::testing::TempDir() + "/calib_cli";
  std::filesystem::create_directories(dir);
  return dir + "/" + name;
}

void write(const std::string& path, const std::string& text) { std::ofstream(path) << text; }

std::vector<double> xmini_truth(const Model& m) {
  std::vector<double> t = m.nominal();
  const char* pert =
      "theta0=0.02;eps_y=-0.015;A1x=-150.3;A3x=149.8;l1=0.2;l3=-0.15;A2x=0.4;A2y=200.3;A2z=-0.25;b1x=-75.2;b1z=0.1;"
      "b3x=75.15;b3z=-0.2;c2x=0.3;c2y=99.8;c2z=0.2;phi=0.3;chi=-0.2;L01=450.4;L02=449.7;L03=450.2;sCx=0.2;sCy=-0.1;"
      "sCz=150.3;gC1=0.01;gC2=-0.02;c0=0.05;e=0.1;f=-0.15;psi=0.03;a0=-0.04;gx=0.05;gy=-0.05;gz=100.2";
  std::stringstream ss(pert);
  std::string kv;
  while (std::getline(ss, kv, ';')) {
    const auto eq = kv.find('=');
    t[m.index(kv.substr(0, eq))] = std::stod(kv.substr(eq + 1));
  }
  return t;
}

}  // namespace

TEST(CalibCli, XminiEndToEndCorrectedFilePredictsUnseenPoses) {
  const auto m = load("xmini");
  const std::vector<double> truth = xmini_truth(*m);
  calib::Sigmas s;
  s.tip_mm = 0.002;
  const std::string machine = source_path("machines/xmini.yaml");
  const std::string rec = tmp("xmini-tracker.csv"), out = tmp("xmini-corrected.yaml");
  write(rec, calib::format_recording(calib::to_recording(
                 *m, calib::simulate(*m, truth, m->random_poses(200, 31), {"tip"}, s, 5), machine)));
  std::filesystem::remove(out);
  const auto r = test::run_command(fmt::format("{} calibrate {} -o {} --json", CSCAM_CLI, rec, out));
  ASSERT_EQ(r.status, 0) << r.output;
  EXPECT_NE(r.output.find("\"unidentifiable\""), std::string::npos);
  ASSERT_TRUE(std::filesystem::exists(out));
  // An independent reading of the corrected file: the machine loader, then FK on unseen poses.
  const machine::Machine cm = machine::load(out);
  const auto k = cm.kinematics();
  const Dataset unseen = calib::simulate(*m, truth, m->random_poses(100, 77), {"tip"}, s, 6);
  double sum = 0;
  for (const auto& p : unseen.poses) {
    kin::Axes q;
    q << p.q[0], p.q[1], p.q[2], deg2rad(p.q[3]), deg2rad(p.q[4]);
    sum += (k->forward(q).tip_mm - Eigen::Vector3d(p.meas[0], p.meas[1], p.meas[2])).squaredNorm();
  }
  const double rms = std::sqrt(sum / static_cast<double>(unseen.poses.size()));
  EXPECT_LT(rms, 2 * s.tip_mm * std::sqrt(3.0)) << rms;
}

TEST(CalibCli, BadInputNamesWhereAndWritesNothing) {
  const std::string out = tmp("never.yaml");
  std::filesystem::remove(out);
  const std::string machine = source_path("machines/xmini.yaml");
  // A column that is no axis of the machine.
  const std::string bad_axis = tmp("bad-axis.csv");
  write(bad_axis, "# kind: static\ncmd.q1,cmd.q2,cmd.q3,cmd.c,cmd.b,tip.x,tip.y,tip.z\n1,2,3,4,5,6,7,8\n");
  auto r = test::run_command(fmt::format("{} calibrate {} --machine {} -o {}", CSCAM_CLI, bad_axis, machine, out));
  EXPECT_NE(r.status, 0);
  EXPECT_NE(r.output.find(bad_axis + ":2:28"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("cmd.b"), std::string::npos) << r.output;
  // A malformed number: file, line and column.
  const std::string bad_num = tmp("bad-num.csv");
  write(bad_num,
        "# kind: static\ncmd.q1,cmd.q2,cmd.q3,cmd.c,cmd.a,tip.x,tip.y,tip.z\n1,2,3,4,5,6,7,8\n1,2,3,4,5,6,x7,8\n");
  r = test::run_command(fmt::format("{} calibrate {} --machine {} -o {}", CSCAM_CLI, bad_num, machine, out));
  EXPECT_NE(r.status, 0);
  EXPECT_NE(r.output.find(bad_num + ":4:13"), std::string::npos) << r.output;
  // Too few measurements.
  r = test::run_command(fmt::format("{} calibrate {} --machine {} -o {} --split 0", CSCAM_CLI,
                                    source_path("machines/../tests/data/xmini-vectors.csv"), machine, out));
  EXPECT_NE(r.status, 0);
  const std::string few = tmp("few.csv");
  write(few,
        "# kind: "
        "static\ncmd.q1,cmd.q2,cmd.q3,cmd.c,cmd.a,tip.x,tip.y,tip.z\n154.669331,158.276253,154.669331,0,0,0,0,0\n");
  r = test::run_command(fmt::format("{} calibrate {} --machine {} -o {}", CSCAM_CLI, few, machine, out));
  EXPECT_NE(r.status, 0);
  EXPECT_NE(r.output.find("at least 38"), std::string::npos) << r.output;
  EXPECT_FALSE(std::filesystem::exists(out));
  // A solve that does not converge: Ceres' termination reason, exit 1, no file.
  const auto m = load("xmini");
  calib::Sigmas s;
  s.tip_mm = 0.002;
  const std::string rec = tmp("xmini-short.csv");
  write(rec, calib::format_recording(calib::to_recording(
                 *m, calib::simulate(*m, xmini_truth(*m), m->random_poses(60, 41), {"tip"}, s, 5), machine)));
  r = test::run_command(fmt::format("{} calibrate {} -o {} --max-iterations 2", CSCAM_CLI, rec, out));
  EXPECT_EQ(r.status, 1) << r.output;
  EXPECT_NE(r.output.find("NO_CONVERGENCE"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("no corrected file written"), std::string::npos) << r.output;
  EXPECT_FALSE(std::filesystem::exists(out));
}

TEST(CalibIdent, RobustLossListsOutlierPoses) {
  const auto m = load("trunnion-ac");
  std::vector<double> truth = m->nominal();
  truth[m->index("EX0C")] = 0.02;
  truth[m->index("EZ0A")] = -0.01;
  calib::Sigmas s;
  s.ptip_mm = 0.0005;
  Dataset d = calib::simulate(*m, truth, m->random_poses(40, 3), {"ptip"}, s, 7);
  for (std::size_t k = 0; k < d.poses.size(); ++k) d.poses[k].line = static_cast<int>(k) + 3;
  d.poses[5].meas[6] += 0.05;  // two gross probing errors (50 um)
  d.poses[17].meas[8] -= 0.08;
  calib::Options o;
  o.free = m->select({"rotary_a", "rotary_c"});
  o.loss = calib::Loss::Huber;
  const calib::Result r = calib::calibrate(*m, d, o);
  ASSERT_TRUE(r.summary.converged);
  ASSERT_EQ(r.outliers.size(), 2u);
  EXPECT_EQ(r.outliers[0].line, 8);
  EXPECT_EQ(r.outliers[1].line, 20);
  EXPECT_NEAR(r.estimate[m->index("EX0C")], 0.02, 0.002);
}

TEST(CalibCli, TrunnionTableProbingAndDesign) {
  const auto m = load("trunnion-ac");
  std::vector<double> truth = m->nominal();
  truth[m->index("EX0C")] = 0.02;
  truth[m->index("EY0A")] = -0.03;
  truth[m->index("EB0A")] = 0.01;
  calib::Sigmas s;
  s.ptip_mm = 0.0005;
  const std::string machine = source_path("machines/trunnion-ac.yaml");
  const std::string rec = tmp("trunnion-probe.csv"), out = tmp("trunnion-corrected.yaml");
  write(rec, calib::format_recording(
                 calib::to_recording(*m, calib::simulate(*m, truth, m->random_poses(40, 3), {"ptip"}, s, 7), machine)));
  auto r = test::run_command(
      fmt::format("{} calibrate {} --machine {} -o {} --free rotary_a,rotary_c", CSCAM_CLI, rec, machine, out));
  ASSERT_EQ(r.status, 0) << r.output;
  EXPECT_NE(r.output.find("EX0C"), std::string::npos);
  const auto m2 = calib::load_model(out);
  for (const auto& q : m->random_poses(5, 99))
    EXPECT_LT((m2->predict(q, m2->nominal()).ptip - m->predict(q, truth).ptip).norm(), 0.005);
  r = test::run_command(fmt::format("{} calibrate --design 12 --machine {} --free rotary_a,rotary_c --candidates 300",
                                    CSCAM_CLI, machine));
  ASSERT_EQ(r.status, 0) << r.output;
  EXPECT_NE(r.output.find("designed"), std::string::npos) << r.output;
  // Free parameters the channel cannot see are named, so that a design's healthy figures (of the others) do not
  // pass for theirs.
  r = test::run_command(
      fmt::format("{} calibrate --design 12 --machine {} --channels tip --free squareness,tool --candidates 300",
                  CSCAM_CLI, machine));
  ASSERT_EQ(r.status, 0) << r.output;
  EXPECT_NE(r.output.find("not identifiable from tip: tool_tilt_x"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("for the identifiable parameters only"), std::string::npos) << r.output;
}

TEST(CalibIdent, PcmmMonteCarloCoverageOf95PercentIntervals) {
  // Gauge noise 0.5 um on the passive link and the probe tip; 100 seeded trials.
  const auto m = load("pcmm");
  std::vector<double> truth = perturbed(*m, all(*m), 0.5, 5);
  truth[m->index("ths1")] = m->nominal()[m->index("ths1")];  // the stage frame's convention (see above)
  const auto poses = m->random_poses(45, 11);
  calib::Sigmas s;
  s.tip_mm = s.len_mm = 0.0005;
  calib::Options o;
  o.free = m->select({"all"});
  o.free.erase(std::find(o.free.begin(), o.free.end(), m->index("ths1")));
  int inside = 0, total = 0;
  for (int trial = 0; trial < 100; ++trial) {
    const Dataset d = calib::simulate(*m, truth, poses, {"len", "tip"}, s, 1000 + static_cast<unsigned>(trial));
    const calib::Result r = calib::calibrate(*m, d, o);
    ASSERT_TRUE(r.summary.converged);
    for (std::size_t i : o.free) {
      ++total;
      inside += std::abs(r.estimate[i] - truth[i]) <= 1.96 * r.stddev[i];
    }
  }
  const double coverage = static_cast<double>(inside) / total;
  EXPECT_GE(coverage, 0.90);
  EXPECT_LE(coverage, 0.99);
}

TEST(CalibCli, XminiPostedWithCorrectedFilePutsTrueTipOnPath) {
  // What the post does per CL point: IK of the machine file. With the corrected file, the true machine
  // (the perturbed parameters) must put the tip on the CL points; with the nominal file it misses by mm.
  const auto m = load("xmini");
  const std::vector<double> truth = xmini_truth(*m);
  calib::Sigmas s;
  s.tip_mm = 0.002;
  const Dataset d = calib::simulate(*m, truth, m->random_poses(200, 51), {"tip", "dir"}, s, 8);
  calib::Dataset fit = d;
  const calib::Result r = calib::calibrate(*m, fit, calib::Options{});
  ASSERT_TRUE(r.summary.converged);
  const std::string out = tmp("xmini-corrected-post.yaml");
  write(out, m->corrected_yaml(r.estimate));
  const auto corrected = machine::load(out).kinematics();
  const auto nominal = machine::load(source_path("machines/xmini.yaml")).kinematics();
  auto worst_on_path = [&](const kin::Kinematics& k) {
    double worst = 0;
    std::vector<kin::Solution> sols;
    for (const auto& q0 : m->random_poses(40, 61)) {
      const auto target = m->predict(q0, m->nominal());  // a CL point: tip and tool axis
      k.inverse_branches(kin::Posed{target.tip, target.dir}, nullptr, sols);
      EXPECT_FALSE(sols.empty());
      if (sols.empty()) continue;
      const kin::Axes& q = sols.front().axes;
      const auto real = m->predict({q[0], q[1], q[2], rad2deg(q[3]), rad2deg(q[4])}, truth);
      worst = std::max(worst, (real.tip - target.tip).norm());
    }
    return worst;
  };
  const double with_nominal = worst_on_path(*nominal), with_corrected = worst_on_path(*corrected);
  EXPECT_GT(with_nominal, 1.0);
  EXPECT_LT(with_corrected, 0.01) << "nominal " << with_nominal;
  RecordProperty("worst_tip_error_nominal_mm", std::to_string(with_nominal));
  RecordProperty("worst_tip_error_corrected_mm", std::to_string(with_corrected));
  std::cout << "XMINI true tip off the CL points: nominal file " << with_nominal << " mm, corrected file "
            << with_corrected << " mm\n";
}

TEST(CalibIdent, RegulariseKeepsUnidentifiableNearNominalAndHoldoutFileIsUsed) {
  const auto m = load("xmini");
  calib::Sigmas s;
  s.tip_mm = 0.002;
  const std::vector<double> truth = xmini_truth(*m);
  const Dataset d = calib::simulate(*m, truth, m->random_poses(120, 71), {"tip"}, s, 9);
  calib::Options o;
  o.regularise = true;
  const calib::Result r = calib::calibrate(*m, d, o);
  ASSERT_TRUE(r.summary.converged);
  ASSERT_FALSE(r.ident.fixed.empty());
  for (std::size_t i : r.ident.fixed) {
    EXPECT_TRUE(std::isfinite(r.stddev[i])) << m->params()[i].name;  // free, with a prior
    EXPECT_LT(std::abs(r.estimate[i] - m->nominal()[i]), 0.1) << m->params()[i].name;
  }
  // The CLI with a separate held-out recording.
  const std::string machine = source_path("machines/xmini.yaml");
  const std::string fit = tmp("xmini-fit.csv"), hold = tmp("xmini-hold.csv");
  write(fit, calib::format_recording(calib::to_recording(*m, d, machine)));
  write(hold, calib::format_recording(calib::to_recording(
                  *m, calib::simulate(*m, truth, m->random_poses(30, 72), {"tip"}, s, 10), machine)));
  const auto c = test::run_command(fmt::format("{} calibrate {} --holdout {} --regularise", CSCAM_CLI, fit, hold));
  ASSERT_EQ(c.status, 0) << c.output;
  EXPECT_NE(c.output.find("held-out (" + hold + ", 30 poses)"), std::string::npos) << c.output;
  EXPECT_NE(c.output.find("regularised toward nominal"), std::string::npos) << c.output;
}

// Without the robust loss and without sigmas in the recording, gross outliers raised their own limit (the
// chi^2-rescaled sigma) and hid: the limit is now the median pose's residual.
TEST(CalibIdent, OutliersShowWithoutTheRobustLossAndWithoutSigmas) {
  const auto m = load("trunnion-ac");
  std::vector<double> truth = m->nominal();
  truth[m->index("EX0C")] = 0.02;
  calib::Sigmas s;
  s.ptip_mm = 0.001;
  Dataset d = calib::simulate(*m, truth, m->random_poses(40, 3), {"ptip"}, s, 7);
  d.sigma = calib::Sigmas{};  // as read from a recording that gives none
  for (std::size_t k = 0; k < d.poses.size(); ++k) d.poses[k].line = static_cast<int>(k) + 3;
  for (const std::size_t k : {4u, 9u, 17u}) d.poses[k].meas[6] += 0.58;  // three probing errors of 0.58 mm
  calib::Options o;
  o.free = m->select({"rotary_a", "rotary_c"});
  const calib::Result r = calib::calibrate(*m, d, o);
  ASSERT_EQ(r.outliers.size(), 3u);
  EXPECT_EQ(r.outliers[0].line, 7);
  EXPECT_EQ(r.outliers[1].line, 12);
  EXPECT_EQ(r.outliers[2].line, 20);
}

// A held-out pose that the corrected model misses by far more than the fit's noise is named (it did not pull the fit,
// so no fitted outlier shows it), by the fitted poses' rule: with and without sigmas in the recording. Oracle: the one
// pose corrupted by 0.05 mm, among 10 held out; the clean held-out poses are never named.
TEST(CalibIdent, AHeldOutPoseFarOutsideTheNoiseIsNamed) {
  const auto m = load("trunnion-ac");
  std::vector<double> truth = m->nominal();
  truth[m->index("EX0C")] = 0.02;
  calib::Sigmas s;
  s.ptip_mm = 0.001;
  for (const bool sigmas : {true, false}) {
    Dataset fit = calib::simulate(*m, truth, m->random_poses(40, 3), {"ptip"}, s, 7);
    Dataset hold = calib::simulate(*m, truth, m->random_poses(10, 4), {"ptip"}, s, 8);
    if (!sigmas) fit.sigma = hold.sigma = calib::Sigmas{};
    for (std::size_t k = 0; k < hold.poses.size(); ++k) hold.poses[k].line = static_cast<int>(k) + 50;
    calib::Options o;
    o.free = m->select({"rotary_a", "rotary_c"});
    const calib::Result r = calib::calibrate(*m, fit, o);
    EXPECT_TRUE(calib::heldout_outliers(*m, hold, r.estimate, r).empty()) << "sigmas " << sigmas;
    hold.poses[6].meas[7] += 0.05;
    const auto bad = calib::heldout_outliers(*m, hold, r.estimate, r);
    ASSERT_EQ(bad.size(), 1u) << "sigmas " << sigmas;
    EXPECT_EQ(bad[0].line, 56);
    EXPECT_GT(bad[0].normalised_rms, 10.0);
    EXPECT_LT(bad[0].p_any, 1e-3);
  }
}

// The CLI names the held-out pose (every 5th of the recording is held out: the 5th pose) in its warning and in --json,
// and still writes the corrected file, which that pose did not pull.
TEST(CalibCli, AHeldOutOutlierIsNamedAtItsLine) {
  const auto m = load("trunnion-ac");
  std::vector<double> truth = m->nominal();
  truth[m->index("EX0C")] = 0.02;
  calib::Sigmas s;
  s.ptip_mm = 0.0005;
  const std::string machine = source_path("machines/trunnion-ac.yaml");
  const std::string rec = tmp("heldout-outlier.csv"), out = tmp("heldout-outlier.yaml");
  Dataset d = calib::simulate(*m, truth, m->random_poses(40, 3), {"ptip"}, s, 7);
  d.poses[4].meas[6] += 0.05;
  write(rec, calib::format_recording(calib::to_recording(*m, d, machine)));
  const auto r = test::run_command(
      fmt::format("{} calibrate {} --machine {} -o {} --free rotary_a,rotary_c --json", CSCAM_CLI, rec, machine, out));
  ASSERT_EQ(r.status, 0) << r.output;
  const auto j = nlohmann::json::parse(r.output.substr(r.output.find('{')));
  const auto& hout = j.at("heldout").at("outliers");
  ASSERT_EQ(hout.size(), 1u) << r.output;
  std::ifstream in(rec);
  std::string line;
  int header = 0;
  for (int n = 1; header == 0 && std::getline(in, line); ++n)
    if (!line.empty() && line[0] != '#') header = n;
  EXPECT_EQ(hout[0].at("line").get<int>(), header + 5);  // the 5th pose's row
  EXPECT_NE(r.output.find("warning: held-out poses"), std::string::npos) << r.output;
  EXPECT_TRUE(std::filesystem::exists(out));
}

// Free parameters that none of the measured channels sees: an error naming them (an empty identifiable set crashed
// the analysis).
TEST(CalibIdent, FreeParametersTheDataCannotSeeAreAnError) {
  const auto m = load("trunnion-ac");
  calib::Sigmas s;
  Dataset d = calib::simulate(*m, m->nominal(), m->random_poses(30, 3), {"tip"}, s, 7);
  calib::Options o;
  o.free = m->select({"rotary_c"});
  try {
    (void)calib::calibrate(*m, d, o);
    FAIL() << "expected an error";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("none of the free parameters (EX0C"), std::string::npos) << e.what();
  }
}

// A corrected file is written only if it predicts held-out poses no worse than the nominal one, and the report says
// when poses cover too little of the working volume for the file to hold away from them.
TEST(CalibCli, NoCorrectedFileThatPredictsWorseAndAWarningWhenPosesAreBunched) {
  namespace fs = std::filesystem;
  const fs::path dir = fs::temp_directory_path() / ("cscam_calib_guard_" + std::to_string(::getpid()));
  fs::create_directories(dir);
  const auto m = load("trunnion-ac");
  std::vector<double> truth = m->nominal();
  truth[m->index("EX0C")] = 0.05;
  truth[m->index("EB0A")] = 0.02;
  calib::Sigmas s;
  s.ptip_mm = 0.001;
  auto write = [&](const Dataset& d, const std::string& name) {
    std::ofstream o(dir / name);
    o << "# machine: trunnion-ac\n# kind: static\n# tool_length: 0\n# sigma.ptip: 0.001\n"
         "cmd.x,cmd.y,cmd.z,cmd.a,cmd.c,ptip.x,ptip.y,ptip.z\n";
    for (const auto& p : d.poses)
      o << fmt::format("{},{},{},{},{},{:.6f},{:.6f},{:.6f}\n", p.q[0], p.q[1], p.q[2], p.q[3], p.q[4], p.meas[6],
                       p.meas[7], p.meas[8]);
  };
  // Outliers ruin the fit: the held-out poses get worse, and nothing is written.
  Dataset bad = calib::simulate(*m, truth, m->random_poses(40, 3), {"ptip"}, s, 7);
  for (const std::size_t k : {3u, 8u, 16u, 23u}) bad.poses[k].meas[6] += 0.6;
  write(bad, "bad.csv");
  const std::string cli = std::string(CSCAM_CLI) + " calibrate ";
  const std::string out_bad = (dir / "bad.yaml").string();
  const auto r1 = test::run_command(cli + (dir / "bad.csv").string() + " --machine trunnion-ac -o " + out_bad);
  EXPECT_EQ(r1.status, 2) << r1.output;
  EXPECT_NE(r1.output.find("predicts the held-out poses worse than the nominal one"), std::string::npos) << r1.output;
  EXPECT_FALSE(fs::exists(out_bad));
  // Poses bunched within a few degrees of A and C: a good fit there, a warning for the rest of the volume.
  std::vector<std::vector<double>> bunched = m->random_poses(40, 5);
  for (std::size_t k = 0; k < bunched.size(); ++k) {
    bunched[k][3] = -1.0 + 0.05 * static_cast<double>(k);
    bunched[k][4] = 0.07 * static_cast<double>(k);
  }
  write(calib::simulate(*m, truth, bunched, {"ptip"}, s, 9), "bunched.csv");
  const auto r2 = test::run_command(cli + (dir / "bunched.csv").string() + " --machine trunnion-ac");
  EXPECT_NE(r2.output.find("the poses cover too little of the volume"), std::string::npos) << r2.output;
  // Spread poses: no such warning.
  write(calib::simulate(*m, truth, m->random_poses(40, 5), {"ptip"}, s, 9), "spread.csv");
  const auto r3 = test::run_command(cli + (dir / "spread.csv").string() + " --machine trunnion-ac");
  EXPECT_EQ(r3.status, 0) << r3.output;
  EXPECT_EQ(r3.output.find("cover too little"), std::string::npos) << r3.output;
  fs::remove_all(dir);
}

// Poses bunched in a small part of the XMINI's volume: the corrected file moved the tip no further in the volume than
// at the poses, so the old comparison said nothing, but it was 0.09 mm off elsewhere. The parameters' covariance
// carried to the tip says so. Spread poses: no warning.
TEST(CalibCli, XminiPosesBunchedInASlabAreFlaggedByTheUncertaintyTheyLeave) {
  const auto m = load("xmini");
  const std::vector<double> truth = xmini_truth(*m);
  const std::string machine = source_path("machines/xmini.yaml");
  std::vector<std::vector<double>> bunched = m->random_poses(60, 31);
  for (std::size_t k = 1; k < bunched.size(); ++k)
    for (std::size_t j = 0; j < bunched[k].size(); ++j)
      bunched[k][j] = bunched[0][j] + 0.08 * (bunched[k][j] - bunched[0][j]);
  auto run = [&](const std::vector<std::vector<double>>& poses, const std::string& name) {
    calib::Sigmas s;
    s.tip_mm = 0.002;
    const std::string rec = tmp(name + ".csv");
    write(rec,
          calib::format_recording(calib::to_recording(*m, calib::simulate(*m, truth, poses, {"tip"}, s, 5), machine)));
    return test::run_command(fmt::format("{} calibrate {} --max-iterations 2000", CSCAM_CLI, rec));
  };
  const auto slab = run(bunched, "xmini-slab");
  EXPECT_EQ(slab.status, 0) << slab.output;
  EXPECT_NE(slab.output.find("uncertain by up to"), std::string::npos) << slab.output;
  const auto spread = run(m->random_poses(60, 31), "xmini-spread");
  EXPECT_EQ(spread.status, 0) << spread.output;
  EXPECT_EQ(spread.output.find("uncertain by up to"), std::string::npos) << spread.output;
}

// Without sigmas in the recording, outliers are judged against the median pose's residual. With one link length per
// pose that median is 0.67 of the noise, and three of it flagged 4 % of clean poses; the median is now scaled by what
// it is for the channels a pose has. The oracle: Gaussian noise, so about 0.3 % beyond three sigmas.
TEST(CalibIdent, OutlierLimitWithoutSigmasFollowsTheChannelsPerPose) {
  const auto m = load("pcmm");
  calib::Sigmas s;
  s.len_mm = 0.0005;
  Dataset d = calib::simulate(*m, m->nominal(), m->random_poses(240, 11), {"len"}, s, 3);
  d.sigma = calib::Sigmas{};  // as read from a recording that gives none
  calib::Options o;
  o.free = m->select({"passive"});
  const calib::Result r = calib::calibrate(*m, d, o);
  EXPECT_LE(r.outliers.size(), 3u);
}

TEST(CalibRecording, ThePcmmPassiveLinkIsNamedByTheMachineFile) {
  // pcmm.link names the passive link, and so the recording's len.<name> column; it was ignored (always len.link).
  std::ifstream in(source_path("machines/pcmm.yaml"));
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  const auto at = text.find("link: link");
  ASSERT_NE(at, std::string::npos);
  const std::string path = ::testing::TempDir() + "/pcmm-probe.yaml";
  { std::ofstream(path) << text.substr(0, at) + "link: probe" + text.substr(at + 10); }
  const auto m = calib::load_model(path);
  ASSERT_EQ(m->links().size(), 1u);
  EXPECT_EQ(m->links()[0], "probe");
  const std::string head = "# kind: static\ncmd.q1,cmd.q2,cmd.q3,";
  EXPECT_NO_THROW((void)calib::dataset_from(calib::parse_recording(head + "len.probe\n1,2,3,4\n", "r.csv"), *m));
  EXPECT_THROW((void)calib::dataset_from(calib::parse_recording(head + "len.link\n1,2,3,4\n", "r.csv"), *m),
               InputError);
  const std::string bad = ::testing::TempDir() + "/pcmm-badlink.yaml";
  { std::ofstream(bad) << text.substr(0, at) + "link: [a, b]" + text.substr(at + 10); }
  EXPECT_THROW((void)calib::load_model(bad), InputError);
}

// A chi^2 tail far out (thousands of degrees of freedom, or a gross outlier) underflows to 0: the report said "p = 0",
// which is false. A 40-sigma normal tail (erfc) is such a value.
TEST(CalibReport, APValueBelowWhatDoublesShowIsNotPrintedAsZero) {
  EXPECT_EQ(calib::p_value_text(0.0), "p < 1e-300");
  EXPECT_EQ(calib::p_value_text(1e-320), "p < 1e-300");  // subnormal: as good as lost
  EXPECT_EQ(calib::p_value_text(0.0312), "p = 0.0312");
  EXPECT_EQ(calib::p_value_text(0.0312, 2), "p = 0.031");
  EXPECT_EQ(calib::p_value_text(1.0), "p = 1");
  const double tail = 0.5 * std::erfc(40.0 / std::sqrt(2.0));  // a 40-sigma normal tail: about 3.7e-350, lost
  EXPECT_EQ(calib::p_value_text(tail), "p < 1e-300");
}

TEST(CalibRecording, ARecordingWithNothingMeasuredIsALocatedError) {
  // A header without pose rows, and pose rows whose measured cells are all empty: the SVD of the empty Jacobian
  // crashed (SIGSEGV). Both name the recording's header line.
  const auto m = load("xmini");
  const std::string head = "# kind: static\ncmd.q1,cmd.q2,cmd.q3,cmd.c,cmd.a,tip.x,tip.y,tip.z\n";
  for (const std::string& body : {std::string(), std::string("1,2,3,4,5,,,\n6,7,8,9,10,,,\n")}) {
    const auto r = calib::parse_recording(head + body, "r.csv");
    try {
      (void)calib::dataset_from(r, *m);
      FAIL() << body;
    } catch (const InputError& e) {
      EXPECT_EQ(e.where().line, 2);
      EXPECT_NE(std::string(e.what()).find("nothing to calibrate"), std::string::npos) << e.what();
    }
  }
}

// ---------------------------------------------------------------------------------------------------
// What may be written: a fit that agrees with the noise, and a change that the noise does not explain
// ---------------------------------------------------------------------------------------------------

namespace {

/// A trunnion-ac static recording (ptip, sigma.ptip given) of `truth` at 40 random poses; `outlier_row` >= 0 adds
/// kOutlierMm to that row's ptip.x. Returns the file line of that row (0 if none).
int write_trunnion_recording(const std::string& path, const Model& m, const std::vector<double>& truth,
                             unsigned noise_seed, int outlier_row) {
  calib::Sigmas s;
  s.ptip_mm = kGaugeSigmaMm;
  Dataset d = calib::simulate(m, truth, m.random_poses(40, 3), {"ptip"}, s, noise_seed);
  std::ofstream o(path);
  o << "# machine: trunnion-ac\n# kind: static\n# tool_length: 0\n# sigma.ptip: " << kGaugeSigmaMm
    << "\ncmd.x,cmd.y,cmd.z,cmd.a,cmd.c,ptip.x,ptip.y,ptip.z\n";
  const int first_row_line = 6;
  for (std::size_t k = 0; k < d.poses.size(); ++k) {
    const auto& p = d.poses[k];
    const double dx = static_cast<int>(k) == outlier_row ? kOutlierMm : 0.0;
    o << fmt::format("{},{},{},{},{},{:.7f},{:.7f},{:.7f}\n", p.q[0], p.q[1], p.q[2], p.q[3], p.q[4], p.meas[6] + dx,
                     p.meas[7], p.meas[8]);
  }
  return outlier_row >= 0 ? first_row_line + outlier_row : 0;
}

}  // namespace

TEST(CalibFit, Chi2TailMatchesClosedForms) {
  for (const double x : {0.01, 0.5, 1.0, 3.84, 10.0, 40.0}) {
    EXPECT_NEAR(calib::chi2_upper_tail(x, 2.0), std::exp(-x / 2), kChi2TailRel * std::max(1.0, std::exp(-x / 2)));
    EXPECT_NEAR(calib::chi2_upper_tail(x, 1.0), std::erfc(std::sqrt(x / 2)), kChi2TailRel);
  }
  // dof 4: (1 + x/2) exp(-x/2).
  EXPECT_NEAR(calib::chi2_upper_tail(7.0, 4.0), (1 + 3.5) * std::exp(-3.5), kChi2TailRel);
}

// An outlier row without a robust loss gave chi^2 ~ 3600 for 86 degrees of freedom, and the corrected file was still
// written. Now: exit 2, the row named by line, --loss suggested, no file; --write-anyway or --loss huber write it.
TEST(CalibCli, AFitThatDisagreesWithTheNoiseWritesNoFile) {
  const auto m = load("trunnion-ac");
  std::vector<double> truth = m->nominal();
  truth[m->index("EX0C")] = kInjectedEX0CMm;
  truth[m->index("EZ0A")] = kInjectedEZ0AMm;
  const std::string rec = tmp("outlier.csv"), out = tmp("outlier.yaml");
  // Row 7 is fitted (every 5th row, from the 5th, is held out).
  const int line = write_trunnion_recording(rec, *m, truth, 7, 7);
  const std::string cmd = fmt::format("{} calibrate {} --free rotary_a,rotary_c -o {}", CSCAM_CLI, rec, out);
  std::filesystem::remove(out);
  auto r = test::run_command(cmd);
  EXPECT_EQ(r.status, 2) << r.output;
  EXPECT_NE(r.output.find("does not agree with the measurement noise"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find(fmt::format("{}:{} (", rec, line)), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("--loss"), std::string::npos) << r.output;
  EXPECT_FALSE(std::filesystem::exists(out));
  r = test::run_command(cmd + " --write-anyway");
  EXPECT_EQ(r.status, 0) << r.output;
  EXPECT_TRUE(std::filesystem::exists(out));
  std::filesystem::remove(out);
  r = test::run_command(cmd + " --loss huber");
  EXPECT_EQ(r.status, 0) << r.output;
  EXPECT_TRUE(std::filesystem::exists(out)) << r.output;
  // The clean recording: consistent, and written.
  write_trunnion_recording(rec, *m, truth, 7, -1);
  std::filesystem::remove(out);
  r = test::run_command(cmd);
  EXPECT_EQ(r.status, 0) << r.output;
  EXPECT_TRUE(std::filesystem::exists(out)) << r.output;
}

// A perfect machine measured with noise: the "correction" is noise, and no file is written.
TEST(CalibCli, ANoiseOnlyRecordingWritesNoFile) {
  const auto m = load("trunnion-ac");
  const std::string rec = tmp("noise-only.csv"), out = tmp("noise-only.yaml");
  write_trunnion_recording(rec, *m, m->nominal(), 3, -1);
  std::filesystem::remove(out);
  const auto r = test::run_command(fmt::format("{} calibrate {} --free rotary_a,rotary_c -o {}", CSCAM_CLI, rec, out));
  EXPECT_EQ(r.status, 0) << r.output;
  EXPECT_NE(r.output.find("no significant correction"), std::string::npos) << r.output;
  EXPECT_FALSE(std::filesystem::exists(out));
}

// The significance test at its stated level: over seeded noise-only recordings few changes count as significant,
// and an injected error always does.
TEST(CalibFit, NoiseOnlyChangesAreRarelySignificantInjectedOnesAlways) {
  const auto m = load("trunnion-ac");
  calib::Sigmas s;
  s.ptip_mm = kGaugeSigmaMm;
  calib::Options o;
  o.free = m->select({"rotary_a", "rotary_c"});
  std::vector<double> truth = m->nominal();
  truth[m->index("EX0C")] = kInjectedEX0CMm;
  truth[m->index("EZ0A")] = kInjectedEZ0AMm;
  int rewrites = 0;
  for (int k = 0; k < kNoiseOnlyTrials; ++k) {
    const auto poses = m->random_poses(40, 100 + static_cast<unsigned>(k));
    const Dataset noise = calib::simulate(*m, m->nominal(), poses, {"ptip"}, s, 500 + static_cast<unsigned>(k));
    const calib::Result r = calib::calibrate(*m, noise, o);
    const calib::WriteCheck w = calib::check_for_writing(*m, noise, r, o.loss);
    EXPECT_TRUE(w.consistent) << k << ": " << w.inconsistency;
    rewrites += w.significant ? 1 : 0;
    const Dataset real = calib::simulate(*m, truth, poses, {"ptip"}, s, 500 + static_cast<unsigned>(k));
    const calib::Result r2 = calib::calibrate(*m, real, o);
    EXPECT_TRUE(calib::check_for_writing(*m, real, r2, o.loss).significant) << k;
  }
  EXPECT_LE(rewrites, kNoiseOnlyMaxRewrites);
}

// ---------------------------------------------------------------------------------------------------
// Loader and recording errors are located
// ---------------------------------------------------------------------------------------------------

namespace {
int line_of(const std::string& text, const std::string& what) {
  const auto at = text.find(what);
  return at == std::string::npos ? -1 : static_cast<int>(std::count(text.begin(), text.begin() + at, '\n')) + 1;
}
using test::error_of;
}  // namespace

// pcmm.yaml without rb3 loaded with rb3 = 250 and said nothing. Every parameter and tip_mm are required.
TEST(CalibModel, PcmmMissingParameterIsAnErrorAtItsSection) {
  std::ifstream in(source_path("machines/pcmm.yaml"));
  std::stringstream ss;
  ss << in.rdbuf();
  const std::string text = ss.str();
  auto without = [&](const std::string& line_start) {
    std::string t = text;
    const auto a = t.find(line_start);
    t.erase(a, t.find('\n', a) - a + 1);
    return t;
  };
  const std::string path = ::testing::TempDir() + "/pcmm-missing.yaml";
  for (const std::string key : {"rb3", "bz", "gs3"}) {
    const std::string t = without("    " + key + ":");
    write(path, t);
    const std::string e = error_of([&] { (void)calib::load_model(path); });
    EXPECT_NE(e.find(fmt::format("{}:{}", path, line_of(t, "  parameters:"))), std::string::npos) << e;
    EXPECT_NE(e.find("missing required parameter(s) " + key), std::string::npos) << e;
  }
  const std::string t = without("  tip_mm:");
  write(path, t);
  const std::string e = error_of([&] { (void)calib::load_model(path); });
  EXPECT_NE(e.find(fmt::format("{}:{}", path, line_of(t, "pcmm:\n"))), std::string::npos) << e;
  EXPECT_NE(e.find("tip_mm"), std::string::npos) << e;
}

// Metadata errors had no line ("0.5um" was even read as 0.5 mm): each is at its file:line:column.
TEST(CalibRecording, MetadataErrorsNameLineAndColumn) {
  const auto m = load("trunnion-ac");
  const std::string body = "cmd.x,cmd.y,cmd.z,cmd.a,cmd.c,ptip.x,ptip.y,ptip.z\n1,2,3,4,5,6,7,8\n";
  struct Case {
    std::string meta, where, says;
  };
  const std::vector<Case> cases = {
      {"# kind: static\n# sigma.ptip: 0.5um\n", "0.5um", "plain number"},
      {"# kind: static\n# tool_length: 20 mm\n", "20 mm", "plain number"},
      {"# note: x\n# kind: statik\n", "statik", "expected trajectory or static"},
      {"# kind: static\n# sigma.ptip: -1\n", "-1", "must be positive"},
      {"# kind: static\n# sigma.tpi: 0.001\n", "0.001", "unknown sigma"},
      {"# kind: static\n# sigma.ptip 0.001\n", " 0.001", "a colon after the key"},
      {"# kind: static\n# kind: static\n", "kind", "given twice"},
  };
  for (const auto& c : cases) {
    const std::string text = c.meta + body;
    // Oracle: the line and 1-based column of the offending text (on the last metadata line).
    const std::size_t last = text.rfind("\n# ", text.find("\ncmd.")) + 1;
    const std::size_t pos = text.find(c.where, last);
    ASSERT_NE(pos, std::string::npos) << c.meta;
    const int line = static_cast<int>(std::count(text.begin(), text.begin() + static_cast<long>(pos), '\n')) + 1;
    const int col = static_cast<int>(pos - last) + 1;
    const std::string e = error_of([&] { (void)calib::dataset_from(calib::parse_recording(text, "rec.csv"), *m); });
    EXPECT_NE(e.find(fmt::format("rec.csv:{}:{}", line, col)), std::string::npos) << c.meta << " -> " << e;
    EXPECT_NE(e.find(c.says), std::string::npos) << c.meta << " -> " << e;
  }
}

// `simulate --noise dir:S` added the noise per component and left the tool axis non-unit (|dir| 0.993 - 1.028).
TEST(CalibCli, SimulatedDirectionNoiseKeepsAUnitVector) {
  const std::string poses = tmp("dir-poses.csv"), rec = tmp("dir-rec.csv");
  auto r = test::run_command(
      fmt::format("{} calibrate --design 20 --machine xmini --channels tip --seed 2 -o {}", CSCAM_CLI, poses));
  ASSERT_EQ(r.status, 0) << r.output;
  r =
      test::run_command(fmt::format("{} simulate {} --machine xmini --channels tip,dir --noise dir:0.01 --decimals 12 "
                                    "-o {}",
                                    CSCAM_CLI, poses, rec));
  ASSERT_EQ(r.status, 0) << r.output;
  const calib::Recording rr = calib::read_recording(rec);
  const int x = rr.column("dir.x");
  ASSERT_GE(x, 0);
  double spread = 0;
  for (Eigen::Index i = 0; i < rr.rows(); ++i) {
    const Eigen::Vector3d d(rr.data(i, x), rr.data(i, x + 1), rr.data(i, x + 2));
    EXPECT_NEAR(d.norm(), 1.0, kUnitDirTol) << i;
    spread = std::max(spread, std::abs(d.z()));
  }
  EXPECT_GT(spread, 0.0);
}

// docs/calibration.md: with link and tip data the stage frame's rotation about the probe axis is the one null
// direction, and ths1 (the stage frame's x axis) is held at nominal. The analysis fixed ths3.
TEST(CalibIdent, PcmmStageFrameConventionHoldsThs1) {
  const auto m = load("pcmm");
  calib::Sigmas s;
  std::vector<double> truth = perturbed(*m, all(*m), 0.5, 41);
  const Dataset both = calib::simulate(*m, truth, m->random_poses(45, 11), {"len", "tip"}, s, 1);
  calib::Options o;
  o.max_iterations = 1000;
  const calib::Result r = calib::calibrate(*m, both, o);
  ASSERT_EQ(r.ident.fixed.size(), 1u);
  EXPECT_EQ(m->params()[r.ident.fixed[0]].name, "ths1");
  EXPECT_EQ(r.estimate[m->index("ths1")], m->nominal()[m->index("ths1")]);
  EXPECT_TRUE(std::isfinite(r.stddev[m->index("ths3")]));
  ASSERT_EQ(r.ident.messages.size(), 1u);
  EXPECT_EQ(r.ident.messages[0].rfind("ths1 cannot be separated from", 0), 0u) << r.ident.messages[0];
}

// The link-only parallel CMM: every printed trade-off ("+1 mm of rb3 looks the same as ...") and null-space vector
// must be a direction the data do not see. Terms below 5 % (10 %) of the largest were dropped, so relations for
// rb3, zb3, gs3 and vectors without sx, sy were not null directions at all.
TEST(CalibIdent, PcmmLinkOnlyTradeOffsAreNullDirections) {
  const auto m = load("pcmm");
  calib::Sigmas s;
  const Dataset d = calib::simulate(*m, m->nominal(), m->random_poses(45, 11), {"len"}, s, 1);
  const calib::Identifiability id = calib::analyse(*m, d, m->nominal(), calib::Options{});
  ASSERT_EQ(id.messages.size(), 7u);
  // Oracle: central differences of the predicted link length, parameter by parameter.
  const std::vector<double> p0 = m->nominal();
  Eigen::MatrixXd J(static_cast<Eigen::Index>(d.poses.size()), static_cast<Eigen::Index>(m->size()));
  auto sc = m->make_scratch();
  std::vector<double> up(10), dn(10);
  for (std::size_t j = 0; j < m->size(); ++j) {
    std::vector<double> pp = p0, pm = p0;
    const double h = 1e-5;
    pp[j] += h;
    pm[j] -= h;
    for (std::size_t k = 0; k < d.poses.size(); ++k) {
      m->predict_channels(d.poses[k].q.data(), pp.data(), up.data(), sc.get());
      m->predict_channels(d.poses[k].q.data(), pm.data(), dn.data(), sc.get());
      J(static_cast<Eigen::Index>(k), static_cast<Eigen::Index>(j)) = (up[9] - dn[9]) / (2 * h);
    }
  }
  auto relative = [&](const std::map<std::string, double>& v) {
    Eigen::VectorXd x = Eigen::VectorXd::Zero(static_cast<Eigen::Index>(m->size()));
    double scale = 0;
    for (const auto& [n, c] : v) {
      x[static_cast<Eigen::Index>(m->index(n))] = c;
      scale += std::abs(c) * J.col(static_cast<Eigen::Index>(m->index(n))).norm();
    }
    return (J * x).norm() / scale;
  };
  for (const std::string& msg : id.messages) {
    // "<p> cannot be separated from ...: +1 <unit> of <p> looks the same as +a n1 -b n2 ...; fixed at nominal"
    const std::string fixed = msg.substr(0, msg.find(' '));
    const auto a = msg.find("looks the same as ");
    ASSERT_NE(a, std::string::npos) << msg;
    std::stringstream ts(msg.substr(a + 18, msg.find(';', a) - a - 18));
    std::map<std::string, double> v{{fixed, 1.0}};
    double c = 0;
    std::string n;
    while (ts >> c >> n) v[n] -= c;
    EXPECT_LT(relative(v), kNullRelationRel) << msg;
  }
  for (const std::string& comb : id.combinations) {
    // "[+1 deg ths3, -0.761 mm zb2, ...] move together: ..."
    std::string body = comb.substr(1, comb.find(']') - 1);
    std::replace(body.begin(), body.end(), ',', ' ');
    std::stringstream ts(body);
    std::map<std::string, double> v;
    double c = 0;
    std::string unit, n;
    while (ts >> c >> unit >> n) v[n] += c;
    EXPECT_LT(relative(v), kNullRelationRel) << comb;
  }
}
