// Geometric verification of an appearance candidate: the query's keypoints matched to the
// candidate's by descriptor, then the candidate's 3D points (its camera frame) located in the
// query image by PnP RANSAC and a Levenberg–Marquardt refinement on the inliers.
#pragma once

#include <string>

#include "absl/status/status.h"
#include "core/common/types.h"
#include "core/features/keypoints.h"

namespace lifemap::appearance {

struct VerifyOptions {
  double ratio_test = 0.8;  // Lowe's ratio between the best and second-best Hamming distance
  int max_hamming = 64;     // a match's best distance at most this (of 256 bits)
  // RANSAC inlier threshold, pixels at 640 columns (scaled with the query's width).
  double reprojection_px = 4.0;
  int ransac_iterations = 300;
  int min_inliers = 15;  // fewer: not verified
  // score = inliers / (inliers + half_score_inliers) for a verified match, so that this many
  // inliers scores 0.5, three times as many 0.75; 0 for a match that is not verified.
  double half_score_inliers = 30.0;

  absl::Status Validate() const;
};

struct Verification {
  bool verified = false;
  int matches = 0;  // descriptor matches whose candidate keypoint has a 3D point
  int inliers = 0;
  double score = 0;            // in [0, 1]; see VerifyOptions::half_score_inliers
  double reprojection_px = 0;  // RMS over the inliers after refinement
  Pose T_match_query;          // the query camera in the candidate camera's frame
  std::string reason;          // why not verified
};

// `query`: the query frame's keypoints (points not needed), with `query_intrinsics`;
// `match`: the candidate's keypoints with their 3D points. Never fails: a candidate that
// cannot be verified says why in `reason`.
Verification VerifyMatch(const features::KeypointSet& query,
                         const CameraIntrinsics& query_intrinsics,
                         const features::KeypointSet& match, const VerifyOptions& options = {});

}  // namespace lifemap::appearance
