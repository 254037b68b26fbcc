#pragma once
/// @file
/// A controller's servo trace (LinuxCNC's motion controller, recorded by halsampler every servo cycle)
/// against the CL path: forward kinematics of the sampled joints, the tip's deviation from the path.
#include <Eigen/Core>
#include <array>
#include <nlohmann/json_fwd.hpp>
#include <string>
#include <vector>

#include "cscam/cl/program.hpp"
#include "cscam/kin/kinematics.hpp"
#include "cscam/nc/reader.hpp"

namespace cscam::report {

/// What the motion controller was doing in a servo cycle (LinuxCNC's motion.motion-type 0..3; tool change,
/// probing, rigid tapping and the rest are Other).
enum class TraceMotion { Idle, Rapid, Feed, Arc, Other };

/// One servo cycle.
struct TraceSample {
  long index = 0;            ///< halsampler's sample number
  kin::Axes joints;          ///< commanded machine axes, canonical order (mm, rad)
  Eigen::Vector3d world_mm;  ///< the controller's commanded X Y Z (machine or TCP coordinates)
  int nc_line = 0;           ///< program line the controller was executing (1-based)
  TraceMotion motion = TraceMotion::Idle;
  int kinematics = 0;  ///< LinuxCNC's switchkins type: 0 identity (joint mode), 1 the machine's (TCP)
};

struct Trace {
  std::string file;
  std::vector<TraceSample> samples;
};

/// Reads `halsampler -t` output of scripts/linuxcnc/config/trunnion-ac.hal's sampler: per line the sample
/// number, joints 0-4, world X Y Z and two more world axes, program line, motion type, velocity, kinematics
/// type. Rotary
/// joints (`rotary[i]`) are in degrees in the file. A gap in the sample numbers or an `overrun` line (the
/// FIFO lost samples) and a malformed line are InputErrors with file and line.
Trace read_halsampler(const std::string& path, const std::array<bool, 5>& rotary);
Trace read_halsampler_text(const std::string& text, const std::string& name, const std::array<bool, 5>& rotary);

struct TraceCheckOptions {
  double tip_tolerance_mm = 0.012;   ///< allowed distance of a feed sample's tip from the CL path
  double axis_tolerance_deg = 0.35;  ///< allowed angle between its tool axis and the CL axis there
};

/// The NC blocks where the tip strayed furthest (one entry per block, largest first).
struct TraceBlock {
  int nc_line = 0;
  double max_tip_deviation_mm = 0.0;
  size_t samples = 0;
};

struct TraceCheckResult {
  bool ok = false;
  std::string message;
  size_t samples = 0;       ///< every servo cycle of the trace
  size_t feed_samples = 0;  ///< those at feed (linear or arc): the compared ones
  double max_tip_deviation_mm = 0.0;
  double p99_tip_deviation_mm = 0.0;  ///< 99th percentile over the feed samples
  long max_tip_sample = -1;           ///< halsampler sample number (servo cycles since the run started)
  int max_tip_nc_line = 0;
  int max_tip_cl_line = 0;  ///< the CL segment nearest to that sample (its end point's line)
  Eigen::Vector3d max_tip_in_part_mm = Eigen::Vector3d::Zero();
  double max_axis_deviation_deg = 0.0;
  int max_axis_nc_line = 0;
  double max_uncovered_cl_mm = 0.0;  ///< largest distance from a CL feed point to the sampled tip path
  int max_uncovered_cl_line = 0;
  std::vector<TraceBlock> worst_blocks;  ///< up to 5
  size_t departure_blocks = 0;
  /// Feed samples off the CL path on one of those retracts or plunges (matched by position and axis, whatever NC
  /// line the controller labelled them with): not compared with the path.
  size_t departure_samples = 0;
  /// The controller's own world X Y Z against ours: in joint mode the joints, in TCP mode the FK tip (LinuxCNC's
  /// kinematics module against the machine file). The world position leads the joints by a few servo cycles
  /// (interpolation); the lag that fits best is used. Reported, not part of ok (work offsets would move it).
  double max_world_mismatch_mm = 0.0;
  double max_world_mismatch_tcp_mm = 0.0;  ///< the same over the TCP samples only
  size_t tcp_samples = 0;
  int world_lag_samples = 0;  ///< feed blocks of the program that leave the CL path along the tool axis
  [[nodiscard]] nlohmann::json json() const;
};

/// Compares every feed sample's tip and axis (FK of its joints through `kinematics`) with the nearest point
/// of the CL feed path, and every CL feed point with the sampled tip path (so that a trace that skipped part
/// of the program fails too). ok when both stay within the options' tolerances.
/// With the program that ran (`nc`), its feed blocks that only move the tool along its fixed axis to or from a
/// point off the CL path (a post's retract before a flip or at the end, or the plunge back) are not compared,
/// as verify does not: they leave the path by design. Axis values of a TCP program are part coordinates.
TraceCheckResult check_trace(const Trace& trace, const cl::Program& cl, const kin::Kinematics& kinematics,
                             const TraceCheckOptions& options, const nc::Program* nc = nullptr);

}  // namespace cscam::report
