#include "core/pipeline/frame_pipeline.h"

#include <chrono>

namespace lifemap::pipeline {
namespace {

double MsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start)
      .count();
}

}  // namespace

absl::StatusOr<FrameAnalysis> FramePipeline::Process(const EncodedRgbdFrame& in) const {
  const auto start = std::chrono::steady_clock::now();
  auto frame = DecodeRgbdFrame(in);
  if (!frame.ok()) return frame.status();
  FrameAnalysis out;
  out.frame = *std::move(frame);
  out.decode_ms = MsSince(start);
  const auto process_start = std::chrono::steady_clock::now();
  out.depth_stats = ComputeDepthStats(out.frame.depth_m);
  out.process_ms = MsSince(process_start);
  return out;
}

}  // namespace lifemap::pipeline
