// Core: error locations, angle helpers, and atomic file writing.
#include <gtest/gtest.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>

#include "cscam/core/atomic_file.hpp"
#include "cscam/core/error.hpp"
#include "cscam/core/units.hpp"

using namespace cscam;
namespace fs = std::filesystem;

TEST(Core, ErrorsCarryFileLineColumn) {
  const InputError e(SourceLoc{"a.cls", 12, 7}, "bad number");
  EXPECT_STREQ(e.what(), "a.cls:12:7: bad number");
  EXPECT_EQ(e.message(), "bad number");
  EXPECT_STREQ(InputError(SourceLoc{"a.cls", 3, 0}, "x").what(), "a.cls:3: x");
  EXPECT_STREQ(InputError("plain").what(), "plain");
}

TEST(Core, WrapPi) {
  EXPECT_NEAR(wrap_pi(3 * kPi), kPi, 1e-12);
  EXPECT_NEAR(wrap_pi(-kPi), kPi, 1e-12);
  EXPECT_NEAR(wrap_pi(0.5), 0.5, 1e-15);
  EXPECT_NEAR(rad2deg(deg2rad(123.25)), 123.25, 1e-12);
}

TEST(Core, AtomicWriteLeavesNothingOnError) {
  const fs::path dir = fs::temp_directory_path() / ("cscam_core_test_" + std::to_string(::getpid()));
  fs::create_directories(dir);
  const std::string target = (dir / "out.txt").string();
  std::ofstream(target) << "old";
  EXPECT_THROW(write_file_atomically(target,
                                     [](std::ostream& os) {
                                       os << "partial";
                                       throw InputError("boom");
                                     }),
               InputError);
  std::ifstream in(target);
  std::string s((std::istreambuf_iterator<char>(in)), {});
  EXPECT_EQ(s, "old");
  size_t n = 0;
  for ([[maybe_unused]] const auto& e : fs::directory_iterator(dir)) ++n;
  EXPECT_EQ(n, 1u);
  write_file_atomically(target, [](std::ostream& os) { os << "new"; });
  std::ifstream in2(target);
  std::string s2((std::istreambuf_iterator<char>(in2)), {});
  EXPECT_EQ(s2, "new");
  EXPECT_THROW(write_file_atomically("/nonexistent-dir/x.txt", [](std::ostream&) {}), InputError);
  fs::remove_all(dir);
}

TEST(Core, WholeDegreesDoNotTruncate) {
  EXPECT_NEAR(deg2rad(5), 5.0 * kPi / 180.0, 1e-15);
  EXPECT_NEAR(rad2deg(1), 180.0 / kPi, 1e-12);
}
