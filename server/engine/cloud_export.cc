#include "server/engine/cloud_export.h"

#include <optional>

#include "absl/strings/str_cat.h"
#include "core/mapping/point_cloud.h"
#include "server/engine/visit_frame.h"

namespace lifemap::server {

absl::StatusOr<CloudExport> ExportCloud(store::Store* store, int64_t map_id,
                                        const std::string& map_name, int64_t visit_id,
                                        double voxel_m, int pixel_stride,
                                        const std::function<bool()>& cancelled) {
  CloudExport out;
  std::optional<MapFrameVisits> frame;
  if (visit_id == 0) {
    auto visits = VisitsInMapFrame(store, map_name);
    if (!visits.ok()) return visits.status();
    frame = *std::move(visits);
    out.left_out = frame->left_out;
  }
  const absl::Status st = store->ForEachKeyframeWithImages(
      map_id, visit_id, [&](const store::KeyframeRecord& k) -> absl::Status {
        if (cancelled && cancelled()) return absl::CancelledError("export cancelled");
        if (!k.T_world_camera) return absl::OkStatus();
        if (frame && frame->in_map_frame.count(k.visit_id) == 0) return absl::OkStatus();
        auto decoded = DecodeRgbdFrame(store::StoredFrame(k));
        if (!decoded.ok()) {
          return absl::DataLossError(absl::StrCat(
              "stored keyframe ", k.id, " cannot be decoded: ", decoded.status().message()));
        }
        mapping::AppendBackProjected(*decoded, *k.T_world_camera, pixel_stride, &out.points);
        ++out.keyframes_used;
        // Bound memory on large maps: fold into voxels as the cloud grows.
        if (out.points.size() > 4'000'000) {
          out.points = mapping::VoxelDownsample(out.points, voxel_m);
        }
        return absl::OkStatus();
      });
  if (!st.ok()) return st;
  if (out.keyframes_used == 0 && !out.left_out.empty()) {
    return absl::FailedPreconditionError(
        absl::StrCat("no posed keyframe of map '", map_name, "' is in the map's frame (",
                     out.left_out.size(), " visits left out: ", out.left_out.front(),
                     "); export one visit with --visit to get it in its own frame"));
  }
  if (out.keyframes_used == 0) {
    return absl::FailedPreconditionError(absl::StrCat(
        "no keyframe of map '", map_name,
        "' has a pose; stream with poses (lifemap stream --use-groundtruth) to export a cloud"));
  }
  out.points = mapping::VoxelDownsample(out.points, voxel_m);
  return out;
}

}  // namespace lifemap::server
