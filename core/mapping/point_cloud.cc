#include "core/mapping/point_cloud.h"

#include <cmath>
#include <cstdint>
#include <map>
#include <tuple>

namespace lifemap::mapping {

void AppendBackProjected(const RgbdFrame& frame, const Pose& T_world_camera, int pixel_stride,
                         std::vector<io::ColoredPoint>* cloud) {
  const auto& k = frame.intrinsics;
  const Eigen::Isometry3f T = T_world_camera.ToIsometry().cast<float>();
  const int stride = std::max(1, pixel_stride);
  for (int v = 0; v < frame.depth_m.rows; v += stride) {
    const float* depth = frame.depth_m.ptr<float>(v);
    const cv::Vec3b* bgr = frame.color_bgr.ptr<cv::Vec3b>(v);
    for (int u = 0; u < frame.depth_m.cols; u += stride) {
      const float z = depth[u];
      if (!(z > 0.0f)) continue;
      const Eigen::Vector3f p_camera(static_cast<float>((u - k.cx) / k.fx) * z,
                                     static_cast<float>((v - k.cy) / k.fy) * z, z);
      const Eigen::Vector3f p = T * p_camera;
      cloud->push_back({p.x(), p.y(), p.z(), bgr[u][2], bgr[u][1], bgr[u][0]});
    }
  }
}

std::vector<io::ColoredPoint> VoxelDownsample(const std::vector<io::ColoredPoint>& cloud,
                                              double voxel_size_m) {
  struct Accumulator {
    double x = 0, y = 0, z = 0;
    uint32_t r = 0, g = 0, b = 0, n = 0;
  };
  using Key = std::tuple<int64_t, int64_t, int64_t>;
  std::map<Key, Accumulator> voxels;
  const double inv = 1.0 / voxel_size_m;
  for (const auto& p : cloud) {
    const Key key{static_cast<int64_t>(std::floor(p.x * inv)),
                  static_cast<int64_t>(std::floor(p.y * inv)),
                  static_cast<int64_t>(std::floor(p.z * inv))};
    auto& a = voxels[key];
    a.x += p.x, a.y += p.y, a.z += p.z;
    a.r += p.r, a.g += p.g, a.b += p.b;
    ++a.n;
  }
  std::vector<io::ColoredPoint> out;
  out.reserve(voxels.size());
  for (const auto& [key, a] : voxels) {
    out.push_back({static_cast<float>(a.x / a.n), static_cast<float>(a.y / a.n),
                   static_cast<float>(a.z / a.n), static_cast<uint8_t>(a.r / a.n),
                   static_cast<uint8_t>(a.g / a.n), static_cast<uint8_t>(a.b / a.n)});
  }
  return out;
}

absl::StatusOr<cv::Mat> FuseDepth(const RgbdFrame& reference, const std::vector<RgbdFrame>& others,
                                  float tolerance_ratio) {
  if (!reference.T_world_camera) {
    return absl::InvalidArgumentError("depth fusion needs the reference frame's pose");
  }
  const auto& k = reference.intrinsics;
  cv::Mat sum(reference.depth_m.size(), CV_32FC1, cv::Scalar(0.0f));
  cv::Mat count(reference.depth_m.size(), CV_32FC1, cv::Scalar(0.0f));
  reference.depth_m.copyTo(sum);
  cv::Mat(reference.depth_m > 0).convertTo(count, CV_32FC1, 1.0 / 255.0);
  // Readings for pixels the reference did not see: the nearest surface wins (a z-buffer).
  cv::Mat fill(reference.depth_m.size(), CV_32FC1, cv::Scalar(0.0f));
  const Eigen::Isometry3f T_ref_world =
      reference.T_world_camera->ToIsometry().inverse().cast<float>();
  for (const auto& other : others) {
    if (!other.T_world_camera) {
      return absl::InvalidArgumentError("depth fusion needs every frame's pose");
    }
    const Eigen::Isometry3f T = T_ref_world * other.T_world_camera->ToIsometry().cast<float>();
    const auto& ko = other.intrinsics;
    for (int v = 0; v < other.depth_m.rows; ++v) {
      const float* depth = other.depth_m.ptr<float>(v);
      for (int u = 0; u < other.depth_m.cols; ++u) {
        const float z = depth[u];
        if (!(z > 0.0f)) continue;
        const Eigen::Vector3f p =
            T * Eigen::Vector3f(static_cast<float>((u - ko.cx) / ko.fx) * z,
                                static_cast<float>((v - ko.cy) / ko.fy) * z, z);
        if (p.z() <= 0.0f) continue;
        const int ur = static_cast<int>(std::lround(k.fx * p.x() / p.z() + k.cx));
        const int vr = static_cast<int>(std::lround(k.fy * p.y() / p.z() + k.cy));
        if (ur < 0 || vr < 0 || ur >= k.width || vr >= k.height) continue;
        const float zr = reference.depth_m.at<float>(vr, ur);
        if (zr > 0.0f) {
          if (std::abs(p.z() - zr) < tolerance_ratio * zr) {
            sum.at<float>(vr, ur) += p.z();
            count.at<float>(vr, ur) += 1.0f;
          }
        } else {
          float& f = fill.at<float>(vr, ur);
          if (f == 0.0f || p.z() < f) f = p.z();
        }
      }
    }
  }
  cv::Mat fused(reference.depth_m.size(), CV_32FC1, cv::Scalar(0.0f));
  for (int v = 0; v < fused.rows; ++v) {
    for (int u = 0; u < fused.cols; ++u) {
      const float c = count.at<float>(v, u);
      fused.at<float>(v, u) = c > 0 ? sum.at<float>(v, u) / c : fill.at<float>(v, u);
    }
  }
  return fused;
}

}  // namespace lifemap::mapping
