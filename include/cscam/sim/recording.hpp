#pragma once
/// @file
/// Recordings (shared/spec/recording.md): CSV with `# key: value` metadata, one header row, one row per
/// sample (trajectory) or pose (static). Empty cells are NaN ("not measured").
#include <optional>
#include <ostream>
#include <string>
#include <utility>
#include <vector>

#include "cscam/core/error.hpp"

namespace cscam::machine {
struct Machine;
}

namespace cscam::sim {

struct Recording {
  std::string file;                                       ///< where it was read from (messages)
  std::vector<std::pair<std::string, std::string>> meta;  ///< metadata in file order
  std::vector<int> meta_line;                             ///< 1-based file line of each metadata entry (0: set)
  std::vector<int> meta_col;                              ///< 1-based column of each entry's value (0: set)
  std::vector<std::string> columns;                       ///< header names
  int header_line = 0;                                    ///< 1-based file line of the header (0: built in memory)
  std::vector<std::vector<double>> data;                  ///< data[column][row]; NaN = empty cell
  std::vector<int> row_line;                              ///< 1-based file line of every row
  std::vector<std::string> warnings;                      ///< e.g. unknown columns

  [[nodiscard]] std::size_t rows() const { return data.empty() ? 0 : data.front().size(); }
  [[nodiscard]] int column(const std::string& name) const;  ///< -1 if absent
  [[nodiscard]] std::optional<std::string> meta_value(const std::string& key) const;
  /// Where a metadata entry's value is (file, line, column), for messages; the file alone when it was set.
  [[nodiscard]] SourceLoc meta_loc(const std::string& key) const;
  /// A numeric metadata value, if present. @throws InputError naming the file and line when it is not a finite
  /// number in [lo, hi].
  [[nodiscard]] std::optional<double> meta_number(const std::string& key, double lo, double hi) const;
  void set_meta(const std::string& key, const std::string& value);
  /// Adds a column (all NaN if `values` is empty) and returns its index.
  int add_column(const std::string& name, std::vector<double> values = {});
};

/// Parses a recording. Throws InputError with file:line:column on a malformed cell, a ragged row or a
/// non-monotonic `t` (naming the row).
Recording read_recording(const std::string& path);
Recording parse_recording(const std::string& text, const std::string& name);

/// Writes metadata, header and rows. `decimals` per column (default 6).
void write_recording(std::ostream& os, const Recording& rec, int decimals = 6);

/// Checks a trajectory recording against a machine: every machine axis must have a `cmd.<axis>`
/// column (error naming the missing column); columns the machine cannot predict (`len.*` of links the
/// machine does not define, `enc.` of a non-axis) are errors naming the column; other unknown columns
/// are added to rec.warnings.
void validate_against(Recording& rec, const machine::Machine& m);

}  // namespace cscam::sim
