#include "server/engine/serial_worker.h"

#include <utility>

namespace lifemap::server {

SerialWorker::SerialWorker() : thread_([this] { Run(); }) {}

SerialWorker::~SerialWorker() {
  {
    absl::MutexLock lock(&mu_);
    stopping_ = true;
  }
  thread_.join();
}

uint64_t SerialWorker::Submit(std::function<void()> job) {
  absl::MutexLock lock(&mu_);
  queue_.push_back(std::move(job));
  return ++submitted_;
}

void SerialWorker::Wait(uint64_t ticket) {
  absl::MutexLock lock(&mu_);
  struct Arg {
    const SerialWorker* worker;
    uint64_t ticket;
  } arg{this, ticket};
  mu_.Await(absl::Condition(
      +[](Arg* a) ABSL_NO_THREAD_SAFETY_ANALYSIS { return a->worker->done_ >= a->ticket; }, &arg));
}

uint64_t SerialWorker::last_ticket() const {
  absl::MutexLock lock(&mu_);
  return submitted_;
}

size_t SerialWorker::queued() const {
  absl::MutexLock lock(&mu_);
  return queue_.size();
}

void SerialWorker::Run() {
  for (;;) {
    std::function<void()> job;
    {
      absl::MutexLock lock(&mu_);
      mu_.Await(absl::Condition(
          +[](SerialWorker* w)
               ABSL_NO_THREAD_SAFETY_ANALYSIS { return w->stopping_ || !w->queue_.empty(); },
          this));
      if (queue_.empty()) return;  // stopping and drained
      job = std::move(queue_.front());
      queue_.pop_front();
    }
    job();
    job = nullptr;  // releases what the job holds before its ticket counts as done
    absl::MutexLock lock(&mu_);
    ++done_;
  }
}

}  // namespace lifemap::server
