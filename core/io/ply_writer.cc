#include "core/io/ply_writer.h"

#include <cstring>

#include "absl/strings/str_cat.h"

namespace lifemap::io {

std::string EncodePlyBinary(const std::vector<ColoredPoint>& points) {
  std::string out = absl::StrCat(
      "ply\nformat binary_little_endian 1.0\ncomment written by lifemap\nelement vertex ",
      points.size(),
      "\nproperty float x\nproperty float y\nproperty float z\n"
      "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n");
  constexpr size_t kRecord = 3 * sizeof(float) + 3;
  const size_t header = out.size();
  out.resize(header + points.size() * kRecord);
  char* p = out.data() + header;
  static_assert(__BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__, "PLY body is written little-endian");
  for (const auto& pt : points) {
    std::memcpy(p, &pt.x, 4);
    std::memcpy(p + 4, &pt.y, 4);
    std::memcpy(p + 8, &pt.z, 4);
    p[12] = static_cast<char>(pt.r);
    p[13] = static_cast<char>(pt.g);
    p[14] = static_cast<char>(pt.b);
    p += kRecord;
  }
  return out;
}

}  // namespace lifemap::io
