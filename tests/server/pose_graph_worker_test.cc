// Loop closure checks (issue 15): a candidate that disagrees with the odometry beyond the drift
// it allows, or has too few inliers, is stored as rejected with the reason and moves nothing; a
// consistent one is accepted, solved, and the visit's correction follows.
#include "server/pose_graph_worker.h"

#include <gtest/gtest.h>

#include "tests/testing/test_util.h"

namespace lifemap::server {
namespace {

class PoseGraphWorkerTest : public ::testing::Test {
 protected:
  void SetUp() override {
    auto s = store::Store::Open(tmp_.File("lifemap.db"));
    ASSERT_TRUE(s.ok()) << s.status();
    store_ = *std::move(s);
    ASSERT_TRUE(store_->CreateMap("m", "", 1.0).ok());
    auto v = store_->StartVisit("m", "", "", 1.0);
    ASSERT_TRUE(v.ok());
    visit_ = *v;
    // Ten keyframes 0.3 m apart along x; the odometry believes they drifted 1 cm per step in y.
    for (int i = 0; i < 10; ++i) {
      store::KeyframeRecord k;
      k.visit_id = visit_.id;
      k.sequence = static_cast<uint64_t>(i);
      k.timestamp_s = 1.0 + i;
      Pose odom;
      odom.translation = {0.3 * i, 0.01 * i, 0};
      k.T_world_camera = odom;
      k.T_odom_camera = odom;
      k.odom_segment = 7;
      k.pose_source = store::StoredPoseSource::kEstimated;
      k.intrinsics = {525, 525, 319.5, 239.5, 640, 480};
      k.depth_scale = 5000;
      k.depth = "d";
      k.color = "c";
      keyframes_.push_back(k);
    }
    ASSERT_TRUE(store_->InsertKeyframes(&keyframes_, {}).ok());
  }

  // A candidate from keyframe `from` to the last one, measured as the truth has it (y = 0)
  // plus `error`.
  LoopCandidate Candidate(int from, const Eigen::Vector3d& error, int inliers = 60) {
    LoopCandidate c;
    c.keyframe_id = keyframes_[from].id;
    c.T_match_query.translation = Eigen::Vector3d(0.3 * (9 - from), 0, 0) + error;
    c.inliers = inliers;
    c.reprojection_px = 1.0;
    return c;
  }

  std::shared_future<absl::StatusOr<int64_t>> Committed(int64_t id) {
    std::promise<absl::StatusOr<int64_t>> p;
    p.set_value(id);
    return p.get_future().share();
  }

  testing::TempDir tmp_;
  std::unique_ptr<store::Store> store_;
  store::VisitRecord visit_;
  std::vector<store::KeyframeRecord> keyframes_;
};

TEST_F(PoseGraphWorkerTest, WrongAndWeakLoopsAreRejectedWithTheReasonAndARightOneCorrects) {
  PoseGraphWorker worker(store_.get(), PoseGraphOptions{});
  std::optional<Pose> correction;
  PoseGraphWorker::Job job;
  job.map_id = visit_.map_id;
  job.visit_id = visit_.id;
  job.committed = Committed(keyframes_.back().id);
  job.on_corrected = [&](const Pose& c) { correction = c; };
  // 2 m off after 2.7 m of path: a perceptual alias, not drift.
  job.candidates = {Candidate(0, {2.0, 0, 0}), Candidate(1, {0, 0, 0}, /*inliers=*/12)};
  worker.Wait(worker.Submit(job));
  EXPECT_FALSE(correction.has_value()) << "nothing accepted, nothing solved";
  auto edges = store_->ListPoseEdges(visit_.map_id, visit_.id);
  ASSERT_TRUE(edges.ok());
  ASSERT_EQ(edges->size(), 2u);
  EXPECT_FALSE((*edges)[0].accepted);
  EXPECT_NE((*edges)[0].reason.find("disagrees with the odometry by 2.0"), std::string::npos)
      << (*edges)[0].reason;
  EXPECT_FALSE((*edges)[1].accepted);
  EXPECT_NE((*edges)[1].reason.find("12 PnP inliers"), std::string::npos) << (*edges)[1].reason;

  // The drift (9 cm in y) is within what 2.7 m of path allows: accepted, solved, corrected.
  job.candidates = {Candidate(0, {0, 0, 0})};
  worker.Wait(worker.Submit(job));
  ASSERT_TRUE(correction.has_value());
  auto listed = store_->ListKeyframes(visit_.map_id, visit_.id);
  ASSERT_TRUE(listed.ok());
  const auto& last = listed->back();
  EXPECT_GT(last.optimisation_id, 0);
  // Pulled back towards y = 0 (the loop and the odometry weighed by their sigmas).
  EXPECT_LT(std::abs(last.T_world_camera->translation.y()), 0.06);
  EXPECT_NEAR(last.T_odom_camera->translation.y(), 0.09, 1e-9) << "odometry kept as tracked";
  const Eigen::Vector3d corrected = correction->ToIsometry() * last.T_odom_camera->translation;
  EXPECT_LT((corrected - last.T_world_camera->translation).norm(), 1e-6)
      << "later frames follow the newest keyframe's correction";
  const LoopClosureStats stats = worker.Stats();
  EXPECT_EQ(stats.candidates, 3);
  EXPECT_EQ(stats.accepted, 1);
  EXPECT_EQ(stats.rejected, 2);
  EXPECT_EQ(stats.solves, 1);
}

TEST_F(PoseGraphWorkerTest, AKeyframeThatWasNotStoredClosesNothing) {
  PoseGraphWorker worker(store_.get(), PoseGraphOptions{});
  PoseGraphWorker::Job job;
  job.map_id = visit_.map_id;
  job.visit_id = visit_.id;
  std::promise<absl::StatusOr<int64_t>> failed;
  failed.set_value(absl::UnavailableError("disk full"));
  job.committed = failed.get_future().share();
  job.candidates = {Candidate(0, {0, 0, 0})};
  worker.Wait(worker.Submit(job));
  auto edges = store_->ListPoseEdges(visit_.map_id, visit_.id);
  ASSERT_TRUE(edges.ok());
  EXPECT_TRUE(edges->empty());
}

// A second tracked visit whose own frame is the first visit's moved by T (2 m along x, turned
// 90 deg about z): two of its keyframes' matches agreeing on T anchor it, its keyframes move into
// the map's frame; a single match, or two that disagree, anchor nothing.
TEST_F(PoseGraphWorkerTest, ATrackedVisitIsAnchoredWhenTwoMatchesAgree) {
  Pose T;  // the second visit's frame in the map's
  T.translation = {2.0, 0.0, 0.0};
  T.rotation = Eigen::AngleAxisd(M_PI / 2, Eigen::Vector3d::UnitZ());
  auto second = store_->StartVisit("m", "", "", 2.0);
  ASSERT_TRUE(second.ok());
  std::vector<store::KeyframeRecord> b;
  for (int i = 0; i < 4; ++i) {
    store::KeyframeRecord k = keyframes_[i];
    k.id = 0;
    k.visit_id = second->id;
    k.timestamp_s = 100.0 + i;
    // Keyframe i of the second visit stands where keyframe i of the first does, in its own
    // frame: T^-1 * (the first visit's pose).
    const Pose own =
        Pose::FromIsometry(T.ToIsometry().inverse() * keyframes_[i].T_world_camera->ToIsometry());
    k.T_world_camera = own;
    k.T_odom_camera = own;
    b.push_back(k);
  }
  ASSERT_TRUE(store_->InsertKeyframes(&b, {}).ok());
  PoseGraphWorker worker(store_.get(), PoseGraphOptions{});
  std::optional<Pose> anchored;
  auto job_for = [&](int i, const Pose& T_match_query) {
    PoseGraphWorker::Job job;
    job.map_id = visit_.map_id;
    job.visit_id = second->id;
    job.committed = Committed(b[i].id);
    job.anchors = {{visit_.id, {keyframes_[i].id, T_match_query, 60, 1.0}}};
    job.on_anchored = [&](const Pose& t) { anchored = t; };
    return job;
  };
  // Keyframe 0's match, then keyframe 1's that disagrees by 0.5 m: nothing yet.
  Pose off;
  off.translation = {0.5, 0, 0};
  worker.Wait(worker.Submit(job_for(0, Pose{})));
  worker.Wait(worker.Submit(job_for(1, off)));
  EXPECT_FALSE(anchored.has_value());
  auto v = store_->GetVisit(second->id);
  ASSERT_TRUE(v.ok());
  EXPECT_FALSE(v->anchor.has_value());
  EXPECT_FALSE(v->first_of_map);
  EXPECT_EQ(v->tracked_keyframes, 4) << "tracked, not anchored: VISIT_FRAME_UNANCHORED";
  auto first = store_->GetVisit(visit_.id);
  ASSERT_TRUE(first.ok());
  EXPECT_TRUE(first->first_of_map);
  // Keyframe 2's agrees with keyframe 0's: anchored to the first visit by T.
  worker.Wait(worker.Submit(job_for(2, Pose{})));
  ASSERT_TRUE(anchored.has_value());
  EXPECT_LT((anchored->translation - T.translation).norm(), 1e-6);
  EXPECT_LT(RotationAngleRad(*anchored, T), 1e-6);
  v = store_->GetVisit(second->id);
  ASSERT_TRUE(v.ok());
  ASSERT_TRUE(v->anchor.has_value());
  EXPECT_EQ(v->anchor->to_visit_id, visit_.id);
  EXPECT_LT(v->anchor->residual_m, 1e-6);
  EXPECT_GT(v->anchor->edge_id, 0);
  // Its keyframes are in the map's frame now: where the first visit's are.
  auto listed = store_->ListKeyframes(visit_.map_id, second->id);
  ASSERT_TRUE(listed.ok());
  ASSERT_EQ(listed->size(), 4u);
  for (int i = 0; i < 4; ++i) {
    EXPECT_LT(((*listed)[i].T_world_camera->translation - keyframes_[i].T_world_camera->translation)
                  .norm(),
              1e-6);
  }
  // Anchored once: later matches change nothing.
  anchored.reset();
  worker.Wait(worker.Submit(job_for(3, off)));
  EXPECT_FALSE(anchored.has_value());
  EXPECT_EQ(worker.Stats().anchors, 1);
}

}  // namespace
}  // namespace lifemap::server
