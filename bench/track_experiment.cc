#include <cstdlib>
#include <iostream>
#include <opencv2/imgcodecs.hpp>
#include <optional>
#include "core/eval/trajectory.h"
#include "core/io/tum_dataset.h"
#include "core/tracking/keyframe_selector.h"
#include "core/tracking/odometry.h"
using namespace lifemap;
int main(int argc, char** argv) {
  auto seq = io::ReadTumSequence(argv[1]);
  tracking::OdometryOptions o;
  o.downscale = std::atoi(argv[2]);
  if (getenv("JUMP_M")) o.max_jump_m = std::atof(getenv("JUMP_M"));
  if (getenv("JUMP_RAD")) o.max_jump_rad = std::atof(getenv("JUMP_RAD"));
  if (getenv("MIN_GRAD")) o.min_gradient = static_cast<float>(std::atof(getenv("MIN_GRAD")));
  if (getenv("FEAT")) o.feature_keypoints = std::atoi(getenv("FEAT"));
  if (getenv("FEAT_INLIERS")) o.feature_min_inliers = std::atoi(getenv("FEAT_INLIERS"));
  if (getenv("CHECK_SPEED")) o.feature_check_speed_mps = std::atof(getenv("CHECK_SPEED"));
  if (getenv("CHECK_TURN")) o.feature_check_turn_dps = std::atof(getenv("CHECK_TURN"));
  if (getenv("FEAT_AGREE_M")) o.feature_agree_m = std::atof(getenv("FEAT_AGREE_M"));
  if (getenv("HOLE_MARGIN")) o.hole_margin = std::atoi(getenv("HOLE_MARGIN"));
  if (getenv("PRIOR_SHARE")) o.prior_share = std::atof(getenv("PRIOR_SHARE"));
  const int stripe = getenv("STRIPE") ? std::atoi(getenv("STRIPE")) : 0;
  int methods[6] = {0, 0, 0, 0, 0, 0};
  int limit = argc > 3 ? std::atoi(argv[3]) : 100000;
  tracking::Tracker tracker(o);
  tracking::KeyframeSelector selector;
  std::vector<eval::TimedPose> est, truth;
  int lost = 0, kf = 0, n = 0;
  const bool verbose = getenv("VERBOSE") != nullptr;
  std::optional<Pose> last_est, last_truth;
  for (const auto& e : seq->frames) {
    if (n++ >= limit) break;
    auto f = io::DecodeTumFrame(*seq, e);
    if (argc > 4 && std::atoi(argv[4]) > 0) {
      std::vector<uchar> buf;
      cv::imencode(".jpg", f->color_bgr, buf, {cv::IMWRITE_JPEG_QUALITY, std::atoi(argv[4])});
      f->color_bgr = cv::imdecode(buf, cv::IMREAD_COLOR);
    }
    if (stripe > 0) {
      // Something close without depth, fixed in the image: dark, no depth, a stripe on the left.
      f->color_bgr.colRange(0, stripe).setTo(cv::Scalar(20, 20, 30));
      f->depth_m.colRange(0, stripe).setTo(0);
    }
    if (getenv("ODOM") && e.T_odom_camera) f->odometry = OdometryReading{*e.T_odom_camera, {}};
    auto t = tracker.Track(*f);
    if (e.T_world_camera) truth.push_back({e.timestamp_s, *e.T_world_camera});
    if (!t.T_world_camera) {
      ++lost;
      if (verbose) std::cout << "frame " << n - 1 << " lost: " << t.reason << "\n";
      continue;
    }
    est.push_back({e.timestamp_s, *t.T_world_camera});
    ++methods[static_cast<int>(t.method)];
    if (verbose && static_cast<int>(t.method) >= 2)
      std::cout << "frame " << n - 1 << " method " << static_cast<int>(t.method) << "\n";
    if (verbose && last_est && last_truth && e.T_world_camera) {
      const Eigen::Isometry3d de =
          last_est->ToIsometry().inverse() * t.T_world_camera->ToIsometry();
      const Eigen::Isometry3d dt =
          last_truth->ToIsometry().inverse() * e.T_world_camera->ToIsometry();
      const double err = (de.translation() - dt.translation()).norm();
      if (err > 0.01) {
        std::cout << "frame " << n - 1 << " step error " << err * 1000 << " mm (moved "
                  << dt.translation().norm() * 1000 << " mm) free: " << t.degenerate_axes.size()
                  << "\n";
        if (getenv("VECTORS")) {
          std::cout << "   est " << de.translation().transpose() * 1000 << " rot "
                    << Eigen::AngleAxisd(de.rotation()).angle() * 180 / M_PI << "  true "
                    << dt.translation().transpose() * 1000 << " rot "
                    << Eigen::AngleAxisd(dt.rotation()).angle() * 180 / M_PI << "\n";
        }
      }
    }
    last_est = t.T_world_camera;
    last_truth = e.T_world_camera;
    if (selector.Decide(e.timestamp_s, t.T_world_camera).selected) {
      selector.Accept(e.timestamp_s, t.T_world_camera);
      tracker.PromoteLastToReference();
      ++kf;
    }
  }
  auto err = eval::CompareTrajectories(est, truth);
  std::cout << "frames " << n << " lost " << lost << " kf " << kf << " ATE "
            << (err.ok() ? err->ate_rmse_m : -1) << " RPE " << (err.ok() ? err->rpe_trans_m : -1)
            << " dense " << methods[1] << " refit " << methods[2] << " features " << methods[3]
            << "\n";
}
