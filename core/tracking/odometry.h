// The server's own poses for frames sent without one (issue 15): frame-to-keyframe RGB-D
// odometry. Each frame is aligned to its visit's reference keyframe by OpenCV contrib's
// RgbdICPOdometry (the photometric term of Steinbrücker et al. plus point-to-plane ICP on the
// depth, so that a texture-poor view keeps the geometric term) at reduced resolution, starting
// from the last tracked pose.
#pragma once

#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "core/common/rgbd_frame.h"
#include "core/common/types.h"

namespace lifemap::tracking {

struct OdometryOptions {
  // Frames are aligned at 1/downscale of their size (640x480 -> 320x240 at 2), [1, 4].
  int downscale = 2;
  // Depth readings used, metres; pairs of points whose depths differ more are not matched.
  float min_depth_m = 0.3f;
  float max_depth_m = 4.0f;
  float max_depth_diff_m = 0.07f;
  // Pixels whose grey-level gradient is below this (per pyramid level, grey levels per pixel)
  // are left out of the photometric term. OpenCV's default, 10, leaves out the soft texture of
  // painted walls seen close up: on such a view the alignment rests on point-to-plane ICP alone,
  // which is free to slide along the wall (sim seed 7: 156 mm ATE at 10, 2.7 mm at 5; chosen
  // there, other seeds in docs/RESULTS.md "Issue 15 (third part)").
  float min_gradient = 5.0f;
  // Pixels (per pyramid level) beside a depth hole that neither term uses: where something
  // closer than the sensor's range has no depth, its edge against the surface behind looks
  // like texture on that surface and moves with the camera. 0 keeps them. Chosen on building
  // seed 13 (208 mm ATE with OpenCV's own pyramids, 5.3 mm at 2); docs/RESULTS.md "Issue 15
  // (fourth part)".
  int hole_margin = 2;
  // Motion from the reference keyframe beyond which an alignment is refused (OpenCV's check).
  float max_translation_m = 0.5f;
  float max_rotation_deg = 40.0f;
  // An aligned pose this far from the last tracked pose is refused as a jump (the allowance
  // grows with the frames lost since).
  double max_jump_m = 0.15;
  double max_jump_rad = 0.35;
  // The feature check: ORB keypoints (`feature_keypoints` at most, 0 = no check) of the frame
  // matched to the reference keyframe's and located by PnP (appearance::VerifyMatch) give a
  // second, independent estimate. It runs where the dense alignment failed or moved the camera
  // faster than `feature_check_speed_mps` / `feature_check_turn_dps` since the last tracked
  // frame (a slide along a plain wall above a tiled floor: point-to-plane ICP is free along the
  // wall, the photometric term weak), not on every frame: detection costs ~8 ms a frame at
  // 640x480. With at least `feature_min_inliers` PnP inliers, a dense alignment that disagrees
  // by more than `feature_agree_m` / `feature_agree_deg` is run again from the PnP estimate, and
  // of the three estimates the one the two images agree with best is kept.
  int feature_keypoints = 500;
  // Handheld TUM fr1 moves up to 0.6 m/s (median 0.33): at 0.4 m/s the check ran on most of
  // its frames and cost ~20 ms a frame served; the slides it catches move 0.5-3.6 m/s, and the
  // synthetic walks track the same at 1.0 as at 0.4 (building seed 11, 300/600/900 frames).
  double feature_check_speed_mps = 1.0;
  double feature_check_turn_dps = 90.0;
  int feature_min_inliers = 30;
  double feature_agree_m = 0.03;
  double feature_agree_deg = 2.0;
  // The robot's odometry (RgbdFrame::odometry, issue 35): its increment since the last tracked
  // frame is the alignment's starting guess, and an alignment further from it than
  // `odometry_gate_sigmas` of its uncertainty is refused; a frame nothing else places is placed
  // by it (TrackingMethod::kOdometry). An increment's uncertainty (one sigma) is its readings'
  // covariance when both carry one, else `odometry_drift` of the distance travelled plus
  // `odometry_floor_m`, and `odometry_drift_deg_per_m` of it plus `odometry_floor_deg` (wheel
  // odometry drifts 1-2 % of the distance; the floor covers the sensor's timing).
  double odometry_drift = 0.02;
  double odometry_drift_deg_per_m = 1.0;
  double odometry_floor_m = 0.005;
  double odometry_floor_deg = 0.5;
  double odometry_gate_sigmas = 3.0;
  // Readings that move faster than this since the visit's last reading are refused as jumps
  // (CheckOdometry): odometry drifts, it does not jump.
  double odometry_max_speed_mps = 3.0;
  double odometry_max_turn_dps = 360.0;
  // A direction of the reference keyframe's depth whose share of the point-to-plane information
  // is below this is reported free (TrackedPose::degenerate_axes; DepthDegeneracy). 0 turns the
  // check off. Chosen between a painted wall seen close up (sim rooms seed 7: the weakest
  // direction 0.04-0.14 % of the information) and a cluttered desk (TUM fr1_xyz: 0.86-1.36 %);
  // docs/RESULTS.md "Issue 35 (session 22)".
  double degenerate_share = 0.0025;
  // Where the reference keyframe's depth pins a direction of motion weakly, a frame's own
  // prediction (the robot's odometry, a client's pose to refine) decides it rather than the
  // alignment: each direction of the alignment's difference from the prediction is kept by
  // s^2 / (s^2 + prior_share^2), s its share of the depth's information (as degenerate_share).
  // Frames without a prediction keep the alignment; 0 keeps it always. Chosen on building seed 3
  // with wheel odometry (ATE 31-49 mm at 0, 6-18 mm at 0.01); docs/RESULTS.md "Issue 54
  // (tracking)".
  double prior_share = 0.01;

  // InvalidArgument naming the first field out of range.
  absl::Status Validate() const;
};

enum class TrackingState {
  kStarted,   // the visit's first tracked frame: it defines the visit's frame
  kTracking,  // aligned to the reference keyframe
  kLost,      // could not be aligned; later frames try again against the same reference
  kRegained,  // aligned again after lost frames
};

// Which estimate a tracked pose is.
enum class TrackingMethod {
  kNone,         // lost, or the visit's first frame
  kDense,        // the dense RGB-D alignment from the last pose
  kRefit,        // the dense alignment run again from the feature (PnP) estimate
  kFeatures,     // the feature (PnP) estimate: the dense alignment disagreed or failed
  kRelocalised,  // after lost frames, placed by a verified match to a keyframe (Relocalise)
  kOdometry,     // the images gave no estimate the robot's odometry agrees with: placed by it
};

struct TrackedPose {
  TrackingState state = TrackingState::kLost;
  TrackingMethod method = TrackingMethod::kNone;
  std::optional<Pose> T_world_camera;  // unset when lost
  std::string reason;                  // why lost, for people reading results
  int lost_frames = 0;                 // consecutive frames lost, this one included
  // Directions the reference keyframe's depth does not pin (issue 35), in the visit's frame,
  // e.g. "translation along x": point-to-plane ICP is free along them (a plain wall, a
  // corridor), and only the photometric term, the feature check or the robot's odometry holds
  // the pose there. Empty when the depth pins all six; set on frames aligned to such a
  // reference (DepthDegeneracy).
  std::vector<std::string> degenerate_axes;
};

// The directions a view's surfaces leave point-to-plane alignment free along: `points` and
// their unit `normals` (camera frame, metres), rotated by `R_world_camera` so the directions
// are named in the world's axes ("translation along x", "rotation about z"). Each point's
// constraint row is (n, (p x n) / d) with d the points' median depth (rotations in metres at
// that depth); a direction whose share of the information matrix (its eigenvalue over the
// trace) is below `min_share` is free. Where the points are too few (< 50) nothing is said.
std::vector<std::string> DepthDegeneracy(const std::vector<Eigen::Vector3d>& points,
                                         const std::vector<Eigen::Vector3d>& normals,
                                         const Eigen::Matrix3d& R_world_camera, double min_share);

// A frame made ready for alignment: grey and depth at the odometry's resolution, and the image
// pyramids and gradients of the photometric and ICP terms. It does not depend on the visit, so
// it can be made on any thread before the frame's turn (the frame service makes it beside the
// frame's other analyses); Track then only aligns.
struct TrackingInput;

// Prepares `frame` for Tracker::Track, which prepares it again if the tracker's options differ
// in resolution or depth range. Never null: a frame that cannot be tracked carries the reason,
// and Track reports it as lost.
std::shared_ptr<TrackingInput> PrepareForTracking(const RgbdFrame& frame,
                                                  const OdometryOptions& options);

// One visit's camera, frame after frame. Thread-compatible: call from one thread (or under a
// lock), frames in order.
class Tracker {
 public:
  explicit Tracker(OdometryOptions options = {});
  ~Tracker();
  Tracker(Tracker&&) noexcept;
  Tracker& operator=(Tracker&&) noexcept;

  // The visit's frame. The first frame of a visit is placed at the origin looking along +x
  // (its forward direction made horizontal) with z up: against `gravity_camera` (unit, camera
  // frame) when the frame has it, else the camera is taken as level (world_x = camera z,
  // world_y = -camera x, world_z = -camera y). Floor plans assume z up (docs/API.md). Track
  // places a visit's first frame by its gravity, else by FloorGravity, else level.
  static Pose FirstPose(const std::optional<Eigen::Vector3d>& gravity_camera = std::nullopt);

  // Gravity (unit, camera frame) from the floor in a depth image (metres), for a visit's first
  // frame sent without gravity (issue 35): the largest plane (core/planes) of at least
  // `min_area_m2` below the camera whose normal is within `max_tilt_deg` of the camera's own
  // down being vertical; nullopt when there is none (the camera is then taken as level).
  static std::optional<Eigen::Vector3d> FloorGravity(const cv::Mat& depth_m,
                                                     const CameraIntrinsics& k,
                                                     double max_tilt_deg = 35.0,
                                                     double min_area_m2 = 0.5);

  // Tracks a decoded frame (depth metres, colour BGR), prepared here unless `prepared` (from
  // PrepareForTracking for this frame) is given. With a `prior` (a client's pose to refine) that
  // pose is the starting guess instead of the last tracked one, and on the visit's first frame
  // it is kept as the visit's frame. The frame's own T_world_camera is not read. A frame without
  // any usable depth is lost, with the reason; a frame whose time is not after the last one's is
  // not tracked and changes nothing (reported lost, with the reason).
  //
  // With the frame's odometry (RgbdFrame::odometry) and the last tracked frame's, their increment
  // is the starting guess and bounds the alignment (OdometryOptions); call CheckOdometry first.
  TrackedPose Track(const RgbdFrame& frame, std::shared_ptr<TrackingInput> prepared = nullptr,
                    const std::optional<Pose>& prior = std::nullopt);

  // Whether `frame`'s odometry reading is one Track can use: InvalidArgument naming
  // frame.odometry when it moved faster than the options allow since the visit's last reading
  // (a jump). OK for a frame without odometry, and for the visit's first reading.
  absl::Status CheckOdometry(const RgbdFrame& frame) const;

  // Relocalisation: places the frame just reported lost (by the last Track call, once it was
  // prepared) at `T_world_camera`, found by other means (a verified appearance match to a
  // stored keyframe of the visit), and makes it the reference later frames are aligned to.
  // Returns kRegained / kRelocalised with that pose; kLost with the reason when the last frame
  // was not one that can be (tracked, from the past, or without usable depth).
  TrackedPose Relocalise(const Pose& T_world_camera);

  // Makes the last frame tracked (not lost) the reference that later frames are aligned to:
  // call when it became a keyframe. Nothing when the last frame was lost.
  void PromoteLastToReference();

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace lifemap::tracking
