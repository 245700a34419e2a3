// The pose graph (issue 15): loops pull a drifted chain back onto the truth; a wrong loop is
// switched off instead of bending the map; bad graphs are refused with the reason.
#include "core/posegraph/pose_graph.h"

#include <cmath>
#include <random>

#include <gtest/gtest.h>

namespace lifemap::posegraph {
namespace {

Pose At(double x, double y, double yaw_rad) {
  Pose p;
  p.translation = {x, y, 0.0};
  p.rotation = Eigen::Quaterniond(Eigen::AngleAxisd(yaw_rad, Eigen::Vector3d::UnitZ()));
  return p;
}

Pose Compose(const Pose& a, const Pose& b) {
  return Pose::FromIsometry(a.ToIsometry() * b.ToIsometry());
}

// `n` keyframes on a circle of radius 2 m (one full turn and a quarter): the truth, and the
// chain of odometry edges between consecutive ones with a small heading bias per step, so the
// integrated chain drifts.
struct Circle {
  std::map<int64_t, Pose> truth;
  std::map<int64_t, Pose> drifted;
  std::vector<Edge> edges;
};

Circle MakeCircle(int n, double bias_rad_per_step) {
  Circle c;
  const int per_turn = n * 4 / 5;
  for (int i = 0; i < n; ++i) {
    const double a = 2 * M_PI * i / per_turn;
    c.truth[i] = At(2 * std::cos(a), 2 * std::sin(a), a + M_PI / 2);
  }
  c.drifted[0] = c.truth[0];
  for (int i = 1; i < n; ++i) {
    Pose step = Relative(c.truth[i - 1], c.truth[i]);
    const Pose bias = At(0, 0, bias_rad_per_step);
    step = Compose(step, bias);
    c.edges.push_back({i - 1, i, step, EdgeKind::kOdometry, 0.01, 0.005});
    c.drifted[i] = Compose(c.drifted[i - 1], step);
  }
  return c;
}

double MaxError(const std::map<int64_t, Pose>& a, const std::map<int64_t, Pose>& b) {
  double worst = 0;
  for (const auto& [id, p] : a)
    worst = std::max(worst, (p.translation - b.at(id).translation).norm());
  return worst;
}

TEST(PoseGraph, LoopsPullADriftedChainBackOntoTheTruth) {
  Circle c = MakeCircle(100, 0.004);
  const double drift = MaxError(c.drifted, c.truth);
  ASSERT_GT(drift, 0.3);
  // The last fifth revisits the first: loops from keyframe i+80 back to i, measured exactly.
  for (int i = 0; i < 20; i += 4) {
    c.edges.push_back(
        {i, i + 80, Relative(c.truth[i], c.truth[i + 80]), EdgeKind::kLoop, 0.03, 0.02});
  }
  auto r = Optimise(c.drifted, c.edges, {0});
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_TRUE(r->rejected.empty());
  EXPECT_LT(r->final_cost, r->initial_cost);
  // A steady heading bias cannot be undone, only spread along the chain: what is left is a
  // small fraction of the drift, and the loop's ends agree.
  EXPECT_LT(MaxError(r->poses, c.truth), 0.2 * drift);
  EXPECT_LT((r->poses.at(80).translation - r->poses.at(0).translation).norm(), 0.03);
  EXPECT_GT(r->max_correction_m, 0.3);
  EXPECT_EQ(r->poses.at(0).translation, c.drifted.at(0).translation);  // the gauge stays
}

TEST(PoseGraph, AWrongLoopIsSwitchedOffAndTheRightOnesStill) {
  Circle c = MakeCircle(100, 0.004);
  for (int i = 0; i < 20; i += 4) {
    c.edges.push_back(
        {i, i + 80, Relative(c.truth[i], c.truth[i + 80]), EdgeKind::kLoop, 0.03, 0.02});
  }
  // A perceptual alias: keyframe 50 (the far side of the circle) "matched" to keyframe 10 as if
  // it stood 0.5 m from it.
  const size_t wrong = c.edges.size();
  c.edges.push_back({10, 50, At(0.5, 0, 0.2), EdgeKind::kLoop, 0.03, 0.02});
  auto r = Optimise(c.drifted, c.edges, {0});
  ASSERT_TRUE(r.ok()) << r.status();
  ASSERT_EQ(r->rejected.size(), 1u);
  EXPECT_EQ(r->rejected[0], wrong);
  EXPECT_EQ(r->solves, 2);
  EXPECT_LT(MaxError(r->poses, c.truth), 0.2 * MaxError(c.drifted, c.truth));
}

TEST(PoseGraph, WithoutLoopsTheChainIsKept) {
  Circle c = MakeCircle(30, 0.004);
  auto r = Optimise(c.drifted, c.edges, {});
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_LT(MaxError(r->poses, c.drifted), 1e-6);
}

TEST(PoseGraph, EdgeChi2IsZeroWhereTheMeasurementHolds) {
  const Pose a = At(1, 2, 0.3), b = At(-1, 0.5, 2.0);
  const Edge e{1, 2, Relative(a, b), EdgeKind::kLoop, 0.01, 0.01};
  EXPECT_LT(EdgeChi2(e, a, b), 1e-12);
  // 1 cm off at sigma 1 cm: chi-square 1.
  Pose b_off = b;
  b_off.translation.z() += 0.01;
  EXPECT_NEAR(EdgeChi2(e, a, b_off), 1.0, 1e-6);
}

TEST(PoseGraph, BadGraphsAreRefusedWithTheReason) {
  std::map<int64_t, Pose> nodes{{1, At(0, 0, 0)}, {2, At(1, 0, 0)}};
  std::vector<Edge> to_unknown{{1, 3, At(1, 0, 0), EdgeKind::kOdometry, 0.01, 0.01}};
  auto r = Optimise(nodes, to_unknown, {});
  ASSERT_FALSE(r.ok());
  EXPECT_NE(r.status().message().find("not in the graph"), std::string::npos);
  std::vector<Edge> to_itself{{1, 1, At(0, 0, 0), EdgeKind::kOdometry, 0.01, 0.01}};
  EXPECT_FALSE(Optimise(nodes, to_itself, {}).ok());
  std::vector<Edge> no_sigma{{1, 2, At(1, 0, 0), EdgeKind::kOdometry, 0.0, 0.01}};
  EXPECT_FALSE(Optimise(nodes, no_sigma, {}).ok());
  std::map<int64_t, Pose> nan_node = nodes;
  nan_node[2].translation.x() = std::nan("");
  std::vector<Edge> fine{{1, 2, At(1, 0, 0), EdgeKind::kOdometry, 0.01, 0.01}};
  EXPECT_FALSE(Optimise(nan_node, fine, {}).ok());
  EXPECT_FALSE(Optimise(nodes, fine, {7}).ok());
  OptimiseOptions bad;
  bad.max_iterations = 0;
  EXPECT_FALSE(Optimise(nodes, fine, {}, bad).ok());
  EXPECT_TRUE(Optimise({}, {}, {}).ok());
}

}  // namespace
}  // namespace lifemap::posegraph
