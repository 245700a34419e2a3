// FramePipeline composes the core modules for one frame. Today: decode and validate, depth
// statistics. Entropy masks, class labels and place matches plug in here as they are built.
#pragma once

#include "absl/status/statusor.h"
#include "core/common/rgbd_frame.h"

namespace lifemap::pipeline {

struct FrameAnalysis {
  RgbdFrame frame;  // decoded images
  DepthStats depth_stats;
  double decode_ms = 0.0;
  double process_ms = 0.0;  // everything after decoding
};

// Stateless and thread-safe: one instance serves every stream.
class FramePipeline {
 public:
  // InvalidArgument (from decoding/validation) for a frame that cannot be used.
  absl::StatusOr<FrameAnalysis> Process(const EncodedRgbdFrame& in) const;
};

}  // namespace lifemap::pipeline
