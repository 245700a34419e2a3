#include "core/pipeline/keyframe.h"

#include "absl/strings/str_cat.h"

namespace lifemap::pipeline {

absl::Status KeyframeFeatureOptions::Validate() const {
  if (max_keypoints < 10 || max_keypoints > 10000) {
    return absl::InvalidArgumentError(
        absl::StrCat("max_keypoints must be in [10, 10000], got ", max_keypoints));
  }
  if (!(detect_scale > 0.2 && detect_scale <= 1.0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("detect_scale must be in (0.2, 1], got ", detect_scale));
  }
  return absl::OkStatus();
}

absl::StatusOr<KeyframeFeatures> ExtractKeyframeFeatures(const FrameAnalysis& analysis,
                                                         const KeyframeFeatureOptions& options) {
  const RgbdFrame& f = analysis.frame;
  if (f.color_bgr.empty()) {
    return absl::FailedPreconditionError("the frame has no colour image to extract features from");
  }
  features::KeypointSet all =
      features::ExtractOrb(f.color_bgr, options.max_keypoints, options.detect_scale);
  features::AttachPoints(f.depth_m, f.intrinsics, &all);
  KeyframeFeatures out;
  if (analysis.entropy) {
    out.entropy_threshold = analysis.entropy->threshold;
    out.superjuts = analysis.entropy->superjuts;
    out.keypoints = features::PruneByMask(all, analysis.entropy->mask);
  } else {
    out.entropy_threshold = 0.0;
    out.keypoints = std::move(all);
  }
  return out;
}

}  // namespace lifemap::pipeline
