#include "core/sim/writer.h"

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <random>

#include <nlohmann/json.hpp>
#include <opencv2/core/utility.hpp>
#include <opencv2/imgcodecs.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/io/tum_dataset.h"

namespace lifemap::sim {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

const char* OpeningName(OpeningType t) { return t == OpeningType::kDoor ? "door" : "window"; }

const char* ShapeName(Solid::Shape shape) {
  switch (shape) {
    case Solid::Shape::kBox:
      return "box";
    case Solid::Shape::kCylinder:
      return "cylinder";
    case Solid::Shape::kBlob:
      return "blob";
    case Solid::Shape::kLathe:
      return "lathe";
  }
  return "unknown";
}

json SceneJson(const Place& place, const Visit& visit, const WriteOptions& options) {
  json walls = json::array();
  const size_t n = place.footprint.size();
  for (size_t i = 0; i < n; ++i) {
    const auto& a = place.footprint[i];
    const auto& b = place.footprint[(i + 1) % n];
    walls.push_back({{"index", i},
                     {"start", {a.x(), a.y()}},
                     {"end", {b.x(), b.y()}},
                     {"length_m", (b - a).norm()}});
  }
  json openings = json::array();
  for (const auto& o : visit.openings) {
    openings.push_back({{"type", OpeningName(o.type)},
                        {"room", o.room},
                        {"connects", o.connects},
                        {"wall", o.wall},
                        {"offset_m", o.offset_m},
                        {"width_m", o.width_m},
                        {"sill_m", o.sill_m},
                        {"top_m", o.top_m},
                        {"open", o.open}});
  }
  json rooms = json::array();
  for (int r = 0; r <= static_cast<int>(place.adjoining_rooms.size()); ++r) {
    const auto& footprint = RoomFootprint(place, r);
    json corners = json::array(), room_walls = json::array();
    for (size_t i = 0; i < footprint.size(); ++i) {
      const auto& a = footprint[i];
      const auto& b = footprint[(i + 1) % footprint.size()];
      corners.push_back({a.x(), a.y()});
      room_walls.push_back({{"index", i},
                            {"start", {a.x(), a.y()}},
                            {"end", {b.x(), b.y()}},
                            {"length_m", (b - a).norm()}});
    }
    rooms.push_back({{"room", r}, {"footprint", corners}, {"walls", room_walls}});
  }
  json objects = json::array();
  for (const auto& s : visit.solids) {
    if (s.cls == SemanticClass::kStairs) continue;  // described under floor_plan.stairs
    objects.push_back({{"instance", s.instance},
                       {"class", ClassName(s.cls)},
                       {"class_id", static_cast<int>(s.cls)},
                       {"shape", ShapeName(s.shape)},
                       {"group", s.group},
                       {"center", {s.center.x(), s.center.y(), s.base_z}},
                       {"yaw_rad", s.yaw},
                       {"size_m", {s.size.x(), s.size.y(), s.size.z()}},
                       {"movable", s.movable}});
  }
  json stairs = json::array();
  for (const auto& st : place.stairs) {
    const Eigen::Vector2d dir(std::cos(st.yaw), std::sin(st.yaw));
    const Eigen::Vector2d centre = st.origin + dir * (st.run_m * st.steps / 2);
    const double nearest_wall = DistanceToEdges(place.footprint, centre);
    stairs.push_back({{"type", st.up ? "up" : "down"},
                      {"origin", {st.origin.x(), st.origin.y()}},
                      {"yaw_rad", st.yaw},
                      {"steps", st.steps},
                      {"rise_m", st.rise_m},
                      {"run_m", st.run_m},
                      {"width_m", st.width_m},
                      {"length_m", st.run_m * st.steps},
                      {"height_m", st.rise_m * st.steps},
                      {"centre_distance_to_nearest_wall_m", nearest_wall}});
  }
  json people = json::array();
  for (const auto& w : visit.walkers) {
    people.push_back({{"instance", w.body.instance},
                      {"class", ClassName(w.body.cls)},
                      {"from", {w.from.x(), w.from.y()}},
                      {"to", {w.to.x(), w.to.y()}},
                      {"height_m", w.body.size.z()},
                      {"diameter_m", w.body.size.x()}});
  }
  json changes = json::array();
  for (const auto& c : visit.changes) {
    changes.push_back({{"kind", c.kind}, {"instance", c.instance}, {"detail", c.detail}});
  }
  json classes = json::object();
  for (int c = 0; c < kClassCount; ++c)
    classes[std::to_string(c)] = ClassName(static_cast<SemanticClass>(c));
  const auto& k = options.intrinsics;
  return {
      {"place_id", place.id},
      {"shape", place.shape},
      {"world",
       {{"curved_props", place.style.curved_props}, {"building_seed", place.style.building_seed}}},
      {"visit", visit.index},
      {"months_since_first", visit.months_since_first},
      {"start_time_s", visit.start_time_s},
      {"frame", "world z up, metres, floor at z = 0; poses T_world_camera (TUM)"},
      {"floor_plan",
       {{"footprint",
         [&] {
           json f = json::array();
           for (const auto& p : place.footprint) f.push_back({p.x(), p.y()});
           return f;
         }()},
        {"wall_height_m", place.wall_height_m},
        {"rooms", rooms},
        {"walls", walls},
        {"openings", openings},
        {"stairs", stairs}}},
      {"objects", objects},
      {"people", people},
      {"changes", changes},
      {"lighting",
       {{"brightness", visit.lighting.brightness},
        {"tint", {visit.lighting.tint.x(), visit.lighting.tint.y(), visit.lighting.tint.z()}},
        {"lamp_on", visit.lighting.lamp_on},
        {"lamp", {visit.lighting.lamp.x(), visit.lighting.lamp.y(), visit.lighting.lamp.z()}}}},
      {"intrinsics",
       {{"fx", k.fx},
        {"fy", k.fy},
        {"cx", k.cx},
        {"cy", k.cy},
        {"width", k.width},
        {"height", k.height}}},
      {"depth_scale", 5000},
      {"classes", classes}};
}

absl::Status Write(const fs::path& path, const cv::Mat& image) {
  if (!cv::imwrite(path.string(), image)) {
    return absl::PermissionDeniedError(absl::StrCat("cannot write ", path.string()));
  }
  return absl::OkStatus();
}

}  // namespace

std::vector<TimedCameraPose> SimulateWheelOdometry(const std::vector<TimedCameraPose>& trajectory,
                                                   const WheelOdometryNoise& noise, uint64_t seed) {
  std::vector<TimedCameraPose> out;
  if (trajectory.empty()) return out;
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> unit(0.0, 1.0);
  const double scale = 1.0 + noise.scale_sigma * unit(rng);
  const double turn_scale = 1.0 + noise.scale_sigma * unit(rng);
  const double yaw_bias = noise.yaw_bias_deg_per_m_sigma * unit(rng) * M_PI / 180.0;
  // The base under the camera: its position on the floor and the heading of the camera's
  // forward; the camera's pose relative to its base (height, pitch, roll) is read exactly.
  struct Base {
    Eigen::Vector2d xy;
    double yaw;
  };
  auto base_of = [](const Pose& T_world_camera) {
    const Eigen::Vector3d forward = T_world_camera.rotation * Eigen::Vector3d::UnitZ();
    return Base{T_world_camera.translation.head<2>(), std::atan2(forward.y(), forward.x())};
  };
  auto isometry_of = [](const Base& b) {
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.linear() = Eigen::AngleAxisd(b.yaw, Eigen::Vector3d::UnitZ()).toRotationMatrix();
    T.translation() << b.xy, 0.0;
    return T;
  };
  Base odom = base_of(trajectory.front().T_world_camera);
  Base previous_truth = odom;
  for (const TimedCameraPose& tp : trajectory) {
    const Base truth = base_of(tp.T_world_camera);
    // The true step in the previous base's frame, as the wheels measure it, with its errors.
    const Eigen::Rotation2Dd to_previous(-previous_truth.yaw);
    const Eigen::Vector2d step = to_previous * (truth.xy - previous_truth.xy);
    const double turn = std::remainder(truth.yaw - previous_truth.yaw, 2 * M_PI);
    const double length = step.norm();
    const Eigen::Vector2d measured =
        step * scale + noise.step_noise * length * Eigen::Vector2d(unit(rng), unit(rng));
    const double measured_turn =
        turn * turn_scale + yaw_bias * length +
        noise.turn_noise_deg * M_PI / 180.0 * unit(rng) * (length > 0 || turn != 0 ? 1.0 : 0.0);
    odom.xy += Eigen::Rotation2Dd(odom.yaw) * measured;
    odom.yaw += measured_turn;
    previous_truth = truth;
    const Eigen::Isometry3d T_base_camera =
        isometry_of(truth).inverse() * tp.T_world_camera.ToIsometry();
    out.push_back({tp.timestamp_s, Pose::FromIsometry(isometry_of(odom) * T_base_camera)});
  }
  return out;
}

absl::StatusOr<WriteSummary> WriteVisit(const std::string& dir, const Place& place,
                                        const Visit& visit, const Visit* previous,
                                        const WriteOptions& options) {
  if (auto s = options.intrinsics.Validate(); !s.ok()) return s;
  const fs::path root(dir);
  std::error_code ec;
  for (const char* sub : {"rgb", "depth", "labels/class", "labels/instance", "moved"}) {
    fs::create_directories(root / sub, ec);
    if (ec)
      return absl::PermissionDeniedError(absl::StrCat("cannot create ", (root / sub).string()));
  }
  Place seen = place;
  seen.openings = visit.openings;
  Place before = place;
  if (previous) before.openings = previous->openings;

  std::ofstream rgb_list(root / "rgb.txt"), depth_list(root / "depth.txt"),
      associations(root / "associations.txt"), groundtruth(root / "groundtruth.txt"),
      accelerometer(root / "accelerometer.txt"), odometry(root / "odometry.txt");
  rgb_list << "# color images\n# timestamp filename\n";
  depth_list << "# depth maps\n# timestamp filename\n";
  groundtruth << "# ground truth trajectory (exact)\n# timestamp tx ty tz qx qy qz qw\n";
  // A still IMU's reading per frame, in the TUM Kinect's convention (io::TumAccelerometerReading),
  // with 0.05 m/s^2 of noise per axis (about 0.3 degrees of tilt).
  accelerometer
      << "# accelerometer data (simulated, TUM Kinect convention)\n# timestamp ax ay az\n";
  std::mt19937_64 imu_noise(options.seed * 7919ULL + visit.index);
  odometry << "# wheel odometry (simulated: ~1-2 % drift of the distance, a yaw bias), "
              "T_odom_camera\n# timestamp tx ty tz qx qy qz qw\n";
  const std::vector<TimedCameraPose> wheel = SimulateWheelOdometry(
      visit.trajectory, options.odometry, options.seed * 104729ULL + visit.index);
  std::normal_distribution<double> imu_sigma(0.0, 0.05);
  const auto& k = options.intrinsics;
  std::ofstream(root / "intrinsics.txt")
      << absl::StrFormat("%.6f %.6f %.6f %.6f %d %d\n", k.fx, k.fy, k.cx, k.cy, k.width, k.height);
  if (previous) {
    fs::create_directories(root / "previous_depth", ec);
    if (ec) {
      return absl::PermissionDeniedError(
          absl::StrCat("cannot create ", (root / "previous_depth").string()));
    }
  }
  // Frames are rendered on every core: each frame's noise comes from its own seed, so the
  // images are the same whatever the order (rendering is ~95 % of a suite's time).
  struct FrameOutcome {
    absl::Status status;
    double valid_depth = 0.0;  // fraction of pixels with a depth
    double moved = 0.0;        // fraction of pixels changed since the previous visit
  };
  const size_t frames = visit.trajectory.size();
  std::vector<FrameOutcome> outcomes(frames);
  cv::parallel_for_(cv::Range(0, static_cast<int>(frames)), [&](const cv::Range& range) {
    for (int f = range.start; f < range.end; ++f) {
      outcomes[f] = [&]() -> FrameOutcome {
        const auto& tp = visit.trajectory[f];
        const uint64_t frame_seed = options.seed * 1000003ULL + visit.index * 100003ULL + f;
        RenderedFrame frame = Render(seen, visit.SolidsAt(f), visit.lighting, k, tp.T_world_camera,
                                     options.sensor, frame_seed);
        cv::Mat moved(k.height, k.width, CV_8UC1, cv::Scalar(0));
        cv::Mat previous_depth;
        if (previous) {
          // What this pose showed on the previous visit: exactly (changed pixels differ in
          // what surface they show or where it is), and as the sensor saw it
          // (previous_depth/, the aligned depth map that eq. 3 of paper 000 compares against).
          const RenderedFrame then = Render(
              before, previous->SolidsAt(std::min<size_t>(f, previous->trajectory.size() - 1)),
              previous->lighting, k, tp.T_world_camera, options.sensor, frame_seed ^ 0x5bd1e995U);
          previous_depth = then.depth_m;
          for (int r = 0; r < k.height; ++r) {
            const uint16_t* a = frame.instance_id.ptr<uint16_t>(r);
            const uint16_t* b = then.instance_id.ptr<uint16_t>(r);
            const uint8_t* ca = frame.class_id.ptr<uint8_t>(r);
            const uint8_t* cb = then.class_id.ptr<uint8_t>(r);
            const float* za = frame.true_depth_m.ptr<float>(r);
            const float* zb = then.true_depth_m.ptr<float>(r);
            uint8_t* m = moved.ptr<uint8_t>(r);
            for (int c = 0; c < k.width; ++c) {
              if (a[c] != b[c] || ca[c] != cb[c] || std::abs(za[c] - zb[c]) > 0.02f) m[c] = 255;
            }
          }
        }
        const std::string name = absl::StrFormat("%.6f", tp.timestamp_s) + ".png";
        cv::Mat depth16;
        frame.depth_m.convertTo(depth16, CV_16UC1, 5000.0);
        if (previous) {
          cv::Mat previous16;
          previous_depth.convertTo(previous16, CV_16UC1, 5000.0);
          if (auto s = Write(root / "previous_depth" / name, previous16); !s.ok()) return {s};
        }
        for (auto s :
             {Write(root / "rgb" / name, frame.color_bgr), Write(root / "depth" / name, depth16),
              Write(root / "labels/class" / name, frame.class_id),
              Write(root / "labels/instance" / name, frame.instance_id),
              Write(root / "moved" / name, moved)}) {
          if (!s.ok()) return {s};
        }
        const double pixels = static_cast<double>(k.width) * k.height;
        return {absl::OkStatus(), cv::countNonZero(frame.depth_m > 0) / pixels,
                cv::countNonZero(moved) / pixels};
      }();
    }
  });
  WriteSummary summary;
  for (size_t f = 0; f < frames; ++f) {
    if (!outcomes[f].status.ok()) return outcomes[f].status;
    const auto& tp = visit.trajectory[f];
    const std::string stamp = absl::StrFormat("%.6f", tp.timestamp_s);
    const std::string name = stamp + ".png";
    rgb_list << stamp << " rgb/" << name << "\n";
    depth_list << stamp << " depth/" << name << "\n";
    associations << stamp << " rgb/" << name << " " << stamp << " depth/" << name << "\n";
    groundtruth << io::FormatTumPoseLine(tp.timestamp_s, tp.T_world_camera) << "\n";
    // The world is z up: gravity is -z.
    Eigen::Vector3d a = io::TumAccelerometerReading(tp.T_world_camera.rotation.inverse() *
                                                    -Eigen::Vector3d::UnitZ());
    for (int i = 0; i < 3; ++i) a[i] += imu_sigma(imu_noise);
    accelerometer << absl::StrFormat("%s %.6f %.6f %.6f\n", stamp, a.x(), a.y(), a.z());
    odometry << io::FormatTumPoseLine(tp.timestamp_s, wheel[f].T_world_camera) << "\n";
    summary.mean_valid_depth += outcomes[f].valid_depth;
    summary.mean_moved += outcomes[f].moved;
    ++summary.frames;
  }
  if (summary.frames > 0) {
    summary.mean_valid_depth /= summary.frames;
    summary.mean_moved /= summary.frames;
  }
  std::ofstream(root / "scene.json") << SceneJson(seen, visit, options).dump(2) << "\n";
  if (!rgb_list || !groundtruth || !accelerometer || !odometry) {
    return absl::DataLossError(absl::StrCat("writing the lists in ", dir, " failed"));
  }
  return summary;
}

}  // namespace lifemap::sim
