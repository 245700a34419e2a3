#include "server/engine/annotation_export.h"

#include <algorithm>
#include <cmath>
#include <optional>
#include <string>
#include <unordered_map>

#include <Eigen/Geometry>
#include <opencv2/imgcodecs.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "server/engine/visit_frame.h"

namespace lifemap::server {
namespace {

constexpr uint8_t kUnlabelled = 255;
constexpr double kTumDepthPerMetre = 5000.0;  // what the TUM reader takes PNG-16 depth in

bool SameCamera(const CameraIntrinsics& a, const CameraIntrinsics& b) {
  return a.width == b.width && a.height == b.height && std::abs(a.fx - b.fx) < 1e-6 &&
         std::abs(a.fy - b.fy) < 1e-6 && std::abs(a.cx - b.cx) < 1e-6 &&
         std::abs(a.cy - b.cy) < 1e-6;
}

}  // namespace

absl::Status ValidateAnnotation(const store::AnnotationRecord& a) {
  if (a.class_name.empty() || a.class_name.size() > 64) {
    return absl::InvalidArgumentError("an annotation's class must be 1-64 characters");
  }
  for (unsigned char c : a.class_name) {
    if (c < 0x20 || c == 0x7f || c == '/' || c == '\\') {
      return absl::InvalidArgumentError(
          "an annotation's class must be printable, without '/' or '\\' (it names a class of "
          "the training folder)");
    }
  }
  if (a.boxes.empty()) {
    return absl::InvalidArgumentError("an annotation needs at least one box (or voxel)");
  }
  if (a.boxes.size() > static_cast<size_t>(kMaxAnnotationBoxes)) {
    return absl::InvalidArgumentError(absl::StrCat("an annotation holds at most ",
                                                   kMaxAnnotationBoxes, " boxes; it has ",
                                                   a.boxes.size(), ": split it"));
  }
  for (size_t i = 0; i < a.boxes.size(); ++i) {
    const store::AnnotationBox& b = a.boxes[i];
    for (int d = 0; d < 3; ++d) {
      if (!std::isfinite(b.min[d]) || !std::isfinite(b.max[d]) ||
          std::abs(b.min[d]) > kMaxAnnotationExtentM ||
          std::abs(b.max[d]) > kMaxAnnotationExtentM) {
        return absl::InvalidArgumentError(
            absl::StrCat("box ", i, " has a coordinate that is not finite or beyond ",
                         kMaxAnnotationExtentM, " m of the map's origin"));
      }
      if (b.min[d] > b.max[d]) {
        return absl::InvalidArgumentError(
            absl::StrCat("box ", i, ": its min exceeds its max along ", std::string(1, "xyz"[d])));
      }
    }
  }
  return absl::OkStatus();
}

std::vector<std::string> AnnotationClasses(const std::vector<store::AnnotationRecord>& all) {
  std::vector<std::string> classes = {"background"};
  for (const auto& a : all) {
    if (std::find(classes.begin(), classes.end(), a.class_name) == classes.end()) {
      classes.push_back(a.class_name);
    }
  }
  return classes;
}

// The annotations' boxes (grown by the margin) hashed on a grid of kCellM cells, so a pixel's
// point tests only the boxes of its cell: selections are thousands of voxel-sized boxes.
// Boxes spanning more than kMaxCellsPerBox cells are tested for every point instead.
class AnnotationProjector::BoxGrid {
 public:
  static constexpr double kCellM = 0.05;
  static constexpr int64_t kMaxCellsPerBox = 4096;
  struct Box {
    Eigen::Vector3d lo, hi;
    uint8_t class_id;
    size_t order;  // lower = later annotation, which wins
  };

  void Add(const Box& box) {
    // Counted in doubles: a box is validated (within ±kMaxAnnotationExtentM) but the count
    // must not overflow whatever it holds.
    const Eigen::Vector3d cells =
        (box.hi / kCellM).array().floor() - (box.lo / kCellM).array().floor() + 1.0;
    if (!(cells.prod() <= static_cast<double>(kMaxCellsPerBox))) {
      large_.push_back(box);
      return;
    }
    const Eigen::Vector3i a = Cell(box.lo), b = Cell(box.hi);
    for (int x = a.x(); x <= b.x(); ++x) {
      for (int y = a.y(); y <= b.y(); ++y) {
        for (int z = a.z(); z <= b.z(); ++z) cells_[Key(x, y, z)].push_back(box);
      }
    }
  }
  bool empty() const { return cells_.empty() && large_.empty(); }
  // Every box's extent: a point outside it is tested against none.
  Eigen::AlignedBox3d all;

  // The class of the latest annotation holding `p`, or kUnlabelled.
  uint8_t ClassAt(const Eigen::Vector3d& p) const {
    const Box* best = nullptr;
    auto test = [&](const std::vector<Box>& boxes) {
      for (const Box& b : boxes) {
        if ((best == nullptr || b.order < best->order) && (p.array() >= b.lo.array()).all() &&
            (p.array() <= b.hi.array()).all()) {
          best = &b;
        }
      }
    };
    const Eigen::Vector3i c = Cell(p);
    if (auto it = cells_.find(Key(c.x(), c.y(), c.z())); it != cells_.end()) test(it->second);
    test(large_);
    return best == nullptr ? kUnlabelled : best->class_id;
  }

 private:
  static Eigen::Vector3i Cell(const Eigen::Vector3d& p) {
    return (p / kCellM).array().floor().cast<int>();
  }
  // Coordinates are within ±kMaxAnnotationExtentM (20,000 cells): 21 bits each.
  static uint64_t Key(int x, int y, int z) {
    auto u = [](int v) { return static_cast<uint64_t>(v + (1 << 20)) & 0x1FFFFF; };
    return (u(x) << 42) | (u(y) << 21) | u(z);
  }
  std::unordered_map<uint64_t, std::vector<Box>> cells_;
  std::vector<Box> large_;
};

AnnotationProjector::AnnotationProjector(const std::vector<store::AnnotationRecord>& annotations,
                                         const std::vector<std::string>& classes, double margin_m)
    : grid_(std::make_unique<BoxGrid>()) {
  size_t order = 0;
  for (auto a = annotations.rbegin(); a != annotations.rend(); ++a, ++order) {
    const auto found = std::find(classes.begin(), classes.end(), a->class_name);
    if (found == classes.end()) continue;
    const auto id = static_cast<uint8_t>(found - classes.begin());
    for (const auto& b : a->boxes) {
      const BoxGrid::Box box{Eigen::Vector3d(b.min[0], b.min[1], b.min[2]).array() - margin_m,
                             Eigen::Vector3d(b.max[0], b.max[1], b.max[2]).array() + margin_m, id,
                             order};
      grid_->all.extend(box.lo);
      grid_->all.extend(box.hi);
      grid_->Add(box);
    }
  }
}

AnnotationProjector::~AnnotationProjector() = default;

cv::Mat AnnotationProjector::Project(const RgbdFrame& frame, const Pose& T_map_camera,
                                     int64_t* labelled) const {
  const cv::Mat& depth = frame.depth_m;
  cv::Mat labels(depth.size(), CV_8UC1, cv::Scalar(kUnlabelled));
  int64_t count = 0;
  if (!grid_->empty()) {
    const Eigen::Isometry3d T = T_map_camera.ToIsometry();
    const CameraIntrinsics& k = frame.intrinsics;
    for (int v = 0; v < depth.rows; ++v) {
      const float* d = depth.ptr<float>(v);
      uint8_t* out = labels.ptr<uint8_t>(v);
      for (int u = 0; u < depth.cols; ++u) {
        const double z = d[u];
        if (!(z > 0)) continue;
        const Eigen::Vector3d p =
            T * Eigen::Vector3d((u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z);
        if (!grid_->all.contains(p)) continue;
        const uint8_t c = grid_->ClassAt(p);
        if (c != kUnlabelled) {
          out[u] = c;
          ++count;
        }
      }
    }
  }
  if (labelled != nullptr) *labelled = count;
  return labels;
}

cv::Mat ProjectAnnotations(const std::vector<store::AnnotationRecord>& annotations,
                           const std::vector<std::string>& classes, const RgbdFrame& frame,
                           const Pose& T_map_camera, double margin_m, int64_t* labelled) {
  return AnnotationProjector(annotations, classes, margin_m).Project(frame, T_map_camera, labelled);
}

absl::StatusOr<TrainingFolder> ExportTrainingFolder(
    store::Store* store, const store::MapRecord& map, const TrainingFolderOptions& options,
    const std::function<bool()>& cancelled,
    const std::function<absl::Status(const std::string& path, const std::string& bytes)>& write) {
  auto annotations = store->ListAnnotations(map.id);
  if (!annotations.ok()) return annotations.status();
  if (annotations->empty()) {
    return absl::FailedPreconditionError(absl::StrCat(
        "map '", map.name,
        "' has no annotation: select voxels or a box in its 3D view (lifemapd --http) and give "
        "them a class first"));
  }
  TrainingFolder out;
  out.classes = AnnotationClasses(*annotations);
  out.class_pixels.assign(out.classes.size(), 0);
  std::optional<CameraIntrinsics> camera;
  int64_t other_camera = 0;
  std::string rgb_list = "# colour images of keyframes that see annotated regions\n";
  std::string depth_list = "# depth images (PNG-16, 5000 per metre)\n";
  const AnnotationProjector projector(*annotations, out.classes, options.margin_m);
  auto walked = ForEachPosedKeyframe(
      store, map.id, map.name, 0, cancelled,
      [&](const store::KeyframeRecord& k, const RgbdFrame& frame) -> absl::Status {
        ++out.keyframes_seen;
        if (!camera) camera = frame.intrinsics;
        if (!SameCamera(*camera, frame.intrinsics)) {
          ++other_camera;
          return absl::OkStatus();
        }
        int64_t labelled = 0;
        const cv::Mat labels = projector.Project(frame, *k.T_world_camera, &labelled);
        if (labelled < options.min_labelled_pixels) return absl::OkStatus();
        for (int v = 0; v < labels.rows; ++v) {
          const uint8_t* row = labels.ptr<uint8_t>(v);
          for (int u = 0; u < labels.cols; ++u) {
            if (row[u] != kUnlabelled) ++out.class_pixels[row[u]];
          }
        }
        out.labelled_pixels += labelled;
        const std::string id = absl::StrCat(k.id);
        const bool jpeg = k.color_encoding == store::StoredColorEncoding::kJpeg;
        const std::string rgb = absl::StrCat("rgb/", id, jpeg ? ".jpg" : ".png");
        const std::string depth_path = absl::StrCat("depth/", id, ".png");
        cv::Mat depth16;
        frame.depth_m.convertTo(depth16, CV_16UC1, kTumDepthPerMetre);
        std::vector<uchar> png;
        if (!cv::imencode(".png", depth16, png)) {
          return absl::InternalError(absl::StrCat("keyframe ", k.id, ": depth PNG not encoded"));
        }
        std::vector<uchar> label_png;
        if (!cv::imencode(".png", labels, label_png)) {
          return absl::InternalError(absl::StrCat("keyframe ", k.id, ": label PNG not encoded"));
        }
        if (auto s = write(rgb, k.color); !s.ok()) return s;
        if (auto s = write(depth_path, std::string(png.begin(), png.end())); !s.ok()) return s;
        if (auto s = write(absl::StrCat("labels/", id, ".png"),
                           std::string(label_png.begin(), label_png.end()));
            !s.ok()) {
          return s;
        }
        // One second apart: the reader pairs colour and depth by time, and keyframes of
        // different visits may share a timestamp.
        const double t = static_cast<double>(out.views_written + 1);
        absl::StrAppendFormat(&rgb_list, "%.6f %s\n", t, rgb);
        absl::StrAppendFormat(&depth_list, "%.6f %s\n", t, depth_path);
        ++out.views_written;
        return absl::OkStatus();
      });
  if (!walked.ok()) return walked.status();
  out.left_out = walked->left_out;
  if (other_camera > 0) {
    out.left_out.push_back(absl::StrCat(other_camera,
                                        " keyframes of another camera (a folder holds one "
                                        "camera's views)"));
  }
  if (out.views_written == 0) {
    return absl::FailedPreconditionError(
        absl::StrCat("no keyframe of map '", map.name, "' sees ", options.min_labelled_pixels,
                     " pixels or more of its ", annotations->size(),
                     " annotations (are they where the map's surfaces are?)"));
  }
  std::string classes;
  for (const auto& c : out.classes) absl::StrAppend(&classes, c, "\n");
  if (auto s = write("labels/classes.txt", classes); !s.ok()) return s;
  if (auto s = write("rgb.txt", rgb_list); !s.ok()) return s;
  if (auto s = write("depth.txt", depth_list); !s.ok()) return s;
  if (auto s = write("intrinsics.txt", absl::StrFormat("%.6f %.6f %.6f %.6f\n", camera->fx,
                                                       camera->fy, camera->cx, camera->cy));
      !s.ok()) {
    return s;
  }
  return out;
}

}  // namespace lifemap::server
