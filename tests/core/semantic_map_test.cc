#include "core/semantic/semantic_map.h"

#include <cmath>
#include <cstring>
#include <random>
#include <sstream>

#include <gtest/gtest.h>
#include <octomap/AbstractOcTree.h>
#include <octomap/ColorOcTree.h>
#include <octomap/OcTree.h>

namespace lifemap::semantic {
namespace {

constexpr int kClasses = 3;

CameraIntrinsics Camera() {
  CameraIntrinsics k;
  k.fx = k.fy = 160.0;
  k.cx = 79.5;
  k.cy = 59.5;
  k.width = 160;
  k.height = 120;
  return k;
}

// A wall 2 m in front of a camera at the origin looking along +z; the left half (x < 0 in the
// map) is class 1, the right half class 2. Each pixel's distribution gives its true class
// `p_true` and shares the rest; with `flip` > 0 that share of pixels (at random) swaps the
// true class for the other half's, so single views are wrong there.
struct View {
  cv::Mat depth;
  std::vector<cv::Mat> probabilities;
};

View WallView(const Pose& T_map_camera, double p_true, double flip, std::mt19937* rng,
              double wall_z = 2.0) {
  const CameraIntrinsics k = Camera();
  View view;
  view.depth = cv::Mat(k.height, k.width, CV_32FC1, cv::Scalar(0));
  for (int c = 0; c < kClasses; ++c) {
    view.probabilities.emplace_back(k.height, k.width, CV_32FC1, cv::Scalar(0));
  }
  const Eigen::Isometry3d T = T_map_camera.ToIsometry();
  std::uniform_real_distribution<double> uniform(0.0, 1.0);
  for (int v = 0; v < k.height; ++v) {
    for (int u = 0; u < k.width; ++u) {
      // Ray-plane intersection with z = wall_z in the map frame.
      const Eigen::Vector3d dir_camera((u - k.cx) / k.fx, (v - k.cy) / k.fy, 1.0);
      const Eigen::Vector3d dir = T.linear() * dir_camera;
      const double t = (wall_z - T.translation().z()) / dir.z();
      if (!(t > 0)) continue;
      const Eigen::Vector3d hit = T.translation() + t * dir;
      view.depth.at<float>(v, u) = static_cast<float>(t);  // depth = z in the camera frame
      int truth = hit.x() < 0 ? 1 : 2;
      if (flip > 0 && uniform(*rng) < flip) truth = 3 - truth;
      for (int c = 0; c < kClasses; ++c) {
        view.probabilities[c].at<float>(v, u) =
            static_cast<float>(c == truth ? p_true : (1.0 - p_true) / (kClasses - 1));
      }
    }
  }
  return view;
}

Pose At(double x, double y) {
  Pose p;
  p.translation = Eigen::Vector3d(x, y, 0);
  return p;
}

std::unique_ptr<SemanticMap> NewMap(SemanticMapOptions options = {}) {
  auto map = SemanticMap::Create(kClasses, {0.5, 0.25, 0.25}, options);
  EXPECT_TRUE(map.ok()) << map.status();
  return std::move(*map);
}

// Share of labelled pixels whose rendered label is the wall's true class at that pixel.
double RenderedAccuracy(const SemanticMap& map, const Pose& pose, double* coverage) {
  const CameraIntrinsics k = Camera();
  std::mt19937 rng(1);
  const View truth = WallView(pose, 1.0, 0.0, &rng);
  auto r = map.Render(truth.depth, k, pose, 1);
  EXPECT_TRUE(r.ok()) << r.status();
  int64_t right = 0;
  for (int v = 0; v < k.height; ++v) {
    for (int u = 0; u < k.width; ++u) {
      const uint8_t l = r->labels.at<uint8_t>(v, u);
      if (l == 255) continue;
      right += truth.probabilities[l].at<float>(v, u) > 0.5f ? 1 : 0;
    }
  }
  *coverage = static_cast<double>(r->labelled_pixels) / static_cast<double>(r->depth_pixels);
  return r->labelled_pixels > 0 ? static_cast<double>(right) / r->labelled_pixels : 0.0;
}

TEST(SemanticMap, RendersWhatWasFused) {
  auto map = NewMap();
  std::mt19937 rng(7);
  const View view = WallView(At(0, 0), 0.7, 0.0, &rng);
  auto stats = map->Fuse(view.depth, Camera(), At(0, 0), view.probabilities);
  ASSERT_TRUE(stats.ok()) << stats.status();
  EXPECT_GT(stats->labelled_voxels, 500);
  EXPECT_GT(stats->free_voxels, 1000);
  double coverage = 0;
  EXPECT_GT(RenderedAccuracy(*map, At(0, 0), &coverage), 0.97);
  EXPECT_GT(coverage, 0.95);
  // From a shifted view the wall is the same.
  EXPECT_GT(RenderedAccuracy(*map, At(0.1, 0.05), &coverage), 0.95);
  const SemanticSummary s = map->Summarize();
  EXPECT_EQ(s.keyframes, 1);
  EXPECT_GT(s.class_volume_m3[1], 0.0);
  EXPECT_GT(s.class_volume_m3[2], 0.0);
  EXPECT_EQ(s.class_volume_m3[0], 0.0);
  EXPECT_NEAR(s.min_m[2], 1.95, 0.051);
}

TEST(SemanticMap, FusingViewsCorrectsSingleViewErrors) {
  // A third of each view's pixels say the wrong class: a single view's labels are 67% right;
  // each voxel is sampled about once per view, so 20 fused views vote: a binomial majority of
  // 20 at 0.67 is right 94% of the time.
  auto map = NewMap();
  std::mt19937 rng(3);
  for (int i = 0; i < 20; ++i) {
    const Pose pose = At(0.02 * i, -0.01 * i);
    const View view = WallView(pose, 0.6, 0.33, &rng);
    ASSERT_TRUE(map->Fuse(view.depth, Camera(), pose, view.probabilities).ok());
  }
  double coverage = 0;
  EXPECT_GT(RenderedAccuracy(*map, At(0.05, 0), &coverage), 0.9);
  EXPECT_GT(coverage, 0.9);
}

TEST(SemanticMap, PriorDecidesWhenObservationsAreUninformative) {
  SemanticMapOptions options;
  options.prior_weight = 1.0;  // eq. 9's prior as is
  auto map = NewMap(options);
  std::mt19937 rng(1);
  const View view = WallView(At(0, 0), 1.0 / kClasses, 0.0, &rng);
  ASSERT_TRUE(map->Fuse(view.depth, Camera(), At(0, 0), view.probabilities).ok());
  const std::vector<float> belief = map->BeliefAt(-0.2, 0.0, 2.03);
  ASSERT_EQ(belief.size(), 3u);
  EXPECT_NEAR(belief[0], 0.5, 1e-3);
  EXPECT_NEAR(belief[1], 0.25, 1e-3);

  // The default starts uniform: the same observations leave every class at 1/3.
  auto uniform = NewMap();
  ASSERT_TRUE(uniform->Fuse(view.depth, Camera(), At(0, 0), view.probabilities).ok());
  const std::vector<float> flat = uniform->BeliefAt(-0.2, 0.0, 2.03);
  ASSERT_EQ(flat.size(), 3u);
  EXPECT_NEAR(flat[0], 1.0 / 3, 1e-3);
  EXPECT_NEAR(flat[2], 1.0 / 3, 1e-3);
}

TEST(SemanticMap, AVoxelThatTurnsFreeForgetsItsClass) {
  // This camera's pixels are 1.9 cm apart at 3 m: an endpoint and a ray every other pixel
  // reach every 5 cm voxel there.
  SemanticMapOptions options;
  options.pixel_stride = 2;
  options.free_space_stride = 2;
  auto map = NewMap(options);
  std::mt19937 rng(1);
  const View near = WallView(At(0, 0), 0.9, 0.0, &rng, 2.02);
  ASSERT_TRUE(map->Fuse(near.depth, Camera(), At(0, 0), near.probabilities).ok());
  ASSERT_FALSE(map->BeliefAt(-0.2, 0.0, 2.03).empty());
  // The wall moved back to 3 m: the rays through 2 m now see free space.
  const View far = WallView(At(0, 0), 0.9, 0.0, &rng, 3.02);
  for (int i = 0; i < 4; ++i) {
    ASSERT_TRUE(map->Fuse(far.depth, Camera(), At(0, 0), far.probabilities).ok());
  }
  EXPECT_TRUE(map->BeliefAt(-0.2, 0.0, 2.03).empty());
  EXPECT_FALSE(map->BeliefAt(-0.2, 0.0, 3.03).empty());
}

TEST(SemanticMap, RefusesBadInputWithoutTouchingTheTree) {
  auto map = NewMap();
  std::mt19937 rng(1);
  View view = WallView(At(0, 0), 0.7, 0.0, &rng);
  ASSERT_TRUE(map->Fuse(view.depth, Camera(), At(0, 0), view.probabilities).ok());
  const std::string before = map->Serialize();

  std::vector<cv::Mat> two(view.probabilities.begin(), view.probabilities.begin() + 2);
  auto s = map->Fuse(view.depth, Camera(), At(0, 0), two).status();
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(s.message().find("have 2 classes"), std::string::npos) << s;
  EXPECT_NE(s.message().find("has 3"), std::string::npos) << s;

  View nan_view = WallView(At(0, 0), 0.7, 0.0, &rng);
  // A sampled pixel (the stride is 4), at a new voxel so a partial update would show.
  nan_view.probabilities[1].at<float>(100, 148) = std::nanf("");
  nan_view.depth.at<float>(100, 148) = 1.0f;
  s = map->Fuse(nan_view.depth, Camera(), At(0, 0), nan_view.probabilities).status();
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(s.message().find("pixel (148, 100)"), std::string::npos) << s;

  s = map->Fuse(view.depth, Camera(), At(5000, 0), view.probabilities).status();
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(s.message().find("outside the semantic octree"), std::string::npos) << s;
  EXPECT_EQ(map->Render(view.depth, Camera(), At(5000, 0), 1).status().code(),
            absl::StatusCode::kInvalidArgument);

  cv::Mat small(60, 80, CV_32FC1, cv::Scalar(1));
  EXPECT_EQ(map->Fuse(small, Camera(), At(0, 0), view.probabilities).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(map->Render(view.depth, Camera(), At(0, 0), 0).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(map->Serialize() == before) << "the refused inputs changed the tree";

  EXPECT_FALSE(SemanticMap::Create(1, {1.0}, {}).ok());
  EXPECT_FALSE(SemanticMap::Create(3, {1.0, 1.0}, {}).ok());
  SemanticMapOptions bad;
  bad.resolution_m = 0;
  EXPECT_FALSE(SemanticMap::Create(3, {1, 1, 1}, bad).ok());
}

TEST(SemanticMap, SnapshotRoundTripsAndRefusesDamage) {
  auto map = NewMap();
  std::mt19937 rng(5);
  for (int i = 0; i < 3; ++i) {
    const View view = WallView(At(0.03 * i, 0), 0.7, 0.1, &rng);
    ASSERT_TRUE(map->Fuse(view.depth, Camera(), At(0.03 * i, 0), view.probabilities).ok());
  }
  const std::string bytes = map->Serialize();
  auto copy = SemanticMap::Deserialize(bytes, SemanticMapOptions{});
  ASSERT_TRUE(copy.ok()) << copy.status();
  EXPECT_TRUE((*copy)->Serialize() == bytes);
  EXPECT_EQ((*copy)->Summarize().labelled_voxels, map->Summarize().labelled_voxels);
  EXPECT_EQ((*copy)->Summarize().keyframes, 3);

  std::string flipped = bytes;
  flipped[bytes.size() / 2] ^= 0x10;
  EXPECT_EQ(SemanticMap::Deserialize(flipped, {}).status().code(), absl::StatusCode::kDataLoss);
  EXPECT_EQ(SemanticMap::Deserialize(bytes.substr(0, bytes.size() - 9), {}).status().code(),
            absl::StatusCode::kDataLoss);
  EXPECT_EQ(SemanticMap::Deserialize("hello", {}).status().code(),
            absl::StatusCode::kInvalidArgument);
  std::string newer = bytes;
  newer[8] = 9;
  EXPECT_EQ(SemanticMap::Deserialize(newer, {}).status().code(),
            absl::StatusCode::kFailedPrecondition);
  SemanticMapOptions coarse;
  coarse.resolution_m = 0.1;
  EXPECT_EQ(SemanticMap::Deserialize(bytes, coarse).status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST(SemanticMap, OctomapReadsItsExports) {
  auto map = NewMap();
  std::mt19937 rng(1);
  const View view = WallView(At(0, 0), 0.8, 0.0, &rng);
  ASSERT_TRUE(map->Fuse(view.depth, Camera(), At(0, 0), view.probabilities).ok());
  const SemanticSummary summary = map->Summarize();

  std::istringstream bt(map->ToOctomapBinary());
  octomap::OcTree occupancy(0.1);
  ASSERT_TRUE(occupancy.readBinary(bt));
  EXPECT_DOUBLE_EQ(occupancy.getResolution(), 0.05);
  int64_t occupied = 0;
  for (auto it = occupancy.begin_leafs(); it != occupancy.end_leafs(); ++it) {
    if (occupancy.isNodeOccupied(*it)) occupied += std::llround(std::pow(it.getSize() / 0.05, 3));
  }
  EXPECT_EQ(occupied, summary.occupied_voxels);

  std::istringstream ot(map->ToOctomapColor({0x808080, 0xff0000, 0x0000ff}));
  std::unique_ptr<octomap::AbstractOcTree> tree(octomap::AbstractOcTree::read(ot));
  ASSERT_NE(tree, nullptr);
  auto* color = dynamic_cast<octomap::ColorOcTree*>(tree.get());
  ASSERT_NE(color, nullptr);
  const octomap::ColorOcTreeNode* left = color->search(-0.3, 0.0, 2.01);
  const octomap::ColorOcTreeNode* right = color->search(0.3, 0.0, 2.01);
  ASSERT_NE(left, nullptr);
  ASSERT_NE(right, nullptr);
  EXPECT_EQ(left->getColor(), octomap::ColorOcTreeNode::Color(255, 0, 0));
  EXPECT_EQ(right->getColor(), octomap::ColorOcTreeNode::Color(0, 0, 255));
  EXPECT_TRUE(color->isNodeOccupied(left));
}

TEST(SemanticMap, MergesAnotherMapMovedIntoItsFrame) {
  // Visit B saw the wall from a frame 1 m to the right of visit A's.
  auto a = NewMap();
  auto b = NewMap();
  std::mt19937 rng(1);
  const View view_a = WallView(At(0, 0), 0.8, 0.0, &rng);
  ASSERT_TRUE(a->Fuse(view_a.depth, Camera(), At(0, 0), view_a.probabilities).ok());
  const View view_b = WallView(At(1.0, 0), 0.8, 0.0, &rng);  // in A's frame
  ASSERT_TRUE(b->Fuse(view_b.depth, Camera(), At(0, 0), view_b.probabilities).ok());
  ASSERT_TRUE(a->Merge(*b, At(1.0, 0)).ok());
  double coverage = 0;
  EXPECT_GT(RenderedAccuracy(*a, At(1.0, 0), &coverage), 0.97);
  EXPECT_GT(coverage, 0.95);
  EXPECT_EQ(a->Summarize().keyframes, 2);

  auto other = SemanticMap::Create(4, {1, 1, 1, 1}, {});
  ASSERT_TRUE(other.ok());
  EXPECT_EQ(a->Merge(**other, At(0, 0)).code(), absl::StatusCode::kFailedPrecondition);
}

TEST(SemanticMap, MergingIntoAnEmptyMapCopiesTheBeliefs) {
  auto a = NewMap();
  std::mt19937 rng(3);
  const View view = WallView(At(0, 0), 0.7, 0.0, &rng);
  ASSERT_TRUE(a->Fuse(view.depth, Camera(), At(0, 0), view.probabilities).ok());
  auto empty = NewMap();
  ASSERT_TRUE(empty->Merge(*a, At(0, 0)).ok());
  const auto voxels = a->LabelledVoxels();
  ASSERT_FALSE(voxels.empty());
  for (const LabelledVoxel& v : voxels) {
    const std::vector<float> before = a->BeliefAt(v.x, v.y, v.z);
    const std::vector<float> after = empty->BeliefAt(v.x, v.y, v.z);
    ASSERT_EQ(after.size(), before.size());
    for (size_t c = 0; c < before.size(); ++c) EXPECT_NEAR(after[c], before[c], 1e-6);
  }
  EXPECT_EQ(empty->LabelledVoxels().size(), voxels.size());
}

TEST(SemanticMap, OneClassAloneForExport) {
  auto map = NewMap();
  std::mt19937 rng(5);
  const View view = WallView(At(0, 0), 0.8, 0.0, &rng);
  ASSERT_TRUE(map->Fuse(view.depth, Camera(), At(0, 0), view.probabilities).ok());
  const auto left = map->LabelledVoxels(1);
  const auto right = map->LabelledVoxels(2);
  ASSERT_FALSE(left.empty());
  ASSERT_FALSE(right.empty());
  const auto only_left = map->OnlyClass(1);
  EXPECT_EQ(only_left->LabelledVoxels().size(), left.size());
  EXPECT_TRUE(only_left->LabelledVoxels(2).empty());
  EXPECT_EQ(only_left->BeliefAt(left[0].x, left[0].y, left[0].z),
            map->BeliefAt(left[0].x, left[0].y, left[0].z));
  EXPECT_TRUE(only_left->BeliefAt(right[0].x, right[0].y, right[0].z).empty());
  // Its .bt holds the left half's voxels only, occupied.
  std::istringstream bt(only_left->ToOctomapBinary());
  octomap::OcTree tree(0.05);
  ASSERT_TRUE(tree.readBinary(bt));
  const octomap::OcTreeNode* node = tree.search(left[0].x, left[0].y, left[0].z);
  ASSERT_NE(node, nullptr);
  EXPECT_TRUE(tree.isNodeOccupied(node));
  EXPECT_EQ(tree.search(right[0].x, right[0].y, right[0].z), nullptr);
}

TEST(SemanticMap, LabelledVoxelsAsPly) {
  const std::vector<LabelledVoxel> voxels = {{1.0f, 2.0f, 3.0f, 0.05f, 2, 0.75f},
                                             {-1.0f, 0.5f, 2.0f, 0.1f, 9, 0.5f}};
  const std::string ply = LabelledVoxelsToPly(voxels, {0x000000, 0x112233, 0xff8000});
  const size_t body = ply.find("end_header\n");
  ASSERT_NE(body, std::string::npos);
  EXPECT_NE(ply.find("element vertex 2\n"), std::string::npos);
  const char* p = ply.data() + body + 11;
  ASSERT_EQ(ply.size() - (body + 11), 2u * 24u);
  float x = 0, confidence = 0, size = 0;
  std::memcpy(&x, p, 4);
  std::memcpy(&confidence, p + 16, 4);
  std::memcpy(&size, p + 20, 4);
  EXPECT_EQ(x, 1.0f);
  EXPECT_EQ(p[12], 2);
  EXPECT_EQ(static_cast<uint8_t>(p[13]), 0xff);
  EXPECT_EQ(static_cast<uint8_t>(p[14]), 0x80);
  EXPECT_EQ(confidence, 0.75f);
  EXPECT_EQ(size, 0.05f);
  // A class beyond the colours given is grey.
  EXPECT_EQ(static_cast<uint8_t>(p[24 + 13]), 0x80);
}

TEST(SemanticMap, RevisitingTheSameSceneDoesNotGrowTheTree) {
  auto map = NewMap();
  std::mt19937 rng(1);
  const View view = WallView(At(0, 0), 0.8, 0.0, &rng);
  // The free-space rays start at each quarter point of their cell in turn: after four
  // keyframes every ray of the view has been cast once.
  for (int i = 0; i < 4; ++i) {
    ASSERT_TRUE(map->Fuse(view.depth, Camera(), At(0, 0), view.probabilities).ok());
  }
  const int64_t nodes = map->Summarize().nodes;
  for (int i = 0; i < 20; ++i) {
    ASSERT_TRUE(map->Fuse(view.depth, Camera(), At(0, 0), view.probabilities).ok());
  }
  EXPECT_LE(map->Summarize().nodes, nodes);
}

}  // namespace
}  // namespace lifemap::semantic
