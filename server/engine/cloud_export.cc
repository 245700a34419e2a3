#include "server/engine/cloud_export.h"

#include "absl/strings/str_cat.h"
#include "core/mapping/point_cloud.h"

namespace lifemap::server {

absl::StatusOr<CloudExport> ExportCloud(store::Store* store, int64_t map_id,
                                        const std::string& map_name, int64_t visit_id,
                                        double voxel_m, int pixel_stride,
                                        const std::function<bool()>& cancelled) {
  CloudExport out;
  const absl::Status st = store->ForEachKeyframeWithImages(
      map_id, visit_id, [&](const store::KeyframeRecord& k) -> absl::Status {
        if (cancelled && cancelled()) return absl::CancelledError("export cancelled");
        if (!k.T_world_camera) return absl::OkStatus();
        auto frame = DecodeRgbdFrame(store::StoredFrame(k));
        if (!frame.ok()) {
          return absl::DataLossError(absl::StrCat(
              "stored keyframe ", k.id, " cannot be decoded: ", frame.status().message()));
        }
        mapping::AppendBackProjected(*frame, *k.T_world_camera, pixel_stride, &out.points);
        ++out.keyframes_used;
        // Bound memory on large maps: fold into voxels as the cloud grows.
        if (out.points.size() > 4'000'000)
          out.points = mapping::VoxelDownsample(out.points, voxel_m);
        return absl::OkStatus();
      });
  if (!st.ok()) return st;
  if (out.keyframes_used == 0) {
    return absl::FailedPreconditionError(absl::StrCat(
        "no keyframe of map '", map_name,
        "' has a pose; stream with poses (lifemap stream --use-groundtruth) to export a cloud"));
  }
  out.points = mapping::VoxelDownsample(out.points, voxel_m);
  return out;
}

}  // namespace lifemap::server
