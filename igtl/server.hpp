// An OpenIGTLink server for the operating room's tools (3D Slicer's OpenIGTLinkIF, SlicerIGT):
// every connected client receives what guidance publishes, frame by frame.
//
// Guidance never waits for a client: publish() only hands the packed messages to each client's
// own sender thread (a queue of at most kQueueFrames frames; the oldest go first when a client
// falls behind). A client that connects late first gets the messages given as "on connect" (the
// needle tip's calibration, the target, the planned trajectory); one that disconnects, or stops
// reading for longer than the send timeout, is dropped with a log line. Clients are not read from.
#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <deque>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "igtl/messages.hpp"

namespace crepuscular::igtlink {

class Server {
 public:
  static constexpr size_t kQueueFrames = 8;

  struct Options {
    int port = 18944;             // OpenIGTLink's (and Slicer's) default; 0: any free port
    int send_timeout_ms = 500;    // a client that accepts nothing for this long is dropped
  };
  struct Stats {
    int clients = 0;                 // connected now
    int64_t connections = 0;         // accepted since start
    int64_t dropped = 0;             // clients dropped (gone, not reading)
    int64_t frames_queued = 0;       // frames handed to client queues
    int64_t frames_overflowed = 0;   // frames a slow client's full queue pushed out
    int64_t messages_sent = 0;
    // Publish to "on the socket" (Send returned), milliseconds, over the last 1000 frames.
    double latency_median_ms = 0, latency_p95_ms = 0;
  };

  // Listens on every interface. Throws Error when the port cannot be opened.
  explicit Server(const Options& options, std::vector<Message> on_connect = {});
  ~Server();
  Server(const Server&) = delete;
  Server& operator=(const Server&) = delete;

  int port() const { return port_; }
  // Replaces what a newly connected client gets first.
  void set_on_connect(std::vector<Message> messages);
  // Hands one frame's messages to every connected client; returns at once.
  void publish(std::vector<Message> messages);
  Stats stats() const;

 private:
  struct Frame {
    std::vector<Message> messages;
    std::chrono::steady_clock::time_point published;
  };
  struct Client;
  void accept_loop();
  void send_loop(const std::shared_ptr<Client>& client);
  void record_latency(double ms);

  Options options_;
  int port_ = 0;
  struct Listener;
  std::unique_ptr<Listener> listener_;
  std::atomic<bool> stop_{false};
  std::thread accept_thread_;
  mutable std::mutex mutex_;
  std::vector<std::shared_ptr<Client>> clients_;
  std::vector<Message> on_connect_;
  Stats stats_;
  std::deque<double> latencies_;
};

}  // namespace crepuscular::igtlink
