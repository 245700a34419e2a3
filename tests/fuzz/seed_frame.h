// A small frame as a robot sends it, for the fuzz targets' seeds (rpc_fuzz, http_fuzz).
#pragma once

#include <cstdint>
#include <string>

#include "lifemap/v1/common.pb.h"

namespace lifemap::fuzz {

// A 32x24 frame with raw pixels (mutations keep it decodable; small, so that the fuzzer runs
// hundreds of inputs a second): a wall one metre away with a box in front, a checkerboard
// colour.
inline v1::Frame SeedFrame(uint64_t sequence) {
  constexpr int kWidth = 32, kHeight = 24;
  v1::Frame f;
  f.set_sequence(sequence);
  f.set_timestamp_s(1000.0 + 0.1 * static_cast<double>(sequence));
  auto* k = f.mutable_intrinsics();
  k->set_fx(26.25), k->set_fy(26.25), k->set_cx(15.5), k->set_cy(11.5);
  k->set_width(kWidth), k->set_height(kHeight);
  std::string depth, color;
  for (int r = 0; r < kHeight; ++r) {
    for (int c = 0; c < kWidth; ++c) {
      const bool box = r > 10 && c > 5 + static_cast<int>(sequence) && c < 15;
      const uint16_t mm = box ? 3500 : 5000 + 20 * c;
      depth.push_back(static_cast<char>(mm & 0xff));
      depth.push_back(static_cast<char>(mm >> 8));
      const char v = ((r / 4 + c / 4) % 2 == 0) ? '\x28' : '\xc8';
      color.append({v, static_cast<char>(box ? 0x20 : v), v});
    }
  }
  f.mutable_depth()->set_encoding(v1::DEPTH_RAW_U16);
  f.mutable_depth()->set_depth_scale(5000.0);
  f.mutable_depth()->set_width(kWidth);
  f.mutable_depth()->set_height(kHeight);
  f.mutable_depth()->set_data(depth);
  f.mutable_color()->set_encoding(v1::COLOR_RAW_RGB8);
  f.mutable_color()->set_width(kWidth);
  f.mutable_color()->set_height(kHeight);
  f.mutable_color()->set_data(color);
  return f;
}

}  // namespace lifemap::fuzz
