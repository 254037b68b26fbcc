#include "cscam/report/backlash.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "cscam/core/units.hpp"
#include "cscam/report/json.hpp"

namespace cscam::report {

namespace {

/// No NC block is cut into more samples than this (a guard against a huge block and a tiny width).
constexpr int kMaxSamplesPerBlock = 200000;

constexpr std::array<char, 3> kComponent{'x', 'y', 'z'};

}  // namespace

std::vector<double> apply_play(const std::vector<double>& x, double width) {
  if (!(width >= 0.0) || !std::isfinite(width)) throw std::invalid_argument("backlash width must be finite and >= 0");
  std::vector<double> y = x;
  if (x.empty()) return y;
  // Engaged in the direction of the first motion: the band [x + c - w/2, x + c + w/2] with its centre
  // offset c = +-w/2 puts the output exactly on the command while it keeps moving that way.
  double c = 0.0;
  for (double v : x)
    if (v != x.front()) {
      c = v > x.front() ? 0.5 * width : -0.5 * width;
      break;
    }
  for (std::size_t i = 1; i < x.size(); ++i)
    y[i] = std::clamp(y[i - 1], x[i] + c - 0.5 * width, x[i] + c + 0.5 * width);
  return y;
}

SampledPath sample_nc(const nc::Program& program, int axis, double max_axis_step, int min_samples_per_block) {
  if (axis < 0 || axis > 4) throw std::invalid_argument("sample_nc: axis index must be 0..4");
  if (!(max_axis_step > 0.0)) throw std::invalid_argument("sample_nc: max_axis_step must be positive");
  SampledPath p;
  const nc::Block* prev = nullptr;
  auto axes_of = [](const nc::Block& b) {
    kin::Axes q;
    for (int a = 0; a < 5; ++a) q[a] = b.axes[static_cast<std::size_t>(a)];
    return q;
  };
  for (const nc::Block& b : program.blocks) {
    if (!std::all_of(b.known.begin(), b.known.end(), [](bool k) { return k; })) continue;
    const kin::Axes qb = axes_of(b);
    if (prev == nullptr) {
      p.q.push_back(qb);
      p.nc_line.push_back(b.line);
      p.feed.push_back(false);
      prev = &b;
      continue;
    }
    const kin::Axes qa = axes_of(*prev);
    const double need = std::ceil(std::abs(qb[axis] - qa[axis]) / max_axis_step);
    const int n = static_cast<int>(std::clamp(need, static_cast<double>(std::max(1, min_samples_per_block)),
                                              static_cast<double>(kMaxSamplesPerBlock)));
    for (int k = 1; k <= n; ++k) {
      p.q.push_back(qa + (static_cast<double>(k) / n) * (qb - qa));
      p.nc_line.push_back(b.line);
      p.feed.push_back(b.motion != nc::Motion::Rapid);
    }
    prev = &b;
  }
  return p;
}

BacklashResult simulate_backlash(const SampledPath& path, const kin::Kinematics& kin, int axis, double width) {
  if (axis < 0 || axis > 4) throw std::invalid_argument("simulate_backlash: axis index must be 0..4");
  if (path.nc_line.size() != path.q.size() || path.feed.size() != path.q.size())
    throw std::invalid_argument("simulate_backlash: the sampled path's arrays differ in length");
  BacklashResult r;
  const kin::AxisInfo& info = kin.axes()[static_cast<std::size_t>(axis)];
  r.axis_name = info.name;
  r.rotary = info.rotary();
  r.width = width;
  std::vector<double> cmd(path.q.size());
  for (std::size_t i = 0; i < path.q.size(); ++i) cmd[i] = path.q[i][axis];
  const std::vector<double> out = apply_play(cmd, width);

  r.tip_commanded_mm.reserve(path.q.size());
  r.tip_actual_mm.reserve(path.q.size());
  for (std::size_t i = 0; i < path.q.size(); ++i) {
    kin::Axes qa = path.q[i];
    qa[axis] = out[i];
    r.tip_commanded_mm.push_back(kin.forward(path.q[i]).tip_mm);
    r.tip_actual_mm.push_back(kin.forward(qa).tip_mm);
  }
  auto deviation = [&](std::size_t i) -> Eigen::Vector3d { return r.tip_actual_mm[i] - r.tip_commanded_mm[i]; };

  // Reversals: the output moves again, against its last direction of motion. While engaged the output
  // follows the command, so the command turned where the output last moved.
  int dir = 0;
  std::size_t last_move = 0;
  for (std::size_t i = 1; i < out.size(); ++i) {
    const double d = out[i] - out[i - 1];
    if (d == 0.0) continue;
    const int s = d > 0 ? 1 : -1;
    if (dir != 0 && s != dir) {
      BacklashReversal v;
      v.begin_sample = last_move;
      v.end_sample = i;
      v.nc_line = path.nc_line[last_move];
      // While cutting: the command turns and the play is taken up inside feed blocks (a turn at a rapid's
      // end or start is taken up on the way in or out).
      v.in_feed = path.feed[last_move] && path.feed[i] && (last_move == 0 || path.feed[last_move - 1]);
      v.tip_mm = r.tip_commanded_mm[last_move];
      v.step_mm = deviation(i) - deviation(last_move);
      r.reversals.push_back(v);
    }
    dir = s;
    last_move = i;
  }

  for (std::size_t i = 0; i < path.q.size(); ++i) {
    if (!path.feed[i]) continue;
    ++r.feed_samples;
    const Eigen::Vector3d d = deviation(i).cwiseAbs();
    for (int c = 0; c < 3; ++c)
      if (d[c] > r.max_abs_deviation_mm[c]) {
        r.max_abs_deviation_mm[c] = d[c];
        r.max_deviation_sample[static_cast<std::size_t>(c)] = i;
        r.max_deviation_nc_line[static_cast<std::size_t>(c)] = path.nc_line[i];
      }
  }
  for (std::size_t k = 0; k < r.reversals.size(); ++k) {
    const BacklashReversal& v = r.reversals[k];
    if (!v.in_feed) continue;
    for (int c = 0; c < 3; ++c)
      if (std::abs(v.step_mm[c]) > r.max_abs_step_mm[c]) {
        r.max_abs_step_mm[c] = std::abs(v.step_mm[c]);
        r.max_step_reversal[static_cast<std::size_t>(c)] = static_cast<int>(k);
      }
  }
  return r;
}

std::string BacklashResult::text() const {
  const double w_file = rotary ? rad2deg(width) : width;
  std::string t = fmt::format(
      "backlash {:.4f} {} on {}: {} reversals of {} ({} while cutting), {} feed samples\n", w_file,
      rotary ? "deg" : "mm", axis_name, reversals.size(), axis_name,
      std::count_if(reversals.begin(), reversals.end(), [](const BacklashReversal& v) { return v.in_feed; }),
      feed_samples);
  t += "  tip deviation over feed blocks (actual - commanded):\n";
  for (std::size_t c = 0; c < 3; ++c) {
    if (feed_samples == 0) break;
    const std::size_t i = max_deviation_sample[c];
    const Eigen::Vector3d& p = tip_commanded_mm[i];
    t += fmt::format("    max |d{}| = {:8.4f} um at NC line {} (tip {:.3f}, {:.3f}, {:.3f})\n", kComponent[c],
                     1000.0 * max_abs_deviation_mm[static_cast<int>(c)], max_deviation_nc_line[c], p.x(), p.y(), p.z());
  }
  t += "  tip step at reversals while cutting:\n";
  for (std::size_t c = 0; c < 3; ++c) {
    const int k = max_step_reversal[c];
    if (k < 0) {
      t += fmt::format("    max |step {}| = {:8.4f} um (no reversal while cutting)\n", kComponent[c], 0.0);
      continue;
    }
    const BacklashReversal& v = reversals[static_cast<std::size_t>(k)];
    t +=
        fmt::format("    max |step {}| = {:8.4f} um at NC line {} (tip {:.3f}, {:.3f}, {:.3f})\n", kComponent[c],
                    1000.0 * max_abs_step_mm[static_cast<int>(c)], v.nc_line, v.tip_mm.x(), v.tip_mm.y(), v.tip_mm.z());
  }
  for (const BacklashReversal& v : reversals)
    t += fmt::format(
        "  reversal at NC line {} ({}): tip ({:.3f}, {:.3f}, {:.3f}), step ({:+.4f}, {:+.4f}, {:+.4f}) um\n", v.nc_line,
        v.in_feed ? "while cutting" : "at a rapid", v.tip_mm.x(), v.tip_mm.y(), v.tip_mm.z(), 1000.0 * v.step_mm.x(),
        1000.0 * v.step_mm.y(), 1000.0 * v.step_mm.z());
  return t;
}

nlohmann::json BacklashResult::json() const {
  auto vec = [](const Eigen::Vector3d& v) {
    return nlohmann::json::array({rounded(v.x(), 7), rounded(v.y(), 7), rounded(v.z(), 7)});
  };
  nlohmann::json revs = nlohmann::json::array();
  for (const BacklashReversal& v : reversals)
    revs.push_back(
        {{"nc_line", v.nc_line}, {"in_feed", v.in_feed}, {"tip_mm", vec(v.tip_mm)}, {"step_mm", vec(v.step_mm)}});
  return {{"axis", axis_name},
          {rotary ? "width_deg" : "width_mm", rounded(rotary ? rad2deg(width) : width, 7)},
          {"feed_samples", feed_samples},
          {"max_abs_deviation_mm", vec(max_abs_deviation_mm)},
          {"max_deviation_nc_line", max_deviation_nc_line},
          {"max_abs_step_mm", vec(max_abs_step_mm)},
          {"reversals", std::move(revs)}};
}

std::string BacklashResult::to_json() const { return json().dump(); }

}  // namespace cscam::report
