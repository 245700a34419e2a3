// Integration tests of architecture-based place recognition (paper 004) served: visits of
// synthetic places streamed with poses build floor plans; a later visit of the same place
// ranks it first, in frame results and through QueryPlace.
#include <grpcpp/grpcpp.h>

#include <chrono>
#include <thread>

#include <gtest/gtest.h>

#include "core/common/image_codec.h"
#include "core/sim/generator.h"
#include "core/sim/renderer.h"
#include "lifemap/v1/place_service.grpc.pb.h"
#include "server/rpc/convert.h"
#include "tests/integration/server_fixture.h"

namespace lifemap {
namespace {

using testing::ServerTest;

const CameraIntrinsics kKinect{525, 525, 319.5, 239.5, 640, 480};

// Frame f of a rendered visit with its pose, as a robot sends it (colour optional).
v1::Frame RenderedFrame(const sim::Place& place, const sim::Visit& v, size_t f, bool color) {
  const CameraIntrinsics& k = kKinect;
  const Pose& pose = v.trajectory[f].T_world_camera;
  const auto frame =
      sim::Render(place, v.SolidsAt(f), v.lighting, k, pose, sim::SensorOptions{}, f + 1);
  v1::Frame fr;
  fr.set_sequence(f);
  fr.set_timestamp_s(v.trajectory[f].timestamp_s);
  server::IntrinsicsToProto(k, fr.mutable_intrinsics());
  fr.mutable_depth()->set_encoding(v1::DEPTH_PNG16);
  fr.mutable_depth()->set_depth_scale(5000);
  fr.mutable_depth()->set_data(*EncodeDepthPng16(frame.depth_m, 5000));
  if (color) {
    fr.mutable_color()->set_encoding(v1::COLOR_JPEG);
    fr.mutable_color()->set_data(*EncodeJpeg(frame.color_bgr, 80));
  }
  server::PoseToProto(pose, fr.mutable_pose());
  return fr;
}

// Sends every `stride`-th frame of a rendered visit through ProcessFrame into `map`'s open
// visit; returns the last result.
v1::FrameResult SendVisit(client::Client* c, const std::string& map, const sim::Place& place,
                          const sim::Visit& v, int stride = 3) {
  v1::FrameResult last;
  for (size_t f = 0; f < v.trajectory.size(); f += static_cast<size_t>(stride)) {
    v1::ProcessFrameRequest req;
    req.set_map(map);
    *req.mutable_frame() = RenderedFrame(place, v, f, /*color=*/true);
    auto r = c->ProcessFrame(req);
    EXPECT_TRUE(r.ok()) << r.status();
    if (r.ok()) last = *r;
  }
  return last;
}

const v1::OutputStatus* PlaceStatus(const v1::FrameResult& r) {
  for (const auto& o : r.outputs()) {
    if (o.output() == v1::FRAME_OUTPUT_PLACE_MATCHES) return &o;
  }
  return nullptr;
}

// Key frames are folded off the reply path, so a result reports the ranking as of a key frame
// or two before; the robot's next frames catch up. Re-sends the visit's last frame (a little
// later: not a key frame) until a result has its place matches computed and at least `matches`
// of them, and returns it.
v1::FrameResult CaughtUp(client::Client* c, const std::string& map, const sim::Place& place,
                         const sim::Visit& v, v1::FrameResult last, int matches) {
  auto ready = [matches](const v1::FrameResult& r) {
    return PlaceStatus(r) != nullptr && PlaceStatus(r)->computed() &&
           r.place_matches_size() >= matches;
  };
  for (int again = 1; again <= 40 && !ready(last); ++again) {
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
    v1::ProcessFrameRequest req;
    req.set_map(map);
    *req.mutable_frame() = RenderedFrame(place, v, v.trajectory.size() - 1, /*color=*/true);
    req.mutable_frame()->set_timestamp_s(req.frame().timestamp_s() + 0.001 * again);
    auto r = c->ProcessFrame(req);
    EXPECT_TRUE(r.ok()) << r.status();
    if (r.ok()) last = *r;
  }
  return last;
}

TEST_F(ServerTest, ALaterVisitOfAPlaceRanksItFirstByArchitecture) {
  auto home = sim::GeneratePlace(3, "rect");
  auto office = sim::GeneratePlace(1, "square");
  ASSERT_TRUE(home.ok() && office.ok());
  sim::Conditions scenery;
  scenery.scenery = true;
  auto home_visits = sim::GenerateVisits(*home, 3, 2, 6, scenery, 90);
  auto office_visits = sim::GenerateVisits(*office, 1, 1, 6, scenery, 90);
  ASSERT_TRUE(home_visits.ok() && office_visits.ok());
  ASSERT_TRUE(client_->CreateMap("home", "").ok());
  ASSERT_TRUE(client_->CreateMap("office", "").ok());

  // The first frame: no plan yet, and the result says why.
  const v1::FrameResult first_home =
      CaughtUp(client_.get(), "home", *home, (*home_visits)[0],
               SendVisit(client_.get(), "home", *home, (*home_visits)[0], 3), /*matches=*/0);
  ASSERT_NE(PlaceStatus(first_home), nullptr);
  EXPECT_TRUE(PlaceStatus(first_home)->computed()) << PlaceStatus(first_home)->reason();
  SendVisit(client_.get(), "office", *office, (*office_visits)[0], 3);
  auto visits = client_->ListVisits("home");
  ASSERT_TRUE(visits.ok() && visits->visits_size() == 1);
  const uint64_t reference = visits->visits(0).id();
  ASSERT_TRUE(client_->EndVisit(reference).ok());

  // Six months later, props moved: the last result ranks the reference visit first. Key
  // frames are folded off the reply path, so a result reports the ranking as of a key frame or
  // two before; the robot's next frames (here the last one again, not a key frame) catch up.
  const v1::FrameResult later =
      CaughtUp(client_.get(), "home", *home, (*home_visits)[1],
               SendVisit(client_.get(), "home", *home, (*home_visits)[1], 3), /*matches=*/2);
  ASSERT_TRUE(PlaceStatus(later)->computed()) << PlaceStatus(later)->reason();
  ASSERT_GE(later.place_matches_size(), 2);
  EXPECT_EQ(later.place_matches(0).map(), "home");
  EXPECT_EQ(later.place_matches(0).visit_id(), reference);
  EXPECT_EQ(later.place_matches(0).method(), v1::MATCH_METHOD_ARCHITECTURE);
  EXPECT_GT(later.place_matches(0).score(), later.place_matches(1).score());

  // QueryPlace for that visit agrees; ListPlaces shows both plans of the map.
  auto channel = grpc::CreateChannel(target_, grpc::InsecureChannelCredentials());
  auto places = v1::PlaceService::NewStub(channel);
  v1::QueryPlaceRequest q;
  visits = client_->ListVisits("home");
  ASSERT_TRUE(visits.ok() && visits->visits_size() == 2);
  q.set_visit_id(visits->visits(0).id() == reference ? visits->visits(1).id()
                                                     : visits->visits(0).id());
  v1::QueryPlaceResponse qr;
  grpc::ClientContext qc;
  ASSERT_TRUE(places->QueryPlace(&qc, q, &qr).ok());
  ASSERT_GE(qr.matches_size(), 1);
  EXPECT_EQ(qr.matches(0).visit_id(), reference);
  EXPECT_NE(qr.descriptor_text().find("C3"), std::string::npos) << qr.descriptor_text();
  v1::ListPlacesRequest lr;
  lr.set_map("home");
  v1::ListPlacesResponse list;
  grpc::ClientContext lc;
  ASSERT_TRUE(places->ListPlaces(&lc, lr, &list).ok());
  EXPECT_EQ(list.places_size(), 2);

  // Bad queries: unknown visit, no visit.
  v1::QueryPlaceRequest unknown;
  unknown.set_visit_id(999999);
  grpc::ClientContext uc;
  EXPECT_EQ(places->QueryPlace(&uc, unknown, &qr).error_code(), grpc::StatusCode::NOT_FOUND);
  grpc::ClientContext nc;
  EXPECT_EQ(places->QueryPlace(&nc, v1::QueryPlaceRequest(), &qr).error_code(),
            grpc::StatusCode::INVALID_ARGUMENT);
  v1::QueryPlaceRequest too_many = q;
  too_many.set_max_results(1001);
  grpc::ClientContext mc;
  EXPECT_EQ(places->QueryPlace(&mc, too_many, &qr).error_code(),
            grpc::StatusCode::INVALID_ARGUMENT);
  v1::QueryPlaceRequest bad_method = q;
  bad_method.add_methods(static_cast<v1::MatchMethod>(42));
  grpc::ClientContext bc;
  EXPECT_EQ(places->QueryPlace(&bc, bad_method, &qr).error_code(),
            grpc::StatusCode::INVALID_ARGUMENT);
  v1::QueryPlaceRequest both = q;
  *both.add_frames() = testing::MakeFrame();
  grpc::ClientContext fc;
  EXPECT_EQ(places->QueryPlace(&fc, both, &qr).error_code(), grpc::StatusCode::INVALID_ARGUMENT);

  // A recording's own key frames (depth and poses, no colour): ranked, not stored — both home
  // visits above the office.
  v1::QueryPlaceRequest recording;
  recording.add_methods(v1::MATCH_METHOD_ARCHITECTURE);
  for (size_t f = 0; f < (*home_visits)[1].trajectory.size(); f += 3) {
    *recording.add_frames() = RenderedFrame(*home, (*home_visits)[1], f, /*color=*/false);
  }
  v1::QueryPlaceResponse rr;
  grpc::ClientContext rc;
  const grpc::Status rs = places->QueryPlace(&rc, recording, &rr);
  ASSERT_TRUE(rs.ok()) << rs.error_message();
  ASSERT_EQ(rr.matches_size(), 3);
  EXPECT_EQ(rr.matches(0).map(), "home");
  EXPECT_EQ(rr.matches(1).map(), "home");
  EXPECT_EQ(rr.matches(2).map(), "office");
  EXPECT_NE(rr.descriptor_text().find("C3"), std::string::npos) << rr.descriptor_text();
  ASSERT_TRUE(client_->ListVisits("home").ok());
  EXPECT_EQ(client_->ListVisits("home")->visits_size(), 2);  // nothing stored
  // Bad frames: no pose (named by index), a single frame (no plan).
  v1::QueryPlaceRequest unposed = recording;
  unposed.mutable_frames(1)->clear_pose();
  grpc::ClientContext uc2;
  const grpc::Status us = places->QueryPlace(&uc2, unposed, &rr);
  EXPECT_EQ(us.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_NE(us.error_message().find("frames[1]: pose is missing"), std::string::npos)
      << us.error_message();
  v1::QueryPlaceRequest single;
  *single.add_frames() = recording.frames(0);
  grpc::ClientContext sc;
  const grpc::Status ss = places->QueryPlace(&sc, single, &rr);
  EXPECT_EQ(ss.error_code(), grpc::StatusCode::FAILED_PRECONDITION);
  EXPECT_NE(ss.error_message().find("several key frames"), std::string::npos) << ss.error_message();
  for (const char* map : {"no-such-map", "bad name!"}) {
    v1::ListPlacesRequest bad_map;
    bad_map.set_map(map);
    grpc::ClientContext lbc;
    const auto code = places->ListPlaces(&lbc, bad_map, &list).error_code();
    EXPECT_EQ(code, std::string(map) == "bad name!" ? grpc::StatusCode::INVALID_ARGUMENT
                                                    : grpc::StatusCode::NOT_FOUND)
        << map;
  }
}

TEST_F(ServerTest, FramesWithoutPosesSayWhyTheyHaveNoPlaceMatches) {
  ASSERT_TRUE(client_->CreateMap("m", "").ok());
  v1::ProcessFrameRequest req;
  req.set_map("m");
  *req.mutable_frame() = testing::MakeFrame();
  auto r = client_->ProcessFrame(req);
  ASSERT_TRUE(r.ok()) << r.status();
  ASSERT_NE(PlaceStatus(*r), nullptr);
  EXPECT_FALSE(PlaceStatus(*r)->computed());
  EXPECT_NE(PlaceStatus(*r)->reason().find("poses"), std::string::npos)
      << PlaceStatus(*r)->reason();
  EXPECT_EQ(r->place_matches_size(), 0);
}

}  // namespace
}  // namespace lifemap
