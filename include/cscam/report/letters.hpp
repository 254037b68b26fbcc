#pragma once
/// @file
/// The NC reader's view of a machine: the G-code letter of each axis and which axes are rotary.
#include <fmt/format.h>

#include <optional>
#include <string>

#include "cscam/core/error.hpp"
#include "cscam/machine/machine.hpp"
#include "cscam/nc/reader.hpp"

namespace cscam::report {

/// Letters and rotary flags of the machine's five axes, for nc::read_file / read_text.
inline nc::AxisLetters axis_letters(const machine::Machine& m) {
  nc::AxisLetters l;
  for (std::size_t i = 0; i < 5; ++i) {
    l.letter[i] = m.post.letters[i][0];
    l.rotary[i] = m.axes[i].rotary();
    l.modulo[i] = m.axes[i].rotary() && m.axes[i].cyclic && m.post.rotary_output == "shortest";
  }
  return l;
}

/// Checks that `program` (read with axis_letters(m)) was written for machine `m`.
/// - An axis word (X Y Z A B C U V W) that the machine has no axis for throws an InputError at its file:line:column:
///   the reader ignores such words, so the program's motion would be silently misread.
/// - A header "(cscam post: machine NAME ...)" naming another machine is returned as an error at the header's line
///   for the caller to throw or print: the letters may well match (two X Y Z B C machines), but the kinematics do
///   not. verify throws it, stats (which only counts axis motion) prints it as a warning.
inline std::optional<InputError> check_machine_of(const nc::Program& program, const machine::Machine& m) {
  if (!program.foreign_axis_words.empty()) {
    const auto& f = program.foreign_axis_words.front();
    std::string mine, theirs;
    for (const auto& l : m.post.letters) mine += (mine.empty() ? "" : " ") + l;
    for (const auto& w : program.foreign_axis_words) theirs += (theirs.empty() ? "" : " ") + std::string(1, w.letter);
    throw InputError(
        SourceLoc{program.file, f.line, f.column},
        fmt::format("axis word '{}' but machine '{}' has no such axis (its letters: {}; letters in the program that "
                    "it lacks: {}): the program was written for another machine{}",
                    f.letter, m.name, mine, theirs,
                    program.header_machine ? fmt::format(" ('{}', says its header)", *program.header_machine) : ""));
  }
  if (program.header_machine && *program.header_machine != m.name)
    return InputError(SourceLoc{program.file, program.header_line, 0},
                      fmt::format("the program was written for machine '{}' (its header says so), not for '{}' given "
                                  "with --machine",
                                  *program.header_machine, m.name));
  return std::nullopt;
}

}  // namespace cscam::report
