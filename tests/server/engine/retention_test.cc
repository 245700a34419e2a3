#include "server/engine/retention.h"

#include <cmath>
#include <set>

#include <chrono>
#include <thread>

#include <gtest/gtest.h>

#include "server/engine/clock.h"
#include "server/engine/engine.h"
#include "tests/testing/test_util.h"

namespace lifemap::server {
namespace {

// A keyframe `x` metres along a corridor, turned `yaw_deg` about the vertical.
RetentionCandidate At(int64_t id, int rank, double x, double yaw_deg = 0, bool protect = false) {
  RetentionCandidate c;
  c.keyframe_id = id;
  c.visit_rank = rank;
  c.pose.translation = {x, 0, 0};
  c.pose.rotation =
      Eigen::Quaterniond(Eigen::AngleAxisd(yaw_deg * M_PI / 180, Eigen::Vector3d::UnitY()));
  c.protect = protect;
  return c;
}

std::set<int64_t> Thinned(const std::vector<ThinnedKeyframe>& plan) {
  std::set<int64_t> ids;
  for (const auto& t : plan) ids.insert(t.keyframe_id);
  return ids;
}

TEST(PlanThinning, KeepsTheNewestVisitsAndThinsOlderViewsTheyCover) {
  RetentionOptions o;
  o.keep_recent_visits = 1;
  o.compact_after_visits = 100;
  // Visit 0 walked 0, 1, 2, 3 m; visit 1 walked 0.1, 1.1 and 5 m; only 0 and 1 m are covered.
  const std::vector<RetentionCandidate> c = {At(1, 0, 0.0), At(2, 0, 1.0), At(3, 0, 2.0),
                                             At(4, 0, 3.0), At(5, 1, 0.1), At(6, 1, 1.1),
                                             At(7, 1, 5.0)};
  const auto plan = PlanThinning(c, 2, o);
  EXPECT_EQ(Thinned(plan), (std::set<int64_t>{1, 2}));
  for (const auto& t : plan) {
    EXPECT_EQ(t.covered_by, t.keyframe_id + 4);
    EXPECT_NEAR(t.distance_m, 0.1, 1e-9);
  }
  // With both visits kept whole nothing goes.
  o.keep_recent_visits = 2;
  EXPECT_TRUE(PlanThinning(c, 2, o).empty());
}

TEST(PlanThinning, NeverThinsProtectedKeyframesNorCoversWithEarlierVisitsOrOtherHeadings) {
  RetentionOptions o;
  o.keep_recent_visits = 1;
  o.compact_after_visits = 100;
  const std::vector<RetentionCandidate> c = {
      At(1, 0, 0.0, 0, /*protect=*/true),  // e.g. its landmarks were matched
      At(2, 0, 1.0, 0),                    // covered only by a view turned 40 degrees
      At(3, 1, 0.0), At(4, 1, 1.0, 40),
      At(5, 2, 2.0)};  // the newest; keyframe 6 of the older visit 1 would cover nothing later
  const auto plan = PlanThinning(c, 3, o);
  EXPECT_TRUE(Thinned(plan).empty());
}

TEST(PlanThinning, EveryThinnedViewStaysCoveredByAKeptKeyframeAcrossManyVisits) {
  RetentionOptions o;  // the defaults: 0.3 m / 15 degrees, 2 newest kept, compact after 5
  o.compact_after_visits = 1000;
  // 20 visits walking the same corridor with 0.12 m of drift per visit: chains of covers
  // would drift away from the first visits' views.
  std::vector<RetentionCandidate> c;
  int64_t id = 1;
  for (int v = 0; v < 20; ++v) {
    for (int k = 0; k < 10; ++k) c.push_back(At(id++, v, 0.5 * k + 0.12 * v));
  }
  const auto plan = PlanThinning(c, 20, o);
  const std::set<int64_t> thinned = Thinned(plan);
  EXPECT_GT(thinned.size(), 100u);
  for (const auto& t : plan) {
    EXPECT_EQ(thinned.count(t.covered_by), 0u)
        << "keyframe " << t.keyframe_id << " is covered by a thinned one";
    EXPECT_LE(t.distance_m, o.cover_m + 1e-9);
    const auto& k = c[static_cast<size_t>(t.keyframe_id - 1)];
    const auto& by = c[static_cast<size_t>(t.covered_by - 1)];
    EXPECT_GE(by.visit_rank, k.visit_rank);
  }
  // The two newest visits are whole.
  for (const auto& k : c) {
    if (k.visit_rank >= 18) {
      EXPECT_EQ(thinned.count(k.keyframe_id), 0u);
    }
  }
}

TEST(PlanThinning, CompactsOldVisitsToASparseSetOfTheirOwn) {
  RetentionOptions o;
  o.keep_recent_visits = 1;
  o.compact_after_visits = 1;
  o.compact_cover_m = 1.0;
  // One old visit along 4 m every 0.25 m and a newest one elsewhere: the old one covers itself
  // at 1 m, keeping about one keyframe a metre.
  std::vector<RetentionCandidate> c;
  for (int k = 0; k < 17; ++k) c.push_back(At(k + 1, 0, 0.25 * k));
  c.push_back(At(100, 1, 50.0));
  const auto plan = PlanThinning(c, 2, o);
  const size_t kept = 17 - plan.size();
  EXPECT_GE(kept, 3u);
  EXPECT_LE(kept, 6u);
  for (const auto& t : plan) EXPECT_LE(t.distance_m, 1.0 + 1e-9);
}

// `retention.after_visit_end`: ending a visit thins the older visits of its map off the reply path.
TEST(RetentionAfterVisitEnd, EndingAVisitThinsTheOlderOnes) {
  testing::TempDir tmp;
  EngineOptions options;
  options.db_path = tmp.File("lifemap.db");
  options.retention.after_visit_end = true;
  options.retention.keep_recent_visits = 1;
  auto engine = Engine::Open(options);
  ASSERT_TRUE(engine.ok()) << engine.status();
  store::Store* store = (*engine)->store();
  auto map = store->CreateMap("hall", "", NowSeconds());
  ASSERT_TRUE(map.ok());
  // Two visits walking the same 2 m with client poses, 10 keyframes each.
  std::vector<int64_t> visits;
  for (int v = 0; v < 2; ++v) {
    auto visit = store->StartVisit("hall", "robot", "", NowSeconds() - 100 + v);
    ASSERT_TRUE(visit.ok());
    std::vector<store::KeyframeRecord> batch;
    for (int k = 0; k < 10; ++k) {
      store::KeyframeRecord r;
      r.visit_id = visit->id;
      r.sequence = static_cast<uint64_t>(k);
      r.timestamp_s = NowSeconds() - 100 + v + 0.01 * k;
      Pose pose;
      pose.translation = {0.2 * k + 0.02 * v, 0, 0};
      r.T_world_camera = pose;
      r.intrinsics = {525, 525, 319.5, 239.5, 640, 480};
      r.depth_scale = 5000;
      r.depth = "depth";
      r.color = "color";
      batch.push_back(r);
    }
    ASSERT_TRUE(store->InsertKeyframes(&batch, {}).ok());
    visits.push_back(visit->id);
  }
  ASSERT_TRUE(store->EndVisit(visits[0], NowSeconds(), {visits[0], 10, 0}).ok());
  ASSERT_TRUE((*engine)->EndVisit(visits[1]).ok());
  size_t left = 10;
  for (int i = 0; i < 100 && left == 10; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
    left = store->ListKeyframes(map->id, visits[0])->size();
  }
  EXPECT_EQ(left, 1u) << "all but the first keyframe of the older visit are covered";
  EXPECT_EQ(store->ListKeyframes(map->id, visits[1])->size(), 10u) << "the newest is kept whole";
}

}  // namespace
}  // namespace lifemap::server
