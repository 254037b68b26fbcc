// Machine definition files: every bundled machine loads and round-trips IK -> FK; bad files give
// errors that name the file, the line and the key.
#include "cscam/machine/machine.hpp"

#include <gtest/gtest.h>

#include <filesystem>

#include "cscam/core/error.hpp"
#include "cscam/core/units.hpp"
#include "test_support.hpp"

using namespace cscam;
using Vec3 = Eigen::Vector3d;

namespace {

std::vector<std::string> bundled_machines() {
  std::vector<std::string> out;
  for (const auto& e : std::filesystem::directory_iterator(test::source_path("machines")))
    if (e.path().extension() == ".yaml") out.push_back(e.path().string());
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
  - {name: a, type: rotary, side: table, direction: [1, 0, 0], limits: [-90, 90]}
  - {name: c, type: rotary, side: table, direction: [0, 0, 1], limits: [-360, 360]}
)";

}  // namespace

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
  expect_error(std::string(kGood) + "bogus: 1\n", {"bad.yaml:8:1", "'bogus'", "unknown key"});
  expect_error("axes: []\n", {"bad.yaml", "'name'", "required key is missing"});
  std::string s = kGood;
  s.replace(s.find("limits: [-90, 90]"), 17, "limits: [90, -90]");
  expect_error(s, {"bad.yaml:6", "axes[3].limits", "min < max"});
  s = kGood;
  s.replace(s.find("[1, 0, 0], limits: [-90"), 9, "[0, 0, 0]");
  expect_error(s, {"bad.yaml:6", "axes[3].direction", "zero vector"});
  s = kGood;
  s.replace(s.find("type: rotary, side: table, direction: [1"), 12, "type: spiral");
  expect_error(s, {"bad.yaml:6", "axes[3].type", "'spiral'"});
  s = kGood;
  s.replace(s.find("limits: [-100, 100]"), 19, "limits: [-100, abc]");
  expect_error(s, {"bad.yaml:3", "axes[0].limits", "'abc'"});
  s = kGood;
  s.replace(s.find("[0, 0, 1], limits: [-360"), 9, "[1, 0, 0]");
  expect_error(s, {"bad.yaml", "parallel"});
  expect_error("name: [unclosed\n", {"bad.yaml:", "YAML syntax error"});
  expect_error(std::string(kGood) + "post: {letters: {q: Q}}\n", {"bad.yaml:8", "post.letters.q", "no such axis"});
  expect_error(std::string(kGood) + "post: {start_branch: positive:x}\n", {"post.start_branch", "not a rotary"});
  expect_error(std::string(kGood) + "kinematics: delta\n", {"unknown kinematics 'delta'"});
}

TEST(Machine, MissingFileIsAnInputError) { EXPECT_THROW(machine::load("/nonexistent/m.yaml"), InputError); }
