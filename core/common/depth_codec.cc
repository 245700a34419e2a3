#include "core/common/depth_codec.h"

#include <cstdint>
#include <cstring>
#include <vector>

#include <zstd.h>

#include "absl/strings/str_cat.h"

namespace lifemap {
namespace {

constexpr char kMagic[4] = {'R', 'V', 'L', '1'};
constexpr size_t kHeaderBytes = 12;

void PutU32(uint32_t v, std::string* out) {
  for (int i = 0; i < 4; ++i) out->push_back(static_cast<char>((v >> (8 * i)) & 0xff));
}

uint32_t GetU32(std::string_view bytes, size_t at) {
  uint32_t v = 0;
  for (int i = 0; i < 4; ++i)
    v |= static_cast<uint32_t>(static_cast<uint8_t>(bytes[at + i])) << (8 * i);
  return v;
}

// Nibbles, most significant first within each 32-bit word.
class NibbleWriter {
 public:
  explicit NibbleWriter(std::string* out) : out_(out) {}
  // Variable length: 3 bits per nibble, the high bit says another nibble follows.
  void Put(uint32_t value) {
    do {
      uint32_t nibble = value & 7u;
      value >>= 3;
      if (value != 0) nibble |= 8u;
      word_ = (word_ << 4) | nibble;
      if (++nibbles_ == 8) Flush();
    } while (value != 0);
  }
  void Finish() {
    if (nibbles_ == 0) return;
    word_ <<= 4 * (8 - nibbles_);
    Flush();
  }

 private:
  void Flush() {
    PutU32(word_, out_);
    word_ = 0;
    nibbles_ = 0;
  }
  std::string* out_;
  uint32_t word_ = 0;
  int nibbles_ = 0;
};

class NibbleReader {
 public:
  NibbleReader(std::string_view bytes, size_t at) : bytes_(bytes), at_(at) {}
  // False when the data ends first or the value does not fit in 32 bits.
  bool Get(uint32_t* value) {
    uint32_t v = 0;
    for (int shift = 0;; shift += 3) {
      if (nibbles_ == 0) {
        if (at_ + 4 > bytes_.size()) return false;
        word_ = GetU32(bytes_, at_);
        at_ += 4;
        nibbles_ = 8;
      }
      const uint32_t nibble = word_ >> 28;
      word_ <<= 4;
      --nibbles_;
      if (shift > 30) return false;
      v |= (nibble & 7u) << shift;
      if ((nibble & 8u) == 0) break;
    }
    *value = v;
    return true;
  }
  size_t position() const { return at_; }

 private:
  std::string_view bytes_;
  size_t at_;
  uint32_t word_ = 0;
  int nibbles_ = 0;
};

// The image size a header declares, refused when it is empty or over `max_pixels`.
absl::Status CheckDeclaredSize(const char* what, uint32_t width, uint32_t height,
                               int64_t max_pixels) {
  if (width == 0 || height == 0 || width > 65535 || height > 65535 ||
      static_cast<int64_t>(width) * height > max_pixels) {
    return absl::InvalidArgumentError(absl::StrCat(
        what, " of ", width, "x", height, " pixels is refused (at most ", max_pixels, " pixels)"));
  }
  return absl::OkStatus();
}

}  // namespace

bool LooksLikeRvl(std::string_view bytes) {
  return bytes.size() >= 4 && std::memcmp(bytes.data(), kMagic, 4) == 0;
}

std::string EncodeRvl(const cv::Mat& depth) {
  CV_Assert(depth.type() == CV_16UC1 && !depth.empty());
  std::string out(kMagic, 4);
  PutU32(static_cast<uint32_t>(depth.cols), &out);
  PutU32(static_cast<uint32_t>(depth.rows), &out);
  out.reserve(kHeaderBytes + depth.total());
  NibbleWriter w(&out);
  cv::Mat continuous = depth.isContinuous() ? depth : depth.clone();
  const uint16_t* p = continuous.ptr<uint16_t>(0);
  const uint16_t* end = p + continuous.total();
  int32_t previous = 0;
  while (p != end) {
    const uint16_t* run = p;
    while (p != end && *p == 0) ++p;
    w.Put(static_cast<uint32_t>(p - run));
    if (p == end) break;  // the decoder stops when the image is full
    run = p;
    while (p != end && *p != 0) ++p;
    w.Put(static_cast<uint32_t>(p - run));
    for (; run != p; ++run) {
      const int32_t delta = static_cast<int32_t>(*run) - previous;
      // Zig-zag; the shift on the unsigned value (shifting a negative int is undefined).
      w.Put((static_cast<uint32_t>(delta) << 1) ^ static_cast<uint32_t>(delta >> 31));
      previous = *run;
    }
  }
  w.Finish();
  return out;
}

absl::StatusOr<cv::Mat> DecodeRvl(std::string_view bytes, int64_t max_pixels) {
  if (bytes.size() < kHeaderBytes || !LooksLikeRvl(bytes)) {
    return absl::InvalidArgumentError("not an RVL depth image (no RVL1 header)");
  }
  const uint32_t width = GetU32(bytes, 4), height = GetU32(bytes, 8);
  if (auto s = CheckDeclaredSize("RVL depth image", width, height, max_pixels); !s.ok()) {
    return s;
  }
  cv::Mat out(static_cast<int>(height), static_cast<int>(width), CV_16UC1);
  uint16_t* p = out.ptr<uint16_t>(0);
  size_t left = out.total();
  NibbleReader r(bytes, kHeaderBytes);
  int32_t previous = 0;
  auto truncated = [] { return absl::InvalidArgumentError("RVL depth image is truncated"); };
  while (left > 0) {
    uint32_t zeros = 0, readings = 0;
    if (!r.Get(&zeros)) return truncated();
    if (zeros > left) return absl::InvalidArgumentError("RVL run of zeros overflows the image");
    std::memset(p, 0, zeros * sizeof(uint16_t));
    p += zeros;
    left -= zeros;
    if (left == 0) break;
    if (!r.Get(&readings)) return truncated();
    if (readings > left)
      return absl::InvalidArgumentError("RVL run of readings overflows the image");
    for (uint32_t i = 0; i < readings; ++i) {
      uint32_t z = 0;
      if (!r.Get(&z)) return truncated();
      const int32_t delta = static_cast<int32_t>(z >> 1) ^ -static_cast<int32_t>(z & 1u);
      const int64_t value = static_cast<int64_t>(previous) + delta;
      if (value <= 0 || value > 65535) {
        return absl::InvalidArgumentError("RVL reading out of the 16-bit range");
      }
      previous = static_cast<int32_t>(value);
      *p++ = static_cast<uint16_t>(value);
    }
    left -= readings;
  }
  if (r.position() != bytes.size()) {
    return absl::InvalidArgumentError(absl::StrCat(
        "RVL depth image has ", bytes.size() - r.position(), " bytes after its last pixel"));
  }
  return out;
}

namespace {

constexpr char kPalettedMagic[4] = {'L', 'M', 'D', '1'};
constexpr size_t kPalettedHeaderBytes = 16;
// Above this many distinct values a palette costs more than it saves (its table alone is
// 2 bytes per value); the indices are then the values themselves.
constexpr size_t kMaxPalette = 16384;
constexpr int kZstdLevel = 3;

}  // namespace

std::string EncodePalettedDepth(const cv::Mat& depth) {
  CV_Assert(depth.type() == CV_16UC1 && !depth.empty());
  std::vector<uint8_t> seen(65536, 0);
  for (int r = 0; r < depth.rows; ++r) {
    const uint16_t* row = depth.ptr<uint16_t>(r);
    for (int c = 0; c < depth.cols; ++c) seen[row[c]] = 1;
  }
  std::vector<uint16_t> palette;
  std::vector<uint16_t> index_of(65536, 0);
  for (int v = 0; v < 65536; ++v) {
    if (!seen[static_cast<size_t>(v)]) continue;
    index_of[static_cast<size_t>(v)] = static_cast<uint16_t>(palette.size());
    palette.push_back(static_cast<uint16_t>(v));
  }
  cv::Mat indices = depth;
  if (palette.size() <= kMaxPalette) {
    // Zero keeps index 0 when it is present (no reading stays a zero run for RVL); when it is
    // not, indices start at 1 so that none reads as "no reading".
    const uint16_t shift = seen[0] ? 0 : 1;
    indices = cv::Mat(depth.size(), CV_16UC1);
    for (int r = 0; r < depth.rows; ++r) {
      const uint16_t* row = depth.ptr<uint16_t>(r);
      uint16_t* out = indices.ptr<uint16_t>(r);
      for (int c = 0; c < depth.cols; ++c) {
        out[c] = static_cast<uint16_t>(index_of[row[c]] + shift);
      }
    }
    if (shift == 1) palette.insert(palette.begin(), 0);
  } else {
    palette.clear();
  }
  const std::string rvl = EncodeRvl(indices);
  std::string out(kPalettedMagic, 4);
  PutU32(static_cast<uint32_t>(depth.cols), &out);
  PutU32(static_cast<uint32_t>(depth.rows), &out);
  PutU32(static_cast<uint32_t>(palette.size()), &out);
  for (uint16_t v : palette) {
    out.push_back(static_cast<char>(v & 0xff));
    out.push_back(static_cast<char>(v >> 8));
  }
  const size_t at = out.size();
  out.resize(at + ZSTD_compressBound(rvl.size()));
  const size_t n =
      ZSTD_compress(out.data() + at, out.size() - at, rvl.data(), rvl.size(), kZstdLevel);
  CV_Assert(!ZSTD_isError(n));  // only for a too-small buffer, which compressBound rules out
  out.resize(at + n);
  return out;
}

absl::StatusOr<cv::Mat> DecodePalettedDepth(std::string_view bytes, int64_t max_pixels) {
  if (bytes.size() < kPalettedHeaderBytes || std::memcmp(bytes.data(), kPalettedMagic, 4) != 0) {
    return absl::InvalidArgumentError("not a paletted depth image (no LMD1 header)");
  }
  const uint32_t width = GetU32(bytes, 4), height = GetU32(bytes, 8);
  const uint32_t palette_size = GetU32(bytes, 12);
  if (auto s = CheckDeclaredSize("paletted depth image", width, height, max_pixels); !s.ok()) {
    return s;
  }
  if (palette_size > 65536 || kPalettedHeaderBytes + 2 * size_t{palette_size} > bytes.size()) {
    return absl::InvalidArgumentError("paletted depth image: palette is truncated");
  }
  std::vector<uint16_t> palette(palette_size);
  for (uint32_t i = 0; i < palette_size; ++i) {
    const size_t at = kPalettedHeaderBytes + 2 * size_t{i};
    palette[i] = static_cast<uint16_t>(static_cast<uint8_t>(bytes[at]) |
                                       (static_cast<uint8_t>(bytes[at + 1]) << 8));
  }
  const std::string_view packed = bytes.substr(kPalettedHeaderBytes + 2 * size_t{palette_size});
  const unsigned long long size = ZSTD_getFrameContentSize(packed.data(), packed.size());
  // RVL never needs more than 12 header bytes plus 6 nibbles per pixel, 2 run lengths of 11.
  const unsigned long long bound = 12 + 16ULL * width * height + 64;
  if (size == ZSTD_CONTENTSIZE_ERROR || size == ZSTD_CONTENTSIZE_UNKNOWN || size > bound) {
    return absl::InvalidArgumentError("paletted depth image: damaged zstd frame");
  }
  std::string rvl(size, '\0');
  const size_t n = ZSTD_decompress(rvl.data(), rvl.size(), packed.data(), packed.size());
  if (ZSTD_isError(n) || n != size) {
    return absl::InvalidArgumentError("paletted depth image: damaged zstd frame");
  }
  auto indices = DecodeRvl(rvl, max_pixels);
  if (!indices.ok()) {
    return absl::InvalidArgumentError(
        absl::StrCat("paletted depth image: ", indices.status().message()));
  }
  if (indices->cols != static_cast<int>(width) || indices->rows != static_cast<int>(height)) {
    return absl::InvalidArgumentError("paletted depth image: its two sizes disagree");
  }
  if (palette.empty()) return indices;
  for (int r = 0; r < indices->rows; ++r) {
    uint16_t* row = indices->ptr<uint16_t>(r);
    for (int c = 0; c < indices->cols; ++c) {
      if (row[c] >= palette.size()) {
        return absl::InvalidArgumentError("paletted depth image: index beyond its palette");
      }
      row[c] = palette[row[c]];
    }
  }
  return indices;
}

}  // namespace lifemap
