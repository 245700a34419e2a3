#include "core/common/task_pool.h"

#include <atomic>
#include <chrono>
#include <set>
#include <thread>

#include <gtest/gtest.h>

#include "absl/synchronization/mutex.h"

namespace lifemap {
namespace {

TEST(TaskPoolTest, SubmitReturnsEachTasksResult) {
  TaskPool pool(2);
  std::vector<std::future<int>> results;
  for (int i = 0; i < 100; ++i) results.push_back(pool.Submit([i] { return i * i; }));
  for (int i = 0; i < 100; ++i) EXPECT_EQ(results[static_cast<size_t>(i)].get(), i * i);
}

TEST(TaskPoolTest, WithoutWorkersEverythingRunsOnTheCaller) {
  TaskPool pool(0);
  const auto caller = std::this_thread::get_id();
  EXPECT_EQ(pool.Submit([] { return std::this_thread::get_id(); }).get(), caller);
  std::thread::id ran;
  pool.RunAll({[&] { ran = std::this_thread::get_id(); }});
  EXPECT_EQ(ran, caller);
}

TEST(TaskPoolTest, RunAllRunsEveryTaskOnceAndUsesTheWorkers) {
  TaskPool pool(2);
  std::vector<std::atomic<int>> runs(64);
  absl::Mutex mu;
  std::set<std::thread::id> threads;
  std::vector<std::function<void()>> tasks;
  for (size_t i = 0; i < runs.size(); ++i) {
    tasks.push_back([&, i] {
      runs[i].fetch_add(1);
      std::this_thread::sleep_for(std::chrono::milliseconds(2));
      absl::MutexLock lock(&mu);
      threads.insert(std::this_thread::get_id());
    });
  }
  pool.RunAll(std::move(tasks));
  for (const auto& r : runs) EXPECT_EQ(r.load(), 1);
  EXPECT_GE(threads.size(), 2u) << "the workers took part";
  EXPECT_LE(threads.size(), 3u) << "the workers and the caller, no more";
}

// Every worker busy with a task that itself calls RunAll and waits: with plain futures this
// deadlocks; here each caller runs what no worker started.
TEST(TaskPoolTest, NestedRunAllOnEveryWorkerDoesNotDeadlock) {
  TaskPool pool(2);
  std::atomic<int> inner{0};
  std::vector<std::future<void>> outer;
  for (int i = 0; i < 8; ++i) {
    outer.push_back(pool.Submit([&] {
      std::vector<std::function<void()>> tasks;
      for (int k = 0; k < 4; ++k) tasks.push_back([&] { inner.fetch_add(1); });
      pool.RunAll(std::move(tasks));
    }));
  }
  for (auto& f : outer) {
    ASSERT_EQ(f.wait_for(std::chrono::seconds(30)), std::future_status::ready) << "deadlock";
  }
  EXPECT_EQ(inner.load(), 32);
}

TEST(TaskPoolTest, AnExceptionReachesTheFuture) {
  TaskPool pool(1);
  auto f = pool.Submit([]() -> int { throw std::runtime_error("boom"); });
  EXPECT_THROW(f.get(), std::runtime_error);
  EXPECT_EQ(pool.Submit([] { return 7; }).get(), 7) << "the worker survives";
}

TEST(TaskPoolTest, DestructionRunsWhatIsQueued) {
  std::atomic<int> ran{0};
  {
    TaskPool pool(1);
    for (int i = 0; i < 20; ++i) pool.Submit([&] { ran.fetch_add(1); });
  }
  EXPECT_EQ(ran.load(), 20);
}

TEST(TaskPoolTest, TheSharedPoolHasAWorkerPerHardwareThread) {
  EXPECT_EQ(TaskPool::Shared().threads(),
            std::max(1, static_cast<int>(std::thread::hardware_concurrency())));
}

}  // namespace
}  // namespace lifemap
