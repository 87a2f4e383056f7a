// A timeline of a run for the engineers who tune it: with CREPUSCULAR_TRACE=FILE set, named
// events (seconds since the first event, the breathing phase in the order of computation or -1,
// a count) are kept in memory and appended to FILE when the process exits, one per line:
//   12.3456 3 eval_begin 1687507
// bench/timeline.py reads it (when the GPU was busy, which phase waited for what). Without the
// variable an event costs one test of a flag. Header-only: the CUDA launchers record too.
#pragma once

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <mutex>
#include <string>
#include <vector>

namespace crepuscular::trace {

struct Event {
  double seconds;
  int phase;
  std::string what;
  long long count;
};

namespace detail {
inline std::mutex& mutex() {
  static std::mutex m;
  return m;
}
inline std::vector<Event>& events() {
  static std::vector<Event> e;
  return e;
}
inline std::chrono::steady_clock::time_point start() {
  static const auto t = std::chrono::steady_clock::now();
  return t;
}
inline void dump() {
  const char* file = std::getenv("CREPUSCULAR_TRACE");
  std::FILE* out = file ? std::fopen(file, "a") : nullptr;
  if (!out) return;
  const std::lock_guard<std::mutex> lock(mutex());
  for (const Event& e : events()) {
    std::fprintf(out, "%.4f %d %s %lld\n", e.seconds, e.phase, e.what.c_str(), e.count);
  }
  std::fprintf(out, "---\n");
  std::fclose(out);
}
// Whether tracing is on; the first call starts the clock and registers the dump (after the
// buffers exist, so that they outlive it).
inline bool on() {
  static const bool enabled = [] {
    start();
    events();
    mutex();
    const bool set = std::getenv("CREPUSCULAR_TRACE") != nullptr;
    if (set) std::atexit(dump);
    return set;
  }();
  return enabled;
}
}  // namespace detail

// The phase this thread computes (-1: none), set by the breathing driver on a phase's thread.
inline int& current_phase() {
  thread_local int phase = -1;
  return phase;
}

// Records `what` (no spaces) with `count`, for `phase` (kThisThread: current_phase()).
constexpr int kThisThread = -2;
inline void event(const std::string& what, long long count = 0, int phase = kThisThread) {
  if (!detail::on()) return;
  const double s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - detail::start()).count();
  const std::lock_guard<std::mutex> lock(detail::mutex());
  detail::events().push_back({s, phase == kThisThread ? current_phase() : phase, what, count});
}

}  // namespace crepuscular::trace
