#include "core/place/descriptor.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "absl/strings/str_format.h"

namespace lifemap::place {
namespace {

// Interior angle (degrees) at the corner where wall a (start→end) meets wall b, for a place
// traversed counter-clockwise: 90 at a convex right-angle corner, 270 at a reflex one.
double InteriorAngle(const Wall& a, const Wall& b) {
  const Eigen::Vector2d da = (a.end - a.start).normalized(), db = (b.end - b.start).normalized();
  const double turn = std::atan2(da.x() * db.y() - da.y() * db.x(), da.dot(db));  // left > 0
  return 180.0 - turn * 180.0 / M_PI;
}

// The same place walked the other way round: walls in reverse order, each read from its other
// end; the angle after reversed wall k is the one that preceded it.
PlaceDescriptor Reversed(const PlaceDescriptor& d) {
  PlaceDescriptor r;
  r.stairs = d.stairs;
  const size_t n = d.corners.size();
  for (size_t k = 0; k < n; ++k) {
    const CornerEntry& w = d.corners[n - 1 - k];
    CornerEntry e;
    e.length_m = w.length_m;
    e.angle_deg = d.corners[(2 * n - 2 - k) % n].angle_deg;
    for (const auto& o : w.openings) {
      e.openings.push_back({o.type, o.length_m, w.length_m - o.distance_m - o.length_m});
    }
    std::reverse(e.openings.begin(), e.openings.end());
    r.corners.push_back(std::move(e));
  }
  return r;
}

double OpeningsDifference(const std::vector<DescriptorOpening>& a,
                          const std::vector<DescriptorOpening>& b, const MatchWeights& w) {
  std::vector<bool> used(b.size(), false);
  double cost = 0;
  for (const auto& oa : a) {
    int best = -1;
    double best_cost = 0;
    for (size_t j = 0; j < b.size(); ++j) {
      if (used[j] || b[j].type != oa.type) continue;
      const double c =
          std::abs(oa.length_m - b[j].length_m) + std::abs(oa.distance_m - b[j].distance_m);
      if (best < 0 || c < best_cost) best = static_cast<int>(j), best_cost = c;
    }
    const double unmatched = oa.type == OpeningType::kDoor ? w.closed_door : w.missing_opening;
    if (best >= 0 && w.opening * best_cost < 2 * unmatched) {
      used[static_cast<size_t>(best)] = true;
      cost += w.opening * best_cost;
    } else {
      cost += unmatched;
    }
  }
  for (size_t j = 0; j < b.size(); ++j) {
    if (!used[j]) cost += b[j].type == OpeningType::kDoor ? w.closed_door : w.missing_opening;
  }
  return cost;
}

double StairsDifference(const std::vector<StairEntry>& a, const std::vector<StairEntry>& b,
                        const MatchWeights& w) {
  std::vector<bool> used(b.size(), false);
  double cost = 0;
  for (const auto& sa : a) {
    int best = -1;
    double best_cost = 0;
    for (size_t j = 0; j < b.size(); ++j) {
      if (used[j] || b[j].ascending != sa.ascending) continue;
      const double c = std::abs(sa.length_m - b[j].length_m) + std::abs(sa.width_m - b[j].width_m) +
                       std::abs(sa.distance_to_wall_m - b[j].distance_to_wall_m);
      if (best < 0 || c < best_cost) best = static_cast<int>(j), best_cost = c;
    }
    if (best >= 0) {
      used[static_cast<size_t>(best)] = true;
      cost += w.stairs * best_cost;
    } else {
      cost += w.missing_stairs;
    }
  }
  for (size_t j = 0; j < b.size(); ++j) cost += used[j] ? 0 : w.missing_stairs;
  return cost;
}

}  // namespace

PlaceDescriptor Describe(const FloorPlan& plan) {
  PlaceDescriptor d;
  const size_t n = plan.walls.size();
  for (size_t i = 0; i < n; ++i) {
    const Wall& w = plan.walls[i];
    CornerEntry e;
    e.length_m = w.length();
    e.angle_deg = InteriorAngle(w, plan.walls[(i + 1) % n]);
    for (const auto& o : w.openings) e.openings.push_back({o.type, o.length(), o.from_m});
    d.corners.push_back(std::move(e));
  }
  for (const auto& s : plan.stairs) {
    d.stairs.push_back({s.ascending, s.length_m, s.width_m, s.distance_to_wall_m});
  }
  return d;
}

std::string DescriptorText(const PlaceDescriptor& d) {
  std::string out;
  for (size_t i = 0; i < d.corners.size(); ++i) {
    const auto& c = d.corners[i];
    out += absl::StrFormat("C%d L=%.2f A=%.1f", static_cast<int>(i), c.length_m, c.angle_deg);
    for (const auto& o : c.openings) {
      out += absl::StrFormat(" %s(%.2f@%.2f)", o.type == OpeningType::kDoor ? "door" : "window",
                             o.length_m, o.distance_m);
    }
    out += "\n";
  }
  for (const auto& s : d.stairs) {
    out += absl::StrFormat("S %s L=%.2f W=%.2f D=%.2f\n", s.ascending ? "up" : "down", s.length_m,
                           s.width_m, s.distance_to_wall_m);
  }
  return out;
}

MatchResult MatchDescriptors(const PlaceDescriptor& query, const PlaceDescriptor& stored,
                             const MatchWeights& w) {
  MatchResult best;
  best.difference = std::numeric_limits<double>::infinity();
  const size_t nq = query.corners.size(), ns = stored.corners.size();
  if (nq == 0 || ns == 0) {
    best.score = 0;
    return best;
  }
  const size_t compared = std::min(nq, ns);
  const double base = w.missing_corner * static_cast<double>(std::max(nq, ns) - compared) +
                      StairsDifference(query.stairs, stored.stairs, w);
  const PlaceDescriptor reversed = Reversed(stored);
  for (int dir = 0; dir < 2; ++dir) {
    const PlaceDescriptor& s = dir == 0 ? stored : reversed;
    for (size_t start = 0; start < ns; ++start) {
      double diff = base;
      for (size_t i = 0; i < compared && diff < best.difference; ++i) {
        const CornerEntry& a = query.corners[i];
        const CornerEntry& b = s.corners[(start + i) % ns];
        diff += w.length * std::abs(a.length_m - b.length_m);
        // The last compared corner's angle only counts when both close the loop there.
        if (i + 1 < compared || nq == ns) diff += w.angle * std::abs(a.angle_deg - b.angle_deg);
        diff += OpeningsDifference(a.openings, b.openings, w);
      }
      if (diff < best.difference) {
        best.difference = diff;
        best.start = static_cast<int>(dir == 0 ? start : (2 * ns - 1 - start) % ns);
        best.reversed = dir == 1;
      }
    }
  }
  best.score = std::exp(-best.difference / static_cast<double>(compared) / 0.7 * std::log(2.0));
  return best;
}

}  // namespace lifemap::place
