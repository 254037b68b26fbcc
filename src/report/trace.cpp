#include "cscam/report/trace.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <charconv>
#include <cmath>
#include <fstream>
#include <limits>
#include <map>
#include <set>
#include <sstream>

#include "cscam/core/error.hpp"
#include "cscam/core/rotations.hpp"
#include "cscam/core/segment.hpp"
#include "cscam/core/units.hpp"
#include "cscam/report/json.hpp"

namespace cscam::report {

namespace {

using Vec3 = Eigen::Vector3d;

struct ClSeg {
  Vec3 p0, p1, u0, u1;
  int line;
};

Vec3 slerp(const Vec3& a, const Vec3& b, double s) {
  const double th = std::acos(std::clamp(a.dot(b), -1.0, 1.0));
  if (th < 1e-9) return ((1 - s) * a + s * b).normalized();
  return (std::sin((1 - s) * th) / std::sin(th) * a + std::sin(s * th) / std::sin(th) * b).normalized();
}

double seg_distance(const Vec3& p0, const Vec3& p1, const Vec3& p, double& t) {
  const Vec3 ab = p1 - p0;
  return point_segment_distance(p, p0, ab, ab.squaredNorm(), &t);
}

// halsampler's columns (trunnion-ac.hal): sample number, 5 joints, 5 world axes, line, motion type, velocity,
// kinematics type.
constexpr int kColumns = 15;

TraceMotion motion_of(int type) {
  switch (type) {
    case 0:
      return TraceMotion::Idle;
    case 1:
      return TraceMotion::Rapid;
    case 2:
      return TraceMotion::Feed;
    case 3:
      return TraceMotion::Arc;
    default:
      return TraceMotion::Other;
  }
}

}  // namespace

Trace read_halsampler_text(const std::string& text, const std::string& name, const std::array<bool, 5>& rotary) {
  Trace tr;
  tr.file = name;
  std::istringstream in(text);
  std::string s;
  int line_no = 0;
  while (std::getline(in, s)) {
    ++line_no;
    const SourceLoc where{name, line_no};
    if (s.find_first_not_of(" \t\r") == std::string::npos) continue;
    if (s.find("overrun") != std::string::npos)
      throw InputError(where, "the sampler FIFO overran: samples were lost (a larger sampler depth is needed)");
    std::array<double, kColumns> v{};
    const char* p = s.data();
    const char* end = s.data() + s.size();
    for (int c = 0; c < kColumns; ++c) {
      while (p < end && (*p == ' ' || *p == '\t')) ++p;
      const auto [q, ec] = std::from_chars(p, end, v[c]);
      if (ec != std::errc() || !std::isfinite(v[c]))
        throw InputError(SourceLoc{name, line_no, static_cast<int>(p - s.data()) + 1},
                         fmt::format("expected {} numbers per sample (halsampler -t output), column {} is not one",
                                     kColumns, c + 1));
      p = q;
    }
    while (p < end && (*p == ' ' || *p == '\t' || *p == '\r')) ++p;
    if (p != end) throw InputError(where, fmt::format("more than {} columns", kColumns));
    // The sample number and the program line are whole numbers that halsampler prints as such (a sampler column
    // of another kind, or a hand-edited file, is not a trace).
    auto whole = [&](int column, double lo, double hi, const char* what) {
      const double x = v[static_cast<size_t>(column)];
      if (!(x >= lo && x <= hi && x == std::round(x)))
        throw InputError(where, fmt::format("column {} ({}) is {:g}: expected a whole number from {:g} to {:g}",
                                            column + 1, what, x, lo, hi));
    };
    whole(0, 0.0, 9.0e15, "the sample number");
    whole(11, -2147483648.0, 2147483647.0, "the program line, a signed 32-bit pin");
    TraceSample smp;
    smp.index = std::lround(v[0]);
    if (!tr.samples.empty() && smp.index != tr.samples.back().index + 1)
      throw InputError(
          where, fmt::format("sample {} follows sample {}: samples were lost", smp.index, tr.samples.back().index));
    for (int a = 0; a < 5; ++a) smp.joints[a] = rotary[static_cast<size_t>(a)] ? deg2rad(v[1 + a]) : v[1 + a];
    smp.world_mm = Vec3(v[6], v[7], v[8]);
    smp.nc_line = static_cast<int>(std::lround(v[11]));
    smp.motion = motion_of(static_cast<int>(std::lround(v[12])));
    smp.kinematics = static_cast<int>(std::lround(v[14]));
    tr.samples.push_back(smp);
  }
  if (tr.samples.empty()) throw InputError(SourceLoc{name}, "no samples (the sampler recorded nothing)");
  return tr;
}

Trace read_halsampler(const std::string& path, const std::array<bool, 5>& rotary) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw InputError(SourceLoc{path}, "cannot open the sample file");
  std::stringstream ss;
  ss << in.rdbuf();
  return read_halsampler_text(ss.str(), path, rotary);
}

TraceCheckResult check_trace(const Trace& trace, const cl::Program& cl, const kin::Kinematics& kinematics,
                             const TraceCheckOptions& options, const nc::Program* nc) {
  TraceCheckResult r;
  r.samples = trace.samples.size();
  std::vector<ClSeg> segs;
  for (size_t i = 1; i < cl.moves.size(); ++i) {
    const auto& a = cl.moves[i - 1];
    const auto& b = cl.moves[i];
    if (b.kind != cl::MotionKind::Feed) continue;
    segs.push_back(
        {a.tip_in_part_mm, b.tip_in_part_mm, a.axis_in_part.normalized(), b.axis_in_part.normalized(), b.line});
  }
  if (segs.empty()) {
    r.message = "the CL program has no feed moves: nothing to compare";
    return r;
  }

  // Tip and axis of every sample (rapids too: they may reach CL points).
  std::vector<kin::Posed> pose(trace.samples.size());
  for (size_t i = 0; i < trace.samples.size(); ++i) pose[i] = kinematics.forward(trace.samples[i].joints);

  // The CL segment a sample is judged against. With the program (--nc): the nearest of the segments its block runs
  // along (below). Without it: the nearest within 64 segments of the previous sample's, and where none of those is
  // within the tolerance, the nearest of the whole path.
  size_t cursor = 0;
  // Without the program, the nearest segment in the neighbourhood of the previous one, even where a far one (a path
  // that crosses itself) is nearer: the sample's axis is judged around both.
  size_t local_cursor = 0;
  double local_t = 0.0;
  // NC line -> the CL segments its block and the two before it run along (with --nc): from where the block two
  // before starts to where this one ends.
  std::map<int, std::pair<size_t, size_t>> segment_of_line;
  int anchor_line = -1;           // the NC line of the sample being placed
  size_t own_lo = 0, own_hi = 0;  // the segments of its block (none: not anchored)
  auto nearest = [&](const Vec3& p, double& t) {
    auto scan = [&](size_t lo, size_t hi) {
      double best = std::numeric_limits<double>::infinity();
      for (size_t k = lo; k < hi; ++k) {
        double tk;
        const double d = seg_distance(segs[k].p0, segs[k].p1, p, tk);
        if (d < best - 1e-12) {
          best = d;
          cursor = k;
          t = tk;
        }
      }
      return best;
    };
    // Anchored on the sample's NC block where the program is known: the sample is judged against the CL segments that
    // block and the two before it run along (the controller's line label runs a block or two ahead of the motion),
    // with a margin. Its own pass, not the nearest one: a walk that crosses itself must not pass a sample that left
    // its pass within the tolerance of another one, nor judge its axis against that other pass.
    if (const auto anchor = segment_of_line.find(anchor_line); anchor != segment_of_line.end()) {
      // A block ending on a CL point may be matched to either segment at that point: one segment of margin each way.
      own_lo = anchor->second.first > 0 ? anchor->second.first - 1 : 0;
      own_hi = std::min(segs.size(), anchor->second.second + 2);
      const double own = scan(own_lo, own_hi);
      local_cursor = cursor;
      local_t = t;
      return own;
    }
    own_lo = own_hi = 0;
    const double local = scan(cursor > 64 ? cursor - 64 : 0, std::min(segs.size(), cursor + 64));
    local_cursor = cursor;
    local_t = t;
    if (local <= options.tip_tolerance_mm) return local;
    return scan(0, segs.size());
  };

  // The controller's world position against the joints (joint mode) or our FK (TCP), at the best lag.
  {
    auto expected = [&](size_t i) -> Vec3 {
      const TraceSample& s = trace.samples[i];
      return s.kinematics == 1 ? pose[i].tip_mm : Vec3(s.joints[0], s.joints[1], s.joints[2]);
    };
    // Samples within the lag window of a kinematics switch compare a world position of one mode with the
    // joints of the other: left out.
    constexpr int kMaxLag = 8;
    std::vector<char> settled(trace.samples.size(), 0);
    for (size_t i = kMaxLag, last_switch = 0; i < trace.samples.size(); ++i) {
      if (trace.samples[i].kinematics != trace.samples[i - 1].kinematics) last_switch = i;
      settled[i] = i >= last_switch + kMaxLag ? 1 : 0;
    }
    double best = std::numeric_limits<double>::infinity();
    for (int lag = 0; lag <= kMaxLag; ++lag) {
      double worst = 0.0, worst_tcp = 0.0;
      for (size_t i = static_cast<size_t>(lag); i < trace.samples.size(); ++i) {
        if (!settled[i]) continue;
        const double d = (trace.samples[i - static_cast<size_t>(lag)].world_mm - expected(i)).norm();
        worst = std::max(worst, d);
        if (trace.samples[i].kinematics == 1) worst_tcp = std::max(worst_tcp, d);
      }
      if (worst < best) {
        best = worst;
        r.max_world_mismatch_mm = worst;
        r.max_world_mismatch_tcp_mm = worst_tcp;
        r.world_lag_samples = lag;
      }
    }
    for (const auto& s : trace.samples) r.tcp_samples += s.kinematics == 1 ? 1 : 0;
  }

  // The program's departures along the tool axis (retract before a flip, plunge after it). A sample is matched to
  // one by where it is, not by its NC line: the controller's motion.program-line runs ahead of the motion it
  // labels (a plunge blended into two short cuts was labelled with the second cut's line while the tool was still
  // 0.03 mm above the CL point).
  struct Departure {
    Vec3 a, b, axis;
  };
  std::vector<Departure> departure_moves;
  std::set<int> departures;
  if (nc != nullptr) {
    auto pose_of = [&](const nc::Block& b) {
      kin::Axes q;
      for (int a = 0; a < 5; ++a) q[a] = b.axes[static_cast<size_t>(a)];
      kin::Posed p = kinematics.forward(q);
      if (nc->tcp) p.tip_mm = Vec3(q[0], q[1], q[2]);  // TCP: X Y Z are the tip in the part frame
      return p;
    };
    auto path_distance = [&](const Vec3& p) {
      double best = std::numeric_limits<double>::infinity(), t;
      for (const auto& sg : segs) best = std::min(best, seg_distance(sg.p0, sg.p1, p, t));
      return best;
    };
    const double cos_axis_tol = std::cos(deg2rad(options.axis_tolerance_deg));
    // Each block matched to the CL segment nearest its end, searching forward from the previous block's (the program
    // follows the CL path in order); a block far off the path (a rapid, a retract) keeps the previous one.
    {
      // Of the segments as near as the nearest (within half the tolerance: printed decimals, a walk that passes
      // through the same point twice), the one closest ahead of the previous block's.
      size_t k_seg = 0;
      std::vector<double> dist;
      std::vector<size_t> ends;  // the segment each block so far ends on
      for (const nc::Block& b : nc->blocks) {
        const Vec3 tip = pose_of(b).tip_mm;
        const size_t lo = k_seg > 16 ? k_seg - 16 : 0, hi = std::min(segs.size(), k_seg + 256);
        dist.assign(hi - lo, 0.0);
        double best = std::numeric_limits<double>::infinity(), t;
        for (size_t k = lo; k < hi; ++k)
          best = std::min(best, dist[k - lo] = seg_distance(segs[k].p0, segs[k].p1, tip, t));
        if (best <= 10.0 * options.tip_tolerance_mm) {
          size_t at = k_seg;
          double cost = std::numeric_limits<double>::infinity();
          for (size_t k = lo; k < hi; ++k) {
            if (dist[k - lo] > best + 0.5 * options.tip_tolerance_mm) continue;
            const double c = k >= k_seg ? static_cast<double>(k - k_seg) : 4.0 * static_cast<double>(k_seg - k);
            if (c < cost) cost = c, at = k;
          }
          k_seg = at;
        }
        ends.push_back(k_seg);
        const size_t from = ends[ends.size() > 3 ? ends.size() - 4 : 0];
        segment_of_line[b.line] = {std::min(from, k_seg), std::max(from, k_seg)};
      }
    }
    for (size_t k = 1; k < nc->blocks.size(); ++k) {
      const nc::Block& b = nc->blocks[k];
      if (b.motion != nc::Motion::Linear) continue;
      const kin::Posed pa = pose_of(nc->blocks[k - 1]), pb = pose_of(b);
      const Vec3 d = pb.tip_mm - pa.tip_mm;
      if (d.norm() <= options.tip_tolerance_mm || pa.axis.dot(pb.axis) < cos_axis_tol ||
          d.cross(pa.axis).norm() > options.tip_tolerance_mm)
        continue;
      if (path_distance(pa.tip_mm) > options.tip_tolerance_mm || path_distance(pb.tip_mm) > options.tip_tolerance_mm) {
        departures.insert(b.line);
        departure_moves.push_back({pa.tip_mm, pb.tip_mm, pa.axis});
      }
    }
    r.departure_blocks = departures.size();
  }

  const double cos_axis_tol = std::cos(deg2rad(options.axis_tolerance_deg));
  auto on_departure = [&](const kin::Posed& p) {
    double t;
    return std::any_of(departure_moves.begin(), departure_moves.end(), [&](const Departure& dm) {
      return seg_distance(dm.a, dm.b, p.tip_mm, t) <= options.tip_tolerance_mm && dm.axis.dot(p.axis) >= cos_axis_tol;
    });
  };
  // The smallest angle between a sample's axis and the CL axis at any pose of the path its tip is within the
  // tolerance of: on a path that doubles back beside itself, the nearest segment may be the one going the other way,
  // with another orientation (as the gate judges a block, docs/safety.md).
  auto best_axis_deg = [&](const Vec3& tip, const Vec3& axis) {
    double best_dot = -1.0;
    const double tol2 = options.tip_tolerance_mm * options.tip_tolerance_mm;
    std::vector<size_t> around;
    auto add = [&](size_t c) {
      for (size_t k = c > 64 ? c - 64 : 0; k < std::min(segs.size(), c + 65); ++k) around.push_back(k);
    };
    if (own_hi > own_lo) {  // anchored: its own block's segments only
      for (size_t k = own_lo; k < own_hi; ++k) around.push_back(k);
    } else {
      add(cursor);
      if (local_cursor != cursor) add(local_cursor);
    }
    for (const size_t k : around) {
      const Vec3 d = segs[k].p1 - segs[k].p0, e = segs[k].p0 - tip;
      const double a = d.squaredNorm(), b = 2.0 * d.dot(e), c = e.squaredNorm() - tol2;
      double t0 = 0.0, t1 = 1.0;  // where |p0 + t d - tip| <= tol
      if (a < 1e-18) {
        if (c > 0) continue;
      } else {
        const double disc = b * b - 4.0 * a * c;
        if (disc < 0) continue;
        t0 = std::max(0.0, (-b - std::sqrt(disc)) / (2.0 * a));
        t1 = std::min(1.0, (-b + std::sqrt(disc)) / (2.0 * a));
        if (t0 > t1) continue;
      }
      const double th = std::acos(std::clamp(segs[k].u0.dot(segs[k].u1), -1.0, 1.0));
      const double dot =
          th < 1e-9 ? segs[k].u0.dot(axis) : rot::arc_best_dot(segs[k].u0, segs[k].u1, th, std::sin(th), axis, t0, t1);
      best_dot = std::max(best_dot, dot);
    }
    return rad2deg(std::acos(std::clamp(best_dot, -1.0, 1.0)));
  };

  std::vector<double> devs;
  std::map<int, TraceBlock> blocks;
  for (size_t i = 0; i < trace.samples.size(); ++i) {
    const TraceSample& s = trace.samples[i];
    if (s.motion != TraceMotion::Feed && s.motion != TraceMotion::Arc) continue;
    double t = 0;
    anchor_line = s.nc_line;
    const double d = nearest(pose[i].tip_mm, t);
    if (on_departure(pose[i])) {  // near its CL end a departure sample is also within tolerance of the path
      ++r.departure_samples;
      continue;
    }
    devs.push_back(d);
    TraceBlock& b = blocks[s.nc_line];
    b.nc_line = s.nc_line;
    b.max_tip_deviation_mm = std::max(b.max_tip_deviation_mm, d);
    ++b.samples;
    if (d > r.max_tip_deviation_mm || r.max_tip_sample < 0) {
      r.max_tip_deviation_mm = d;
      r.max_tip_sample = s.index;
      r.max_tip_nc_line = s.nc_line;
      r.max_tip_cl_line = segs[cursor].line;
      r.max_tip_in_part_mm = pose[i].tip_mm;
    }
    const Vec3 u = slerp(segs[cursor].u0, segs[cursor].u1, t);
    double ang = rad2deg(std::acos(std::clamp(u.dot(pose[i].axis), -1.0, 1.0)));
    if (ang > options.axis_tolerance_deg) {
      // A far segment nearer than the neighbourhood (a walk crossing itself, the controller a little off here): the
      // axis is judged at the neighbourhood's nearest point too.
      const Vec3 ul = slerp(segs[local_cursor].u0, segs[local_cursor].u1, local_t);
      ang = std::min({ang, rad2deg(std::acos(std::clamp(ul.dot(pose[i].axis), -1.0, 1.0))),
                      best_axis_deg(pose[i].tip_mm, pose[i].axis)});
    }
    if (ang > r.max_axis_deviation_deg) {
      r.max_axis_deviation_deg = ang;
      r.max_axis_nc_line = s.nc_line;
    }
  }
  r.feed_samples = devs.size();
  if (devs.empty()) {
    r.message = fmt::format("{}: no sample at feed: the program did not cut", trace.file);
    return r;
  }
  std::sort(devs.begin(), devs.end());
  r.p99_tip_deviation_mm =
      devs[std::min(devs.size() - 1, static_cast<size_t>(0.99 * static_cast<double>(devs.size())))];
  for (const auto& [line, b] : blocks) r.worst_blocks.push_back(b);
  std::sort(r.worst_blocks.begin(), r.worst_blocks.end(),
            [](const TraceBlock& a, const TraceBlock& b) { return a.max_tip_deviation_mm > b.max_tip_deviation_mm; });
  if (r.worst_blocks.size() > 5) r.worst_blocks.resize(5);

  // Coverage: every CL feed point (and the start of every feed run) must lie on the sampled tip path. The
  // samples advance with the CL, so search on from where the previous point was found, then everywhere.
  size_t scursor = 0;
  auto covered = [&](const Vec3& p) {
    auto scan = [&](size_t lo, size_t hi, bool stop_early) {
      double best = std::numeric_limits<double>::infinity();
      for (size_t k = lo; k + 1 < hi; ++k) {
        double tk;
        const double d = seg_distance(pose[k].tip_mm, pose[k + 1].tip_mm, p, tk);
        if (d < best) {
          best = d;
          scursor = k;
          if (stop_early && d <= 0.1 * options.tip_tolerance_mm) break;
        }
      }
      return best;
    };
    const size_t c0 = scursor;
    const double local = scan(c0, pose.size(), true);
    if (local <= options.tip_tolerance_mm) return local;
    return std::min(local, scan(0, pose.size(), false));
  };
  if (pose.size() == 1) {
    r.max_uncovered_cl_mm = std::numeric_limits<double>::infinity();
  } else {
    for (size_t i = 0; i < cl.moves.size(); ++i) {
      const bool feed_end = cl.moves[i].kind == cl::MotionKind::Feed;
      const bool feed_start = i + 1 < cl.moves.size() && cl.moves[i + 1].kind == cl::MotionKind::Feed;
      if (!feed_end && !feed_start) continue;
      const double d = covered(cl.moves[i].tip_in_part_mm);
      if (d > r.max_uncovered_cl_mm) {
        r.max_uncovered_cl_mm = d;
        r.max_uncovered_cl_line = cl.moves[i].line;
      }
    }
  }

  const bool tip_ok = r.max_tip_deviation_mm <= options.tip_tolerance_mm;
  const bool axis_ok = r.max_axis_deviation_deg <= options.axis_tolerance_deg;
  const bool cover_ok = r.max_uncovered_cl_mm <= options.tip_tolerance_mm;
  r.ok = tip_ok && axis_ok && cover_ok;
  const Vec3& w = r.max_tip_in_part_mm;
  r.message = fmt::format(
      "{}: {} {} servo samples ({} at feed compared, {} on the {} departure blocks not): tip within {:.4f} mm of the "
      "CL path "
      "(99% within {:.4f}), "
      "largest at NC line {} near CL line {}, sample {}, tip ({:.4f}, {:.4f}, {:.4f}); tool axis within {:.4f} "
      "deg; every CL point within {:.4f} mm of the path (CL line {}); tolerance {:.4f} mm / {:.3f} deg; "
      "controller's world X Y Z within {:.6f} mm of ours ({} TCP samples, lag {} cycles)",
      trace.file, r.ok ? "OK" : "FAILED", r.samples, r.feed_samples, r.departure_samples, r.departure_blocks,
      r.max_tip_deviation_mm, r.p99_tip_deviation_mm, r.max_tip_nc_line, r.max_tip_cl_line, r.max_tip_sample, w.x(),
      w.y(), w.z(), r.max_axis_deviation_deg, r.max_uncovered_cl_mm, r.max_uncovered_cl_line, options.tip_tolerance_mm,
      options.axis_tolerance_deg, r.max_world_mismatch_mm, r.tcp_samples, r.world_lag_samples);
  return r;
}

nlohmann::json TraceCheckResult::json() const {
  nlohmann::json worst = nlohmann::json::array();
  for (const auto& b : worst_blocks)
    worst.push_back(
        {{"nc_line", b.nc_line}, {"max_tip_deviation_mm", rounded(b.max_tip_deviation_mm, 6)}, {"samples", b.samples}});
  return {
      {"ok", ok},
      {"samples", samples},
      {"feed_samples", feed_samples},
      {"max_tip_deviation_mm", rounded(max_tip_deviation_mm, 6)},
      {"p99_tip_deviation_mm", rounded(p99_tip_deviation_mm, 6)},
      {"max_tip_sample", max_tip_sample},
      {"max_tip_nc_line", max_tip_nc_line},
      {"max_tip_cl_line", max_tip_cl_line},
      {"max_tip_in_part_mm",
       {rounded(max_tip_in_part_mm.x(), 6), rounded(max_tip_in_part_mm.y(), 6), rounded(max_tip_in_part_mm.z(), 6)}},
      {"max_axis_deviation_deg", rounded(max_axis_deviation_deg, 6)},
      {"max_axis_nc_line", max_axis_nc_line},
      {"max_uncovered_cl_mm", rounded(max_uncovered_cl_mm, 6)},
      {"max_uncovered_cl_line", max_uncovered_cl_line},
      {"worst_blocks", worst},
      {"departure_blocks", departure_blocks},
      {"departure_samples", departure_samples},
      {"tcp_samples", tcp_samples},
      {"max_world_mismatch_mm", rounded(max_world_mismatch_mm, 6)},
      {"max_world_mismatch_tcp_mm", rounded(max_world_mismatch_tcp_mm, 6)},
      {"world_lag_samples", world_lag_samples},
      {"message", message}};
}

}  // namespace cscam::report
