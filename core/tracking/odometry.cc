#include "core/tracking/odometry.h"

#include <algorithm>
#include <cmath>

#include <Eigen/Eigenvalues>

#include <opencv2/core/eigen.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/rgbd.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/appearance/verify.h"
#include "core/features/keypoints.h"
#include "core/planes/planes.h"

namespace lifemap::tracking {
namespace {

// cv::Mat 4x4 CV_64F <-> Eigen isometry.
Eigen::Isometry3d ToIsometry(const cv::Mat& Rt) {
  Eigen::Matrix4d m;
  cv::cv2eigen(Rt, m);
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = m.topLeftCorner<3, 3>();
  T.translation() = m.topRightCorner<3, 1>();
  return T;
}

cv::Mat ToMat(const Eigen::Isometry3d& T) {
  cv::Mat Rt;
  const Eigen::Matrix4d m = T.matrix();
  cv::eigen2cv(m, Rt);
  return Rt;
}

double AngleOf(const Eigen::Isometry3d& T) { return Eigen::AngleAxisd(T.rotation()).angle(); }

}  // namespace

absl::Status OdometryOptions::Validate() const {
  if (!(odometry_drift >= 0 && odometry_drift <= 1 && odometry_drift_deg_per_m >= 0 &&
        odometry_drift_deg_per_m <= 90 && odometry_floor_m > 0 && odometry_floor_m <= 1 &&
        odometry_floor_deg > 0 && odometry_floor_deg <= 45 && odometry_gate_sigmas >= 1 &&
        odometry_gate_sigmas <= 10)) {
    return absl::InvalidArgumentError(
        "odometry_drift must be within [0, 1], odometry_drift_deg_per_m within [0, 90], "
        "odometry_floor_m within (0, 1], odometry_floor_deg within (0, 45] and "
        "odometry_gate_sigmas within [1, 10]");
  }
  if (!(odometry_max_speed_mps > 0 && odometry_max_speed_mps <= 100 && odometry_max_turn_dps > 0 &&
        odometry_max_turn_dps <= 3600)) {
    return absl::InvalidArgumentError(
        "odometry_max_speed_mps must be within (0, 100] and odometry_max_turn_dps within "
        "(0, 3600]");
  }
  if (downscale < 1 || downscale > 4) {
    return absl::InvalidArgumentError(
        absl::StrCat("odometry downscale must be within [1, 4], got ", downscale));
  }
  if (!(min_depth_m >= 0 && max_depth_m > min_depth_m && max_depth_m <= 50)) {
    return absl::InvalidArgumentError(
        absl::StrCat("odometry depth range must satisfy 0 <= min < max <= 50 m, got ", min_depth_m,
                     "-", max_depth_m));
  }
  if (!(max_depth_diff_m > 0 && max_depth_diff_m <= 1)) {
    return absl::InvalidArgumentError(
        absl::StrCat("odometry max_depth_diff_m must be within (0, 1], got ", max_depth_diff_m));
  }
  if (!(max_translation_m > 0 && max_translation_m <= 10 && max_rotation_deg > 0 &&
        max_rotation_deg <= 180)) {
    return absl::InvalidArgumentError(
        "odometry max_translation_m must be within (0, 10] and max_rotation_deg within (0, 180]");
  }
  if (!(max_jump_m > 0 && max_jump_m <= 10 && max_jump_rad > 0 && max_jump_rad <= M_PI)) {
    return absl::InvalidArgumentError(
        "odometry max_jump_m must be within (0, 10] and max_jump_rad within (0, pi]");
  }
  if (!(min_gradient >= 0 && min_gradient <= 255)) {
    return absl::InvalidArgumentError(
        absl::StrCat("odometry min_gradient must be within [0, 255], got ", min_gradient));
  }
  if (hole_margin < 0 || hole_margin > 8) {
    return absl::InvalidArgumentError(
        absl::StrCat("odometry hole_margin must be within [0, 8] pixels, got ", hole_margin));
  }
  if (feature_keypoints < 0 || feature_keypoints > 5000 || feature_min_inliers < 6 ||
      feature_min_inliers > 1000) {
    return absl::InvalidArgumentError(absl::StrCat(
        "odometry feature_keypoints must be within [0, 5000] and feature_min_inliers within "
        "[6, 1000], got ",
        feature_keypoints, " and ", feature_min_inliers));
  }
  if (!(feature_check_speed_mps > 0 && feature_check_speed_mps <= 100 &&
        feature_check_turn_dps > 0 && feature_check_turn_dps <= 3600)) {
    return absl::InvalidArgumentError(
        "odometry feature_check_speed_mps must be within (0, 100] and feature_check_turn_dps "
        "within (0, 3600]");
  }
  if (!(degenerate_share >= 0 && degenerate_share <= 0.1)) {
    return absl::InvalidArgumentError(
        absl::StrCat("odometry degenerate_share must be within [0, 0.1], got ", degenerate_share));
  }
  if (!(prior_share >= 0 && prior_share <= 0.1)) {
    return absl::InvalidArgumentError(
        absl::StrCat("odometry prior_share must be within [0, 0.1], got ", prior_share));
  }
  if (!(feature_agree_m > 0 && feature_agree_m <= 1 && feature_agree_deg > 0 &&
        feature_agree_deg <= 45)) {
    return absl::InvalidArgumentError(
        "odometry feature_agree_m must be within (0, 1] and feature_agree_deg within (0, 45]");
  }
  return absl::OkStatus();
}

namespace {

cv::Mat CameraMatrix(const CameraIntrinsics& k, int downscale) {
  const double s = 1.0 / downscale;
  return (cv::Mat_<double>(3, 3) << k.fx * s, 0, (k.cx + 0.5) * s - 0.5, 0, k.fy * s,
          (k.cy + 0.5) * s - 0.5, 0, 0, 1);
}

cv::Ptr<cv::rgbd::RgbdICPOdometry> MakeOdometry(const CameraIntrinsics& k,
                                                const OdometryOptions& options) {
  auto odometry =
      cv::rgbd::RgbdICPOdometry::create(CameraMatrix(k, options.downscale), options.min_depth_m,
                                        options.max_depth_m, options.max_depth_diff_m);
  odometry->setMinGradientMagnitudes(
      cv::Mat(std::vector<float>(4, options.min_gradient), /*copyData=*/true));
  odometry->setMaxTranslation(options.max_translation_m);
  odometry->setMaxRotation(options.max_rotation_deg);
  return odometry;
}

bool SameCamera(const CameraIntrinsics& a, const CameraIntrinsics& b) {
  return a.fx == b.fx && a.fy == b.fy && a.cx == b.cx && a.cy == b.cy && a.width == b.width &&
         a.height == b.height;
}

// Whether a frame prepared with `a` can be aligned by an odometry set up with `b`: the
// options that shape a prepared frame (resolution, depth range) agree.
bool SamePreparation(const OdometryOptions& a, const OdometryOptions& b) {
  return a.downscale == b.downscale && a.min_depth_m == b.min_depth_m &&
         a.min_gradient == b.min_gradient && a.max_depth_m == b.max_depth_m &&
         a.max_depth_diff_m == b.max_depth_diff_m && a.feature_keypoints == b.feature_keypoints &&
         a.hole_margin == b.hole_margin;
}

// How far apart two estimates of one pose are.
bool Agree(const Eigen::Isometry3d& a, const Eigen::Isometry3d& b, const OdometryOptions& o) {
  const Eigen::Isometry3d d = a.inverse() * b;
  return d.translation().norm() <= o.feature_agree_m &&
         AngleOf(d) <= o.feature_agree_deg * M_PI / 180.0;
}

// How well `current` agrees with `reference` when moved by T_reference_current: the share of
// its sampled pixels (every 4th row and column, with depth) that land inside the reference
// image on a depth within 2 cm + 2 % and a grey level within 16 of their own. Both frames at
// the odometry's resolution, `K` its camera matrix. The arbiter between the dense and the
// feature estimates: where one slid along a wall its depth still agrees, but the tiles, window
// and furniture edges in its view no longer do.
double Consistency(const cv::rgbd::OdometryFrame& current, const cv::rgbd::OdometryFrame& reference,
                   const cv::Mat& K, const Eigen::Isometry3d& T_reference_current) {
  const double fx = K.at<double>(0, 0), fy = K.at<double>(1, 1), cx = K.at<double>(0, 2),
               cy = K.at<double>(1, 2);
  const Eigen::Matrix3d R = T_reference_current.linear();
  const Eigen::Vector3d t = T_reference_current.translation();
  int sampled = 0, consistent = 0;
  for (int r = 0; r < current.depth.rows; r += 4) {
    const float* z_row = current.depth.ptr<float>(r);
    const uchar* g_row = current.image.ptr<uchar>(r);
    for (int c = 0; c < current.depth.cols; c += 4) {
      const float z = z_row[c];
      if (!(z > 0) || !std::isfinite(z)) continue;
      ++sampled;
      const Eigen::Vector3d p = R * Eigen::Vector3d((c - cx) / fx * z, (r - cy) / fy * z, z) + t;
      if (p.z() <= 0) continue;
      const int u = static_cast<int>(std::lround(fx * p.x() / p.z() + cx));
      const int v = static_cast<int>(std::lround(fy * p.y() / p.z() + cy));
      if (u < 0 || v < 0 || u >= reference.depth.cols || v >= reference.depth.rows) continue;
      const float zr = reference.depth.at<float>(v, u);
      if (!(zr > 0) || std::abs(zr - p.z()) > 0.02 + 0.02 * p.z()) continue;
      if (std::abs(static_cast<int>(reference.image.at<uchar>(v, u)) - g_row[c]) > 16) continue;
      ++consistent;
    }
  }
  return sampled > 0 ? static_cast<double>(consistent) / sampled : 0.0;
}

// The pyramid levels of OpenCV's RgbdICPOdometry (its default iteration counts 7, 7, 7, 10).
constexpr int kPyramidLevels = 4;

// The depth and mask pyramids of a frame, made here rather than by OpenCV, which blurs the
// depth image with its holes (pyrDown of metres and zeros): beside a hole the coarse levels then
// hold depths between the surface and zero, a phantom surface both terms align to. And where
// something closer than the sensor's range has no depth (furniture passed within 45 cm), its
// edge against the wall behind looks like texture on that wall which moves with the camera, and
// the photometric term follows it. So a coarse pixel's depth averages only readings that agree
// with its own, and each level's mask leaves out the pixels within `hole_margin` pixels of a
// hole. The grey pyramid stays OpenCV's. Building seed 13 (900 frames): ATE 208 mm with
// OpenCV's pyramids, 5.3 mm with these.
void BuildPyramids(const cv::Mat& depth, const OdometryOptions& options,
                   std::vector<cv::Mat>* pyramid_depth, std::vector<cv::Mat>* pyramid_mask) {
  pyramid_depth->resize(kPyramidLevels);
  pyramid_mask->resize(kPyramidLevels);
  cv::Mat level = depth.clone();
  level.setTo(0, ~((level > options.min_depth_m) & (level < options.max_depth_m)));
  for (int i = 0; i < kPyramidLevels; ++i) {
    if (i > 0) {
      // Coarse pixel (r, c) is fine pixel (2r, 2c), as in pyrDown and OpenCV's camera matrix
      // per level: the mean of that pixel's 3x3 neighbours (weights 1-2-1) that have depth
      // within `max_depth_diff_m` of it, none where it has none.
      const cv::Mat& finer = (*pyramid_depth)[i - 1];
      level = cv::Mat((finer.rows + 1) / 2, (finer.cols + 1) / 2, CV_32F, cv::Scalar(0));
      for (int r = 0; r < level.rows; ++r) {
        float* out = level.ptr<float>(r);
        for (int c = 0; c < level.cols; ++c) {
          const float centre = finer.at<float>(2 * r, 2 * c);
          if (!(centre > 0)) continue;
          float sum = 0, weight = 0;
          for (int dr = -1; dr <= 1; ++dr) {
            const int rr = 2 * r + dr;
            if (rr < 0 || rr >= finer.rows) continue;
            for (int dc = -1; dc <= 1; ++dc) {
              const int cc = 2 * c + dc;
              if (cc < 0 || cc >= finer.cols) continue;
              const float z = finer.at<float>(rr, cc);
              if (!(z > 0) || std::abs(z - centre) > options.max_depth_diff_m) continue;
              const float w = static_cast<float>((2 - std::abs(dr)) * (2 - std::abs(dc)));
              sum += w * z;
              weight += w;
            }
          }
          out[c] = sum / weight;
        }
      }
    }
    (*pyramid_depth)[i] = level;
    cv::Mat valid = level > 0;
    if (options.hole_margin > 0) {
      const int side = 2 * options.hole_margin + 1;
      cv::erode(valid, valid, cv::getStructuringElement(cv::MORPH_RECT, cv::Size(side, side)),
                cv::Point(-1, -1), 1, cv::BORDER_CONSTANT, cv::Scalar(255));
    }
    (*pyramid_mask)[i] = valid;
  }
}

// The robot's motion between two odometry readings, with its uncertainty (one sigma).
struct OdometryStep {
  Eigen::Isometry3d T_last_current;  // the current camera in the last one's frame
  double sigma_m = 0;
  double sigma_rad = 0;
};

OdometryStep StepOf(const OdometryReading& last, const OdometryReading& current,
                    const OdometryOptions& o) {
  OdometryStep step;
  step.T_last_current =
      last.T_odom_camera.ToIsometry().inverse() * current.T_odom_camera.ToIsometry();
  const double distance = step.T_last_current.translation().norm();
  if (!last.covariance || !current.covariance) {
    step.sigma_m = o.odometry_drift * distance + o.odometry_floor_m;
    step.sigma_rad = (o.odometry_drift_deg_per_m * distance + o.odometry_floor_deg) * M_PI / 180.0;
  } else {
    // Cumulative covariances: the increment's is their difference (independent increments);
    // its translation and rotation sigmas are the roots of its blocks' traces. The floor stays:
    // a covariance that did not grow does not make the step exact.
    const Eigen::Matrix<double, 6, 6> d = *current.covariance - *last.covariance;
    step.sigma_m = std::sqrt(std::max(0.0, d.topLeftCorner<3, 3>().trace())) + o.odometry_floor_m;
    step.sigma_rad = std::sqrt(std::max(0.0, d.bottomRightCorner<3, 3>().trace())) +
                     o.odometry_floor_deg * M_PI / 180.0;
  }
  return step;
}

// The pyramid level whose points and normals InformationOf reads: half the odometry's resolution
// (160x120 at 320x240). At 40x30 a desk's objects vanish and TUM fr1_xyz's views looked as
// free along the desk as a plain wall (0.00 % of the information).
constexpr int kDegeneracyLevel = 1;

// How firmly point-to-plane alignment against a view pins each direction of motion: the
// information matrix of rows (n, (p x n) / d) over the view's points p and unit normals n (in
// the frame they are given in; d their median depth, so rotations count in metres at that
// depth), divided by its trace, as its eigen-directions (columns, translation then rotation, in
// that frame) and their shares (ascending), decomposed once per view. A small motion
// (translation t, rotation w about the frame's origin) moves a point's residual by
// n.t + (p x n).w. Unknown (no directions) with fewer than 50 points.
struct DepthInformation {
  bool known = false;
  Eigen::Matrix<double, 6, 1> shares = Eigen::Matrix<double, 6, 1>::Zero();
  Eigen::Matrix<double, 6, 6> directions = Eigen::Matrix<double, 6, 6>::Identity();
  double depth_m = 1.0;
};

DepthInformation InformationOf(const std::vector<Eigen::Vector3d>& points,
                               const std::vector<Eigen::Vector3d>& normals) {
  DepthInformation info;
  if (points.size() < 50 || points.size() != normals.size()) return info;
  std::vector<double> depths;
  depths.reserve(points.size());
  for (const auto& p : points) depths.push_back(p.z());
  std::nth_element(depths.begin(), depths.begin() + depths.size() / 2, depths.end());
  info.depth_m = std::max(depths[depths.size() / 2], 0.1);
  Eigen::Matrix<double, 6, 6> H = Eigen::Matrix<double, 6, 6>::Zero();
  for (size_t i = 0; i < points.size(); ++i) {
    Eigen::Matrix<double, 6, 1> row;
    row.head<3>() = normals[i];
    row.tail<3>() = points[i].cross(normals[i]) / info.depth_m;
    H.noalias() += row * row.transpose();
  }
  const double trace = H.trace();
  if (!(trace > 0)) return info;
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix<double, 6, 6>> eigen(H / trace);
  info.known = true;
  info.shares = eigen.eigenvalues();
  info.directions = eigen.eigenvectors();
  return info;
}

// A prepared reference frame's DepthInformation (its cached cloud and normals at
// kDegeneracyLevel), in its camera frame.
DepthInformation InformationOf(const cv::rgbd::OdometryFrame& f) {
  if (static_cast<int>(f.pyramidNormals.size()) <= kDegeneracyLevel ||
      static_cast<int>(f.pyramidCloud.size()) <= kDegeneracyLevel) {
    return {};
  }
  const cv::Mat& cloud = f.pyramidCloud[kDegeneracyLevel];
  const cv::Mat& normals = f.pyramidNormals[kDegeneracyLevel];
  if (cloud.size() != normals.size() || cloud.type() != CV_32FC3 || normals.type() != CV_32FC3) {
    return {};
  }
  const cv::Mat& depth = f.pyramidDepth[kDegeneracyLevel];
  std::vector<Eigen::Vector3d> points, unit_normals;
  for (int r = 0; r < cloud.rows; ++r) {
    for (int c = 0; c < cloud.cols; ++c) {
      if (!(depth.at<float>(r, c) > 0)) continue;
      const cv::Vec3f p = cloud.at<cv::Vec3f>(r, c), n = normals.at<cv::Vec3f>(r, c);
      if (!std::isfinite(n[0]) || !std::isfinite(p[2]) || !(p[2] > 0)) continue;
      const Eigen::Vector3d nn(n[0], n[1], n[2]);
      if (nn.norm() < 0.5) continue;
      points.emplace_back(p[0], p[1], p[2]);
      unit_normals.push_back(nn.normalized());
    }
  }
  return InformationOf(points, unit_normals);
}

// The directions of `info` (a view's, camera frame) whose share is below `min_share`, named in
// the world's axes (the camera rotated by `R_world_camera`).
std::vector<std::string> FreeDirections(const DepthInformation& info,
                                        const Eigen::Matrix3d& R_world_camera, double min_share) {
  if (min_share <= 0 || !info.known) return {};
  // Rotating the information into the world's axes keeps its shares and turns its directions.
  Eigen::Matrix<double, 6, 6> rotate = Eigen::Matrix<double, 6, 6>::Zero();
  rotate.topLeftCorner<3, 3>() = R_world_camera;
  rotate.bottomRightCorner<3, 3>() = R_world_camera;
  std::vector<std::string> free;
  static const char* kAxis[] = {"x", "y", "z"};
  for (int i = 0; i < 6; ++i) {
    const double share = info.shares(i);
    if (share >= min_share) continue;
    const Eigen::Matrix<double, 6, 1> v = rotate * info.directions.col(i);
    int axis = 0;
    v.cwiseAbs().maxCoeff(&axis);
    free.push_back(absl::StrFormat("%s %s (%.2f %% of the depth's information)",
                                   axis < 3 ? "translation along" : "rotation about",
                                   kAxis[axis % 3], 100 * share));
  }
  return free;
}

// The alignment `aligned` (T_reference_current) where the reference's depth pins the motion,
// `prior` (the motion model's T_reference_current) where it does not: their difference
// (aligned * prior^-1, in the reference camera's frame) is weighted, per eigen-direction of
// the reference's information with share s, by s^2 / (s^2 + prior_share^2), so a direction
// the depth leaves free (a plain wall's two in-plane translations and the turn about its
// normal) follows the prior, and a pinned one the alignment. Point-to-plane ICP along a free
// direction is noise (the photometric term of a plain wall hardly helps), and that noise, kept
// at every keyframe, is what bent the tracks (issue 54).
Eigen::Isometry3d FollowPriorWhereFree(const Eigen::Isometry3d& aligned,
                                       const Eigen::Isometry3d& prior, const DepthInformation& info,
                                       double prior_share) {
  if (prior_share <= 0 || !info.known) return aligned;
  const Eigen::Isometry3d D = aligned * prior.inverse();
  const Eigen::AngleAxisd turn(D.rotation());
  Eigen::Matrix<double, 6, 1> xi;
  xi.head<3>() = D.translation();
  xi.tail<3>() = turn.axis() * turn.angle() * info.depth_m;
  const Eigen::Array<double, 6, 1> s = info.shares.array().max(0.0);
  const Eigen::Matrix<double, 6, 1> weight =
      (s.square() / (s.square() + prior_share * prior_share)).matrix();
  const Eigen::Matrix<double, 6, 6>& V = info.directions;
  const Eigen::Matrix<double, 6, 1> kept = V * weight.asDiagonal() * V.transpose() * xi;
  Eigen::Isometry3d D_kept = Eigen::Isometry3d::Identity();
  const Eigen::Vector3d w = kept.tail<3>() / info.depth_m;
  if (w.norm() > 0)
    D_kept.linear() = Eigen::AngleAxisd(w.norm(), w.normalized()).toRotationMatrix();
  D_kept.translation() = kept.head<3>();
  return D_kept * prior;
}

}  // namespace

std::vector<std::string> DepthDegeneracy(const std::vector<Eigen::Vector3d>& points,
                                         const std::vector<Eigen::Vector3d>& normals,
                                         const Eigen::Matrix3d& R_world_camera, double min_share) {
  return FreeDirections(InformationOf(points, normals), R_world_camera, min_share);
}

struct TrackingInput {
  CameraIntrinsics intrinsics;
  OdometryOptions options;                 // prepared with these
  cv::Ptr<cv::rgbd::OdometryFrame> frame;  // null when the frame cannot be tracked
  std::string why_not;
  // The feature check's input: the frame's full-resolution colour and depth (shared, not
  // copied), and its ORB keypoints with 3D points (camera frame) once a check has needed them.
  cv::Mat color_bgr, depth_m;
  std::optional<features::KeypointSet> keypoints;
};

namespace {

// The frame's keypoints for the feature check, detected on first use.
const features::KeypointSet& KeypointsOf(TrackingInput& in, int max_keypoints) {
  if (!in.keypoints) {
    // Four pyramid levels: a frame and its reference keyframe are close in scale.
    features::OrbOptions orb;
    orb.max_keypoints = max_keypoints;
    orb.pyramid_levels = 4;
    in.keypoints = features::ExtractOrb(in.color_bgr, orb);
    features::AttachPoints(in.depth_m, in.intrinsics, &*in.keypoints);
  }
  return *in.keypoints;
}

}  // namespace

std::shared_ptr<TrackingInput> PrepareForTracking(const RgbdFrame& f,
                                                  const OdometryOptions& options) {
  auto in = std::make_shared<TrackingInput>();
  in->intrinsics = f.intrinsics;
  in->options = options;
  if (f.color_bgr.empty()) {
    in->why_not = "the frame has no colour (odometry needs it)";
    return in;
  }
  cv::Mat gray, depth;
  cv::cvtColor(f.color_bgr, gray, cv::COLOR_BGR2GRAY);
  if (options.downscale > 1) {
    const cv::Size size(f.depth_m.cols / options.downscale, f.depth_m.rows / options.downscale);
    cv::resize(gray, gray, size, 0, 0, cv::INTER_AREA);
    cv::resize(f.depth_m, depth, size, 0, 0, cv::INTER_NEAREST);
  } else {
    depth = f.depth_m.clone();
  }
  const size_t usable = static_cast<size_t>(
      cv::countNonZero((depth > options.min_depth_m) & (depth < options.max_depth_m)));
  if (usable < depth.total() / 20) {
    in->why_not = absl::StrCat(
        "too little depth within ", options.min_depth_m, "-", options.max_depth_m, " m to track (",
        usable * 100 / std::max<size_t>(1, depth.total()), " % of the pixels)");
    return in;
  }
  if (options.feature_keypoints > 0) {
    in->color_bgr = f.color_bgr;
    in->depth_m = f.depth_m;
  }
  in->frame = cv::rgbd::OdometryFrame::create(gray, depth);
  BuildPyramids(depth, options, &in->frame->pyramidDepth, &in->frame->pyramidMask);
  try {
    // The source-side cache (pyramids, gradients, normals) of the coming alignment.
    MakeOdometry(f.intrinsics, options)
        ->prepareFrameCache(in->frame, cv::rgbd::OdometryFrame::CACHE_SRC);
  } catch (const cv::Exception& e) {
    in->frame = nullptr;
    in->why_not = absl::StrCat("the frame could not be prepared for odometry: ", e.what());
  }
  return in;
}

struct Tracker::Impl {
  OdometryOptions options;
  cv::Ptr<cv::rgbd::RgbdICPOdometry> odometry;
  CameraIntrinsics intrinsics;  // of the frames the odometry was set up for (full size)

  // The reference keyframe, prepared (frame, keypoints), and its pose; null before the visit's
  // first trackable frame. The inputs keep their frames' full-resolution colour and depth for
  // the feature check: ~2.1 MB each at 640x480, so about 4 MB per tracked visit.
  std::shared_ptr<TrackingInput> reference;
  Eigen::Isometry3d T_world_reference = Eigen::Isometry3d::Identity();
  // The directions the reference's depth leaves free (DepthDegeneracy), found once per
  // reference (~0.1 ms).
  std::vector<std::string> reference_degenerate;
  DepthInformation reference_information;
  // The last frame tracked, prepared, and its pose relative to the reference.
  std::shared_ptr<TrackingInput> last;
  Eigen::Isometry3d T_reference_last = Eigen::Isometry3d::Identity();
  bool last_tracked = false;
  int lost_frames = 0;
  double last_timestamp_s = 0.0;          // of the last frame tracked or lost
  double last_tracked_timestamp_s = 0.0;  // of the last frame tracked
  // The last frame Track reported lost after preparing it, until the next Track: what
  // Relocalise places (its time is `last_timestamp_s`), and its odometry reading.
  std::shared_ptr<TrackingInput> lost;
  std::optional<OdometryReading> lost_odometry;
  // The robot's odometry at the last tracked frame (when it came with one): increments are
  // taken from it.
  std::optional<OdometryReading> last_odometry;
  // The visit's last odometry reading and its frame's time, for CheckOdometry's jump test.
  std::optional<OdometryReading> latest_odometry;
  double latest_odometry_s = 0.0;

  // Makes `input` (prepared, trackable) the reference and the last tracked frame, at
  // `T_world_camera`: the visit's first frame, or a relocalised one.
  void RestartAt(std::shared_ptr<TrackingInput> input, const Eigen::Isometry3d& T_world_camera,
                 double timestamp_s, std::optional<OdometryReading> robot_odometry) {
    last_odometry = std::move(robot_odometry);
    odometry->prepareFrameCache(input->frame, cv::rgbd::OdometryFrame::CACHE_ALL);
    reference = input;
    last = std::move(input);
    T_world_reference = T_world_camera;
    SetReferenceInformation();
    T_reference_last = Eigen::Isometry3d::Identity();
    last_tracked = true;
    last_tracked_timestamp_s = timestamp_s;
    lost_frames = 0;
  }

  // The reference's depth information and the directions it leaves free (~0.1 ms).
  void SetReferenceInformation() {
    reference_information = InformationOf(*reference->frame);
    reference_degenerate =
        FreeDirections(reference_information, T_world_reference.linear(), options.degenerate_share);
  }
};

Tracker::Tracker(OdometryOptions options) : impl_(std::make_unique<Impl>()) {
  impl_->options = options;
}
Tracker::~Tracker() = default;
Tracker::Tracker(Tracker&&) noexcept = default;
Tracker& Tracker::operator=(Tracker&&) noexcept = default;

Pose Tracker::FirstPose(const std::optional<Eigen::Vector3d>& gravity_camera) {
  // The world's axes in camera coordinates: z against gravity, x the camera's forward made
  // horizontal (its right, turned, when it looks straight up or down), y = z × x.
  const Eigen::Vector3d up = gravity_camera && gravity_camera->norm() > 0
                                 ? Eigen::Vector3d(-gravity_camera->normalized())
                                 : Eigen::Vector3d(0, -1, 0);
  Eigen::Vector3d forward = Eigen::Vector3d::UnitZ() - up.z() * up;
  if (forward.norm() < 1e-6) forward = Eigen::Vector3d::UnitX() - up.x() * up;
  forward.normalize();
  Eigen::Matrix3d R;  // rows: the world's x, y, z axes in the camera frame
  R.row(0) = forward;
  R.row(1) = up.cross(forward);
  R.row(2) = up;
  Pose p;
  p.rotation = Eigen::Quaterniond(R).normalized();
  return p;
}

std::optional<Eigen::Vector3d> Tracker::FloorGravity(const cv::Mat& depth_m,
                                                     const CameraIntrinsics& k, double max_tilt_deg,
                                                     double min_area_m2) {
  auto planes = planes::ExtractPlanes(depth_m, k);
  if (!planes.ok()) return std::nullopt;
  const Eigen::Vector3f level_up(0, -1, 0);  // a level camera's up, in its own frame
  const float min_cos = static_cast<float>(std::cos(max_tilt_deg * M_PI / 180.0));
  for (const planes::Plane& p : planes->planes) {  // largest first
    if (p.area_m2 < min_area_m2) break;
    // The floor is below the camera (+y) and faces it: its normal, towards the camera, is up.
    if (p.normal.dot(level_up) < min_cos || p.centroid.y() <= 0) continue;
    return Eigen::Vector3d(-p.normal.cast<double>().normalized());
  }
  return std::nullopt;
}

TrackedPose Tracker::Track(const RgbdFrame& frame, std::shared_ptr<TrackingInput> prepared,
                           const std::optional<Pose>& prior) {
  Impl& m = *impl_;
  m.lost = nullptr;
  m.lost_odometry.reset();
  TrackedPose out;
  auto lose = [&](std::string why) {
    m.last_tracked = false;
    out.state = TrackingState::kLost;
    out.reason = std::move(why);
    out.lost_frames = ++m.lost_frames;
    return out;
  };
  if (m.reference != nullptr && !(frame.timestamp_s > m.last_timestamp_s)) {
    // A frame from the past (reordered or replayed) is not tracked, and changes nothing.
    out.state = TrackingState::kLost;
    out.lost_frames = m.lost_frames;
    out.reason = absl::StrFormat(
        "the frame's time %.6f s is not after the last tracked frame's %.6f s: not tracked",
        frame.timestamp_s, m.last_timestamp_s);
    return out;
  }
  m.last_timestamp_s = frame.timestamp_s;
  if (frame.odometry) {
    m.latest_odometry = frame.odometry;
    m.latest_odometry_s = frame.timestamp_s;
  }
  const CameraIntrinsics& k = frame.intrinsics;
  if (m.odometry == nullptr || !SameCamera(k, m.intrinsics)) {
    if (m.reference != nullptr) return lose("the camera's intrinsics changed within the visit");
    m.intrinsics = k;
    m.odometry = MakeOdometry(k, m.options);
  }
  if (prepared == nullptr || !SamePreparation(prepared->options, m.options) ||
      !SameCamera(prepared->intrinsics, k)) {
    prepared = PrepareForTracking(frame, m.options);
  }
  // With the robot's odometry at this frame and at the last tracked one, their increment moves
  // the last pose: the prediction, and the bound of every estimate (see OdometryOptions).
  std::optional<OdometryStep> odometry_step;
  if (m.reference != nullptr && frame.odometry && m.last_odometry && !prior) {
    odometry_step = StepOf(*m.last_odometry, *frame.odometry, m.options);
  }
  if (prepared->frame == nullptr) {
    if (!odometry_step) return lose(prepared->why_not);
    // No image to align (a dark room, no depth): the odometry places the frame, which cannot
    // become the reference; the next increment is taken from the last frame with images.
    m.last_tracked = false;
    out.state = TrackingState::kTracking;
    out.method = TrackingMethod::kOdometry;
    out.reason = prepared->why_not;
    out.T_world_camera = Pose::FromIsometry(m.T_world_reference * m.T_reference_last *
                                            odometry_step->T_last_current);
    return out;
  }
  cv::Ptr<cv::rgbd::OdometryFrame> current = prepared->frame;
  if (m.reference == nullptr) {
    // The visit's first trackable frame defines its frame.
    std::optional<Eigen::Vector3d> gravity = frame.gravity_camera;
    if (!gravity && !prior) gravity = FloorGravity(frame.depth_m, k);
    m.RestartAt(prepared, prior ? prior->ToIsometry() : FirstPose(gravity).ToIsometry(),
                frame.timestamp_s, frame.odometry);
    out.state = TrackingState::kStarted;
    out.T_world_camera = Pose::FromIsometry(m.T_world_reference);
    return out;
  }
  // Prediction: the last tracked pose. A constant-velocity prediction was tried and dropped: on
  // texture-poor synthetic views an alignment that slid along a wall fed the next prediction,
  // and the estimate ran away (sim seed 3, 300 frames: ATE 5.6 m against 6 mm from the last
  // pose; TUM fr1_xyz unchanged; docs/RESULTS.md).
  // With a prior (a client's pose to refine) it starts from that instead.
  const Eigen::Isometry3d predicted = prior ? m.T_world_reference.inverse() * prior->ToIsometry()
                                      : odometry_step
                                          ? m.T_reference_last * odometry_step->T_last_current
                                          : m.T_reference_last;
  // The dense alignment from `guess`: T_reference_current, or why not. src = the current
  // frame, dst = the reference: Rt maps current-camera points into the reference camera.
  std::string dense_failure;
  auto align = [&](const Eigen::Isometry3d& guess) -> std::optional<Eigen::Isometry3d> {
    cv::Mat Rt;
    try {
      if (m.odometry->compute(current, m.reference->frame, Rt, ToMat(guess)) && !Rt.empty()) {
        return ToIsometry(Rt);
      }
      dense_failure =
          "the view could not be aligned to the reference keyframe (too little overlap, "
          "texture or geometry)";
    } catch (const cv::Exception& e) {
      dense_failure = absl::StrCat("odometry failed: ", e.what());
    }
    return std::nullopt;
  };
  // After lost frames the camera may have moved on: the allowed jump grows with them (OpenCV's
  // own limits still bound it).
  const double allowance = 1.0 + m.lost_frames;
  auto jump_failure = [&](const Eigen::Isometry3d& T_reference_current) -> std::string {
    const Eigen::Isometry3d jump = predicted.inverse() * T_reference_current;
    if (odometry_step) {
      const double gate_m = m.options.odometry_gate_sigmas * odometry_step->sigma_m;
      const double gate_rad = m.options.odometry_gate_sigmas * odometry_step->sigma_rad;
      if (jump.translation().norm() > gate_m || AngleOf(jump) > gate_rad) {
        return absl::StrFormat(
            "the alignment disagreed with the robot's odometry by %.3f m / %.2f deg (allowed "
            "%.3f m / %.2f deg)",
            jump.translation().norm(), AngleOf(jump) * 180 / M_PI, gate_m, gate_rad * 180 / M_PI);
      }
      return "";
    }
    if (jump.translation().norm() > m.options.max_jump_m * allowance ||
        AngleOf(jump) > m.options.max_jump_rad * allowance) {
      return absl::StrCat("the alignment jumped ", jump.translation().norm(), " m / ",
                          AngleOf(jump) * 180 / M_PI, " deg from the prediction");
    }
    return "";
  };
  std::optional<Eigen::Isometry3d> dense = align(predicted);
  std::string dense_jump = dense ? jump_failure(*dense) : "";
  if (!dense_jump.empty()) dense.reset();
  // The feature check (see OdometryOptions), where the dense alignment failed or moved the
  // camera faster than `feature_check_speed_mps` / `feature_check_turn_dps` from the last pose.
  std::optional<Eigen::Isometry3d> by_features;
  bool suspicious = !dense;
  if (dense) {
    const Eigen::Isometry3d step = m.T_reference_last.inverse() * *dense;
    const double dt = std::max(frame.timestamp_s - m.last_tracked_timestamp_s, 1e-3);
    suspicious = step.translation().norm() / dt > m.options.feature_check_speed_mps ||
                 AngleOf(step) * 180 / M_PI / dt > m.options.feature_check_turn_dps;
  }
  if (suspicious && m.options.feature_keypoints > 0) {
    appearance::VerifyOptions verify;
    verify.min_inliers = m.options.feature_min_inliers;
    const appearance::Verification v =
        appearance::VerifyMatch(KeypointsOf(*prepared, m.options.feature_keypoints), k,
                                KeypointsOf(*m.reference, m.options.feature_keypoints), verify);
    if (v.verified && jump_failure(v.T_match_query.ToIsometry()).empty()) {
      by_features = v.T_match_query.ToIsometry();
    }
  }
  Eigen::Isometry3d T_reference_current;
  TrackingMethod method = TrackingMethod::kDense;
  if (dense && (!by_features || Agree(*dense, *by_features, m.options))) {
    T_reference_current = *dense;
  } else if (by_features) {
    // The dense alignment disagreed with the features, or failed: run it again from theirs,
    // and keep whichever estimate the two images agree with best (an earlier one on a tie).
    std::vector<std::pair<TrackingMethod, Eigen::Isometry3d>> candidates;
    if (dense) candidates.push_back({TrackingMethod::kDense, *dense});
    if (auto refit = align(*by_features); refit && jump_failure(*refit).empty()) {
      candidates.push_back({TrackingMethod::kRefit, *refit});
    }
    candidates.push_back({TrackingMethod::kFeatures, *by_features});
    const cv::Mat K = CameraMatrix(k, m.options.downscale);
    double best = -1;
    for (const auto& [how, T] : candidates) {
      const double score = Consistency(*current, *m.reference->frame, K, T);
      if (score > best + 0.01) {
        best = score;
        method = how;
        T_reference_current = T;
      }
    }
  } else if (odometry_step) {
    // Nothing the images gave agrees with the robot's odometry: it places the frame.
    method = TrackingMethod::kOdometry;
    T_reference_current = predicted;
    out.reason = dense_jump.empty() ? dense_failure : dense_jump;
  } else {
    m.lost = prepared;  // for Relocalise, until the next Track
    m.lost_odometry = frame.odometry;
    return lose(dense_jump.empty() ? dense_failure : dense_jump);
  }
  // Where the reference's depth leaves a direction free and the frame came with a prediction of
  // its own (the robot's odometry, a client's pose), the prediction decides it
  // (FollowPriorWhereFree). Without one, neither the last pose nor constant velocity serves: on
  // real hand-held views the pull to the last pose doubled the frame-to-frame error (TUM fr1_desk
  // RPE 8.5 -> 18 mm) and the synthetic walks stayed bent (docs/RESULTS.md "Issue 54 (tracking)").
  if ((odometry_step || prior) &&
      (method == TrackingMethod::kDense || method == TrackingMethod::kRefit)) {
    T_reference_current = FollowPriorWhereFree(T_reference_current, predicted,
                                               m.reference_information, m.options.prior_share);
  }
  out.state = m.lost_frames == 0 ? TrackingState::kTracking : TrackingState::kRegained;
  out.method = method;
  out.degenerate_axes = m.reference_degenerate;
  m.T_reference_last = T_reference_current;
  m.last = prepared;
  m.last_odometry = frame.odometry;
  m.last_tracked_timestamp_s = frame.timestamp_s;
  m.last_tracked = true;
  m.lost_frames = 0;
  out.T_world_camera = Pose::FromIsometry(m.T_world_reference * T_reference_current);
  return out;
}

absl::Status Tracker::CheckOdometry(const RgbdFrame& frame) const {
  const Impl& m = *impl_;
  if (!frame.odometry || !m.latest_odometry || !(frame.timestamp_s > m.latest_odometry_s)) {
    return absl::OkStatus();
  }
  const Eigen::Isometry3d step = m.latest_odometry->T_odom_camera.ToIsometry().inverse() *
                                 frame.odometry->T_odom_camera.ToIsometry();
  const double dt = frame.timestamp_s - m.latest_odometry_s;
  // Half a second's worth of the limits on top, for frames close together in time.
  const double max_m = m.options.odometry_max_speed_mps * (dt + 0.5);
  const double max_deg = m.options.odometry_max_turn_dps * (dt + 0.5);
  const double moved_m = step.translation().norm(), turned_deg = AngleOf(step) * 180 / M_PI;
  if (moved_m > max_m || turned_deg > max_deg) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "frame.odometry.pose jumped %.2f m / %.1f deg in %.3f s since the visit's previous "
        "reading (at most %.2f m / %.1f deg: %.1f m/s, %.0f deg/s): odometry drifts, it does not "
        "jump; send the same odometry frame throughout a visit, or start a new visit after a "
        "reset",
        moved_m, turned_deg, dt, max_m, max_deg, m.options.odometry_max_speed_mps,
        m.options.odometry_max_turn_dps));
  }
  return absl::OkStatus();
}

TrackedPose Tracker::Relocalise(const Pose& T_world_camera) {
  Impl& m = *impl_;
  TrackedPose out;
  if (m.lost == nullptr) {
    out.state = m.last_tracked ? TrackingState::kTracking : TrackingState::kLost;
    out.lost_frames = m.lost_frames;
    out.reason = "only a frame just lost (with usable depth) can be relocalised";
    return out;
  }
  m.RestartAt(std::move(m.lost), T_world_camera.ToIsometry(), m.last_timestamp_s,
              std::move(m.lost_odometry));
  out.state = TrackingState::kRegained;
  out.method = TrackingMethod::kRelocalised;
  out.T_world_camera = T_world_camera;
  return out;
}

void Tracker::PromoteLastToReference() {
  Impl& m = *impl_;
  if (!m.last_tracked || m.last == nullptr || m.last == m.reference) return;
  m.odometry->prepareFrameCache(m.last->frame, cv::rgbd::OdometryFrame::CACHE_ALL);
  m.T_world_reference = m.T_world_reference * m.T_reference_last;
  m.reference = m.last;
  m.T_reference_last = Eigen::Isometry3d::Identity();
  m.SetReferenceInformation();
}

}  // namespace lifemap::tracking
