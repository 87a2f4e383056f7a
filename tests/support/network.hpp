// Tests that talk over 127.0.0.1: a free port, and a helper program run in the background.
#pragma once

#include <string>

namespace crepuscular::test {

// A TCP port free on 127.0.0.1 now: bound by the system, then released for the test to use.
int free_loopback_port();

// `command` started by the shell in the background (its output discarded); killed when this
// object goes (SIGKILL), whatever the test's outcome.
class BackgroundProcess {
 public:
  explicit BackgroundProcess(const std::string& command);
  ~BackgroundProcess();
  BackgroundProcess(const BackgroundProcess&) = delete;
  BackgroundProcess& operator=(const BackgroundProcess&) = delete;
  int pid() const { return pid_; }

 private:
  int pid_ = 0;
};

}  // namespace crepuscular::test
