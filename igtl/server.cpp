#include "igtl/server.hpp"

#include <igtlServerSocket.h>
#include <igtlClientSocket.h>

#include <algorithm>
#include <csignal>

#include "foundation/error.hpp"
#include "foundation/log.hpp"
#include "igtl/socket_close.hpp"

namespace crepuscular::igtlink {

using Clock = std::chrono::steady_clock;

struct Server::Listener {
  igtl::ServerSocket::Pointer socket = igtl::ServerSocket::New();
};

struct Server::Client {
  igtl::ClientSocket::Pointer socket;
  std::string address;
  std::thread thread;
  std::mutex mutex;
  std::condition_variable wake;
  std::deque<std::shared_ptr<const Frame>> queue;
  std::atomic<bool> done{false};
};

Server::Server(const Options& options, std::vector<Message> on_connect)
    : options_(options), listener_(std::make_unique<Listener>()),
      on_connect_(std::move(on_connect)) {
  if (options_.port < 0 || options_.port > 65535) {
    throw Error("OpenIGTLink server: port " + std::to_string(options_.port) +
                " is not a TCP port (0 to 65535)");
  }
  // A client that goes away mid-send must not end guidance with SIGPIPE: send fails instead.
  std::signal(SIGPIPE, SIG_IGN);
  if (listener_->socket->CreateServer(options_.port) != 0) {
    throw Error("OpenIGTLink server: cannot listen on port " + std::to_string(options_.port) +
                " (in use by another program, e.g. Slicer's own server?)");
  }
  port_ = listener_->socket->GetServerPort();
  accept_thread_ = std::thread([this] { accept_loop(); });
  spdlog::info("OpenIGTLink: serving on port {} (connect 3D Slicer's OpenIGTLinkIF as a client)",
               port_);
}

Server::~Server() {
  stop_ = true;
  if (accept_thread_.joinable()) accept_thread_.join();
  std::vector<std::shared_ptr<Client>> clients;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    clients.swap(clients_);
  }
  for (const auto& c : clients) {
    c->wake.notify_all();
    if (c->thread.joinable()) c->thread.join();
    close_socket(*c->socket);
  }
  close_socket(*listener_->socket);
}

void Server::set_on_connect(std::vector<Message> messages) {
  std::lock_guard<std::mutex> lock(mutex_);
  on_connect_ = std::move(messages);
}

void Server::accept_loop() {
  while (!stop_) {
    igtl::ClientSocket::Pointer socket = listener_->socket->WaitForConnection(100);
    // Clients whose sender ended (gone, not reading) leave the list here.
    std::vector<std::shared_ptr<Client>> ended;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      for (auto it = clients_.begin(); it != clients_.end();) {
        if ((*it)->done) {
          ended.push_back(*it);
          it = clients_.erase(it);
        } else {
          ++it;
        }
      }
      stats_.clients = int(clients_.size());
    }
    for (const auto& c : ended) {
      if (c->thread.joinable()) c->thread.join();
      close_socket(*c->socket);
    }
    if (socket.IsNull() || stop_) continue;
    auto client = std::make_shared<Client>();
    client->socket = socket;
    int port = 0;
    socket->GetSocketAddressAndPort(client->address, port);  // names this end; the count tells them apart
    client->address = "#" + std::to_string(stats_.connections + 1);
    socket->SetSendTimeout(options_.send_timeout_ms);
    std::vector<Message> first;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      first = on_connect_;
      ++stats_.connections;
    }
    if (!first.empty()) {
      client->queue.push_back(std::make_shared<const Frame>(Frame{first, Clock::now()}));
    }
    client->thread = std::thread([this, client] { send_loop(client); });
    std::lock_guard<std::mutex> lock(mutex_);
    clients_.push_back(client);
    stats_.clients = int(clients_.size());
    spdlog::info("OpenIGTLink: client {} connected", client->address);
  }
}

void Server::send_loop(const std::shared_ptr<Client>& client) {
  while (!stop_) {
    std::shared_ptr<const Frame> frame;
    {
      std::unique_lock<std::mutex> lock(client->mutex);
      client->wake.wait_for(lock, std::chrono::milliseconds(100),
                            [&] { return stop_ || !client->queue.empty(); });
      if (client->queue.empty()) continue;
      frame = client->queue.front();
      client->queue.pop_front();
    }
    bool first = true;
    for (const Message& m : frame->messages) {
      if (client->socket->Send(m.bytes.data(), int(m.bytes.size())) == 0) {
        spdlog::warn("OpenIGTLink: client {} dropped (disconnected, or accepted nothing for {} ms)",
                     client->address, options_.send_timeout_ms);
        std::lock_guard<std::mutex> lock(mutex_);
        ++stats_.dropped;
        client->done = true;
        return;
      }
      if (first) {
        record_latency(std::chrono::duration<double, std::milli>(Clock::now() - frame->published)
                           .count());
        first = false;
      }
      std::lock_guard<std::mutex> lock(mutex_);
      ++stats_.messages_sent;
    }
  }
  client->done = true;
}

void Server::record_latency(double ms) {
  std::lock_guard<std::mutex> lock(mutex_);
  latencies_.push_back(ms);
  while (latencies_.size() > 1000) latencies_.pop_front();
}

void Server::publish(std::vector<Message> messages) {
  if (messages.empty()) return;
  const auto frame = std::make_shared<const Frame>(Frame{std::move(messages), Clock::now()});
  std::lock_guard<std::mutex> lock(mutex_);
  for (const auto& c : clients_) {
    if (c->done) continue;
    {
      std::lock_guard<std::mutex> queue_lock(c->mutex);
      if (c->queue.size() >= kQueueFrames) {
        c->queue.pop_front();
        ++stats_.frames_overflowed;
      }
      c->queue.push_back(frame);
      ++stats_.frames_queued;
    }
    c->wake.notify_one();
  }
}

Server::Stats Server::stats() const {
  std::lock_guard<std::mutex> lock(mutex_);
  Stats s = stats_;
  if (!latencies_.empty()) {
    std::vector<double> v(latencies_.begin(), latencies_.end());
    std::sort(v.begin(), v.end());
    s.latency_median_ms = v[v.size() / 2];
    s.latency_p95_ms = v[std::min(v.size() - 1, size_t(0.95 * double(v.size() - 1) + 0.5))];
  }
  return s;
}

}  // namespace crepuscular::igtlink
