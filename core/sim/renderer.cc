#include "core/sim/renderer.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <random>

#include <Eigen/Geometry>

namespace lifemap::sim {
namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();

struct Hit {
  double t = kInf;  // along a camera ray whose z component is 1: t is the depth
  SemanticClass cls = SemanticClass::kNone;
  uint16_t instance = 0;
  Eigen::Vector3d normal{0, 0, 1};
  Eigen::Vector2d uv{0, 0};  // surface coordinates, metres
  uint32_t texture_seed = 0;
  Eigen::Vector3f albedo{0.5f, 0.5f, 0.5f};
  bool has_depth = true;  // false: seen, but no depth reading (glass, far outdoors)
  double texture_scale = 1.0;
  float contrast = 1.0f;
  bool prints = true;
  double tile_m = 0;

  void Paint(const Finish& f) {
    texture_seed = f.texture_seed;
    albedo = f.albedo;
    texture_scale = f.texture_scale;
    contrast = f.contrast;
    prints = f.prints;
    tile_m = f.tile_m;
  }
};

uint32_t Hash(uint32_t x) {
  x ^= x >> 16;
  x *= 0x7feb352dU;
  x ^= x >> 15;
  x *= 0x846ca68bU;
  x ^= x >> 16;
  return x;
}

float Lattice(uint32_t seed, int32_t i, int32_t j) {
  return static_cast<float>(Hash(seed ^ Hash(static_cast<uint32_t>(i) * 73856093U ^
                                             static_cast<uint32_t>(j) * 19349663U)) &
                            0xffffff) /
         16777215.0f;
}

// Bilinear value noise in [0, 1].
float Noise(uint32_t seed, double u, double v) {
  const double fu = std::floor(u), fv = std::floor(v);
  const int32_t i = static_cast<int32_t>(fu), j = static_cast<int32_t>(fv);
  const float a = static_cast<float>(u - fu), b = static_cast<float>(v - fv);
  const float sa = a * a * (3 - 2 * a), sb = b * b * (3 - 2 * b);
  const float n00 = Lattice(seed, i, j), n10 = Lattice(seed, i + 1, j);
  const float n01 = Lattice(seed, i, j + 1), n11 = Lattice(seed, i + 1, j + 1);
  return (n00 * (1 - sa) + n10 * sa) * (1 - sb) + (n01 * (1 - sa) + n11 * sa) * sb;
}

// Trilinear value noise in [0, 1] over 3D (the crumple of blobs).
float Noise3(uint32_t seed, const Eigen::Vector3d& p) {
  const Eigen::Vector3d f(std::floor(p.x()), std::floor(p.y()), std::floor(p.z()));
  const Eigen::Vector3d w = p - f;
  const Eigen::Vector3d s = w.cwiseProduct(w).cwiseProduct(Eigen::Vector3d::Constant(3) - 2 * w);
  const auto i = static_cast<uint32_t>(static_cast<int32_t>(f.x()));
  const auto j = static_cast<uint32_t>(static_cast<int32_t>(f.y()));
  const auto k = static_cast<uint32_t>(static_cast<int32_t>(f.z()));
  auto at = [&](uint32_t di, uint32_t dj, uint32_t dk) {
    return static_cast<double>(Hash(seed ^ Hash((i + di) * 73856093U ^ (j + dj) * 19349663U ^
                                                (k + dk) * 83492791U)) &
                               0xffffff) /
           16777215.0;
  };
  auto lerp = [](double a, double b, double t) { return a + (b - a) * t; };
  const double x00 = lerp(at(0, 0, 0), at(1, 0, 0), s.x()),
               x10 = lerp(at(0, 1, 0), at(1, 1, 0), s.x());
  const double x01 = lerp(at(0, 0, 1), at(1, 0, 1), s.x()),
               x11 = lerp(at(0, 1, 1), at(1, 1, 1), s.x());
  return static_cast<float>(lerp(lerp(x00, x10, s.y()), lerp(x01, x11, s.y()), s.z()));
}

// Procedural albedo: two octaves of value noise plus, for some surfaces, printed patches, so
// keypoint detectors find structure everywhere. A tiled finish repeats one tile's pattern with
// dark grout lines between tiles.
Eigen::Vector3f Texture(const Hit& h) {
  const double s = h.texture_scale;
  Eigen::Vector2d uv = h.uv;
  bool grout = false;
  if (h.tile_m > 0) {
    const Eigen::Vector2d cell(std::floor(uv.x() / h.tile_m), std::floor(uv.y() / h.tile_m));
    uv -= h.tile_m * cell;
    constexpr double kGroutM = 0.006;
    grout = uv.x() < kGroutM || uv.y() < kGroutM;
  }
  const float coarse = Noise(h.texture_seed, uv.x() * 3 * s, uv.y() * 3 * s);
  const float fine = Noise(h.texture_seed * 7 + 1, uv.x() * 25 * s, uv.y() * 25 * s);
  float shade = 0.55f + (h.contrast * 0.35f) * coarse + (h.contrast * 0.2f) * (fine - 0.5f);
  if (h.prints) {
    // Printed patches: a coarse grid of cells, some of which carry a dark or bright print.
    const int32_t ci = static_cast<int32_t>(std::floor(uv.x() * 4 * s));
    const int32_t cj = static_cast<int32_t>(std::floor(uv.y() * 4 * s));
    const uint32_t cell = Hash(
        h.texture_seed ^ Hash(static_cast<uint32_t>(ci) * 31U + static_cast<uint32_t>(cj) * 977U));
    if ((cell & 7U) == 0U) shade *= 0.45f;
    if ((cell & 7U) == 1U) shade = std::min(1.2f, shade * 1.5f);
  }
  if (grout) shade *= 0.4f;
  return h.albedo * shade;
}

void HitHorizontal(const Place& place, const Eigen::Vector3d& o, const Eigen::Vector3d& d, double z,
                   bool floor, Hit* best) {
  if (std::abs(d.z()) < 1e-12) return;
  const double t = (z - o.z()) / d.z();
  if (t <= 1e-6 || t >= best->t) return;
  const Eigen::Vector3d p = o + t * d;
  bool inside = InsidePolygon(place.footprint, p.x(), p.y());
  for (size_t r = 0; !inside && r < place.adjoining_rooms.size(); ++r) {
    inside = InsidePolygon(place.adjoining_rooms[r], p.x(), p.y());
  }
  if (!inside) return;
  if (floor) {
    for (const auto& st : place.stairs) {
      if (st.up) continue;
      // The stairwell: the flight's footprint is open.
      const Eigen::Vector2d rel = p.head<2>() - st.origin;
      const double along = rel.x() * std::cos(st.yaw) + rel.y() * std::sin(st.yaw);
      const double across = -rel.x() * std::sin(st.yaw) + rel.y() * std::cos(st.yaw);
      if (along >= 0 && along <= st.run_m * st.steps && std::abs(across) <= st.width_m / 2) return;
    }
  }
  best->t = t;
  best->cls = floor ? SemanticClass::kFloor : SemanticClass::kCeiling;
  best->instance = 0;
  best->normal = Eigen::Vector3d(0, 0, floor ? 1 : -1);
  best->uv = p.head<2>();
  best->Paint(floor ? place.materials.floor : place.materials.ceiling);
  best->has_depth = true;
}

// A wall segment's geometry, computed once per frame.
struct WallGeometry {
  Eigen::Vector2d a, e, inward;
  double length;
  int room, index;
};

std::vector<WallGeometry> Walls(const Place& place) {
  std::vector<WallGeometry> walls;
  for (int room = 0; room <= static_cast<int>(place.adjoining_rooms.size()); ++room) {
    const auto& footprint = RoomFootprint(place, room);
    const size_t n = footprint.size();
    for (size_t w = 0; w < n; ++w) {
      const Eigen::Vector2d a = footprint[w];
      const Eigen::Vector2d b = footprint[(w + 1) % n];
      const double length = (b - a).norm();
      const Eigen::Vector2d e = (b - a) / length;
      walls.push_back({a, e, Eigen::Vector2d(-e.y(), e.x()), length, room,
                       static_cast<int>(w)});  // counter-clockwise: inward is to the left
    }
  }
  return walls;
}

void HitWalls(const Place& place, const std::vector<WallGeometry>& walls, const Eigen::Vector3d& o,
              const Eigen::Vector3d& d, Hit* best) {
  for (size_t w = 0; w < walls.size(); ++w) {
    const Eigen::Vector2d& a = walls[w].a;
    const Eigen::Vector2d& e = walls[w].e;
    const Eigen::Vector2d& inward = walls[w].inward;
    const double length = walls[w].length;
    const double facing = inward.dot(d.head<2>());
    if (facing >= -1e-12) continue;  // seen from behind or edge-on
    const double t = inward.dot(a - o.head<2>()) / facing;
    if (t <= 1e-6 || t >= best->t) continue;
    const Eigen::Vector3d p = o + t * d;
    const double u = e.dot(p.head<2>() - a);
    if (u < 0 || u > length || p.z() < 0 || p.z() > place.wall_height_m) continue;
    Hit h;
    h.t = t;
    h.cls = SemanticClass::kWall;
    h.normal = Eigen::Vector3d(inward.x(), inward.y(), 0);
    h.uv = Eigen::Vector2d(u + 10.0 * w, p.z());
    h.Paint(place.materials.wall);
    if (place.materials.wall_per_segment) h.texture_seed += static_cast<uint32_t>(w);
    bool through = false;
    for (const auto& op : place.openings) {
      if (op.room != walls[w].room || op.wall != walls[w].index) continue;
      if (u < op.offset_m || u > op.offset_m + op.width_m || p.z() < op.sill_m ||
          p.z() > op.top_m) {
        continue;
      }
      if (op.type == OpeningType::kWindow) {
        // Glass and the outdoors beyond it give the Kinect no reading.
        h.cls = SemanticClass::kWindow;
        h.has_depth = false;
        h.albedo = Eigen::Vector3f(0.85f, 0.92f, 1.0f);
        h.texture_scale = 0.1;
      } else if (op.open && op.connects) {
        through = true;  // an open door between rooms: the other room is rendered beyond
      } else if (op.open) {
        // An open door shows the space beyond: a surface 2 m behind the wall, not this room's.
        h.t = t + 2.0 / -facing;
        h.cls = SemanticClass::kNone;
        h.albedo = Eigen::Vector3f(0.35f, 0.35f, 0.38f);
      } else {
        h.cls = SemanticClass::kDoor;
        // Painted wood, the wall's texture seed.
        h.Paint({h.texture_seed, {0.45f, 0.30f, 0.18f}, 2.0, 1.0f, true, 0});
      }
      break;
    }
    if (!through && h.t < best->t) *best = h;
  }
}

// A solid's placement, computed once per frame: centre and yaw's cosine and sine.
struct SolidFrame {
  const Solid* solid;
  Eigen::Vector3d centre;
  double cos_yaw, sin_yaw;
  double radius_sq;  // of a sphere around the solid, for a cheap rejection per ray
};

SolidFrame Prepare(const Solid& s) {
  if (s.shape == Solid::Shape::kBlob) {
    const double r = 0.5 * s.size.maxCoeff() * BlobReach(s);
    return {&s, Eigen::Vector3d(s.center.x(), s.center.y(), s.base_z + s.size.z() / 2 - s.sink_m),
            std::cos(s.yaw), std::sin(s.yaw), r * r};
  }
  const double r_xy = FootprintRadius(s);
  const double half_h = s.size.z() / 2;
  return {&s, Eigen::Vector3d(s.center.x(), s.center.y(), s.base_z + half_h), std::cos(s.yaw),
          std::sin(s.yaw), r_xy * r_xy + half_h * half_h};
}

// The first crossing of a ray (local frame, origin lo, direction ld) with a crumpled ellipsoid
// centred at the origin, or false. Written here (no library ray-casts implicit surfaces): the
// radius along each direction is displaced by value noise, so the ray is sampled uniformly
// across the bounding sphere and the first sign change refined by bisection; the normal is
// the field's gradient by central differences.
bool HitBlob(const Solid& s, const Eigen::Vector3d& lo, const Eigen::Vector3d& ld, double* t_hit,
             Eigen::Vector3d* normal, Eigen::Vector2d* uv) {
  const Eigen::Vector3d inv_semi = (s.size / 2).cwiseInverse();
  // Signed field in unit-sphere coordinates: > 0 outside.
  auto field = [&](const Eigen::Vector3d& p) {
    const Eigen::Vector3d q = p.cwiseProduct(inv_semi);
    const double r = q.norm();
    if (r < 1e-9) return -1.0;
    const Eigen::Vector3d dir = q / r;
    const double f = s.crumple_frequency;
    const double n = 0.65 * Noise3(s.texture_seed, dir * f) +
                     0.35 * Noise3(s.texture_seed * 3 + 5, dir * (2.7 * f));
    return r - (1 + s.crumple * (2 * n - 1));
  };
  // The sphere the surface stays inside, in unit-sphere coordinates: the march starts on it.
  const Eigen::Vector3d q0 = lo.cwiseProduct(inv_semi), dq = ld.cwiseProduct(inv_semi);
  const double bound = BlobReach(s);
  const double a = dq.squaredNorm(), b = q0.dot(dq), c = q0.squaredNorm() - bound * bound;
  const double disc = b * b - a * c;
  if (disc < 0 || a < 1e-18) return false;
  const double enter = std::max((-b - std::sqrt(disc)) / a, 1e-6);
  const double leave = (-b + std::sqrt(disc)) / a;
  if (leave <= enter) return false;
  constexpr int kSteps = 48;
  const double step = (leave - enter) / kSteps;
  double t0 = enter;
  if (field(lo + t0 * ld) <= 0) return false;  // the camera is inside
  for (int i = 1; i <= kSteps; ++i) {
    double t1 = enter + i * step;
    if (field(lo + t1 * ld) <= 0) {
      for (int k = 0; k < 12; ++k) {
        const double tm = 0.5 * (t0 + t1);
        (field(lo + tm * ld) > 0 ? t0 : t1) = tm;
      }
      *t_hit = t1;
      const Eigen::Vector3d p = lo + t1 * ld;
      constexpr double kEps = 1e-3;
      Eigen::Vector3d g;
      for (int axis = 0; axis < 3; ++axis) {
        Eigen::Vector3d e = Eigen::Vector3d::Zero();
        e[axis] = kEps;
        g[axis] = field(p + e) - field(p - e);
      }
      *normal = g.norm() > 1e-12 ? g.normalized() : Eigen::Vector3d(p.normalized());
      *uv = Eigen::Vector2d(std::atan2(p.y(), p.x()) * s.size.x() / 2, p.z());
      return true;
    }
    t0 = t1;
  }
  return false;
}

// The first crossing of a ray (local frame, z = 0 at the solid's base) with a surface of
// revolution: each profile segment is a cone frustum (or, level, an annulus), intersected
// exactly.
bool HitLathe(const Solid& s, const Eigen::Vector3d& lo, const Eigen::Vector3d& ld, double* t_hit,
              Eigen::Vector3d* normal, Eigen::Vector2d* uv) {
  double best = kInf;
  for (size_t i = 0; i + 1 < s.profile.size(); ++i) {
    const double h0 = s.profile[i].x(), r0 = s.profile[i].y();
    const double h1 = s.profile[i + 1].x(), r1 = s.profile[i + 1].y();
    if (h1 - h0 < 1e-9) {
      // A level annulus between radii r0 and r1: facing up where the profile steps in.
      if (std::abs(ld.z()) < 1e-12) continue;
      const double t = (h0 - lo.z()) / ld.z();
      if (t <= 1e-6 || t >= best) continue;
      const Eigen::Vector3d p = lo + t * ld;
      const double rho = std::hypot(p.x(), p.y());
      if (rho < std::min(r0, r1) || rho > std::max(r0, r1)) continue;
      best = t;
      *normal = Eigen::Vector3d(0, 0, r1 < r0 ? 1 : -1);
      continue;
    }
    // x^2 + y^2 = (A + B t)^2 with the radius r(z) = r0 + k (z - h0).
    const double k = (r1 - r0) / (h1 - h0);
    const double A = r0 + k * (lo.z() - h0), B = k * ld.z();
    const double qa = ld.x() * ld.x() + ld.y() * ld.y() - B * B;
    const double qb = lo.x() * ld.x() + lo.y() * ld.y() - A * B;
    const double qc = lo.x() * lo.x() + lo.y() * lo.y() - A * A;
    double roots[2];
    int n = 0;
    if (std::abs(qa) < 1e-12) {
      if (std::abs(qb) > 1e-12) roots[n++] = -qc / (2 * qb);
    } else {
      const double disc = qb * qb - qa * qc;
      if (disc < 0) continue;
      roots[n++] = (-qb - std::sqrt(disc)) / qa;
      roots[n++] = (-qb + std::sqrt(disc)) / qa;
    }
    for (int r = 0; r < n; ++r) {
      const double t = roots[r];
      if (t <= 1e-6 || t >= best) continue;
      const Eigen::Vector3d p = lo + t * ld;
      if (p.z() < h0 || p.z() > h1 || A + B * t < 0) continue;
      best = t;
      *normal = Eigen::Vector3d(p.x(), p.y(), -k * (A + B * t)).normalized();
    }
  }
  if (best == kInf) return false;
  const Eigen::Vector3d p = lo + best * ld;
  *t_hit = best;
  *uv = Eigen::Vector2d(std::atan2(p.y(), p.x()) * s.size.x() / 2, p.z());
  return true;
}

void HitSolid(const SolidFrame& sf, const Eigen::Vector3d& o, const Eigen::Vector3d& d, Hit* best) {
  const Solid& s = *sf.solid;
  const double half_h = s.size.z() / 2;
  const Eigen::Vector3d& c = sf.centre;
  // Reject rays that miss the bounding sphere: |(c - o) x d|^2 / |d|^2 > r^2.
  const Eigen::Vector3d oc = c - o;
  if (oc.cross(d).squaredNorm() > sf.radius_sq * d.squaredNorm()) return;
  // World to the solid's frame: rotate by -yaw.
  const double cy = sf.cos_yaw, sy = -sf.sin_yaw;
  auto to_local = [&](const Eigen::Vector3d& v) {
    return Eigen::Vector3d(cy * v.x() - sy * v.y(), sy * v.x() + cy * v.y(), v.z());
  };
  const Eigen::Vector3d lo = to_local(o - c), ld = to_local(d);
  double t_hit = kInf;
  Eigen::Vector3d local_normal = Eigen::Vector3d::Zero();
  Eigen::Vector2d uv = Eigen::Vector2d::Zero();
  if (s.shape == Solid::Shape::kBlob) {
    if (!HitBlob(s, lo, ld, &t_hit, &local_normal, &uv)) return;
  } else if (s.shape == Solid::Shape::kLathe) {
    if (!HitLathe(s, lo + Eigen::Vector3d(0, 0, half_h), ld, &t_hit, &local_normal, &uv)) return;
  } else if (s.shape == Solid::Shape::kBox) {
    const Eigen::Vector3d half(s.size.x() / 2, s.size.y() / 2, half_h);
    double t0 = -kInf, t1 = kInf;
    int axis = -1;
    double sign = 1;
    for (int i = 0; i < 3; ++i) {
      if (std::abs(ld[i]) < 1e-12) {
        if (std::abs(lo[i]) > half[i]) return;
        continue;
      }
      double a = (-half[i] - lo[i]) / ld[i], b = (half[i] - lo[i]) / ld[i];
      double near_sign = -1;
      if (a > b) {
        std::swap(a, b);
        near_sign = 1;
      }
      if (a > t0) {
        t0 = a;
        axis = i;
        sign = near_sign;
      }
      t1 = std::min(t1, b);
      if (t0 > t1) return;
    }
    if (axis < 0 || t0 <= 1e-6) return;
    t_hit = t0;
    local_normal = Eigen::Vector3d::Zero();
    local_normal[axis] = sign;
    const Eigen::Vector3d p = lo + t0 * ld;
    uv = axis == 2 ? Eigen::Vector2d(p.x(), p.y())
                   : Eigen::Vector2d(axis == 0 ? p.y() : p.x(), p.z());
  } else {
    const double r = s.size.x() / 2;
    // Side: (lo + t ld)_xy on the circle of radius r.
    const double a = ld.x() * ld.x() + ld.y() * ld.y();
    const double b = lo.x() * ld.x() + lo.y() * ld.y();
    const double cc = lo.x() * lo.x() + lo.y() * lo.y() - r * r;
    const double disc = b * b - a * cc;
    if (a > 1e-12 && disc >= 0) {
      const double t = (-b - std::sqrt(disc)) / a;
      const Eigen::Vector3d p = lo + t * ld;
      if (t > 1e-6 && std::abs(p.z()) <= half_h) {
        t_hit = t;
        local_normal = Eigen::Vector3d(p.x(), p.y(), 0).normalized();
        uv = Eigen::Vector2d(std::atan2(p.y(), p.x()) * r, p.z());
      }
    }
    // Top cap.
    if (std::abs(ld.z()) > 1e-12) {
      const double t = (half_h - lo.z()) / ld.z();
      const Eigen::Vector3d p = lo + t * ld;
      if (t > 1e-6 && t < t_hit && p.x() * p.x() + p.y() * p.y() <= r * r && ld.z() < 0) {
        t_hit = t;
        local_normal = Eigen::Vector3d(0, 0, 1);
        uv = p.head<2>();
      }
    }
    if (t_hit == kInf) return;
  }
  if (t_hit >= best->t) return;
  const double cw = sf.cos_yaw, sw = sf.sin_yaw;
  best->t = t_hit;
  best->cls = s.cls;
  best->instance = static_cast<uint16_t>(s.instance);
  best->normal = Eigen::Vector3d(cw * local_normal.x() - sw * local_normal.y(),
                                 sw * local_normal.x() + cw * local_normal.y(), local_normal.z());
  best->uv = uv;
  best->Paint({s.texture_seed, s.color, 2.0, 1.0f, true, 0});
  best->has_depth = true;
}

// The image rectangle a solid can cover (its bounding box's corners projected), or the whole
// image when a corner is behind the camera.
cv::Rect ScreenRect(const Solid& s, const CameraIntrinsics& k, const Eigen::Isometry3d& T_cw) {
  const double r = FootprintRadius(s);
  const auto [bottom, top] = VerticalExtent(s);
  double u0 = kInf, v0 = kInf, u1 = -kInf, v1 = -kInf;
  for (int i = 0; i < 8; ++i) {
    const Eigen::Vector3d corner(s.center.x() + ((i & 1) ? r : -r),
                                 s.center.y() + ((i & 2) ? r : -r), (i & 4) ? top : bottom);
    const Eigen::Vector3d pc = T_cw * corner;
    if (pc.z() < 0.05) return cv::Rect(0, 0, k.width, k.height);
    const double u = k.fx * pc.x() / pc.z() + k.cx, v = k.fy * pc.y() / pc.z() + k.cy;
    u0 = std::min(u0, u), u1 = std::max(u1, u), v0 = std::min(v0, v), v1 = std::max(v1, v);
  }
  const int x0 = std::max(0, static_cast<int>(std::floor(u0)) - 1);
  const int y0 = std::max(0, static_cast<int>(std::floor(v0)) - 1);
  const int x1 = std::min(k.width, static_cast<int>(std::ceil(u1)) + 2);
  const int y1 = std::min(k.height, static_cast<int>(std::ceil(v1)) + 2);
  if (x1 <= x0 || y1 <= y0) return cv::Rect();
  return cv::Rect(x0, y0, x1 - x0, y1 - y0);
}

}  // namespace

RenderedFrame Render(const Place& place, const std::vector<Solid>& solids, const Lighting& lighting,
                     const CameraIntrinsics& k, const Pose& T_world_camera,
                     const SensorOptions& sensor, uint64_t seed) {
  RenderedFrame out;
  out.depth_m = cv::Mat(k.height, k.width, CV_32FC1, cv::Scalar(0.0f));
  out.true_depth_m = cv::Mat(k.height, k.width, CV_32FC1, cv::Scalar(0.0f));
  out.color_bgr = cv::Mat(k.height, k.width, CV_8UC3, cv::Scalar::all(0));
  out.class_id = cv::Mat(k.height, k.width, CV_8UC1, cv::Scalar(0));
  out.instance_id = cv::Mat(k.height, k.width, CV_16UC1, cv::Scalar(0));

  const Eigen::Isometry3d T_wc = T_world_camera.ToIsometry();
  const Eigen::Isometry3d T_cw = T_wc.inverse();
  const Eigen::Matrix3d R = T_wc.linear();
  const Eigen::Vector3d o = T_wc.translation();
  std::vector<cv::Rect> rects;
  std::vector<SolidFrame> prepared;
  rects.reserve(solids.size());
  for (const auto& s : solids) {
    rects.push_back(ScreenRect(s, k, T_cw));
    prepared.push_back(Prepare(s));
  }
  const Eigen::Vector3d light = Eigen::Vector3d(0.3, 0.5, 1.0).normalized();
  const std::vector<WallGeometry> walls = Walls(place);
  std::mt19937_64 rng(seed);
  // Gaussian samples come from a table indexed by a fast generator: a normal_distribution
  // draw per pixel and channel cost a quarter of the frame.
  static const std::vector<float> kGauss = [] {
    std::mt19937 table_rng(12345);
    std::normal_distribution<float> g(0.0f, 1.0f);
    std::vector<float> t(1 << 16);
    for (auto& v : t) v = g(table_rng);
    return t;
  }();
  uint64_t state = seed * 0x9E3779B97F4A7C15ULL + 1;
  auto gauss = [&state]() {
    state ^= state << 13;
    state ^= state >> 7;
    state ^= state << 17;
    return kGauss[state & 0xffff];
  };
  cv::Mat normal_dot(k.height, k.width, CV_32FC1, cv::Scalar(1.0f));

  for (int v = 0; v < k.height; ++v) {
    float* true_depth = out.true_depth_m.ptr<float>(v);
    cv::Vec3b* bgr = out.color_bgr.ptr<cv::Vec3b>(v);
    uint8_t* cls = out.class_id.ptr<uint8_t>(v);
    uint16_t* inst = out.instance_id.ptr<uint16_t>(v);
    float* cosine = normal_dot.ptr<float>(v);
    for (int u = 0; u < k.width; ++u) {
      const Eigen::Vector3d d_cam((u - k.cx) / k.fx, (v - k.cy) / k.fy, 1.0);
      const Eigen::Vector3d d = R * d_cam;  // unnormalised: t is the depth
      Hit hit;
      HitWalls(place, walls, o, d, &hit);
      if (d.z() < 0) {
        HitHorizontal(place, o, d, 0.0, true, &hit);
      } else {
        HitHorizontal(place, o, d, place.wall_height_m, false, &hit);
      }
      for (size_t i = 0; i < solids.size(); ++i) {
        if (rects[i].contains(cv::Point(u, v))) HitSolid(prepared[i], o, d, &hit);
      }
      if (hit.t == kInf) continue;
      cls[u] = static_cast<uint8_t>(hit.cls);
      inst[u] = hit.instance;
      if (hit.has_depth) true_depth[u] = static_cast<float>(hit.t);
      const Eigen::Vector3d dn = d.normalized();
      cosine[u] = static_cast<float>(std::abs(hit.normal.dot(dn)));
      const float lambert = static_cast<float>(std::abs(hit.normal.dot(light)));
      float shade = 0.45f + 0.55f * lambert;
      Eigen::Vector3f lamp_gain(1.0f, 1.0f, 1.0f);
      if (lighting.lamp_on) {
        // Inverse-square fall-off, cosine at the surface; a warm colour.
        const Eigen::Vector3d p = o + hit.t * d;
        const Eigen::Vector3d to_lamp = lighting.lamp - p;
        const double dist_sq = std::max(to_lamp.squaredNorm(), 0.05);
        const double cosine_lamp = std::max(0.0, hit.normal.dot(to_lamp) / std::sqrt(dist_sq));
        const float extra = static_cast<float>(lighting.lamp_power * cosine_lamp / dist_sq);
        lamp_gain = Eigen::Vector3f(1.0f + extra, 1.0f + 0.8f * extra, 1.0f + 0.55f * extra);
      }
      Eigen::Vector3f c = Texture(hit).cwiseProduct(lamp_gain) * shade;
      if (hit.cls == SemanticClass::kWindow) c = hit.albedo;  // bright outdoors
      c = c.cwiseProduct(lighting.tint) * static_cast<float>(lighting.brightness * sensor.exposure);
      for (int ch = 0; ch < 3; ++ch) {
        const float noise = sensor.noise ? static_cast<float>(sensor.color_noise) * gauss() : 0.0f;
        const float value = std::clamp(c[2 - ch] * 255.0f + noise, 0.0f, 255.0f);
        bgr[u][ch] = static_cast<uint8_t>(std::lround(value));
      }
    }
  }

  // Sensor model on the exact depth.
  std::uniform_real_distribution<double> uniform(0.0, 1.0);
  constexpr double kDisparityStep = 1.0 / (8.0 * 580.0 * 0.075);  // 1/8 px, f 580 px, 7.5 cm
  for (int v = 0; v < k.height; ++v) {
    const float* true_depth = out.true_depth_m.ptr<float>(v);
    const float* cosine = normal_dot.ptr<float>(v);
    float* depth = out.depth_m.ptr<float>(v);
    for (int u = 0; u < k.width; ++u) {
      const double z = true_depth[u];
      if (!(z > 0)) continue;
      if (!sensor.noise) {
        depth[u] = static_cast<float>(z);
        continue;
      }
      if (z > sensor.max_range_m || z < sensor.min_range_m || cosine[u] < sensor.grazing_cos) {
        continue;
      }
      bool edge = false;
      for (const auto& [dv, du] :
           {std::pair{0, 1}, std::pair{1, 0}, std::pair{0, -1}, std::pair{-1, 0}}) {
        const int vv = v + dv, uu = u + du;
        if (vv < 0 || vv >= k.height || uu < 0 || uu >= k.width) continue;
        const float zn = out.true_depth_m.at<float>(vv, uu);
        if (zn > 0 && std::abs(zn - z) > 0.05 * z) edge = true;
      }
      if (edge && uniform(rng) < sensor.edge_dropout) continue;
      // Noise as Nguyen et al. (3DIMPVT 2012) for Kinect v1, then disparity quantisation.
      const double sigma = 0.0012 + 0.0019 * (z - 0.4) * (z - 0.4);
      const double noisy = z + sigma * gauss();
      const double disparity = std::round((1.0 / noisy) / kDisparityStep) * kDisparityStep;
      depth[u] = static_cast<float>(1.0 / disparity);
    }
  }
  return out;
}

}  // namespace lifemap::sim
