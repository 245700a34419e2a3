// The browser view's connection threads (issue 52, item 9): httplib serves each connection on
// a thread of its task queue for as long as the connection lasts, and its fixed ThreadPool let
// 200 slow clients (headers sent a byte at a time) take every thread and stop the view for
// everyone. This queue starts a thread per connection as it comes, up to `max_threads`; past
// that, enqueue waits for one to end, so further connections wait in the kernel's accept
// queue and take no file descriptor of the process (gRPC shares those). Idle threads end after
// a few seconds.
#pragma once

#include <chrono>
#include <condition_variable>
#include <cstddef>
#include <deque>
#include <functional>
#include <map>
#include <mutex>
#include <string>
#include <thread>
#include <utility>
#include <vector>

// Last: it includes <resolv.h>, whose `_res` macro breaks Eigen's headers included after it.
#include <httplib.h>

namespace lifemap::server {

class ConnectionPool : public httplib::TaskQueue {
 public:
  explicit ConnectionPool(size_t max_threads);
  ~ConnectionPool() override;  // shutdown()

  // Runs `fn` on an idle thread, or a new one; blocks while `max_threads` are busy.
  void enqueue(std::function<void()> fn) override;
  // Runs what is queued and joins every thread (httplib calls it once the listener closed).
  void shutdown() override;

  size_t threads() const;  // alive now (for tests)

 private:
  void Work();
  void ReapEnded();  // joins the threads that ended (mu_ held)

  const size_t max_threads_;
  mutable std::mutex mu_;
  std::condition_variable work_;  // a job queued, or shutting down
  std::condition_variable room_;  // a thread became idle or ended
  std::deque<std::function<void()>> jobs_;
  std::vector<std::thread> threads_;
  std::vector<std::thread::id> ended_;  // ended, not joined yet
  size_t alive_ = 0;
  size_t idle_ = 0;
  bool shutting_down_ = false;
};

// Bounds each client's connections to the view (issue 52, item 9). httplib gives no hook between
// accept and the request's headers, which is where a slow client holds its connection, so this
// looks from outside: Sweep() lists the process's sockets connected on the view's port
// (/proc/self/fd, getsockname, getpeername) and shuts down a client's oldest ones beyond
// `max_per_client` (its threads then see the connection end and return). ShutdownAll() does
// so to every one, so that a stop does not wait for slow clients. A socket is checked again
// just before it is shut down; it is never closed here (its thread owns it).
class ConnectionLimiter {
 public:
  ConnectionLimiter(int port, size_t max_per_client);

  // Returns the addresses whose connections were cut, with how many.
  std::vector<std::pair<std::string, size_t>> Sweep();
  void ShutdownAll();

 private:
  struct Seen {
    std::string peer;  // IP:PORT
    std::chrono::steady_clock::time_point since;
  };
  const int port_;
  const size_t max_per_client_;
  std::map<int, Seen> seen_;  // by fd
};

}  // namespace lifemap::server
