// What the client libraries make of a cluster's fanned-out answers (issue 39): one ranking per
// method, best first across shards; figures summed. The Python client merges alike
// (client/python/tests).
#include "client/cluster_merge.h"

#include <gtest/gtest.h>

namespace lifemap::client {
namespace {

v1::PlaceMatch Match(const std::string& map, double score, v1::MatchMethod method) {
  v1::PlaceMatch m;
  m.set_map(map);
  m.set_score(score);
  m.set_method(method);
  return m;
}

TEST(ClusterMerge, PlaceRankingsMergeByScorePerMethodAndKeepMaxResults) {
  v1::QueryPlaceResponse s1;
  *s1.add_matches() = Match("lab", 0.6, v1::MATCH_METHOD_FUSED);
  *s1.add_matches() = Match("lab", 0.5, v1::MATCH_METHOD_ARCHITECTURE);
  *s1.add_matches() = Match("lab", 0.9, v1::MATCH_METHOD_APPEARANCE);
  auto* f0 = s1.add_frames();
  f0->set_index(0);
  f0->set_reason("no verified match");
  s1.set_descriptor_text("corner 1");
  auto* arch = s1.add_method_status();
  arch->set_method(v1::MATCH_METHOD_ARCHITECTURE);
  arch->set_computed(true);
  auto* app = s1.add_method_status();
  app->set_method(v1::MATCH_METHOD_APPEARANCE);
  app->set_computed(false);
  app->set_reason("no vocabulary yet");

  v1::QueryPlaceResponse s2;
  *s2.add_matches() = Match("office", 0.8, v1::MATCH_METHOD_FUSED);
  *s2.add_matches() = Match("hall", 0.7, v1::MATCH_METHOD_FUSED);
  *s2.add_matches() = Match("office", 0.95, v1::MATCH_METHOD_APPEARANCE);
  auto* g0 = s2.add_frames();
  g0->set_index(0);
  *g0->add_matches() = Match("office", 0.95, v1::MATCH_METHOD_APPEARANCE);
  auto* arch2 = s2.add_method_status();
  arch2->set_method(v1::MATCH_METHOD_ARCHITECTURE);
  arch2->set_computed(false);
  arch2->set_reason("no places stored");
  auto* app2 = s2.add_method_status();
  app2->set_method(v1::MATCH_METHOD_APPEARANCE);
  app2->set_computed(true);

  const v1::QueryPlaceResponse merged = MergePlaceAnswers({{"s1", s1}, {"s2", s2}}, 2);
  ASSERT_EQ(5, merged.matches_size());  // fused: 2 of 3; architecture 1; appearance 2
  EXPECT_EQ("office", merged.matches(0).map());
  EXPECT_EQ(v1::MATCH_METHOD_FUSED, merged.matches(0).method());
  EXPECT_EQ("hall", merged.matches(1).map());
  EXPECT_EQ(v1::MATCH_METHOD_ARCHITECTURE, merged.matches(2).method());
  EXPECT_EQ("office", merged.matches(3).map());
  EXPECT_EQ(v1::MATCH_METHOD_APPEARANCE, merged.matches(3).method());
  EXPECT_EQ("lab", merged.matches(4).map());
  ASSERT_EQ(1, merged.frames_size());
  EXPECT_EQ(1, merged.frames(0).matches_size());
  EXPECT_TRUE(merged.frames(0).reason().empty()) << "a shard matched the frame";
  EXPECT_EQ("corner 1", merged.descriptor_text());
  ASSERT_EQ(2, merged.method_status_size());
  EXPECT_EQ(v1::MATCH_METHOD_ARCHITECTURE, merged.method_status(0).method());
  EXPECT_TRUE(merged.method_status(0).computed());
  EXPECT_TRUE(merged.method_status(1).computed());

  // No shard computed a method: its reasons, by shard.
  const v1::QueryPlaceResponse alone = MergePlaceAnswers({{"s2", s2}}, 10);
  EXPECT_FALSE(alone.method_status(0).computed());
  EXPECT_EQ("s2: no places stored", alone.method_status(0).reason());
}

TEST(ClusterMerge, StatsAreSummedWithTheShortestUptime) {
  v1::Stats a;
  a.set_maps(2);
  a.set_keyframes(100);
  a.set_frames_processed(1000);
  a.set_process_cpu_s(12.5);
  a.set_uptime_s(300);
  a.mutable_appearance()->set_enabled(true);
  a.mutable_appearance()->set_has_vocabulary(true);
  a.mutable_appearance()->set_vocabulary_id(7);
  a.mutable_appearance()->set_keyframes(90);
  v1::Stats b = a;
  b.set_maps(3);
  b.set_uptime_s(100);
  b.mutable_appearance()->set_has_vocabulary(false);
  b.mutable_appearance()->set_vocabulary_id(0);
  const v1::Stats merged = MergeStats({a, b});
  EXPECT_EQ(5u, merged.maps());
  EXPECT_EQ(200u, merged.keyframes());
  EXPECT_EQ(2000u, merged.frames_processed());
  EXPECT_DOUBLE_EQ(25.0, merged.process_cpu_s());
  EXPECT_DOUBLE_EQ(100.0, merged.uptime_s());
  EXPECT_FALSE(merged.appearance().has_vocabulary());
  EXPECT_EQ(0u, merged.appearance().vocabulary_id()) << "each shard trains its own";
  EXPECT_EQ(180u, merged.appearance().keyframes());
  EXPECT_EQ(7u, MergeStats({a}).appearance().vocabulary_id());
}

}  // namespace
}  // namespace lifemap::client
