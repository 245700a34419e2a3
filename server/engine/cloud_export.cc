#include "server/engine/cloud_export.h"

#include <optional>

#include "absl/strings/str_cat.h"
#include "core/mapping/point_cloud.h"
#include "server/engine/visit_frame.h"

namespace lifemap::server {

absl::StatusOr<CloudExport> ExportCloud(store::Store* store, int64_t map_id,
                                        const std::string& map_name, int64_t visit_id,
                                        double voxel_m, int pixel_stride,
                                        const std::function<bool()>& cancelled,
                                        int64_t keyframe_stride) {
  CloudExport out;
  auto used = ForEachPosedKeyframe(
      store, map_id, map_name, visit_id, cancelled,
      [&](const store::KeyframeRecord& k, const RgbdFrame& frame) {
        mapping::AppendBackProjected(frame, *k.T_world_camera, pixel_stride, &out.points);
        // Bound memory on large maps: fold into voxels as the cloud
        // grows.
        if (out.points.size() > 4'000'000) {
          out.points = mapping::VoxelDownsample(out.points, voxel_m);
        }
        return absl::OkStatus();
      },
      keyframe_stride);
  if (!used.ok()) return used.status();
  out.keyframes_used = used->used;
  out.left_out = used->left_out;
  out.points = mapping::VoxelDownsample(out.points, voxel_m);
  return out;
}

}  // namespace lifemap::server
