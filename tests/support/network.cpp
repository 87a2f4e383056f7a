#include "tests/support/network.hpp"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <csignal>
#include <cstdio>

#include "foundation/error.hpp"

namespace crepuscular::test {

int free_loopback_port() {
  const int probe = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  socklen_t length = sizeof(address);
  const bool ok = ::bind(probe, reinterpret_cast<sockaddr*>(&address), sizeof(address)) == 0 &&
                  ::getsockname(probe, reinterpret_cast<sockaddr*>(&address), &length) == 0;
  ::close(probe);
  if (!ok) throw Error("tests: no free TCP port on 127.0.0.1");
  return ntohs(address.sin_port);
}

BackgroundProcess::BackgroundProcess(const std::string& command) {
  FILE* pipe = ::popen((command + " > /dev/null 2>&1 & echo $!").c_str(), "r");
  if (pipe == nullptr) throw Error("tests: cannot start " + command);
  const int read = std::fscanf(pipe, "%d", &pid_);
  ::pclose(pipe);
  if (read != 1 || pid_ <= 0) throw Error("tests: cannot start " + command);
}

BackgroundProcess::~BackgroundProcess() { ::kill(pid_, SIGKILL); }

}  // namespace crepuscular::test
