// Closing an OpenIGTLink socket for good. The library's Socket::CloseSocket (1.11, Debian) only
// shuts the connection down and never closes the descriptor: a server accepting connection
// after connection runs out of descriptors (found by fuzzing). close_socket() does both.
#pragma once

#include <igtlSocket.h>
#include <unistd.h>

namespace crepuscular::igtlink {

// The descriptor is protected in igtl::Socket; a pointer to member through a derived class
// reads it on any socket.
struct SocketDescriptor : igtl::Socket {
  static int of(igtl::Socket& socket) { return socket.*(&SocketDescriptor::m_SocketDescriptor); }
};

inline void close_socket(igtl::Socket& socket) {
  const int fd = SocketDescriptor::of(socket);
  socket.CloseSocket();  // shutdown
  if (fd >= 0) ::close(fd);
}

}  // namespace crepuscular::igtlink
