// Ray-casting RGB-D renderer for the synthetic world: exact depth, class and instance per
// pixel, then a Kinect-v1-like sensor model on top.
#pragma once

#include <cstdint>

#include <opencv2/core.hpp>

#include "core/common/types.h"
#include "core/sim/world.h"

namespace lifemap::sim {

struct SensorOptions {
  bool noise = true;          // depth noise growing with z^2, disparity quantisation
  double max_range_m = 4.5;   // no reading beyond
  double min_range_m = 0.45;  // no reading closer
  double grazing_cos = 0.12;  // no reading where |cos(incidence)| is below this
  double edge_dropout = 0.5;  // probability of losing a pixel at a depth discontinuity
  double color_noise = 2.0;   // grey levels (of 255), Gaussian
  double exposure = 1.0;      // colour gain
};

struct RenderedFrame {
  cv::Mat depth_m;       // CV_32FC1, 0 = no reading (after the sensor model)
  cv::Mat true_depth_m;  // CV_32FC1, exact depth of the first surface (0 = none)
  cv::Mat color_bgr;     // CV_8UC3
  cv::Mat class_id;      // CV_8UC1, SemanticClass of the first surface
  cv::Mat instance_id;   // CV_16UC1, Solid::instance (0 for walls, floor, ceiling, none)
};

// Renders `place` with the solids given (a visit's arrangement) from T_world_camera.
// Deterministic for a seed: the same arguments give the same bits.
RenderedFrame Render(const Place& place, const std::vector<Solid>& solids, const Lighting& lighting,
                     const CameraIntrinsics& k, const Pose& T_world_camera,
                     const SensorOptions& sensor, uint64_t seed);

}  // namespace lifemap::sim
