// FramePipeline composes the core modules for one frame: decode and validate, depth statistics,
// entropy masks (paper 000). Class labels and place matches plug in here as they are built.
#pragma once

#include <optional>

#include <Eigen/Core>

#include "absl/status/statusor.h"
#include "core/common/rgbd_frame.h"
#include "core/entropy/entropy_mask.h"

namespace lifemap::pipeline {

struct PipelineOptions {
  bool entropy_masks = true;
  entropy::EntropyMaskOptions entropy;
  // "Up" (against gravity) in the world frame of client poses; TUM's mocap frame is z-up.
  Eigen::Vector3f world_up = Eigen::Vector3f::UnitZ();

  absl::Status Validate() const;
};

// Per-frame settings a request may override.
struct FrameRequest {
  std::optional<float> entropy_threshold;  // [0, 1]
};

struct FrameAnalysis {
  RgbdFrame frame;  // decoded images
  DepthStats depth_stats;
  // Set when entropy masks are enabled and could be computed; otherwise entropy_status says why.
  std::optional<entropy::EntropyMaskResult> entropy;
  absl::Status entropy_status;
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

  const PipelineOptions& options() const { return options_; }

 private:
  PipelineOptions options_;
};

// The unit up direction in the camera frame: from T_world_camera when known, else the image's
// up (-y).
Eigen::Vector3f UpInCamera(const std::optional<Pose>& T_world_camera,
                           const Eigen::Vector3f& world_up);

}  // namespace lifemap::pipeline
