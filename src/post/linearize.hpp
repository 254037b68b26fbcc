#pragma once
// The linearizer: splits one CL segment, travelled by a straight joint-space move, into pieces whose real tool
// path stays within the tolerance of the straight CL segment (tip, or ball centre) and of the interpolated CL
// axis. Pure maths on the kinematics: no G-code, no I/O.
#include <Eigen/Core>
#include <array>
#include <optional>
#include <string>
#include <vector>

#include "cscam/cl/program.hpp"
#include "cscam/core/error.hpp"
#include "cscam/kin/kinematics.hpp"

namespace cscam::post {

/// Spherical interpolation of the CL tool axis between two points (angle computed once per segment).
class Slerp {
 public:
  Slerp(const Eigen::Vector3d& a, const Eigen::Vector3d& b);
  Eigen::Vector3d operator()(double s) const;
  /// The angle (rad) the interpolation turns through from a to b.
  [[nodiscard]] double angle() const { return th_; }
  /// The largest u . (*this)(t) over t in [lo, hi] (0 <= lo <= hi <= 1): the point of that stretch of the arc
  /// nearest the unit vector u.
  [[nodiscard]] double best_dot(const Eigen::Vector3d& u, double lo, double hi) const;

 private:
  /// std::sin(x), remembered for the last few x: the linearizer's samples at a quarter, half and three quarters
  /// of a segment need sin(th / 4), sin(th / 2) and sin(3 th / 4) twice each.
  double sine(double x) const;
  static constexpr int kMemo = 4;
  Eigen::Vector3d a_, b_;
  double th_, sn_ = 0.0;
  mutable std::array<double, kMemo> memo_x_{}, memo_sin_{};
  mutable int memo_size_ = 0, memo_next_ = 0;
};

/// The rotaries' change from qa to qb, named as in the machine file: "c 341.000 -> -337.000 deg, a 15.000 -> 15.000
/// deg" (for the messages of refused segments and of turns).
std::string rotary_change(const kin::Kinematics& k, const kin::Axes& qa, const kin::Axes& qb);

/// The linearizer's refusal of a segment whose two ends lie on different IK branches (inside it the rotaries would
/// have to flip): the sequencer then turns the rotaries at an end instead (retract, turn, plunge).
class BranchChangeError : public InputError {
 public:
  using InputError::InputError;
};

class Linearizer {
 public:
  struct Settings {
    double tolerance_mm = 0.01;
    double axis_tolerance_rad = 0.005;
    double control_offset_mm = 0.0;  ///< the controlled point is tip + offset * axis (a ball centre)
    int max_depth = 14;
    bool enabled = true;
    bool planned = false;  ///< the axis values come from the planner (for the advice an error gives)
    /// The plan's cone (rad): where the CL's own axes are given, a piece whose axis stays within the cone of the
    /// CL axis is also within the tolerance (the gate accepts cone + axis tolerance of a planned program).
    double cone_rad = 0.0;
  };

  /// The CL's own tool axes at the two ends of a planned segment (the plan's axes may tilt within the cone).
  struct ClAxes {
    Eigen::Vector3d from, to;
  };
  /// One piece of the segment: the axis values at its end and the length of the CL path it covers.
  struct Piece {
    kin::Axes q_end;
    double path_mm = 0.0;
  };
  /// What the linearizer did (added to the post's summary).
  struct Stats {
    std::size_t inserted_points = 0;
    std::size_t ik_calls = 0;
    double max_checked_tip_deviation_mm = 0.0;
    std::vector<std::string> warnings;
  };

  Linearizer(const kin::Kinematics& k, const Settings& s);

  /// Pieces, in order, of the move q0 (at m0) -> q1 (at m1) on one branch. Every inserted point passes
  /// kin.check_limits, else InputError naming the CL line (file `cl_file`). Throws InputError when a limit
  /// forces the rotaries to flip inside the segment.
  void split(const cl::Move& m0, const kin::Axes& q0, const cl::Move& m1, const kin::Axes& q1,
             const std::string& cl_file, std::vector<Piece>& out, Stats& stats, const ClAxes* cl_axes = nullptr);

 private:
  /// The axis a piece is judged by: the slerp of the segment's own axes and, for a planned segment whose CL axes
  /// are given, the slerp of those, widened by the cone.
  struct Axis {
    Slerp own;
    std::optional<Slerp> cl;
  };
  /// Where a sample of the machine's move lies along the CL segment: its parameter in time (s), the projection of
  /// its controlled point on the segment's line (t_line) and its squared distance from that line (h2). The gate
  /// places a sample by its tip, so that is where its axis is judged: over the stretch of the segment whose CL points
  /// lie within the tip tolerance of it (stretch()).
  struct Along {
    double s, t_line, h2;
  };
  [[nodiscard]] static Along along(const Eigen::Vector3d& ctrl, const Eigen::Vector3d& P0, const Eigen::Vector3d& ab,
                                   double L2, double s);
  /// The stretch [lo, hi] of the segment (of squared length L2) within the tip tolerance of the sample w.
  [[nodiscard]] std::array<double, 2> stretch(const Along& w, double L2) const;
  /// Whether the tool axis u of a sample is within the tolerance: of the segment's own axes at some point of its
  /// stretch, or (planned, with the CL's axes given) within the cone of the CL's there.
  [[nodiscard]] bool axis_ok(const Axis& axis, const Eigen::Vector3d& u, const Along& w, double L2) const;
  /// By how much (rad) u misses the axis over the sample's stretch, beyond what is allowed besides
  /// axis_tolerance_rad (the cone).
  [[nodiscard]] double axis_deviation(const Axis& axis, const Eigen::Vector3d& u, const Along& w, double L2) const;
  /// Whether the straight joint move qa -> qb leaves the tolerance of the CL segment P0P1 between the
  /// parameters sa and sb (sampled at a quarter, half and three quarters; where the kinematics bounds the motion and
  /// the bound between those leaves too little room, as densely as it needs).
  bool exceeds(const kin::Axes& qa, const kin::Axes& qb, double sa, double sb, const Eigen::Vector3d& P0,
               const Eigen::Vector3d& P1, const Axis& axis, Stats& stats) const;
  /// The largest tip (mm) and axis (rad, axis_deviation) deviation of the joint interpolation qa -> qb from the
  /// CL segment.
  void worst_deviation(const kin::Axes& qa, const kin::Axes& qb, double sa, double sb, const Eigen::Vector3d& P0,
                       const Eigen::Vector3d& P1, const Axis& axis, double& tip_mm, double& axis_rad) const;

  struct Span {
    double sa, sb;
    kin::Axes qa, qb;
    int depth;
  };
  /// What an error that refuses a segment advises.
  [[nodiscard]] std::string remedy() const;
  const kin::Kinematics& kin_;
  Settings set_;
  double cos_tol_axis_ = 1.0;
  double cos_cone_tol_ = 1.0;      ///< cos(cone)
  double cos_fast_axis_ = 1.0;     ///< cos(0.9 axis tolerance): the check without trigonometry (axis_ok)
  double cos_fast_cone_ = 1.0;     ///< cos(cone - 0.1 axis tolerance)
  double tip_certified_mm_ = 0.0;  ///< what a piece's whole path must stay within: its samples plus their bound
  std::vector<Span> stack_;
};

}  // namespace cscam::post
