#include "server/engine/occupancy_export.h"

#include <octomap/OcTree.h>

#include <algorithm>
#include <cmath>
#include <map>
#include <memory>
#include <optional>
#include <sstream>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/mapping/point_cloud.h"
#include "server/engine/visit_frame.h"

namespace lifemap::server {
namespace {

constexpr uint8_t kOccupied = 0;
constexpr uint8_t kFree = 254;
constexpr uint8_t kUnknown = 205;

struct Built {
  std::unique_ptr<octomap::OcTree> tree;
  int64_t keyframes_used = 0;
  std::vector<std::string> left_out;
  std::vector<double> camera_z;  // of the keyframes used
};

// OctoMap's own ray casting (insertPointCloud: each ray's cells free, its end occupied, by the
// sensor model's log-odds): the library's method, not ours.
absl::StatusOr<Built> Build(store::Store* store, int64_t map_id, const std::string& map_name,
                            int64_t visit_id, const OccupancyOptions& options,
                            const std::function<bool()>& cancelled) {
  Built out;
  out.tree = std::make_unique<octomap::OcTree>(options.resolution_m);
  std::vector<io::ColoredPoint> points;
  auto used = ForEachPosedKeyframe(
      store, map_id, map_name, visit_id, cancelled,
      [&](const store::KeyframeRecord& k, const RgbdFrame& frame) {
        points.clear();
        mapping::AppendBackProjected(frame, *k.T_world_camera, options.pixel_stride, &points);
        const Eigen::Vector3d& origin = k.T_world_camera->translation;
        octomap::Pointcloud scan;
        scan.reserve(points.size());
        for (const auto& p : points) scan.push_back(p.x, p.y, p.z);
        out.tree->insertPointCloud(
            scan,
            octomap::point3d(static_cast<float>(origin.x()), static_cast<float>(origin.y()),
                             static_cast<float>(origin.z())),
            options.max_range_m, /*lazy_eval=*/false, /*discretize=*/true);
        out.camera_z.push_back(origin.z());
        return absl::OkStatus();
      });
  if (!used.ok()) return used.status();
  out.keyframes_used = used->used;
  out.left_out = used->left_out;
  out.tree->prune();
  return out;
}

// The floor: of the occupied voxels below the median camera, the height most of them share
// (a floor seen is the largest horizontal surface under the cameras).
std::optional<double> EstimateFloor(const octomap::OcTree& tree, std::vector<double> camera_z) {
  std::nth_element(camera_z.begin(), camera_z.begin() + camera_z.size() / 2, camera_z.end());
  const double below = camera_z[camera_z.size() / 2];
  const double res = tree.getResolution();
  std::map<int64_t, double> count;  // by height bin: voxel volume (leaves merge when pruned)
  for (auto it = tree.begin_leafs(), end = tree.end_leafs(); it != end; ++it) {
    if (!tree.isNodeOccupied(*it) || it.getZ() >= below) continue;
    const double cells = std::pow(it.getSize() / res, 2.0);
    count[static_cast<int64_t>(std::floor(it.getZ() / res))] += cells;
  }
  if (count.empty()) return std::nullopt;
  const auto best = std::max_element(
      count.begin(), count.end(), [](const auto& a, const auto& b) { return a.second < b.second; });
  return (static_cast<double>(best->first) + 0.5) * res;
}

}  // namespace

absl::StatusOr<OccupancyExport> ExportOccupancy(store::Store* store, int64_t map_id,
                                                const std::string& map_name, int64_t visit_id,
                                                const OccupancyOptions& options,
                                                const std::function<bool()>& cancelled) {
  auto built = Build(store, map_id, map_name, visit_id, options, cancelled);
  if (!built.ok()) return built.status();
  OccupancyExport out;
  std::ostringstream s;
  built->tree->writeBinary(s);  // OctoMap's own .bt writer (maximum-likelihood occupancy)
  out.octree_bt = s.str();
  out.keyframes_used = built->keyframes_used;
  out.left_out = built->left_out;
  for (auto it = built->tree->begin_leafs(), end = built->tree->end_leafs(); it != end; ++it) {
    out.occupied_voxels += built->tree->isNodeOccupied(*it);
  }
  return out;
}

absl::StatusOr<OccupancyGrid> ExportOccupancyGrid(store::Store* store, int64_t map_id,
                                                  const std::string& map_name, int64_t visit_id,
                                                  const OccupancyOptions& options,
                                                  const OccupancyGridOptions& grid_options,
                                                  const std::function<bool()>& cancelled) {
  auto built = Build(store, map_id, map_name, visit_id, options, cancelled);
  if (!built.ok()) return built.status();
  const octomap::OcTree& tree = *built->tree;
  OccupancyGrid grid;
  grid.resolution_m = options.resolution_m;
  grid.keyframes_used = built->keyframes_used;
  grid.left_out = built->left_out;
  grid.min_height_m = grid_options.min_height_m;
  grid.max_height_m = grid_options.max_height_m;
  if (grid_options.floor_z) {
    grid.floor_z = *grid_options.floor_z;
  } else {
    auto floor = EstimateFloor(tree, built->camera_z);
    if (!floor) {
      return absl::FailedPreconditionError(absl::StrCat(
          "map '", map_name,
          "' shows no surface below its cameras to take as the floor: give the floor's height "
          "(--floor-z, metres in the map's frame)"));
    }
    grid.floor_z = *floor;
    grid.floor_estimated = true;
  }
  const double low = grid.floor_z + grid.min_height_m;
  const double high = grid.floor_z + grid.max_height_m;
  double min_x, min_y, min_z, max_x, max_y, max_z;
  tree.getMetricMin(min_x, min_y, min_z);
  tree.getMetricMax(max_x, max_y, max_z);
  const double res = grid.resolution_m;
  grid.origin_x = std::floor(min_x / res) * res;
  grid.origin_y = std::floor(min_y / res) * res;
  grid.width = std::max(1, static_cast<int>(std::ceil((max_x - grid.origin_x) / res)));
  grid.height = std::max(1, static_cast<int>(std::ceil((max_y - grid.origin_y) / res)));
  grid.cells.assign(static_cast<size_t>(grid.width) * static_cast<size_t>(grid.height), kUnknown);
  // A leaf in the band marks the cells under it: occupied wins over free, free over unknown.
  for (auto it = tree.begin_leafs(), end = tree.end_leafs(); it != end; ++it) {
    const double half = it.getSize() / 2;
    if (it.getZ() + half <= low || it.getZ() - half >= high) continue;
    const bool occupied = tree.isNodeOccupied(*it);
    const int x0 = static_cast<int>(std::floor((it.getX() - half - grid.origin_x) / res + 1e-6));
    const int y0 = static_cast<int>(std::floor((it.getY() - half - grid.origin_y) / res + 1e-6));
    const int n = std::max(1, static_cast<int>(std::lround(it.getSize() / res)));
    for (int y = std::max(0, y0); y < std::min(grid.height, y0 + n); ++y) {
      for (int x = std::max(0, x0); x < std::min(grid.width, x0 + n); ++x) {
        // Row 0 is the top of the image: the largest y.
        uint8_t& cell =
            grid.cells[static_cast<size_t>(grid.height - 1 - y) * static_cast<size_t>(grid.width) +
                       static_cast<size_t>(x)];
        if (occupied) {
          cell = kOccupied;
        } else if (cell == kUnknown) {
          cell = kFree;
        }
      }
    }
  }
  for (const uint8_t c : grid.cells) {
    grid.occupied_cells += c == kOccupied;
    grid.free_cells += c == kFree;
  }
  return grid;
}

std::string OccupancyGrid::ToPgm() const {
  std::string out = absl::StrFormat(
      "P5\n# lifemap occupancy grid: %.3f m cells, floor z %.3f m, obstacles %.2f-%.2f m above "
      "it\n%d %d\n255\n",
      resolution_m, floor_z, min_height_m, max_height_m, width, height);
  out.append(cells.begin(), cells.end());
  return out;
}

}  // namespace lifemap::server
