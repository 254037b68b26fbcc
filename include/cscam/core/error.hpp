#pragma once
/// @file
/// Errors that carry where and what: `file:line:column: message`.
#include <stdexcept>
#include <string>

namespace cscam {

/// A position in a user's input file. line/column are 1-based; 0 means "unknown".
struct SourceLoc {
  std::string file;
  int line = 0;
  int column = 0;

  /// "file:line:column", dropping the parts that are unknown.
  [[nodiscard]] std::string str() const;
};

/// Bad user input: a malformed file, an unreachable pose, an impossible option.
/// The CLI prints what() and exits non-zero.
class InputError : public std::runtime_error {
 public:
  InputError(SourceLoc where, const std::string& what);
  explicit InputError(const std::string& what);
  [[nodiscard]] const SourceLoc& where() const { return where_; }
  /// The message without the location prefix.
  [[nodiscard]] const std::string& message() const { return message_; }

 private:
  SourceLoc where_;
  std::string message_;
};

/// An always-on invariant check: a violated invariant is a bug in cscam, not bad input.
[[noreturn]] void invariant_failed(const char* expr, const char* file, int line, const std::string& msg);

}  // namespace cscam

#define CSCAM_CHECK(cond, msg)                                                \
  do {                                                                        \
    if (!(cond)) ::cscam::invariant_failed(#cond, __FILE__, __LINE__, (msg)); \
  } while (0)
