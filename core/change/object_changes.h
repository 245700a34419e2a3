// What appeared, vanished or moved between two visits of a place (issue 36), from their
// keyframes' depth in the map's frame.
//
// Each visit's readings are binned into voxels. A voxel one visit holds and the other does not
// hold, nor any voxel next to it, is a candidate. It is a change only where the other visit saw
// *through* it: one of that visit's keyframes has the voxel in view, unoccluded, with readings
// well beyond it there. This is paper 000's eq. 3 (a negative disparity, never mere absence)
// taken into 3D: what the other visit did not look at, or saw only behind something else, is
// not evidence. A candidate that its own visit also saw through, from at least half as many
// keyframes as saw it, held something passing (a person walking by): it is transient, not a
// change of the place, and so is an object most of whose voxels are (its head is seen only
// from afar). A passer-by last seen where its visit never looks again is reported as appeared:
// nothing says it left. Lighting changes nothing here: only depth is read. Changed voxels are
// clustered into objects (26-connected). A door leaf that vanished is a door opened, one that
// appeared a door closed (a tall, thin, door-wide object); a tall, thin panel longer than any
// door is a wall gone or new; otherwise a vanished and an appeared object of similar volume
// close together are one object that moved.
#pragma once

#include <cstdint>
#include <vector>

#include <Eigen/Core>
#include <opencv2/core.hpp>

#include "absl/status/statusor.h"
#include "core/common/types.h"

namespace lifemap::change {

// One keyframe's depth seen from its pose in the map's frame.
struct PosedDepth {
  cv::Mat depth_m;  // CV_32FC1 metres, 0 = no reading; `intrinsics` describe this image
  CameraIntrinsics intrinsics;
  Pose T_world_camera;
};

// Every `stride`-th pixel of `depth_m` (CV_32FC1 metres) as a smaller image, with the
// intrinsics that describe it (pixels are picked, not averaged: an average across an object's
// edge is a surface that is not there).
PosedDepth Subsample(const cv::Mat& depth_m, const CameraIntrinsics& intrinsics, int stride,
                     const Pose& T_world_camera);

struct ChangeOptions {
  double voxel_m = 0.05;     // edge of the voxels readings are binned into
  double max_range_m = 4.0;  // readings farther are neither occupancy nor evidence
  // A reading at least this much beyond a voxel (plus `depth_noise_ratio` of its depth) sees
  // through it; one within that of it sees it.
  double seen_through_m = 0.10;
  double depth_noise_ratio = 0.01;
  int min_views = 2;       // keyframes of its visit that must see a voxel for it to count
  int min_free_views = 2;  // keyframes of the other visit that must see through a candidate
  // Objects smaller than this are not reported (sensor noise, pose error at edges).
  int min_object_voxels = 10;
  double min_object_m = 0.15;  // largest side of its box
  // A candidate its own visit saw through from this many keyframes (and at least half as many
  // as saw it) is transient.
  int transient_min_views = 2;
  // Changed voxels at most this many voxels apart (per axis) are one object: 1 joins touching
  // voxels (26-connected); 2 bridges a one-voxel gap (a chair's legs and seat seen in parts).
  int cluster_gap_voxels = 1;
  // An object whose candidate voxels are transient in at least this share passed by as a whole.
  double transient_share = 0.25;
  // A vanished and an appeared object pair as a move when their centres are at most this far
  // apart and their volumes within this ratio (5: one side of a chair seen before, its seat and
  // legs after; chosen on building seed 12, where 3 split two moved chairs).
  double max_move_m = 1.5;
  double max_volume_ratio = 5.0;
  // Doors: `up` is the map frame's up (unit); a panel at least this tall, this wide and at most
  // this thick (across its face) is a door leaf.
  Eigen::Vector3d up = Eigen::Vector3d::UnitZ();
  double door_min_height_m = 1.2;  // of it seen: a camera at robot height sees few tops
  double door_min_width_m = 0.55, door_max_width_m = 1.3;
  double door_max_thickness_m = 0.25;
  // Walls: a panel at least this tall (of it seen) and long, and at most this thick, that
  // appeared is a wall new, that vanished a wall gone (longer than door_max_width_m: a door
  // is never a wall).
  double wall_min_height_m = 1.5;
  double wall_min_length_m = 1.5;
  double wall_max_thickness_m = 0.3;

  // InvalidArgument naming the first setting outside its range.
  absl::Status Validate() const;
};

enum class ChangeKind {
  kAppeared,
  kVanished,
  kMoved,
  kDoorOpened,
  kDoorClosed,
  kWallNew,
  kWallGone
};
// "appeared", "vanished", "moved", "door_opened", "door_closed" (the names of sim's scene.json),
// "wall_new", "wall_gone"
const char* ChangeKindName(ChangeKind kind);

struct ObjectChange {
  ChangeKind kind = ChangeKind::kAppeared;
  // Where the object is on the later visit (appeared, moved) or was on the earlier (vanished):
  // the centroid of its voxels, map frame, metres.
  Eigen::Vector3d center = Eigen::Vector3d::Zero();
  Eigen::Vector3d from_center = Eigen::Vector3d::Zero();  // moved: where it was; else = center
  Eigen::Vector3d extent = Eigen::Vector3d::Zero();       // axis-aligned size in the map frame, m
  int voxels = 0;
  int evidence_views = 0;  // keyframes of the other visit that saw through it (most of a voxel)
  std::vector<Eigen::Vector3d> voxel_centers;       // at `center`
  std::vector<Eigen::Vector3d> from_voxel_centers;  // moved: at `from_center`
};

struct ObjectChanges {
  std::vector<ObjectChange> objects;       // largest first
  int64_t from_voxels = 0, to_voxels = 0;  // voxels each visit holds (seen from min_views)
  int64_t candidate_voxels = 0;            // held by one visit only
  int64_t changed_voxels = 0;              // candidates the other visit saw through
  int64_t transient_voxels = 0;            // ... dropped: their own visit saw through them too
  int64_t passing_voxels = 0;              // changed, dropped with a mostly transient object
  int64_t unobserved_voxels = 0;  // candidates the other visit never saw through (no evidence)
};

// `from` is the earlier visit, `to` the later; both in one frame (the map's). InvalidArgument
// for bad options or a view whose depth is not CV_32FC1 of its intrinsics' size.
absl::StatusOr<ObjectChanges> DetectObjectChanges(const std::vector<PosedDepth>& from,
                                                  const std::vector<PosedDepth>& to,
                                                  const ChangeOptions& options = {});

}  // namespace lifemap::change
