// Research tool (issue 15): re-solves a stored visit's pose graph (its keyframes' odometry poses
// and accepted loop edges, read from a lifemap database) with other settings, and scores each
// against a TUM ground truth. Usage:
//   posegraph_replay DB MAP_ID VISIT_ID TUM_DIR
#include <cstdlib>
#include <iostream>

#include "core/eval/trajectory.h"
#include "core/io/tum_dataset.h"
#include "core/posegraph/pose_graph.h"
#include "server/store/store.h"

using namespace lifemap;

int main(int argc, char** argv) {
  if (argc != 5) {
    std::cerr << "usage: posegraph_replay DB MAP_ID VISIT_ID TUM_DIR\n";
    return 2;
  }
  auto store = store::Store::Open(argv[1]);
  if (!store.ok()) {
    std::cerr << store.status() << "\n";
    return 1;
  }
  const int64_t map_id = std::atoll(argv[2]), visit_id = std::atoll(argv[3]);
  auto keyframes = (*store)->ListKeyframes(map_id, visit_id);
  auto edges = (*store)->ListPoseEdges(map_id, visit_id);
  if (!keyframes.ok() || !edges.ok()) return 1;
  auto seq = io::ReadTumSequence(argv[4]);
  if (!seq.ok()) {
    std::cerr << seq.status() << "\n";
    return 1;
  }
  const std::vector<eval::TimedPose> truth = eval::GroundTruth(*seq);
  std::sort(keyframes->begin(), keyframes->end(),
            [](const auto& a, const auto& b) { return a.id < b.id; });
  std::map<int64_t, Pose> odom;
  std::map<int64_t, double> time;
  std::vector<const store::KeyframeRecord*> nodes;
  for (const auto& k : *keyframes) {
    if (!k.T_odom_camera) continue;
    nodes.push_back(&k);
    odom[k.id] = *k.T_odom_camera;
    time[k.id] = k.timestamp_s;
  }
  auto score = [&](const std::map<int64_t, Pose>& poses) {
    std::vector<eval::TimedPose> est;
    for (const auto& [id, p] : poses) est.push_back({time[id], p});
    auto e = eval::CompareTrajectories(est, truth);
    return e.ok() ? e->ate_rmse_m * 1000 : -1.0;
  };
  std::cout << "odometry alone: ATE " << score(odom) << " mm\n";
  for (double odo_scale : {0.0, 1.0, 2.0, 4.0}) {
    for (double odo_k : {0.02, 0.05}) {
      std::vector<posegraph::Edge> graph;
      for (size_t i = 1; i < nodes.size(); ++i) {
        posegraph::Edge e;
        e.from = nodes[i - 1]->id;
        e.to = nodes[i]->id;
        e.T_from_to = posegraph::Relative(odom[e.from], odom[e.to]);
        const double d = e.T_from_to.translation.norm();
        const double a = Eigen::AngleAxisd(e.T_from_to.rotation).angle();
        e.sigma_m = 0.003 + odo_k * d;
        e.sigma_rad = 0.002 + odo_k * a + 0.01 * d;
        graph.push_back(e);
      }
      int loops = 0;
      for (const auto& l : *edges) {
        if (!l.accepted && l.reason.find("outvoted") == std::string::npos) continue;
        if (!odom.count(l.from_keyframe) || !odom.count(l.to_keyframe)) continue;
        graph.push_back(
            {l.from_keyframe, l.to_keyframe, l.T_from_to, posegraph::EdgeKind::kLoop, 0.02, 0.01});
        ++loops;
      }
      posegraph::OptimiseOptions o;
      o.odometry_robust_scale = odo_scale;
      auto r = posegraph::Optimise(odom, graph, {nodes.front()->id}, o);
      if (!r.ok()) {
        std::cerr << r.status() << "\n";
        continue;
      }
      std::cout << "odometry robust " << odo_scale << ", sigma per m " << odo_k << ": " << loops
                << " loops, " << r->rejected.size() << " rejected, ATE " << score(r->poses)
                << " mm, " << r->solve_ms << " ms\n";
    }
  }
}
