#include "core/normals/normals.h"

#include <cmath>

#include "absl/strings/str_cat.h"

namespace lifemap::normals {
namespace {

// One pass of the edge-aware box filter along rows (horizontal) or columns.
void SmoothPass(const cv::Mat& in, cv::Mat* out, int radius, float ratio, bool horizontal) {
  *out = cv::Mat(in.size(), CV_32FC1, cv::Scalar(0.0f));
  const int rows = in.rows, cols = in.cols;
  for (int r = 0; r < rows; ++r) {
    const float* src = in.ptr<float>(r);
    float* dst = out->ptr<float>(r);
    for (int c = 0; c < cols; ++c) {
      const float z = src[c];
      if (!(z > 0.0f)) continue;
      const float tolerance = ratio * z;
      float sum = 0.0f;
      int n = 0;
      for (int d = -radius; d <= radius; ++d) {
        float v;
        if (horizontal) {
          const int cc = c + d;
          if (cc < 0 || cc >= cols) continue;
          v = src[cc];
        } else {
          const int rr = r + d;
          if (rr < 0 || rr >= rows) continue;
          v = in.ptr<float>(rr)[c];
        }
        if (v > 0.0f && std::abs(v - z) < tolerance) {
          sum += v;
          ++n;
        }
      }
      dst[c] = sum / static_cast<float>(n);  // n >= 1: the centre itself
    }
  }
}

bool Continuous(const cv::Vec3f& a, const cv::Vec3f& b, float ratio) {
  return a[2] > 0.0f && b[2] > 0.0f && std::abs(a[2] - b[2]) < ratio * std::min(a[2], b[2]);
}

// Accumulates area-weighted triangle normals (the cross product's length is twice the area) at
// the triangle's corners.
void AddTriangle(const cv::Mat& points, cv::Mat* sums, cv::Point p0, cv::Point p1, cv::Point p2) {
  const cv::Vec3f& a = points.at<cv::Vec3f>(p0);
  const cv::Vec3f n = (points.at<cv::Vec3f>(p1) - a).cross(points.at<cv::Vec3f>(p2) - a);
  for (const cv::Point& p : {p0, p1, p2}) sums->at<cv::Vec3f>(p) += n;
}

// Records the count of valid normals; FailedPrecondition when there is none.
absl::StatusOr<NormalMap> Finish(NormalMap out, int valid) {
  out.valid_normals = valid;
  if (valid == 0) {
    return absl::FailedPreconditionError(
        "no pixel has a usable normal: the depth image has no valid neighbouring readings");
  }
  return out;
}

}  // namespace

bool UpperTriangle(const cv::Mat& points, int r, int c, float ratio) {
  if (r + 1 >= points.rows || c + 1 >= points.cols) return false;
  const cv::Vec3f& a = points.at<cv::Vec3f>(r, c);
  const cv::Vec3f& b = points.at<cv::Vec3f>(r + 1, c);
  const cv::Vec3f& d = points.at<cv::Vec3f>(r, c + 1);
  return Continuous(a, b, ratio) && Continuous(a, d, ratio) && Continuous(b, d, ratio);
}

bool LowerTriangle(const cv::Mat& points, int r, int c, float ratio) {
  if (r + 1 >= points.rows || c + 1 >= points.cols) return false;
  const cv::Vec3f& a = points.at<cv::Vec3f>(r, c + 1);
  const cv::Vec3f& b = points.at<cv::Vec3f>(r + 1, c);
  const cv::Vec3f& d = points.at<cv::Vec3f>(r + 1, c + 1);
  return Continuous(a, b, ratio) && Continuous(a, d, ratio) && Continuous(b, d, ratio);
}

absl::Status NormalOptions::Validate() const {
  if (smoothing_radius_px < 0 || smoothing_radius_px > 15) {
    return absl::InvalidArgumentError(
        absl::StrCat("smoothing_radius_px must be within [0, 15], got ", smoothing_radius_px));
  }
  if (neighbor_step_px < 1 || neighbor_step_px > 8) {
    return absl::InvalidArgumentError(
        absl::StrCat("neighbor_step_px must be within [1, 8], got ", neighbor_step_px));
  }
  if (!(max_depth_jump_ratio > 0.0f && max_depth_jump_ratio <= 1.0f)) {
    return absl::InvalidArgumentError(
        absl::StrCat("max_depth_jump_ratio must be within (0, 1], got ", max_depth_jump_ratio));
  }
  return absl::OkStatus();
}

absl::StatusOr<NormalMap> ComputeNormals(const cv::Mat& depth_m, const CameraIntrinsics& k,
                                         const NormalOptions& options) {
  if (auto s = options.Validate(); !s.ok()) return s;
  if (depth_m.empty() || depth_m.type() != CV_32FC1) {
    return absl::InvalidArgumentError("normals need a non-empty CV_32FC1 depth image in metres");
  }
  if (depth_m.cols != k.width || depth_m.rows != k.height) {
    return absl::InvalidArgumentError(absl::StrCat("depth is ", depth_m.cols, "x", depth_m.rows,
                                                   " but the intrinsics say ", k.width, "x",
                                                   k.height));
  }
  if (auto s = k.Validate(); !s.ok()) return s;

  cv::Mat depth = depth_m;
  if (options.smoothing_radius_px > 0) {
    cv::Mat tmp, smoothed;
    SmoothPass(depth_m, &tmp, options.smoothing_radius_px, options.max_depth_jump_ratio, true);
    SmoothPass(tmp, &smoothed, options.smoothing_radius_px, options.max_depth_jump_ratio, false);
    depth = smoothed;
  }

  NormalMap out;
  const int rows = depth.rows, cols = depth.cols;
  out.points = cv::Mat(rows, cols, CV_32FC3, cv::Scalar::all(0));
  out.normals = cv::Mat(rows, cols, CV_32FC3, cv::Scalar::all(0));
  const float inv_fx = static_cast<float>(1.0 / k.fx), inv_fy = static_cast<float>(1.0 / k.fy);
  const float cx = static_cast<float>(k.cx), cy = static_cast<float>(k.cy);
  for (int r = 0; r < rows; ++r) {
    const float* z = depth.ptr<float>(r);
    cv::Vec3f* p = out.points.ptr<cv::Vec3f>(r);
    const float y_scale = (static_cast<float>(r) - cy) * inv_fy;
    for (int c = 0; c < cols; ++c) {
      if (z[c] > 0.0f) {
        p[c] = cv::Vec3f((static_cast<float>(c) - cx) * inv_fx * z[c], y_scale * z[c], z[c]);
      }
    }
  }

  if (options.method == NormalMethod::kMeshVertex) {
    cv::Mat sums(rows, cols, CV_32FC3, cv::Scalar::all(0));
    for (int r = 0; r + 1 < rows; ++r) {
      for (int c = 0; c + 1 < cols; ++c) {
        if (UpperTriangle(out.points, r, c, options.max_depth_jump_ratio)) {
          AddTriangle(out.points, &sums, {c, r}, {c, r + 1}, {c + 1, r});
        }
        if (LowerTriangle(out.points, r, c, options.max_depth_jump_ratio)) {
          AddTriangle(out.points, &sums, {c + 1, r}, {c, r + 1}, {c + 1, r + 1});
        }
      }
    }
    int valid = 0;
    for (int r = 0; r < rows; ++r) {
      const cv::Vec3f* p = out.points.ptr<cv::Vec3f>(r);
      const cv::Vec3f* sum = sums.ptr<cv::Vec3f>(r);
      cv::Vec3f* n = out.normals.ptr<cv::Vec3f>(r);
      for (int c = 0; c < cols; ++c) {
        const float norm = static_cast<float>(cv::norm(sum[c]));
        if (!(norm > 0.0f)) continue;
        n[c] = sum[c] * (1.0f / norm);
        if (n[c].dot(p[c]) > 0.0f) n[c] = -n[c];  // face the camera
        ++valid;
      }
    }
    return Finish(std::move(out), valid);
  }

  // Eq. 2: n = (X[k, l+s] - X[k, l]) x (X[k+s, l] - X[k, l]), normalised. Where the right or
  // lower neighbour is missing or across a depth jump, the left or upper one is used with the
  // sign flipped; the normal is finally turned to face the camera.
  const int s = options.neighbor_step_px;
  const float ratio = options.max_depth_jump_ratio;
  auto usable = [&](const cv::Vec3f& centre, int rr, int cc) {
    if (rr < 0 || rr >= rows || cc < 0 || cc >= cols) return false;
    const float zz = out.points.at<cv::Vec3f>(rr, cc)[2];
    return zz > 0.0f && std::abs(zz - centre[2]) < ratio * centre[2];
  };
  int valid = 0;
  for (int r = 0; r < rows; ++r) {
    const cv::Vec3f* p = out.points.ptr<cv::Vec3f>(r);
    cv::Vec3f* n = out.normals.ptr<cv::Vec3f>(r);
    for (int c = 0; c < cols; ++c) {
      const cv::Vec3f& x = p[c];
      if (!(x[2] > 0.0f)) continue;
      cv::Vec3f du, dv;
      if (usable(x, r, c + s)) {
        du = p[c + s] - x;
      } else if (usable(x, r, c - s)) {
        du = x - p[c - s];
      } else {
        continue;
      }
      if (usable(x, r + s, c)) {
        dv = out.points.at<cv::Vec3f>(r + s, c) - x;
      } else if (usable(x, r - s, c)) {
        dv = x - out.points.at<cv::Vec3f>(r - s, c);
      } else {
        continue;
      }
      cv::Vec3f cross = du.cross(dv);
      const float norm = static_cast<float>(cv::norm(cross));
      if (!(norm > 0.0f)) continue;
      cross *= 1.0f / norm;
      if (cross.dot(x) > 0.0f) cross = -cross;  // face the camera
      n[c] = cross;
      ++valid;
    }
  }
  return Finish(std::move(out), valid);
}

}  // namespace lifemap::normals
