// Surface normals from an organized depth image (paper 000, eq. 2).
#pragma once

#include <opencv2/core.hpp>

#include "absl/status/statusor.h"
#include "core/common/types.h"

namespace lifemap::normals {

// How a pixel's normal is estimated.
enum class NormalMethod {
  kCrossProduct,  // eq. 2 of paper 000: cross product of the right and lower neighbours
  kMeshVertex,    // the paper's mesh variant: the organized cloud's triangles (two per pixel
                  // quad, corners depth-continuous), each vertex the area-weighted mean of its
                  // triangles' normals
};

// The triangles of the organized mesh over a pixel quad (r, c)-(r+1, c+1): the upper-left one
// (r,c),(r+1,c),(r,c+1) and the lower-right one (r,c+1),(r+1,c),(r+1,c+1). A triangle exists
// when its three corners have depth within max_depth_jump_ratio of each other.
bool UpperTriangle(const cv::Mat& points, int r, int c, float max_depth_jump_ratio);
bool LowerTriangle(const cv::Mat& points, int r, int c, float max_depth_jump_ratio);

struct NormalOptions {
  NormalMethod method = NormalMethod::kCrossProduct;
  // Edge-aware smoothing of depth before the cross products: a separable box of this radius
  // (pixels) that averages only neighbours within max_depth_jump_ratio of the centre's depth.
  // Raw Kinect normals on a flat table scatter by ~30 degrees; radius 3 brings that to a few
  // degrees without blurring across object boundaries. 0 = no smoothing.
  int smoothing_radius_px = 3;
  // Neighbour offset for the cross product of eq. 2 (1 = adjacent pixels as in the paper; 2
  // halves the noise for the same cost).
  int neighbor_step_px = 2;
  // Two pixels are on the same surface only if their depths differ by less than this fraction
  // of the depth (0.05 = 5 cm at 1 m). Used by smoothing and normal estimation.
  float max_depth_jump_ratio = 0.05f;

  absl::Status Validate() const;
};

// points: CV_32FC3 camera-frame coordinates in metres (x right, y down, z forward), (0,0,0)
// where depth is missing. normals: CV_32FC3 unit normals facing the camera (n . X < 0), (0,0,0)
// where no normal could be estimated.
struct NormalMap {
  cv::Mat points;
  cv::Mat normals;
  int valid_normals = 0;
};

// InvalidArgument for an empty or non-CV_32FC1 depth, a size different from the intrinsics', or
// invalid options; FailedPrecondition when no pixel has a usable normal (e.g. no depth at all).
absl::StatusOr<NormalMap> ComputeNormals(const cv::Mat& depth_m, const CameraIntrinsics& k,
                                         const NormalOptions& options = {});

}  // namespace lifemap::normals
