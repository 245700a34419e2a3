// Paper 002's semi-automatic annotation (issue 38): a class given once to a region of a map's
// frame (AnnotationRecord: boxes, a selected voxel being one) is projected into every keyframe
// that sees it, giving per-pixel labels for training the forest without labelling images one by
// one. The result is a TUM-format labelled folder that `lifemap train --data DIR
// --frame-stride 1` reads (core/forest/labeled_data.h, "label-png").
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/rgbd_frame.h"
#include "server/store/store.h"

namespace lifemap::server {

// Limits on what an annotation may hold (validated before it is stored).
inline constexpr int kMaxAnnotationBoxes = 100000;
inline constexpr double kMaxAnnotationExtentM = 1000.0;  // |coordinate| and box side

// INVALID_ARGUMENT naming what is wrong: a class name that is not 1-64 printable characters
// other than '/', no boxes or more than kMaxAnnotationBoxes, a box whose min exceeds its max,
// a coordinate that is not finite or beyond kMaxAnnotationExtentM.
absl::Status ValidateAnnotation(const store::AnnotationRecord& annotation);

// The folder's classes: "background" first (class 0), then every other class the annotations
// name, in the order they were first given.
std::vector<std::string> AnnotationClasses(const std::vector<store::AnnotationRecord>& all);

// Labels of one view: 8-bit class ids (AnnotationClasses' order; 255 where no annotation holds
// the pixel's depth point, or no depth). A point inside boxes of several annotations takes the
// latest one's class. `margin_m` grows every box on each side (depth noise puts a surface a
// little outside the voxels it was seen in). `labelled` counts the labelled pixels.
// AnnotationProjector holds the boxes hashed once, for projecting into many views (a training
// folder's); ProjectAnnotations builds one for a single view.
class AnnotationProjector {
 public:
  AnnotationProjector(const std::vector<store::AnnotationRecord>& annotations,
                      const std::vector<std::string>& classes, double margin_m);
  ~AnnotationProjector();
  AnnotationProjector(const AnnotationProjector&) = delete;
  AnnotationProjector& operator=(const AnnotationProjector&) = delete;
  cv::Mat Project(const RgbdFrame& frame, const Pose& T_map_camera, int64_t* labelled) const;

 private:
  class BoxGrid;
  std::unique_ptr<BoxGrid> grid_;
};
cv::Mat ProjectAnnotations(const std::vector<store::AnnotationRecord>& annotations,
                           const std::vector<std::string>& classes, const RgbdFrame& frame,
                           const Pose& T_map_camera, double margin_m, int64_t* labelled);

struct TrainingFolderOptions {
  double margin_m = 0.02;
  int64_t min_labelled_pixels = 100;  // views with fewer are left out
};

struct TrainingFolder {
  std::vector<std::string> classes;
  int64_t keyframes_seen = 0;  // posed keyframes in the map's frame looked at
  int64_t views_written = 0;   // of those, with at least min_labelled_pixels
  int64_t labelled_pixels = 0;
  std::vector<int64_t> class_pixels;  // per class
  std::vector<std::string> left_out;  // visits not in the map's frame, other cameras
};

// Projects map `map`'s annotations into its posed keyframes in the map's frame and hands every
// file of the folder to `write` (a path relative to the folder, its bytes): rgb/ID.jpg|png (the
// stored colour as stored), depth/ID.png (PNG-16, 5000 per metre), labels/ID.png,
// labels/classes.txt, rgb.txt and depth.txt (one second apart, in keyframe order) and
// intrinsics.txt. Keyframes of a camera other than the first one's are left out (one folder
// has one camera). FAILED_PRECONDITION when the map has no annotation or no view sees one;
// CANCELLED when `cancelled` says so; `write`'s own error ends it.
absl::StatusOr<TrainingFolder> ExportTrainingFolder(
    store::Store* store, const store::MapRecord& map, const TrainingFolderOptions& options,
    const std::function<bool()>& cancelled,
    const std::function<absl::Status(const std::string& path, const std::string& bytes)>& write);

}  // namespace lifemap::server
