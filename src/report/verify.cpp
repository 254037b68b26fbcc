#include "cscam/report/verify.hpp"

#include <fmt/format.h>
#include <tbb/blocked_range.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <fstream>
#include <limits>
#include <optional>
#include <span>
#include <sstream>
#include <stdexcept>
#include <string_view>

#include "cscam/core/default_init.hpp"
#include "cscam/core/error.hpp"
#include "cscam/core/parallel.hpp"
#include "cscam/core/rotations.hpp"
#include "cscam/core/segment.hpp"
#include "cscam/core/tolerances.hpp"
#include "cscam/core/units.hpp"
#include "cscam/kin/track.hpp"
#include "cscam/report/json.hpp"
#include "cscam/report/letters.hpp"

namespace cscam::report {

namespace {

using Vec3 = Eigen::Vector3d;

// No default member values: a million-segment array is left unwritten by resize() and filled in parallel.
struct ClSeg {
  Vec3 p0, p1, u0, u1;
  int line;
  bool arc_interior;  ///< p1 is a point generated inside a CIRCLE/ (an NC arc passes it between its ends)
  double th;          ///< slerp_angle(u0, u1)
  double sin_th;      ///< sin(th)
};

/// The angle slerp() turns through from a to b.
double slerp_angle(const Vec3& a, const Vec3& b) { return std::acos(std::clamp(a.dot(b), -1.0, 1.0)); }

/// slerp with its angle th = slerp_angle(a, b) and sin(th) computed once (per CL segment).
Vec3 slerp(const Vec3& a, const Vec3& b, double th, double sin_th, double s) {
  if (th < 1e-9) return ((1 - s) * a + s * b).normalized();
  return (std::sin((1 - s) * th) / sin_th * a + std::sin(s * th) / sin_th * b).normalized();
}

/// Distance from p to the segment and the segment parameter of the closest point.
double seg_distance(const ClSeg& s, const Vec3& p, double& t) {
  const Vec3 ab = s.p1 - s.p0;
  return point_segment_distance(p, s.p0, ab, ab.squaredNorm(), &t);
}

/// The nearest of the CL segments [lo, hi) to p: its distance, and its index and parameter in `arg` and `t` (left as
/// they are, and +inf returned, for an empty range).
double nearest_in(std::span<const ClSeg> segs, const Vec3& p, std::size_t lo, std::size_t hi, std::size_t& arg,
                  double& t) {
  double best = std::numeric_limits<double>::infinity();
  for (std::size_t k = lo; k < hi; ++k) {
    double tk;
    const double d = seg_distance(segs[k], p, tk);
    if (d < best) {
      best = d;
      arg = k;
      t = tk;
    }
  }
  return best;
}

/// How many CL segments either side of the cursor the tip search reaches (a path that doubles back passes segments a
/// few CL points behind it), and either side of the nearest one a sample's axis may be matched on
/// (best_axis_dot_near): the same window, since a sample may be wherever its tip could have been placed.
constexpr std::size_t kWindowSegs = 64;

/// The best match of the tool axis u along the CL segment s where its tip is within tip_tol of p: the largest
/// u . slerp(u0, u1, t) over the stretch of t whose CL tip lies within tip_tol of p (-2 when none does). On a segment
/// shorter than the tolerance the projection of p fixes no parameter: the machine may be anywhere along that stretch
/// of the orientation, and its axis is judged by the nearest there.
double best_axis_dot_near(const ClSeg& s, const Vec3& p, const Vec3& u, double tip_tol) {
  const Vec3 ab = s.p1 - s.p0;
  const double L2 = ab.squaredNorm();
  double lo = 0.0, hi = 1.0;
  if (L2 > 0) {
    const double t_line = (p - s.p0).dot(ab) / L2;  // on the line, unclamped
    const double h2 = (s.p0 + t_line * ab - p).squaredNorm();
    if (h2 > tip_tol * tip_tol) return -2.0;
    const double half = std::sqrt((tip_tol * tip_tol - h2) / L2);
    lo = std::max(0.0, t_line - half);
    hi = std::min(1.0, t_line + half);
    if (lo > hi) return -2.0;
  } else if ((s.p0 - p).norm() > tip_tol) {
    return -2.0;
  }
  return s.sin_th < 1e-12 ? std::max(u.dot(s.u0), u.dot(s.u1))
                          : rot::arc_best_dot(s.u0, s.u1, s.th, s.sin_th, u, lo, hi);
}

/// A feed block that moves the tool only along its own axis, away from the CL path (a post's retract
/// before a flip or unwind, or the plunge back): every sample lies on the line through the block's start
/// along its axis, the axis stays within tolerance, and no sample is below the CL path (no gouge).
/// `poses` are the FK samples of the block (0..n at qa + i/n (qb - qa)) and FK(qb) at index n + 1;
/// `cl_point_near(p)` gives the nearest CL path point and its axis.
/// `slack_mm` / `slack_rad`: how far the move may leave its samples between them (0 for fixed sampling).
/// `chain` (in/out): the CL point (and its axis) the last departure was judged against. A retract or plunge written
/// in several blocks (a PKM's, whose joints move the tip straight only piece by piece) has pieces with neither end on
/// the path: they are judged against that point when it lies on their line. Set to the point this block was judged
/// against when it is a departure.
template <typename Near>
bool departure(const kin::Posed* poses, int n, double tip_tol, double axis_tol_rad, double slack_mm, double slack_rad,
               double ball_r, Near&& cl_point_near, std::optional<std::pair<Vec3, Vec3>>& chain) {
  const kin::Posed &pa = poses[0], &pb = poses[n + 1];
  if ((pb.tip_mm - pa.tip_mm).norm() <= tip_tol) return false;
  const double room_mm = tip_tol - slack_mm;
  // The geometric tests of every sample first: a cutting block fails them at once, before any CL lookup (the tip
  // off the axis line first: the cosine of the axis test is then only taken for a block along its axis).
  for (int i = 0; i <= n; ++i) {
    const kin::Posed& p = i == n ? pb : poses[i];
    if ((p.tip_mm - pa.tip_mm).cross(pa.axis).norm() > room_mm) return false;
  }
  const double cos_axis_tol = std::cos(std::max(0.0, axis_tol_rad - slack_rad));
  for (int i = 0; i <= n; ++i) {
    const kin::Posed& p = i == n ? pb : poses[i];
    if (p.axis.dot(pa.axis) < cos_axis_tol) return false;
  }
  // Below the path: judged against the CL point the block leaves from or comes down to (the end on the path). A
  // retract that rises past the next cut, a few millimetres above and beside (a path climbing level by level), is
  // not below that cut's points; only a block with neither end on the path is judged by the nearest point.
  const auto ctrl_of = [&](const kin::Posed& p) -> Vec3 { return p.tip_mm + ball_r * p.axis; };
  std::optional<std::pair<Vec3, Vec3>> anchor;
  for (const kin::Posed* end : {&pa, &pb}) {
    const Vec3 at_end = ctrl_of(*end);
    const auto [c, u] = cl_point_near(at_end);
    if ((at_end - c).norm() <= tip_tol) {
      anchor = std::pair<Vec3, Vec3>(c, u);
      break;
    }
  }
  if (!anchor && chain && (chain->first - ctrl_of(pa)).cross(pa.axis).norm() <= room_mm) anchor = chain;
  for (int i = 0; i <= n; ++i) {
    const kin::Posed& p = i == n ? pb : poses[i];
    const Vec3 ctrl = ctrl_of(p);  // the compared point: tip, or ball centre
    const auto [c, u] = anchor ? *anchor : cl_point_near(ctrl);
    if ((ctrl - c).dot(u) < -room_mm) return false;
  }
  chain = anchor;
  return true;
}

/// A tool-tip-control program holds the tip (part frame) in its linear words and the tool vector in its
/// rotary words; the control moves both linearly between blocks.
class TipWordsKinematics final : public kin::Kinematics {
 public:
  TipWordsKinematics(const kin::Kinematics& machine_kin, bool gnomonic)
      : k_(machine_kin),
        virtual_wrist_(machine_kin.traits().tcp_rotary_words == kin::Traits::TcpRotaryWords::VirtualWrist),
        gnomonic_(gnomonic) {
    for (int i = 0; i < 5; ++i)
      if (!k_.axes()[static_cast<size_t>(i)].rotary()) lin_[static_cast<size_t>(nlin_++)] = i;
  }
  [[nodiscard]] const std::vector<kin::AxisInfo>& axes() const override { return k_.axes(); }
  [[nodiscard]] std::array<int, 2> rotary_pair() const override { return k_.rotary_pair(); }
  [[nodiscard]] kin::Posed forward(const kin::Axes& q) const override {
    kin::Posed p;
    p.tip_mm = Vec3(q[lin_[0]], q[lin_[1]], q[lin_[2]]);
    const auto rp = k_.rotary_pair();
    if (gnomonic_) {
      // Vector form: the rotary slots hold the vector's gnomonic coordinates (x/z, y/z), in which the great
      // circle between two vectors is the straight line.
      p.axis = Vec3(q[rp[0]], q[rp[1]], 1.0).normalized();
    } else if (virtual_wrist_) {
      // Virtual wrist angles of an untilted platform (the post's Cartesian words): u(C, A).
      const double c = q[rp[0]], a = q[rp[1]];
      p.axis = Vec3(-std::sin(a) * std::sin(c), -std::sin(a) * std::cos(c), std::cos(a));
    } else if (!k_.tool_axis_at(q[rp[0]], q[rp[1]], p.tip_mm, p.axis)) {
      p.axis = Vec3::Constant(std::numeric_limits<double>::quiet_NaN());
    }
    return p;
  }
  /// The tip is linear in the words (no acceleration); the axis turns with the rotary words: through the machine's
  /// rotaries (its own bound), or through the virtual wrist's two turns (their spans summed). The vector form's
  /// gnomonic interpolation has no bound here (fixed sampling).
  bool motion_bound(const kin::Axes& qa, const kin::Axes& qb, kin::MotionBound& out) const override {
    if (gnomonic_) return false;
    const auto rp = k_.rotary_pair();
    if (virtual_wrist_) {
      // u = sin A w(C) + cos A z, w(C) a horizontal unit vector: |u'| <= |dA| + |sin A| |dC| and
      // |u''| <= dA^2 + 2 |dA| |dC| + |sin A| dC^2 (t in [0, 1]). A turn of C weighs only by sin A: at the pole the
      // vector does not move whatever C does (the XMINI's wrist flipping C half a turn there was judged 0.022 deg off).
      const double dc = std::abs(qb[rp[0]] - qa[rp[0]]), da = std::abs(qb[rp[1]] - qa[rp[1]]);
      const double a_max = std::max(std::abs(qa[rp[1]]), std::abs(qb[rp[1]]));  // A is linear in t: |A| peaks at an end
      const double s = a_max >= 0.5 * kPi ? 1.0 : std::sin(a_max);
      out.axis_rate_rad = da + s * dc;
      out.axis_accel = da * da + 2.0 * da * dc + s * dc * dc;
    } else if (!k_.motion_bound(qa, qb, out)) {  // its axis bound depends on the rotaries only
      return false;
    }
    out.tip_accel_mm = 0.0;
    return std::isfinite(out.axis_rate_rad);
  }
  void inverse_all(const kin::Posed&, const kin::Axes*, std::vector<kin::Solution>&) const override {
    throw std::logic_error("TipWordsKinematics has no inverse");
  }
  void inverse_branches(const kin::Posed&, const kin::Axes*, std::vector<kin::Solution>&) const override {
    throw std::logic_error("TipWordsKinematics has no inverse");
  }
  bool solve_for_rotaries(const kin::Posed&, kin::Axes&) const override { return false; }
  bool tool_axis_at(double, double, const Vec3&, Vec3&) const override { return false; }
  [[nodiscard]] kin::Traits traits() const override { return k_.traits(); }

 private:
  const kin::Kinematics& k_;
  bool virtual_wrist_;
  bool gnomonic_;
  std::array<int, 3> lin_{};
  int nlin_ = 0;
};

}  // namespace

bool uses_tool_tip_control(const std::string& t) {
  static constexpr std::array<std::string_view, 8> kWords = {"(cartesian:", "G43.4",  "G43.5", "G234",
                                                             "M428",        "TRAORI", "TCPM",  "M128"};
  auto any_in = [](std::string_view v) {
    return std::any_of(kWords.begin(), kWords.end(), [v](std::string_view w) { return v.find(w) != v.npos; });
  };
  // Eight searches through a million-block text: in parallel pieces, each overlapping the next by more than
  // a word, so that every occurrence lies whole in some piece.
  constexpr std::size_t kPiece = std::size_t{1} << 20, kOverlap = 16;
  if (t.size() <= kPiece) return any_in(t);
  std::atomic<bool> found{false};
  parallel_range(0, (t.size() + kPiece - 1) / kPiece, 1, [&](const tbb::blocked_range<std::size_t>& r) {
    for (std::size_t c = r.begin(); c != r.end() && !found.load(std::memory_order_relaxed); ++c)
      if (any_in(std::string_view(t).substr(c * kPiece, kPiece + kOverlap))) found = true;
  });
  return found;
}

nc::Program read_for_machine(const std::string& nc_text, const std::string& name, const machine::Machine& m) {
  nc::AxisLetters letters = axis_letters(m);
  const bool tcp = uses_tool_tip_control(nc_text);
  if (tcp) {
    int k = 0;
    for (size_t i = 0; i < 5; ++i)
      if (!letters.rotary[i]) letters.letter[i] = "XYZ"[k++];
  }
  nc::Program p = nc::read_text(nc_text, name, letters);
  p.tcp = p.tcp || tcp;  // our Cartesian header says so too
  resolve_work_planes(p, m);
  return p;
}

nc::Program read_file_for_machine(const std::string& path, const machine::Machine& m) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw InputError(SourceLoc{path}, "cannot open NC file");
  std::stringstream ss;
  ss << in.rdbuf();
  return read_for_machine(ss.str(), path, m);
}

std::unique_ptr<kin::Kinematics> tool_tip_kinematics(const kin::Kinematics& machine_kinematics, bool vectors) {
  return std::make_unique<TipWordsKinematics>(machine_kinematics, vectors);
}

std::string resolve_tool_vectors(nc::Program& nc, const kin::Kinematics& k, int* bad_line) {
  if (!nc.tcp_vectors) return {};
  const auto rp = k.rotary_pair();
  for (auto& b : nc.blocks) {
    if (!b.has_vector) continue;
    const Vec3 u(b.tool_vector[0], b.tool_vector[1], b.tool_vector[2]);
    if (!(u.z() > 1e-6 * u.norm())) {
      if (bad_line) *bad_line = b.line;
      return fmt::format("{}:{}: tool vector ({:.6f}, {:.6f}, {:.6f}) does not point up from the part", nc.file, b.line,
                         u.x(), u.y(), u.z());
    }
    b.axes[static_cast<size_t>(rp[0])] = u.x() / u.z();
    b.axes[static_cast<size_t>(rp[1])] = u.y() / u.z();
    b.known[static_cast<size_t>(rp[0])] = b.known[static_cast<size_t>(rp[1])] = true;
  }
  return {};
}

namespace {

/// Replaces the arc of block b, read in the coordinates of work plane w (nc reader: centre_u/v in the plane's axes
/// of b.arc->plane), by its circle in machine axes at the fixed rotaries of q. With the rotaries fixed the machine's
/// X Y Z follow the tip rigidly: the plane's directions map to machine directions, found through the kinematics
/// (no assumption about the machine's layout). Returns why it cannot, or nothing.
std::string tilted_arc(nc::Block& b, const kin::Kinematics& k, const nc::WorkPlane& w, const kin::Axes& q,
                       const Vec3& axis, const Vec3& p_start) {
  const nc::ArcGeometry& g = *b.arc;
  const std::array<int, 3> uvw = g.plane == 17   ? std::array<int, 3>{0, 1, 2}
                                 : g.plane == 18 ? std::array<int, 3>{2, 0, 1}
                                                 : std::array<int, 3>{1, 2, 0};
  std::array<int, 3> slot{};  // the machine's X Y Z slots (the reader's arc has them in u v w order)
  for (int c = 0; c < 3; ++c) slot[static_cast<size_t>(uvw[static_cast<size_t>(c)])] = g.slot[static_cast<size_t>(c)];
  auto machine_xyz = [&](const Vec3& p_in_plane, Vec3& out) {
    kin::Axes s = q;
    if (!k.solve_for_rotaries(kin::Posed{rot::from_plane(w.R_part_plane, w.origin_in_part_mm, p_in_plane), axis}, s))
      return false;
    for (int c = 0; c < 3; ++c) out[c] = s[slot[static_cast<size_t>(c)]];
    return true;
  };
  Vec3 centre_in_plane = p_start;
  centre_in_plane[uvw[0]] = g.centre_u;
  centre_in_plane[uvw[1]] = g.centre_v;
  nc::ArcGeometry::Tilted t;
  Vec3 at_u, at_v;
  if (!machine_xyz(centre_in_plane, t.centre_mm) || !machine_xyz(centre_in_plane + Vec3::Unit(uvw[0]), at_u) ||
      !machine_xyz(centre_in_plane + Vec3::Unit(uvw[1]), at_v))
    return fmt::format("no machine axis values put the tip at the centre of the arc in {} (line {})", w.form, w.line);
  t.u = at_u - t.centre_mm;
  t.v = at_v - t.centre_mm;
  if (std::abs(t.u.norm() - 1.0) > 1e-9 || std::abs(t.v.norm() - 1.0) > 1e-9 || std::abs(t.u.dot(t.v)) > 1e-9)
    return fmt::format("the arc in {} (line {}) is no circle of the machine's axes (they do not move the tip rigidly)",
                       w.form, w.line);
  nc::ArcGeometry m = g;
  m.slot = slot;
  m.centre_u = m.centre_v = 0.0;
  m.tilted = t;
  b.arc = std::make_shared<const nc::ArcGeometry>(m);
  return {};
}

}  // namespace

std::string resolve_work_planes(nc::Program& nc, const kin::Kinematics& k, int* bad_line) {
  // A TCP program that cancels tool-tip control for its planes has machine-word blocks (all of them, when every
  // stretch is a plane) besides tip-word ones. Not a program whose header alone says TCP (no word switches it).
  std::size_t last_machine = 0;  // one past the last machine-word block of such a program
  if (nc.tcp_words)
    for (std::size_t bi = 0; bi < nc.blocks.size(); ++bi)
      if (!nc.blocks[bi].tcp) last_machine = bi + 1;
  const bool mixed = last_machine > 0;
  const auto& xyz = nc.xyz_slots;
  const bool have_xyz = xyz[0] >= 0 && xyz[1] >= 0 && xyz[2] >= 0;
  if (!nc.work_planes && !(mixed && have_xyz)) return {};
  const auto rp = k.rotary_pair();
  auto fail = [&](const nc::Block& b, const std::string& what) {
    if (bad_line) *bad_line = b.line;
    return what;
  };
  if (!have_xyz)
    return fail(nc.blocks.empty() ? nc::Block{} : nc.blocks.front(),
                "a tilted work plane on a machine without linear axes lettered X, Y, Z is not read");
  kin::Axes prev = kin::Axes::Zero();  // the machine axes where the machine is
  bool have_prev = false;
  int plane_line = -1;          // the plane the blocks are in
  Vec3 p_plane = Vec3::Zero();  // the modal plane coordinates
  std::array<bool, 3> p_known{};
  std::array<double, 2> rot_at{};  // the rotaries the plane was switched on at
  const double cos_tol = std::cos(deg2rad(tol::kVerifySlackDeg));
  auto all_known = [](const nc::Block& b) {
    return std::all_of(b.known.begin(), b.known.end(), [](bool x) { return x; });
  };
  // A machine-word block of a mixed program as the tip words of its machine axes (the rotaries stay; in vector form
  // the tool vector is the axis there), so that the whole program reads as one TCP program; its axes are kept. Inside a
  // 3+2 stretch the rotaries stand still and the tip moves straight with the linear axes: the TCP view interpolates it
  // exactly.
  auto to_tip_words = [&](std::size_t bi, nc::Block& b) {
    if (!mixed || !all_known(b)) return;
    nc.machine_axes.emplace_back(bi, b.axes);  // the machine goes exactly there (the gate's limits)
    kin::Axes q;
    for (int i = 0; i < 5; ++i) q[i] = b.axes[static_cast<size_t>(i)];
    const kin::Posed p = k.forward(q);
    for (int c = 0; c < 3; ++c) {
      const auto s = static_cast<size_t>(xyz[static_cast<size_t>(c)]);
      if (b.words[s] || std::abs(p.tip_mm[c] - b.axes[s]) > 0) b.words[s] = true;
      b.axes[s] = p.tip_mm[c];
    }
    if (nc.tcp_vectors) {
      b.tool_vector = {p.axis.x(), p.axis.y(), p.axis.z()};
      b.has_vector = true;
    }
  };
  for (std::size_t bi = 0; bi < nc.blocks.size(); ++bi) {
    nc::Block& b = nc.blocks[bi];
    if (mixed && b.tcp) {
      // Tip words: where the control moves the machine, followed only as far as a machine-word block comes later
      // (its words not given are those axes).
      plane_line = -1;
      // A word not given stays where the block before left it, in tip words (the reader's modal value is a machine
      // word after a switch).
      if (bi > 0)
        for (std::size_t i = 0; i < 5; ++i)
          if (!b.words[i] && nc.blocks[bi - 1].known[i]) b.axes[i] = nc.blocks[bi - 1].axes[i];
      if (bi >= last_machine || !all_known(b)) continue;
      const Vec3 tip(b.axes[static_cast<size_t>(xyz[0])], b.axes[static_cast<size_t>(xyz[1])],
                     b.axes[static_cast<size_t>(xyz[2])]);
      Vec3 axis(b.tool_vector[0], b.tool_vector[1], b.tool_vector[2]);
      bool ok = nc.tcp_vectors
                    ? b.has_vector && axis.norm() > 0
                    : k.tool_axis_at(b.axes[static_cast<size_t>(rp[0])], b.axes[static_cast<size_t>(rp[1])], tip, axis);
      // Angle words name the rotaries (the linear axes follow from the tip); a vector leaves the choice to the control.
      kin::Axes sol = prev;
      sol[rp[0]] = b.axes[static_cast<size_t>(rp[0])];
      sol[rp[1]] = b.axes[static_cast<size_t>(rp[1])];
      const kin::Posed pose{tip, axis.normalized()};
      ok = ok && (nc.tcp_vectors ? kin::nearest_solution(k, pose, prev, sol) : k.solve_for_rotaries(pose, sol));
      if (ok) prev = sol;
      have_prev = ok;
      continue;
    }
    if (!b.plane) {
      plane_line = -1;
      if (have_prev)  // a word not given: the axis stays where it is (also after a plane)
        for (int i = 0; i < 5; ++i)
          if (!b.words[static_cast<size_t>(i)]) {
            b.axes[static_cast<size_t>(i)] = prev[i];
            b.known[static_cast<size_t>(i)] = true;
          }
      if (all_known(b)) {
        for (int i = 0; i < 5; ++i) prev[i] = b.axes[static_cast<size_t>(i)];
        have_prev = true;
      }
      to_tip_words(bi, b);
      continue;
    }
    const nc::WorkPlane& w = *b.plane;
    const std::string where = fmt::format("{}:{}: ", nc.file, b.line);
    if (!b.known[static_cast<size_t>(rp[0])] || !b.known[static_cast<size_t>(rp[1])])
      return fail(b, where + fmt::format("{} (line {}) before the rotaries were positioned", w.form, w.line));
    kin::Axes q = prev;
    q[rp[0]] = b.axes[static_cast<size_t>(rp[0])];
    q[rp[1]] = b.axes[static_cast<size_t>(rp[1])];
    const bool new_plane = w.line != plane_line;
    if (new_plane) {  // the words not given are where the machine is
      p_known = {have_prev, have_prev, have_prev};
      if (have_prev) p_plane = rot::to_plane(w.R_part_plane, w.origin_in_part_mm, k.forward(prev).tip_mm);
      rot_at = {q[rp[0]], q[rp[1]]};
      plane_line = w.line;
    }
    if (std::abs(q[rp[0]] - rot_at[0]) > 1e-12 || std::abs(q[rp[1]] - rot_at[1]) > 1e-12)
      return fail(b, where + fmt::format("a rotary turns inside the tilted work plane {} (line {})", w.form, w.line));
    const Vec3 p_start = p_plane;  // an arc's start, in plane coordinates
    for (int c = 0; c < 3; ++c)
      if (b.words[static_cast<size_t>(xyz[static_cast<size_t>(c)])]) {
        p_plane[c] = b.axes[static_cast<size_t>(xyz[static_cast<size_t>(c)])];
        p_known[static_cast<size_t>(c)] = true;
      }
    if (!p_known[0] || !p_known[1] || !p_known[2])
      return fail(b, where + fmt::format("the first block in {} (line {}) must give X, Y and Z: no machine position "
                                         "is known before it",
                                         w.form, w.line));
    const Vec3 tip = rot::from_plane(w.R_part_plane, w.origin_in_part_mm, p_plane);
    Vec3 axis;
    if (!k.tool_axis_at(q[rp[0]], q[rp[1]], tip, axis))
      return fail(b, where + "no tool axis at the positioned rotaries");
    const Vec3 z = w.R_part_plane.col(2);
    if (new_plane && axis.dot(z) < cos_tol)
      return fail(b, where + fmt::format("the Z axis of {} (line {}) is ({:.6f}, {:.6f}, {:.6f}) but the rotaries "
                                         "positioned before it hold the tool along ({:.6f}, {:.6f}, {:.6f}): the "
                                         "control would turn them (G53.1, TURN, CYCLE800), which this reader does "
                                         "not follow; position the rotaries before the plane",
                                         w.form, w.line, z.x(), z.y(), z.z(), axis.x(), axis.y(), axis.z()));
    if (!k.solve_for_rotaries(kin::Posed{tip, axis}, q))
      return fail(b, where + fmt::format("no machine axis values put the tip at ({:.4f}, {:.4f}, {:.4f}) in {} "
                                         "(line {}) at the positioned rotaries",
                                         tip.x(), tip.y(), tip.z(), w.form, w.line));
    if (b.arc) {  // the circle in the plane's coordinates, into machine axes
      if (mixed)
        return fail(b, where + fmt::format("an arc in the tilted work plane {} (line {}) of a program that switches "
                                           "tool-tip control is not read",
                                           w.form, w.line));
      if (!have_prev)
        return fail(
            b, where + fmt::format("an arc in {} (line {}) before the machine's position is known", w.form, w.line));
      const std::string why = tilted_arc(b, k, w, q, axis, p_start);
      if (!why.empty()) return fail(b, where + why);
    }
    for (int i = 0; i < 5; ++i) {
      b.axes[static_cast<size_t>(i)] = q[i];
      b.known[static_cast<size_t>(i)] = true;
      // every linear axis may move in a plane block (its words were plane coordinates)
      if (!k.axes()[static_cast<size_t>(i)].rotary() && std::abs(q[i] - prev[i]) > 0)
        b.words[static_cast<size_t>(i)] = true;
    }
    b.plane.reset();
    prev = q;
    have_prev = true;
    to_tip_words(bi, b);
  }
  return {};
}

void resolve_work_planes(nc::Program& nc, const machine::Machine& m) {
  if (!nc.work_planes && !nc.tcp_words) return;
  const auto k = m.make_kinematics(nc.tool_length_mm.value_or(m.default_tool_length_mm));
  if (const std::string why = resolve_work_planes(nc, *k); !why.empty()) throw InputError(why);  // names file:line
}

VerifyOptions verify_options_for(const machine::Machine& machine, double tolerance_mm, double axis_tolerance_deg,
                                 double cone_deg) {
  VerifyOptions vo;
  vo.tip_tolerance_mm = (tolerance_mm > 0 ? tolerance_mm : machine.post.tolerance_mm) + tol::kVerifySlackMm;
  vo.axis_tolerance_deg =
      (axis_tolerance_deg > 0 ? axis_tolerance_deg : machine.post.axis_tolerance_deg) + tol::kVerifySlackDeg + cone_deg;
  vo.ball_centre = cone_deg > 0;
  vo.cone_deg = cone_deg;
  return vo;
}

VerifyResult verify(const nc::Program& nc, const cl::Program& cl, const kin::Kinematics& kinematics,
                    const VerifyOptions& options) {
  VerifyResult r;
  if (const nc::Program::Unmodelled* u = nc::first_unmodelled_before_motion(nc)) {
    r.message = fmt::format("FAILED: {}:{}: {}, which verify does not model: the moves after it cannot be checked",
                            nc.file, u->line, u->what);
    return r;
  }
  // The compared point: the tip, or the ball centre of a ball mill (what a tilted plan keeps on the path).
  double ball_r = 0.0;
  if (options.ball_centre)
    for (const auto& t : cl.tools)
      if (t.is_ball()) ball_r = 0.5 * t.diameter_mm;
  auto point = [&](const Vec3& tip, const Vec3& axis) -> Vec3 { return tip + ball_r * axis; };
  // The CL feed segments, in order: counted per fixed chunk of moves, then filled in parallel at their places.
  std::vector<ClSeg, DefaultInitAllocator<ClSeg>> segs;
  {
    constexpr std::size_t kSegChunk = 4096;
    const std::size_t n_moves = cl.moves.size();
    const std::size_t chunks = n_moves > 1 ? (n_moves - 2) / kSegChunk + 1 : 0;  // moves 1 .. n - 1
    std::vector<std::size_t> first(chunks + 1, 0);
    parallel_range(0, chunks, 8, [&](const tbb::blocked_range<std::size_t>& r) {  // counts (a pass over 80 MB)
      for (std::size_t c = r.begin(); c != r.end(); ++c) {
        std::size_t count = 0;
        for (std::size_t i = 1 + c * kSegChunk; i < std::min(n_moves, 1 + (c + 1) * kSegChunk); ++i)
          count += cl.moves[i].kind == cl::MotionKind::Feed;
        first[c + 1] = count;
      }
    });
    for (std::size_t c = 0; c < chunks; ++c) first[c + 1] += first[c];  // then their running sums
    segs.resize(first[chunks]);
    parallel_range(0, chunks, 1, [&](const tbb::blocked_range<std::size_t>& r) {
      for (std::size_t c = r.begin(); c != r.end(); ++c) {
        std::size_t k = first[c];
        for (std::size_t i = 1 + c * kSegChunk; i < std::min(n_moves, 1 + (c + 1) * kSegChunk); ++i) {
          const auto& a = cl.moves[i - 1];
          const auto& b = cl.moves[i];
          if (b.kind != cl::MotionKind::Feed) continue;
          const Vec3 ua = a.axis_in_part.normalized(), ub = b.axis_in_part.normalized();
          const double th = slerp_angle(ua, ub);
          segs[k++] = {
              point(a.tip_in_part_mm, ua), point(b.tip_in_part_mm, ub), ua, ub, b.line, b.from_arc, th, std::sin(th)};
        }
      }
    });
  }
  if (segs.empty()) {
    r.ok = true;
    r.message = "the CL program has no feed moves: nothing to compare";
    return r;
  }
  auto nearest = [&](const Vec3& p, size_t& cursor, bool global, double& t) {
    if (!global) {
      // The path mostly advances segment by segment: within tolerance of the current or the next segment is
      // enough to pass (the reported deviation is then an upper bound); only otherwise search the window. The
      // nearer of the two is taken: a sample just past a CL point is near the next segment, and the current one
      // would overstate its deviation by up to the tolerance.
      double t_near = 0.0;
      size_t arg_near = cursor;
      const double best_near = nearest_in(segs, p, cursor, std::min(segs.size(), cursor + 2), arg_near, t_near);
      // (Within the tolerance less the share the bound between samples may add: past that, the window below may
      // hold a nearer segment, e.g. where the path doubles back beside itself.)
      if (best_near <= (1.0 - options.bound_fraction) * options.tip_tolerance_mm) {
        cursor = arg_near;
        t = t_near;
        return best_near;
      }
    }
    if (global) {
      // After a rapid the cut usually resumes at the next CL segments: try them before a full scan.
      size_t arg_local = cursor;
      const double best_local = nearest_in(segs, p, cursor, std::min(segs.size(), cursor + kWindowSegs), arg_local, t);
      if (best_local <= options.tip_tolerance_mm) {
        cursor = arg_local;
        return best_local;
      }
    }
    // As far back as ahead: a path that doubles back passes segments a few CL points behind the cursor.
    size_t lo = global ? 0 : (cursor > kWindowSegs ? cursor - kWindowSegs : 0);
    size_t hi = global ? segs.size() : std::min(segs.size(), cursor + kWindowSegs);
    // The NC follows the CL in order: the first segment at or after the cursor within the tolerance is taken before a
    // nearer one behind it. A path that runs out and back over itself passes its first visit again; snapping back
    // there (a tie at the turning point) left the cut after it beyond the window (a 20 mm "deviation").
    const double pass_mm = (1.0 - options.bound_fraction) * options.tip_tolerance_mm;
    double best = std::numeric_limits<double>::infinity(), best_fwd = best;
    size_t arg = cursor, arg_fwd = cursor;
    double tb = 0, tb_fwd = 0;
    for (size_t k = lo; k < hi; ++k) {
      double tk;
      const double d = seg_distance(segs[k], p, tk);
      if (d < best - 1e-12) {
        best = d;
        arg = k;
        tb = tk;
      }
      if (!global && k >= cursor && d <= pass_mm && !(best_fwd <= pass_mm)) {
        best_fwd = d;
        arg_fwd = k;
        tb_fwd = tk;
      }
    }
    if (best_fwd <= pass_mm) {
      cursor = arg_fwd;
      t = tb_fwd;
      return best_fwd;
    }
    cursor = arg;
    t = tb;
    return best;
  };

  std::vector<Vec3> nc_feed_points;
  std::vector<int> nc_feed_lines;
  // At most two per block (its ends): no regrowth of a million-point array; pages never written stay untouched.
  nc_feed_points.reserve(2 * nc.blocks.size());
  nc_feed_lines.reserve(2 * nc.blocks.size());
  size_t cursor = 0;
  bool after_rapid = true;
  const nc::Block* prev = nullptr;
  auto to_axes = [](const nc::Block& b) {
    kin::Axes q;
    for (int a = 0; a < 5; ++a) q[a] = b.axes[static_cast<size_t>(a)];
    return q;
  };
  // Forward kinematics of every sample is independent of the search along the CL path: computed in parallel
  // for a chunk of blocks (fixed chunks, fixed slots), then walked in order as before. Same numbers at any
  // thread count.
  const int n_fixed = std::max(1, options.samples_per_block);
  const double tip_budget_mm = options.bound_fraction * options.tip_tolerance_mm;
  const double axis_budget_rad = options.bound_fraction * deg2rad(options.axis_tolerance_deg);
  const double axis_tol_rad = deg2rad(options.axis_tolerance_deg);
  constexpr std::size_t kChunk = 4096;
  // How a feed block is sampled: n intervals; `bounded` blocks take FK(qa) and FK(qb) exactly at their ends and
  // carry the bound between samples (docs/safety.md), the others sample qa + k/n (qb - qa) (or the arc) as always.
  struct BlockSampling {
    std::size_t offset = 0;  ///< first slot in `poses` (samples 0..n, then FK(qb) at n + 1)
    int n = 0;               ///< 0: no samples (a rapid, the first block)
    bool bounded = false;
    double tip_slack_mm = 0.0;    ///< how far the compared point may leave the polyline through the samples
    double axis_slack_rad = 0.0;  ///< how far the axis may turn away from the nearest sample
    kin::MotionBound bound;
  };
  // The samples of one chunk: which blocks are bounded, the FK at their shared ends (`nodes`, from block n0 on)
  // and every sample's pose.
  struct ChunkSamples {
    std::vector<BlockSampling> sampling;
    std::vector<kin::Posed> poses, nodes;
  };
  // The XMINI's FK is a Newton solve warm-started from the thread's previous one: its last digits depend on
  // which block a thread solved before, so there the samples are computed in order (numbers independent of the
  // thread count, as everywhere else).
  const bool fk_in_order = kinematics.traits().forward_depends_on_call_order;
  struct AxisSample {
    std::size_t seg;
    double t;
    const kin::Posed* pose;
    int nc_line;
    double slack_deg;
    std::size_t block;
    int n;  ///< the block's sample intervals
  };
  std::vector<AxisSample> axis_samples;
  std::vector<double> axis_angles;
  // The last sample walked: its compared point, the CL segment it was matched to and its distance to it.
  constexpr size_t kNoSeg = std::numeric_limits<size_t>::max();
  Vec3 walk_pt = Vec3::Zero();
  size_t walk_seg = kNoSeg;
  double walk_d = 0.0;
  // The tool axis of pose p against the CL orientation at parameter t of segment seg, in degrees, with slack_deg (the
  // bound between samples) added. Where the path doubles back on itself, or runs through segments shorter than the
  // tip tolerance, the nearest CL point need not be where the block is along the orientation: a sample that misses
  // there is judged where some CL pose near it (its tip within the tip tolerance, on this segment or a neighbour)
  // has the axis.
  auto axis_angle_deg = [&](std::size_t seg, double t, const kin::Posed& p, double slack_deg) {
    const ClSeg& sg = segs[seg];
    double dot = slerp(sg.u0, sg.u1, sg.th, sg.sin_th, t).dot(p.axis);
    if (rad2deg(std::acos(std::clamp(dot, -1.0, 1.0))) + slack_deg > options.axis_tolerance_deg) {
      const Vec3 pt = point(p.tip_mm, p.axis);
      for (std::size_t k = seg > kWindowSegs ? seg - kWindowSegs : 0; k < std::min(segs.size(), seg + kWindowSegs + 1);
           ++k)
        dot = std::max(dot, best_axis_dot_near(segs[k], pt, p.axis, options.tip_tolerance_mm));
    }
    return rad2deg(std::acos(std::clamp(dot, -1.0, 1.0))) + slack_deg;
  };
  // The largest axis deviation (deg, the new bound added) of bounded block bi sampled afresh with enough intervals
  // that the bound (slack_deg at n intervals) takes at most half of `room_deg`; its samples are matched, by tip, on
  // the CL segments its first samples [i0, i1) of axis_samples were matched on and their neighbours.
  auto refine_axis = [&](std::size_t bi, int n, double slack_deg, double room_deg, std::size_t i0, std::size_t i1) {
    const double want = std::ceil(2.0 * slack_deg * n / room_deg);
    const int n2 = want < options.max_adaptive_samples ? std::max(2 * n, static_cast<int>(want))
                                                       : std::max(n, options.max_adaptive_samples);
    std::size_t s_lo = segs.size(), s_hi = 0;
    for (std::size_t k = i0; k < i1; ++k) {
      s_lo = std::min(s_lo, axis_samples[k].seg);
      s_hi = std::max(s_hi, axis_samples[k].seg);
    }
    s_lo = s_lo > kWindowSegs ? s_lo - kWindowSegs : 0;
    s_hi = std::min(segs.size() - 1, s_hi + kWindowSegs);
    const kin::Axes qa = to_axes(nc.blocks[bi - 1]), qb = to_axes(nc.blocks[bi]);
    const double slack2_deg = slack_deg * n / n2;
    double worst = 0.0;
    for (int k = 0; k <= n2; ++k) {
      const kin::Posed p = kinematics.forward(qa + (static_cast<double>(k) / n2) * (qb - qa));
      std::size_t seg = s_lo;
      double t = 0.0;
      nearest_in(segs, point(p.tip_mm, p.axis), s_lo, s_hi + 1, seg, t);
      worst = std::max(worst, axis_angle_deg(seg, t, p, slack2_deg));
    }
    return worst;
  };
  auto run = [&](std::size_t b0, std::size_t b1, std::size_t grain, const auto& body) {
    if (fk_in_order)
      body(tbb::blocked_range<std::size_t>(b0, b1));
    else
      parallel_range(b0, b1, grain, body);
  };
  // Steps 1-3 for the chunk [c0, c0 + kChunk): pure functions of the program, so the next chunk's are computed
  // while this one is walked (below); the walk and its results are the same as computing them first.
  auto prepare = [&](std::size_t c0, ChunkSamples& cs) {
    auto& sampling = cs.sampling;
    auto& poses = cs.poses;
    auto& nodes = cs.nodes;
    const std::size_t c1 = std::min(nc.blocks.size(), c0 + kChunk);
    sampling.assign(c1 - c0, BlockSampling{});
    // 1. Which blocks have a motion bound (from the joint spans, no FK).
    run(c0, c1, 1024, [&](const tbb::blocked_range<std::size_t>& r) {
      for (std::size_t bi = r.begin(); bi != r.end(); ++bi) {
        if (bi == 0 || nc.blocks[bi].motion == nc::Motion::Rapid) continue;
        BlockSampling& bs = sampling[bi - c0];
        bs.n = n_fixed;
        bs.bounded = options.adaptive_samples && !nc.blocks[bi].arc &&
                     kinematics.motion_bound(to_axes(nc.blocks[bi - 1]), to_axes(nc.blocks[bi]), bs.bound);
      }
    });
    // 2. FK at the block ends the bounded blocks share (block i ends where block i + 1 starts).
    const std::size_t n0 = c0 > 0 ? c0 - 1 : 0;
    nodes.resize(c1 - n0);
    run(n0, c1, 1024, [&](const tbb::blocked_range<std::size_t>& r) {
      for (std::size_t i = r.begin(); i != r.end(); ++i) {
        const bool used = (i >= c0 && sampling[i - c0].bounded) || (i + 1 < c1 && sampling[i + 1 - c0].bounded);
        if (used) nodes[i - n0] = kinematics.forward(to_axes(nc.blocks[i]));
      }
    });
    // 3. The number of samples of the bounded blocks: between samples h = 1/n apart the compared point leaves
    // their polyline by at most M h^2 / 8 and the axis turns at most (speed bound) h / 2 away from the nearest.
    // The axis speed is at most the model's rate bound, and at most |u_b - u_a| + A / 2 (its mean velocity over
    // the block plus what its acceleration A can change it by): far smaller where a rotary swings about an axis
    // the tool nearly points along.
    run(c0, c1, 1024, [&](const tbb::blocked_range<std::size_t>& r) {
      for (std::size_t bi = r.begin(); bi != r.end(); ++bi) {
        BlockSampling& bs = sampling[bi - c0];
        if (!bs.bounded) continue;
        const kin::MotionBound& mb = bs.bound;
        const double accel = mb.tip_accel_mm + ball_r * mb.axis_accel;
        const double rate =
            std::min(mb.axis_rate_rad, (nodes[bi - n0].axis - nodes[bi - 1 - n0].axis).norm() + 0.5 * mb.axis_accel);
        const double need = std::max(
            {2.0, std::ceil(std::sqrt(accel / (8.0 * tip_budget_mm))), std::ceil(rate / (2.0 * axis_budget_rad))});
        const int cap = std::max(2, options.max_adaptive_samples);
        bs.n = need < cap ? static_cast<int>(need) : cap;  // NaN: the cap
        bs.tip_slack_mm = accel / (8.0 * bs.n * bs.n);
        bs.axis_slack_rad = rate / (2.0 * bs.n);
        if (!(bs.tip_slack_mm >= 0.0) || !(bs.axis_slack_rad >= 0.0))  // not finite: never passes
          bs.tip_slack_mm = bs.axis_slack_rad = std::numeric_limits<double>::infinity();
      }
    });
    std::size_t total = 0;
    for (BlockSampling& bs : sampling) {
      bs.offset = total;
      if (bs.n > 0) total += static_cast<std::size_t>(bs.n) + 2;
    }
    poses.resize(total);
    // 3. The samples.
    run(c0, c1, 256, [&](const tbb::blocked_range<std::size_t>& r) {
      for (std::size_t bi = r.begin(); bi != r.end(); ++bi) {
        const BlockSampling& bs = sampling[bi - c0];
        if (bs.n == 0) continue;
        const int n = bs.n;
        const kin::Axes qa = to_axes(nc.blocks[bi - 1]), qb = to_axes(nc.blocks[bi]);
        kin::Posed* out = &poses[bs.offset];
        const nc::Block& nb = nc.blocks[bi];
        if (bs.bounded) {
          out[0] = nodes[bi - 1 - n0];
          for (int k = 1; k < n; ++k) out[k] = kinematics.forward(qa + (static_cast<double>(k) / n) * (qb - qa));
          out[n] = out[n + 1] = nodes[bi - n0];
          continue;
        }
        for (int k = 0; k <= n; ++k) {
          const double t = static_cast<double>(k) / n;
          if (nb.arc) {  // along the arc the control moves on, not its chord
            const auto p = nc::point_on(nc.blocks[bi - 1].axes, nb, t);
            kin::Axes q;
            for (int a = 0; a < 5; ++a) q[a] = p[static_cast<size_t>(a)];
            out[k] = kinematics.forward(q);
          } else {
            out[k] = kinematics.forward(qa + t * (qb - qa));
          }
        }
        out[n + 1] = kinematics.forward(qb);
      }
    });
  };
  std::optional<std::pair<Vec3, Vec3>> departure_chain;  // see departure()
  std::array<ChunkSamples, 2> chunk_samples;
  if (!nc.blocks.empty()) prepare(0, chunk_samples[0]);
  for (std::size_t c0 = 0, cur = 0; c0 < nc.blocks.size(); c0 += kChunk, cur ^= 1) {
    const std::size_t c1 = std::min(nc.blocks.size(), c0 + kChunk);
    const std::size_t next = c0 + kChunk;
    // The next chunk's samples beside this chunk's walk; on models whose FK depends on call order after it, so
    // that the FK calls come in the sequential order (the walk makes none).
    Background ahead;
    if (next < nc.blocks.size() && !fk_in_order) ahead.run([&, next] { prepare(next, chunk_samples[cur ^ 1]); });
    const std::vector<BlockSampling>& sampling = chunk_samples[cur].sampling;
    const std::vector<kin::Posed>& poses = chunk_samples[cur].poses;
    // 4. The walk along the CL path, in order.
    for (std::size_t bi = c0; bi < c1; ++bi) {
      const nc::Block& b = nc.blocks[bi];
      if (b.motion == nc::Motion::Rapid || prev == nullptr) {
        after_rapid = true;
        prev = &b;
        continue;
      }
      const BlockSampling& bs = sampling[bi - c0];
      const int n = bs.n;
      const kin::Posed* bp = &poses[bs.offset];
      if (departure(
              bp, n, options.tip_tolerance_mm, axis_tol_rad, bs.tip_slack_mm, bs.axis_slack_rad, ball_r,
              [&](const Vec3& p) {
                size_t c = cursor;
                double t;
                nearest(p, c, false, t);
                const ClSeg& sg = segs[c];
                return std::pair<Vec3, Vec3>(sg.p0 + t * (sg.p1 - sg.p0), slerp(sg.u0, sg.u1, sg.th, sg.sin_th, t));
              },
              departure_chain)) {
        // A retract or plunge along the fixed tool axis (a post's flip or unwind): off the path by design,
        // like a rapid; the CL points around it must still be reached.
        ++r.axial_blocks;
        for (const kin::Posed* p : {&bp[0], &bp[n + 1]}) {  // its ends may be CL points (a CL plunge or retract)
          nc_feed_points.push_back(point(p->tip_mm, p->axis));
          nc_feed_lines.push_back(b.line);
        }
        after_rapid = true;
        prev = &b;
        continue;
      }
      ++r.feed_blocks;
      departure_chain.reset();  // a cut ends a retract-turn-plunge
      // Bounded blocks: the straight line between consecutive samples stays within the larger of its ends'
      // distances to either end's segment (the distance to a convex set is convex along a line), and the move
      // stays within tip_slack_mm of that line.
      const Vec3 start_pt = point(bp[0].tip_mm, bp[0].axis);
      if (after_rapid || start_pt != walk_pt) walk_seg = kNoSeg;  // the block starts where the walk stood
      walk_pt = start_pt;
      const double axis_slack_deg = rad2deg(bs.axis_slack_rad);
      for (int k = after_rapid ? 0 : 1; k <= n; ++k) {
        const kin::Posed& p = bp[k];
        const Vec3 pt = point(p.tip_mm, p.axis);
        double t;
        const double d_point = nearest(pt, cursor, after_rapid && k == 0, t);
        double d = d_point;
        if (bs.bounded && k > 0) {
          double unused;
          if (walk_seg == cursor) {
            d = std::max(d_point, walk_d);
          } else {
            d = std::max(d_point, seg_distance(segs[cursor], walk_pt, unused));
            if (walk_seg != kNoSeg) d = std::min(d, std::max(walk_d, seg_distance(segs[walk_seg], pt, unused)));
          }
          d += bs.tip_slack_mm;
        }
        walk_pt = pt;
        walk_seg = cursor;
        walk_d = d_point;
        after_rapid = false;
        ++r.samples;
        if (d > r.max_tip_deviation_mm) {
          r.max_tip_deviation_mm = d;
          r.max_tip_nc_line = b.line;
          r.max_tip_cl_line = segs[cursor].line;
        }
        axis_samples.push_back({cursor, t, &p, b.line, axis_slack_deg, bi, n});
        if (k == n || k == 0) {
          nc_feed_points.push_back(pt);
          nc_feed_lines.push_back(b.line);
        }
      }
      prev = &b;
    }
    // The tool axis against the CL orientation where the walk found each sample: independent per sample, so in
    // parallel; the maximum is then taken in sample order (the first of equal values, as a sequential scan).
    axis_angles.resize(axis_samples.size());
    parallel_range(0, axis_samples.size(), 1024, [&](const tbb::blocked_range<std::size_t>& rg) {
      for (std::size_t i = rg.begin(); i != rg.end(); ++i) {
        const AxisSample& a = axis_samples[i];
        axis_angles[i] = axis_angle_deg(a.seg, a.t, *a.pose, a.slack_deg);
      }
    });
    // A bounded block whose axis passes at every sample, but not once the bound between samples is added, is sampled
    // again as finely as the room it leaves needs (the bound shrinks with the spacing; the verdict stays a proven
    // one): a sixteenth of the tolerance on top of an axis at the post's own tolerance refused it (0.3101 deg).
    for (std::size_t i = 0; i < axis_samples.size();) {
      std::size_t j = i;
      double worst = 0.0, worst_bare = 0.0;
      for (; j < axis_samples.size() && axis_samples[j].block == axis_samples[i].block; ++j) {
        worst = std::max(worst, axis_angles[j]);
        worst_bare = std::max(worst_bare, axis_angles[j] - axis_samples[j].slack_deg);
      }
      if (worst > options.axis_tolerance_deg && worst_bare < options.axis_tolerance_deg &&
          axis_samples[i].slack_deg > 0.0) {
        const double refined = refine_axis(axis_samples[i].block, axis_samples[i].n, axis_samples[i].slack_deg,
                                           options.axis_tolerance_deg - worst_bare, i, j);
        for (std::size_t k = i; k < j; ++k) axis_angles[k] = std::min(axis_angles[k], refined);
      }
      i = j;
    }
    for (std::size_t i = 0; i < axis_samples.size(); ++i)
      if (axis_angles[i] > r.max_axis_deviation_deg) {
        r.max_axis_deviation_deg = axis_angles[i];
        r.max_axis_nc_line = axis_samples[i].nc_line;
      }
    axis_samples.clear();
    ahead.wait();
    if (next < nc.blocks.size() && fk_in_order) prepare(next, chunk_samples[cur ^ 1]);
  }
  // Coverage: every CL feed point must be reached by the NC path (nothing skipped).
  if (!nc_feed_points.empty()) {
    size_t c = 0;
    const bool nc_arcs =
        std::any_of(nc.blocks.begin(), nc.blocks.end(), [](const nc::Block& b) { return bool(b.arc); });
    for (const ClSeg& s : segs) {
      // Inside a CL arc written as G2/G3 the NC has no block end: the samples along the arc (above) stand for it.
      if (nc_arcs && s.arc_interior) continue;
      // Squared distances; the next few points first: a point posted at the CL point is almost always among
      // them, and one within the sampling budget of it ends the search (the distance found is an upper bound of
      // the nearest, as every distance reported here).
      double best2 = std::numeric_limits<double>::infinity();
      const size_t lo = c > 4 ? c - 4 : 0, hi = std::min(nc_feed_points.size(), c + 256);
      const size_t near_hi = std::min(hi, c + 8);
      size_t arg = c;
      auto scan = [&](size_t k0, size_t k1) {
        for (size_t k = k0; k < k1; ++k) {
          const double d2 = (nc_feed_points[k] - s.p1).squaredNorm();
          if (d2 < best2) {
            best2 = d2;
            arg = k;
          }
        }
      };
      scan(lo, near_hi);
      if (!(best2 <= tip_budget_mm * tip_budget_mm)) scan(near_hi, hi);
      if (best2 > options.tip_tolerance_mm * options.tip_tolerance_mm)  // lost the thread (e.g. after a long
        scan(0, nc_feed_points.size());                                 // rapid): search globally
      double best = std::sqrt(best2);
      c = arg;
      if (options.cone_deg > 0.0) {
        // An approach or retract along the CL axis, which a planned program runs along its own axis.
        const Vec3 d = s.p1 - s.p0;
        if (s.th < 1e-9 && d.norm() > 0.0 && d.cross(s.u0).norm() <= 1e-6 * d.norm())
          best = std::max(0.0, best - 2.0 * d.norm() * std::sin(0.5 * deg2rad(options.cone_deg)));
      }
      if (best > r.max_uncovered_cl_mm) {
        r.max_uncovered_cl_mm = best;
        r.max_uncovered_cl_line = s.line;
      }
    }
  } else {
    r.max_uncovered_cl_mm = std::numeric_limits<double>::infinity();
    r.max_uncovered_cl_line = segs.front().line;
  }
  const bool tip_ok = r.max_tip_deviation_mm <= options.tip_tolerance_mm;
  const bool axis_ok = r.max_axis_deviation_deg <= options.axis_tolerance_deg;
  const bool cover_ok = r.max_uncovered_cl_mm <= options.tip_tolerance_mm;
  r.ok = tip_ok && axis_ok && cover_ok;
  if (r.ok) {
    r.message =
        fmt::format("OK: max tip deviation {:.5f} mm, max axis deviation {:.4f} deg over {} samples in {} feed blocks",
                    r.max_tip_deviation_mm, r.max_axis_deviation_deg, r.samples, r.feed_blocks);
  } else {
    r.message = "FAILED:";
    if (!tip_ok)
      r.message += fmt::format(" tip deviation {:.5f} mm > {:.5f} mm at NC line {} (CL line {});",
                               r.max_tip_deviation_mm, options.tip_tolerance_mm, r.max_tip_nc_line, r.max_tip_cl_line);
    if (!axis_ok)
      r.message += fmt::format(" axis deviation {:.4f} deg > {:.4f} deg at NC line {};", r.max_axis_deviation_deg,
                               options.axis_tolerance_deg, r.max_axis_nc_line);
    if (!cover_ok)
      r.message += fmt::format(" CL point at line {} not reached (nearest NC point {:.5f} mm away);",
                               r.max_uncovered_cl_line, r.max_uncovered_cl_mm);
    r.message.pop_back();  // the last item's ';'
  }
  return r;
}

nlohmann::json VerifyResult::json() const {
  return {{"ok", ok},
          {"feed_blocks", feed_blocks},
          {"samples", samples},
          {"max_tip_deviation_mm", rounded(max_tip_deviation_mm, 6)},
          {"max_tip_nc_line", max_tip_nc_line},
          {"max_tip_cl_line", max_tip_cl_line},
          {"max_axis_deviation_deg", rounded(max_axis_deviation_deg, 6)},
          {"max_axis_nc_line", max_axis_nc_line},
          {"max_uncovered_cl_mm", rounded(max_uncovered_cl_mm, 6)},
          {"max_uncovered_cl_line", max_uncovered_cl_line},
          {"message", message}};
}

std::string VerifyResult::to_json() const { return json().dump(); }

}  // namespace cscam::report
