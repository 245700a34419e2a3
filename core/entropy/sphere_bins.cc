#include "core/entropy/sphere_bins.h"

#include <cmath>

namespace lifemap::entropy {
namespace {

// Cube-map face and its (u, v) in [-1, 1] for a direction; the face is the dominant axis.
inline int Face(float x, float y, float z, float* u, float* v) {
  const float ax = std::abs(x), ay = std::abs(y), az = std::abs(z);
  if (ax >= ay && ax >= az) {
    *u = y / ax;
    *v = z / ax;
    return x > 0 ? 0 : 1;
  }
  if (ay >= az) {
    *u = x / ay;
    *v = z / ay;
    return y > 0 ? 2 : 3;
  }
  *u = x / az;
  *v = y / az;
  return z > 0 ? 4 : 5;
}

// Clamped in float before the conversion, so that any input (NaN included) gives a cell.
inline int Cell(float t) {
  const float f = (t + 1.0f) * 0.5f * SphereBins::kLutSide;
  if (!(f >= 0.0f)) return 0;
  if (f >= static_cast<float>(SphereBins::kLutSide - 1)) return SphereBins::kLutSide - 1;
  return static_cast<int>(f);
}

}  // namespace

SphereBins::SphereBins(int count) {
  const double golden_angle = M_PI * (3.0 - std::sqrt(5.0));
  for (int i = 0; i < count; ++i) {
    const double z = 1.0 - (2.0 * i + 1.0) / count;
    const double radius = std::sqrt(std::max(0.0, 1.0 - z * z));
    const double phi = golden_angle * i;
    centers_.emplace_back(static_cast<float>(radius * std::cos(phi)),
                          static_cast<float>(radius * std::sin(phi)), static_cast<float>(z));
  }
  constexpr int side = kLutSide;
  lut_.resize(6 * side * side);
  for (int face = 0; face < 6; ++face) {
    for (int v = 0; v < side; ++v) {
      for (int u = 0; u < side; ++u) {
        const float a = (u + 0.5f) / side * 2.0f - 1.0f, b = (v + 0.5f) / side * 2.0f - 1.0f;
        Eigen::Vector3f d;
        switch (face) {
          case 0:
            d = {1, a, b};
            break;
          case 1:
            d = {-1, a, b};
            break;
          case 2:
            d = {a, 1, b};
            break;
          case 3:
            d = {a, -1, b};
            break;
          case 4:
            d = {a, b, 1};
            break;
          default:
            d = {a, b, -1};
            break;
        }
        lut_[(face * side + v) * side + u] = static_cast<unsigned char>(BinExact(d.normalized()));
      }
    }
  }
}

int SphereBins::BinExact(const Eigen::Vector3f& n) const {
  int best = 0;
  float best_dot = -2.0f;
  for (int i = 0; i < count(); ++i) {
    const float d = centers_[i].dot(n);
    if (d > best_dot) {
      best_dot = d;
      best = i;
    }
  }
  return best;
}

int SphereBins::Bin(float x, float y, float z) const {
  float u, v;
  const int face = Face(x, y, z, &u, &v);
  return lut_[(face * kLutSide + Cell(v)) * kLutSide + Cell(u)];
}

}  // namespace lifemap::entropy
