#pragma once
/// @file
/// How many worker threads the parallel parts (simulate, diagnose) use. Every parallel loop partitions
/// its work by index and writes to fixed slots, so the output does not depend on this number; a test runs
/// the same input at 1, 2 and 3 threads and compares the bytes.
#include <cstdlib>
#include <string>
#include <thread>

namespace cscam {

/// CSCAM_THREADS when set to a positive number, else the hardware concurrency (at least 1).
inline std::size_t worker_threads() {
  if (const char* e = std::getenv("CSCAM_THREADS")) {
    char* end = nullptr;
    const long v = std::strtol(e, &end, 10);
    if (end != e && v > 0 && v <= 256) return static_cast<std::size_t>(v);
  }
  const unsigned h = std::thread::hardware_concurrency();
  return h ? h : 1;
}

}  // namespace cscam
