#include "core/io/labeled_pcd.h"

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <exception>
#include <filesystem>
#include <fstream>
#include <initializer_list>
#include <map>
#include <optional>
#include <set>
#include <sstream>
#include <string>

#include <pcl/common/io.h>
#include <pcl/io/pcd_io.h>

#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "absl/strings/string_view.h"
#include "absl/strings/strip.h"

namespace lifemap::io {

CameraIntrinsics KinectDefaultIntrinsics(int width, int height) {
  const double sx = width / 640.0, sy = height / 480.0;
  return {525.0 * sx, 525.0 * sy, 319.5 * sx, 239.5 * sy, width, height};
}

namespace {

// Larger than any depth camera's image; keeps a header's claim from allocating gigabytes.
constexpr uint32_t kMaxSide = 8192;

// The header is read here first, strictly, and PCL sees only files whose header is a plain PCD
// v0.7 header: PCL 1.13's own header reader threw, allocated from any number (a COUNT of 10^56
// asked for 200 GB), dropped fields of COUNT 0 in one reading and not another, and corrupted
// its heap on some headers of repeated and binary-laden lines (all found by
// tests/fuzz/labeled_pcd_fuzz). Here: printable lines; each key once (VERSION, COUNT and
// VIEWPOINT optional), no other; unique field names; SIZE 1, 2, 4 or 8 with TYPE I, U or F
// (F only 4 or 8); COUNT 1-1024; one value per field in each; WIDTH and HEIGHT 1-kMaxSide;
// POINTS their product; DATA ascii, binary or binary_compressed.
absl::Status CheckHeader(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  std::map<std::string, std::vector<std::string>> lines;
  std::string line;
  for (int n = 0; n < 64 && std::getline(in, line); ++n) {
    if (!line.empty() && line.back() == '\r') line.pop_back();
    for (const char c : line) {
      if ((c < 0x20 || c > 0x7e) && c != '\t') {
        return absl::InvalidArgumentError("the header has a line that is not text");
      }
    }
    if (line.empty() || line[0] == '#') continue;
    std::vector<std::string> words =
        absl::StrSplit(line, absl::ByAnyChar(" \t"), absl::SkipEmpty());
    if (words.empty()) continue;  // blanks only
    const std::string key = words.front();
    words.erase(words.begin());
    static const std::set<std::string> kKeys = {"VERSION", "FIELDS", "SIZE",      "TYPE",   "COUNT",
                                                "WIDTH",   "HEIGHT", "VIEWPOINT", "POINTS", "DATA"};
    if (kKeys.count(key) == 0)
      return absl::InvalidArgumentError(absl::StrCat("unknown header line '", key, "'"));
    if (!lines.emplace(key, words).second) {
      return absl::InvalidArgumentError(absl::StrCat("the header has two ", key, " lines"));
    }
    if (key == "DATA") {
      // PCL goes on reading header lines after DATA, skipping empty and comment lines, until
      // one is not a key: a body that spells keys there ("VERSION...", "COLUMNS...") is read
      // as header and sizes the buffer (206 GB for inputs of the long labeled_pcd_fuzz runs).
      std::string next;
      for (int more = 0; more < 64 && std::getline(in, next); ++more) {
        const absl::string_view body = absl::StripLeadingAsciiWhitespace(next);
        if (body.empty() || body[0] == '#') continue;
        for (const char* k : {"VERSION", "FIELDS", "COLUMNS", "SIZE", "TYPE", "COUNT", "WIDTH",
                              "HEIGHT", "VIEWPOINT", "POINTS", "DATA"}) {
          if (absl::StartsWith(body, k)) {
            return absl::InvalidArgumentError(absl::StrCat("the data after DATA begins with '", k,
                                                           "', which PCL reads as header"));
          }
        }
        break;
      }
      break;
    }
  }
  for (const char* needed : {"FIELDS", "SIZE", "TYPE", "WIDTH", "HEIGHT", "POINTS", "DATA"}) {
    if (lines.count(needed) == 0) {
      return absl::InvalidArgumentError(absl::StrCat("the header has no ", needed, " line"));
    }
  }
  const auto& fields = lines["FIELDS"];
  const std::set<std::string> unique(fields.begin(), fields.end());
  if (fields.empty() || fields.size() > 64 || unique.size() != fields.size()) {
    return absl::InvalidArgumentError("FIELDS must name 1 to 64 different fields");
  }
  if (lines.count("COUNT") == 0) lines["COUNT"] = std::vector<std::string>(fields.size(), "1");
  for (const char* key : {"SIZE", "TYPE", "COUNT"}) {
    if (lines[key].size() != fields.size()) {
      return absl::InvalidArgumentError(absl::StrCat(key, " must give one value per field"));
    }
  }
  const auto whole = [](const std::string& word, uint64_t most) -> std::optional<uint64_t> {
    uint64_t v = 0;
    if (!absl::SimpleAtoi(word, &v) || v < 1 || v > most) return std::nullopt;
    return v;
  };
  for (size_t i = 0; i < fields.size(); ++i) {
    const auto size = whole(lines["SIZE"][i], 8);
    const std::string& type = lines["TYPE"][i];
    if (!size || (*size != 1 && *size != 2 && *size != 4 && *size != 8) ||
        (type != "I" && type != "U" && type != "F") || (type == "F" && *size < 4) ||
        !whole(lines["COUNT"][i], 1024)) {
      return absl::InvalidArgumentError(
          absl::StrCat("field '", fields[i], "' has a SIZE, TYPE or COUNT PCD does not define"));
    }
  }
  const auto one = [&lines, &whole](const char* key, uint64_t most) -> std::optional<uint64_t> {
    const auto& words = lines[key];
    return words.size() == 1 ? whole(words[0], most) : std::nullopt;
  };
  const auto width = one("WIDTH", kMaxSide), height = one("HEIGHT", kMaxSide);
  const auto points = one("POINTS", uint64_t{kMaxSide} * kMaxSide);
  if (!width || !height || !points || *points != *width * *height) {
    return absl::InvalidArgumentError(
        absl::StrCat("WIDTH and HEIGHT must be whole numbers from 1 to ", kMaxSide,
                     " and POINTS their product"));
  }
  const auto& data = lines["DATA"];
  if (data.size() != 1 ||
      (data[0] != "ascii" && data[0] != "binary" && data[0] != "binary_compressed")) {
    return absl::InvalidArgumentError("DATA must be ascii, binary or binary_compressed");
  }
  return absl::OkStatus();
}

// PCL reads the body by the header's field sizes and offsets without checking them against each
// other (a SIZE that does not fit its TYPE made PCL 1.13 read far outside its buffer; found by
// tests/fuzz/labeled_pcd_fuzz): so every field must have a known type, one value or a few, and
// lie right after the one before, and the point must be as long as its fields.
absl::Status CheckFieldLayout(const pcl::PCLPointCloud2& header) {
  uint32_t offset = 0;
  for (const auto& f : header.fields) {
    const int size = pcl::getFieldSize(f.datatype);
    if (f.datatype < pcl::PCLPointField::INT8 || f.datatype > pcl::PCLPointField::FLOAT64 ||
        size == 0 || f.count < 1 || f.count > 1024 || f.offset != offset) {
      return absl::InvalidArgumentError(absl::StrCat("field '", f.name,
                                                     "' has a SIZE, TYPE or COUNT PCD does not "
                                                     "define, or they disagree"));
    }
    const bool xyz = f.name == "x" || f.name == "y" || f.name == "z";
    if ((xyz && f.datatype != pcl::PCLPointField::FLOAT32) ||
        ((xyz || f.name == "rgba" || f.name == "rgb" || f.name == "label") &&
         (size != 4 || f.count != 1))) {
      return absl::InvalidArgumentError(absl::StrCat(
          "field '", f.name, "' must be one 4-byte value (x y z float, rgba and label 4 bytes)"));
    }
    offset += static_cast<uint32_t>(size) * f.count;
  }
  if (offset != header.point_step) {
    return absl::InvalidArgumentError(
        absl::StrCat("the fields take ", offset, " bytes but a point has ", header.point_step));
  }
  return absl::OkStatus();
}

// PCL allocates what a binary_compressed body says it unpacks to (a 3.4 GB claim in an 800-byte
// file; found by tests/fuzz/labeled_pcd_fuzz) and trusts a binary body to be whole: so the
// body must hold, or unpack to, exactly the points the header names. `data_type` and
// `data_start` as PCDReader::readHeader gives them (0 ascii, 1 binary, 2 binary_compressed).
absl::Status CheckBodySize(const std::string& path, const pcl::PCLPointCloud2& header,
                           int data_type, unsigned int data_start) {
  if (data_type == 0) return absl::OkStatus();  // ascii: PCL reads line by line
  std::ifstream in(path, std::ios::binary | std::ios::ate);
  const auto file_bytes = static_cast<uint64_t>(in.tellg());
  const uint64_t points_bytes =
      uint64_t{header.width} * header.height * uint64_t{header.point_step};
  if (data_type == 1) {
    if (file_bytes < data_start + points_bytes) {
      return absl::InvalidArgumentError(absl::StrCat(
          "the binary body holds ", file_bytes - std::min(file_bytes, uint64_t{data_start}),
          " bytes, not the ", points_bytes, " its header names (truncated?)"));
    }
    return absl::OkStatus();
  }
  uint32_t sizes[2] = {0, 0};  // compressed, uncompressed
  in.seekg(data_start);
  if (!in.read(reinterpret_cast<char*>(sizes), sizeof(sizes)) || sizes[1] != points_bytes ||
      sizes[0] > file_bytes - data_start - sizeof(sizes)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "the compressed body's sizes (", sizes[0], " packed, ", sizes[1],
        " unpacked) do not fit the file or the ", points_bytes, " bytes its header names"));
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<LabeledFrame> ReadLabeledPcd(const std::string& path) {
  if (!std::filesystem::exists(path))
    return absl::NotFoundError(absl::StrCat(path, ": no such file"));
  if (absl::Status s = CheckHeader(path); !s.ok()) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": ", s.message()));
  }
  pcl::PCLPointCloud2 header_only;
  pcl::PCDReader reader;
  Eigen::Vector4f origin;
  Eigen::Quaternionf orientation;
  int version = 0, data_type = 0;
  unsigned int data_idx = 0;
  // PCL throws (std::out_of_range, pcl::PCLException, ...) on some malformed files and returns
  // an error on others: both are "not a PCD file" here (found by tests/fuzz/labeled_pcd_fuzz).
  try {
    if (reader.readHeader(path, header_only, origin, orientation, version, data_type, data_idx) !=
        0) {
      return absl::InvalidArgumentError(absl::StrCat(path, ": not a readable PCD file"));
    }
  } catch (const std::exception& e) {
    return absl::InvalidArgumentError(
        absl::StrCat(path, ": not a readable PCD file (", e.what(), ")"));
  }
  bool has_label = false, has_rgba = false;
  for (const auto& f : header_only.fields) {
    has_label |= f.name == "label";
    has_rgba |= f.name == "rgba" || f.name == "rgb";
  }
  if (!has_label || !has_rgba) {
    return absl::InvalidArgumentError(
        absl::StrCat(path, ": needs the fields x y z rgba label (a labelled RGB-D cloud)"));
  }
  if (absl::Status s = CheckFieldLayout(header_only); !s.ok()) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": ", s.message()));
  }
  if (header_only.width < 1) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": the header names no points"));
  }
  if (header_only.height <= 1) {
    return absl::InvalidArgumentError(
        absl::StrCat(path, ": the cloud is not organized (height 1): no pixel grid"));
  }
  if (header_only.width > kMaxSide || header_only.height > kMaxSide) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": a ", header_only.width, "x",
                                                   header_only.height, " cloud; at most ", kMaxSide,
                                                   " points a side are read"));
  }
  if (absl::Status s = CheckBodySize(path, header_only, data_type, data_idx); !s.ok()) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": ", s.message()));
  }
  // The file is read as PCL's untyped blob and the points are taken from it here, by the
  // blob's own field offsets: PCL's conversion to a typed cloud copied past the blob for a
  // header whose fields it read differently the second time (found by
  // tests/fuzz/labeled_pcd_fuzz).
  pcl::PCLPointCloud2 blob;
  try {
    if (reader.read(path, blob) != 0) {
      return absl::InvalidArgumentError(absl::StrCat(path, ": could not be read as PCD"));
    }
  } catch (const std::exception& e) {
    return absl::InvalidArgumentError(
        absl::StrCat(path, ": could not be read as PCD (", e.what(), ")"));
  }
  if (absl::Status s = CheckFieldLayout(blob); !s.ok()) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": ", s.message()));
  }
  const auto field_named =
      [&blob](std::initializer_list<const char*> names) -> const pcl::PCLPointField* {
    for (const auto& f : blob.fields) {
      for (const char* name : names) {
        if (f.name == name) return &f;
      }
    }
    return nullptr;
  };
  const pcl::PCLPointField* z = field_named({"z"});
  const pcl::PCLPointField* rgba = field_named({"rgba", "rgb"});
  const pcl::PCLPointField* label = field_named({"label"});
  if (z == nullptr || rgba == nullptr || label == nullptr ||
      (label->datatype != pcl::PCLPointField::UINT32 &&
       label->datatype != pcl::PCLPointField::INT32)) {
    return absl::InvalidArgumentError(
        absl::StrCat(path, ": needs the fields z (float), rgba and label (4-byte integer)"));
  }
  if (blob.height <= 1 || blob.width < 1 || blob.width > kMaxSide || blob.height > kMaxSide ||
      blob.data.size() != size_t{blob.width} * blob.height * blob.point_step) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": holds ", blob.data.size(),
                                                   " bytes, not the ", blob.width, "x", blob.height,
                                                   " grid its header names"));
  }
  const int w = static_cast<int>(blob.width), h = static_cast<int>(blob.height);
  LabeledFrame out;
  out.frame.intrinsics = KinectDefaultIntrinsics(w, h);
  out.frame.timestamp_s = 1.0;
  out.frame.depth_m = cv::Mat(h, w, CV_32FC1, cv::Scalar(0.0f));
  out.frame.color_bgr = cv::Mat(h, w, CV_8UC3, cv::Scalar::all(0));
  out.labels = cv::Mat(h, w, CV_32SC1, cv::Scalar(0));
  for (int r = 0; r < h; ++r) {
    float* depth = out.frame.depth_m.ptr<float>(r);
    cv::Vec3b* bgr = out.frame.color_bgr.ptr<cv::Vec3b>(r);
    int* labels = out.labels.ptr<int>(r);
    for (int c = 0; c < w; ++c) {
      const uint8_t* point = blob.data.data() + (size_t{static_cast<uint32_t>(r)} * blob.width +
                                                 static_cast<uint32_t>(c)) *
                                                    blob.point_step;
      float z_m = 0;
      uint32_t packed = 0;  // 0xAARRGGBB
      int32_t id = 0;
      std::memcpy(&z_m, point + z->offset, sizeof(z_m));
      std::memcpy(&packed, point + rgba->offset, sizeof(packed));
      std::memcpy(&id, point + label->offset, sizeof(id));
      depth[c] = std::isfinite(z_m) && z_m > 0 ? z_m : 0.0f;
      bgr[c] = cv::Vec3b(packed & 0xff, (packed >> 8) & 0xff, (packed >> 16) & 0xff);
      labels[c] = id;
    }
  }
  return out;
}

cv::Mat MosdTableObjectClasses(const cv::Mat& labels) {
  cv::Mat classes(labels.size(), CV_8UC1, cv::Scalar(255));
  classes.setTo(0, (labels >= 1) & (labels < 10));
  classes.setTo(1, labels >= 20);
  return classes;
}

}  // namespace lifemap::io
