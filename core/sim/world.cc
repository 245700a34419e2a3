#include "core/sim/world.h"

#include <algorithm>
#include <cmath>

namespace lifemap::sim {

bool InsidePolygon(const std::vector<Eigen::Vector2d>& poly, double x, double y) {
  bool inside = false;
  for (size_t i = 0, j = poly.size() - 1; i < poly.size(); j = i++) {
    const auto& a = poly[i];
    const auto& b = poly[j];
    if (((a.y() > y) != (b.y() > y)) &&
        (x < (b.x() - a.x()) * (y - a.y()) / (b.y() - a.y()) + a.x())) {
      inside = !inside;
    }
  }
  return inside;
}

double DistanceToEdges(const std::vector<Eigen::Vector2d>& poly, const Eigen::Vector2d& p) {
  double best = 1e9;
  for (size_t i = 0; i < poly.size(); ++i) {
    const Eigen::Vector2d a = poly[i], b = poly[(i + 1) % poly.size()];
    const double t = std::clamp((p - a).dot(b - a) / (b - a).squaredNorm(), 0.0, 1.0);
    best = std::min(best, (a + t * (b - a) - p).norm());
  }
  return best;
}

double FootprintRadius(const Solid& s) {
  switch (s.shape) {
    case Solid::Shape::kBox:
      return 0.5 * std::hypot(s.size.x(), s.size.y());
    case Solid::Shape::kBlob:
      return 0.5 * std::max(s.size.x(), s.size.y()) * BlobReach(s);
    default:
      return s.size.x() / 2;
  }
}

std::pair<double, double> VerticalExtent(const Solid& s) {
  if (s.shape != Solid::Shape::kBlob) return {s.base_z, s.base_z + s.size.z()};
  const double centre = s.base_z + s.size.z() / 2 - s.sink_m;
  const double half = 0.5 * s.size.z() * BlobReach(s);
  return {centre - half, centre + half};
}

bool MovableClass(SemanticClass c) {
  switch (c) {
    case SemanticClass::kChair:
    case SemanticClass::kBox:
    case SemanticClass::kCylinder:
    case SemanticClass::kBook:
    case SemanticClass::kMug:
    case SemanticClass::kClutter:
    case SemanticClass::kPerson:
    case SemanticClass::kPlant:
    case SemanticClass::kBag:
    case SemanticClass::kClothes:
    case SemanticClass::kBall:
    case SemanticClass::kLamp:
    case SemanticClass::kBottle:
      return true;
    default:
      return false;
  }
}

const std::vector<Eigen::Vector2d>& RoomFootprint(const Place& place, int index) {
  return index == 0 ? place.footprint : place.adjoining_rooms[static_cast<size_t>(index - 1)];
}

const char* ClassName(SemanticClass c) {
  static const char* const kNames[] = {
      "none",   "floor", "wall",  "ceiling", "door",     "window", "table", "shelf",   "cabinet",
      "bed",    "sofa",  "chair", "box",     "cylinder", "book",   "mug",   "clutter", "person",
      "stairs", "plant", "bag",   "clothes", "ball",     "lamp",   "bottle"};
  static_assert(sizeof(kNames) / sizeof(kNames[0]) == kClassCount, "a name for every class");
  const int i = static_cast<int>(c);
  return i >= 0 && i < kClassCount ? kNames[i] : "unknown";
}

}  // namespace lifemap::sim
