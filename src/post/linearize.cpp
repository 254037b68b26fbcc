#include "linearize.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdint>

#include "cscam/core/error.hpp"
#include "cscam/core/rotations.hpp"
#include "cscam/core/segment.hpp"
#include "cscam/core/tolerances.hpp"
#include "cscam/kin/track.hpp"

namespace cscam::post {

using Vec3 = Eigen::Vector3d;

Slerp::Slerp(const Vec3& a, const Vec3& b) : a_(a), b_(b), th_(std::acos(std::clamp(a.dot(b), -1.0, 1.0))) {
  sn_ = std::sin(th_);
}

double Slerp::sine(double x) const {
  for (int k = 0; k < memo_size_; ++k)  // the same bits (not -0 for +0)
    if (std::bit_cast<std::uint64_t>(memo_x_[static_cast<size_t>(k)]) == std::bit_cast<std::uint64_t>(x))
      return memo_sin_[static_cast<size_t>(k)];
  const double v = std::sin(x);
  memo_x_[static_cast<size_t>(memo_next_)] = x;
  memo_sin_[static_cast<size_t>(memo_next_)] = v;
  memo_next_ = (memo_next_ + 1) % kMemo;
  memo_size_ = std::min(memo_size_ + 1, kMemo);
  return v;
}

Vec3 Slerp::operator()(double s) const {
  if (th_ < 1e-9) return ((1 - s) * a_ + s * b_).normalized();
  return (sine((1 - s) * th_) / sn_ * a_ + sine(s * th_) / sn_ * b_).normalized();
}

double Slerp::best_dot(const Vec3& u, double lo, double hi) const {
  return sn_ < 1e-12 ? std::max(u.dot(a_), u.dot(b_)) : rot::arc_best_dot(a_, b_, th_, sn_, u, lo, hi);
}

namespace {
// Two axis vectors this far apart in rotary travel at the same pose are different IK branches, not a
// continuous turn (a subdivided span's rotaries move far less than this).
constexpr double kBranchChangeRad = 1e-3;
}  // namespace

std::string rotary_change(const kin::Kinematics& k, const kin::Axes& qa, const kin::Axes& qb) {
  const auto rp = k.rotary_pair();
  const auto& ax = k.axes();
  return fmt::format("{} {:.3f} -> {:.3f} deg, {} {:.3f} -> {:.3f} deg", ax[static_cast<size_t>(rp[0])].name,
                     qa[rp[0]] * 180.0 / M_PI, qb[rp[0]] * 180.0 / M_PI, ax[static_cast<size_t>(rp[1])].name,
                     qa[rp[1]] * 180.0 / M_PI, qb[rp[1]] * 180.0 / M_PI);
}

std::string Linearizer::remedy() const {
  // A planned program already chose its orientations within a cone: between two of them the tool axis passes by a
  // singular orientation (the interpolated axis needs the primary rotary to swing), which another grid or cone avoids.
  return set_.planned ? "the planned orientations pass beside a singular orientation here: plan again with another "
                        "--cone or --resolution, or split the segment"
                      : "split the segment or plan it with a cone";
}

namespace {
/// Samples a piece takes at most to prove its tip path (more: it is split instead).
constexpr double kMaxCertifySamples = 256;
}  // namespace

Linearizer::Linearizer(const kin::Kinematics& k, const Settings& s)
    : kin_(k),
      set_(s),
      cos_tol_axis_(std::cos(s.axis_tolerance_rad)),
      // Within the cone itself: the axis tolerance is left for what the gate's denser samples find between the
      // linearizer's (the joint path may bulge out of the cone there).
      cos_cone_tol_(std::cos(std::min(M_PI, s.cone_rad))),
      cos_fast_axis_(std::cos(0.9 * s.axis_tolerance_rad)),
      cos_fast_cone_(std::cos(std::min(M_PI, std::max(0.0, s.cone_rad - 0.1 * s.axis_tolerance_rad)))),
      // The gate's tolerance (the post's plus its slack) less a sixteenth for the bound between its samples and a
      // quarter of the slack for the rounding of the printed words.
      tip_certified_mm_((s.tolerance_mm + tol::kVerifySlackMm) * (1.0 - 1.0 / 16) - 0.25 * tol::kVerifySlackMm) {}

Linearizer::Along Linearizer::along(const Vec3& ctrl, const Vec3& P0, const Vec3& ab, double L2, double s) {
  if (!(L2 > 0)) return {s, s, 0.0};  // no tip motion: anywhere along the orientation (stretch)
  const Vec3 d = ctrl - P0;
  const double t_line = d.dot(ab) / L2;
  return {s, t_line, std::max(0.0, d.squaredNorm() - t_line * t_line * L2)};
}

std::array<double, 2> Linearizer::stretch(const Along& w, double L2) const {
  if (!(L2 > 0)) return {0.0, 1.0};
  const double half = std::sqrt(std::max(0.0, set_.tolerance_mm * set_.tolerance_mm - w.h2) / L2);
  const double t = std::clamp(w.t_line, 0.0, 1.0);
  return {std::clamp(w.t_line - half, 0.0, t), std::clamp(w.t_line + half, t, 1.0)};
}

bool Linearizer::axis_ok(const Axis& axis, const Vec3& u, const Along& w, double L2) const {
  // Without trigonometry where the sample is where its time says (the tip moves evenly): within 0.9 of the
  // tolerance at s, and the tip's projection at most 0.1 of it further along the arc.
  const double lag = std::abs(std::clamp(w.t_line, 0.0, 1.0) - w.s);
  if (lag * axis.own.angle() <= 0.1 * set_.axis_tolerance_rad && u.dot(axis.own(w.s)) >= cos_fast_axis_) return true;
  const auto [lo, hi] = stretch(w, L2);
  if (axis.own.best_dot(u, lo, hi) >= cos_tol_axis_) return true;
  // Near a singular orientation the slerp of two planned axes can pass on the other side of the pole from the
  // machine's joint interpolation (a fraction of a degree away, but with the primary rotary half a turn apart);
  // both are within the cone the plan was made in.
  if (!axis.cl) return false;
  if (lag * axis.cl->angle() <= 0.1 * set_.axis_tolerance_rad && u.dot((*axis.cl)(w.s)) >= cos_fast_cone_) return true;
  return axis.cl->best_dot(u, lo, hi) >= cos_cone_tol_;
}

double Linearizer::axis_deviation(const Axis& axis, const Vec3& u, const Along& w, double L2) const {
  const auto angle = [](double dot) { return std::acos(std::clamp(dot, -1.0, 1.0)); };
  const auto [lo, hi] = stretch(w, L2);
  const double own = angle(axis.own.best_dot(u, lo, hi));
  return axis.cl ? std::min(own, angle(axis.cl->best_dot(u, lo, hi)) - set_.cone_rad) : own;
}

bool Linearizer::exceeds(const kin::Axes& qa, const kin::Axes& qb, double sa, double sb, const Vec3& P0, const Vec3& P1,
                         const Axis& axis, Stats& stats) const {
  const Vec3 ab = P1 - P0;
  const double L2 = ab.squaredNorm();
  double dmax = 0.0;
  for (double t : {0.5, 0.25, 0.75}) {
    const kin::Posed p = kin_.forward(qa + t * (qb - qa));
    const Vec3 ctrl = p.tip_mm + set_.control_offset_mm * p.axis;
    const double dtip = point_segment_distance(ctrl, P0, ab, L2);
    stats.max_checked_tip_deviation_mm = std::max(stats.max_checked_tip_deviation_mm, dtip);
    dmax = std::max(dmax, dtip);
    if (dtip > set_.tolerance_mm || !axis_ok(axis, p.axis, along(ctrl, P0, ab, L2, sa + t * (sb - sa)), L2))
      return true;
  }
  // Between samples h apart the controlled point strays from their polyline by at most M h^2 / 8 (M: the move's bound
  // on its second derivative). Where that leaves room past what the gate allows (C swinging 18 deg in one planned
  // block: 0.0122 mm between samples that found less than 0.01), the piece is sampled as densely as the bound needs.
  kin::MotionBound mb;
  if (!kin_.motion_bound(qa, qb, mb)) return false;  // no bound (an iterative FK): the gate samples at fixed points
  const double M = mb.tip_accel_mm + std::abs(set_.control_offset_mm) * mb.axis_accel;
  if (dmax + M / 128.0 <= tip_certified_mm_) return false;  // h = 1/4
  const double room = tip_certified_mm_ - dmax;
  const double need = std::ceil(std::sqrt(M / (4.0 * room)));  // the bound within half the room
  if (!(need <= kMaxCertifySamples)) return true;              // a span half as long has a bound a quarter as large
  const int n = std::max(8, static_cast<int>(need));
  for (int k = 1; k < n; ++k) {
    const double t = static_cast<double>(k) / n;
    const kin::Posed p = kin_.forward(qa + t * (qb - qa));
    const double dtip = point_segment_distance(p.tip_mm + set_.control_offset_mm * p.axis, P0, ab, L2);
    stats.max_checked_tip_deviation_mm = std::max(stats.max_checked_tip_deviation_mm, dtip);
    if (dtip > set_.tolerance_mm) return true;
    dmax = std::max(dmax, dtip);
  }
  return dmax + M / (8.0 * n * n) > tip_certified_mm_;
}

void Linearizer::worst_deviation(const kin::Axes& qa, const kin::Axes& qb, double sa, double sb, const Vec3& P0,
                                 const Vec3& P1, const Axis& axis, double& tip_mm, double& axis_rad) const {
  tip_mm = axis_rad = 0.0;
  const Vec3 ab = P1 - P0;
  const double L2 = ab.squaredNorm();
  for (int i = 1; i < 16; ++i) {
    const double t = i / 16.0;
    const kin::Posed p = kin_.forward(qa + t * (qb - qa));
    const Vec3 ctrl = p.tip_mm + set_.control_offset_mm * p.axis;
    tip_mm = std::max(tip_mm, point_segment_distance(ctrl, P0, ab, L2));
    axis_rad = std::max(axis_rad, axis_deviation(axis, p.axis, along(ctrl, P0, ab, L2, sa + t * (sb - sa)), L2));
  }
}

void Linearizer::split(const cl::Move& m0, const kin::Axes& q0, const cl::Move& m1, const kin::Axes& q1,
                       const std::string& cl_file, std::vector<Piece>& out, Stats& stats, const ClAxes* cl_axes) {
  out.clear();
  auto check_limits = [&](const kin::Axes& q) {
    const std::string v = kin_.check_limits(q);
    if (!v.empty())
      throw InputError(SourceLoc{cl_file, m1.line, 0},
                       fmt::format("the post refuses a block outside the limits: {}", v));
  };
  const double off = set_.control_offset_mm;
  // The controlled points: tips, or ball centres when the plan keeps those on the CL path.
  const Vec3 P0 = m0.tip_in_part_mm + off * m0.axis_in_part.normalized();
  const Vec3 P1 = m1.tip_in_part_mm + off * m1.axis_in_part.normalized();
  const Axis axis{Slerp(m0.axis_in_part.normalized(), m1.axis_in_part.normalized()),
                  cl_axes && set_.cone_rad > 0
                      ? std::optional<Slerp>(Slerp(cl_axes->from.normalized(), cl_axes->to.normalized()))
                      : std::nullopt};
  // Explicit stack of spans [sa, sb] with their axis values; emits spans in order.
  stack_.clear();
  stack_.push_back({0.0, 1.0, q0, q1, 0});
  while (!stack_.empty()) {
    const Span pc = stack_.back();
    stack_.pop_back();
    if (set_.enabled && pc.depth < set_.max_depth && exceeds(pc.qa, pc.qb, pc.sa, pc.sb, P0, P1, axis, stats)) {
      const double sm = 0.5 * (pc.sa + pc.sb);
      const Vec3 axis_m = axis.own(sm);
      const kin::Posed target{P0 + sm * (P1 - P0) - off * axis_m, axis_m};
      // First keep the rotaries the machine would pass through anyway and only correct the linear axes:
      // near the singularity a fresh IK of the interpolated axis is ill-conditioned (its azimuth is
      // arbitrary) while the interpolated rotaries already give an axis within tolerance.
      kin::Axes qm = 0.5 * (pc.qa + pc.qb);
      {
        // The axis the interpolated rotaries give; the controlled point is put exactly on the path with that
        // axis, so only the axis error is left to judge.
        Vec3 a_int;
        const auto rp = kin_.rotary_pair();
        const Vec3 ctrl = P0 + sm * (P1 - P0);
        const double L2 = (P1 - P0).squaredNorm();
        const Along at_sm{sm, sm, 0.0};  // the controlled point is put on the path at sm
        if (kin_.tool_axis_at(qm[rp[0]], qm[rp[1]], target.tip_mm, a_int) && axis_ok(axis, a_int, at_sm, L2) &&
            kin_.solve_for_rotaries(kin::Posed{ctrl - off * a_int, a_int}, qm) &&
            axis_ok(axis, kin_.forward(qm).axis, at_sm, L2)) {
          check_limits(qm);
          ++stats.inserted_points;
          stack_.push_back({sm, pc.sb, qm, pc.qb, pc.depth + 1});
          stack_.push_back({pc.sa, sm, pc.qa, qm, pc.depth + 1});
          continue;
        }
      }
      // Otherwise continue the solution branch from the span's start (no flips), as the conventional
      // strategy does between CL points.
      const Vec3 axis_a = axis.own(pc.sa);
      const kin::Posed from{P0 + pc.sa * (P1 - P0) - off * axis_a, axis_a};
      ++stats.ik_calls;
      bool jumped = false;
      std::string why;
      const bool tracked = kin::track_checked(kin_, pc.qa, from, target, qm, jumped, &why);
      if (tracked && jumped)
        throw BranchChangeError(
            SourceLoc{cl_file, m1.line, 0},
            fmt::format("the machine cannot follow the CL segment from line {} to line {} ({}) "
                        "continuously: inside it a limit{} forces the rotaries to flip (the "
                        "tool would leave the path); {}",
                        m0.line, m1.line, rotary_change(kin_, q0, q1), why.empty() ? "" : " (" + why + ")", remedy()));
      if (!tracked) {
        stats.warnings.push_back(
            fmt::format("{}: no IK solution while linearising", SourceLoc{cl_file, m1.line, 0}.str()));
      } else {
        check_limits(qm);
        ++stats.inserted_points;
        stack_.push_back({sm, pc.sb, qm, pc.qb, pc.depth + 1});
        stack_.push_back({pc.sa, sm, pc.qa, qm, pc.depth + 1});
        continue;
      }
    } else if (set_.enabled && pc.depth >= set_.max_depth && exceeds(pc.qa, pc.qb, pc.sa, pc.sb, P0, P1, axis, stats)) {
      // A span this short that still misses the tolerance is a singular region (the rotaries turn fast but the
      // tool stays close) or a branch change hidden between two subdivision points (a limit met inside the span,
      // the tool swept across the part). The first is written with a warning and judged by the gate; the second
      // would be refused by the gate anyway, so it is refused here with its cause.
      double tip_mm = 0.0, axis_rad = 0.0;
      worst_deviation(pc.qa, pc.qb, pc.sa, pc.sb, P0, P1, axis, tip_mm, axis_rad);
      if (tip_mm > set_.tolerance_mm + tol::kVerifySlackMm ||
          axis_rad > set_.axis_tolerance_rad + tol::kVerifySlackDeg * M_PI / 180.0) {
        const Vec3 axis_a = axis.own(pc.sa), axis_b = axis.own(pc.sb);
        const kin::Posed from{P0 + pc.sa * (P1 - P0) - off * axis_a, axis_a};
        const kin::Posed to{P0 + pc.sb * (P1 - P0) - off * axis_b, axis_b};
        kin::Axes qt;
        bool jumped = false;
        std::string why;
        const bool tracked = kin::track_checked(kin_, pc.qa, from, to, qt, jumped, &why);
        const auto rp = kin_.rotary_pair();
        const bool branch_change =
            !tracked || jumped ||
            std::abs(qt[rp[0]] - pc.qb[rp[0]]) + std::abs(qt[rp[1]] - pc.qb[rp[1]]) > kBranchChangeRad;
        if (branch_change)
          throw BranchChangeError(
              SourceLoc{cl_file, m1.line, 0},
              fmt::format("the machine cannot follow the CL segment from line {} to line {} ({}): {:.1f}% along it the "
                          "rotaries must change IK branch{} (one block would leave the path by {:.4f} mm and {:.3f} "
                          "deg); {}",
                          m0.line, m1.line, rotary_change(kin_, q0, q1), 100.0 * pc.sb,
                          why.empty() ? "" : " (" + why + ")", tip_mm, axis_rad * 180.0 / M_PI, remedy()));
        throw InputError(
            SourceLoc{cl_file, m1.line, 0},
            fmt::format("the machine cannot follow the CL segment from line {} to line {} ({}): {:.1f}% along it the "
                        "rotaries turn too fast to stay within the tolerance (one block would leave the path by {:.4f} "
                        "mm and {:.3f} deg); {}",
                        m0.line, m1.line, rotary_change(kin_, q0, q1), 100.0 * pc.sb, tip_mm, axis_rad * 180.0 / M_PI,
                        remedy()));
      }
      stats.warnings.push_back(fmt::format("{}: tolerance not reached after {} subdivisions (singular region?)",
                                           SourceLoc{cl_file, m1.line, 0}.str(), set_.max_depth));
    }
    out.push_back({pc.qb, (pc.sb - pc.sa) * (P1 - P0).norm()});
  }
}

}  // namespace cscam::post
