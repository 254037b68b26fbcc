#pragma once
// Parallel loops of the planner over an immutable C-space (private to src/plan/).
//
// The planner runs many small loops (a beam block of a few hundred cells, the rows of a distance transform): an
// arena and per-thread FCL workspaces made afresh for each of them cost more than the loop itself once most cells
// are certified without a query. So the arena is made once per thread count and kept, and every thread keeps its
// query workspace for its lifetime. Loops too small to share, or a single worker, run inline.
#include <tbb/blocked_range.h>
#include <tbb/enumerable_thread_specific.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include <cstddef>
#include <map>
#include <memory>
#include <mutex>

#include "cscam/core/parallel.hpp"
#include "cscam/core/threads.hpp"
#include "cscam/cspace/cspace.hpp"

namespace cscam::plan::detail {

/// The arena of `threads` workers, made on first use and kept (arenas are safe to enter from several threads).
inline tbb::task_arena& planner_arena(int threads) {
  static std::mutex mu;
  static std::map<int, std::unique_ptr<tbb::task_arena>> arenas;
  const std::lock_guard<std::mutex> lock(mu);
  auto& a = arenas[threads];
  if (!a) a = std::make_unique<tbb::task_arena>(threads);
  return *a;
}

/// This thread's collision-query workspace (FCL objects reused across loops).
inline geom::QueryWorkspace& thread_workspace() {
  thread_local geom::QueryWorkspace ws;
  return ws;
}

/// Evaluates items in parallel over the immutable space, one workspace per thread. `job(i, ws, counters)` must only
/// touch item i, so the outcome (and the summed counters) does not depend on the thread count.
template <typename Job>
void parallel_items(std::size_t n, cspace::Counters& total, Job&& job) {
  const int threads = static_cast<int>(worker_threads());
  if (n <= 1 || threads <= 1) {
    for (std::size_t i = 0; i < n; ++i) job(i, thread_workspace(), total);
    return;
  }
  tbb::enumerable_thread_specific<cspace::Counters> locals;
  planner_arena(threads).execute([&] {
    parallel_range(0, n, 1, [&](const tbb::blocked_range<std::size_t>& r) {
      cspace::Counters& c = locals.local();
      geom::QueryWorkspace& ws = thread_workspace();
      for (std::size_t i = r.begin(); i != r.end(); ++i) job(i, ws, c);
    });
  });
  for (const cspace::Counters& c : locals) total += c;
}

/// Runs `job(i)` for i in [0, n) in parallel (pure computations that write slot i only).
template <typename Job>
void parallel_indices(std::size_t n, Job&& job) {
  const int threads = static_cast<int>(worker_threads());
  if (n <= 1 || threads <= 1) {
    for (std::size_t i = 0; i < n; ++i) job(i);
    return;
  }
  planner_arena(threads).execute([&] {
    parallel_range(0, n, 1, [&](const tbb::blocked_range<std::size_t>& r) {
      for (std::size_t i = r.begin(); i != r.end(); ++i) job(i);
    });
  });
}

}  // namespace cscam::plan::detail
