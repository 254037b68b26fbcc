// Machine definition files: every bundled machine loads and round-trips IK -> FK; bad files give
// errors that name the file, the line and the key.
#include "cscam/machine/machine.hpp"

#include <gtest/gtest.h>

#include <bit>
#include <cstdint>
#include <filesystem>
#include <random>

#include "cscam/core/error.hpp"
#include "cscam/core/units.hpp"
#include "cscam/kin/serial.hpp"
#include "test_support.hpp"

using namespace cscam;
using Vec3 = Eigen::Vector3d;

namespace {

std::vector<std::string> bundled_machines() {
  std::vector<std::string> out;
  for (const auto& e : std::filesystem::directory_iterator(test::source_path("machines")))
    if (e.path().extension() == ".yaml" && e.path().stem() != "pcmm")  // the CMM: calib_test covers it
      out.push_back(e.path().string());
  std::sort(out.begin(), out.end());
  return out;
}

/// Expects load_text to fail with a message containing every fragment.
void expect_error(const std::string& yaml, std::initializer_list<std::string> fragments) {
  try {
    machine::load_text(yaml, "bad.yaml");
    FAIL() << "expected an InputError for:\n" << yaml;
  } catch (const InputError& e) {
    const std::string msg = e.what();
    for (const auto& f : fragments) EXPECT_NE(msg.find(f), std::string::npos) << "'" << f << "' not in: " << msg;
  }
}

const char* kGood = R"(name: t
axes:
  - {name: x, type: linear, side: head, direction: [1, 0, 0], limits: [-100, 100]}
  - {name: y, type: linear, side: head, direction: [0, 1, 0], limits: [-100, 100]}
  - {name: z, type: linear, side: head, direction: [0, 0, 1], limits: [-100, 100]}
  - {name: a, type: rotary, side: table, direction: [1, 0, 0], pivot_mm: [0, 0, 0], limits: [-90, 90]}
  - {name: c, type: rotary, side: table, direction: [0, 0, 1], pivot_mm: [0, 0, 0], limits: [-360, 360]}
chains: {table: [a, c], head: [x, y, z]}
)";

}  // namespace

TEST(Machine, TheCmmFileIsRefusedWithAReason) {
  try {
    machine::load(test::source_path("machines/pcmm.yaml"));
    FAIL() << "pcmm.yaml is not a machine tool";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("pcmm.yaml:"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("cscam calibrate"), std::string::npos) << e.what();
  }
}

TEST(Machine, BundledMachinesLoadAndRoundTrip) {
  const auto files = bundled_machines();
  ASSERT_GE(files.size(), 4u);
  auto rng = test::rng(11);
  std::uniform_real_distribution<double> U(0, 1);
  for (const auto& f : files) {
    SCOPED_TRACE(f);
    const machine::Machine m = machine::load(f);
    if (m.kind != machine::ModelKind::Serial) continue;
    const auto kin = m.kinematics();
    std::vector<kin::Solution> sols;
    int checked = 0;
    for (int i = 0; i < 500; ++i) {
      // Random axis values inside the limits -> FK pose -> every IK branch must reproduce it.
      kin::Axes q;
      for (int a = 0; a < 5; ++a) {
        const auto& ax = m.axes[static_cast<size_t>(a)];
        const double lo = std::max(ax.min, ax.rotary() ? -4 * kPi : -1e9),
                     hi = std::min(ax.max, ax.rotary() ? 4 * kPi : 1e9);
        q[a] = lo + (hi - lo) * U(rng);
      }
      const kin::Posed target = kin->forward(q);
      kin->inverse_all(target, &q, sols);
      ASSERT_FALSE(sols.empty());
      bool found_q = false;
      for (const auto& s : sols) {
        const kin::Posed p = kin->forward(s.axes);
        EXPECT_LT((p.tip_mm - target.tip_mm).norm(), tol::kRoundTripMm);
        EXPECT_LT((p.axis - target.axis).norm(), tol::kRoundTripRad);
        found_q |= (s.axes - q).norm() < 1e-7;
        ++checked;
      }
      EXPECT_TRUE(found_q) << "the original axis values must be among the IK solutions";
    }
    EXPECT_GT(checked, 500);
  }
}

TEST(Machine, GoodMinimalFileLoads) {
  const auto m = machine::load_text(kGood, "good.yaml");
  EXPECT_EQ(m.name, "t");
  EXPECT_EQ(m.post.letters[3], "A");
  EXPECT_NEAR(m.axes[3].max, deg2rad(90.0), 1e-12);
}

TEST(Machine, BadInputNamesLineAndKey) {
  expect_error(std::string(kGood) + "bogus: 1\n", {"bad.yaml:9:1", "'bogus'", "unknown key"});
  expect_error("axes: []\n", {"bad.yaml", "'name'", "required key is missing"});
  std::string s = kGood;
  s.replace(s.find("limits: [-90, 90]"), 17, "limits: [90, -90]");
  expect_error(s, {"bad.yaml:6", "axes[3].limits", "min < max"});
  s = kGood;
  s.replace(s.find("[1, 0, 0], pivot_mm"), 9, "[0, 0, 0]");
  expect_error(s, {"bad.yaml:6", "axes[3].direction", "zero vector"});
  s = kGood;
  s.replace(s.find("type: rotary, side: table, direction: [1"), 12, "type: spiral");
  expect_error(s, {"bad.yaml:6", "axes[3].type", "'spiral'"});
  s = kGood;
  s.replace(s.find("limits: [-100, 100]"), 19, "limits: [-100, abc]");
  expect_error(s, {"bad.yaml:3", "axes[0].limits", "'abc'"});
  s = kGood;
  s.replace(s.find("[0, 0, 1], pivot_mm: [0, 0, 0], limits: [-360"), 9, "[1, 0, 0]");
  expect_error(s, {"bad.yaml", "parallel"});
  expect_error("name: [unclosed\n", {"bad.yaml:", "YAML syntax error"});
  expect_error(std::string(kGood) + "post: {letters: {q: Q}}\n", {"bad.yaml:9", "post.letters.q", "no such axis"});
  expect_error(std::string(kGood) + "post: {start_branch: positive:x}\n", {"post.start_branch", "not a rotary"});
  // CYCLE800 quotes the swivel record: a quote (or anything not a name) would end the string early.
  expect_error(std::string(kGood) + "post: {swivel_record: 'T\"C'}\n", {"bad.yaml:9", "post.swivel_record", "T\"C"});
  expect_error(std::string(kGood) + "post: {swivel_record: ''}\n", {"post.swivel_record", "1-32 letters"});
  EXPECT_EQ(machine::load_text(std::string(kGood) + "post: {swivel_record: TABLE_1}\n", "ok.yaml").post.swivel_record,
            "TABLE_1");
  expect_error(std::string(kGood) + "kinematics: delta\n", {"unknown kinematics 'delta'"});
}

TEST(Machine, HostileFilesNameTheFileTheLineAndTheKey) {
  const std::string good = kGood;
  auto with = [&](const std::string& from, const std::string& to) {
    std::string s = good;
    const auto at = s.find(from);
    EXPECT_NE(at, std::string::npos) << from;
    return s.replace(at, from.size(), to);
  };
  // Duplicate axis letters: given, or by default (two axes whose names start alike).
  expect_error(good + "post: {letters: {a: C}}\n", {"bad.yaml:9:", "post.letters.c", "duplicate axis letter 'C'"});
  std::string a2 = with("{name: c, type: rotary", "{name: a2, type: rotary");
  a2.replace(a2.find("table: [a, c]"), 13, "table: [a, a2]");
  expect_error(a2, {"bad.yaml:", "duplicate axis letter 'A'", "'a' and 'a2'", "give post.letters"});
  expect_error(good + "post:\n  letters: {x: F}\n", {"bad.yaml:10:", "post.letters.x", "not an axis word"});
  // A rotary axis without its pivot.
  expect_error(with("pivot_mm: [0, 0, 0], limits: [-360", "limits: [-360"),
               {"bad.yaml:7:", "axes[4].pivot_mm", "required key is missing"});
  // No chains: block, or half of one.
  expect_error(with("chains: {table: [a, c], head: [x, y, z]}\n", ""), {"bad.yaml:1:", "'chains'", "missing"});
  expect_error(with("chains: {table: [a, c], head: [x, y, z]}", "chains: {table: [a, c]}"),
               {"bad.yaml:8:", "chains.head", "missing"});
  // Duplicate keys anywhere: yaml-cpp would silently keep the first.
  expect_error(good + "post:\n  tolerance_mm: 0.01\n  tolerance_mm: 0.5\n",
               {"bad.yaml:11:3", "post.tolerance_mm", "duplicate key", "line 10"});
  expect_error(good + "name: u\n", {"bad.yaml:9:1", "'name'", "duplicate key (already given at line 1)"});
  expect_error(with("{name: x, type: linear,", "{name: x, name: w, type: linear,"),
               {"bad.yaml:3:", "axes[0].name", "duplicate key"});
  // Zero or negative tolerances and feeds.
  expect_error(good + "post: {tolerance_mm: 0}\n", {"bad.yaml:9:", "post.tolerance_mm", "must be positive"});
  expect_error(good + "post: {tolerance_mm: -0.01}\n", {"bad.yaml:9:", "post.tolerance_mm", "must be positive"});
  expect_error(good + "post:\n  axis_tolerance_deg: 0\n", {"bad.yaml:10:", "post.axis_tolerance_deg", "positive"});
  expect_error(with("limits: [-90, 90]}", "limits: [-90, 90], max_feed: -5}"),
               {"bad.yaml:6:", "axes[3].max_feed", "must be positive"});
  expect_error(with("limits: [-90, 90]}", "limits: [-90, 90], max_accel: 0}"),
               {"bad.yaml:6:", "axes[3].max_accel", "must be positive"});
  // The XMINI file too (its own loader).
  expect_error("name: x\nkinematics: xmini\nxmini:\n  tool_length_mm: 50\n  tool_length_mm: 60\n",
               {"bad.yaml:5:3", "xmini.tool_length_mm", "duplicate key"});
  expect_error("name: x\nkinematics: xmini\npost: {letters: {q1: V}}\n", {"bad.yaml:3:", "duplicate axis letter 'V'"});
  expect_error("name: x\nkinematics: xmini\npost: {tolerance_mm: 0}\n", {"bad.yaml:3:", "post.tolerance_mm"});
}

TEST(Machine, KeyLocationsForLaterErrors) {
  const auto m = machine::load_text(std::string(kGood) + "post:\n  safe_z_mm: 50\n", "m.yaml");
  EXPECT_EQ(m.where("post.safe_z_mm").str(), "m.yaml:10:3");
  EXPECT_EQ(m.where("axes[3].limits").line, 6);
  EXPECT_EQ(m.where("post.dialect").str(), "m.yaml");  // a default: the file alone
}

TEST(Machine, MissingFileIsAnInputError) { EXPECT_THROW(machine::load("/nonexistent/m.yaml"), InputError); }

// Found by fuzz/machine_fuzz: a mapping key that is not a scalar made yaml-cpp throw past the loader.
TEST(MachineFuzzRegressions, NonScalarKeyIsAnInputError) {
  try {
    machine::load(test::source_path("tests/data/fuzz-regressions/machine-nonscalar-key.yaml"));
    FAIL() << "accepted";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("machine-nonscalar-key.yaml:"), std::string::npos) << e.what();
  }
}

// ---------------------------------------------------------------------------------------------------
// Machine bodies (geometry.bodies) and the link poses that place them
// ---------------------------------------------------------------------------------------------------

TEST(MachineBodies, BundledMachinesShipBodiesWithSourcesOnBothSides) {
  for (const auto& path : bundled_machines()) {
    const machine::Machine m = machine::load(path);
    if (m.kind != machine::ModelKind::Serial) continue;
    SCOPED_TRACE(path);
    ASSERT_FALSE(m.geometry.bodies.empty());
    bool head = false, fixed = false;
    for (const auto& b : m.geometry.bodies) {
      EXPECT_FALSE(b.source.empty()) << b.name;
      EXPECT_GT(b.where.line, 0) << b.name;
      (b.side == machine::BodySide::Head ? head : fixed) = true;
    }
    EXPECT_TRUE(head);
    EXPECT_TRUE(fixed);
  }
  const machine::Machine haas = machine::load(test::source_path("machines/haas-umc750.yaml"));
  const auto& platter = haas.geometry.bodies.front();
  EXPECT_EQ(platter.name, "platter");
  EXPECT_EQ(platter.shape, machine::BodyShape::Cylinder);
  EXPECT_DOUBLE_EQ(platter.diameter_mm, 500.0);  // Haas UMC-750 data sheet
  EXPECT_EQ(platter.axis, haas.axis_index("c"));
  EXPECT_EQ(platter.side, machine::BodySide::Table);
}

TEST(MachineBodies, BadBodiesNameTheLineAndTheKey) {
  const std::string g = std::string(kGood) + "geometry:\n  bodies:\n";
  expect_error(g + "    - {name: p, attach: q, box: {min_mm: [0, 0, 0], max_mm: [1, 1, 1]}, source: s}\n",
               {"bad.yaml:", "geometry.bodies[0].attach", "no axis 'q'"});
  expect_error(g + "    - {name: p, attach: c, box: {min_mm: [0, 0, 0], max_mm: [1, 1, 1]}}\n",
               {"geometry.bodies[0].source", "required key is missing"});
  expect_error(g + "    - {name: p, attach: c, source: s, box: {min_mm: [0, 0, 0], max_mm: [1, 1, 1]},\n"
                   "       cylinder: {from_mm: [0, 0, 0], to_mm: [0, 0, 1], diameter_mm: 3}}\n",
               {"geometry.bodies[0]", "exactly one of box, cylinder, mesh"});
  expect_error(g + "    - {name: p, attach: c, source: s, box: {min_mm: [0, 0, 0], max_mm: [1, -1, 1]}}\n",
               {"bad.yaml:11:", "min_mm must be below max_mm"});
  expect_error(
      g + "    - {name: p, attach: x, source: s, cylinder: {from_mm: [0, 0, 0], to_mm: [0, 0, 1], diameter_mm: 0}}\n",
      {"cylinder.diameter_mm", "must be positive"});
  expect_error(g + "    - {name: p, attach: base, source: s, mesh: {file: nowhere.stl}}\n", {"mesh.file", "not found"});
  expect_error(g + "    - {name: p, attach: base, source: s, box: {min_mm: [0, 0, 0], max_mm: [1, 1, 1]}}\n" +
                   "    - {name: p, attach: a, source: s, box: {min_mm: [0, 0, 0], max_mm: [1, 1, 1]}}\n",
               {"geometry.bodies[1].name", "used twice"});
  const machine::Machine ok = machine::load_text(
      g + "    - {name: fork, attach: a, source: s, box: {min_mm: [0, 0, 0], max_mm: [1, 1, 1]}}\n", "ok.yaml");
  ASSERT_EQ(ok.geometry.bodies.size(), 1u);
  EXPECT_EQ(ok.geometry.bodies[0].side, machine::BodySide::Table);
}

namespace {

/// solve_for_rotaries as the generic chain walk it was written as (the oracle of the stepped one).
bool reference_solve_for_rotaries(const kin::SerialGeometry<double>& g, const kin::Posed& pose, kin::Axes& q) {
  std::array<int, 3> lin{};
  int n = 0;
  for (int i = 0; i < 5; ++i)
    if (g.joints[static_cast<size_t>(i)].type == kin::AxisType::Linear) lin[static_cast<size_t>(n++)] = i;
  auto col = [&](int idx) {
    for (int c = 0; c < 3; ++c)
      if (lin[static_cast<size_t>(c)] == idx) return c;
    return -1;
  };
  auto R = [&](int idx) {
    const auto& j = g.joints[static_cast<size_t>(idx)];
    return kin::detail::axis_angle<double>(j.direction, q[idx] + j.offset);
  };
  Vec3 t0 = g.gauge_home_mm - g.tool_length_mm * g.tool_direction_home;
  Eigen::Matrix3d A = Eigen::Matrix3d::Zero();
  for (auto it = g.head_chain.rbegin(); it != g.head_chain.rend(); ++it) {
    const auto& j = g.joints[static_cast<size_t>(*it)];
    if (j.type == kin::AxisType::Linear) {
      t0 += j.direction * j.offset;
      A.col(col(*it)) += j.direction;
    } else {
      const Eigen::Matrix3d Rj = R(*it);
      t0 = Rj * (t0 - j.pivot_mm) + j.pivot_mm;
      A = Rj * A;
    }
  }
  for (int idx : g.table_chain) {
    const auto& j = g.joints[static_cast<size_t>(idx)];
    if (j.type == kin::AxisType::Linear) {
      t0 -= j.direction * j.offset;
      A.col(col(idx)) -= j.direction;
    } else {
      const Eigen::Matrix3d Rt = R(idx).transpose();
      t0 = Rt * (t0 - j.pivot_mm) + j.pivot_mm;
      A = Rt * A;
    }
  }
  t0 -= g.part_origin_home_mm;
  if (std::abs(A.determinant()) < 1e-12) return false;
  const Vec3 l = A.inverse() * (pose.tip_mm - t0);
  for (int c = 0; c < 3; ++c) q[lin[static_cast<size_t>(c)]] = l[c];
  return true;
}

}  // namespace

TEST(SerialKinematics, SteppedForwardAndSolveAreTheGenericOnesToTheBit) {
  // forward() and solve_for_rotaries() run on steps laid out once (faster); every number must stay the generic
  // chain walk's (serial_forward and the walk above), bit for bit: the post's and the gate's output depend on them.
  auto rng = test::rng(12);
  std::uniform_real_distribution<double> U(-1.0, 1.0);
  for (const auto& path : bundled_machines()) {
    const machine::Machine m = machine::load(path);
    if (m.kind != machine::ModelKind::Serial) continue;
    SCOPED_TRACE(path);
    for (const double tool_mm : {m.default_tool_length_mm, 123.456}) {
      const auto kk = m.make_kinematics(tool_mm);
      const auto* sk = dynamic_cast<const kin::SerialKinematics*>(kk.get());
      ASSERT_NE(sk, nullptr);
      for (int trial = 0; trial < 500; ++trial) {
        kin::Axes q;
        for (int i = 0; i < 5; ++i) q[i] = m.axes[static_cast<size_t>(i)].rotary() ? 7.0 * U(rng) : 300.0 * U(rng);
        const kin::Posed fast = sk->forward(q), ref = kin::serial_forward(sk->geometry(), q);
        for (int c = 0; c < 3; ++c) {
          EXPECT_EQ(std::bit_cast<std::uint64_t>(fast.tip_mm[c]), std::bit_cast<std::uint64_t>(ref.tip_mm[c]));
          EXPECT_EQ(std::bit_cast<std::uint64_t>(fast.axis[c]), std::bit_cast<std::uint64_t>(ref.axis[c]));
        }
        const kin::Posed target{Vec3(100.0 * U(rng), 100.0 * U(rng), 100.0 * U(rng)), fast.axis};
        kin::Axes qs = q, qr = q;
        ASSERT_EQ(sk->solve_for_rotaries(target, qs), reference_solve_for_rotaries(sk->geometry(), target, qr));
        for (int i = 0; i < 5; ++i) EXPECT_EQ(std::bit_cast<std::uint64_t>(qs[i]), std::bit_cast<std::uint64_t>(qr[i]));
      }
    }
  }
}

TEST(MachineBodies, LinkPosesAgreeWithForwardKinematics) {
  // Oracles: FK (serial_forward) for the head's end link, rigidity of the table chain for its links.
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> U(-1.0, 1.0);
  for (const auto& path : bundled_machines()) {
    const machine::Machine m = machine::load(path);
    if (m.kind != machine::ModelKind::Serial) continue;
    SCOPED_TRACE(path);
    const auto kk = m.make_kinematics(m.default_tool_length_mm);
    const auto& g = *m.serial;
    const Vec3 tip_home = g.gauge_home_mm - m.default_tool_length_mm * g.tool_direction_home;
    for (int trial = 0; trial < 20; ++trial) {
      kin::Axes q;
      for (int i = 0; i < 5; ++i) q[i] = m.axes[static_cast<size_t>(i)].rotary() ? 1.5 * U(rng) : 200.0 * U(rng);
      const kin::Posed fk = kk->forward(q);
      // The last head link carries the tool: it maps the home tip and axis to FK's.
      Eigen::Isometry3d Th;
      const int last_head = g.head_chain.empty() ? -1 : g.head_chain.back();
      ASSERT_TRUE(kk->link_in_part(last_head, q, Th));
      EXPECT_LT((Th * tip_home - fk.tip_mm).norm(), 1e-9);
      EXPECT_LT((Th.linear() * g.tool_direction_home - fk.axis).norm(), 1e-12);
      // The last table link carries the part: fixed in the part frame (up to the part origin).
      Eigen::Isometry3d Tt;
      const int last_table = g.table_chain.empty() ? -1 : g.table_chain.back();
      ASSERT_TRUE(kk->link_in_part(last_table, q, Tt));
      EXPECT_LT((Tt.translation() + g.part_origin_home_mm).norm(), 1e-9);
      EXPECT_LT((Tt.linear() - Eigen::Matrix3d::Identity()).norm(), 1e-12);
      // A point on a table joint's axis is shared by the link before it and the link it drives.
      Eigen::Isometry3d Tprev;
      ASSERT_TRUE(kk->link_in_part(-1, q, Tprev));
      for (int idx : g.table_chain) {
        const auto& j = g.joints[static_cast<size_t>(idx)];
        Eigen::Isometry3d Tj;
        ASSERT_TRUE(kk->link_in_part(idx, q, Tj));
        if (j.type == kin::AxisType::Rotary) {
          const Vec3 p = j.pivot_mm + 37.0 * j.direction;
          EXPECT_LT((Tj * p - Tprev * p).norm(), 1e-9);
        }
        Tprev = Tj;
      }
      // All links at once (one pass over the joints) are the links one by one; the head link is head_in_part.
      std::array<Eigen::Isometry3d, 6> all;
      ASSERT_TRUE(kk->links_in_part(q, 6, 0x3fu, all.data()));
      for (int l = 0; l < 6; ++l) {
        Eigen::Isometry3d one;
        ASSERT_TRUE(kk->link_in_part(l - 1, q, one));
        EXPECT_LT((all[static_cast<std::size_t>(l)].matrix() - one.matrix()).norm(), 1e-12) << "link " << l;
      }
      Eigen::Isometry3d Thead;
      ASSERT_TRUE(kk->head_in_part(q, Thead));
      EXPECT_LT((Thead.matrix() - Th.matrix()).norm(), 1e-12);
      // head_link() names the link whose pose that is (the C-space places the head with the other links).
      ASSERT_GE(kk->head_link(), 0);
      EXPECT_LT((all[static_cast<std::size_t>(kk->head_link())].matrix() - Thead.matrix()).norm(), 1e-12);
      // The tool axis as a primary rotation of a secondary vector (tabulated by the C-space) is FK's axis.
      Eigen::Matrix3d R1;
      Vec3 v2;
      const auto rp = kk->rotary_pair();
      ASSERT_TRUE(kk->axis_factors(q[rp[0]], q[rp[1]], &R1, &v2));
      EXPECT_LT((R1 * v2 - fk.axis).norm(), 1e-12);
    }
    Eigen::Isometry3d T;
    EXPECT_FALSE(kk->link_in_part(7, kin::Axes::Zero(), T));  // no such joint
  }
}

// kin::Kinematics::motion_bound against dense FK: for random straight joint moves on every bundled serial machine
// (small to half-turn spans), the tip leaves the polyline through n + 1 equally spaced samples by at most
// tip_accel h^2 / 8, the unit axis leaves its own polyline by at most axis_accel h^2 / 8, the axis turns at most
// axis_rate h / 2 away from the nearest sample, and its speed never exceeds |u_b - u_a| + axis_accel / 2 (the
// tighter rate verify uses). Oracle: 1000 FK samples per move, independent of the bound's derivation.
TEST(Machines, MotionBoundHoldsAgainstDenseFk) {
  auto rng = test::rng(77);
  std::uniform_real_distribution<double> u01(0.0, 1.0);
  constexpr int kDense = 1000;
  for (const char* name : {"haas-umc750", "trunnion-ac", "head-table-bc45", "head-head-ac"}) {
    const auto m = machine::load(test::source_path(std::string("machines/") + name + ".yaml"));
    const auto k = m.kinematics();
    int tight = 0;
    for (int trial = 0; trial < 60; ++trial) {
      const double scale = std::pow(10.0, -3.0 + 3.0 * u01(rng));  // fraction of the stroke: 0.001 .. 1
      kin::Axes qa, qb;
      for (int i = 0; i < 5; ++i) {
        const auto& a = m.axes[static_cast<size_t>(i)];
        const double lo = a.rotary() ? std::max(a.min, -kPi) : a.min, hi = a.rotary() ? std::min(a.max, kPi) : a.max;
        qa[i] = lo + (hi - lo) * u01(rng);
        qb[i] = std::clamp(qa[i] + scale * (hi - lo) * (2.0 * u01(rng) - 1.0), lo, hi);
      }
      kin::MotionBound mb;
      ASSERT_TRUE(k->motion_bound(qa, qb, mb)) << name;
      std::vector<kin::Posed> dense(kDense + 1);
      for (int j = 0; j <= kDense; ++j)
        dense[static_cast<size_t>(j)] = k->forward(qa + (double(j) / kDense) * (qb - qa));
      const Vec3 ua = dense.front().axis, ub = dense.back().axis;
      double max_speed = 0.0;
      for (int j = 0; j < kDense; ++j)
        max_speed = std::max(
            max_speed, kDense * (dense[static_cast<size_t>(j + 1)].axis - dense[static_cast<size_t>(j)].axis).norm());
      const double rate_tight = (ub - ua).norm() + 0.5 * mb.axis_accel;
      EXPECT_LE(max_speed, std::min(mb.axis_rate_rad, rate_tight) * (1 + 1e-6) + 1e-12) << name << " trial " << trial;
      for (int n : {1, 2, 3, 5, 8}) {
        const double h = 1.0 / n;
        double tip_off = 0.0, axis_off = 0.0, turn = 0.0;
        std::vector<kin::Posed> s(static_cast<size_t>(n) + 1);
        for (int i = 0; i <= n; ++i) s[static_cast<size_t>(i)] = k->forward(qa + (double(i) / n) * (qb - qa));
        for (int j = 0; j <= kDense; ++j) {
          const double t = double(j) / kDense;
          const int i = std::min(n - 1, static_cast<int>(t * n));
          const double w = t * n - i;
          const auto &p0 = s[static_cast<size_t>(i)], &p1 = s[static_cast<size_t>(i) + 1];
          const auto& d = dense[static_cast<size_t>(j)];
          tip_off = std::max(tip_off, (d.tip_mm - ((1 - w) * p0.tip_mm + w * p1.tip_mm)).norm());
          axis_off = std::max(axis_off, (d.axis - ((1 - w) * p0.axis + w * p1.axis)).norm());
          const auto& nearest = w < 0.5 ? p0 : p1;
          turn = std::max(turn, std::acos(std::clamp(d.axis.dot(nearest.axis), -1.0, 1.0)));
        }
        EXPECT_LE(tip_off, mb.tip_accel_mm * h * h / 8 + 1e-9) << name << " trial " << trial << " n " << n;
        EXPECT_LE(axis_off, mb.axis_accel * h * h / 8 + 1e-12) << name << " trial " << trial << " n " << n;
        EXPECT_LE(turn, std::min(mb.axis_rate_rad, rate_tight) * h / 2 + 1e-7) << name << " trial " << trial;
        if (n == 2 && tip_off > 0.05 * mb.tip_accel_mm * h * h / 8) ++tight;
      }
    }
    EXPECT_GT(tight, 10) << name << ": the bound is not vacuous (within 20x of the dense deviation)";
  }
}

TEST(Machine, AccelerationsInModelUnits) {
  const auto m = machine::load(test::source_path("machines/trunnion-ac.yaml"));
  // 300 mm/s^2 on X, 300 deg/s^2 on A (the LinuxCNC sim's MAX_ACCELERATION), stored in mm and rad.
  EXPECT_DOUBLE_EQ(m.axes[0].max_accel, 300.0);
  EXPECT_NEAR(m.axes[3].max_accel, 300.0 * kPi / 180.0, 1e-12);
  // Absent: unknown (0), which the post takes as every axis alike.
  const auto h = machine::load(test::source_path("machines/haas-umc750.yaml"));
  for (const auto& a : h.axes) EXPECT_EQ(a.max_accel, 0.0) << a.name;
}
