// A checksum for lifemap's own binary files (models, semantic octree snapshots): 64-bit FNV-1a.
// Detects truncation and bit rot, not tampering.
#pragma once

#include <cstdint>
#include <string>
#include <string_view>

namespace lifemap {

inline uint64_t Fnv1a64(std::string_view bytes) {
  uint64_t h = 1469598103934665603ULL;
  for (const char c : bytes) {
    h ^= static_cast<uint8_t>(c);
    h *= 1099511628211ULL;
  }
  return h;
}

// Appends the checksum of `bytes` so far (8 bytes, the machine's order: little-endian on every
// platform lifemap builds for), as the files above end.
inline void AppendFnv1a64(std::string* bytes) {
  const uint64_t h = Fnv1a64(*bytes);
  bytes->append(reinterpret_cast<const char*>(&h), sizeof(h));
}

}  // namespace lifemap
