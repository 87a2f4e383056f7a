// OpenIGTLink in: tool poses from a tracking server such as PLUS (or any OpenIGTLink sender),
// TRANSFORM or TDATA messages, kept as the latest pose per device name.
//
// Either side can be the server: "igtl://HOST:PORT" connects to a tracking server (reconnecting
// with back-off, 0.1 s doubling to 2 s, when it goes away); "igtl-server:PORT" listens for one
// sender at a time. A background thread reads; guidance only looks up the latest poses.
//
// Robust protocol handling: header versions 1 and 2 are accepted; a body larger than 1 MB is
// refused before anything is allocated for it; the body CRC is checked; unknown message types
// are skipped; a malformed message (wrong CRC, bad version, oversized or truncated) drops that
// connection with a log line, never the process.
#pragma once

#include <Eigen/Geometry>
#include <atomic>
#include <chrono>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>

namespace crepuscular::igtlink {

class PoseReceiver {
 public:
  using Clock = std::chrono::steady_clock;
  static constexpr int64_t kMaxBodyBytes = 1 << 20;

  struct Pose {
    Eigen::Isometry3d transform = Eigen::Isometry3d::Identity();  // tool to reference, mm
    int64_t timestamp_ns = 0;    // the message's own timestamp
    Clock::time_point received;  // when it arrived here
  };
  struct Stats {
    int64_t connections = 0;  // connections made (or accepted)
    int64_t ended = 0;        // connections over (closed by the sender, or dropped)
    int64_t messages = 0;     // messages read whole
    int64_t poses = 0;        // poses taken from them
    int64_t skipped = 0;      // messages of types not read (skipped by their body size)
    int64_t dropped = 0;      // connections dropped for a malformed message
    int64_t failed_connects = 0;  // attempts to reach the tracking server that failed
    std::string last_problem;
  };

  // uri: "igtl://HOST:PORT" or "igtl-server:PORT". Throws Error for a malformed URI, or when the
  // server port cannot be opened.
  explicit PoseReceiver(const std::string& uri);
  ~PoseReceiver();
  PoseReceiver(const PoseReceiver&) = delete;
  PoseReceiver& operator=(const PoseReceiver&) = delete;

  std::optional<Pose> latest(const std::string& device) const;
  Stats stats() const;
  const std::string& uri() const { return uri_; }
  int port() const { return port_; }  // the port listened on (igtl-server:0 picks one)

 private:
  struct Connection;
  void run();
  // Reads messages until the connection ends or a message is malformed; returns why it ended.
  std::string read_connection(Connection& connection);
  void keep(const std::string& device, const Eigen::Isometry3d& transform, int64_t timestamp_ns);

  std::string uri_, host_;
  int port_ = 0;
  std::chrono::steady_clock::time_point last_unreachable_warning_{};  // receiver thread only
  bool server_ = false;
  struct Listener;
  std::unique_ptr<Listener> listener_;
  std::atomic<bool> stop_{false};
  std::thread thread_;
  mutable std::mutex mutex_;
  std::map<std::string, Pose> poses_;
  Stats stats_;
};

}  // namespace crepuscular::igtlink
