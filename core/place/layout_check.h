// Whether a view agrees with a place's floor plan (issue 15): the architecture check of loop
// closures and visit anchors. An appearance match says where a camera is; placed there, its
// depth readings must not lie beyond the plan's walls. Furniture, people and anything else in
// front of a wall are no contradiction (the readings stop short of it), and neither are the
// plan's doors and windows; a reading well beyond a wall, where the plan has no opening, is:
// the camera is not where the match puts it (another room that shares furniture, a repeated
// poster, a rotated alias), or the plan is wrong there.
#pragma once

#include <opencv2/core/mat.hpp>

#include "core/common/types.h"
#include "core/place/floor_plan.h"

namespace lifemap::place {

struct LayoutCheckOptions {
  int stride_px = 8;       // every N-th pixel's reading is checked (80 × 60 at 640 × 480)
  double margin_m = 0.30;  // a reading this far beyond a wall is seen through it (plan error,
                           // depth noise and a wall's thickness fit within it)
  // Only crossings between these heights above the plan's floor count: below, skirting and
  // floor noise; above, walls the plan did not see the top of.
  double min_height_m = 0.2;
  double max_height_m = 2.0;
  double opening_margin_m = 0.15;  // an opening is taken this much wider and taller
  double max_range_m = 6.0;        // readings farther away are not checked (noisy, rare indoors)
  // Only walls the plan saw (observed_m2 > 0) count: for a plan still being built, whose
  // outline closes across walls not seen yet (issue 54: another visit's views checked against
  // the plan of a visit in progress).
  bool seen_walls_only = false;
};

struct LayoutAgreement {
  int readings = 0;            // depth readings checked
  int through_walls = 0;       // ... that lie beyond a wall of the plan, not through an opening
  bool camera_inside = false;  // the camera stands within the plan's outline
  // through_walls / readings (0 with no readings).
  double ThroughShare() const;
};

// Checks `depth_m` (CV_32FC1 metres, 0 = no reading; its size as `k`'s) seen from
// `T_plan_camera` (the camera in the plan's frame: the frame of the poses it was built from)
// against the plan's walls and openings. A plan without walls gives no crossings.
LayoutAgreement CheckLayout(const FloorPlan& plan, const cv::Mat& depth_m,
                            const CameraIntrinsics& k, const Pose& T_plan_camera,
                            const LayoutCheckOptions& options = {});

// How one plan's walls sit in another's (issue 54): an L room's plan placed in a rectangular
// room's puts its inner corner's walls where the rectangle has floor, while the depth readings
// of the L room's views stop short of the rectangle's walls and so agree with it (CheckLayout).
struct PlanAgreement {
  double seen_wall_m = 0;  // length of the placed plan's seen walls (observed_m2 > 0)
  double on_floor_m = 0;   // ... that lies within the other's outline, away from its walls
  // on_floor_m / seen_wall_m (0 with no seen walls).
  double OnFloorShare() const;
};

// Places `placed`'s seen walls by `T_plan_placed` (its frame in `plan`'s) in `plan` and measures
// how much of them lies inside `plan`'s outline farther than `margin_m` from every one of its
// walls: where `plan` says there is floor, `placed` saw a wall. Nothing is said where either plan
// has fewer than 3 walls (no outline).
PlanAgreement ComparePlans(const FloorPlan& placed, const FloorPlan& plan,
                           const Pose& T_plan_placed, double margin_m = 0.5);

}  // namespace lifemap::place
