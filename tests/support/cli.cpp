#include "tests/support/cli.hpp"

#include <sys/wait.h>

#include <array>
#include <cstdio>
#include <cstdlib>

namespace crepuscular::test {

int run_command(const std::string& command, std::string* output, Capture capture) {
  int status = 0;
  if (!output) {
    status = std::system((command + " > /dev/null 2>&1").c_str());
  } else {
    const std::string redirect = capture == Capture::kStderr ? " 2>&1 > /dev/null" : " 2>&1";
    output->clear();
    FILE* pipe = ::popen((command + redirect).c_str(), "r");
    if (!pipe) return -1;
    std::array<char, 4096> buffer{};
    size_t n = 0;
    while ((n = std::fread(buffer.data(), 1, buffer.size(), pipe)) > 0) {
      output->append(buffer.data(), n);
    }
    status = ::pclose(pipe);
  }
  return status != -1 && WIFEXITED(status) ? WEXITSTATUS(status) : -1;
}

}  // namespace crepuscular::test
