#include "igtl/pose_receiver.hpp"

#include <igtlClientSocket.h>
#include <igtlMessageHeader.h>
#include <igtlServerSocket.h>
#include <igtlTrackingDataMessage.h>
#include <igtlTransformMessage.h>
#include <igtl_header.h>
#include <igtl_transform.h>
#include <igtl_util.h>

#include <algorithm>
#include <csignal>
#include <cstring>

#include "foundation/error.hpp"
#include "foundation/log.hpp"
#include "igtl/socket_close.hpp"

namespace crepuscular::igtlink {

struct PoseReceiver::Listener {
  igtl::ServerSocket::Pointer socket = igtl::ServerSocket::New();
};

struct PoseReceiver::Connection {
  igtl::ClientSocket::Pointer socket;
};

namespace {

int parse_port(const std::string& text, const std::string& uri) {
  char* end = nullptr;
  const long port = std::strtol(text.c_str(), &end, 10);
  if (text.empty() || *end != '\0' || port < 0 || port > 65535) {
    throw Error(uri + ": port '" + text + "' is not a TCP port (0 to 65535)");
  }
  return int(port);
}

Eigen::Isometry3d isometry(igtl::Matrix4x4& m) {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 4; ++c) T.matrix()(r, c) = m[r][c];
  }
  return T;
}

// A pose a tracker could mean: finite, a rotation (orthonormal within 1e-3), within 10 m.
bool plausible(const Eigen::Isometry3d& T) {
  if (!T.matrix().allFinite() || T.translation().norm() > 1e4) return false;
  const Eigen::Matrix3d R = T.linear();
  return (R.transpose() * R - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff() < 1e-3 &&
         R.determinant() > 0;
}

}  // namespace

PoseReceiver::PoseReceiver(const std::string& uri) : uri_(uri) {
  // The library's own "Debug: ... Failed to connect" lines to stderr are replaced by ours.
  igtl::Object::SetGlobalWarningDisplay(false);
  const std::string client_prefix = "igtl://", server_prefix = "igtl-server:";
  if (uri.rfind(client_prefix, 0) == 0) {
    const std::string rest = uri.substr(client_prefix.size());
    const size_t colon = rest.rfind(':');
    if (colon == std::string::npos || colon == 0) {
      throw Error(uri + ": expected igtl://HOST:PORT (e.g. igtl://localhost:18944)");
    }
    host_ = rest.substr(0, colon);
    port_ = parse_port(rest.substr(colon + 1), uri);
  } else if (uri.rfind(server_prefix, 0) == 0) {
    server_ = true;
    port_ = parse_port(uri.substr(server_prefix.size()), uri);
    listener_ = std::make_unique<Listener>();
    if (listener_->socket->CreateServer(port_) != 0) {
      throw Error(uri + ": cannot listen on port " + std::to_string(port_) + " (in use?)");
    }
    port_ = listener_->socket->GetServerPort();
  } else {
    throw Error(uri + ": expected igtl://HOST:PORT (connect to a tracking server) or "
                      "igtl-server:PORT (let the tracker connect)");
  }
  std::signal(SIGPIPE, SIG_IGN);
  thread_ = std::thread([this] { run(); });
}

PoseReceiver::~PoseReceiver() {
  stop_ = true;
  if (thread_.joinable()) thread_.join();
  if (listener_) close_socket(*listener_->socket);
}

std::optional<PoseReceiver::Pose> PoseReceiver::latest(const std::string& device) const {
  std::lock_guard<std::mutex> lock(mutex_);
  const auto it = poses_.find(device);
  if (it == poses_.end()) return std::nullopt;
  return it->second;
}

PoseReceiver::Stats PoseReceiver::stats() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return stats_;
}

void PoseReceiver::keep(const std::string& device, const Eigen::Isometry3d& transform,
                        int64_t timestamp_ns) {
  std::lock_guard<std::mutex> lock(mutex_);
  poses_[device] = Pose{transform, timestamp_ns, Clock::now()};
  ++stats_.poses;
}

void PoseReceiver::run() {
  double backoff_s = 0.1;
  while (!stop_) {
    Connection c;
    if (server_) {
      c.socket = listener_->socket->WaitForConnection(100);
      if (c.socket.IsNull()) continue;
    } else {
      c.socket = igtl::ClientSocket::New();
      if (c.socket->ConnectToServer(host_.c_str(), port_) != 0) {
        close_socket(*c.socket);
        // Said in our words when it starts and every 10 s while it lasts: without poses nothing
        // is tracked, and the library itself says so only in debug lines.
        const auto now = Clock::now();
        int64_t failed;
        {
          std::lock_guard<std::mutex> lock(mutex_);
          failed = ++stats_.failed_connects;
          stats_.last_problem = "cannot reach the tracking server";
        }
        if (failed == 1 || now - last_unreachable_warning_ >= std::chrono::seconds(10)) {
          last_unreachable_warning_ = now;
          spdlog::warn(
              "OpenIGTLink poses: cannot reach the tracking server at {}:{} ({} attempt(s)); is "
              "it running and is the address right? Retrying; no pose arrives until it answers",
              host_, port_, failed);
        }
        const auto until = Clock::now() + std::chrono::duration<double>(backoff_s);
        while (!stop_ && Clock::now() < until) std::this_thread::sleep_for(std::chrono::milliseconds(10));
        backoff_s = std::min(2.0, backoff_s * 2);
        continue;
      }
    }
    backoff_s = 0.1;
    // A stalled sender must not hold the reader forever: the stop flag is checked between reads.
    c.socket->SetReceiveTimeout(200);
    {
      std::lock_guard<std::mutex> lock(mutex_);
      ++stats_.connections;
    }
    spdlog::info("OpenIGTLink poses: connected ({})", uri_);
    const std::string why = read_connection(c);
    close_socket(*c.socket);
    {
      std::lock_guard<std::mutex> lock(mutex_);
      ++stats_.ended;
    }
    if (!why.empty()) spdlog::warn("OpenIGTLink poses: {}: {}; connection dropped", uri_, why);
  }
}

std::string PoseReceiver::read_connection(Connection& c) {
  igtl::MessageHeader::Pointer header = igtl::MessageHeader::New();
  const auto drop = [&](const std::string& why) {
    std::lock_guard<std::mutex> lock(mutex_);
    ++stats_.dropped;
    stats_.last_problem = why;
    return why;
  };
  // Receive exactly n bytes, waiting out receive timeouts while the stop flag is clear. false
  // when the connection ended.
  const auto receive = [&](void* data, int n) {
    char* p = static_cast<char*>(data);
    int got = 0;
    while (got < n && !stop_) {
      const int r = c.socket->Receive(p + got, n - got, 0);
      if (r > 0) {
        got += r;
      } else if (r == 0) {
        return false;  // closed (or failed)
      }
      // r < 0: the receive timeout passed; look at the stop flag and go on
    }
    return got == n;
  };
  while (!stop_) {
    header->InitPack();
    if (!receive(header->GetPackPointer(), header->GetPackSize())) {
      return stop_ ? "" : "the sender closed the connection";
    }
    const unsigned char* raw = static_cast<const unsigned char*>(header->GetPackPointer());
    const int version = raw[0] << 8 | raw[1];
    if (version != 1 && version != 2) {
      return drop("header version " + std::to_string(version) + " (1 and 2 are read)");
    }
    // The header's own fields by the library's C API (CRC of the body), taken before Unpack()
    // converts the buffer to host byte order in place.
    igtl_header h;
    std::memcpy(&h, raw, sizeof(h));
    igtl_header_convert_byte_order(&h);
    // Every field from that C view: the C++ header class of this library version reads
    // version 1 only.
    const uint64_t body = h.body_size;
    const std::string type(h.name, strnlen(h.name, sizeof(h.name)));
    const std::string device(h.device_name, strnlen(h.device_name, sizeof(h.device_name)));
    if (body > uint64_t(kMaxBodyBytes)) {
      return drop("a " + type + " message announces " + std::to_string(body) +
                  " bytes (at most " + std::to_string(kMaxBodyBytes) + " are read)");
    }
    // 32.32 fixed point: seconds, then the fraction of a second in units of 2^-32.
    const int64_t stamp = int64_t(h.timestamp >> 32) * 1000000000 +
                          int64_t(((h.timestamp & 0xffffffffULL) * 1000000000ULL) >> 32);
    if (type == "TRANSFORM") {
      std::vector<unsigned char> data(static_cast<size_t>(body));
      if (!receive(data.data(), int(body))) return "the sender closed the connection";
      // As the library computes it: the CRC of nothing first, then the body.
      if (crc64(data.data(), body, crc64(nullptr, 0, 0ULL)) != h.crc) {
        return drop("TRANSFORM " + device + ": CRC does not match its body");
      }
      // Header version 2 (OpenIGTLink 3): extended header first, metadata last.
      size_t begin = 0, end = data.size();
      if (version == 2) {
        if (data.size() < 12) return drop("TRANSFORM " + device + ": truncated extended header");
        const size_t extended = size_t(data[0]) << 8 | data[1];
        const size_t meta_header = size_t(data[2]) << 8 | data[3];
        const size_t meta = size_t(data[4]) << 24 | size_t(data[5]) << 16 |
                            size_t(data[6]) << 8 | data[7];
        if (extended < 12 || extended + meta_header + meta > data.size()) {
          return drop("TRANSFORM " + device + ": extended header sizes exceed the body");
        }
        begin = extended;
        end = data.size() - meta_header - meta;
      }
      if (end - begin != 48) {
        return drop("TRANSFORM " + device + ": content of " + std::to_string(end - begin) +
                    " bytes, expected 48");
      }
      igtl_float32 values[12];
      std::memcpy(values, data.data() + begin, 48);
      igtl_transform_convert_byte_order(values);  // columns of R, then the translation
      Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
      for (int c = 0; c < 3; ++c) {
        for (int r = 0; r < 3; ++r) T.matrix()(r, c) = values[3 * c + r];
      }
      T.translation() = Eigen::Vector3d(values[9], values[10], values[11]);
      if (!plausible(T)) return drop("TRANSFORM " + device + ": not a rigid transform");
      keep(device, T, stamp);
    } else if (type == "TDATA" && version == 1) {
      header->Unpack();
      igtl::TrackingDataMessage::Pointer m = igtl::TrackingDataMessage::New();
      m->SetMessageHeader(header);
      m->AllocatePack();
      if (!receive(m->GetPackBodyPointer(), m->GetPackBodySize())) return "the sender closed the connection";
      if (!(m->Unpack(1) & igtl::MessageHeader::UNPACK_BODY)) {
        return drop("TDATA: CRC does not match its body");
      }
      for (int i = 0; i < m->GetNumberOfTrackingDataElements(); ++i) {
        igtl::TrackingDataElement::Pointer e;
        m->GetTrackingDataElement(i, e);
        igtl::Matrix4x4 matrix;
        e->GetMatrix(matrix);
        const Eigen::Isometry3d T = isometry(matrix);
        if (!plausible(T)) return drop(std::string("TDATA ") + e->GetName() + ": not a rigid transform");
        keep(e->GetName(), T, stamp);
      }
    } else {
      // Not a pose: skipped by its announced size.
      std::vector<char> sink(std::min<uint64_t>(body, 65536));
      uint64_t left = body;
      while (left > 0) {
        const int n = int(std::min<uint64_t>(left, sink.size()));
        if (!receive(sink.data(), n)) return "the sender closed the connection";
        left -= uint64_t(n);
      }
      std::lock_guard<std::mutex> lock(mutex_);
      ++stats_.skipped;
    }
    std::lock_guard<std::mutex> lock(mutex_);
    ++stats_.messages;
  }
  return "";
}

}  // namespace crepuscular::igtlink
