#include "server/engine/keyframe_committer.h"

#include <vector>

#include <spdlog/spdlog.h>

namespace lifemap::server {

KeyframeCommitter::KeyframeCommitter(store::Store* store, int batch_max, CommittedHook on_committed)
    : store_(store),
      batch_max_(batch_max),
      on_committed_(std::move(on_committed)),
      thread_([this] { Run(); }) {}

KeyframeCommitter::~KeyframeCommitter() {
  {
    absl::MutexLock lock(&mu_);
    stopping_ = true;
  }
  thread_.join();
}

std::future<absl::StatusOr<int64_t>> KeyframeCommitter::Submit(
    std::optional<store::KeyframeRecord> keyframe, store::VisitFrameCount frame_count) {
  Pending p{std::move(keyframe), frame_count, {}};
  auto future = p.done.get_future();
  absl::MutexLock lock(&mu_);
  queue_.push_back(std::move(p));
  return future;
}

uint64_t KeyframeCommitter::committed() const {
  absl::MutexLock lock(&mu_);
  return committed_;
}

void KeyframeCommitter::Run() {
  for (;;) {
    std::deque<Pending> batch;
    {
      absl::MutexLock lock(&mu_);
      mu_.Await(absl::Condition(
          +[](KeyframeCommitter* c) { return c->stopping_ || !c->queue_.empty(); }, this));
      if (queue_.empty()) return;  // stopping and drained
      while (!queue_.empty() && static_cast<int>(batch.size()) < batch_max_) {
        batch.push_back(std::move(queue_.front()));
        queue_.pop_front();
      }
    }
    Commit(&batch);
  }
}

void KeyframeCommitter::Commit(std::deque<Pending>* batch) {
  std::vector<store::KeyframeRecord> keyframes;
  std::vector<store::VisitFrameCount> counts;
  for (auto& p : *batch) {
    if (p.keyframe) keyframes.push_back(std::move(*p.keyframe));
    counts.push_back(p.frame_count);
  }
  absl::Status status = store_->InsertKeyframes(&keyframes, counts);
  if (status.ok()) {
    if (on_committed_) {
      for (const auto& k : keyframes) {
        if (!k.resent) on_committed_(k);  // a resend's first copy was indexed already
      }
    }
    size_t next = 0;
    int64_t n = 0;
    for (auto& p : *batch) {
      p.done.set_value(p.keyframe ? keyframes[next++].id : int64_t{0});
      n += p.keyframe ? 1 : 0;
    }
    absl::MutexLock lock(&mu_);
    committed_ += static_cast<uint64_t>(n);
    return;
  }
  if (batch->size() == 1) {
    spdlog::warn("keyframe commit failed: {}", status.ToString());
    batch->front().done.set_value(status);
    return;
  }
  // One bad item (say, a visit whose map was deleted) must not fail the others: retry one by
  // one. The failed transaction wrote nothing.
  size_t next = 0;
  for (auto& p : *batch) {
    std::deque<Pending> single;
    Pending retry{p.keyframe ? std::optional<store::KeyframeRecord>(std::move(keyframes[next++]))
                             : std::nullopt,
                  p.frame_count, std::move(p.done)};
    single.push_back(std::move(retry));
    Commit(&single);
  }
}

}  // namespace lifemap::server
