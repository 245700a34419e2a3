// Loop closure served (issue 15): a synthetic visit around a room and a quarter more, streamed
// without poses, closes its loop: verified appearance matches to its own earlier keyframes
// become pose-graph edges, the solve corrects the stored keyframes, and the visit says so.
#include <thread>

#include <gtest/gtest.h>

#include "core/common/image_codec.h"
#include "core/eval/trajectory.h"
#include "core/sim/generator.h"
#include "core/sim/renderer.h"
#include "server/convert.h"
#include "tests/integration/server_fixture.h"

namespace lifemap {
namespace {

using testing::ServerTest;

const CameraIntrinsics kKinect{525, 525, 319.5, 239.5, 640, 480};

// Frame f of a rendered visit as a robot without localisation sends it (sensor noise on, the
// noise seeded as `lifemap sim --seed 3` does; PNG colour: JPEG's blocks cost the odometry on
// these texture-poor walls, docs/RESULTS.md).
v1::Frame UnposedFrame(const sim::Place& place, const sim::Visit& v, size_t f) {
  const auto frame =
      sim::Render(place, v.SolidsAt(f), v.lighting, kKinect, v.trajectory[f].T_world_camera,
                  sim::SensorOptions{}, 3 * 1000003ULL + f);
  v1::Frame fr;
  fr.set_sequence(f);
  fr.set_timestamp_s(v.trajectory[f].timestamp_s);
  server::IntrinsicsToProto(kKinect, fr.mutable_intrinsics());
  fr.mutable_depth()->set_encoding(v1::DEPTH_PNG16);
  fr.mutable_depth()->set_depth_scale(5000);
  fr.mutable_depth()->set_data(*EncodeDepthPng16(frame.depth_m, 5000));
  fr.mutable_color()->set_encoding(v1::COLOR_PNG);
  fr.mutable_color()->set_data(*EncodePng(frame.color_bgr));
  return fr;
}

TEST_F(ServerTest, ATrackedVisitAroundARoomClosesItsLoop) {
  server::ServerConfig config;
  config.appearance.min_training_keyframes = 10;  // a vocabulary early in the one visit
  StartServer(config);
  auto place = sim::GeneratePlace(3, "rect");
  ASSERT_TRUE(place.ok()) << place.status();
  auto visits = sim::GenerateVisits(*place, 3, 1, 0, sim::Conditions{}, 600);
  ASSERT_TRUE(visits.ok()) << visits.status();
  const sim::Visit& visit = (*visits)[0];
  ASSERT_TRUE(client_->CreateMap("room", "").ok());
  v1::StreamStart start;
  start.set_map("room");
  start.mutable_options()->set_result_images(v1::RESULT_IMAGES_NONE);
  auto stream = client_->OpenStream(start);
  ASSERT_TRUE(stream.ok()) << stream.status();
  std::thread sender([&] {
    for (size_t f = 0; f < visit.trajectory.size(); ++f) {
      if (!(*stream)->Send(UnposedFrame(*place, visit, f))) break;
    }
    (*stream)->CloseSend();
  });
  std::vector<eval::TimedPose> answered, truth;
  int lost = 0;
  v1::FrameResult r;
  while ((*stream)->Receive(&r)) {
    ASSERT_FALSE(r.has_error()) << r.error().message();
    lost += r.tracking().state() == v1::TRACKING_LOST;
    if (r.keyframe().committed() && r.pose_source() == v1::POSE_SOURCE_ESTIMATED) {
      answered.push_back({r.timestamp_s(), *server::PoseFromProto(r.pose())});
    }
  }
  sender.join();
  ASSERT_TRUE((*stream)->Finish().ok());
  EXPECT_EQ(lost, 0);
  for (const auto& p : visit.trajectory) truth.push_back({p.timestamp_s, p.T_world_camera});

  // The stream ended only once its loops were closed: the visit reports them.
  auto listed_visits = client_->ListVisits("room");
  ASSERT_TRUE(listed_visits.ok());
  ASSERT_EQ(listed_visits->visits_size(), 1);
  const v1::Visit& v = listed_visits->visits(0);
  EXPECT_GE(v.loops_accepted(), 5u);
  EXPECT_GE(v.pose_graph_solves(), 1u);
  EXPECT_EQ(v.frame(), v1::VISIT_FRAME_MAP) << "the map's first visit: its frame is the map's";

  // The stored keyframes (corrected) are closer to the truth than the poses answered on the way.
  auto listed = client_->ListKeyframes("room", v.id());
  ASSERT_TRUE(listed.ok());
  std::vector<eval::TimedPose> stored;
  for (const auto& k : listed->keyframes()) {
    ASSERT_EQ(k.pose_source(), v1::POSE_SOURCE_ESTIMATED);
    stored.push_back({k.timestamp_s(), *server::PoseFromProto(k.pose())});
  }
  auto online = eval::CompareTrajectories(answered, truth);
  auto corrected = eval::CompareTrajectories(stored, truth);
  ASSERT_TRUE(online.ok() && corrected.ok());
  std::cout << "answered ATE " << online->ate_rmse_m * 1000 << " mm, stored "
            << corrected->ate_rmse_m * 1000 << " mm; loops " << v.loops_accepted() << "/"
            << v.loops_rejected() << ", solves " << v.pose_graph_solves() << "\n";
  EXPECT_LT(corrected->ate_rmse_m, online->ate_rmse_m);
  EXPECT_LT(corrected->ate_rmse_m, 0.03);
}

}  // namespace
}  // namespace lifemap
