// libFuzzer target: arbitrary bytes as a frame's depth and colour images must give a Status,
// never a crash, hang or out-of-bounds access.
//
//   CC=clang CXX=clang++ cmake -S . -B build-fuzz -G Ninja -DLIFEMAP_BUILD_FUZZERS=ON \
//       -DLIFEMAP_BUILD_TESTS=OFF -DLIFEMAP_BUILD_BENCHMARKS=OFF
//   cmake --build build-fuzz --target image_codec_fuzz
//   mkdir -p /tmp/corpus && build-fuzz/bin/image_codec_fuzz -max_total_time=60 /tmp/corpus
//   tests/fuzz/corpus
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "core/common/image_codec.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string_view bytes(reinterpret_cast<const char*>(data), size);
  (void)lifemap::ProbeImage(bytes);
  // Small declared sizes keep each run fast; the header checks compare against them.
  (void)lifemap::DecodeDepthMetres({lifemap::DepthEncoding::kPng16, bytes, 64, 48, 5000.0});
  (void)lifemap::DecodeDepthMetres({lifemap::DepthEncoding::kRawU16, bytes, 16, 12, 1000.0});
  (void)lifemap::DecodeColorBgr({lifemap::ColorEncoding::kJpeg, bytes, 64, 48});
  (void)lifemap::DecodeColorBgr({lifemap::ColorEncoding::kPng, bytes, 64, 48});
  return 0;
}
