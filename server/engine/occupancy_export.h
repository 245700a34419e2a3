// Occupancy of a map without any model (issue 37): the stored keyframes' depth ray-cast into an
// OctoMap OcTree (occupied where depth ended, free along each ray), and that octree cut between
// the floor and the robot's height into a 2D occupancy grid in the ROS map_server format (PGM +
// YAML), the input of a navigation stack. ExportMap's EXPORT_OCCUPANCY_OCTREE_BT and
// EXPORT_OCCUPANCY_GRID_PGM.
//
// Frame: the map's (a visit's own with visit_id), z up, as TUM's motion capture, lifemap sim and
// the server's tracked visits (levelled by gravity or the floor) have it.
#pragma once

#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "server/store/store.h"

namespace lifemap::server {

struct OccupancyOptions {
  double resolution_m = 0.05;  // voxel edge; [0.01, 1]
  int pixel_stride = 4;        // every stride-th pixel's depth is a ray; [1, 16]
  double max_range_m = 4.0;    // depth beyond is free space up to here only (noise grows)
};

struct OccupancyGridOptions {
  // The floor's height in the map's frame; unset: the most populated height of occupied voxels
  // below the cameras (the floor seen; say it when the floor is not in view).
  std::optional<double> floor_z;
  double min_height_m = 0.10;  // above the floor: the band an obstacle must reach into
  double max_height_m = 1.50;  // ... the robot's height
};

struct OccupancyExport {
  std::string octree_bt;  // OctoMap binary (.bt): occupancy, octovis and octomap::OcTree read it
  int64_t keyframes_used = 0;
  uint64_t occupied_voxels = 0;
  std::vector<std::string> left_out;  // map-level: visits not in the map's frame, and why
};

// A ROS map_server grid: cells row-major from the top row (largest y) as PGM stores them;
// 0 occupied, 254 free, 205 unknown (the ROS defaults for thresholds 0.65 / 0.196).
struct OccupancyGrid {
  int width = 0;
  int height = 0;
  double resolution_m = 0;
  double origin_x = 0, origin_y = 0;  // the lower-left cell's corner in the map's frame
  double floor_z = 0;
  bool floor_estimated = false;
  double min_height_m = 0, max_height_m = 0;
  std::vector<uint8_t> cells;
  int64_t keyframes_used = 0;
  std::vector<std::string> left_out;
  uint64_t occupied_cells = 0, free_cells = 0;

  std::string ToPgm() const;  // binary P5, maxval 255 (the YAML is the client's to write)
};

// `visit_id` 0: the map's visits in its frame (the others in `left_out`); else that visit in its
// own frame. FAILED_PRECONDITION when no keyframe has a pose (there); DATA_LOSS for a keyframe
// that does not decode; CANCELLED when `cancelled` says so between keyframes.
absl::StatusOr<OccupancyExport> ExportOccupancy(store::Store* store, int64_t map_id,
                                                const std::string& map_name, int64_t visit_id,
                                                const OccupancyOptions& options,
                                                const std::function<bool()>& cancelled);
absl::StatusOr<OccupancyGrid> ExportOccupancyGrid(store::Store* store, int64_t map_id,
                                                  const std::string& map_name, int64_t visit_id,
                                                  const OccupancyOptions& options,
                                                  const OccupancyGridOptions& grid,
                                                  const std::function<bool()>& cancelled);

}  // namespace lifemap::server
