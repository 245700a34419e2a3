#include "core/entropy/entropy_mask.h"

#include <cmath>

#include <opencv2/imgproc.hpp>

#include "absl/strings/str_cat.h"

namespace lifemap::entropy {

absl::Status EntropyMaskOptions::Validate() const {
  if (downsample < 1 || downsample > 8) {
    return absl::InvalidArgumentError(
        absl::StrCat("downsample must be within [1, 8], got ", downsample));
  }
  if (!(threshold >= 0.0f && threshold <= 1.0f)) {
    return absl::InvalidArgumentError(
        absl::StrCat("entropy threshold must be within [0, 1], got ", threshold));
  }
  if (auto s = normals.Validate(); !s.ok()) return s;
  if (auto s = superjuts.Validate(); !s.ok()) return s;
  return scores.Validate();
}

absl::StatusOr<EntropyMaskResult> ComputeEntropyMask(const cv::Mat& depth_m,
                                                     const cv::Mat& color_bgr,
                                                     const CameraIntrinsics& intrinsics,
                                                     const Eigen::Vector3f& up_camera,
                                                     const EntropyMaskOptions& options) {
  if (auto s = options.Validate(); !s.ok()) return s;
  if (depth_m.empty() || depth_m.type() != CV_32FC1 || depth_m.cols != intrinsics.width ||
      depth_m.rows != intrinsics.height) {
    return absl::InvalidArgumentError(
        "entropy masks need CV_32FC1 depth in metres of the intrinsics' size");
  }
  if (!color_bgr.empty() && (color_bgr.size() != depth_m.size() || color_bgr.type() != CV_8UC3)) {
    return absl::InvalidArgumentError("colour must be CV_8UC3 of the depth's size");
  }
  if (!(std::abs(up_camera.norm() - 1.0f) < 1e-3f)) {
    return absl::InvalidArgumentError("up direction must be a unit vector");
  }
  const int f = options.downsample;
  cv::Mat depth = depth_m, gray;
  CameraIntrinsics k = intrinsics;
  if (f > 1) {
    depth = cv::Mat((depth_m.rows + f - 1) / f, (depth_m.cols + f - 1) / f, CV_32FC1);
    for (int r = 0; r < depth.rows; ++r) {
      const float* src = depth_m.ptr<float>(r * f);
      float* dst = depth.ptr<float>(r);
      for (int c = 0; c < depth.cols; ++c) dst[c] = src[c * f];
    }
    // Pixel (c, r) of the subsampled image is pixel (f c, f r) of the original.
    k.fx /= f, k.fy /= f, k.cx /= f, k.cy /= f;
    k.width = depth.cols, k.height = depth.rows;
  }
  if (!color_bgr.empty() && options.textureness) {
    cv::Mat full_gray;
    cv::cvtColor(color_bgr, full_gray, cv::COLOR_BGR2GRAY);
    if (f > 1) {
      cv::resize(full_gray, gray, depth.size(), 0, 0, cv::INTER_AREA);
    } else {
      gray = full_gray;
    }
  }
  // Eq. 2 neighbours and smoothing act on the working image; keep their reach in full-size
  // pixels roughly constant.
  normals::NormalOptions normal_options = options.normals;
  normal_options.smoothing_radius_px = std::max(1, normal_options.smoothing_radius_px / f);
  normal_options.neighbor_step_px = std::max(1, normal_options.neighbor_step_px / f);
  normal_options.method =
      options.mesh ? normals::NormalMethod::kMeshVertex : normals::NormalMethod::kCrossProduct;
  auto map = normals::ComputeNormals(depth, k, normal_options);
  if (!map.ok()) return map.status();
  segmentation::SuperjutOptions superjut_options = options.superjuts;
  superjut_options.min_size_px = std::max(1, superjut_options.min_size_px / (f * f));
  superjut_options.graph =
      options.mesh ? segmentation::SuperjutGraph::kMesh : segmentation::SuperjutGraph::kImageGrid;
  auto superjuts = segmentation::SegmentSuperjuts(*map, superjut_options);
  if (!superjuts.ok()) return superjuts.status();
  auto scores = ScoreSuperjuts(*superjuts, *map, gray, up_camera, options.scores);
  if (!scores.ok()) return scores.status();

  EntropyMaskResult out;
  out.threshold = options.threshold;
  out.superjuts = *std::move(scores);
  for (auto& s : out.superjuts) s.size_px *= f * f;
  cv::Mat score = NegEntropyImage(*superjuts, out.superjuts);
  cv::Mat mask = EntropyMask(*superjuts, out.superjuts, options.threshold);
  if (f > 1) {
    const cv::Size full = depth_m.size();
    cv::resize(superjuts->labels, out.labels, full, 0, 0, cv::INTER_NEAREST);
    cv::resize(score, out.score_image, full, 0, 0, cv::INTER_NEAREST);
    cv::resize(mask, out.mask, full, 0, 0, cv::INTER_NEAREST);
  } else {
    out.labels = superjuts->labels;
    out.score_image = score;
    out.mask = mask;
  }
  return out;
}

}  // namespace lifemap::entropy
