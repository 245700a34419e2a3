#include "core/forest/labeled_data.h"

#include <algorithm>
#include <filesystem>
#include <fstream>

#include <opencv2/imgcodecs.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/strip.h"
#include "core/io/labeled_pcd.h"
#include "core/io/tum_dataset.h"
#include "core/sim/world.h"

namespace lifemap::forest {
namespace {

namespace fs = std::filesystem;
using sim::SemanticClass;

// TUM-format depth: 16-bit PNG, 5000 units per metre (TUM and lifemap sim).
constexpr double kTumDepthScale = 5000.0;

// A folder's classes and a lookup from its label values to class ids (kIgnore = unlabelled).
struct ClassScheme {
  std::vector<std::string> names;
  std::vector<uint32_t> colors;
  cv::Mat lut;    // 1x256 CV_8UC1: label value -> class id or kIgnore
  cv::Mat known;  // 1x256 CV_8UC1: 255 for values that may appear (classes, "unlabelled")

  void Allow(int value, uint8_t class_id) {
    lut.at<uint8_t>(value) = class_id;
    known.at<uint8_t>(value) = 255;
  }
  void Reset() {
    lut = cv::Mat(1, 256, CV_8UC1, cv::Scalar(kIgnore));
    known = cv::Mat(1, 256, CV_8UC1, cv::Scalar(0));
    known.at<uint8_t>(kIgnore) = 255;
  }
};

ClassScheme SimScheme(SimClasses mode) {
  ClassScheme s;
  s.Reset();
  s.Allow(static_cast<int>(SemanticClass::kNone), kIgnore);  // no surface
  if (mode == SimClasses::kAll) {
    for (int id = 1; id < sim::kClassCount; ++id) {
      s.names.push_back(sim::ClassName(static_cast<SemanticClass>(id)));
      s.colors.push_back(DefaultClassColor(id - 1));
      s.Allow(id, static_cast<uint8_t>(id - 1));
    }
    return s;
  }
  s.names = {"structure", "furniture", "prop", "person"};
  s.colors = {0x808080, 0x4363D8, 0xF58231, 0xE6194B};
  auto group = [&](std::initializer_list<SemanticClass> classes, uint8_t g) {
    for (SemanticClass c : classes) s.Allow(static_cast<int>(c), g);
  };
  group({SemanticClass::kFloor, SemanticClass::kWall, SemanticClass::kCeiling, SemanticClass::kDoor,
         SemanticClass::kWindow, SemanticClass::kStairs},
        0);
  group({SemanticClass::kTable, SemanticClass::kShelf, SemanticClass::kCabinet, SemanticClass::kBed,
         SemanticClass::kSofa, SemanticClass::kChair, SemanticClass::kLamp},
        1);
  group({SemanticClass::kBox, SemanticClass::kCylinder, SemanticClass::kBook, SemanticClass::kMug,
         SemanticClass::kClutter, SemanticClass::kPlant, SemanticClass::kBag,
         SemanticClass::kClothes, SemanticClass::kBall, SemanticClass::kBottle},
        2);
  group({SemanticClass::kPerson}, 3);
  return s;
}

absl::StatusOr<ClassScheme> ReadClassesTxt(const fs::path& path) {
  std::ifstream in(path);
  if (!in) {
    return absl::NotFoundError(absl::StrCat(
        path.string(), " is missing: name one class per line (line 1 = class 0 = background)"));
  }
  ClassScheme s;
  std::string line;
  while (std::getline(in, line)) {
    const std::string name(absl::StripAsciiWhitespace(line));
    if (name.empty() || name[0] == '#') continue;
    s.names.push_back(name);
  }
  if (s.names.size() < 2 || s.names.size() > 254) {
    return absl::InvalidArgumentError(
        absl::StrCat(path.string(), " names ", s.names.size(), " classes; a model needs 2 to 254"));
  }
  s.Reset();
  for (size_t c = 0; c < s.names.size(); ++c) {
    s.Allow(static_cast<int>(c), static_cast<uint8_t>(c));
    s.colors.push_back(DefaultClassColor(static_cast<int>(c)));
  }
  return s;
}

absl::Status ReadMosdFolder(const fs::path& dir, LabeledDataset* out) {
  std::vector<std::string> files;
  for (const auto& e : fs::directory_iterator(dir)) {
    if (e.path().extension() == ".pcd") files.push_back(e.path().string());
  }
  std::sort(files.begin(), files.end());
  for (const auto& f : files) {
    auto frame = io::ReadLabeledPcd(f);
    if (!frame.ok()) return frame.status();
    LabeledImage im;
    im.depth_m = frame->frame.depth_m;
    im.color_bgr = frame->frame.color_bgr;
    im.labels = io::MosdTableObjectClasses(frame->labels);
    LabeledView view;
    view.intrinsics = io::KinectDefaultIntrinsics(im.depth_m.cols, im.depth_m.rows);
    out->views.push_back(view);
    out->images.push_back(std::move(im));
  }
  return absl::OkStatus();
}

// A TUM-format folder whose label PNGs live in `label_dir`, named like the colour images.
// A PNG file's image as it is stored (any depth and channels); empty when the file is missing,
// unreadable or not a PNG. cv::imread would decode whatever format the bytes are (JPEG 2000,
// TIFF, ...): labels are PNG only, so only the PNG decoder sees them.
cv::Mat ReadPng(const fs::path& path) {
  static constexpr char kSignature[] = "\x89PNG\r\n\x1a\n";
  std::ifstream in(path, std::ios::binary);
  const std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  if (bytes.compare(0, sizeof(kSignature) - 1, kSignature) != 0) return cv::Mat();
  return cv::imdecode(
      cv::Mat(1, static_cast<int>(bytes.size()), CV_8UC1, const_cast<char*>(bytes.data())),
      cv::IMREAD_UNCHANGED);
}

absl::Status ReadTumLabelled(const fs::path& dir, const fs::path& label_dir,
                             const ClassScheme& scheme, int frame_stride, LabeledDataset* out) {
  auto seq = io::ReadTumSequence(dir.string());
  if (!seq.ok()) return seq.status();
  for (size_t i = 0; i < seq->frames.size(); i += static_cast<size_t>(frame_stride)) {
    const auto& e = seq->frames[i];
    const fs::path label_path =
        label_dir / fs::path(e.rgb_path).filename().replace_extension(".png");
    LabeledImage im;
    const cv::Mat depth = cv::imread(e.depth_path, cv::IMREAD_ANYDEPTH);
    im.color_bgr = cv::imread(e.rgb_path, cv::IMREAD_COLOR);
    const cv::Mat raw = ReadPng(label_path);
    if (depth.empty() || depth.type() != CV_16UC1) {
      return absl::InvalidArgumentError(
          absl::StrCat(e.depth_path, ": not a 16-bit depth PNG (TUM: 5000 units per metre)"));
    }
    if (im.color_bgr.empty()) return absl::NotFoundError(absl::StrCat(e.rgb_path, ": unreadable"));
    if (raw.empty() && fs::exists(label_path)) {
      return absl::InvalidArgumentError(
          absl::StrCat(label_path.string(), ": not a readable PNG (labels are 8-bit PNGs)"));
    }
    if (raw.empty()) {
      return absl::NotFoundError(
          absl::StrCat(label_path.string(), ": no label image for ", e.rgb_path,
                       " (8-bit PNG named like the colour image, class id per pixel)"));
    }
    if (raw.type() != CV_8UC1) {
      return absl::InvalidArgumentError(
          absl::StrCat(label_path.string(), ": labels must be an 8-bit single-channel PNG"));
    }
    if (raw.size() != depth.size() || raw.size() != im.color_bgr.size()) {
      return absl::InvalidArgumentError(
          absl::StrCat(label_path.string(), ": size differs from its colour/depth images"));
    }
    cv::LUT(raw, scheme.lut, im.labels);
    // A value that is neither a class nor "unlabelled" is a labelling error: say where.
    cv::Mat known;
    cv::LUT(raw, scheme.known, known);
    if (cv::countNonZero(known) != known.rows * known.cols) {
      cv::Point where;
      cv::minMaxLoc(known, nullptr, nullptr, &where, nullptr);
      return absl::InvalidArgumentError(absl::StrCat(
          label_path.string(), ": label ", raw.at<uint8_t>(where), " at (", where.x, ", ", where.y,
          ") is not one of the ", scheme.names.size(), " classes named (255 = unlabelled)"));
    }
    depth.convertTo(im.depth_m, CV_32FC1, 1.0 / kTumDepthScale);
    LabeledView view;
    view.timestamp_s = e.timestamp_s;
    std::string source;
    view.intrinsics = io::TumSequenceIntrinsics(*seq, depth.cols, depth.rows, &source);
    view.T_world_camera = e.T_world_camera;
    out->views.push_back(view);
    out->images.push_back(std::move(im));
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<LabeledDataset> ReadLabeledData(const std::vector<std::string>& dirs,
                                               const LabeledDataOptions& options) {
  if (options.frame_stride < 1) {
    return absl::InvalidArgumentError("frame_stride must be at least 1");
  }
  LabeledDataset data;
  for (const auto& d : dirs) {
    const fs::path dir(d);
    if (!fs::is_directory(dir)) return absl::NotFoundError(absl::StrCat(d, ": not a directory"));
    ClassScheme scheme;
    absl::Status read;
    LabeledDataset part;
    if (fs::exists(dir / "labels" / "class") && fs::exists(dir / "scene.json")) {
      part.kind = "sim";
      scheme = SimScheme(options.sim_classes);
      read = ReadTumLabelled(dir, dir / "labels" / "class", scheme, options.frame_stride, &part);
    } else if (fs::exists(dir / "labels" / "classes.txt")) {
      part.kind = "label-png";
      auto s = ReadClassesTxt(dir / "labels" / "classes.txt");
      if (!s.ok()) return s.status();
      scheme = *std::move(s);
      read = ReadTumLabelled(dir, dir / "labels", scheme, options.frame_stride, &part);
    } else {
      part.kind = "mosd";
      scheme.names = {"table", "object"};
      scheme.colors = {0x808080, 0xE6194B};
      read = ReadMosdFolder(dir, &part);
    }
    if (!read.ok()) return read;
    if (part.images.empty()) {
      return absl::NotFoundError(absl::StrCat(
          d,
          ": no labelled images (expected mOSD .pcd files, a lifemap sim visit, or a TUM "
          "folder with labels/classes.txt and label PNGs)"));
    }
    if (data.class_names.empty()) {
      data.class_names = scheme.names;
      data.class_colors = scheme.colors;
      data.kind = part.kind;
    } else if (data.class_names != scheme.names) {
      return absl::InvalidArgumentError(absl::StrCat(
          d, " has classes [", absl::StrJoin(scheme.names, ", "), "] but ", data.sources.front(),
          " has [", absl::StrJoin(data.class_names, ", "), "]: read folders of the same classes"));
    }
    for (auto& im : part.images) data.images.push_back(std::move(im));
    for (LabeledView& v : part.views) {
      v.source = data.sources.size();
      data.views.push_back(v);
    }
    data.sources.push_back(d);
  }
  if (data.images.empty()) return absl::InvalidArgumentError("no folders given");
  return data;
}

}  // namespace lifemap::forest
