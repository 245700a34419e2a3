#include "core/eval/trajectory.h"

#include <algorithm>
#include <cmath>

#include <Eigen/Geometry>

#include "absl/strings/str_cat.h"

namespace lifemap::eval {
namespace {

// The ground-truth pose nearest in time, if within max_dt_s. `truth` is sorted by time.
const TimedPose* Nearest(const std::vector<TimedPose>& truth, double t, double max_dt_s) {
  auto it = std::lower_bound(truth.begin(), truth.end(), t,
                             [](const TimedPose& p, double v) { return p.timestamp_s < v; });
  const TimedPose* best = nullptr;
  if (it != truth.end()) best = &*it;
  if (it != truth.begin()) {
    const TimedPose* before = &*(it - 1);
    if (best == nullptr || t - before->timestamp_s < best->timestamp_s - t) best = before;
  }
  if (best == nullptr || std::abs(best->timestamp_s - t) > max_dt_s) return nullptr;
  return best;
}

}  // namespace

std::vector<TimedPose> GroundTruth(const io::TumSequence& sequence) {
  std::vector<TimedPose> truth;
  for (const auto& f : sequence.frames) {
    if (f.T_world_camera) truth.push_back({f.timestamp_s, *f.T_world_camera});
  }
  return truth;
}

absl::StatusOr<TrajectoryErrors> CompareTrajectories(const std::vector<TimedPose>& estimate,
                                                     const std::vector<TimedPose>& truth,
                                                     double max_dt_s, double rpe_delta_s) {
  std::vector<TimedPose> sorted_truth = truth;
  std::sort(sorted_truth.begin(), sorted_truth.end(),
            [](const TimedPose& a, const TimedPose& b) { return a.timestamp_s < b.timestamp_s; });
  std::vector<const TimedPose*> est, gt;
  for (const TimedPose& e : estimate) {
    if (const TimedPose* g = Nearest(sorted_truth, e.timestamp_s, max_dt_s)) {
      est.push_back(&e);
      gt.push_back(g);
    }
  }
  if (est.size() < 3) {
    return absl::InvalidArgumentError(
        absl::StrCat("only ", est.size(), " of ", estimate.size(),
                     " estimated poses have a ground-truth pose within ", max_dt_s,
                     " s; at least 3 are needed to align the trajectories"));
  }
  const int n = static_cast<int>(est.size());
  Eigen::Matrix3Xd src(3, n), dst(3, n);
  for (int i = 0; i < n; ++i) {
    src.col(i) = est[static_cast<size_t>(i)]->pose.translation;
    dst.col(i) = gt[static_cast<size_t>(i)]->pose.translation;
  }
  TrajectoryErrors out;
  out.associated = n;
  // Horn/Umeyama without scale: RGB-D odometry is metric.
  out.T_truth_estimate.matrix() = Eigen::umeyama(src, dst, /*with_scaling=*/false);
  double sum_sq = 0.0;
  for (int i = 0; i < n; ++i) {
    const double e = (out.T_truth_estimate * src.col(i) - dst.col(i)).norm();
    out.position_errors_m.push_back(e);
    sum_sq += e * e;
    out.ate_max_m = std::max(out.ate_max_m, e);
  }
  out.ate_rmse_m = std::sqrt(sum_sq / n);

  // RPE: each pose against the first one at least rpe_delta_s later; a trajectory shorter than
  // that uses its whole span once.
  const double span = est.back()->timestamp_s - est.front()->timestamp_s;
  out.rpe_delta_s = std::min(rpe_delta_s, span);
  double trans_sq = 0.0, rot_sq = 0.0;
  int pairs = 0;
  for (int i = 0; i < n; ++i) {
    int j = i + 1;
    while (j < n &&
           est[static_cast<size_t>(j)]->timestamp_s - est[static_cast<size_t>(i)]->timestamp_s <
               out.rpe_delta_s - 1e-9) {
      ++j;
    }
    if (j >= n) break;
    const Eigen::Isometry3d E_est = est[static_cast<size_t>(i)]->pose.ToIsometry().inverse() *
                                    est[static_cast<size_t>(j)]->pose.ToIsometry();
    const Eigen::Isometry3d E_gt = gt[static_cast<size_t>(i)]->pose.ToIsometry().inverse() *
                                   gt[static_cast<size_t>(j)]->pose.ToIsometry();
    const Eigen::Isometry3d error = E_gt.inverse() * E_est;
    trans_sq += error.translation().squaredNorm();
    const double angle = Eigen::AngleAxisd(error.rotation()).angle() * 180.0 / M_PI;
    rot_sq += angle * angle;
    ++pairs;
  }
  if (pairs > 0) {
    out.rpe_trans_m = std::sqrt(trans_sq / pairs);
    out.rpe_rot_deg = std::sqrt(rot_sq / pairs);
  }
  return out;
}

}  // namespace lifemap::eval
