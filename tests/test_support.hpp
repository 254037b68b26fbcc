#pragma once
// Shared test helpers: paths, seeded randomness, and the tolerances (all from cscam/core/tolerances.hpp).
#include <cstdio>
#include <fstream>
#include <functional>
#include <iterator>
#include <random>
#include <string>

#include "cscam/core/error.hpp"
#include "cscam/core/tolerances.hpp"

namespace cscam::test {

inline std::string source_path(const std::string& rel) { return std::string(CSCAM_SOURCE_DIR) + "/" + rel; }

/// A file's whole text ("" if it cannot be read).
inline std::string read_text(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

/// The message of the InputError that f throws, or "(no error)".
inline std::string error_of(const std::function<void()>& f) {
  try {
    f();
  } catch (const InputError& e) {
    return e.what();
  }
  return "(no error)";
}

/// Every randomised test draws from this seed so failures reproduce.
inline constexpr unsigned kSeed = 20261122u;
inline std::mt19937_64 rng(unsigned salt = 0) { return std::mt19937_64(kSeed + salt); }

/// Runs a shell command, returns its exit status and captures stdout (+stderr if merge).
struct CommandResult {
  int status = -1;
  std::string output;
};
inline CommandResult run_command(const std::string& cmd) {
  CommandResult r;
  FILE* p = ::popen((cmd + " 2>&1").c_str(), "r");
  if (!p) return r;
  char buf[4096];
  size_t n;
  while ((n = fread(buf, 1, sizeof buf, p)) > 0) r.output.append(buf, n);
  int st = ::pclose(p);
  r.status = WIFEXITED(st) ? WEXITSTATUS(st) : -1;
  return r;
}

}  // namespace cscam::test
