// A place's architecture from posed key frames (paper 004, section 3.3): planes of every key
// frame brought into the world frame, the ground found, large vertical planes become walls
// (line segments ordered around the place) with their openings — doors (reaching the floor, up
// to 2.10 m) and windows (between about 1.2 and 2.10 m) — and stairs (regularly spaced
// parallel horizontal planes, ascending or descending).
//
// Built incrementally: AddKeyframe folds one key frame in (cheap), Build derives the plan.
// The planes of successive key frames are merged per wall line on a grid of 5 cm cells (along
// the line × height) rather than by polygon union (polyclipping): each cell carries the
// evidence the outline and the openings need, which a union of polygons does not — covered
// (a planar region lies there), seen through (a key frame's ray passed it: a reading beyond the
// wall, or none within the sensor's range: glass and far space give none) and occluded (a ray
// stopped in front of it). A wall cell is open where rays pass it more often than they stop in
// front of it (furniture occluding the wall); a cell covered but also seen through held
// something that moved (a person walking by). The outline is the closed chain of walls that
// best explains what was seen (see Build).
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include <Eigen/Core>
#include <opencv2/core.hpp>

#include "absl/status/statusor.h"
#include "core/common/types.h"
#include "core/planes/planes.h"

namespace lifemap::place {

enum class OpeningType { kDoor = 0, kWindow = 1 };

struct WallOpening {
  OpeningType type = OpeningType::kDoor;
  double from_m = 0;  // along the wall from its start corner
  double to_m = 0;
  double bottom_m = 0;  // above the floor
  double top_m = 0;
  double length() const { return to_m - from_m; }
};

struct Wall {
  Eigen::Vector2d start, end;  // ground-plane coordinates (metres); the place is on the left
  double observed_m2 = 0;      // wall area seen
  std::vector<WallOpening> openings;
  double length() const { return (end - start).norm(); }
};

struct StairFlight {
  bool ascending = true;
  int steps = 0;
  double rise_m = 0;    // mean height between treads
  double length_m = 0;  // along the flight
  double width_m = 0;   // across it
  Eigen::Vector2d center{0, 0};
  double distance_to_wall_m = 0;  // from its centre to the nearest wall
};

// How well the key frames agree on the floor. A rigid track sees one level floor; one that
// bends (drift in pitch, roll or height: issue 54) sees it tilt and rise from key frame to key
// frame. From each key frame's lowest upward plane of min_floor_sighting_m2 or more below it
// (within floor_search_deg of the plan's up): the 90th percentile of its tilt from up, and how
// far the floor's level moves over the visit (`drift_m`): the largest difference between the
// 25th-percentile height of the sightings of a third of the key frames (in the order folded)
// and that of all. The low quantile and the thirds: a key frame that saw only a table top
// reports a plane 0.7 m above the floor, never one below it, and tables are seen now and then,
// while a bend moves every later sighting (building seed 41: a rigid 40-frame visit's 90th
// percentile of heights off their median was 0.78 m; docs/RESULTS.md).
struct FloorAgreement {
  int keyframes = 0;  // key frames that saw a floor-like plane (0: nothing to judge by)
  double tilt_deg_p90 = 0;
  double drift_m = 0;
};

struct FloorPlan {
  double floor_height_m = 0;  // along world_up
  FloorAgreement floor_agreement;
  std::vector<Wall> walls;  // counter-clockwise around the place; wall i ends at corner i+1
  std::vector<StairFlight> stairs;
  int keyframes = 0;
  // Ground-plane basis: world point p ↦ (e1·p, e2·p); `up` the frame's up the heights are
  // along. The defaults are a z-up frame's (the builder's with its default `world_up`, and what
  // a plan stored before issue 54 is read in).
  Eigen::Vector3d e1 = Eigen::Vector3d::UnitX(), e2 = Eigen::Vector3d::UnitY(),
                  up = Eigen::Vector3d::UnitZ();
};

struct FloorPlanOptions {
  Eigen::Vector3d world_up = Eigen::Vector3d::UnitZ();  // TUM's mocap and lifemap sim: z up
  // Where `world_up` is a guess (a tracked visit whose first frame showed no floor and came
  // without gravity is tilted as its first camera was: issue 54), the plan takes its up from the
  // floor instead: the normal of the largest upward plane of at least `level_min_area_m2`, more
  // than floor_below_cameras_m below the camera and within floor_search_deg of world_up, in the
  // first key frame that shows one (a table top is as level as the floor). Key frames before it
  // wait; after `level_max_wait_keyframes` without one, world_up stands. FloorPlan::up says
  // which was taken.
  bool up_from_floor = false;
  double level_min_area_m2 = 0.5;
  int level_max_wait_keyframes = 8;
  double vertical_tolerance_deg = 10;    // a plane within this of vertical is a wall candidate
  double horizontal_tolerance_deg = 10;  // ... of horizontal: floor, stairs, tops
  double merge_angle_deg = 10;           // walls of several key frames on one line
  double merge_offset_m = 0.15;
  double min_wall_m2 = 0.6;        // observed area for a wall to enter the plan
  double min_wall_length_m = 0.8;  // seen along the wall (shorter: furniture sides, pillars)
  double max_wall_gap_m = 1.2;     // a wider gap in what was seen of a line splits it in two walls
  double min_wall_top_m = 1.5;     // ... the height above the floor it must be seen up to,
  double wall_top_share = 0.65;    // ... and at least this share of the highest wall's
  double cell_m = 0.05;            // along-wall and height resolution of the evidence grids
  double min_opening_m = 0.4;      // narrower gaps are not openings
  double door_top_m = 2.10;        // paper 004's norms (ISO)
  double window_sill_m = 1.20;
  int ray_stride_px = 8;        // every N-th pixel casts an evidence ray
  double sensor_range_m = 4.0;  // depth beyond which a missing reading says nothing (Kinect: 4.5)
  // The floor: upward area binned by height; the bin with the most area at least this far
  // below the cameras' mean height, with at least this much area.
  double floor_bin_m = 0.02;
  double floor_below_cameras_m = 0.5;
  double min_floor_m2 = 1.0;
  // FloorAgreement: a key frame's floor-like plane is within this of up, at least this large.
  double floor_search_deg = 35;
  double min_floor_sighting_m2 = 0.3;
  // Wall candidates: evidence up to this height above the floor; a covered cell that this many
  // rays passed through (and more than twice as many as stopped in front of it) held something
  // that moved; a run needs this many covered cells.
  double max_wall_height_m = 3.5;
  double free_over_covered = 3;  // rays (2–5 give the same plans on the suite)
  int min_wall_cells = 20;
  // A shorter face less than this in front of a longer parallel wall is furniture against it.
  double furniture_depth_m = 0.8;
  // The outline: joining two walls may extend them this far together (metres); crossing a
  // wall not seen costs its length and this.
  double max_join_m = 2.5;
  double unseen_wall_cost_m = 1.0;
  // Stairs: treads at most this large, a riser and a run between consecutive treads within
  // these bounds, at least this many treads seen.
  double max_tread_m2 = 3.0;
  double min_riser_m = 0.10, max_riser_m = 0.25;
  double min_tread_run_m = 0.15, max_tread_run_m = 0.5;
  int min_treads = 3;

  // InvalidArgument naming the first setting outside its range.
  absl::Status Validate() const;
};

class FloorPlanBuilder {
 public:
  // `options` must be valid (FloorPlanOptions::Validate).
  explicit FloorPlanBuilder(FloorPlanOptions options = {});
  ~FloorPlanBuilder();
  FloorPlanBuilder(FloorPlanBuilder&&) noexcept;
  FloorPlanBuilder& operator=(FloorPlanBuilder&&) noexcept;

  // Folds in one key frame: its planes (camera frame), smoothed depth and intrinsics (for the
  // evidence rays), and T_world_camera. InvalidArgument for a non-finite or non-unit pose.
  absl::Status AddKeyframe(const planes::PlaneSet& planes, const CameraIntrinsics& k,
                           const Pose& T_world_camera);
  // The same from a key frame's depth (CV_32FC1 metres, 0 = no reading): its planes are
  // extracted first. InvalidArgument also for a depth image the planes cannot be taken from.
  absl::Status AddDepthKeyframe(const cv::Mat& depth_m, const CameraIntrinsics& k,
                                const Pose& T_world_camera,
                                const planes::PlaneOptions& plane_options = {});

  // FailedPrecondition when the plan cannot be derived yet, saying why: fewer than 2 key
  // frames, key frames waiting for a floor to level the plan by (up_from_floor), no floor seen (no
  // large horizontal plane facing up below the cameras), or fewer than 3 walls. The steps
  // (core/place/floor_plan_steps.h): the floor, wall candidates, tall walls, hidden faces dropped,
  // the outline, each wall's openings, collinear walls merged, stairs.
  absl::StatusOr<FloorPlan> Build() const;

  // Key frames added (folded, or waiting for a floor to level the plan by).
  int keyframes() const;

 private:
  struct State;
  std::unique_ptr<State> s_;
};

}  // namespace lifemap::place
