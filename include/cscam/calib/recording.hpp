#pragma once
/// @file
/// Recordings (spec/recording.md): CSV with `# key: value` metadata lines at the top, one header row,
/// one row per sample (`kind: trajectory`, with a strictly increasing `t`) or per pose
/// (`kind: static`). Empty cells mean "not measured" and are read as NaN. Every error names the file,
/// the line and (where it applies) the column.
#include <Eigen/Core>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "cscam/core/error.hpp"

namespace cscam::calib {

/// A recording in memory. Values are in the file's units (mm, deg, s, ...).
struct Recording {
  std::string file;                          ///< path or name used in messages
  std::map<std::string, std::string> meta;   ///< the `# key: value` lines
  std::map<std::string, SourceLoc> meta_at;  ///< where each value is (file, line, column), for messages
  std::vector<std::string> columns;          ///< header, in file order
  std::vector<int> line_of_row;              ///< 1-based source line of every data row
  int header_line = 0;                       ///< 1-based line of the header row
  Eigen::MatrixXd data;                      ///< rows x columns, NaN = not measured

  /// `kind` metadata: "trajectory", "static" or empty when not given.
  [[nodiscard]] std::string kind() const;
  /// `tool_length` metadata in mm, if given.
  [[nodiscard]] std::optional<double> tool_length_mm() const;
  /// Where a metadata value is (file:line:column), or the file alone when it was not read from one.
  [[nodiscard]] SourceLoc meta_loc(const std::string& key) const;
  /// A metadata value as a plain number (no unit; from_chars, the whole value) that is positive (or >= 0 with
  /// `zero_ok`), if given. @throws InputError at the value's file:line:column otherwise.
  [[nodiscard]] std::optional<double> meta_number(const std::string& key, bool zero_ok = false) const;
  /// Index of a column by name, or -1.
  [[nodiscard]] int column(const std::string& name) const;
  [[nodiscard]] bool has(const std::string& name) const { return column(name) >= 0; }
  [[nodiscard]] Eigen::Index rows() const { return data.rows(); }
};

/// Reads a recording file with the sim module's reader (sim::read_recording), then adds the
/// calibration view. Throws InputError (file:line:column) on malformed input: a non-numeric cell, a
/// row with the wrong number of cells, a duplicate or unknown column (the known families are t,
/// cmd.*, enc.*, tip.*, ptip.*, dir.*, len.*, acc.*, temp.*), a `kind` other than trajectory or
/// static, a missing or non-increasing `t` in a trajectory (a recording without `kind` is a
/// trajectory).
Recording read_recording(const std::string& path);
/// The same from text; `name` is used in messages.
Recording parse_recording(const std::string& text, const std::string& name);

/// Checks the recording against a machine's axes (lower-case names): every `cmd.<axis>` and
/// `enc.<axis>` must name an axis of the machine (else InputError naming the column and listing the
/// axes), every axis needs a `cmd.<axis>` column, and `len.<link>` must name a link in `links`.
void check_axes(const Recording& rec, const std::vector<std::string>& axes, const std::vector<std::string>& links);

/// Writes a recording (metadata, header, rows; NaN as an empty cell) with full precision.
std::string format_recording(const Recording& rec);

}  // namespace cscam::calib
