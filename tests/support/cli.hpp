// Runs a shell command (and the `crepuscular` command line) from a test: exit code and output.
#pragma once

#include <string>

namespace crepuscular::test {

// Which of a command's output streams run_command hands back; the other goes to /dev/null.
enum class Capture {
  kStdoutAndStderr,  // both, interleaved as printed
  kStderr,           // error messages only
};

// Runs `command` through /bin/sh. Returns its exit code, or -1 when it did not exit (a signal).
// With `output`, fills it with the streams `capture` names; without, all output is discarded.
int run_command(const std::string& command, std::string* output = nullptr,
                Capture capture = Capture::kStdoutAndStderr);

// `crepuscular ARGS` (ARGS as the shell reads them), as run_command. CREPUSCULAR_BINARY is defined
// only in test programs declared with crepuscular_add_test(... CLI), which wait for the binary.
#if defined(CREPUSCULAR_BINARY)
inline int run_cli(const std::string& args, std::string* output = nullptr,
                   Capture capture = Capture::kStdoutAndStderr) {
  return run_command(std::string(CREPUSCULAR_BINARY) + " " + args, output, capture);
}
#endif

}  // namespace crepuscular::test
