#include "core/features/keypoints.h"

#include <algorithm>
#include <cmath>

#include <opencv2/features2d.hpp>
#include <opencv2/imgproc.hpp>

namespace lifemap::features {

KeypointSet ExtractOrb(const cv::Mat& color_bgr, const cv::Mat& mask, int max_keypoints) {
  KeypointSet out;
  out.type = "orb";
  cv::Mat gray;
  cv::cvtColor(color_bgr, gray, cv::COLOR_BGR2GRAY);
  auto orb = cv::ORB::create(max_keypoints);
  std::vector<cv::KeyPoint> keypoints;
  cv::Mat descriptors;
  orb->detectAndCompute(gray, cv::noArray(), keypoints, descriptors);
  out.detected = static_cast<int>(keypoints.size());
  for (size_t i = 0; i < keypoints.size(); ++i) {
    const auto& k = keypoints[i];
    if (!mask.empty()) {
      const int c = std::clamp(static_cast<int>(std::lround(k.pt.x)), 0, mask.cols - 1);
      const int r = std::clamp(static_cast<int>(std::lround(k.pt.y)), 0, mask.rows - 1);
      if (mask.at<unsigned char>(r, c) != 0) {
        ++out.masked;
        continue;
      }
    }
    out.keypoints.push_back({k.pt.x, k.pt.y, k.size, k.angle, k.response});
    out.descriptors.push_back(descriptors.row(static_cast<int>(i)));
  }
  return out;
}

}  // namespace lifemap::features
