// Baselines the forest is read against (issue 5): a purely geometric table/object labeller and
// OpenCV's random trees on simple per-pixel features.
#pragma once

#include <memory>
#include <vector>

#include <opencv2/core.hpp>

#include "absl/status/statusor.h"
#include "core/common/types.h"
#include "core/forest/forest.h"

namespace lifemap::forest {

// Fits the dominant plane of the depth image by RANSAC (the supporting table) and labels
// pixels more than `height_m` on the camera's side of it as 1 (object), the rest 0 (table);
// kIgnore without depth. Deterministic for a seed.
cv::Mat PlaneBaseline(const cv::Mat& depth_m, const CameraIntrinsics& k, float height_m = 0.015f,
                      uint64_t seed = 1);

// cv::ml::RTrees on per-pixel (depth, L*, a*, b*) with no context: what the forest's
// depth-normalised region features add is the difference.
class PixelTreesBaseline {
 public:
  static absl::StatusOr<PixelTreesBaseline> Train(const std::vector<LabeledImage>& images,
                                                  int class_count, int pixels_per_image = 2000,
                                                  uint64_t seed = 1);
  // Labels every `stride`-th pixel with depth (blocks copy their corner), kIgnore elsewhere.
  cv::Mat Predict(const cv::Mat& depth_m, const cv::Mat& color_bgr, int stride = 2) const;

 private:
  struct Impl;
  std::shared_ptr<Impl> impl_;
};

}  // namespace lifemap::forest
