#include "core/pipeline/frame_pipeline.h"

#include <chrono>
#include <cmath>

#include "absl/strings/str_cat.h"

namespace lifemap::pipeline {
namespace {

double MsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start)
      .count();
}

}  // namespace

absl::Status PipelineOptions::Validate() const {
  if (!(std::abs(world_up.norm() - 1.0f) < 1e-3f)) {
    return absl::InvalidArgumentError("world_up must be a unit vector");
  }
  return entropy.Validate();
}

Eigen::Vector3f UpInCamera(const std::optional<Pose>& T_world_camera,
                           const Eigen::Vector3f& world_up) {
  if (!T_world_camera) return Eigen::Vector3f(0, -1, 0);
  // R_world_camera^T maps world directions into the camera frame.
  return (T_world_camera->rotation.conjugate().cast<float>() * world_up).normalized();
}

absl::StatusOr<FrameAnalysis> FramePipeline::Process(const EncodedRgbdFrame& in,
                                                     const FrameRequest& request) const {
  if (request.entropy_threshold &&
      !(*request.entropy_threshold >= 0.0f && *request.entropy_threshold <= 1.0f)) {
    return absl::InvalidArgumentError(
        absl::StrCat("entropy_threshold must be within [0, 1], got ", *request.entropy_threshold));
  }
  const auto start = std::chrono::steady_clock::now();
  auto frame = DecodeRgbdFrame(in);
  if (!frame.ok()) return frame.status();
  FrameAnalysis out;
  out.frame = *std::move(frame);
  out.decode_ms = MsSince(start);
  const auto process_start = std::chrono::steady_clock::now();
  out.depth_stats = ComputeDepthStats(out.frame.depth_m);
  if (options_.entropy_masks) {
    entropy::EntropyMaskOptions options = options_.entropy;
    if (request.entropy_threshold) options.threshold = *request.entropy_threshold;
    auto result = entropy::ComputeEntropyMask(
        out.frame.depth_m, out.frame.color_bgr, out.frame.intrinsics,
        UpInCamera(out.frame.T_world_camera, options_.world_up), options);
    if (result.ok()) {
      out.entropy = *std::move(result);
    } else {
      out.entropy_status = result.status();
    }
  } else {
    out.entropy_status = absl::FailedPreconditionError("entropy masks are disabled");
  }
  out.process_ms = MsSince(process_start);
  return out;
}

}  // namespace lifemap::pipeline
