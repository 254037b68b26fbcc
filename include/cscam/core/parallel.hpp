#pragma once
/// @file
/// The parallel loops of cspace-cam, on TBB; in a ThreadSanitizer build on plain threads.
///
/// Debian's TBB library is not instrumented, so ThreadSanitizer cannot see the synchronisation inside it (task
/// spawning, stealing, the join) and reports dozens of races in TBB's own partitioner and allocator, which hide
/// any real race in our loop bodies. A TSan build (CSCAM_TSAN) therefore runs the same bodies on std::threads,
/// whose creation and join TSan does see: what it then checks is exactly whether our bodies race with each other
/// or with the code around the loop. Release builds use TBB unchanged.
#include <cstddef>
#include <exception>
#include <utility>

#if defined(__SANITIZE_THREAD__)
#define CSCAM_TSAN_BUILD 1
#elif defined(__has_feature)
#if __has_feature(thread_sanitizer)
#define CSCAM_TSAN_BUILD 1
#endif
#endif

#include <tbb/blocked_range.h>
#ifdef CSCAM_TSAN_BUILD
#include <algorithm>
#include <atomic>
#include <thread>
#include <vector>

#include "cscam/core/threads.hpp"
#else
#include <tbb/parallel_for.h>
#include <tbb/parallel_invoke.h>
#include <tbb/task_group.h>
#endif

namespace cscam {

/// body(tbb::blocked_range<std::size_t>) over [begin, end) in pieces of at least `grain`, in parallel.
template <typename Body>
void parallel_range(std::size_t begin, std::size_t end, std::size_t grain, const Body& body) {
#ifdef CSCAM_TSAN_BUILD
  grain = std::max<std::size_t>(grain, 1);
  const std::size_t pieces = end > begin ? (end - begin + grain - 1) / grain : 0;
  const std::size_t threads = std::min<std::size_t>(std::max<std::size_t>(worker_threads(), 2), pieces);
  std::atomic<std::size_t> next{0};
  std::exception_ptr error;
  std::atomic<bool> failed{false};
  auto work = [&] {
    for (std::size_t p; (p = next.fetch_add(1)) < pieces;) {
      if (failed.load()) return;
      const std::size_t b = begin + p * grain;
      try {
        body(tbb::blocked_range<std::size_t>(b, std::min(end, b + grain)));
      } catch (...) {
        if (!failed.exchange(true)) error = std::current_exception();
      }
    }
  };
  std::vector<std::thread> pool;
  for (std::size_t t = 1; t < threads; ++t) pool.emplace_back(work);
  work();
  for (auto& t : pool) t.join();
  if (error) std::rethrow_exception(error);
#else
  tbb::parallel_for(tbb::blocked_range<std::size_t>(begin, end, std::max<std::size_t>(grain, 1)), body);
#endif
}

/// f() and g() in parallel.
template <typename F, typename G>
void parallel_invoke(const F& f, const G& g) {
#ifdef CSCAM_TSAN_BUILD
  std::exception_ptr error;
  std::thread t([&] {
    try {
      f();
    } catch (...) {
      error = std::current_exception();
    }
  });
  try {
    g();
  } catch (...) {
    t.join();
    throw;
  }
  t.join();
  if (error) std::rethrow_exception(error);
#else
  tbb::parallel_invoke(f, g);
#endif
}

/// One job started now that runs beside the caller until wait() (or the destructor) joins it. wait() rethrows
/// what the job threw.
class Background {
 public:
  Background() = default;
  template <typename F>
  void run(F f) {
#ifdef CSCAM_TSAN_BUILD
    thread_ = std::thread([this, f = std::move(f)] {
      try {
        f();
      } catch (...) {
        error_ = std::current_exception();
      }
    });
#else
    group_.run(std::move(f));
#endif
  }
  void wait() {
#ifdef CSCAM_TSAN_BUILD
    if (thread_.joinable()) thread_.join();
    if (error_) std::rethrow_exception(std::exchange(error_, nullptr));
#else
    group_.wait();
#endif
  }
  ~Background() {
#ifdef CSCAM_TSAN_BUILD
    if (thread_.joinable()) thread_.join();
#else
    try {
      group_.wait();
    } catch (...) {  // a job's error is only reported through wait(); here the caller is already unwinding
    }
#endif
  }
  Background(const Background&) = delete;
  Background& operator=(const Background&) = delete;

 private:
#ifdef CSCAM_TSAN_BUILD
  std::thread thread_;
  std::exception_ptr error_;
#else
  tbb::task_group group_;
#endif
};

}  // namespace cscam
