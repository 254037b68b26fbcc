#pragma once
/// @file
/// Geometric calibration: identifiability analysis of the column-scaled Jacobian, a Ceres
/// least-squares solve with automatic differentiation through the model, covariance, robust loss,
/// held-out validation and pose selection.
///
/// @code
///   auto model = calib::load_model("machines/xmini.yaml");
///   calib::Dataset data = calib::dataset_from(calib::read_recording("rec.csv"), *model);
///   calib::Options opt;                       // every parameter a candidate
///   calib::Result r = calib::calibrate(*model, data, opt);
///   if (r.summary.converged) write(model->corrected_yaml(r.estimate));
/// @endcode
#include <Eigen/Core>
#include <array>
#include <cstdint>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "cscam/calib/model.hpp"
#include "cscam/calib/recording.hpp"

namespace cscam::calib {

/// Standard deviations of the measurement channels (the residual weights are 1/sigma).
struct Sigmas {
  double tip_mm = 0.001;
  double ptip_mm = 0.001;
  double dir = 1e-5;  ///< unit-vector components (~ rad)
  double len_mm = 0.001;
  bool given = false;  ///< true when they come from the recording or the caller (not defaults)
};

/// One static pose: commanded axes and the measured channels (model->channel_names() order, NaN where
/// not measured).
struct PoseData {
  std::vector<double> q;
  std::vector<double> meas;
  int line = 0;  ///< source line in the recording (0 if synthetic)
};

/// The poses of a static recording, with the channel sigmas.
struct Dataset {
  std::string file;
  std::vector<PoseData> poses;
  Sigmas sigma;
  /// Independent scalar measurements (a measured direction counts 2).
  [[nodiscard]] std::size_t measurement_count() const;
};

/// Turns a recording into a dataset for `model`: checks the axes (InputError naming the column), sets
/// the model's channels, reads optional `sigma.tip`, `sigma.ptip`, `sigma.dir`, `sigma.len` metadata.
/// A trajectory recording is accepted (its samples are treated as poses).
Dataset dataset_from(const Recording& rec, const Model& model);

/// Simulates a static recording: `channels` (e.g. {"tip"}, {"ptip"}, {"tip","dir"}, {"len.link"})
/// predicted with parameters `truth` at `poses`, plus Gaussian noise of `sigma` (seeded).
Dataset simulate(const Model& model, const std::vector<double>& truth, const std::vector<std::vector<double>>& poses,
                 const std::vector<std::string>& channels, const Sigmas& sigma, std::uint64_t seed);
/// The same as a Recording (`kind: static`), for writing to a file.
Recording to_recording(const Model& model, const Dataset& d, const std::string& machine_file);

enum class Loss { None, Huber, Cauchy };

struct Options {
  std::vector<std::size_t> free;  ///< candidate parameters (indices); empty = all
  Loss loss = Loss::None;
  double loss_scale = 3.0;  ///< in units of sigma
  /// A scaled singular value below rank_tolerance * sigma_max counts as zero (an unidentifiable
  /// combination).
  double rank_tolerance = 1e-7;
  /// Instead of fixing unidentifiable parameters at nominal, keep them free with a prior
  /// (deviation / prior_sigma, in file units) pulling them to nominal.
  bool regularise = false;
  double prior_sigma = 0.01;
  int max_iterations = 100;
  double function_tolerance = 1e-15;
  double parameter_tolerance = 1e-12;
  double gradient_tolerance = 1e-16;
  /// Starting point (file units); empty = nominal.
  std::vector<double> start;
  bool covariance = true;
};

/// Identifiability of a parameter set for a dataset, from the SVD of the column-scaled Jacobian.
struct Identifiability {
  std::vector<std::size_t> candidates;    ///< the parameters analysed
  std::vector<double> singular_values;    ///< of the scaled Jacobian, descending
  double condition_number = 0;            ///< sigma_max / sigma_min (over the candidates)
  double condition_identified = 0;        ///< sigma_max / sigma_min over the identifiable subset
  double O1 = 0, O2 = 0, O3 = 0, O4 = 0;  ///< observability indices (of the candidates)
  /// O1..O4 of the identifiable subset (what the solve actually works with).
  std::array<double, 4> observability_identified{};
  int rank = 0;
  std::vector<std::size_t> identifiable;  ///< free after the analysis
  std::vector<std::size_t> fixed;         ///< fixed at nominal (or regularised)
  std::vector<std::string> messages;      ///< one per fixed parameter: what it cannot be told from
  std::vector<std::string> combinations;  ///< the null-space vectors in words
};

/// What Ceres reported.
struct SolverSummary {
  bool converged = false;
  std::string termination;  ///< Ceres' termination type (CONVERGENCE, NO_CONVERGENCE, FAILURE, ...)
  std::string message;      ///< Ceres' message
  int iterations = 0;
  double initial_cost = 0, final_cost = 0;  ///< 0.5 * sum of squared weighted residuals
  double time_s = 0;
  std::vector<double> cost_history;  ///< per iteration
  std::vector<double> step_history;  ///< max |parameter change| per iteration (file units)
};

/// RMS and maximum residual per channel group ("tip", "ptip", "dir", "len.<link>").
struct ResidualStats {
  std::map<std::string, double> rms, max;
  std::map<std::string, std::size_t> count;
};
ResidualStats residual_stats(const Model& model, const Dataset& d, const std::vector<double>& p);

struct Result {
  Identifiability ident;
  SolverSummary summary;
  std::vector<double> estimate;  ///< all parameters (file units)
  std::vector<double> stddev;    ///< per parameter; NaN for fixed ones
  Eigen::MatrixXd covariance;    ///< of all parameters (file units; zero rows for fixed ones); empty when not computed
  std::vector<std::pair<std::pair<std::size_t, std::size_t>, double>> correlations;  ///< |rho| > 0.9
  double chi2_reduced = 0;  ///< sum (r/sigma)^2 / (m - free): ~1 when the sigmas are right
  /// Sum of squared weighted residuals (not robustified) over the poses the fit trusts: all of them, or with a
  /// robust loss all but the listed outliers; its degrees of freedom (measurements - free parameters) and
  /// P(chi^2_dof >= chi2). A tiny p says the residuals are larger than the sigmas allow.
  double chi2 = 0, chi2_dof = 0, chi2_p = 1;
  ResidualStats before, after;
  struct Outlier {
    std::size_t pose;
    int line;
    double normalised_rms;
    /// Chance that at least one of the dataset's clean poses lies this far out (per-pose chi^2 tail times the
    /// number of poses): small = a real outlier, not the largest of many noisy poses.
    double p_any = 1;
  };
  std::vector<Outlier> outliers;
  /// What the outlier rule divides a pose's normalised RMS residual by: 1 where the recording gives its sigmas,
  /// otherwise the noise level estimated from the median pose (so that other poses, e.g. held-out ones, can be judged
  /// by the same rule: heldout_outliers).
  double residual_scale = 1.0;
};

/// Exact data without sigmas: the fit's noise estimate is rounding, and every "outlier" judged against it is too.
bool noise_is_rounding(const Dataset& d, const Result& r);

/// Poses of `d` (e.g. held out of the fit) that the parameters `p` predict worse than the fit's noise allows, by the
/// rule the fit's own poses are judged by: normalised RMS residual above 3 x `r.residual_scale`, with its chance
/// among d's poses (p_any). Such a pose did not pull the fit: a bad measurement, or an effect the model lacks there.
std::vector<Result::Outlier> heldout_outliers(const Model& model, const Dataset& d, const std::vector<double>& p,
                                              const Result& r);

/// P(X >= x) for X ~ chi^2 with `dof` degrees of freedom.
double chi2_upper_tail(double x, double dof);

/// "p = 0.0312" for a p-value, or "p < 1e-300" where it is smaller than doubles show (a chi^2 tail of thousands of
/// degrees of freedom underflows to 0, which is not "p = 0").
std::string p_value_text(double p, int significant_digits = 3);

/// Whether a fit may be written as a corrected machine file.
struct WriteCheck {
  /// The residuals agree with the noise: with the recording's sigmas, chi2_p >= alpha; and no outlier with
  /// p_any < alpha is left at full weight (no robust loss).
  bool consistent = true;
  std::string inconsistency;  ///< why not, for a person (names the worst rows by line)
  /// Some change is larger than its uncertainty allows: the joint test (change' C^-1 change ~ chi^2_n) or
  /// the largest |change| / sigma against its Bonferroni limit, either at level alpha.
  bool significant = true;
  double mahalanobis = 0, p_joint = 1;
  double max_z = 0, p_max = 1;  ///< largest |change| / stddev, and its Bonferroni-corrected p
  std::string largest;          ///< the parameter of max_z
};
/// Judges `r` at level `alpha` (default 1e-3 for consistency and 0.01 for significance).
WriteCheck check_for_writing(const Model& model, const Dataset& d, const Result& r, Loss loss, double alpha_fit = 1e-3,
                             double alpha_change = 0.01);

/// Identifiability analysis at parameters `p` (file units) for the candidates in `opt.free`.
Identifiability analyse(const Model& model, const Dataset& d, const std::vector<double>& p, const Options& opt);

/// The weighted Jacobian (rows: measured channels / sigma, columns: `cols`) at `p`, by automatic
/// differentiation.
Eigen::MatrixXd jacobian(const Model& model, const Dataset& d, const std::vector<double>& p,
                         const std::vector<std::size_t>& cols);

/// Identifies the parameters. Throws InputError when the data hold fewer independent measurements than
/// free parameters (saying how many are needed). A solve that does not converge returns
/// summary.converged = false with Ceres' termination reason.
Result calibrate(const Model& model, const Dataset& d, const Options& opt);

/// Pose selection: chooses `n` of `candidates` greedily to maximise log det(J^T J) of the scaled
/// Jacobian (D-optimal) or the smallest singular value (O3) for the parameters `free`, measuring
/// `channels`. Returns the indices of the chosen candidates.
std::vector<std::size_t> select_poses(const Model& model, const std::vector<std::vector<double>>& candidates,
                                      const std::vector<std::string>& channels, const std::vector<std::size_t>& free,
                                      std::size_t n, bool o3 = false);

}  // namespace cscam::calib
