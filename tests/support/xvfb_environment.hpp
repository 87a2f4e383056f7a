// For overlay test programs run directly without a display (ctest runs them under xvfb-run): a
// private Xvfb for the whole suite, started when DISPLAY is unset and Xvfb is installed.
// Include in exactly one file of a test program.
#pragma once

#include <gtest/gtest.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>

#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <string>
#include <thread>
#include <vector>

extern char** environ;

namespace crepuscular::test {

class XvfbEnvironment : public ::testing::Environment {
 public:
  void SetUp() override {
    const char* display = std::getenv("DISPLAY");
    if ((display && *display) || !std::filesystem::exists("/usr/bin/Xvfb")) return;
    for (int n = 99; n < 130; ++n) {
      if (std::filesystem::exists("/tmp/.X" + std::to_string(n) + "-lock")) continue;
      const std::string name = ":" + std::to_string(n);
      std::vector<std::string> args = {"Xvfb", name, "-screen", "0", "1920x1080x24", "-nolisten",
                                       "tcp"};
      std::vector<char*> argv;
      for (auto& a : args) argv.push_back(a.data());
      argv.push_back(nullptr);
      if (posix_spawn(&pid_, "/usr/bin/Xvfb", nullptr, nullptr, argv.data(), environ) != 0) return;
      const std::string socket = "/tmp/.X11-unix/X" + std::to_string(n);
      for (int i = 0; i < 100 && !std::filesystem::exists(socket); ++i)
        std::this_thread::sleep_for(std::chrono::milliseconds(50));
      if (std::filesystem::exists(socket)) {
        setenv("DISPLAY", name.c_str(), 1);
        return;
      }
      TearDown();
    }
  }
  void TearDown() override {
    if (pid_ > 0) {
      kill(pid_, SIGTERM);
      waitpid(pid_, nullptr, 0);
      pid_ = 0;
    }
  }

 private:
  pid_t pid_ = 0;
};

inline ::testing::Environment* const xvfb_environment =
    ::testing::AddGlobalTestEnvironment(new XvfbEnvironment);

}  // namespace crepuscular::test
