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

}  // namespace lifemap::mapping
