// Back-projection of depth images into coloured point clouds in the map frame, and voxel
// down-sampling to keep exported clouds small.
#pragma once

#include <vector>

#include "absl/status/statusor.h"

#include "core/common/rgbd_frame.h"
#include "core/io/ply_writer.h"

namespace lifemap::mapping {

// Appends the points of every `pixel_stride`-th pixel with a depth reading, transformed by
// T_world_camera into the world frame, coloured from the frame's colour image.
void AppendBackProjected(const RgbdFrame& frame, const Pose& T_world_camera, int pixel_stride,
                         std::vector<io::ColoredPoint>* cloud);

// Keeps one point per occupied voxel of edge `voxel_size_m` (the centroid, mean colour).
// Hand-written (an ordered map of voxel keys, ~20 lines) instead of pcl::VoxelGrid so exports do
// not pull PCL's compile time into the server; output order is deterministic (sorted by voxel key).
std::vector<io::ColoredPoint> VoxelDownsample(const std::vector<io::ColoredPoint>& cloud,
                                              double voxel_size_m);

// A multi-frame reconstruction at one view (paper 000's meshes come from KinectFusion; this is
// the simplest fusion where poses are known): every pixel of `others` is reprojected into
// `reference`'s camera and averaged with the readings there that agree within
// `tolerance_ratio` of the depth; pixels the reference missed take the nearest agreeing
// surface. Returns CV_32FC1 metres of the reference's size. The frames must carry
// T_world_camera; InvalidArgument otherwise.
absl::StatusOr<cv::Mat> FuseDepth(const RgbdFrame& reference, const std::vector<RgbdFrame>& others,
                                  float tolerance_ratio = 0.03f);

}  // namespace lifemap::mapping
