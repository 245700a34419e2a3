#include "core/pipeline/frame_pipeline.h"

#include <chrono>
#include <cmath>
#include <functional>
#include <optional>
#include <vector>

#include "absl/strings/str_cat.h"
#include "core/common/task_pool.h"

namespace lifemap::pipeline {
namespace {

double MsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start)
      .count();
}

// Labels with a depth reading only (the forest's features are depth-normalised), the winning
// probability, and per-class tallies.
absl::StatusOr<FrameLabels> LabelFrame(const forest::Forest& forest, const RgbdFrame& frame,
                                       forest::Decision decision, int stride) {
  auto p = forest.Predict(frame.depth_m, frame.color_bgr, decision, stride);
  if (!p.ok()) return p.status();
  FrameLabels out;
  out.stride = stride;
  out.labels = p->labels;
  out.confidence = cv::Mat(out.labels.size(), CV_8UC1, cv::Scalar(0));
  const int classes = forest.class_count();
  out.class_pixels.assign(static_cast<size_t>(classes), 0);
  std::vector<double> sums(static_cast<size_t>(classes), 0.0);
  double total = 0.0;
  for (int r = 0; r < out.labels.rows; ++r) {
    const float* depth = frame.depth_m.ptr<float>(r);
    uint8_t* label = out.labels.ptr<uint8_t>(r);
    uint8_t* confidence = out.confidence.ptr<uint8_t>(r);
    for (int c = 0; c < out.labels.cols; ++c) {
      if (!(depth[c] > 0.0f) || label[c] >= classes) {
        label[c] = forest::kIgnore;
        continue;
      }
      const float prob = p->probabilities[label[c]].ptr<float>(r)[c];
      confidence[c] = cv::saturate_cast<uint8_t>(prob * 255.0f);
      ++out.class_pixels[label[c]];
      sums[label[c]] += prob;
      total += prob;
      ++out.labelled_pixels;
    }
  }
  out.class_mean_confidence.resize(static_cast<size_t>(classes));
  for (size_t c = 0; c < sums.size(); ++c) {
    out.class_mean_confidence[c] =
        out.class_pixels[c] > 0 ? sums[c] / static_cast<double>(out.class_pixels[c]) : 0.0;
  }
  out.mean_confidence = out.labelled_pixels > 0 ? total / out.labelled_pixels : 0.0;
  out.probabilities = std::move(p->probabilities);
  return out;
}

}  // namespace

absl::Status PipelineOptions::Validate() const {
  if (auto s = frame_limits.Validate(); !s.ok()) return s;
  if (!(std::abs(world_up.norm() - 1.0f) < 1e-3f)) {
    return absl::InvalidArgumentError("world_up must be a unit vector");
  }
  if (label_stride < 1 || label_stride > 16) {
    return absl::InvalidArgumentError(
        absl::StrCat("label stride must be within [1, 16], got ", label_stride));
  }
  return entropy.Validate();
}

Eigen::Vector3f UpInCamera(const std::optional<Pose>& T_world_camera,
                           const Eigen::Vector3f& world_up,
                           const std::optional<Eigen::Vector3d>& gravity_camera) {
  if (!T_world_camera && gravity_camera) return (-*gravity_camera).normalized().cast<float>();
  if (!T_world_camera) return Eigen::Vector3f(0, -1, 0);
  // R_world_camera^T maps world directions into the camera frame.
  return (T_world_camera->rotation.conjugate().cast<float>() * world_up).normalized();
}

void FramePipeline::ComputeEntropy(FrameAnalysis* analysis, const FrameRequest& request) const {
  if (!options_.entropy_masks) {
    analysis->entropy_status = absl::FailedPreconditionError("entropy masks are disabled");
    return;
  }
  entropy::EntropyMaskOptions options = options_.entropy;
  if (request.entropy_threshold) options.threshold = *request.entropy_threshold;
  const RgbdFrame& f = analysis->frame;
  auto result = entropy::ComputeEntropyMask(
      f.depth_m, f.color_bgr, f.intrinsics,
      UpInCamera(f.T_world_camera, options_.world_up, f.gravity_camera), options);
  if (result.ok()) {
    analysis->entropy = *std::move(result);
    analysis->entropy_status = absl::OkStatus();
  } else {
    analysis->entropy_status = result.status();
  }
}

absl::StatusOr<FrameAnalysis> FramePipeline::Process(const EncodedRgbdFrame& in,
                                                     const FrameRequest& request) const {
  const auto start = std::chrono::steady_clock::now();
  auto frame = DecodeRgbdFrame(in, /*decode_color=*/true, options_.frame_limits);
  if (!frame.ok()) return frame.status();
  FrameAnalysis out;
  out.frame = *std::move(frame);
  out.decode_ms = MsSince(start);
  const auto process_start = std::chrono::steady_clock::now();
  out.depth_stats = ComputeDepthStats(out.frame.depth_m);
  // Labels run beside the entropy masks as two tasks of the shared pool (the forest splits its
  // rows over two more); both read the decoded frame only.
  std::optional<absl::StatusOr<FrameLabels>> labels;
  std::vector<std::function<void()>> tasks;
  if (request.labeller != nullptr) {
    tasks.push_back([&] {
      labels =
          LabelFrame(*request.labeller, out.frame, options_.label_decision, options_.label_stride);
    });
  }
  if (request.entropy_masks) {
    tasks.push_back([&] { ComputeEntropy(&out, request); });
  } else {
    out.entropy_status = absl::FailedPreconditionError(kNotRequested);
  }
  TaskPool::Shared().RunAll(std::move(tasks));
  if (labels) {
    if (labels->ok()) {
      out.labels = *std::move(*labels);
    } else {
      out.labels_status = labels->status();
    }
  }
  out.process_ms = MsSince(process_start);
  return out;
}

}  // namespace lifemap::pipeline
