// A checksum for lifemap's own binary files (models, semantic octree snapshots): 64-bit FNV-1a.
// Detects truncation and bit rot, not tampering.
#pragma once

#include <cstdint>
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

}  // namespace lifemap
