#pragma once
/// @file
/// Calibration models: a flat vector of geometric parameters for any bundled machine, and the
/// prediction of every measurable channel (spec/recording.md) from commanded axes and a parameter
/// vector. The prediction runs the project's own templated kinematics (kin::serial_forward,
/// kin::xmini_forward, kin::pcmm_forward); there is no second copy of any model.
///
/// Units: every parameter value and every axis value in this API is in *file units*: mm for lengths,
/// degrees for angles (what machine files and recordings use). Predicted channels are mm (tip, ptip,
/// len) and unit vectors (dir).
///
/// Typical use (plain doubles, e.g. from the `sim`/`diagnose` modules):
/// @code
///   auto model = cscam::calib::load_model("machines/trunnion-ac.yaml");
///   std::vector<double> p = model->nominal();
///   p[model->index("EX0C")] += 0.01;                      // 10 um offset of the C axis line
///   auto pred = model->predict({10, 20, 30, 15, 45}, p); // cmd.* in machine axis order, mm / deg
///   Eigen::Vector3d ptip = pred.ptip;
///   std::string yaml = model->corrected_yaml(p);         // the machine file with the changed values
/// @endcode
#include <Eigen/Core>
#include <cstdint>
#include <limits>
#include <map>
#include <memory>
#include <string>
#include <vector>

namespace ceres {
template <typename T, int N>
struct Jet;
}

namespace cscam::calib {

/// Jet width used for automatic differentiation (ceres::DynamicAutoDiffCostFunction stride).
inline constexpr int kJetStride = 16;
using Jet = ceres::Jet<double, kJetStride>;

/// One geometric parameter of a calibration model.
struct ParamInfo {
  std::string name;         ///< e.g. "EX0C", "theta0", "rb1"
  std::string group;        ///< e.g. "rotary_c", "wrist", "legs", "base", "passive"
  std::string unit;         ///< "mm" or "deg"
  double nominal = 0.0;     ///< value in the machine file as loaded (file units)
  std::string description;  ///< one line for a person
  /// A frame convention rather than geometry (the PCMM's ths1 names the stage frame's x axis): when the data
  /// cannot tell it from others, it is the one held at nominal.
  bool gauge = false;
};

/// Every channel the model can predict for one pose. Channels the model does not have are NaN.
struct Prediction {
  Eigen::Vector3d tip = Eigen::Vector3d::Constant(std::numeric_limits<double>::quiet_NaN());   ///< W, mm
  Eigen::Vector3d dir = Eigen::Vector3d::Constant(std::numeric_limits<double>::quiet_NaN());   ///< W, tip->spindle
  Eigen::Vector3d ptip = Eigen::Vector3d::Constant(std::numeric_limits<double>::quiet_NaN());  ///< part frame, mm
  std::map<std::string, double> len;  ///< passive links by name, mm (the gauge reading)
};

/// Per-pose scratch (e.g. the forward-kinematics warm start of a parallel machine). Not shared between
/// threads.
struct Scratch {
  virtual ~Scratch() = default;
};

/// A machine's geometric parameters and its measurement prediction. Immutable; thread-safe for const
/// use when each thread passes its own Scratch.
class Model {
 public:
  virtual ~Model() = default;

  /// "serial", "xmini" or "pcmm".
  [[nodiscard]] virtual std::string kind() const = 0;
  /// The machine file this model was loaded from (may be empty for a model built in code).
  [[nodiscard]] const std::string& file() const { return file_; }
  /// Names of the commanded axes in recording order (lower case: "x", "q2", ...).
  [[nodiscard]] const std::vector<std::string>& axis_names() const { return axes_; }
  /// For each axis: true if rotary (values in degrees).
  [[nodiscard]] const std::vector<bool>& axis_rotary() const { return rotary_; }
  /// The parameters, in vector order.
  [[nodiscard]] const std::vector<ParamInfo>& params() const { return params_; }
  [[nodiscard]] std::size_t size() const { return params_.size(); }
  /// The nominal parameter vector (file units).
  [[nodiscard]] std::vector<double> nominal() const;
  /// Index of a parameter by name; throws InputError listing the names if unknown.
  [[nodiscard]] std::size_t index(const std::string& name) const;
  /// Indices selected by a list of names and/or group names; throws InputError on an unknown one.
  [[nodiscard]] std::vector<std::size_t> select(const std::vector<std::string>& names_or_groups) const;
  /// Channel names this model predicts, in the order of predict_channels():
  /// tip.x tip.y tip.z dir.x dir.y dir.z ptip.x ptip.y ptip.z len.<link>...
  [[nodiscard]] std::vector<std::string> channel_names() const;
  /// The passive links (`len.<name>`) this model knows.
  [[nodiscard]] const std::vector<std::string>& links() const { return links_; }
  /// Tool length (mm) used by predictions (gauge point to tip); recordings may override.
  [[nodiscard]] double tool_length_mm() const { return tool_length_mm_; }
  void set_tool_length_mm(double L) { tool_length_mm_ = L; }

  /// Every channel for commanded axes `q` (file units, machine axis order) and parameters `p`.
  [[nodiscard]] Prediction predict(const std::vector<double>& q, const std::vector<double>& p,
                                   Scratch* scratch = nullptr) const;
  /// The same as a flat vector in channel_names() order (9 + links().size() values).
  virtual void predict_channels(const double* q, const double* p, double* out, Scratch* scratch) const = 0;
  /// The same with parameters as Jets (automatic differentiation). `q` stays plain.
  virtual void predict_channels(const double* q, const Jet* p, Jet* out, Scratch* scratch) const = 0;
  /// `n` commanded poses (file units, axis order) drawn at random inside the machine's working
  /// volume, reproducibly from `seed`: candidates for pose selection and poses for simulated data.
  [[nodiscard]] virtual std::vector<std::vector<double>> random_poses(std::size_t n, std::uint64_t seed) const = 0;
  /// A fresh per-pose scratch (may be null).
  [[nodiscard]] virtual std::unique_ptr<Scratch> make_scratch() const { return nullptr; }

  /// The machine file's text with the parameters set to `p`: comments kept, every changed value
  /// marked with a trailing `# calibrated: was X`. Throws InputError if the file cannot be read.
  [[nodiscard]] virtual std::string corrected_yaml(const std::vector<double>& p) const = 0;
  /// Parameters that differ from nominal by more than `eps` (file units), as name -> deviation.
  [[nodiscard]] std::map<std::string, double> deviations(const std::vector<double>& p, double eps = 0.0) const;

 protected:
  std::string file_;
  std::vector<std::string> axes_;
  std::vector<bool> rotary_;
  std::vector<ParamInfo> params_;
  std::vector<std::string> links_;
  double tool_length_mm_ = 0.0;
};

/// Loads the calibration model of a machine file (a path; `kinematics:` serial, xmini or pcmm).
/// Throws InputError naming the file on bad input.
std::shared_ptr<Model> load_model(const std::string& path);

}  // namespace cscam::calib
