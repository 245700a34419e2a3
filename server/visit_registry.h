// Per-visit state that outlives one stream: the keyframe selector and the frame counter, so a
// robot that reconnects (or sends unary ProcessFrame calls) continues where it stopped.
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <unordered_map>

#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "core/tracking/keyframe_selector.h"
#include "server/architecture.h"
#include "server/store/store.h"

namespace lifemap::server {

struct VisitState {
  int64_t visit_id = 0;
  int64_t map_id = 0;
  std::string map_name;
  // Serialises frames of one visit (several streams to one visit are processed in turn).
  absl::Mutex mu;
  tracking::KeyframeSelector selector ABSL_GUARDED_BY(mu);
  int64_t frame_count ABSL_GUARDED_BY(mu) = 0;
  VisitArchitecture architecture ABSL_GUARDED_BY(mu);
};

// Thread-safe.
class VisitRegistry {
 public:
  VisitRegistry(store::Store* store, PlaceIndex* places) : store_(store), places_(places) {}

  // The state of an open visit, loaded from the store on first use (the selector resumes from
  // the visit's last keyframe; the architecture is rebuilt from its stored key frames).
  // NOT_FOUND for an unknown visit; FAILED_PRECONDITION if ended.
  absl::StatusOr<std::shared_ptr<VisitState>> Get(int64_t visit_id);
  // Forgets a visit (ended, or its map deleted).
  void Forget(int64_t visit_id);
  // Forgets a map's visits and cached settings (deleted, renamed or updated).
  void ForgetMap(int64_t map_id);

  // The map's own entropy threshold (nullopt = the server default), cached.
  absl::StatusOr<std::optional<double>> MapEntropyThreshold(int64_t map_id);

 private:
  // Folds the visit's stored posed key frames into its architecture (a resumed visit).
  void RebuildArchitecture(VisitState* state) ABSL_EXCLUSIVE_LOCKS_REQUIRED(state->mu);

  store::Store* const store_;
  PlaceIndex* const places_;
  absl::Mutex mu_;
  std::unordered_map<int64_t, std::shared_ptr<VisitState>> visits_ ABSL_GUARDED_BY(mu_);
  std::unordered_map<int64_t, std::optional<double>> map_thresholds_ ABSL_GUARDED_BY(mu_);
};

}  // namespace lifemap::server
