#include "core/common/image_codec.h"

#include <cerrno>
#include <cmath>
#include <cstring>
#include <fstream>
#include <sstream>
#include <vector>

#include <png.h>
#include <zlib.h>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "absl/strings/str_cat.h"
#include "core/common/depth_codec.h"
#include "core/common/types.h"

namespace lifemap {
namespace {

constexpr unsigned char kPngSignature[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};

uint32_t ReadBigEndian32(const unsigned char* p) {
  return (uint32_t{p[0]} << 24) | (uint32_t{p[1]} << 16) | (uint32_t{p[2]} << 8) | uint32_t{p[3]};
}

const unsigned char* Bytes(std::string_view s) {
  return reinterpret_cast<const unsigned char*>(s.data());
}

absl::StatusOr<ImageHeader> ProbePng(std::string_view data) {
  const unsigned char* p = Bytes(data);
  // Signature (8) + IHDR chunk (4 length + 4 type + 13 data + 4 CRC) + IEND (12).
  if (data.size() < 8 + 25 + 12) {
    return absl::InvalidArgumentError(
        absl::StrCat("PNG is truncated: ", data.size(), " bytes is too short for a PNG file"));
  }
  if (std::memcmp(p + 12, "IHDR", 4) != 0 || ReadBigEndian32(p + 8) != 13) {
    return absl::InvalidArgumentError("PNG is malformed: the first chunk is not IHDR");
  }
  // A complete PNG ends with the 12-byte IEND chunk: length 0, "IEND", CRC AE426082.
  static constexpr unsigned char kIend[12] = {0,   0,   0,    0,    'I',  'E',
                                              'N', 'D', 0xAE, 0x42, 0x60, 0x82};
  if (std::memcmp(p + data.size() - 12, kIend, 12) != 0) {
    return absl::InvalidArgumentError(
        "PNG is truncated or corrupt: it does not end with an IEND chunk; send the whole file");
  }
  ImageHeader h;
  h.format = ImageFormat::kPng;
  const uint32_t w = ReadBigEndian32(p + 16);
  const uint32_t hgt = ReadBigEndian32(p + 20);
  if (w == 0 || hgt == 0 || w > 1u << 16 || hgt > 1u << 16) {
    return absl::InvalidArgumentError(
        absl::StrCat("PNG declares an impossible size ", w, "x", hgt));
  }
  h.width = static_cast<int>(w);
  h.height = static_cast<int>(hgt);
  h.bit_depth = p[24];
  switch (p[25]) {  // colour type
    case 0:
      h.channels = 1;
      break;
    case 2:
      h.channels = 3;
      break;
    case 3:
      h.channels = 3;
      break;  // palette, decoded to colour
    case 4:
      h.channels = 2;
      break;
    case 6:
      h.channels = 4;
      break;
    default:
      return absl::InvalidArgumentError(absl::StrCat("PNG has an unknown colour type ", p[25]));
  }
  return h;
}

absl::StatusOr<ImageHeader> ProbeJpeg(std::string_view data) {
  const unsigned char* p = Bytes(data);
  const size_t n = data.size();
  // The file must end with EOI (FFD9); some encoders pad with a few zero bytes after it.
  size_t end = n;
  while (end > 2 && p[end - 1] == 0 && n - end < 16) --end;
  if (end < 4 || p[end - 2] != 0xFF || p[end - 1] != 0xD9) {
    return absl::InvalidArgumentError(
        "JPEG is truncated or corrupt: it does not end with an EOI marker; send the whole file");
  }
  // Walk the marker segments to the first start-of-frame (SOFn) header.
  size_t i = 2;
  while (i + 4 <= n) {
    if (p[i] != 0xFF) {
      return absl::InvalidArgumentError("JPEG is malformed: expected a marker");
    }
    const unsigned char marker = p[i + 1];
    if (marker == 0xFF) {  // fill byte
      ++i;
      continue;
    }
    const size_t len = (size_t{p[i + 2]} << 8) | p[i + 3];
    const bool is_sof =
        marker >= 0xC0 && marker <= 0xCF && marker != 0xC4 && marker != 0xC8 && marker != 0xCC;
    if (is_sof) {
      if (i + 10 > n || len < 8) break;
      ImageHeader h;
      h.format = ImageFormat::kJpeg;
      h.bit_depth = p[i + 4];
      h.height = (p[i + 5] << 8) | p[i + 6];
      h.width = (p[i + 7] << 8) | p[i + 8];
      h.channels = p[i + 9];
      if (h.width == 0 || h.height == 0) {
        return absl::InvalidArgumentError("JPEG declares a zero image size");
      }
      return h;
    }
    if (len < 2) break;
    i += 2 + len;
  }
  return absl::InvalidArgumentError("JPEG is malformed: no frame header (SOF) found");
}

absl::Status CheckSize(const char* what, int width, int height, int want_w, int want_h) {
  if (width != want_w || height != want_h) {
    return absl::InvalidArgumentError(absl::StrCat(what, " is ", width, "x", height,
                                                   " but the frame says ", want_w, "x", want_h));
  }
  return absl::OkStatus();
}

absl::Status CheckExpectedSize(const char* what, int width, int height) {
  if (width < CameraIntrinsics::kMinSide || height < CameraIntrinsics::kMinSide ||
      width > CameraIntrinsics::kMaxSide || height > CameraIntrinsics::kMaxSide) {
    return absl::InvalidArgumentError(absl::StrCat(what, " size ", width, "x", height,
                                                   " is outside [", CameraIntrinsics::kMinSide,
                                                   ", ", CameraIntrinsics::kMaxSide, "]"));
  }
  return absl::OkStatus();
}

absl::StatusOr<cv::Mat> Imdecode(std::string_view data, int flags, const char* what) {
  // imdecode does not modify the buffer; wrapping avoids a copy.
  const cv::Mat buf(1, static_cast<int>(data.size()), CV_8UC1,
                    const_cast<char*>(data.data()));  // NOLINT: read-only use
  cv::Mat img;
  try {
    img = cv::imdecode(buf, flags);
  } catch (const cv::Exception& e) {
    return absl::InvalidArgumentError(absl::StrCat(what, " could not be decoded: ", e.what()));
  }
  if (img.empty()) {
    return absl::InvalidArgumentError(absl::StrCat(what, " could not be decoded (corrupt data)"));
  }
  return img;
}

}  // namespace

absl::StatusOr<ImageHeader> ProbeImage(std::string_view bytes) {
  if (bytes.size() >= 8 && std::memcmp(bytes.data(), kPngSignature, 8) == 0) {
    return ProbePng(bytes);
  }
  if (bytes.size() >= 3 && Bytes(bytes)[0] == 0xFF && Bytes(bytes)[1] == 0xD8 &&
      Bytes(bytes)[2] == 0xFF) {
    return ProbeJpeg(bytes);
  }
  if (bytes.empty()) return absl::InvalidArgumentError("image data is empty");
  return absl::InvalidArgumentError("image data is neither PNG nor JPEG (unknown signature)");
}

absl::Status DepthRange::Validate() const {
  if (!(min_m > 0.0f && min_m < max_m && max_m <= 1000.0f)) {
    return absl::InvalidArgumentError(
        absl::StrCat("depth range must satisfy 0 < min_depth_m < max_depth_m <= 1000, got [", min_m,
                     ", ", max_m, "]"));
  }
  return absl::OkStatus();
}

namespace {

// Readings outside the range (and NaN, infinite, negative ones) become 0, no reading.
void KeepDepthRange(const DepthRange& range, cv::Mat* depth_m) {
  float* v = depth_m->ptr<float>();
  const size_t n = depth_m->total();
  const float lo = range.min_m, hi = range.max_m;
  for (size_t i = 0; i < n; ++i) {
    // A select rather than a conditional store, so that it vectorises; NaN fails the test.
    v[i] = (v[i] >= lo && v[i] <= hi) ? v[i] : 0.0f;
  }
}

absl::StatusOr<cv::Mat> DecodeDepthUnranged(const EncodedDepth& depth) {
  if (auto s = CheckExpectedSize("depth", depth.width, depth.height); !s.ok()) return s;
  const size_t pixels = static_cast<size_t>(depth.width) * static_cast<size_t>(depth.height);
  const bool scaled = depth.encoding != DepthEncoding::kRawF32;
  // Written so that NaN fails the test too.
  if (scaled && !(depth.depth_scale >= kMinDepthScale && depth.depth_scale <= kMaxDepthScale)) {
    return absl::InvalidArgumentError(
        absl::StrCat("depth_scale must be within [", kMinDepthScale, ", ", kMaxDepthScale,
                     "] units per metre (TUM: 5000, millimetres: 1000), got ", depth.depth_scale));
  }
  cv::Mat out(depth.height, depth.width, CV_32FC1);
  switch (depth.encoding) {
    case DepthEncoding::kPng16: {
      auto header = ProbeImage(depth.data);
      if (!header.ok()) {
        return absl::InvalidArgumentError(absl::StrCat("depth: ", header.status().message()));
      }
      if (header->format != ImageFormat::kPng || header->bit_depth != 16 || header->channels != 1) {
        return absl::InvalidArgumentError(
            absl::StrCat("depth must be a 16-bit single-channel PNG, got a ",
                         header->format == ImageFormat::kPng ? "PNG" : "JPEG", " with ",
                         header->channels, " channel(s) of ", header->bit_depth, " bits"));
      }
      if (auto s = CheckSize("depth PNG", header->width, header->height, depth.width, depth.height);
          !s.ok()) {
        return s;
      }
      auto raw = Imdecode(depth.data, cv::IMREAD_ANYDEPTH, "depth PNG");
      if (!raw.ok()) return raw.status();
      if (raw->type() != CV_16UC1) {
        return absl::InvalidArgumentError("depth PNG did not decode to 16-bit grey");
      }
      raw->convertTo(out, CV_32FC1, 1.0 / depth.depth_scale);
      return out;
    }
    case DepthEncoding::kRvl:
    case DepthEncoding::kPaletted: {
      auto raw = depth.encoding == DepthEncoding::kRvl ? DecodeRvl(depth.data)
                                                       : DecodePalettedDepth(depth.data);
      if (!raw.ok()) {
        return absl::InvalidArgumentError(absl::StrCat("depth: ", raw.status().message()));
      }
      if (auto s = CheckSize("depth image", raw->cols, raw->rows, depth.width, depth.height);
          !s.ok()) {
        return s;
      }
      raw->convertTo(out, CV_32FC1, 1.0 / depth.depth_scale);
      return out;
    }
    case DepthEncoding::kRawU16: {
      if (depth.data.size() != pixels * 2) {
        return absl::InvalidArgumentError(absl::StrCat("raw uint16 depth has ", depth.data.size(),
                                                       " bytes; ", depth.width, "x", depth.height,
                                                       " needs ", pixels * 2));
      }
      const cv::Mat raw(depth.height, depth.width, CV_16UC1,
                        const_cast<char*>(depth.data.data()));  // NOLINT: read-only use
      raw.convertTo(out, CV_32FC1, 1.0 / depth.depth_scale);
      return out;
    }
    case DepthEncoding::kRawF32: {
      if (depth.data.size() != pixels * 4) {
        return absl::InvalidArgumentError(absl::StrCat("raw float32 depth has ", depth.data.size(),
                                                       " bytes; ", depth.width, "x", depth.height,
                                                       " needs ", pixels * 4));
      }
      std::memcpy(out.data, depth.data.data(), pixels * 4);  // NaN and the rest: KeepDepthRange
      return out;
    }
  }
  return absl::InvalidArgumentError("unknown depth encoding");
}

}  // namespace

absl::StatusOr<cv::Mat> DecodeDepthMetres(const EncodedDepth& depth, const DepthRange& range) {
  if (auto s = range.Validate(); !s.ok()) return s;
  auto out = DecodeDepthUnranged(depth);
  if (!out.ok()) return out;
  KeepDepthRange(range, &*out);
  return out;
}

absl::StatusOr<cv::Mat> DecodeColorBgr(const EncodedColor& color) {
  if (auto s = CheckExpectedSize("colour", color.width, color.height); !s.ok()) return s;
  if (color.encoding == ColorEncoding::kRawRgb8) {
    const size_t need = static_cast<size_t>(color.width) * color.height * 3;
    if (color.data.size() != need) {
      return absl::InvalidArgumentError(absl::StrCat("raw RGB8 colour has ", color.data.size(),
                                                     " bytes; ", color.width, "x", color.height,
                                                     " needs ", need));
    }
    const cv::Mat rgb(color.height, color.width, CV_8UC3,
                      const_cast<char*>(color.data.data()));  // NOLINT: read-only use
    cv::Mat bgr;
    cv::cvtColor(rgb, bgr, cv::COLOR_RGB2BGR);
    return bgr;
  }
  auto header = ProbeImage(color.data);
  if (!header.ok()) {
    return absl::InvalidArgumentError(absl::StrCat("colour: ", header.status().message()));
  }
  const ImageFormat want =
      color.encoding == ColorEncoding::kJpeg ? ImageFormat::kJpeg : ImageFormat::kPng;
  if (header->format != want) {
    return absl::InvalidArgumentError(
        absl::StrCat("colour is declared ", want == ImageFormat::kJpeg ? "JPEG" : "PNG",
                     " but the data is ", header->format == ImageFormat::kJpeg ? "JPEG" : "PNG"));
  }
  if (header->bit_depth != 8) {
    return absl::InvalidArgumentError(
        absl::StrCat("colour must have 8 bits per channel, got ", header->bit_depth));
  }
  if (auto s = CheckSize("colour image", header->width, header->height, color.width, color.height);
      !s.ok()) {
    return s;
  }
  return Imdecode(color.data, cv::IMREAD_COLOR, "colour image");
}

namespace {

// Depth in metres to uint16 units at `depth_scale`; readings that do not fit are 0.
absl::StatusOr<cv::Mat> QuantiseDepth(const cv::Mat& depth_m, double depth_scale) {
  if (depth_m.type() != CV_32FC1 || depth_m.empty()) {
    return absl::InvalidArgumentError("depth encoding needs a non-empty CV_32FC1 image");
  }
  if (!(depth_scale > 0.0) || !std::isfinite(depth_scale)) {
    return absl::InvalidArgumentError("depth_scale must be > 0");
  }
  cv::Mat u16(depth_m.size(), CV_16UC1);
  for (int r = 0; r < depth_m.rows; ++r) {
    const float* src = depth_m.ptr<float>(r);
    uint16_t* dst = u16.ptr<uint16_t>(r);
    for (int c = 0; c < depth_m.cols; ++c) {
      const double units = std::round(static_cast<double>(src[c]) * depth_scale);
      dst[c] = (std::isfinite(units) && units > 0.0 && units <= 65535.0)
                   ? static_cast<uint16_t>(units)
                   : 0;
    }
  }
  return u16;
}

}  // namespace

absl::StatusOr<std::string> EncodeDepthPng16(const cv::Mat& depth_m, double depth_scale) {
  auto u16 = QuantiseDepth(depth_m, depth_scale);
  if (!u16.ok()) return u16.status();
  return EncodePng(*u16);
}

absl::StatusOr<std::string> EncodeDepthRvl(const cv::Mat& depth_m, double depth_scale) {
  auto u16 = QuantiseDepth(depth_m, depth_scale);
  if (!u16.ok()) return u16.status();
  return EncodeRvl(*u16);
}

absl::StatusOr<std::string> EncodeDepthPaletted(const cv::Mat& depth_m, double depth_scale) {
  auto u16 = QuantiseDepth(depth_m, depth_scale);
  if (!u16.ok()) return u16.status();
  return EncodePalettedDepth(*u16);
}

namespace {

void AppendPngBytes(png_structp png, png_bytep data, png_size_t n) {
  static_cast<std::string*>(png_get_io_ptr(png))->append(reinterpret_cast<const char*>(data), n);
}
void FlushNothing(png_structp) {}

// 8-bit grey PNG written with libpng itself: the "up" filter and zlib's run-length strategy.
// Written here because cv::imencode offers no filter choice, and libpng's adaptive filtering is
// most of its cost: on the per-frame result images (labels, masks, per-segment scores and
// confidences: runs of equal values) this is 2.6x faster than cv::imencode at level 1 and a
// third smaller (docs/BENCHMARKS.md). False when libpng fails (out of memory).
bool EncodeGreyPng(const cv::Mat& grey, std::string* out) {
  png_structp png = png_create_write_struct(PNG_LIBPNG_VER_STRING, nullptr, nullptr, nullptr);
  if (png == nullptr) return false;
  png_infop info = png_create_info_struct(png);
  // libpng reports errors by longjmp to here; nothing between here and a png_* call below
  // needs destroying (no C++ object is made in between).
  if (info == nullptr || setjmp(png_jmpbuf(png))) {
    png_destroy_write_struct(&png, &info);
    return false;
  }
  png_set_write_fn(png, out, AppendPngBytes, FlushNothing);
  png_set_IHDR(png, info, static_cast<png_uint_32>(grey.cols), static_cast<png_uint_32>(grey.rows),
               8, PNG_COLOR_TYPE_GRAY, PNG_INTERLACE_NONE, PNG_COMPRESSION_TYPE_DEFAULT,
               PNG_FILTER_TYPE_DEFAULT);
  png_set_filter(png, PNG_FILTER_TYPE_BASE, PNG_FILTER_UP);
  png_set_compression_level(png, 1);
  png_set_compression_strategy(png, Z_RLE);
  png_write_info(png, info);
  for (int r = 0; r < grey.rows; ++r) {
    png_write_row(png, const_cast<png_bytep>(grey.ptr<uint8_t>(r)));
  }
  png_write_end(png, nullptr);
  png_destroy_write_struct(&png, &info);
  return true;
}

}  // namespace

absl::StatusOr<std::string> EncodePng(const cv::Mat& image) {
  if (image.type() == CV_8UC1 && !image.empty()) {
    std::string out;
    out.reserve(image.total() / 8);
    if (!EncodeGreyPng(image, &out)) return absl::InternalError("PNG encoding failed");
    return out;
  }
  std::vector<unsigned char> buf;
  // Compression level 1: these are written on the keyframe path; level 1 is ~3x faster than
  // the default 3 and within a few percent in size for depth and colour images.
  if (!cv::imencode(".png", image, buf, {cv::IMWRITE_PNG_COMPRESSION, 1})) {
    return absl::InternalError("PNG encoding failed");
  }
  return std::string(buf.begin(), buf.end());
}

absl::StatusOr<std::string> EncodeJpeg(const cv::Mat& bgr, int quality) {
  if (quality < 1 || quality > 100) {
    return absl::InvalidArgumentError("JPEG quality must be in [1, 100]");
  }
  std::vector<unsigned char> buf;
  if (!cv::imencode(".jpg", bgr, buf, {cv::IMWRITE_JPEG_QUALITY, quality})) {
    return absl::InternalError("JPEG encoding failed");
  }
  return std::string(buf.begin(), buf.end());
}

absl::StatusOr<std::string> ReadFileBytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    const int err = errno;
    if (err == ENOENT) return absl::NotFoundError(absl::StrCat(path, ": no such file"));
    if (err == EACCES)
      return absl::PermissionDeniedError(absl::StrCat(path, ": permission denied"));
    return absl::UnavailableError(absl::StrCat(path, ": cannot open: ", std::strerror(err)));
  }
  std::ostringstream ss;
  ss << in.rdbuf();
  if (in.bad()) return absl::DataLossError(absl::StrCat(path, ": read error"));
  return std::move(ss).str();
}

}  // namespace lifemap
