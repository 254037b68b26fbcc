// The safety gate and the post's flips. The gate is an oracle only if it can fail: every rule is shown
// failing on a program that was tampered with in one place (an axis beyond its limit, a feed above
// max_feed, a tip moved off the path, a CL point skipped), naming that NC line, and write_checked then
// leaves no file. The post's flip/unwind handling is checked by the gate, by an independent FK scan of
// every feed block, and by LinuxCNC's rs274.
#include "cscam/gate/gate.hpp"

#include <fmt/format.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <functional>
#include <regex>
#include <sstream>
#include <utility>

#include "cscam/cl/program.hpp"
#include "cscam/core/error.hpp"
#include "cscam/core/units.hpp"
#include "cscam/cspace/cspace.hpp"
#include "cscam/geom/mesh.hpp"
#include "cscam/geom/scene.hpp"
#include "cscam/machine/machine.hpp"
#include "cscam/nc/reader.hpp"
#include "cscam/plan/plan.hpp"
#include "cscam/post/post.hpp"
#include "cscam/report/letters.hpp"
#include "cscam/report/verify.hpp"
#include "rs274_support.hpp"
#include "test_support.hpp"

using namespace cscam;
namespace fs = std::filesystem;

namespace {

machine::Machine load_machine(const std::string& name) {
  return machine::load(test::source_path("machines/" + name + ".yaml"));
}

struct Posted {
  std::string text;
  post::Summary summary;
};

Posted post_program(const cl::Program& prog, const machine::Machine& m, const kin::Kinematics& k) {
  const auto axes = post::conventional_axes(prog, m, k);
  std::ostringstream os;
  post::Options o;
  Posted p;
  post::write_nc(os, prog, m, k, axes, o, p.summary);
  p.text = os.str();
  return p;
}

/// The gate's collision check against `space` (which must outlive it): one workspace and counters per worker.
/// `prog` posted with the conventional strategy in `dialect`: the text and the post's summary.
std::pair<std::string, post::Summary> conventionally_posted(const cl::Program& prog, const machine::Machine& m,
                                                            const kin::Kinematics& k, const std::string& dialect) {
  post::Options o;
  o.dialect = dialect;
  post::Summary sum;
  std::ostringstream os;
  post::write_nc(os, prog, m, k, post::conventional_axes(prog, m, k), o, sum);
  return {os.str(), std::move(sum)};
}

std::function<gate::Options::CollisionCheck(int)> collision_against(const cspace::Space& space) {
  // As the commands do: a path check per worker (the space is the caller's: not owned), one cutter for every tool.
  return [&space](int) -> gate::Options::CollisionCheck {
    auto check =
        std::make_shared<cspace::PathCheck>(std::shared_ptr<const cspace::Space>(std::shared_ptr<void>(), &space));
    return [check](const kin::Axes& q, bool whole_tool) {
      return (*check)(q, whole_tool ? cspace::SweepMode::Rapid : cspace::SweepMode::Cutting);
    };
  };
}

std::vector<std::string> lines_of(const std::string& text) {
  std::vector<std::string> out;
  std::istringstream is(text);
  for (std::string l; std::getline(is, l);) out.push_back(l);
  return out;
}

std::string join(const std::vector<std::string>& lines) {
  std::string s;
  for (const auto& l : lines) s += l + "\n";
  return s;
}

/// The 1-based number of the n-th line (from `from`) that starts with `prefix`.
int find_line(const std::vector<std::string>& lines, const std::string& prefix, int from = 0) {
  for (size_t i = static_cast<size_t>(from); i < lines.size(); ++i)
    if (lines[i].rfind(prefix, 0) == 0) return static_cast<int>(i) + 1;
  return 0;
}

/// A program on the trunnion: the ISO/CATIA example (linear and rotary motion, a rapid).
struct Fixture {
  machine::Machine m = load_machine("trunnion-ac");
  cl::Program prog = cl::read_file(test::source_path("examples/cl/iso_catia.cls"));
  std::shared_ptr<const kin::Kinematics> k = m.make_kinematics(post::tool_length_for(m, 0));
  Posted posted = post_program(prog, m, *k);
  gate::Options opt = gate::options_for(m, 0, 0, 0);
  gate::Summary run(const std::string& text) const {
    return gate::check(text, "t.ngc", prog, m, *k, opt, &posted.summary.cl_line_of_nc_line);
  }
};

bool has_kind(const gate::Summary& s, gate::Violation::Kind kind, int nc_line) {
  for (const auto& v : s.violations)
    if (v.kind == kind && (nc_line == 0 || v.nc_line == nc_line)) return true;
  return false;
}

}  // namespace

TEST(Gate, PassesTheConventionalProgram) {
  Fixture f;
  const auto s = f.run(f.posted.text);
  EXPECT_TRUE(s.ok) << s.message;
  EXPECT_GT(s.limit_checks, 50u);
  EXPECT_GT(s.deviation.samples, 100u);
  EXPECT_LE(s.max_velocity_ratio, 1.0 + f.opt.feed_slack);
}

TEST(Gate, RefusesAnAxisBeyondItsLimit) {
  Fixture f;
  auto lines = lines_of(f.posted.text);
  const int n = find_line(lines, "G1", 20);
  ASSERT_GT(n, 0);
  // The trunnion's A stops at -100/+50 deg: A100 is beyond it.
  lines[static_cast<size_t>(n - 1)] =
      std::regex_replace(lines[static_cast<size_t>(n - 1)], std::regex(" A-?[0-9.]+"), "");
  lines[static_cast<size_t>(n - 1)] += " A100.0";
  const auto s = f.run(join(lines));
  ASSERT_FALSE(s.ok);
  EXPECT_TRUE(has_kind(s, gate::Violation::Kind::Limit, n)) << s.message;
  EXPECT_NE(s.message.find("limits"), std::string::npos) << s.message;
}

TEST(Gate, LimitViolationsOfALongProgramAreReportedInBlockOrder) {
  // Several of the gate's chunks of 4096 blocks, whose limits are checked ahead in parallel: every block beyond
  // a limit is reported, in block order, at any chunk boundary.
  Fixture f;
  std::vector<std::string> lines = {"G21 G90 G94", "G0 X0 Y0 Z50 A0 C0"};
  std::vector<int> beyond;
  for (int i = 0; i < 10000; ++i) {
    const bool out = i == 0 || i == 5 || i == 4094 || i == 4095 || i == 8190 || i == 8191 || i == 9999;
    lines.push_back(fmt::format("G1 X{:.2f} Y0 Z50 A{} C0 F1000", 0.01 * (i % 100), out ? "100.0" : "0"));
    if (out) beyond.push_back(static_cast<int>(lines.size()));
  }
  const auto s = f.run(join(lines));
  std::vector<int> reported;
  for (const auto& v : s.violations)
    if (v.kind == gate::Violation::Kind::Limit) reported.push_back(v.nc_line);
  EXPECT_EQ(reported, beyond);
}

TEST(Gate, RefusesAFeedAboveMaxFeed) {
  Fixture f;
  auto lines = lines_of(f.posted.text);
  // An inverse-time block with rotary motion, made 1000 times faster than the post wrote it.
  int n = 0;
  for (int from = 0; (n = find_line(lines, "G1", from)) > 0; from = n) {
    const std::string& l = lines[static_cast<size_t>(n - 1)];
    if (l.find(" C") != std::string::npos && l.find(" F") != std::string::npos) break;
  }
  if (n == 0)
    for (int from = 0; (n = find_line(lines, "G93 G1", from)) > 0; from = n)
      if (lines[static_cast<size_t>(n - 1)].find(" F") != std::string::npos) break;
  ASSERT_GT(n, 0) << "no rotary feed block in the program";
  std::smatch mt;
  std::string& l = lines[static_cast<size_t>(n - 1)];
  ASSERT_TRUE(std::regex_search(l, mt, std::regex(" F([0-9.]+)")));
  const double F = std::stod(mt[1].str());
  l = std::regex_replace(l, std::regex(" F[0-9.]+"), " F" + std::to_string(F * 1000.0));
  const auto s = f.run(join(lines));
  ASSERT_FALSE(s.ok);
  EXPECT_TRUE(has_kind(s, gate::Violation::Kind::Velocity, n)) << s.message;
}

TEST(Gate, RefusesATipOffThePathAndNamesTheClLine) {
  Fixture f;
  auto lines = lines_of(f.posted.text);
  // Move one feed block's X by 0.5 mm: far beyond the 0.01 mm tolerance.
  int n = 0;
  for (int from = 20; (n = find_line(lines, "G1", from)) > 0; from = n)
    if (lines[static_cast<size_t>(n - 1)].find(" X") != std::string::npos) break;
  ASSERT_GT(n, 0);
  std::string& l = lines[static_cast<size_t>(n - 1)];
  std::smatch mt;
  ASSERT_TRUE(std::regex_search(l, mt, std::regex(" X(-?[0-9.]+)")));
  const double x = std::stod(mt[1].str());
  l = std::regex_replace(l, std::regex(" X-?[0-9.]+"), fmt::format(" X{:.4f}", x + 0.5));
  const auto s = f.run(join(lines));
  ASSERT_FALSE(s.ok);
  ASSERT_TRUE(has_kind(s, gate::Violation::Kind::Deviation, 0)) << s.message;
  const auto& v = s.violations.front();
  EXPECT_TRUE(v.nc_line == n || v.nc_line == n + 1) << "gate blamed NC line " << v.nc_line << ", tampered " << n;
  EXPECT_GT(v.cl_line, 0);
}

TEST(Gate, RefusesASkippedClPoint) {
  Fixture f;
  auto lines = lines_of(f.posted.text);
  // Drop the last feed block before the end: its CL point is never reached.
  int last = 0;
  for (int from = 0, n; (n = find_line(lines, "G1", from)) > 0; from = n) last = n;
  ASSERT_GT(last, 0);
  lines.erase(lines.begin() + last - 1);
  const auto s = f.run(join(lines));
  ASSERT_FALSE(s.ok) << "a skipped CL point must be found";
  EXPECT_TRUE(has_kind(s, gate::Violation::Kind::Coverage, 0) || has_kind(s, gate::Violation::Kind::Deviation, 0))
      << s.message;
}

TEST(Gate, WriteCheckedLeavesNoFileOnFailure) {
  Fixture f;
  const fs::path dir = fs::temp_directory_path() / ("cscam_gate_test_" + std::to_string(::getpid()));
  fs::create_directories(dir);
  const fs::path out = dir / "bad.ngc";
  fs::remove(out);
  auto lines = lines_of(f.posted.text);
  const int n = find_line(lines, "G1", 20);
  lines[static_cast<size_t>(n - 1)] += " A100.0";
  try {
    gate::write_checked(out.string(), join(lines), f.prog, f.m, *f.k, f.opt, &f.posted.summary.cl_line_of_nc_line);
    FAIL() << "the gate let an unsafe program through";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("unsafe program not written"), std::string::npos) << e.what();
    EXPECT_EQ(e.where().line, n) << e.what();
  }
  EXPECT_FALSE(fs::exists(out));
  for (const auto& entry : fs::directory_iterator(dir)) ADD_FAILURE() << "left behind: " << entry.path();
  gate::write_checked(out.string(), f.posted.text, f.prog, f.m, *f.k, f.opt, &f.posted.summary.cl_line_of_nc_line);
  EXPECT_TRUE(fs::exists(out));
  // The text is written while it is checked: the file holds exactly the text checked, and nothing else is left.
  std::ifstream in(out, std::ios::binary);
  const std::string written((std::istreambuf_iterator<char>(in)), {});
  EXPECT_EQ(written, f.posted.text);
  std::size_t files = 0;
  for ([[maybe_unused]] const auto& entry : fs::directory_iterator(dir)) ++files;
  EXPECT_EQ(files, 1u);
  // A passing program that cannot be written is still an error naming the file.
  EXPECT_THROW(gate::write_checked((dir / "missing" / "x.ngc").string(), f.posted.text, f.prog, f.m, *f.k, f.opt,
                                   &f.posted.summary.cl_line_of_nc_line),
               InputError);
  fs::remove_all(dir);
}

// --- The post's flips and unwinds ------------------------------------------------------------------

namespace {

/// Independent of the gate: the largest rotary change (deg) of any feed block that also moves the tip
/// sideways (not along the tool axis): a flip inside a cut shows up here.
double largest_rotary_step_while_cutting(const std::string& text, const machine::Machine& m, const kin::Kinematics& k) {
  const nc::Program p = nc::read_text(text, "t.ngc", report::axis_letters(m));
  const auto rp = k.rotary_pair();
  double worst = 0;
  for (size_t i = 1; i < p.blocks.size(); ++i) {
    const auto& a = p.blocks[i - 1];
    const auto& b = p.blocks[i];
    if (b.motion == nc::Motion::Rapid) continue;
    const double step = std::max(std::abs(b.axes[static_cast<size_t>(rp[0])] - a.axes[static_cast<size_t>(rp[0])]),
                                 std::abs(b.axes[static_cast<size_t>(rp[1])] - a.axes[static_cast<size_t>(rp[1])]));
    worst = std::max(worst, rad2deg(step));
  }
  return worst;
}

}  // namespace

TEST(PostFlips, CyclicLimitOnAHeadHeadMachineRetractsTurnsAndPlunges) {
  // NX's variable-axis path on the A/C fork head: C runs into its -360 deg stop. Before the fix the post
  // swung A+1.9 -> A-1.9 and C-360 -> C-180 in one G1 block (15 mm off the path).
  const auto m = load_machine("head-head-ac");
  const auto prog = cl::read_file(test::source_path("examples/nx-haas-umc750/variable_axis.cls"));
  const auto k = m.make_kinematics(post::tool_length_for(m, 0));
  const Posted p = post_program(prog, m, *k);
  EXPECT_GE(p.summary.retracts, 1u);
  const auto s =
      gate::check(p.text, "hh.ngc", prog, m, *k, gate::options_for(m, 0, 0, 0), &p.summary.cl_line_of_nc_line);
  EXPECT_TRUE(s.ok) << s.message;
  EXPECT_LT(largest_rotary_step_while_cutting(p.text, m, *k), 30.0);
  test::expect_rs274_agrees(p.text, m, "gate_hh");
}

TEST(PostFlips, RefusePolicyNamesTheClLine) {
  auto m = load_machine("head-head-ac");
  m.post.singularity.flip = "refuse";
  const auto prog = cl::read_file(test::source_path("examples/nx-haas-umc750/variable_axis.cls"));
  const auto k = m.make_kinematics(post::tool_length_for(m, 0));
  try {
    post_program(prog, m, *k);
    FAIL() << "flip: refuse must refuse";
  } catch (const InputError& e) {
    EXPECT_GT(e.where().line, 0);
    EXPECT_NE(std::string(e.what()).find("refuse"), std::string::npos) << e.what();
  }
}

TEST(PostFlips, XminiTurnsCInPlaceAtTheSingularPoint) {
  // Seed 000's cut crosses the wrist singularity (a = 0) at x = 0; the branch rule keeps a >= 0, so C must
  // turn 180 deg. At a = 0 that turn does not move the tool: the post turns there, with the tool held.
  const auto m = load_machine("xmini");
  const auto prog = cl::read_file(test::source_path("examples/xmini/seed000_x_cut.cls"));
  const auto k = m.make_kinematics(post::tool_length_for(m, 0));
  const Posted p = post_program(prog, m, *k);
  EXPECT_EQ(p.summary.reorientations, 1u);
  EXPECT_EQ(p.summary.retracts, 0u);
  const auto s =
      gate::check(p.text, "x.ngc", prog, m, *k, gate::options_for(m, 0, 0, 0), &p.summary.cl_line_of_nc_line);
  EXPECT_TRUE(s.ok) << s.message;
  EXPECT_LT(s.deviation.max_tip_deviation_mm, m.post.tolerance_mm);
}

TEST(PostFlips, MachineFileRejectsABadPolicy) {
  const std::string path = test::source_path("machines/head-head-ac.yaml");
  std::ifstream in(path);
  std::stringstream ss;
  ss << in.rdbuf();
  std::string text = ss.str();
  text = std::regex_replace(text, std::regex("flip: auto"), "flip: sometimes");
  try {
    machine::load_text(text, "bad-machine.yaml");
    FAIL() << "an unknown flip policy must be an error";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("bad-machine.yaml"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("post.singularity.flip"), std::string::npos) << e.what();
    EXPECT_GT(e.where().line, 0);
  }
}

// --- Rapids against the part ---------------------------------------------------------------------------

TEST(Gate, RefusesARapidThroughThePart) {
  // Seed 002's groove, planned at cone 25 deg (3+2, clear of the lips) and posted: its rapids clear the part.
  // The same program with one rapid sent down into the groove's floor must be refused, naming that block.
  // (The conventional orientation itself hits the lip: the gate refuses that program with meshes given.)
  const auto m = load_machine("trunnion-ac");
  const auto prog = cl::read_file(test::source_path("examples/groove/groove.cls"));
  const auto k = m.make_kinematics(post::tool_length_for(m, 0));
  geom::Scene scene;
  scene.add("groove", geom::ObstacleRole::Part, geom::load_mesh(test::source_path("examples/groove/groove.stl")));
  scene.build(false);
  const auto tool = geom::ToolShape::from_cutter(10, 5, 30);
  plan::Options po;
  po.cspace.cone_rad = deg2rad(25.0);
  po.cspace.ball_radius_mm = 5.0;
  po.cspace.check_collision = true;
  const plan::Plan planned = plan::Planner(m, k, &scene, &tool, po).run(prog);
  std::ostringstream os;
  post::Options o;
  o.control_offset_mm = 5.0;
  post::Summary sum;
  post::write_nc(os, planned.program, m, *k, planned.axes, o, sum);
  const cspace::Space space(k, &scene, &tool, po.cspace, nullptr);
  gate::Options opt = gate::options_for(m, 0, 0, 25.0);
  opt.make_collision = collision_against(space);
  const auto ok = gate::check(os.str(), "g.ngc", planned.program, m, *k, opt, &sum.cl_line_of_nc_line);
  EXPECT_TRUE(ok.ok) << ok.message;
  EXPECT_GT(ok.collision_checks, 10u);

  auto lines = lines_of(os.str());
  const int last_g0 = [&] {
    int n = 0;
    for (int from = 0, i; (i = find_line(lines, "G0", from)) > 0; from = i) n = i;
    return n;
  }();
  ASSERT_GT(last_g0, 0);
  lines.insert(lines.begin() + last_g0, "G0 Z-20.0");  // from the retract height down through the part
  const auto bad = gate::check(join(lines), "g.ngc", planned.program, m, *k, opt, nullptr);
  ASSERT_FALSE(bad.ok);
  EXPECT_TRUE(has_kind(bad, gate::Violation::Kind::Collision, last_g0 + 1)) << bad.message;
  // Refused on the way to disk, with what to do: the colliding move is none of the CL's (a retract or exit the post
  // adds goes post.singularity.retract_mm along the axis, then along Z), and nothing is written.
  {
    const std::string path =
        (std::filesystem::temp_directory_path() / ("cscam_gate_hint_" + std::to_string(::getpid()) + ".ngc")).string();
    try {
      gate::write_checked(path, join(lines), planned.program, m, *k, opt, nullptr);
      ADD_FAILURE() << "a colliding program was written";
    } catch (const InputError& e) {
      const std::string msg = e.what();
      EXPECT_NE(msg.find("rapid move collides"), std::string::npos) << msg;
      EXPECT_NE(msg.find("a move the post added, not a CL move"), std::string::npos) << msg;
      EXPECT_NE(msg.find("post.singularity.retract_mm"), std::string::npos) << msg;
    }
    EXPECT_FALSE(std::filesystem::exists(path));
  }

  // Feed moves are checked too, not only the CL points: a feed block inserted in the middle of the cut that
  // dives 20 mm through the floor and the next block back up. Its end and its inside collide; the CL points
  // around it are the planner's, certified free.
  lines = lines_of(os.str());
  int mid_g1 = 0;
  for (int from = 0, i, n = 0; (i = find_line(lines, "G1", from)) > 0; from = i)
    if (++n == 40) mid_g1 = i;
  ASSERT_GT(mid_g1, 0);
  lines.insert(lines.begin() + mid_g1, "G1 Z-20.0");
  const auto feed = gate::check(join(lines), "g.ngc", planned.program, m, *k, opt, nullptr);
  ASSERT_FALSE(feed.ok);
  EXPECT_TRUE(has_kind(feed, gate::Violation::Kind::Collision, mid_g1 + 1)) << feed.message;
  EXPECT_NE(feed.message.find("feed move collides"), std::string::npos) << feed.message;
}

// Collisions are sampled along the path at most collision_step (0.5 mm) of joint motion apart, across blocks: the same
// 40 mm cut in blocks of 0.1 mm takes about as many checks as in blocks of 0.2 mm (one per block end took 200 more),
// and a wall 1 mm thick that the shank crosses is still found, in the block where the shank first meets it.
TEST(Gate, CollisionsAreSampledAlongThePathAcrossShortBlocks) {
  const auto m = load_machine("trunnion-ac");
  const auto k = m.make_kinematics(post::tool_length_for(m, 0));
  const auto tool = geom::ToolShape::from_cutter(10, 5, 30);  // flutes to z + 30, shank (r 5) to z + 50, holder above
  auto gate_with_wall = [&](double block_mm, double wall_x) {
    std::string text = "UNITS/MM\nMULTAX/ON\nCUTTER/10,5\nFEDRAT/MMPM,1000\n";
    const int n = static_cast<int>(std::lround(40.0 / block_mm));
    for (int i = 0; i <= n; ++i) text += fmt::format("GOTO/{:.4f},0,5,0,0,1\n", -20.0 + block_mm * i);
    const cl::Program prog = cl::read_text(text, "line.cls");
    const Posted p = post_program(prog, m, *k);
    geom::Scene scene;
    // Beside the shank only (tip at z 5: shank z 35..55): z 38..52.
    scene.add("wall", geom::ObstacleRole::Part, geom::box_mesh({wall_x, -50, 38}, {wall_x + 1.0, 50, 52}, "the wall"));
    scene.build(false);
    cspace::Options co;
    co.check_collision = true;
    co.collision.clearance_mm = 0.5;
    const cspace::Space space(k, &scene, &tool, co, nullptr);
    gate::Options opt = gate::options_for(m, 0, 0, 0);
    opt.make_collision = collision_against(space);
    return gate::check(p.text, "line.ngc", prog, m, *k, opt, &p.summary.cl_line_of_nc_line);
  };
  const auto coarse = gate_with_wall(0.2, 200.0), fine = gate_with_wall(0.1, 200.0);
  EXPECT_TRUE(coarse.ok) << coarse.message;
  EXPECT_TRUE(fine.ok) << fine.message;
  EXPECT_GT(fine.blocks, coarse.blocks + 190);
  EXPECT_LE(fine.collision_checks, coarse.collision_checks + 5) << coarse.collision_checks;
  // The shank (r 5, clearance 0.5) meets the wall's face at x 7 with the tip at x 1.5: between CL points 107 and 108
  // (x 1.4, 1.6; CL lines 112 and 113). The block named holds a pose at most a sample step (0.5 mm) further, x 2.0:
  // it ends by CL point 110 (line 115).
  const auto hit = gate_with_wall(0.2, 7.0);
  ASSERT_FALSE(hit.ok);
  ASSERT_EQ(hit.violations.front().kind, gate::Violation::Kind::Collision) << hit.message;
  EXPECT_NE(hit.message.find("hits wall"), std::string::npos) << hit.message;
  const int cl_line = hit.violations.front().cl_line;
  EXPECT_GE(cl_line, 113) << hit.message;
  EXPECT_LE(cl_line, 115) << hit.message;
}

TEST(PostFlips, SameInputGivesByteIdenticalOutput) {
  // Determinism: no hidden state (thread-local IK warm starts, caches) may change the program.
  const auto m = load_machine("head-head-ac");
  const auto prog = cl::read_file(test::source_path("examples/nx-haas-umc750/variable_axis.cls"));
  const auto k = m.make_kinematics(post::tool_length_for(m, 0));
  const Posted a = post_program(prog, m, *k);
  const auto mx = load_machine("xmini");
  const auto kx = mx.make_kinematics(post::tool_length_for(mx, 0));
  (void)post_program(cl::read_file(test::source_path("examples/xmini/seed000_x_cut.cls")), mx, *kx);  // other state
  const Posted b = post_program(prog, m, *k);
  EXPECT_EQ(a.text, b.text);
}

// --- CL arcs written as G2/G3 (issue 10, part 3) ---------------------------------------------------------------

namespace {

/// Posts `prog`, checks that the gate passes, that rs274 accepts the program and moves to our end points, and that
/// every rs274 ARC_FEED has the centre and direction our reader took from the same block.
std::string post_arcs_checked(const cl::Program& prog, const std::string& machine_name, std::size_t want_arcs) {
  const auto m = load_machine(machine_name);
  const auto k = m.make_kinematics(post::tool_length_for(m, 0));
  const Posted p = post_program(prog, m, *k);
  EXPECT_EQ(p.summary.arc_blocks, want_arcs);
  const auto s =
      gate::check(p.text, "arcs.ngc", prog, m, *k, gate::options_for(m, 0, 0, 0), &p.summary.cl_line_of_nc_line);
  EXPECT_TRUE(s.ok) << s.message;
  test::expect_rs274_agrees(p.text, m, "arcs_" + machine_name);
  const nc::Program ours = nc::read_text(p.text, "arcs.ngc", report::axis_letters(m));
  std::vector<const nc::Block*> arcs;
  for (const auto& b : ours.blocks)
    if (b.arc) arcs.push_back(&b);
  const auto& theirs = test::arcs_out();
  EXPECT_EQ(arcs.size(), want_arcs);
  EXPECT_EQ(theirs.size(), arcs.size());
  for (std::size_t i = 0; i < std::min(theirs.size(), arcs.size()); ++i) {
    EXPECT_EQ(theirs[i].plane, arcs[i]->arc->plane);
    EXPECT_NEAR(theirs[i].centre_first, arcs[i]->arc->centre_u, test::kRs274HalfUnit);
    EXPECT_NEAR(theirs[i].centre_second, arcs[i]->arc->centre_v, test::kRs274HalfUnit);
    EXPECT_EQ(theirs[i].turn > 0, arcs[i]->arc->sweep_rad > 0) << "arc " << i;
  }
  return p.text;
}

}  // namespace

TEST(GateArcs, NxZigzagCirclesBecomeArcsThatPassTheGateAndRs274) {
  // NX's own post printed 34 G02/G03 here (the 35th CIRCLE, 0.8 degrees, as a G01); the direction agrees with it.
  const cl::Program prog = cl::read_file(test::source_path("examples/nx-haas-umc750/zigzag_smoothed.cls"));
  const std::string text = post_arcs_checked(prog, "haas-umc750", 35);
  EXPECT_NE(text.find("G3 X-0.0559 Y154.9997 I2.5000 J0.0000"), std::string::npos);  // NX: G03 ... I.0984 J0.0 (inch)
}

TEST(GateArcs, SyntheticHelixAndZxArcOnTheTrunnion) {
  // A CCW helix about +Z (NX's CIRCLE runs clockwise about its i,j,k), then a half circle in the ZX plane.
  const std::string cl =
      "PARTNO HELIX\nUNITS/MM\nMULTAX/ON\nCUTTER/6,3\nLOADTL/1\nFEDRAT/MMPM,800\nRAPID\nGOTO/10,0,5,0,0,1\n"
      "GOTO/10,0,0,0,0,1\nCIRCLE/0,0,0,0,0,-1,10,0.01\nGOTO/0,10,-2,0,0,1\nGOTO/0,10,-3\n"
      "CIRCLE/5,10,-3,0,1,0,5,0.01\nGOTO/10,10,-3\nGOTO/10,10,5\nFINI\n";
  const cl::Program prog = cl::read_text(cl, "helix.cls");
  ASSERT_EQ(prog.arcs.size(), 2u);
  const std::string text = post_arcs_checked(prog, "trunnion-ac", 2);
  EXPECT_NE(text.find("G18"), std::string::npos);
}

TEST(GateArcs, RefusesAnArcWhoseCentreMovedAndNamesTheBlock) {
  const cl::Program prog = cl::read_file(test::source_path("examples/nx-haas-umc750/zigzag_smoothed.cls"));
  const auto m = load_machine("haas-umc750");
  const auto k = m.make_kinematics(post::tool_length_for(m, 0));
  const Posted p = post_program(prog, m, *k);
  std::vector<std::string> lines;
  std::istringstream in(p.text);
  for (std::string l; std::getline(in, l);) lines.push_back(l);
  const int n = find_line(lines, "G3 ");
  ASSERT_GT(n, 0);
  std::string& l = lines[static_cast<size_t>(n - 1)];
  const auto at = l.find(" I2.5000");
  ASSERT_NE(at, std::string::npos) << l;
  l.replace(at, 8, " I2.6000");  // the centre 0.1 mm along X
  const auto s =
      gate::check(join(lines), "t.ngc", prog, m, *k, gate::options_for(m, 0, 0, 0), &p.summary.cl_line_of_nc_line);
  EXPECT_FALSE(s.ok);
  EXPECT_TRUE(has_kind(s, gate::Violation::Kind::Deviation, n)) << s.message;
}

// The NC file never replaces the CL file it came from (`-o PART.cls` by mistake).
TEST(Gate, TheOutputNeverOverwritesItsClInput) {
  namespace fs = std::filesystem;
  const fs::path cl_path = fs::temp_directory_path() / ("cscam_gate_self_" + std::to_string(::getpid()) + ".cls");
  const std::string cl_text = "UNITS/MM\nFEDRAT/MMPM,500\nGOTO/0,0,10\nGOTO/10,0,10\n";
  std::ofstream(cl_path) << cl_text;
  const cl::Program prog = cl::read_file(cl_path.string());
  const auto m = machine::load(test::source_path("machines/trunnion-ac.yaml"));
  const auto k = m.kinematics();
  std::ostringstream os;
  post::Summary sum;
  post::write_nc(os, prog, m, *k, post::conventional_axes(prog, m, *k), post::Options{}, sum);
  try {
    (void)gate::write_checked(cl_path.string(), os.str(), prog, m, *k, gate::options_for(m, 0, 0, 0));
    FAIL() << "expected an error";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("would overwrite its CL input"), std::string::npos) << e.what();
  }
  std::ifstream in(cl_path);
  EXPECT_EQ(std::string(std::istreambuf_iterator<char>(in), {}), cl_text);  // untouched
  fs::remove(cl_path);
}

// A rapid move must touch nothing, its cutting end included: a G0 that drags the ball 3 mm deep across a block was
// passed, because the cutting end was left out of every check as it is for feed moves. The same path as a feed
// passes (the cutting end is in the material by design), and a rapid that ends on the block (where a cut starts)
// passes too.
TEST(Gate, ARapidMayNotCutWithItsCuttingEnd) {
  const auto m = load_machine("trunnion-ac");
  const auto k = m.make_kinematics(post::tool_length_for(m, 0));
  const auto tool = geom::ToolShape::from_cutter(10, 5, 30);
  geom::Scene scene;
  scene.add("block", geom::ObstacleRole::Part, geom::box_mesh({-30, -30, 0}, {30, 30, 20}, "the block"));
  scene.build(false);
  cspace::Options co;
  co.check_collision = true;
  const cspace::Space space(k, &scene, &tool, co, nullptr);
  gate::Options opt = gate::options_for(m, 0, 0, 0);
  opt.make_collision = collision_against(space);
  auto run = [&](const std::string& motion) {
    // Across the block with the tip 3 mm below its top (z 17), from clear air on one side to clear air on the other.
    const std::string text =
        "UNITS/MM\nMULTAX/ON\nCUTTER/10,5\nFEDRAT/MMPM,1000\nGOTO/-60,0,60,0,0,1\nGOTO/-60,0,17,0,0,1\n" + motion +
        "GOTO/60,0,17,0,0,1\nGOTO/60,0,60,0,0,1\n";
    const cl::Program prog = cl::read_text(text, "across.cls");
    const Posted p = post_program(prog, m, *k);
    return gate::check(p.text, "across.ngc", prog, m, *k, opt, &p.summary.cl_line_of_nc_line);
  };
  const auto rapid = run("RAPID\n");
  ASSERT_FALSE(rapid.ok);
  EXPECT_NE(rapid.message.find("hits block"), std::string::npos) << rapid.message;
  const auto feed = run("");
  EXPECT_TRUE(feed.ok) << feed.message;
  // A rapid down onto the top face (the ball tangent to it at the end) passes.
  const cl::Program onto = cl::read_text(
      "UNITS/MM\nMULTAX/ON\nCUTTER/10,5\nFEDRAT/MMPM,1000\nGOTO/0,0,60,0,0,1\nRAPID\nGOTO/0,0,20,0,0,1\n"
      "GOTO/10,0,20,0,0,1\n",
      "onto.cls");
  const Posted p = post_program(onto, m, *k);
  const auto down = gate::check(p.text, "onto.ngc", onto, m, *k, opt, &p.summary.cl_line_of_nc_line);
  EXPECT_TRUE(down.ok) << down.message;
}

namespace {

/// Independent of the gate's search: the worst over the samples of every feed block of the smallest angle (deg)
/// between the sample's tool axis and the axis of a CL pose whose tip lies within `tip_tol_mm` of the sample's tip.
/// Every CL segment is tried (no window, no cursor), each sampled finely with its axis interpolated on the great
/// circle. +inf where a sample has no CL pose within the tip tolerance. Blocks that move the tip only along the tool
/// axis (the post's retract and plunge, off the path by design) are left out.
double worst_axis_against_any_cl_pose(const std::string& nc_text, const cl::Program& prog, const machine::Machine& m,
                                      const kin::Kinematics& k, double tip_tol_mm) {
  const nc::Program p = nc::read_text(nc_text, "t.ngc", report::axis_letters(m));
  struct Pose {
    Eigen::Vector3d tip, axis;
  };
  std::vector<Pose> cl_poses;
  constexpr int kClSteps = 400;
  for (std::size_t i = 1; i < prog.moves.size(); ++i) {
    const auto &a = prog.moves[i - 1], &b = prog.moves[i];
    if (b.kind != cl::MotionKind::Feed) continue;
    const Eigen::Vector3d ua = a.axis_in_part.normalized(), ub = b.axis_in_part.normalized();
    const double th = std::acos(std::clamp(ua.dot(ub), -1.0, 1.0));
    for (int s = 0; s <= kClSteps; ++s) {
      const double t = static_cast<double>(s) / kClSteps;
      const Eigen::Vector3d u =
          th < 1e-12 ? ua : ((std::sin((1 - t) * th) * ua + std::sin(t * th) * ub) / std::sin(th)).normalized();
      cl_poses.push_back({a.tip_in_part_mm + t * (b.tip_in_part_mm - a.tip_in_part_mm), u});
    }
  }
  constexpr int kNcSteps = 50;
  double worst = 0.0;
  for (std::size_t i = 1; i < p.blocks.size(); ++i) {
    if (p.blocks[i].motion != nc::Motion::Linear) continue;
    kin::Axes qa, qb;
    for (int j = 0; j < 5; ++j) {
      qa[j] = p.blocks[i - 1].axes[static_cast<std::size_t>(j)];
      qb[j] = p.blocks[i].axes[static_cast<std::size_t>(j)];
    }
    const kin::Posed xa = k.forward(qa), xb = k.forward(qb);
    if ((xb.tip_mm - xa.tip_mm).norm() > tip_tol_mm &&
        (xb.tip_mm - xa.tip_mm).cross(xa.axis.normalized()).norm() <= tip_tol_mm)
      continue;
    for (int s = 0; s <= kNcSteps; ++s) {
      const kin::Posed x = k.forward(qa + (static_cast<double>(s) / kNcSteps) * (qb - qa));
      double best = std::numeric_limits<double>::infinity();
      for (const Pose& c : cl_poses)
        if ((c.tip - x.tip_mm).norm() <= tip_tol_mm)
          best = std::min(best, rad2deg(std::acos(std::clamp(c.axis.dot(x.axis.normalized()), -1.0, 1.0))));
      worst = std::max(worst, best);
    }
  }
  return worst;
}

}  // namespace

TEST(Gate, AWalkThatCrossesItselfLaterIsJudgedWhereverItsTipCouldBe) {
  // A random walk (generate_cl.py seed 5) doubles back, and 20 CL points later runs through the same spot with the
  // axis 2.5 deg away. A sample near that spot was placed by its tip on the later segment, and its axis was only
  // tried on the three segments either side of it: the gate refused a good program ("tool axis leaves the CL
  // orientation by 2.4941 deg"). A sample's axis is now tried over the whole window its tip could be placed in.
  // The oracle: every CL pose whose tip is within the tolerance, searched without a window. The control: one block
  // with A turned by 1 deg is still refused.
  const auto m = load_machine("head-head-ac");
  const auto prog = cl::read_file(test::source_path("tests/data/crossing_walk.cls"));
  const auto k = m.make_kinematics(post::tool_length_for(m, 0));
  const Posted p = post_program(prog, m, *k);
  const auto opt = gate::options_for(m, 0, 0, 0);
  const auto s = gate::check(p.text, "walk.ngc", prog, m, *k, opt, &p.summary.cl_line_of_nc_line);
  EXPECT_TRUE(s.ok) << s.message;
  EXPECT_LE(worst_axis_against_any_cl_pose(p.text, prog, m, *k, opt.tip_tolerance_mm), opt.axis_tolerance_deg);

  // The block into the spot the walk crosses again later (CL line 13, the fifth point), turned by 1 deg in A.
  auto lines = lines_of(p.text);
  const auto& cl_of = p.summary.cl_line_of_nc_line;
  int nc_line = 0;  // 1-based
  for (std::size_t j = 0; j < cl_of.size(); ++j)
    if (cl_of[j] == 13 && lines[j].rfind("G1 ", 0) == 0) nc_line = static_cast<int>(j) + 1;
  ASSERT_GT(nc_line, 0);
  std::string& line = lines[static_cast<std::size_t>(nc_line - 1)];
  std::smatch a;
  ASSERT_TRUE(std::regex_search(line, a, std::regex("A(-?[0-9.]+)"))) << line;
  line = std::regex_replace(line, std::regex("A-?[0-9.]+"), fmt::format("A{:.4f}", std::stod(a[1].str()) + 1.0));
  const std::string tampered = join(lines);
  EXPECT_GT(worst_axis_against_any_cl_pose(tampered, prog, m, *k, opt.tip_tolerance_mm), opt.axis_tolerance_deg);
  const auto bad = gate::check(tampered, "walk.ngc", prog, m, *k, opt, &p.summary.cl_line_of_nc_line);
  EXPECT_FALSE(bad.ok);
  EXPECT_TRUE(has_kind(bad, gate::Violation::Kind::Deviation, 0)) << bad.message;
}

// A state change the read-back does not model moves the machine where the gate does not look: a coordinate shift,
// rotation, scaling or mirror, offset data, a new work offset, a cancelled or changed length offset, a tool change
// without one. Each, put in front of a cut (as an INSERT/ would), is refused at its own line, and verify fails on it;
// the same words that change nothing (a cancel, the offset in force, the same H, a tool change with its G43 and the
// spindle started again) pass.
TEST(Gate, AStateChangeTheReadBackDoesNotModelIsRefusedAtItsLine) {
  Fixture f;
  const auto lines = lines_of(f.posted.text);
  const int cut = find_line(lines, "G1", 20);
  ASSERT_GT(cut, 0);
  auto with = [&](const std::vector<std::string>& inserted) {
    auto l = lines;
    l.insert(l.begin() + (cut - 1), inserted.begin(), inserted.end());
    return join(l);
  };
  for (const std::string w : {"G92 X10.", "G92.3", "G52 X5.", "G68 X0 Y0 R30.", "G51 X0 Y0 P2", "G51.1 X0",
                              "G10 L2 P1 X5.", "G55", "G54.1 P3", "G49", "G43 H7", "T5 M6"}) {
    const gate::Summary s = f.run(with({w}));
    EXPECT_FALSE(s.ok) << w;
    EXPECT_TRUE(has_kind(s, gate::Violation::Kind::Unreadable, cut)) << w << ": " << s.message;
    const nc::Program p = nc::read_text(with({w}), "t.ngc", report::axis_letters(f.m));
    const report::VerifyResult v = report::verify(p, f.prog, *f.k, report::verify_options_for(f.m));
    EXPECT_FALSE(v.ok) << w;
    EXPECT_NE(v.message.find(fmt::format("t.ngc:{}:", cut)), std::string::npos) << w << ": " << v.message;
  }
  for (const std::vector<std::string> w :
       {std::vector<std::string>{"G92.1"}, {"G54"}, {"G43 H1"}, {"G69"}, {"T5 M6", "G43 H5", "M3"}, {"G4 P1."}})
    EXPECT_TRUE(f.run(with(w)).ok) << w.front() << ": " << f.run(with(w)).message;
  // After the last move it changes nothing the gate checks.
  auto l = lines;
  l.insert(l.end() - 2, "G92 X0 Y0 Z0");
  EXPECT_TRUE(f.run(join(l)).ok) << f.run(join(l)).message;
}

// A feed move with the spindle stopped, where the CL cuts with it running, is refused at that move (an M5 from an
// INSERT, in every dialect); the same M5 followed by an M3 passes, and so does a feed move the CL itself makes with
// the spindle off (its SPINDL/OFF: the post writes M5 and the CL means it).
TEST(Gate, AFeedMoveWithTheSpindleStoppedWhereTheClCutsIsRefused) {
  const auto m = load_machine("trunnion-ac");
  const auto k = m.kinematics();
  const std::string head =
      "UNITS/MM\nMULTAX\nCUTTER/6\nLOADTL/1\nSPINDL/8000,CLW\nFEDRAT/MMPM,1000\nRAPID\n"
      "GOTO/0,0,20,0,0,1\nGOTO/0,0,10,0,0,1\n";
  for (const char* dialect : {"linuxcnc", "fanuc", "siemens", "heidenhain"}) {
    SCOPED_TRACE(dialect);
    auto run = [&](const std::string& middle) {
      const cl::Program prog = cl::read_text(head + middle + "GOTO/20,0,10,0,0,1\nGOTO/20,20,10,0,0,1\n", "s.cls");
      const auto [text, sum] = conventionally_posted(prog, m, *k, dialect);
      return gate::check(text, "s.nc", prog, m, *k, gate::options_for(m, 0, 0, 0), &sum.cl_line_of_nc_line);
    };
    const gate::Summary stopped = run("INSERT/M5\n");
    EXPECT_FALSE(stopped.ok);
    ASSERT_FALSE(stopped.violations.empty());
    EXPECT_NE(stopped.violations.front().message.find("spindle stopped"), std::string::npos) << stopped.message;
    EXPECT_EQ(stopped.violations.front().cl_line, 11) << stopped.message;  // the GOTO after the INSERT
    EXPECT_TRUE(run("INSERT/M5\nINSERT/M3\n").ok) << run("INSERT/M5\nINSERT/M3\n").message;
    EXPECT_TRUE(run("SPINDL/OFF\n").ok) << run("SPINDL/OFF\n").message;
  }
}

// A tool change stops the spindle (M6; LinuxCNC's interpreter reports STOP_SPINDLE_TURNING at CHANGE_TOOL). Where the
// CL switched it on before the change and not again after it, the post restarts it as it was (it cut with the second
// tool with the spindle stopped, and the gate passed that); a program without that restart is refused at the cut.
TEST(Gate, TheSpindleStoppedByAToolChangeIsRestartedAndRequired) {
  const auto m = load_machine("trunnion-ac");
  const auto k = m.kinematics();
  const cl::Program prog = cl::read_text(
      "UNITS/MM\nMULTAX\nCUTTER/6\nLOADTL/1\nSPINDL/8000,CLW\nFEDRAT/MMPM,1000\nRAPID\nGOTO/0,0,20,0,0,1\n"
      "GOTO/0,0,10,0,0,1\nGOTO/20,0,10,0,0,1\nRAPID\nGOTO/20,0,40,0,0,1\nCUTTER/8\nLOADTL/2\nRAPID\n"
      "GOTO/0,20,20,0,0,1\nGOTO/0,20,10,0,0,1\nGOTO/20,20,10,0,0,1\n",
      "t.cls");
  for (const char* dialect : {"linuxcnc", "fanuc", "haas", "siemens"}) {
    SCOPED_TRACE(dialect);
    auto [text, sum] = conventionally_posted(prog, m, *k, dialect);
    const auto change = text.find("M6\n");
    const auto second = text.find("M6\n", change + 1);
    ASSERT_NE(second, std::string::npos) << text;
    const auto restart = text.find("S8000 M3\n", second);
    ASSERT_NE(restart, std::string::npos) << "restarted after the second change\n" << text;
    const auto ok = gate::check(text, "t.nc", prog, m, *k, gate::options_for(m, 0, 0, 0), &sum.cl_line_of_nc_line);
    EXPECT_TRUE(ok.ok) << ok.message;
    text.replace(restart, 9, "(no M3)\n");  // the same line count: the NC -> CL line map still holds
    const auto stopped = gate::check(text, "t.nc", prog, m, *k, gate::options_for(m, 0, 0, 0), &sum.cl_line_of_nc_line);
    EXPECT_FALSE(stopped.ok) << text;
    EXPECT_NE(stopped.message.find("spindle stopped (the tool change (M6) at line"), std::string::npos)
        << stopped.message;
  }
}
