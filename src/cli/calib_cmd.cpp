// `cscam calibrate`: identify a machine's geometric parameters from a static recording, say what the
// data cannot determine, validate on held-out poses and write the corrected machine file.
#include "calib_cmd.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <memory>
#include <nlohmann/json.hpp>
#include <numeric>
#include <random>
#include <sstream>

#include "cscam/calib/calibrate.hpp"
#include "cscam/calib/model.hpp"
#include "cscam/calib/recording.hpp"
#include "cscam/core/atomic_file.hpp"
#include "cscam/core/error.hpp"
#include "plan_cmd.hpp"
#include "validators.hpp"

namespace fs = std::filesystem;

namespace cscam::cli {

namespace {

/// A held-out pose is reported when so large a residual has less than this chance among clean poses (the level the
/// fit's own outliers are judged at: check_for_writing's alpha_fit).
constexpr double kHeldOutAlpha = 1e-3;

struct CalibArgs {
  std::string rec, machine, out, holdout, svg, loss, free, channels;
  bool json = false, regularise = false, o3 = false, write_anyway = false;
  int design = 0, candidates = 1000, max_iterations = 100;
  double split = 0.2;
  double tool_length = -1;
  unsigned seed = 1;
};

std::vector<std::string> split_list(const std::string& s) {
  std::vector<std::string> out;
  std::stringstream ss(s);
  std::string item;
  while (std::getline(ss, item, ',')) {
    item.erase(0, item.find_first_not_of(' '));
    item.erase(item.find_last_not_of(' ') + 1);
    if (!item.empty()) out.push_back(item);
  }
  return out;
}

nlohmann::json stats_json(const calib::ResidualStats& s) {
  nlohmann::json j = nlohmann::json::object();
  for (const auto& [g, v] : s.rms) j[g] = {{"rms", v}, {"max", s.max.at(g)}, {"count", s.count.at(g)}};
  return j;
}

std::string stats_line(const calib::ResidualStats& b, const calib::ResidualStats& a) {
  std::string out;
  for (const auto& [g, v] : b.rms)
    out += fmt::format("  {:<10} RMS {:.6f} -> {:.6f}   max {:.6f} -> {:.6f}\n", g, v,
                       a.rms.count(g) ? a.rms.at(g) : NAN, b.max.at(g), a.max.count(g) ? a.max.at(g) : NAN);
  return out;
}

/// Per-pose residual norm of every channel group, before and after, as a bar chart.
void write_svg(const std::string& dir, const calib::Model& m, const calib::Dataset& d, const std::vector<double>& p0,
               const std::vector<double>& p1, const calib::Identifiability& id) {
  fs::create_directories(dir);
  const std::size_t nch = 9 + m.links().size();
  std::vector<double> before, after;
  auto norm_res = [&](const std::vector<double>& p, std::vector<double>& out) {
    auto s = m.make_scratch();
    std::vector<double> pr(nch);
    for (const auto& pose : d.poses) {
      m.predict_channels(pose.q.data(), p.data(), pr.data(), s.get());
      double r2 = 0;
      for (std::size_t c = 0; c < nch; ++c)
        if (!std::isnan(pose.meas[c])) r2 += (pose.meas[c] - pr[c]) * (pose.meas[c] - pr[c]);
      out.push_back(std::sqrt(r2) * 1000.0);  // um
    }
  };
  norm_res(p0, before);
  norm_res(p1, after);
  auto chart = [&](const std::string& file, const std::string& title, const std::vector<double>& v,
                   const std::string& colour) {
    const double W = 800, H = 300, L = 60, B = 40;
    const double vmax = std::max(1e-12, *std::max_element(v.begin(), v.end()));
    std::string s = fmt::format(
        "<svg xmlns='http://www.w3.org/2000/svg' width='{}' height='{}' font-family='sans-serif' font-size='12'>\n"
        "<text x='{}' y='16'>{}</text>\n",
        W, H, L, title);
    const double bw = (W - L - 10) / static_cast<double>(std::max<std::size_t>(v.size(), 1));
    for (std::size_t i = 0; i < v.size(); ++i) {
      const double h = (H - B - 30) * v[i] / vmax;
      s += fmt::format("<rect x='{:.1f}' y='{:.1f}' width='{:.1f}' height='{:.1f}' fill='{}'/>\n", L + i * bw,
                       H - B - h, std::max(bw - 1, 0.5), h, colour);
    }
    s += fmt::format("<line x1='{}' y1='{}' x2='{}' y2='{}' stroke='black'/>\n", L, H - B, W - 10, H - B);
    s += fmt::format("<text x='5' y='{}'>{:.3g}</text><text x='5' y='{}'>0</text>\n", 35, vmax, H - B);
    s += fmt::format("<text x='{}' y='{}'>pose (file order)</text></svg>\n", W / 2, H - 10);
    write_file_atomically(dir + "/" + file, [&](std::ostream& o) { o << s; });
  };
  chart("residuals_before.svg", "|residual| per pose before calibration (nominal), um", before, "#c0392b");
  chart("residuals_after.svg", "|residual| per pose after calibration, um", after, "#2471a3");
  std::vector<double> logsv;
  for (double s : id.singular_values) logsv.push_back(std::log10(std::max(s, 1e-20)) + 20);
  chart("singular_values.svg", "scaled-Jacobian singular values (log10 + 20)", logsv, "#7d3c98");
}

int run_design(const CalibArgs& a, calib::Model& model, nlohmann::json& js) {
  const std::vector<std::string> ch = a.channels.empty()
                                          ? (model.kind() == "pcmm"    ? std::vector<std::string>{"len"}
                                             : model.kind() == "xmini" ? std::vector<std::string>{"tip"}
                                                                       : std::vector<std::string>{"ptip"})
                                          : split_list(a.channels);
  const auto cand = model.random_poses(static_cast<std::size_t>(a.candidates), a.seed);
  calib::Sigmas sig;
  const calib::Dataset all = calib::simulate(model, model.nominal(), cand, ch, sig, a.seed);
  calib::Options o;
  if (!a.free.empty()) o.free = model.select(split_list(a.free));
  const calib::Identifiability id = calib::analyse(model, all, model.nominal(), o);
  const std::size_t N = static_cast<std::size_t>(a.design);
  const std::vector<std::size_t> chosen = calib::select_poses(model, cand, ch, id.identifiable, N, a.o3);
  std::vector<std::vector<double>> dposes, rposes;
  for (std::size_t i : chosen) dposes.push_back(cand[i]);
  rposes = model.random_poses(N, a.seed + 7919);
  // Compare: conditioning and the parameter errors of a simulated calibration (same truth, same noise).
  std::mt19937_64 rng(a.seed + 17);
  std::uniform_real_distribution<double> u(-0.05, 0.05);
  std::vector<double> truth = model.nominal();
  for (std::size_t i : id.identifiable) truth[i] += u(rng);
  calib::Options fo;
  fo.free = id.identifiable;
  fo.rank_tolerance = 0;  // keep every identifiable parameter free, however weak
  auto evaluate = [&](const std::vector<std::vector<double>>& poses, const char* label) {
    const calib::Dataset d = calib::simulate(model, truth, poses, ch, sig, a.seed + 3);
    const calib::Identifiability idd = calib::analyse(model, d, model.nominal(), fo);
    double err2 = 0, sd2 = 0;
    int k = 0;
    nlohmann::json r = {
        {"poses", poses.size()}, {"condition_number", idd.condition_number}, {"O1", idd.O1}, {"O3", idd.O3}};
    try {
      const calib::Result res = calib::calibrate(model, d, fo);
      for (std::size_t i : id.identifiable) {
        err2 += (res.estimate[i] - truth[i]) * (res.estimate[i] - truth[i]);
        if (std::isfinite(res.stddev[i])) sd2 += res.stddev[i] * res.stddev[i];
        ++k;
      }
      r["rms_parameter_error"] = std::sqrt(err2 / std::max(k, 1));
      r["rms_parameter_stddev"] = std::sqrt(sd2 / std::max(k, 1));
    } catch (const InputError& e) {
      r["error"] = e.what();
    }
    if (!a.json)
      std::cout << fmt::format(
          "  {:<8} {:4d} poses: condition {:.4g}, O1 {:.4g}, O3 {:.4g}, RMS parameter error {:.3g} "
          "(predicted sd {:.3g})\n",
          label, poses.size(), idd.condition_number, idd.O1, idd.O3, r.value("rms_parameter_error", NAN),
          r.value("rms_parameter_stddev", NAN));
    return r;
  };
  if (!a.json) {
    std::cout << fmt::format("design: {} of {} candidate poses, {} ({}), measuring {}\n", N, cand.size(),
                             a.o3 ? "O3 (largest smallest singular value)" : "D-optimal (largest log det)",
                             model.kind(), fmt::join(ch, ","));
    std::cout << fmt::format("  {} identifiable parameters of {} candidates (rank of all candidates)\n",
                             id.identifiable.size(), id.candidates.size());
    // The figures below are for the identifiable ones: say which are not, and why, or the design looks healthy for
    // parameters it cannot calibrate.
    for (const auto& msg : id.messages)
      std::cout << "  not identifiable from " << fmt::format("{}", fmt::join(ch, ",")) << ": " << msg << "\n";
    for (const auto& comb : id.combinations)  // (a single parameter's own null vector repeats its message)
      if (comb.find(',') < comb.find(']')) std::cout << "  only in combination: " << comb << "\n";
    if (!id.messages.empty())
      std::cout << "  the figures below are for the identifiable parameters only; the others stay nominal\n";
  }
  js["identifiability"] = {{"candidates", id.candidates.size()},
                           {"identified", id.identifiable.size()},
                           {"unidentifiable", id.messages},
                           {"null_space", id.combinations}};
  js["design"] = {{"chosen", evaluate(dposes, "designed")}, {"random", evaluate(rposes, "random")}};
  if (!a.out.empty()) {
    calib::Recording r;
    r.meta["kind"] = "static";
    r.meta["machine"] = model.file();
    r.meta["note"] = fmt::format("{} poses chosen by cscam calibrate --design", N);
    for (const auto& ax : model.axis_names()) r.columns.push_back("cmd." + ax);
    for (const auto& c : model.channel_names())
      for (const auto& w : ch)
        if (c == w || c.rfind(w + ".", 0) == 0) r.columns.push_back(c);
    r.data = Eigen::MatrixXd::Constant(static_cast<Eigen::Index>(dposes.size()),
                                       static_cast<Eigen::Index>(r.columns.size()), NAN);
    for (std::size_t k = 0; k < dposes.size(); ++k)
      for (std::size_t j = 0; j < dposes[k].size(); ++j)
        r.data(static_cast<Eigen::Index>(k), static_cast<Eigen::Index>(j)) = dposes[k][j];
    write_file_atomically(a.out, [&](std::ostream& o) { o << calib::format_recording(r); });
    if (!a.json) std::cout << "wrote the chosen poses (to be measured) to " << a.out << "\n";
  }
  if (a.json) std::cout << js.dump(2) << "\n";
  return 0;
}

int run_calibrate(const CalibArgs& a) {
  nlohmann::json js;
  std::optional<calib::Recording> rec;
  if (!a.rec.empty()) rec = calib::read_recording(a.rec);
  std::string mpath = a.machine;
  if (mpath.empty() && rec) {
    const auto it = rec->meta.find("machine");
    if (it != rec->meta.end() && !it->second.empty()) mpath = resolve_recorded_machine(a.rec, it->second);
  }
  if (mpath.empty())
    throw InputError(SourceLoc{a.rec}, "no machine: give --machine or a '# machine:' line in the recording");
  mpath = resolve_machine(mpath);
  const std::shared_ptr<calib::Model> model = calib::load_model(mpath);
  if (rec && rec->tool_length_mm()) model->set_tool_length_mm(*rec->tool_length_mm());
  if (a.tool_length >= 0) model->set_tool_length_mm(a.tool_length);
  js["machine"] = mpath;
  js["kind"] = model->kind();
  if (a.design > 0) return run_design(a, *model, js);
  if (!rec) throw InputError("calibrate: give a recording (or --design N to choose poses)");
  if (rec->kind() != "static" && !rec->kind().empty())
    throw InputError(SourceLoc{a.rec},
                     fmt::format("calibrate needs a static recording (kind: static), got '{}'", rec->kind()));

  calib::Dataset data = calib::dataset_from(*rec, *model);
  std::optional<calib::Dataset> hold;
  std::string hold_label;
  if (!a.holdout.empty()) {
    hold = calib::dataset_from(calib::read_recording(a.holdout), *model);
    hold_label = a.holdout;
  }
  calib::Options opt;
  if (!a.free.empty()) opt.free = model->select(split_list(a.free));
  opt.regularise = a.regularise;
  opt.max_iterations = a.max_iterations;
  if (a.loss == "huber")
    opt.loss = calib::Loss::Huber;
  else if (a.loss == "cauchy")
    opt.loss = calib::Loss::Cauchy;
  else if (!a.loss.empty())
    throw InputError(fmt::format("--loss: expected huber or cauchy, got '{}'", a.loss));
  // What a held-out part must leave room for: the parameters the poses can identify (fixing the rest), not every
  // candidate (26 for the parallel CMM's link lengths, of which 19 are identifiable).
  const std::size_t nfree = a.regularise ? (opt.free.empty() ? model->size() : opt.free.size())
                                         : calib::analyse(*model, data, model->nominal(), opt).identifiable.size();
  if (!hold && a.split > 0) {
    // Hold out every k-th pose if the rest still has twice as many measurements as free parameters.
    const std::size_t k = static_cast<std::size_t>(std::max(2.0, std::round(1.0 / a.split)));
    calib::Dataset fit, h;
    fit.file = h.file = data.file;
    fit.sigma = h.sigma = data.sigma;
    for (std::size_t i = 0; i < data.poses.size(); ++i) (i % k == k - 1 ? h : fit).poses.push_back(data.poses[i]);
    if (fit.measurement_count() >= 2 * nfree && !h.poses.empty()) {
      data = fit;
      hold = h;
      hold_label = fmt::format("every {}th pose of {}", k, a.rec);
    }
  }
  const calib::Result r = calib::calibrate(*model, data, opt);
  const auto& id = r.ident;
  const auto& P = model->params();

  // ---- report (text to stdout, or to stderr with --json) ----
  std::ostringstream t;
  t << fmt::format("calibrate {} ({} poses, {} measurements) on {} [{}]\n", a.rec, data.poses.size(),
                   data.measurement_count(), mpath, model->kind());
  t << fmt::format("identifiability of {} candidate parameters (column-scaled Jacobian):\n", id.candidates.size());
  t << fmt::format("  rank {} of {}; condition number {:.4g} (identified subset {:.4g})\n", id.rank,
                   id.candidates.size(), id.condition_number, id.condition_identified);
  t << fmt::format("  observability O1 {:.4g}  O2 {:.4g}  O3 {:.4g}  O4 {:.4g}\n", id.O1, id.O2, id.O3, id.O4);
  t << fmt::format("  identified subset ({}): O1 {:.4g}  O2 {:.4g}  O3 {:.4g}  O4 {:.4g}\n", id.identifiable.size(),
                   id.observability_identified[0], id.observability_identified[1], id.observability_identified[2],
                   id.observability_identified[3]);
  for (const auto& m : id.messages) t << "  - " << m << "\n";
  for (const auto& c : id.combinations) t << "  null space: " << c << "\n";
  t << fmt::format("solver: {} after {} iterations ({}); cost {:.6g} -> {:.6g}; {:.3f} s\n", r.summary.termination,
                   r.summary.iterations, r.summary.message, r.summary.initial_cost, r.summary.final_cost,
                   r.summary.time_s);
  t << fmt::format("  reduced chi^2 {:.4g} (about 1 when the recording's sigmas are right{})\n", r.chi2_reduced,
                   data.sigma.given ? "" : "; sigmas not given: defaults, standard deviations rescaled");
  t << "parameters (file units):\n";
  t << fmt::format("  {:<8} {:<10} {:>16} {:>16} {:>12} {:>11}\n", "name", "group", "nominal", "estimate", "change",
                   "std dev");
  for (std::size_t i : id.candidates) {
    const bool fixed = std::find(id.identifiable.begin(), id.identifiable.end(), i) == id.identifiable.end();
    t << fmt::format("  {:<8} {:<10} {:>16.9f} {:>16.9f} {:>+12.3e} {:>11}\n", P[i].name, P[i].group, P[i].nominal,
                     r.estimate[i], r.estimate[i] - P[i].nominal,
                     fixed && !a.regularise ? std::string("fixed") : fmt::format("{:.3e}", r.stddev[i]));
  }
  if (!r.correlations.empty()) {
    t << "correlations above 0.9:\n";
    for (const auto& [ij, rho] : r.correlations)
      t << fmt::format("  {} ~ {}: {:+.4f}\n", P[ij.first].name, P[ij.second].name, rho);
  }
  if (!r.outliers.empty()) {
    t << "outlier poses (normalised RMS residual > 3):\n";
    for (const auto& o : r.outliers) t << fmt::format("  {}:{}: {:.2f} sigma\n", a.rec, o.line, o.normalised_rms);
  }
  t << "residuals on the fitted poses (measured - predicted, before -> after):\n" << stats_line(r.before, r.after);
  calib::ResidualStats hb, ha;
  // A corrected file must predict poses it was not fitted to better than the nominal one: a channel whose held-out
  // residual rises clearly (by more than 10 % and to more than three sigmas) means the data do not pin the
  // parameters down, or hold outliers, and the file is not written.
  std::string worse;
  std::vector<calib::Result::Outlier> heldout_bad;
  if (hold) {
    hb = calib::residual_stats(*model, *hold, model->nominal());
    ha = calib::residual_stats(*model, *hold, r.estimate);
    t << fmt::format("held-out ({}, {} poses), before -> after:\n", hold_label, hold->poses.size())
      << stats_line(hb, ha);
    // Held-out poses far outside the fit's noise did not pull the fit, but a user must hear of them (a bad
    // measurement, or an effect the model lacks there): by the rule the fitted poses are judged by, and only where
    // both sets give their noise the same way (sigmas in both files, or in neither). Not on exact data, whose noise
    // is rounding.
    if (hold->sigma.given == data.sigma.given && !calib::noise_is_rounding(data, r))
      for (const auto& o : calib::heldout_outliers(*model, *hold, r.estimate, r))
        if (o.p_any < kHeldOutAlpha) heldout_bad.push_back(o);
    if (!heldout_bad.empty()) {
      t << "warning: held-out poses the corrected model does not predict within the noise (they were not fitted: "
           "a bad measurement, or an effect the model lacks there):\n";
      for (const auto& o : heldout_bad)
        t << fmt::format("  {}:{}: {:.1f} sigma\n", hold->file.empty() ? hold_label : hold->file, o.line,
                         o.normalised_rms);
    }
    for (const auto& [g, before] : hb.rms) {
      const auto it = ha.rms.find(g);
      if (it == ha.rms.end()) continue;
      const double sigma = g == "tip"    ? data.sigma.tip_mm
                           : g == "ptip" ? data.sigma.ptip_mm
                           : g == "dir"  ? data.sigma.dir
                                         : data.sigma.len_mm;
      const double width = g == "tip" || g == "ptip" || g == "dir" ? std::sqrt(3.0) : 1.0;
      if (it->second > 1.1 * before && it->second > 3.0 * sigma * width)
        worse += fmt::format("{}{} {:.6g} -> {:.6g}", worse.empty() ? "" : ", ", g, before, it->second);
    }
  } else {
    t << fmt::format(
        "not validated: no held-out poses ({} with {} measurements for {} free parameters; the fitted "
        "part needs twice as many measurements as free parameters to spare some: add poses, or give "
        "--holdout)\n",
        a.split > 0 ? "too few poses" : "--split 0", data.measurement_count(), nfree);
  }
  js["validated"] = hold.has_value();
  // Extrapolation: poses that cover a small part of the working volume fit well where they are, and the corrected
  // file can be far off elsewhere. How far it moves the measured channels from the nominal model over random poses of
  // the working volume, against how far at the measured poses, says so.
  {
    const std::size_t nch = model->channel_names().size();
    std::vector<char> measured(nch, 0);
    for (const auto& pose : data.poses)
      for (std::size_t c = 0; c < nch; ++c) measured[c] |= static_cast<char>(!std::isnan(pose.meas[c]));
    auto scratch = model->make_scratch();
    const std::vector<double> nominal = model->nominal();
    std::vector<double> a0(nch), a1(nch);
    auto moved = [&](const std::vector<double>& q) {
      model->predict_channels(q.data(), nominal.data(), a0.data(), scratch.get());
      model->predict_channels(q.data(), r.estimate.data(), a1.data(), scratch.get());
      double worst = 0;
      for (std::size_t g0 = 0; g0 < nch; g0 += g0 < 9 ? 3 : 1) {
        if (g0 >= 3 && g0 < 6) continue;  // directions: unitless, judged through the tip
        double d2 = 0;
        for (std::size_t c = g0; c < g0 + (g0 < 9 ? 3 : 1); ++c)
          if (measured[c]) d2 += (a1[c] - a0[c]) * (a1[c] - a0[c]);
        worst = std::max(worst, std::sqrt(d2));
      }
      return worst;
    };
    double at_poses = 0, in_volume = 0;
    for (const auto& pose : data.poses) at_poses = std::max(at_poses, moved(pose.q));
    for (const auto& q : model->random_poses(200, a.seed + 1)) in_volume = std::max(in_volume, moved(q));
    const double floor_mm = 3.0 * std::max(data.sigma.tip_mm, data.sigma.ptip_mm);
    js["extrapolation"] = {{"max_change_at_poses_mm", at_poses}, {"max_change_in_volume_mm", in_volume}};
    if (in_volume > 5.0 * at_poses + floor_mm)
      t << fmt::format(
          "warning: the corrected model moves the tip by up to {:.4g} mm from the nominal one over the "
          "working volume, but by at most {:.4g} mm at the measured poses: the poses cover too little of "
          "the volume to trust the corrected file away from them (spread them: --design)\n",
          in_volume, at_poses);
  }
  // The same question asked of the uncertainty: the parameters' covariance carried to the tip at the measured poses and
  // at random poses of the working volume. Poses bunched in a small region pin down only the combinations that matter
  // there; elsewhere the corrected file can be off by far more than its fit says (0.09 mm RMS on the XMINI from poses
  // in a 15 mm slab), although it moves the tip no further there than at the poses.
  if (r.covariance.size() > 0 && !id.identifiable.empty()) {
    const std::size_t nch = model->channel_names().size();
    std::vector<char> measured(nch, 0);
    for (const auto& pose : data.poses)
      for (std::size_t c = 0; c < nch; ++c) measured[c] |= static_cast<char>(!std::isnan(pose.meas[c]));
    auto scratch = model->make_scratch();
    const auto& ids = id.identifiable;
    Eigen::MatrixXd S(static_cast<Eigen::Index>(ids.size()), static_cast<Eigen::Index>(ids.size()));
    for (std::size_t i = 0; i < ids.size(); ++i)
      for (std::size_t j = 0; j < ids.size(); ++j)
        S(static_cast<Eigen::Index>(i), static_cast<Eigen::Index>(j)) =
            r.covariance(static_cast<Eigen::Index>(ids[i]), static_cast<Eigen::Index>(ids[j]));
    std::vector<double> pp = r.estimate, up(nch), dn(nch);
    // The largest standard deviation of a measured position (tip, ptip: as a vector; a link length) at pose q.
    auto sd_at = [&](const std::vector<double>& q) {
      Eigen::MatrixXd J = Eigen::MatrixXd::Zero(static_cast<Eigen::Index>(nch), static_cast<Eigen::Index>(ids.size()));
      for (std::size_t j = 0; j < ids.size(); ++j) {
        const double h = 1e-6 * std::max(1.0, std::abs(pp[ids[j]]));
        const double keep = pp[ids[j]];
        pp[ids[j]] = keep + h;
        model->predict_channels(q.data(), pp.data(), up.data(), scratch.get());
        pp[ids[j]] = keep - h;
        model->predict_channels(q.data(), pp.data(), dn.data(), scratch.get());
        pp[ids[j]] = keep;
        for (std::size_t c = 0; c < nch; ++c)
          J(static_cast<Eigen::Index>(c), static_cast<Eigen::Index>(j)) = (up[c] - dn[c]) / (2 * h);
      }
      const Eigen::VectorXd var = (J * S * J.transpose()).diagonal();
      double worst = 0;
      for (std::size_t g0 = 0; g0 < nch; g0 += g0 < 9 ? 3 : 1) {
        if (g0 >= 3 && g0 < 6) continue;  // directions: judged through the tip
        double v = 0;
        for (std::size_t c = g0; c < g0 + (g0 < 9 ? 3 : 1); ++c)
          if (measured[c] && std::isfinite(var(static_cast<Eigen::Index>(c)))) v += var(static_cast<Eigen::Index>(c));
        worst = std::max(worst, std::sqrt(std::max(0.0, v)));
      }
      return worst;
    };
    double sd_poses = 0, sd_volume = 0;
    for (const auto& pose : data.poses) sd_poses = std::max(sd_poses, sd_at(pose.q));
    for (const auto& q : model->random_poses(200, a.seed + 2)) sd_volume = std::max(sd_volume, sd_at(q));
    const double noise = std::max({data.sigma.tip_mm, data.sigma.ptip_mm, data.sigma.len_mm});
    js["extrapolation"]["max_stddev_at_poses_mm"] = sd_poses;
    js["extrapolation"]["max_stddev_in_volume_mm"] = sd_volume;
    if (sd_volume > 5.0 * sd_poses && sd_volume > 3.0 * noise)
      t << fmt::format(
          "warning: the corrected model is uncertain by up to {:.4g} mm (one standard deviation) at random poses of "
          "the "
          "working volume, against {:.4g} mm at the measured poses: they cover too little of the volume to trust the "
          "corrected file away from them (spread them: --design)\n",
          sd_volume, sd_poses);
  }
  if (data.sigma.given && r.chi2_reduced > 100.0)
    t << fmt::format(
        "warning: reduced chi^2 {:.3g}: the model with these free parameters does not explain the "
        "measurements (other parameters are off too, or the sigmas are far too small)\n",
        r.chi2_reduced);

  js["recording"] = a.rec;
  js["poses"] = data.poses.size();
  js["measurements"] = data.measurement_count();
  js["identifiability"] = {{"candidates", id.candidates.size()},
                           {"rank", id.rank},
                           {"singular_values", id.singular_values},
                           {"condition_number", id.condition_number},
                           {"condition_identified", id.condition_identified},
                           {"O1", id.O1},
                           {"O2", id.O2},
                           {"O3", id.O3},
                           {"O4", id.O4},
                           {"identified", id.identifiable.size()},
                           {"observability_identified", id.observability_identified},
                           {"unidentifiable", id.messages},
                           {"null_space", id.combinations}};
  js["solver"] = {{"converged", r.summary.converged},
                  {"termination", r.summary.termination},
                  {"message", r.summary.message},
                  {"iterations", r.summary.iterations},
                  {"initial_cost", r.summary.initial_cost},
                  {"final_cost", r.summary.final_cost},
                  {"time_s", r.summary.time_s},
                  {"cost_history", r.summary.cost_history}};
  nlohmann::json params = nlohmann::json::array();
  for (std::size_t i : id.candidates) {
    const bool fixed = std::find(id.identifiable.begin(), id.identifiable.end(), i) == id.identifiable.end();
    params.push_back({{"name", P[i].name},
                      {"group", P[i].group},
                      {"unit", P[i].unit},
                      {"nominal", P[i].nominal},
                      {"estimate", r.estimate[i]},
                      {"change", r.estimate[i] - P[i].nominal},
                      {"identified", !fixed},
                      {"stddev", std::isfinite(r.stddev[i]) ? nlohmann::json(r.stddev[i]) : nlohmann::json(nullptr)}});
  }
  js["parameters"] = params;
  nlohmann::json corr = nlohmann::json::array();
  for (const auto& [ij, rho] : r.correlations)
    corr.push_back({{"a", P[ij.first].name}, {"b", P[ij.second].name}, {"rho", rho}});
  js["correlations"] = corr;
  nlohmann::json outl = nlohmann::json::array();
  for (const auto& o : r.outliers) outl.push_back({{"line", o.line}, {"normalised_rms", o.normalised_rms}});
  js["outliers"] = outl;
  js["chi2_reduced"] = r.chi2_reduced;
  js["fit"] = {{"before", stats_json(r.before)}, {"after", stats_json(r.after)}};
  if (hold) {
    nlohmann::json hout = nlohmann::json::array();
    for (const auto& o : heldout_bad) hout.push_back({{"line", o.line}, {"normalised_rms", o.normalised_rms}});
    js["heldout"] = {{"source", hold_label}, {"before", stats_json(hb)}, {"after", stats_json(ha)}, {"outliers", hout}};
  }
  // The `geometric` finding in the vocabulary of spec/recording.md.
  {
    nlohmann::json gp = nlohmann::json::object();
    std::string target;
    for (std::size_t i : id.identifiable) {
      const double dv = r.estimate[i] - P[i].nominal;
      if (std::isfinite(r.stddev[i]) && std::abs(dv) <= 3 * r.stddev[i]) continue;
      gp[P[i].name + "_" + P[i].unit] = dv;
      target += (target.empty() ? "" : ",") + P[i].name;
    }
    js["finding"] = {{"effect", "geometric"}, {"target", target}, {"parameters", gp}};
  }

  // Whether the fit may become a machine file: residuals that the noise explains, and a change larger than the noise
  // would make on a perfect machine.
  const calib::WriteCheck wc = calib::check_for_writing(*model, data, r, opt.loss);
  if (data.sigma.given) {
    t << fmt::format("fit: chi^2 {:.4g} for {:.0f} degrees of freedom, {}\n", r.chi2, r.chi2_dof,
                     calib::p_value_text(r.chi2_p));
  } else {
    // Without the recording's sigmas the chi^2 is only the default weights' (1 um): the noise is what the residuals
    // say, the standard deviations are scaled to it, and there is nothing to test the fit against.
    t << fmt::format(
        "fit: the recording gives no sigmas (sigma.tip, ...): the residuals put the noise at {:.3g} times the default "
        "weights (tip, ptip, len {:g} um; dir {:g} urad), and the standard deviations are scaled to that; the fit is "
        "not tested against a noise level\n",
        std::sqrt(std::max(0.0, r.chi2_reduced)), 1e3 * data.sigma.tip_mm, 1e6 * data.sigma.dir);
  }
  t << fmt::format("change: joint chi^2 {:.4g} ({}); largest |change| / std dev {:.2f} ({}, Bonferroni {})\n",
                   wc.mahalanobis, calib::p_value_text(wc.p_joint), wc.max_z, wc.largest,
                   calib::p_value_text(wc.p_max));
  js["fit_check"] = {{"chi2", r.chi2},
                     {"dof", r.chi2_dof},
                     {"p", r.chi2_p},
                     {"consistent", wc.consistent},
                     {"inconsistency", wc.inconsistency},
                     {"significant", wc.significant},
                     {"change_chi2", wc.mahalanobis},
                     {"change_p", wc.p_joint},
                     {"max_z", wc.max_z},
                     {"max_z_parameter", wc.largest},
                     {"max_z_p", wc.p_max}};
  int rc = 0;
  if (!r.summary.converged) {
    t << fmt::format("not converged: Ceres ended with {} ({}); no corrected file written\n", r.summary.termination,
                     r.summary.message);
    rc = 1;
  } else if (!worse.empty()) {
    t << fmt::format(
        "the corrected model predicts the held-out poses worse than the nominal one ({}): no corrected "
        "file written (the poses do not pin the parameters down, or hold outliers: see the "
        "identifiability and outlier lists above; --loss huber down-weights outliers)\n",
        worse);
    js["refused"] = worse;
    rc = 2;
  } else if (!wc.consistent && a.out.empty()) {
    t << "warning: the fit does not agree with the measurement noise: " << wc.inconsistency
      << " (--loss huber or cauchy down-weights outlier rows)\n";
  } else if (!wc.consistent && !a.write_anyway) {
    t << fmt::format(
        "the fit does not agree with the measurement noise: {}. No corrected file written (a robust loss, --loss "
        "huber or cauchy, down-weights outlier rows; fix or remove them; or give --write-anyway to write it "
        "regardless)\n",
        wc.inconsistency);
    js["refused"] = wc.inconsistency;
    rc = 2;
  } else if (!wc.significant && (a.out.empty() || !a.write_anyway)) {
    t << fmt::format(
        "no significant correction; the machine file is consistent with the recording (every change is within what "
        "the noise allows){}\n",
        a.out.empty() ? "" : ": no corrected file written (--write-anyway writes it regardless)");
    js["significant"] = false;
  } else if (!a.out.empty()) {
    if (!wc.consistent)
      t << "warning: writing although the fit does not agree with the noise (--write-anyway): " << wc.inconsistency
        << "\n";
    const std::string text = model->corrected_yaml(r.estimate);
    write_file_atomically(a.out, [&](std::ostream& o) { o << text; });
    t << "wrote " << a.out << "\n";
    js["output"] = a.out;
  }
  if (!a.svg.empty()) write_svg(a.svg, *model, data, model->nominal(), r.estimate, id);
  if (a.json) {
    std::cerr << t.str();
    std::cout << js.dump(2) << "\n";
  } else {
    std::cout << t.str();
  }
  return rc;
}

}  // namespace

std::function<int()> add_calib_commands(CLI::App& app) {
  auto a = std::make_shared<CalibArgs>();
  auto* c = app.add_subcommand("calibrate",
                               "Identify a machine's geometric parameters from a static recording and write the "
                               "corrected machine file");
  c->add_option("recording", a->rec, "static recording (spec/recording.md)");
  c->add_option("-m,--machine", a->machine, "machine file or bundled name (default: the recording's '# machine:')");
  c->add_option("-o,--output", a->out, "corrected machine file to write (with --design: the chosen poses)");
  c->add_option("--free", a->free, "candidate parameters: names and/or groups, comma-separated (default: all)");
  c->add_option("--holdout", a->holdout, "a second recording for validation (default: every 5th pose held out)");
  c->add_option("--split", a->split, "fraction of poses held out when --holdout is not given (0: none)")
      ->check(CLI::Range(0.0, 0.5));
  c->add_flag("--json", a->json, "print one JSON document on stdout (the text report goes to stderr)");
  c->add_option("--svg", a->svg, "folder for residual and singular-value charts");
  c->add_option("--loss", a->loss, "robust loss: huber or cauchy (scale 3 sigma)");
  c->add_flag("--write-anyway", a->write_anyway,
              "write the corrected file even when the fit disagrees with the noise (chi^2, outliers) or changes "
              "nothing significantly");
  c->add_flag("--regularise", a->regularise, "keep unidentifiable parameters free with a prior instead of fixing them");
  c->add_option("--design", a->design, "choose N poses from candidates in the working volume (D-optimal)");
  c->add_flag("--o3", a->o3, "with --design: maximise the smallest singular value instead of log det");
  c->add_option("--candidates", a->candidates, "with --design: number of random candidate poses")
      ->check(CLI::Range(10, 100000));
  c->add_option("--channels", a->channels, "with --design: measured channels, e.g. tip or ptip or len,tip");
  c->add_option("--seed", a->seed, "random seed for --design and the comparison");
  c->add_option("--max-iterations", a->max_iterations, "Levenberg-Marquardt iteration limit (default 100)")
      ->check(CLI::Range(1, 100000));
  c->add_option("--tool-length", a->tool_length, "tool length, mm (default: recording, then machine file)")
      ->check(cli::kNonNegative);
  return [a, c]() -> int {
    if (!*c) return -1;
    return run_calibrate(*a);
  };
}

}  // namespace cscam::cli
