#pragma once
/// @file
/// The NC reader's view of a machine: the G-code letter of each axis and which axes are rotary.
#include "cscam/machine/machine.hpp"
#include "cscam/nc/reader.hpp"

namespace cscam::report {

/// Letters and rotary flags of the machine's five axes, for nc::read_file / read_text.
inline nc::AxisLetters axis_letters(const machine::Machine& m) {
  nc::AxisLetters l;
  for (std::size_t i = 0; i < 5; ++i) {
    l.letter[i] = m.post.letters[i][0];
    l.rotary[i] = m.axes[i].rotary();
  }
  return l;
}

}  // namespace cscam::report
