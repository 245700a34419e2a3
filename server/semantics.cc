#include "server/semantics.h"

#include "absl/strings/str_cat.h"
#include "spdlog/spdlog.h"

namespace lifemap::server {

void VisitSemantics::Fuse(const SemanticKeyframe& keyframe,
                          const semantic::SemanticMapOptions& options) {
  absl::MutexLock lock(&mu_);
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
  if (!stats.ok()) {
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

semantic::SemanticSummary VisitSemantics::Summarize() const {
  absl::ReaderMutexLock lock(&mu_);
  return map_ ? map_->Summarize() : semantic::SemanticSummary{};
}

}  // namespace lifemap::server
