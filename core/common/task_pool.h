// A fixed set of worker threads, sized to the machine, shared by every stream and every stage
// of the frame pipeline: frames of one stream are analysed side by side on it, and a frame's
// own parallel parts (labels beside entropy masks, the forest's rows) run on it too, instead of
// threads spawned per frame.
//
// Nested use is safe: `RunAll` lets its caller run the tasks no worker has started yet, so a
// task of the pool that calls `RunAll` never waits for a worker that is busy with it, and the
// machine never has more threads at work than the pool has plus its callers.
#pragma once

#include <deque>
#include <functional>
#include <future>
#include <memory>
#include <thread>
#include <type_traits>
#include <vector>

#include "absl/synchronization/mutex.h"

namespace lifemap {

// Thread-safe.
class TaskPool {
 public:
  // `threads` workers; 0 runs every task on the calling thread (Submit included).
  explicit TaskPool(int threads);
  // Runs what is queued, then joins the workers.
  ~TaskPool();
  TaskPool(const TaskPool&) = delete;
  TaskPool& operator=(const TaskPool&) = delete;

  // The process's pool: one worker per hardware thread (at least 1), made on first use.
  static TaskPool& Shared();

  int threads() const { return static_cast<int>(workers_.size()); }

  // Queues `task` behind every task queued before it; its result (or exception) in the future.
  template <typename F>
  auto Submit(F task) -> std::future<std::invoke_result_t<F>> {
    using R = std::invoke_result_t<F>;
    auto packaged = std::make_shared<std::packaged_task<R()>>(std::move(task));
    std::future<R> result = packaged->get_future();
    if (workers_.empty()) {
      (*packaged)();
    } else {
      Push([packaged] { (*packaged)(); }, /*front=*/false);
    }
    return result;
  }

  // Runs every task and returns once all have run. The caller runs them too (the first at once,
  // then each that no worker has started), and the workers' share goes ahead of Submit's queue,
  // so that work already under way finishes before new work starts. Tasks must not throw.
  void RunAll(std::vector<std::function<void()>> tasks);

 private:
  void Push(std::function<void()> task, bool front);
  void Work();

  absl::Mutex mu_;
  std::deque<std::function<void()>> queue_ ABSL_GUARDED_BY(mu_);
  bool stopping_ ABSL_GUARDED_BY(mu_) = false;
  std::vector<std::thread> workers_;
};

}  // namespace lifemap
