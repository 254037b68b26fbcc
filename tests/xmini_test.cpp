// XMINI kinematics: the reference vectors of tests/data/xmini-vectors.csv (nominal and perturbed),
// home, IK -> FK round trips over the working volume, the analytic Jacobian against finite differences,
// parameter derivatives through ceres::Jet, limits, the singular wrist and parasitic motion.
#include "cscam/kin/xmini.hpp"

#include <ceres/jet.h>
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <map>
#include <sstream>
#include <string>
#include <vector>

#include "cscam/core/error.hpp"
#include "cscam/core/units.hpp"
#include "test_support.hpp"

using namespace cscam;
using namespace cscam::kin;
using Vec3 = Eigen::Vector3d;

namespace {

// Tolerances. The vectors are printed with 9 decimals; the round trip ones are the project's.
constexpr double kVectorMm = 1e-6;
constexpr double kVectorDeg = 1e-7;
constexpr double kHomeMm = 1e-5;  // home q is printed with 6 decimals
constexpr double kHomeRad = 1e-7;
constexpr double kJacobianRel = 1e-6;
constexpr double kJetRel = 1e-6;
constexpr int kRandomPoses = 1000;

// The working volume: a cylinder of diameter 300, z -100..100, tool tilt up to 30 deg.
constexpr double kVolumeRadiusMm = 150.0;
constexpr double kVolumeZMinMm = -100.0, kVolumeZMaxMm = 100.0;
constexpr double kMaxTiltDeg = 30.0;

double angle_between(const Vec3& a, const Vec3& b) { return std::atan2(a.cross(b).norm(), a.dot(b)); }

// ------------------------------------------------------------------------------------------------
// The reference vectors
// ------------------------------------------------------------------------------------------------
struct VectorRow {
  int id = 0;
  std::string param_set;
  double tool_length = 0;
  Vec3 tip = Vec3::Zero(), u = Vec3::Zero();
  int branch = 0;
  double q1 = 0, q2 = 0, q3 = 0, c_deg = 0, a_deg = 0, alpha_deg = 0, beta_deg = 0;
};

struct VectorFile {
  std::map<std::string, double> perturbation;  ///< name -> value in file units
  std::vector<VectorRow> rows;
};

std::vector<std::string> split(const std::string& s, char sep) {
  std::vector<std::string> out;
  std::stringstream ss(s);
  std::string item;
  while (std::getline(ss, item, sep)) out.push_back(item);
  return out;
}

std::string trim(const std::string& s) {
  const auto b = s.find_first_not_of(" \t\r#");
  const auto e = s.find_last_not_of(" \t\r");
  return b == std::string::npos ? std::string() : s.substr(b, e - b + 1);
}

VectorFile read_vectors() {
  const std::string path = test::source_path("tests/data/xmini-vectors.csv");
  std::ifstream in(path);
  if (!in) throw std::runtime_error("cannot open " + path);
  VectorFile vf;
  std::vector<std::string> header;
  std::string line;
  int line_no = 0;
  while (std::getline(in, line)) {
    ++line_no;
    if (line.empty()) continue;
    if (line[0] == '#') {
      // Comment line 3: "# theta0=0.02;eps_y=-0.015;..." (file units, degrees for angles).
      if (line_no == 3)
        for (const std::string& kv : split(trim(line), ';')) {
          const auto eq = kv.find('=');
          if (eq == std::string::npos) throw std::runtime_error("bad perturbation entry '" + kv + "'");
          vf.perturbation[trim(kv.substr(0, eq))] = std::stod(kv.substr(eq + 1));
        }
      continue;
    }
    const std::vector<std::string> f = split(trim(line), ',');
    if (header.empty()) {
      header = f;
      continue;
    }
    std::map<std::string, std::string> m;
    for (std::size_t i = 0; i < header.size() && i < f.size(); ++i) m[header[i]] = f[i];
    auto d = [&](const char* k) { return std::stod(m.at(k)); };
    VectorRow r;
    r.id = std::stoi(m.at("case"));
    r.param_set = m.at("param_set");
    r.tool_length = d("tool_length");
    r.tip = Vec3(d("tip_x"), d("tip_y"), d("tip_z"));
    r.u = Vec3(d("u_x"), d("u_y"), d("u_z"));
    r.branch = std::stoi(m.at("branch"));
    r.q1 = d("q1");
    r.q2 = d("q2");
    r.q3 = d("q3");
    r.c_deg = d("c_deg");
    r.a_deg = d("a_deg");
    r.alpha_deg = d("alpha_deg");
    r.beta_deg = d("beta_deg");
    vf.rows.push_back(r);
  }
  return vf;
}

const VectorFile& vectors() {
  static const VectorFile vf = read_vectors();
  return vf;
}

XminiParams<double> perturbed_params() {
  XminiParams<double> p = XminiParams<double>::nominal();
  for (const auto& [name, value] : vectors().perturbation) p.set(name, value);
  return p;
}

XminiParams<double> params_for(const std::string& set) {
  if (set == "nominal") return XminiParams<double>::nominal();
  if (set == "perturbed") return perturbed_params();
  throw std::runtime_error("unknown param_set " + set);
}

/// Difference of two angles in degrees, modulo 360 when `modulo`.
double angle_diff_deg(double a, double b, bool modulo) {
  const double d = a - b;
  return modulo ? std::abs(std::remainder(d, 360.0)) : std::abs(d);
}

bool matches_row(const XminiIkSolution& s, const VectorRow& r, bool c_modulo) {
  return std::abs(s.q1_mm - r.q1) <= kVectorMm && std::abs(s.q2_mm - r.q2) <= kVectorMm &&
         std::abs(s.q3_mm - r.q3) <= kVectorMm && angle_diff_deg(rad2deg(s.a_rad), r.a_deg, false) <= kVectorDeg &&
         angle_diff_deg(rad2deg(s.alpha_rad), r.alpha_deg, false) <= kVectorDeg &&
         angle_diff_deg(rad2deg(s.beta_rad), r.beta_deg, false) <= kVectorDeg &&
         angle_diff_deg(rad2deg(s.c_rad), r.c_deg, c_modulo) <= kVectorDeg;
}

std::string describe(const XminiIkSolution& s) {
  std::ostringstream o;
  o.precision(10);
  o << "branch " << s.branch << " winding " << s.winding << ": q=(" << s.q1_mm << ", " << s.q2_mm << ", " << s.q3_mm
    << ") c=" << rad2deg(s.c_rad) << " a=" << rad2deg(s.a_rad) << " alpha=" << rad2deg(s.alpha_rad)
    << " beta=" << rad2deg(s.beta_rad) << " exact=" << s.exact << " res=" << s.residual_mm;
  return o.str();
}

// ------------------------------------------------------------------------------------------------
// Random poses over the working volume
// ------------------------------------------------------------------------------------------------
struct RandomPose {
  Vec3 tip, u;
};

std::vector<RandomPose> random_poses(int n, unsigned salt) {
  auto rng = test::rng(salt);
  std::uniform_real_distribution<double> U(0.0, 1.0);
  std::vector<RandomPose> out;
  const double cos_max = std::cos(deg2rad(kMaxTiltDeg));
  for (int i = 0; i < n; ++i) {
    const double r = kVolumeRadiusMm * std::sqrt(U(rng)), th = 2 * kPi * U(rng);
    const double z = kVolumeZMinMm + (kVolumeZMaxMm - kVolumeZMinMm) * U(rng);
    const double ct = 1.0 - (1.0 - cos_max) * U(rng), st = std::sqrt(1 - ct * ct), ph = 2 * kPi * U(rng);
    out.push_back({Vec3(r * std::cos(th), r * std::sin(th), z), Vec3(st * std::cos(ph), st * std::sin(ph), ct)});
  }
  return out;
}

}  // namespace

// ================================================================================================
// Parameters
// ================================================================================================

TEST(XminiParams, TableOrderNamesAndUnits) {
  const auto& info = XminiParams<double>::info();
  ASSERT_EQ(info.size(), 38u);
  EXPECT_EQ(info.front().name, "pWB_x");
  EXPECT_EQ(info[3].name, "theta0");
  EXPECT_EQ(info[25].name, "sCx");
  EXPECT_EQ(info.back().name, "gz");
  // set(name) must write the member at the same index as the name (catches a mis-ordered table).
  for (std::size_t i = 0; i < info.size(); ++i) {
    XminiParams<double> p = XminiParams<double>::nominal();
    p.set(info[i].name, 12.5);
    EXPECT_NEAR(p[i], info[i].angle() ? deg2rad(12.5) : 12.5, 1e-15) << info[i].name;
    EXPECT_NEAR(p.get(info[i].name), 12.5, 1e-12) << info[i].name;
  }
  const auto nom = XminiParams<double>::nominal();
  EXPECT_EQ(nom.pWB_z, 900.0);
  EXPECT_EQ(nom.A2y, 200.0);
  EXPECT_EQ(nom.gz, 100.0);
  EXPECT_EQ(info[xmini_param_index("phi")].unit, "deg");
  EXPECT_EQ(info[xmini_param_index("L02")].unit, "mm");
}

TEST(XminiParams, UnknownNameThrows) {
  XminiParams<double> p = XminiParams<double>::nominal();
  EXPECT_THROW(p.set("pWB_w", 1.0), InputError);
  EXPECT_THROW((void)p.get("nope"), InputError);
}

TEST(XminiParams, FlatVectorAndCastRoundTrip) {
  const XminiParams<double> p = perturbed_params();
  const auto a = p.to_array();
  const auto v = p.to_vector();
  const XminiParams<double> pa = XminiParams<double>::from_array(a);
  const XminiParams<double> pv = XminiParams<double>::from_vector(v);
  for (std::size_t i = 0; i < XminiParams<double>::kCount; ++i) {
    EXPECT_EQ(pa[i], p[i]);
    EXPECT_EQ(pv[i], p[i]);
  }
  using J = ceres::Jet<double, 2>;
  const XminiParams<double> back = p.cast<J>().cast<double>();
  for (std::size_t i = 0; i < XminiParams<double>::kCount; ++i) EXPECT_EQ(back[i], p[i]);
  EXPECT_NEAR(p.theta0, deg2rad(0.02), 1e-18);  // parsed from the CSV comment, in degrees
}

// ================================================================================================
// Reference vectors
// ================================================================================================

TEST(XminiVectors, FileParses) {
  EXPECT_EQ(vectors().perturbation.size(), 34u);
  EXPECT_EQ(vectors().rows.size(), 42u);
}

TEST(XminiVectors, EveryRowIsAnIkBranch) {
  int checked = 0;
  for (const VectorRow& r : vectors().rows) {
    const XminiModel model(params_for(r.param_set), XminiLimits{}, r.tool_length);
    const std::vector<XminiIkSolution> sols = model.inverse(r.tip, r.u);
    std::string all;
    for (const auto& s : sols) all += "\n  " + describe(s);
    SCOPED_TRACE("case " + std::to_string(r.id) + " (" + r.param_set + ")" + all);
    // The row's c must be one of the returned windings exactly (not only modulo 360).
    const XminiIkSolution* exact_match = nullptr;
    const XminiIkSolution* modulo_match = nullptr;
    for (const auto& s : sols) {
      if (matches_row(s, r, false)) exact_match = &s;
      if (matches_row(s, r, true)) modulo_match = &s;
    }
    ASSERT_NE(modulo_match, nullptr) << "no branch matches";
    ASSERT_NE(exact_match, nullptr) << "the row's c is not one of the returned windings";
    EXPECT_EQ(exact_match->branch, r.branch) << "branch sign convention";
    EXPECT_TRUE(exact_match->exact);
    EXPECT_TRUE(exact_match->feasible());
    ++checked;
  }
  EXPECT_EQ(checked, 42);
}

TEST(XminiVectors, NominalBranchesShareThePlatformPerturbedDoNot) {
  // The two wrist branches give the same tool pose from the same platform state when psi = gx = gy =
  // e = 0 (nominal); with the perturbed wrist, they need different platform states.
  for (const VectorRow& r : vectors().rows) {
    const XminiModel model(params_for(r.param_set), XminiLimits{}, r.tool_length);
    const auto sols = model.inverse(r.tip, r.u);
    const XminiIkSolution* p = nullptr;
    const XminiIkSolution* m = nullptr;
    for (const auto& s : sols) (s.branch > 0 ? p : m) = &s;
    ASSERT_TRUE(p && m);
    const double dq = std::abs(p->q2_mm - m->q2_mm);
    if (r.param_set == "nominal")
      EXPECT_LT(dq, 1e-9) << r.id;
    else
      EXPECT_GT(dq, 1e-3) << r.id;
  }
}

TEST(XminiVectors, ParasiticMotionVerticalToolNeedsA) {
  // Rows with a vertical tool away from the centre have a != 0; IK agrees, and so does a fresh pose.
  int vertical = 0;
  for (const VectorRow& r : vectors().rows) {
    if (r.u.z() < 1.0 - 1e-12) continue;
    ++vertical;
    EXPECT_GT(std::abs(r.a_deg), 1.0) << r.id;
  }
  EXPECT_GE(vertical, 4);
  const XminiModel model;
  for (const auto& s : model.inverse(Vec3(100, 50, 0), Vec3(0, 0, 1))) {
    EXPECT_GT(std::abs(rad2deg(s.a_rad)), 1.0) << describe(s);
    EXPECT_TRUE(s.exact);
  }
}

// ================================================================================================
// Home
// ================================================================================================

TEST(XminiHome, ForwardGivesOriginAndVerticalTool) {
  const XminiModel model;
  XminiWorkspace ws;
  const XminiJoints<double> q(154.669331, 158.276253, 154.669331, 0.0, 0.0);
  const auto fk = model.forward(q, ws);
  ASSERT_TRUE(fk.summary.converged);
  EXPECT_LE(fk.summary.residual_norm, kXminiFkResidualMm);
  EXPECT_LT(fk.pose.tip_in_W_mm.norm(), kHomeMm) << fk.pose.tip_in_W_mm.transpose();
  EXPECT_LT(angle_between(fk.pose.u_in_W, Vec3::UnitZ()), kHomeRad);
  EXPECT_NEAR(fk.state[3], 600.0, kHomeMm);
}

TEST(XminiHome, InverseGivesHomeStrokes) {
  const XminiModel model;
  const auto sols = model.inverse(Vec3::Zero(), Vec3::UnitZ());
  bool found = false;
  for (const auto& s : sols) {
    EXPECT_NEAR(s.q1_mm, 154.669331, kHomeMm);
    EXPECT_NEAR(s.q2_mm, 158.276253, kHomeMm);
    EXPECT_NEAR(s.q3_mm, 154.669331, kHomeMm);
    EXPECT_NEAR(s.a_rad, 0.0, kHomeRad);
    EXPECT_TRUE(s.singular);  // u along the C axis at home
    if (s.branch == 1 && s.winding == 0) {
      found = true;
      EXPECT_EQ(s.c_rad, 0.0);  // no hint: c = 0
    }
  }
  EXPECT_TRUE(found);
}

// ================================================================================================
// Round trips
// ================================================================================================

class XminiRoundTrip : public ::testing::TestWithParam<const char*> {};

TEST_P(XminiRoundTrip, ForwardOfEveryInverseBranchReturnsThePose) {
  const std::string set = GetParam();
  const XminiModel model(params_for(set));
  XminiWorkspace ws;
  std::vector<XminiIkSolution> sols;
  int branches = 0, feasible = 0;
  double worst_mm = 0, worst_rad = 0;
  for (const RandomPose& pose : random_poses(kRandomPoses, set == "nominal" ? 1 : 2)) {
    model.inverse(pose.tip, pose.u, sols);
    ASSERT_GE(sols.size(), 2u);
    for (const auto& s : sols) {
      ASSERT_TRUE(s.exact) << describe(s);
      EXPECT_GT(std::cos(s.beta_rad), 0.0);
      const auto fk = model.forward(s.joints(), ws);
      ASSERT_TRUE(fk.summary.converged) << describe(s);
      const double e_mm = (fk.pose.tip_in_W_mm - pose.tip).norm();
      const double e_rad = angle_between(fk.pose.u_in_W, pose.u);
      worst_mm = std::max(worst_mm, e_mm);
      worst_rad = std::max(worst_rad, e_rad);
      EXPECT_LE(e_mm, tol::kRoundTripMm) << describe(s);
      EXPECT_LE(e_rad, tol::kRoundTripRad) << describe(s);
      // FK lands on the IK's platform state (the physical assembly mode), not another one.
      EXPECT_NEAR(fk.state[0], s.alpha_rad, 1e-10);
      EXPECT_NEAR(fk.state[1], s.beta_rad, 1e-10);
      ++branches;
      feasible += s.feasible();
    }
  }
  RecordProperty("worst_mm", std::to_string(worst_mm));
  EXPECT_GE(branches, 2 * kRandomPoses);
  EXPECT_GT(feasible, kRandomPoses);  // most of the volume is reachable inside the limits
}

INSTANTIATE_TEST_SUITE_P(Params, XminiRoundTrip, ::testing::Values("nominal", "perturbed"));

TEST(XminiForward, ColdAndWarmStartAgreeAndConverge) {
  const XminiModel model(perturbed_params());
  XminiWorkspace warm;
  int max_warm_iterations = 0;
  for (const RandomPose& pose : random_poses(200, 3)) {
    const auto sols = model.inverse(pose.tip, pose.u);
    const XminiJoints<double> q = sols.front().joints();
    XminiWorkspace cold;
    const auto a = model.forward(q, cold);
    const auto b = model.forward(q, warm);
    ASSERT_TRUE(a.summary.converged && b.summary.converged);
    EXPECT_LE(a.summary.residual_norm, kXminiFkResidualMm);
    EXPECT_LE((a.state - b.state).norm(), 1e-9);
    max_warm_iterations = std::max(max_warm_iterations, b.summary.iterations);
    // Re-solving the same joints from the warm start needs no iteration.
    EXPECT_EQ(model.forward(q, warm).summary.iterations, 0);
  }
  EXPECT_LE(max_warm_iterations, 8);
}

// ================================================================================================
// Jacobians
// ================================================================================================

TEST(XminiJacobian, AnalyticMatchesCentralDifferences) {
  for (const char* set : {"nominal", "perturbed"}) {
    const XminiModel model(params_for(set), XminiLimits{}, 65.0);
    XminiWorkspace ws;
    for (const RandomPose& pose : random_poses(50, 4)) {
      for (const auto& s : model.inverse(pose.tip, pose.u)) {
        if (s.winding != 0) continue;
        const XminiJoints<double> q = s.joints();
        const Eigen::Matrix<double, 6, 5> J = model.jacobian(q, ws);
        for (int j = 0; j < 5; ++j) {
          const double h = j < 3 ? 1e-4 : 1e-6;  // mm, rad
          XminiJoints<double> qp = q, qm = q;
          qp[j] += h;
          qm[j] -= h;
          const auto fp = model.forward(qp, ws), fm = model.forward(qm, ws);
          Eigen::Matrix<double, 6, 1> fd;
          fd << (fp.pose.tip_in_W_mm - fm.pose.tip_in_W_mm) / (2 * h), (fp.pose.u_in_W - fm.pose.u_in_W) / (2 * h);
          const double scale = std::max(1.0, J.col(j).norm());
          EXPECT_LE((J.col(j) - fd).norm(), kJacobianRel * scale)
              << set << " column " << j << "\nanalytic " << J.col(j).transpose() << "\nfd       " << fd.transpose();
        }
      }
    }
  }
}

TEST(XminiJet, ParameterDerivativesMatchFiniteDifferences) {
  constexpr int N = static_cast<int>(kXminiParamCount);
  using J = ceres::Jet<double, N>;
  const double L = 70.0;
  const XminiParams<double> base = perturbed_params();
  XminiParams<J> pj = base.cast<J>();
  for (int i = 0; i < N; ++i) pj[static_cast<std::size_t>(i)].v[i] = 1.0;

  const XminiModel model(base, XminiLimits{}, L);
  XminiWorkspace ws;
  for (const RandomPose& pose : random_poses(5, 5)) {
    const XminiJoints<double> q = model.inverse(pose.tip, pose.u).front().joints();
    const XminiFkResult<J> fj = xmini_forward(pj, XminiJoints<J>(q.cast<J>()), L, ws);
    ASSERT_TRUE(fj.summary.converged);
    // Values are unchanged by the implicit-function step.
    const auto fd0 = xmini_forward(base, q, L, ws);
    EXPECT_LE((fd0.pose.tip_in_W_mm - xmini_detail::matrix_cast<double>(fj.pose.tip_in_W_mm)).norm(), 1e-11);
    EXPECT_LE((pose.tip - fd0.pose.tip_in_W_mm).norm(), tol::kRoundTripMm);
    for (int i = 0; i < N; ++i) {
      const auto& in = XminiParams<double>::info()[static_cast<std::size_t>(i)];
      const double h = in.angle() ? 1e-6 : 1e-4;  // rad, mm
      XminiParams<double> pp = base, pm = base;
      pp[static_cast<std::size_t>(i)] += h;
      pm[static_cast<std::size_t>(i)] -= h;
      const auto fp = xmini_forward(pp, q, L, ws), fm = xmini_forward(pm, q, L, ws);
      Eigen::Matrix<double, 6, 1> fd, jet;
      fd << (fp.pose.tip_in_W_mm - fm.pose.tip_in_W_mm) / (2 * h), (fp.pose.u_in_W - fm.pose.u_in_W) / (2 * h);
      for (int k = 0; k < 3; ++k) {
        jet[k] = fj.pose.tip_in_W_mm[k].v[i];
        jet[3 + k] = fj.pose.u_in_W[k].v[i];
      }
      EXPECT_LE((jet - fd).norm(), kJetRel * std::max(1.0, jet.norm()))
          << in.name << "\njet " << jet.transpose() << "\nfd  " << fd.transpose();
    }
  }
}

TEST(XminiJet, LegLengthsDifferentiateToo) {
  using J = ceres::Jet<double, 1>;
  XminiParams<J> p = XminiParams<double>::nominal().cast<J>();
  p.A2y.v[0] = 1.0;
  const XminiState<J> x(J(0.05), J(-0.03), J(4.0), J(610.0));
  const Eigen::Matrix<J, 4, 1> rho = leg_lengths(p, x);
  // rho2 = |E + R c2 - A2|: d rho2 / d A2y = -(leg_2 . e_y) / rho2.
  const XminiPlatform<double> P =
      platform_from_state(XminiParams<double>::nominal(), XminiState<double>(0.05, -0.03, 4.0, 610.0));
  EXPECT_NEAR(rho[1].v[0], -P.leg_B_mm[1].y() / P.rho_mm[1], 1e-14);
  EXPECT_EQ(rho[0].v[0], 0.0);
}

// ================================================================================================
// Limits, windings, singular wrist
// ================================================================================================

TEST(XminiLimits, StrokeViolationIsReportedWithTheLimit) {
  const XminiModel model;
  XminiWorkspace ws;
  const XminiJoints<double> q(340.0, 361.2, 345.0, deg2rad(30.0), deg2rad(15.0));
  const auto fk = model.forward(q, ws);
  ASSERT_TRUE(fk.summary.converged);
  const auto sols = model.inverse(fk.pose.tip_in_W_mm, fk.pose.u_in_W);
  bool found = false;
  for (const auto& s : sols) {
    EXPECT_FALSE(s.feasible());
    if (s.branch != 1 || s.winding != 0) continue;
    found = true;
    EXPECT_NEAR(s.q2_mm, 361.2, 1e-8);
    ASSERT_EQ(s.violations.size(), 1u);
    EXPECT_EQ(s.violations[0].joint, XminiJoint::Q2);
    EXPECT_EQ(s.violations[0].describe(), "q2 = 361.200 mm exceeds stroke limit 350 mm");
  }
  EXPECT_TRUE(found);
  EXPECT_TRUE(feasible_solutions(sols).empty());
}

TEST(XminiLimits, AAndPassiveJointViolations) {
  const XminiModel model;
  XminiWorkspace ws;
  const XminiJoints<double> q(200.0, 200.0, 200.0, deg2rad(10.0), deg2rad(-55.0));
  const auto fk = model.forward(q, ws);
  const auto sols = model.inverse(fk.pose.tip_in_W_mm, fk.pose.u_in_W);
  bool a_reported = false;
  for (const auto& s : sols)
    for (const auto& v : s.violations)
      if (v.joint == XminiJoint::A && !v.above) {
        a_reported = true;
        EXPECT_EQ(v.describe(), "a = -55.000 deg is below A-axis limit -50 deg");
      }
  EXPECT_TRUE(a_reported);

  const auto v = check_limits(XminiLimits{}, XminiJoints<double>(100, 100, 100, 0, 0),
                              XminiState<double>(deg2rad(27.0), deg2rad(-26.0), 0, 600));
  ASSERT_EQ(v.size(), 2u);
  EXPECT_EQ(v[0].describe(), "alpha = 27.000 deg exceeds passive-joint limit 25 deg");
  EXPECT_EQ(v[1].describe(), "beta = -26.000 deg is below passive-joint limit -25 deg");
  EXPECT_TRUE(check_limits(XminiLimits{}, XminiJoints<double>(0, 350, 0, deg2rad(270), deg2rad(-50)),
                           XminiState<double>(deg2rad(25), deg2rad(-25), 0, 600))
                  .empty());  // limits are inclusive
}

TEST(XminiLimits, EveryCWindingInsideTheLimitsIsReturned) {
  const VectorRow& r = vectors().rows.at(1);  // c = 122.3 deg: windings 122.3 and -237.7
  ASSERT_NEAR(r.c_deg, 122.333501850, 1e-9);
  const XminiModel model(XminiParams<double>::nominal(), XminiLimits{}, r.tool_length);
  const auto sols = model.inverse(r.tip, r.u);
  std::vector<double> plus_c;
  for (const auto& s : sols)
    if (s.branch == 1) plus_c.push_back(rad2deg(s.c_rad));
  ASSERT_EQ(plus_c.size(), 2u);
  EXPECT_NEAR(plus_c[0], r.c_deg - 360.0, 1e-9);
  EXPECT_NEAR(plus_c[1], r.c_deg, 1e-9);

  // A machine file narrows C to +-90 deg: the branch-(+1) solution has no winding inside; it is
  // returned once, flagged.
  XminiLimits narrow;
  narrow.c_min_rad = deg2rad(-90.0);
  narrow.c_max_rad = deg2rad(90.0);
  const XminiModel m2(XminiParams<double>::nominal(), narrow, r.tool_length);
  int flagged = 0;
  for (const auto& s : m2.inverse(r.tip, r.u)) {
    if (s.branch != 1) {
      EXPECT_TRUE(s.feasible()) << describe(s);  // c = -57.7 deg
      continue;
    }
    ++flagged;
    ASSERT_EQ(s.violations.size(), 1u);
    EXPECT_EQ(s.violations[0].joint, XminiJoint::C);
    EXPECT_EQ(s.violations[0].describe(), "c = 122.334 deg exceeds C-axis limit 90 deg");
  }
  EXPECT_EQ(flagged, 1);
}

TEST(XminiSingular, VerticalToolAtTheCentreKeepsTheHint) {
  const XminiModel model;
  XminiWorkspace ws;
  const double hint = deg2rad(37.0);
  const auto sols = model.inverse(Vec3(0, 0, -20), Vec3::UnitZ(), hint);
  ASSERT_FALSE(sols.empty());
  bool kept = false;
  for (const auto& s : sols) {
    EXPECT_TRUE(s.singular);
    EXPECT_TRUE(s.exact);
    EXPECT_NEAR(s.a_rad, 0.0, 1e-12);
    if (s.branch == 1 && std::abs(std::remainder(s.c_rad - hint, 2 * kPi)) < 1e-12) kept = true;
    const auto fk = model.forward(s.joints(), ws);
    EXPECT_LE((fk.pose.tip_in_W_mm - Vec3(0, 0, -20)).norm(), tol::kRoundTripMm);
    EXPECT_LE(angle_between(fk.pose.u_in_W, Vec3::UnitZ()), tol::kRoundTripRad);
  }
  EXPECT_TRUE(kept);
}

TEST(XminiSingular, NearSingularIsNotFlaggedAndRoundTrips) {
  const XminiModel model;
  XminiWorkspace ws;
  const Vec3 u = Vec3(1e-7, -2e-7, 1).normalized();
  for (const auto& s : model.inverse(Vec3(0, 0, -20), u)) {
    EXPECT_FALSE(s.singular);
    const auto fk = model.forward(s.joints(), ws);
    EXPECT_LE((fk.pose.tip_in_W_mm - Vec3(0, 0, -20)).norm(), tol::kRoundTripMm) << describe(s);
    EXPECT_LE(angle_between(fk.pose.u_in_W, u), tol::kRoundTripRad) << describe(s);
  }
}

TEST(XminiModelTest, RejectsBadInput) {
  EXPECT_THROW(XminiModel(XminiParams<double>::nominal(), XminiLimits{}, -1.0), InputError);
  XminiParams<double> p = XminiParams<double>::nominal();
  p.set("psi", 90.0);
  EXPECT_THROW(XminiModel{p}, InputError);
  const XminiModel model;
  EXPECT_THROW((void)model.inverse(Vec3::Zero(), Vec3::Zero()), InputError);
}
