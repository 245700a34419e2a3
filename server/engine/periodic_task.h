// One background thread that runs a function every `period` until destroyed: the server's
// housekeeping (is the database file still in place, keys revoked beside the server, streams
// that went quiet). Thread-safe.
#pragma once

#include <functional>
#include <thread>

#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"

namespace lifemap::server {

class PeriodicTask {
 public:
  // `tick` runs first after one `period`, then every `period` after it returned.
  PeriodicTask(absl::Duration period, std::function<void()> tick);
  // Waits for a running tick to return, then stops.
  ~PeriodicTask();
  PeriodicTask(const PeriodicTask&) = delete;
  PeriodicTask& operator=(const PeriodicTask&) = delete;

 private:
  void Run();

  const absl::Duration period_;
  const std::function<void()> tick_;
  absl::Mutex mu_;
  bool stopping_ ABSL_GUARDED_BY(mu_) = false;
  std::thread thread_;  // last: starts once the fields above exist
};

}  // namespace lifemap::server
