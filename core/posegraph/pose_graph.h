// A pose graph over keyframes (issue 15): relative-pose measurements between keyframes
// (odometry between consecutive ones, loop closures and visit anchors from verified appearance
// matches) and the keyframe poses that agree best with them, by non-linear least squares on
// SE(3) (Ceres). Loop and anchor edges carry a robust (Cauchy) loss, and those that still
// disagree with the rest after optimisation are switched off and the graph solved again: a wrong
// loop closure bends a map for good, so an edge that the others outvote is dropped, not averaged.
#pragma once

#include <cstdint>
#include <map>
#include <set>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/types.h"

namespace lifemap::posegraph {

enum class EdgeKind {
  kOdometry,  // consecutive keyframes of a visit, from the tracker: trusted, no robust loss
  kLoop,      // a verified appearance match within a visit
  kAnchor,    // a verified appearance match to another visit of the map
};

// "odometry", "loop", "anchor".
const char* EdgeKindName(EdgeKind kind);

// One measurement: the pose of keyframe `to` in the camera frame of keyframe `from`, with its
// standard deviations (per axis, metres and radians).
struct Edge {
  int64_t from = 0;
  int64_t to = 0;
  Pose T_from_to;
  EdgeKind kind = EdgeKind::kOdometry;
  double sigma_m = 0.01;
  double sigma_rad = 0.01;
};

struct OptimiseOptions {
  int max_iterations = 100;  // Levenberg–Marquardt iterations per solve, [1, 1000]
  // The robust loss of loop and anchor edges: whitened residuals (in sigmas) up to about this
  // count fully, larger ones less and less (Cauchy), > 0.
  double robust_scale = 2.0;
  // Odometry edges get a Cauchy loss of this scale too when > 0 (0: plain least squares), so
  // that one bad odometry step can take a loop's correction instead of the whole chain bending.
  double odometry_robust_scale = 0.0;
  // After a solve, a loop or anchor edge whose whitened squared residual exceeds this is
  // switched off and the graph solved again (at most `max_rejection_rounds` times); 22.5 is the
  // 99.9 % point of chi-square with 6 degrees of freedom. > 0.
  double outlier_chi2 = 22.5;
  int max_rejection_rounds = 3;  // [0, 10]
  int threads = 1;               // Ceres' threads, [1, 64]

  absl::Status Validate() const;
};

struct OptimiseResult {
  std::map<int64_t, Pose> poses;  // every node's optimised pose, T_world_keyframe
  std::vector<size_t> rejected;   // indices into the edges of loop/anchor edges switched off
  int iterations = 0;             // over every solve
  int solves = 0;
  double initial_cost = 0;  // Ceres' cost (half the sum of squared whitened residuals)
  double final_cost = 0;
  double solve_ms = 0;
  double max_correction_m = 0;  // largest translation of any node between input and output
  bool converged = false;       // the last solve converged (not stopped by its iteration limit)
  std::string report;           // Ceres' brief report of the last solve
};

// Optimises `initial` (every node's starting pose, T_world_keyframe) against `edges`. Nodes in
// `fixed` keep their poses (the gauge); with none, the smallest id is fixed. InvalidArgument
// for an edge naming an unknown node, an edge from a node to itself, non-finite poses or
// non-positive sigmas; an empty graph returns `initial` unchanged.
absl::StatusOr<OptimiseResult> Optimise(const std::map<int64_t, Pose>& initial,
                                        const std::vector<Edge>& edges,
                                        const std::set<int64_t>& fixed,
                                        const OptimiseOptions& options = {});

// The relative pose T_a^-1 * T_b (b in a's frame).
Pose Relative(const Pose& a, const Pose& b);

// The whitened squared residual of `edge` at poses `a` (its from) and `b` (its to): 0 when they
// agree exactly with the measurement.
double EdgeChi2(const Edge& edge, const Pose& a, const Pose& b);

}  // namespace lifemap::posegraph
