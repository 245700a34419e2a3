#include "core/appearance/verify.h"

#include <cmath>

#include <opencv2/calib3d.hpp>

#include "absl/strings/str_cat.h"
#include "core/appearance/hamming.h"

namespace lifemap::appearance {

absl::Status VerifyOptions::Validate() const {
  if (!(ratio_test > 0 && ratio_test <= 1)) {
    return absl::InvalidArgumentError(
        absl::StrCat("ratio_test must be in (0, 1], got ", ratio_test));
  }
  if (max_hamming < 1 || max_hamming > 256) {
    return absl::InvalidArgumentError(
        absl::StrCat("max_hamming must be in [1, 256], got ", max_hamming));
  }
  if (!(reprojection_px > 0 && reprojection_px <= 50)) {
    return absl::InvalidArgumentError(
        absl::StrCat("reprojection_px must be in (0, 50], got ", reprojection_px));
  }
  if (ransac_iterations < 10 || ransac_iterations > 100000) {
    return absl::InvalidArgumentError(
        absl::StrCat("ransac_iterations must be in [10, 100000], got ", ransac_iterations));
  }
  if (min_inliers < 4) {
    return absl::InvalidArgumentError(absl::StrCat("min_inliers must be ≥ 4, got ", min_inliers));
  }
  if (!(half_score_inliers > 0)) {
    return absl::InvalidArgumentError("half_score_inliers must be > 0");
  }
  return absl::OkStatus();
}

Verification VerifyMatch(const features::KeypointSet& query,
                         const CameraIntrinsics& query_intrinsics,
                         const features::KeypointSet& match, const VerifyOptions& options) {
  Verification v;
  if (match.points.size() != match.size()) {
    v.reason = "the candidate has no 3D points";
    return v;
  }
  if (query.size() == 0 || match.size() == 0) {
    v.reason = "no keypoints to match";
    return v;
  }
  for (const features::KeypointSet* set : {&query, &match}) {
    const cv::Mat& d = set->descriptors;
    if (d.type() != CV_8UC1 || d.cols != 32 || d.rows != static_cast<int>(set->size())) {
      v.reason = "descriptors are not one 32-byte row per keypoint (ORB)";
      return v;
    }
  }
  // For each query keypoint, the best and second-best candidate keypoints with a 3D point.
  std::vector<cv::Point3f> object;
  std::vector<cv::Point2f> image;
  std::vector<internal::Descriptor> stored(match.size());
  for (size_t m = 0; m < match.size(); ++m) {
    stored[m] = internal::LoadDescriptor(match.descriptors.ptr<uint8_t>(static_cast<int>(m)));
  }
  for (size_t q = 0; q < query.size(); ++q) {
    const internal::Descriptor qd =
        internal::LoadDescriptor(query.descriptors.ptr<uint8_t>(static_cast<int>(q)));
    int best = 257, second = 257;
    size_t best_m = 0;
    for (size_t m = 0; m < stored.size(); ++m) {
      const int d = internal::Distance(qd, stored[m]);
      if (d < best) {
        second = best;
        best = d;
        best_m = m;
      } else if (d < second) {
        second = d;
      }
    }
    if (best > options.max_hamming || best >= options.ratio_test * second) continue;
    const Eigen::Vector3f& p = match.points[best_m];
    if (!p.allFinite()) continue;
    object.emplace_back(p.x(), p.y(), p.z());
    image.emplace_back(query.keypoints[q].x, query.keypoints[q].y);
  }
  v.matches = static_cast<int>(object.size());
  if (v.matches < options.min_inliers) {
    v.reason =
        absl::StrCat(v.matches, " descriptor matches with depth, fewer than ", options.min_inliers);
    return v;
  }
  const cv::Matx33d K(query_intrinsics.fx, 0, query_intrinsics.cx, 0, query_intrinsics.fy,
                      query_intrinsics.cy, 0, 0, 1);
  const double threshold = options.reprojection_px * query_intrinsics.width / 640.0;
  cv::Mat rvec, tvec;
  std::vector<int> inliers;
  const bool found = cv::solvePnPRansac(object, image, K, cv::noArray(), rvec, tvec, false,
                                        options.ransac_iterations, static_cast<float>(threshold),
                                        0.999, inliers, cv::SOLVEPNP_EPNP);
  if (!found || static_cast<int>(inliers.size()) < options.min_inliers) {
    v.inliers = static_cast<int>(inliers.size());
    v.reason = absl::StrCat("PnP RANSAC found ", inliers.size(), " inliers of ", v.matches,
                            ", fewer than ", options.min_inliers);
    return v;
  }
  std::vector<cv::Point3f> object_in;
  std::vector<cv::Point2f> image_in;
  for (int i : inliers) {
    object_in.push_back(object[static_cast<size_t>(i)]);
    image_in.push_back(image[static_cast<size_t>(i)]);
  }
  cv::solvePnPRefineLM(object_in, image_in, K, cv::noArray(), rvec, tvec);
  // Inliers again under the refined pose.
  std::vector<cv::Point2f> projected;
  cv::projectPoints(object, rvec, tvec, K, cv::noArray(), projected);
  int n = 0;
  double squared = 0;
  for (size_t i = 0; i < object.size(); ++i) {
    const double dx = projected[i].x - image[i].x, dy = projected[i].y - image[i].y;
    const double e2 = dx * dx + dy * dy;
    if (e2 <= threshold * threshold) {
      ++n;
      squared += e2;
    }
  }
  v.inliers = n;
  if (n < options.min_inliers) {
    v.reason = absl::StrCat("refined pose keeps ", n, " inliers, fewer than ", options.min_inliers);
    return v;
  }
  cv::Mat R;
  cv::Rodrigues(rvec, R);
  // solvePnP gives T_query_match (candidate camera → query camera); report its inverse.
  Eigen::Isometry3d T_query_match = Eigen::Isometry3d::Identity();
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) T_query_match.linear()(r, c) = R.at<double>(r, c);
    T_query_match.translation()(r) = tvec.at<double>(r);
  }
  v.T_match_query = Pose::FromIsometry(T_query_match.inverse());
  v.reprojection_px = std::sqrt(squared / n);
  v.verified = true;
  v.score = n / (n + options.half_score_inliers);
  return v;
}

}  // namespace lifemap::appearance
