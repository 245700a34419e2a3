// Keypoints and descriptors for appearance matching, with the zones an entropy mask marks as
// likely to move pruned before they are stored (paper 000).
#pragma once

#include <string>
#include <vector>

#include <opencv2/core.hpp>

namespace lifemap::features {

struct Keypoint {
  float x = 0, y = 0;  // pixels
  float size = 0;      // diameter, pixels
  float angle = 0;     // degrees
  float response = 0;
};

struct KeypointSet {
  std::string type;  // "orb"
  std::vector<Keypoint> keypoints;
  cv::Mat descriptors;  // one row per keypoint (ORB: 32 bytes, CV_8UC1)
  int detected = 0;     // before pruning
  int masked = 0;       // dropped because they lay in masked zones
};

// ORB keypoints (OpenCV, up to max_keypoints) of a BGR image; those where `mask` (CV_8UC1 of
// the image's size, or empty) is non-zero are dropped.
KeypointSet ExtractOrb(const cv::Mat& color_bgr, const cv::Mat& mask, int max_keypoints = 1000);

}  // namespace lifemap::features
