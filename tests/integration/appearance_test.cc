// Integration tests of appearance place recognition served (paper 000): keyframes of a TUM
// recording stored in one visit are recognised, with a verified relative pose, by the frames of
// a later visit; another desk is not; the vocabulary and index survive a restart.
#include <gtest/gtest.h>

#include "core/io/tum_dataset.h"
#include "server/rpc/convert.h"
#include "tests/integration/server_fixture.h"

namespace lifemap {
namespace {

using testing::ServerTest;

using testing::ReadTumFrames;
using testing::TumFrames;

std::vector<v1::PlaceMatch> AppearanceMatches(const v1::FrameResult& r) {
  std::vector<v1::PlaceMatch> out;
  for (const auto& m : r.place_matches()) {
    if (m.method() == v1::MATCH_METHOD_APPEARANCE) out.push_back(m);
  }
  return out;
}

const v1::OutputStatus& PlaceStatus(const v1::FrameResult& r) {
  for (const auto& o : r.outputs()) {
    if (o.output() == v1::FRAME_OUTPUT_PLACE_MATCHES) return o;
  }
  static const v1::OutputStatus kNone;
  return kNone;
}

class AppearanceTest : public ServerTest {
 protected:
  void SetUp() override {
    server::ServerConfig config;
    config.appearance.min_training_keyframes = 4;  // a test's few keyframes train a vocabulary
    StartServer(config);
  }

  // Sends frames into `map`'s open visit (a new one when none is open) with ProcessFrame.
  std::vector<v1::FrameResult> Send(const std::string& map, const std::vector<v1::Frame>& frames,
                                    std::optional<double> appearance_interval_s) {
    std::vector<v1::FrameResult> out;
    for (const auto& f : frames) {
      v1::ProcessFrameRequest req;
      req.set_map(map);
      *req.mutable_frame() = f;
      req.mutable_options()->set_keyframe_max_interval_s(0.15);
      if (appearance_interval_s) {
        req.mutable_options()->set_appearance_interval_s(*appearance_interval_s);
      }
      auto r = client_->ProcessFrame(req);
      EXPECT_TRUE(r.ok()) << r.status();
      if (r.ok()) out.push_back(*r);
    }
    return out;
  }
};

TEST_F(AppearanceTest, ALaterVisitRecognisesStoredKeyframesWithTheirPoseAndAnotherDeskDoesNot) {
  const std::string xyz_dir = lifemap::testing::SharedDataset("tum_fr1_xyz_subset");
  const std::string desk_dir = lifemap::testing::SharedDataset("tum_fr1_desk_subset");
  if (xyz_dir.empty() || desk_dir.empty()) GTEST_SKIP() << "../shared/data TUM fr1 subsets absent";
  const TumFrames xyz = ReadTumFrames(xyz_dir);
  const TumFrames desk = ReadTumFrames(desk_dir);
  ASSERT_GE(xyz.frames.size(), 30u);
  ASSERT_TRUE(client_->CreateMap("office", "").ok());

  // Visit 1 stores the even frames. Before the vocabulary exists, results say why they have no
  // appearance matches.
  std::vector<v1::Frame> even, odd;
  for (size_t i = 0; i < xyz.frames.size(); ++i) (i % 2 == 0 ? even : odd).push_back(xyz.frames[i]);
  const auto first = Send("office", even, std::nullopt);
  ASSERT_FALSE(first.empty());
  EXPECT_TRUE(first[0].keyframe().selected());
  EXPECT_TRUE(AppearanceMatches(first[0]).empty());
  EXPECT_NE(PlaceStatus(first[0]).reason().find("no appearance vocabulary yet"), std::string::npos)
      << PlaceStatus(first[0]).reason();
  int keyframes = 0;
  for (const auto& r : first) keyframes += r.keyframe().committed() ? 1 : 0;
  ASSERT_GE(keyframes, 4);
  auto visits = client_->ListVisits("office");
  ASSERT_TRUE(visits.ok());
  ASSERT_EQ(visits->visits_size(), 1);
  const uint64_t stored_visit = visits->visits(0).id();
  ASSERT_TRUE(client_->EndVisit(stored_visit).ok());

  // Visit 2: the odd frames, each asking for appearance matches. Indexing follows commits off
  // the reply path; by the later frames every keyframe of visit 1 is indexed.
  const auto second = Send("office", odd, /*appearance_interval_s=*/0.0);
  int matched = 0;
  for (size_t i = 0; i < second.size(); ++i) {
    const auto matches = AppearanceMatches(second[i]);
    if (matches.empty()) continue;
    ++matched;
    const v1::PlaceMatch& best = matches[0];
    EXPECT_EQ(best.map(), "office");
    EXPECT_EQ(best.visit_id(), stored_visit);
    EXPECT_GT(best.keyframe_id(), 0u);
    EXPECT_GT(best.score(), 0.3);
    EXPECT_LE(best.score(), 1.0);
    EXPECT_TRUE(PlaceStatus(second[i]).computed());
    // The relative pose against the ground truth of the two frames.
    auto kf = client_->GetKeyframe("office", best.keyframe_id());
    ASSERT_TRUE(kf.ok()) << kf.status();
    size_t stored_index = 0;
    for (size_t j = 0; j < xyz.frames.size(); ++j) {
      if (std::abs(xyz.frames[j].timestamp_s() - kf->summary().timestamp_s()) < 1e-6)
        stored_index = j;
    }
    const size_t query_index = 2 * i + 1;
    ASSERT_TRUE(xyz.truth[stored_index] && xyz.truth[query_index]);
    const Eigen::Isometry3d truth =
        xyz.truth[stored_index]->ToIsometry().inverse() * xyz.truth[query_index]->ToIsometry();
    auto estimated = server::PoseFromProto(best.t_match_query());
    ASSERT_TRUE(estimated.ok());
    const Eigen::Isometry3d error = truth.inverse() * estimated->ToIsometry();
    EXPECT_LT(error.translation().norm(), 0.05) << "query frame " << query_index;
    EXPECT_LT(Eigen::AngleAxisd(error.linear()).angle(), 0.05);
  }
  EXPECT_GE(matched, static_cast<int>(second.size()) / 2);

  // QueryPlace by appearance on a few frames: each answered in order; both visits of the desk
  // ranked (the second holds some of these very frames as keyframes).
  v1::QueryPlaceRequest query;
  query.add_methods(v1::MATCH_METHOD_APPEARANCE);
  for (size_t i = 1; i < odd.size(); i += 4) *query.add_frames() = odd[i];
  auto answer = client_->QueryPlace(query);
  ASSERT_TRUE(answer.ok()) << answer.status();
  ASSERT_EQ(answer->frames_size(), query.frames_size());
  int frames_matched = 0;
  for (int i = 0; i < answer->frames_size(); ++i) {
    EXPECT_EQ(answer->frames(i).index(), static_cast<uint32_t>(i));
    frames_matched += answer->frames(i).matches_size() > 0 ? 1 : 0;
  }
  EXPECT_GE(frames_matched, query.frames_size() - 1);
  ASSERT_EQ(answer->matches_size(), 2);
  EXPECT_TRUE(answer->matches(0).visit_id() == stored_visit ||
              answer->matches(1).visit_id() == stored_visit);
  EXPECT_GE(answer->matches(0).score(), answer->matches(1).score());
  EXPECT_EQ(answer->matches(0).method(), v1::MATCH_METHOD_APPEARANCE);
  // Both methods on frames without poses: appearance answers, architecture says why not, and
  // there is no fused ranking.
  query.clear_methods();
  answer = client_->QueryPlace(query);
  ASSERT_TRUE(answer.ok()) << answer.status();
  ASSERT_EQ(answer->method_status_size(), 2);
  EXPECT_FALSE(answer->method_status(0).computed());
  EXPECT_NE(answer->method_status(0).reason().find("pose is missing"), std::string::npos);
  EXPECT_TRUE(answer->method_status(1).computed());
  for (const auto& m : answer->matches()) EXPECT_NE(m.method(), v1::MATCH_METHOD_FUSED);
  // The second (stored) visit, by appearance: the first.
  visits = client_->ListVisits("office");
  ASSERT_TRUE(visits.ok());
  ASSERT_EQ(visits->visits_size(), 2);
  v1::QueryPlaceRequest by_visit;
  by_visit.set_visit_id(visits->visits(0).id() == stored_visit ? visits->visits(1).id()
                                                               : visits->visits(0).id());
  by_visit.add_methods(v1::MATCH_METHOD_APPEARANCE);
  answer = client_->QueryPlace(by_visit);
  ASSERT_TRUE(answer.ok()) << answer.status();
  ASSERT_GE(answer->matches_size(), 1);
  EXPECT_EQ(answer->matches(0).visit_id(), stored_visit);

  // Another desk of the same office: asked, computed, nothing verified.
  ASSERT_TRUE(client_->CreateMap("elsewhere", "").ok());
  const auto other = Send("elsewhere", desk.frames, 0.0);
  for (const auto& r : other) EXPECT_TRUE(AppearanceMatches(r).empty());

  // After a restart the stored vocabulary and keyframes answer at once.
  RestartServer();
  const auto again = Send("office", {odd[odd.size() / 2]}, 0.0);
  ASSERT_EQ(again.size(), 1u);
  EXPECT_FALSE(AppearanceMatches(again[0]).empty()) << PlaceStatus(again[0]).reason();
}

TEST_F(AppearanceTest, WithEntropyMasksDisabledKeyframesKeepEveryFeature) {
  const std::string xyz_dir = lifemap::testing::SharedDataset("tum_fr1_xyz_subset");
  if (xyz_dir.empty()) GTEST_SKIP() << "../shared/data TUM fr1 subsets absent";
  server::ServerConfig config;
  config.pipeline.entropy_masks = false;
  StartServer(config);
  const TumFrames xyz = ReadTumFrames(xyz_dir);
  ASSERT_TRUE(client_->CreateMap("plain", "").ok());
  const auto results = Send("plain", {xyz.frames[0], xyz.frames[10]}, std::nullopt);
  ASSERT_EQ(results.size(), 2u);
  auto listed = client_->ListKeyframes("plain", 0);
  ASSERT_TRUE(listed.ok()) << listed.status();
  ASSERT_EQ(listed->keyframes_size(), 2);
  for (const auto& k : listed->keyframes()) {
    EXPECT_GT(k.keypoints_stored(), 300u);  // unpruned: nothing masked
    EXPECT_EQ(k.keypoints_masked(), 0u);
  }
}

TEST_F(AppearanceTest, ABadIntervalIsRefusedAndNonKeyframesSayHowToAsk) {
  // Retraining with nothing stored yet says what to do first.
  auto rebuilt = client_->RebuildAppearanceIndex(/*retrain=*/true);
  EXPECT_TRUE(absl::IsFailedPrecondition(rebuilt.status())) << rebuilt.status();
  EXPECT_NE(rebuilt.status().message().find("stream some frames"), absl::string_view::npos);

  ASSERT_TRUE(client_->CreateMap("m", "").ok());
  v1::ProcessFrameRequest req;
  req.set_map("m");
  *req.mutable_frame() = lifemap::testing::MakeFrame();
  req.mutable_options()->set_appearance_interval_s(-1);
  auto r = client_->ProcessFrame(req);
  EXPECT_TRUE(absl::IsInvalidArgument(r.status()));
  EXPECT_NE(r.status().message().find("appearance_interval_s"), absl::string_view::npos);
  req.mutable_options()->clear_appearance_interval_s();
  ASSERT_TRUE(client_->ProcessFrame(req).ok());  // the visit's first frame: a keyframe
  req.mutable_frame()->set_timestamp_s(req.frame().timestamp_s() + 0.01);
  r = client_->ProcessFrame(req);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_FALSE(r->keyframe().selected());
  EXPECT_NE(PlaceStatus(*r).reason().find("appearance_interval_s"), std::string::npos)
      << PlaceStatus(*r).reason();

  // A query of more frames than appearance takes is refused before any work, saying the cap.
  v1::QueryPlaceRequest many;
  many.add_methods(v1::MATCH_METHOD_APPEARANCE);
  for (int i = 0; i < 201; ++i) *many.add_frames() = lifemap::testing::MakeFrame(64, 48);
  auto refused = client_->QueryPlace(many);
  EXPECT_TRUE(absl::IsInvalidArgument(refused.status())) << refused.status();
  EXPECT_NE(refused.status().message().find("at most 200"), absl::string_view::npos);
}

}  // namespace
}  // namespace lifemap
