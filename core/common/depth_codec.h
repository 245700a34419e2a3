// Lossless codecs for 16-bit depth images (0 = no reading), written here: no Debian package has
// either, and both beat PNG-16 (docs/BENCHMARKS.md, "Stored bytes per keyframe").
//
// RVL (A. D. Wilson, "Fast Lossless Depth Image Compression", ISS 2017): runs of zeros and of
// readings alternate; each reading is the zig-zag difference to the previous one in 3-bit
// groups with a continuation bit, packed into 32-bit words. ~1.6 ms a VGA frame, but larger
// than PNG-16 on Kinect depth at TUM's scale (162 KB against 114 KB).
// Byte layout (little-endian): "RVL1", uint32 width, uint32 height, then the packed words.
//
// Paletted (lifemap's store): a structured-light or stereo sensor reports few distinct depths
// (quantised disparity: ~300 per TUM frame of 0.2 mm units), so the image is stored as its
// sorted distinct values and each pixel's index among them; neighbouring indices differ by
// disparity steps, which RVL codes in one nibble, and zstd then removes what RVL's nibbles
// leave. Exactly the sensor's values come back. TUM: 55 KB in ~3 ms (PNG-16 level 1: 114 KB,
// 12 ms).
// Byte layout (little-endian): "LMD1", uint32 width, uint32 height, uint32 palette size P
// (0 = no palette: indices are the values), P uint16 values ascending, then zstd(RVL(indices)).
#pragma once

#include <string>
#include <string_view>

#include <opencv2/core.hpp>

#include "absl/status/statusor.h"

namespace lifemap {

// `depth` is a non-empty CV_16UC1 image (0 = no reading).
std::string EncodeRvl(const cv::Mat& depth);

// The CV_16UC1 image; InvalidArgument for anything that is not a complete RVL image (wrong
// magic, a size over `max_pixels`, truncated or trailing data), never a crash.
absl::StatusOr<cv::Mat> DecodeRvl(std::string_view bytes, int64_t max_pixels = 64 << 20);

// True when the bytes start with RVL's magic.
bool LooksLikeRvl(std::string_view bytes);

// `depth` is a non-empty CV_16UC1 image.
std::string EncodePalettedDepth(const cv::Mat& depth);

// The CV_16UC1 image; InvalidArgument for damaged data (as DecodeRvl).
absl::StatusOr<cv::Mat> DecodePalettedDepth(std::string_view bytes, int64_t max_pixels = 64 << 20);

}  // namespace lifemap
