#include "cscam/cspace/cspace.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <numbers>
#include <utility>

#include "cscam/core/error.hpp"
#include "cscam/core/units.hpp"

namespace cscam::cspace {

Counters& Counters::operator+=(const Counters& o) {
  cells_enumerated += o.cells_enumerated;
  ik += o.ik;
  stroke += o.stroke;
  collision += o.collision;
  cache_hits += o.cache_hits;
  certified += o.certified;
  translated += o.translated;
  witnessed += o.witnessed;
  swept += o.swept;
  swept_queries += o.swept_queries;
  return *this;
}

Space::Space(std::shared_ptr<const kin::Kinematics> kinematics, const geom::Scene* scene, const geom::ToolShape* tool,
             Options options, const geom::Scene* head)
    : kin_(std::move(kinematics)), scene_(scene), tool_(tool), opt_(std::move(options)), head_(head) {
  if (!(opt_.resolution_rad > 0)) throw InputError("C-space resolution must be positive");
  if (opt_.cone_rad < 0 || opt_.min_tilt_rad < 0) throw InputError("cone and minimum tilt must not be negative");
  if (opt_.min_tilt_rad > opt_.cone_rad && opt_.cone_rad > 0)
    throw InputError(fmt::format("minimum tilt {:.3f} deg exceeds the cone {:.3f} deg: no orientation is allowed",
                                 rad2deg(opt_.min_tilt_rad), rad2deg(opt_.cone_rad)));
  links_ = std::max(scene_ ? scene_->link_count() : 0, head_ ? head_->link_count() : 0);
  for (const geom::Scene* sc : {scene_, head_})
    if (sc)
      for (std::size_t i = 0; i < sc->obstacle_count(); ++i)
        if (sc->obstacle_link(i) >= 0) used_links_ |= 1u << sc->obstacle_link(i);
  if (links_ > 0) {
    CSCAM_CHECK(links_ <= kMaxLinks, "machine link index out of range");
    // A certificate (same axis, tip moved < margin) covers a machine body only if the body keeps its pose in the
    // part frame when only the linear axes change: true unless the table chain has a linear joint.
    kin::Axes q0 = kin::Axes::Zero(), q1 = kin::Axes::Zero();
    for (std::size_t i = 0; i < kin_->axes().size(); ++i)
      if (kin_->axes()[i].type == kin::AxisType::Linear) q1[static_cast<int>(i)] = 37.0;
    LinkPoses a, b;
    if (!place_links(*kin_, q0, links_, a, used_links_) || !place_links(*kin_, q1, links_, b, used_links_))
      throw InputError("the machine's kinematics cannot place its machine bodies (link poses unavailable)");
    for (int l = 0; l < (scene_ ? scene_->link_count() : 0); ++l)
      if (((used_links_ >> l) & 1u) && !a[static_cast<std::size_t>(l)].isApprox(b[static_cast<std::size_t>(l)], 1e-12))
        certify_links_ = false;
  }
  if (head_)
    for (std::size_t i = 0; i < head_->obstacle_count(); ++i)
      if (head_->obstacle_link(i) >= 0) certify_head_ = false;
  if (head_ && kin_->head_link() >= 0 && kin_->head_link() < kMaxLinks) head_link_ = kin_->head_link();
  if (tool_) {
    tip_tool_.cutter = {tool_->cutter.diameter_mm, 0.0,
                        tool_->cutter.corner_radius_mm + 2.0 * kRapidSweepMarginCapMm + 1e-3};
    double rmax = 0.0, top = 0.0;
    for (const geom::ToolSegment& sgm : tool_->segments()) {
      rmax = std::max(rmax, sgm.radius_mm);
      top = std::max(top, sgm.z1_mm);
    }
    reach_mm_ = top + rmax + std::max(opt_.collision.clearance_mm, opt_.collision.cutter_clearance_mm);
    cutter_reach_mm_ = tool_->cutter.flute_length_mm + 0.5 * tool_->cutter.diameter_mm +
                       2.0 * std::max(0.0, opt_.collision.cutter_clearance_mm);
  }
  const auto rp = kin_->rotary_pair();
  rot1_ = rp[0];
  rot2_ = rp[1];
  auto range = [&](int axis, int& lo, int& hi, const std::array<double, 2>& window) {
    const kin::AxisInfo& a = kin_->axes()[static_cast<size_t>(axis)];
    double mn = a.min, mx = a.max;
    // Exact cells are few, so cone 0 affords more explicit windings of a cyclic axis than the grid does.
    const double span = opt_.cone_rad <= 0 ? 2.0 * opt_.cyclic_span_rad : opt_.cyclic_span_rad;
    if (a.cyclic || mx - mn > 2 * span) {
      const bool fitted = std::isfinite(window[0]) && std::isfinite(window[1]) && window[0] < window[1];
      mn = std::max(mn, fitted ? window[0] : -span);
      mx = std::min(mx, fitted ? window[1] : span);
    }
    lo = static_cast<int>(std::ceil(mn / opt_.resolution_rad - 1e-9));
    hi = static_cast<int>(std::floor(mx / opt_.resolution_rad + 1e-9));
  };
  range(rot1_, i1_min_, i1_max_, opt_.cyclic_window_rad[0]);
  range(rot2_, i2_min_, i2_max_, opt_.cyclic_window_rad[1]);
  // A serial machine's axis is R(primary) v(secondary): one factor per grid row and column instead of two rotation
  // matrices per cell (the flood fill of a cone near the singular axis visits thousands of cells per point).
  tip_free_axis_ = kin_->axis_factors(0.0, 0.0, nullptr, nullptr);
  if (opt_.cone_rad > 0 && tip_free_axis_) {
    R1_grid_.resize(static_cast<std::size_t>(i1_max_ - i1_min_) + 1);
    v2_grid_.resize(static_cast<std::size_t>(i2_max_ - i2_min_) + 1);
    for (int i = i1_min_; i <= i1_max_; ++i)
      kin_->axis_factors(r1_of(i), 0.0, &R1_grid_[static_cast<std::size_t>(i - i1_min_)], nullptr);
    for (int i = i2_min_; i <= i2_max_; ++i)
      kin_->axis_factors(0.0, r2_of(i), nullptr, &v2_grid_[static_cast<std::size_t>(i - i2_min_)]);
    // Fit v2 = p + q cos + r sin to the table (least squares) and keep it only if it reproduces every entry: the
    // closed-form rows then find exactly the cells a test of every grid cell would.
    const auto n2 = static_cast<Eigen::Index>(v2_grid_.size());
    if (n2 >= 3) {
      Eigen::MatrixXd X(n2, 3), Y(n2, 3);
      for (Eigen::Index j = 0; j < n2; ++j) {
        const double a = r2_of(i2_min_ + static_cast<int>(j));
        X.row(j) << 1.0, std::cos(a), std::sin(a);
        Y.row(j) = v2_grid_[static_cast<std::size_t>(j)].transpose();
      }
      const Eigen::MatrixXd coef = X.colPivHouseholderQr().solve(Y);
      v2_p_ = coef.row(0).transpose();
      v2_q_ = coef.row(1).transpose();
      v2_r_ = coef.row(2).transpose();
      rows_in_closed_form_ = (X * coef - Y).cwiseAbs().maxCoeff() < 1e-9;
    }
  }
}

template <typename Take>
void Space::scan_rows(const Eigen::Vector3d& u, double cos_min, Take&& take) const {
  constexpr double kTurn = 2.0 * std::numbers::pi;
  // The closed form only brackets the columns (one column of margin, a band for round-off); each is then decided
  // by the same test as any other grid cell, on the tabulated axis.
  constexpr double kBand = 1e-9;
  const double res = opt_.resolution_rad;
  for (int i1 = i1_min_; i1 <= i1_max_; ++i1) {
    const Eigen::Vector3d w = R1_grid_[static_cast<std::size_t>(i1 - i1_min_)].transpose() * u;
    // cos to the CL axis along the row: alpha + beta cos(r2) + gamma sin(r2) = alpha + rho cos(r2 - phi)
    const double alpha = w.dot(v2_p_), beta = w.dot(v2_q_), gamma = w.dot(v2_r_);
    const double rho = std::hypot(beta, gamma);
    if (alpha + rho < cos_min - kBand) continue;
    auto test = [&](int i2) {
      const double d = grid_axis(i1, i2).dot(u);
      if (d >= cos_min) take(d, i1, i2);
    };
    if (alpha - rho >= cos_min + kBand || rho < kBand) {
      for (int i2 = i2_min_; i2 <= i2_max_; ++i2) test(i2);
      continue;
    }
    const double phi = std::atan2(gamma, beta);
    const double half = std::acos(std::clamp((cos_min - alpha) / rho, -1.0, 1.0)) + kBand;
    // Every winding of [phi - half, phi + half] that meets the grid's columns, in column order.
    const double lo_rad = r2_of(i2_min_), hi_rad = r2_of(i2_max_);
    int next = i2_min_;  // columns below this one are done (windings may overlap when half is near pi)
    for (double k = std::floor((lo_rad - phi - half) / kTurn); phi - half + k * kTurn <= hi_rad; k += 1.0) {
      const int a = std::max(next, static_cast<int>(std::floor((phi - half + k * kTurn) / res)) - 1);
      const int b = std::min(i2_max_, static_cast<int>(std::ceil((phi + half + k * kTurn) / res)) + 1);
      for (int i2 = a; i2 <= b; ++i2) test(i2);
      next = std::max(next, b + 1);
    }
  }
}

bool Space::axis_at(double r1, double r2, const Eigen::Vector3d& tip_mm, Eigen::Vector3d& axis) const {
  if (!R1_grid_.empty()) {
    const double res = opt_.resolution_rad;
    const long i1 = std::lround(r1 / res), i2 = std::lround(r2 / res);
    if (i1 >= i1_min_ && i1 <= i1_max_ && i2 >= i2_min_ && i2 <= i2_max_ && r1 == r1_of(static_cast<int>(i1)) &&
        r2 == r2_of(static_cast<int>(i2))) {
      axis = grid_axis(static_cast<int>(i1), static_cast<int>(i2));
      return true;
    }
  }
  return kin_->tool_axis_at(r1, r2, tip_mm, axis);
}

bool Space::pose_axis(const kin::Posed& cl, double r1, double r2, Eigen::Vector3d& axis) const {
  if (!axis_at(r1, r2, cl.tip_mm, axis)) return false;
  // Where the axis depends on the tip (a parallel machine's platform tilts as it moves), it is judged where the
  // tool will be: with a ball mill the new orientation moves the tip by up to r |a - a_cl| (0.5 mm at 10 deg for
  // r = 3), which turned the XMINI's axis 0.03 deg past a 10 deg cone the CL tip's axis was inside.
  if (tip_free_axis_ || opt_.ball_radius_mm <= 0) return true;
  const Eigen::Vector3d centre = cl.tip_mm + opt_.ball_radius_mm * cl.axis;
  const Eigen::Vector3d tip = centre - opt_.ball_radius_mm * axis;
  return axis_at(r1, r2, tip, axis);
}

Eigen::Vector3d Space::axis_of(double r1, double r2) const {
  Eigen::Vector3d a;
  axis_at(r1, r2, Eigen::Vector3d::Zero(), a);
  return a;
}

bool Space::in_cone(const kin::Posed& cl, double r1, double r2, float* orient_err) const {
  Eigen::Vector3d a;
  if (!pose_axis(cl, r1, r2, a)) return false;
  const double err = std::acos(std::clamp(a.dot(cl.axis), -1.0, 1.0));
  if (orient_err) *orient_err = static_cast<float>(err);
  // A tiny floor on the cone lets exact IK cells (cone 0) pass their own test despite rounding.
  return err <= std::max(opt_.cone_rad, 1e-7) && err >= opt_.min_tilt_rad - 1e-12;
}

bool Space::in_cone_cos(const kin::Posed& cl, double r1, double r2, double& dot) const {
  Eigen::Vector3d a;
  if (!pose_axis(cl, r1, r2, a)) return false;
  dot = std::clamp(a.dot(cl.axis), -1.0, 1.0);
  // Clear of both bounds by far more than round-off: decided by the cosine; near one: in_cone's own test.
  constexpr double kBand = 1e-9;
  const double cos_cone = std::cos(std::max(opt_.cone_rad, 1e-7));
  if (dot < cos_cone - kBand) return false;
  const double cos_min = opt_.min_tilt_rad > 0 ? std::cos(opt_.min_tilt_rad - 1e-12) : 2.0;
  if (dot > cos_cone + kBand && dot < cos_min - kBand) return true;
  if (dot > cos_min + kBand) return false;
  const double err = std::acos(dot);
  return err <= std::max(opt_.cone_rad, 1e-7) && err >= opt_.min_tilt_rad - 1e-12;
}

kin::Posed Space::tool_pose(const kin::Posed& cl, double r1, double r2) const {
  Eigen::Vector3d a;
  if (!pose_axis(cl, r1, r2, a)) a = cl.axis;
  if (opt_.ball_radius_mm > 0) {
    // Ball-end: the ball centre is what the CL path fixes; a new orientation moves the tip.
    const Eigen::Vector3d centre = cl.tip_mm + opt_.ball_radius_mm * cl.axis;
    return {centre - opt_.ball_radius_mm * a, a};
  }
  return {cl.tip_mm, a};
}

std::size_t Space::count_in_cone(const kin::Posed& cl, std::size_t cap) const {
  if (opt_.cone_rad > 0 && rows_in_closed_form_) {  // (cells inside a minimum tilt counted too: at most a few)
    std::size_t n = 0;
    scan_rows(cl.axis, std::cos(opt_.cone_rad) - 1e-15, [&](double, int, int) { ++n; });
    return std::min(n, cap);
  }
  std::vector<Cell> cells;
  Counters ignored;
  enumerate(cl, cells, cap, ignored);
  return cells.size();
}

void Space::enumerate(const kin::Posed& cl, std::vector<Cell>& out, std::size_t cap, Counters& c) const {
  out.clear();
  std::vector<kin::Solution> sols;  // (the row scan needs none)
  if (opt_.cone_rad <= 0 || !rows_in_closed_form_) kin_->inverse_all(cl, nullptr, sols);
  const double res = opt_.resolution_rad;
  const double lo1 = i1_min_ * res - 1e-9, hi1 = i1_max_ * res + 1e-9, lo2 = i2_min_ * res - 1e-9,
               hi2 = i2_max_ * res + 1e-9;
  if (opt_.cone_rad <= 0) {
    // Exact orientation: the cells are the IK solutions themselves (every branch and winding).
    for (const auto& s : sols) {
      const double r1 = s.axes[rot1_], r2 = s.axes[rot2_];
      if (r1 < lo1 || r1 > hi1 || r2 < lo2 || r2 > hi2) continue;
      Cell cell;
      cell.r1 = r1;
      cell.r2 = r2;
      cell.i1 = static_cast<int>(std::lround(r1 / res));
      cell.i2 = static_cast<int>(std::lround(r2 / res));
      cell.orient_err = static_cast<float>(s.axis_error_rad);  // 0 unless the machine reaches the axis only nearly
      cell.singular = s.singular;
      out.push_back(cell);
    }
    c.cells_enumerated += out.size();
    return;
  }
  // Serial machines: a scan of the rows in closed form (scan_rows, below). Others: a best-first flood fill over the
  // grid cells inside the cone, seeded at the grid cells around every IK solution:
  // cells come out closest to the CL axis first, so the cap bounds the work as well as the output (near the
  // singularity the cone covers every primary angle: far too many cells to visit all). The min-tilt annulus is
  // crossed (cells inside min tilt are traversed but not output).
  // Visited marks on the dense grid, reused between calls of this thread; only touched entries are reset.
  thread_local std::vector<std::uint8_t> seen;
  thread_local std::vector<std::size_t> touched;
  const std::size_t n1 = static_cast<std::size_t>(i1_max_ - i1_min_) + 1;
  const std::size_t ncells = n1 * (static_cast<std::size_t>(i2_max_ - i2_min_) + 1);
  if (seen.size() < ncells) seen.assign(ncells, 0);
  touched.clear();
  const double cos_cone = std::cos(opt_.cone_rad);
  // Keyed on the cosine to the CL axis (the angle falls as it grows): one arc cosine per cell output, not per push.
  struct Item {
    double dot;
    int i1, i2;
    bool operator<(const Item& o) const { return dot < o.dot; }
  };
  thread_local std::vector<Item> heap;
  heap.clear();
  bool push_heap_order = false;
  Eigen::Vector3d a;
  auto push = [&](int i1, int i2) {
    if (i1 < i1_min_ || i1 > i1_max_ || i2 < i2_min_ || i2 > i2_max_) return;
    const std::size_t at = static_cast<std::size_t>(i2 - i2_min_) * n1 + static_cast<std::size_t>(i1 - i1_min_);
    if (seen[at]) return;
    seen[at] = 1;
    touched.push_back(at);
    if (!R1_grid_.empty()) {
      a = grid_axis(i1, i2);
    } else if (!pose_axis(cl, i1 * res, i2 * res, a)) {
      return;
    }
    const double d = a.dot(cl.axis);
    if (d < cos_cone - 1e-15) return;
    heap.push_back({d, i1, i2});
    if (push_heap_order) std::push_heap(heap.begin(), heap.end());
  };
  // Seeds: the grid cells around every solution. A rotary value with no winding on the grid (beyond a limit) seeds
  // from the grid's nearest edge instead, in every winding of the other rotary on the grid (inverse_all lists only
  // the solution itself then): the cone may still hold reachable cells inside the limit (the XMINI's A one degree past
  // its stroke, with a 10 degree cone, had none found before). Inside the limits every winding is a solution of its
  // own.
  constexpr double kTurn = 2.0 * std::numbers::pi;
  thread_local std::vector<double> seeds1, seeds2;
  // The windings of v on the grid [lo, hi]; none: false, and `edge` gets the grid's end nearest to one of them.
  auto on_grid = [&](double v, int lo, int hi, std::vector<double>& out, double& edge) {
    out.clear();
    const double vlo = lo * res, vhi = hi * res;
    const double kmin = std::ceil((vlo - v) / kTurn), kmax = std::floor((vhi - v) / kTurn);
    for (double k = kmin; k <= kmax; ++k) out.push_back(v + k * kTurn);
    const double below = v + kmax * kTurn, above = v + kmin * kTurn;  // without one: the windings either side
    edge = vlo - below <= above - vhi ? vlo : vhi;
    return !out.empty();
  };
  auto seed = [&] {
    for (const auto& s : sols) {
      const double v1 = s.axes[rot1_], v2 = s.axes[rot2_];
      double e1 = 0, e2 = 0;
      const bool in1 = on_grid(v1, i1_min_, i1_max_, seeds1, e1), in2 = on_grid(v2, i2_min_, i2_max_, seeds2, e2);
      if (in1 && in2) {
        seeds1.assign(1, v1);
        seeds2.assign(1, v2);
      }
      if (!in1) seeds1.assign(1, e1);
      if (!in2) seeds2.assign(1, e2);
      for (const double a1 : seeds1)
        for (const double a2 : seeds2)
          for (int d1 = 0; d1 <= 1; ++d1)
            for (int d2 = 0; d2 <= 1; ++d2) {
              const int i1 = static_cast<int>(std::floor(a1 / res)) + d1,
                        i2 = static_cast<int>(std::floor(a2 / res)) + d2;
              push(in1 ? i1 : std::clamp(i1, i1_min_, i1_max_), in2 ? i2 : std::clamp(i2, i2_min_, i2_max_));
            }
    }
  };
  // Small records while filling; the (larger) cells are built once, in their final order.
  struct Found {
    float err;
    int i1, i2;
  };
  thread_local std::vector<Found> found;
  found.clear();
  auto take = [&](const Item& it) {
    const double err = std::acos(std::clamp(it.dot, -1.0, 1.0));
    if (err >= opt_.min_tilt_rad) found.push_back({static_cast<float>(err), it.i1, it.i2});
    push(it.i1 + 1, it.i2);
    push(it.i1 - 1, it.i2);
    push(it.i1, it.i2 + 1);
    push(it.i1, it.i2 - 1);
  };
  // First a plain flood fill (a stack, no heap order): when the whole cone fits under the cap, the output is the
  // whole cone, sorted below, whatever the visiting order. Past the cap it starts again best-first, which visits
  // only the closest cells. (Neighbouring points have cones of about the same size: after an overflow this thread
  // goes best-first at once. Only the work depends on that, never the cells.)
  thread_local bool overflowed_before = false;
  bool whole = !overflowed_before;
  if (rows_in_closed_form_) {
    // Every in-cone grid cell, row by row (no flood fill, no heap), also where the cone runs off the grid's end
    // (cells there that no solution seeds). The cap keeps the closest after the sort below.
    thread_local std::vector<Item> in_cone;
    in_cone.clear();
    scan_rows(cl.axis, cos_cone - 1e-15, [&](double d, int i1, int i2) { in_cone.push_back({d, i1, i2}); });
    // Past the cap, angles (an arc cosine each) only for the cells that can make it: those within a hair of the
    // cap-th largest cosine (the float angles the sort uses may tie across less than that).
    double least_dot = -2.0;
    if (opt_.min_tilt_rad <= 0 && cap > 0 && in_cone.size() > cap) {
      const auto kth = in_cone.begin() + static_cast<std::ptrdiff_t>(cap - 1);
      std::nth_element(in_cone.begin(), kth, in_cone.end(), [](const Item& x, const Item& y) { return y < x; });
      least_dot = kth->dot - 1e-6;
    }
    for (const Item& it : in_cone) {
      if (it.dot < least_dot) continue;
      const double err = std::acos(std::clamp(it.dot, -1.0, 1.0));
      if (err >= opt_.min_tilt_rad) found.push_back({static_cast<float>(err), it.i1, it.i2});
    }
    whole = true;
  } else if (whole) {
    seed();
    while (!heap.empty()) {
      const Item it = heap.back();
      heap.pop_back();
      take(it);
      if (found.size() > cap) {
        whole = false;
        break;
      }
    }
    for (std::size_t at : touched) seen[at] = 0;
    overflowed_before = !whole;
  }
  if (!whole && !rows_in_closed_form_) {
    touched.clear();
    heap.clear();
    found.clear();
    push_heap_order = true;
    seed();
    while (!heap.empty() && found.size() < cap) {
      std::pop_heap(heap.begin(), heap.end());
      const Item it = heap.back();
      heap.pop_back();
      take(it);
    }
    overflowed_before = !heap.empty();  // in-cone cells left over: the cone is larger than the cap
    for (std::size_t at : touched) seen[at] = 0;
  }
  // Sorted by angle, then index: one 64-bit key per cell, the float's bits (a non-negative float orders as its bits
  // do) above the cell's row-major grid position (i2, then i1), which sorts several times faster than the records.
  auto before = [](const Found& x, const Found& y) {
    if (x.err != y.err) return x.err < y.err;
    return std::tie(x.i2, x.i1) < std::tie(y.i2, y.i1);
  };
  const auto n1_grid = static_cast<std::uint64_t>(i1_max_ - i1_min_) + 1;
  const auto n2_grid = static_cast<std::uint64_t>(i2_max_ - i2_min_) + 1;
  constexpr int kPosBits = 30;
  if (n1_grid * n2_grid <= (std::uint64_t{1} << kPosBits)) {
    thread_local std::vector<std::uint64_t> keys;
    keys.resize(found.size());
    for (std::size_t j = 0; j < found.size(); ++j) {
      std::uint32_t bits = 0;
      std::memcpy(&bits, &found[j].err, sizeof bits);
      const std::uint64_t pos = static_cast<std::uint64_t>(found[j].i2 - i2_min_) * n1_grid +
                                static_cast<std::uint64_t>(found[j].i1 - i1_min_);
      keys[j] = (static_cast<std::uint64_t>(bits) << kPosBits) | pos;
    }
    // LSD radix sort, 11 bits at a time, every digit's histogram from one pass, skipping the digits all keys share:
    // a cone's thousands of keys sort about 2.5x faster than by comparison (the keys are distinct, so the order is
    // the same).
    constexpr int kDigitBits = 11, kDigits = (32 + kPosBits + kDigitBits - 1) / kDigitBits;
    constexpr std::uint64_t kMask = (1u << kDigitBits) - 1;
    thread_local std::vector<std::uint32_t> counts;
    counts.assign(static_cast<std::size_t>(kDigits) << kDigitBits, 0);
    for (const std::uint64_t k : keys)
      for (int dgt = 0; dgt < kDigits; ++dgt)
        ++counts[(static_cast<std::size_t>(dgt) << kDigitBits) + ((k >> (dgt * kDigitBits)) & kMask)];
    thread_local std::vector<std::uint64_t> spare;
    spare.resize(keys.size());
    for (int dgt = 0; dgt < kDigits && !keys.empty(); ++dgt) {
      std::uint32_t* start = counts.data() + (static_cast<std::size_t>(dgt) << kDigitBits);
      const int shift = dgt * kDigitBits;
      if (start[(keys.front() >> shift) & kMask] == keys.size()) continue;  // one value: nothing to sort
      std::uint32_t sum = 0;
      for (std::size_t b = 0; b <= kMask; ++b) sum += std::exchange(start[b], sum);
      for (const std::uint64_t k : keys) spare[start[(k >> shift) & kMask]++] = k;
      keys.swap(spare);
    }
    for (std::size_t j = 0; j < found.size(); ++j) {
      const auto bits = static_cast<std::uint32_t>(keys[j] >> kPosBits);
      float err = 0;
      std::memcpy(&err, &bits, sizeof err);
      const std::uint64_t pos = keys[j] & ((std::uint64_t{1} << kPosBits) - 1);
      found[j] = {err, i1_min_ + static_cast<int>(pos % n1_grid), i2_min_ + static_cast<int>(pos / n1_grid)};
    }
  } else {
    std::sort(found.begin(), found.end(), before);
  }
  if (found.size() > cap) found.resize(cap);  // (the row scan lists the whole cone)
  out.resize(found.size());                   // built in place: a copy per cell was a visible share of the listing
  for (std::size_t j = 0; j < found.size(); ++j) {
    Cell& cell = out[j];
    const Found& f = found[j];
    cell.r1 = f.i1 * res;
    cell.r2 = f.i2 * res;
    cell.i1 = f.i1;
    cell.i2 = f.i2;
    cell.orient_err = f.err;
  }
  c.cells_enumerated += out.size();
}

void Space::evaluate(const kin::Posed& cl, Cell& cell, geom::QueryWorkspace& ws, Counters& c, Certificate* cert,
                     HitCertificate* hit) const {
  if (cell.status != Status::Unknown) {
    ++c.cache_hits;
    return;
  }
  const kin::Posed pose = tool_pose(cl, cell.r1, cell.r2);
  kin::Axes q = kin::Axes::Zero();
  q[rot1_] = cell.r1;
  q[rot2_] = cell.r2;
  ++c.ik;
  if (!kin_->solve_for_rotaries(pose, q)) {
    cell.status = Status::Stroke;
    cell.detail = "no linear-axis solution";
    return;
  }
  cell.axes = q;
  ++c.stroke;
  std::string v = kin_->check_limits(q);
  if (v.empty()) v = kin_->passive_violation(q);
  if (!v.empty()) {
    cell.status = Status::Stroke;
    cell.detail = std::move(v);
    return;
  }
  if (opt_.check_collision && scene_ && tool_) {
    LinkPoses links;
    geom::CheckOptions linked;
    const Eigen::Isometry3d* head_placed = nullptr;
    const geom::CheckOptions& co = with_links(q, links, linked, &head_placed);
    // Head bodies are certified by their bounding boxes grown by the margin (check_meshes has no clearance).
    const bool certify = certify_links_ && certify_head_;
    // A certificate from a neighbouring point covers this pose: same rotaries and axis, moved less than the margin.
    if (cert && cert->valid && certify && cell.r1 == cert->r1 && cell.r2 == cert->r2 &&
        pose.axis.dot(cert->axis) > 1.0 - 1e-15 && (pose.tip_mm - cert->tip_mm).norm() < cert->margin_mm) {
      ++c.certified;
      cell.status = Status::Feasible;
      return;
    }
    if (hit && certify) {
      // A hit certificate from a neighbouring point covers this pose: same rotaries and axis, moved less than the
      // margin.
      if (hit->valid && cell.r1 == hit->r1 && cell.r2 == hit->r2 && pose.axis.dot(hit->axis) > 1.0 - 1e-15 &&
          (pose.tip_mm - hit->tip_mm).norm() < hit->margin_mm) {
        ++c.certified;
        cell.status = Status::Collision;
        cell.detail = hit->detail;
        return;
      }
      hit->valid = false;
      // It collided last time: probe eroded. A hit decides this cell and certifies the next points. The previous
      // contact first (one triangle test), then a query.
      const geom::Witness wit = hit->witness;
      if (hit->collided_before && hit->probe_mm >= kMinHitProbeMm) {
        geom::CheckOptions o = co;
        o.erosion_mm = hit->probe_mm;
        geom::CollisionResult r = geom::check_witness(*scene_, *tool_, pose, o, ws, wit);
        if (r.collides) {
          ++c.witnessed;
        } else {
          ++c.collision;
          r = geom::check(*scene_, *tool_, pose, o, ws);
        }
        if (r.collides) {
          cell.status = Status::Collision;
          cell.detail = collision_detail(r);
          *hit = {true,          pose.tip_mm,   pose.axis, cell.r1,     cell.r2,
                  hit->probe_mm, hit->probe_mm, true,      cell.detail, {r.segment, r.obstacle, r.triangle}};
          return;
        }
        hit->probe_mm *= 0.5;  // less erosion next time (a deep hit is rare at the edge of the free region)
      }
      // Shallower than the erosion: the previous contact may still prove this point's hit.
      if (wit.valid()) {
        const geom::CollisionResult r = geom::check_witness(*scene_, *tool_, pose, co, ws, wit);
        if (r.collides) {
          ++c.witnessed;
          cell.status = Status::Collision;
          cell.detail = collision_detail(r);
          hit->collided_before = true;
          return;
        }
        hit->witness = {};
      }
    }
    if (cert && certify) {
      // Probe with a margin; on success this pose certifies its neighbours. The cutter body is extended
      // toward the tip by the margin (less relief) so that a translation along the axis is covered too.
      const double r = tool_->cutter.corner_radius_mm;
      const double relief = opt_.collision.relief_mm >= 0 ? opt_.collision.relief_mm : (r > 0 ? 0.2 * r : 0.5);
      const double m = std::min(cert->probe_mm, relief);
      geom::CheckOptions o = co;
      o.clearance_mm += m;
      o.cutter_clearance_mm += m;
      o.relief_mm = relief - m;
      ++c.collision;
      Eigen::Isometry3d T_head_part;
      if (m > 0 && !geom::check(*scene_, *tool_, pose, o, ws).collides &&
          (!head_ || !head_pose(q, head_placed, T_head_part) ||
           geom::meshes_apart(*head_, T_head_part, *scene_, co, m))) {
        *cert = {true, pose.tip_mm, pose.axis, cell.r1, cell.r2, m, cert->probe_mm};
        cell.status = Status::Feasible;
        return;
      }
      cert->valid = false;
    }
    ++c.collision;
    const geom::CollisionResult r = geom::check(*scene_, *tool_, pose, co, ws);
    if (hit) {
      hit->collided_before = r.collides;
      if (r.collides) hit->witness = {r.segment, r.obstacle, r.triangle};
    }
    if (r.collides) {
      cell.status = Status::Collision;
      cell.detail = collision_detail(r);
      return;
    }
    if (hit) hit->probe_mm = 1.0;
    if (!std::isnan(r.min_distance_mm)) cell.clearance_mm = static_cast<float>(r.min_distance_mm);
    if (head_) {
      Eigen::Isometry3d T;
      if (head_pose(q, head_placed, T)) {
        int hm = -1;
        const geom::CollisionResult h = geom::check_meshes(*head_, T, *scene_, co, ws, &hm);
        if (h.collides) {
          cell.status = Status::Collision;
          cell.detail = fmt::format("{} hits {}", head_->obstacle_name(static_cast<std::size_t>(hm)),
                                    scene_->obstacle_name(static_cast<std::size_t>(h.obstacle)));
          return;
        }
      }
    }
  }
  cell.status = Status::Feasible;
}

std::string Space::collision_at(const kin::Posed& pose, geom::QueryWorkspace& ws, Counters& c) const {
  if (!opt_.check_collision || !scene_ || !tool_) return {};
  ++c.collision;
  const geom::CollisionResult r = geom::check(*scene_, *tool_, pose, opt_.collision, ws);
  if (!r.collides) return {};
  return collision_detail(r);
}

std::string Space::collision_detail(const geom::CollisionResult& r) const {
  return fmt::format("{} hits {}", geom::to_string(r.part),
                     r.obstacle >= 0 ? scene_->obstacle_name(static_cast<std::size_t>(r.obstacle)) : std::string("?"));
}

bool Space::free_with_margin(const kin::Posed& cl, const Cell& cell, double margin_mm, geom::QueryWorkspace& ws,
                             Counters& c) const {
  if (!opt_.check_collision || !scene_ || !tool_) return true;
  LinkPoses links;
  geom::CheckOptions linked;
  geom::CheckOptions o = with_links(cell.axes, links, linked);
  o.clearance_mm += margin_mm;
  o.cutter_clearance_mm += margin_mm;
  ++c.collision;
  return !geom::check(*scene_, *tool_, tool_pose(cl, cell.r1, cell.r2), o, ws).collides;
}

std::string Space::collision_at_axes(const kin::Axes& q, geom::QueryWorkspace& ws, Counters& c, SweepMode mode) const {
  if (!opt_.check_collision || !scene_ || !tool_) return {};
  LinkPoses links;
  geom::CheckOptions linked;
  const Eigen::Isometry3d* head_placed = nullptr;
  const geom::CheckOptions& co = with_links(q, links, linked, &head_placed);
  if (mode == SweepMode::Rapid) {  // the whole tool, its cutting end too: a rapid must not touch anything
    if (std::string hit = collision_inflated_placed(co, kin_->forward(q), 0.0, SweepMode::Rapid, ws, c); !hit.empty())
      return hit;
  } else {
    ++c.collision;
    const geom::CollisionResult r = geom::check(*scene_, *tool_, kin_->forward(q), co, ws);
    if (r.collides) return collision_detail(r);
  }
  if (!head_) return {};
  Eigen::Isometry3d T;
  if (!head_pose(q, head_placed, T)) return {};
  int hm = -1;
  const geom::CollisionResult h = geom::check_meshes(*head_, T, *scene_, co, ws, &hm);
  if (!h.collides) return {};
  return fmt::format("{} hits {}", head_->obstacle_name(static_cast<std::size_t>(hm)),
                     scene_->obstacle_name(static_cast<std::size_t>(h.obstacle)));
}

bool Space::head_pose(const kin::Axes& q, const Eigen::Isometry3d* placed, Eigen::Isometry3d& T) const {
  if (placed) {
    T = *placed;
    return true;
  }
  return kin_->head_in_part(q, T);
}

bool Space::place_links(const kin::Kinematics& k, const kin::Axes& q, int n, LinkPoses& T, unsigned used) {
  return k.links_in_part(q, n, used, T.data());
}

const geom::CheckOptions& Space::with_links(const kin::Axes& q, LinkPoses& links, geom::CheckOptions& scratch,
                                            const Eigen::Isometry3d** head) const {
  if (head) *head = nullptr;
  // Nothing to place: no linked obstacle, or only fixed ones and the options leave machine obstacles out.
  if (links_ == 0 || (!head_ && !(opt_.collision.roles & static_cast<unsigned>(geom::ObstacleRole::Machine))))
    return opt_.collision;
  if (head && head_link_ >= 0) {  // the head's link in the same pass: the joint motions are computed once
    CSCAM_CHECK(place_links(*kin_, q, std::max(links_, head_link_ + 1), links, used_links_ | (1u << head_link_)),
                "machine link poses unavailable");
    *head = &links[static_cast<std::size_t>(head_link_)];
  } else {
    CSCAM_CHECK(place_links(*kin_, q, links_, links, used_links_), "machine link poses unavailable");
  }
  scratch = opt_.collision;
  scratch.links_in_part = links.data();
  return scratch;
}

}  // namespace cscam::cspace
