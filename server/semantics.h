// Paper 002's semantic octree served (issue 16): each visit's posed, labelled keyframes are
// fused into the visit's octree off the reply path (on a SerialWorker, in keyframe order), and
// every posed frame of the visit gets the octree's labels rendered into it.
//
// One octree per visit, in the visit's frame: client poses, or the server's tracking (with the
// pose-graph correction known when the keyframe was fused). Not yet: octrees per map (visits
// merged once aligned), snapshots in the store (a restarted server starts the visit's octree
// empty), export.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "core/common/types.h"
#include "core/semantic/semantic_map.h"

namespace lifemap::server {

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

  semantic::SemanticSummary Summarize() const;

 private:
  mutable absl::Mutex mu_;
  std::unique_ptr<semantic::SemanticMap> map_ ABSL_GUARDED_BY(mu_);
  std::string model_ ABSL_GUARDED_BY(mu_);
  absl::Status error_ ABSL_GUARDED_BY(mu_);  // the last fusion's, if it failed
};

}  // namespace lifemap::server
