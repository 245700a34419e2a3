// Per-superjut low-level features (paper 000, section III-B) and the neg-entropy score and mask
// (eq. 4) used to prune zones likely to move before matching.
#pragma once

#include <vector>

#include <Eigen/Core>
#include <opencv2/core.hpp>

#include "absl/status/statusor.h"
#include "core/normals/normals.h"
#include "core/segmentation/superjuts.h"

namespace lifemap::entropy {

struct EntropyOptions {
  int bins = 80;  // M, points on the golden spiral, [2, 255]
  // Eigen-transform textureness (Targhi et al.) on square windows of this side, evaluated every
  // `texture_stride_px` pixels (each pixel takes the value of its window); 0 stride = off.
  int texture_window_px = 16;
  int texture_stride_px = 16;

  absl::Status Validate() const;
};

struct SuperjutScore {
  int id = 0;
  int size_px = 0;
  float entropy = 0;        // -sum p log p of the histogram of normals, nats, [0, log M]
  float planarity = 0;      // share of the dominant bin, (0, 1]
  float horizontality = 0;  // |up . n_mode|: 1 = horizontal surface (floor, table), 0 = wall
  float textureness = 0;    // mean eigen-transform over the superjut's pixels, [0, 1]
  float neg_entropy = 0;    // eq. 4: 1 - entropy / log M, [0, 1]; low = likely to move
};

// Scores every superjut. `gray` (CV_8UC1, same size) feeds textureness; empty = textureness 0.
// `up_camera` is the unit "up" direction (against gravity) in the camera frame: from the pose
// when known, else the image's up, (0, -1, 0).
absl::StatusOr<std::vector<SuperjutScore>> ScoreSuperjuts(const segmentation::Superjuts& superjuts,
                                                          const normals::NormalMap& normals,
                                                          const cv::Mat& gray,
                                                          const Eigen::Vector3f& up_camera,
                                                          const EntropyOptions& options = {});

// Eigen-transform of a grey image on a grid: CV_32FC1 of ceil(rows/stride) x ceil(cols/stride),
// each the mean of the smaller singular values (all but the two largest) of the window centred
// there, intensities scaled to [0, 1] and divided by the window side so values lie in [0, 1].
cv::Mat EigenTransformGrid(const cv::Mat& gray, int window_px, int stride_px);

// Neg-entropy per pixel as 0–255 (CV_8UC1); 0 where there is no superjut.
cv::Mat NegEntropyImage(const segmentation::Superjuts& superjuts,
                        const std::vector<SuperjutScore>& scores);

// 255 where the pixel's superjut scores below `threshold` (likely to move), else 0.
cv::Mat EntropyMask(const segmentation::Superjuts& superjuts,
                    const std::vector<SuperjutScore>& scores, float threshold);

}  // namespace lifemap::entropy
