#pragma once
/// @file
/// Write a file atomically: to a temporary beside it, then rename. Nothing partial is left on error.
#include <filesystem>
#include <fstream>
#include <functional>
#include <string>

namespace cscam {

/// Calls `write(stream)` on a temporary file next to `path`, then renames it to `path`.
/// If `write` throws, the temporary is removed and the exception propagates; `path` is untouched.
void write_file_atomically(const std::string& path, const std::function<void(std::ostream&)>& write);

/// write_file_atomically in two steps, for writing while something else decides whether the file may exist:
/// write() fills the temporary beside `path`, commit() renames it to `path`; a temporary not committed is removed
/// by the destructor (and by a write() or commit() that throws). `path` is untouched until commit().
class PendingFile {
 public:
  explicit PendingFile(std::string path) : path_(std::move(path)) {}
  PendingFile(const PendingFile&) = delete;
  PendingFile& operator=(const PendingFile&) = delete;
  ~PendingFile();
  /// Calls `write(stream)` on the temporary; throws InputError (directory missing, write failed) or what `write`
  /// throws.
  void write(const std::function<void(std::ostream&)>& write);
  /// Renames the written temporary to `path`.
  void commit();

 private:
  void remove_temporary() noexcept;
  std::string path_;
  std::filesystem::path tmp_;  ///< empty: no temporary on disk
};

}  // namespace cscam
