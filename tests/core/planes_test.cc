#include "core/planes/planes.h"

#include <cmath>

#include <gtest/gtest.h>

#include "core/sim/generator.h"
#include "core/sim/renderer.h"

namespace lifemap::planes {
namespace {

CameraIntrinsics Kinect() { return {525, 525, 319.5, 239.5, 640, 480}; }

// Depth of the plane n·x = d seen through pixel (u, v).
float DepthOfPlane(const Eigen::Vector3f& n, float d, int u, int v, const CameraIntrinsics& k) {
  const Eigen::Vector3f ray((u - k.cx) / k.fx, (v - k.cy) / k.fy, 1.0f);
  return d / n.dot(ray);
}

TEST(Planes, AFrontoParallelWallIsOnePlaneOfTheRightSizeAndPlace) {
  const auto k = Kinect();
  cv::Mat depth(480, 640, CV_32FC1, cv::Scalar(2.0f));
  auto set = ExtractPlanes(depth, k);
  ASSERT_TRUE(set.ok()) << set.status();
  ASSERT_EQ(set->planes.size(), 1u);
  const Plane& p = set->planes[0];
  EXPECT_NEAR(p.normal.z(), -1.0f, 1e-4);
  EXPECT_NEAR(p.offset_m, -2.0f, 1e-4);
  // The image covers 640/525 × 480/525 of a plane at 2 m.
  EXPECT_NEAR(p.area_m2, (640.0f * 2 / 525) * (480.0f * 2 / 525), 0.01f);
  EXPECT_EQ(p.points, 640 * 480);
}

TEST(Planes, TwoWallsAtACornerAreTwoPlanesAndTheEdgeIsSplitDown) {
  // A corner: the left half a plane turned +40°, the right half −40° about the vertical axis,
  // meeting 2.5 m away.
  const auto k = Kinect();
  const float a = 40.0f * static_cast<float>(M_PI) / 180.0f;
  const Eigen::Vector3f n1(-std::sin(a), 0, -std::cos(a)), n2(std::sin(a), 0, -std::cos(a));
  const Eigen::Vector3f apex(-0.13f, 0, 2.5f);  // the crease at u ≈ 292, inside every cell
  cv::Mat depth(480, 640, CV_32FC1);
  for (int v = 0; v < 480; ++v) {
    for (int u = 0; u < 640; ++u) {
      const float z1 = DepthOfPlane(n1, n1.dot(apex), u, v, k);
      const float z2 = DepthOfPlane(n2, n2.dot(apex), u, v, k);
      depth.at<float>(v, u) =
          std::max(z1, z2) > 0 ? std::min(z1 > 0 ? z1 : 1e9f, z2 > 0 ? z2 : 1e9f) : 0;
    }
  }
  PlaneOptions o;
  o.median_kernel = 1;
  auto set = ExtractPlanes(depth, k, o);
  ASSERT_TRUE(set.ok()) << set.status();
  ASSERT_GE(set->planes.size(), 2u);
  int matched = 0;
  for (const Eigen::Vector3f& n : {n1, n2}) {
    for (size_t i = 0; i < 2; ++i) {
      if (set->planes[i].normal.dot(n) > 0.999f) {
        ++matched;
        EXPECT_NEAR(set->planes[i].offset_m, n.dot(apex), 0.01f);
      }
    }
  }
  EXPECT_EQ(matched, 2);
  // Near the crease the quadtree split below its root cells.
  int smallest = 1 << 30;
  for (const auto& r : set->regions) smallest = std::min(smallest, r.rect.width);
  EXPECT_LT(smallest, o.root_px);
}

TEST(Planes, BadInputsAreClearErrors) {
  EXPECT_TRUE(absl::IsInvalidArgument(ExtractPlanes(cv::Mat(), Kinect()).status()));
  EXPECT_TRUE(absl::IsInvalidArgument(
      ExtractPlanes(cv::Mat(480, 640, CV_16UC1, cv::Scalar(1)), Kinect()).status()));
  EXPECT_TRUE(absl::IsInvalidArgument(
      ExtractPlanes(cv::Mat(240, 320, CV_32FC1, cv::Scalar(1.0f)), Kinect()).status()));
  PlaneOptions o;
  o.median_kernel = 4;
  EXPECT_TRUE(absl::IsInvalidArgument(
      ExtractPlanes(cv::Mat(480, 640, CV_32FC1, cv::Scalar(1.0f)), Kinect(), o).status()));
  // No depth at all: no planes, not an error.
  auto none = ExtractPlanes(cv::Mat(480, 640, CV_32FC1, cv::Scalar(0.0f)), Kinect());
  ASSERT_TRUE(none.ok());
  EXPECT_TRUE(none->planes.empty());
}

TEST(Planes, FindsFloorAndWallsInARenderedRoom) {
  auto place = sim::GeneratePlace(3, "rect");
  ASSERT_TRUE(place.ok());
  // Camera 1.2 m high in the middle of the room, looking along +x with a slight downward tilt.
  Eigen::Vector2d centre(0, 0);
  for (const auto& c : place->footprint) centre += c;
  centre /= static_cast<double>(place->footprint.size());
  const Eigen::Matrix3d R_world_cam =
      (Eigen::AngleAxisd(-M_PI / 2, Eigen::Vector3d::UnitZ()) *
       Eigen::AngleAxisd(-M_PI / 2 - 0.35, Eigen::Vector3d::UnitX()))
          .toRotationMatrix();
  Pose pose;
  pose.translation = Eigen::Vector3d(centre.x(), centre.y(), 1.2);
  pose.rotation = Eigen::Quaterniond(R_world_cam);
  sim::SensorOptions sensor;
  const auto frame = sim::Render(*place, {}, sim::Lighting{}, Kinect(), pose, sensor, 1);
  auto set = ExtractPlanes(frame.depth_m, Kinect());
  ASSERT_TRUE(set.ok()) << set.status();
  const Eigen::Vector3f up = (R_world_cam.transpose() * Eigen::Vector3d::UnitZ()).cast<float>();
  bool floor = false, wall = false;
  for (const auto& p : set->planes) {
    if (p.area_m2 < 0.5f) continue;
    const float c = p.normal.dot(up);
    if (c > 0.98f) {
      // Floor: 1.2 m below the camera.
      floor = floor || std::abs(-p.offset_m - 1.2f) < 0.05f;
    } else if (std::abs(c) < 0.05f) {
      wall = true;
    }
  }
  EXPECT_TRUE(floor);
  EXPECT_TRUE(wall);
}

}  // namespace
}  // namespace lifemap::planes
