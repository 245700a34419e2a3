// The server's own poses (issue 15): a recording streamed without poses is tracked, keyframes
// are stored with the estimates, and a frame that cannot be tracked says so.
#include <thread>

#include <gtest/gtest.h>
#include <opencv2/core.hpp>

#include "client/lifemap_client.h"
#include "core/common/image_codec.h"
#include "core/eval/trajectory.h"
#include "core/io/tum_dataset.h"
#include "server/rpc/convert.h"
#include "tests/integration/server_fixture.h"
#include "tests/testing/test_util.h"

namespace lifemap {
namespace {

using testing::ServerTest;

TEST_F(ServerTest, AStreamWithoutPosesIsTrackedAndAFrameWithoutDepthIsLostThenRegained) {
  LIFEMAP_REQUIRE_DATASET(dir, "tum_fr1_xyz_subset");
  const testing::TumFrames tum = testing::ReadTumFrames(dir);
  ASSERT_FALSE(tum.frames.empty());
  ASSERT_TRUE(client_->CreateMap("office", "").ok());
  v1::StreamStart start;
  start.set_map("office");
  auto stream = client_->OpenStream(start);
  ASSERT_TRUE(stream.ok()) << stream.status();
  constexpr size_t kBlind = 12;  // this frame's depth is all "no reading"
  const std::string no_depth = *EncodeDepthPng16(cv::Mat(480, 640, CV_32FC1, 0.0f), 5000.0);
  std::thread sender([&] {
    for (size_t i = 0; i < tum.frames.size(); ++i) {
      v1::Frame f = tum.frames[i];
      if (i == kBlind) f.mutable_depth()->set_data(no_depth);
      ASSERT_TRUE((*stream)->Send(f));
    }
    (*stream)->CloseSend();
  });
  std::vector<v1::FrameResult> results;
  v1::FrameResult r;
  while ((*stream)->Receive(&r)) results.push_back(r);
  sender.join();
  ASSERT_TRUE((*stream)->Finish().ok());
  ASSERT_EQ(results.size(), tum.frames.size());

  std::vector<eval::TimedPose> estimate, truth;
  std::map<uint64_t, Pose> keyframe_pose;
  for (size_t i = 0; i < results.size(); ++i) {
    const auto& res = results[i];
    ASSERT_FALSE(res.has_error()) << i << ": " << res.error().message();
    ASSERT_TRUE(res.has_tracking()) << i;
    if (i == kBlind) {
      EXPECT_EQ(res.tracking().state(), v1::TRACKING_LOST);
      EXPECT_EQ(res.pose_source(), v1::POSE_SOURCE_NONE);
      EXPECT_NE(res.tracking().reason().find("too little depth"), std::string::npos)
          << res.tracking().reason();
      for (const auto& o : res.outputs()) {
        if (o.output() == v1::FRAME_OUTPUT_POSE) {
          EXPECT_FALSE(o.computed());
          EXPECT_NE(o.reason().find("tracking lost"), std::string::npos) << o.reason();
        }
      }
      continue;
    }
    EXPECT_EQ(res.tracking().state(), i == 0            ? v1::TRACKING_STARTED
                                      : i == kBlind + 1 ? v1::TRACKING_REGAINED
                                                        : v1::TRACKING_OK)
        << i << ": " << res.tracking().reason();
    ASSERT_EQ(res.pose_source(), v1::POSE_SOURCE_ESTIMATED) << i;
    estimate.push_back({res.timestamp_s(), *server::PoseFromProto(res.pose())});
    truth.push_back({tum.frames[i].timestamp_s(), *tum.truth[i]});
    if (res.keyframe().committed())
      keyframe_pose[res.keyframe().keyframe_id()] = estimate.back().pose;
  }
  auto errors = eval::CompareTrajectories(estimate, truth);
  ASSERT_TRUE(errors.ok()) << errors.status();
  EXPECT_LT(errors->ate_rmse_m, 0.01) << "the tracked trajectory within a centimetre";
  // Keyframes were chosen by the estimated motion (not by time alone) and stored with it.
  EXPECT_GE(keyframe_pose.size(), 3u);
  auto listed = client_->ListKeyframes("office", 0);
  ASSERT_TRUE(listed.ok()) << listed.status();
  ASSERT_EQ(static_cast<size_t>(listed->keyframes_size()), keyframe_pose.size());
  for (const auto& kf : listed->keyframes()) {
    ASSERT_TRUE(kf.has_pose());
    EXPECT_EQ(kf.pose_source(), v1::POSE_SOURCE_ESTIMATED);
    EXPECT_NEAR(kf.pose().tx(), keyframe_pose[kf.id()].translation.x(), 1e-9);
  }
}

// Gravity from the robot's IMU levels a tracked visit; a zero-length one is refused, naming it.
TEST_F(ServerTest, GravityLevelsATrackedVisitAndAZeroVectorIsRefused) {
  LIFEMAP_REQUIRE_DATASET(dir, "tum_fr1_xyz_subset");
  auto frame = testing::FirstTumFrame(dir);
  ASSERT_TRUE(frame.ok()) << frame.status();
  ASSERT_TRUE(client_->CreateMap("m", "").ok());
  v1::ProcessFrameRequest req;
  req.set_map("m");
  *req.mutable_frame() = *frame;
  req.mutable_frame()->mutable_gravity()->set_y(0.5 * 9.81);  // pitched 60 degrees down
  req.mutable_frame()->mutable_gravity()->set_z(std::sqrt(0.75) * 9.81);
  auto r = client_->ProcessFrame(req);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->tracking().state(), v1::TRACKING_STARTED);
  ASSERT_EQ(r->pose_source(), v1::POSE_SOURCE_ESTIMATED);
  const Pose pose = *server::PoseFromProto(r->pose());
  const Eigen::Vector3d forward = pose.rotation * Eigen::Vector3d::UnitZ();
  EXPECT_NEAR(forward.z(), -std::sqrt(0.75), 1e-6) << "the camera looks 60 degrees down";
  EXPECT_NEAR(forward.y(), 0.0, 1e-6);

  req.mutable_frame()->mutable_gravity()->Clear();
  req.mutable_frame()->mutable_gravity()->set_x(0.0);
  req.mutable_frame()->set_timestamp_s(frame->timestamp_s() + 1);
  auto zero = client_->ProcessFrame(req);
  EXPECT_TRUE(absl::IsInvalidArgument(zero.status())) << zero.status();
  EXPECT_NE(zero.status().message().find("frame.gravity"), std::string::npos) << zero.status();
}

// The robot's odometry (issue 35): every malformed reading is refused naming the field, and a
// jump of metres between two frames of a visit is refused without touching the visit, whose
// next frame is tracked as if the bad one had never come.
TEST_F(ServerTest, BadOdometryIsRefusedNamingTheFieldAndLeavesTheVisitAsItWas) {
  LIFEMAP_REQUIRE_DATASET(dir, "tum_fr1_xyz_subset");
  const testing::TumFrames tum = testing::ReadTumFrames(dir);
  ASSERT_GE(tum.frames.size(), 3u);
  ASSERT_TRUE(client_->CreateMap("m", "").ok());
  // Frame i with odometry that tells the truth (the mocap pose), moved `jump_x` metres along x.
  auto request = [&](size_t i, double jump_x) {
    v1::ProcessFrameRequest req;
    req.set_map("m");
    *req.mutable_frame() = tum.frames[i];
    req.mutable_frame()->clear_pose();
    Pose odometry = tum.truth[i].value_or(Pose{});
    odometry.translation.x() += jump_x;
    server::PoseToProto(odometry, req.mutable_frame()->mutable_odometry()->mutable_pose());
    return req;
  };
  auto expect_refused = [&](const v1::ProcessFrameRequest& req, const std::string& words) {
    auto r = client_->ProcessFrame(req);
    EXPECT_TRUE(absl::IsInvalidArgument(r.status())) << words << ": " << r.status();
    EXPECT_NE(r.status().message().find(words), std::string::npos) << r.status();
  };
  auto nan = request(0, std::nan(""));
  expect_refused(nan, "frame.odometry.pose");
  auto not_unit = request(0, 0.0);
  not_unit.mutable_frame()->mutable_odometry()->mutable_pose()->set_qw(0.5);
  expect_refused(not_unit, "frame.odometry.pose");
  auto no_pose = request(0, 0.0);
  no_pose.mutable_frame()->mutable_odometry()->clear_pose();
  expect_refused(no_pose, "frame.odometry.pose is missing");
  auto not_pd = request(0, 0.0);
  for (int i = 0; i < 36; ++i) not_pd.mutable_frame()->mutable_odometry()->add_covariance(0.0);
  expect_refused(not_pd, "frame.odometry: covariance is not positive definite");
  auto short_covariance = request(0, 0.0);
  short_covariance.mutable_frame()->mutable_odometry()->add_covariance(1e-4);
  expect_refused(short_covariance, "36 values");

  auto first = client_->ProcessFrame(request(0, 0.0));
  ASSERT_TRUE(first.ok()) << first.status();
  EXPECT_EQ(first->tracking().state(), v1::TRACKING_STARTED);
  expect_refused(request(1, 4.0), "frame.odometry.pose jumped 3.99 m");
  auto next = client_->ProcessFrame(request(2, 0.0));
  ASSERT_TRUE(next.ok()) << next.status();
  EXPECT_EQ(next->tracking().state(), v1::TRACKING_OK) << next->tracking().reason();
  EXPECT_EQ(next->tracking().method(), v1::TRACKING_METHOD_DENSE) << "the images agree with it";
}

// A robot whose own poses are noisy asks for them to be refined (FrameOptions.refine_pose):
// the results say REFINED and lie closer to the ground truth than what was sent.
TEST_F(ServerTest, ClientPosesAreRefinedWhenAsked) {
  LIFEMAP_REQUIRE_DATASET(dir, "tum_fr1_xyz_subset");
  const testing::TumFrames tum = testing::ReadTumFrames(dir);
  ASSERT_FALSE(tum.frames.empty());
  ASSERT_TRUE(client_->CreateMap("m", "").ok());
  v1::StreamStart start;
  start.set_map("m");
  start.mutable_options()->set_refine_pose(true);
  auto stream = client_->OpenStream(start);
  ASSERT_TRUE(stream.ok()) << stream.status();
  std::vector<eval::TimedPose> sent, refined, truth;
  std::thread sender([&] {
    for (size_t i = 0; i < tum.frames.size(); ++i) {
      v1::Frame f = tum.frames[i];
      Pose noisy = *tum.truth[i];
      // 2 cm of noise, alternating in sign along each axis: a drifting, jittery odometry.
      noisy.translation += 0.02 * Eigen::Vector3d(i % 2 ? 1 : -1, i % 3 ? 1 : -1, i % 5 ? -1 : 1);
      server::PoseToProto(noisy, f.mutable_pose());
      sent.push_back({f.timestamp_s(), noisy});
      ASSERT_TRUE((*stream)->Send(f));
    }
    (*stream)->CloseSend();
  });
  v1::FrameResult r;
  size_t i = 0;
  while ((*stream)->Receive(&r)) {
    ASSERT_FALSE(r.has_error()) << r.error().message();
    EXPECT_EQ(r.pose_source(), v1::POSE_SOURCE_REFINED) << i << ": " << r.tracking().reason();
    refined.push_back({r.timestamp_s(), *server::PoseFromProto(r.pose())});
    truth.push_back({r.timestamp_s(), *tum.truth[i++]});
  }
  sender.join();
  ASSERT_TRUE((*stream)->Finish().ok());
  ASSERT_EQ(refined.size(), tum.frames.size());
  auto before = eval::CompareTrajectories(sent, truth);
  auto after = eval::CompareTrajectories(refined, truth);
  ASSERT_TRUE(before.ok() && after.ok());
  std::cerr << "fr1_xyz, 2 cm of pose noise: sent ATE " << before->ate_rmse_m * 1000
            << " mm, refined " << after->ate_rmse_m * 1000 << " mm\n";
  EXPECT_LT(after->ate_rmse_m, 0.5 * before->ate_rmse_m)
      << "refined " << after->ate_rmse_m << " m against " << before->ate_rmse_m << " m sent";
  auto listed = client_->ListKeyframes("m", 0);
  ASSERT_TRUE(listed.ok() && listed->keyframes_size() > 0);
  for (const auto& kf : listed->keyframes()) EXPECT_EQ(kf.pose_source(), v1::POSE_SOURCE_REFINED);
}

}  // namespace
}  // namespace lifemap
