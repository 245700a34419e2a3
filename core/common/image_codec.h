// Decoding and encoding of the image formats lifemap accepts on the wire and keeps in its
// store. Everything from a client or a file is checked before it is decoded: a wrong size, a
// truncated PNG/JPEG or an unsupported layout gives InvalidArgument, never a crash.
#pragma once

#include <cstdint>
#include <string>
#include <string_view>

#include <opencv2/core.hpp>

#include "absl/status/statusor.h"

namespace lifemap {

enum class ImageFormat { kUnknown, kPng, kJpeg };

// What a compressed image's header says, read without decoding the pixels.
struct ImageHeader {
  ImageFormat format = ImageFormat::kUnknown;
  int width = 0;
  int height = 0;
  int channels = 0;   // 1 grey, 2 grey+alpha, 3 colour, 4 colour+alpha
  int bit_depth = 0;  // bits per channel sample: 8 or 16 (PNG); 8 (JPEG)
};

// Reads the PNG IHDR or the JPEG SOF header and checks the file is complete (PNG ends with an
// IEND chunk; JPEG ends with an EOI marker). InvalidArgument says what is wrong.
absl::StatusOr<ImageHeader> ProbeImage(std::string_view bytes);

// kRvl and kPaletted: lossless codecs of the uint16 values (core/common/depth_codec.h);
// metres = value / depth_scale.
enum class DepthEncoding { kPng16, kRawU16, kRawF32, kRvl, kPaletted };

struct EncodedDepth {
  DepthEncoding encoding = DepthEncoding::kPng16;
  std::string_view data;
  int width = 0;  // expected size; raw encodings need it, PNG is checked against it
  int height = 0;
  double depth_scale = 0.0;  // units per metre for kPng16 / kRawU16 (TUM 5000)
};

// depth_scale bounds, units per metre: 1 (uint16 metres) to 10^6 (micrometres).
inline constexpr double kMinDepthScale = 1.0;
inline constexpr double kMaxDepthScale = 1e6;

// The depths a sensor plausibly reports, metres. A reading outside is no reading (0), so that
// every decoded depth is 0 or finite within [min_m, max_m] and the per-frame stages (normals,
// bins, forest offsets scaled by 1/depth) never see a value that overflows them.
struct DepthRange {
  float min_m = 0.05f;  // (0, max_m)
  float max_m = 50.0f;  // (min_m, 1000]
  absl::Status Validate() const;
};

// Decodes depth into CV_32FC1 metres; pixels without a reading are 0. NaN, infinite and
// negative float readings, and readings outside `range`, count as no reading. InvalidArgument
// for a depth_scale outside [kMinDepthScale, kMaxDepthScale] (scaled encodings).
absl::StatusOr<cv::Mat> DecodeDepthMetres(const EncodedDepth& depth, const DepthRange& range = {});

enum class ColorEncoding { kJpeg, kPng, kRawRgb8 };

struct EncodedColor {
  ColorEncoding encoding = ColorEncoding::kJpeg;
  std::string_view data;
  int width = 0;
  int height = 0;
};

// Decodes colour into CV_8UC3 in OpenCV's BGR order (grey and alpha inputs are converted).
absl::StatusOr<cv::Mat> DecodeColorBgr(const EncodedColor& color);

// Depth in metres (CV_32FC1) to a 16-bit PNG at `depth_scale` units per metre. Readings that do
// not fit in 16 bits at that scale (or are not positive and finite) are stored as 0.
absl::StatusOr<std::string> EncodeDepthPng16(const cv::Mat& depth_m, double depth_scale);

// The same values as RVL or paletted (core/common/depth_codec.h): lossless at `depth_scale`.
// Paletted is half PNG-16's size on Kinect-class depth and ~4x faster to encode.
absl::StatusOr<std::string> EncodeDepthRvl(const cv::Mat& depth_m, double depth_scale);
absl::StatusOr<std::string> EncodeDepthPaletted(const cv::Mat& depth_m, double depth_scale);

// Any 8-bit 1- or 3-channel image (BGR) or 16-bit grey image to PNG.
absl::StatusOr<std::string> EncodePng(const cv::Mat& image);

// BGR image to JPEG, quality in [1, 100].
absl::StatusOr<std::string> EncodeJpeg(const cv::Mat& bgr, int quality = 90);

// Raw bytes of a file; NotFound / PermissionDenied / DataLoss with the path in the message.
absl::StatusOr<std::string> ReadFileBytes(const std::string& path);

}  // namespace lifemap
