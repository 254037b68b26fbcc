// The cscam program as a user runs it: exit codes, messages, and no partial output on error.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>

#include "test_support.hpp"

namespace fs = std::filesystem;
using cscam::test::run_command;

namespace {

struct TempDir {
  fs::path path;
  TempDir() {
    path = fs::temp_directory_path() / ("cscam_cli_" + std::to_string(::getpid()) + "_" +
                                        ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::create_directories(path);
  }
  ~TempDir() { fs::remove_all(path); }
  std::string file(const std::string& name, const std::string& text = "") const {
    const auto p = (path / name).string();
    if (!text.empty()) std::ofstream(p) << text;
    return p;
  }
};

const std::string kCli = CSCAM_CLI;

}  // namespace

TEST(Cli, PostVerifyStatsOnRealNxFile) {
  TempDir d;
  const std::string cl = cscam::test::shared_path("data/real/nx-haas-umc750/variable_axis.cls");
  const std::string out = d.file("va.ngc");
  auto r = run_command(kCli + " post " + cl + " --machine haas-umc750 -o " + out);
  ASSERT_EQ(r.status, 0) << r.output;
  EXPECT_NE(r.output.find("wrote"), std::string::npos);
  r = run_command(kCli + " verify " + out + " --machine haas-umc750 --cl " + cl);
  EXPECT_EQ(r.status, 0) << r.output;
  EXPECT_NE(r.output.find("OK"), std::string::npos) << r.output;
  r = run_command(kCli + " stats " + out + " " +
                  cscam::test::shared_path("data/real/nx-haas-umc750/variable_axis.nx-post.nc") +
                  " --machine haas-umc750");
  EXPECT_EQ(r.status, 0) << r.output;
  EXPECT_NE(r.output.find("C reversals"), std::string::npos) << r.output;
}

TEST(Cli, VerifyFailsWhenTheProgramLeavesTheTolerance) {
  TempDir d;
  const std::string cl = d.file("swing.cls",
                                "UNITS/MM\nMULTAX\nFEDRAT/MMPM,1000\nRAPID\nGOTO/100,50,20,0,0,1\n"
                                "GOTO/110,50,20,0.5,0,0.8660254\n");
  const std::string out = d.file("swing.ngc");
  auto r = run_command(kCli + " post " + cl + " --machine trunnion-ac --no-linearise -o " + out);
  ASSERT_EQ(r.status, 0) << r.output;
  r = run_command(kCli + " verify " + out + " --machine trunnion-ac --cl " + cl);
  EXPECT_EQ(r.status, 1) << r.output;
  EXPECT_NE(r.output.find("FAILED"), std::string::npos) << r.output;
}

TEST(Cli, BadClInputExitsNonZeroWithLocationAndWritesNothing) {
  TempDir d;
  const std::string cl = d.file("bad.cls", "UNITS/MM\nMULTAX\nGOTO/1,2,3,0,0,1\nGOTO/1,2,x3,0,0,1\n");
  const std::string out = d.file("bad.ngc");
  const auto r = run_command(kCli + " post " + cl + " --machine trunnion-ac -o " + out);
  EXPECT_EQ(r.status, 2) << r.output;
  EXPECT_NE(r.output.find("bad.cls:4:"), std::string::npos) << r.output;
  EXPECT_FALSE(fs::exists(out));
  for (const auto& e : fs::directory_iterator(d.path)) EXPECT_EQ(e.path().string().find(".tmp"), std::string::npos);
}

TEST(Cli, UnreachablePointKeepsThePreviousOutputIntact) {
  TempDir d;
  const std::string cl = d.file("far.cls", "UNITS/MM\nMULTAX\nGOTO/0,0,0,0,0,1\nGOTO/5000,0,0,0,0,1\n");
  const std::string out = d.file("far.ngc", "previous content\n");
  const auto r = run_command(kCli + " post " + cl + " --machine trunnion-ac -o " + out);
  EXPECT_EQ(r.status, 2) << r.output;
  EXPECT_NE(r.output.find("far.cls:4"), std::string::npos) << r.output;
  std::ifstream in(out);
  std::string content((std::istreambuf_iterator<char>(in)), {});
  EXPECT_EQ(content, "previous content\n");
}

TEST(Cli, BadMachineAndBadArguments) {
  TempDir d;
  const std::string cl = d.file("ok.cls", "UNITS/MM\nGOTO/0,0,0\n");
  auto r = run_command(kCli + " post " + cl + " --machine no-such-machine");
  EXPECT_EQ(r.status, 2);
  EXPECT_NE(r.output.find("no-such-machine"), std::string::npos) << r.output;
  const std::string m = d.file("m.yaml", "name: x\naxes: 3\n");
  r = run_command(kCli + " post " + cl + " --machine " + m);
  EXPECT_EQ(r.status, 2);
  EXPECT_NE(r.output.find("m.yaml:2"), std::string::npos) << r.output;
  r = run_command(kCli + " post " + cl + " --machine trunnion-ac --dialect klingon -o " + d.file("o.ngc"));
  EXPECT_EQ(r.status, 2);
  EXPECT_NE(r.output.find("klingon"), std::string::npos) << r.output;
  r = run_command(kCli + " post");
  EXPECT_NE(r.status, 0);
}

TEST(Cli, PlanAndCompareOnTheSeedGroove) {
  TempDir d;
  const std::string cl = cscam::test::source_path("examples/groove/groove.cls");
  const std::string stl = cscam::test::source_path("examples/groove/groove.stl");
  const std::string out = d.file("g.ngc"), json = d.file("g.json");
  auto r = run_command(kCli + " compare " + cl + " --machine trunnion-ac --part " + stl + " --cone 25 -o " + out +
                       " --json-out " + json + " --svg " + (d.path / "svg").string());
  ASSERT_EQ(r.status, 0) << r.output;
  EXPECT_NE(r.output.find("fixed 2 axes + simultaneous 3 axes"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("the conventional program collides"), std::string::npos) << r.output;
  EXPECT_TRUE(fs::exists(d.path / "svg" / "segment1_cspace.svg"));
  std::ifstream j(json);
  std::string js((std::istreambuf_iterator<char>(j)), {});
  EXPECT_NE(js.find("\"tiers\": [1]"), std::string::npos) << js;
  r = run_command(kCli + " verify " + out + " --machine trunnion-ac --cl " + cl + " --cone 25");
  EXPECT_EQ(r.status, 0) << r.output;
}

TEST(Cli, PlanRejectsAnOpenMeshNamingTheFile) {
  TempDir d;
  const std::string stl = d.file("open.stl",
                                 "solid t\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 0\n"
                                 "endloop\nendfacet\nendsolid t\n");
  const std::string cl = d.file("p.cls", "UNITS/MM\nMULTAX\nCUTTER/6,3\nGOTO/0,0,0,0,0,1\nGOTO/1,0,0,0,0,1\n");
  const std::string out = d.file("p.ngc");
  const auto r = run_command(kCli + " plan " + cl + " --machine trunnion-ac --part " + stl + " -o " + out);
  EXPECT_EQ(r.status, 2) << r.output;
  EXPECT_NE(r.output.find("open.stl"), std::string::npos) << r.output;
  EXPECT_FALSE(fs::exists(out));
}

TEST(Cli, PlanWithNoFeasibleCellWritesNothing) {
  TempDir d;
  const std::string cl = d.file("u.cls", "UNITS/MM\nMULTAX\nGOTO/0,0,0,0,0,1\nGOTO/450,0,0,0,0.9396926,0.3420201\n");
  const std::string out = d.file("u.ngc");
  const auto r = run_command(kCli + " plan " + cl + " --machine trunnion-ac -o " + out);
  EXPECT_EQ(r.status, 2) << r.output;
  EXPECT_NE(r.output.find("u.cls:4"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("nearest feasible cell"), std::string::npos) << r.output;
  EXPECT_FALSE(fs::exists(out));
}
