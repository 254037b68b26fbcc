// Calibration engine: scaled-Jacobian SVD identifiability, Ceres solve, covariance, validation,
// pose selection.
#include "cscam/calib/calibrate.hpp"

#include <ceres/ceres.h>
#include <fmt/format.h>

#include <Eigen/QR>
#include <Eigen/SVD>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <numeric>
#include <random>

#include "cscam/core/error.hpp"
#include "cscam/core/tolerances.hpp"
#include "unsupported/Eigen/SpecialFunctions"

namespace cscam::calib {

namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
/// A term of a null-space vector or a trade-off smaller than this (relative to the largest, scaled units) is
/// rounding of the SVD / QR, not part of the relation.
constexpr double kNullTermRel = 1e-6;

/// Channel group of channel index c (tip, dir, ptip, len.<link>).
std::string group_of(const Model& m, std::size_t c) {
  if (c < 3) return "tip";
  if (c < 6) return "dir";
  if (c < 9) return "ptip";
  return "len." + m.links()[c - 9];
}

double sigma_of(const Sigmas& s, std::size_t c) {
  if (c < 3) return s.tip_mm;
  if (c < 6) return s.dir;
  if (c < 9) return s.ptip_mm;
  return s.len_mm;
}

/// Per pose of d under the parameters p: the RMS and the sum of squares of its residuals in sigmas, and its degrees of
/// freedom (a unit direction has 2, not 3).
void normalised_pose_residuals(const Model& model, const Dataset& d, const std::vector<double>& p,
                               std::vector<double>& pose_rms, std::vector<double>& pose_chi2,
                               std::vector<double>& pose_dof) {
  const std::size_t nch = 9 + model.links().size();
  std::vector<double> out(nch);
  auto scratch = model.make_scratch();
  pose_rms.assign(d.poses.size(), 0.0);
  pose_chi2.assign(d.poses.size(), 0.0);
  pose_dof.assign(d.poses.size(), 0.0);
  for (std::size_t k = 0; k < d.poses.size(); ++k) {
    const auto& pose = d.poses[k];
    model.predict_channels(pose.q.data(), p.data(), out.data(), scratch.get());
    double s2 = 0;
    int cnt = 0;
    bool dir = false;
    for (std::size_t c = 0; c < nch; ++c)
      if (!std::isnan(pose.meas[c])) {
        const double r = (pose.meas[c] - out[c]) / sigma_of(d.sigma, c);
        s2 += r * r;
        ++cnt;
        dir = dir || (c >= 3 && c < 6);
      }
    pose_rms[k] = cnt ? std::sqrt(s2 / cnt) : 0.0;
    pose_chi2[k] = s2;
    pose_dof[k] = cnt - (dir ? 1 : 0);
  }
}

/// Residuals of one pose: (measured - predicted) / sigma for every measured channel.
struct PoseResidual {
  const Model* model;
  const PoseData* pose;
  std::vector<std::size_t> idx;
  std::vector<double> w;
  std::size_t nch;
  mutable std::unique_ptr<Scratch> scratch;

  PoseResidual(const Model& m, const PoseData& p, const Sigmas& s)
      : model(&m), pose(&p), nch(9 + m.links().size()), scratch(m.make_scratch()) {
    for (std::size_t c = 0; c < nch; ++c)
      if (!std::isnan(p.meas[c])) {
        idx.push_back(c);
        w.push_back(1.0 / sigma_of(s, c));
      }
  }

  template <typename T>
  bool operator()(T const* const* params, T* res) const {
    std::vector<T> out(nch);
    model->predict_channels(pose->q.data(), params[0], out.data(), scratch.get());
    for (std::size_t k = 0; k < idx.size(); ++k) {
      res[k] = (T(pose->meas[idx[k]]) - out[idx[k]]) * w[k];
      using std::isfinite;
      if (!isfinite(res[k])) return false;
    }
    return true;
  }
};

using CostFn = ceres::DynamicAutoDiffCostFunction<PoseResidual, kJetStride>;

CostFn* make_cost(const Model& m, const PoseData& p, const Sigmas& s, std::size_t n, std::size_t* nres = nullptr) {
  auto* f = new PoseResidual(m, p, s);
  auto* c = new CostFn(f);
  c->AddParameterBlock(static_cast<int>(n));
  c->SetNumResiduals(static_cast<int>(f->idx.size()));
  if (nres) *nres = f->idx.size();
  return c;
}

/// Prior pulling parameter i to its nominal value.
struct Prior {
  std::size_t i;
  double nominal, inv_sigma;
  template <typename T>
  bool operator()(T const* const* p, T* r) const {
    r[0] = (p[0][i] - T(nominal)) * inv_sigma;
    return true;
  }
};

/// The scaled Jacobian rows of every pose for one candidate set of channels.
Eigen::MatrixXd stacked_jacobian(const Model& model, const Dataset& d, const std::vector<double>& p,
                                 std::vector<int>* pose_of_row) {
  const std::size_t n = model.size();
  std::vector<Eigen::MatrixXd> blocks;
  Eigen::Index rows = 0;
  for (std::size_t k = 0; k < d.poses.size(); ++k) {
    std::size_t nr = 0;
    std::unique_ptr<CostFn> c(make_cost(model, d.poses[k], d.sigma, n, &nr));
    if (nr == 0) continue;
    Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> J(static_cast<Eigen::Index>(nr),
                                                                             static_cast<Eigen::Index>(n));
    Eigen::VectorXd r(static_cast<Eigen::Index>(nr));
    const double* pp = p.data();
    double* jj = J.data();
    if (!c->Evaluate(&pp, r.data(), &jj))
      throw InputError(SourceLoc{d.file, d.poses[k].line, 0},
                       "the model cannot be evaluated at this pose (the mechanism does not assemble)");
    blocks.emplace_back(J);
    rows += J.rows();
    if (pose_of_row)
      for (std::size_t i = 0; i < nr; ++i) pose_of_row->push_back(static_cast<int>(k));
  }
  Eigen::MatrixXd out(rows, static_cast<Eigen::Index>(n));
  Eigen::Index r0 = 0;
  for (const auto& b : blocks) {
    out.middleRows(r0, b.rows()) = b;
    r0 += b.rows();
  }
  return out;
}

}  // namespace

std::size_t Dataset::measurement_count() const {
  std::size_t m = 0;
  for (const auto& p : poses) {
    for (std::size_t c = 0; c < p.meas.size(); ++c)
      if (!std::isnan(p.meas[c]) && (c < 3 || c >= 6)) ++m;
    bool dir = false;
    for (std::size_t c = 3; c < 6 && c < p.meas.size(); ++c) dir = dir || !std::isnan(p.meas[c]);
    if (dir) m += 2;
  }
  return m;
}

Dataset dataset_from(const Recording& rec, const Model& model) {
  check_axes(rec, model.axis_names(), model.links());
  Dataset d;
  d.file = rec.file;
  auto meta = [&](const char* key, double& v) {
    if (const auto x = rec.meta_number(key)) {
      v = *x;
      d.sigma.given = true;
    }
  };
  // A sigma for a channel family the calibration does not know (sigma.tpi) would be ignored: an error at its line.
  for (const auto& [k, v] : rec.meta)
    if (k.rfind("sigma.", 0) == 0 && k != "sigma.tip" && k != "sigma.ptip" && k != "sigma.dir" && k != "sigma.len")
      throw InputError(rec.meta_loc(k),
                       fmt::format("metadata '{}': unknown sigma (expected sigma.tip, sigma.ptip, sigma.dir or "
                                   "sigma.len)",
                                   k));
  meta("sigma.tip", d.sigma.tip_mm);
  meta("sigma.ptip", d.sigma.ptip_mm);
  meta("sigma.dir", d.sigma.dir);
  meta("sigma.len", d.sigma.len_mm);
  const std::vector<std::string> ch = model.channel_names();
  std::vector<int> col(ch.size());
  bool any = false;
  for (std::size_t c = 0; c < ch.size(); ++c) {
    col[c] = rec.column(ch[c]);
    any = any || col[c] >= 0;
  }
  if (!any) {
    std::string list;
    for (const auto& c : ch) list += (list.empty() ? "" : ", ") + c;
    throw InputError(SourceLoc{rec.file, rec.header_line, 0},
                     fmt::format("no measured channel for a {} machine (expected some of: {})", model.kind(), list));
  }
  for (Eigen::Index r = 0; r < rec.rows(); ++r) {
    PoseData p;
    p.line = rec.line_of_row[static_cast<std::size_t>(r)];
    for (const auto& a : model.axis_names()) p.q.push_back(rec.data(r, rec.column("cmd." + a)));
    p.meas.assign(ch.size(), kNaN);
    for (std::size_t c = 0; c < ch.size(); ++c)
      if (col[c] >= 0) p.meas[c] = rec.data(r, col[c]);
    d.poses.push_back(std::move(p));
  }
  if (d.measurement_count() == 0)
    throw InputError(SourceLoc{rec.file, rec.header_line, 0},
                     rec.rows() == 0 ? std::string("no pose rows: nothing to calibrate from")
                                     : fmt::format("every measured cell of the {} pose rows is empty: nothing to "
                                                   "calibrate from",
                                                   rec.rows()));
  return d;
}

Dataset simulate(const Model& model, const std::vector<double>& truth, const std::vector<std::vector<double>>& poses,
                 const std::vector<std::string>& channels, const Sigmas& sigma, std::uint64_t seed) {
  Dataset d;
  d.file = "simulated";
  d.sigma = sigma;
  d.sigma.given = true;
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> g(0.0, 1.0);
  const std::vector<std::string> names = model.channel_names();
  std::vector<bool> use(names.size(), false);
  for (const auto& c : channels) {
    bool hit = false;
    for (std::size_t i = 0; i < names.size(); ++i)
      if (names[i] == c || names[i].rfind(c + ".", 0) == 0) use[i] = hit = true;
    if (!hit) throw InputError(fmt::format("simulate: unknown channel '{}'", c));
  }
  auto scratch = model.make_scratch();
  std::vector<double> out(names.size());
  for (const auto& q : poses) {
    PoseData p;
    p.q = q;
    p.meas.assign(names.size(), kNaN);
    model.predict_channels(q.data(), truth.data(), out.data(), scratch.get());
    for (std::size_t i = 0; i < names.size(); ++i)
      if (use[i]) p.meas[i] = out[i] + sigma_of(sigma, i) * g(rng);
    if (use[3]) {  // a measured direction stays a unit vector
      Eigen::Vector3d v(p.meas[3], p.meas[4], p.meas[5]);
      v.normalize();
      for (int c = 0; c < 3; ++c) p.meas[3 + static_cast<std::size_t>(c)] = v[c];
    }
    d.poses.push_back(std::move(p));
  }
  return d;
}

Recording to_recording(const Model& model, const Dataset& d, const std::string& machine_file) {
  Recording r;
  r.file = d.file;
  r.meta["kind"] = "static";
  if (!machine_file.empty()) r.meta["machine"] = machine_file;
  r.meta["tool_length"] = fmt::format("{}", model.tool_length_mm());
  r.meta["sigma.tip"] = fmt::format("{}", d.sigma.tip_mm);
  r.meta["sigma.ptip"] = fmt::format("{}", d.sigma.ptip_mm);
  r.meta["sigma.dir"] = fmt::format("{}", d.sigma.dir);
  r.meta["sigma.len"] = fmt::format("{}", d.sigma.len_mm);
  const auto ch = model.channel_names();
  std::vector<std::size_t> used;
  for (std::size_t c = 0; c < ch.size(); ++c)
    for (const auto& p : d.poses)
      if (!std::isnan(p.meas[c])) {
        used.push_back(c);
        break;
      }
  for (const auto& a : model.axis_names()) r.columns.push_back("cmd." + a);
  for (std::size_t c : used) r.columns.push_back(ch[c]);
  r.data.resize(static_cast<Eigen::Index>(d.poses.size()), static_cast<Eigen::Index>(r.columns.size()));
  for (std::size_t k = 0; k < d.poses.size(); ++k) {
    const auto ki = static_cast<Eigen::Index>(k);
    for (std::size_t a = 0; a < d.poses[k].q.size(); ++a) r.data(ki, static_cast<Eigen::Index>(a)) = d.poses[k].q[a];
    for (std::size_t j = 0; j < used.size(); ++j)
      r.data(ki, static_cast<Eigen::Index>(d.poses[k].q.size() + j)) = d.poses[k].meas[used[j]];
    r.line_of_row.push_back(0);
  }
  return r;
}

ResidualStats residual_stats(const Model& model, const Dataset& d, const std::vector<double>& p) {
  ResidualStats s;
  std::map<std::string, double> sum;
  const std::size_t nch = 9 + model.links().size();
  std::vector<double> out(nch);
  auto scratch = model.make_scratch();
  for (const auto& pose : d.poses) {
    model.predict_channels(pose.q.data(), p.data(), out.data(), scratch.get());
    for (std::size_t g0 = 0; g0 < nch;) {
      const std::size_t width = g0 < 9 ? 3 : 1;
      double r2 = 0;
      bool any = false;
      for (std::size_t c = g0; c < g0 + width; ++c)
        if (!std::isnan(pose.meas[c])) {
          any = true;
          r2 += (pose.meas[c] - out[c]) * (pose.meas[c] - out[c]);
        }
      if (any) {
        const std::string g = group_of(model, g0);
        sum[g] += r2;
        s.count[g] += 1;
        s.max[g] = std::max(s.max[g], std::sqrt(r2));
      }
      g0 += width;
    }
  }
  for (const auto& [g, v] : sum) s.rms[g] = std::sqrt(v / static_cast<double>(s.count[g]));
  return s;
}

Eigen::MatrixXd jacobian(const Model& model, const Dataset& d, const std::vector<double>& p,
                         const std::vector<std::size_t>& cols) {
  const Eigen::MatrixXd J = stacked_jacobian(model, d, p, nullptr);
  Eigen::MatrixXd out(J.rows(), static_cast<Eigen::Index>(cols.size()));
  for (std::size_t j = 0; j < cols.size(); ++j)
    out.col(static_cast<Eigen::Index>(j)) = J.col(static_cast<Eigen::Index>(cols[j]));
  return out;
}

Identifiability analyse(const Model& model, const Dataset& d, const std::vector<double>& p, const Options& opt) {
  Identifiability id;
  id.candidates = opt.free;
  if (id.candidates.empty()) {
    id.candidates.resize(model.size());
    std::iota(id.candidates.begin(), id.candidates.end(), 0);
  }
  const Eigen::MatrixXd J = jacobian(model, d, p, id.candidates);
  if (J.rows() == 0) throw InputError(SourceLoc{d.file}, "no measured values: nothing to calibrate from");
  const auto m = static_cast<Eigen::Index>(id.candidates.size());
  Eigen::VectorXd norm = J.colwise().norm().transpose();
  const double maxnorm = norm.size() ? norm.maxCoeff() : 0.0;
  std::vector<std::size_t> live;  // candidate positions with an effect
  for (Eigen::Index j = 0; j < m; ++j) {
    if (norm[j] <= 1e-12 * std::max(maxnorm, 1e-300)) {
      id.fixed.push_back(id.candidates[static_cast<std::size_t>(j)]);
      id.messages.push_back(fmt::format("{} has no effect on the measured channels: fixed at nominal",
                                        model.params()[id.candidates[static_cast<std::size_t>(j)]].name));
      norm[j] = 1.0;
    } else {
      live.push_back(static_cast<std::size_t>(j));
    }
  }
  const Eigen::MatrixXd Js = J * norm.cwiseInverse().asDiagonal();
  Eigen::BDCSVD<Eigen::MatrixXd> svd(Js, Eigen::ComputeThinV);
  const Eigen::VectorXd s = svd.singularValues();
  id.singular_values.assign(s.data(), s.data() + s.size());
  const double smax = s.size() ? s[0] : 0.0, smin = s.size() ? s[s.size() - 1] : 0.0;
  id.condition_number = smin > 0 ? smax / smin : std::numeric_limits<double>::infinity();
  const double npose = static_cast<double>(std::max<std::size_t>(d.poses.size(), 1));
  double logsum = 0;
  for (Eigen::Index i = 0; i < s.size(); ++i) logsum += std::log(std::max(s[i], 1e-300));
  id.O1 = smin > 0 ? std::exp(logsum / static_cast<double>(s.size())) / std::sqrt(npose) : 0.0;
  id.O2 = smax > 0 ? smin / smax : 0.0;
  id.O3 = smin;
  id.O4 = smax > 0 ? smin * smin / smax : 0.0;
  id.rank = 0;
  for (Eigen::Index i = 0; i < s.size(); ++i)
    if (s[i] > opt.rank_tolerance * smax) ++id.rank;
  // Null space in words.
  const Eigen::MatrixXd V = svd.matrixV();
  for (Eigen::Index k = id.rank; k < s.size(); ++k) {
    const Eigen::VectorXd v = V.col(k);
    const double vmax = v.cwiseAbs().maxCoeff();
    std::vector<std::pair<double, std::size_t>> terms;
    for (Eigen::Index j = 0; j < m; ++j)
      // Every term that is not rounding: dropping the small ones (below 10 % of the largest, in scaled units) left
      // vectors that are no null direction (the PCMM's stage turn without sx, sy).
      if (std::abs(v[j]) >= kNullTermRel * vmax) terms.push_back({v[j], id.candidates[static_cast<std::size_t>(j)]});
    std::sort(terms.begin(), terms.end(), [](auto& a, auto& b) { return std::abs(a.first) > std::abs(b.first); });
    // Physical steps (file units), normalised so that the largest is 1.
    std::vector<double> phys;
    for (const auto& [val, pi] : terms) {
      const Eigen::Index j = std::find(id.candidates.begin(), id.candidates.end(), pi) - id.candidates.begin();
      phys.push_back(val / norm[j]);
    }
    double pmax = 0;
    for (double x : phys) pmax = std::abs(x) > std::abs(pmax) ? x : pmax;
    std::string t;
    for (std::size_t i = 0; i < terms.size(); ++i)
      t += fmt::format("{}{:+.3g} {} {}", i == 0 ? "" : ", ", phys[i] / pmax, model.params()[terms[i].second].unit,
                       model.params()[terms[i].second].name);
    id.combinations.push_back(
        fmt::format("[{}] move together: the data see no change along this direction "
                    "(scaled singular value {:.1e} of {:.1e})",
                    t, s[k], smax));
  }
  // Which parameters to fix: greedily in candidate order (the model lists the parameters a user cares
  // about first, e.g. rotary-axis location errors before part origin and gauge point), keep a column
  // when it adds a direction the kept ones do not span; the rest are fixed. Frame conventions (ParamInfo::gauge) go
  // last, so that they are the ones fixed when the data cannot see them.
  Eigen::MatrixXd Jl(Js.rows(), static_cast<Eigen::Index>(live.size()));
  for (std::size_t j = 0; j < live.size(); ++j)
    Jl.col(static_cast<Eigen::Index>(j)) = Js.col(static_cast<Eigen::Index>(live[j]));
  std::vector<Eigen::Index> keep, drop, order;
  for (int pass = 0; pass < 2; ++pass)
    for (Eigen::Index j = 0; j < Jl.cols(); ++j)
      if (model.params()[id.candidates[live[static_cast<std::size_t>(j)]]].gauge == (pass == 1)) order.push_back(j);
  {
    Eigen::MatrixXd Q(Jl.rows(), 0);
    const double thr = std::max(opt.rank_tolerance * smax, 1e-12);
    for (const Eigen::Index j : order) {
      Eigen::VectorXd v = Jl.col(j);
      for (int pass = 0; pass < 2; ++pass) v -= Q * (Q.transpose() * v);  // re-orthogonalised Gram-Schmidt
      if (v.norm() > thr && static_cast<int>(keep.size()) < id.rank) {
        Q.conservativeResize(Eigen::NoChange, Q.cols() + 1);
        Q.col(Q.cols() - 1) = v.normalized();
        keep.push_back(j);
      } else {
        drop.push_back(j);
      }
    }
  }
  std::sort(keep.begin(), keep.end());
  std::sort(drop.begin(), drop.end());
  if (keep.empty()) {
    std::string names;
    for (const std::size_t pi : id.candidates) names += (names.empty() ? "" : ", ") + model.params()[pi].name;
    throw InputError(SourceLoc{d.file},
                     fmt::format("none of the free parameters ({}) changes what these poses measure: nothing can be "
                                 "calibrated from them (free parameters that these channels see, with --free, or "
                                 "measure channels that see these)",
                                 names));
  }
  Eigen::MatrixXd K(Jl.rows(), static_cast<Eigen::Index>(keep.size()));
  for (std::size_t j = 0; j < keep.size(); ++j) K.col(static_cast<Eigen::Index>(j)) = Jl.col(keep[j]);
  Eigen::ColPivHouseholderQR<Eigen::MatrixXd> kqr(K);
  for (Eigen::Index j : keep) id.identifiable.push_back(id.candidates[live[static_cast<std::size_t>(j)]]);
  for (Eigen::Index j : drop) {
    const std::size_t pi = id.candidates[live[static_cast<std::size_t>(j)]];
    const Eigen::VectorXd c = kqr.solve(Jl.col(j));
    const double cmax = c.size() ? c.cwiseAbs().maxCoeff() : 0.0;
    std::vector<std::pair<double, std::size_t>> terms;
    for (Eigen::Index k = 0; k < c.size(); ++k)
      if (std::abs(c[k]) >= kNullTermRel * cmax) terms.push_back({c[k], static_cast<std::size_t>(k)});
    std::sort(terms.begin(), terms.end(), [](auto& a, auto& b) { return std::abs(a.first) > std::abs(b.first); });
    std::string t, names;
    const double nf = norm[static_cast<Eigen::Index>(live[static_cast<std::size_t>(j)])];
    for (const auto& [coef, k] : terms) {
      const std::size_t jj = live[static_cast<std::size_t>(keep[k])];
      const double phys = coef * nf / norm[static_cast<Eigen::Index>(jj)];
      t += fmt::format("{}{:+.4g} {}", t.empty() ? "" : " ", phys, model.params()[id.candidates[jj]].name);
      names += (names.empty() ? "" : ", ") + model.params()[id.candidates[jj]].name;
    }
    id.fixed.push_back(pi);
    if (terms.empty())
      id.messages.push_back(fmt::format("{} is not determined by these data; {}", model.params()[pi].name,
                                        opt.regularise ? "regularised toward nominal" : "fixed at nominal"));
    else
      id.messages.push_back(fmt::format("{} cannot be separated from {}: +1 {} of {} looks the same as {}; {}",
                                        model.params()[pi].name, names, model.params()[pi].unit,
                                        model.params()[pi].name, t,
                                        opt.regularise ? "regularised toward nominal" : "fixed at nominal"));
  }
  // Conditioning of what remains.
  if (!keep.empty()) {
    Eigen::JacobiSVD<Eigen::MatrixXd> s2(K);
    const Eigen::VectorXd ss = s2.singularValues();
    const double a = ss[0], b = ss[ss.size() - 1];
    id.condition_identified = b > 0 ? a / b : std::numeric_limits<double>::infinity();
    double ls = 0;
    for (Eigen::Index i = 0; i < ss.size(); ++i) ls += std::log(std::max(ss[i], 1e-300));
    id.observability_identified = {std::exp(ls / static_cast<double>(ss.size())) / std::sqrt(npose),
                                   a > 0 ? b / a : 0.0, b, a > 0 ? b * b / a : 0.0};
  }
  std::sort(id.identifiable.begin(), id.identifiable.end());
  return id;
}

Result calibrate(const Model& model, const Dataset& d, const Options& opt) {
  const auto t0 = std::chrono::steady_clock::now();
  const std::size_t n = model.size();
  Result res;
  std::vector<double> p = opt.start.empty() ? model.nominal() : opt.start;
  if (p.size() != n) throw InputError(fmt::format("start vector has {} values, the model {}", p.size(), n));
  Options o = opt;
  if (o.free.empty()) {
    o.free.resize(n);
    std::iota(o.free.begin(), o.free.end(), 0);
  }
  const std::size_t mcount = d.measurement_count();
  if (mcount < o.free.size())
    throw InputError(SourceLoc{d.file},
                     fmt::format("{} independent measurements for {} free parameters: at least {} are needed ({} more; "
                                 "add poses or fix parameters with --free)",
                                 mcount, o.free.size(), o.free.size(), o.free.size() - mcount));
  res.before = residual_stats(model, d, p);
  res.ident = analyse(model, d, p, o);

  ceres::Problem::Options po;
  ceres::Problem problem(po);
  ceres::LossFunction* loss = nullptr;
  for (const auto& pose : d.poses) {
    std::size_t nr = 0;
    CostFn* c = make_cost(model, pose, d.sigma, n, &nr);
    if (nr == 0) {
      delete c;
      continue;
    }
    if (o.loss == Loss::Huber) loss = new ceres::HuberLoss(o.loss_scale);
    if (o.loss == Loss::Cauchy) loss = new ceres::CauchyLoss(o.loss_scale);
    problem.AddResidualBlock(c, loss, p.data());
  }
  std::vector<int> constant;
  std::vector<bool> is_free(n, false);
  for (std::size_t i : res.ident.identifiable) is_free[i] = true;
  if (o.regularise)
    for (std::size_t i : res.ident.fixed) {
      is_free[i] = true;
      auto* c = new ceres::DynamicAutoDiffCostFunction<Prior, kJetStride>(
          new Prior{i, model.params()[i].nominal, 1.0 / o.prior_sigma});
      c->AddParameterBlock(static_cast<int>(n));
      c->SetNumResiduals(1);
      problem.AddResidualBlock(c, nullptr, p.data());
    }
  for (std::size_t i = 0; i < n; ++i)
    if (!is_free[i]) constant.push_back(static_cast<int>(i));
  if (static_cast<std::size_t>(std::count(is_free.begin(), is_free.end(), true)) == 0) {
    throw InputError(SourceLoc{d.file}, "no parameter is identifiable from these data (every candidate was fixed)");
  }
  if (!constant.empty()) problem.SetManifold(p.data(), new ceres::SubsetManifold(static_cast<int>(n), constant));

  struct History : ceres::IterationCallback {
    std::vector<double>* p;
    std::vector<double> last;
    SolverSummary* s;
    ceres::CallbackReturnType operator()(const ceres::IterationSummary& it) override {
      s->cost_history.push_back(it.cost);
      double step = 0;
      for (std::size_t i = 0; i < p->size(); ++i) step = std::max(step, std::abs((*p)[i] - last[i]));
      s->step_history.push_back(step);
      last = *p;
      // Exact (noise-free) data: once the cost sits at the floating-point floor, relative tolerances
      // can no longer be met; that is convergence, not failure.
      if (s->cost_history.size() > 1 && it.cost <= 1e-24 * s->cost_history.front())
        return ceres::SOLVER_TERMINATE_SUCCESSFULLY;
      return ceres::SOLVER_CONTINUE;
    }
  } hist;
  hist.p = &p;
  hist.last = p;
  hist.s = &res.summary;
  ceres::Solver::Options so;
  so.linear_solver_type = ceres::DENSE_QR;
  so.max_num_iterations = o.max_iterations;
  so.function_tolerance = o.function_tolerance;
  so.parameter_tolerance = o.parameter_tolerance;
  so.gradient_tolerance = o.gradient_tolerance;
  so.num_threads = 1;
  so.logging_type = ceres::SILENT;
  so.update_state_every_iteration = true;
  so.callbacks.push_back(&hist);
  ceres::Solver::Summary summary;
  ceres::Solve(so, &problem, &summary);
  res.summary.termination = ceres::TerminationTypeToString(summary.termination_type);
  res.summary.message = summary.message;
  res.summary.iterations = static_cast<int>(summary.iterations.size()) - 1;
  res.summary.initial_cost = summary.initial_cost;
  res.summary.final_cost = summary.final_cost;
  res.summary.converged =
      summary.termination_type == ceres::CONVERGENCE || summary.termination_type == ceres::USER_SUCCESS;
  res.estimate = p;
  res.after = residual_stats(model, d, p);
  const std::size_t nfree = res.ident.identifiable.size();
  res.chi2_reduced = mcount > nfree ? 2.0 * summary.final_cost / static_cast<double>(mcount - nfree) : kNaN;

  // Covariance (Ceres, dense SVD: the pseudo-inverse where the information matrix is singular).
  res.stddev.assign(n, kNaN);
  if (o.covariance && res.summary.converged) {
    ceres::Covariance::Options co;
    co.algorithm_type = ceres::DENSE_SVD;
    co.null_space_rank = -1;
    co.min_reciprocal_condition_number = 1e-14;
    co.num_threads = 1;
    ceres::Covariance cov(co);
    std::vector<std::pair<const double*, const double*>> blocks{{p.data(), p.data()}};
    if (cov.Compute(blocks, &problem)) {
      Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> C(static_cast<Eigen::Index>(n),
                                                                               static_cast<Eigen::Index>(n));
      cov.GetCovarianceBlock(p.data(), p.data(), C.data());
      const double scale = d.sigma.given ? 1.0 : (std::isfinite(res.chi2_reduced) ? res.chi2_reduced : 1.0);
      C *= scale;
      res.covariance = C;
      for (std::size_t i = 0; i < n; ++i)
        if (is_free[i])
          res.stddev[i] = std::sqrt(std::max(0.0, C(static_cast<Eigen::Index>(i), static_cast<Eigen::Index>(i))));
      for (std::size_t a = 0; a < n; ++a)
        for (std::size_t b = a + 1; b < n; ++b) {
          if (!is_free[a] || !is_free[b]) continue;
          const auto ia = static_cast<Eigen::Index>(a), ib = static_cast<Eigen::Index>(b);
          const double den = std::sqrt(C(ia, ia) * C(ib, ib));
          if (den <= 0) continue;
          const double rho = C(ia, ib) / den;
          if (std::abs(rho) > 0.9) res.correlations.push_back({{a, b}, rho});
        }
    }
  }
  // Outlier poses: normalised RMS residual above 3 (3 sigma per channel). Without sigmas in the recording the scale
  // is the median pose's: rescaled by the reduced chi^2, gross outliers raise their own limit and hide.
  {
    std::vector<double> pose_rms, pose_chi2, pose_dof;
    normalised_pose_residuals(model, d, p, pose_rms, pose_chi2, pose_dof);
    double scale = 1.0;
    if (!d.sigma.given && !pose_rms.empty()) {
      std::vector<double> sorted = pose_rms;
      std::nth_element(sorted.begin(), sorted.begin() + static_cast<std::ptrdiff_t>(sorted.size() / 2), sorted.end());
      // The median pose RMS of k unit normals is sqrt(median chi^2_k / k), about (1 - 2/(9k))^(3/2) (Wilson-Hilferty):
      // 0.67 for one link length per pose, where 3 medians flagged 4 % of clean poses.
      std::vector<int> counts(d.poses.size());
      for (std::size_t k = 0; k < d.poses.size(); ++k)
        counts[k] = static_cast<int>(
            std::count_if(d.poses[k].meas.begin(), d.poses[k].meas.end(), [](double v) { return !std::isnan(v); }));
      std::nth_element(counts.begin(), counts.begin() + static_cast<std::ptrdiff_t>(counts.size() / 2), counts.end());
      const double kc = std::max(1, counts[counts.size() / 2]);
      const double median_rms = std::pow(1.0 - 2.0 / (9.0 * kc), 1.5);
      scale = std::max(sorted[sorted.size() / 2] / median_rms, 1e-300);
    }
    res.residual_scale = scale;
    const double npose = static_cast<double>(d.poses.size());
    std::vector<bool> out_pose(d.poses.size(), false);
    for (std::size_t k = 0; k < d.poses.size(); ++k)
      if (pose_rms[k] > 3.0 * scale) {
        const double z = pose_rms[k] / scale, nk = std::max(pose_dof[k], 1.0);
        const double p_any = std::min(1.0, npose * chi2_upper_tail(z * z * nk, nk));
        res.outliers.push_back({k, d.poses[k].line, z, p_any});
        out_pose[k] = true;
      }
    // The fit's chi^2 over the poses it trusts: a robust loss has down-weighted the outliers, so they are left out.
    double chi2 = 0, m = 0;
    for (std::size_t k = 0; k < d.poses.size(); ++k) {
      if (o.loss != Loss::None && out_pose[k]) continue;
      chi2 += pose_chi2[k];
      m += pose_dof[k];
    }
    res.chi2 = chi2;
    res.chi2_dof = std::max(0.0, m - static_cast<double>(nfree));
    res.chi2_p = res.chi2_dof > 0 ? chi2_upper_tail(chi2, res.chi2_dof) : 1.0;
  }
  res.summary.time_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return res;
}

bool noise_is_rounding(const Dataset& d, const Result& r) { return !d.sigma.given && !(r.chi2_reduced > 1e-12); }

std::vector<Result::Outlier> heldout_outliers(const Model& model, const Dataset& d, const std::vector<double>& p,
                                              const Result& r) {
  std::vector<double> pose_rms, pose_chi2, pose_dof;
  normalised_pose_residuals(model, d, p, pose_rms, pose_chi2, pose_dof);
  std::vector<Result::Outlier> out;
  const double npose = static_cast<double>(d.poses.size()), scale = r.residual_scale;
  for (std::size_t k = 0; k < d.poses.size(); ++k)
    if (pose_rms[k] > 3.0 * scale) {
      const double z = pose_rms[k] / scale, nk = std::max(pose_dof[k], 1.0);
      out.push_back({k, d.poses[k].line, z, std::min(1.0, npose * chi2_upper_tail(z * z * nk, nk))});
    }
  return out;
}

double chi2_upper_tail(double x, double dof) {
  if (!(dof > 0)) return 1.0;
  if (!(x > 0)) return 1.0;
  if (!std::isfinite(x)) return 0.0;
  return Eigen::numext::igammac(0.5 * dof, 0.5 * x);
}

std::string p_value_text(double p, int significant_digits) {
  if (!(p >= 1e-300)) return std::isnan(p) ? "p = nan" : "p < 1e-300";
  return fmt::format("p = {:.{}g}", p, significant_digits);
}

WriteCheck check_for_writing(const Model& model, const Dataset& d, const Result& r, Loss loss, double alpha_fit,
                             double alpha_change) {
  WriteCheck w;
  // Consistency with the noise. Without sigmas in the recording the noise is estimated from the residuals, so the
  // chi^2 says nothing; outliers are still judged against the median pose.
  std::vector<Result::Outlier> bad;
  if (loss == Loss::None && !noise_is_rounding(d, r))
    for (const auto& o : r.outliers)
      if (o.p_any < alpha_fit) bad.push_back(o);
  std::sort(bad.begin(), bad.end(), [](auto& a, auto& b) { return a.normalised_rms > b.normalised_rms; });
  std::string rows;
  for (std::size_t i = 0; i < bad.size() && i < 5; ++i)
    rows += fmt::format("{}{}:{} ({:.1f} sigma)", i ? ", " : "", d.file, bad[i].line, bad[i].normalised_rms);
  if (bad.size() > 5) rows += fmt::format(" and {} more", bad.size() - 5);
  if (d.sigma.given && r.chi2_p < alpha_fit) {
    w.consistent = false;
    w.inconsistency = fmt::format(
        "chi^2 {:.4g} for {:.0f} degrees of freedom ({} < {:g}): the residuals are larger than the "
        "recording's sigmas allow",
        r.chi2, r.chi2_dof, p_value_text(r.chi2_p, 2), alpha_fit);
    if (rows.empty()) {
      // Name the poses that contribute most.
      std::vector<const Result::Outlier*> all;
      for (const auto& o : r.outliers) all.push_back(&o);
      std::sort(all.begin(), all.end(), [](auto* a, auto* b) { return a->normalised_rms > b->normalised_rms; });
      for (std::size_t i = 0; i < all.size() && i < 5; ++i)
        rows += fmt::format("{}{}:{} ({:.1f} sigma)", i ? ", " : "", d.file, all[i]->line, all[i]->normalised_rms);
    }
  }
  if (!bad.empty() && w.consistent) {
    w.consistent = false;
    w.inconsistency = fmt::format("{} outlier pose(s) left at full weight", bad.size());
  }
  if (!w.consistent && !rows.empty()) w.inconsistency += "; worst rows: " + rows;
  // Significance of the change: is any of it more than the noise would move a perfect machine's parameters?
  const auto& ids = r.ident.identifiable;
  if (r.covariance.size() > 0 && !ids.empty()) {
    const auto n = static_cast<Eigen::Index>(ids.size());
    Eigen::MatrixXd C(n, n);
    Eigen::VectorXd dv(n);
    for (Eigen::Index i = 0; i < n; ++i) {
      dv[i] = r.estimate[ids[static_cast<std::size_t>(i)]] - model.params()[ids[static_cast<std::size_t>(i)]].nominal;
      for (Eigen::Index j = 0; j < n; ++j)
        C(i, j) = r.covariance(static_cast<Eigen::Index>(ids[static_cast<std::size_t>(i)]),
                               static_cast<Eigen::Index>(ids[static_cast<std::size_t>(j)]));
    }
    // Scaled to unit diagonal (mm and degrees, strongly correlated): a pseudo-inverse of the correlation matrix.
    Eigen::VectorXd sd = C.diagonal().cwiseMax(0.0).cwiseSqrt();
    bool ok = true;
    for (Eigen::Index i = 0; i < n; ++i) ok = ok && sd[i] > 0 && std::isfinite(sd[i]);
    if (ok) {
      const Eigen::VectorXd z = dv.cwiseQuotient(sd);
      const Eigen::MatrixXd R = sd.cwiseInverse().asDiagonal() * C * sd.cwiseInverse().asDiagonal();
      Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> es(R);
      const Eigen::VectorXd ev = es.eigenvalues();
      const double emax = ev.maxCoeff();
      double m2 = 0, rank = 0;
      const Eigen::VectorXd u = es.eigenvectors().transpose() * z;
      for (Eigen::Index i = 0; i < n; ++i)
        if (ev[i] > 1e-12 * emax) {
          m2 += u[i] * u[i] / ev[i];
          rank += 1;
        }
      w.mahalanobis = m2;
      w.p_joint = chi2_upper_tail(m2, rank);
      Eigen::Index imax = 0;
      w.max_z = z.cwiseAbs().maxCoeff(&imax);
      w.largest = model.params()[ids[static_cast<std::size_t>(imax)]].name;
      w.p_max = std::min(1.0, static_cast<double>(n) * chi2_upper_tail(w.max_z * w.max_z, 1.0));
      w.significant = w.p_joint < alpha_change || w.p_max < alpha_change;
    }
  }
  return w;
}

std::vector<std::size_t> select_poses(const Model& model, const std::vector<std::vector<double>>& candidates,
                                      const std::vector<std::string>& channels, const std::vector<std::size_t>& free,
                                      std::size_t n, bool o3) {
  Sigmas unit;
  const Dataset d = simulate(model, model.nominal(), candidates, channels, unit, 1);
  std::vector<int> pose_of_row;
  const Eigen::MatrixXd Jall = stacked_jacobian(model, d, model.nominal(), &pose_of_row);
  Eigen::MatrixXd J(Jall.rows(), static_cast<Eigen::Index>(free.size()));
  for (std::size_t j = 0; j < free.size(); ++j)
    J.col(static_cast<Eigen::Index>(j)) = Jall.col(static_cast<Eigen::Index>(free[j]));
  const Eigen::VectorXd norm = J.colwise().norm().transpose().cwiseMax(1e-300);
  J = J * norm.cwiseInverse().asDiagonal();
  // Rows of every candidate.
  std::vector<std::vector<Eigen::Index>> rows(candidates.size());
  for (Eigen::Index r = 0; r < J.rows(); ++r)
    rows[static_cast<std::size_t>(pose_of_row[static_cast<std::size_t>(r)])].push_back(r);
  const auto m = static_cast<Eigen::Index>(free.size());
  const double ridge = 1e-9 * static_cast<double>(candidates.size()) / static_cast<double>(std::max<std::size_t>(n, 1));
  Eigen::MatrixXd M = ridge * Eigen::MatrixXd::Identity(m, m);
  std::vector<bool> used(candidates.size(), false);
  std::vector<std::size_t> chosen;
  for (std::size_t step = 0; step < n && step < candidates.size(); ++step) {
    double best = -std::numeric_limits<double>::infinity();
    std::size_t bi = candidates.size();
    const Eigen::LLT<Eigen::MatrixXd> llt(M);
    for (std::size_t c = 0; c < candidates.size(); ++c) {
      if (used[c] || rows[c].empty()) continue;
      Eigen::MatrixXd Jc(static_cast<Eigen::Index>(rows[c].size()), m);
      for (std::size_t k = 0; k < rows[c].size(); ++k) Jc.row(static_cast<Eigen::Index>(k)) = J.row(rows[c][k]);
      double score;
      if (!o3) {
        // log det(M + Jc^T Jc) - log det M = log det(I + Jc M^-1 Jc^T)
        const Eigen::MatrixXd S = Eigen::MatrixXd::Identity(Jc.rows(), Jc.rows()) + Jc * llt.solve(Jc.transpose());
        score = std::log(S.determinant());
      } else {
        Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> es(M + Jc.transpose() * Jc, Eigen::EigenvaluesOnly);
        score = es.eigenvalues()[0];
      }
      if (score > best) {
        best = score;
        bi = c;
      }
    }
    if (bi == candidates.size()) break;
    used[bi] = true;
    chosen.push_back(bi);
    for (Eigen::Index r : rows[bi]) M += J.row(r).transpose() * J.row(r);
  }
  return chosen;
}

}  // namespace cscam::calib
