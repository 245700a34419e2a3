#include "core/mapping/point_cloud.h"

#include <cstring>

#include <gtest/gtest.h>

#include "core/io/ply_writer.h"

namespace lifemap::mapping {
namespace {

RgbdFrame Plane(double z) {
  RgbdFrame f;
  f.intrinsics = {100, 100, 49.5, 39.5, 100, 80};
  f.depth_m = cv::Mat(80, 100, CV_32FC1, cv::Scalar(static_cast<float>(z)));
  f.depth_m.at<float>(0, 0) = 0.0f;  // no reading
  f.color_bgr = cv::Mat(80, 100, CV_8UC3, cv::Scalar(255, 0, 0));
  return f;
}

TEST(BackProjection, PlacesPixelsOnThePlaneInWorldFrame) {
  Pose T;
  T.translation = {0, 0, 1};
  std::vector<io::ColoredPoint> cloud;
  AppendBackProjected(Plane(2.0), T, 1, &cloud);
  EXPECT_EQ(cloud.size(), 100u * 80u - 1u);
  for (const auto& p : cloud) {
    ASSERT_FLOAT_EQ(p.z, 3.0f);
    ASSERT_EQ(p.b, 255);
    ASSERT_EQ(p.r, 0);
  }
  // Pixel (0, 1): x = (1 - 49.5) / 100 * 2.
  EXPECT_NEAR(cloud[0].x, (1 - 49.5) / 100.0 * 2.0, 1e-5);
}

TEST(VoxelDownsample, KeepsOnePointPerVoxel) {
  std::vector<io::ColoredPoint> cloud = {{0.01f, 0.01f, 0.01f, 10, 10, 10},
                                         {0.02f, 0.02f, 0.02f, 30, 30, 30},
                                         {0.51f, 0.0f, 0.0f, 0, 0, 0}};
  const auto out = VoxelDownsample(cloud, 0.1);
  ASSERT_EQ(out.size(), 2u);
  EXPECT_NEAR(out[0].x, 0.015f, 1e-6);
  EXPECT_EQ(out[0].r, 20);
}

TEST(Ply, HeaderCountsVerticesAndBodyHasFifteenBytesEach) {
  const std::string ply = io::EncodePlyBinary({{1, 2, 3, 4, 5, 6}, {0, 0, 0, 0, 0, 0}});
  const auto end = ply.find("end_header\n");
  ASSERT_NE(end, std::string::npos);
  EXPECT_NE(ply.find("element vertex 2\n"), std::string::npos);
  EXPECT_EQ(ply.size() - (end + 11), 2u * 15u);
  float x;
  std::memcpy(&x, ply.data() + end + 11, 4);
  EXPECT_FLOAT_EQ(x, 1.0f);
}

}  // namespace
}  // namespace lifemap::mapping
