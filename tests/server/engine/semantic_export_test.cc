// The semantic octree export (issue 16): which visits' octrees lie in the map's frame, and where
// a visit anchored into it goes.
#include "server/engine/semantic_export.h"

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "tests/testing/test_util.h"

namespace lifemap::server {
namespace {

constexpr int kClasses = 3;

CameraIntrinsics Camera() { return {40, 40, 19.5, 14.5, 40, 30}; }

// A visit's octree: a wall 2.02 m in front of a camera at the origin, all of class `label`.
std::string WallOctree(int label, const semantic::SemanticMapOptions& options) {
  auto map = semantic::SemanticMap::Create(kClasses, {1, 1, 1}, options);
  EXPECT_TRUE(map.ok());
  const CameraIntrinsics k = Camera();
  const cv::Mat depth(k.height, k.width, CV_32FC1, cv::Scalar(2.02f));
  std::vector<cv::Mat> p;
  for (int c = 0; c < kClasses; ++c) {
    p.emplace_back(k.height, k.width, CV_32FC1, cv::Scalar(c == label ? 0.9f : 0.05f));
  }
  EXPECT_TRUE((*map)->Fuse(depth, k, Pose{}, p).ok());
  return (*map)->Serialize();
}

class SemanticExportTest : public ::testing::Test {
 protected:
  void SetUp() override {
    auto s = store::Store::Open(tmp_.File("lifemap.db"));
    ASSERT_TRUE(s.ok()) << s.status();
    store_ = *std::move(s);
    auto map = store_->CreateMap("m", "", 1.0);
    ASSERT_TRUE(map.ok());
    map_ = *map;
    options_.pixel_stride = 1;  // every pixel: the wall's voxels are contiguous
  }

  // A visit with one keyframe (client-posed or tracked) and a snapshot of a wall of `label`.
  store::VisitRecord Visit(bool tracked, int label, std::string model = "forest") {
    auto v = store_->StartVisit("m", "", "", 1.0);
    EXPECT_TRUE(v.ok());
    std::vector<store::KeyframeRecord> k(1);
    k[0].visit_id = v->id;
    k[0].timestamp_s = 1.0;
    k[0].T_world_camera = Pose{};
    if (tracked) {
      k[0].T_odom_camera = Pose{};
      k[0].pose_source = store::StoredPoseSource::kEstimated;
    }
    k[0].intrinsics = Camera();
    k[0].depth_scale = 5000;
    k[0].depth = "d";
    k[0].color = "c";
    EXPECT_TRUE(store_->InsertKeyframes(&k, {}).ok());
    store::SemanticSnapshotRecord r;
    r.visit_id = v->id;
    r.model = std::move(model);
    r.class_count = kClasses;
    r.resolution_m = options_.resolution_m;
    r.keyframes = 1;
    r.bytes = WallOctree(label, options_);
    r.updated_time_s = static_cast<double>(v->id);
    EXPECT_TRUE(store_->PutSemanticSnapshot(r).ok());
    return *v;
  }

  // Anchors `visit` to `to` (by their first keyframes) with its frame 1 m to the right of the
  // map's (x + 1).
  absl::Status AnchorOneMetreRight(const store::VisitRecord& visit, const store::VisitRecord& to) {
    store::PoseEdgeRecord edge;
    edge.map_id = map_.id;
    edge.kind = store::StoredEdgeKind::kAnchor;
    auto from_keyframes = store_->ListKeyframes(map_.id, visit.id);
    auto to_keyframes = store_->ListKeyframes(map_.id, to.id);
    if (!from_keyframes.ok() || !to_keyframes.ok()) return absl::InternalError("no keyframes");
    edge.from_keyframe = from_keyframes->front().id;
    edge.to_keyframe = to_keyframes->front().id;
    edge.accepted = true;
    store::VisitAnchor anchor;
    anchor.to_visit_id = to.id;
    anchor.T_map_visit.translation = {1.0, 0.0, 0.0};
    return store_->AnchorVisit(visit.id, edge, &anchor);
  }

  absl::StatusOr<SemanticExport> Collect(int64_t visit_id) {
    VisitRegistry registry(store_.get(), nullptr);
    return CollectSemanticExport(store_.get(), &registry, nullptr, map_, visit_id, options_);
  }

  testing::TempDir tmp_;
  std::unique_ptr<store::Store> store_;
  store::MapRecord map_;
  semantic::SemanticMapOptions options_;
};

TEST_F(SemanticExportTest, MergesTheVisitsInTheMapsFrameOnly) {
  const store::VisitRecord first = Visit(/*tracked=*/false, 1);
  const store::VisitRecord anchored = Visit(/*tracked=*/true, 2);
  const store::VisitRecord adrift = Visit(/*tracked=*/true, 2);
  // The anchored visit's frame lies 1 m to the right of the map's (x + 1).
  ASSERT_TRUE(AnchorOneMetreRight(anchored, first).ok());

  auto e = Collect(0);
  ASSERT_TRUE(e.ok()) << e.status();
  EXPECT_TRUE(e->in_map_frame);
  EXPECT_EQ(e->visits, (std::vector<int64_t>{first.id, anchored.id}));
  ASSERT_EQ(e->left_out.size(), 1u);
  EXPECT_NE(e->left_out[0].find("not anchored"), std::string::npos) << e->left_out[0];
  // The camera looked along +z at a wall 2 m away; its footprint is about ±1 m in x. The first
  // visit's class holds at x = -0.6, the anchored one's (moved 1 m right) at x = 1.6.
  const auto left = e->map->BeliefAt(-0.6, 0.0, 2.02);
  ASSERT_EQ(left.size(), 3u);
  EXPECT_GT(left[1], 0.5f);
  const auto right = e->map->BeliefAt(1.6, 0.0, 2.02);
  ASSERT_EQ(right.size(), 3u);
  EXPECT_GT(right[2], 0.5f);
  EXPECT_EQ(e->class_names, (std::vector<std::string>{"class 0", "class 1", "class 2"}))
      << "the model was never uploaded: classes are numbered";
  const auto summary = nlohmann::json::parse(SemanticExportSummaryJson(*e));
  EXPECT_EQ(summary["frame"], "map");
  EXPECT_EQ(summary["left_out"].size(), 1u);

  // One visit not anchored: exported in its own frame, and said so.
  auto alone = Collect(adrift.id);
  ASSERT_TRUE(alone.ok()) << alone.status();
  EXPECT_FALSE(alone->in_map_frame);
  EXPECT_EQ(nlohmann::json::parse(SemanticExportSummaryJson(*alone))["frame"], "visit");
}

TEST_F(SemanticExportTest, OctreesOfAnotherModelAreLeftOut) {
  const store::VisitRecord old_model = Visit(false, 1, "old");
  const store::VisitRecord new_model = Visit(false, 2, "new");
  auto e = Collect(0);
  ASSERT_TRUE(e.ok()) << e.status();
  EXPECT_EQ(e->model, "new");
  EXPECT_EQ(e->visits, (std::vector<int64_t>{new_model.id}));
  ASSERT_EQ(e->left_out.size(), 1u);
  EXPECT_NE(e->left_out[0].find("model 'old'"), std::string::npos) << e->left_out[0];
  (void)old_model;
}

TEST_F(SemanticExportTest, TheMapsOctreeIsStoredAndMergedAgainWhenAVisitChanges) {
  const store::VisitRecord first = Visit(/*tracked=*/false, 1);
  const store::VisitRecord tracked = Visit(/*tracked=*/true, 2);
  auto merged = Collect(0);
  ASSERT_TRUE(merged.ok()) << merged.status();
  EXPECT_FALSE(merged->stored);
  EXPECT_EQ(merged->visits, (std::vector<int64_t>{first.id}));
  auto stored = store_->GetMapSemanticSnapshot(map_.id);
  ASSERT_TRUE(stored.ok()) << stored.status();
  EXPECT_EQ(stored->octree.model, "forest");

  // Nothing changed: the stored one is read back, the same octree, the same account.
  auto again = Collect(0);
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_TRUE(again->stored);
  EXPECT_EQ(again->visits, merged->visits);
  EXPECT_EQ(again->left_out, merged->left_out);
  EXPECT_EQ(again->map->Serialize(), merged->map->Serialize());
  EXPECT_EQ(nlohmann::json::parse(SemanticExportSummaryJson(*again))["map_octree"], "stored");

  // The tracked visit anchored: merged again, with it.
  ASSERT_TRUE(AnchorOneMetreRight(tracked, first).ok());
  auto anchored = Collect(0);
  ASSERT_TRUE(anchored.ok()) << anchored.status();
  EXPECT_FALSE(anchored->stored);
  EXPECT_EQ(anchored->visits, (std::vector<int64_t>{first.id, tracked.id}));

  // A visit's snapshot replaced: the refresh after a visit ends merges again, exports read it.
  auto snapshot = store_->GetSemanticSnapshot(first.id);
  ASSERT_TRUE(snapshot.ok());
  snapshot->bytes = WallOctree(0, options_);
  snapshot->updated_time_s += 10;
  ASSERT_TRUE(store_->PutSemanticSnapshot(*snapshot).ok());
  RefreshMapSemanticOctree(store_.get(), "m", options_);
  auto refreshed = Collect(0);
  ASSERT_TRUE(refreshed.ok()) << refreshed.status();
  EXPECT_TRUE(refreshed->stored);
  EXPECT_GT(refreshed->map->BeliefAt(-0.6, 0.0, 2.02)[0], 0.5f) << "the new snapshot's class";

  // One visit's export is never the map's stored octree.
  auto one = Collect(first.id);
  ASSERT_TRUE(one.ok());
  EXPECT_FALSE(one->stored);

  ASSERT_TRUE(store_->DeleteMap("m").ok());
  EXPECT_TRUE(absl::IsNotFound(store_->GetMapSemanticSnapshot(map_.id).status()));
}

TEST_F(SemanticExportTest, NoOctreeSaysHowToGetOne) {
  auto e = Collect(0);
  EXPECT_EQ(e.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_NE(e.status().message().find("semantic.enabled"), std::string::npos) << e.status();
}

}  // namespace
}  // namespace lifemap::server
