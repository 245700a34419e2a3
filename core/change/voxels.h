// Within core/change: voxel keys and the walk over posed depth readings that both the visit
// comparison (object_changes.cc) and the surfaces for moved masks (moved_zones.cc) bin.
#pragma once

#include <cmath>
#include <cstdint>
#include <vector>

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "core/change/object_changes.h"

namespace lifemap::change::internal {

// Voxel coordinates packed into one key: 21 bits per axis, offset so that negative indices
// pack (±2^20 voxels: ±52 km at 5 cm).
inline constexpr int64_t kVoxelOffset = int64_t{1} << 20;
inline constexpr int64_t kVoxelMask = (int64_t{1} << 21) - 1;

struct VoxelIndex {
  int64_t x = 0, y = 0, z = 0;
};

inline int64_t Pack(const VoxelIndex& i) {
  return ((i.x + kVoxelOffset) << 42) | ((i.y + kVoxelOffset) << 21) | (i.z + kVoxelOffset);
}
inline VoxelIndex Unpack(int64_t key) {
  return {((key >> 42) & kVoxelMask) - kVoxelOffset, ((key >> 21) & kVoxelMask) - kVoxelOffset,
          (key & kVoxelMask) - kVoxelOffset};
}
// The key of the voxel holding world point `p` (metres), voxels of edge 1 / `inv_voxel_m`.
inline int64_t VoxelKey(const Eigen::Vector3d& p, double inv_voxel_m) {
  return Pack({static_cast<int64_t>(std::floor(p.x() * inv_voxel_m)),
               static_cast<int64_t>(std::floor(p.y() * inv_voxel_m)),
               static_cast<int64_t>(std::floor(p.z() * inv_voxel_m))});
}

// Calls fn(view_index, p_world) for every reading of `views` up to `max_range_m`, back-projected
// by its view's intrinsics into the world frame of its pose.
template <typename Fn>
void ForEachReading(const std::vector<PosedDepth>& views, double max_range_m, Fn&& fn) {
  for (size_t i = 0; i < views.size(); ++i) {
    const PosedDepth& w = views[i];
    const Eigen::Isometry3d T = w.T_world_camera.ToIsometry();
    const auto& k = w.intrinsics;
    for (int v = 0; v < w.depth_m.rows; ++v) {
      const float* row = w.depth_m.ptr<float>(v);
      for (int u = 0; u < w.depth_m.cols; ++u) {
        const double d = row[u];
        if (!(d > 0.0) || d > max_range_m) continue;
        fn(i, T * Eigen::Vector3d((u - k.cx) / k.fx * d, (v - k.cy) / k.fy * d, d));
      }
    }
  }
}

}  // namespace lifemap::change::internal
