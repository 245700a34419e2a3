#include "core/io/tum_dataset.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/image_codec.h"

namespace lifemap::io {
namespace {

namespace fs = std::filesystem;

struct TimedFile {
  double timestamp_s;
  std::string path;
};

// Splits non-comment lines of a whitespace-separated list into fields; line numbers for errors.
absl::StatusOr<std::vector<std::pair<int, std::vector<std::string>>>> ReadTable(
    const std::string& path) {
  std::ifstream in(path);
  if (!in) return absl::NotFoundError(absl::StrCat(path, ": cannot open"));
  std::vector<std::pair<int, std::vector<std::string>>> rows;
  std::string line;
  int number = 0;
  while (std::getline(in, line)) {
    ++number;
    if (!line.empty() && line.back() == '\r') line.pop_back();
    const auto first = line.find_first_not_of(" \t");
    if (first == std::string::npos || line[first] == '#') continue;
    std::istringstream fields(line);
    std::vector<std::string> row;
    for (std::string f; fields >> f;) row.push_back(f);
    rows.emplace_back(number, std::move(row));
  }
  return rows;
}

absl::StatusOr<double> ParseDouble(const std::string& text, const std::string& path, int line) {
  try {
    size_t used = 0;
    const double v = std::stod(text, &used);
    if (used == text.size() && std::isfinite(v)) return v;
  } catch (const std::exception&) {
  }
  return absl::InvalidArgumentError(
      absl::StrCat(path, ":", line, ": '", text, "' is not a finite number"));
}

absl::StatusOr<std::vector<TimedFile>> ReadFileList(const std::string& dir, const std::string& name,
                                                    int* missing) {
  const std::string path = (fs::path(dir) / name).string();
  auto rows = ReadTable(path);
  if (!rows.ok()) return rows.status();
  std::vector<TimedFile> files;
  for (const auto& [line, row] : *rows) {
    if (row.size() < 2) {
      return absl::InvalidArgumentError(
          absl::StrCat(path, ":", line, ": expected 'timestamp filename'"));
    }
    auto t = ParseDouble(row[0], path, line);
    if (!t.ok()) return t.status();
    const std::string file = (fs::path(dir) / row[1]).string();
    if (!fs::exists(file)) {
      ++*missing;
      continue;
    }
    files.push_back({*t, file});
  }
  std::sort(files.begin(), files.end(),
            [](const TimedFile& a, const TimedFile& b) { return a.timestamp_s < b.timestamp_s; });
  return files;
}

// TUM's associate.py: every candidate pair closer than max_dt, taken greedily by increasing
// time difference so that each image is used at most once.
std::vector<std::pair<size_t, size_t>> Associate(const std::vector<TimedFile>& rgb,
                                                 const std::vector<TimedFile>& depth,
                                                 double max_dt) {
  struct Candidate {
    double dt;
    size_t r, d;
  };
  std::vector<Candidate> candidates;
  size_t lo = 0;
  for (size_t r = 0; r < rgb.size(); ++r) {
    while (lo < depth.size() && depth[lo].timestamp_s < rgb[r].timestamp_s - max_dt) ++lo;
    for (size_t d = lo; d < depth.size() && depth[d].timestamp_s < rgb[r].timestamp_s + max_dt;
         ++d) {
      candidates.push_back({std::abs(depth[d].timestamp_s - rgb[r].timestamp_s), r, d});
    }
  }
  std::sort(candidates.begin(), candidates.end(), [](const Candidate& a, const Candidate& b) {
    return a.dt < b.dt || (a.dt == b.dt && a.r < b.r);
  });
  std::vector<bool> rgb_used(rgb.size()), depth_used(depth.size());
  std::vector<std::pair<size_t, size_t>> pairs;
  for (const auto& c : candidates) {
    if (rgb_used[c.r] || depth_used[c.d]) continue;
    rgb_used[c.r] = depth_used[c.d] = true;
    pairs.emplace_back(c.r, c.d);
  }
  std::sort(pairs.begin(), pairs.end());
  return pairs;
}

}  // namespace

absl::StatusOr<Eigen::Vector3d> TumGravityFromAccelerometer(const Eigen::Vector3d& reading) {
  if (!reading.allFinite() || reading.norm() < 1e-6) {
    return absl::InvalidArgumentError("accelerometer reading of zero length or not finite");
  }
  return Eigen::Vector3d(reading.x(), reading.y(), -reading.z()).normalized();
}

Eigen::Vector3d TumAccelerometerReading(const Eigen::Vector3d& gravity_camera) {
  const Eigen::Vector3d g = gravity_camera.normalized() * 9.81;
  return {g.x(), g.y(), -g.z()};
}

absl::StatusOr<std::vector<TimedPose>> ReadTumTrajectory(const std::string& path) {
  auto rows = ReadTable(path);
  if (!rows.ok()) return rows.status();
  std::vector<TimedPose> poses;
  poses.reserve(rows->size());
  for (const auto& [line, row] : *rows) {
    if (row.size() != 8) {
      return absl::InvalidArgumentError(
          absl::StrCat(path, ":", line,
                       ": expected 8 fields 'timestamp tx ty tz qx qy qz qw', got ", row.size()));
    }
    double v[8];
    for (int i = 0; i < 8; ++i) {
      auto parsed = ParseDouble(row[i], path, line);
      if (!parsed.ok()) return parsed.status();
      v[i] = *parsed;
    }
    auto pose = Pose::FromComponents(v[1], v[2], v[3], v[4], v[5], v[6], v[7]);
    if (!pose.ok()) {
      return absl::InvalidArgumentError(
          absl::StrCat(path, ":", line, ": ", pose.status().message()));
    }
    poses.push_back({v[0], *pose});
  }
  std::stable_sort(poses.begin(), poses.end(), [](const TimedPose& a, const TimedPose& b) {
    return a.timestamp_s < b.timestamp_s;
  });
  return poses;
}

std::optional<Pose> InterpolateTrajectory(const std::vector<TimedPose>& trajectory, double t,
                                          double max_gap_s) {
  auto after = std::lower_bound(trajectory.begin(), trajectory.end(), t,
                                [](const TimedPose& p, double v) { return p.timestamp_s < v; });
  if (after == trajectory.end()) return std::nullopt;
  if (after->timestamp_s == t) return after->pose;
  if (after == trajectory.begin()) return std::nullopt;
  const auto before = std::prev(after);
  const double gap = after->timestamp_s - before->timestamp_s;
  if (gap > max_gap_s) return std::nullopt;
  return Interpolate(before->pose, after->pose, (t - before->timestamp_s) / gap);
}

std::string FormatTumPoseLine(double timestamp_s, const Pose& pose) {
  const auto& t = pose.translation;
  const auto& q = pose.rotation;
  return absl::StrFormat("%.6f %.6f %.6f %.6f %.9f %.9f %.9f %.9f", timestamp_s, t.x(), t.y(),
                         t.z(), q.x(), q.y(), q.z(), q.w());
}

absl::StatusOr<TumSequence> ReadTumSequence(const std::string& dir, const TumReadOptions& options) {
  if (!fs::is_directory(dir)) {
    return absl::NotFoundError(absl::StrCat(dir, ": not a directory"));
  }
  TumSequence seq;
  seq.dir = dir;
  if (!options.associations_file.empty()) {
    auto rows = ReadTable(options.associations_file);
    if (!rows.ok()) return rows.status();
    for (const auto& [line, row] : *rows) {
      if (row.size() < 4) {
        return absl::InvalidArgumentError(absl::StrCat(options.associations_file, ":", line,
                                                       ": expected 't_rgb rgb t_depth depth'"));
      }
      auto tr = ParseDouble(row[0], options.associations_file, line);
      auto td = ParseDouble(row[2], options.associations_file, line);
      if (!tr.ok()) return tr.status();
      if (!td.ok()) return td.status();
      TumFrameEntry e{*tr,          (fs::path(dir) / row[1]).string(),
                      *td,          (fs::path(dir) / row[3]).string(),
                      std::nullopt, std::nullopt,
                      std::nullopt};
      if (!fs::exists(e.rgb_path) || !fs::exists(e.depth_path)) {
        ++seq.listed_but_missing;
        continue;
      }
      seq.frames.push_back(std::move(e));
    }
  } else {
    const bool have_lists =
        fs::exists(fs::path(dir) / "rgb.txt") && fs::exists(fs::path(dir) / "depth.txt");
    if (!have_lists) {
      return absl::NotFoundError(absl::StrCat(
          dir,
          ": no rgb.txt and depth.txt; a TUM folder lists its images there (or name an "
          "associations file)"));
    }
    int missing_rgb = 0, missing_depth = 0;
    auto rgb = ReadFileList(dir, "rgb.txt", &missing_rgb);
    if (!rgb.ok()) return rgb.status();
    auto depth = ReadFileList(dir, "depth.txt", &missing_depth);
    if (!depth.ok()) return depth.status();
    seq.listed_but_missing = missing_rgb + missing_depth;
    for (const auto& [r, d] : Associate(*rgb, *depth, options.max_association_dt_s)) {
      seq.frames.push_back({(*rgb)[r].timestamp_s, (*rgb)[r].path, (*depth)[d].timestamp_s,
                            (*depth)[d].path, std::nullopt, std::nullopt, std::nullopt});
    }
  }
  std::sort(
      seq.frames.begin(), seq.frames.end(),
      [](const TumFrameEntry& a, const TumFrameEntry& b) { return a.timestamp_s < b.timestamp_s; });
  if (seq.frames.empty()) {
    return absl::FailedPreconditionError(absl::StrCat(dir, ": no colour/depth pair found (",
                                                      seq.listed_but_missing,
                                                      " listed files are missing)"));
  }

  const std::string gt_path = (fs::path(dir) / "groundtruth.txt").string();
  if (fs::exists(gt_path)) {
    auto trajectory = ReadTumTrajectory(gt_path);
    if (!trajectory.ok()) return trajectory.status();
    seq.has_groundtruth = true;
    for (auto& f : seq.frames) {
      f.T_world_camera =
          InterpolateTrajectory(*trajectory, f.timestamp_s, options.max_groundtruth_gap_s);
      if (f.T_world_camera) ++seq.frames_with_pose;
    }
  }

  const std::string odometry_path = (fs::path(dir) / "odometry.txt").string();
  if (fs::exists(odometry_path)) {
    auto trajectory = ReadTumTrajectory(odometry_path);
    if (!trajectory.ok()) return trajectory.status();
    seq.has_odometry = true;
    for (auto& f : seq.frames) {
      f.T_odom_camera =
          InterpolateTrajectory(*trajectory, f.timestamp_s, options.max_groundtruth_gap_s);
      if (f.T_odom_camera) ++seq.frames_with_odometry;
    }
  }

  const std::string accel_path = (fs::path(dir) / "accelerometer.txt").string();
  if (fs::exists(accel_path)) {
    auto rows = ReadTable(accel_path);
    if (!rows.ok()) return rows.status();
    std::vector<std::pair<double, Eigen::Vector3d>> readings;
    for (const auto& [line, row] : *rows) {
      if (row.size() < 4) {
        return absl::InvalidArgumentError(
            absl::StrCat(accel_path, ":", line, ": expected 'timestamp ax ay az'"));
      }
      double v[4];
      for (int i = 0; i < 4; ++i) {
        auto parsed = ParseDouble(row[i], accel_path, line);
        if (!parsed.ok()) return parsed.status();
        v[i] = *parsed;
      }
      readings.push_back({v[0], {v[1], v[2], v[3]}});
    }
    std::sort(readings.begin(), readings.end(),
              [](const auto& a, const auto& b) { return a.first < b.first; });
    seq.has_accelerometer = true;
    const double w = options.accelerometer_window_s;
    for (auto& f : seq.frames) {
      auto it = std::lower_bound(readings.begin(), readings.end(), f.timestamp_s - w,
                                 [](const auto& r, double t) { return r.first < t; });
      Eigen::Vector3d sum = Eigen::Vector3d::Zero();
      for (; it != readings.end() && it->first <= f.timestamp_s + w; ++it) sum += it->second;
      if (auto g = TumGravityFromAccelerometer(sum); g.ok()) {
        f.gravity_camera = *g;
        ++seq.frames_with_gravity;
      }
    }
  }

  const std::string intrinsics_path = (fs::path(dir) / "intrinsics.txt").string();
  if (fs::exists(intrinsics_path)) {
    auto rows = ReadTable(intrinsics_path);
    if (!rows.ok()) return rows.status();
    if (rows->empty() || rows->front().second.size() < 4) {
      return absl::InvalidArgumentError(
          absl::StrCat(intrinsics_path, ": expected 'fx fy cx cy [width height]'"));
    }
    const auto& [line, row] = rows->front();
    CameraIntrinsics k;
    double v[6] = {0, 0, 0, 0, 0, 0};
    for (size_t i = 0; i < std::min<size_t>(row.size(), 6); ++i) {
      auto parsed = ParseDouble(row[i], intrinsics_path, line);
      if (!parsed.ok()) return parsed.status();
      v[i] = *parsed;
    }
    k.fx = v[0];
    k.fy = v[1];
    k.cx = v[2];
    k.cy = v[3];
    k.width = static_cast<int>(v[4]);
    k.height = static_cast<int>(v[5]);
    seq.intrinsics = k;
  }
  return seq;
}

CameraIntrinsics TumIntrinsicsFor(const std::string& dir, int width, int height,
                                  std::string* source) {
  CameraIntrinsics k;
  k.width = width;
  k.height = height;
  std::string lower = fs::absolute(dir).lexically_normal().string();
  std::transform(lower.begin(), lower.end(), lower.begin(), ::tolower);
  auto has = [&](const char* a, const char* b) {
    return lower.find(a) != std::string::npos || lower.find(b) != std::string::npos;
  };
  // Official TUM calibrations (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats).
  if (has("freiburg1", "fr1")) {
    k.fx = 517.3, k.fy = 516.5, k.cx = 318.6, k.cy = 255.3;
    if (source) *source = "TUM freiburg1 calibration (from the folder name)";
  } else if (has("freiburg2", "fr2")) {
    k.fx = 520.9, k.fy = 521.0, k.cx = 325.1, k.cy = 249.7;
    if (source) *source = "TUM freiburg2 calibration (from the folder name)";
  } else if (has("freiburg3", "fr3")) {
    k.fx = 535.4, k.fy = 539.2, k.cx = 320.1, k.cy = 247.6;
    if (source) *source = "TUM freiburg3 calibration (from the folder name)";
  } else {
    k.fx = 525.0, k.fy = 525.0, k.cx = 319.5, k.cy = 239.5;
    if (source) *source = "TUM ROS default (525, 525, 319.5, 239.5)";
  }
  // The calibrations are for 640x480; scale them to other sizes.
  if (width != 640 || height != 480) {
    const double sx = width / 640.0, sy = height / 480.0;
    k.fx *= sx, k.cx *= sx, k.fy *= sy, k.cy *= sy;
  }
  return k;
}

CameraIntrinsics TumSequenceIntrinsics(const TumSequence& seq, int width, int height,
                                       std::string* source) {
  if (!seq.intrinsics) return TumIntrinsicsFor(seq.dir, width, height, source);
  CameraIntrinsics k = *seq.intrinsics;
  k.width = width;
  k.height = height;
  if (source) *source = "intrinsics.txt";
  return k;
}

absl::StatusOr<RgbdFrame> DecodeTumFrame(const TumSequence& seq, const TumFrameEntry& e,
                                         bool decode_color) {
  auto depth = ReadFileBytes(e.depth_path);
  if (!depth.ok()) return depth.status();
  absl::StatusOr<std::string> color = std::string();
  if (decode_color) color = ReadFileBytes(e.rgb_path);
  if (!color.ok()) return color.status();
  // The size (and the colour's format) from the image that is decoded first.
  const std::string& sized_path = decode_color ? e.rgb_path : e.depth_path;
  auto header = ProbeImage(decode_color ? *color : *depth);
  if (!header.ok()) {
    return absl::InvalidArgumentError(absl::StrCat(sized_path, ": ", header.status().message()));
  }
  EncodedRgbdFrame encoded;
  encoded.timestamp_s = e.timestamp_s;
  encoded.intrinsics = TumSequenceIntrinsics(seq, header->width, header->height, nullptr);
  encoded.depth = {DepthEncoding::kPng16, *depth, 0, 0, 5000.0};
  encoded.color = {header->format == ImageFormat::kPng ? ColorEncoding::kPng : ColorEncoding::kJpeg,
                   *color, 0, 0};
  encoded.T_world_camera = e.T_world_camera;
  auto frame = DecodeRgbdFrame(encoded, decode_color);
  if (!frame.ok()) {
    return absl::InvalidArgumentError(absl::StrCat(sized_path, ": ", frame.status().message()));
  }
  return frame;
}

}  // namespace lifemap::io
