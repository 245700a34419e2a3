// Keypoints and descriptors for appearance matching (paper 000): detected once per keyframe,
// each with its 3D point from the depth image, and pruned where an entropy mask marks zones
// likely to move before they are stored or matched.
#pragma once

#include <string>
#include <vector>

#include <Eigen/Core>
#include <opencv2/core.hpp>

#include "core/common/types.h"

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
  // Per keypoint, its point in the camera frame (metres, x right, y down, z forward) from the
  // depth reading at its pixel; NaN where there is none. Empty when no depth was attached.
  std::vector<Eigen::Vector3f> points;
  int detected = 0;  // before pruning
  int masked = 0;    // dropped because they lay in masked zones

  size_t size() const { return keypoints.size(); }
  // Keypoints that have a 3D point.
  int with_points() const;
};

// How ORB runs (OpenCV's detector, its defaults). A 3-level pyramid 1.5 apart takes 0.58 of
// the time per keyframe (7.8 against 13.4 ms in one run) but costs 1-4 points of F1 on the
// building suites, half-resolution detection 6 points on the rooms suite (docs/BENCHMARKS.md,
// "Features per keyframe"): both are options, not defaults.
struct OrbOptions {
  int max_keypoints = 1000;  // detected at most, [10, 10000]
  // < 1: detect on the image resized by this factor (0.5: a quarter of the pixels); keypoints
  // come back in the full image's pixels, sizes scaled alike. (0.2, 1].
  double detect_scale = 1.0;
  int pyramid_levels = 8;      // scale pyramid levels, [1, 12]
  double pyramid_scale = 1.2;  // ratio between levels, (1, 2]
};

// ORB keypoints and descriptors of a BGR image, none pruned.
KeypointSet ExtractOrb(const cv::Mat& color_bgr, const OrbOptions& options = {});

// Fills `set->points` from a depth image (CV_32FC1 metres, 0 or NaN = no reading) registered
// with the colour image the keypoints came from.
void AttachPoints(const cv::Mat& depth_m, const CameraIntrinsics& intrinsics, KeypointSet* set);

// The keypoints where `mask` (CV_8UC1 of the image's size, or empty) is zero, in order; the
// others are counted in `masked`.
KeypointSet PruneByMask(const KeypointSet& set, const cv::Mat& mask);

// The keypoints whose `keep` entry is true (keep.size() == set.size()); the others are counted
// in `masked`. For pruning by a rule other than a mask (the evaluation's null and oracle).
KeypointSet Select(const KeypointSet& set, const std::vector<bool>& keep);

}  // namespace lifemap::features
