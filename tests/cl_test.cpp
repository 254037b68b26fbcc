// Tests of the CL reader: real NX CLSF files, CIRCLE/ tessellation checked against NX's own post output,
// ISO 4343 / CATIA flavour syntax, the CSV form, and the error paths with their file:line:column.
#include <fmt/format.h>
#include <gtest/gtest.h>
#include <tbb/task_arena.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <iterator>
#include <sstream>
#include <string>
#include <vector>

#include "cscam/cl/program.hpp"
#include "cscam/core/error.hpp"
#include "cscam/core/tolerances.hpp"
#include "cscam/core/units.hpp"
#include "test_support.hpp"

namespace cscam::cl {
namespace {

using Eigen::Vector3d;
using test::source_path;

/// Values the reader computes exactly from the printed numbers (a scale by 25.4, a normalisation).
constexpr double kExactMm = 1e-9;
/// NX prints its G-code to 4 decimals of an inch; matching a CL arc to its G02/G03 block allows for that.
constexpr double kNcRoundingMm = 0.0002 * kMmPerInch;

const std::string kVariableAxis = "examples/nx-haas-umc750/variable_axis.cls";
const std::string kZigzag = "examples/nx-haas-umc750/zigzag_smoothed.cls";
const std::string kZigzagNc = "examples/nx-haas-umc750/zigzag_smoothed.nx-post.nc";

std::vector<std::string> lines_of(const std::string& path) {
  std::ifstream in(path);
  EXPECT_TRUE(in.good()) << path;
  std::vector<std::string> out;
  for (std::string l; std::getline(in, l);) out.push_back(l);
  return out;
}

size_t count_kind(const Program& p, MotionKind k) {
  size_t n = 0;
  for (const Move& m : p.moves) n += m.kind == k;
  return n;
}

/// The InputError thrown by reading `text`, or a test failure.
InputError error_of(const std::string& text, const std::string& name = "t.cls") {
  try {
    (void)read_text(text, name);
  } catch (const InputError& e) {
    return e;
  }
  ADD_FAILURE() << "no InputError for:\n" << text;
  return InputError("none");
}

std::vector<const Event*> events_of(const Program& p, Event::Kind k) {
  std::vector<const Event*> out;
  for (const Event& e : p.events)
    if (e.kind == k) out.push_back(&e);
  return out;
}

// ------------------------------------------------------------------------------------------------------------
// Real NX files

TEST(ClRealNx, VariableAxisParsesInInches) {
  const Program p = read_file(source_path(kVariableAxis));
  EXPECT_EQ(p.source_units, LengthUnit::Inch);  // no UNITS/: FEDRAT/IPM decides
  EXPECT_TRUE(p.warnings.empty()) << p.warnings.front().where.str() << ": " << p.warnings.front().message;
  EXPECT_EQ(p.moves.size(), 348u);  // grep -c '^GOTO'
  EXPECT_EQ(count_kind(p, MotionKind::Rapid), 3u);
  EXPECT_TRUE(p.multax);
  EXPECT_EQ(p.part_name, "NORM_PART");

  // GOTO/-4.2721,-3.0148,3.0000,-0.3778015,-0.0069217,0.9258607 on line 10, a rapid.
  const Move& first = p.moves.front();
  EXPECT_EQ(first.line, 10);
  EXPECT_EQ(first.kind, MotionKind::Rapid);
  EXPECT_EQ(first.feed_mm_per_min, 0.0);
  EXPECT_NEAR(first.tip_in_part_mm.x(), -4.2721 * 25.4, kExactMm);
  EXPECT_NEAR(first.tip_in_part_mm.y(), -3.0148 * 25.4, kExactMm);
  EXPECT_NEAR(first.tip_in_part_mm.z(), 3.0 * 25.4, kExactMm);
  const Vector3d a0 = Vector3d(-0.3778015, -0.0069217, 0.9258607).normalized();
  EXPECT_LT((first.axis_in_part - a0).norm(), kExactMm);
  EXPECT_NEAR(first.axis_in_part.norm(), 1.0, kExactMm);

  // Line 13 "GOTO/-3.5785,-3.0021,1.3002" omits i,j,k: the axis carries over (through line 24).
  const Move& second = p.moves[1];
  EXPECT_EQ(second.line, 13);
  EXPECT_EQ(second.kind, MotionKind::Rapid);
  EXPECT_LT((second.axis_in_part - a0).norm(), kExactMm);
  EXPECT_EQ(p.moves[10].line, 24);
  EXPECT_LT((p.moves[10].axis_in_part - a0).norm(), kExactMm);
  EXPECT_EQ(p.moves[11].line, 26);  // the next one gives its own axis
  EXPECT_GT((p.moves[11].axis_in_part - a0).norm(), 0.01);

  // FEDRAT/IPM,10 -> 254 mm/min for every feed move.
  for (const Move& m : p.moves)
    if (m.kind == MotionKind::Feed) {
      EXPECT_NEAR(m.feed_mm_per_min, 254.0, kExactMm) << "line " << m.line;
    }

  // TLDATA/MILL,1.0,0.5,3.0 (inches): a 25.4 mm ball mill named by TOOL PATH/.
  ASSERT_EQ(p.tools.size(), 1u);
  const Tool& t = p.tools[0];
  EXPECT_NEAR(t.diameter_mm, 25.4, kExactMm);
  EXPECT_NEAR(t.corner_radius_mm, 12.7, kExactMm);
  EXPECT_NEAR(t.length_mm, 76.2, kExactMm);
  EXPECT_TRUE(t.is_ball());
  EXPECT_EQ(t.name, "BALL_MILL_1.00");
  for (const Move& m : p.moves) EXPECT_EQ(m.tool_index, 0);

  // MSYS/3,3,0,... : origin in mm.
  ASSERT_TRUE(p.msys.has_value());
  EXPECT_NEAR((*p.msys)(0, 0), 76.2, kExactMm);
  EXPECT_NEAR((*p.msys)(1, 0), 76.2, kExactMm);
  EXPECT_NEAR((*p.msys)(2, 0), 0.0, kExactMm);

  const auto ops = events_of(p, Event::Kind::OperationStart);
  ASSERT_EQ(ops.size(), 1u);
  EXPECT_EQ(ops[0]->text, "NORM_PART");
  const auto tcs = events_of(p, Event::Kind::ToolChange);
  ASSERT_EQ(tcs.size(), 1u);
  EXPECT_EQ(tcs[0]->tool_index, 0);
  EXPECT_EQ(tcs[0]->before_move, 0u);
  const auto comments = events_of(p, Event::Kind::Comment);
  ASSERT_EQ(comments.size(), 1u);
  EXPECT_EQ(comments[0]->text, "centerline data");
  EXPECT_EQ(comments[0]->line, 4);
}

TEST(ClRealNx, ZigzagParsesInMillimetres) {
  const Program p = read_file(source_path(kZigzag));
  EXPECT_EQ(p.source_units, LengthUnit::Millimetre);  // FEDRAT/MMPM
  EXPECT_TRUE(p.warnings.empty());
  size_t gotos = 0;
  for (const Move& m : p.moves) gotos += !m.from_arc;
  EXPECT_EQ(gotos, 75u);
  EXPECT_GT(p.moves.size(), gotos);  // arcs added points
  EXPECT_EQ(count_kind(p, MotionKind::Rapid), 3u);
  ASSERT_EQ(p.tools.size(), 1u);  // TLDATA then LOAD/TOOL,0: one tool
  EXPECT_EQ(p.tools[0].number, 0);
  EXPECT_EQ(p.tools[0].name, "FACEMILL");
  EXPECT_NEAR(p.tools[0].diameter_mm, 10.0, kExactMm);
  EXPECT_FALSE(p.tools[0].is_ball());
  EXPECT_EQ(events_of(p, Event::Kind::ToolChange).size(), 1u);
  EXPECT_NEAR(p.moves[2].feed_mm_per_min, 250.0, kExactMm);
}

/// A CIRCLE/ record read straight from the file, with the GOTO/ that ends it.
struct ClArc {
  int line = 0;
  Vector3d centre, normal, end;
  double r = 0;
};

std::vector<ClArc> circles_in(const std::string& path) {
  std::vector<ClArc> out;
  const auto lines = lines_of(path);
  for (size_t i = 0; i + 1 < lines.size(); ++i) {
    ClArc a;
    double tol;
    if (std::sscanf(lines[i].c_str(), "CIRCLE/%lf,%lf,%lf,%lf,%lf,%lf,%lf,%lf", &a.centre.x(), &a.centre.y(),
                    &a.centre.z(), &a.normal.x(), &a.normal.y(), &a.normal.z(), &a.r, &tol) != 8)
      continue;
    EXPECT_EQ(std::sscanf(lines[i + 1].c_str(), "GOTO/%lf,%lf,%lf", &a.end.x(), &a.end.y(), &a.end.z()), 3);
    a.line = static_cast<int>(i) + 1;
    out.push_back(a);
  }
  return out;
}

TEST(ClCircle, RealArcsLieOnTheirCirclesWithinTolerance) {
  ReadOptions opt;
  for (const double tol : {0.001, 0.01}) {
    opt.arc_tolerance_mm = tol;
    const Program p = read_file(source_path(kZigzag), opt);
    const auto arcs = circles_in(source_path(kZigzag));
    ASSERT_EQ(arcs.size(), 35u);
    size_t checked_points = 0;
    for (const ClArc& a : arcs) {
      // The moves of this arc: generated points (line = the CIRCLE line), then the end GOTO on the next line.
      size_t k = 0;
      while (k < p.moves.size() && p.moves[k].line != a.line + 1) ++k;
      ASSERT_LT(k, p.moves.size()) << "no end GOTO for CIRCLE on line " << a.line;
      const Move& end = p.moves[k];
      EXPECT_FALSE(end.from_arc);
      EXPECT_LT((end.tip_in_part_mm - a.end).norm(), kExactMm) << "line " << a.line;
      size_t first = k;
      while (first > 0 && p.moves[first - 1].from_arc && p.moves[first - 1].line == a.line) --first;
      ASSERT_GT(first, 0u);
      const Vector3d n = a.normal.normalized();
      double prev_angle = 0;
      for (size_t i = first; i < k; ++i) {
        const Move& m = p.moves[i];
        EXPECT_TRUE(m.from_arc);
        EXPECT_EQ(m.kind, MotionKind::Feed);
        const Vector3d d = m.tip_in_part_mm - a.centre;
        const Vector3d radial = d - d.dot(n) * n;
        EXPECT_NEAR(radial.norm(), a.r, kExactMm) << "line " << a.line;
        ++checked_points;
        // Chord error of each step: r (1 - cos(step/2)) <= tolerance, with the step taken from the start point.
        const Vector3d s = p.moves[first - 1].tip_in_part_mm - a.centre;
        const Vector3d s_radial = s - s.dot(n) * n;
        const double angle = std::atan2(s_radial.cross(radial).dot(n), s_radial.dot(radial));
        const double step = std::abs(angle - prev_angle);
        EXPECT_LE(a.r * (1 - std::cos(step / 2)), tol + kExactMm) << "line " << a.line;
        prev_angle = angle;
      }
      // ... and the last step, to the end point.
      if (k > first) {
        const Vector3d s = p.moves[first - 1].tip_in_part_mm - a.centre, e = end.tip_in_part_mm - a.centre;
        const Vector3d sr = s - s.dot(n) * n, er = e - e.dot(n) * n;
        double angle = std::atan2(sr.cross(er).dot(n), sr.dot(er));
        if (angle > 0) angle -= 2 * kPi;  // clockwise about n
        EXPECT_LE(a.r * (1 - std::cos(std::abs(angle - prev_angle) / 2)), tol + 1e-6) << "line " << a.line;
      }
    }
    EXPECT_GT(checked_points, 100u);
  }
}

/// A G02/G03 block of NX's post output, in mm.
struct NcArc {
  bool ccw = false;
  Vector3d start, end, centre;
};

std::vector<NcArc> nc_arcs(const std::string& path) {
  std::vector<NcArc> out;
  Vector3d pos = Vector3d::Zero();
  int motion = 0;
  for (std::string line : lines_of(path)) {
    if (line.find('(') != std::string::npos) line = line.substr(0, line.find('('));
    if (line.find("G28") != std::string::npos || line.find("G53") != std::string::npos) continue;
    std::istringstream in(line);
    Vector3d next = pos;
    double i = 0, j = 0;
    bool has_ij = false;
    for (std::string w; in >> w;) {
      const char c = w[0];
      const double v = std::atof(w.c_str() + 1);
      if (c == 'G' && v >= 0 && v <= 3) motion = static_cast<int>(v);
      if (c == 'X') next.x() = v * kMmPerInch;
      if (c == 'Y') next.y() = v * kMmPerInch;
      if (c == 'Z') next.z() = v * kMmPerInch;
      if (c == 'I') i = v * kMmPerInch, has_ij = true;
      if (c == 'J') j = v * kMmPerInch, has_ij = true;
    }
    if ((motion == 2 || motion == 3) && has_ij) out.push_back({motion == 3, pos, next, pos + Vector3d(i, j, 0)});
    pos = next;
  }
  return out;
}

// Which way does NX mean a CIRCLE/? Its own post printed zigzag_smoothed.cls with G02/G03; every arc we generate
// must turn the same way as the G-code arc that ends at the same point.
TEST(ClCircle, SenseOfRotationMatchesNxPostOutput) {
  const Program p = read_file(source_path(kZigzag));
  const auto arcs = nc_arcs(source_path(kZigzagNc));
  ASSERT_EQ(arcs.size(), 34u);  // the 35th CIRCLE/ (0.8 degrees) came out as a G01
  int matched_cw = 0, matched_ccw = 0;
  for (size_t k = 1; k + 1 < p.moves.size(); ++k) {
    if (!p.moves[k].from_arc || p.moves[k - 1].from_arc) continue;  // first generated point of an arc
    size_t e = k;
    while (p.moves[e].from_arc) ++e;
    const Vector3d start = p.moves[k - 1].tip_in_part_mm, end = p.moves[e].tip_in_part_mm;
    for (const NcArc& a : arcs) {
      if ((a.end - end).head<2>().norm() > kNcRoundingMm || (a.start - start).head<2>().norm() > kNcRoundingMm)
        continue;
      const Vector3d c = a.centre;
      // Sense of our arc seen from +Z (the G17 plane): the turn from the start to the first generated point.
      const double turn = (start - c).head<2>().x() * (p.moves[k].tip_in_part_mm - c).head<2>().y() -
                          (start - c).head<2>().y() * (p.moves[k].tip_in_part_mm - c).head<2>().x();
      EXPECT_EQ(turn > 0, a.ccw) << "arc ending at line " << p.moves[e].line << " is G0" << (a.ccw ? 3 : 2);
      (a.ccw ? matched_ccw : matched_cw)++;
    }
  }
  EXPECT_EQ(matched_cw + matched_ccw, 34);
  EXPECT_GT(matched_cw, 0);
  EXPECT_GT(matched_ccw, 0);
}

TEST(ClCircle, SyntheticArcsQuarterFullAndHelical) {
  const std::string head = "UNITS/MM\nFEDRAT/MMPM,100\nGOTO/10,0,0\n";
  // Clockwise about +Z from angle 0 to -90 degrees: a quarter, in the x>0, y<0 quadrant.
  Program p = read_text(head + "CIRCLE/0,0,0,0,0,1,10,0.01\nGOTO/0,-10,0\n", "q.cls");
  ASSERT_GT(p.moves.size(), 3u);
  for (const Move& m : p.moves)
    if (m.from_arc) {
      EXPECT_GT(m.tip_in_part_mm.x(), 0);
      EXPECT_LT(m.tip_in_part_mm.y(), 0);
      EXPECT_EQ(m.line, 4);
      EXPECT_NEAR(m.feed_mm_per_min, 100.0, kExactMm);
    }
  EXPECT_EQ(p.moves.back().line, 5);
  EXPECT_FALSE(p.moves.back().from_arc);
  // The same with (0,0,-1): the other three quarters.
  p = read_text(head + "CIRCLE/0,0,0,0,0,-1,10,0.01\nGOTO/0,-10,0\n", "q3.cls");
  bool seen_upper_half = false;
  for (const Move& m : p.moves) seen_upper_half |= m.from_arc && m.tip_in_part_mm.y() > 5;
  EXPECT_TRUE(seen_upper_half);
  // End = start: a full circle. A tighter tolerance gives more points; a helix climbs linearly.
  ReadOptions coarse, fine;
  coarse.arc_tolerance_mm = 0.01;
  fine.arc_tolerance_mm = 0.0001;
  const Program full = read_text(head + "CIRCLE/0,0,0,0,0,1,10\nGOTO/10,0,5\n", "full.cls", coarse);
  const Program full_fine = read_text(head + "CIRCLE/0,0,0,0,0,1,10\nGOTO/10,0,5\n", "full.cls", fine);
  EXPECT_GT(full_fine.moves.size(), full.moves.size());
  double min_x = 1e9;
  for (size_t i = 1; i + 1 < full.moves.size(); ++i) {
    const Move& m = full.moves[i];
    ASSERT_TRUE(m.from_arc);
    min_x = std::min(min_x, m.tip_in_part_mm.x());
    EXPECT_NEAR(m.tip_in_part_mm.head<2>().norm(), 10.0, kExactMm);
    EXPECT_GT(m.tip_in_part_mm.z(), full.moves[i - 1].tip_in_part_mm.z());
  }
  EXPECT_LT(min_x, -9.9);  // went all the way round
  // A CIRCLE with no start point is not an error: a warning, then a straight move.
  const Program lone = read_text("UNITS/MM\nCIRCLE/0,0,0,0,0,1,10\nGOTO/10,0,0\n", "lone.cls");
  EXPECT_EQ(lone.moves.size(), 1u);
  EXPECT_EQ(lone.warnings.size(), 1u);
  // A start point off the circle is drawn anyway, with a warning naming the CIRCLE line.
  const Program off = read_text(head + "CIRCLE/0,0,0,0,0,1,9\nGOTO/0,-9,0\n", "off.cls");
  ASSERT_EQ(off.warnings.size(), 1u);
  EXPECT_EQ(off.warnings[0].where.line, 4);
  EXPECT_NE(off.warnings[0].message.find("1.0000 mm off the circle"), std::string::npos) << off.warnings[0].message;
}

// ------------------------------------------------------------------------------------------------------------
// ISO 4343 / CATIA flavour

const char* const kIso =
    "$$ CATIA-like header\n"                                  // 1
    "PARTNO  bracket op 10\n"                                 // 2
    "units / inches\n"                                        // 3
    "MULTAX\n"                                                // 4
    "CUTTER/ 0.5, 0.25, 0, 0.25, 0, 0, 2.0 $$ ball 1/2 in\n"  // 5
    "LOADTL/ 3, 1\n"                                          // 6
    "SPINDL/ 8000, CCLW\n"                                    // 7
    "COOLNT/ flood\n"                                         // 8
    "FEDRAT/ 20.0\n"                                          // 9
    "FROM/ 0, 0, 4\n"                                         // 10
    "goto  / 1., -.5, 1E-1 , 0,0,1\n"                         // 11
    "GOTO/ 2.0, 0.0, $\n"                                     // 12
    "      0.5, +0.0, 0.6, 0.8   $$ continued\n"              // 13
    "\n"                                                      // 14
    "RAPID\n"                                                 // 15
    "GOTO/3,0,1\n"                                            // 16
    "STOP\n"                                                  // 17
    "SPINDL/OFF\n"                                            // 18
    "COOLNT/OFF\n"                                            // 19
    "FINI\n"                                                  // 20
    "GOTO/9,9,9\n";                                           // 21: after FINI, ignored

TEST(ClIso, CatiaFlavourStatements) {
  const Program p = read_text(kIso, "iso.cls");
  EXPECT_TRUE(p.warnings.empty()) << p.warnings.front().message;
  EXPECT_EQ(p.source_units, LengthUnit::Inch);
  EXPECT_EQ(p.part_name, "bracket op 10");
  EXPECT_TRUE(p.multax);
  ASSERT_EQ(p.tools.size(), 1u);  // CUTTER then LOADTL: one tool
  EXPECT_EQ(p.tools[0].number, 3);
  EXPECT_NEAR(p.tools[0].diameter_mm, 12.7, kExactMm);
  EXPECT_NEAR(p.tools[0].corner_radius_mm, 6.35, kExactMm);
  EXPECT_NEAR(p.tools[0].length_mm, 50.8, kExactMm);  // h of the 7-parameter form
  EXPECT_TRUE(p.tools[0].is_ball());

  ASSERT_EQ(p.moves.size(), 4u);
  const Move& from = p.moves[0];
  EXPECT_EQ(from.kind, MotionKind::Rapid);
  EXPECT_EQ(from.feed_mm_per_min, 0.0);
  EXPECT_LT((from.tip_in_part_mm - Vector3d(0, 0, 101.6)).norm(), kExactMm);
  EXPECT_EQ(from.line, 10);
  EXPECT_EQ(from.tool_index, 0);
  const Move& g1 = p.moves[1];
  EXPECT_EQ(g1.kind, MotionKind::Feed);
  EXPECT_NEAR(g1.feed_mm_per_min, 20.0 * 25.4, kExactMm);  // a bare FEDRAT is in the file's unit
  EXPECT_LT((g1.tip_in_part_mm - Vector3d(25.4, -12.7, 2.54)).norm(), kExactMm);
  const Move& g2 = p.moves[2];  // joined by '$'
  EXPECT_EQ(g2.line, 12);
  EXPECT_LT((g2.tip_in_part_mm - Vector3d(50.8, 0, 12.7)).norm(), kExactMm);
  EXPECT_LT((g2.axis_in_part - Vector3d(0, 0.6, 0.8)).norm(), kExactMm);
  EXPECT_EQ(p.moves[3].kind, MotionKind::Rapid);
  EXPECT_EQ(p.moves[3].feed_mm_per_min, 0.0);
  EXPECT_LT((p.moves[3].axis_in_part - Vector3d(0, 0.6, 0.8)).norm(), kExactMm);

  using K = Event::Kind;
  std::vector<K> kinds;
  for (const Event& e : p.events) kinds.push_back(e.kind);
  const std::vector<K> expected = {K::Comment, K::ToolChange, K::Comment,    K::SpindleOn, K::CoolantOn,
                                   K::Comment, K::Stop,       K::SpindleOff, K::CoolantOff};
  EXPECT_EQ(kinds, expected);
  ASSERT_EQ(p.events.size(), expected.size());
  EXPECT_EQ(p.events[0].text, "CATIA-like header");
  EXPECT_EQ(p.events[1].line, 5);
  EXPECT_EQ(p.events[1].tool_index, 0);
  EXPECT_EQ(p.events[2].text, "ball 1/2 in");
  EXPECT_NEAR(p.events[3].spindle_rpm, 8000.0, kExactMm);
  EXPECT_FALSE(p.events[3].clockwise);
  EXPECT_EQ(p.events[4].text, "FLOOD");
  EXPECT_EQ(p.events[5].text, "continued");
  EXPECT_EQ(p.events[5].line, 13);
  EXPECT_EQ(p.events[6].before_move, 4u);
  for (size_t i = 1; i < p.events.size(); ++i) {  // ordered by before_move, then line
    EXPECT_LE(p.events[i - 1].before_move, p.events[i].before_move);
    if (p.events[i - 1].before_move == p.events[i].before_move) {
      EXPECT_LE(p.events[i - 1].line, p.events[i].line);
    }
  }
}

TEST(ClIso, SpindleAndFeedForms) {
  const Program p = read_text(
      "UNITS/MM\nSPINDL/RPM,1200,CLW\nSPINDL/OFF\nSPINDL/ON\nSPINDL/ 70.0,RPM,CCLW\n"
      "FEDRAT/MMPM,300\nGOTO/0,0,0\nFEDRAT/10,IPM\nGOTO/1,0,0\nFEDRAT/IPM,2\nGOTO/2,0,0\nFEDRAT/150\nGOTO/3,0,0\n",
      "f.cls");
  const auto on = events_of(p, Event::Kind::SpindleOn);
  ASSERT_EQ(on.size(), 3u);
  EXPECT_NEAR(on[0]->spindle_rpm, 1200, kExactMm);
  EXPECT_TRUE(on[0]->clockwise);
  EXPECT_NEAR(on[1]->spindle_rpm, 1200, kExactMm);  // SPINDL/ON restarts at the last speed
  EXPECT_NEAR(on[2]->spindle_rpm, 70, kExactMm);
  EXPECT_FALSE(on[2]->clockwise);
  EXPECT_EQ(events_of(p, Event::Kind::SpindleOff).size(), 1u);
  ASSERT_EQ(p.moves.size(), 4u);
  EXPECT_EQ(p.source_units, LengthUnit::Millimetre);
  EXPECT_NEAR(p.moves[0].feed_mm_per_min, 300, kExactMm);
  EXPECT_NEAR(p.moves[1].feed_mm_per_min, 254, kExactMm);  // explicit IPM in an mm file
  EXPECT_NEAR(p.moves[2].feed_mm_per_min, 50.8, kExactMm);
  EXPECT_NEAR(p.moves[3].feed_mm_per_min, 150, kExactMm);
  EXPECT_NEAR(p.moves[1].tip_in_part_mm.x(), 1.0, kExactMm);  // positions stay mm
  EXPECT_FALSE(p.multax);
}

TEST(ClIso, UnitDecision) {
  // No UNITS/: the first FEDRAT that names a unit decides, even when it comes after the first GOTO.
  Program p = read_text("GOTO/1,0,0\nFEDRAT/IPM,10\nGOTO/2,0,0\n", "a.cls");
  EXPECT_EQ(p.source_units, LengthUnit::Inch);
  EXPECT_NEAR(p.moves[0].tip_in_part_mm.x(), 25.4, kExactMm);
  // UNITS/ beats FEDRAT.
  p = read_text("FEDRAT/IPM,10\nUNITS/MM\nGOTO/1,0,0\n", "b.cls");
  EXPECT_EQ(p.source_units, LengthUnit::Millimetre);
  EXPECT_NEAR(p.moves[0].tip_in_part_mm.x(), 1.0, kExactMm);
  EXPECT_NEAR(p.moves[0].feed_mm_per_min, 254.0, kExactMm);
  // Nothing said: mm.
  p = read_text("GOTO/1,0,0\n", "c.cls");
  EXPECT_EQ(p.source_units, LengthUnit::Millimetre);
  EXPECT_NEAR(p.moves[0].tip_in_part_mm.x(), 1.0, kExactMm);
  // The option overrides everything.
  ReadOptions mm;
  mm.units = LengthUnit::Millimetre;
  p = read_text("UNITS/INCHES\nGOTO/1,0,0\n", "d.cls", mm);
  EXPECT_EQ(p.source_units, LengthUnit::Millimetre);
  EXPECT_NEAR(p.moves[0].tip_in_part_mm.x(), 1.0, kExactMm);
  ReadOptions inch;
  inch.units = LengthUnit::Inch;
  p = read_text("GOTO/1,0,0\n", "e.cls", inch);
  EXPECT_NEAR(p.moves[0].tip_in_part_mm.x(), 25.4, kExactMm);
}

TEST(ClIso, ToolsMergeAndChange) {
  const Program p = read_text(
      "TOOL PATH/OP1,TOOL,EM10\nTLDATA/MILL,10,1,50\nLOAD/TOOL,5\nGOTO/0,0,0\n"
      "TOOL PATH/OP2,TOOL,EM10\nTLDATA/MILL,10,1,50\nLOAD/TOOL,5\nGOTO/1,0,0\n"  // same tool again: no change
      "CUTTER/6,3\nLOADTL/7\nGOTO/2,0,0\nLOADTL/5\nGOTO/3,0,0\nMULTAX/OFF\n",
      "tools.cls");
  ASSERT_EQ(p.tools.size(), 2u);
  EXPECT_EQ(p.tools[0].number, 5);
  EXPECT_EQ(p.tools[0].name, "EM10");
  EXPECT_NEAR(p.tools[0].corner_radius_mm, 1.0, kExactMm);
  EXPECT_EQ(p.tools[1].number, 7);
  EXPECT_TRUE(p.tools[1].is_ball());
  const auto tc = events_of(p, Event::Kind::ToolChange);
  ASSERT_EQ(tc.size(), 3u);  // 5, 7, back to 5
  EXPECT_EQ(tc[0]->line, 2);
  EXPECT_EQ(tc[1]->tool_index, 1);
  EXPECT_EQ(tc[2]->tool_index, 0);
  ASSERT_EQ(p.moves.size(), 4u);
  EXPECT_EQ(p.moves[0].tool_index, 0);
  EXPECT_EQ(p.moves[1].tool_index, 0);
  EXPECT_EQ(p.moves[2].tool_index, 1);
  EXPECT_EQ(p.moves[3].tool_index, 0);
  EXPECT_EQ(events_of(p, Event::Kind::OperationStart).size(), 2u);
  EXPECT_EQ(p.part_name, "OP1");
  EXPECT_FALSE(p.multax);
}

TEST(ClIso, UnknownRecordWarnsAndContinues) {
  const Program p = read_text("UNITS/MM\nGOTO/0,0,0\n  FOO/1,2\nGOTO/1,0,0\n", "w.cls");
  EXPECT_EQ(p.moves.size(), 2u);
  ASSERT_EQ(p.warnings.size(), 1u);
  EXPECT_EQ(p.warnings[0].where.line, 3);
  EXPECT_EQ(p.warnings[0].where.column, 3);
  EXPECT_EQ(p.warnings[0].where.file, "w.cls");
  EXPECT_NE(p.warnings[0].message.find("unknown record 'FOO' ignored"), std::string::npos);
  // PAINT and NX's listing trailer are known: no warning.
  EXPECT_TRUE(
      read_text("UNITS/MM\nPAINT/COLOR,3\nGOTO/0,0,0\nTool Path Listing has 2 lines.\n", "n.cls").warnings.empty());
}

// Records that move, repeat or replace the motion around them (a canned cycle's GOTOs are hole positions; TRACUT,
// COPY, INDEX, ROTABL move or repeat the path; RETRCT adds a retract; incremental mode and a non-zero ORIGIN change
// what the GOTOs' coordinates mean) are errors naming their line: ignored with a warning, the program
// would not drill, or would cut somewhere else. TRACUT/NOMORE and CYCLE/OFF end such a state and are harmless alone.
TEST(ClIso, RecordsThatChangeTheMotionAreErrorsNotWarnings) {
  for (const auto& [rec, what] : std::vector<std::pair<std::string, std::string>>{
           {"CYCLE/DRILL,DEPTH,12,MMPM,150,CLEAR,3", "canned cycles are not supported"},
           {"CYCLE/DRILL,12,IPM,5,0.1", "canned cycles are not supported"},
           {"TRACUT/1,0,0,10,0,1,0,0,0,0,1,0", "TRACUT/ is not supported"},
           {"COPY/1,XYROT,90,3", "COPY/ is not supported"},
           {"INDEX/1", "INDEX/ is not supported"},
           {"ROTABL/90,CLW", "ROTABL/ is not supported"},
           {"GOHOME/0,0,100", "GOHOME/ is not supported"},
           {"RETRCT", "RETRCT is not supported"},
           {"SET/MODE,INCR", "incremental CL coordinates are not supported"},
           {"MODE/INCR", "incremental CL coordinates are not supported"},
           {"ORIGIN/10,0,0", "ORIGIN/10,0,0 is not supported"},
           {"ORIGIN/ZERO", "is not supported"},
           {"TLAXIS/NORMAL", "TLAXIS/"}}) {
    const InputError e = error_of("UNITS/MM\nGOTO/0,0,5\n" + rec + "\nGOTO/10,0,5\n");
    EXPECT_EQ(e.where().line, 3) << rec;
    EXPECT_NE(std::string(e.what()).find(what), std::string::npos) << rec << ": " << e.what();
  }
  const Program p = read_text("UNITS/MM\nTRACUT/NOMORE\nCYCLE/OFF\nORIGIN/0,0,0\nGOTO/0,0,0\n", "ok.cls");
  EXPECT_TRUE(p.warnings.empty());
  EXPECT_EQ(p.moves.size(), 1u);
  // Absolute mode is what cscam reads anyway: a warning that it was ignored, no error.
  const Program abs = read_text("UNITS/MM\nSET/MODE,ABSOL\nGOTO/0,0,0\n", "abs.cls");
  EXPECT_EQ(abs.warnings.size(), 1u);
  EXPECT_EQ(abs.moves.size(), 1u);
}

// TLAXIS/i,j,k gives the tool axis of the GOTOs without one (3-axis GOTOs after a tilted axis: a 3+2 stretch).
TEST(ClIso, TlaxisSetsTheAxisOfThreeAxisGotos) {
  const Program p =
      read_text("UNITS/MM\nMULTAX\nTLAXIS/0,1,1\nGOTO/0,0,0\nGOTO/1,0,0,0,0,1\nTLAXIS/1,0,0\nGOTO/2,0,0\n", "t.cls");
  ASSERT_EQ(p.moves.size(), 3u);
  EXPECT_LT((p.moves[0].axis_in_part - Eigen::Vector3d(0, 1, 1).normalized()).norm(), 1e-12);
  EXPECT_LT((p.moves[1].axis_in_part - Eigen::Vector3d::UnitZ()).norm(), 1e-12);
  EXPECT_LT((p.moves[2].axis_in_part - Eigen::Vector3d::UnitX()).norm(), 1e-12);
  EXPECT_TRUE(p.warnings.empty());
  EXPECT_NE(std::string(error_of("UNITS/MM\nTLAXIS/0,0,0\nGOTO/0,0,0\n").what()).find("TLAXIS"), std::string::npos);
}

// NX's drilling tool: TLDATA/DRILL,d,point angle,length,... (the point angle is no corner radius: a 118 deg point
// was refused as a corner radius of 118 mm). Other tool types are read as a mill's numbers, with a warning.
TEST(ClIso, TldataDrillIsADrillNotACornerRadius) {
  const Program p = read_text("UNITS/MM\nTLDATA/DRILL,8,118,50,35\nLOAD/TOOL,3\nGOTO/0,0,10\nGOTO/0,0,0\n", "d.cls");
  ASSERT_EQ(p.tools.size(), 1u);
  EXPECT_DOUBLE_EQ(p.tools[0].diameter_mm, 8.0);
  EXPECT_DOUBLE_EQ(p.tools[0].corner_radius_mm, 0.0);
  EXPECT_DOUBLE_EQ(p.tools[0].length_mm, 50.0);
  EXPECT_NE(std::string(error_of("UNITS/MM\nTLDATA/DRILL,8,200,50\nGOTO/0,0,0\n").what()).find("point angle"),
            std::string::npos);
  const Program t = read_text("UNITS/MM\nTLDATA/TCUTTER,20,1,60\nGOTO/0,0,0\n", "t.cls");
  ASSERT_EQ(t.warnings.size(), 1u);
  EXPECT_NE(t.warnings[0].message.find("TLDATA/TCUTTER read as TLDATA/MILL"), std::string::npos);
  ASSERT_EQ(t.tools.size(), 1u);
  EXPECT_DOUBLE_EQ(t.tools[0].corner_radius_mm, 1.0);
}

TEST(ClIso, ExamplesParse) {
  const Program iso = read_file(source_path("examples/cl/iso_catia.cls"));
  EXPECT_TRUE(iso.warnings.empty());
  EXPECT_EQ(iso.source_units, LengthUnit::Millimetre);
  EXPECT_GT(iso.moves.size(), 5u);
  EXPECT_EQ(iso.tools.size(), 1u);
  const Program csv = read_file(source_path("examples/cl/points_csv.cls"));
  EXPECT_GT(csv.moves.size(), 3u);
  EXPECT_TRUE(csv.multax);
}

// ------------------------------------------------------------------------------------------------------------
// CSV

TEST(ClCsv, WithHeaderAndFeed) {
  const Program p = read_text(
      "# exported points\nx,y,z,i,j,k,feed\n\n1,2,3,0,0,1,500\n# a comment\n4, 5, 6, 0, 3, 4\n7,8,9,0,0,2,250\n",
      "p.csv");
  ASSERT_EQ(p.moves.size(), 3u);
  EXPECT_EQ(p.source_units, LengthUnit::Millimetre);
  EXPECT_TRUE(p.multax);
  EXPECT_LT((p.moves[0].tip_in_part_mm - Vector3d(1, 2, 3)).norm(), kExactMm);
  EXPECT_NEAR(p.moves[0].feed_mm_per_min, 500, kExactMm);
  EXPECT_EQ(p.moves[0].line, 4);
  EXPECT_LT((p.moves[1].axis_in_part - Vector3d(0, 0.6, 0.8)).norm(), kExactMm);
  EXPECT_NEAR(p.moves[1].feed_mm_per_min, 500, kExactMm);  // carried
  EXPECT_NEAR(p.moves[2].feed_mm_per_min, 250, kExactMm);
  EXPECT_EQ(p.moves[2].line, 7);
  EXPECT_EQ(events_of(p, Event::Kind::Comment).size(), 2u);
}

TEST(ClCsv, WithoutHeaderOrFeed) {
  const Program p = read_text("1,2,3,0,0,1\r\n4,5,6,1,0,0\r\n", "p.csv");
  ASSERT_EQ(p.moves.size(), 2u);
  EXPECT_LT((p.moves[1].tip_in_part_mm - Vector3d(4, 5, 6)).norm(), kExactMm);
  EXPECT_LT((p.moves[1].axis_in_part - Vector3d(1, 0, 0)).norm(), kExactMm);
  EXPECT_EQ(p.moves[1].kind, MotionKind::Feed);
  ReadOptions inch;
  inch.units = LengthUnit::Inch;
  const Program q = read_text("1,2,3,0,0,1,10\n", "p.csv", inch);
  EXPECT_NEAR(q.moves[0].tip_in_part_mm.z(), 3 * 25.4, kExactMm);
  EXPECT_NEAR(q.moves[0].feed_mm_per_min, 254, kExactMm);
}

TEST(ClCsv, Errors) {
  InputError e = error_of("1,2,3,0,0,1\n1,2,3,0,0,0\n", "p.csv");
  EXPECT_NE(std::string(e.what()).find("p.csv:2:7:"), std::string::npos) << e.what();
  e = error_of("1,2,3,0,0,1\n1,2,3,0,0\n", "p.csv");
  EXPECT_NE(std::string(e.what()).find("p.csv:2:7:"), std::string::npos) << e.what();
  EXPECT_NE(std::string(e.what()).find("got 5"), std::string::npos) << e.what();
  e = error_of("1,2,3,0,0,1\n1,2,x3,0,0,1\n", "p.csv");
  EXPECT_NE(std::string(e.what()).find("p.csv:2:5:"), std::string::npos) << e.what();
}

// ------------------------------------------------------------------------------------------------------------
// Error paths: each names file:line:column of the offending field.

void expect_error_at(const std::string& text, const std::string& where, const std::string& words) {
  const InputError e = error_of(text);
  const std::string what = e.what();
  EXPECT_NE(what.find("t.cls:" + where + ":"), std::string::npos) << what;
  EXPECT_NE(what.find(words), std::string::npos) << what;
}

TEST(ClErrors, FileLineColumn) {
  expect_error_at("UNITS/MM\nGOTO/1,2,3,0,0,0\n", "2:12", "zero-length tool axis");
  expect_error_at("UNITS/MM\nGOTO/1,2,3,0,0,1e-300\n", "2:12", "zero-length");
  expect_error_at("GOTO/1,nan,3\n", "1:8", "not a finite number");
  expect_error_at("GOTO/1,2,3,0,NaN,1\n", "1:14", "not a finite number");
  expect_error_at("GOTO/1,2,-inf\n", "1:10", "not a finite number");
  expect_error_at("GOTO/1,2,1e999\n", "1:10", "out of range");
  expect_error_at("GOTO/1,1e308,3\n", "1:8", "beyond any machine");
  expect_error_at("GOTO/1,2,3,4\n", "1:12", "expected 3 (x,y,z) or 6 (x,y,z,i,j,k), got 4");
  expect_error_at("GOTO/1,2,3,0,0,1,7\n", "1:18", "got 7");
  expect_error_at("GOTO/1,2\n", "1:9", "got 2");
  expect_error_at("GOTO/1.2.3,2,3\n", "1:6", "malformed number (expected a number, got '1.2.3')");
  expect_error_at("GOTO/1, abc ,3\n", "1:9", "got 'abc'");
  expect_error_at("GOTO/1,,3\n", "1:8", "malformed number");
  expect_error_at("GOTO/ 1, 2, $\n   3, 0,0,$\n  0\n", "2:7", "zero-length");  // inside a continuation
  expect_error_at("GOTO/0,0,0\nCIRCLE/0,0,0,0,0,0,5\nGOTO/1,0,0\n", "2:14", "zero-length circle axis");
  expect_error_at("FEDRAT/IPM,1.0.0\n", "1:12", "malformed number");
  expect_error_at("CUTTER/abc\n", "1:8", "malformed number");
  expect_error_at("UNITS/FEET\n", "1:7", "unknown unit");
  // A circle no machine can travel, and end points that do not lie on the circle at all (fuzzing found the
  // first: a few bytes expanded into half a million points).
  expect_error_at("GOTO/40,20,6\nCIRCLE/40,15,6,0,0,-1,500000000\nGOTO/40,20,6\n", "2:23", "beyond any machine");
  expect_error_at("FEDRAT/100\nGOTO/10,0,0\nCIRCLE/0,0,0,0,0,1,5\nGOTO/0,-5,0\n", "3:1", "off the circle");
  // A start at the centre is a radius off the circle, not an arc to straighten.
  expect_error_at("FEDRAT/100\nGOTO/0,0,10\nCIRCLE/0,0,0,0,0,1,5,0.01\nGOTO/20,0,0\n", "3:1", "15.0000 mm off");
  expect_error_at("FEDRAT/100\nGOTO/5,0,0\nCIRCLE/0,0,0,0,0,1,5\nCIRCLE/0,0,0,0,0,1,5\nGOTO/0,5,0\n", "4:1",
                  "follows the CIRCLE/ of line 3 without the GOTO/");
  // A zero feed, and a feed per revolution with no spindle speed to convert it, are not feeds.
  expect_error_at("FEDRAT/0,MMPM\nGOTO/1,2,3\n", "1:8", "feed must be positive");
  expect_error_at("FEDRAT/0.1,MMPR\nGOTO/1,2,3\n", "1:1", "feed per revolution (IPR/MMPR) before any spindle");
}

// MULTAX/OFF is 3-axis mode: the tool axis is +Z (or the last TLAXIS/) until a GOTO/ gives one again.
TEST(ClIso, MultaxOffMeansAVerticalTool) {
  const Program p = read_text(
      "UNITS/MM\nMULTAX/ON\nFEDRAT/MMPM,600\nGOTO/0,0,0,0.1,0,0.995\nMULTAX/OFF\nGOTO/10,0,0\nMULTAX/ON\n"
      "GOTO/20,0,0\nGOTO/30,0,0,0,0.6,0.8\n",
      "m.cls");
  ASSERT_EQ(p.moves.size(), 4u);
  EXPECT_GT((p.moves[0].axis_in_part - Eigen::Vector3d::UnitZ()).norm(), 0.05);
  EXPECT_LT((p.moves[1].axis_in_part - Eigen::Vector3d::UnitZ()).norm(), kExactMm);
  EXPECT_LT((p.moves[2].axis_in_part - Eigen::Vector3d::UnitZ()).norm(), kExactMm);  // until a GOTO/ gives one
  EXPECT_LT((p.moves[3].axis_in_part - Eigen::Vector3d(0, 0.6, 0.8)).norm(), kExactMm);
  EXPECT_TRUE(p.multax);
  // A fixed axis given by TLAXIS/ (a 3+2 stretch) is kept by MULTAX/OFF: the 3-coordinate GOTOs after it were cut
  // with a vertical tool.
  const Program t = read_text(
      "UNITS/MM\nFEDRAT/MMPM,600\nTLAXIS/0,-0.6,0.8\nGOTO/0,0,0\nGOTO/0,0,0,0.1,0,0.995\nMULTAX/OFF\n"
      "GOTO/10,0,0\n",
      "t.cls");
  ASSERT_EQ(t.moves.size(), 3u);
  EXPECT_LT((t.moves[0].axis_in_part - Eigen::Vector3d(0, -0.6, 0.8)).norm(), kExactMm);
  EXPECT_LT((t.moves[2].axis_in_part - Eigen::Vector3d(0, -0.6, 0.8)).norm(), kExactMm);
}

// Inputs found by fuzz/cl_fuzz (tests/data/fuzz-regressions): each is refused quickly with a located error.
TEST(ClErrors, FuzzRegressions) {
  for (const char* file : {"cl-huge-circle.cls"}) {
    std::ifstream in(test::source_path(std::string("tests/data/fuzz-regressions/") + file), std::ios::binary);
    ASSERT_TRUE(in) << file;
    const std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    try {
      (void)read_text(text, file);
      ADD_FAILURE() << file << ": read without an error";
    } catch (const InputError& e) {
      EXPECT_GT(e.where().line, 0) << e.what();
    }
  }
}

TEST(ClErrors, ErrorCarriesLocation) {
  const InputError e = error_of("UNITS/MM\n\nGOTO/1,2,3,0,0,0\n", "x.cls");
  EXPECT_EQ(e.where().file, "x.cls");
  EXPECT_EQ(e.where().line, 3);
  EXPECT_EQ(e.where().column, 12);
}

TEST(ClErrors, MissingFileNamesIt) {
  const std::string path = "/nonexistent/dir/missing_part.cls";
  try {
    (void)read_file(path);
    FAIL() << "no error";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find(path), std::string::npos) << e.what();
  }
}

// ------------------------------------------------------------------------------------------------------------
// Hostile input: never a silent success.

TEST(ClHostile, EmptyBinaryAndMotionlessFilesHaveNoMotionRecords) {
  for (const std::string text : {std::string(), std::string("\n  \r\n\t\n"), std::string("\xEF\xBB\xBF")}) {
    const InputError e = error_of(text, "empty.cls");
    EXPECT_EQ(e.where().file, "empty.cls");
    EXPECT_EQ(e.where().line, 1);
    EXPECT_NE(e.message().find("no motion records"), std::string::npos) << e.what();
  }
  // Binary: a NUL byte (here on line 2), or mostly control characters.
  InputError e = error_of(std::string("GOTO/1,2,3\nab\0cd\n", 17), "bin.cls");
  EXPECT_EQ(e.where().line, 2);
  EXPECT_EQ(e.where().column, 3);
  EXPECT_NE(e.message().find("no motion records"), std::string::npos) << e.what();
  EXPECT_NE(e.message().find("binary"), std::string::npos) << e.what();
  std::string noise;
  auto rng = test::rng(7);
  for (int i = 0; i < 3000; ++i) noise.push_back(static_cast<char>(1 + rng() % 255));
  e = error_of(noise, "noise.bin");
  EXPECT_NE(e.message().find("binary"), std::string::npos) << e.what();
  // Text without a single motion (the error names the last line).
  e = error_of("$$ just comments\nUNITS/MM\nFEDRAT/MMPM,100\nSPINDL/1000\n", "still.cls");
  EXPECT_EQ(e.where().file, "still.cls");
  EXPECT_EQ(e.where().line, 4);
  EXPECT_NE(e.message().find("no motion records"), std::string::npos) << e.what();
  // Motion only after FINI does not count.
  EXPECT_NE(error_of("UNITS/MM\nFINI\nGOTO/1,2,3\n").message().find("no motion records"), std::string::npos);
  // Binary through read_file as well.
  const std::string path = ::testing::TempDir() + "/cscam_cl_binary.cls";
  {
    std::ofstream out(path, std::ios::binary);
    out << std::string(1, '\x7f') << std::string("ELF\x02\x01\x01\0\0\0", 9);
  }
  try {
    (void)read_file(path);
    ADD_FAILURE() << "no error for a binary file";
  } catch (const InputError& ex) {
    EXPECT_EQ(ex.where().file, path);
    EXPECT_NE(ex.message().find("no motion records"), std::string::npos) << ex.what();
  }
  std::remove(path.c_str());
}

TEST(ClHostile, MissingFeedIsAnErrorUnlessADefaultIsGiven) {
  ReadOptions strict;
  strict.require_feed = true;
  // No feed anywhere: the first feed move is named.
  const std::string nofeed = "UNITS/MM\nRAPID\nGOTO/0,0,5\nGOTO/0,0,0\nGOTO/1,0,0\n";
  try {
    (void)read_text(nofeed, "nofeed.cls", strict);
    ADD_FAILURE() << "no error without a feed";
  } catch (const InputError& e) {
    EXPECT_EQ(e.where().str(), "nofeed.cls:4");
    EXPECT_NE(e.message().find("no feed rate anywhere"), std::string::npos) << e.what();
    EXPECT_NE(e.message().find("--default-feed"), std::string::npos) << e.what();
  }
  // A feed move before the first FEDRAT/.
  try {
    (void)read_text("UNITS/MM\nGOTO/0,0,0\nFEDRAT/MMPM,100\nGOTO/1,0,0\n", "late.cls", strict);
    ADD_FAILURE() << "no error for a feed move before FEDRAT";
  } catch (const InputError& e) {
    EXPECT_EQ(e.where().str(), "late.cls:2");
    EXPECT_NE(e.message().find("before any feed rate"), std::string::npos) << e.what();
  }
  // CSV without a feed column.
  EXPECT_THROW((void)read_text("0,0,0,0,0,1\n1,0,0,0,0,1\n", "p.csv", strict), InputError);
  // Rapids alone need no feed.
  EXPECT_NO_THROW((void)read_text("UNITS/MM\nFROM/0,0,50\nRAPID\nGOTO/0,0,5\n", "r.cls", strict));
  // With a default feed: every unfed feed move gets it, with one warning.
  ReadOptions dflt = strict;
  dflt.default_feed_mm_per_min = 250.0;
  const Program p = read_text(nofeed, "nofeed.cls", dflt);
  ASSERT_EQ(p.moves.size(), 3u);
  EXPECT_EQ(p.moves[0].feed_mm_per_min, 0.0);  // the rapid
  EXPECT_EQ(p.moves[1].feed_mm_per_min, 250.0);
  EXPECT_EQ(p.moves[2].feed_mm_per_min, 250.0);
  ASSERT_EQ(p.warnings.size(), 1u);
  EXPECT_EQ(p.warnings[0].where.str(), "nofeed.cls:4");
  EXPECT_NE(p.warnings[0].message.find("default feed 250"), std::string::npos) << p.warnings[0].message;
  // A default never overrides the file's own feed.
  const Program q = read_text("UNITS/MM\nFEDRAT/MMPM,100\nGOTO/1,0,0\n", "f.cls", dflt);
  EXPECT_EQ(q.moves[0].feed_mm_per_min, 100.0);
  EXPECT_TRUE(q.warnings.empty());
  // The default itself must be a feed.
  dflt.default_feed_mm_per_min = -5;
  EXPECT_THROW((void)read_text(nofeed, "nofeed.cls", dflt), InputError);
  // Without require_feed (verify's reading), no error.
  EXPECT_NO_THROW((void)read_text(nofeed, "nofeed.cls"));
}

TEST(ClHostile, AssumedMillimetresAreAWarning) {
  Program p = read_text("FEDRAT/100\nGOTO/1,0,0\nGOTO/2,0,0\n", "nounits.cls");
  ASSERT_EQ(p.warnings.size(), 1u);
  EXPECT_EQ(p.warnings[0].where.str(), "nounits.cls:2");
  EXPECT_NE(p.warnings[0].message.find("taken as mm"), std::string::npos) << p.warnings[0].message;
  p = read_text("0,0,0,0,0,1,100\n", "p.csv");
  ASSERT_EQ(p.warnings.size(), 1u);
  EXPECT_NE(p.warnings[0].message.find("taken as mm"), std::string::npos);
  // UNITS/, FEDRAT/ with a unit, or the option: no warning.
  EXPECT_TRUE(read_text("UNITS/MM\nFEDRAT/100\nGOTO/1,0,0\n", "u.cls").warnings.empty());
  EXPECT_TRUE(read_text("FEDRAT/MMPM,100\nGOTO/1,0,0\n", "f.cls").warnings.empty());
  ReadOptions mm;
  mm.units = LengthUnit::Millimetre;
  EXPECT_TRUE(read_text("FEDRAT/100\nGOTO/1,0,0\n", "o.cls", mm).warnings.empty());
  EXPECT_TRUE(read_text("0,0,0,0,0,1,100\n", "p.csv", mm).warnings.empty());
}

TEST(ClErrors, BadArcTolerance) {
  ReadOptions o;
  o.arc_tolerance_mm = 0;
  EXPECT_THROW((void)read_text("GOTO/0,0,0\n", "t.cls", o), InputError);
}

// A large file is read with the GOTO/ numbers converted ahead in parallel (more than one thread): the program, its
// warnings and its errors must be those of the reading on one thread, whatever the lines look like.
TEST(ClReader, NumbersReadAheadGiveTheSameProgramAndErrors) {
  std::string text = "PARTNO AHEAD\nUNITS/MM\nMULTAX/ON\nFEDRAT/MMPM,1500\n";
  const char* forms[] = {"GOTO/{:.4f},{:.4f},{:.4f},0.0000000,0.0000000,1.0000000\n",
                         "goto / {:.3f} , {:.4f},{:.4f} $$ a comment\n",
                         "GOTO/+{:.4f},{:.4f},{:.2e}\n",
                         "GOTO/{:.4f},$\n  {:.4f},{:.4f}\n",
                         "  GOTO/{:.4f},{:.4f},{:.4f},0,0,1   \r\n",
                         "GOTO/{:.4f},{:.4f},{:.4f},0.6,0,0.8\n"};
  for (int i = 0; text.size() < (std::size_t{3} << 20); ++i) {
    const double x = 0.01 * i, y = std::sin(0.001 * i), z = 1.0 + 1e-3 * (i % 97);
    text += fmt::format(fmt::runtime(forms[i % 6]), x, y, z);
    if (i % 1000 == 0) text += "RAPID\n";
  }
  auto read_at = [&](int threads, const std::string& t) {
    tbb::task_arena arena(threads);
    return arena.execute([&] { return read_text(t, "ahead.cls", {}); });
  };
  const Program one = read_at(1, text), two = read_at(2, text);
  ASSERT_EQ(one.moves.size(), two.moves.size());
  for (std::size_t i = 0; i < one.moves.size(); ++i) {
    EXPECT_EQ(one.moves[i].tip_in_part_mm, two.moves[i].tip_in_part_mm) << i;
    EXPECT_EQ(one.moves[i].axis_in_part, two.moves[i].axis_in_part) << i;
    EXPECT_EQ(one.moves[i].line, two.moves[i].line) << i;
    EXPECT_EQ(one.moves[i].kind, two.moves[i].kind) << i;
  }
  ASSERT_EQ(one.warnings.size(), two.warnings.size());
  // Broken GOTO/ lines deep in the file: the same error (line, column, words) at 1 and 2 threads.
  for (const char* bad : {"GOTO/1.0,2.0,x3\n", "GOTO/1.0,2.0\n", "GOTO/1,2,3,0,0\n", "GOTO/1,2,1e999\n",
                          "GOTO/1,2,3,0,0,0\n", "GOTO/1,2,3,4,5,6,7\n"}) {
    std::string broken = text;
    broken.insert(broken.find('\n', broken.size() * 2 / 3) + 1, bad);
    std::string e1, e2;
    try {
      read_at(1, broken);
    } catch (const InputError& e) {
      e1 = e.what();
    }
    try {
      read_at(2, broken);
    } catch (const InputError& e) {
      e2 = e.what();
    }
    EXPECT_FALSE(e1.empty()) << bad;
    EXPECT_EQ(e1, e2) << bad;
  }
}

TEST(ClFeed, AFeedPerRevolutionFollowsTheSpindleSpeed) {
  // 0.1 mm/rev at 5000 rpm is 500 mm/min; after SPINDL/RPM,2000 the same chip load is 200 mm/min (it stayed 500,
  // 2.5 times too fast). A per-minute feed does not follow the spindle.
  const Program p = read_text(
      "UNITS/MM\nSPINDL/RPM,5000\nFEDRAT/MMPR,0.1\nGOTO/0,0,0\nGOTO/10,0,0\nSPINDL/RPM,2000\nGOTO/20,0,0\n"
      "FEDRAT/MMPM,300\nSPINDL/RPM,6000\nGOTO/30,0,0\n",
      "rev.cls");
  ASSERT_EQ(p.moves.size(), 4u);
  EXPECT_NEAR(p.moves[1].feed_mm_per_min, 500.0, kExactMm);
  EXPECT_NEAR(p.moves[2].feed_mm_per_min, 0.1 * 2000.0, kExactMm);
  EXPECT_NEAR(p.moves[3].feed_mm_per_min, 300.0, kExactMm);
}

}  // namespace
}  // namespace cscam::cl
