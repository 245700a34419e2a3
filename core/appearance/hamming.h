// Internal to core/appearance: 256-bit descriptors as four words, and their Hamming distance
// (inlined; the module is compiled with -mpopcnt where the CPU has it).
#pragma once

#include <array>
#include <cstdint>
#include <cstring>

namespace lifemap::appearance::internal {

using Descriptor = std::array<uint64_t, 4>;

inline Descriptor LoadDescriptor(const uint8_t* d) {
  Descriptor out;
  std::memcpy(out.data(), d, sizeof(out));
  return out;
}

inline int Distance(const Descriptor& a, const Descriptor& b) {
  return __builtin_popcountll(a[0] ^ b[0]) + __builtin_popcountll(a[1] ^ b[1]) +
         __builtin_popcountll(a[2] ^ b[2]) + __builtin_popcountll(a[3] ^ b[3]);
}

}  // namespace lifemap::appearance::internal
