// Writes coloured point clouds as binary little-endian PLY (readable by MeshLab, CloudCompare,
// Open3D and PCL).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

namespace lifemap::io {

struct ColoredPoint {
  float x, y, z;  // metres
  uint8_t r, g, b;
};

// The whole file: header and binary body ("x y z" float, "red green blue" uchar).
std::string EncodePlyBinary(const std::vector<ColoredPoint>& points);

}  // namespace lifemap::io
