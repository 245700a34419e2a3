// Durable keyframe writes off the reply path: one thread takes queued keyframes and commits
// them in batches (group commit: one transaction, one fsync for everything queued meanwhile).
// A caller acknowledges a keyframe to its client only once its future holds an id.
#pragma once

#include <cstdint>
#include <deque>
#include <functional>
#include <future>
#include <optional>
#include <thread>

#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "server/store/store.h"

namespace lifemap::server {

class KeyframeCommitter {
 public:
  // Called on the committer's thread with each keyframe after its transaction committed (its
  // id set), before the submitter's future is fulfilled. Must not block for long.
  using CommittedHook = std::function<void(const store::KeyframeRecord&)>;

  // `store` must outlive the committer. batch_max bounds one transaction.
  KeyframeCommitter(store::Store* store, int batch_max, CommittedHook on_committed = {});
  // Commits everything still queued, then stops.
  ~KeyframeCommitter();
  KeyframeCommitter(const KeyframeCommitter&) = delete;
  KeyframeCommitter& operator=(const KeyframeCommitter&) = delete;

  // Queues a keyframe (or, with nullopt, only a visit frame-count update). The future becomes
  // the stored keyframe id (0 for count-only updates) once committed, or the error. Thread-safe.
  std::future<absl::StatusOr<int64_t>> Submit(std::optional<store::KeyframeRecord> keyframe,
                                              store::VisitFrameCount frame_count);

  uint64_t committed() const;

 private:
  struct Pending {
    std::optional<store::KeyframeRecord> keyframe;
    store::VisitFrameCount frame_count;
    std::promise<absl::StatusOr<int64_t>> done;
  };
  void Run();
  void Commit(std::deque<Pending>* batch);

  store::Store* const store_;
  const int batch_max_;
  const CommittedHook on_committed_;
  mutable absl::Mutex mu_;
  std::deque<Pending> queue_ ABSL_GUARDED_BY(mu_);
  bool stopping_ ABSL_GUARDED_BY(mu_) = false;
  uint64_t committed_ ABSL_GUARDED_BY(mu_) = 0;
  std::thread thread_;
};

}  // namespace lifemap::server
