// Signal watcher: a thread in sigwait, so that the cleanup runs as ordinary code, not inside a
// signal handler. SIGXFSZ and SIGPIPE are ignored: the write that meets them fails instead.
#include "foundation/interruptions.hpp"

#include <pthread.h>
#include <signal.h>
#include <unistd.h>

#include <csignal>
#include <cstdio>
#include <filesystem>
#include <mutex>
#include <set>
#include <system_error>
#include <thread>

namespace crepuscular {

namespace {

std::mutex g_mutex;
std::set<std::string>& partial_outputs() {
  static std::set<std::string> paths;
  return paths;
}
std::atomic<bool> g_stop{false};
std::atomic<bool> g_graceful{false};

[[noreturn]] void remove_and_exit(int signal) {
  {
    std::lock_guard<std::mutex> lock(g_mutex);
    for (const std::string& path : partial_outputs()) {
      std::error_code ec;
      std::filesystem::remove_all(path, ec);
    }
  }
  const char* name = signal == SIGINT ? "SIGINT" : signal == SIGTERM ? "SIGTERM" : "SIGHUP";
  std::fprintf(stderr, "\nerror: interrupted (%s%s): partial output removed\n", name,
               signal == SIGHUP ? ", the terminal closed" : "");
  std::fflush(stderr);
  ::_exit(128 + signal);
}

}  // namespace

void watch_interruptions() {
  // A write past the file size limit, or into a closed pipe or socket, fails (EFBIG, EPIPE) and
  // the writer reports it as an error, instead of the process dying with its files half written.
  std::signal(SIGXFSZ, SIG_IGN);
  std::signal(SIGPIPE, SIG_IGN);
  sigset_t set;
  sigemptyset(&set);
  sigaddset(&set, SIGINT);
  sigaddset(&set, SIGTERM);
  sigaddset(&set, SIGHUP);
  if (pthread_sigmask(SIG_BLOCK, &set, nullptr) != 0) return;
  std::thread([set] {
    for (;;) {
      int signal = 0;
      if (sigwait(&set, &signal) != 0) continue;
      if (g_graceful.exchange(false)) {  // the job stops at its next frame; a second signal ends it
        g_stop.store(true);
        continue;
      }
      remove_and_exit(signal);
    }
  }).detach();
}

void register_partial_output(const std::string& path) {
  std::lock_guard<std::mutex> lock(g_mutex);
  partial_outputs().insert(path);
}

void unregister_partial_output(const std::string& path) {
  std::lock_guard<std::mutex> lock(g_mutex);
  partial_outputs().erase(path);
}

const std::atomic<bool>* stop_flag_on_interruption() {
  g_stop.store(false);
  g_graceful.store(true);
  return &g_stop;
}

}  // namespace crepuscular
