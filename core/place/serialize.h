// JSON forms of a floor plan and a descriptor, as the store keeps them with a visit and the CLI
// prints them. Lengths in metres, angles in degrees, ground-plane coordinates of the plan.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/place/descriptor.h"
#include "core/place/floor_plan.h"

namespace lifemap::place {

// {"corners": [{"length_m", "angle_deg", "openings": [{"type": "door"|"window", "length_m",
// "distance_m"}]}], "stairs": [{"ascending", "length_m", "width_m", "distance_to_wall_m"}]}
std::string DescriptorToJson(const PlaceDescriptor& d);
// InvalidArgument naming what is malformed.
absl::StatusOr<PlaceDescriptor> DescriptorFromJson(const std::string& json);

// {"floor_height_m", "keyframes", "walls": [{"start": [x, y], "end": [x, y], "openings": [...]}],
// "stairs": [{"ascending", "steps", "rise_m", "length_m", "width_m", "center": [x, y],
// "distance_to_wall_m"}]}
std::string FloorPlanToJson(const FloorPlan& plan);
absl::StatusOr<FloorPlan> FloorPlanFromJson(const std::string& json);

// The plan as an SVG drawing, 100 px per metre, y up: walls black, doors brown, windows blue,
// stairs a green circle. With `truth`, the truth is drawn first, wide and pale, under the plan.
// A header above it holds `title` (what the plan is of), a legend and a 1 m scale bar.
// `markers` (when given) are drawn as small red dots on top, each an SVG circle of class
// "keyframe" with its id as data-id (the browser view links them), and widen the drawing to
// hold them.
struct PlanMarker {
  Eigen::Vector2d at;  // ground-plane coordinates, as the walls' (e1·p, e2·p)
  int64_t id = 0;
};
std::string FloorPlanSvg(const FloorPlan& plan, const FloorPlan* truth = nullptr,
                         const std::string& title = "",
                         const std::vector<PlanMarker>* markers = nullptr);
// The same drawing as a BGR image (for PNG files).
cv::Mat FloorPlanImage(const FloorPlan& plan, const FloorPlan* truth = nullptr,
                       const std::string& title = "");

}  // namespace lifemap::place
