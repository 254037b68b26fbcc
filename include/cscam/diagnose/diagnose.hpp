#pragma once
/// @file
/// Diagnosis of a trajectory recording (shared/spec/recording.md): simulate from cmd.* and subtract,
/// estimate the noise, locate the mismatch, explain it with effects from sim's library selected on
/// held-out time blocks, and report.
#include <map>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "cscam/machine/machine.hpp"
#include "cscam/sim/effects.hpp"
#include "cscam/sim/recording.hpp"

namespace cscam::diagnose {

struct Options {
  std::size_t max_fit_samples = 60000;     ///< samples used for the joint fits (stride over the recording)
  std::size_t max_screen_samples = 15000;  ///< samples used to screen candidates
  int time_blocks = 12;                    ///< blocks of time; every third one is held out
  int max_effects = 6;
  /// An effect is accepted when it lowers the held-out sum of squares (in units of the noise variance) by
  /// more than max(min_gain_sum, min_gain x the number of held-out values).
  double min_gain = 0.01;
  double min_gain_sum = 40;
  bool keep_plot_data = false;  ///< keep series for the SVG pictures
};

struct Localization {
  std::string channel;
  double t_start = 0, t_end = 0, rms = 0;
  std::string coincides_with;
};

struct Finding {
  std::unique_ptr<sim::Effect> effect;
  std::string group;  ///< channel group it is judged on (tip, enc.q2, ...)
  std::string explains;
  double heldout_rms_before = 0, heldout_rms_after = 0;
  double share = 0;  ///< fraction of the explained held-out residual
  /// A transient that acts only in training blocks (the one reversal of a run): accepted on its training gain, and
  /// heldout_rms_* are then taken on the training blocks where it acts.
  bool judged_on_training = false;
  /// Other effects that explain this recording as well, refitted jointly with the effects found before it: their
  /// held-out residual is larger by less than an effect must explain to be accepted. The recording cannot tell them
  /// apart (on a circle, Z bowing along X is Z bowing along Y); another motion may.
  std::vector<std::string> alternatives;
};

struct Series {
  std::string name;
  std::vector<double> x, y;
};

struct Report {
  std::string recording, machine;
  std::size_t samples = 0;
  std::vector<std::pair<std::string, double>> rms_before;  ///< per channel group
  std::vector<std::pair<std::string, double>> noise;       ///< estimated noise RMS per group
  std::vector<Localization> localization;
  std::vector<Finding> findings;
  double heldout_rms_before = 0, heldout_rms_after = 0;  ///< all fitted channels, noise-weighted
  std::size_t heldout_values = 0;                        ///< held-out values those two are taken over
  /// The held-out residual left after the findings is clearly above the noise: something the library does not
  /// model (or models only in part) is in the recording.
  bool residual_above_noise = false;
  /// Constant offsets per channel component clearly above its noise (mm or deg): a zero or reference shift, or an
  /// effect that the recording shows only as a constant (lost motion on an axis that never reverses). Fitted with
  /// the findings; not physics the recording can name.
  std::vector<std::pair<std::string, double>> offsets;
  std::string verdict;
  std::vector<std::string> warnings;
  std::vector<std::pair<std::string, double>> seconds;  ///< time per stage
  // Plot data (keep_plot_data): residual before/after vs time of the main channel, vs its feature, spectrum.
  std::vector<Series> plots_time, plots_feature, plots_spectrum;
  std::string feature_name, main_channel;
  std::vector<double> peak_freqs;

  [[nodiscard]] std::string to_json() const;
  [[nodiscard]] std::string text() const;
};

/// Diagnoses a trajectory recording against machine m (plus the effects it already models).
/// Throws InputError on bad input (missing cmd.* column, unpredictable channel, too little data).
Report diagnose(sim::Recording& rec, const machine::Machine& m, const std::vector<const sim::Effect*>& known,
                const Options& o = {});

/// The machine file text with an `effects:` section for the known + found effects (replacing any old one).
std::string model_yaml(const std::string& machine_file_text, const std::vector<const sim::Effect*>& effects);
/// LinuxCNC INI lines ([JOINT_n] BACKLASH, COMP_FILE, COMP_FILE_TYPE) and compensation tables
/// (file name -> text) for backlash, scale and cyclic effects.
std::string linuxcnc_ini(const machine::Machine& m, const std::vector<const sim::Effect*>& effects,
                         const std::string& comp_prefix, std::map<std::string, std::string>& comp_files);
/// SVG pictures of a report with plot data: file name -> SVG text.
std::map<std::string, std::string> svg_pictures(const Report& r);

}  // namespace cscam::diagnose
