#include "core/change/object_changes.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <deque>
#include <utility>

#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>

#include "absl/container/flat_hash_map.h"
#include "absl/container/flat_hash_set.h"
#include "absl/strings/str_cat.h"
#include "core/change/voxels.h"

namespace lifemap::change {
namespace {

using internal::Pack;
using internal::Unpack;
using internal::VoxelIndex;

// What one visit's readings say of a voxel: how many readings fell in it, from how many of the
// visit's keyframes.
struct Cell {
  int hits = 0;
  int views = 0;
  int last_view = -1;
};
using Grid = absl::flat_hash_map<int64_t, Cell>;

Grid BinReadings(const std::vector<PosedDepth>& views, const ChangeOptions& o) {
  Grid grid;
  const double inv = 1.0 / o.voxel_m;
  internal::ForEachReading(views, o.max_range_m, [&](size_t view, const Eigen::Vector3d& p) {
    Cell& c = grid[internal::VoxelKey(p, inv)];
    ++c.hits;
    if (c.last_view != static_cast<int>(view)) {
      ++c.views;
      c.last_view = static_cast<int>(view);
    }
  });
  return grid;
}

Eigen::Vector3d Center(int64_t key, double voxel_m) {
  const VoxelIndex i = Unpack(key);
  return Eigen::Vector3d((static_cast<double>(i.x) + 0.5) * voxel_m,
                         (static_cast<double>(i.y) + 0.5) * voxel_m,
                         (static_cast<double>(i.z) + 0.5) * voxel_m);
}

// Whether `grid` holds the voxel or any of its 26 neighbours.
bool HeldNearby(const Grid& grid, int64_t key) {
  const VoxelIndex c = Unpack(key);
  for (int64_t dx = -1; dx <= 1; ++dx) {
    for (int64_t dy = -1; dy <= 1; ++dy) {
      for (int64_t dz = -1; dz <= 1; ++dz) {
        if (grid.contains(Pack({c.x + dx, c.y + dy, c.z + dz}))) return true;
      }
    }
  }
  return false;
}

// A view's camera, ready to project world points.
struct Camera {
  const PosedDepth* view = nullptr;
  Eigen::Matrix3d R_camera_world;
  Eigen::Vector3d t_camera_world;
};

std::vector<Camera> Cameras(const std::vector<PosedDepth>& views) {
  std::vector<Camera> out;
  out.reserve(views.size());
  for (const auto& w : views) {
    const Eigen::Isometry3d T = w.T_world_camera.ToIsometry().inverse();
    out.push_back({&w, T.linear(), T.translation()});
  }
  return out;
}

enum class Look { kOutOfView, kOccluded, kSeen, kSeenThrough };

// What one view's readings say of world point `p`: out of its view (or no reading near its
// pixel), a reading within the margin of it (seen), every reading around its pixel beyond it
// by more than the margin (seen through), or something nearer (occluded).
Look LookAt(const Camera& cam, const Eigen::Vector3d& p, const ChangeOptions& o) {
  const Eigen::Vector3d X = cam.R_camera_world * p + cam.t_camera_world;
  const double z = X.z();
  if (z < 0.1 || z > o.max_range_m) return Look::kOutOfView;
  const auto& k = cam.view->intrinsics;
  const int u = static_cast<int>(std::lround(k.fx * X.x() / z + k.cx));
  const int v = static_cast<int>(std::lround(k.fy * X.y() / z + k.cy));
  const cv::Mat& depth = cam.view->depth_m;
  if (u < 1 || v < 1 || u >= depth.cols - 1 || v >= depth.rows - 1) return Look::kOutOfView;
  const double margin = o.seen_through_m + o.depth_noise_ratio * z;
  double nearest = 1e9;
  int readings = 0;
  for (int dv = -1; dv <= 1; ++dv) {
    const float* row = depth.ptr<float>(v + dv);
    for (int du = -1; du <= 1; ++du) {
      const double d = row[u + du];
      if (!(d > 0.0)) continue;
      ++readings;
      if (std::abs(d - z) <= margin) return Look::kSeen;
      nearest = std::min(nearest, d);
    }
  }
  if (readings == 0) return Look::kOutOfView;
  return nearest > z + margin ? Look::kSeenThrough : Look::kOccluded;
}

struct Counts {
  int seen = 0;
  int through = 0;
};
Counts CountLooks(const std::vector<Camera>& cameras, const Eigen::Vector3d& p,
                  const ChangeOptions& o) {
  Counts c;
  for (const auto& cam : cameras) {
    switch (LookAt(cam, p, o)) {
      case Look::kSeen:
        ++c.seen;
        break;
      case Look::kSeenThrough:
        ++c.through;
        break;
      default:
        break;
    }
  }
  return c;
}

struct Cluster {
  std::vector<int64_t> keys;
  std::vector<Eigen::Vector3d> centers;
  Eigen::Vector3d centroid = Eigen::Vector3d::Zero();
  Eigen::Vector3d extent = Eigen::Vector3d::Zero();
  int evidence = 0;
};

// Judged candidates (key → the other visit's seen-through count, or -1 for transient) into
// 26-connected objects of changed voxels. An object whose voxels are transient in at least
// `transient_share` is something passing as a whole (a walker's head is seen only from afar,
// while its body is seen through later): it is dropped, its changed voxels counted in
// `*passing`.
std::vector<Cluster> ClusterVoxels(const absl::flat_hash_map<int64_t, int>& changed,
                                   const ChangeOptions& o, int64_t* passing) {
  std::vector<Cluster> out;
  absl::flat_hash_set<int64_t> done;
  std::vector<int64_t> keys;
  keys.reserve(changed.size());
  for (const auto& [key, unused] : changed) keys.push_back(key);
  std::sort(keys.begin(), keys.end());  // deterministic order of the clusters
  for (int64_t seed : keys) {
    if (!done.insert(seed).second) continue;
    Cluster c;
    std::deque<int64_t> open{seed};
    while (!open.empty()) {
      const int64_t key = open.front();
      open.pop_front();
      c.keys.push_back(key);
      const VoxelIndex i = Unpack(key);
      const int64_t g = o.cluster_gap_voxels;
      for (int64_t dx = -g; dx <= g; ++dx) {
        for (int64_t dy = -g; dy <= g; ++dy) {
          for (int64_t dz = -g; dz <= g; ++dz) {
            const int64_t n = Pack({i.x + dx, i.y + dy, i.z + dz});
            if (changed.contains(n) && done.insert(n).second) open.push_back(n);
          }
        }
      }
    }
    const auto transient = std::count_if(c.keys.begin(), c.keys.end(),
                                         [&](int64_t key) { return changed.at(key) < 0; });
    const int64_t kept = static_cast<int64_t>(c.keys.size()) - transient;
    if (kept == 0) continue;
    if (static_cast<double>(transient) >= o.transient_share * static_cast<double>(c.keys.size())) {
      *passing += kept;
      continue;
    }
    c.keys.erase(std::remove_if(c.keys.begin(), c.keys.end(),
                                [&](int64_t key) { return changed.at(key) < 0; }),
                 c.keys.end());
    Eigen::Vector3d lo = Eigen::Vector3d::Constant(1e18), hi = -lo;
    for (int64_t key : c.keys) {
      const Eigen::Vector3d p = Center(key, o.voxel_m);
      c.centers.push_back(p);
      c.centroid += p;
      lo = lo.cwiseMin(p);
      hi = hi.cwiseMax(p);
      c.evidence = std::max(c.evidence, changed.at(key));
    }
    c.centroid /= static_cast<double>(c.keys.size());
    c.extent = (hi - lo).array() + o.voxel_m;
    if (static_cast<int>(c.keys.size()) >= o.min_object_voxels &&
        c.extent.maxCoeff() >= o.min_object_m) {
      out.push_back(std::move(c));
    }
  }
  return out;
}

absl::Status CheckViews(const std::vector<PosedDepth>& views, const char* which) {
  for (size_t i = 0; i < views.size(); ++i) {
    const auto& w = views[i];
    if (w.depth_m.type() != CV_32FC1 || w.depth_m.cols != w.intrinsics.width ||
        w.depth_m.rows != w.intrinsics.height) {
      return absl::InvalidArgumentError(
          absl::StrCat(which, " view ", i, ": depth must be CV_32FC1 of its intrinsics' size (",
                       w.intrinsics.width, "x", w.intrinsics.height, "), not type ",
                       w.depth_m.type(), " of ", w.depth_m.cols, "x", w.depth_m.rows));
    }
  }
  return absl::OkStatus();
}

// A cluster's shape as a panel: its seen height along `up`, and its length and thickness on
// the ground plane along the principal axes of its voxels (metres, a voxel's edge included).
struct PanelShape {
  double height = 0, length = 0, thickness = 0;
};
PanelShape ShapeOf(const Cluster& c, const ChangeOptions& o) {
  const Eigen::Vector3d up = o.up.normalized();
  const Eigen::Vector3d e1 = up.unitOrthogonal(), e2 = up.cross(e1);
  double lo = 1e18, hi = -1e18;
  Eigen::Vector2d mean = Eigen::Vector2d::Zero();
  std::vector<Eigen::Vector2d> ground;
  for (const auto& p : c.centers) {
    lo = std::min(lo, p.dot(up));
    hi = std::max(hi, p.dot(up));
    ground.emplace_back(p.dot(e1), p.dot(e2));
    mean += ground.back();
  }
  mean /= static_cast<double>(ground.size());
  Eigen::Matrix2d cov = Eigen::Matrix2d::Zero();
  for (const auto& g : ground) cov += (g - mean) * (g - mean).transpose();
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> eig(cov);
  const Eigen::Vector2d across = eig.eigenvectors().col(0), along = eig.eigenvectors().col(1);
  double a_lo = 1e18, a_hi = -1e18, t_lo = 1e18, t_hi = -1e18;
  for (const auto& g : ground) {
    a_lo = std::min(a_lo, g.dot(along));
    a_hi = std::max(a_hi, g.dot(along));
    t_lo = std::min(t_lo, g.dot(across));
    t_hi = std::max(t_hi, g.dot(across));
  }
  return {hi - lo + o.voxel_m, a_hi - a_lo + o.voxel_m, t_hi - t_lo + o.voxel_m};
}

// A door leaf: tall, door-wide and thin across its face.
bool DoorLeaf(const PanelShape& s, const ChangeOptions& o) {
  return s.height >= o.door_min_height_m && s.length >= o.door_min_width_m &&
         s.length <= o.door_max_width_m && s.thickness <= o.door_max_thickness_m;
}

// A wall: tall, longer than any door and thin (a partition put up or taken down).
bool WallPanel(const PanelShape& s, const ChangeOptions& o) {
  return s.height >= o.wall_min_height_m && s.length >= o.wall_min_length_m &&
         s.thickness <= o.wall_max_thickness_m;
}

ObjectChange FromCluster(ChangeKind kind, Cluster&& c) {
  ObjectChange o;
  o.kind = kind;
  o.center = o.from_center = c.centroid;
  o.extent = c.extent;
  o.voxels = static_cast<int>(c.keys.size());
  o.evidence_views = c.evidence;
  o.voxel_centers = std::move(c.centers);
  return o;
}

}  // namespace

PosedDepth Subsample(const cv::Mat& depth_m, const CameraIntrinsics& intrinsics, int stride,
                     const Pose& T_world_camera) {
  stride = std::max(stride, 1);
  PosedDepth out;
  out.T_world_camera = T_world_camera;
  const int cols = (depth_m.cols + stride - 1) / stride,
            rows = (depth_m.rows + stride - 1) / stride;
  out.depth_m.create(rows, cols, CV_32FC1);
  for (int v = 0; v < rows; ++v) {
    const float* in = depth_m.ptr<float>(v * stride);
    float* o = out.depth_m.ptr<float>(v);
    for (int u = 0; u < cols; ++u) o[u] = in[u * stride];
  }
  out.intrinsics = intrinsics;
  out.intrinsics.fx /= stride;
  out.intrinsics.fy /= stride;
  out.intrinsics.cx /= stride;
  out.intrinsics.cy /= stride;
  out.intrinsics.width = cols;
  out.intrinsics.height = rows;
  return out;
}

absl::Status ChangeOptions::Validate() const {
  auto positive = [](double v) { return std::isfinite(v) && v > 0.0; };
  if (!positive(voxel_m) || voxel_m > 1.0) {
    return absl::InvalidArgumentError(absl::StrCat("voxel_m must lie in (0, 1] m, not ", voxel_m));
  }
  if (!positive(max_range_m)) {
    return absl::InvalidArgumentError(absl::StrCat("max_range_m must be > 0, not ", max_range_m));
  }
  if (!positive(seen_through_m)) {
    return absl::InvalidArgumentError(
        absl::StrCat("seen_through_m must be > 0, not ", seen_through_m));
  }
  if (!std::isfinite(depth_noise_ratio) || depth_noise_ratio < 0.0) {
    return absl::InvalidArgumentError(
        absl::StrCat("depth_noise_ratio must be >= 0, not ", depth_noise_ratio));
  }
  if (min_views < 1 || min_free_views < 1 || transient_min_views < 1 || min_object_voxels < 1 ||
      cluster_gap_voxels < 1 || cluster_gap_voxels > 3) {
    return absl::InvalidArgumentError(
        "min_views, min_free_views, transient_min_views and min_object_voxels must be at least "
        "1, cluster_gap_voxels within [1, 3]");
  }
  if (!std::isfinite(min_object_m) || min_object_m < 0.0 || !std::isfinite(max_move_m) ||
      max_move_m < 0.0) {
    return absl::InvalidArgumentError("min_object_m and max_move_m must be >= 0");
  }
  if (!std::isfinite(max_volume_ratio) || max_volume_ratio < 1.0) {
    return absl::InvalidArgumentError(
        absl::StrCat("max_volume_ratio must be >= 1, not ", max_volume_ratio));
  }
  if (!(transient_share > 0.0 && transient_share <= 1.0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("transient_share must lie in (0, 1], not ", transient_share));
  }
  if (!up.allFinite() || std::abs(up.norm() - 1.0) > 1e-3) {
    return absl::InvalidArgumentError("up must be a unit vector");
  }
  if (!(door_min_width_m > 0.0 && door_max_width_m >= door_min_width_m && door_min_height_m > 0.0 &&
        door_max_thickness_m > 0.0)) {
    return absl::InvalidArgumentError(
        "door sizes must be > 0, with door_max_width_m >= door_min_width_m");
  }
  if (!(wall_min_height_m > 0.0 && wall_min_length_m > door_max_width_m &&
        wall_max_thickness_m > 0.0)) {
    return absl::InvalidArgumentError(
        "wall sizes must be > 0, with wall_min_length_m > door_max_width_m (a door is no wall)");
  }
  return absl::OkStatus();
}

const char* ChangeKindName(ChangeKind kind) {
  switch (kind) {
    case ChangeKind::kAppeared:
      return "appeared";
    case ChangeKind::kVanished:
      return "vanished";
    case ChangeKind::kMoved:
      return "moved";
    case ChangeKind::kDoorOpened:
      return "door_opened";
    case ChangeKind::kDoorClosed:
      return "door_closed";
    case ChangeKind::kWallNew:
      return "wall_new";
    case ChangeKind::kWallGone:
      return "wall_gone";
  }
  return "unknown";
}

absl::StatusOr<ObjectChanges> DetectObjectChanges(const std::vector<PosedDepth>& from,
                                                  const std::vector<PosedDepth>& to,
                                                  const ChangeOptions& options) {
  if (auto s = options.Validate(); !s.ok()) return s;
  if (auto s = CheckViews(from, "earlier visit's"); !s.ok()) return s;
  if (auto s = CheckViews(to, "later visit's"); !s.ok()) return s;
  ObjectChanges out;
  const Grid grid_from = BinReadings(from, options);
  const Grid grid_to = BinReadings(to, options);
  const std::vector<Camera> cameras_from = Cameras(from), cameras_to = Cameras(to);

  // The voxels one visit holds (seen from min_views keyframes) and the other has no reading in
  // or next to; judged against the other visit's views (evidence) and its own (transient).
  auto judge = [&](const Grid& mine, const Grid& other, const std::vector<Camera>& own_cameras,
                   const std::vector<Camera>& other_cameras, int64_t* held) {
    std::vector<int64_t> candidates;
    for (const auto& [key, cell] : mine) {
      if (cell.views < options.min_views) continue;
      ++*held;
      if (!HeldNearby(other, key)) candidates.push_back(key);
    }
    out.candidate_voxels += static_cast<int64_t>(candidates.size());
    std::vector<int> verdict(candidates.size(), 0);  // > 0: changed (evidence), -1 transient
    cv::parallel_for_(cv::Range(0, static_cast<int>(candidates.size())), [&](const cv::Range& r) {
      for (int i = r.start; i < r.end; ++i) {
        const Eigen::Vector3d p = Center(candidates[i], options.voxel_m);
        const Counts there = CountLooks(other_cameras, p, options);
        if (there.through < options.min_free_views || there.through <= there.seen) continue;
        const Counts here = CountLooks(own_cameras, p, options);
        const int saw = std::max(here.seen, mine.at(candidates[i]).views);
        // A surface that stays is seen through by its own visit only at its edges; one that
        // passed by is seen through wherever the visit looked again after it had gone.
        const bool transient =
            here.through >= options.transient_min_views && 2 * here.through >= saw;
        verdict[i] = transient ? -1 : there.through;
      }
    });
    absl::flat_hash_map<int64_t, int> judged;
    for (size_t i = 0; i < candidates.size(); ++i) {
      if (verdict[i] != 0) {
        judged[candidates[i]] = verdict[i];
        ++(verdict[i] > 0 ? out.changed_voxels : out.transient_voxels);
      } else {
        ++out.unobserved_voxels;
      }
    }
    return ClusterVoxels(judged, options, &out.passing_voxels);
  };
  std::vector<Cluster> appeared =
      judge(grid_to, grid_from, cameras_to, cameras_from, &out.to_voxels);
  std::vector<Cluster> vanished =
      judge(grid_from, grid_to, cameras_from, cameras_to, &out.from_voxels);

  // Walls and door leaves are walls gone or new and doors opened or closed, never half of a
  // move.
  auto take_panels = [&](std::vector<Cluster>* clusters, ChangeKind wall, ChangeKind door) {
    std::vector<Cluster> rest;
    for (auto& c : *clusters) {
      const PanelShape shape = ShapeOf(c, options);
      if (WallPanel(shape, options)) {
        out.objects.push_back(FromCluster(wall, std::move(c)));
      } else if (DoorLeaf(shape, options)) {
        out.objects.push_back(FromCluster(door, std::move(c)));
      } else {
        rest.push_back(std::move(c));
      }
    }
    *clusters = std::move(rest);
  };
  take_panels(&vanished, ChangeKind::kWallGone, ChangeKind::kDoorOpened);
  take_panels(&appeared, ChangeKind::kWallNew, ChangeKind::kDoorClosed);

  // Moves: the closest vanished/appeared pairs of similar volume, greedily.
  struct Pair {
    double distance;
    size_t v, a;
  };
  std::vector<Pair> pairs;
  for (size_t v = 0; v < vanished.size(); ++v) {
    for (size_t a = 0; a < appeared.size(); ++a) {
      const double d = (vanished[v].centroid - appeared[a].centroid).norm();
      const double nv = static_cast<double>(vanished[v].keys.size());
      const double na = static_cast<double>(appeared[a].keys.size());
      if (d <= options.max_move_m &&
          std::max(nv, na) <= options.max_volume_ratio * std::min(nv, na)) {
        pairs.push_back({d, v, a});
      }
    }
  }
  std::sort(pairs.begin(), pairs.end(), [](const Pair& x, const Pair& y) {
    return std::tie(x.distance, x.v, x.a) < std::tie(y.distance, y.v, y.a);
  });
  std::vector<bool> v_used(vanished.size(), false), a_used(appeared.size(), false);
  for (const Pair& p : pairs) {
    if (v_used[p.v] || a_used[p.a]) continue;
    v_used[p.v] = a_used[p.a] = true;
    ObjectChange moved = FromCluster(ChangeKind::kMoved, std::move(appeared[p.a]));
    moved.from_center = vanished[p.v].centroid;
    moved.evidence_views = std::min(moved.evidence_views, vanished[p.v].evidence);
    moved.from_voxel_centers = std::move(vanished[p.v].centers);
    out.objects.push_back(std::move(moved));
  }
  for (size_t a = 0; a < appeared.size(); ++a) {
    if (!a_used[a])
      out.objects.push_back(FromCluster(ChangeKind::kAppeared, std::move(appeared[a])));
  }
  for (size_t v = 0; v < vanished.size(); ++v) {
    if (!v_used[v])
      out.objects.push_back(FromCluster(ChangeKind::kVanished, std::move(vanished[v])));
  }
  std::stable_sort(
      out.objects.begin(), out.objects.end(),
      [](const ObjectChange& x, const ObjectChange& y) { return x.voxels > y.voxels; });
  return out;
}

}  // namespace lifemap::change
