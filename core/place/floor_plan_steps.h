// Internal to core/place (and its tests): the evidence FloorPlanBuilder accumulates from key
// frames, and the steps Build derives a plan from it with, in order — the floor, wall
// candidates, tall walls, hidden faces, the outline, openings, the collinear merge, stairs.
// Each step is a plain function of what the ones before it found.
#pragma once

#include <cstdint>
#include <unordered_map>
#include <vector>

#include <Eigen/Core>

#include "absl/status/statusor.h"
#include "core/place/floor_plan.h"

namespace lifemap::place::steps {

// Distance (metres) from ground point `p` to the segment a-b (to a where they coincide).
double DistanceToSegment(const Eigen::Vector2d& p, const Eigen::Vector2d& a,
                         const Eigen::Vector2d& b);

// Evidence about one cell of a wall (along × height).
struct Cell {
  float covered = 0;   // a planar region or a reading lies on the wall here
  float free = 0;      // a ray passed here: a reading beyond the wall, or none
  float occluded = 0;  // a ray stopped in front of the wall here
};

// A cell's key in a wall's grid: column s along the line, row h up (both in cells).
inline int64_t Key(int s, int h) {
  // Shifted unsigned: shifting a negative int64 left is undefined.
  return static_cast<int64_t>((static_cast<uint64_t>(static_cast<uint32_t>(s)) << 32) |
                              static_cast<uint32_t>(h));
}
inline int KeyS(int64_t k) { return static_cast<int>(k >> 32); }
inline int KeyH(int64_t k) { return static_cast<int>(static_cast<int32_t>(k & 0xffffffff)); }

// Where a camera saw a stretch of a wall line from.
struct Sighting {
  double s0 = 0, s1 = 0;       // the stretch along the line (metres, the line's tangent)
  Eigen::Vector2d from{0, 0};  // the camera on the ground
  double area = 0;             // planar area seen (m²)
};

// A vertical plane's line on the ground, accumulated over key frames.
struct WallAcc {
  Eigen::Vector2d n;  // unit normal towards the side the cameras saw it from
  double offset = 0;  // n·q = offset on the line
  double area = 0;    // planar area seen (m²)
  std::unordered_map<int64_t, Cell> cells;
  std::vector<Sighting> sightings;
  Eigen::Vector2d tangent() const { return {n.y(), -n.x()}; }  // the seen side on its left
  // Signed distance of ground point p from the line (metres; positive on the seen side).
  double side(const Eigen::Vector2d& p) const { return n.dot(p) - offset; }
};

// A horizontal planar patch of one key frame.
struct Patch {
  double height = 0;  // along up
  Eigen::Vector2d centroid{0, 0};
  Eigen::Vector2d lo{0, 0}, hi{0, 0};
  double area = 0;
  bool faces_up = true;
};

// A run of one wall line that may be a wall of the outline.
struct WallCandidate {
  const WallAcc* acc = nullptr;
  double s0 = 0, s1 = 0, top = 0;
  double seen_m2 = 0;                // distinct covered cells of the run
  Eigen::Vector2d a{0, 0}, b{0, 0};  // endpoints of the seen extent
  Eigen::Vector2d from{0, 0};        // where the cameras that saw the run were, on average
  double length() const { return s1 - s0; }
};

// Evidence rays go no farther (depth, metres).
constexpr double kRayRangeM = 8.0;

// 1. The floor's height: the height (floor_bin_m bins) with the most upward-facing area below
// the cameras. FailedPrecondition when too little floor was seen.
// A key frame's lowest upward plane below it (FloorAgreement): its tilt from the plan's up and
// its height along it.
struct FloorSighting {
  double tilt_deg, height;
};
// FloorAgreement over the key frames' sightings, in the order they were folded.
FloorAgreement AgreeOnFloor(const std::vector<FloorSighting>& sightings);

absl::StatusOr<double> FindFloor(const std::vector<Patch>& patches, double camera_height,
                                 const FloorPlanOptions& o);

// 2. Runs of covered columns along each wall line, between the floor and max_wall_height_m;
// a gap wider than max_wall_gap_m splits a line; furniture whose top was seen over is dropped.
std::vector<WallCandidate> FindWallCandidates(const std::vector<WallAcc>& walls, double floor,
                                              const FloorPlanOptions& o);

// 3. Walls rise above furniture: the candidates seen up to wall_top_share of the highest.
std::vector<WallCandidate> KeepTallWalls(const std::vector<WallCandidate>& candidates,
                                         const FloorPlanOptions& o);

// 4. Faces not on the outline dropped: furniture in front of a longer parallel wall, a face
// behind one (seen through an opening), a face wholly behind another wall seen through it.
std::vector<WallCandidate> DropHiddenFaces(const std::vector<WallCandidate>& tall,
                                           const FloorPlanOptions& o);

// 5. The outline: the closed chain of faces (counter-clockwise) that best explains what was
// seen, with unseen walls across gaps; without one, the faces ordered around `centre`.
// walls[i] is null for an unseen wall; corners[i] is where walls[i] starts.
struct Outline {
  std::vector<const WallCandidate*> walls;
  std::vector<Eigen::Vector2d> corners;
};
Outline ChainOutline(const std::vector<WallCandidate>& faces, const Eigen::Vector2d& centre,
                     const FloorPlanOptions& o);

// 6. The doors and windows of a wall of the outline (`wall`'s corners set), from the evidence
// of its candidate.
std::vector<WallOpening> FindOpenings(const WallCandidate& candidate, const Wall& wall,
                                      double floor, const FloorPlanOptions& o);

// 7. Collinear neighbours become one wall and walls of no length drop out (while more than 3).
void MergeCollinearWalls(std::vector<Wall>* walls, const FloorPlanOptions& o);

// 8. Stairs: horizontal patches off the floor grouped into treads, chained by riser and run.
std::vector<StairFlight> FindStairs(const std::vector<Patch>& patches, double floor,
                                    const std::vector<Wall>& walls, const FloorPlanOptions& o);

}  // namespace lifemap::place::steps
