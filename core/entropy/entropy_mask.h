// The per-frame entropy-mask path: depth (+ colour) -> normals -> superjuts -> scores -> score
// image and mask. The server and the evaluation tools call this one function.
#pragma once

#include <vector>

#include <Eigen/Core>
#include <opencv2/core.hpp>

#include "absl/status/statusor.h"
#include "core/entropy/superjut_scores.h"

namespace lifemap::entropy {

struct EntropyMaskOptions {
  // Work on every `downsample`-th pixel of each row and column (depth is subsampled, not
  // averaged, so depth edges stay sharp); the score image and mask come back at full size.
  // 2 (320x240 from 640x480) keeps the whole path near 10 ms on one core; 1 = full resolution.
  int downsample = 2;
  // The paper's mesh variant (organized-mesh vertex normals and triangle edges) instead of the
  // image-domain one (eq. 2 normals, 8-connected grid). Overrides normals.method and
  // superjuts.graph.
  bool mesh = false;
  normals::NormalOptions normals;
  segmentation::SuperjutOptions superjuts;  // min_size_px counts full-resolution pixels
  EntropyOptions scores;
  bool textureness = true;
  float threshold = 0.5f;  // superjuts with neg-entropy below this are masked, [0, 1]

  absl::Status Validate() const;
};

struct EntropyMaskResult {
  std::vector<SuperjutScore> superjuts;  // size_px in full-resolution pixels
  cv::Mat labels;                        // CV_32SC1 full size, superjut id or -1
  cv::Mat score_image;  // CV_8UC1 full size, neg-entropy 0-255 (0 where no superjut)
  cv::Mat mask;         // CV_8UC1 full size, 255 = masked (likely to move)
  float threshold = 0;
};

// depth_m CV_32FC1 metres of the intrinsics' size; color_bgr CV_8UC3 of the same size or empty
// (textureness 0). up_camera: unit up direction in the camera frame.
absl::StatusOr<EntropyMaskResult> ComputeEntropyMask(const cv::Mat& depth_m,
                                                     const cv::Mat& color_bgr,
                                                     const CameraIntrinsics& intrinsics,
                                                     const Eigen::Vector3f& up_camera,
                                                     const EntropyMaskOptions& options = {});

}  // namespace lifemap::entropy
