#pragma once
/// @file
/// Swept collision check of a whole planned (or conventional) program: every move between consecutive CL points
/// as the straight joint-space move the control makes, and the reorientation between segments as the post performs
/// it (retract to the safe plane, rotate, position, plunge). Each move is certified by cspace::Space::swept.
#include <cstddef>
#include <string>
#include <vector>

#include "cscam/cl/program.hpp"
#include "cscam/cspace/cspace.hpp"
#include "cscam/machine/machine.hpp"

namespace cscam::plan {

/// One move that the swept check did not certify free.
struct SweptHit {
  std::size_t move = 0;  ///< index into Program::moves of the move's destination
  int line = 0;          ///< its CL line
  bool reorientation = false;  ///< a leg of the reorientation into that move (not the CL move itself)
  cspace::SweptResult result;
};

/// Summary of a program's swept check.
struct SweptSummary {
  std::size_t moves = 0;        ///< moves (and reorientation legs) checked
  std::size_t collisions = 0;   ///< of them colliding
  std::size_t uncertified = 0;  ///< of them neither certified free nor found colliding
  std::vector<SweptHit> hits;   ///< every colliding or uncertified move, in program order
};

/// The safe plane (Z axis value) the post reorients at, or NaN when the machine has no Z axis.
[[nodiscard]] double safe_z_of(const machine::Machine& machine);

/// Checks every move of `program` with axis values `axes` (one per CL move). A move into a feed point, or out of
/// one, is checked in Cutting mode (the cutting end may touch); a move between two rapid points, and the legs of a
/// reorientation in the air, in Rapid mode (the whole tool counts).
/// `certified` (optional, one flag per move): moves already certified free with these axis values, not checked again.
SweptSummary check_program(const cspace::Space& space, const machine::Machine& machine, const cl::Program& program,
                           const std::vector<kin::Axes>& axes, cspace::Counters& counters,
                           const std::vector<char>* certified = nullptr);

}  // namespace cscam::plan
