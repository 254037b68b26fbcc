#pragma once
/// @file
/// Backlash (lost motion) simulation: what a play of a few micrometres on one axis does to the tool tip.
///
/// The model is the classic play (dead-band) operator: the axis output follows the command only after
/// the command has moved the full width in the new direction. The drive is taken as engaged in the
/// direction of its first motion, so the output equals the command until the first reversal and lags it
/// by the width after every reversal. Forward kinematics of the output then gives the tip path that the
/// machine would really cut, and its deviation from the commanded tip path shows where the play marks
/// the surface. On a parallel machine (XMINI) a leg reversal moves the tip in every component, so the
/// deviation is reported per component (x, y, z of the part frame).
#include <Eigen/Core>
#include <array>
#include <nlohmann/json_fwd.hpp>
#include <string>
#include <vector>

#include "cscam/kin/kinematics.hpp"
#include "cscam/nc/reader.hpp"

namespace cscam::report {

/// The play operator on a sequence of commanded values (mm or rad): the output for each command.
/// `width` is the full lost motion (>= 0). Engaged in the direction of the first non-zero change.
std::vector<double> apply_play(const std::vector<double>& commanded, double width);

/// A commanded axis path, sampled densely enough for the play to act (see sample_nc).
struct SampledPath {
  std::vector<kin::Axes> q;  ///< commanded axis values (mm, rad)
  std::vector<int> nc_line;  ///< NC line of the block each sample belongs to
  std::vector<bool> feed;    ///< sample lies in a feed block (rapids are simulated but not reported)
};

/// Samples every motion block of an NC program as a straight line in axis space (what a joint-space
/// control interpolates), so that `axis` moves at most `max_axis_step` between samples and every
/// block gets at least `min_samples_per_block` samples. Blocks before every axis is known are skipped.
SampledPath sample_nc(const nc::Program& program, int axis, double max_axis_step, int min_samples_per_block = 4);

/// One reversal of the axis with play: where it began and what the tip did once the play was taken up.
struct BacklashReversal {
  std::size_t begin_sample = 0;  ///< the command's turning point (output still engaged on the old side)
  std::size_t end_sample = 0;    ///< first sample where the output moves again in the new direction
  int nc_line = 0;               ///< NC line of begin_sample
  bool in_feed = false;          ///< while cutting: turning point and take-up inside feed blocks
  Eigen::Vector3d tip_mm = Eigen::Vector3d::Zero();   ///< commanded tip at the turning point (part frame)
  Eigen::Vector3d step_mm = Eigen::Vector3d::Zero();  ///< tip deviation after minus before (x, y, z)
};

/// The tip paths with and without play and their comparison.
struct BacklashResult {
  std::string axis_name;
  bool rotary = false;
  double width = 0.0;                             ///< mm or rad
  std::vector<Eigen::Vector3d> tip_commanded_mm;  ///< FK of the commanded samples
  std::vector<Eigen::Vector3d> tip_actual_mm;     ///< FK of the samples with play
  std::vector<BacklashReversal> reversals;        ///< every completed reversal of the axis
  /// Over feed samples: the largest |actual - commanded| per component, where (sample index, NC line).
  Eigen::Vector3d max_abs_deviation_mm = Eigen::Vector3d::Zero();
  std::array<std::size_t, 3> max_deviation_sample{};
  std::array<int, 3> max_deviation_nc_line{};
  /// Over reversals while cutting (in_feed): the largest |step| per component and which one (-1: none).
  Eigen::Vector3d max_abs_step_mm = Eigen::Vector3d::Zero();
  std::array<int, 3> max_step_reversal{-1, -1, -1};
  std::size_t feed_samples = 0;

  /// A short report for a person: per component max deviation and max step, with NC lines and tips.
  [[nodiscard]] std::string text() const;
  [[nodiscard]] nlohmann::json json() const;
  [[nodiscard]] std::string to_json() const;  ///< json().dump()
};

/// Applies a play of full width `width` (mm or rad) to axis `axis` of the sampled commanded path, runs
/// forward kinematics on both and compares them. Throws std::invalid_argument on a bad axis or width.
BacklashResult simulate_backlash(const SampledPath& path, const kin::Kinematics& kinematics, int axis, double width);

}  // namespace cscam::report
