// The NC reader: modal words, units, inverse time, NX's listing header, and errors with file:line:column.
#include <gtest/gtest.h>

#include "cscam/core/error.hpp"
#include "cscam/core/units.hpp"
#include "cscam/nc/reader.hpp"
#include "test_support.hpp"

using namespace cscam;

namespace {
nc::AxisLetters xyzbc() {
  nc::AxisLetters l;
  l.letter = {'X', 'Y', 'Z', 'B', 'C'};
  l.rotary = {false, false, false, true, true};
  return l;
}
}  // namespace

TEST(NcReader, ModalAxesUnitsAndFeedModes) {
  const auto p = nc::read_text(
      "%\n(cscam tool_length_mm=42.5000 tolerance_mm=0.01)\nG21 G90\nG0 X1 Y2 Z3 B4 C5\nG93 G1 X2 B5 F120.5\n"
      "G94 G1 Y-.5 F300\nG20\nG1 X1.\n;comment X9\nG91 G1 X1\nM2\n%\n",
      "t.ngc", xyzbc());
  ASSERT_EQ(p.blocks.size(), 5u);
  ASSERT_TRUE(p.tool_length_mm.has_value());
  EXPECT_DOUBLE_EQ(*p.tool_length_mm, 42.5);
  EXPECT_EQ(p.blocks[0].motion, nc::Motion::Rapid);
  EXPECT_DOUBLE_EQ(p.blocks[1].axes[0], 2.0);
  EXPECT_DOUBLE_EQ(p.blocks[1].axes[1], 2.0);  // modal
  EXPECT_NEAR(p.blocks[1].axes[3], deg2rad(5.0), 1e-15);
  EXPECT_TRUE(p.blocks[1].inverse_time);
  EXPECT_DOUBLE_EQ(p.blocks[1].feed, 120.5);
  EXPECT_FALSE(p.blocks[2].inverse_time);
  EXPECT_DOUBLE_EQ(p.blocks[2].axes[1], -0.5);
  EXPECT_DOUBLE_EQ(p.blocks[3].axes[0], 25.4);  // G20
  EXPECT_DOUBLE_EQ(p.blocks[4].axes[0], 50.8);  // G91 incremental
  EXPECT_EQ(p.blocks[4].line, 10);
}

TEST(NcReader, ReadsNxHaasOutput) {
  const auto p = nc::read_file(test::source_path("examples/nx-haas-umc750/variable_axis.nx-post.nc"), xyzbc());
  EXPECT_TRUE(p.tcp);  // G234
  ASSERT_GT(p.blocks.size(), 300u);
  // N70 G00 B-22.201 C1.05 is the first positioning block (G28 blocks are not positions).
  EXPECT_NEAR(rad2deg(p.blocks[0].axes[3]), -22.201, 1e-12);
  EXPECT_NEAR(rad2deg(p.blocks[0].axes[4]), 1.05, 1e-12);
  const auto z = nc::read_file(test::source_path("examples/nx-haas-umc750/zigzag_smoothed.nx-post.nc"), xyzbc());
  EXPECT_GT(z.blocks.size(), 50u);  // the listing header before '%' is skipped
}

TEST(NcReader, MalformedNumberNamesLineAndColumn) {
  try {
    nc::read_text("G1 X1\nG1 X1.2.3\n", "bad.ngc", xyzbc());
    FAIL();
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("bad.ngc:2:5"), std::string::npos) << e.what();
  }
  EXPECT_THROW(nc::read_text("G1 X#1\n", "bad.ngc", xyzbc()), InputError);
  EXPECT_THROW(nc::read_file("/nonexistent.ngc", xyzbc()), InputError);
}

// The reader records which machine our header names and the axis words the given letters do not cover, so that
// stats and verify can refuse another machine's program instead of silently ignoring its words.
TEST(NcReader, HeaderMachineAndForeignAxisWords) {
  const auto p = nc::read_text(
      "%\n(CSCAM)\n(cscam post: machine trunnion-ac dialect linuxcnc strategy conventional)\nG21 G90\n"
      "G0 X1 Y2 Z3 A10 C5\nG1 X2 A11 I3 J4 F100\nG1 U1\nM2\n%\n",
      "t.ngc", xyzbc());
  ASSERT_TRUE(p.header_machine.has_value());
  EXPECT_EQ(*p.header_machine, "trunnion-ac");
  EXPECT_EQ(p.header_line, 3);
  ASSERT_EQ(p.foreign_axis_words.size(), 2u);  // each letter once, where it first appears; I J are not axes
  EXPECT_EQ(p.foreign_axis_words[0].letter, 'A');
  EXPECT_EQ(p.foreign_axis_words[0].line, 5);
  EXPECT_EQ(p.foreign_axis_words[0].column, 13);
  EXPECT_EQ(p.foreign_axis_words[1].letter, 'U');
  EXPECT_EQ(p.foreign_axis_words[1].line, 7);
  // NX's own Haas program: no header of ours, and every axis word is one of X Y Z B C.
  const auto nx = nc::read_file(test::source_path("examples/nx-haas-umc750/variable_axis.nx-post.nc"), xyzbc());
  EXPECT_FALSE(nx.header_machine.has_value());
  EXPECT_TRUE(nx.foreign_axis_words.empty());
}
