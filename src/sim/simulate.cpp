#include "cscam/sim/simulate.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <exception>
#include <random>
#include <thread>

#include "cscam/calib/model.hpp"
#include "cscam/cl/program.hpp"
#include "cscam/core/error.hpp"
#include "cscam/core/threads.hpp"
#include "cscam/core/units.hpp"
#include "cscam/nc/reader.hpp"
#include "cscam/post/post.hpp"

namespace cscam::sim {

namespace {

/// The white noise's sigma of channel group `g` (0: none).
double noise_sigma(const SimulateOptions& o, const std::string& g) {
  double s = 0;
  for (const auto& ns : o.noise)
    if (ns.group == g) s = ns.sigma;
  return s;
}

/// Noise for a group that is not recorded is a mistake on the command line, not a no-op.
void check_noise_groups(const SimulateOptions& o) {
  for (const auto& ns : o.noise)
    if (std::find(o.channels.begin(), o.channels.end(), ns.group) == o.channels.end())
      throw InputError(fmt::format("--noise {}: that channel group is not recorded (--channels)", ns.group));
}
constexpr double kRad2Deg = 180.0 / 3.14159265358979323846;

kin::Axes to_file_units(const kin::Axes& q, const machine::Machine& m) {
  kin::Axes r = q;
  for (int i = 0; i < 5; ++i)
    if (m.axes[static_cast<size_t>(i)].rotary()) r[i] *= kRad2Deg;
  return r;
}

/// Time of a move at the axes' maximum feeds (file units; max_feed is mm/min or rad/min).
double rapid_time(const kin::Axes& d, const machine::Machine& m) {
  double t = 0;
  for (int i = 0; i < 5; ++i) {
    const auto& ax = m.axes[static_cast<size_t>(i)];
    const double dist = ax.rotary() ? std::abs(d[i]) / kRad2Deg : std::abs(d[i]);
    const double f = ax.max_feed > 0 ? ax.max_feed : (ax.rotary() ? 50.0 : 5000.0);
    t = std::max(t, 60.0 * dist / f);
  }
  return t;
}

void path_length(const kin::Axes& d, const machine::Machine& m, double& lin, double& rot) {
  lin = rot = 0;
  for (int i = 0; i < 5; ++i) (m.axes[static_cast<size_t>(i)].rotary() ? rot : lin) += d[i] * d[i];
  lin = std::sqrt(lin);
  rot = std::sqrt(rot);
}

template <class F>
void parallel_for(size_t n, F&& f) {
  const size_t nt = n > 20000 ? worker_threads() : 1;
  if (nt == 1) {
    f(size_t{0}, n);
    return;
  }
  std::vector<std::thread> th;
  std::vector<std::exception_ptr> err(nt);
  for (size_t k = 0; k < nt; ++k)
    th.emplace_back([&, k] {
      try {
        f(n * k / nt, n * (k + 1) / nt);
      } catch (...) {
        err[k] = std::current_exception();
      }
    });
  for (auto& t : th) t.join();
  for (auto& e : err)
    if (e) std::rethrow_exception(e);
}
}  // namespace

std::vector<Block> blocks_from_nc(const nc::Program& prog, const machine::Machine& m) {
  std::vector<Block> out;
  if (prog.blocks.empty()) throw InputError(SourceLoc{prog.file}, "the NC program has no motion blocks");
  // Axes not yet programmed take their first programmed value (the machine is assumed to be there).
  kin::Axes first = kin::Axes::Zero();
  std::array<bool, 5> have{};
  for (const auto& b : prog.blocks)
    for (int i = 0; i < 5; ++i)
      if (!have[i] && b.known[i]) first[i] = b.axes[i], have[i] = true;
  kin::Axes prev = to_file_units(first, m);
  Block start;
  start.end = prev;
  out.push_back(start);
  for (const auto& b : prog.blocks) {
    kin::Axes q;
    for (int i = 0; i < 5; ++i) q[i] = b.known[i] ? b.axes[i] : first[i];
    q = to_file_units(q, m);
    const kin::Axes d = q - prev;
    Block blk;
    blk.end = q;
    double lin = 0, rot = 0;
    path_length(d, m, lin, rot);
    blk.length = lin > 1e-9 ? lin : rot;
    if (blk.length < 1e-12) continue;
    if (b.motion == nc::Motion::Rapid) {
      blk.duration_s = rapid_time(d, m);
    } else if (b.inverse_time) {
      if (!(b.feed > 0)) throw InputError(SourceLoc{prog.file, b.line}, "G93 block without a positive F word");
      blk.duration_s = 60.0 / b.feed;
    } else {
      if (!(b.feed > 0)) throw InputError(SourceLoc{prog.file, b.line}, "feed move without a positive F word");
      blk.duration_s = 60.0 * blk.length / b.feed;
    }
    blk.duration_s = std::max(blk.duration_s, rapid_time(d, m));  // never faster than the axes can go
    out.push_back(blk);
    prev = q;
  }
  return out;
}

std::vector<Block> blocks_from_cl(const std::string& cl_file, const machine::Machine& m, double tool_length_mm) {
  const cl::Program prog = cl::read_file(cl_file, {});
  const auto kin = m.make_kinematics(tool_length_mm);
  const auto axes = post::conventional_axes(prog, m, *kin);
  std::vector<Block> out;
  if (axes.empty()) throw InputError(SourceLoc{cl_file}, "the CL program has no motion");
  Block start;
  start.end = to_file_units(axes.front(), m);
  out.push_back(start);
  for (size_t i = 1; i < axes.size(); ++i) {
    const auto& mv = prog.moves[i];
    Block blk;
    blk.end = to_file_units(axes[i], m);
    const kin::Axes d = blk.end - out.back().end;
    double lin = 0, rot = 0;
    path_length(d, m, lin, rot);
    blk.length = lin > 1e-9 ? lin : rot;
    if (blk.length < 1e-12) continue;
    const double tip_dist = (mv.tip_in_part_mm - prog.moves[i - 1].tip_in_part_mm).norm();
    blk.duration_s = rapid_time(d, m);
    if (mv.kind == cl::MotionKind::Feed && mv.feed_mm_per_min > 0)
      blk.duration_s = std::max(blk.duration_s, 60.0 * tip_dist / mv.feed_mm_per_min);
    out.push_back(blk);
  }
  return out;
}

Trajectory profile(const std::vector<Block>& blocks, const ProfileOptions& o) {
  if (!(o.rate_hz > 0)) throw InputError("--rate must be positive");
  if (blocks.empty()) throw InputError("profile: no blocks");
  // Per block: trapezoid of the path parameter s in [0, L] with cruise speed L / duration.
  struct Seg {
    double t0, T, L, V, A, ta;
    kin::Axes a, b;
  };
  std::vector<Seg> segs;
  double t = o.dwell_s;
  for (size_t k = 1; k < blocks.size(); ++k) {
    Seg s;
    s.a = blocks[k - 1].end;
    s.b = blocks[k].end;
    s.L = blocks[k].length;
    s.A = o.accel;
    s.V = s.L / std::max(blocks[k].duration_s, 1e-9);
    if (s.V * s.V / s.A >= s.L) {  // triangular: never reaches the feed
      s.V = std::sqrt(s.L * s.A);
      s.ta = s.V / s.A;
      s.T = 2 * s.ta;
    } else {
      s.ta = s.V / s.A;
      s.T = s.L / s.V + s.ta;
    }
    s.t0 = t;
    t += s.T;
    segs.push_back(s);
  }
  const double total = t + o.dwell_s;
  Trajectory tr;
  const auto n = static_cast<size_t>(std::ceil(total * o.rate_hz - 1e-9)) + 1;  // the last sample at or after the end
  if (n > 50'000'000) throw InputError(fmt::format("the recording would have {} samples: lower --rate", n));
  tr.t.resize(n);
  tr.cmd.resize(n);
  size_t k = 0;
  for (size_t i = 0; i < n; ++i) {
    const double ti = static_cast<double>(i) / o.rate_hz;
    tr.t[i] = ti;
    if (segs.empty()) {
      tr.cmd[i] = blocks.front().end;
      continue;
    }
    while (k + 1 < segs.size() && ti >= segs[k + 1].t0) ++k;
    const Seg& s = segs[k];
    const double tau = std::clamp(ti - s.t0, 0.0, s.T);
    double pos;
    if (tau < s.ta)
      pos = 0.5 * s.A * tau * tau;
    else if (tau > s.T - s.ta)
      pos = s.L - 0.5 * s.A * (s.T - tau) * (s.T - tau);
    else
      pos = 0.5 * s.A * s.ta * s.ta + s.V * (tau - s.ta);
    const double f = s.L > 0 ? std::clamp(pos / s.L, 0.0, 1.0) : 1.0;
    tr.cmd[i] = s.a + f * (s.b - s.a);
  }
  return tr;
}

Predictor::Predictor(const machine::Machine& m, double tool_length_mm) : m_(m) {
  kin_ = m_.make_kinematics(tool_length_mm);
  if (m_.serial) {
    head_only_ = *m_.serial;
    head_only_->tool_length_mm = tool_length_mm;
    head_only_->table_chain.clear();
  }
}

void Predictor::fk(const kin::Axes& q, Eigen::Vector3d& tip, Eigen::Vector3d& ptip, Eigen::Vector3d& dir) const {
  kin::Axes r = q;
  for (int i = 0; i < 5; ++i)
    if (m_.axes[static_cast<size_t>(i)].rotary()) r[i] /= kRad2Deg;
  const kin::Posed p = kin_->forward(r);
  ptip = p.tip_mm;
  if (head_only_) {
    const kin::Posed w = kin::serial_forward(*head_only_, r);
    tip = w.tip_mm + head_only_->part_origin_home_mm;
    dir = w.axis;
  } else {
    tip = p.tip_mm;
    dir = p.axis;
  }
  if (!std::isfinite(ptip.x()))
    throw InputError(
        fmt::format("forward kinematics has no solution for the commanded axes ({:.6f}, {:.6f}, {:.6f}, "
                    "{:.6f}, {:.6f})",
                    q[0], q[1], q[2], q[3], q[4]));
}

Eigen::Matrix3d Predictor::part_from_machine(const kin::Axes& q) const {
  Eigen::Matrix3d R = Eigen::Matrix3d::Identity();
  if (!m_.serial) return R;
  // As serial_forward undoes the table chain, base outward.
  for (const int idx : m_.serial->table_chain) {
    const auto& j = m_.serial->joints[static_cast<size_t>(idx)];
    if (j.type != kin::AxisType::Rotary) continue;
    R = kin::detail::axis_angle<double>(j.direction, q[idx] / kRad2Deg + j.offset).transpose() * R;
  }
  return R;
}

void Predictor::jacobian(const kin::Axes& q, Eigen::Matrix<double, 9, 5>& J) const {
  const double h = 1e-3;
  Eigen::Vector3d t0, p0, d0, t1, p1, d1;
  for (int j = 0; j < 5; ++j) {
    kin::Axes a = q, b = q;
    a[j] -= h;
    b[j] += h;
    fk(a, t0, p0, d0);
    fk(b, t1, p1, d1);
    J.block<3, 1>(0, j) = (t1 - t0) / (2 * h);
    J.block<3, 1>(3, j) = (p1 - p0) / (2 * h);
    J.block<3, 1>(6, j) = (d1 - d0) / (2 * h);
  }
}

std::vector<double> temperature_at(const SimulateOptions::Temperature& readings, const std::vector<double>& t) {
  const auto& rt = readings.t;
  const auto& deg = readings.deg_c;
  if (rt.empty() || rt.size() != deg.size())
    throw InputError(
        fmt::format("temperature {}: no readings (or times and readings of different counts)", readings.sensor));
  std::vector<double> at(t.size());
  std::size_t k = 0;
  for (std::size_t i = 0; i < t.size(); ++i) {
    while (k + 1 < rt.size() && rt[k + 1] <= t[i]) ++k;
    if (t[i] <= rt.front() || k + 1 >= rt.size()) {
      at[i] = t[i] <= rt.front() ? deg.front() : deg.back();
      continue;
    }
    const double f = (t[i] - rt[k]) / (rt[k + 1] - rt[k]);
    at[i] = (1 - f) * deg[k] + f * deg[k + 1];
  }
  return at;
}

Recording simulate(const Trajectory& traj, const machine::Machine& m, const std::vector<const Effect*>& effects,
                   const SimulateOptions& o, const machine::Machine* truth_machine) {
  const size_t n = traj.t.size();
  const double L = o.tool_length_mm >= 0 ? o.tool_length_mm : m.default_tool_length_mm;
  const Predictor truth(truth_machine ? *truth_machine : m, L);
  std::array<bool, 5> rot{};
  for (int i = 0; i < 5; ++i) rot[i] = m.axes[static_cast<size_t>(i)].rotary();
  Context ctx = make_context(traj.t, traj.cmd, rot, 1);
  // Recorded temperatures at the samples (interpolated, held past their ends), and their rise for thermal_growth.
  std::vector<std::pair<std::string, std::vector<double>>> temps;
  for (const auto& tp : o.temperatures) {
    std::vector<double> at = temperature_at(tp, traj.t);
    std::vector<double> rise(n);
    for (size_t i = 0; i < n; ++i) rise[i] = at[i] - at.front();
    ctx.temp_rise.emplace_back(tp.sensor, std::move(rise));
    temps.emplace_back(tp.sensor, std::move(at));
  }
  for (const Effect* e : effects)
    if (e->follows_temperature() && !ctx.temperature(e->note))
      throw InputError(
          fmt::format("effect {} on {}: it follows temperature sensor '{}', which this simulation has no readings of "
                      "(give them with --temperatures FILE.csv: columns t and temp.{})",
                      e->name(), e->target, e->note, e->note.empty() ? "<sensor>" : e->note));

  std::vector<kin::Axes> actual(traj.cmd), enc(traj.cmd);
  for (const Effect* e : effects) {
    if (e->scope() != Scope::Axis) continue;
    for (size_t i = 0; i < n; ++i) {
      const double d = e->value(ctx, i, e->p.data());
      actual[i][e->axis] += d;
      if (e->enc_visible) enc[i][e->axis] += d;
    }
  }
  auto want = [&](const std::string& g) {
    return std::find(o.channels.begin(), o.channels.end(), g) != o.channels.end();
  };
  for (const auto& c : o.channels)
    if (c != "tip" && c != "ptip" && c != "enc" && c != "acc" && c != "dir")
      throw InputError(fmt::format("--channels: unknown channel group '{}' (expected tip, ptip, enc, acc, dir)", c));

  Recording rec;
  rec.set_meta("machine", o.machine_ref.empty() ? m.file : o.machine_ref);
  rec.set_meta("kind", "trajectory");
  rec.set_meta("tool_length", fmt::format("{}", L));
  if (o.spindle_rpm > 0) {
    rec.set_meta("spindle_rpm", fmt::format("{}", o.spindle_rpm));
    rec.set_meta("flutes", fmt::format("{}", o.flutes));
  }
  if (!o.note.empty()) rec.set_meta("note", o.note);
  rec.add_column("t", traj.t);
  for (int j = 0; j < 5; ++j) {
    std::vector<double> v(n);
    for (size_t i = 0; i < n; ++i) v[i] = traj.cmd[i][j];
    rec.add_column("cmd." + m.axes[static_cast<size_t>(j)].name, std::move(v));
  }
  std::vector<Eigen::Vector3d> tip(n), ptip(n), dir(n);
  // Geometric deviations: the channels come from the calibration model with the deviated parameters.
  std::shared_ptr<calib::Model> geo;
  std::vector<double> pg;
  for (const Effect* e : effects)
    if (e->scope() == Scope::Geometric) {
      if (!geo) {
        geo = calib::load_model(m.file);
        geo->set_tool_length_mm(L);
        pg = geo->nominal();
      }
      pg[geo->index(e->target)] += e->p[0];
    }
  parallel_for(n, [&](size_t a, size_t b) {
    if (geo) {
      auto scratch = geo->make_scratch();
      std::vector<double> out(9 + geo->links().size());
      for (size_t i = a; i < b; ++i) {
        geo->predict_channels(actual[i].data(), pg.data(), out.data(), scratch.get());
        tip[i] = Eigen::Vector3d(out[0], out[1], out[2]);
        dir[i] = Eigen::Vector3d(out[3], out[4], out[5]);
        ptip[i] = Eigen::Vector3d(out[6], out[7], out[8]);
        if (!std::isfinite(out[0]) || !std::isfinite(out[6]))
          throw InputError(
              fmt::format("geometric: the deviated machine has no forward-kinematics solution at t = {:.4f} s "
                          "(deviation too large?)",
                          traj.t[i]));
      }
      return;
    }
    for (size_t i = a; i < b; ++i) truth.fk(actual[i], tip[i], ptip[i], dir[i]);
  });
  // Effects on the tool point (tool.x|y|z): the tip moves in W, and ptip by the same vector turned into the part frame.
  for (const Effect* e : effects)
    if (e->scope() == Scope::Channel && e->channel.rfind("tool.", 0) == 0) {
      const int c = e->channel.back() - 'x';
      for (size_t i = 0; i < n; ++i) {
        const double d = e->value(ctx, i, e->p.data());
        tip[i][c] += d;
        ptip[i] += d * truth.part_from_machine(actual[i]).col(c);
      }
    }
  std::mt19937_64 rng(o.seed);
  auto sigma_of = [&](const std::string& g) { return noise_sigma(o, g); };
  check_noise_groups(o);
  auto add_channel = [&](const std::string& name, std::vector<double> v, double sigma) {
    for (const Effect* e : effects)
      if (e->scope() == Scope::Channel && e->channel == name)
        for (size_t i = 0; i < n; ++i) v[i] += e->value(ctx, i, e->p.data());
    if (sigma > 0) {
      std::normal_distribution<double> nd(0.0, sigma);
      for (auto& x : v) x += nd(rng);
    }
    rec.add_column(name, std::move(v));
  };
  const char* xyz[3] = {"x", "y", "z"};
  auto vec_group = [&](const std::string& g, const std::vector<Eigen::Vector3d>& src, double sigma) {
    for (int c = 0; c < 3; ++c) {
      std::vector<double> v(n);
      for (size_t i = 0; i < n; ++i) v[i] = src[i][c];
      add_channel(g + "." + xyz[c], std::move(v), sigma);
    }
  };
  if (want("enc"))
    for (int j = 0; j < 5; ++j) {
      std::vector<double> v(n);
      for (size_t i = 0; i < n; ++i) v[i] = enc[i][j];
      add_channel("enc." + m.axes[static_cast<size_t>(j)].name, std::move(v), sigma_of("enc"));
    }
  // Channel effects on the tip also move what an accelerometer sees: acc from the tip with them.
  std::vector<Eigen::Vector3d> tip_fx = tip;
  for (const Effect* e : effects)
    if (e->scope() == Scope::Channel && e->channel.rfind("tip.", 0) == 0) {
      const int c = e->channel.back() - 'x';
      for (size_t i = 0; i < n; ++i) tip_fx[i][c] += e->value(ctx, i, e->p.data());
    }
  for (auto& [sensor, deg_c] : temps) rec.add_column("temp." + sensor, std::move(deg_c));
  if (want("tip")) vec_group("tip", tip, sigma_of("tip"));
  if (want("ptip")) vec_group("ptip", ptip, sigma_of("ptip"));
  if (want("dir")) {
    // A measured tool axis is a unit vector: the noise turns it (sigma per component, about sigma rad), and the
    // result is normalised. Added per component alone, it lengthened the vector and gave it a third, radial error
    // that no instrument reports and that the calibration's chi^2 (2 degrees of freedom per direction) did not expect.
    std::vector<Eigen::Vector3d> noisy = dir;
    if (const double s = sigma_of("dir"); s > 0) {
      std::normal_distribution<double> nd(0.0, s);
      for (auto& v : noisy) {
        for (int c = 0; c < 3; ++c) v[c] += nd(rng);
        v.normalize();
      }
    }
    vec_group("dir", noisy, 0.0);
  }
  if (want("acc")) {
    std::vector<Eigen::Vector3d> acc(n, Eigen::Vector3d::Zero());
    for (size_t i = 1; i + 1 < n; ++i) {
      const double h0 = traj.t[i] - traj.t[i - 1], h1 = traj.t[i + 1] - traj.t[i];
      acc[i] = 2.0 * ((tip_fx[i + 1] - tip_fx[i]) / h1 - (tip_fx[i] - tip_fx[i - 1]) / h0) / (h0 + h1) * 1e-3;
    }
    vec_group("acc", acc, sigma_of("acc"));
  }
  return rec;
}

Recording simulate_static(const calib::Model& model, const std::vector<std::vector<double>>& poses,
                          const std::vector<std::pair<std::string, double>>& values, const SimulateOptions& o) {
  std::vector<double> p = model.nominal();
  for (const auto& [name, v] : values) p[model.index(name)] = v;
  const std::vector<std::string> names = model.channel_names();
  const auto& axes = model.axis_names();
  auto sigma_of = [&](const std::string& g) { return noise_sigma(o, g); };
  for (const auto& c : o.channels)
    if (c != "tip" && c != "ptip" && c != "dir" && c != "len")
      throw InputError(fmt::format("--channels: a static measurement records tip, ptip, dir or len, not '{}'", c));
  check_noise_groups(o);
  // Every channel of the chosen groups, predicted for every pose.
  const std::size_t n = poses.size();
  std::vector<std::vector<double>> out(names.size(), std::vector<double>(n));
  auto scratch = model.make_scratch();
  std::vector<double> row(names.size());
  for (std::size_t i = 0; i < n; ++i) {
    CSCAM_CHECK(poses[i].size() == axes.size(), "a pose has one value per axis");
    model.predict_channels(poses[i].data(), p.data(), row.data(), scratch.get());
    for (std::size_t c = 0; c < names.size(); ++c) out[c][i] = row[c];
  }
  Recording rec;
  rec.set_meta("machine", o.machine_ref.empty() ? model.file() : o.machine_ref);
  rec.set_meta("kind", "static");
  if (!o.note.empty()) rec.set_meta("note", o.note);
  for (std::size_t j = 0; j < axes.size(); ++j) {
    std::vector<double> v(n);
    for (std::size_t i = 0; i < n; ++i) v[i] = poses[i][j];
    rec.add_column("cmd." + axes[j], std::move(v));
  }
  std::mt19937_64 rng(o.seed);
  for (const auto& g : o.channels) {
    if (g == "dir" && sigma_of("dir") > 0) {
      // A measured direction is a unit vector: the noise turns it, and it is normalised (as simulate() does).
      std::normal_distribution<double> nd(0.0, sigma_of("dir"));
      const auto at = [&](const char* c) {
        return static_cast<std::size_t>(std::find(names.begin(), names.end(), std::string("dir.") + c) - names.begin());
      };
      const std::size_t cx = at("x"), cy = at("y"), cz = at("z");
      if (cz < names.size())
        for (std::size_t i = 0; i < n; ++i) {
          Eigen::Vector3d u(out[cx][i], out[cy][i], out[cz][i]);
          if (!u.allFinite()) continue;
          for (int c = 0; c < 3; ++c) u[c] += nd(rng);
          u.normalize();
          out[cx][i] = u.x(), out[cy][i] = u.y(), out[cz][i] = u.z();
        }
    }
    bool any = false;
    for (std::size_t c = 0; c < names.size(); ++c) {
      if (names[c].rfind(g + ".", 0) != 0) continue;
      std::vector<double>& v = out[c];
      // A channel the model does not measure is NaN at every pose: not recorded (len on a machine without links).
      if (std::all_of(v.begin(), v.end(), [](double x) { return std::isnan(x); })) continue;
      for (std::size_t i = 0; i < n; ++i)
        if (!std::isfinite(v[i]))
          throw InputError(fmt::format("pose {}: the {}machine has no solution there ({} is not finite)", i + 1,
                                       values.empty() ? "" : "deviated ", names[c]));
      if (const double s = sigma_of(g); s > 0 && g != "dir") {
        std::normal_distribution<double> nd(0.0, s);
        for (double& x : v) x += nd(rng);
      }
      rec.add_column(names[c], std::move(v));
      any = true;
    }
    if (!any) throw InputError(fmt::format("--channels {}: machine '{}' does not measure that group", g, model.file()));
  }
  return rec;
}

}  // namespace cscam::sim
