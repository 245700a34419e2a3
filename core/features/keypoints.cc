#include "core/features/keypoints.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include <opencv2/features2d.hpp>
#include <opencv2/imgproc.hpp>

namespace lifemap::features {

int KeypointSet::with_points() const {
  return static_cast<int>(std::count_if(points.begin(), points.end(),
                                        [](const Eigen::Vector3f& p) { return p.allFinite(); }));
}

KeypointSet ExtractOrb(const cv::Mat& color_bgr, const OrbOptions& options) {
  KeypointSet out;
  out.type = "orb";
  cv::Mat gray;
  cv::cvtColor(color_bgr, gray, cv::COLOR_BGR2GRAY);
  double detect_scale = options.detect_scale;
  if (detect_scale > 0 && detect_scale < 1) {
    cv::resize(gray, gray, cv::Size(), detect_scale, detect_scale, cv::INTER_AREA);
  } else {
    detect_scale = 1;
  }
  auto orb = cv::ORB::create(options.max_keypoints, static_cast<float>(options.pyramid_scale),
                             options.pyramid_levels);
  std::vector<cv::KeyPoint> keypoints;
  orb->detectAndCompute(gray, cv::noArray(), keypoints, out.descriptors);
  out.detected = static_cast<int>(keypoints.size());
  out.keypoints.reserve(keypoints.size());
  // Pixel centres map as (x + 0.5) / scale - 0.5.
  const auto up = static_cast<float>(1.0 / detect_scale);
  const float shift = 0.5f * (up - 1.0f);
  for (const auto& k : keypoints) {
    out.keypoints.push_back(
        {k.pt.x * up + shift, k.pt.y * up + shift, k.size * up, k.angle, k.response});
  }
  return out;
}

void AttachPoints(const cv::Mat& depth_m, const CameraIntrinsics& k, KeypointSet* set) {
  constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
  set->points.assign(set->keypoints.size(), Eigen::Vector3f::Constant(kNaN));
  if (depth_m.empty()) return;
  for (size_t i = 0; i < set->keypoints.size(); ++i) {
    const auto& kp = set->keypoints[i];
    const int c = static_cast<int>(std::lround(kp.x));
    const int r = static_cast<int>(std::lround(kp.y));
    if (c < 0 || r < 0 || c >= depth_m.cols || r >= depth_m.rows) continue;
    const float z = depth_m.at<float>(r, c);
    if (!(z > 0) || !std::isfinite(z)) continue;
    set->points[i] = {static_cast<float>((kp.x - k.cx) / k.fx) * z,
                      static_cast<float>((kp.y - k.cy) / k.fy) * z, z};
  }
}

KeypointSet Select(const KeypointSet& set, const std::vector<bool>& keep) {
  KeypointSet out;
  out.type = set.type;
  out.detected = set.detected;
  out.masked = set.masked;
  const bool has_points = set.points.size() == set.keypoints.size();
  for (size_t i = 0; i < set.keypoints.size(); ++i) {
    if (!keep[i]) {
      ++out.masked;
      continue;
    }
    out.keypoints.push_back(set.keypoints[i]);
    out.descriptors.push_back(set.descriptors.row(static_cast<int>(i)));
    if (has_points) out.points.push_back(set.points[i]);
  }
  return out;
}

KeypointSet PruneByMask(const KeypointSet& set, const cv::Mat& mask) {
  std::vector<bool> keep(set.keypoints.size(), true);
  if (!mask.empty()) {
    for (size_t i = 0; i < keep.size(); ++i) {
      const auto& k = set.keypoints[i];
      const int c = std::clamp(static_cast<int>(std::lround(k.x)), 0, mask.cols - 1);
      const int r = std::clamp(static_cast<int>(std::lround(k.y)), 0, mask.rows - 1);
      keep[i] = mask.at<unsigned char>(r, c) == 0;
    }
  }
  return Select(set, keep);
}

}  // namespace lifemap::features
