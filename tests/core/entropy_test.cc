// Normals, superjuts and neg-entropy scores on analytic scenes rendered by ray casting.
#include <cmath>
#include <random>

#include <gtest/gtest.h>

#include "core/entropy/sphere_bins.h"
#include "core/entropy/superjut_scores.h"
#include "core/normals/normals.h"
#include "core/segmentation/superjuts.h"

namespace lifemap {
namespace {

const CameraIntrinsics kCamera{320, 320, 159.5, 119.5, 320, 240};

// A scene of a plane and optional objects, in camera coordinates (x right, y down, z ahead).
struct Scene {
  Eigen::Vector3f plane_normal{0, 0, -1};  // plane n . X = d, normal towards the camera
  float plane_d = -2.0f;                   // default: the wall z = 2
  bool has_box = false;
  Eigen::Vector3f box_min, box_max;  // axis-aligned in camera coordinates
  bool has_sphere = false;
  Eigen::Vector3f sphere_center;
  float sphere_radius = 0;

  // Depth (metres along z) of the first surface hit at pixel (u, v), 0 if none.
  float DepthAt(int u, int v) const {
    const Eigen::Vector3f ray((u - kCamera.cx) / kCamera.fx, (v - kCamera.cy) / kCamera.fy, 1);
    float best = 1e9f;
    const float denom = plane_normal.dot(ray);
    if (std::abs(denom) > 1e-6f) {
      const float t = plane_d / denom;
      if (t > 0) best = t;
    }
    if (has_box) {
      float t0 = 0, t1 = 1e9f;
      for (int a = 0; a < 3; ++a) {
        float near = (box_min[a] - 0) / ray[a], far = (box_max[a] - 0) / ray[a];
        if (near > far) std::swap(near, far);
        t0 = std::max(t0, near);
        t1 = std::min(t1, far);
      }
      if (t0 <= t1 && t0 > 0) best = std::min(best, t0);
    }
    if (has_sphere) {
      const float b = ray.dot(sphere_center),
                  c = sphere_center.squaredNorm() - sphere_radius * sphere_radius;
      const float a = ray.squaredNorm(), disc = b * b - a * c;
      if (disc >= 0) best = std::min(best, (b - std::sqrt(disc)) / a);
    }
    return best < 1e8f ? best : 0.0f;  // t along a ray with z = 1 is the depth
  }

  cv::Mat Render() const {
    cv::Mat depth(kCamera.height, kCamera.width, CV_32FC1);
    for (int v = 0; v < depth.rows; ++v) {
      for (int u = 0; u < depth.cols; ++u) depth.at<float>(v, u) = DepthAt(u, v);
    }
    return depth;
  }
};

struct Analysis {
  normals::NormalMap normals;
  segmentation::Superjuts superjuts;
  std::vector<entropy::SuperjutScore> scores;
};

Analysis Analyse(const cv::Mat& depth, bool mesh = false) {
  Analysis a;
  normals::NormalOptions normal_options;
  segmentation::SuperjutOptions superjut_options;
  if (mesh) {
    normal_options.method = normals::NormalMethod::kMeshVertex;
    superjut_options.graph = segmentation::SuperjutGraph::kMesh;
  }
  auto n = normals::ComputeNormals(depth, kCamera, normal_options);
  EXPECT_TRUE(n.ok()) << n.status();
  a.normals = *n;
  auto s = segmentation::SegmentSuperjuts(a.normals, superjut_options);
  EXPECT_TRUE(s.ok()) << s.status();
  a.superjuts = *s;
  auto sc = entropy::ScoreSuperjuts(a.superjuts, a.normals, cv::Mat(), {0, -1, 0});
  EXPECT_TRUE(sc.ok()) << sc.status();
  a.scores = *sc;
  return a;
}

TEST(Normals, FrontoParallelWallFacesTheCamera) {
  Scene wall;
  const cv::Mat depth = wall.Render();
  auto n = normals::ComputeNormals(depth, kCamera);
  ASSERT_TRUE(n.ok());
  const cv::Vec3f normal = n->normals.at<cv::Vec3f>(120, 160);
  EXPECT_NEAR(normal[2], -1.0f, 1e-4);
  EXPECT_EQ(n->valid_normals, 320 * 240);
}

TEST(Normals, TiltedFloorPointsUp) {
  Scene floor;
  floor.plane_normal = Eigen::Vector3f(0, -1, -0.3f).normalized();      // up (-y), towards camera
  floor.plane_d = floor.plane_normal.dot(Eigen::Vector3f(0, 1.0f, 0));  // 1 m below the camera
  auto n = normals::ComputeNormals(floor.Render(), kCamera);
  ASSERT_TRUE(n.ok());
  const cv::Vec3f normal = n->normals.at<cv::Vec3f>(200, 160);
  EXPECT_NEAR(normal[0], floor.plane_normal.x(), 1e-3);
  EXPECT_NEAR(normal[1], floor.plane_normal.y(), 1e-3);
  EXPECT_NEAR(normal[2], floor.plane_normal.z(), 1e-3);
}

TEST(Normals, RejectsDepthWithoutReadingsAndBadInput) {
  cv::Mat none(240, 320, CV_32FC1, cv::Scalar(0.0f));
  EXPECT_TRUE(absl::IsFailedPrecondition(normals::ComputeNormals(none, kCamera).status()));
  cv::Mat nan(240, 320, CV_32FC1, cv::Scalar(std::nanf("")));
  EXPECT_TRUE(absl::IsFailedPrecondition(normals::ComputeNormals(nan, kCamera).status()));
  EXPECT_TRUE(absl::IsInvalidArgument(
      normals::ComputeNormals(cv::Mat(10, 10, CV_32FC1, cv::Scalar(1.0f)), kCamera).status()));
  EXPECT_TRUE(absl::IsInvalidArgument(
      normals::ComputeNormals(cv::Mat(240, 320, CV_16UC1), kCamera).status()));
  normals::NormalOptions bad;
  bad.neighbor_step_px = 0;
  EXPECT_TRUE(
      absl::IsInvalidArgument(normals::ComputeNormals(Scene().Render(), kCamera, bad).status()));
}

TEST(Normals, NaNReadingsCountAsMissing) {
  cv::Mat depth = Scene().Render();
  depth.at<float>(100, 100) = std::nanf("");
  auto n = normals::ComputeNormals(depth, kCamera);
  ASSERT_TRUE(n.ok());
  EXPECT_EQ(n->points.at<cv::Vec3f>(100, 100), cv::Vec3f(0, 0, 0));
  for (int r = 0; r < depth.rows; ++r) {
    for (int c = 0; c < depth.cols; ++c) {
      const cv::Vec3f v = n->normals.at<cv::Vec3f>(r, c);
      ASSERT_TRUE(std::isfinite(v[0]) && std::isfinite(v[1]) && std::isfinite(v[2]));
    }
  }
}

TEST(Superjuts, APlaneIsOneSuperjutWithEntropyNearZero) {
  const Analysis a = Analyse(Scene().Render());
  ASSERT_EQ(a.superjuts.count(), 1);
  EXPECT_LT(a.scores[0].entropy, 0.05f);
  EXPECT_GT(a.scores[0].neg_entropy, 0.98f);
  EXPECT_GT(a.scores[0].planarity, 0.99f);
  EXPECT_LT(a.scores[0].horizontality, 0.05f) << "a wall is vertical";
}

// A box standing on a floor seen obliquely: its front face meets the floor at a concave edge
// with continuous depth; the box must still be cut from the floor there.
TEST(Superjuts, SplitsBoxFromFloorAtConcaveEdge) {
  Scene s;
  s.plane_normal = Eigen::Vector3f(0, -1, 0);  // floor 0.6 m below the camera: y = 0.6
  s.plane_d = -0.6f;
  s.has_box = true;
  s.box_min = {-0.15f, 0.3f, 2.0f};  // 30 cm high, resting on the floor 2 m ahead
  s.box_max = {0.15f, 0.6f, 2.3f};
  const cv::Mat depth = s.Render();
  const Analysis a = Analyse(depth);
  // A pixel on the box's front face and one on the floor just in front of it.
  int front_row = -1, floor_row = -1;
  for (int v = 120; v < 240; ++v) {
    const float z = depth.at<float>(v, 160);
    if (front_row < 0 && std::abs(z - 2.0f) < 1e-3f) front_row = v;
    if (front_row >= 0 && z < 2.0f - 0.02f) {
      floor_row = v;
      break;
    }
  }
  ASSERT_GE(front_row, 0);
  ASSERT_GE(floor_row, 0);
  const int box_label = a.superjuts.labels.at<int>(front_row + 5, 160);
  const int floor_label = a.superjuts.labels.at<int>(floor_row + 5, 160);
  ASSERT_GE(box_label, 0);
  ASSERT_GE(floor_label, 0);
  EXPECT_NE(box_label, floor_label);
  EXPECT_GT(a.scores[floor_label].horizontality, 0.95f) << "the floor is horizontal";
  EXPECT_LT(a.scores[box_label].horizontality, 0.05f) << "the box's front face is vertical";
  // Without the concave edge there would be nothing to cut: the floor far from the box is one
  // superjut with the floor near it.
  EXPECT_EQ(a.superjuts.labels.at<int>(235, 20), floor_label);
}

TEST(Superjuts, ASphereHasHighEntropy) {
  Scene s;
  s.has_sphere = true;
  s.sphere_center = {0, 0, 1.2f};
  s.sphere_radius = 0.35f;
  const Analysis a = Analyse(s.Render());
  const int sphere = a.superjuts.labels.at<int>(120, 160);
  const int wall = a.superjuts.labels.at<int>(5, 5);
  ASSERT_NE(sphere, wall);
  EXPECT_GT(a.scores[sphere].entropy, 2.0f) << "normals spread over many bins";
  EXPECT_LT(a.scores[sphere].neg_entropy, 0.6f);
  EXPECT_GT(a.scores[wall].neg_entropy, 0.95f);
  const cv::Mat mask = entropy::EntropyMask(a.superjuts, a.scores, 0.8f);
  EXPECT_EQ(mask.at<unsigned char>(120, 160), 255) << "the sphere is masked";
  EXPECT_EQ(mask.at<unsigned char>(5, 5), 0) << "the wall is kept";
  const cv::Mat score = entropy::NegEntropyImage(a.superjuts, a.scores);
  EXPECT_LT(score.at<unsigned char>(120, 160), score.at<unsigned char>(5, 5));
}

// The paper's mesh variant (vertex normals averaged over the organized mesh's triangles, edges
// between vertices sharing a triangle) behaves the same on the analytic scenes.
TEST(MeshSuperjuts, PlaneBoxAndSphere) {
  const Analysis plane = Analyse(Scene().Render(), true);
  ASSERT_EQ(plane.superjuts.count(), 1);
  EXPECT_GT(plane.scores[0].neg_entropy, 0.98f);

  Scene s;
  s.plane_normal = Eigen::Vector3f(0, -1, 0);
  s.plane_d = -0.6f;
  s.has_box = true;
  s.box_min = {-0.15f, 0.3f, 2.0f};
  s.box_max = {0.15f, 0.6f, 2.3f};
  const cv::Mat depth = s.Render();
  const Analysis box = Analyse(depth, true);
  int front_row = -1;
  for (int v = 120; v < 240 && front_row < 0; ++v) {
    if (std::abs(depth.at<float>(v, 160) - 2.0f) < 1e-3f) front_row = v;
  }
  ASSERT_GE(front_row, 0);
  EXPECT_NE(box.superjuts.labels.at<int>(front_row + 5, 160),
            box.superjuts.labels.at<int>(235, 160))
      << "box front face and floor are separate superjuts";

  Scene ball;
  ball.has_sphere = true;
  ball.sphere_center = {0, 0, 1.2f};
  ball.sphere_radius = 0.35f;
  const Analysis sphere = Analyse(ball.Render(), true);
  const int id = sphere.superjuts.labels.at<int>(120, 160);
  ASSERT_GE(id, 0);
  EXPECT_LT(sphere.scores[id].neg_entropy, 0.6f);
}

TEST(Normals, MeshVertexNormalOfAPlaneMatchesEq2) {
  Scene floor;
  floor.plane_normal = Eigen::Vector3f(0, -1, -0.3f).normalized();
  floor.plane_d = floor.plane_normal.dot(Eigen::Vector3f(0, 1.0f, 0));
  normals::NormalOptions mesh;
  mesh.method = normals::NormalMethod::kMeshVertex;
  auto n = normals::ComputeNormals(floor.Render(), kCamera, mesh);
  ASSERT_TRUE(n.ok());
  const cv::Vec3f normal = n->normals.at<cv::Vec3f>(200, 160);
  EXPECT_NEAR(normal[1], floor.plane_normal.y(), 1e-3);
  EXPECT_NEAR(normal[2], floor.plane_normal.z(), 1e-3);
}

TEST(Superjuts, RejectsBadOptions) {
  const Analysis a = Analyse(Scene().Render());
  segmentation::SuperjutOptions bad;
  bad.k = 0;
  EXPECT_TRUE(absl::IsInvalidArgument(segmentation::SegmentSuperjuts(a.normals, bad).status()));
  EXPECT_TRUE(
      absl::IsInvalidArgument(segmentation::SegmentSuperjuts(normals::NormalMap{}, {}).status()));
}

TEST(SphereBins, GoldenSpiralCellsHaveNearlyEqualArea) {
  const entropy::SphereBins bins(80);
  std::mt19937 rng(7);
  std::normal_distribution<float> g;
  std::vector<int> count(80, 0);
  int lut_agrees = 0;
  constexpr int kSamples = 400000;
  for (int i = 0; i < kSamples; ++i) {
    const Eigen::Vector3f n = Eigen::Vector3f(g(rng), g(rng), g(rng)).normalized();
    const int exact = bins.BinExact(n);
    ++count[exact];
    lut_agrees += bins.Bin(n.x(), n.y(), n.z()) == exact;
  }
  const float mean = kSamples / 80.0f;
  for (int b = 0; b < 80; ++b) {
    EXPECT_NEAR(count[b] / mean, 1.0f, 0.2f) << "bin " << b;
  }
  EXPECT_GT(lut_agrees, kSamples * 0.97) << "the lookup table matches the exact binning";
}

TEST(EigenTransform, TexturedPatchScoresHigherThanFlatOne) {
  cv::Mat gray(64, 64, CV_8UC1, cv::Scalar(128));
  cv::Mat noise(64, 32, CV_8UC1);
  cv::randu(noise, 0, 255);
  noise.copyTo(gray(cv::Rect(32, 0, 32, 64)));
  const cv::Mat grid = entropy::EigenTransformGrid(gray, 16, 16);
  EXPECT_LT(grid.at<float>(2, 0), 0.01f);
  EXPECT_GT(grid.at<float>(2, 3), 0.05f);
  EXPECT_LE(grid.at<float>(2, 3), 1.0f);
}

}  // namespace
}  // namespace lifemap
