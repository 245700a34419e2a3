// One background thread that runs jobs in the order they were submitted, with tickets to wait
// for. For work off the reply path that must keep an order (a visit's keyframes fused in frame
// order). Thread-safe.
#pragma once

#include <cstdint>
#include <deque>
#include <functional>
#include <thread>

#include "absl/synchronization/mutex.h"

namespace lifemap::server {

class SerialWorker {
 public:
  SerialWorker();
  // Runs every queued job, then stops.
  ~SerialWorker();
  SerialWorker(const SerialWorker&) = delete;
  SerialWorker& operator=(const SerialWorker&) = delete;

  // Queues `job`; returns its ticket for Wait(). The job is destroyed (releasing what it holds)
  // before its ticket counts as done.
  uint64_t Submit(std::function<void()> job);
  // Blocks until the job with `ticket` (and every one before it) has run.
  void Wait(uint64_t ticket);
  // The ticket of the last job submitted (0: none yet).
  uint64_t last_ticket() const;
  // Jobs queued and not yet started.
  size_t queued() const;

 private:
  void Run();

  mutable absl::Mutex mu_;
  std::deque<std::function<void()>> queue_ ABSL_GUARDED_BY(mu_);
  uint64_t submitted_ ABSL_GUARDED_BY(mu_) = 0;
  uint64_t done_ ABSL_GUARDED_BY(mu_) = 0;
  bool stopping_ ABSL_GUARDED_BY(mu_) = false;
  std::thread thread_;
};

}  // namespace lifemap::server
