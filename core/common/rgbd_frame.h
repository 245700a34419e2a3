// One RGB-D observation, as received (encoded) and as decoded for the algorithms.
#pragma once

#include <cstdint>
#include <optional>
#include <vector>

#include <opencv2/core.hpp>

#include "absl/status/statusor.h"
#include "core/common/image_codec.h"
#include "core/common/types.h"

namespace lifemap {

// The robot's own motion estimate at a frame's time (wheel odometry, or any dead reckoning):
// the camera's pose in the odometry's frame, which drifts but never jumps. Only increments
// between a visit's frames are used, so its origin does not matter.
struct OdometryReading {
  Pose T_odom_camera;
  // 6x6, row-major over (x, y, z, rotation about x, y, z), metres² and radians², cumulative as in
  // ROS nav_msgs/Odometry: the uncertainty of an increment is the difference of its ends'. Unset:
  // the server's default (tracking::OdometryOptions, 2 % of the distance travelled).
  std::optional<Eigen::Matrix<double, 6, 6>> covariance;

  // A reading from a validated pose and `covariance_row_major` (0 values: none, else 36).
  // InvalidArgument (naming "covariance") for another count, values not finite, a matrix that is
  // not symmetric (within 1e-9 relative) or not positive definite.
  static absl::StatusOr<OdometryReading> Make(const Pose& T_odom_camera,
                                              const std::vector<double>& covariance_row_major);
};

// A frame as it arrives: encoded images that view the caller's buffers (not owned).
struct EncodedRgbdFrame {
  uint64_t sequence = 0;
  double timestamp_s = 0.0;  // capture time, seconds since the Unix epoch; > 0
  CameraIntrinsics intrinsics;
  EncodedDepth depth;
  EncodedColor color;
  std::optional<Pose> T_world_camera;  // from the client, already validated
  // Gravity in the camera frame, unit length (an IMU's reading, normalised), when the client
  // sent one.
  std::optional<Eigen::Vector3d> gravity_camera;
  std::optional<OdometryReading> odometry;  // already validated
};

// A decoded frame. depth_m is CV_32FC1 metres (0 = no reading); color_bgr CV_8UC3; both of the
// intrinsics' size.
struct RgbdFrame {
  uint64_t sequence = 0;
  double timestamp_s = 0.0;
  CameraIntrinsics intrinsics;
  cv::Mat depth_m;
  cv::Mat color_bgr;
  std::optional<Pose> T_world_camera;
  std::optional<Eigen::Vector3d> gravity_camera;  // unit length, when the client sent it
  std::optional<OdometryReading> odometry;        // when the client sent it
};

// What a frame may hold (config section `frames`).
struct FrameLimits {
  DepthRange depth_range;            // readings outside are no reading
  int64_t max_pixels = 1280 * 1024;  // per image; [kMinSide², kMaxSide²] of CameraIntrinsics
  absl::Status Validate() const;
};

// Validates the timestamp and intrinsics, checks both images against the intrinsics' size and
// decodes them. InvalidArgument names the field and what to send instead. Without
// `decode_color` the colour is neither checked nor decoded (color_bgr stays empty): for uses of
// depth alone. InvalidArgument for a frame of more than limits.max_pixels; depth readings
// outside limits.depth_range count as no reading.
absl::StatusOr<RgbdFrame> DecodeRgbdFrame(const EncodedRgbdFrame& in, bool decode_color = true,
                                          const FrameLimits& limits = {});

struct DepthStats {
  float valid_fraction = 0.0f;  // share of pixels with a reading, [0, 1]
  float median_m = 0.0f;        // median over valid pixels; 0 when there are none
};

DepthStats ComputeDepthStats(const cv::Mat& depth_m);

}  // namespace lifemap
