#include "core/io/tum_dataset.h"

#include <algorithm>
#include <cmath>
#include <fstream>

#include <gtest/gtest.h>

#include "tests/testing/test_util.h"

namespace lifemap::io {
namespace {

TEST(TumSequence, ReadsFr1XyzWithGroundTruth) {
  LIFEMAP_REQUIRE_DATASET(dir, "tum_fr1_xyz_subset");
  auto seq = ReadTumSequence(dir);
  ASSERT_TRUE(seq.ok()) << seq.status();
  // 37 colour and 37 depth images; TUM's one-to-one association within 20 ms pairs 32.
  EXPECT_EQ(seq->frames.size(), 32u);
  EXPECT_TRUE(seq->has_groundtruth);
  EXPECT_EQ(seq->frames_with_pose, 32);
  for (size_t i = 1; i < seq->frames.size(); ++i) {
    EXPECT_LT(seq->frames[i - 1].timestamp_s, seq->frames[i].timestamp_s);
  }
  for (const auto& f : seq->frames) {
    EXPECT_LT(std::abs(f.timestamp_s - f.depth_timestamp_s), 0.02);
  }
  // The first image at t=1305031102.175304 lies between mocap samples near (1.34, 0.63, 1.66).
  const auto& p = *seq->frames[0].T_world_camera;
  EXPECT_NEAR(p.translation.x(), 1.3406, 0.002);
  EXPECT_NEAR(p.translation.y(), 0.6266, 0.002);
  EXPECT_NEAR(p.translation.z(), 1.6577, 0.002);
}

TEST(TumSequence, GravityFromTheAccelerometerAgreesWithTheMocapVertical) {
  // fr1_xyz's accelerometer.txt (the Kinect's, ~100 Hz) against the ground truth's vertical
  // (TUM's mocap frame is z up) at every frame: the hand-held camera's own accelerations tilt
  // single readings, the window mean stays within a few degrees.
  LIFEMAP_REQUIRE_DATASET(dir, "tum_fr1_xyz_subset");
  auto seq = ReadTumSequence(dir);
  ASSERT_TRUE(seq.ok()) << seq.status();
  EXPECT_TRUE(seq->has_accelerometer);
  EXPECT_EQ(seq->frames_with_gravity, 32);
  std::vector<double> errors_deg;
  for (const auto& f : seq->frames) {
    ASSERT_TRUE(f.gravity_camera && f.T_world_camera);
    const Eigen::Vector3d truth = f.T_world_camera->rotation.inverse() * -Eigen::Vector3d::UnitZ();
    EXPECT_NEAR(f.gravity_camera->norm(), 1.0, 1e-9);
    errors_deg.push_back(std::acos(std::clamp(truth.dot(*f.gravity_camera), -1.0, 1.0)) * 180 /
                         M_PI);
  }
  std::sort(errors_deg.begin(), errors_deg.end());
  EXPECT_LT(errors_deg[errors_deg.size() / 2], 6.0);
  EXPECT_LT(errors_deg.back(), 15.0);
  // A still reading and back; zero is refused.
  const Eigen::Vector3d g(0.1, 0.9, 0.4);
  EXPECT_LT((*TumGravityFromAccelerometer(TumAccelerometerReading(g)) - g.normalized()).norm(),
            1e-12);
  EXPECT_FALSE(TumGravityFromAccelerometer(Eigen::Vector3d::Zero()).ok());
}

TEST(TumSequence, SkipsListedButMissingImages) {
  LIFEMAP_REQUIRE_DATASET(dir, "tum_fr1_desk_subset");
  auto seq = ReadTumSequence(dir);
  ASSERT_TRUE(seq.ok()) << seq.status();
  // rgb.txt lists 613 images of the full sequence; only 9 colour/depth pairs are present.
  EXPECT_EQ(seq->frames.size(), 9u);
  EXPECT_GT(seq->listed_but_missing, 500);
}

TEST(TumSequence, RejectsMissingFolderAndMalformedLines) {
  EXPECT_TRUE(absl::IsNotFound(ReadTumSequence("/nonexistent/lifemap").status()));
  testing::TempDir tmp;
  EXPECT_TRUE(absl::IsNotFound(ReadTumSequence(tmp.path()).status()))
      << "a folder without rgb.txt/depth.txt";
  std::ofstream(tmp.File("rgb.txt")) << "# comment\nnot-a-number rgb/x.png\n";
  std::ofstream(tmp.File("depth.txt")) << "";
  auto s = ReadTumSequence(tmp.path()).status();
  EXPECT_TRUE(absl::IsInvalidArgument(s));
  EXPECT_NE(s.message().find("rgb.txt:2"), std::string::npos) << s;
}

TEST(TumSequence, AccelerometerFileIsCheckedAndAZeroReadingGivesNoGravity) {
  testing::TempDir tmp;
  testing::WriteSyntheticTum(tmp.path(), 3);  // frames at 1700000000 + i / 30 s
  // A malformed line names the file and the line.
  std::ofstream(tmp.File("accelerometer.txt")) << "# timestamp ax ay az\n1700000000.0 0 9.8\n";
  auto s = ReadTumSequence(tmp.path()).status();
  EXPECT_TRUE(absl::IsInvalidArgument(s));
  EXPECT_NE(s.message().find("accelerometer.txt:2"), std::string::npos) << s;
  std::ofstream(tmp.File("accelerometer.txt")) << "1700000000.0 0 x 0\n";
  s = ReadTumSequence(tmp.path()).status();
  EXPECT_TRUE(absl::IsInvalidArgument(s));
  EXPECT_NE(s.message().find("accelerometer.txt:1"), std::string::npos) << s;
  // Readings summing to zero near a frame give it no gravity rather than a NaN one; frames with
  // no reading within the window get none either.
  std::ofstream(tmp.File("accelerometer.txt")) << "1700000000.0 0 0 0\n1700000000.0333 0 9.8 0\n";
  TumReadOptions options;
  options.accelerometer_window_s = 0.01;
  auto seq = ReadTumSequence(tmp.path(), options);
  ASSERT_TRUE(seq.ok()) << seq.status();
  EXPECT_TRUE(seq->has_accelerometer);
  EXPECT_EQ(seq->frames_with_gravity, 1);
  EXPECT_FALSE(seq->frames[0].gravity_camera.has_value());
  ASSERT_TRUE(seq->frames[1].gravity_camera.has_value());
  EXPECT_NEAR(seq->frames[1].gravity_camera->y(), 1.0, 1e-12);
  EXPECT_FALSE(seq->frames[2].gravity_camera.has_value());
}

TEST(TumTrajectory, RejectsNonUnitQuaternionWithLineNumber) {
  testing::TempDir tmp;
  std::ofstream(tmp.File("gt.txt")) << "1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0 3\n";
  auto s = ReadTumTrajectory(tmp.File("gt.txt")).status();
  EXPECT_NE(s.message().find("gt.txt:2"), std::string::npos) << s;
}

TEST(TumTrajectory, InterpolatesOnlyInsideAndAcrossSmallGaps) {
  std::vector<TimedPose> t(2);
  t[0].timestamp_s = 1.0;
  t[1].timestamp_s = 1.01;
  t[1].pose.translation = {1, 0, 0};
  auto mid = InterpolateTrajectory(t, 1.005, 0.1);
  ASSERT_TRUE(mid.has_value());
  EXPECT_NEAR(mid->translation.x(), 0.5, 1e-9);
  EXPECT_FALSE(InterpolateTrajectory(t, 0.9, 0.1).has_value());
  EXPECT_FALSE(InterpolateTrajectory(t, 1.2, 0.1).has_value());
  EXPECT_FALSE(InterpolateTrajectory(t, 1.005, 0.001).has_value());
}

TEST(TumIntrinsics, PicksCalibrationByFolderName) {
  std::string source;
  auto k = TumIntrinsicsFor("/data/rgbd_dataset_freiburg1_xyz", 640, 480, &source);
  EXPECT_DOUBLE_EQ(k.fx, 517.3);
  EXPECT_NE(source.find("freiburg1"), std::string::npos);
  k = TumIntrinsicsFor("/data/somewhere", 320, 240, &source);
  EXPECT_DOUBLE_EQ(k.fx, 262.5);
  EXPECT_TRUE(k.Validate().ok());
}

TEST(TumPoseLine, FormatsEightFields) {
  Pose p;
  p.translation = {1, 2, 3};
  EXPECT_EQ(FormatTumPoseLine(5.5, p),
            "5.500000 1.000000 2.000000 3.000000 0.000000000 0.000000000 0.000000000 "
            "1.000000000");
}

}  // namespace
}  // namespace lifemap::io
