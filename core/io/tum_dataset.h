// Reader for TUM RGB-D benchmark folders (rgb/, depth/, rgb.txt, depth.txt, groundtruth.txt),
// the format of the real recordings and of lifemap's synthetic world.
#pragma once

#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/rgbd_frame.h"
#include "core/common/types.h"

namespace lifemap::io {

struct TimedPose {
  double timestamp_s = 0.0;
  Pose pose;  // T_world_camera
};

struct TumFrameEntry {
  double timestamp_s = 0.0;  // the colour image's time
  std::string rgb_path;      // absolute or relative to the working directory
  double depth_timestamp_s = 0.0;
  std::string depth_path;
  std::optional<Pose> T_world_camera;  // ground truth interpolated at timestamp_s, if known
  // Gravity's direction in the camera frame (unit; x right, y down, z forward) from the
  // recording's accelerometer.txt, if it has one (TumGravityFromAccelerometer).
  std::optional<Eigen::Vector3d> gravity_camera;
  // The robot's odometry at the frame's time (T_odom_camera) from the recording's odometry.txt
  // (TUM trajectory lines), if it has one: interpolated like the ground truth.
  std::optional<Pose> T_odom_camera;
};

struct TumReadOptions {
  // Colour and depth images are paired when their times differ by less than this (TUM's
  // associate.py uses 0.02 s).
  double max_association_dt_s = 0.02;
  // Ground truth is interpolated only between samples at most this far apart (mocap: 0.01 s).
  double max_groundtruth_gap_s = 0.1;
  // A frame's gravity is the mean of the accelerometer's readings within this of its time (the
  // Kinect's runs at ~100 Hz; averaging takes out some of a hand-held camera's own motion).
  double accelerometer_window_s = 0.1;
  // A list file that names the pairs directly ("t_rgb rgb_path t_depth depth_path"); empty =
  // pair rgb.txt and depth.txt by time.
  std::string associations_file;
};

struct TumSequence {
  std::string dir;
  std::vector<TumFrameEntry> frames;  // time order, only pairs whose files exist
  int listed_but_missing = 0;         // entries named in the lists whose files are absent
  bool has_groundtruth = false;
  int frames_with_pose = 0;
  bool has_accelerometer = false;  // accelerometer.txt was read
  int frames_with_gravity = 0;
  bool has_odometry = false;  // odometry.txt was read
  int frames_with_odometry = 0;
  std::optional<CameraIntrinsics> intrinsics;  // from DIR/intrinsics.txt when present
};

// Reads a TUM-format folder. NotFound when the folder or its lists are missing;
// InvalidArgument for malformed lines (with file and line number); FailedPrecondition when no
// colour/depth pair remains.
absl::StatusOr<TumSequence> ReadTumSequence(const std::string& dir,
                                            const TumReadOptions& options = {});

// One frame of a sequence read and decoded (16-bit PNG depth at TUM's 5000 units per metre,
// PNG or JPEG colour), with its intrinsics (TumSequenceIntrinsics) and its ground-truth pose
// when known. Without `decode_color` the colour file is not read (color_bgr stays empty; the
// size comes from the depth image). NotFound for a missing file; InvalidArgument names the
// image that does not decode.
absl::StatusOr<RgbdFrame> DecodeTumFrame(const TumSequence& seq, const TumFrameEntry& entry,
                                         bool decode_color = true);

// Gravity's direction in the camera frame from one reading of a TUM recording's
// accelerometer.txt ("timestamp ax ay az", m/s^2). The Kinect's accelerometer measures the
// support force (up) in a frame turned 180 degrees about the optical axis from the camera's, so
// gravity in the camera frame is (ax, ay, -az) normalised: on fr1_xyz this agrees with the
// mocap ground truth's vertical within 5 degrees (median; the hand-held camera's own
// accelerations add up to ~15). lifemap's synthetic recordings write the same convention.
// InvalidArgument for a reading of (near) zero length or not finite.
absl::StatusOr<Eigen::Vector3d> TumGravityFromAccelerometer(const Eigen::Vector3d& reading);
// The inverse: the reading a still accelerometer gives for `gravity_camera` (any length),
// 9.81 m/s^2 long.
Eigen::Vector3d TumAccelerometerReading(const Eigen::Vector3d& gravity_camera);

// Reads "timestamp tx ty tz qx qy qz qw" lines (comments with '#').
absl::StatusOr<std::vector<TimedPose>> ReadTumTrajectory(const std::string& path);

// The pose at time t by interpolation between the two samples around t, or nullopt when t is
// outside the trajectory or the samples around it are more than max_gap_s apart.
std::optional<Pose> InterpolateTrajectory(const std::vector<TimedPose>& trajectory, double t,
                                          double max_gap_s);

// One TUM trajectory line, "timestamp tx ty tz qx qy qz qw", without a newline.
std::string FormatTumPoseLine(double timestamp_s, const Pose& pose);

// Intrinsics of a sequence's images of width × height: its intrinsics.txt (source
// "intrinsics.txt"), else TumIntrinsicsFor its folder.
CameraIntrinsics TumSequenceIntrinsics(const TumSequence& seq, int width, int height,
                                       std::string* source);

// Intrinsics for a TUM folder: DIR/intrinsics.txt ("fx fy cx cy"), else the official
// calibration of the freiburg1/2/3 camera named in the path, else TUM's ROS default
// (525, 525, 319.5, 239.5). `source` says which was used.
CameraIntrinsics TumIntrinsicsFor(const std::string& dir, int width, int height,
                                  std::string* source);

}  // namespace lifemap::io
