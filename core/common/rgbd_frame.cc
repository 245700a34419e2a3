#include "core/common/rgbd_frame.h"

#include <algorithm>
#include <cmath>
#include <vector>

#include <Eigen/Eigenvalues>

#include "absl/strings/str_cat.h"

namespace lifemap {

absl::Status FrameLimits::Validate() const {
  if (auto s = depth_range.Validate(); !s.ok()) return s;
  constexpr int64_t kMin = int64_t{CameraIntrinsics::kMinSide} * CameraIntrinsics::kMinSide;
  constexpr int64_t kMax = int64_t{CameraIntrinsics::kMaxSide} * CameraIntrinsics::kMaxSide;
  if (max_pixels < kMin || max_pixels > kMax) {
    return absl::InvalidArgumentError(
        absl::StrCat("max_pixels must be within [", kMin, ", ", kMax, "], got ", max_pixels));
  }
  return absl::OkStatus();
}

absl::StatusOr<OdometryReading> OdometryReading::Make(
    const Pose& T_odom_camera, const std::vector<double>& covariance_row_major) {
  OdometryReading out;
  out.T_odom_camera = T_odom_camera;
  if (covariance_row_major.empty()) return out;
  if (covariance_row_major.size() != 36) {
    return absl::InvalidArgumentError(absl::StrCat(
        "covariance must hold 36 values (6x6, row-major over x, y, z, rotation about x, y, z) or "
        "none, got ",
        covariance_row_major.size()));
  }
  Eigen::Matrix<double, 6, 6> c;
  for (int r = 0; r < 6; ++r) {
    for (int k = 0; k < 6; ++k) c(r, k) = covariance_row_major[r * 6 + k];
  }
  if (!c.allFinite()) return absl::InvalidArgumentError("covariance holds NaN or infinite values");
  if (!(c - c.transpose()).isZero(1e-9 * std::max(1.0, c.cwiseAbs().maxCoeff()))) {
    return absl::InvalidArgumentError("covariance is not symmetric");
  }
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix<double, 6, 6>> eigen(c);
  if (eigen.info() != Eigen::Success || !(eigen.eigenvalues().minCoeff() > 0)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "covariance is not positive definite (smallest eigenvalue ",
        eigen.info() == Eigen::Success ? eigen.eigenvalues().minCoeff() : 0.0,
        "); send variances > 0 on the diagonal, or no covariance for the server's default"));
  }
  out.covariance = c;
  return out;
}

absl::StatusOr<RgbdFrame> DecodeRgbdFrame(const EncodedRgbdFrame& in, bool decode_color,
                                          const FrameLimits& limits) {
  if (!std::isfinite(in.timestamp_s) || in.timestamp_s <= 0.0) {
    return absl::InvalidArgumentError(
        absl::StrCat("timestamp_s must be a positive number of seconds since the Unix epoch, got ",
                     in.timestamp_s));
  }
  if (auto s = in.intrinsics.Validate(); !s.ok()) return s;
  const int64_t pixels = int64_t{in.intrinsics.width} * in.intrinsics.height;
  if (pixels > limits.max_pixels) {
    return absl::InvalidArgumentError(
        absl::StrCat("frame is ", in.intrinsics.width, "x", in.intrinsics.height, " = ", pixels,
                     " pixels; this server takes at most ", limits.max_pixels,
                     " (frames.max_pixels): send a smaller image"));
  }

  const bool depth_declared = in.depth.width != 0 || in.depth.height != 0;
  const bool color_declared = decode_color && (in.color.width != 0 || in.color.height != 0);
  if (depth_declared && color_declared &&
      (in.depth.width != in.color.width || in.depth.height != in.color.height)) {
    // Neither is blamed alone: either may be the odd one.
    return absl::InvalidArgumentError(
        absl::StrCat("colour is declared ", in.color.width, "x", in.color.height, " and depth ",
                     in.depth.width, "x", in.depth.height,
                     "; they must be the same size (depth registered to the colour "
                     "camera), and the intrinsics say ",
                     in.intrinsics.width, "x", in.intrinsics.height));
  }
  EncodedDepth depth = in.depth;
  depth.width = in.intrinsics.width;
  depth.height = in.intrinsics.height;
  if (in.depth.width != 0 || in.depth.height != 0) {
    if (in.depth.width != depth.width || in.depth.height != depth.height) {
      return absl::InvalidArgumentError(absl::StrCat(
          "depth is declared ", in.depth.width, "x", in.depth.height, " but the intrinsics say ",
          depth.width, "x", depth.height, "; depth must be registered to the colour camera"));
    }
  }
  EncodedColor color = in.color;
  color.width = in.intrinsics.width;
  color.height = in.intrinsics.height;
  if (decode_color && (in.color.width != 0 || in.color.height != 0)) {
    if (in.color.width != color.width || in.color.height != color.height) {
      return absl::InvalidArgumentError(absl::StrCat("colour is declared ", in.color.width, "x",
                                                     in.color.height, " but the intrinsics say ",
                                                     color.width, "x", color.height));
    }
  }

  RgbdFrame out;
  out.sequence = in.sequence;
  out.timestamp_s = in.timestamp_s;
  out.intrinsics = in.intrinsics;
  out.T_world_camera = in.T_world_camera;
  out.gravity_camera = in.gravity_camera;
  out.odometry = in.odometry;
  auto d = DecodeDepthMetres(depth, limits.depth_range);
  if (!d.ok()) return d.status();
  out.depth_m = *std::move(d);
  if (!decode_color) return out;
  auto c = DecodeColorBgr(color);
  if (!c.ok()) return c.status();
  out.color_bgr = *std::move(c);
  return out;
}

DepthStats ComputeDepthStats(const cv::Mat& depth_m) {
  DepthStats stats;
  if (depth_m.empty()) return stats;
  std::vector<float> valid;
  valid.reserve(depth_m.total());
  for (int r = 0; r < depth_m.rows; ++r) {
    const float* row = depth_m.ptr<float>(r);
    for (int c = 0; c < depth_m.cols; ++c) {
      if (row[c] > 0.0f) valid.push_back(row[c]);
    }
  }
  stats.valid_fraction = static_cast<float>(valid.size()) / static_cast<float>(depth_m.total());
  if (!valid.empty()) {
    auto mid = valid.begin() + static_cast<std::ptrdiff_t>(valid.size() / 2);
    std::nth_element(valid.begin(), mid, valid.end());
    stats.median_m = *mid;
  }
  return stats;
}

}  // namespace lifemap
