// Loop closure served (issue 15): a synthetic visit around a room and a quarter more, streamed
// without poses, closes its loop: verified appearance matches to its own earlier keyframes
// become pose-graph edges, the solve corrects the stored keyframes, and the visit says so.
#include <chrono>
#include <map>
#include <optional>
#include <thread>
#include <utility>

#include <gtest/gtest.h>

#include "core/common/image_codec.h"
#include "core/eval/trajectory.h"
#include "core/sim/generator.h"
#include "core/sim/renderer.h"
#include "server/rpc/convert.h"
#include "tests/integration/server_fixture.h"

namespace lifemap {
namespace {

using testing::ServerTest;

const CameraIntrinsics kKinect{525, 525, 319.5, 239.5, 640, 480};

// Sim seed 3's rectangular room and one walk through it: 600 frames, a loop and a quarter.
absl::StatusOr<std::pair<sim::Place, sim::Visit>> RoomWalk() {
  auto place = sim::GeneratePlace(3, "rect");
  if (!place.ok()) return place.status();
  auto visits = sim::GenerateVisits(*place, 3, 1, 0, sim::Conditions{}, 600);
  if (!visits.ok()) return visits.status();
  return std::make_pair(*std::move(place), (*visits)[0]);
}

// A stream into a new map "room" whose results carry no images.
absl::StatusOr<std::unique_ptr<client::FrameStream>> OpenRoomStream(client::Client& client) {
  if (auto map = client.CreateMap("room", ""); !map.ok()) return map.status();
  v1::StreamStart start;
  start.set_map("room");
  start.mutable_options()->set_result_images(v1::RESULT_IMAGES_NONE);
  return client.OpenStream(start);
}

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
  auto walk = RoomWalk();
  ASSERT_TRUE(walk.ok()) << walk.status();
  const sim::Place& place = walk->first;
  const sim::Visit& visit = walk->second;
  auto stream = OpenRoomStream(*client_);
  ASSERT_TRUE(stream.ok()) << stream.status();
  std::thread sender([&] {
    for (size_t f = 0; f < visit.trajectory.size(); ++f) {
      if (!(*stream)->Send(UnposedFrame(place, visit, f))) break;
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

// Relocalisation: a robot that loses its camera (here: 4 s of a walk, then nothing until it is
// back near where it started, 12 s in) is placed again by a verified appearance match to one of
// its visit's keyframes, and tracked on from there.
TEST_F(ServerTest, ALostCameraIsRelocalisedAgainstItsVisitsKeyframes) {
  server::ServerConfig config;
  config.appearance.min_training_keyframes = 5;  // a vocabulary within the first seconds
  StartServer(config);
  auto walk = RoomWalk();
  ASSERT_TRUE(walk.ok()) << walk.status();
  const sim::Place& place = walk->first;
  const sim::Visit& visit = walk->second;
  auto stream = OpenRoomStream(*client_);
  ASSERT_TRUE(stream.ok()) << stream.status();
  std::vector<size_t> sent;
  for (size_t f = 0; f < 120; ++f) sent.push_back(f);
  for (size_t f = 480; f < 540; ++f) sent.push_back(f);  // one loop on: where it began
  std::thread sender([&] {
    for (size_t f : sent) {
      // Time for the first keyframes' vocabulary to be trained and indexed before the gap.
      if (f == 480) std::this_thread::sleep_for(std::chrono::seconds(3));
      if (!(*stream)->Send(UnposedFrame(place, visit, f))) break;
    }
    (*stream)->CloseSend();
  });
  std::map<size_t, Pose> estimated;
  std::optional<size_t> relocalised;
  int lost_after = 0;
  v1::FrameResult r;
  while ((*stream)->Receive(&r)) {
    ASSERT_FALSE(r.has_error()) << r.error().message();
    if (r.tracking().method() == v1::TRACKING_METHOD_RELOCALISED && !relocalised) {
      relocalised = r.sequence();
      EXPECT_EQ(r.tracking().state(), v1::TRACKING_REGAINED);
      EXPECT_NE(r.tracking().reason().find("keyframe"), std::string::npos) << r.tracking().reason();
      std::cout << "frame " << r.sequence() << ": " << r.tracking().reason() << "\n";
    }
    if (relocalised && r.sequence() > *relocalised) {
      lost_after += r.tracking().state() == v1::TRACKING_LOST;
    }
    if (r.pose_source() == v1::POSE_SOURCE_ESTIMATED) {
      estimated[r.sequence()] = *server::PoseFromProto(r.pose());
    }
  }
  sender.join();
  ASSERT_TRUE((*stream)->Finish().ok());
  ASSERT_TRUE(relocalised.has_value()) << "no frame after the gap was relocalised";
  EXPECT_LT(*relocalised, 490u) << "relocalised within the first frames after the gap";
  EXPECT_EQ(lost_after, 0) << "tracked on from the relocalised frame";
  // Where it was placed, against the truth, both relative to the visit's first frame.
  ASSERT_TRUE(estimated.count(0) && estimated.count(*relocalised));
  const Eigen::Isometry3d est =
      estimated[0].ToIsometry().inverse() * estimated[*relocalised].ToIsometry();
  const Eigen::Isometry3d truth = visit.trajectory[0].T_world_camera.ToIsometry().inverse() *
                                  visit.trajectory[*relocalised].T_world_camera.ToIsometry();
  const Eigen::Isometry3d error = truth.inverse() * est;
  std::cout << "relocalised at frame " << *relocalised << ": error "
            << error.translation().norm() * 100 << " cm, "
            << Eigen::AngleAxisd(error.rotation()).angle() * 180 / M_PI << " deg\n";
  EXPECT_LT(error.translation().norm(), 0.05);
  EXPECT_LT(Eigen::AngleAxisd(error.rotation()).angle() * 180 / M_PI, 2.0);
}

}  // namespace
}  // namespace lifemap
