#include "cscam/gate/gate.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <map>
#include <stdexcept>
#include <unordered_map>

#include "cscam/core/atomic_file.hpp"
#include "cscam/core/error.hpp"
#include "cscam/core/parallel.hpp"
#include "cscam/core/tolerances.hpp"
#include "cscam/core/units.hpp"
#include "cscam/kin/track.hpp"
#include "cscam/nc/reader.hpp"
#include "cscam/report/letters.hpp"

namespace cscam::gate {

namespace {

using Vec3 = Eigen::Vector3d;

std::string axis_value(const kin::AxisInfo& a, double v) {
  return a.rotary() ? fmt::format("{:.4f} deg", rad2deg(v)) : fmt::format("{:.4f} mm", v);
}

}  // namespace

Options options_for(const machine::Machine& machine, double tolerance_mm, double axis_tolerance_deg, double cone_deg) {
  Options o;
  const report::VerifyOptions vo = report::verify_options_for(machine, tolerance_mm, axis_tolerance_deg, cone_deg);
  o.tip_tolerance_mm = vo.tip_tolerance_mm;
  o.axis_tolerance_deg = vo.axis_tolerance_deg;
  o.ball_centre = vo.ball_centre;
  return o;
}

Summary check(const std::string& nc_text, const std::string& nc_name, const cl::Program& cl,
              const machine::Machine& machine, const kin::Kinematics& kinematics, const Options& options,
              const std::vector<int>* cl_line_of_nc_line, nc::Program* read_back) {
  Summary s;
  auto cl_line_of = [&](int nc_line) {
    if (!cl_line_of_nc_line || nc_line <= 0 || static_cast<size_t>(nc_line) >= cl_line_of_nc_line->size()) return 0;
    return (*cl_line_of_nc_line)[static_cast<size_t>(nc_line)];
  };
  auto add = [&](Violation::Kind kind, int nc_line, int cl_line, std::string msg) {
    s.violations.push_back({kind, nc_line, cl_line ? cl_line : cl_line_of(nc_line), std::move(msg)});
  };

  // Tool-tip control: the program says so (G43.4 / G234 / TCPM words, or our Cartesian header); its linear
  // words are then the tip X Y Z. Vector forms (G43.5 I J K, A3 B3 C3) get their rotaries by IK.
  nc::Program ncp;
  try {
    ncp = report::read_for_machine(nc_text, nc_name, machine);
  } catch (const InputError& e) {
    add(Violation::Kind::Unreadable, e.where().line, 0,
        fmt::format("the program cannot be read back: {}", e.message()));
    s.message = s.violations.front().message;
    return s;
  }
  // A coordinate shift, rotation or scaling, a new work offset or a lost length offset (an INSERT can bring any of
  // them) moves the machine where the read-back does not: the moves after it cannot be checked.
  if (const nc::Program::Unmodelled* u = nc::first_unmodelled_before_motion(ncp)) {
    add(Violation::Kind::Unreadable, u->line, 0,
        fmt::format("{}, which the gate does not model: the moves after it cannot be checked", u->what));
    s.message = s.violations.front().message;
    return s;
  }
  // A feed move with the spindle stopped (an M5 the CL did not ask for, e.g. from an INSERT) where the CL cuts with it
  // running: the tool would be pushed through the material standing still.
  // (Only where a stop has feed blocks: a program's last M5 has none.)
  const bool stopped_feeds =
      cl_line_of_nc_line &&
      std::any_of(ncp.spindle_stops.begin(), ncp.spindle_stops.end(), [&](const nc::Program::SpindleStop& st) {
        for (std::size_t bi = st.first_block; bi < st.end_block && bi < ncp.blocks.size(); ++bi)
          if (ncp.blocks[bi].motion != nc::Motion::Rapid) return true;
        return false;
      });
  if (stopped_feeds) {
    std::unordered_map<int, bool> cl_running;  // CL line of a move -> the spindle runs there
    bool on = false;
    std::size_t e = 0;
    for (std::size_t i = 0; i < cl.moves.size(); ++i) {
      for (; e < cl.events.size() && cl.events[e].before_move <= i; ++e) {
        if (cl.events[e].kind == cl::Event::Kind::SpindleOn) on = true;
        if (cl.events[e].kind == cl::Event::Kind::SpindleOff) on = false;
      }
      if (cl.moves[i].kind == cl::MotionKind::Feed) cl_running[cl.moves[i].line] = on;
    }
    for (const auto& stop : ncp.spindle_stops)
      for (std::size_t bi = stop.first_block; bi < stop.end_block && bi < ncp.blocks.size(); ++bi) {
        const nc::Block& b = ncp.blocks[bi];
        if (b.motion == nc::Motion::Rapid) continue;
        const int cl_line = cl_line_of(b.line);
        if (const auto it = cl_running.find(cl_line); it != cl_running.end() && it->second) {
          add(Violation::Kind::Limit, b.line, cl_line,
              fmt::format("feed move with the spindle stopped ({} at line {}) where the CL cuts with it running",
                          stop.what, stop.line));
          break;
        }
      }
  }
  s.tool_tip_control = ncp.tcp;  // read_for_machine has scanned the text for the TCP words (uses_tool_tip_control)
  {
    int bad_line = 0;
    if (const std::string why = report::resolve_tool_vectors(ncp, kinematics, &bad_line); !why.empty()) {
      add(Violation::Kind::Limit, bad_line, 0, why);
      s.message = s.violations.front().message;
      return s;
    }
  }
  s.blocks = ncp.blocks.size();
  const auto& ax = kinematics.axes();
  std::array<bool, 5> letters_rotary{};
  for (size_t i = 0; i < 5; ++i) letters_rotary[i] = ax[i].rotary();
  const auto tip_kin_ptr = report::tool_tip_kinematics(kinematics, ncp.tcp_vectors);
  const kin::Kinematics& tip_kin = *tip_kin_ptr;

  // Tip and tool axis against the CL path, sampled inside every feed block: it reads only the program and the
  // CL path, so it runs beside the limit and velocity checks below (its violations are added after theirs).
  report::VerifyOptions vo;
  vo.tip_tolerance_mm = options.tip_tolerance_mm;
  vo.axis_tolerance_deg = options.axis_tolerance_deg;
  vo.samples_per_block = options.samples_per_block;
  vo.ball_centre = options.ball_centre;
  // The XMINI's FK is warm-started from the calling thread's previous solve: there the comparison runs on this
  // thread after the checks below, so that its last digits do not depend on the thread count.
  const bool verify_here = kinematics.traits().forward_depends_on_call_order;
  auto compare = [&] {
    s.deviation =
        report::verify(ncp, cl, s.tool_tip_control ? static_cast<const kin::Kinematics&>(tip_kin) : kinematics, vo);
  };
  Background tg;
  if (!verify_here) tg.run(compare);

  // Machine (joint) values of every block: the words themselves, or for tool-tip control the IK solution
  // nearest the previous block's (what the control computes), inside every limit.
  // Machine words are the joints themselves: only tool-tip control keeps its IK solutions (40 MB fewer to fill for a
  // million-block machine-word program).
  std::vector<kin::Axes> tcp_joints(s.tool_tip_control ? ncp.blocks.size() : 0, kin::Axes::Zero());
  auto joints = [&](std::size_t bi) -> kin::Axes {
    if (s.tool_tip_control) return tcp_joints[bi];
    kin::Axes q;
    for (int i = 0; i < 5; ++i) q[i] = ncp.blocks[bi].axes[static_cast<size_t>(i)];
    return q;
  };
  std::vector<char> joints_ok(ncp.blocks.size(), 0);
  // With machine words every block's limits are independent of the others: checked in parallel (fixed slots),
  // then reported in block order below, as the sequential loop did. Tool-tip control needs the previous
  // block's solution, so it stays in order.
  // Only the blocks that fail are kept (block, message), per fixed chunk of blocks: a program inside its limits
  // costs no string per block.
  constexpr std::size_t kLimitChunk = 4096;
  std::vector<std::vector<std::pair<std::size_t, std::string>>> limit_violation;
  const bool limits_ahead = !s.tool_tip_control && !kinematics.traits().forward_depends_on_call_order;
  if (limits_ahead) {
    limit_violation.resize((ncp.blocks.size() + kLimitChunk - 1) / kLimitChunk);
    parallel_range(0, limit_violation.size(), 1, [&](const tbb::blocked_range<std::size_t>& r) {
      for (std::size_t c = r.begin(); c != r.end(); ++c)
        for (std::size_t bi = c * kLimitChunk; bi < std::min(ncp.blocks.size(), (c + 1) * kLimitChunk); ++bi) {
          const nc::Block& b = ncp.blocks[bi];
          if (!std::all_of(b.known.begin(), b.known.end(), [](bool k) { return k; })) continue;
          kin::Axes q;
          for (int i = 0; i < 5; ++i) q[i] = b.axes[static_cast<size_t>(i)];
          std::string v = kinematics.check_limits(q);
          if (v.empty()) v = kinematics.passive_violation(q);
          if (!v.empty()) limit_violation[c].emplace_back(bi, std::move(v));
        }
    });
  }
  std::size_t violation_chunk = 0, next_violation = 0;  // the first entry of that chunk not yet taken
  kin::Axes prev = kin::Axes::Zero();
  // A TCP program that cancels TCP for its tilted planes: its machine-word blocks (read as tip words) go exactly to
  // their machine axes (kept by the reader), no IK choice.
  std::size_t next_machine = 0;
  const bool angle_words = s.tool_tip_control && !ncp.tcp_vectors &&
                           kinematics.traits().tcp_rotary_words == kin::Traits::TcpRotaryWords::MachineAngles;
  for (size_t bi = 0; bi < ncp.blocks.size(); ++bi) {
    const nc::Block& b = ncp.blocks[bi];
    if (!std::all_of(b.known.begin(), b.known.end(), [](bool k) { return k; })) {
      // Before every axis has been programmed only the programmed words can be checked.
      for (int i = 0; i < 5; ++i) {
        const auto& a = ax[static_cast<size_t>(i)];
        const double slack = a.rotary() ? deg2rad(tol::kLimitSlackDeg) : tol::kLimitSlackMm;
        if (!s.tool_tip_control && b.known[static_cast<size_t>(i)] &&
            (b.axes[static_cast<size_t>(i)] < a.min - slack || b.axes[static_cast<size_t>(i)] > a.max + slack))
          add(Violation::Kind::Limit, b.line, 0,
              fmt::format("{} = {} outside its limits", a.name, axis_value(a, b.axes[static_cast<size_t>(i)])));
      }
      continue;
    }
    kin::Axes q;
    for (int i = 0; i < 5; ++i) q[i] = b.axes[static_cast<size_t>(i)];
    ++s.limit_checks;
    if (s.tool_tip_control) {
      const kin::Posed pose = tip_kin.forward(q);
      std::string why;
      kin::Axes sol = q;
      while (next_machine < ncp.machine_axes.size() && ncp.machine_axes[next_machine].first < bi) ++next_machine;
      const bool machine_words = next_machine < ncp.machine_axes.size() && ncp.machine_axes[next_machine].first == bi;
      if (machine_words) {
        for (int i = 0; i < 5; ++i) sol[i] = ncp.machine_axes[next_machine].second[static_cast<size_t>(i)];
        if (std::string v = kinematics.check_limits(sol); !v.empty()) {
          add(Violation::Kind::Limit, b.line, 0, v);
          continue;
        }
      } else if (angle_words) {
        // The rotary words are the machine's own angles: the control puts the rotaries there (a flip's G0 to the
        // other branch of the same axis turns them), and only the linear axes follow from the tip.
        const auto rp = kinematics.rotary_pair();
        sol = prev;
        sol[rp[0]] = q[rp[0]];
        sol[rp[1]] = q[rp[1]];
        if (!pose.tip_mm.allFinite() || !kinematics.solve_for_rotaries(pose, sol)) {
          add(Violation::Kind::Limit, b.line, 0,
              fmt::format("no linear axis values reach tip ({:.4f}, {:.4f}, {:.4f}) with these rotary words",
                          pose.tip_mm.x(), pose.tip_mm.y(), pose.tip_mm.z()));
          continue;
        }
        if (std::string v = kinematics.check_limits(sol); !v.empty()) {
          add(Violation::Kind::Limit, b.line, 0, v);
          continue;
        }
      } else if (!pose.axis.allFinite() || !kin::nearest_solution(kinematics, pose, prev, sol, &why)) {
        add(Violation::Kind::Limit, b.line, 0,
            fmt::format("no machine axis values inside the limits reach tip ({:.4f}, {:.4f}, {:.4f}) with this tool "
                        "vector{}",
                        pose.tip_mm.x(), pose.tip_mm.y(), pose.tip_mm.z(), why.empty() ? "" : ": " + why));
        continue;
      }
      q = sol;
    } else {
      std::string v;
      if (limits_ahead) {
        auto& found = limit_violation[bi / kLimitChunk];
        if (bi / kLimitChunk != violation_chunk) {
          violation_chunk = bi / kLimitChunk;
          next_violation = 0;
        }
        while (next_violation < found.size() && found[next_violation].first < bi) ++next_violation;
        if (next_violation < found.size() && found[next_violation].first == bi)
          v = std::move(found[next_violation++].second);
      } else {
        v = kinematics.check_limits(q);
        if (v.empty()) v = kinematics.passive_violation(q);
      }
      if (!v.empty()) {
        add(Violation::Kind::Limit, b.line, 0, v);
        continue;
      }
    }
    if (s.tool_tip_control) tcp_joints[bi] = q;
    joints_ok[bi] = 1;
    prev = q;
  }

  // Inside every move: passive joints (nonlinear in the axes) and collisions. Feed moves are checked as well
  // as rapids: the planner certifies the motion between CL points, but the machine moves between NC blocks,
  // and the points the post inserted (linearisation, retracts, arcs) are only checked here. The collision
  // test excludes the cutting end of the tool (see geom::CheckOptions::relief_mm), so cutting is not a hit.
  auto move_span = [&](size_t bi) {
    const nc::Block& b = ncp.blocks[bi];
    const kin::Axes qa = joints(bi - 1), qb = joints(bi);
    double span = 0.0;
    for (int i = 0; i < 5; ++i)
      span = std::max(span, std::abs(qb[i] - qa[i]) / (ax[static_cast<size_t>(i)].rotary() ? deg2rad(1.0) : 1.0));
    if (b.arc) span = std::max(span, nc::linear_path_mm(ncp.blocks[bi - 1].axes, b, letters_rotary));
    return span;
  };
  // Collisions first, in parallel over fixed chunks of moves (one check, with its own workspace, per chunk): each
  // move's first hit, taken below in block order as the serial loop found them.
  constexpr std::size_t kCollisionChunk = 1024;
  std::vector<std::vector<std::pair<std::size_t, std::string>>> hits;
  std::vector<std::size_t> chunk_checks;
  if (options.make_collision && ncp.blocks.size() > 1) {
    const std::size_t chunks = (ncp.blocks.size() - 1 + kCollisionChunk - 1) / kCollisionChunk;
    hits.resize(chunks);
    chunk_checks.assign(chunks, 0);
    // Samples at most `step` of joint motion apart along the path, across blocks (a million blocks of 0.2 mm need not
    // be checked at every block end), and at the end of every run of checked blocks (a chunk's end included: the next
    // chunk goes on from there). An arc is sampled on its own points from its start.
    const double step = std::max(options.collision_step, 1e-6);
    const bool translate = kinematics.traits().linear_axes_translate;
    auto body = [&](const tbb::blocked_range<std::size_t>& r) {
      std::map<int, Options::CollisionCheck> checks;  // per tool in the spindle (made when first needed)
      int last_tool = -1;
      const Options::CollisionCheck* last = nullptr;  // (the tool changes rarely: no lookup per sample)
      auto collides = [&](int tool_changes, const kin::Axes& q, bool whole_tool) {
        if (!last || tool_changes != last_tool) {
          Options::CollisionCheck& c = checks[tool_changes];
          if (!c) c = options.make_collision(tool_changes);
          last = &c, last_tool = tool_changes;
        }
        return (*last)(q, whole_tool);
      };
      std::vector<double> at;  // fractions of a block to check
      for (std::size_t c = r.begin(); c != r.end(); ++c) {
        const std::size_t b0 = 1 + c * kCollisionChunk, b1 = std::min(ncp.blocks.size(), 1 + (c + 1) * kCollisionChunk);
        double carried = 0.0;  // joint motion since the last pose checked
        for (std::size_t bi = b0; bi < b1; ++bi) {
          if (!joints_ok[bi] || !joints_ok[bi - 1]) {
            carried = step;  // the next run starts with its first pose
            continue;
          }
          const nc::Block& b = ncp.blocks[bi];
          const kin::Axes qa = joints(bi - 1), qb = joints(bi);
          const double span = move_span(bi);
          const bool run_ends = bi + 1 >= b1 || !joints_ok[bi + 1];
          const bool arc = b.arc && !s.tool_tip_control;
          // A rapid is sampled on its own, at least at its middle, with the whole tool away from its ends (where the
          // tool leaves or reaches the material as the CL put it: options.rapid_contact_mm).
          const bool rapid = b.motion == nc::Motion::Rapid;
          Eigen::Vector3d tip_a = Eigen::Vector3d::Zero(), tip_b = tip_a;
          if (rapid) tip_a = kinematics.forward(qa).tip_mm, tip_b = kinematics.forward(qb).tip_mm;
          bool straight_rapid = rapid && translate;
          for (int i = 0; i < 5 && straight_rapid; ++i)
            straight_rapid = !letters_rotary[static_cast<std::size_t>(i)] || qa[i] == qb[i];
          at.clear();
          if (rapid) {
            const int n = std::clamp(static_cast<int>(std::ceil(span / step)), 2, 20000);
            for (int k = 1; k <= n; ++k) at.push_back(static_cast<double>(k) / n);
            carried = 0.0;
          } else if (arc) {
            const int n = std::clamp(static_cast<int>(std::ceil(span / step)), 1, 20000);
            for (int k = 1; k <= n; ++k) at.push_back(static_cast<double>(k) / n);
            carried = 0.0;
          } else {
            const double h = std::max(step, span / 20000.0);
            double d = std::max(0.0, h - carried);
            for (; d <= span; d += h) at.push_back(span > 0 ? d / span : 1.0);
            if (run_ends && (at.empty() || at.back() < 1.0)) at.push_back(1.0);
            carried = at.empty() ? carried + span : span * (1.0 - at.back());
          }
          for (const double t : at) {
            kin::Axes q = qa + t * (qb - qa);
            if (arc) {
              const auto p = nc::point_on(ncp.blocks[bi - 1].axes, b, t);
              for (int i = 0; i < 5; ++i) q[i] = p[static_cast<size_t>(i)];
            }
            ++chunk_checks[c];
            bool whole_tool = false;
            if (rapid) {
              // With the rotaries held on such a machine the tip moves on the straight line between the ends.
              const Eigen::Vector3d tip =
                  straight_rapid ? Eigen::Vector3d(tip_a + t * (tip_b - tip_a)) : kinematics.forward(q).tip_mm;
              whole_tool = std::min((tip - tip_a).norm(), (tip - tip_b).norm()) > options.rapid_contact_mm;
            }
            if (std::string hit = collides(b.tool_changes, q, whole_tool); !hit.empty()) {
              hits[c].emplace_back(bi, std::move(hit));
              break;
            }
          }
        }
      }
    };
    // (The XMINI's FK is warm-started from the thread's previous solve: there the moves go in order on this thread,
    // so that a hit at the edge does not depend on the thread count.)
    if (kinematics.traits().forward_depends_on_call_order)
      body(tbb::blocked_range<std::size_t>(0, chunks));
    else
      parallel_range(0, chunks, 1, body);
    for (const std::size_t n : chunk_checks) s.collision_checks += n;
  }
  std::size_t hit_chunk = 0, next_hit = 0;  // the first entry of hits[hit_chunk] not yet taken
  for (size_t bi = 1; bi < ncp.blocks.size(); ++bi) {
    if (!joints_ok[bi] || !joints_ok[bi - 1]) continue;
    const nc::Block& b = ncp.blocks[bi];
    const kin::Axes qa = joints(bi - 1);
    const kin::Axes qb = joints(bi);
    const bool rapid = b.motion == nc::Motion::Rapid;
    const double span = move_span(bi);
    const int n = std::clamp(static_cast<int>(std::ceil(span / std::max(options.collision_step, 1e-6))), 1, 4000);
    for (int k = 1; k < n; ++k) {
      kin::Axes q = qa + (static_cast<double>(k) / n) * (qb - qa);
      if (b.arc && !s.tool_tip_control) {  // machine words on an arc: its points, inside the limits too
        const auto p = nc::point_on(ncp.blocks[bi - 1].axes, b, static_cast<double>(k) / n);
        for (int i = 0; i < 5; ++i) q[i] = p[static_cast<size_t>(i)];
        if (const std::string v = kinematics.check_limits(q); !v.empty()) {
          add(Violation::Kind::Limit, b.line, 0, fmt::format("inside the arc: {}", v));
          break;
        }
      }
      if (const std::string v = kinematics.passive_violation(q); !v.empty()) {
        add(Violation::Kind::Limit, b.line, 0, fmt::format("inside the move: {}", v));
        break;
      }
    }
    if (!hits.empty()) {
      const std::size_t c = (bi - 1) / kCollisionChunk;
      if (c != hit_chunk) hit_chunk = c, next_hit = 0;
      auto& found = hits[c];
      while (next_hit < found.size() && found[next_hit].first < bi) ++next_hit;
      if (next_hit < found.size() && found[next_hit].first == bi)
        add(Violation::Kind::Collision, b.line, 0,
            fmt::format("{} move collides: {}", rapid ? "rapid" : "feed", found[next_hit].second));
    }
  }

  // Axis velocities of feed blocks against max_feed (time from G93 inverse time, or from F and the length
  // of the move as an RS274 control measures it: linear axes first, else rotary degrees).
  for (size_t bi = 1; bi < ncp.blocks.size(); ++bi) {
    const nc::Block& b = ncp.blocks[bi];
    if (b.motion == nc::Motion::Rapid || !joints_ok[bi] || !joints_ok[bi - 1]) continue;
    kin::Axes wa, wb;  // the words (tip or joints) that set the programmed length
    for (int i = 0; i < 5; ++i) {
      wa[i] = ncp.blocks[bi - 1].axes[static_cast<size_t>(i)];
      wb[i] = b.axes[static_cast<size_t>(i)];
    }
    kin::Axes dq = joints(bi) - joints(bi - 1);
    if (b.arc && !s.tool_tip_control) {
      // On an arc the plane's axes peak at the path speed in the plane: their "distance" is the arc's length (in a
      // tilted plane each machine axis' share of it).
      const auto travel = nc::arc_axis_travel(ncp.blocks[bi - 1].axes, b);
      for (int i = 0; i < 5; ++i) dq[i] = travel[static_cast<size_t>(i)];
    }
    if (dq.cwiseAbs().maxCoeff() < 1e-12) continue;
    double minutes = 0.0;
    if (b.inverse_time) {
      if (b.feed <= 0) {
        add(Violation::Kind::Velocity, b.line, 0, "inverse-time feed block without a positive F word");
        continue;
      }
      minutes = 1.0 / b.feed;
    } else {
      double lin2 = 0.0, rot2 = 0.0;
      for (int i = 0; i < 5; ++i) {
        const double d = wb[i] - wa[i];
        (ax[static_cast<size_t>(i)].rotary() ? rot2 : lin2) += d * d;
      }
      if (b.arc) lin2 = std::pow(nc::linear_path_mm(ncp.blocks[bi - 1].axes, b, letters_rotary), 2);
      const double len = lin2 > 1e-18 ? std::sqrt(lin2) : rad2deg(std::sqrt(rot2));
      if (b.feed <= 0) {
        add(Violation::Kind::Velocity, b.line, 0, "feed move with no feed rate (F0)");
        continue;
      }
      minutes = len / b.feed;
    }
    for (int i = 0; i < 5; ++i) {
      const auto& a = ax[static_cast<size_t>(i)];
      if (a.max_feed <= 0) continue;
      const double v = std::abs(dq[i]) / std::max(minutes, 1e-12);
      const double ratio = v / a.max_feed;
      if (ratio > s.max_velocity_ratio) {
        s.max_velocity_ratio = ratio;
        s.max_velocity_nc_line = b.line;
      }
      if (ratio > 1.0 + options.feed_slack)
        add(Violation::Kind::Velocity, b.line, 0,
            a.rotary() ? fmt::format("axis {} would turn at {:.1f} deg/min, above its max_feed {:.1f} deg/min", a.name,
                                     rad2deg(v), rad2deg(a.max_feed))
                       : fmt::format("axis {} would move at {:.1f} mm/min, above its max_feed {:.1f} mm/min", a.name, v,
                                     a.max_feed));
    }
  }

  tg.wait();  // the tip/axis comparison started above
  if (verify_here) compare();
  const auto& d = s.deviation;
  if (d.max_tip_deviation_mm > vo.tip_tolerance_mm)
    add(Violation::Kind::Deviation, d.max_tip_nc_line, d.max_tip_cl_line,
        fmt::format("tool tip leaves the CL path by {:.4f} mm (allowed {:.4f} mm)", d.max_tip_deviation_mm,
                    vo.tip_tolerance_mm));
  if (d.max_axis_deviation_deg > vo.axis_tolerance_deg)
    add(Violation::Kind::Deviation, d.max_axis_nc_line, 0,
        fmt::format("tool axis leaves the CL orientation by {:.4f} deg (allowed {:.4f} deg)", d.max_axis_deviation_deg,
                    vo.axis_tolerance_deg));
  if (d.max_uncovered_cl_mm > vo.tip_tolerance_mm)
    add(Violation::Kind::Coverage, 0, d.max_uncovered_cl_line,
        std::isfinite(d.max_uncovered_cl_mm)
            ? fmt::format("the CL point is never reached (nearest programmed point {:.4f} mm away)",
                          d.max_uncovered_cl_mm)
            : std::string("the CL feed moves are never reached: the program has no feed blocks"));

  s.ok = s.violations.empty();
  if (s.ok) {
    s.message = fmt::format(
        "passed: {} blocks inside the limits, axis velocities up to {:.0f}% of max_feed, max tip deviation {:.5f} mm, "
        "max axis deviation {:.4f} deg{}",
        s.blocks, 100.0 * s.max_velocity_ratio, d.max_tip_deviation_mm, d.max_axis_deviation_deg,
        options.make_collision ? fmt::format(", {} collision checks inside the moves", s.collision_checks)
                               : std::string());
  } else {
    const Violation& v = s.violations.front();
    s.message = fmt::format("{}{}{}", v.message, v.nc_line ? fmt::format(" at NC line {}", v.nc_line) : std::string(),
                            v.cl_line ? fmt::format(" (CL line {})", v.cl_line) : std::string());
    if (s.violations.size() > 1) s.message += fmt::format("; {} more violation(s)", s.violations.size() - 1);
  }
  if (read_back) *read_back = std::move(ncp);
  return s;
}

Summary write_checked(const std::string& path, const std::string& nc_text, const cl::Program& cl,
                      const machine::Machine& machine, const kin::Kinematics& kinematics, const Options& options,
                      const std::vector<int>* cl_line_of_nc_line, nc::Program* read_back) {
  std::error_code ec;
  if (!cl.file.empty() && std::filesystem::equivalent(path, cl.file, ec))
    throw InputError(SourceLoc{path},
                     fmt::format("the NC output would overwrite its CL input {}: give another -o", cl.file));
  // The text goes to a temporary file beside `path` while it is checked (the check reads this same text): a program
  // that passes is then only renamed into place, and the temporary of one that fails is removed unread. Declared
  // in this order, the writer is joined before the temporary can go.
  PendingFile file(path);
  Background writer;
  writer.run([&] { file.write([&](std::ostream& os) { os << nc_text; }); });
  Summary s = check(nc_text, path, cl, machine, kinematics, options, cl_line_of_nc_line, read_back);
  if (!s.ok) {
    try {
      writer.wait();  // its own failure does not matter: the program is refused
    } catch (...) {
    }
    const Violation& v = s.violations.front();
    std::string where = v.cl_line ? fmt::format(" (from {})", SourceLoc{cl.file, v.cl_line, 0}.str()) : std::string();
    if (!v.cl_line && v.kind == Violation::Kind::Collision)
      where = fmt::format(
          " (a move the post added, not a CL move: its retracts and exits go {:g} mm along the tool axis "
          "(post.singularity.retract_mm), then along Z to the safe height (post.safe_z_mm); a retract along the tool "
          "axis in the CL, clear of the part, avoids it)",
          machine.post.singularity.retract_mm);
    std::string more;
    for (size_t i = 1; i < s.violations.size() && i < 5; ++i) {
      const Violation& w = s.violations[i];
      more += fmt::format("\n  also: {}{}{}", w.message, w.nc_line ? fmt::format(" at NC line {}", w.nc_line) : "",
                          w.cl_line ? fmt::format(" (CL line {})", w.cl_line) : "");
    }
    if (s.violations.size() > 5) more += fmt::format("\n  ... {} violations in all", s.violations.size());
    throw InputError(SourceLoc{path, v.nc_line, 0},
                     fmt::format("unsafe program not written: {}{}{}", v.message, where, more));
  }
  writer.wait();  // rethrows a failed write (no directory, disk full): nothing is in place then
  file.commit();
  return s;
}

}  // namespace cscam::gate
