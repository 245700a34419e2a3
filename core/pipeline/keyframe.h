// The keyframe step: what a frame chosen as a keyframe adds to the map besides its images.
// Features are extracted once per keyframe (ORB with 3D points from depth) and pruned by the
// frame's entropy mask (paper 000: keypoints on superjuts likely to move are never stored or
// matched); the floor-plan fold and the appearance index take them from here.
#pragma once

#include <vector>

#include "absl/status/status.h"
#include "core/entropy/superjut_scores.h"
#include "core/features/keypoints.h"
#include "core/pipeline/frame_pipeline.h"

namespace lifemap::pipeline {

struct KeyframeFeatureOptions {
  features::OrbOptions orb;  // detection before pruning

  absl::Status Validate() const;
};

// What the entropy mask made of a keyframe: its superjuts as scored, the threshold applied,
// and the keypoints kept for matching (those in masked zones dropped), with 3D points.
struct KeyframeFeatures {
  double entropy_threshold = 0;
  std::vector<entropy::SuperjutScore> superjuts;
  features::KeypointSet keypoints;
};

// A keyframe's features from its analysis: ORB on the colour image, 3D points from its depth,
// pruned by its entropy mask when the analysis has one (unpruned otherwise: entropy_threshold
// is then 0 and superjuts empty). FailedPrecondition for a frame without colour.
absl::StatusOr<KeyframeFeatures> ExtractKeyframeFeatures(const FrameAnalysis& analysis,
                                                         const KeyframeFeatureOptions& options);

}  // namespace lifemap::pipeline
