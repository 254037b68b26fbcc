// Swept (between-point) collision checks with a clearance certificate.
#include <fmt/format.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <vector>

#include "cscam/cspace/cspace.hpp"

namespace cscam::cspace {

const char* to_string(SweepStatus s) {
  switch (s) {
    case SweepStatus::Free:
      return "free";
    case SweepStatus::Collides:
      return "collides";
    case SweepStatus::Uncertified:
      return "uncertified";
  }
  return "?";
}

namespace {

constexpr double kInfinity = std::numeric_limits<double>::infinity();

/// Bisection limits of one swept move: past these the move is reported Uncertified (never Free).
constexpr int kMaxDepth = 40;
constexpr std::uint64_t kMaxQueriesPerMove = 2000;

/// |d tip / d q_j| and |d axis / d q_j| (rad per unit) at q, by forward differences.
struct Gains {
  std::array<double, 5> tip{}, axis{};
};

Gains gains_at(const kin::Kinematics& k, const kin::Axes& q, const kin::Axes& dq) {
  Gains g;
  const kin::Posed p0 = k.forward(q);
  for (int j = 0; j < 5; ++j) {
    if (dq[j] == 0) continue;  // an axis that does not move contributes nothing
    constexpr double eps = 1e-6;
    kin::Axes qq = q;
    qq[j] += eps;
    const kin::Posed p1 = k.forward(qq);
    g.tip[static_cast<size_t>(j)] = (p1.tip_mm - p0.tip_mm).norm() / eps;
    g.axis[static_cast<size_t>(j)] = (p1.axis - p0.axis).norm() / eps;
  }
  return g;
}

}  // namespace

double interval_reach_bound(const kin::Posed& at_lo, const kin::Posed& at_hi, double half_width,
                            const kin::MotionBound& bound, double lever_mm) {
  const double h2 = half_width * half_width;
  // The unit axis turns by at most its arc length from the middle, bounded exactly as the tip's path (|a'| is the
  // angular speed).
  const double tip = 0.5 * (at_hi.tip_mm - at_lo.tip_mm).norm() + h2 * bound.tip_accel_mm;
  const double turn = 0.5 * (at_hi.axis - at_lo.axis).norm() + h2 * bound.axis_accel;
  return tip + lever_mm * turn;
}

double Space::cutting_margin_cap_mm() const {
  if (!tool_) return 0.0;
  const double r = tool_->cutter.corner_radius_mm;
  return opt_.collision.relief_mm >= 0 ? opt_.collision.relief_mm : (r > 0 ? 0.2 * r : 0.5);
}

std::string Space::collision_inflated(const kin::Axes& q, const kin::Posed& pose, double m, SweepMode mode,
                                      geom::QueryWorkspace& ws, Counters& c, double m_cutter) const {
  if (!checks_collision()) return {};
  // Machine bodies carried by the axes are placed for q. (They may move relative to the part within a move, so for
  // them the inflation certifies only the sampled poses, as for head meshes.)
  LinkPoses links;
  geom::CheckOptions scratch;
  return collision_inflated_placed(with_links(q, links, scratch), pose, m, mode, ws, c, m_cutter);
}

std::string Space::collision_inflated_placed(const geom::CheckOptions& placed, const kin::Posed& pose, double m,
                                             SweepMode mode, geom::QueryWorkspace& ws, Counters& c,
                                             double m_cutter) const {
  if (m_cutter < 0) m_cutter = m;
  auto name = [&](const geom::CollisionResult& r, const char* part) {
    return fmt::format(
        "{} hits {}", part ? part : geom::to_string(r.part),
        r.obstacle >= 0 ? scene_->obstacle_name(static_cast<std::size_t>(r.obstacle)) : std::string("?"));
  };
  geom::CheckOptions o = placed;
  o.clearance_mm += m;
  o.cutter_clearance_mm += m_cutter;
  if (mode == SweepMode::Cutting) {
    // The checked cutter body reaches down its margin further toward the tip (the Minkowski sum's lower cap).
    o.relief_mm = std::max(0.0, cutting_margin_cap_mm() - m_cutter);
    ++c.collision;
    const geom::CollisionResult r = geom::check(*scene_, *tool_, pose, o, ws);
    return r.collides ? name(r, nullptr) : std::string();
  }
  // Rapid: the cutter body from its corner radius up, plus the tip cylinder (ball or corner region) below it,
  // shifted m toward the tip so that its lower cap covers the inflation.
  o.relief_mm = 0.0;
  ++c.collision;
  const geom::CollisionResult r = geom::check(*scene_, *tool_, pose, o, ws);
  if (r.collides) return name(r, nullptr);
  const kin::Posed low{pose.tip_mm - m_cutter * pose.axis, pose.axis};
  ++c.collision;
  const geom::CollisionResult t = geom::check(*scene_, tip_tool_, low, o, ws);
  return t.collides ? name(t, "cutter tip") : std::string();
}

SweptResult Space::swept(const kin::Axes& qa, const kin::Axes& qb, SweepMode mode, geom::QueryWorkspace& ws,
                         Counters& c, std::uint64_t max_queries) const {
  const std::uint64_t budget = max_queries > 0 ? max_queries : kMaxQueriesPerMove;
  SweptResult res;
  ++c.swept;
  Counters q_count;  // its queries count as swept queries, apart from the cell queries
  if (!checks_collision()) return res;
  const kin::Axes dq = qb - qa;
  const double cap = mode == SweepMode::Cutting ? cutting_margin_cap_mm() : kRapidSweepMarginCapMm;
  const auto& axes = kin_->axes();
  // Bound on the speed (mm per unit move parameter) of every point of the tool body over [lo, hi].
  // The body is symmetric about its axis, so its motion is the tip's plus the axis tilt times the reach.
  // Tip: linear gains are sampled at both ends and the middle (constant on a serial machine, 25 % slack
  // where they vary); a rotary moves the tip at the tip's distance from its axis, which over the interval grows
  // at most by twice the tip's own travel (the carried axis moves too): rho(t) <= rho_max + 2 h V_tip.
  auto speed_bound = [&](double lo, double hi) {
    const double h = hi - lo;
    std::array<Gains, 3> g = {gains_at(*kin_, qa + lo * dq, dq), gains_at(*kin_, qa + 0.5 * (lo + hi) * dq, dq),
                              gains_at(*kin_, qa + hi * dq, dq)};
    double A = 0, Brho = 0, B = 0, Vaxis = 0;
    for (int j = 0; j < 5; ++j) {
      const auto J = static_cast<size_t>(j);
      const double d = std::abs(dq[j]);
      if (d == 0) continue;
      double tip = 0, tmin = std::numeric_limits<double>::infinity(), ax = 0, amin = tmin;
      for (const Gains& x : g) {
        tip = std::max(tip, x.tip[J]);
        tmin = std::min(tmin, x.tip[J]);
        ax = std::max(ax, x.axis[J]);
        amin = std::min(amin, x.axis[J]);
      }
      if (axes[J].rotary()) {
        Brho += d * tip;
        B += d;
        Vaxis += d * std::max(1.0, ax);  // a rotation tilts the axis at most at its own rate
      } else {
        A += d * tip * (tip - tmin > 1e-9 ? 1.25 : 1.0);
        Vaxis += d * ax * (ax - amin > 1e-9 ? 1.25 : 1.0);
      }
    }
    const double denom = 1.0 - 2.0 * h * B;
    if (denom < 0.5) return std::pair{kInfinity, kInfinity};  // interval turns too far: split
    // The whole body, and the cutter body alone (a shorter lever: near the part it is often what limits the margin).
    return std::pair{(A + Brho) / denom + reach_mm_ * Vaxis, (A + Brho) / denom + cutter_reach_mm_ * Vaxis};
  };
  // Where the kinematics bounds the move's second derivatives, the second-order bound from the interval's end poses
  // (interval_reach_bound) too; the smaller of the two holds.
  kin::MotionBound mb;
  const bool second_order = kin_->motion_bound(qa, qb, mb);
  struct Interval {
    double lo, hi;
    int depth;
    kin::Posed at_lo, at_hi;
  };
  std::vector<Interval> stack{{0.0, 1.0, 0, kin_->forward(qa), kin_->forward(qb)}};
  while (!stack.empty()) {
    const Interval iv = stack.back();
    stack.pop_back();
    const double t = 0.5 * (iv.lo + iv.hi);
    const kin::Axes q = qa + t * dq;
    const kin::Posed pose = kin_->forward(q);
    const auto [v_body, v_cutter] = speed_bound(iv.lo, iv.hi);
    const double h = 0.5 * (iv.hi - iv.lo);
    double m = h * v_body, m_cutter = h * v_cutter;
    if (second_order) {
      m = std::min(m, interval_reach_bound(iv.at_lo, iv.at_hi, h, mb, reach_mm_));
      m_cutter = std::min(m_cutter, interval_reach_bound(iv.at_lo, iv.at_hi, h, mb, cutter_reach_mm_));
    }
    m += 1e-6;
    m_cutter += 1e-6;
    // The cutter body near the part bounds its margin by the relief; the others' margins have no such bound, but
    // past the rapid cap an inflated probe fails near anything, and splitting is cheaper.
    if (m_cutter <= cap && m <= std::max(cap, kRapidSweepMarginCapMm)) {
      ++res.queries;
      if (collision_inflated(q, pose, m, mode, ws, q_count, m_cutter).empty()) {
        if (head_) {
          // Head meshes: at the certified poses (sampled, not certified).
          const std::string h = collision_at_axes(q, ws, q_count);
          if (!h.empty()) {
            res = {SweepStatus::Collides, t, h, res.queries + 1};
            break;
          }
        }
        continue;
      }
    }
    ++res.queries;
    const std::string hit = collision_inflated(q, pose, 0.0, mode, ws, q_count);
    if (!hit.empty()) {
      res.status = SweepStatus::Collides;
      res.t = t;
      res.detail = hit;
      break;
    }
    if (iv.depth >= kMaxDepth || res.queries >= budget) {
      res.status = SweepStatus::Uncertified;
      res.t = t;
      res.detail = fmt::format("clearance too small to certify within {} queries", res.queries);
      break;
    }
    stack.push_back({t, iv.hi, iv.depth + 1, pose, iv.at_hi});  // left half first: the earliest hit is found first
    stack.push_back({iv.lo, t, iv.depth + 1, iv.at_lo, pose});
  }
  res.queries = q_count.collision;
  c.swept_queries += q_count.collision;
  return res;
}

}  // namespace cscam::cspace
