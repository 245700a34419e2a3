#include "core/change/moved_zones.h"

#include <algorithm>
#include <cmath>

#include <Eigen/Geometry>

#include "absl/container/flat_hash_map.h"
#include "core/change/voxels.h"

namespace lifemap::change {

cv::Mat MovedZones(const cv::Mat& depth_i, const std::vector<cv::Mat>& others, int window,
                   float threshold_m) {
  cv::Mat moved(depth_i.size(), CV_8UC1, cv::Scalar(0));
  const int lo = window / 2, hi = window - lo;  // 10: offsets -5 .. +4
  std::vector<float> values;
  values.reserve(static_cast<size_t>(window) * window);
  for (const cv::Mat& depth_j : others) {
    cv::Mat diff(depth_i.size(), CV_32FC1, cv::Scalar(0.0f));
    for (int r = 0; r < diff.rows; ++r) {
      const float* a = depth_i.ptr<float>(r);
      const float* b = depth_j.ptr<float>(r);
      float* d = diff.ptr<float>(r);
      for (int c = 0; c < diff.cols; ++c) d[c] = (a[c] > 0 && b[c] > 0) ? b[c] - a[c] : 0.0f;
    }
    // Median over the window (clipped at the image border); an even window as in the paper.
    for (int r = 0; r < diff.rows; ++r) {
      unsigned char* out = moved.ptr<unsigned char>(r);
      for (int c = 0; c < diff.cols; ++c) {
        if (out[c]) continue;
        values.clear();
        for (int rr = std::max(0, r - lo); rr < std::min(diff.rows, r + hi); ++rr) {
          const float* d = diff.ptr<float>(rr);
          for (int cc = std::max(0, c - lo); cc < std::min(diff.cols, c + hi); ++cc) {
            values.push_back(d[cc]);
          }
        }
        auto mid = values.begin() + static_cast<std::ptrdiff_t>(values.size() / 2);
        std::nth_element(values.begin(), mid, values.end());
        if (*mid > threshold_m) out[c] = 255;
      }
    }
  }
  return moved;
}

SurfacePoints SurfaceOf(const std::vector<PosedDepth>& views, double voxel_m, double max_range_m) {
  struct Sum {
    Eigen::Vector3d sum = Eigen::Vector3d::Zero();
    int n = 0;
  };
  absl::flat_hash_map<int64_t, Sum> voxels;
  const double inv = 1.0 / voxel_m;
  internal::ForEachReading(views, max_range_m, [&](size_t, const Eigen::Vector3d& p) {
    Sum& s = voxels[internal::VoxelKey(p, inv)];
    s.sum += p;
    ++s.n;
  });
  SurfacePoints out;
  out.voxel_m = voxel_m;
  out.points.reserve(voxels.size());
  for (const auto& [unused, s] : voxels) out.points.push_back((s.sum / s.n).cast<float>());
  return out;
}

cv::Mat RenderSurface(const SurfacePoints& surface, const CameraIntrinsics& k, int stride,
                      const Pose& T_world_camera, double max_range_m) {
  stride = std::max(stride, 1);
  const int cols = (k.width + stride - 1) / stride, rows = (k.height + stride - 1) / stride;
  cv::Mat depth(rows, cols, CV_32FC1, cv::Scalar(0.0f));
  const Eigen::Isometry3d T = T_world_camera.ToIsometry().inverse();
  const Eigen::Matrix3f R = T.linear().cast<float>();
  const Eigen::Vector3f t = T.translation().cast<float>();
  const float fx = static_cast<float>(k.fx / stride), fy = static_cast<float>(k.fy / stride);
  const float cx = static_cast<float>(k.cx / stride), cy = static_cast<float>(k.cy / stride);
  const float half_voxel = static_cast<float>(0.5 * surface.voxel_m);
  const float far = static_cast<float>(max_range_m);
  for (const Eigen::Vector3f& p : surface.points) {
    const Eigen::Vector3f X = R * p + t;
    const float z = X.z();
    if (z < 0.1f || z > far) continue;
    const float u = fx * X.x() / z + cx, v = fy * X.y() / z + cy;
    // The pixels the point's voxel covers: half its side either way.
    const float r = half_voxel * fx / z;
    const int u0 = std::max(0, static_cast<int>(std::lround(u - r)));
    const int u1 = std::min(cols - 1, static_cast<int>(std::lround(u + r)));
    const int v0 = std::max(0, static_cast<int>(std::lround(v - r)));
    const int v1 = std::min(rows - 1, static_cast<int>(std::lround(v + r)));
    for (int y = v0; y <= v1; ++y) {
      float* row = depth.ptr<float>(y);
      for (int x = u0; x <= u1; ++x) {
        if (row[x] == 0.0f || z < row[x]) row[x] = z;
      }
    }
  }
  return depth;
}

cv::Mat FullSizeMask(const MovedMask& m, int width, int height) {
  cv::Mat full(height, width, CV_8UC1, cv::Scalar(0));
  const int stride = std::max(m.stride, 1);
  for (int v = 0; v < height; ++v) {
    const int sv = std::min(v / stride, m.mask.rows - 1);
    if (sv < 0) break;
    const uint8_t* in = m.mask.ptr<uint8_t>(sv);
    uint8_t* out = full.ptr<uint8_t>(v);
    for (int u = 0; u < width; ++u) out[u] = in[std::min(u / stride, m.mask.cols - 1)];
  }
  return full;
}

MovedMask MovedAgainst(const cv::Mat& depth_m, const CameraIntrinsics& k,
                       const Pose& T_world_camera, const SurfacePoints& previous,
                       const MovedOptions& options) {
  MovedMask out;
  out.stride = std::max(options.stride, 1);
  PosedDepth now = Subsample(depth_m, k, out.stride, T_world_camera);
  cv::Mat& d = now.depth_m;
  d.setTo(0.0f, d > options.max_range_m);
  const cv::Mat then = RenderSurface(previous, k, out.stride, T_world_camera, options.max_range_m);
  out.compared_pixels = cv::countNonZero((d > 0.0f) & (then > 0.0f));
  out.mask = MovedZones(d, {then}, options.window, options.threshold_m);
  out.moved_pixels = cv::countNonZero(out.mask);
  return out;
}

}  // namespace lifemap::change
