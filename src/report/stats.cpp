#include "cscam/report/stats.hpp"

#include <fmt/format.h>

#include <cmath>

#include "cscam/core/tolerances.hpp"
#include "cscam/core/units.hpp"
#include "cscam/report/json.hpp"

namespace cscam::report {

namespace {

/// Counts direction changes with a hysteresis so that noise and rounding are not counted.
class ReversalCounter {
 public:
  explicit ReversalCounter(double h) : h_(h) {}
  void add(double v) {
    if (!started_) {
      extreme_ = v;
      started_ = true;
      return;
    }
    if (dir_ == 0) {
      if (std::abs(v - extreme_) > h_) {
        dir_ = v > extreme_ ? 1 : -1;
        extreme_ = v;
      }
    } else if (dir_ > 0) {
      if (v > extreme_)
        extreme_ = v;
      else if (extreme_ - v > h_) {
        ++count_;
        dir_ = -1;
        extreme_ = v;
      }
    } else {
      if (v < extreme_)
        extreme_ = v;
      else if (v - extreme_ > h_) {
        ++count_;
        dir_ = 1;
        extreme_ = v;
      }
    }
  }
  [[nodiscard]] int count() const { return count_; }

 private:
  double h_;
  double extreme_ = 0.0;
  int dir_ = 0;
  int count_ = 0;
  bool started_ = false;
};

struct Sample {
  std::array<double, 5> v;  // mm / deg
  bool rapid;
  int line;
};

Stats compute_samples(const std::vector<Sample>& s, const std::array<std::string, 5>& names,
                      const std::array<bool, 5>& rotary) {
  Stats st;
  std::array<ReversalCounter, 5> rev = {ReversalCounter(0), ReversalCounter(0), ReversalCounter(0), ReversalCounter(0),
                                        ReversalCounter(0)};
  for (size_t a = 0; a < 5; ++a) {
    st.axes[a].name = names[a];
    st.axes[a].rotary = rotary[a];
    rev[a] = ReversalCounter(rotary[a] ? tol::kReversalHysteresisDeg : tol::kReversalHysteresisMm);
    if (!s.empty()) st.axes[a].min = st.axes[a].max = s[0].v[a];
  }
  st.motion_blocks = s.empty() ? 0 : s.size();
  SegmentStat seg;
  std::array<bool, 5> seg_moving{};
  bool in_seg = false;
  auto close_seg = [&]() {
    if (!in_seg) return;
    seg.moving_axes = 0;
    seg.moving_rotaries = 0;
    for (size_t a = 0; a < 5; ++a)
      if (seg_moving[a]) {
        ++seg.moving_axes;
        if (rotary[a]) ++seg.moving_rotaries;
      }
    st.segments.push_back(seg);
    in_seg = false;
  };
  for (size_t i = 0; i < s.size(); ++i) {
    for (size_t a = 0; a < 5; ++a) {
      rev[a].add(s[i].v[a]);
      st.axes[a].min = std::min(st.axes[a].min, s[i].v[a]);
      st.axes[a].max = std::max(st.axes[a].max, s[i].v[a]);
    }
    if (i == 0) continue;
    int moving = 0;
    std::array<bool, 5> mv{};
    for (size_t a = 0; a < 5; ++a) {
      const double d = std::abs(s[i].v[a] - s[i - 1].v[a]);
      st.axes[a].travel += d;
      if (!s[i].rapid) st.axes[a].largest_step = std::max(st.axes[a].largest_step, d);
      if (d > 1e-6) {
        mv[a] = true;
        ++moving;
      }
    }
    if (s[i].rapid) {
      close_seg();
      continue;
    }
    ++st.feed_blocks;
    ++st.blocks_by_simultaneous[static_cast<size_t>(moving)];
    if (!in_seg) {
      seg = SegmentStat{};
      seg.first_line = s[i].line;
      seg_moving = {};
      in_seg = true;
    }
    seg.last_line = s[i].line;
    ++seg.blocks;
    seg.max_simultaneous = std::max(seg.max_simultaneous, moving);
    for (size_t a = 0; a < 5; ++a) seg_moving[a] = seg_moving[a] || mv[a];
  }
  close_seg();
  for (size_t a = 0; a < 5; ++a) st.axes[a].reversals = rev[a].count();
  return st;
}

}  // namespace

Stats compute(const nc::Program& program, const std::array<std::string, 5>& names, const std::array<bool, 5>& rotary,
              const std::array<double, 5>* max_feed) {
  std::vector<Sample> s;
  s.reserve(program.blocks.size());
  for (const nc::Block& b : program.blocks) {
    Sample x{};
    for (size_t a = 0; a < 5; ++a) x.v[a] = rotary[a] ? rad2deg(b.axes[a]) : b.axes[a];
    x.rapid = b.motion == nc::Motion::Rapid;
    x.line = b.line;
    s.push_back(x);
  }
  Stats st = compute_samples(s, names, rotary);
  st.source = program.file;
  // Cycle time, block by block from the previous block's position.
  st.rapid_time_known = max_feed != nullptr;
  st.dwell_minutes = program.dwell_seconds / 60.0;
  for (size_t i = 1; i < s.size(); ++i) {
    const nc::Block& b = program.blocks[i];
    double lin2 = 0.0, rot2 = 0.0, rapid_min = 0.0;
    for (size_t a = 0; a < 5; ++a) {
      const double d = s[i].v[a] - s[i - 1].v[a];
      (rotary[a] ? rot2 : lin2) += d * d;
      if (max_feed && (*max_feed)[a] > 0) rapid_min = std::max(rapid_min, std::abs(d) / (*max_feed)[a]);
    }
    if (b.motion == nc::Motion::Rapid) {
      st.rapid_minutes += rapid_min;
    } else if (b.feed > 0) {
      if (b.arc) lin2 = std::pow(nc::linear_path_mm(program.blocks[i - 1].axes, b, rotary), 2);  // the arc's length
      st.feed_minutes += b.inverse_time ? 1.0 / b.feed : (lin2 > 1e-18 ? std::sqrt(lin2) : std::sqrt(rot2)) / b.feed;
    }
  }
  return st;
}

Stats compute(const std::vector<kin::Axes>& path, const std::vector<bool>& rapid,
              const std::array<std::string, 5>& names, const std::array<bool, 5>& rotary) {
  std::vector<Sample> s;
  s.reserve(path.size());
  for (size_t i = 0; i < path.size(); ++i) {
    Sample x{};
    for (size_t a = 0; a < 5; ++a)
      x.v[a] = rotary[a] ? rad2deg(path[i][static_cast<int>(a)]) : path[i][static_cast<int>(a)];
    x.rapid = i < rapid.size() && rapid[i];
    x.line = static_cast<int>(i) + 1;
    s.push_back(x);
  }
  return compute_samples(s, names, rotary);
}

nlohmann::json Stats::json() const {
  nlohmann::json ax = nlohmann::json::array();
  for (const auto& x : axes)
    ax.push_back({{"name", x.name},
                  {"unit", x.rotary ? "deg" : "mm"},
                  {"travel", rounded(x.travel, 4)},
                  {"reversals", x.reversals},
                  {"largest_step", rounded(x.largest_step, 4)},
                  {"min", rounded(x.min, 4)},
                  {"max", rounded(x.max, 4)}});
  nlohmann::json segs = nlohmann::json::array();
  for (const auto& g : segments)
    segs.push_back({{"first_line", g.first_line},
                    {"last_line", g.last_line},
                    {"blocks", g.blocks},
                    {"moving_axes", g.moving_axes},
                    {"moving_rotaries", g.moving_rotaries},
                    {"max_simultaneous", g.max_simultaneous}});
  return {{"source", source},
          {"motion_blocks", motion_blocks},
          {"feed_blocks", feed_blocks},
          {"axes", std::move(ax)},
          {"segments", std::move(segs)},
          {"feed_blocks_by_simultaneous_axes", blocks_by_simultaneous},
          {"feed_minutes", rounded(feed_minutes, 4)},
          {"rapid_minutes", rapid_time_known ? nlohmann::json(rounded(rapid_minutes, 4)) : nlohmann::json()},
          {"dwell_minutes", rounded(dwell_minutes, 4)},
          {"cycle_minutes", rounded(feed_minutes + rapid_minutes + dwell_minutes, 4)}};
}

std::string Stats::to_json() const { return json().dump(); }

std::string table(const std::vector<Stats>& cols, const std::vector<std::string>& headers) {
  std::string t;
  int w = 14;
  for (const auto& h : headers) w = std::max(w, static_cast<int>(h.size()) + 2);
  t += fmt::format("{:<28}", "");
  for (const auto& h : headers) t += fmt::format("{:>{}}", h, w);
  t += "\n";
  auto row = [&](const std::string& label, auto&& cell) {
    t += fmt::format("{:<28}", label);
    for (const auto& c : cols) t += fmt::format("{:>{}}", cell(c), w);
    t += "\n";
  };
  row("motion blocks", [](const Stats& s) { return fmt::format("{}", s.motion_blocks); });
  row("feed blocks", [](const Stats& s) { return fmt::format("{}", s.feed_blocks); });
  for (size_t a = 0; a < 5; ++a) {
    const std::string nm = cols.empty() ? "" : cols[0].axes[a].name;
    const std::string unit = cols.empty() || !cols[0].axes[a].rotary ? "mm" : "deg";
    row(fmt::format("{} travel ({})", nm, unit),
        [a](const Stats& s) { return fmt::format("{:.3f}", s.axes[a].travel); });
    row(fmt::format("{} reversals", nm), [a](const Stats& s) { return fmt::format("{}", s.axes[a].reversals); });
    if (!cols.empty() && cols[0].axes[a].rotary)
      row(fmt::format("{} largest step (deg)", nm),
          [a](const Stats& s) { return fmt::format("{:.3f}", s.axes[a].largest_step); });
  }
  row("cycle time (min)", [](const Stats& s) {
    return s.rapid_time_known ? fmt::format("{:.2f}", s.feed_minutes + s.rapid_minutes + s.dwell_minutes)
                              : fmt::format("{:.2f}+rapids", s.feed_minutes + s.dwell_minutes);
  });
  row("cutting segments", [](const Stats& s) { return fmt::format("{}", s.segments.size()); });
  row("max simultaneous axes", [](const Stats& s) {
    int m = 0;
    for (const auto& g : s.segments) m = std::max(m, g.max_simultaneous);
    return fmt::format("{}", m);
  });
  row("segments 3+2 / 4ax / 5ax", [](const Stats& s) {
    int c[3] = {0, 0, 0};
    for (const auto& g : s.segments) ++c[std::min(g.moving_rotaries, 2)];
    return fmt::format("{} / {} / {}", c[0], c[1], c[2]);
  });
  return t;
}

}  // namespace cscam::report
