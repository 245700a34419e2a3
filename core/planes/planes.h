// Planar regions of a depth image by recursive quadtree decomposition, clustered into planes
// (paper 004, sections 3.1–3.2).
//
// The paper's equations 1–4 lost their symbols in the text; reconstructed from the methods it
// cites, they are:
//  (1) flat(R)   ⇔ MSE(R) < T_mse(z̄) ∧ curv(R) < T_curv, with the total-least-squares plane
//      of R's back-projected points: MSE = λ₀ (smallest eigenvalue of their covariance, the
//      mean squared point-to-plane distance) and curv = λ₀ / (λ₀ + λ₁ + λ₂) — both from
//      integral images of the point moments, as in Holzer et al. [53];
//  (2) DCI(p) = 1 ⇔ ∃ q ∈ N4(p): |d(p) − d(q)| > T_dci(d(p)), the depth-change indication map of
//      [54] with a threshold growing with depth (the sensor's noise does);
//  (3) smooth(R) ⇔ Σ_{p∈R} DCI(p) = 0;
//  (4) same plane(Rᵢ, Rⱼ) ⇔ ∠(nᵢ, nⱼ) < T_angle ∧ |dᵢ − dⱼ| < T_offset, with n·x = d each
//      region's plane (unit normal towards the camera, d its distance from the camera centre).
// A region that is flat and smooth is planar; otherwise it is split into four until it is
// smaller than the minimum size.
#pragma once

#include <vector>

#include <Eigen/Core>
#include <opencv2/core.hpp>

#include "absl/status/statusor.h"
#include "core/common/types.h"

namespace lifemap::planes {

struct PlaneOptions {
  int median_kernel = 5;   // median smoothing of the depth (odd pixels; 1 = none)
  int root_px = 64;        // the quadtree's root cells tile the image at this size
  int min_region_px = 8;   // regions are not split below this side
  float min_valid = 0.8f;  // share of a region's pixels that must have depth
  // T_mse(z) = (mse_rms_m + mse_quad * z²)²: the plane's RMS residual may grow like the
  // Kinect's noise (metres).
  float mse_rms_m = 0.005f;
  float mse_quad = 0.008f;
  float max_curvature = 0.01f;
  float dci_relative = 0.03f;  // T_dci(z) = dci_relative * z (metres)
  float merge_angle_deg = 8.0f;
  float merge_offset_m = 0.06f;

  absl::Status Validate() const;
};

// One planar quadtree leaf.
struct PlanarRegion {
  cv::Rect rect;             // pixels
  Eigen::Vector3f normal;    // unit, camera frame, towards the camera
  float offset_m = 0;        // n·x = offset for points x of the plane (≤ 0 with n to camera)
  Eigen::Vector3f centroid;  // camera frame, metres
  int points = 0;
  float rms_m = 0;  // RMS point-to-plane residual
  float curvature = 0;
  int plane = -1;  // index into PlaneSet::planes
};

// Regions of one plane (eq. 4), refitted together.
struct Plane {
  Eigen::Vector3f normal;  // unit, towards the camera
  float offset_m = 0;
  Eigen::Vector3f centroid;
  int points = 0;
  float area_m2 = 0;  // sum of the regions' areas on the plane
  std::vector<int> regions;
  // Each region's rectangle as a quad on the plane (camera frame, metres): 4 corners each.
  std::vector<Eigen::Vector3f> quads;
};

struct PlaneSet {
  std::vector<PlanarRegion> regions;
  std::vector<Plane> planes;  // largest area first
  cv::Mat smoothed_depth_m;   // after median smoothing
};

// InvalidArgument for an empty or non-CV_32FC1 depth image, intrinsics of another size, or bad
// options. Depth in metres, 0 = no reading.
absl::StatusOr<PlaneSet> ExtractPlanes(const cv::Mat& depth_m, const CameraIntrinsics& k,
                                       const PlaneOptions& options = {});

}  // namespace lifemap::planes
