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
  // In inch, F is inch/min, but a move of the rotaries alone has its F in deg/min (the gate read it as inch/min and
  // refused a TCP reorientation for an X 25.4 times too fast). Also in a TNC's inch program.
  const auto q =
      nc::read_text("G20 G90 G94\nG0 X0 Y0 Z0 B0 C0\nG1 X1. F10.\nG1 B10. F100.\nG1 X2. B20.\n", "i.ngc", xyzbc());
  ASSERT_EQ(q.blocks.size(), 4u);
  EXPECT_DOUBLE_EQ(q.blocks[1].feed, 254.0);
  EXPECT_DOUBLE_EQ(q.blocks[2].feed, 100.0);  // deg/min
  EXPECT_DOUBLE_EQ(q.blocks[3].feed, 2540.0);
  const auto h = nc::read_text(
      "0 BEGIN PGM P INCH\n1 L X+0 Y+0 Z+0 B+0 C+0 R0 FMAX\n2 L X+1 R0 F10\n3 L B+10 R0 F100\n", "i.h", xyzbc());
  ASSERT_EQ(h.blocks.size(), 3u);
  EXPECT_DOUBLE_EQ(h.blocks[1].feed, 254.0);
  EXPECT_DOUBLE_EQ(h.blocks[2].feed, 100.0);
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

TEST(NcReader, SinumerikIdentifiersAssignmentsShortWayAndVectors) {
  const auto p = nc::read_text(
      "; (cscam post: machine m dialect siemens strategy s)\nG71 G90 G94 G17 G40 G64\nTRAFOOF\nG54\nT=\"BALL6\"\n"
      "M6\nD1\nCYCLE800(0,\"TC1\",200000,57,0,0,0,0,0,0,0,0,0,-1,100,1)\nTRAORI\nORIWKS ORIVECT\nR1=2.5\n"
      "G0 X=10 Y2 Z=ACP(3) A3=0.6 B3=0 C3=0.8\nG1 X11 C=DC(350) F100 ; a comment\nG1 C=DC(10)\nTRAFOOF\nM30\n",
      "s.mpf", xyzbc());
  EXPECT_TRUE(p.tcp);
  EXPECT_TRUE(p.tcp_vectors);
  ASSERT_TRUE(p.header_machine.has_value());
  EXPECT_EQ(*p.header_machine, "m");
  ASSERT_EQ(p.blocks.size(), 3u);
  EXPECT_DOUBLE_EQ(p.blocks[0].axes[0], 10.0);
  EXPECT_DOUBLE_EQ(p.blocks[0].axes[2], 3.0);
  EXPECT_TRUE(p.blocks[0].has_vector);
  EXPECT_DOUBLE_EQ(p.blocks[0].tool_vector[0], 0.6);
  EXPECT_DOUBLE_EQ(p.blocks[0].tool_vector[2], 0.8);
  // C=DC(350) from an unknown C is 350; DC(10) from 350 goes the short way to 370
  EXPECT_NEAR(rad2deg(p.blocks[1].axes[4]), 350.0, 1e-9);
  EXPECT_NEAR(rad2deg(p.blocks[2].axes[4]), 370.0, 1e-9);
  EXPECT_TRUE(p.foreign_axis_words.empty()) << "A3/B3/C3 are no axis words";
}

TEST(NcReader, ModuloRotaryReadTheShortWay) {
  auto l = xyzbc();
  l.modulo[4] = true;
  const auto p = nc::read_text("G0 X0 Y0 Z0 B0 C350\nG1 C10 F100\nG1 C100\nG1 C190\nG1 C20\n", "m.ngc", l);
  ASSERT_EQ(p.blocks.size(), 5u);
  EXPECT_NEAR(rad2deg(p.blocks[1].axes[4]), 370.0, 1e-9);
  EXPECT_NEAR(rad2deg(p.blocks[2].axes[4]), 460.0, 1e-9);
  EXPECT_NEAR(rad2deg(p.blocks[3].axes[4]), 550.0, 1e-9);
  EXPECT_NEAR(rad2deg(p.blocks[4].axes[4]), 380.0, 1e-9);  // back the short way
}

TEST(NcReader, FanucVectorFormAndLinuxcncSwitchkins) {
  const auto v = nc::read_text("G43.5 H1\nG1 X1 Y2 Z3 I0 J0.6 K0.8 F100\nG1 X2\nG49\n", "v.nc", xyzbc());
  EXPECT_TRUE(v.tcp);
  EXPECT_TRUE(v.tcp_vectors);
  ASSERT_EQ(v.blocks.size(), 2u);
  EXPECT_DOUBLE_EQ(v.blocks[1].tool_vector[1], 0.6);  // modal
  const auto l = nc::read_text("M428\nG0 X1 Y2 Z3 B0 C0\nM429\n", "l.ngc", xyzbc());
  EXPECT_TRUE(l.tcp);
  EXPECT_FALSE(l.tcp_vectors);
}

TEST(NcReader, HeidenhainConversational) {
  const std::string text =
      "0 BEGIN PGM PART MM\n1 ; (cscam post: machine m dialect heidenhain strategy s)\n"
      "2 ; (cscam tool_length_mm=12.5000 tolerance_mm=0.0100)\n3 CYCL DEF 247 DATUM SETTING ~\n  Q339=+1 ;DATUM\n"
      "4 TOOL CALL 1 Z S6000\n5 FUNCTION TCPM F TCP AXIS POS PATHCTRL AXIS\n6 L Z+100 R0 FMAX M3\n"
      "7 L X+1.5 Y-2 B+10 C-20.5 R0 FMAX\n8 L X+2.5 R0 F1500\n9 L Y-3 ; comment\n10 END PGM PART MM\n11 L X+99\n";
  const auto p = nc::read_text(text, "h.h", xyzbc());
  EXPECT_TRUE(p.tcp);
  ASSERT_TRUE(p.tool_length_mm.has_value());
  EXPECT_DOUBLE_EQ(*p.tool_length_mm, 12.5);
  ASSERT_EQ(p.blocks.size(), 4u);
  EXPECT_EQ(p.blocks[0].motion, nc::Motion::Rapid);
  EXPECT_DOUBLE_EQ(p.blocks[0].axes[2], 100.0);
  EXPECT_NEAR(rad2deg(p.blocks[1].axes[4]), -20.5, 1e-12);
  EXPECT_EQ(p.blocks[2].motion, nc::Motion::Linear);
  EXPECT_DOUBLE_EQ(p.blocks[2].feed, 1500.0);
  EXPECT_DOUBLE_EQ(p.blocks[3].axes[1], -3.0);
  EXPECT_DOUBLE_EQ(p.blocks[3].feed, 1500.0);  // modal
  EXPECT_EQ(p.blocks[3].line, 11);
  try {
    nc::read_text("0 BEGIN PGM P MM\n1 L X+1..5\n", "bad.h", xyzbc());
    FAIL();
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("bad.h:2:"), std::string::npos) << e.what();
  }
}

// --- Tilted work planes -----------------------------------------------------------------------------------
// The frames are checked against rotations written out by hand (the reader uses core/rotations.hpp).
namespace {
Eigen::Matrix3d hand_rx(double d) {
  const double a = deg2rad(d);
  Eigen::Matrix3d m;
  m << 1, 0, 0, 0, std::cos(a), -std::sin(a), 0, std::sin(a), std::cos(a);
  return m;
}
Eigen::Matrix3d hand_ry(double d) {
  const double a = deg2rad(d);
  Eigen::Matrix3d m;
  m << std::cos(a), 0, std::sin(a), 0, 1, 0, -std::sin(a), 0, std::cos(a);
  return m;
}
Eigen::Matrix3d hand_rz(double d) {
  const double a = deg2rad(d);
  Eigen::Matrix3d m;
  m << std::cos(a), -std::sin(a), 0, std::sin(a), std::cos(a), 0, 0, 0, 1;
  return m;
}
}  // namespace

TEST(NcReader, FanucG682FrameWordsAndG69) {
  const auto p = nc::read_text(
      "%\nG0 X0 Y0 Z100 B0 C0\nG0 B30 C45\nG68.2 X10. Y0 Z-5 I45 J30 K0\nG53.1\nG0 X1 Y2 Z3\nG1 X4 F100\nG69\n"
      "G0 Z100\nM30\n%\n",
      "f.ngc", xyzbc());
  EXPECT_TRUE(p.work_planes);
  ASSERT_EQ(p.blocks.size(), 5u);  // G68.2's X Y Z are its origin, not a move
  EXPECT_EQ(p.blocks[1].plane, nullptr);
  ASSERT_NE(p.blocks[2].plane, nullptr);
  const nc::WorkPlane& w = *p.blocks[2].plane;
  EXPECT_LT((w.R_part_plane - hand_rz(45) * hand_rx(30)).norm(), 1e-12);
  EXPECT_LT((w.origin_in_part_mm - Eigen::Vector3d(10, 0, -5)).norm(), 1e-12);
  EXPECT_EQ(w.line, 4);
  EXPECT_EQ(w.form, "G68.2");
  EXPECT_DOUBLE_EQ(p.blocks[2].axes[0], 1.0);  // plane coordinates until resolve_work_planes
  EXPECT_TRUE(p.blocks[3].words[0]);
  EXPECT_FALSE(p.blocks[3].words[1]);
  ASSERT_NE(p.blocks[3].plane, nullptr);
  EXPECT_EQ(p.blocks[4].plane, nullptr);  // after G69
  EXPECT_EQ(p.xyz_slots, (std::array<int, 3>{0, 1, 2}));
}

TEST(NcReader, SiemensCycle800Mode57AndHeidenhainPlaneSpatial) {
  const auto s = nc::read_text(
      "G71 G90\nG0 X0 Y0 Z100 B0 C0\nG0 B20 C10\nCYCLE800(0,\"TC1\",0,57,1,2,3,10,20,30,0,0,5,1,0)\nG0 X1 Y1 Z1\n"
      "CYCLE800()\nG0 Z100\nM30\n",
      "s.mpf", xyzbc());
  ASSERT_EQ(s.blocks.size(), 4u);
  ASSERT_NE(s.blocks[2].plane, nullptr);
  const Eigen::Matrix3d Rs = hand_rx(10) * hand_ry(20) * hand_rz(30);  // axis by axis X, Y', Z''
  EXPECT_LT((s.blocks[2].plane->R_part_plane - Rs).norm(), 1e-12);
  // origin: the reference point X0 Y0 Z0 plus the zero point X1 Y1 Z1 of the rotated frame
  EXPECT_LT((s.blocks[2].plane->origin_in_part_mm - (Eigen::Vector3d(1, 2, 3) + Rs * Eigen::Vector3d(0, 0, 5))).norm(),
            1e-12);
  EXPECT_EQ(s.blocks[3].plane, nullptr);

  const auto h = nc::read_text(
      "0 BEGIN PGM P MM\n1 L X+0 Y+0 Z+100 B+0 C+0 R0 FMAX\n2 L B+20 C+10 R0 FMAX\n"
      "3 PLANE SPATIAL SPA+10 SPB-20 SPC+30 STAY\n4 L X+1 Y+1 Z+1 R0 FMAX\n5 L X+2 R0 F500\n6 PLANE RESET STAY\n"
      "7 L Z+100 R0 FMAX\n8 L Z+500 R0 FMAX M91\n9 END PGM P MM\n",
      "h.h", xyzbc());
  ASSERT_EQ(h.blocks.size(), 5u);  // the M91 block is a machine position: noted, not taken
  ASSERT_NE(h.blocks[2].plane, nullptr);
  EXPECT_LT((h.blocks[2].plane->R_part_plane - hand_rz(30) * hand_ry(-20) * hand_rx(10)).norm(), 1e-12);
  EXPECT_NE(h.blocks[3].plane, nullptr);
  EXPECT_EQ(h.blocks[4].plane, nullptr);
  ASSERT_EQ(h.notes.size(), 1u);
  EXPECT_NE(h.notes[0].find("h.h:9: M91"), std::string::npos) << h.notes[0];
}

TEST(NcReader, ArcsInATiltedPlaneAreReadInItsCoordinates) {
  // G68.2 / CYCLE800: G17 is the plane's XY; centre and ends are plane coordinates until resolve_work_planes.
  for (const std::string& text :
       {std::string("%\nG0 X0 Y0 Z100 B0 C0\nG0 B30 C45\nG68.2 X0 Y0 Z0 I45 J30 K0\nG53.1\nG0 X10 Y0 Z5\n"
                    "G1 Z0 F100\nG17 G3 X0 Y10 I-10 J0\nG2 X10 Y0 R10\nG69\nM30\n%\n"),
        std::string("G71 G90\nG0 X0 Y0 Z100 B0 C0\nG0 B30 C45\nCYCLE800(0,\"TC1\",0,57,0,0,0,10,20,30,0,0,0,1,0)\n"
                    "G0 X10 Y0 Z5\nG1 Z0 F100\nG17 G3 X0 Y10 I-10 J0\nG2 X10 Y0 R10\nCYCLE800()\nM30\n")}) {
    const auto p = nc::read_text(text, "a.ngc", xyzbc());
    ASSERT_EQ(p.blocks.size(), 6u);
    for (std::size_t i : {4u, 5u}) {
      const nc::Block& b = p.blocks[i];
      ASSERT_NE(b.plane, nullptr);
      ASSERT_NE(b.arc, nullptr);
      EXPECT_EQ(b.arc->plane, 17);
      EXPECT_FALSE(b.arc->tilted);  // in the plane's coordinates: a plain G17 circle there
      EXPECT_NEAR(b.arc->centre_u, 0.0, 1e-12);
      EXPECT_NEAR(b.arc->centre_v, 0.0, 1e-12);
      EXPECT_NEAR(b.arc->start_radius_mm, 10.0, 1e-12);
      EXPECT_NEAR(b.arc->sweep_rad, i == 4 ? 0.5 * kPi : -0.5 * kPi, 1e-12);
    }
  }
}

TEST(NcReader, WorkPlaneFormsItCannotFollowAreRefusedWithTheirLine) {
  auto error_of = [](const std::string& text) {
    try {
      nc::read_text(text, "e.ngc", xyzbc());
    } catch (const InputError& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  EXPECT_NE(error_of("G0 X0 Y0 Z0 B0 C0\nCYCLE800(0,\"TC1\",0,27,0,0,0,10,0,0,0,0,0,1,0)\n")
                .find("CYCLE800 mode 27 is not read"),
            std::string::npos);
  // an arc's start must be given in the plane's coordinates (the machine position before it is in other ones)
  EXPECT_NE(error_of("G0 X0 Y0 Z0 B0 C0\nG68.2 X0 Y0 Z0 I0 J10 K0\nG2 X1 Y1 I1 J0 F100\n")
                .find("e.ngc:3:1: arc in a tilted work plane (G68.2) before its plane's axes are given in it"),
            std::string::npos);
  EXPECT_NE(error_of("G0 X0 Y0 Z0 B0 C0\nG68.2 X0 Y0 Z0 I0 J10 K0\nG1 X5 Z1 F100\nG3 X0 Y5 I-5 J0\n")
                .find("e.ngc:4:1: arc in a tilted work plane (G68.2) before its plane's axes are given in it"),
            std::string::npos);
  EXPECT_NE(error_of("G0 X0 Y0 Z0 B0 C0\nG68.2 X0 Y0 Z0 I0 J10 K0\nG91 G1 X1 F100\n")
                .find("e.ngc:3:1: incremental (G91) words in a tilted work plane (G68.2) are not read"),
            std::string::npos);
  EXPECT_NE(error_of("0 BEGIN PGM P MM\n1 PLANE PROJECTED PROPR+0 PROMIN+0 ROT+0 STAY\n").find("e.ngc:2:"),
            std::string::npos);
  // SUPA and G53 are machine positions: noted, not taken as work positions
  const auto p = nc::read_text("G0 X1 Y2 Z3 B0 C0\nG0 SUPA Z0\nG53 G0 Z0\nG1 X2 F100\n", "m.mpf", xyzbc());
  ASSERT_EQ(p.blocks.size(), 2u);
  EXPECT_DOUBLE_EQ(p.blocks[1].axes[2], 3.0);
  EXPECT_EQ(p.notes.size(), 2u);
}

TEST(NcReader, ToolTipControlIsFollowedBlockByBlock) {
  // Each block notes whether TCP was in force when it was written: the words that switch it on and off per dialect.
  auto tcp_of = [](const std::string& text) {
    const auto p = nc::read_text(text, "t.nc", xyzbc());
    EXPECT_TRUE(p.tcp_words);
    std::string flags;
    for (const auto& b : p.blocks) flags += b.tcp ? 'T' : 'm';
    return flags;
  };
  EXPECT_EQ(tcp_of("G43.4 H1\nG0 X1 Y0 Z0 B0 C0\nG49\nG43 H1\nG0 Z10\nG43.5 H1\nG1 X2 I0 J0 K1 F100\nG43 H1\nG0 Z20\n"),
            "TmTm");
  EXPECT_EQ(tcp_of("G234 H1\nG0 X1 Y0 Z0 B0 C0\nG49\nG0 Z10\nG254\nG1 X2 F100\nG255\nG234 H1\nG0 Z20\n"), "TmmT");
  EXPECT_EQ(tcp_of("TRAORI\nG0 X1 Y0 Z0 B0 C0\nTRAFOOF\nG0 Z10\nTRAORI\nG0 Z20\n"), "TmT");
  EXPECT_EQ(tcp_of("M428\nG0 X1 Y0 Z0 B0 C0\nM429\nG0 Z10\n"), "Tm");
  EXPECT_EQ(tcp_of("0 BEGIN PGM P MM\n1 FUNCTION TCPM F TCP AXIS POS PATHCTRL AXIS\n2 L X+1 Y+0 Z+0 B+0 C+0 R0 FMAX\n"
                   "3 FUNCTION RESET TCPM\n4 L Z+10 R0 FMAX\n5 M128\n6 L Z+20 R0 FMAX\n7 M129\n8 L Z+30 R0 FMAX\n"),
            "TmTm");
  // a plane while TCP is on is refused (the control would too); after the cancel it is read
  auto error_of = [](const std::string& text) {
    try {
      nc::read_text(text, "e.ngc", xyzbc());
    } catch (const InputError& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  EXPECT_NE(error_of("G43.4 H1\nG0 X0 Y0 Z0 B10 C0\nG68.2 X0 Y0 Z0 I0 J10 K0\nG53.1\nG0 X1 Y1 Z1\n")
                .find("e.ngc:5:1: a tilted work plane (G68.2) under tool-tip control is not read"),
            std::string::npos);
  EXPECT_EQ(error_of("G43.4 H1\nG0 X0 Y0 Z0 B10 C0\nG49\nG43 H1\nG68.2 X0 Y0 Z0 I0 J10 K0\nG53.1\nG0 X1 Y1 Z1\n"),
            "no error");
  // a header alone (no TCP word) notes none
  EXPECT_FALSE(nc::read_text("(cartesian: X Y Z = tool tip)\nG0 X1 Y2 Z3 B0 C0\n", "h.nc", xyzbc()).tcp_words);
}

// The state changes the reader does not model are noted at their lines (Program::unmodelled), in every dialect it
// reads; their resets, and the first selection of a work offset or length offset, are not. A tool change matters
// only when a Z word follows it before a new G43 (a Fanuc program positions X Y first, then G43 H Z).
TEST(NcReader, StateChangesItDoesNotModelAreNotedWithTheirLines) {
  auto lines_of = [](const std::string& text) {
    std::vector<int> out;
    for (const auto& u : nc::read_text(text, "u.nc", xyzbc()).unmodelled) out.push_back(u.line);
    return out;
  };
  using V = std::vector<int>;
  EXPECT_EQ(lines_of("G54 G49\nT1 M6\nG0 X1 Y2\nG43 H1 Z50\nG1 X2\nG92.1\nG69\nG50.1\nG0 Z9\n"), V{});
  EXPECT_EQ(lines_of("G54\nG0 X0\nG55\nG1 X1\n"), V{3});
  EXPECT_EQ(lines_of("G43 H1 Z9\nG49\nG0 X1\nG1 Z0\n"), V{2});       // noted where it was lost, at the Z word
  EXPECT_EQ(lines_of("G43 H1 Z9\nT2 M6\nG0 X1\nZ5\n"), V{2});        // the tool change without G43
  EXPECT_EQ(lines_of("G43 H1 Z9\nT2 M6\nG0 X1\nG43 H2 Z5\n"), V{});  // with it
  EXPECT_EQ(lines_of("G43 H1 Z9\nG43 H3\nG0 X1\n"), V{2});
  EXPECT_EQ(lines_of("G0 X0\nG52 X5 Y5\nG68 X0 Y0 R9\nG51 P2\nG10 L2 P1 X1\nG92 X0\n"), (V{2, 3, 4, 5, 6}));
  // G52's and G68's words are their shift and centre, not a position.
  EXPECT_EQ(nc::read_text("G0 X1\nG52 X5\nG68 X7 Y0 R9\n", "u.nc", xyzbc()).blocks.size(), 1u);
  // Sinumerik frames (alone: a reset) and Heidenhain's transformation cycles.
  EXPECT_EQ(lines_of("G54\nTRANS\nROT ; reset\nTRANS X10\nG500\nAROT RPL=30\n"), (V{4, 5, 6}));
  EXPECT_EQ(
      lines_of("0 BEGIN PGM P MM\n1 CYCL DEF 7.0 DATUM SHIFT\n2 CYCL DEF 7.1 X+10\n3 TRANS DATUM RESET\n"
               "4 CYCL DEF 10.0 ROTATION\n5 TRANS DATUM AXIS X+5\n6 CYCL DEF 247 DATUM SETTING\n7 END PGM P MM\n"),
      (V{2, 5, 6}));
}

// Dwells: G4 P without a decimal point is milliseconds (Fanuc, Haas), with one seconds, always seconds in our
// LinuxCNC programs; G4 X / U are seconds and no position; Sinumerik G4 F is seconds and not the feed; G4 S
// (revolutions) is counted, not timed; Heidenhain cycle 9.
TEST(NcReader, DwellsAreTimedAndTheirWordsAreNeitherPositionsNorFeeds) {
  auto read = [](const std::string& t) { return nc::read_text(t, "d.nc", xyzbc()); };
  EXPECT_DOUBLE_EQ(read("G4 P2500\n").dwell_seconds, 2.5);
  EXPECT_DOUBLE_EQ(read("N10 G04 P2.5\n").dwell_seconds, 2.5);
  EXPECT_DOUBLE_EQ(read("(cscam post: machine m dialect linuxcnc strategy s)\nG4 P2\n").dwell_seconds, 2.0);
  const auto x = read("G1 X5 F100\nG04 X1.5\nG1 Y1\n");
  EXPECT_DOUBLE_EQ(x.dwell_seconds, 1.5);
  ASSERT_EQ(x.blocks.size(), 2u);
  EXPECT_DOUBLE_EQ(x.blocks[1].axes[0], 5.0);
  const auto f = read("G1 X1 F100\nG4 F2\nG1 X2\nG4 S10\n");
  EXPECT_DOUBLE_EQ(f.dwell_seconds, 2.0);
  EXPECT_EQ(f.dwells, 2u);
  ASSERT_EQ(f.blocks.size(), 2u);
  EXPECT_DOUBLE_EQ(f.blocks[1].feed, 100.0);
  const auto h = read("0 BEGIN PGM P MM\n1 CYCL DEF 9.0 DWELL TIME\n2 CYCL DEF 9.1 DWELL 1.25\n3 END PGM P MM\n");
  EXPECT_EQ(h.dwells, 1u);
  EXPECT_DOUBLE_EQ(h.dwell_seconds, 1.25);
  // P elsewhere is no dwell.
  EXPECT_EQ(read("G64 P0.01\nG1 X1 F10\n").dwells, 0u);
}

// The spindle's stops: an M5 after an M3 / M4 opens one at the next line (its own block's motion runs first), an M3
// closes it before its block's motion; an M5 before the spindle ever ran is none.
TEST(NcReader, SpindleStopsCoverTheBlocksReadWhileItIsStopped) {
  const auto p =
      nc::read_text("M5\nG0 X0\nS100 M3\nG1 X1 F10\nG1 X2 M5\nG1 X3\nG1 X4\nM4 G1 X5\nX6 M5\n", "s.nc", xyzbc());
  ASSERT_EQ(p.blocks.size(), 7u);
  ASSERT_EQ(p.spindle_stops.size(), 2u);
  EXPECT_EQ(p.spindle_stops[0].line, 5);
  EXPECT_EQ(p.spindle_stops[0].first_block, 3u);  // G1 X3
  EXPECT_EQ(p.spindle_stops[0].end_block, 5u);    // up to, not including, the M4 block
  EXPECT_EQ(p.spindle_stops[1].line, 9);
  EXPECT_EQ(p.spindle_stops[1].first_block, 7u);  // nothing after it
  EXPECT_EQ(p.spindle_stops[1].end_block, 7u);
  const auto h = nc::read_text("0 BEGIN PGM P MM\n1 L X+1 R0 F100 M3\n2 M5\n3 L X+2\n4 L X+3 M3\n5 END PGM P MM\n",
                               "h.h", xyzbc());
  ASSERT_EQ(h.spindle_stops.size(), 1u);
  EXPECT_EQ(h.spindle_stops[0].first_block, 1u);
  EXPECT_EQ(h.spindle_stops[0].end_block, 2u);
}

// Which tool is in the spindle at each block, as the gate checks every move with its own cutter: a tool change is an
// M6 (with its T word, or after it on a line of its own, as Sinumerik writes it) or a Heidenhain TOOL CALL with a tool
// number; "TOOL CALL Z S..." alone only sets the spindle speed.
TEST(NcReader, ToolChangesAreCountedBlockByBlock) {
  const auto g = nc::read_text(
      "G21 G90\nG0 X0 Y0 Z50 B0 C0\nT1 M6\nG43 H1\nG1 X1 F100\nT2\nG1 X2\nM6\nG43 H2\nG1 X3\nT3 M6\nG43 H3\nG0 Z60\n",
      "t.ngc", xyzbc());
  ASSERT_EQ(g.blocks.size(), 5u);
  const std::vector<int> expected{0, 1, 1, 2, 3};  // before any change; T2 alone preselects
  for (std::size_t i = 0; i < expected.size(); ++i) EXPECT_EQ(g.blocks[i].tool_changes, expected[i]) << i;
  const auto h = nc::read_text(
      "0 BEGIN PGM P MM\n1 L X+0 Y+0 Z+50 B+0 C+0 R0 FMAX\n2 TOOL CALL 4 Z\n3 TOOL CALL Z S8000\n4 L X+1 R0 F100\n"
      "5 TOOL CALL \"D6\" Z\n6 L X+2 R0 F100\n7 END PGM P MM\n",
      "t.h", xyzbc());
  ASSERT_EQ(h.blocks.size(), 3u);
  EXPECT_EQ(h.blocks[0].tool_changes, 0);
  EXPECT_EQ(h.blocks[1].tool_changes, 1);
  EXPECT_EQ(h.blocks[2].tool_changes, 2);
}

// Motion the read-back cannot follow is not modelled (the gate refuses it, verify fails at its line): subprogram and
// macro calls, cutter compensation, canned cycles, G28 through an intermediate point, a feed from where G53 left an
// axis, a move after M30. NX's Haas post's own home moves (G53 G0 Z0, G91 G28 X0 Y0 between operations) are not.
TEST(NcReader, MotionTheReadBackCannotFollowIsNotModelled) {
  const std::string head = "G21 G90\nG0 X0 Y0 Z50 B0 C0\nG1 Z10 F100\n";
  for (const auto& [line, says] : std::vector<std::pair<std::string, std::string>>{
           {"M98 P1000", "M98 calls a subprogram"},
           {"M99", "M99 returns from a subprogram"},
           {"G65 P9000", "G65 calls a macro"},
           {"G41 D1", "G41 offsets the tool"},
           {"G81 Z-5 R2", "G81 is a canned cycle"},
           {"G90 G28 Z0", "G28 goes home through an intermediate point"},
           {"o100 call", "o-word 'call'"},
           {"L100", "L100 calls a subprogram"},
           {"G53 G0 Z0", "the move starts where G53 at line 4 left axis Z"},
           {"M30", "a move after the program's end (M30 at line 4)"}}) {
    const auto p = nc::read_text(head + line + "\nG1 X5 F100\nG1 X10\n", "u.ngc", xyzbc());
    ASSERT_FALSE(p.unmodelled.empty()) << line;
    EXPECT_NE(p.unmodelled.front().what.find(says), std::string::npos) << line << ": " << p.unmodelled.front().what;
  }
  const auto nx = nc::read_text(
      "G21 G90\nG53 G0 Z0\nG91 G28 X0 Y0\nG91 G28 B0 C0\nG90\nT1 M6\nS1000 M3\nG0 X1 Y1 B0 C0\nG43 Z5 H1\n"
      "G1 Z1 F100\nG1 X5\nG0 Z5\nG53 G0 Z0\nG91 G28 X0 Y0\nG90\nM30\n",
      "nx.ngc", xyzbc());
  EXPECT_TRUE(nx.unmodelled.empty()) << nx.unmodelled.front().what;
}

// A UTF-8 byte-order mark before the program is skipped (a Windows editor writes one); a byte that is not text is
// named by its value, not printed raw.
TEST(NcReader, AByteOrderMarkIsSkippedAndABinaryByteNamed) {
  const std::string prog = "G21 G90\nG0 X0 Y0 Z50 B0 C0\nG1 X5 F100\n";
  const auto plain = nc::read_text(prog, "p.ngc", xyzbc());
  const auto bom = nc::read_text("\xEF\xBB\xBF" + prog, "b.ngc", xyzbc());
  ASSERT_EQ(bom.blocks.size(), plain.blocks.size());
  EXPECT_EQ(bom.blocks.back().axes, plain.blocks.back().axes);
  const std::string err = test::error_of([&] { nc::read_text("G21\nG1 X5 \x01 F100\n", "x.ngc", xyzbc()); });
  EXPECT_NE(err.find("x.ngc:2:7: unexpected byte 0x01"), std::string::npos) << err;
}
