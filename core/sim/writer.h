// Writes a generated visit as a TUM-format folder that `lifemap stream --tum` reads unchanged,
// plus ground truth: labels/ (class and instance PNGs), moved/ (zones changed since the previous
// visit) and scene.json (floor plan, openings, objects, changes).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "core/sim/generator.h"
#include "core/sim/renderer.h"

namespace lifemap::sim {

// How the simulated wheel odometry drifts (odometry.txt): per visit, a scale error of the
// distance and of the turns (normal, sigma `scale_sigma`) and a yaw bias per metre (sigma
// `yaw_bias_deg_per_m_sigma`); per frame, noise of `step_noise` of the step's length and
// `turn_noise_deg` of its turn. Defaults: ~1-2 % of the distance, as a differential-drive base.
struct WheelOdometryNoise {
  double scale_sigma = 0.015;
  double yaw_bias_deg_per_m_sigma = 0.5;
  double step_noise = 0.005;
  double turn_noise_deg = 0.05;
};

struct WriteOptions {
  CameraIntrinsics intrinsics{525.0, 525.0, 319.5, 239.5, 640, 480};
  SensorOptions sensor;
  uint64_t seed = 1;
  WheelOdometryNoise odometry;
};

struct WriteSummary {
  int frames = 0;
  double mean_valid_depth = 0;  // share of pixels with a depth reading
  double mean_moved = 0;        // share of pixels marked moved
};

// The wheel odometry a robot carrying the camera along `trajectory` would report: the camera's
// pose in the odometry's frame (T_odom_camera, starting where the truth starts), its planar
// motion (x, y, heading of the camera's forward) integrated with `noise`, its height, pitch and
// roll exact (the mast's joints are read, not integrated). Deterministic in `seed`.
std::vector<TimedCameraPose> SimulateWheelOdometry(const std::vector<TimedCameraPose>& trajectory,
                                                   const WheelOdometryNoise& noise, uint64_t seed);

// `previous` (may be null) is the visit before, for moved/. Creates `dir`. Writes the TUM
// lists, groundtruth.txt, accelerometer.txt (a still IMU, with noise) and odometry.txt
// (SimulateWheelOdometry, "timestamp tx ty tz qx qy qz qw").
absl::StatusOr<WriteSummary> WriteVisit(const std::string& dir, const Place& place,
                                        const Visit& visit, const Visit* previous,
                                        const WriteOptions& options);

}  // namespace lifemap::sim
