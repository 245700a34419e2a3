// Appearance place recognition (paper 000's purpose): which stored keyframe does this view
// show? The query's words pick candidates from the inverted index; each is verified by PnP on
// its stored 3D points. Both sides' features are pruned by their entropy masks before they get
// here (core/pipeline/keyframe.h).
#pragma once

#include <functional>
#include <vector>

#include "absl/status/statusor.h"
#include "core/appearance/index.h"
#include "core/appearance/verify.h"
#include "core/appearance/vocabulary.h"

namespace lifemap::appearance {

struct RecognizerOptions {
  int candidates = 8;  // index candidates verified per query, [1, 100]
  VerifyOptions verify;

  absl::Status Validate() const;
};

struct AppearanceMatch {
  KeyframeRef keyframe;
  float index_score = 0;  // the inverted file's L1 score
  Verification verification;
};

struct Recognition {
  std::vector<AppearanceMatch> matches;  // verified, best score first
  int candidates = 0;                    // verified or not
  int rejected = 0;                      // candidates that failed verification
};

// The candidate keyframe's stored features (with 3D points). Called from several threads at once
// (candidates are verified side by side): it must be thread-safe.
using FeatureLoader = std::function<absl::StatusOr<features::KeypointSet>(const KeyframeRef&)>;
using KeyframeFilter = std::function<bool(const KeyframeRef&)>;

// FailedPrecondition when there is nothing to match: no keyframe indexed (besides those
// `exclude` rejects), or a query with no features (all pruned, or a textureless view), saying
// which. A candidate whose features cannot be loaded counts as rejected.
absl::StatusOr<Recognition> Recognize(const features::KeypointSet& query,
                                      const CameraIntrinsics& query_intrinsics,
                                      const Vocabulary& vocabulary, const InvertedIndex& index,
                                      const FeatureLoader& load, const KeyframeFilter& exclude,
                                      const RecognizerOptions& options = {});

}  // namespace lifemap::appearance
