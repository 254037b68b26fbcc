#include "cscam/post/post.hpp"

#include <fmt/format.h>

#include <cmath>
#include <cstddef>
#include <ostream>
#include <sstream>
#include <string>
#include <utility>
#include <vector>

#include "cscam/core/error.hpp"
#include "cscam/core/units.hpp"
#include "cscam/post/dialect.hpp"
#include "linearize.hpp"
#include "sequencer.hpp"

// The post in three parts: the linearizer (linearize.cpp: where points must be inserted), the motion sequencer
// (which blocks, in which order) and one formatter per dialect (dialects.cpp: how a controller family spells them).
// The sequencer is the class detail::Sequencer (sequencer.hpp), its member functions defined by concern:
// sequencer.cpp (construction, the run over the program, CL events, the program's end, the buffer, word emission),
// sequencer_modes.cpp (tool-tip control, tilted work planes, rotary clamps, blend modes and corner bounds),
// sequencer_rapid.cpp (rapids, retracts, flips and unwinds, PKM repositioning), sequencer_feed.cpp (feeds, arcs,
// linearised feeds and their timing, the segments split ahead) and sequencer_tcp.cpp (Cartesian blocks under
// tool-tip control). This file: the post's public functions (write_nc, can_follow, dialects).

namespace cscam::post {

std::vector<std::string> dialects() { return dialect_names(); }

bool can_follow(const kin::Kinematics& kinematics, const machine::Machine& machine, const Options& options,
                const kin::Posed& p0, const kin::Axes& q0, const kin::Posed& p1, const kin::Axes& q1) {
  Linearizer lin(kinematics, detail::linearizer_settings(machine, options));
  cl::Move m0, m1;
  m0.tip_in_part_mm = p0.tip_mm;
  m0.axis_in_part = p0.axis;
  m1.tip_in_part_mm = p1.tip_mm;
  m1.axis_in_part = p1.axis;
  std::vector<Linearizer::Piece> pieces;
  Linearizer::Stats stats;
  try {
    lin.split(m0, q0, m1, q1, std::string(), pieces, stats);
  } catch (const InputError&) {
    return false;  // where the post would refuse the segment (a flip, or the rotaries turning too fast)
  }
  return true;
}

namespace {

/// A std::ostringstream sink that nothing was written to yet (the CLI's, the benchmark's) gets room for the expected
/// text at once: it would otherwise double its buffer some twenty times for a million-block program, copying the text
/// and faulting in twice its size. Room never written costs no memory; a longer text regrows as before.
void reserve_text(std::ostream& out, std::size_t bytes) {
  auto* s = dynamic_cast<std::ostringstream*>(&out);
  if (s == nullptr || s->tellp() != std::streampos(0) || !s->view().empty()) return;
  std::string room;
  room.reserve(bytes);
  s->str(std::move(room));
}

}  // namespace

void write_nc(std::ostream& out, const cl::Program& program, const machine::Machine& machine,
              const kin::Kinematics& kinematics, const std::vector<kin::Axes>& axes, const Options& options,
              Summary& summary) {
  CSCAM_CHECK(axes.size() == program.moves.size(), "one axis vector per CL move");
  CSCAM_CHECK(!options.cone_reference || options.cone_reference->moves.size() == program.moves.size(),
              "the cone's reference CL has the program's moves");
  {
    // A tolerance finer than the words' last decimal cannot be held: rounding the words alone moves the tip by up to
    // half that unit, and the blend limit (G64 P) would print as 0, which LinuxCNC reads as no limit at all.
    const double tol_mm = options.tolerance_mm > 0 ? options.tolerance_mm : machine.post.tolerance_mm;
    const double unit_mm = std::pow(10.0, -machine.post.decimals_linear) * (machine.post.inch ? kMmPerInch : 1.0);
    if (tol_mm < unit_mm)
      throw InputError(
          fmt::format("tolerance {:g} mm is finer than the program's linear words carry ({} decimals{}: "
                      "{:g} mm): give at least that, or more decimals (post.decimals_linear)",
                      tol_mm, machine.post.decimals_linear, machine.post.inch ? " of an inch" : "", unit_mm));
    const double axis_tol_deg =
        options.axis_tolerance_deg > 0 ? options.axis_tolerance_deg : machine.post.axis_tolerance_deg;
    const double unit_deg = std::pow(10.0, -machine.post.decimals_rotary);
    if (axis_tol_deg < unit_deg)
      throw InputError(
          fmt::format("axis tolerance {:g} deg is finer than the program's rotary words carry ({} "
                      "decimals: {:g} deg): give at least that, or more decimals (post.decimals_rotary)",
                      axis_tol_deg, machine.post.decimals_rotary, unit_deg));
  }
  reserve_text(out, 96 * program.moves.size() + (std::size_t{1} << 16));  // ~50-65 bytes a block, a block a move
  {
    Summary probe;
    if (detail::Sequencer(out, program, machine, kinematics, options, probe).planes_only(axes)) {
      Options machine_words = options;
      machine_words.tcp = false;
      detail::Sequencer w(out, program, machine, kinematics, machine_words, summary);
      summary.warnings.push_back(
          fmt::format("{}: tool-tip control asked for, but every stretch is cut in a tilted work plane: written in "
                      "machine coordinates (TCP would be cancelled around every plane)",
                      program.file));
      w.run(axes);
      return;
    }
  }
  detail::Sequencer w(out, program, machine, kinematics, options, summary);
  w.run(axes);
}

}  // namespace cscam::post
