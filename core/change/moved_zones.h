// The zones of a frame that moved since an earlier visit (paper 000's eq. 3, issue 36's
// per-frame mask): the earlier visit's surfaces rendered at the frame's pose and compared with
// the frame's depth.
#pragma once

#include <cstdint>
#include <vector>

#include <Eigen/Core>
#include <opencv2/core.hpp>

#include "core/change/object_changes.h"
#include "core/common/types.h"

namespace lifemap::change {

// Eq. 3 of paper 000: the zones of depth map `depth_i` that moved, against every other aligned
// depth map of the same place: median-filtered (window x window) differences D_j - D_i above
// `threshold_m` in any j (something is nearer now than it was). Pixels where either map has no
// reading count as no difference. Returns CV_8UC1, 255 = moved.
cv::Mat MovedZones(const cv::Mat& depth_i, const std::vector<cv::Mat>& others, int window = 10,
                   float threshold_m = 0.05f);

// A visit's surfaces in the map's frame, to be rendered at other poses: one point per voxel
// holding readings, at their mean.
struct SurfacePoints {
  std::vector<Eigen::Vector3f> points;
  double voxel_m = 0.05;
};

// The surfaces of `views` (readings up to `max_range_m`) binned at `voxel_m`.
SurfacePoints SurfaceOf(const std::vector<PosedDepth>& views, double voxel_m, double max_range_m);

// `surface` seen by camera `k` at `T_world_camera`, every `stride`-th pixel: per pixel the depth
// (metres) of the nearest point, each point covering the pixels its voxel spans; 0 where none.
// CV_32FC1 of ceil(width / stride) x ceil(height / stride).
cv::Mat RenderSurface(const SurfacePoints& surface, const CameraIntrinsics& k, int stride,
                      const Pose& T_world_camera, double max_range_m);

struct MovedOptions {
  int stride = 4;             // the frame is compared every n-th pixel
  int window = 3;             // eq. 3's median window, in compared pixels (12 px at stride 4)
  float threshold_m = 0.10f;  // nearer by more than this: moved (Kinect noise at 4 m is ~5 cm)
  double max_range_m = 4.0;
};

struct MovedMask {
  cv::Mat mask;  // CV_8UC1 at `stride`, 255 = moved
  int stride = 1;
  int64_t moved_pixels = 0;     // of the mask
  int64_t compared_pixels = 0;  // where both the frame and the rendering have a depth
  double share() const {
    return compared_pixels > 0 ? static_cast<double>(moved_pixels) / compared_pixels : 0.0;
  }
};

// The mask at the frame's size (`width` x `height`): each compared pixel's verdict copied to
// its stride cell.
cv::Mat FullSizeMask(const MovedMask& m, int width, int height);

// The frame's depth (CV_32FC1 metres, of `k`'s size) against `previous` rendered at its pose.
MovedMask MovedAgainst(const cv::Mat& depth_m, const CameraIntrinsics& k,
                       const Pose& T_world_camera, const SurfacePoints& previous,
                       const MovedOptions& options = {});

}  // namespace lifemap::change
