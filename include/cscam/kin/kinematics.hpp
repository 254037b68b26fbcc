#pragma once
/// @file
/// The interface every machine's kinematics offers to the planner, the post and verification.
#include <Eigen/Geometry>
#include <array>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "cscam/kin/types.hpp"

namespace cscam::kin {

/// What the post and the gate need to know about a machine's kinematics beyond the maths, so that no code
/// asks which model it is (as LinuxCNC keeps each machine's kinematics behind one interface).
struct Traits {
  /// The linear axis the tool retracts along (machine Z), or -1 when no axis is one (a PKM's legs): the
  /// post then retracts the tip along the tool axis to the safe plane.
  int retract_axis = -1;
  /// Rotary words under tool-tip control: the machine's own rotary angles (a serial machine: they alone set
  /// the tool vector), or the angles of a virtual wrist (C, A) of an untilted platform (the XMINI).
  enum class TcpRotaryWords { MachineAngles, VirtualWrist } tcp_rotary_words = TcpRotaryWords::MachineAngles;
  /// Axes the control drives (all five for every model so far).
  std::array<bool, 5> actuated{true, true, true, true, true};
  /// A parallel machine (PKM): every Cartesian move moves every actuated leg, so the legs' reversals count.
  bool parallel = false;
  /// FK is an iterative solve warm-started from the calling thread's previous call (the XMINI's Newton): its last
  /// digits depend on call order, so callers that promise the same numbers at any thread count evaluate it in order.
  bool forward_depends_on_call_order = false;
  /// The linear axes are prismatic joints of unit direction in a chain: with the rotaries held, a change of the
  /// linear axes by d translates every link relative to every other, by at most sum |d_i| mm. A check can then bound
  /// a rotary-free move's motion without FK (a serial machine; not a PKM, whose legs turn its platform).
  bool linear_axes_translate = false;
};

/// Bounds on how the tool moves along the straight joint-space move qa -> qb, q(t) = qa + t (qb - qa), t in
/// [0, 1] (derivatives with respect to t). They let a check sample a move sparsely and still bound it between
/// its samples: the tip path leaves the polyline through samples h apart (in t) by at most
/// tip_accel_mm h^2 / 8, and the tool axis turns by at most axis_rate_rad h / 2 away from the nearest sample.
struct MotionBound {
  double tip_accel_mm = 0.0;   ///< sup |d^2 tip / dt^2| (mm)
  double axis_rate_rad = 0.0;  ///< sup of the tool axis's angular speed (rad per unit t)
  double axis_accel = 0.0;     ///< sup |d^2 axis / dt^2| of the unit axis vector (per unit t^2)
};

/// Immutable kinematic model of a 5-axis machine. Implementations are thread-safe for const use.
class Kinematics {
 public:
  virtual ~Kinematics() = default;
  /// The five axes in their canonical order (the order of Axes).
  [[nodiscard]] virtual const std::vector<AxisInfo>& axes() const = 0;
  /// Indices of the two rotary axes in the order the C-space uses (primary, secondary).
  [[nodiscard]] virtual std::array<int, 2> rotary_pair() const = 0;
  /// Forward kinematics: axis values to the tool pose in the part frame.
  [[nodiscard]] virtual Posed forward(const Axes& q) const = 0;
  /// Every IK branch with every rotary winding inside the limits (limit-violating solutions are
  /// returned too, flagged). `hint` resolves singular rotaries (keeps the previous angle).
  virtual void inverse_all(const Posed& pose, const Axes* hint, std::vector<Solution>& out) const = 0;
  /// The basic IK branches (one winding each, principal angles in (-pi, pi]). Cheaper than inverse_all.
  virtual void inverse_branches(const Posed& pose, const Axes* hint, std::vector<Solution>& out) const = 0;
  /// Given both rotary values, the remaining (linear/leg) axes that put the tip at `tip_mm`.
  /// Returns false if no such values exist. `q` holds the rotaries on entry and all axes on exit.
  virtual bool solve_for_rotaries(const Posed& pose, Axes& q) const = 0;
  /// The tool axis (part frame) that the two rotary values give with the tip at `tip_mm`. For a serial
  /// machine it does not depend on the tip; on a PKM the platform attitude (parasitic motion) makes it
  /// depend on the position. Returns false if no axis values put the tip there.
  virtual bool tool_axis_at(double primary, double secondary, const Eigen::Vector3d& tip_mm,
                            Eigen::Vector3d& axis) const = 0;
  /// For models whose tool axis is a rotation of the primary applied to a vector of the secondary alone, independent
  /// of the tip (a serial machine: axis = R_primary(primary) * v_secondary(secondary)): the two factors, so that a
  /// caller can tabulate axes over a grid of rotary values. False (the default) for other models.
  virtual bool axis_factors(double /*primary*/, double /*secondary*/, Eigen::Matrix3d* /*R_primary*/,
                            Eigen::Vector3d* /*v_secondary*/) const {
    return false;
  }
  /// The rigid motion of the tool-side end link (spindle housing) for axis values q: it maps a point given
  /// in the machine frame at home to its position in the part frame. False if the model cannot say.
  virtual bool head_in_part(const Axes& /*q*/, Eigen::Isometry3d& /*T*/) const { return false; }
  /// The rigid motion of the link that joint `axis` drives (the body it carries, up to the next joint of its
  /// chain) for axis values q: it maps a point given in the machine frame at home to the part frame.
  /// `axis` = -1 is the machine base. False if the model cannot say (then machine bodies cannot be placed).
  virtual bool link_in_part(int /*axis*/, const Axes& /*q*/, Eigen::Isometry3d& /*T*/) const { return false; }
  /// The link l (as in links_in_part) whose pose is head_in_part's, or -1 when the model has none: a caller that
  /// places links anyway gets the head's pose with them.
  [[nodiscard]] virtual int head_link() const { return -1; }
  /// link_in_part for the links l < n whose bit l is set in `used` (link 0: the base, 1 + i: axis i), into T[l]:
  /// models override it to share the joint motions between the links.
  virtual bool links_in_part(const Axes& q, int n, unsigned used, Eigen::Isometry3d* T) const {
    for (int l = 0; l < n; ++l)
      if (((used >> l) & 1u) && !link_in_part(l - 1, q, T[l])) return false;
    return true;
  }
  /// Bounds on the tool's motion along the straight move qa -> qb (see MotionBound). False if the model has no
  /// such bound (an iterative FK, a PKM): callers then sample at a fixed density.
  virtual bool motion_bound(const Axes& /*qa*/, const Axes& /*qb*/, MotionBound& /*out*/) const { return false; }
  /// Limits that the axis values alone do not show, e.g. a PKM's passive joint angles; empty if none broken.
  [[nodiscard]] virtual std::string passive_violation(const Axes& /*q*/) const { return {}; }
  /// The model's traits; the default: a linear axis named "z" to retract along, machine angles under TCP.
  [[nodiscard]] virtual Traits traits() const {
    Traits t;
    const auto& a = axes();
    for (std::size_t i = 0; i < a.size(); ++i)
      if (!a[i].rotary() && a[i].name == "z") t.retract_axis = static_cast<int>(i);
    return t;
  }
  /// First limit that q violates, or empty.
  [[nodiscard]] std::string check_limits(const Axes& q) const;
  /// Choose for every rotary of `s` the winding nearest to `prev` (same angle modulo 2 pi), if within limits.
  void nearest_winding(Axes& s, const Axes& prev) const;
  /// Adds to `out` every winding of `base` that lies inside the rotary limits.
  void expand_windings(const Solution& base, std::vector<Solution>& out) const;
};

}  // namespace cscam::kin
