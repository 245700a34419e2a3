// Plain geometric types shared by every lifemap module.
#pragma once

#include <Eigen/Geometry>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace lifemap {

// Pinhole intrinsics of a depth-registered colour camera, in pixels.
struct CameraIntrinsics {
  double fx = 0.0;
  double fy = 0.0;
  double cx = 0.0;
  double cy = 0.0;
  int width = 0;   // image width the intrinsics refer to, pixels
  int height = 0;  // image height, pixels

  // InvalidArgument unless fx, fy are finite and a physical focal length for the image's side
  // (fx / width and fy / height within [kMinFocalPerSide, kMaxFocalPerSide]: fields of view
  // from about 1° to 170°), the size is within [kMinSide, kMaxSide] and the principal point
  // lies inside the image.
  absl::Status Validate() const;

  static constexpr int kMinSide = 8;
  static constexpr int kMaxSide = 4096;
  static constexpr double kMinFocalPerSide = 0.04;
  static constexpr double kMaxFocalPerSide = 60.0;
};

// A rigid transform T_a_b (maps points from frame b into frame a). Units: metres.
struct Pose {
  Eigen::Vector3d translation = Eigen::Vector3d::Zero();
  Eigen::Quaterniond rotation = Eigen::Quaterniond::Identity();

  Eigen::Isometry3d ToIsometry() const;
  static Pose FromIsometry(const Eigen::Isometry3d& T);

  // Builds a pose from raw components as received from a client or a file. InvalidArgument
  // for NaN/inf values, a translation component beyond kMaxTranslationM or a quaternion whose
  // norm is not within kUnitTolerance of 1; otherwise the quaternion is normalised.
  static absl::StatusOr<Pose> FromComponents(double tx, double ty, double tz, double qx, double qy,
                                             double qz, double qw);

  static constexpr double kUnitTolerance = 1e-3;
  // An indoor map spans far less: coordinates are relative to the map's own origin.
  static constexpr double kMaxTranslationM = 1e4;
};

// Translation distance (metres) and rotation angle (radians) between two poses.
double TranslationDistanceM(const Pose& a, const Pose& b);
double RotationAngleRad(const Pose& a, const Pose& b);

// Interpolates between two poses: linear in translation, slerp in rotation; t in [0, 1].
Pose Interpolate(const Pose& a, const Pose& b, double t);

}  // namespace lifemap
