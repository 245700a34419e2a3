// Trajectory accuracy in the TUM RGB-D benchmark's convention (Sturm et al. 2012): estimated
// poses are associated with ground truth by timestamp, aligned by one rigid transform (no
// scale: RGB-D is metric), and scored by the absolute trajectory error (ATE, RMSE of the
// positions) and the relative pose error over a time step (RPE: the drift per second).
#pragma once

#include <vector>

#include <Eigen/Geometry>

#include "absl/status/statusor.h"
#include "core/common/types.h"
#include "core/io/tum_dataset.h"

namespace lifemap::eval {

using io::TimedPose;

struct TrajectoryErrors {
  int associated = 0;       // estimated poses with a ground-truth pose within max_dt_s
  double ate_rmse_m = 0.0;  // after the rigid alignment
  double ate_max_m = 0.0;
  double rpe_trans_m = 0.0;  // RMSE over pairs `rpe_delta_s` apart (or the longest span there is)
  double rpe_rot_deg = 0.0;
  double rpe_delta_s = 0.0;                                            // the step the RPE used
  Eigen::Isometry3d T_truth_estimate = Eigen::Isometry3d::Identity();  // the alignment
  std::vector<double> position_errors_m;  // per associated pose, in estimate order
};

// A recording's ground truth: its frames that have a ground-truth pose, in frame order.
std::vector<TimedPose> GroundTruth(const io::TumSequence& sequence);

// InvalidArgument with fewer than 3 associated poses (no alignment is defined).
absl::StatusOr<TrajectoryErrors> CompareTrajectories(const std::vector<TimedPose>& estimate,
                                                     const std::vector<TimedPose>& truth,
                                                     double max_dt_s = 0.02,
                                                     double rpe_delta_s = 1.0);

}  // namespace lifemap::eval
