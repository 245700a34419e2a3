#include "core/sim/generator.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <random>
#include <set>
#include <tuple>

#include <Eigen/Geometry>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"

namespace lifemap::sim {
namespace {

// A place for `s` whose footprint lies inside the room `margin` from the walls and clear of the
// solids standing on the same surface; false after many tries.
bool PlaceFreelyIn(const std::vector<Eigen::Vector2d>& room, const std::vector<Solid>& others,
                   Solid* s, std::mt19937_64* rng, double margin, const Eigen::Vector2d& lo,
                   const Eigen::Vector2d& hi) {
  std::uniform_real_distribution<double> ux(lo.x(), hi.x()), uy(lo.y(), hi.y()), yaw(-M_PI, M_PI);
  for (int attempt = 0; attempt < 200; ++attempt) {
    s->center = {ux(*rng), uy(*rng)};
    s->yaw = yaw(*rng);
    if (!InsidePolygon(room, s->center.x(), s->center.y()) ||
        DistanceToEdges(room, s->center) < FootprintRadius(*s) + margin) {
      continue;
    }
    bool clear = true;
    for (const auto& o : others) {
      // Stairs block every surface (a flight down leaves a hole in the floor).
      const bool same_surface =
          o.cls == SemanticClass::kStairs || std::abs(o.base_z - s->base_z) < 0.05;
      if (same_surface &&
          (o.center - s->center).norm() < FootprintRadius(o) + FootprintRadius(*s) + 0.05) {
        clear = false;
        break;
      }
    }
    if (clear) return true;
  }
  return false;
}

// The axis-aligned bounds of a footprint.
std::pair<Eigen::Vector2d, Eigen::Vector2d> Bounds(const std::vector<Eigen::Vector2d>& poly) {
  Eigen::Vector2d lo(1e9, 1e9), hi(-1e9, -1e9);
  for (const auto& p : poly) lo = lo.cwiseMin(p), hi = hi.cwiseMax(p);
  return {lo, hi};
}

// The same in the main room.
bool PlaceFreely(const Place& place, const std::vector<Solid>& others, Solid* s,
                 std::mt19937_64* rng, double margin, const Eigen::Vector2d& lo,
                 const Eigen::Vector2d& hi) {
  return PlaceFreelyIn(place.footprint, others, s, rng, margin, lo, hi);
}

Eigen::Vector3f RandomColor(std::mt19937_64* rng) {
  std::uniform_real_distribution<float> c(0.2f, 0.95f);
  return {c(*rng), c(*rng), c(*rng)};
}

// A movable prop of a random kind at height base_z.
Solid RandomProp(std::mt19937_64* rng, int instance, double base_z) {
  std::uniform_int_distribution<int> kind(0, 4);
  std::uniform_real_distribution<double> size(0.12, 0.35);
  Solid s;
  s.instance = instance;
  s.movable = true;
  s.base_z = base_z;
  s.texture_seed = static_cast<uint32_t>((*rng)());
  s.color = RandomColor(rng);
  switch (kind(*rng)) {
    case 0:
      s.cls = SemanticClass::kBox;
      s.size = {size(*rng), size(*rng), size(*rng)};
      break;
    case 1:
      s.cls = SemanticClass::kCylinder;
      s.shape = Solid::Shape::kCylinder;
      s.size = {size(*rng) * 0.7, 0, size(*rng) * 1.2};
      break;
    case 2:
      s.cls = SemanticClass::kMug;
      s.shape = Solid::Shape::kCylinder;
      s.size = {0.08, 0, 0.1};
      break;
    case 3:
      s.cls = SemanticClass::kBook;
      s.size = {0.22, 0.16, 0.04};
      break;
    default:
      s.cls = SemanticClass::kClutter;
      s.size = {0.08, 0.06, 0.05};
  }
  return s;
}

// The kinds of curved and crumpled props (PlaceStyle::curved_props).
enum class CurvedKind { kPlant, kBag, kClothes, kBall, kLamp, kBottle, kStack };

Solid Lathe(std::vector<Eigen::Vector2d> profile) {
  Solid s;
  s.shape = Solid::Shape::kLathe;
  double r = 0;
  for (const auto& p : profile) r = std::max(r, p.y());
  s.size = {2 * r, 2 * r, profile.back().x()};
  s.profile = std::move(profile);
  return s;
}

Solid Blob(const Eigen::Vector3d& size, double crumple, double frequency, double sink) {
  Solid s;
  s.shape = Solid::Shape::kBlob;
  s.size = size;
  s.crumple = crumple;
  s.crumple_frequency = frequency;
  s.sink_m = sink;
  return s;
}

// The parts of one movable curved or crumpled prop at the origin, yaw 0, standing at base_z,
// scaled by `scale` (smaller on a table). The parts of a plant, a lamp or a bottle share the
// instance; a stack's pieces are instances instance, instance + 1, ...; all share the group
// `instance`.
std::vector<Solid> CurvedProp(std::mt19937_64* rng, CurvedKind kind, int instance, double base_z,
                              double scale) {
  auto u = [rng](double lo, double hi) {
    return std::uniform_real_distribution<double>(lo, hi)(*rng);
  };
  std::vector<Solid> parts;
  switch (kind) {
    case CurvedKind::kPlant: {
      const double r = u(0.08, 0.14) * scale, h = u(0.15, 0.28) * scale;
      Solid pot = Lathe({{0, 0}, {0, 0.8 * r}, {h, r}, {h, 0}});
      pot.cls = SemanticClass::kPlant;
      pot.color = {static_cast<float>(u(0.5, 0.75)), static_cast<float>(u(0.25, 0.4)), 0.2f};
      parts.push_back(pot);
      Solid foliage =
          Blob(Eigen::Vector3d(u(0.3, 0.6), u(0.3, 0.6), u(0.35, 0.8)) * scale, 0.3, 6.0, 0);
      foliage.cls = SemanticClass::kPlant;
      foliage.base_z = h - 0.03 * scale;
      foliage.color = {static_cast<float>(u(0.12, 0.3)), static_cast<float>(u(0.4, 0.65)),
                       static_cast<float>(u(0.1, 0.25))};
      parts.push_back(foliage);
      break;
    }
    case CurvedKind::kBag:
      parts.push_back(Blob(Eigen::Vector3d(u(0.3, 0.5), u(0.18, 0.3), u(0.28, 0.45)) * scale, 0.08,
                           2.5, 0.02 * scale));
      parts.back().cls = SemanticClass::kBag;
      break;
    case CurvedKind::kClothes: {
      const Eigen::Vector3d size = Eigen::Vector3d(u(0.5, 0.8), u(0.4, 0.7), u(0.3, 0.5)) * scale;
      parts.push_back(Blob(size, 0.25, 5.0, 0.45 * size.z()));
      parts.back().cls = SemanticClass::kClothes;
      break;
    }
    case CurvedKind::kBall: {
      const double d = u(0.15, 0.3) * scale;
      parts.push_back(Blob(Eigen::Vector3d(d, d, d), 0, 1, 0));
      parts.back().cls = SemanticClass::kBall;
      break;
    }
    case CurvedKind::kLamp: {
      const double h = u(1.4, 1.7) * scale, shade = u(0.18, 0.25) * scale;
      parts.push_back(Lathe({{0, 0},
                             {0, 0.15 * scale},
                             {0.03 * scale, 0.15 * scale},
                             {0.03 * scale, 0.015 * scale},
                             {h - 0.3 * scale, 0.015 * scale},
                             {h - 0.3 * scale, shade},
                             {h, 0.55 * shade},
                             {h, 0}}));
      parts.back().cls = SemanticClass::kLamp;
      break;
    }
    case CurvedKind::kBottle: {
      const double r = u(0.03, 0.045), h = u(0.2, 0.32);
      parts.push_back(
          Lathe({{0, 0}, {0, r}, {0.6 * h, r}, {0.78 * h, 0.35 * r}, {h, 0.35 * r}, {h, 0}}));
      parts.back().cls = SemanticClass::kBottle;
      break;
    }
    case CurvedKind::kStack: {
      // Irregular clutter piled up: boxes and lumps, each resting on the one below.
      const int pieces = 2 + static_cast<int>((*rng)() % 3);
      double z = 0;
      for (int i = 0; i < pieces; ++i) {
        const Eigen::Vector3d size =
            Eigen::Vector3d(u(0.15, 0.35), u(0.15, 0.35), u(0.06, 0.15)) * scale;
        Solid piece = (*rng)() % 2 == 0 ? Blob(size, 0.15, 4.0, 0) : Solid();
        if (piece.shape == Solid::Shape::kBox) piece.size = size;
        piece.cls = SemanticClass::kClutter;
        piece.instance = instance + i;
        piece.center = {u(-0.03, 0.03), u(-0.03, 0.03)};
        piece.yaw = u(-0.4, 0.4);
        piece.base_z = z;
        z += size.z();
        parts.push_back(piece);
      }
      break;
    }
  }
  for (auto& part : parts) {
    if (part.instance == 0) part.instance = instance;
    part.group = instance;
    part.movable = true;
    part.base_z += base_z;
    part.texture_seed = static_cast<uint32_t>((*rng)());
    if (part.cls != SemanticClass::kPlant) part.color = RandomColor(rng);
  }
  return parts;
}

// Places the parts of a prop (built at the origin by CurvedProp) clear of `others` inside the
// room, turned together; false after many tries.
bool PlacePropIn(const std::vector<Eigen::Vector2d>& room, const std::vector<Solid>& others,
                 std::vector<Solid>* parts, std::mt19937_64* rng, double margin,
                 const Eigen::Vector2d& lo, const Eigen::Vector2d& hi) {
  // A cylinder around every part stands for the prop while it is placed.
  Solid probe = parts->front();
  probe.shape = Solid::Shape::kCylinder;
  double radius = 0;
  for (const auto& p : *parts) radius = std::max(radius, p.center.norm() + FootprintRadius(p));
  probe.size = {2 * radius, 2 * radius, 1};
  if (!PlaceFreelyIn(room, others, &probe, rng, margin, lo, hi)) return false;
  const Eigen::Rotation2Dd turn(probe.yaw);
  for (auto& p : *parts) {
    p.center = probe.center + turn * p.center;
    p.yaw += probe.yaw;
  }
  return true;
}

// One more next_instance for every instance among the parts.
int InstancesUsed(const std::vector<Solid>& parts) {
  int last = 0;
  for (const auto& p : parts) last = std::max(last, p.instance);
  return parts.empty() ? 0 : last - parts.front().instance + 1;
}

// Where a table's top is: the square its props stand in.
std::pair<Eigen::Vector2d, Eigen::Vector2d> TableTop(const Solid& table) {
  const double r = std::min(table.size.x(), table.size.y()) / 2 - 0.05;
  return {table.center - Eigen::Vector2d(r, r), table.center + Eigen::Vector2d(r, r)};
}

// A curved prop of a random kind for a table (small) or the floor.
std::vector<Solid> RandomCurvedProp(std::mt19937_64* rng, int instance, double base_z,
                                    bool on_table) {
  static const CurvedKind kTable[] = {CurvedKind::kPlant, CurvedKind::kBag, CurvedKind::kBall,
                                      CurvedKind::kBottle, CurvedKind::kStack};
  static const CurvedKind kFloor[] = {CurvedKind::kPlant, CurvedKind::kBag,  CurvedKind::kClothes,
                                      CurvedKind::kBall,  CurvedKind::kLamp, CurvedKind::kStack};
  const CurvedKind kind = on_table ? kTable[(*rng)() % 5] : kFloor[(*rng)() % 6];
  return CurvedProp(rng, kind, instance, base_z, on_table ? 0.6 : 1.0);
}

// Whether the straight line from a to b stays inside the polygon (crosses none of its edges).
bool InSight(const std::vector<Eigen::Vector2d>& polygon, const Eigen::Vector2d& a,
             const Eigen::Vector2d& b) {
  auto cross = [](const Eigen::Vector2d& u, const Eigen::Vector2d& v) {
    return u.x() * v.y() - u.y() * v.x();
  };
  const Eigen::Vector2d d = b - a;
  for (size_t i = 0; i < polygon.size(); ++i) {
    const Eigen::Vector2d& p = polygon[i];
    const Eigen::Vector2d e = polygon[(i + 1) % polygon.size()] - p;
    const double den = cross(d, e);
    if (std::abs(den) < 1e-12) continue;
    const double t = cross(p - a, e) / den, u = cross(p - a, d) / den;
    if (t > 1e-9 && t < 1 - 1e-9 && u >= 0 && u <= 1) return false;
  }
  return true;
}

Pose LookPose(const Eigen::Vector3d& position, double yaw, double pitch) {
  const Eigen::Vector3d forward(std::cos(yaw) * std::cos(pitch), std::sin(yaw) * std::cos(pitch),
                                -std::sin(pitch));
  const Eigen::Vector3d right = forward.cross(Eigen::Vector3d::UnitZ()).normalized();
  const Eigen::Vector3d down = forward.cross(right);
  Eigen::Matrix3d R;
  R.col(0) = right;
  R.col(1) = down;
  R.col(2) = forward;
  Pose p;
  p.translation = position;
  p.rotation = Eigen::Quaterniond(R).normalized();
  return p;
}

}  // namespace

std::vector<Solid> StairSolids(const Stairs& st, int first_instance) {
  std::vector<Solid> steps;
  const Eigen::Vector2d dir(std::cos(st.yaw), std::sin(st.yaw));
  for (int i = 0; i < st.steps; ++i) {
    Solid s;
    s.cls = SemanticClass::kStairs;
    s.instance = first_instance + i;
    s.yaw = st.yaw;
    s.color = {0.5f, 0.5f, 0.52f};
    s.texture_seed = 977U + static_cast<uint32_t>(i);
    s.center = st.origin + dir * (st.run_m * (i + 0.5));
    s.size = {st.run_m, st.width_m, 0};
    if (st.up) {
      // Step i: a block from the floor up to its tread, (i + 1) risers high.
      s.base_z = 0;
      s.size.z() = st.rise_m * (i + 1);
    } else {
      // Step i down: its tread (i + 1) risers below the floor, a block down to the flight's
      // bottom.
      const double bottom = -st.rise_m * (st.steps + 1);
      s.base_z = bottom;
      s.size.z() = -st.rise_m * (i + 1) - bottom;
    }
    steps.push_back(s);
  }
  return steps;
}

absl::StatusOr<Conditions> ParseConditions(const std::string& text) {
  Conditions c;
  if (text.empty() || text == "none") return c;
  for (absl::string_view part : absl::StrSplit(text, ',')) {
    if (part == "lighting") {
      c.lighting = true;
    } else if (part == "scenery") {
      c.scenery = true;
    } else if (part == "dynamic") {
      c.dynamic = true;
    } else {
      return absl::InvalidArgumentError(
          absl::StrCat("unknown condition '", part,
                       "': use lighting, dynamic, scenery (comma-separated) or none"));
    }
  }
  return c;
}

Materials RoomMaterials(uint32_t texture_seed) {
  Materials m;
  m.floor = {texture_seed * 3 + 11, {0.55f, 0.42f, 0.30f}, 1.0, 1.0f, true, 0};
  m.ceiling = {texture_seed * 3 + 13, {0.9f, 0.9f, 0.88f}, 0.3, 1.0f, true, 0};
  m.wall = {texture_seed * 5, {0.82f, 0.80f, 0.74f}, 0.5, 1.0f, true, 0};
  m.wall_per_segment = true;
  return m;
}

Materials BuildingMaterials(uint64_t building_seed) {
  std::mt19937_64 rng(building_seed * 0xA24BAED4963EE407ULL + 3);
  auto seed = [&rng] { return static_cast<uint32_t>(rng()); };
  std::uniform_real_distribution<float> tone(0.35f, 0.7f), paint(0.75f, 0.9f);
  Materials m;
  // Carpet or vinyl tiles, 50 cm, the same print on every tile of every room.
  m.floor = {seed(), {tone(rng), tone(rng) * 0.9f, tone(rng) * 0.8f}, 2.0, 0.8f, true, 0.5};
  m.ceiling = {seed(), {0.9f, 0.9f, 0.88f}, 0.3, 0.3f, false, 0};
  // Paint: nearly plain, one colour throughout.
  const float white = paint(rng);
  m.wall = {seed(), {white, white * 0.98f, white * 0.93f}, 0.5, 0.15f, false, 0};
  m.wall_per_segment = false;
  return m;
}

absl::StatusOr<PlaceStyle> ParseWorld(const std::string& world, uint64_t building_seed) {
  PlaceStyle style;
  if (world == "rooms") return style;
  if (world == "building") {
    style.curved_props = true;
    style.building_seed = building_seed == 0 ? 1 : building_seed;
    return style;
  }
  return absl::InvalidArgumentError(absl::StrCat(
      "unknown world '", world,
      "': use building (places sharing materials and furniture, curved props) or rooms (each "
      "place its own textures, boxes and cylinders)"));
}

absl::StatusOr<Place> GeneratePlace(uint64_t seed, const std::string& shape,
                                    const PlaceStyle& style) {
  std::mt19937_64 rng(seed * 0x9E3779B97F4A7C15ULL + 1);
  std::uniform_real_distribution<double> side(3.5, 7.5);
  Place place;
  place.shape = shape;
  place.id = absl::StrCat("place-", seed, "-", shape);
  place.texture_seed = static_cast<uint32_t>(rng());
  place.wall_height_m = std::uniform_real_distribution<double>(2.5, 3.2)(rng);
  const double w = side(rng);
  const double d = shape == "square" ? w : side(rng);
  if (shape == "rect" || shape == "square") {
    place.footprint = {{0, 0}, {w, 0}, {w, d}, {0, d}};
  } else if (shape == "L") {
    const double cw = w * std::uniform_real_distribution<double>(0.35, 0.55)(rng);
    const double cd = d * std::uniform_real_distribution<double>(0.35, 0.55)(rng);
    place.footprint = {{0, 0}, {w, 0}, {w, d - cd}, {w - cw, d - cd}, {w - cw, d}, {0, d}};
  } else if (shape == "T") {
    // A stem (width sw, length sl) below a bar (width w + 2, depth bd), counter-clockwise.
    const double bar = w + 2.0;
    const double sw = std::max(2.2, w * 0.5), sl = d * 0.6, bd = std::max(2.5, d * 0.6);
    const double x0 = (bar - sw) / 2, x1 = (bar + sw) / 2;
    place.footprint = {{x0, 0},        {x1, 0},      {x1, sl}, {bar, sl},
                       {bar, sl + bd}, {0, sl + bd}, {0, sl},  {x0, sl}};
  } else if (shape == "U") {
    // A block with a notch (width nw, depth nd) cut into its far side, counter-clockwise.
    const double uw = w + 2.0, ud = d + 1.0;
    const double nw = uw * 0.34, nd = ud * 0.45;
    const double x0 = (uw - nw) / 2, x1 = (uw + nw) / 2;
    place.footprint = {{0, 0},        {uw, 0},       {uw, ud}, {x1, ud},
                       {x1, ud - nd}, {x0, ud - nd}, {x0, ud}, {0, ud}};
  } else {
    return absl::InvalidArgumentError(
        absl::StrCat("place shape '", shape, "' is not one of rect, square, L, T, U"));
  }
  // A door on the first wall, windows on other walls long enough for one.
  const size_t n = place.footprint.size();
  auto wall_length = [&](size_t i) {
    return (place.footprint[(i + 1) % n] - place.footprint[i]).norm();
  };
  Opening door;
  door.type = OpeningType::kDoor;
  door.wall = 0;
  door.width_m = 0.9;
  door.offset_m = std::uniform_real_distribution<double>(0.4, wall_length(0) - 1.3)(rng);
  door.open = true;
  door.connects = true;
  place.openings.push_back(door);
  {
    // A second room beyond the first wall (wall 0 runs along +x at y = 0 for every shape),
    // reached through the door: its shared wall runs the other way and holds the door's twin.
    const Eigen::Vector2d a = place.footprint[0], b = place.footprint[1];
    const double depth = std::uniform_real_distribution<double>(2.5, 4.0)(rng);
    place.adjoining_rooms.push_back({{a.x(), -depth}, {b.x(), -depth}, {b.x(), 0.0}, {a.x(), 0.0}});
    Opening twin = door;
    twin.room = 1;
    twin.wall = 2;
    twin.offset_m = (b - a).norm() - door.offset_m - door.width_m;
    place.openings.push_back(twin);
    if ((b - a).norm() > 2.6) {
      Opening window;
      window.type = OpeningType::kWindow;
      window.room = 1;
      window.wall = 0;
      window.width_m = 1.0;
      window.offset_m = std::uniform_real_distribution<double>(0.4, (b - a).norm() - 1.4)(rng);
      window.sill_m = 1.2;
      place.openings.push_back(window);
    }
  }
  for (size_t i = 1; i < n; ++i) {
    if (wall_length(i) < 2.2 || (rng() % 3) == 0) continue;
    Opening window;
    window.type = OpeningType::kWindow;
    window.wall = static_cast<int>(i);
    window.width_m = std::uniform_real_distribution<double>(0.8, 1.4)(rng);
    window.offset_m =
        std::uniform_real_distribution<double>(0.4, wall_length(i) - window.width_m - 0.4)(rng);
    window.sill_m = std::uniform_real_distribution<double>(1.1, 1.3)(rng);
    window.top_m = 2.1;
    place.openings.push_back(window);
  }

  // Furniture: a table in the open, a shelf and a cabinet against walls.
  const auto [lo, hi] = Bounds(place.footprint);
  int instance = 1;
  Solid table;
  table.cls = SemanticClass::kTable;
  table.instance = instance++;
  table.size = {1.2, 0.8, 0.75};
  table.texture_seed = static_cast<uint32_t>(rng());
  table.color = {0.6f, 0.45f, 0.3f};
  if (PlaceFreely(place, place.solids, &table, &rng, 0.7, lo, hi)) place.solids.push_back(table);
  for (auto [cls, size] : {std::pair{SemanticClass::kShelf, Eigen::Vector3d(0.9, 0.35, 1.8)},
                           std::pair{SemanticClass::kCabinet, Eigen::Vector3d(0.6, 0.5, 0.9)}}) {
    // Against a wall: along the wall's direction, pushed in from it.
    const size_t wi = 1 + rng() % (n - 1);
    const Eigen::Vector2d a = place.footprint[wi], b = place.footprint[(wi + 1) % n];
    const double length = (b - a).norm();
    if (length < size.x() + 0.8) continue;
    const Eigen::Vector2d e = (b - a) / length, inward(-e.y(), e.x());
    Solid s;
    s.cls = cls;
    s.instance = instance++;
    s.size = size;
    s.yaw = std::atan2(e.y(), e.x());
    s.center = a +
               e * std::uniform_real_distribution<double>(0.4 + size.x() / 2,
                                                          length - 0.4 - size.x() / 2)(rng) +
               inward * (size.y() / 2 + 0.02);
    s.texture_seed = static_cast<uint32_t>(rng());
    s.color = RandomColor(&rng);
    bool clear = true;
    for (const auto& o : place.solids) {
      if ((o.center - s.center).norm() < FootprintRadius(o) + FootprintRadius(s)) clear = false;
    }
    // Keep clear of the wall's openings.
    for (const auto& op : place.openings) {
      const double u = e.dot(s.center - a);
      if (op.wall == static_cast<int>(wi) && u + size.x() / 2 > op.offset_m - 0.1 &&
          u - size.x() / 2 < op.offset_m + op.width_m + 0.1) {
        clear = false;
      }
    }
    if (clear) place.solids.push_back(s);
  }
  // Half the places have a flight of stairs along a wall, going up or down: the first wall
  // (from a random one) with room for it clear of openings and furniture.
  if (rng() % 2 == 0) {
    Stairs st;
    st.up = rng() % 2 == 0;
    st.steps = 5 + static_cast<int>(rng() % 4);
    st.rise_m = std::uniform_real_distribution<double>(0.15, 0.19)(rng);
    st.run_m = std::uniform_real_distribution<double>(0.26, 0.32)(rng);
    st.width_m = 1.0;
    const double flight = st.run_m * st.steps;
    const size_t first = rng() % n;
    for (size_t k = 0; k < n && place.stairs.empty(); ++k) {
      const size_t wi = (first + k) % n;
      const Eigen::Vector2d a = place.footprint[wi], b = place.footprint[(wi + 1) % n];
      const double length = (b - a).norm();
      if (length < flight + 1.0) continue;
      const Eigen::Vector2d e = (b - a) / length, inward(-e.y(), e.x());
      const double u = std::uniform_real_distribution<double>(0.4, length - flight - 0.4)(rng);
      bool clear = true;
      for (const auto& op : place.openings) {
        if (op.wall == static_cast<int>(wi) && u < op.offset_m + op.width_m + 0.3 &&
            u + flight > op.offset_m - 0.3) {
          clear = false;
        }
      }
      st.yaw = std::atan2(e.y(), e.x());
      st.origin = a + e * u + inward * (st.width_m / 2 + 0.02);
      const Eigen::Vector2d mid = st.origin + e * (flight / 2);
      for (const auto& o : place.solids) {
        if ((o.center - mid).norm() < FootprintRadius(o) + flight / 2 + 0.3) clear = false;
      }
      if (!clear) continue;
      place.stairs.push_back(st);
      for (const auto& step : StairSolids(st, 1000)) place.solids.push_back(step);
    }
  }
  // Props: on the table and on the floor.
  std::uniform_int_distribution<int> count(3, 6);
  const int on_table = place.solids.empty() ? 0 : count(rng);
  for (int i = 0; i < on_table; ++i) {
    Solid prop = RandomProp(&rng, instance, table.base_z + table.size.z());
    const auto [tlo, thi] = TableTop(table);
    if (PlaceFreely(place, place.solids, &prop, &rng, 0.0, tlo, thi)) {
      ++instance;
      place.solids.push_back(prop);
    }
  }
  for (int i = 0; i < 3; ++i) {
    Solid prop = RandomProp(&rng, instance, 0.0);
    if (PlaceFreely(place, place.solids, &prop, &rng, 0.3, lo, hi)) {
      ++instance;
      place.solids.push_back(prop);
    }
  }
  // Chairs (furniture that gets rearranged: movable) and, in larger rooms, a sofa or a bed.
  for (int i = 0; i < 2; ++i) {
    Solid chair;
    chair.cls = SemanticClass::kChair;
    chair.instance = instance;
    chair.movable = true;
    chair.size = {0.45, 0.45, 0.9};
    chair.texture_seed = static_cast<uint32_t>(rng());
    chair.color = RandomColor(&rng);
    if (PlaceFreely(place, place.solids, &chair, &rng, 0.3, lo, hi)) {
      ++instance;
      place.solids.push_back(chair);
    }
  }
  if ((hi - lo).prod() > 20.0) {
    Solid big;
    const bool bed = rng() % 2 == 0;
    big.cls = bed ? SemanticClass::kBed : SemanticClass::kSofa;
    big.instance = instance;
    big.size = bed ? Eigen::Vector3d(2.0, 1.4, 0.55) : Eigen::Vector3d(1.9, 0.85, 0.8);
    big.texture_seed = static_cast<uint32_t>(rng());
    big.color = RandomColor(&rng);
    if (PlaceFreely(place, place.solids, &big, &rng, 0.4, lo, hi)) {
      ++instance;
      place.solids.push_back(big);
    }
  }
  // Clutter: a heap of many small pieces on the floor (each its own instance).
  Solid heap_centre = RandomProp(&rng, 0, 0.0);
  heap_centre.size = {0.6, 0.6, 0.1};
  if (PlaceFreely(place, place.solids, &heap_centre, &rng, 0.3, lo, hi)) {
    std::uniform_real_distribution<double> offset(-0.25, 0.25), piece(0.04, 0.14);
    const int pieces = 6 + static_cast<int>(rng() % 7);
    for (int i = 0; i < pieces; ++i) {
      Solid bit;
      bit.cls = SemanticClass::kClutter;
      bit.instance = instance++;
      bit.movable = true;
      bit.shape = rng() % 3 == 0 ? Solid::Shape::kCylinder : Solid::Shape::kBox;
      bit.center = heap_centre.center + Eigen::Vector2d(offset(rng), offset(rng));
      bit.yaw = std::uniform_real_distribution<double>(-M_PI, M_PI)(rng);
      bit.base_z = (i % 3) * 0.04;  // a little pile: some pieces rest on others
      bit.size = {piece(rng), piece(rng), piece(rng) * 0.6};
      bit.texture_seed = static_cast<uint32_t>(rng());
      bit.color = RandomColor(&rng);
      place.solids.push_back(bit);
    }
  }
  // The adjoining room: a cabinet and a few props.
  for (const auto& room : place.adjoining_rooms) {
    const auto [rlo, rhi] = Bounds(room);
    Solid cabinet;
    cabinet.cls = SemanticClass::kCabinet;
    cabinet.instance = instance;
    cabinet.size = {0.8, 0.5, 1.0};
    cabinet.texture_seed = static_cast<uint32_t>(rng());
    cabinet.color = RandomColor(&rng);
    if (PlaceFreelyIn(room, place.solids, &cabinet, &rng, 0.2, rlo, rhi)) {
      ++instance;
      place.solids.push_back(cabinet);
    }
    for (int i = 0; i < 3; ++i) {
      Solid prop = RandomProp(&rng, instance, 0.0);
      if (PlaceFreelyIn(room, place.solids, &prop, &rng, 0.2, rlo, rhi)) {
        ++instance;
        place.solids.push_back(prop);
      }
    }
  }
  place.style = style;
  place.materials = style.building_seed != 0 ? BuildingMaterials(style.building_seed)
                                             : RoomMaterials(place.texture_seed);
  if (style.building_seed != 0) {
    // The building's furniture models: one texture and colour per class, in every place.
    for (auto& s : place.solids) {
      if (s.cls < SemanticClass::kTable || s.cls > SemanticClass::kChair) continue;
      std::mt19937_64 model(style.building_seed * 0x9FB21C651E98DF25ULL +
                            static_cast<uint64_t>(s.cls));
      s.texture_seed = static_cast<uint32_t>(model());
      s.color = RandomColor(&model);
    }
  }
  if (style.curved_props) {
    // Curved and crumpled props: a few small ones on the table, more on the floor of each room.
    std::mt19937_64 props(seed * 0xC2B2AE3D27D4EB4FULL + 5);
    // Places a prop's parts in the room (inside lo..hi) and takes its instances, if it fits.
    auto add = [&](std::vector<Solid> parts, const std::vector<Eigen::Vector2d>& room,
                   double margin, const Eigen::Vector2d& plo, const Eigen::Vector2d& phi) {
      if (!PlacePropIn(room, place.solids, &parts, &props, margin, plo, phi)) return;
      instance += InstancesUsed(parts);
      place.solids.insert(place.solids.end(), parts.begin(), parts.end());
    };
    const bool table_placed =
        std::any_of(place.solids.begin(), place.solids.end(),
                    [](const Solid& s) { return s.cls == SemanticClass::kTable; });
    if (table_placed) {
      const auto [tlo, thi] = TableTop(table);
      for (int i = 0; i < 2; ++i) {
        add(RandomCurvedProp(&props, instance, table.base_z + table.size.z(), true),
            place.footprint, 0.0, tlo, thi);
      }
    }
    static const CurvedKind kMainRoom[] = {
        CurvedKind::kPlant, CurvedKind::kPlant, CurvedKind::kClothes, CurvedKind::kBag,
        CurvedKind::kBall,  CurvedKind::kLamp,  CurvedKind::kStack};
    for (CurvedKind kind : kMainRoom) {
      add(CurvedProp(&props, kind, instance, 0.0, 1.0), place.footprint, 0.3, lo, hi);
    }
    for (const auto& room : place.adjoining_rooms) {
      const auto [rlo, rhi] = Bounds(room);
      for (int i = 0; i < 2; ++i)
        add(RandomCurvedProp(&props, instance, 0.0, false), room, 0.2, rlo, rhi);
    }
  }
  return place;
}

std::vector<Solid> Visit::SolidsAt(size_t f) const {
  std::vector<Solid> out = solids;
  const double t = trajectory.size() > 1 ? static_cast<double>(f) / (trajectory.size() - 1) : 0.0;
  for (const auto& w : walkers) {
    Solid body = w.body;
    body.center = w.from + t * (w.to - w.from);
    out.push_back(body);
  }
  return out;
}

absl::StatusOr<std::vector<Visit>> GenerateVisits(const Place& place, uint64_t seed, int count,
                                                  double months_apart, const Conditions& conditions,
                                                  int frames) {
  if (count < 1 || count > 100) {
    return absl::InvalidArgumentError(absl::StrCat("visits must be within [1, 100], got ", count));
  }
  if (frames < 2 || frames > 100000) {
    return absl::InvalidArgumentError(
        absl::StrCat("frames per visit must be within [2, 100000], got ", frames));
  }
  if (!(months_apart >= 0 && months_apart <= 120)) {
    return absl::InvalidArgumentError(
        absl::StrCat("months apart must be within [0, 120], got ", months_apart));
  }
  std::mt19937_64 rng(seed * 0xD1B54A32D192ED03ULL + 7);
  // The trajectory circles the point farthest from the walls.
  const auto [lo, hi] = Bounds(place.footprint);
  Eigen::Vector2d centre = (lo + hi) / 2;
  double clearance = 0;
  for (double x = lo.x(); x <= hi.x(); x += 0.1) {
    for (double y = lo.y(); y <= hi.y(); y += 0.1) {
      const Eigen::Vector2d p(x, y);
      if (!InsidePolygon(place.footprint, p.x(), p.y())) continue;
      const double dist = DistanceToEdges(place.footprint, p);
      if (dist > clearance) clearance = dist, centre = p;
    }
  }
  const double radius = std::min(0.8, 0.4 * clearance);
  // A room not seen whole from that point (T, U; some L) gets further loops: each around the
  // clearest point not yet in sight, until every part of the floor is in sight of a loop and
  // near it (within kSightM: an arm of a U seen from afar shows its walls edge-on).
  constexpr double kSightM = 4.0;
  struct Loop {
    Eigen::Vector2d centre;
    double radius;
  };
  std::vector<Loop> loops = {{centre, radius}};
  for (int extra = 0; extra < 3; ++extra) {
    double best = 0;
    Eigen::Vector2d next = centre;
    for (double x = lo.x(); x <= hi.x(); x += 0.1) {
      for (double y = lo.y(); y <= hi.y(); y += 0.1) {
        const Eigen::Vector2d p(x, y);
        if (!InsidePolygon(place.footprint, p.x(), p.y())) continue;
        bool seen = false;
        for (const auto& l : loops) {
          seen =
              seen || ((l.centre - p).norm() <= kSightM && InSight(place.footprint, l.centre, p));
        }
        const double dist = DistanceToEdges(place.footprint, p);
        if (!seen && dist > best) best = dist, next = p;
      }
    }
    if (best < 0.8) break;  // only corners and slivers out of sight: no room for a loop
    loops.push_back({next, std::min(0.8, 0.4 * best)});
  }
  constexpr double kFirstVisit = 1.7e9;  // 2023-11-14 UTC
  std::vector<Visit> visits;
  int next_instance = 1;
  for (const auto& s : place.solids) next_instance = std::max(next_instance, s.instance + 1);
  for (int vi = 0; vi < count; ++vi) {
    Visit v;
    v.index = vi;
    v.months_since_first = vi * months_apart;
    v.start_time_s = kFirstVisit + v.months_since_first * 30.44 * 86400.0;
    if (vi == 0) {
      v.solids = place.solids;
      v.openings = place.openings;
    } else {
      const Visit& prev = visits.back();
      v.solids = prev.solids;
      v.openings = prev.openings;
      v.lighting = prev.lighting;
      if (conditions.scenery) {
        std::uniform_real_distribution<double> p(0.0, 1.0);
        std::vector<Solid> kept;
        // What happened to each group (the solids that move together), decided at its first
        // solid and applied to the rest.
        struct Fate {
          bool vanished = false;
          Eigen::Vector2d from{0, 0}, to{0, 0};
          double turn = 0;
        };
        std::map<int, Fate> fates;
        std::set<int> reported;
        auto report = [&](const char* kind, const Solid& s) {
          if (reported.insert(s.instance).second) {
            v.changes.push_back({kind, s.instance, ClassName(s.cls)});
          }
        };
        for (auto s : v.solids) {
          if (!s.movable) {
            kept.push_back(s);
            continue;
          }
          if (s.group > 0) {
            if (auto it = fates.find(s.group); it != fates.end()) {
              const Fate& fate = it->second;
              if (fate.vanished) {
                report("vanished", s);
                continue;
              }
              if (fate.turn != 0 || fate.to != fate.from) {
                s.center = fate.to + Eigen::Rotation2Dd(fate.turn) * (s.center - fate.from);
                s.yaw += fate.turn;
                report("moved", s);
              }
              kept.push_back(s);
              continue;
            }
          }
          Fate fate;
          fate.from = fate.to = s.center;
          const double r = p(rng);
          if (r < 0.2) {
            report("vanished", s);
            fate.vanished = true;
            if (s.group > 0) fates[s.group] = fate;
            continue;
          }
          if (r < 0.7) {
            std::vector<Solid> others = kept;
            for (const auto& o : v.solids) {
              const bool together = s.group > 0 ? o.group == s.group : o.instance == s.instance;
              if (!together) others.push_back(o);
            }
            Solid moved = s;
            const Eigen::Vector2d span(0.5, 0.5);
            if (PlaceFreely(place, others, &moved, &rng, 0.0, s.center - span, s.center + span)) {
              report("moved", s);
              fate.to = moved.center;
              fate.turn = moved.yaw - s.yaw;
              s = moved;
            }
          }
          if (s.group > 0) fates[s.group] = fate;
          kept.push_back(s);
        }
        v.solids = kept;
        const Solid* table = nullptr;
        for (const auto& s : place.solids) {
          if (s.cls == SemanticClass::kTable) table = &s;
        }
        for (int i = 0; i < 2; ++i) {
          const double base = table && (rng() & 1) ? table->base_z + table->size.z() : 0.0;
          Eigen::Vector2d plo = lo, phi = hi;
          if (base > 0) std::tie(plo, phi) = TableTop(*table);
          const double margin = base > 0 ? 0.0 : 0.3;
          if (place.style.curved_props && rng() % 2 == 0) {
            // Half of what appears in a world of curved props is curved.
            auto parts = RandomCurvedProp(&rng, next_instance, base, base > 0);
            if (PlacePropIn(place.footprint, v.solids, &parts, &rng, margin, plo, phi)) {
              for (const auto& part : parts) {
                if (part.instance >= next_instance) {
                  v.changes.push_back({"appeared", part.instance, ClassName(part.cls)});
                  next_instance = part.instance + 1;
                }
              }
              v.solids.insert(v.solids.end(), parts.begin(), parts.end());
            }
            continue;
          }
          Solid prop = RandomProp(&rng, next_instance, base);
          if (PlaceFreely(place, v.solids, &prop, &rng, margin, plo, phi)) {
            v.changes.push_back({"appeared", next_instance, ClassName(prop.cls)});
            ++next_instance;
            v.solids.push_back(prop);
          }
        }
        bool toggle_connecting = false;
        for (auto& op : v.openings) {
          if (op.type != OpeningType::kDoor || op.room != 0) continue;
          if (p(rng) < 0.5) {
            op.open = !op.open;
            toggle_connecting |= op.connects;
            v.changes.push_back({op.open ? "door_opened" : "door_closed", 0, ""});
          }
        }
        // A connecting door's twin (the same door seen from the other room) follows it.
        for (auto& op : v.openings) {
          if (toggle_connecting && op.connects && op.room != 0) op.open = !op.open;
        }
      }
      if (conditions.lighting) {
        std::uniform_real_distribution<double> b(0.55, 1.3), t(-0.15, 0.15);
        v.lighting.brightness = b(rng);
        const float warm = static_cast<float>(t(rng));
        v.lighting.tint = {1.0f + warm, 1.0f, 1.0f - warm};
        // A standing lamp near a corner, switched on or off.
        v.lighting.lamp_on = rng() % 2 == 0;
        const Eigen::Vector2d corner = place.footprint[rng() % place.footprint.size()];
        const Eigen::Vector2d towards = (centre - corner).normalized();
        v.lighting.lamp =
            Eigen::Vector3d(corner.x() + 0.5 * towards.x(), corner.y() + 0.5 * towards.y(), 1.7);
        v.changes.push_back({"lighting", 0,
                             absl::StrCat("brightness ", v.lighting.brightness, ", lamp ",
                                          v.lighting.lamp_on ? "on" : "off")});
      }
    }
    if (conditions.dynamic && vi > 0) {
      // One or two people cross the room during the visit.
      const int people = 1 + static_cast<int>(rng() % 2);
      for (int i = 0; i < people; ++i) {
        Walker w;
        w.body.shape = Solid::Shape::kCylinder;
        w.body.cls = SemanticClass::kPerson;
        w.body.instance = next_instance++;
        w.body.movable = true;
        w.body.size = {0.4, 0, std::uniform_real_distribution<double>(1.6, 1.85)(rng)};
        w.body.color = RandomColor(&rng);
        w.body.texture_seed = static_cast<uint32_t>(rng());
        // From near one wall to near another, through the room's free middle.
        for (Eigen::Vector2d* end : {&w.from, &w.to}) {
          for (int attempt = 0; attempt < 200; ++attempt) {
            const Eigen::Vector2d p(std::uniform_real_distribution<double>(lo.x(), hi.x())(rng),
                                    std::uniform_real_distribution<double>(lo.y(), hi.y())(rng));
            if (InsidePolygon(place.footprint, p.x(), p.y()) &&
                DistanceToEdges(place.footprint, p) > 0.5) {
              *end = p;
              break;
            }
          }
        }
        v.walkers.push_back(w);
        v.changes.push_back({"person", w.body.instance, "walking through"});
      }
    }
    // A loop and a quarter around the centre, looking outwards at the walls, camera at ~1.4 m:
    // consecutive frames overlap, and the last quarter revisits the start (a loop closure).
    // With several loops, the frames are shared among them and each loop is whole plus a
    // quarter; the camera moves from one loop to the next between two frames.
    const double phase = std::uniform_real_distribution<double>(0, 2 * M_PI)(rng);
    const double height = std::uniform_real_distribution<double>(1.3, 1.5)(rng);
    const int per_loop =
        (frames + static_cast<int>(loops.size()) - 1) / static_cast<int>(loops.size());
    for (int f = 0; f < frames; ++f) {
      const Loop& loop = loops[static_cast<size_t>(f / per_loop)];
      const int g = f % per_loop;
      const double a = phase + 2.5 * M_PI * g / per_loop;
      const Eigen::Vector3d position(loop.centre.x() + loop.radius * std::cos(a),
                                     loop.centre.y() + loop.radius * std::sin(a),
                                     height + 0.03 * std::sin(5 * a));
      const double yaw = a + 0.35 * std::sin(3 * a);
      const double pitch = 0.30 + 0.08 * std::sin(2 * a);
      // Frames come at 30 Hz unless that would move the camera faster than a person walks
      // (kMaxWalkSpeedMps, kMaxTurnRateRadps): then the frames are further apart in time, so
      // a short visit (few frames) lasts as long as its path takes to walk, and the move from
      // one loop to the next takes its walking time.
      const Pose pose = LookPose(position, yaw, pitch);
      double t = v.start_time_s;
      if (!v.trajectory.empty()) {
        const Pose& last = v.trajectory.back().T_world_camera;
        t = v.trajectory.back().timestamp_s +
            std::max({1.0 / 30.0, TranslationDistanceM(last, pose) / kMaxWalkSpeedMps,
                      RotationAngleRad(last, pose) / kMaxTurnRateRadps});
      }
      v.trajectory.push_back({t, pose});
    }
    visits.push_back(std::move(v));
  }
  return visits;
}

}  // namespace lifemap::sim
