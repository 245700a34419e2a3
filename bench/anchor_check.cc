// Research tool (issue 15): how well a tracked visit was anchored into its map's frame, against
// ground truth in one world frame (synthetic visits of one place). The reference visit's stored
// keyframes and the anchored visit's (both in the map's frame once anchored) are each aligned
// rigidly to their ground truth; if the anchor were exact, and each visit's own trajectory
// too, the two alignments would be the same: their difference is the anchoring error.
// Usage: anchor_check DB MAP_ID REF_VISIT REF_TUM_DIR VISIT TUM_DIR
#include <cmath>
#include <cstdlib>
#include <iostream>

#include "core/eval/trajectory.h"
#include "core/io/tum_dataset.h"
#include "server/store/store.h"

using namespace lifemap;

int main(int argc, char** argv) {
  if (argc != 7) {
    std::cerr << "usage: anchor_check DB MAP_ID REF_VISIT REF_TUM_DIR VISIT TUM_DIR\n";
    return 2;
  }
  auto store = store::Store::Open(argv[1]);
  if (!store.ok()) {
    std::cerr << store.status() << "\n";
    return 1;
  }
  const int64_t map_id = std::atoll(argv[2]);
  Eigen::Isometry3d align[2];
  for (int i = 0; i < 2; ++i) {
    auto keyframes = (*store)->ListKeyframes(map_id, std::atoll(argv[3 + 2 * i]));
    if (!keyframes.ok()) return 1;
    std::vector<eval::TimedPose> est;
    for (const auto& k : *keyframes) {
      if (k.T_world_camera) est.push_back({k.timestamp_s, *k.T_world_camera});
    }
    auto seq = io::ReadTumSequence(argv[4 + 2 * i]);
    if (!seq.ok()) {
      std::cerr << seq.status() << "\n";
      return 1;
    }
    auto e = eval::CompareTrajectories(est, eval::GroundTruth(*seq));
    if (!e.ok()) {
      std::cerr << e.status() << "\n";
      return 1;
    }
    align[i] = e->T_truth_estimate;
    std::cout << (i == 0 ? "reference" : "anchored") << " visit: ATE " << e->ate_rmse_m * 1000
              << " mm over " << e->associated << " keyframes\n";
  }
  const Eigen::Isometry3d diff = align[0].inverse() * align[1];
  std::cout << "anchoring error: " << diff.translation().norm() * 100 << " cm, "
            << Eigen::AngleAxisd(diff.rotation()).angle() * 180 / M_PI << " deg\n";
}
