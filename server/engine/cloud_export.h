// A map's stored keyframes (or one visit's) as one coloured point cloud: each posed keyframe's
// depth back-projected into the world frame of its stored pose, colour from its image, merged
// on a voxel grid. ExportMap's EXPORT_CLOUD_PLY.
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/io/ply_writer.h"
#include "server/store/store.h"

namespace lifemap::server {

struct CloudExport {
  std::vector<io::ColoredPoint> points;  // one per occupied voxel
  int64_t keyframes_used = 0;            // posed keyframes back-projected
  // Map-level (visit_id 0): the visits left out, not in the map's frame ("visit N: why").
  std::vector<std::string> left_out;
};

// `visit_id` 0: every visit of the map in the map's frame (visit_frame.h; the others are
// listed in `left_out`); else that visit alone, in its own frame. `voxel_m` > 0 and `pixel_stride`
// >= 1 (the caller validates them). FAILED_PRECONDITION naming `map_name` when no keyframe has a
// pose; DATA_LOSS for a stored keyframe that does not decode; CANCELLED when `cancelled` says so
// between keyframes. `keyframe_stride` > 1: every n-th posed keyframe only (the browser view's
// level of detail for large maps). Memory stays bounded on large maps: the cloud is folded into
// voxels as it grows.
absl::StatusOr<CloudExport> ExportCloud(store::Store* store, int64_t map_id,
                                        const std::string& map_name, int64_t visit_id,
                                        double voxel_m, int pixel_stride,
                                        const std::function<bool()>& cancelled,
                                        int64_t keyframe_stride = 1);

}  // namespace lifemap::server
