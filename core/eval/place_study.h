// Paper 004's evaluation on lifemap's synthetic suite (`lifemap sim suite`): every visit's floor
// plan against its scene's ground truth (the paper's Fig. 11: wall lengths, corner angles,
// openings), and place recognition per condition subset (Table 2) by architecture and, as a
// baseline in the same run, by appearance alone.
//
// Recognition is open-set: each query visit is tried twice, once against the references of
// every place (its own among them: a "known" trial) and once with its own place left out (an
// "unknown" trial, which should be rejected). At a score threshold t a trial's best reference is
// accepted when its score is at least t; precision = right accepts / all accepts, recall =
// right accepts / known trials.
#pragma once

#include <array>
#include <functional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/features/keypoints.h"
#include "core/place/descriptor.h"
#include "core/place/floor_plan.h"
#include "core/tracking/keyframe_selector.h"

namespace lifemap::eval {

struct PlaceStudyOptions {
  tracking::KeyframeOptions keyframes;  // the server's key-frame selection
  place::FloorPlanOptions floor_plan;
  place::MatchWeights weights;
  int appearance_keyframes = 8;  // evenly spaced key frames per visit the baseline keeps (0: none)
  int orb_keypoints = 500;
  double ratio_test = 0.8;  // Lowe's ratio for ORB matches
  double ransac_px = 2.0;   // fundamental-matrix RANSAC threshold
  int threads = 0;          // 0 = one per core
  // Score thresholds to accept a match at, per method; negative: the one of the best F1 over
  // the suite (optimistic). Fixed ones (chosen on another suite) make the evaluation held out.
  double architecture_threshold = -1;
  double appearance_threshold = -1;
};

// The floor plan a synthetic visit's scene.json describes: the main room's walls
// (counter-clockwise) with the doors and windows open on this visit, and its stairs.
struct TruthPlan {
  std::string place_id, shape;
  place::FloorPlan plan;
  int closed_doors = 0;  // flush with their wall: no gap for the builder to find
};
// NotFound without the file; InvalidArgument naming what is malformed.
absl::StatusOr<TruthPlan> ReadTruthPlan(const std::string& scene_json_path);

// A built plan against the truth. Walls pair by line: direction within 10°, the built wall's
// middle within 0.3 m of the truth's line, overlapping over half the shorter of the two (each
// wall pairs once, largest overlap first). A corner is compared where truth walls i and i+1 pair
// with consecutive built walls. A truth opening is found when its paired wall has an opening of
// the same type whose middle is within max(0.3 m, half its width) of the truth's.
struct WallPair {
  int truth = -1, built = -1;
  double truth_m = 0, built_m = 0;
};
struct FloorPlanError {
  int truth_walls = 0, built_walls = 0, walls_found = 0;
  std::vector<WallPair> pairs;
  std::vector<double> length_errors_m;   // |built − truth| per paired wall
  std::vector<double> angle_errors_deg;  // per corner compared
  int truth_openings = 0, openings_found = 0, extra_openings = 0;
  int truth_stairs = 0, stairs_found = 0;  // same direction, centre within 1 m
  bool outline_right = false;              // every wall paired, none extra, in the same order
};
FloorPlanError CompareFloorPlans(const place::FloorPlan& built, const place::FloorPlan& truth);

// A TUM-format visit folded as the server folds one: key frames chosen on its ground-truth
// poses, each one's planes into a floor plan; and ORB of evenly spaced key frames for the
// appearance baseline.
struct FoldedVisit {
  int frames = 0, keyframes = 0;
  absl::Status plan_status;  // why there is no plan, when there is none
  place::FloorPlan plan;
  place::PlaceDescriptor descriptor;
  std::vector<features::KeypointSet> appearance;
};
// FailedPrecondition when frames lack poses (groundtruth.txt); reading errors as they come.
absl::StatusOr<FoldedVisit> FoldVisit(const std::string& tum_dir, const PlaceStudyOptions& options);

// Appearance similarity in [0, 1]: for each of the query's kept key frames, the best share of
// its keypoints that are RANSAC inliers of ratio-test matches against one of the reference's
// key frames; the mean over the query's frames.
double AppearanceSimilarity(const FoldedVisit& query, const FoldedVisit& reference,
                            const PlaceStudyOptions& options);

struct PrPoint {
  double threshold = 0, precision = 1, recall = 0, f1 = 0;
};

struct RecognitionTrial {
  size_t query = 0;  // index into PlaceStudy::visits
  int subset = 0;    // 1..8
  bool known = true;
  std::string predicted;  // best reference's place ("" when the gallery is empty)
  double score = 0;
  bool correct = false;  // known and predicted its own place
};

// Precision, recall and F1 of `trials` (of one subset when subset > 0) at `threshold`.
PrPoint EvaluateTrials(const std::vector<RecognitionTrial>& trials, double threshold,
                       int subset = 0);

struct MethodResult {
  std::string name;  // "architecture" or "appearance"
  std::vector<RecognitionTrial> trials;
  std::vector<PrPoint> curve;  // every subset together, threshold swept 0..1
  PrPoint operating;           // the threshold of the best F1 over every subset together
  std::array<PrPoint, 8> subsets;
  std::array<double, 8> top1{};  // known trials whose best reference is their own place
};

struct SuiteVisit {
  std::string path, place_id, shape, role, conditions;
  int subset = 0;  // 0 = reference
  FoldedVisit folded;
  bool has_truth = false;
  TruthPlan truth;
  FloorPlanError error;  // with truth (a visit without a plan: an empty one's)
};

struct PlaceStudy {
  std::vector<SuiteVisit> visits;
  MethodResult architecture, appearance;
  double seconds = 0;
};

// The visits DIR/manifest.json (lifemap sim suite) lists, with role, subset and shape (nothing
// folded). NotFound without it; InvalidArgument for a malformed one.
absl::StatusOr<std::vector<SuiteVisit>> ReadSuiteManifest(const std::string& suite_dir);

// Fills m->curve (thresholds 0..1 in steps of 0.005), m->operating (at `threshold`, or the best
// F1 over every subset when it is negative), m->subsets and m->top1 from m->trials.
void SummariseTrials(double threshold, MethodResult* m);

// Runs job(0..n-1) on `threads` threads (0 = one per core).
void ParallelFor(size_t n, int threads, const std::function<void(size_t)>& job);

// Reads DIR/manifest.json (lifemap sim suite), folds every visit and evaluates. `progress`
// (may be empty) hears one line per folded visit.
absl::StatusOr<PlaceStudy> RunPlaceStudy(const std::string& suite_dir,
                                         const PlaceStudyOptions& options,
                                         const std::function<void(const std::string&)>& progress);

}  // namespace lifemap::eval
