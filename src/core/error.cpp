#include "cscam/core/error.hpp"

#include <fmt/format.h>

namespace cscam {

std::string SourceLoc::str() const {
  if (file.empty() && line == 0) return {};
  std::string s = file.empty() ? std::string("<input>") : file;
  if (line > 0) s += fmt::format(":{}", line);
  if (line > 0 && column > 0) s += fmt::format(":{}", column);
  return s;
}

InputError::InputError(SourceLoc where, const std::string& what)
    : std::runtime_error(where.str().empty() ? what : where.str() + ": " + what),
      where_(std::move(where)),
      message_(what) {}

InputError::InputError(const std::string& what) : std::runtime_error(what), message_(what) {}

void invariant_failed(const char* expr, const char* file, int line, const std::string& msg) {
  throw std::logic_error(fmt::format("internal error at {}:{}: check '{}' failed: {}", file, line, expr, msg));
}

}  // namespace cscam
