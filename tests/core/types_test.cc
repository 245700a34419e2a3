#include "core/common/types.h"

#include <cmath>
#include <limits>

#include <gtest/gtest.h>

namespace lifemap {
namespace {

CameraIntrinsics Tum() { return {517.3, 516.5, 318.6, 255.3, 640, 480}; }

TEST(CameraIntrinsics, AcceptsTumCalibration) { EXPECT_TRUE(Tum().Validate().ok()); }

TEST(CameraIntrinsics, RejectsZeroNegativeAndNaNFocalLengths) {
  for (double fx : {0.0, -1.0, std::nan("")}) {
    CameraIntrinsics k = Tum();
    k.fx = fx;
    const auto s = k.Validate();
    EXPECT_TRUE(absl::IsInvalidArgument(s)) << fx;
  }
  CameraIntrinsics k = Tum();
  k.fy = std::numeric_limits<double>::infinity();
  EXPECT_TRUE(absl::IsInvalidArgument(k.Validate()));
}

TEST(CameraIntrinsics, RejectsPrincipalPointOutsideImage) {
  CameraIntrinsics k = Tum();
  k.cx = 640.0;
  EXPECT_NE(k.Validate().message().find("principal point"), std::string::npos);
}

TEST(CameraIntrinsics, RejectsImpossibleSizes) {
  CameraIntrinsics k = Tum();
  k.width = 0;
  EXPECT_TRUE(absl::IsInvalidArgument(k.Validate()));
  k.width = 100000;
  EXPECT_TRUE(absl::IsInvalidArgument(k.Validate()));
}

TEST(Pose, NormalisesNearlyUnitQuaternion) {
  auto p = Pose::FromComponents(1, 2, 3, 0, 0, 0, 1.0005);
  ASSERT_TRUE(p.ok());
  EXPECT_NEAR(p->rotation.norm(), 1.0, 1e-12);
}

TEST(Pose, RejectsNonUnitQuaternion) {
  auto p = Pose::FromComponents(0, 0, 0, 0, 0, 0, 2.0);
  ASSERT_FALSE(p.ok());
  EXPECT_NE(p.status().message().find("unit norm"), std::string::npos);
  EXPECT_FALSE(Pose::FromComponents(0, 0, 0, 0, 0, 0, 0).ok());
}

TEST(Pose, RejectsNaNTranslation) {
  EXPECT_TRUE(
      absl::IsInvalidArgument(Pose::FromComponents(std::nan(""), 0, 0, 0, 0, 0, 1).status()));
}

TEST(Pose, InterpolatesHalfway) {
  Pose a, b;
  b.translation = {2, 0, 0};
  b.rotation = Eigen::Quaterniond(Eigen::AngleAxisd(M_PI / 2, Eigen::Vector3d::UnitZ()));
  const Pose m = Interpolate(a, b, 0.5);
  EXPECT_NEAR(m.translation.x(), 1.0, 1e-12);
  EXPECT_NEAR(RotationAngleRad(a, m), M_PI / 4, 1e-9);
  EXPECT_NEAR(TranslationDistanceM(a, b), 2.0, 1e-12);
}

}  // namespace
}  // namespace lifemap
