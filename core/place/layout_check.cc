#include "core/place/layout_check.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include <Eigen/Geometry>

#include "core/place/floor_plan_steps.h"

namespace lifemap::place {
namespace {

// 2D cross product.
double Cross(const Eigen::Vector2d& a, const Eigen::Vector2d& b) {
  return a.x() * b.y() - a.y() * b.x();
}

// Whether ground point `p` is inside the closed polygon through the walls' start corners
// (even-odd rule).
bool InsideOutline(const std::vector<Wall>& walls, const Eigen::Vector2d& p) {
  bool inside = false;
  for (const Wall& w : walls) {
    const Eigen::Vector2d& a = w.start;
    const Eigen::Vector2d& b = w.end;
    if ((a.y() > p.y()) != (b.y() > p.y()) &&
        p.x() < a.x() + (p.y() - a.y()) * (b.x() - a.x()) / (b.y() - a.y())) {
      inside = !inside;
    }
  }
  return inside;
}

// Whether a crossing `along_m` from the wall's start, `height_m` above the floor, passes
// through one of its openings (taken `margin_m` larger on every side).
bool ThroughOpening(const Wall& w, double along_m, double height_m, double margin_m) {
  for (const WallOpening& o : w.openings) {
    if (along_m >= o.from_m - margin_m && along_m <= o.to_m + margin_m &&
        height_m >= o.bottom_m - margin_m && height_m <= o.top_m + margin_m) {
      return true;
    }
  }
  return false;
}

}  // namespace

double PlanAgreement::OnFloorShare() const {
  return seen_wall_m > 0 ? on_floor_m / seen_wall_m : 0.0;
}

PlanAgreement ComparePlans(const FloorPlan& placed, const FloorPlan& plan,
                           const Pose& T_plan_placed, double margin_m) {
  PlanAgreement out;
  if (placed.walls.size() < 3 || plan.walls.size() < 3) return out;
  constexpr double kStepM = 0.10;  // walls are sampled this finely
  const Eigen::Isometry3d T = T_plan_placed.ToIsometry();
  // A wall point 1 m above the placed plan's floor, in `plan`'s ground coordinates.
  const double height = placed.floor_height_m + 1.0;
  for (const Wall& w : placed.walls) {
    if (!(w.observed_m2 > 0)) continue;
    const double length = w.length();
    const int samples = std::max(1, static_cast<int>(length / kStepM));
    for (int i = 0; i < samples; ++i) {
      const Eigen::Vector2d g = w.start + (w.end - w.start) * ((i + 0.5) / samples);
      const Eigen::Vector3d p3 = T * (g.x() * placed.e1 + g.y() * placed.e2 + height * placed.up);
      const Eigen::Vector2d p(plan.e1.dot(p3), plan.e2.dot(p3));
      const double piece = length / samples;
      out.seen_wall_m += piece;
      if (!InsideOutline(plan.walls, p)) continue;
      double nearest = std::numeric_limits<double>::infinity();
      for (const Wall& v : plan.walls)
        nearest = std::min(nearest, steps::DistanceToSegment(p, v.start, v.end));
      if (nearest > margin_m) out.on_floor_m += piece;
    }
  }
  return out;
}

double LayoutAgreement::ThroughShare() const {
  return readings > 0 ? static_cast<double>(through_walls) / readings : 0.0;
}

LayoutAgreement CheckLayout(const FloorPlan& plan, const cv::Mat& depth_m,
                            const CameraIntrinsics& k, const Pose& T_plan_camera,
                            const LayoutCheckOptions& options) {
  LayoutAgreement out;
  const Eigen::Isometry3d T = T_plan_camera.ToIsometry();
  const Eigen::Vector3d c3 = T.translation();
  const Eigen::Vector2d c(plan.e1.dot(c3), plan.e2.dot(c3));
  const double c_height = plan.up.dot(c3) - plan.floor_height_m;
  out.camera_inside = plan.walls.size() >= 3 && InsideOutline(plan.walls, c);
  const int stride = std::max(1, options.stride_px);
  for (int v = stride / 2; v < depth_m.rows; v += stride) {
    const float* row = depth_m.ptr<float>(v);
    for (int u = stride / 2; u < depth_m.cols; u += stride) {
      const double z = row[u];
      if (!(z > 0) || !std::isfinite(z)) continue;
      const Eigen::Vector3d ray_camera((u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z);
      const double range = ray_camera.norm();
      if (range > options.max_range_m) continue;
      ++out.readings;
      const Eigen::Vector3d p3 = T * ray_camera;
      const Eigen::Vector2d p(plan.e1.dot(p3), plan.e2.dot(p3));
      const double p_height = plan.up.dot(p3) - plan.floor_height_m;
      const Eigen::Vector2d d = p - c;
      for (const Wall& w : plan.walls) {
        if (options.seen_walls_only && !(w.observed_m2 > 0)) continue;
        // c + t d = w.start + s (w.end - w.start), t and s in [0, 1].
        const Eigen::Vector2d e = w.end - w.start;
        const double den = Cross(d, e);
        if (std::abs(den) < 1e-12) continue;  // parallel to the wall
        const Eigen::Vector2d f = w.start - c;
        const double t = Cross(f, e) / den;
        const double s = Cross(f, d) / den;
        if (t <= 0 || t >= 1 || s < 0 || s > 1) continue;
        // How far beyond the wall the reading lies, along the ray.
        if ((1 - t) * range < options.margin_m) continue;
        const double height = c_height + t * (p_height - c_height);
        if (height < options.min_height_m || height > options.max_height_m) continue;
        if (ThroughOpening(w, s * e.norm(), height, options.opening_margin_m)) continue;
        ++out.through_walls;
        break;
      }
    }
  }
  return out;
}

}  // namespace lifemap::place
