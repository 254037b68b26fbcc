#pragma once
/// @file
/// The effect library: one definition per physical effect, used both to inject it (`cscam simulate`)
/// and to fit it (`cscam diagnose`). Names, targets, parameter keys and sign conventions follow
/// shared/spec/recording.md.
///
/// Two scopes:
/// - axis effects add a deviation dq(t) to the actual position of one axis (mm or deg): the tip follows
///   through forward kinematics, and the axis's own `enc.<axis>` channel sees it when the effect is
///   `enc_visible` (lost motion, lag, spikes, compliance are seen by an external scale; scale, cyclic and
///   squareness errors live in the encoder or the structure and are not);
/// - channel effects add a deviation to one measured channel component (`tip.z`, `enc.q2`, ...).
///
/// Every effect is written once as a template `eval<T>(ctx, i, p)` over an internal parameter vector `p`;
/// injection evaluates it with doubles, fitting with ceres::Jet (automatic derivatives).
#include <array>
#include <cstdint>
#include <limits>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "cscam/kin/types.hpp"

namespace cscam::machine {
struct Machine;
}

namespace cscam::sim {

/// Per-sample features of the commanded motion that effects read. Axis values in file units (mm, deg).
struct Context {
  std::vector<double> t;                         ///< s
  std::array<std::vector<double>, 5> q, v, a;    ///< position, velocity (/s), acceleration (/s^2)
  std::array<std::vector<double>, 5> dir;        ///< +1 / -1: sign of the axis's last motion
  std::array<std::vector<double>, 5> since_rev;  ///< s since the axis's last reversal; +inf before the first
  /// Commanded travel (mm or deg) since the axis's last reversal; +inf before the first.
  std::array<std::vector<double>, 5> travel_since_rev;
  /// Commanded travel (mm or deg) since the start of the recording (for an axis that starts against its first move).
  std::array<std::vector<double>, 5> travel;
  std::array<bool, 5> rotary{};
  double t0 = 0, duration = 0;
  std::vector<size_t> index;  ///< row of the full recording each sample comes from
  /// Time and commanded velocity at every row of the full recording (not strided): effects with a memory (a
  /// first-order servo's following error) integrate over these and read the result at `index`.
  std::vector<double> t_full;
  std::array<std::vector<double>, 5> v_full;
  /// Tells contexts apart for effects that cache a series computed over one (0: not made by make_context).
  std::uint64_t id = 0;
  /// Recorded temperatures (`temp.<sensor>` columns) at the samples: the rise since the first reading, degC, per
  /// sensor name (without `temp.`). Filled by whoever has the readings (simulate, diagnose); empty otherwise.
  std::vector<std::pair<std::string, std::vector<double>>> temp_rise;
  /// temp_rise of `sensor`, or null if it was not recorded.
  [[nodiscard]] const std::vector<double>* temperature(const std::string& sensor) const {
    for (const auto& [name, rise] : temp_rise)
      if (name == sensor) return &rise;
    return nullptr;
  }
  [[nodiscard]] size_t size() const { return t.size(); }
  /// The recorded range of axis `j` (file units): lo > hi when it has no sample.
  struct Range {
    double lo, hi;
    [[nodiscard]] double travel() const { return hi > lo ? hi - lo : 0.0; }
  };
  [[nodiscard]] Range range(size_t j) const;
};

/// Builds the context from the full-rate commanded trajectory (file units) and keeps every `stride`-th
/// sample. Derivatives and reversal state are computed at full rate.
Context make_context(const std::vector<double>& t, const std::vector<kin::Axes>& cmd, const std::array<bool, 5>& rotary,
                     size_t stride = 1);

/// Axis: a deviation of one axis; Channel: added to one channel; Geometric: a deviation of one machine-file
/// parameter (calib::Model), entering every geometric channel through the model's sensitivity.
enum class Scope { Axis, Channel, Geometric };

/// Hints for the starting grid of nonlinear parameters (e.g. spectral peaks of a channel).
struct GridHints {
  std::vector<double> frequencies_hz;
  std::vector<double> step_times_s;  ///< times of the largest jumps of a channel's residual (for `step`)
};

/// One effect instance: a definition from the library bound to a target, with parameter values.
class Effect {
 public:
  virtual ~Effect() = default;
  [[nodiscard]] virtual std::string name() const = 0;
  [[nodiscard]] virtual Scope scope() const = 0;
  /// Internal parameter names (the vector `p` the model is written in) and which enter linearly.
  [[nodiscard]] virtual std::vector<std::string> internal_names() const = 0;
  [[nodiscard]] virtual std::vector<bool> linear() const = 0;
  /// What the effect looks like in the data (for people and for `explains`).
  [[nodiscard]] virtual std::string signature() const = 0;
  /// Deviation at sample i (axis units for axis effects, channel units for channel effects).
  [[nodiscard]] virtual double value(const Context& ctx, size_t i, const double* p) const = 0;
  /// The same and its gradient with respect to p (automatic differentiation with ceres::Jet).
  virtual double value_grad(const Context& ctx, size_t i, const double* p, double* grad) const = 0;
  /// The parameters in the spec's keys and units (e.g. magnitude_mm), from the internal vector.
  [[nodiscard]] virtual std::vector<std::pair<std::string, double>> reported() const = 0;
  /// Sets the internal vector from reported keys (order of reported()); throws InputError on a bad set.
  virtual void set_reported(const std::vector<std::pair<std::string, double>>& kv) = 0;
  /// Starting points for fitting: internal vectors with the nonlinear parameters on a grid (linear 0).
  [[nodiscard]] virtual std::vector<std::vector<double>> grid(const Context& ctx, const GridHints& hints) const;
  /// Extra text for the report (e.g. the source of a vibration); empty if none.
  [[nodiscard]] virtual std::string source() const { return {}; }
  /// The effect follows a recorded temperature, that of sensor `note` (temp.<note>): it needs its readings.
  [[nodiscard]] virtual bool follows_temperature() const { return false; }
  [[nodiscard]] virtual std::unique_ptr<Effect> clone() const = 0;

  std::string target;  ///< as in the report: axis name, "x,y", or channel (tip.z)
  int axis = -1;       ///< axis index (axis scope)
  int axis2 = -1;      ///< second axis (squareness)
  bool rotary = false;
  std::string channel;  ///< channel component (channel scope), e.g. "tip.z"
  bool enc_visible = true;
  std::vector<double> p;  ///< internal parameters
  std::string note;       ///< e.g. "tooth_passing" for a vibration; the sensor a thermal_growth or _expansion follows
  /// Geometric scope: d(tip[3], ptip[3], dir[3]) / d(parameter) per context sample, and the parameter's
  /// nominal value and unit (file units).
  std::shared_ptr<const std::vector<std::array<double, 9>>> geo_sens;
  double nominal = 0;
  std::string unit;
};

/// A geometric deviation of one machine-file parameter `name` (calibration model), deviation `dev`
/// (file units). Its value is the deviation; the sensitivity table says how the channels move.
std::unique_ptr<Effect> make_geometric(const std::string& name, const std::string& unit, double nominal, double dev);

/// The names of every effect in the library.
std::vector<std::string> effect_names();
/// A new effect bound to `target` on machine m (parameters zero). Throws InputError on an unknown name
/// or a target the machine does not have.
std::unique_ptr<Effect> make_effect(const std::string& name, const std::string& target, const machine::Machine& m);
/// Parses `NAME:TARGET:V1[:V2...]` or `NAME:TARGET:key=value,key=value` (the --inject syntax).
std::unique_ptr<Effect> parse_effect(const std::string& spec, const machine::Machine& m);
/// `geometric:NAME=VALUE[,NAME=VALUE]` as (name, absolute machine-file value) pairs. Throws InputError on bad syntax.
std::vector<std::pair<std::string, double>> parse_geometric_values(const std::string& spec);
/// The same, and `geometric:NAME=VALUE[,NAME=VALUE]` (absolute machine-file values) as one effect per parameter.
std::vector<std::unique_ptr<Effect>> parse_effects(const std::string& spec, const machine::Machine& m);
/// The `effects:` section of a machine file (list of {effect, target, parameters: {key: value}}).
std::vector<std::unique_ptr<Effect>> load_machine_effects(const std::string& machine_file, const machine::Machine& m);
/// YAML text of an `effects:` section for these effects.
std::string effects_yaml(const std::vector<const Effect*>& effects);

}  // namespace cscam::sim
