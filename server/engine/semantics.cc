#include "server/engine/semantics.h"

#include "absl/strings/str_cat.h"
#include "server/engine/clock.h"
#include "spdlog/spdlog.h"

namespace lifemap::server {

void VisitSemantics::Fuse(const SemanticKeyframe& keyframe,
                          const semantic::SemanticMapOptions& options) {
  absl::MutexLock lock(&mu_);
  ++fusions_;
  if (map_ == nullptr || model_ != keyframe.model || map_->class_count() != keyframe.class_count) {
    auto map = semantic::SemanticMap::Create(keyframe.class_count, keyframe.class_prior, options);
    if (!map.ok()) {
      error_ = map.status();
      return;
    }
    if (map_ != nullptr) {
      spdlog::info("semantic octree restarted: keyframes now labelled by model '{}' (was '{}')",
                   keyframe.model, model_);
    }
    map_ = *std::move(map);
    model_ = keyframe.model;
  }
  auto stats = map_->Fuse(keyframe.depth_m, keyframe.intrinsics, keyframe.T_visit_camera,
                          keyframe.probabilities);
  error_ = stats.status();
  if (stats.ok()) {
    ++fused_since_snapshot_;
  } else {
    spdlog::warn("semantic fusion refused a keyframe: {}", std::string(stats.status().message()));
  }
}

absl::StatusOr<semantic::RenderedLabels> VisitSemantics::Render(const std::string& model,
                                                                const cv::Mat& depth_m,
                                                                const CameraIntrinsics& intrinsics,
                                                                const Pose& T_visit_camera,
                                                                int stride) const {
  absl::ReaderMutexLock lock(&mu_);
  if (map_ == nullptr) {
    return absl::FailedPreconditionError(
        error_.ok() ? "no keyframe of this visit fused yet (fusion runs off the reply path, a "
                      "keyframe or two behind)"
                    : absl::StrCat("semantic fusion failed: ", error_.message()));
  }
  if (model_ != model) {
    return absl::FailedPreconditionError(absl::StrCat("the visit's octree holds model '", model_,
                                                      "' and this frame was labelled by '", model,
                                                      "': it restarts with the next keyframe"));
  }
  return map_->Render(depth_m, intrinsics, T_visit_camera, stride);
}

std::optional<store::SemanticSnapshotRecord> VisitSemantics::SnapshotIfDue(int64_t visit_id,
                                                                           int every) {
  {
    absl::MutexLock lock(&mu_);
    if (map_ == nullptr || fused_since_snapshot_ == 0 || fused_since_snapshot_ < every) {
      return std::nullopt;
    }
    fused_since_snapshot_ = 0;
  }
  // Serialised under the reader lock: frames go on rendering meanwhile. Only the worker that
  // calls this fuses or replaces the octree, so it cannot change in between.
  absl::ReaderMutexLock lock(&mu_);
  return SemanticSnapshotOf(visit_id, model_, *map_);
}

store::SemanticSnapshotRecord SemanticSnapshotOf(int64_t visit_id, const std::string& model,
                                                 const semantic::SemanticMap& map) {
  store::SemanticSnapshotRecord r;
  r.visit_id = visit_id;
  r.model = model;
  r.class_count = map.class_count();
  r.resolution_m = map.resolution_m();
  r.keyframes = map.keyframes();
  r.bytes = map.Serialize();
  r.updated_time_s = NowSeconds();
  return r;
}

void VisitSemantics::Restore(const store::SemanticSnapshotRecord& snapshot,
                             const semantic::SemanticMapOptions& options) {
  auto map = semantic::SemanticMap::Deserialize(snapshot.bytes, options);
  if (!map.ok()) {
    spdlog::warn("visit {}: stored semantic octree not restored ({}); it starts empty",
                 snapshot.visit_id, std::string(map.status().message()));
    return;
  }
  Replace(*std::move(map), snapshot.model);
}

void VisitSemantics::Replace(std::unique_ptr<semantic::SemanticMap> map, const std::string& model) {
  absl::MutexLock lock(&mu_);
  map_ = std::move(map);
  model_ = model;
  error_ = absl::OkStatus();
  fused_since_snapshot_ = 0;
}

int64_t VisitSemantics::fusions() const {
  absl::ReaderMutexLock lock(&mu_);
  return fusions_;
}

void StoreSemanticSnapshotIfDue(store::Store* store, int64_t visit_id, VisitSemantics* semantics,
                                int every) {
  auto snapshot = semantics->SnapshotIfDue(visit_id, every);
  if (!snapshot) return;
  if (auto s = store->PutSemanticSnapshot(*snapshot); !s.ok()) {
    spdlog::warn("visit {}: semantic octree snapshot not stored: {}", visit_id,
                 std::string(s.message()));
  }
}

}  // namespace lifemap::server
