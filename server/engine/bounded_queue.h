// A FIFO with a capacity, between one producing and one consuming thread. The frame service
// puts a stream's processed frames here; when it is full the reading thread stops reading, and
// gRPC's flow control then holds back the sender, so a fast robot cannot fill the server's
// memory.
#pragma once

#include <cstddef>
#include <deque>
#include <optional>

#include "absl/synchronization/mutex.h"

namespace lifemap::server {

// Thread-safe.
template <typename T>
class BoundedQueue {
 public:
  explicit BoundedQueue(size_t capacity) : capacity_(capacity) {}

  // Blocks while the queue holds `capacity` items.
  void Push(T item) {
    absl::MutexLock lock(&mu_);
    mu_.Await(absl::Condition(this, &BoundedQueue::HasRoom));
    items_.push_back(std::move(item));
  }
  // No more items will be pushed; Pop() returns nullopt once the queue is empty.
  void Close() {
    absl::MutexLock lock(&mu_);
    closed_ = true;
  }
  // Blocks until an item is available; nullopt once closed and drained.
  std::optional<T> Pop() {
    absl::MutexLock lock(&mu_);
    mu_.Await(absl::Condition(this, &BoundedQueue::ReadyToPop));
    if (items_.empty()) return std::nullopt;
    T item = std::move(items_.front());
    items_.pop_front();
    return item;
  }
  size_t size() const {
    absl::MutexLock lock(&mu_);
    return items_.size();
  }

 private:
  bool HasRoom() const ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_) { return items_.size() < capacity_; }
  bool ReadyToPop() const ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_) { return closed_ || !items_.empty(); }

  const size_t capacity_;
  mutable absl::Mutex mu_;
  std::deque<T> items_ ABSL_GUARDED_BY(mu_);
  bool closed_ ABSL_GUARDED_BY(mu_) = false;
};

// A count of slots shared by several threads: the frame service takes one for each frame it
// reads and gives it back once the frame is answered, so a stream holds at most `capacity`
// frames across all its stages. Thread-safe.
class Slots {
 public:
  explicit Slots(size_t capacity) : free_(capacity) {}
  // Blocks until a slot is free, and takes it.
  void Acquire() {
    absl::MutexLock lock(&mu_);
    mu_.Await(absl::Condition(
        +[](size_t* free) { return *free > 0; }, &free_));
    --free_;
  }
  void Release() {
    absl::MutexLock lock(&mu_);
    ++free_;
  }

 private:
  absl::Mutex mu_;
  size_t free_ ABSL_GUARDED_BY(mu_);
};

}  // namespace lifemap::server
