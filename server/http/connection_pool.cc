#include "server/http/connection_pool.h"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>

#include <algorithm>
#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <optional>

namespace lifemap::server {
namespace {

// An idle thread ends after this long without a connection to serve.
constexpr auto kIdleExit = std::chrono::seconds(5);

}  // namespace

ConnectionPool::ConnectionPool(size_t max_threads) : max_threads_(max_threads) {}

ConnectionPool::~ConnectionPool() { shutdown(); }

void ConnectionPool::enqueue(std::function<void()> fn) {
  std::unique_lock<std::mutex> lock(mu_);
  // Back-pressure on the listener: a connection beyond the threads' number stays in the
  // kernel's backlog until one of them ends.
  room_.wait(lock,
             [this] { return shutting_down_ || idle_ > jobs_.size() || alive_ < max_threads_; });
  ReapEnded();
  jobs_.push_back(std::move(fn));
  if (idle_ >= jobs_.size()) {
    work_.notify_one();
    return;
  }
  ++alive_;
  threads_.emplace_back([this] { Work(); });
}

void ConnectionPool::Work() {
  std::unique_lock<std::mutex> lock(mu_);
  for (;;) {
    if (jobs_.empty()) {
      if (shutting_down_) break;
      ++idle_;
      const bool woke =
          work_.wait_for(lock, kIdleExit, [this] { return !jobs_.empty() || shutting_down_; });
      --idle_;
      if (!woke) break;  // idle too long: end (its std::thread is joined at shutdown)
      continue;
    }
    std::function<void()> fn = std::move(jobs_.front());
    jobs_.pop_front();
    lock.unlock();
    fn();
    lock.lock();
    room_.notify_one();
  }
  --alive_;
  ended_.push_back(std::this_thread::get_id());
  room_.notify_one();
}

void ConnectionPool::ReapEnded() {
  // Called with mu_ held: an ended thread released mu_ for the last time before we took it, so
  // it only has its return left and joins at once.
  for (const auto id : ended_) {
    auto it = std::find_if(threads_.begin(), threads_.end(),
                           [id](const std::thread& t) { return t.get_id() == id; });
    if (it == threads_.end()) continue;
    it->join();
    threads_.erase(it);
  }
  ended_.clear();
}

void ConnectionPool::shutdown() {
  std::vector<std::thread> threads;
  {
    std::lock_guard<std::mutex> lock(mu_);
    shutting_down_ = true;
    threads.swap(threads_);
  }
  work_.notify_all();
  room_.notify_all();
  for (auto& t : threads) {
    if (t.joinable()) t.join();
  }
}

size_t ConnectionPool::threads() const {
  std::lock_guard<std::mutex> lock(mu_);
  return alive_;
}

namespace {

struct Peer {
  std::string ip;
  std::string ip_port;
};

// The peer of `fd` when it is a TCP socket connected on local port `port`.
std::optional<Peer> PeerOnPort(int fd, int port) {
  sockaddr_storage local{};
  socklen_t len = sizeof(local);
  if (getsockname(fd, reinterpret_cast<sockaddr*>(&local), &len) != 0) return std::nullopt;
  int local_port = 0;
  if (local.ss_family == AF_INET) {
    local_port = ntohs(reinterpret_cast<const sockaddr_in*>(&local)->sin_port);
  } else if (local.ss_family == AF_INET6) {
    local_port = ntohs(reinterpret_cast<const sockaddr_in6*>(&local)->sin6_port);
  } else {
    return std::nullopt;
  }
  if (local_port != port) return std::nullopt;
  sockaddr_storage remote{};
  len = sizeof(remote);
  // The listening socket has no peer (ENOTCONN).
  if (getpeername(fd, reinterpret_cast<sockaddr*>(&remote), &len) != 0) return std::nullopt;
  char text[INET6_ADDRSTRLEN] = {};
  int remote_port = 0;
  if (remote.ss_family == AF_INET) {
    const auto* a = reinterpret_cast<const sockaddr_in*>(&remote);
    inet_ntop(AF_INET, &a->sin_addr, text, sizeof(text));
    remote_port = ntohs(a->sin_port);
  } else {
    const auto* a = reinterpret_cast<const sockaddr_in6*>(&remote);
    inet_ntop(AF_INET6, &a->sin6_addr, text, sizeof(text));
    remote_port = ntohs(a->sin6_port);
  }
  return Peer{text, std::string(text) + ":" + std::to_string(remote_port)};
}

// The process's file descriptors.
std::vector<int> OpenDescriptors() {
  std::vector<int> fds;
  std::error_code ec;
  for (const auto& entry : std::filesystem::directory_iterator("/proc/self/fd", ec)) {
    const std::string name = entry.path().filename().string();
    char* end = nullptr;
    const long fd = std::strtol(name.c_str(), &end, 10);
    if (end != name.c_str() && *end == '\0') fds.push_back(static_cast<int>(fd));
  }
  return fds;
}

}  // namespace

ConnectionLimiter::ConnectionLimiter(int port, size_t max_per_client)
    : port_(port), max_per_client_(max_per_client) {}

std::vector<std::pair<std::string, size_t>> ConnectionLimiter::Sweep() {
  const auto now = std::chrono::steady_clock::now();
  std::map<int, Seen> current;
  std::map<std::string, std::vector<int>> by_client;
  for (int fd : OpenDescriptors()) {
    auto peer = PeerOnPort(fd, port_);
    if (!peer) continue;
    auto it = seen_.find(fd);
    // The same fd with another peer is another connection.
    const bool known = it != seen_.end() && it->second.peer == peer->ip_port;
    current[fd] = Seen{peer->ip_port, known ? it->second.since : now};
    by_client[peer->ip].push_back(fd);
  }
  seen_ = std::move(current);
  std::vector<std::pair<std::string, size_t>> cut;
  for (auto& [ip, fds] : by_client) {
    if (fds.size() <= max_per_client_) continue;
    std::sort(fds.begin(), fds.end(),
              [this](int a, int b) { return seen_[a].since < seen_[b].since; });
    size_t n = 0;
    for (size_t i = 0; i + max_per_client_ < fds.size(); ++i) {
      const int fd = fds[i];
      // Still the same connection (its thread may have closed it and the fd been reused).
      auto peer = PeerOnPort(fd, port_);
      if (!peer || peer->ip_port != seen_[fd].peer) continue;
      if (::shutdown(fd, SHUT_RDWR) == 0) ++n;
    }
    if (n > 0) cut.emplace_back(ip, n);
  }
  return cut;
}

void ConnectionLimiter::ShutdownAll() {
  for (int fd : OpenDescriptors()) {
    if (PeerOnPort(fd, port_)) ::shutdown(fd, SHUT_RDWR);
  }
}

}  // namespace lifemap::server
