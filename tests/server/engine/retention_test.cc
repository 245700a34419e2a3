#include "server/engine/retention.h"

#include <cmath>
#include <set>

#include <gtest/gtest.h>

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

}  // namespace
}  // namespace lifemap::server
