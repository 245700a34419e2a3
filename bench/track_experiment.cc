#include <cstdlib>
#include <iostream>
#include <opencv2/imgcodecs.hpp>
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
  int limit = argc > 3 ? std::atoi(argv[3]) : 100000;
  tracking::Tracker tracker(o);
  tracking::KeyframeSelector selector;
  std::vector<eval::TimedPose> est, truth;
  int lost = 0, kf = 0, n = 0;
  for (const auto& e : seq->frames) {
    if (n++ >= limit) break;
    auto f = io::DecodeTumFrame(*seq, e);
    if (argc > 4 && std::atoi(argv[4]) > 0) {
      std::vector<uchar> buf;
      cv::imencode(".jpg", f->color_bgr, buf, {cv::IMWRITE_JPEG_QUALITY, std::atoi(argv[4])});
      f->color_bgr = cv::imdecode(buf, cv::IMREAD_COLOR);
    }
    auto t = tracker.Track(*f);
    if (e.T_world_camera) truth.push_back({e.timestamp_s, *e.T_world_camera});
    if (!t.T_world_camera) {
      ++lost;
      continue;
    }
    est.push_back({e.timestamp_s, *t.T_world_camera});
    if (selector.Decide(e.timestamp_s, t.T_world_camera).selected) {
      selector.Accept(e.timestamp_s, t.T_world_camera);
      tracker.PromoteLastToReference();
      ++kf;
    }
  }
  auto err = eval::CompareTrajectories(est, truth);
  std::cout << "frames " << n << " lost " << lost << " kf " << kf << " ATE "
            << (err.ok() ? err->ate_rmse_m : -1) << " RPE " << (err.ok() ? err->rpe_trans_m : -1)
            << "\n";
}
