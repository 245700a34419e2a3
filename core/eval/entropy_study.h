// The experiments of paper 000 on scenes with ground truth of what moves: the feature study
// (Fig. 6: how well entropy, planarity, horizontality, textureness separate moved from static
// superjuts) and the matching study (eqs. 5, 6, Figs. 9, 10: precision and recall of keypoint
// matches as neg-entropy masks prune them).
#pragma once

#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "absl/status/statusor.h"
#include "core/common/rgbd_frame.h"
#include "core/entropy/entropy_mask.h"

namespace lifemap::eval {

// One view with ground truth: `moved` marks pixels of things that move (objects), `labelled`
// the pixels whose ground truth is known (moved or static).
struct LabeledScene {
  std::string name;
  RgbdFrame frame;
  cv::Mat moved;     // CV_8UC1, 255 = moved / object
  cv::Mat labelled;  // CV_8UC1, 255 = ground truth known
};

struct FeatureStudyOptions {
  entropy::EntropyMaskOptions entropy;  // downsample 1 by default for the study
  FeatureStudyOptions() { entropy.downsample = 1; }
};

// One superjut's features and ground truth.
struct SuperjutSample {
  std::string scene;
  int id = 0;
  int size_px = 0;
  double moved_fraction = 0;  // of its labelled pixels
  bool moved = false;         // majority of labelled pixels moved
  double entropy = 0, planarity = 0, horizontality = 0, textureness = 0, neg_entropy = 0;
};

struct FeatureAuc {
  // Oriented as the paper's hypothesis: 1 = perfectly separates, 0.5 = chance. Entropy and
  // textureness are expected higher on moved superjuts, planarity and horizontality lower.
  double entropy = 0.5, planarity = 0.5, horizontality = 0.5, textureness = 0.5;
};

struct FeatureStudy {
  std::vector<SuperjutSample> superjuts;  // those with labelled pixels
  int moved_superjuts = 0;
  FeatureAuc superjut_auc;  // one sample per superjut
  FeatureAuc pixel_auc;     // one sample per labelled pixel, judged by its own label
};

absl::StatusOr<FeatureStudy> RunFeatureStudy(const std::vector<LabeledScene>& scenes,
                                             const FeatureStudyOptions& options = {});

enum class Keypoints { kSift, kOrb };

struct MatchingStudyOptions {
  entropy::EntropyMaskOptions entropy;
  Keypoints keypoints = Keypoints::kSift;
  int max_keypoints = 2000;
  double ratio = 0.85;               // Lowe's ratio test, as the paper
  double ransac_threshold_px = 2.0;  // Sampson distance for F inliers
  int ransac_iterations = 10000;
  double min_recall = 0.8;         // the best threshold per pair keeps at least this recall
  std::vector<double> thresholds;  // neg-entropy sweep; empty = 0, 0.05, ..., 1
  unsigned seed = 7;               // for the null mask's permutation
  MatchingStudyOptions() { entropy.downsample = 1; }
};

// One point of a precision–recall sweep for one pair.
struct SweepPoint {
  double threshold = 0;
  int kept = 0;          // |S_th|
  int kept_inliers = 0;  // |I_GT ∩ S_th|
  double precision = 0;  // eq. 5 (0 when nothing is kept)
  double recall = 0;     // eq. 6
  int kept_static_inliers = 0;
  double static_precision = 0;  // against the static ground truth
};

struct PairResult {
  std::string a, b;
  int matches = 0;
  int inliers = 0;         // |I_GT| (RANSAC F on all matches)
  int static_inliers = 0;  // consistent with F fitted on matches off the objects
  double raw_inlier_ratio = 0;
  double raw_static_ratio = 0;
  std::vector<SweepPoint> entropy_sweep, null_sweep;
  SweepPoint oracle;  // masking the labelled objects
};

struct MatchingSummary {
  int pairs = 0;
  int skipped_pairs = 0;  // fewer than 8 matches
  double raw_inlier_ratio = 0;
  double best_threshold = 0;       // mean over pairs of the per-pair best threshold
  double masked_inlier_ratio = 0;  // mean at each pair's best threshold
  double inlier_ratio_gain = 0;    // mean(masked) / mean(raw) - 1
  double recall_at_best = 0;
  double null_inlier_ratio_gain = 0;
  double oracle_inlier_ratio_gain = 0;
  double oracle_recall = 0;
  // The same against the static ground truth.
  double static_raw_ratio = 0, static_masked_ratio = 0, static_gain = 0;
  double static_null_gain = 0, static_oracle_gain = 0;
  // One threshold for every pair (fixed_threshold, chosen elsewhere or on this set).
  double fixed_threshold = 0, fixed_masked_ratio = 0, fixed_gain = 0, fixed_recall = 0;
  // Mean curves over pairs, per threshold.
  std::vector<double> thresholds, mean_precision, mean_recall, null_precision, null_recall;
};

struct MatchingStudy {
  std::vector<PairResult> pairs;
  MatchingSummary summary;
};

// The pairs (indices into `scenes`) to match; empty = every pair. fixed_threshold < 0: chosen
// on this set (the threshold of the best mean precision with mean recall >= min_recall).
// Scenes without ground truth (empty `moved`) count nothing as moved: oracle and static figures
// then equal the unmasked ones.
absl::StatusOr<MatchingStudy> RunMatchingStudy(const std::vector<LabeledScene>& scenes,
                                               const MatchingStudyOptions& options,
                                               double fixed_threshold = -1.0,
                                               std::vector<std::pair<size_t, size_t>> pairs = {});

}  // namespace lifemap::eval
