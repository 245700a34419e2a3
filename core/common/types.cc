#include "core/common/types.h"

#include <cmath>

#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"

namespace lifemap {

absl::Status CameraIntrinsics::Validate() const {
  for (double v : {fx, fy, cx, cy}) {
    if (!std::isfinite(v)) {
      return absl::InvalidArgumentError(
          "intrinsics contain NaN or infinity; send fx, fy, cx, cy as finite pixel values");
    }
  }
  if (fx <= 0.0 || fy <= 0.0) {
    return absl::InvalidArgumentError(
        absl::StrCat("intrinsics focal lengths must be > 0 pixels, got fx=", fx, " fy=", fy));
  }
  if (width < kMinSide || height < kMinSide || width > kMaxSide || height > kMaxSide) {
    return absl::InvalidArgumentError(absl::StrCat("intrinsics image size ", width, "x", height,
                                                   " is outside [", kMinSide, ", ", kMaxSide,
                                                   "] pixels per side"));
  }
  if (fx < kMinFocalPerSide * width || fx > kMaxFocalPerSide * width ||
      fy < kMinFocalPerSide * height || fy > kMaxFocalPerSide * height) {
    return absl::InvalidArgumentError(absl::StrCat(
        "intrinsics focal lengths fx=", fx, " fy=", fy, " are not physical for a ", width, "x",
        height, " image: fx must be within [", kMinFocalPerSide * width, ", ",
        kMaxFocalPerSide * width, "] and fy within [", kMinFocalPerSide * height, ", ",
        kMaxFocalPerSide * height, "] pixels (a field of view from 1 to 170 degrees)"));
  }
  if (cx < 0.0 || cx >= width || cy < 0.0 || cy >= height) {
    return absl::InvalidArgumentError(absl::StrCat(
        "principal point (", cx, ", ", cy, ") lies outside the ", width, "x", height, " image"));
  }
  return absl::OkStatus();
}

Eigen::Isometry3d Pose::ToIsometry() const {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = rotation.toRotationMatrix();
  T.translation() = translation;
  return T;
}

Pose Pose::FromIsometry(const Eigen::Isometry3d& T) {
  Pose p;
  p.translation = T.translation();
  p.rotation = Eigen::Quaterniond(T.linear()).normalized();
  return p;
}

absl::StatusOr<Pose> Pose::FromComponents(double tx, double ty, double tz, double qx, double qy,
                                          double qz, double qw) {
  for (double v : {tx, ty, tz, qx, qy, qz, qw}) {
    if (!std::isfinite(v)) {
      return absl::InvalidArgumentError("pose contains NaN or infinity");
    }
  }
  for (double v : {tx, ty, tz}) {
    if (std::abs(v) > kMaxTranslationM) {
      return absl::InvalidArgumentError(
          absl::StrCat("pose translation (", tx, ", ", ty, ", ", tz, ") m has a component beyond ",
                       kMaxTranslationM, " m; send metres relative to the map's own origin"));
    }
  }
  const double norm = std::sqrt(qx * qx + qy * qy + qz * qz + qw * qw);
  if (std::abs(norm - 1.0) > kUnitTolerance) {
    return absl::InvalidArgumentError(absl::StrCat("pose quaternion must have unit norm (within ",
                                                   kUnitTolerance, "), got |q|=", norm,
                                                   "; normalise (qx, qy, qz, qw) before sending"));
  }
  Pose p;
  p.translation = Eigen::Vector3d(tx, ty, tz);
  p.rotation = Eigen::Quaterniond(qw / norm, qx / norm, qy / norm, qz / norm);
  return p;
}

double TranslationDistanceM(const Pose& a, const Pose& b) {
  return (a.translation - b.translation).norm();
}

double RotationAngleRad(const Pose& a, const Pose& b) {
  return a.rotation.angularDistance(b.rotation);
}

Pose Interpolate(const Pose& a, const Pose& b, double t) {
  Pose p;
  p.translation = (1.0 - t) * a.translation + t * b.translation;
  p.rotation = a.rotation.slerp(t, b.rotation).normalized();
  return p;
}

}  // namespace lifemap
