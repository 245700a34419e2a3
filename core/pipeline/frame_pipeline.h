// FramePipeline composes the core modules for one frame: decode and validate, depth statistics,
// entropy masks (paper 000) and random-forest class labels (paper 002), the two concurrently.
// Place matches plug in here as they are built.
#pragma once

#include <optional>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "absl/status/statusor.h"
#include "core/common/rgbd_frame.h"
#include "core/entropy/entropy_mask.h"
#include "core/forest/forest.h"

namespace lifemap::pipeline {

struct PipelineOptions {
  // Frames larger are refused; depth readings outside the range are no reading.
  FrameLimits frame_limits;
  bool entropy_masks = true;
  entropy::EntropyMaskOptions entropy;
  // "Up" (against gravity) in the world frame of client poses; TUM's mocap frame is z-up.
  Eigen::Vector3f world_up = Eigen::Vector3f::UnitZ();
  // Class labels: every label_stride-th pixel is classified and its cell copies the result.
  int label_stride = 4;
  forest::Decision label_decision = forest::Decision::kBalanced;

  absl::Status Validate() const;
};

// Per-frame settings a request may override.
struct FrameRequest {
  // [0, 1]; the caller validates it (out of range, the masks are not computed and
  // entropy_status says why).
  std::optional<float> entropy_threshold;
  // The model that labels this frame (the caller keeps it alive during Process); null = no
  // labels (the caller knows why).
  const forest::Forest* labeller = nullptr;
  // False: no entropy mask for this frame (the client skipped it); entropy_status says so.
  bool entropy_masks = true;
};
// Why an output a client skipped is absent (entropy_status here; the server's output statuses).
inline constexpr char kNotRequested[] = "not requested (FrameOptions.skip_outputs)";

// A frame's class labels and what the server reports of them. The per-class probabilities
// are kept for 3D semantic fusion, which accumulates them per voxel.
struct FrameLabels {
  cv::Mat labels;      // CV_8UC1 class id; forest::kIgnore where there is no depth reading
  cv::Mat confidence;  // CV_8UC1, the winning class's probability × 255 (0 without depth)
  std::vector<cv::Mat> probabilities;         // CV_32FC1 per class, as the forest predicted them
  std::vector<int64_t> class_pixels;          // labelled pixels per class
  std::vector<double> class_mean_confidence;  // mean winning probability per class
  int64_t labelled_pixels = 0;
  double mean_confidence = 0.0;
  int stride = 1;
};

struct FrameAnalysis {
  RgbdFrame frame;  // decoded images
  DepthStats depth_stats;
  // Set when entropy masks are enabled and could be computed; otherwise entropy_status says why.
  std::optional<entropy::EntropyMaskResult> entropy;
  absl::Status entropy_status;
  // Set when the request had a labeller and the frame could be labelled.
  std::optional<FrameLabels> labels;
  absl::Status labels_status;  // why labelling failed, when the request had a labeller
  double decode_ms = 0.0;
  double process_ms = 0.0;  // everything after decoding
};

// Thread-safe: one instance serves every stream.
class FramePipeline {
 public:
  explicit FramePipeline(PipelineOptions options = {}) : options_(std::move(options)) {}

  // InvalidArgument (from decoding/validation) for a frame that cannot be used. A frame that
  // decodes but has, say, no depth at all is analysed as far as possible: entropy_status says
  // why the masks are missing.
  absl::StatusOr<FrameAnalysis> Process(const EncodedRgbdFrame& in,
                                        const FrameRequest& request = {}) const;

  // Computes the entropy mask of an analysed frame that has none yet because its request
  // skipped it (a keyframe still prunes its features by it). Sets analysis->entropy or
  // entropy_status, as Process does; nothing when masks are disabled in the options.
  void ComputeEntropy(FrameAnalysis* analysis, const FrameRequest& request) const;

  const PipelineOptions& options() const { return options_; }

 private:
  PipelineOptions options_;
};

// The unit up direction in the camera frame: from T_world_camera when known, else against the
// frame's gravity (an IMU's), else the image's up (-y).
Eigen::Vector3f UpInCamera(const std::optional<Pose>& T_world_camera,
                           const Eigen::Vector3f& world_up,
                           const std::optional<Eigen::Vector3d>& gravity_camera = std::nullopt);

}  // namespace lifemap::pipeline
