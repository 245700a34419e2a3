// Paper 002's semantic octree served (issue 16): each visit's posed, labelled keyframes are
// fused into the visit's octree off the reply path (on a SerialWorker, in keyframe order), and
// every posed frame of the visit gets the octree's labels rendered into it.
//
// One octree per visit, in the visit's frame: client poses, or the server's tracking (with the
// pose-graph correction known when the keyframe was fused). Snapshots go to the store every
// kSemanticSnapshotKeyframes fused keyframes and when the visit ends, and a resumed visit
// starts from its snapshot. A map's octree is merged from its visits' snapshots when exported
// (server/semantic_export.h). A visit's octree can be rebuilt from its stored keyframes
// (server/semantic_rebuild.h).
#pragma once

#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "core/common/types.h"
#include "core/semantic/semantic_map.h"
#include "server/store/store.h"

namespace lifemap::server {

// Keyframes fused between two snapshots of a visit's octree (and one when the visit ends).
inline constexpr int kSemanticSnapshotKeyframes = 10;

// What the worker fuses of one keyframe.
struct SemanticKeyframe {
  std::string model;  // the name of the model that labelled it
  int class_count = 0;
  std::vector<double> class_prior;
  cv::Mat depth_m;
  CameraIntrinsics intrinsics;
  Pose T_visit_camera;
  std::vector<cv::Mat> probabilities;  // the forest's, per class
};

// Thread-safe: Fuse on the worker, Render from any frame's thread.
class VisitSemantics {
 public:
  // Fuses a keyframe. The octree is made for the model that labels the visit's first fused
  // keyframe; a keyframe labelled by another model (the map's active model changed) starts the
  // octree afresh for that model: a map's octree holds one model's classes. Errors (bad input)
  // are kept for the frames' output status.
  void Fuse(const SemanticKeyframe& keyframe, const semantic::SemanticMapOptions& options);

  // The octree's labels in a frame labelled by `model` at T_visit_camera. FailedPrecondition
  // saying why not: no keyframe fused yet (or every fusion failed: why), or fused with another
  // model; InvalidArgument for a bad frame or a pose outside the octree.
  absl::StatusOr<semantic::RenderedLabels> Render(const std::string& model, const cv::Mat& depth_m,
                                                  const CameraIntrinsics& intrinsics,
                                                  const Pose& T_visit_camera, int stride) const;

  // A snapshot for the store when at least `every` keyframes were fused since the last one
  // (any, with `every` 0), else nullopt. Counts it as taken. Call it from the thread that
  // fuses (the semantic worker): frames render while the octree is serialised.
  std::optional<store::SemanticSnapshotRecord> SnapshotIfDue(int64_t visit_id, int every);
  // Restores a stored snapshot (a resumed visit after a restart). A damaged or incompatible
  // one (resolution changed in the config) is logged and skipped: the octree starts empty.
  void Restore(const store::SemanticSnapshotRecord& snapshot,
               const semantic::SemanticMapOptions& options);
  // Puts `map` (labelled by `model`, stored already) in place of the octree: a rebuild.
  void Replace(std::unique_ptr<semantic::SemanticMap> map, const std::string& model);
  // Keyframes given to Fuse so far (fused or refused): a rebuild checks that none came while
  // it ran.
  int64_t fusions() const;

 private:
  mutable absl::Mutex mu_;
  std::unique_ptr<semantic::SemanticMap> map_ ABSL_GUARDED_BY(mu_);
  std::string model_ ABSL_GUARDED_BY(mu_);
  absl::Status error_ ABSL_GUARDED_BY(mu_);  // the last fusion's, if it failed
  int fused_since_snapshot_ ABSL_GUARDED_BY(mu_) = 0;
  int64_t fusions_ ABSL_GUARDED_BY(mu_) = 0;
};

// The store's record of `map`, a visit's octree labelled by `model`, stamped now.
store::SemanticSnapshotRecord SemanticSnapshotOf(int64_t visit_id, const std::string& model,
                                                 const semantic::SemanticMap& map);

// Stores the visit's octree when a snapshot is due (VisitSemantics::SnapshotIfDue); a failed
// write is logged (the octree stays in memory and the next snapshot tries again).
void StoreSemanticSnapshotIfDue(store::Store* store, int64_t visit_id, VisitSemantics* semantics,
                                int every);

}  // namespace lifemap::server
