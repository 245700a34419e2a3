// Deterministic generation of places, visits months apart, and camera trajectories.
#pragma once

#include <cmath>
#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/types.h"
#include "core/sim/world.h"

namespace lifemap::sim {

// What changes between visits (paper 004's Table 1 conditions).
struct Conditions {
  bool lighting = false;  // brightness and colour temperature change
  bool scenery = false;   // props move, appear, vanish; a door opens or closes
  bool dynamic = false;   // people walk through the room during the visit
};

// Parses "lighting,scenery" (or "none"). InvalidArgument names an unknown condition.
absl::StatusOr<Conditions> ParseConditions(const std::string& text);

struct Change {
  std::string kind;  // "moved", "appeared", "vanished", "door_opened", "door_closed", "lighting"
  int instance = 0;  // the solid, for object changes
  std::string detail;
};

struct TimedCameraPose {
  double timestamp_s = 0;
  Pose T_world_camera;
};

// A person walking in a straight line across the room during a visit (dynamic objects).
struct Walker {
  Solid body;                // a cylinder of class kPerson; body.center is ignored
  Eigen::Vector2d from, to;  // positions at the visit's first and last frame
};

struct Visit {
  int index = 0;
  double months_since_first = 0;
  double start_time_s = 0;        // Unix time of the first frame
  std::vector<Solid> solids;      // the arrangement seen on this visit
  std::vector<Opening> openings;  // with this visit's door states
  Lighting lighting;
  std::vector<Change> changes;  // relative to the previous visit
  std::vector<TimedCameraPose> trajectory;
  std::vector<Walker> walkers;

  // The solids seen at frame `f`: the arrangement plus the walkers where they are then.
  std::vector<Solid> SolidsAt(size_t f) const;
};

// The boxes a flight of stairs is made of (class kStairs, not movable), for rendering.
std::vector<Solid> StairSolids(const Stairs& stairs, int first_instance);

// shape: rect, square, L, T or U. InvalidArgument for other shapes. The default style is the
// first world (issue 3): the same seed and shape give the same place as then, bit for bit.
absl::StatusOr<Place> GeneratePlace(uint64_t seed, const std::string& shape,
                                    const PlaceStyle& style = {});

// The finishes of a place of the first world: its own floor, ceiling and per-wall textures
// from its texture seed.
Materials RoomMaterials(uint32_t texture_seed);
// The finishes every place of one building shares: a tiled floor covering, one low-contrast
// wall paint, one ceiling.
Materials BuildingMaterials(uint64_t building_seed);

// The worlds of `lifemap sim --world`: "building" (curved props, places sharing materials and
// furniture models; the default of `sim suite`) or "rooms" (the first world). The building
// seed is the suite's seed. InvalidArgument names the choices.
absl::StatusOr<PlaceStyle> ParseWorld(const std::string& world, uint64_t building_seed);

// The camera moves at most as fast as a person carrying it: 1 m/s and 60°/s.
inline constexpr double kMaxWalkSpeedMps = 1.0;
inline constexpr double kMaxTurnRateRadps = M_PI / 3.0;

// `count` visits `months_apart` months apart, each with `frames` frames along one loop (and a
// quarter) through the room, at 30 Hz or slower where needed to keep to a walking speed
// (kMaxWalkSpeedMps, kMaxTurnRateRadps): fewer frames make a visit of the same path, the
// frames further apart in time. Visit 0 is the reference; later ones apply the conditions'
// changes.
absl::StatusOr<std::vector<Visit>> GenerateVisits(const Place& place, uint64_t seed, int count,
                                                  double months_apart, const Conditions& conditions,
                                                  int frames);

}  // namespace lifemap::sim
