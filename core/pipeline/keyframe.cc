#include "core/pipeline/keyframe.h"

#include "absl/strings/str_cat.h"

namespace lifemap::pipeline {

absl::Status KeyframeFeatureOptions::Validate() const {
  if (orb.max_keypoints < 10 || orb.max_keypoints > 10000) {
    return absl::InvalidArgumentError(
        absl::StrCat("max_keypoints must be in [10, 10000], got ", orb.max_keypoints));
  }
  if (!(orb.detect_scale > 0.2 && orb.detect_scale <= 1.0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("detect_scale must be in (0.2, 1], got ", orb.detect_scale));
  }
  if (orb.pyramid_levels < 1 || orb.pyramid_levels > 12) {
    return absl::InvalidArgumentError(
        absl::StrCat("pyramid_levels must be in [1, 12], got ", orb.pyramid_levels));
  }
  if (!(orb.pyramid_scale > 1.0 && orb.pyramid_scale <= 2.0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("pyramid_scale must be in (1, 2], got ", orb.pyramid_scale));
  }
  return absl::OkStatus();
}

absl::StatusOr<KeyframeFeatures> ExtractKeyframeFeatures(const FrameAnalysis& analysis,
                                                         const KeyframeFeatureOptions& options) {
  const RgbdFrame& f = analysis.frame;
  if (f.color_bgr.empty()) {
    return absl::FailedPreconditionError("the frame has no colour image to extract features from");
  }
  features::KeypointSet all = features::ExtractOrb(f.color_bgr, options.orb);
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
