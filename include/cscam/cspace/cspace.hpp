#pragma once
/// @file
/// The configuration space of a machine's two rotary axes at one CL point (seed 002): a grid of
/// (primary, secondary) rotary values. A cell is feasible when (1) its tool axis lies in the allowed cone
/// around the CL axis, (2) the linear axes it needs are inside their strokes, (3) tool and holder do not
/// collide with the part or fixture. Cells are evaluated lazily and cached: collision queries dominate.
#include <array>
#include <cstdint>
#include <functional>
#include <limits>
#include <memory>
#include <string>
#include <unordered_map>
#include <vector>

#include "cscam/cspace/status.hpp"
#include "cscam/geom/scene.hpp"
#include "cscam/kin/kinematics.hpp"

namespace cscam::cspace {

/// Per-operation settings of the C-space.
struct Options {
  double cone_rad = 0.0;      ///< allowed angle between the cell's tool axis and the CL axis; 0: exact IK
  double min_tilt_rad = 0.0;  ///< keep at least this angle from the CL axis (ball mills off dead centre)
  double resolution_rad = 1.0 * 3.14159265358979323846 / 180.0;
  /// Ball-end tools keep the ball centre fixed when the orientation changes (the tip moves); others keep
  /// the tip. Set from the CL tool.
  double ball_radius_mm = 0.0;
  bool check_collision = true;
  geom::CheckOptions collision;
  /// Range of a cyclic rotary in the grid (explicit windings), rad: [-cyclic_span, +cyclic_span] (twice that at cone
  /// 0).
  double cyclic_span_rad = 2.0 * 3.14159265358979323846;
  /// Where finite: the grid range of the primary [0] and secondary [1] rotary, rad, in place of +-cyclic_span_rad for a
  /// cyclic (or very wide) axis, within its limits. plan::fit_cyclic_windows sets it to the windings a program needs,
  /// so that a path that keeps turning one way (a spiral) is not unwound every turn or two.
  std::array<std::array<double, 2>, 2> cyclic_window_rad{
      {{std::numeric_limits<double>::quiet_NaN(), std::numeric_limits<double>::quiet_NaN()},
       {std::numeric_limits<double>::quiet_NaN(), std::numeric_limits<double>::quiet_NaN()}}};
};

/// One cell: rotary values (unwrapped, rad) and its lazily computed status.
struct Cell {
  double r1 = 0.0, r2 = 0.0;  ///< primary, secondary rotary values
  int i1 = 0, i2 = 0;         ///< grid indices (for exact IK cells at cone 0: branch/winding ids)
  float orient_err = 0.0f;    ///< angle to the CL axis, rad
  Status status = Status::Unknown;
  bool singular = false;  ///< exact IK cell whose primary rotary is free (tool axis along it)
  float clearance_mm = std::numeric_limits<float>::quiet_NaN();
  std::string detail;                  ///< for a failed cell: the broken limit or the part that collided
  kin::Axes axes = kin::Axes::Zero();  ///< every axis (valid once evaluated and not Orientation)
};

/// Query counters (for benchmarks and the compare report).
struct Counters {
  std::uint64_t cells_enumerated = 0;
  std::uint64_t ik = 0;         ///< linear-axis solves for a cell
  std::uint64_t stroke = 0;     ///< limit checks
  std::uint64_t collision = 0;  ///< collision queries
  std::uint64_t cache_hits = 0;
  std::uint64_t certified = 0;      ///< collision queries skipped by a clearance certificate
  std::uint64_t translated = 0;     ///< of those, poses certified from the linear axes' changes alone (no FK)
  std::uint64_t witnessed = 0;      ///< collision queries replaced by the previous contact's one-triangle test
  std::uint64_t swept = 0;          ///< swept (between-point) moves checked
  std::uint64_t swept_queries = 0;  ///< collision queries those swept checks made (not in `collision`)
  Counters& operator+=(const Counters& o);
};

/// Reuse between neighbouring points: a pose proven free with an extra margin m (shapes inflated by m,
/// cutter body extended m toward the tip) stays free under any translation shorter than m with the same
/// axis, so the next points of a fixed orientation need no query until the tool has moved m. It is keyed on the
/// rotary values too: with them fixed, machine bodies keep their pose (table side) or move with the tool (head).
struct Certificate {
  bool valid = false;
  Eigen::Vector3d tip_mm = Eigen::Vector3d::Zero();
  Eigen::Vector3d axis = Eigen::Vector3d::UnitZ();
  double r1 = 0.0, r2 = 0.0;  ///< rotary values of the certified pose, rad
  double margin_mm = 0.0;
  /// The margin the next probe asks for (at most the relief above the cutting end): smaller margins certify fewer
  /// neighbours but succeed in tighter places (CertificateStore adapts it per cell).
  double probe_mm = 1.0;
};

/// The counterpart for collisions: a pose whose tool, eroded by a margin m, still hits an obstacle makes every pose
/// within m of it hit too (the eroded body plus m lies inside the tool there). With the same rotaries (same axis and
/// machine-body poses), a cell that collided stays colliding over the next points until the tool has moved m.
struct HitCertificate {
  bool valid = false;
  Eigen::Vector3d tip_mm = Eigen::Vector3d::Zero();
  Eigen::Vector3d axis = Eigen::Vector3d::UnitZ();
  double r1 = 0.0, r2 = 0.0;  ///< rotary values of the certified pose, rad
  double margin_mm = 0.0;
  double probe_mm = 1.0;         ///< the erosion the next probe asks for (halved after a probe that found no hit)
  bool collided_before = false;  ///< the cell's last evaluation collided: probe eroded at the next one
  std::string detail;            ///< what the eroded tool hit
  geom::Witness witness;         ///< the contact of the cell's last collision (tested first at the next point)
};

/// How a motion between two poses is checked. Cutting: the cutting end (ball or corner radius plus relief) is in
/// contact with the material by design and is excluded, as at the CL points. Rapid: the whole tool body from the
/// tip counts (a rapid must not touch anything).
enum class SweepMode : std::uint8_t { Cutting, Rapid };

/// Largest inflation a Rapid-mode swept check uses before it bisects an interval, mm: larger margins certify
/// longer intervals in open space with fewer queries; near obstacles they fail anyway.
inline constexpr double kRapidSweepMarginCapMm = 5.0;

/// Smallest erosion a hit probe uses, mm (below it a probe rarely certifies more than the point itself).
inline constexpr double kMinHitProbeMm = 1.0 / 16.0;

/// Outcome of a swept check of one straight joint-space move.
enum class SweepStatus : std::uint8_t {
  Free,         ///< certified free over the whole move
  Collides,     ///< a pose on the move collides (at `t`)
  Uncertified,  ///< no collision found, but the clearance is too small to certify within the query budget
};
const char* to_string(SweepStatus s);

struct SweptResult {
  SweepStatus status = SweepStatus::Free;
  double t = 0.0;      ///< move parameter (0: start, 1: end) of the collision or of the uncertified spot
  std::string detail;  ///< what collides
  std::uint64_t queries = 0;
};

/// How far any point of a tool body moves, over a sub-interval [lo, hi] of a straight joint-space move, away from
/// where it is at the middle of the sub-interval, mm. The body lies within `lever_mm` of the tip (its top along the
/// axis plus its radius). `at_lo` and `at_hi` are the tool poses at the ends of the sub-interval, `half_width`
/// = (hi - lo) / 2 in the move's parameter, and `bound` the kinematics' MotionBound of the whole move.
///
/// Second order: with K >= |tip''|, |tip'(mid)| <= |tip(hi) - tip(lo)| / (2 h) + h K / 2 (h the half width), so the
/// tip stays within |tip(hi) - tip(lo)| / 2 + h^2 K of its middle position; the axis likewise turns by at most
/// |a(hi) - a(lo)| / 2 + h^2 K_axis. Where the linear axes cancel the tip motion a rotary causes (a table machine),
/// and near the singular axis where the primary rotary barely tilts the tool, this is far below a first-order
/// bound from the axes' gains.
[[nodiscard]] double interval_reach_bound(const kin::Posed& at_lo, const kin::Posed& at_hi, double half_width,
                                          const kin::MotionBound& bound, double lever_mm);

/// The C-space model: immutable, shared by threads. Per-thread scratch lives in Workspace.
class Space {
 public:
  /// `scene` and `tool` may be null (no collision checking). `head` holds machine meshes that move with the
  /// spindle (machine file geometry.head_mesh), checked against `scene`. All must outlive the Space.
  /// Machine obstacles with a link (geom::Scene::add) in `scene` or `head` are placed per cell with
  /// Kinematics::link_in_part: link 0 is the machine base, link 1 + i the link that axis i drives.
  /// @throws InputError when there are linked obstacles and the kinematics cannot place links.
  Space(std::shared_ptr<const kin::Kinematics> kinematics, const geom::Scene* scene, const geom::ToolShape* tool,
        Options options, const geom::Scene* head = nullptr);

  [[nodiscard]] const Options& options() const { return opt_; }
  [[nodiscard]] const kin::Kinematics& kinematics() const { return *kin_; }
  /// Grid index ranges of the two rotaries (inclusive).
  [[nodiscard]] int i1_min() const { return i1_min_; }
  [[nodiscard]] int i1_max() const { return i1_max_; }
  [[nodiscard]] int i2_min() const { return i2_min_; }
  [[nodiscard]] int i2_max() const { return i2_max_; }
  [[nodiscard]] double r1_of(int i1) const { return i1 * opt_.resolution_rad; }
  [[nodiscard]] double r2_of(int i2) const { return i2 * opt_.resolution_rad; }

  /// The cells of a CL pose that pass the orientation test (cheap: no stroke/collision yet), at most
  /// `cap` of them, closest to the CL axis first. At cone 0 these are the exact IK solutions.
  void enumerate(const kin::Posed& cl_pose, std::vector<Cell>& out, std::size_t cap, Counters& c) const;
  /// How many cells enumerate() would list for this pose with this cap (at most), without listing them where the grid
  /// rows have a closed form (a count along each row; cells inside the minimum tilt are counted too); otherwise the
  /// listing's size. For sizing planning windows.
  [[nodiscard]] std::size_t count_in_cone(const kin::Posed& cl_pose, std::size_t cap) const;
  /// Orientation test of one grid cell (cone and minimum tilt); fills orient_err.
  [[nodiscard]] bool in_cone(const kin::Posed& cl_pose, double r1, double r2, float* orient_err = nullptr) const;
  /// in_cone's answer without an arc cosine away from the bounds (for long scans): `dot` gets the cosine of the
  /// angle to the CL axis (clamped to [-1, 1]).
  [[nodiscard]] bool in_cone_cos(const kin::Posed& cl_pose, double r1, double r2, double& dot) const;
  /// The tool pose a cell gives at a CL pose (tip moves for a ball mill so the centre stays put).
  [[nodiscard]] kin::Posed tool_pose(const kin::Posed& cl_pose, double r1, double r2) const;
  /// Stroke and collision of a cell (the orientation test must have passed). Fills status, axes, detail.
  /// With `hit`, the same for collisions: a cell that collided at its previous evaluation is probed with the tool
  /// eroded (one query that, when it hits, certifies the next points), and a pose the certificate covers collides
  /// without a query.
  void evaluate(const kin::Posed& cl_pose, Cell& cell, geom::QueryWorkspace& ws, Counters& c,
                Certificate* certificate = nullptr, HitCertificate* hit = nullptr) const;
  /// Collision of an arbitrary tool pose (for reorientation moves). Empty string if free. Without axis values
  /// it cannot place machine bodies (linked obstacles) or the head: use collision_at_axes() when q is known.
  [[nodiscard]] std::string collision_at(const kin::Posed& tool_pose, geom::QueryWorkspace& ws, Counters& c) const;
  /// Whether a feasible cell stays free with `margin_mm` more clearance (a cheap measure of room for
  /// tie-breaking: collision queries only, no distance query).
  [[nodiscard]] bool free_with_margin(const kin::Posed& cl_pose, const Cell& cell, double margin_mm,
                                      geom::QueryWorkspace& ws, Counters& c) const;
  /// Collision of the tool and the machine head meshes for axis values q. Empty string if free.
  /// With SweepMode::Rapid the whole tool counts, its cutting end too (as a rapid move must touch nothing).
  [[nodiscard]] std::string collision_at_axes(const kin::Axes& q, geom::QueryWorkspace& ws, Counters& c,
                                              SweepMode mode = SweepMode::Cutting) const;
  /// Swept check of the straight joint-space move qa -> qb (what a control does between two blocks), with a
  /// clearance certificate: the interval around a pose is free when the tool there, inflated by the largest
  /// distance any tool point can travel over the interval, is free. That distance is the smaller of a first-order bound
  /// (the axis travel, the tip's lever arms about the rotaries, the tool length) and, where the kinematics gives a
  /// MotionBound, interval_reach_bound. Intervals that cannot be certified are bisected.
  /// Machine head meshes are checked at the certified poses only (sampled, not certified). A move not certified
  /// within `max_queries` collision queries (0: the default budget, 2000) is Uncertified.
  [[nodiscard]] SweptResult swept(const kin::Axes& qa, const kin::Axes& qb, SweepMode mode, geom::QueryWorkspace& ws,
                                  Counters& c, std::uint64_t max_queries = 0) const;
  /// Whether the tool at `pose` (the FK of axes `q`, which place any machine bodies), inflated by `margin_mm` in
  /// every direction (superset of the Minkowski sum), is free. Empty string if free.
  /// `cutter_margin_mm` >= 0: the cutter body's own (smaller) margin, the others keep `margin_mm`.
  [[nodiscard]] std::string collision_inflated(const kin::Axes& q, const kin::Posed& pose, double margin_mm,
                                               SweepMode mode, geom::QueryWorkspace& ws, Counters& c,
                                               double cutter_margin_mm = -1.0) const;
  /// Largest motion margin a Cutting-mode inflated check accepts (the relief above the cutting end), mm.
  [[nodiscard]] double cutting_margin_cap_mm() const;
  [[nodiscard]] bool checks_collision() const { return opt_.check_collision && scene_ && tool_; }
  /// The tool axis (part frame) of rotary values.
  [[nodiscard]] Eigen::Vector3d axis_of(double r1, double r2) const;

 private:
  friend class PathCheck;
  std::shared_ptr<const kin::Kinematics> kin_;
  const geom::Scene* scene_;
  const geom::ToolShape* tool_;
  Options opt_;
  const geom::Scene* head_ = nullptr;
  static constexpr int kMaxLinks = 6;  // the base and one link per axis
  using LinkPoses = std::array<Eigen::Isometry3d, kMaxLinks>;
  int links_ = 0;              // machine links used by the obstacles (0: none)
  bool certify_links_ = true;  // certificates stay sound with the linked obstacles
  bool certify_head_ = true;   // head bodies all move rigidly with the spindle (none has a link)
  unsigned used_links_ = 0;    // bit l: an obstacle uses link l
  int head_link_ = -1;         // the link that carries the head meshes (Kinematics::head_link), if placed with links
  static bool place_links(const kin::Kinematics& k, const kin::Axes& q, int n, LinkPoses& T, unsigned used);
  /// opt_.collision, or a copy in `scratch` with the link poses for q when obstacles have links. With `head`, the head
  /// meshes' pose is placed with the links when they are placed at all (one pass over the joints), and `*head` is then
  /// set to it; otherwise `*head` is left null (call Kinematics::head_in_part).
  const geom::CheckOptions& with_links(const kin::Axes& q, LinkPoses& links, geom::CheckOptions& scratch,
                                       const Eigen::Isometry3d** head = nullptr) const;
  /// The head meshes' pose for q: from the links `with_links` placed, or from the kinematics. False if unavailable.
  /// collision_inflated() with the machine bodies already placed (with_links() for the pose's axes).
  [[nodiscard]] std::string collision_inflated_placed(const geom::CheckOptions& placed, const kin::Posed& pose,
                                                      double margin_mm, SweepMode mode, geom::QueryWorkspace& ws,
                                                      Counters& c, double cutter_margin_mm = -1.0) const;
  /// "<tool part> hits <obstacle>" for a tool collision.
  [[nodiscard]] std::string collision_detail(const geom::CollisionResult& r) const;
  bool head_pose(const kin::Axes& q, const Eigen::Isometry3d* placed, Eigen::Isometry3d& T) const;
  /// The tool axis for rotary values, through the grid tables for grid values (the same numbers everywhere).
  bool axis_at(double r1, double r2, const Eigen::Vector3d& tip_mm, Eigen::Vector3d& axis) const;
  /// The tool axis of tool_pose(cl, r1, r2): axis_at the tip where that pose puts it.
  bool pose_axis(const kin::Posed& cl, double r1, double r2, Eigen::Vector3d& axis) const;
  bool tip_free_axis_ = false;  ///< the kinematics' axis does not depend on the tip (Kinematics::axis_factors)
  [[nodiscard]] Eigen::Vector3d grid_axis(int i1, int i2) const {
    return R1_grid_[static_cast<std::size_t>(i1 - i1_min_)] * v2_grid_[static_cast<std::size_t>(i2 - i2_min_)];
  }
  std::vector<Eigen::Matrix3d> R1_grid_;  ///< Kinematics::axis_factors per grid row (empty: no such factors)
  std::vector<Eigen::Vector3d> v2_grid_;  ///< ... per grid column
  /// v2 = p + q cos(r2) + r sin(r2) over the whole grid (a rotation of a fixed vector about a fixed axis, as on every
  /// serial machine): each grid row's cone cells are then one interval of r2 per winding, found in closed form.
  bool rows_in_closed_form_ = false;
  Eigen::Vector3d v2_p_ = Eigen::Vector3d::Zero(), v2_q_ = Eigen::Vector3d::Zero(), v2_r_ = Eigen::Vector3d::Zero();
  /// The in-cone grid cells of a CL axis, row by row (rows_in_closed_form_): (cosine to the axis, i1, i2).
  /// `take(cosine, i1, i2)` per cell (a template: it runs for every cell of every cone; defined in cspace.cpp).
  template <typename Take>
  void scan_rows(const Eigen::Vector3d& cl_axis, double cos_min, Take&& take) const;
  geom::ToolShape tip_tool_;      ///< the lowest part of the cutter as a flat cylinder (Rapid-mode sweeps)
  double reach_mm_ = 0.0;         ///< tool length plus largest checked radius: lever arm of a tool-axis rotation
  double cutter_reach_mm_ = 0.0;  ///< the same for the cutter body alone (its top plus its checked radius)
  int rot1_ = 0, rot2_ = 0;
  int i1_min_ = 0, i1_max_ = 0, i2_min_ = 0, i2_max_ = 0;
};

/// The collision check of poses met in order along a path (the safety gate's samples), for one thread: a pose found
/// free with the tool and head inflated by a margin certifies every later pose whose bodies stay within that margin
/// of where they were, relative to the part and to every machine link that carries an obstacle. Those poses need no
/// query. Its answer for every pose is the answer of Space::collision_at_axes() or a proof that it is free.
class PathCheck {
 public:
  explicit PathCheck(std::shared_ptr<const Space> space);
  /// Empty if the tool and head at axes q are free, else what collides (as Space::collision_at_axes()).
  [[nodiscard]] std::string operator()(const kin::Axes& q, SweepMode mode);
  [[nodiscard]] const Counters& counters() const { return counters_; }

 private:
  static constexpr int kMaxFrames = 7;  // the part and one per machine link
  static constexpr int kMaxHeads = 7;   // head meshes placed by the head pose, or by one machine link each
  struct Frames {
    std::array<Eigen::Vector3d, kMaxFrames> tip, axis;
    std::array<Eigen::Isometry3d, static_cast<std::size_t>(kMaxFrames) * kMaxHeads>
        head;  // [frame * kMaxHeads + group]
  };
  /// The tool (and head) relative to every frame that carries obstacles, for axes q; false if a link or the head
  /// cannot be placed (then no certificate is used).
  bool frames_at(const kin::Axes& q, const kin::Posed& pose, Frames& out) const;
  std::shared_ptr<const Space> space_;
  geom::QueryWorkspace ws_;
  Counters counters_;
  std::array<int, kMaxFrames> frame_link_{};  // -1: the part frame, else the machine link
  int frames_ = 0;
  std::array<int, kMaxHeads> head_link_{};  // per group of head meshes: -1 placed by the head pose, else the link
  std::array<Eigen::AlignedBox3d, kMaxHeads> head_box_;  // per group: the bounding box of its meshes (its own frame)
  int heads_ = 0;
  bool usable_ = false;  // certificates are sound for this space
  bool valid_ = false;
  int cooldown_ = 0;  // poses left to check exactly after the smallest probe failed
  // Linear axes translate (kin::Traits::linear_axes_translate): a pose with the certified pose's rotaries has moved
  // every body by at most the sum of its linear axes' changes, relative to every frame, and needs no FK.
  bool translate_ = false;
  std::array<bool, 5> rotary_{};
  kin::Axes at_q_ = kin::Axes::Zero();  // the certified pose's axes
  SweepMode mode_ = SweepMode::Cutting;
  double margin_mm_ = 0.0, cutter_margin_mm_ = 0.0;  // of the valid certificate
  double probe_mm_ = 0.0, cutter_probe_mm_ = 0.0;    // what the next probe asks for
  Frames at_;                                        // the certified pose
};

}  // namespace cscam::cspace
