#pragma once
// LinuxCNC's own interpreter as the oracle for our G-code: run `rs274 -g` and compare every move it makes
// with the axis values we meant.
#include <gtest/gtest.h>
#include <unistd.h>

#include <array>
#include <filesystem>
#include <fstream>
#include <regex>
#include <sstream>
#include <string>
#include <vector>

#include "cscam/core/units.hpp"
#include "cscam/machine/machine.hpp"
#include "cscam/nc/reader.hpp"
#include "cscam/report/letters.hpp"
#include "test_support.hpp"

namespace cscam::test {

/// rs274 prints 4 decimals: agreement to half a unit in the last place.
inline constexpr double kRs274HalfUnit = 0.5e-4 + 1e-9;

/// The ARC_FEEDs of the last rs274_moves run: plane, centre (first, second axis of the plane), turn (+1 CCW, -1 CW).
struct Rs274Arc {
  int plane;
  double centre_first, centre_second, turn;
};
inline std::vector<Rs274Arc>& arcs_out() {
  static std::vector<Rs274Arc> a;
  return a;
}

/// Runs rs274 -g on the text and returns every STRAIGHT_FEED/TRAVERSE as (x y z a b c), and its output.
/// `ini_dir`, when given, is a folder of the repository (under tests/data) with an `rs274-*.ini` and what it
/// names: it is copied beside the program and passed with -i (e.g. the remaps of LinuxCNC's M428/M429).
inline std::vector<std::array<double, 6>> rs274_moves(const std::string& text, const std::string& tag, std::string& log,
                                                      const std::string& ini_dir = "") {
  namespace fs = std::filesystem;
  // Each run in its own directory, and one rs274 at a time machine-wide: the standalone interpreter keeps
  // state beside it and crashed (bus error) when two test processes ran it at once under ctest -j.
  static int counter = 0;
  const fs::path dir =
      fs::temp_directory_path() / ("cscam_rs274_" + std::to_string(::getpid()) + "_" + std::to_string(counter++));
  fs::create_directories(dir);
  const std::string path = (dir / (tag + ".ngc")).string();
  std::ofstream(path) << text;
  const std::string lock = (fs::temp_directory_path() / "cscam_rs274.lock").string();
  std::string ini_arg;
  if (!ini_dir.empty()) {
    fs::copy(source_path(ini_dir), dir, fs::copy_options::recursive);
    for (const auto& e : fs::directory_iterator(dir))
      if (e.path().extension() == ".ini") ini_arg = "-i '" + e.path().filename().string() + "' ";
  }
  const auto r =
      run_command("cd '" + dir.string() + "' && flock '" + lock + "' rs274 " + ini_arg + "-g '" + path + "'");
  log = r.output;
  arcs_out().clear();
  std::vector<std::array<double, 6>> moves;
  std::istringstream in(r.output);
  std::string line;
  const std::regex re(R"(STRAIGHT_(FEED|TRAVERSE)\(([^)]*)\))");
  const std::regex arc_re(R"(ARC_FEED\(([^)]*)\))");
  std::smatch m;
  int plane = 17;
  while (std::getline(in, line)) {
    if (line.find("CANON_PLANE_XY") != std::string::npos) plane = 17;
    if (line.find("CANON_PLANE_XZ") != std::string::npos) plane = 18;
    if (line.find("CANON_PLANE_YZ") != std::string::npos) plane = 19;
    if (std::regex_search(line, m, arc_re)) {
      // ARC_FEED(first end, second end, first centre, second centre, turn, axis end, a, b, c): the plane's first
      // and second axes are (X, Y) for G17, (Z, X) for G18, (Y, Z) for G19.
      std::array<double, 9> f{};
      std::istringstream vs(m[1].str());
      for (auto& x : f) {
        vs >> x;
        vs.ignore(2, ',');
      }
      const std::array<int, 3> uvw = plane == 17   ? std::array<int, 3>{0, 1, 2}
                                     : plane == 18 ? std::array<int, 3>{2, 0, 1}
                                                   : std::array<int, 3>{1, 2, 0};
      std::array<double, 6> v{};
      v[static_cast<size_t>(uvw[0])] = f[0];
      v[static_cast<size_t>(uvw[1])] = f[1];
      v[static_cast<size_t>(uvw[2])] = f[5];
      v[3] = f[6];
      v[4] = f[7];
      v[5] = f[8];
      moves.push_back(v);
      arcs_out().push_back({plane, f[2], f[3], f[4]});
      continue;
    }
    if (!std::regex_search(line, m, re)) continue;
    std::array<double, 6> v{};
    std::istringstream vs(m[2].str());
    for (auto& x : v) {
      vs >> x;
      vs.ignore(2, ',');
    }
    moves.push_back(v);
  }
  fs::remove_all(dir);
  return moves;
}

/// rs274 accepts the program and every move equals ours (read back by our NC reader), axis by axis: rs274
/// prints x y z a b c, and our five axes go to the slots of their letters.
inline void expect_rs274_agrees(const std::string& text, const machine::Machine& m, const std::string& tag,
                                const std::string& ini_dir = "", const nc::AxisLetters* letters = nullptr) {
  std::string log;
  const auto moves = rs274_moves(text, tag, log, ini_dir);
  EXPECT_EQ(log.find("error"), std::string::npos) << log.substr(0, 2000);
  EXPECT_EQ(log.find("Error"), std::string::npos) << log.substr(0, 2000);
  EXPECT_EQ(log.find("Unknown"), std::string::npos) << log.substr(0, 2000);
  const nc::Program ours = nc::read_text(text, tag, letters ? *letters : report::axis_letters(m));
  ASSERT_EQ(moves.size(), ours.blocks.size()) << "rs274 and our reader see different numbers of moves";
  ASSERT_GT(moves.size(), 1u);
  const std::string slots = "XYZABC";
  for (size_t i = 0; i < moves.size(); ++i)
    for (size_t a = 0; a < 5; ++a) {
      const size_t slot = slots.find(m.post.letters[a][0]);
      ASSERT_NE(slot, std::string::npos);
      const double ours_v = m.axes[a].rotary() ? rad2deg(ours.blocks[i].axes[a]) : ours.blocks[i].axes[a];
      ASSERT_NEAR(moves[i][slot], ours_v, kRs274HalfUnit) << tag << " move " << i << " axis " << m.axes[a].name;
    }
}

}  // namespace cscam::test
