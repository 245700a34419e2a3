// Writes a generated visit as a TUM-format folder that `lifemap stream --tum` reads unchanged,
// plus ground truth: labels/ (class and instance PNGs), moved/ (zones changed since the previous
// visit) and scene.json (floor plan, openings, objects, changes).
#pragma once

#include <string>

#include "absl/status/status.h"
#include "core/sim/generator.h"
#include "core/sim/renderer.h"

namespace lifemap::sim {

struct WriteOptions {
  CameraIntrinsics intrinsics{525.0, 525.0, 319.5, 239.5, 640, 480};
  SensorOptions sensor;
  uint64_t seed = 1;
};

struct WriteSummary {
  int frames = 0;
  double mean_valid_depth = 0;  // share of pixels with a depth reading
  double mean_moved = 0;        // share of pixels marked moved
};

// `previous` (may be null) is the visit before, for moved/. Creates `dir`.
absl::StatusOr<WriteSummary> WriteVisit(const std::string& dir, const Place& place,
                                        const Visit& visit, const Visit* previous,
                                        const WriteOptions& options);

}  // namespace lifemap::sim
