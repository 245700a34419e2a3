#include "core/place/floor_plan.h"

#include <algorithm>
#include <cmath>
#include <functional>
#include <limits>
#include <map>
#include <optional>
#include <unordered_map>

#include <Eigen/Geometry>

#include "absl/strings/str_cat.h"
#include "core/place/floor_plan_steps.h"

namespace lifemap::place {

using steps::Cell;
using steps::FloorSighting;
using steps::Key;
using steps::kRayRangeM;
using steps::Patch;
using steps::Sighting;
using steps::WallAcc;

namespace {

double Deg(double d) { return d * M_PI / 180.0; }

// Where two 2D lines p + s·d meet; false when (nearly) parallel.
bool Intersect(const Eigen::Vector2d& p1, const Eigen::Vector2d& d1, const Eigen::Vector2d& p2,
               const Eigen::Vector2d& d2, Eigen::Vector2d* x) {
  const double den = d1.x() * d2.y() - d1.y() * d2.x();
  if (std::abs(den) < std::sin(Deg(20))) return false;
  const Eigen::Vector2d w = p2 - p1;
  const double s = (w.x() * d2.y() - w.y() * d2.x()) / den;
  *x = p1 + s * d1;
  return true;
}

// The q-quantile (0..1) of `values` (nearest rank; 0 for none).
double Quantile(std::vector<double> values, double q) {
  if (values.empty()) return 0;
  const size_t rank = static_cast<size_t>(std::ceil(q * static_cast<double>(values.size())));
  const size_t i = std::min(values.size() - 1, rank > 0 ? rank - 1 : 0);
  std::nth_element(values.begin(), values.begin() + static_cast<std::ptrdiff_t>(i), values.end());
  return values[i];
}

}  // namespace

struct FloorPlanBuilder::State {
  FloorPlanOptions o;
  Eigen::Vector3d up, e1, e2;
  int keyframes = 0;
  // Key frames waiting for a floor to level the plan by (FloorPlanOptions::up_from_floor), and
  // whether `up` is settled (taken from a floor, or world_up after waiting).
  struct Waiting {
    planes::PlaneSet planes;
    CameraIntrinsics k;
    Pose pose;
  };
  std::vector<Waiting> waiting;
  bool up_settled = false;
  std::vector<Eigen::Vector3d> cameras;  // world positions
  std::vector<WallAcc> walls;
  std::vector<Patch> patches;
  std::vector<FloorSighting> floor_sightings;  // one a key frame that saw one (FloorAgreement)

  Eigen::Vector2d Ground(const Eigen::Vector3d& p) const { return {e1.dot(p), e2.dot(p)}; }

  // `up` (unit) and a ground-plane basis for it: e1 the world's x (else y) made horizontal.
  void SetUp(const Eigen::Vector3d& unit_up) {
    up = unit_up;
    const Eigen::Vector3d any =
        std::abs(up.x()) < 0.9 ? Eigen::Vector3d::UnitX() : Eigen::Vector3d::UnitY();
    e1 = (any - any.dot(up) * up).normalized();
    e2 = up.cross(e1);
  }
  void Fold(const planes::PlaneSet& planes, const CameraIntrinsics& k, const Pose& pose);
};

FloorPlanBuilder::FloorPlanBuilder(FloorPlanOptions options) : s_(std::make_unique<State>()) {
  s_->o = options;
  s_->SetUp(options.world_up.normalized());
  s_->up_settled = !options.up_from_floor;
}
FloorPlanBuilder::~FloorPlanBuilder() = default;
FloorPlanBuilder::FloorPlanBuilder(FloorPlanBuilder&&) noexcept = default;
FloorPlanBuilder& FloorPlanBuilder::operator=(FloorPlanBuilder&&) noexcept = default;
int FloorPlanBuilder::keyframes() const {
  return s_->keyframes + static_cast<int>(s_->waiting.size());
}

namespace {

// The up a key frame's floor gives (FloorPlanOptions::up_from_floor), in the world frame, if it
// shows one: its largest upward plane of level_min_area_m2 or more, below the camera, near
// `prior_up`.
std::optional<Eigen::Vector3d> FloorUp(const planes::PlaneSet& planes, const Pose& pose,
                                       const Eigen::Vector3d& prior_up, const FloorPlanOptions& o) {
  const Eigen::Matrix3d R = pose.rotation.toRotationMatrix();
  const double min_cos = std::cos(Deg(o.floor_search_deg));
  for (const auto& p : planes.planes) {  // largest first
    if (p.area_m2 < o.level_min_area_m2) break;
    const Eigen::Vector3d n = (R * p.normal.cast<double>()).normalized();
    const Eigen::Vector3d below = R * p.centroid.cast<double>();  // from the camera
    if (n.dot(prior_up) > min_cos && below.dot(prior_up) < -o.floor_below_cameras_m) return n;
  }
  return std::nullopt;
}

}  // namespace

absl::Status FloorPlanBuilder::AddKeyframe(const planes::PlaneSet& planes,
                                           const CameraIntrinsics& k, const Pose& T_world_camera) {
  State& s = *s_;
  const Pose& pose = T_world_camera;
  if (!pose.translation.allFinite() || !pose.rotation.coeffs().allFinite() ||
      std::abs(pose.rotation.norm() - 1.0) > 1e-3) {
    return absl::InvalidArgumentError(
        "key frame pose must be finite with a unit quaternion (T_world_camera)");
  }
  const cv::Mat& depth = planes.smoothed_depth_m;
  if (!depth.empty() && (depth.cols != k.width || depth.rows != k.height || !(k.fx > 0))) {
    return absl::InvalidArgumentError("intrinsics do not match the key frame's depth image");
  }
  if (s.up_settled) {
    s.Fold(planes, k, pose);
    return absl::OkStatus();
  }
  s.waiting.push_back({planes, k, pose});
  const std::optional<Eigen::Vector3d> floor_up = FloorUp(planes, pose, s.up, s.o);
  if (!floor_up && static_cast<int>(s.waiting.size()) < s.o.level_max_wait_keyframes) {
    return absl::OkStatus();
  }
  if (floor_up) s.SetUp(*floor_up);
  s.up_settled = true;
  for (const auto& w : s.waiting) s.Fold(w.planes, w.k, w.pose);
  s.waiting.clear();
  return absl::OkStatus();
}

void FloorPlanBuilder::State::Fold(const planes::PlaneSet& planes, const CameraIntrinsics& k,
                                   const Pose& pose) {
  State& s = *this;
  const cv::Mat& depth = planes.smoothed_depth_m;
  const Eigen::Matrix3d R = pose.rotation.toRotationMatrix();
  const Eigen::Vector3d& origin = pose.translation;
  const double cos_vertical = std::sin(Deg(s.o.vertical_tolerance_deg));
  const double cos_horizontal = std::cos(Deg(s.o.horizontal_tolerance_deg));
  const double cell = s.o.cell_m;

  const double cos_floor_search = std::cos(Deg(s.o.floor_search_deg));
  // The key frame's floor: its lowest upward plane of min_floor_sighting_m2 or more below the
  // camera. The largest one was a table top in some key frames (building seed 11: 0.78 m above
  // the floor), and a rigid track then looked bent.
  std::optional<FloorSighting> floor_sighting;
  for (const auto& p : planes.planes) {
    const Eigen::Vector3d n = R * p.normal.cast<double>();
    const Eigen::Vector3d c = R * p.centroid.cast<double>() + origin;
    const double cos_up = n.dot(s.up);
    if (cos_up > cos_floor_search && p.area_m2 >= s.o.min_floor_sighting_m2 &&
        c.dot(s.up) < origin.dot(s.up) - s.o.floor_below_cameras_m &&
        (!floor_sighting || c.dot(s.up) < floor_sighting->height)) {
      floor_sighting = {std::acos(std::min(1.0, cos_up)) * 180.0 / M_PI, c.dot(s.up)};
    }
    if (std::abs(cos_up) > cos_horizontal) {
      Patch patch;
      patch.height = c.dot(s.up);
      patch.centroid = s.Ground(c);
      patch.lo = patch.hi = patch.centroid;
      for (const auto& q : p.quads) {
        const Eigen::Vector2d g = s.Ground(R * q.cast<double>() + origin);
        patch.lo = patch.lo.cwiseMin(g);
        patch.hi = patch.hi.cwiseMax(g);
      }
      patch.area = p.area_m2;
      patch.faces_up = cos_up > 0;
      s.patches.push_back(patch);
      continue;
    }
    if (std::abs(cos_up) > cos_vertical) continue;  // slanted: neither wall nor floor
    const Eigen::Vector2d n2 = s.Ground(n).normalized();
    const double offset = n2.dot(s.Ground(c));
    WallAcc* acc = nullptr;
    for (auto& w : s.walls) {
      if (w.n.dot(n2) > std::cos(Deg(s.o.merge_angle_deg)) &&
          std::abs(w.offset - offset) < s.o.merge_offset_m) {
        acc = &w;
        break;
      }
    }
    if (acc == nullptr) {
      s.walls.emplace_back();
      acc = &s.walls.back();
      acc->n = n2;
      acc->offset = offset;
    } else {
      // The line settles on the area-weighted mean of what was seen.
      const double a = acc->area, b = p.area_m2;
      acc->n = (acc->n * a + n2 * b).normalized();
      acc->offset = (acc->offset * a + offset * b) / std::max(a + b, 1e-9);
    }
    acc->area += p.area_m2;
    const Eigen::Vector2d t = acc->tangent();
    Sighting sighting{std::numeric_limits<double>::max(), std::numeric_limits<double>::lowest(),
                      s.Ground(origin), p.area_m2};
    // Rasterise each region's quad into covered cells by sampling it finely enough.
    for (size_t q = 0; q + 3 < p.quads.size(); q += 4) {
      Eigen::Vector3d w[4];
      for (int i = 0; i < 4; ++i) w[i] = R * p.quads[q + i].cast<double>() + origin;
      const double edge = std::max((w[1] - w[0]).norm(), (w[3] - w[0]).norm());
      const int steps = std::clamp(static_cast<int>(std::ceil(2 * edge / cell)), 1, 64);
      for (int i = 0; i <= steps; ++i) {
        const double a = static_cast<double>(i) / steps;
        const Eigen::Vector3d top = w[0] + a * (w[1] - w[0]), bottom = w[3] + a * (w[2] - w[3]);
        for (int j = 0; j <= steps; ++j) {
          const Eigen::Vector3d x = top + (static_cast<double>(j) / steps) * (bottom - top);
          const double along = t.dot(s.Ground(x));
          sighting.s0 = std::min(sighting.s0, along), sighting.s1 = std::max(sighting.s1, along);
          const int si = static_cast<int>(std::floor(along / cell));
          const int hi = static_cast<int>(std::floor(x.dot(s.up) / cell));
          acc->cells[Key(si, hi)].covered += 1;
        }
      }
    }
    if (sighting.s0 <= sighting.s1) acc->sightings.push_back(sighting);
  }

  // Evidence rays: through each wall the camera faces, where does the reading lie?
  if (!depth.empty()) {
    const Eigen::Vector2d o2 = s.Ground(origin);
    const double oh = origin.dot(s.up);
    for (auto& w : s.walls) {
      // Small faces (clutter, furniture sides) are not worth the rays; a wall passes this
      // size within a key frame or two.
      if (w.area < 0.5 * s.o.min_wall_m2) continue;
      const double side = w.side(o2);
      if (side <= 0.05) continue;  // the camera is behind (or on) this wall's line
      const Eigen::Vector2d t = w.tangent();
      for (int v = s.o.ray_stride_px / 2; v < depth.rows; v += s.o.ray_stride_px) {
        const float* row = depth.ptr<float>(v);
        for (int u = s.o.ray_stride_px / 2; u < depth.cols; u += s.o.ray_stride_px) {
          // Camera ray with unit z, so the parameter along it is the depth.
          const Eigen::Vector3d d = R * Eigen::Vector3d((u - k.cx) / k.fx, (v - k.cy) / k.fy, 1.0);
          const Eigen::Vector2d d2 = s.Ground(d);
          const double den = w.n.dot(d2);
          if (den > -1e-6) continue;  // parallel to or away from the wall
          const double lambda = (w.offset - w.n.dot(o2)) / den;
          if (lambda <= 0 || lambda > kRayRangeM) continue;
          const Eigen::Vector2d hit2 = o2 + lambda * d2;
          const double hit_h = oh + lambda * d.dot(s.up);
          Cell& c = w.cells[Key(static_cast<int>(std::floor(t.dot(hit2) / cell)),
                                static_cast<int>(std::floor(hit_h / cell)))];
          const float z = row[u];
          const double margin = 0.08 + 0.02 * lambda;
          // A reading on the wall adds nothing: coverage comes from planar regions only (a
          // floor point near the line would otherwise pass for wall).
          // No reading says the line is open there only within the sensor's range (beyond
          // it, a wall gives no reading either).
          if ((!(z > 0) && lambda < s.o.sensor_range_m) || z > lambda + margin) {
            c.free += 1;
          } else if (z < lambda - margin) {
            c.occluded += 1;
          }
        }
      }
    }
  }
  s.cameras.push_back(origin);
  if (floor_sighting) s.floor_sightings.push_back(*floor_sighting);
  ++s.keyframes;
}

absl::Status FloorPlanBuilder::AddDepthKeyframe(const cv::Mat& depth_m, const CameraIntrinsics& k,
                                                const Pose& T_world_camera,
                                                const planes::PlaneOptions& plane_options) {
  auto planes = planes::ExtractPlanes(depth_m, k, plane_options);
  if (!planes.ok()) return planes.status();
  return AddKeyframe(*planes, k, T_world_camera);
}

absl::Status FloorPlanOptions::Validate() const {
  auto bad = [](const char* name, double value, const char* range) {
    return absl::InvalidArgumentError(
        absl::StrCat("floor plan option ", name, " must be ", range, ", got ", value));
  };
  if (!world_up.allFinite() || world_up.norm() < 1e-6) {
    return absl::InvalidArgumentError(
        "floor plan option world_up must be a finite non-zero vector");
  }
  const struct {
    const char* name;
    double value, lo, hi;
  } ranges[] = {
      {"vertical_tolerance_deg", vertical_tolerance_deg, 0.1, 45},
      {"horizontal_tolerance_deg", horizontal_tolerance_deg, 0.1, 45},
      {"merge_angle_deg", merge_angle_deg, 0.1, 45},
      {"merge_offset_m", merge_offset_m, 0.001, 2},
      {"min_wall_m2", min_wall_m2, 0, 100},
      {"min_wall_length_m", min_wall_length_m, 0, 100},
      {"max_wall_gap_m", max_wall_gap_m, 0, 100},
      {"min_wall_top_m", min_wall_top_m, 0, 10},
      {"wall_top_share", wall_top_share, 0, 1},
      {"cell_m", cell_m, 0.005, 1},
      {"min_opening_m", min_opening_m, 0, 10},
      {"door_top_m", door_top_m, 0.5, 10},
      {"window_sill_m", window_sill_m, 0.1, 10},
      {"ray_stride_px", static_cast<double>(ray_stride_px), 1, 256},
      {"sensor_range_m", sensor_range_m, 0.1, 100},
      {"floor_bin_m", floor_bin_m, 0.001, 1},
      {"floor_below_cameras_m", floor_below_cameras_m, 0, 10},
      {"min_floor_m2", min_floor_m2, 0, 1000},
      {"floor_search_deg", floor_search_deg, 1, 89},
      {"min_floor_sighting_m2", min_floor_sighting_m2, 0, 1000},
      {"level_min_area_m2", level_min_area_m2, 0, 1000},
      {"level_max_wait_keyframes", static_cast<double>(level_max_wait_keyframes), 1, 1000},
      {"max_wall_height_m", max_wall_height_m, 0.5, 100},
      {"free_over_covered", free_over_covered, 0, 1000},
      {"min_wall_cells", static_cast<double>(min_wall_cells), 1, 1e6},
      {"furniture_depth_m", furniture_depth_m, 0, 10},
      {"max_join_m", max_join_m, 0, 100},
      {"unseen_wall_cost_m", unseen_wall_cost_m, 0, 100},
      {"max_tread_m2", max_tread_m2, 0, 100},
      {"min_riser_m", min_riser_m, 0, 1},
      {"max_riser_m", max_riser_m, 0, 1},
      {"min_tread_run_m", min_tread_run_m, 0, 5},
      {"max_tread_run_m", max_tread_run_m, 0, 5},
      {"min_treads", static_cast<double>(min_treads), 2, 1000},
  };
  for (const auto& r : ranges) {
    if (!(r.value >= r.lo && r.value <= r.hi)) {
      return bad(r.name, r.value, absl::StrCat("within [", r.lo, ", ", r.hi, "]").c_str());
    }
  }
  if (window_sill_m >= door_top_m) return bad("window_sill_m", window_sill_m, "below door_top_m");
  if (min_riser_m >= max_riser_m) return bad("min_riser_m", min_riser_m, "below max_riser_m");
  if (min_tread_run_m >= max_tread_run_m) {
    return bad("min_tread_run_m", min_tread_run_m, "below max_tread_run_m");
  }
  return absl::OkStatus();
}

namespace steps {

double DistanceToSegment(const Eigen::Vector2d& p, const Eigen::Vector2d& a,
                         const Eigen::Vector2d& b) {
  const Eigen::Vector2d ab = b - a;
  const double len2 = ab.squaredNorm();
  const double t = len2 > 0 ? std::clamp((p - a).dot(ab) / len2, 0.0, 1.0) : 0.0;
  return (a + t * ab - p).norm();
}

// The level is read from the sightings, not from the plan's floor: that is found among all
// upward patches and, on few key frames, can be another surface (building seed 11: 0.78 m off
// at 23 key frames of a rigid track; docs/RESULTS.md).
FloorAgreement AgreeOnFloor(const std::vector<FloorSighting>& sightings) {
  constexpr double kLevelQuantile = 0.25;
  FloorAgreement a;
  a.keyframes = static_cast<int>(sightings.size());
  std::vector<double> tilts, heights;
  for (const auto& f : sightings) {
    tilts.push_back(f.tilt_deg);
    heights.push_back(f.height);
  }
  a.tilt_deg_p90 = Quantile(tilts, 0.9);
  const double level = Quantile(heights, kLevelQuantile);
  const size_t n = heights.size();
  for (size_t part = 0; part < 3 && n >= 3; ++part) {
    const std::vector<double> third(
        heights.begin() + static_cast<std::ptrdiff_t>(part * n / 3),
        heights.begin() + static_cast<std::ptrdiff_t>((part + 1) * n / 3));
    a.drift_m = std::max(a.drift_m, std::abs(Quantile(third, kLevelQuantile) - level));
  }
  return a;
}

absl::StatusOr<double> FindFloor(const std::vector<Patch>& patches, double camera_h,
                                 const FloorPlanOptions& o) {
  const double bin = o.floor_bin_m;
  std::map<int, double> floor_area;
  for (const auto& p : patches) {
    if (p.faces_up && p.height < camera_h - o.floor_below_cameras_m) {
      floor_area[static_cast<int>(std::floor(p.height / bin))] += p.area;
    }
  }
  int best_bin = 0;
  double best_area = 0;
  for (const auto& [b, area] : floor_area) {
    const double a = area + (floor_area.count(b - 1) ? floor_area.at(b - 1) : 0) +
                     (floor_area.count(b + 1) ? floor_area.at(b + 1) : 0);
    if (a > best_area) best_area = a, best_bin = b;
  }
  if (best_area < o.min_floor_m2) {
    return absl::FailedPreconditionError(
        absl::StrCat("no floor seen (largest upward plane below the cameras: ", best_area,
                     " m²); the key frames must see the ground"));
  }
  double sum_h = 0, sum_a = 0;
  for (const auto& p : patches) {
    if (p.faces_up && std::abs(p.height / bin - (best_bin + 0.5)) <= 1.5) {
      sum_h += p.height * p.area, sum_a += p.area;
    }
  }
  return sum_h / sum_a;
}

std::vector<WallCandidate> FindWallCandidates(const std::vector<WallAcc>& walls, double floor,
                                              const FloorPlanOptions& o) {
  // Runs of covered columns (cells between the floor and max_wall_height_m above it) along each
  // wall line. A gap wider than a door splits a line into separate walls: collinear walls on
  // either side of a notch (T, U rooms), or a wall's continuation seen through a door.
  const double cell = o.cell_m;
  const int max_gap = static_cast<int>(std::ceil(o.max_wall_gap_m / cell));
  const auto free_over_covered = static_cast<float>(o.free_over_covered);
  std::vector<WallCandidate> cands;
  for (const auto& w : walls) {
    if (w.area < o.min_wall_m2) continue;
    std::map<int, std::pair<int, double>> columns;  // column -> covered cells, top
    for (const auto& [key, c] : w.cells) {
      // Seen covered but also seen through (rays passed on beyond the line): something that
      // moved (a person walking by, a prop taken away), not the wall.
      if (c.covered <= 0 || (c.free >= free_over_covered && c.free > 2 * c.occluded)) continue;
      const double h = (KeyH(key) + 0.5) * cell - floor;
      if (h < 0 || h > o.max_wall_height_m) continue;
      auto& col = columns[KeyS(key)];
      col.first += 1;
      col.second = std::max(col.second, h);
    }
    const Eigen::Vector2d t = w.tangent(), base = w.n * w.offset;
    for (auto it = columns.begin(); it != columns.end();) {
      // One run: columns no more than max_gap apart.
      std::vector<std::pair<int, int>> run;  // column, cells
      double top = 0;
      int prev = it->first;
      for (; it != columns.end() && it->first - prev <= max_gap; prev = it->first, ++it) {
        run.emplace_back(it->first, it->second.first);
        top = std::max(top, it->second.second);
      }
      int cells = 0;
      for (const auto& r : run) cells += r.second;
      if (cells < o.min_wall_cells || cells * cell * cell < o.min_wall_m2 ||
          top < o.min_wall_top_m) {
        continue;
      }
      // The extent without its outermost 1 % of cells (stray readings).
      int lo_count = 0, hi_count = 0;
      size_t lo = 0, hi = run.size() - 1;
      while (lo < hi && (lo_count += run[lo].second) <= cells / 100) ++lo;
      while (hi > lo && (hi_count += run[hi].second) <= cells / 100) --hi;
      // Furniture ends below the ceiling: where rays passed just above a face's top along most
      // of it, its top was in view, so it is not a wall (nothing is seen above a wall's top).
      int seen_over = 0;
      for (const auto& r : run) {
        float free = 0, occluded = 0;
        for (int h = static_cast<int>(std::floor((floor + top + 0.1) / cell));
             h <= static_cast<int>(std::floor((floor + top + 0.4) / cell)); ++h) {
          auto c = w.cells.find(Key(r.first, h));
          if (c == w.cells.end()) continue;
          free += c->second.free;
          occluded += c->second.occluded;
        }
        seen_over += free >= 1 && free > occluded ? 1 : 0;
      }
      if (seen_over > 0.5 * static_cast<double>(run.size())) continue;
      WallCandidate cand;
      cand.acc = &w;
      cand.s0 = (run[lo].first + 0.5) * cell;
      cand.s1 = (run[hi].first + 0.5) * cell;
      cand.top = top;
      cand.seen_m2 = cells * cell * cell;
      if (cand.length() < o.min_wall_length_m) continue;
      cand.a = base + cand.s0 * t;
      cand.b = base + cand.s1 * t;
      Eigen::Vector2d from(0, 0);
      double from_area = 0;
      for (const auto& v : w.sightings) {
        if (v.s1 >= cand.s0 && v.s0 <= cand.s1) from += v.area * v.from, from_area += v.area;
      }
      if (!(from_area > 0)) continue;
      cand.from = from / from_area;
      cands.push_back(cand);
    }
  }
  return cands;
}

std::vector<WallCandidate> KeepTallWalls(const std::vector<WallCandidate>& cands,
                                         const FloorPlanOptions& o) {
  // Paper 004 keeps the highest large vertical polygons; how high a wall is seen depends on the
  // camera's tilt, so relative to the highest one.
  double highest = 0;
  for (const auto& c : cands) highest = std::max(highest, c.top);
  std::vector<WallCandidate> tall;
  for (const auto& c : cands) {
    if (c.top >= o.wall_top_share * highest) tall.push_back(c);
  }
  return tall;
}

std::vector<WallCandidate> DropHiddenFaces(const std::vector<WallCandidate>& tall,
                                           const FloorPlanOptions& o) {
  // Not the outline: (a) of two parallel faces one behind the other, the shorter — a face less
  // than furniture_depth_m in front of a longer wall is furniture against it (where the wall
  // was hidden behind it), a face behind a longer wall was seen through an opening in it; (b) a
  // face wholly behind another wall kept by (a), seen through it: the sight line from the
  // cameras that saw the face to its middle crosses that wall away from its ends (through a
  // door or window, e.g. the next room's side wall; a wall behind another's line but seen past
  // its end is its neighbour around a reflex corner, as the sides of a U's notch and the walls
  // beside it).
  auto overlap = [](const WallCandidate& on, const WallCandidate& c, double margin) {
    // Share of c's extent, projected onto `on`'s line, within on's extent grown by `margin`
    // metres at either end (shrunk where negative).
    const Eigen::Vector2d t = on.acc->tangent();
    const double c0 = std::min(t.dot(c.a), t.dot(c.b)), c1 = std::max(t.dot(c.a), t.dot(c.b));
    const double lo = std::max(c0, on.s0 - margin), hi = std::min(c1, on.s1 + margin);
    if (c1 - c0 < 0.05) return lo <= hi ? 1.0 : 0.0;
    return std::max(0.0, hi - lo) / (c1 - c0);
  };
  const double gap = o.max_wall_gap_m;  // what furniture may hide of a wall, at either end
  std::vector<WallCandidate> kept;
  for (size_t i = 0; i < tall.size(); ++i) {
    const WallCandidate& c = tall[i];
    bool hidden = false;
    for (size_t j = 0; j < tall.size() && !hidden; ++j) {
      const WallCandidate& other = tall[j];
      if (j == i || other.acc->n.dot(c.acc->n) <= std::cos(Deg(o.merge_angle_deg))) continue;
      const double in_front = c.acc->offset - other.acc->offset;  // of other, along the normal
      hidden = c.length() < other.length() &&
               ((in_front > o.merge_offset_m && in_front < o.furniture_depth_m &&
                 overlap(other, c, gap) > 0.5) ||
                (in_front < -o.merge_offset_m && overlap(other, c, 0.2) > 0.5));
    }
    if (!hidden) kept.push_back(c);
  }
  std::vector<WallCandidate> faces;
  for (const WallCandidate& c : kept) {
    bool hidden = false;
    const Eigen::Vector2d mid = 0.5 * (c.a + c.b);
    for (const WallCandidate& other : kept) {
      if (&other == &c || other.acc->n.dot(c.acc->n) > std::cos(Deg(o.merge_angle_deg))) continue;
      const double at_from = other.acc->side(c.from), at_mid = other.acc->side(mid);
      if (other.acc->side(c.a) >= -0.2 || other.acc->side(c.b) >= -0.2 || at_from <= 0) continue;
      const Eigen::Vector2d cross = c.from + (at_from / (at_from - at_mid)) * (mid - c.from);
      const double along = other.acc->tangent().dot(cross);
      hidden = along > other.s0 + 0.3 && along < other.s1 - 0.3;
      if (hidden) break;
    }
    if (!hidden) faces.push_back(c);
  }
  return faces;
}

Outline ChainOutline(const std::vector<WallCandidate>& faces, const Eigen::Vector2d& centre,
                     const FloorPlanOptions& o) {
  // Walls chained end to start, counter-clockwise (the place on their left), into the closed
  // chain through the largest face that best explains what was seen: the most wall seen along
  // it, the least extension of walls to their corners, the fewest and shortest unseen walls.
  // Walls off the chain (seen through a door, furniture) drop out. Where no chain closes, the
  // walls are ordered by direction from the cameras' centre.
  const double max_join = o.max_join_m;  // metres of extension, both walls together
  auto join = [&](const WallCandidate& p, const WallCandidate& q, Eigen::Vector2d* corner) {
    const Eigen::Vector2d tp = p.acc->tangent(), tq = q.acc->tangent();
    Eigen::Vector2d x;
    if (Intersect(p.a, tp, q.a, tq, &x)) {
      if (tp.dot(x) < p.s0 + 0.3 || tq.dot(x) > q.s1 - 0.3) return 1e9;
      *corner = x;
      // A wall seen on past the corner, behind the other wall's line, was seen through an
      // opening near the corner (the next room's wall on the same line): that overshoot counts
      // a fifth.
      const bool p_past = tp.dot(p.b) > tp.dot(x) && q.acc->side(p.b) < -0.05;
      const bool q_past = tq.dot(q.a) < tq.dot(x) && p.acc->side(q.a) < -0.05;
      return (p_past ? 0.2 : 1.0) * (x - p.b).norm() + (q_past ? 0.2 : 1.0) * (x - q.a).norm();
    }
    if (tp.dot(tq) < 0) return 1e9;  // antiparallel: the other side of the room
    *corner = 0.5 * (p.b + q.a);
    return (p.b - q.a).norm() + std::abs(p.acc->offset - q.acc->offset);
  };
  // A wall not seen at all (hidden behind furniture or people all along, or out of the
  // cameras' view) is a gap between two walls: the chain may cross it from one wall's end to the
  // other's start when the unseen wall would have the place on its left (facing the cameras that
  // saw its neighbours), at a cost of its length and unseen_wall_cost_m.
  constexpr double kMaxUnseen = kRayRangeM;  // metres: no evidence is gathered farther
  struct Link {
    int to;       // face index
    double cost;  // metres
    bool unseen;  // across a wall not seen, from `at` to `unseen_end`
    Eigen::Vector2d at, unseen_end;
  };
  auto across = [&](const WallCandidate& p, const WallCandidate& q, Link* link) {
    const Eigen::Vector2d g = q.a - p.b;
    const double len = g.norm();
    if (len < 0.3 || len > kMaxUnseen) return false;
    const Eigen::Vector2d left(-g.y() / len, g.x() / len);
    if (left.dot(0.5 * (p.from + q.from) - 0.5 * (p.b + q.a)) <= 0.3) return false;
    const Eigen::Vector2d tp = p.acc->tangent(), tq = q.acc->tangent();
    link->at = p.b, link->unseen_end = q.a;
    if (std::abs(tp.dot(tq)) > std::cos(Deg(20))) {
      // Between parallel walls the unseen one runs across them, beyond all that was seen of
      // either (a wall is seen short more often than long).
      const double e = std::max(tp.dot(p.b), tp.dot(q.a));
      link->at = p.b + (e - tp.dot(p.b)) * tp;
      link->unseen_end = q.a + ((e - tp.dot(q.a)) / tp.dot(tq)) * tq;
    }
    link->cost = (link->at - p.b).norm() + (link->unseen_end - q.a).norm() +
                 (link->unseen_end - link->at).norm() + o.unseen_wall_cost_m;
    return true;
  };
  std::vector<std::vector<Link>> links(faces.size());
  for (size_t i = 0; i < faces.size(); ++i) {
    std::vector<Link> gaps;
    for (size_t j = 0; j < faces.size(); ++j) {
      if (j == i) continue;
      Link l{static_cast<int>(j), 0, false, Eigen::Vector2d::Zero(), Eigen::Vector2d::Zero()};
      l.cost = join(faces[i], faces[j], &l.at);
      if (l.cost < max_join) {
        links[i].push_back(l);
      } else if (across(faces[i], faces[j], &l)) {
        l.unseen = true;
        gaps.push_back(l);
      }
    }
    // Only the two nearest gaps: an unseen wall joins neighbours, not any two walls.
    std::sort(gaps.begin(), gaps.end(),
              [](const Link& x, const Link& y) { return x.cost < y.cost; });
    if (gaps.size() > 2) gaps.resize(2);
    links[i].insert(links[i].end(), gaps.begin(), gaps.end());
  }
  size_t largest = 0;
  double seen_total = 0;
  for (size_t i = 0; i < faces.size(); ++i) {
    if (faces[i].seen_m2 > faces[largest].seen_m2) largest = i;
    seen_total += faces[i].length();
  }
  // Depth-first over the chains from the largest face (at most 2 unseen walls in one), with a
  // bound (no chain scores below its cost so far less all the wall length seen) and a budget of
  // expansions, which the few faces and links of a room stay far below. Score: the joins' and
  // unseen walls' costs less the seen length of the walls on the chain (metres).
  std::vector<const Link*> path, best_path;
  std::vector<bool> used(faces.size(), false);
  double best_score = std::numeric_limits<double>::max();
  int budget = 200000;
  std::function<void(size_t, double, double, int)> search = [&](size_t cur, double cost,
                                                                double gained, int unseen) {
    if (--budget < 0 || cost - seen_total >= best_score) return;  // gains at most seen_total
    for (const Link& l : links[cur]) {
      const auto j = static_cast<size_t>(l.to);
      const int u = unseen + (l.unseen ? 1 : 0);
      if (u > 2) continue;
      if (j == largest) {
        const size_t walls = path.size() + 1 + static_cast<size_t>(u);
        if (walls >= 3 && path.size() + 1 >= 2 && cost + l.cost - gained < best_score) {
          best_score = cost + l.cost - gained;
          best_path = path;
          best_path.push_back(&l);
        }
        continue;
      }
      if (used[j]) continue;
      used[j] = true;
      path.push_back(&l);
      search(j, cost + l.cost, gained + faces[j].length(), u);
      path.pop_back();
      used[j] = false;
    }
  };
  used[largest] = true;
  search(largest, 0, faces[largest].length(), 0);
  std::vector<int> chain;              // face index; -1: a wall not seen
  std::vector<Eigen::Vector2d> joins;  // joins[k]: where chain[k] meets chain[k + 1]
  const bool closed = !best_path.empty();
  if (closed) {
    chain.push_back(static_cast<int>(largest));
    for (const Link* l : best_path) {
      joins.push_back(l->at);
      if (l->unseen) {
        chain.push_back(-1);
        joins.push_back(l->unseen_end);
      }
      if (static_cast<size_t>(l->to) != largest) chain.push_back(l->to);
    }
  }
  Outline out;
  if (closed) {
    for (size_t k = 0; k < chain.size(); ++k) {
      out.walls.push_back(chain[k] < 0 ? nullptr : &faces[static_cast<size_t>(chain[k])]);
      out.corners.push_back(joins[(k + chain.size() - 1) % chain.size()]);  // where it starts
    }
    return out;
  }
  for (const auto& f : faces) out.walls.push_back(&f);
  auto angle = [&](const WallCandidate* c) {
    const Eigen::Vector2d m = 0.5 * (c->a + c->b) - centre;
    return std::atan2(m.y(), m.x());
  };
  std::sort(out.walls.begin(), out.walls.end(),
            [&](const WallCandidate* x, const WallCandidate* y) { return angle(x) < angle(y); });
  const size_t m = out.walls.size();
  for (size_t i = 0; i < m; ++i) {
    const WallCandidate& prev = *out.walls[(i + m - 1) % m];
    Eigen::Vector2d x = Eigen::Vector2d::Zero();
    out.corners.push_back(
        join(prev, *out.walls[i], &x) < max_join ? x : 0.5 * (prev.b + out.walls[i]->a));
  }
  return out;
}

std::vector<WallOpening> FindOpenings(const WallCandidate& c, const Wall& wall, double floor,
                                      const FloorPlanOptions& o) {
  // Columns (cells along the wall) whose opening band is open, runs of them.
  const double cell = o.cell_m;
  const Eigen::Vector2d t = c.acc->tangent();
  const double sa = t.dot(wall.start), sb = t.dot(wall.end);
  const int first = static_cast<int>(std::floor(std::min(sa, sb) / cell));
  const int last = static_cast<int>(std::floor(std::max(sa, sb) / cell));
  auto band = [&](int col, double lo, double hi, double* covered_share, bool* open) {
    int cells = 0, covered = 0;
    double free = 0, occluded = 0;
    for (int h = static_cast<int>(std::floor((floor + lo) / cell));
         h < static_cast<int>(std::floor((floor + hi) / cell)); ++h) {
      ++cells;
      auto it = c.acc->cells.find(Key(col, h));
      if (it == c.acc->cells.end()) continue;
      covered += it->second.covered > 0;
      free += it->second.free;
      occluded += it->second.occluded;
    }
    *covered_share = cells ? static_cast<double>(covered) / cells : 0;
    *open = *covered_share < 0.15 && free > 0 && free > occluded;
  };
  std::vector<int> kind(static_cast<size_t>(std::max(0, last - first + 1)), -1);
  for (int col = first; col <= last; ++col) {
    double door_cov, sill_cov, win_cov;
    bool door_open, sill_open, win_open;
    band(col, 0.15, o.door_top_m - 0.2, &door_cov, &door_open);
    band(col, o.window_sill_m + 0.1, o.door_top_m - 0.15, &win_cov, &win_open);
    band(col, 0.3, o.window_sill_m - 0.3, &sill_cov, &sill_open);
    int k = -1;
    if (door_open) {
      k = static_cast<int>(OpeningType::kDoor);
    } else if (win_open && sill_cov > 0.4) {
      k = static_cast<int>(OpeningType::kWindow);
    }
    kind[static_cast<size_t>(col - first)] = k;
  }
  std::vector<WallOpening> openings;
  for (size_t i0 = 0; i0 < kind.size();) {
    if (kind[i0] < 0) {
      ++i0;
      continue;
    }
    size_t i1 = i0;
    while (i1 + 1 < kind.size() && kind[i1 + 1] == kind[i0]) ++i1;
    const double len = static_cast<double>(i1 - i0 + 1) * cell;
    if (len >= o.min_opening_m) {
      WallOpening opening;
      opening.type = static_cast<OpeningType>(kind[i0]);
      // Along the wall from its start corner (s grows from start to end).
      const double from = (first + static_cast<int>(i0)) * cell - sa;
      opening.from_m = std::max(0.0, sb >= sa ? from : -from - len);
      opening.to_m = opening.from_m + len;
      opening.bottom_m = opening.type == OpeningType::kDoor ? 0.0 : o.window_sill_m;
      opening.top_m = o.door_top_m;
      openings.push_back(opening);
    }
    i0 = i1 + 1;
  }
  return openings;
}

void MergeCollinearWalls(std::vector<Wall>* walls, const FloorPlanOptions& o) {
  // Where a wall was seen only in part, the chain crosses the rest as an unseen wall on the
  // same line, or meets a corner twice: collinear neighbours become one wall (its openings
  // measured from the new start) and walls of no length drop out.
  for (bool changed = true; changed && walls->size() > 3;) {
    changed = false;
    for (size_t i = 0; i < walls->size() && walls->size() > 3; ++i) {
      const size_t j = (i + 1) % walls->size();
      Wall& a = (*walls)[i];
      const Wall& b = (*walls)[j];
      const Eigen::Vector2d da = a.end - a.start, db = b.end - b.start;
      const bool tiny = db.norm() < 0.05;
      const bool collinear = da.norm() >= 0.05 && da.normalized().dot(db.normalized()) >
                                                      std::cos(Deg(o.merge_angle_deg));
      if (!tiny && !collinear) continue;
      const double shift = da.norm();
      for (WallOpening opening : b.openings) {
        opening.from_m += shift, opening.to_m += shift;
        a.openings.push_back(opening);
      }
      a.end = b.end;
      a.observed_m2 += b.observed_m2;
      walls->erase(walls->begin() + static_cast<std::ptrdiff_t>(j));
      changed = true;
      break;
    }
  }
}

std::vector<StairFlight> FindStairs(const std::vector<Patch>& patches, double floor,
                                    const std::vector<Wall>& walls, const FloorPlanOptions& o) {
  // Horizontal patches off the floor, grouped by tread (height, place), chained where heights
  // step by a riser and positions by a tread.
  struct Tread {
    double height, area;
    Eigen::Vector2d centroid;
  };
  std::vector<Tread> treads;
  for (const auto& p : patches) {
    const double h = p.height - floor;
    if (!p.faces_up || std::abs(h) < 0.08 || std::abs(h) > 2.0 || p.area > o.max_tread_m2) {
      continue;
    }
    bool merged = false;
    for (auto& t : treads) {
      if (std::abs(t.height - h) < 0.04 && (t.centroid - p.centroid).norm() < 0.3) {
        t.centroid = (t.centroid * t.area + p.centroid * p.area) / (t.area + p.area);
        t.area = std::max(t.area, p.area);
        merged = true;
        break;
      }
    }
    if (!merged) treads.push_back({h, p.area, p.centroid});
  }
  std::vector<StairFlight> flights;
  for (int dir : {1, -1}) {
    std::vector<Tread> side;
    for (const auto& t : treads) {
      if (t.height * dir > 0) side.push_back(t);
    }
    std::sort(side.begin(), side.end(), [&](const Tread& a, const Tread& b) {
      return std::abs(a.height) < std::abs(b.height);
    });
    // The longest chain of treads from any start: the lowest treads of a flight seen from its
    // top are hidden behind the higher ones, so a chain may begin a few steps up.
    std::vector<Tread> flight;
    for (size_t first = 0; first < side.size(); ++first) {
      std::vector<Tread> run_of = {side[first]};
      for (size_t k = first + 1; k < side.size(); ++k) {
        const double rise = std::abs(side[k].height) - std::abs(run_of.back().height);
        const double run = (side[k].centroid - run_of.back().centroid).norm();
        if (rise > o.min_riser_m && rise < o.max_riser_m && run > o.min_tread_run_m &&
            run < o.max_tread_run_m) {
          run_of.push_back(side[k]);
        }
      }
      if (run_of.size() > flight.size()) flight = std::move(run_of);
    }
    if (static_cast<int>(flight.size()) < o.min_treads) continue;
    const double rise = (std::abs(flight.back().height) - std::abs(flight.front().height)) /
                        static_cast<double>(flight.size() - 1);
    // Steps below the first tread seen: its height in risers, which must be whole.
    const double below = std::abs(flight.front().height) / rise - 1;
    if (below < -0.3 || std::abs(below - std::round(below)) > 0.3) continue;
    const int hidden = static_cast<int>(std::lround(std::max(0.0, below)));
    StairFlight f;
    f.ascending = dir > 0;
    f.steps = static_cast<int>(flight.size()) + hidden;
    f.rise_m = rise;
    const double run = (flight.back().centroid - flight.front().centroid).norm() /
                       static_cast<double>(flight.size() - 1);
    f.length_m = run * static_cast<double>(f.steps);
    double area = 0;
    for (const auto& t : flight) area += t.area;
    f.width_m = run > 0 ? area / static_cast<double>(flight.size()) / run : 0;
    f.center = 0.5 * (flight.front().centroid + flight.back().centroid);
    if (hidden > 0 && run > 0) {  // the hidden steps lie before the first tread seen
      const Eigen::Vector2d along = (flight.back().centroid - flight.front().centroid).normalized();
      f.center -= 0.5 * hidden * run * along;
    }
    f.distance_to_wall_m = 1e9;
    for (const auto& w : walls) {
      f.distance_to_wall_m =
          std::min(f.distance_to_wall_m, DistanceToSegment(f.center, w.start, w.end));
    }
    flights.push_back(f);
  }
  return flights;
}

}  // namespace steps

absl::StatusOr<FloorPlan> FloorPlanBuilder::Build() const {
  const State& s = *s_;
  if (keyframes() < 2) {
    return absl::FailedPreconditionError(
        absl::StrCat("a floor plan needs several key frames around the place; have ", keyframes()));
  }
  if (!s.waiting.empty()) {
    return absl::FailedPreconditionError(absl::StrCat(
        "the frame's up is a guess and no key frame has shown a floor to level the plan by yet (",
        s.waiting.size(), " key frames waiting, up to ", s.o.level_max_wait_keyframes, ")"));
  }
  FloorPlan plan;
  plan.keyframes = s.keyframes;
  plan.up = s.up, plan.e1 = s.e1, plan.e2 = s.e2;
  double camera_h = 0;
  Eigen::Vector2d centre(0, 0);
  for (const auto& c : s.cameras) camera_h += c.dot(s.up), centre += s.Ground(c);
  camera_h /= static_cast<double>(s.cameras.size());
  centre /= static_cast<double>(s.cameras.size());

  auto floor = steps::FindFloor(s.patches, camera_h, s.o);
  if (!floor.ok()) return floor.status();
  plan.floor_height_m = *floor;
  plan.floor_agreement = steps::AgreeOnFloor(s.floor_sightings);
  const auto faces = steps::DropHiddenFaces(
      steps::KeepTallWalls(steps::FindWallCandidates(s.walls, *floor, s.o), s.o), s.o);
  if (faces.size() < 3) {
    return absl::FailedPreconditionError(
        absl::StrCat("only ", faces.size(), " walls seen (need 3 or more around the place)"));
  }
  const steps::Outline outline = steps::ChainOutline(faces, centre, s.o);
  const size_t n = outline.walls.size();
  for (size_t i = 0; i < n; ++i) {
    Wall wall;
    wall.start = outline.corners[i];
    wall.end = outline.corners[(i + 1) % n];
    if (const steps::WallCandidate* c = outline.walls[i]; c != nullptr) {
      wall.observed_m2 = c->seen_m2;
      wall.openings = steps::FindOpenings(*c, wall, *floor, s.o);
    }  // else not seen: no area, no openings
    plan.walls.push_back(std::move(wall));
  }
  steps::MergeCollinearWalls(&plan.walls, s.o);
  plan.stairs = steps::FindStairs(s.patches, *floor, plan.walls, s.o);
  return plan;
}

}  // namespace lifemap::place
