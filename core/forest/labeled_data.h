// Readers for labelled RGB-D data the forest trains and is evaluated on: folders of organized
// mOSD point clouds, lifemap's synthetic visits, and TUM-format folders with label PNGs.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/types.h"
#include "core/forest/forest.h"

namespace lifemap::forest {

// How a synthetic visit's 18 surface classes are presented to the forest.
enum class SimClasses {
  kGrouped,  // structure (floor, wall, ceiling, door, window, stairs) = background,
             // furniture (table, shelf, cabinet, bed, sofa, chair), prop (movable objects),
             // person
  kAll,      // every class of core/sim (floor = class 0 = background)
};

struct LabeledDataOptions {
  int frame_stride = 10;  // TUM-format folders: every N-th frame
  SimClasses sim_classes = SimClasses::kGrouped;
};

// Where an image was taken, for evaluations that fuse views (one per image, same order).
struct LabeledView {
  size_t source = 0;            // index into LabeledDataset::sources
  double timestamp_s = 0.0;     // TUM-format folders; 0 for mOSD
  CameraIntrinsics intrinsics;  // the folder's intrinsics.txt or calibration; Kinect's for mOSD
  std::optional<Pose> T_world_camera;  // ground truth where the folder has it
};

struct LabeledDataset {
  std::vector<LabeledImage> images;
  std::vector<LabeledView> views;        // parallel to images
  std::vector<std::string> class_names;  // class 0 is the background
  std::vector<uint32_t> class_colors;    // 0xRRGGBB per class
  std::string kind;                      // "mosd", "sim" or "label-png"
  std::vector<std::string> sources;      // the folders read
};

// Reads every folder in `dirs`; each is one of:
//  - a folder of mOSD .pcd files: classes table (background) and object;
//  - a synthetic visit (`lifemap sim`: scene.json and labels/class/): see SimClasses;
//  - a TUM-format folder (rgb.txt, depth.txt; depth PNG-16 at 5000 per metre) with
//    labels/NAME.png (8-bit class id per pixel, NAME the colour image's name, 255 = unlabelled)
//    and labels/classes.txt naming one class per line (line 1 = class 0 = background).
// Every folder must carry the same classes. NotFound: a folder, image or label is missing;
// InvalidArgument: a label beyond the named classes, sizes that do not agree, or folders of
// different classes; the message names the file.
absl::StatusOr<LabeledDataset> ReadLabeledData(const std::vector<std::string>& dirs,
                                               const LabeledDataOptions& options = {});

}  // namespace lifemap::forest
