#pragma once
/// @file
/// Motion profiles from NC or CL programs, channel prediction by forward kinematics, and the simulator
/// that writes recordings with injected effects and noise.
#include <Eigen/Core>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "cscam/calib/model.hpp"
#include "cscam/kin/kinematics.hpp"
#include "cscam/machine/machine.hpp"
#include "cscam/sim/effects.hpp"
#include "cscam/sim/recording.hpp"

namespace cscam::nc {
struct Program;
}

namespace cscam::sim {

/// Commanded axis values against time (file units: mm and deg).
struct Trajectory {
  std::vector<double> t;
  std::vector<kin::Axes> cmd;
};

struct ProfileOptions {
  double rate_hz = 1000;
  /// Acceleration of the path parameter, mm/s^2 (deg/s^2 for rotary-only moves). Every block is a
  /// trapezoid that starts and ends at rest (exact stop, G61): accelerate, cruise at the feed, decelerate.
  double accel = 2000;
  double dwell_s = 0;  ///< rest before the first and after the last block
};

/// Motion blocks: end points (file units), feed, and the block's nominal duration at the feed.
struct Block {
  kin::Axes end = kin::Axes::Zero();
  double duration_s = 0;  ///< time at the programmed feed (without acceleration)
  double length = 0;      ///< path length (mm of the linear axes, or deg if only rotaries move)
};

/// Blocks of an NC program: G1 at F mm/min along the linear axes (rotaries alone: F deg/min), G93 in
/// inverse time (1/F min), G0 at each axis's max_feed. Arcs are taken as chords (as nc::read does).
std::vector<Block> blocks_from_nc(const nc::Program& prog, const machine::Machine& m);
/// Blocks of a CL program posted with the conventional strategy: every CL point's axis values, the
/// block time from the tip's path length at the CL feed (rapids at the axes' max feed).
std::vector<Block> blocks_from_cl(const std::string& cl_file, const machine::Machine& m, double tool_length_mm);
/// Samples the trapezoidal profile of the blocks at rate_hz.
Trajectory profile(const std::vector<Block>& blocks, const ProfileOptions& o);

/// Predicts measured channels from axis values (file units) by forward kinematics.
class Predictor {
 public:
  Predictor(const machine::Machine& m, double tool_length_mm);
  /// tip in W, tip in the part frame, tool direction in W.
  void fk(const kin::Axes& q, Eigen::Vector3d& tip, Eigen::Vector3d& ptip, Eigen::Vector3d& dir) const;
  /// d(tip, ptip, dir)/dq by central differences (rows 0-2 tip, 3-5 ptip, 6-8 dir; per mm or deg).
  void jacobian(const kin::Axes& q, Eigen::Matrix<double, 9, 5>& J) const;
  /// The rotation taking a vector of the machine frame W into the part frame at q (file units): how a move of the
  /// tool point in W shows in ptip. The identity on a machine without table-side rotaries.
  [[nodiscard]] Eigen::Matrix3d part_from_machine(const kin::Axes& q) const;
  [[nodiscard]] const machine::Machine& machine() const { return m_; }
  [[nodiscard]] bool rotary(int i) const { return m_.axes[static_cast<size_t>(i)].rotary(); }

 private:
  machine::Machine m_;
  std::shared_ptr<const kin::Kinematics> kin_;
  std::optional<kin::SerialGeometry<double>> head_only_;
};

struct NoiseSpec {
  std::string group;  ///< tip, ptip, enc, acc, dir
  double sigma = 0;
};

struct SimulateOptions {
  std::vector<std::string> channels{"tip", "enc"};
  std::vector<NoiseSpec> noise;
  unsigned seed = 1;
  double tool_length_mm = -1;  ///< <0: the machine default
  double spindle_rpm = 0;      ///< 0: none
  int flutes = 0;
  std::string machine_ref;  ///< what to write in the `machine` metadata
  std::string note;
  /// Temperatures to record (`temp.<sensor>`) and for thermal_growth effects to follow: per sensor, times (s) and
  /// readings (degC), interpolated linearly at the samples (held beyond their ends).
  struct Temperature {
    std::string sensor;
    std::vector<double> t, deg_c;
  };
  std::vector<Temperature> temperatures;
};

/// A sensor's readings at times `t` (s): linear between readings, the first and last held beyond them.
std::vector<double> temperature_at(const SimulateOptions::Temperature& readings, const std::vector<double>& t);

/// Applies effects (axis effects through FK, channel effects added) to a commanded trajectory and
/// returns the recording (cmd.* always; the chosen channels). `truth_machine`, if given, is the machine
/// the data come from (geometric deviations); predictions in diagnose use the nominal one.
Recording simulate(const Trajectory& traj, const machine::Machine& m, const std::vector<const Effect*>& effects,
                   const SimulateOptions& o, const machine::Machine* truth_machine = nullptr);

/// Measures static poses on a machine known only by its calibration model (the parallel CMM, which has no 5-axis
/// kinematics to run a program on): every pose's channels predicted with the parameters set to `values` (name,
/// absolute machine-file value; the others nominal), white noise per group (`tip`, `ptip`, `dir`, `len`: every
/// len.<link>), `o.channels` the groups to record. Poses are in the model's axis order and file units. Throws
/// InputError naming the pose (1-based) where the deviated machine has no solution, and on a group the model does
/// not measure.
Recording simulate_static(const calib::Model& model, const std::vector<std::vector<double>>& poses,
                          const std::vector<std::pair<std::string, double>>& values, const SimulateOptions& o);

}  // namespace cscam::sim
