// Paper 000's purpose evaluated: which stored keyframe a view shows, months later, after things
// moved, by appearance with the entropy pruning and without it, on a synthetic suite (`lifemap
// sim suite`) and on real recordings.
//
// Suite. Each visit's keyframes are chosen as the server chooses them (on ground-truth poses);
// each gets ORB keypoints with 3D points, and four feature sets: pruned by its entropy mask
// ("pruned", what lifemapd stores), all of them ("unpruned"), the same number dropped at random
// ("null": does the mask beat chance?), and those on movable objects dropped by the scene's
// class labels ("oracle": what a perfect mask would give). Per feature set a vocabulary is
// trained on the reference keyframes, which are indexed; each query keyframe is recognised
// against every reference keyframe (a "known" trial) and again with its own place left out (an
// "unknown" trial, to be rejected), as lifemapd does: index candidates verified by PnP. Two more
// methods join per query keyframe: architecture alone (its visit's floor plan against every
// reference visit's, paper 004) and fused (per place, the mean of the pruned appearance score
// and the architecture score).
#pragma once

#include <array>
#include <functional>
#include <map>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/appearance/recognizer.h"
#include "core/entropy/entropy_mask.h"
#include "core/eval/place_study.h"
#include "core/pipeline/keyframe.h"

namespace lifemap::eval {

// The feature sets compared, in this order.
inline constexpr std::array<const char*, 4> kFeatureVariants = {"pruned", "unpruned", "null",
                                                                "oracle"};

struct AppearanceStudyOptions {
  PlaceStudyOptions places;  // key-frame selection and the architecture method
  pipeline::KeyframeFeatureOptions features;
  entropy::EntropyMaskOptions entropy;
  appearance::VocabularyOptions vocabulary;
  appearance::RecognizerOptions recognizer;
  // Per method ("pruned", ..., "architecture", "fused"): the score to accept a match at;
  // absent: the best F1 over every subset together (chosen on the suite itself, optimistic).
  std::map<std::string, double> thresholds;
  uint64_t seed = 1;     // the null variant's random choice
  int query_stride = 1;  // every N-th query keyframe of a visit is tried (a quicker look)
  int threads = 0;       // 0 = one per core
};

struct AppearanceMethod {
  MethodResult result;  // trials (query = index into AppearanceStudy::keyframes), curve, subsets
  std::array<double, 8> recall_at_full_precision{};
  // Verified right matches of known trials against the ground-truth relative pose: medians.
  double pose_error_cm = 0, pose_error_deg = 0;
  int poses_compared = 0;
  double mean_keypoints = 0;  // per query keyframe, after pruning
};

struct StudyKeyframe {
  size_t visit = 0;  // index into AppearanceStudy::visits
  double timestamp_s = 0;
};

struct AppearanceStudy {
  std::vector<SuiteVisit> visits;
  std::vector<StudyKeyframe> keyframes;
  std::map<std::string, AppearanceMethod> methods;  // the four variants, architecture, fused
  int reference_keyframes = 0, query_keyframes = 0;
  double pruned_share = 0;  // of detected keypoints, dropped by the entropy masks
  double seconds = 0;
};

// NotFound / InvalidArgument for the suite as ReadSuiteManifest; reading errors as they come.
absl::StatusOr<AppearanceStudy> RunAppearanceStudy(
    const std::string& suite_dir, const AppearanceStudyOptions& options,
    const std::function<void(const std::string&)>& progress);

// Real recordings: each query view against a gallery of views, per feature variant (the oracle
// where labels exist). A view's best verified score, and whether it is one the caller expects
// to be recognised.
struct RealView {
  std::string name;
  features::KeypointSet all;  // unpruned, with 3D points
  cv::Mat entropy_mask;       // 255 = masked
  cv::Mat movable;            // 255 = a labelled movable object (empty: no oracle)
  CameraIntrinsics intrinsics;
};
struct RealTrial {
  std::string query, best;  // best: the gallery view of the best verified match ("" = none)
  double score = 0;
  int inliers = 0;
};
// Per variant: for each query view (by index), recognised against `gallery` (a vocabulary
// trained on the gallery). `exclude_same_index`: the query set is the gallery (each view's own
// entry left out).
std::map<std::string, std::vector<RealTrial>> RecogniseRealViews(
    const std::vector<RealView>& gallery, const std::vector<RealView>& queries,
    bool exclude_same_index, const AppearanceStudyOptions& options);

// The views of the mOSD folder (learn/ and test/ PCDs: one table, objects changed): Kinect
// intrinsics, entropy masks, objects from the labels as the oracle's movable set.
absl::StatusOr<std::vector<RealView>> ReadMosdViews(const std::string& dir,
                                                    const AppearanceStudyOptions& options);
// The key frames of a TUM folder (chosen on its ground-truth poses, else by time).
absl::StatusOr<std::vector<RealView>> ReadTumViews(const std::string& dir,
                                                   const AppearanceStudyOptions& options);

}  // namespace lifemap::eval
