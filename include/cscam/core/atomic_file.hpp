#pragma once
/// @file
/// Write a file atomically: to a temporary beside it, then rename. Nothing partial is left on error.
#include <fstream>
#include <functional>
#include <string>

namespace cscam {

/// Calls `write(stream)` on a temporary file next to `path`, then renames it to `path`.
/// If `write` throws, the temporary is removed and the exception propagates; `path` is untouched.
void write_file_atomically(const std::string& path, const std::function<void(std::ostream&)>& write);

}  // namespace cscam
