#include "core/common/task_pool.h"

#include <algorithm>
#include <atomic>

namespace lifemap {

TaskPool::TaskPool(int threads) {
  workers_.reserve(static_cast<size_t>(std::max(threads, 0)));
  for (int i = 0; i < threads; ++i) workers_.emplace_back([this] { Work(); });
}

TaskPool::~TaskPool() {
  {
    absl::MutexLock lock(&mu_);
    stopping_ = true;
  }
  for (auto& w : workers_) w.join();
}

TaskPool& TaskPool::Shared() {
  // Never destroyed: tasks may still be queued by threads that outlive main's locals.
  static TaskPool* pool =
      new TaskPool(std::max(1, static_cast<int>(std::thread::hardware_concurrency())));
  return *pool;
}

void TaskPool::Push(std::function<void()> task, bool front) {
  absl::MutexLock lock(&mu_);
  if (front) {
    queue_.push_front(std::move(task));
  } else {
    queue_.push_back(std::move(task));
  }
}

void TaskPool::Work() {
  for (;;) {
    std::function<void()> task;
    {
      absl::MutexLock lock(&mu_);
      mu_.Await(absl::Condition(
          +[](TaskPool* p)
               ABSL_EXCLUSIVE_LOCKS_REQUIRED(p->mu_) { return p->stopping_ || !p->queue_.empty(); },
          this));
      if (queue_.empty()) return;  // stopping, and nothing left
      task = std::move(queue_.front());
      queue_.pop_front();
    }
    task();
  }
}

void TaskPool::RunAll(std::vector<std::function<void()>> tasks) {
  if (tasks.empty()) return;
  // Tasks are claimed by index, by the caller and by helpers queued on the pool; a helper that
  // starts after every task was claimed returns at once.
  struct Shared {
    std::vector<std::function<void()>> tasks;
    std::atomic<size_t> next{0};
    absl::Mutex mu;
    size_t done ABSL_GUARDED_BY(mu) = 0;
  };
  auto shared = std::make_shared<Shared>();
  shared->tasks = std::move(tasks);
  const size_t n = shared->tasks.size();
  auto claim_and_run = [](Shared* s) {
    for (;;) {
      const size_t i = s->next.fetch_add(1);
      if (i >= s->tasks.size()) return;
      s->tasks[i]();
      absl::MutexLock lock(&s->mu);
      ++s->done;
    }
  };
  const size_t helpers = std::min(n - 1, workers_.size());
  for (size_t h = 0; h < helpers; ++h) {
    Push([shared, claim_and_run] { claim_and_run(shared.get()); }, /*front=*/true);
  }
  claim_and_run(shared.get());
  absl::MutexLock lock(&shared->mu);
  shared->mu.Await(absl::Condition(
      +[](Shared* s) ABSL_EXCLUSIVE_LOCKS_REQUIRED(s->mu) { return s->done == s->tasks.size(); },
      shared.get()));
}

}  // namespace lifemap
