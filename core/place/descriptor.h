// The architecture descriptor of a place and its matching (paper 004, sections 3.4 and 4.2).
//
// Descriptor: per corner i (counter-clockwise), the length of the wall to the next corner and
// the angle between that wall and the next, the openings on that wall (type, length, distance
// from corner i), then the stairs (type, length, width, distance from the nearest wall).
//
// Matching (Algorithm 2): the query is compared against a stored descriptor from every starting
// corner in both directions; the difference is a weighted sum of wall-length, angle, opening
// and stairs differences, and the smallest over starts and directions is the place's
// difference. "Every open/closed state of the openings" is taken in closed form: an opening
// present on one side only costs `closed_door` when it is a door (it may have been closed) and
// `missing_opening` otherwise — the minimum over the states, evaluated per door.
#pragma once

#include <string>
#include <vector>

#include "core/place/floor_plan.h"

namespace lifemap::place {

struct DescriptorOpening {
  OpeningType type = OpeningType::kDoor;
  double length_m = 0;
  double distance_m = 0;  // from the wall's start corner to the opening's near edge
};

struct CornerEntry {
  double length_m = 0;   // wall from this corner to the next
  double angle_deg = 0;  // interior angle at the next corner, between this wall and the next
  std::vector<DescriptorOpening> openings;
};

struct StairEntry {
  bool ascending = true;
  double length_m = 0, width_m = 0;
  double distance_to_wall_m = 0;
};

struct PlaceDescriptor {
  std::vector<CornerEntry> corners;
  std::vector<StairEntry> stairs;
};

PlaceDescriptor Describe(const FloorPlan& plan);

// One line per corner and stair, for people and logs:
// "C0 L=4.20 A=90.0 door(0.90@1.10)" ... "S up L=1.68 W=1.00 D=0.40".
std::string DescriptorText(const PlaceDescriptor& d);

struct MatchWeights {
  double length = 1.0;           // per metre of wall-length difference
  double angle = 1.0 / 30.0;     // per degree (30° weighs as 1 m)
  double opening = 0.5;          // per metre of opening length + position difference
  double closed_door = 0.3;      // a door on one side only
  double missing_opening = 0.8;  // a window on one side only
  double stairs = 0.5;           // per metre of stairs size + position difference
  double missing_stairs = 1.0;
  double missing_corner = 1.5;  // per corner the two descriptors differ by
};

struct MatchResult {
  double difference = 0;  // smaller is more similar
  // exp(−difference / corners compared): 1 identical; a caller rejects unknown places below a
  // threshold (difference ≈ 0.7 per wall gives 0.5).
  double score = 0;
  int start = 0;          // the stored corner the query's corner 0 matched
  bool reversed = false;  // matched walking the stored place clockwise
};

MatchResult MatchDescriptors(const PlaceDescriptor& query, const PlaceDescriptor& stored,
                             const MatchWeights& weights = {});

}  // namespace lifemap::place
