#include "server/engine/options.h"

#include <cmath>
#include <utility>

#include "absl/strings/str_cat.h"

namespace lifemap::server {

absl::Status PoseGraphOptions::Validate() const {
  if (loop_min_inliers < 6 || loop_min_inliers > 10000) {
    return absl::InvalidArgumentError(absl::StrCat(
        "pose_graph.loop_min_inliers must be within [6, 10000], got ", loop_min_inliers));
  }
  const std::pair<const char*, double> positive[] = {
      {"loop_max_reprojection_px", loop_max_reprojection_px},
      {"loop_max_disagreement_m", loop_max_disagreement_m},
      {"loop_max_disagreement_deg", loop_max_disagreement_deg}};
  for (const auto& [name, v] : positive) {
    if (!(v > 0) || !std::isfinite(v)) {
      return absl::InvalidArgumentError(
          absl::StrCat("pose_graph.", name, " must be a positive number, got ", v));
    }
  }
  const std::pair<const char*, double> non_negative[] = {
      {"loop_max_disagreement_per_m", loop_max_disagreement_per_m},
      {"loop_max_disagreement_deg_per_m", loop_max_disagreement_deg_per_m},
      {"anchor_max_floor_tilt_deg", anchor_max_floor_tilt_deg},
      {"anchor_max_floor_offset_m", anchor_max_floor_offset_m}};
  for (const auto& [name, v] : non_negative) {
    if (!(v >= 0) || !std::isfinite(v)) {
      return absl::InvalidArgumentError(
          absl::StrCat("pose_graph.", name, " must be a number >= 0, got ", v));
    }
  }
  const std::pair<const char*, double> shares[] = {
      {"layout_max_through_share", layout_max_through_share},
      {"anchor_drop_through_share", anchor_drop_through_share},
      {"layout_max_own_plan_share", layout_max_own_plan_share},
      {"layout_max_plan_on_floor_share", layout_max_plan_on_floor_share},
      {"anchor_max_lost_share", anchor_max_lost_share}};
  for (const auto& [name, v] : shares) {
    if (!(v >= 0 && v <= 1)) {
      return absl::InvalidArgumentError(
          absl::StrCat("pose_graph.", name, " must be within [0, 1], got ", v));
    }
  }
  if (!(anchor_min_spread_m >= 0 && anchor_min_spread_m <= 1000)) {
    return absl::InvalidArgumentError(
        absl::StrCat("pose_graph.anchor_min_spread_m must be within [0, 1000] metres, got ",
                     anchor_min_spread_m));
  }
  if (anchor_revision_min_matches < 2 || anchor_revision_min_matches > 100) {
    return absl::InvalidArgumentError(
        absl::StrCat("pose_graph.anchor_revision_min_matches must be within [2, 100], got ",
                     anchor_revision_min_matches));
  }
  return absl::OkStatus();
}

absl::Status VisitChangeOptions::Validate() const {
  if (pixel_stride < 1 || pixel_stride > 16) {
    return absl::InvalidArgumentError(
        absl::StrCat("changes.pixel_stride must lie in [1, 16], not ", pixel_stride));
  }
  if (auto s = change.Validate(); !s.ok()) {
    return absl::InvalidArgumentError(absl::StrCat("changes.", s.message()));
  }
  if (moved.stride < 1 || moved.stride > 16) {
    return absl::InvalidArgumentError(
        absl::StrCat("changes.moved_stride must lie in [1, 16], not ", moved.stride));
  }
  if (moved.window < 1 || moved.window > 15) {
    return absl::InvalidArgumentError(
        absl::StrCat("changes.moved_window must lie in [1, 15], not ", moved.window));
  }
  if (!(moved.threshold_m > 0.0f && moved.threshold_m < 10.0f)) {
    return absl::InvalidArgumentError(
        absl::StrCat("changes.moved_threshold_m must lie in (0, 10) m, not ", moved.threshold_m));
  }
  return absl::OkStatus();
}

absl::Status RetentionOptions::Validate() const {
  const std::pair<const char*, double> metres[] = {{"cover_m", cover_m},
                                                   {"compact_cover_m", compact_cover_m}};
  for (const auto& [name, v] : metres) {
    if (!(v >= 0 && v <= 100)) {
      return absl::InvalidArgumentError(
          absl::StrCat("retention.", name, " must lie in [0, 100] metres, not ", v));
    }
  }
  const std::pair<const char*, double> degrees[] = {{"cover_deg", cover_deg},
                                                    {"compact_cover_deg", compact_cover_deg}};
  for (const auto& [name, v] : degrees) {
    if (!(v >= 0 && v <= 180)) {
      return absl::InvalidArgumentError(
          absl::StrCat("retention.", name, " must lie in [0, 180] degrees, not ", v));
    }
  }
  if (keep_recent_visits < 1 || keep_recent_visits > 1000) {
    return absl::InvalidArgumentError(absl::StrCat(
        "retention.keep_recent_visits must lie in [1, 1000], not ", keep_recent_visits));
  }
  if (recognised_within_visits < 0 || recognised_within_visits > 1000) {
    return absl::InvalidArgumentError(
        absl::StrCat("retention.recognised_within_visits must lie in [0, 1000], not ",
                     recognised_within_visits));
  }
  if (compact_after_visits < 1 || compact_after_visits > 100000) {
    return absl::InvalidArgumentError(absl::StrCat(
        "retention.compact_after_visits must lie in [1, 100000], not ", compact_after_visits));
  }
  return absl::OkStatus();
}

absl::Status EngineOptions::Validate() const {
  if (db_path.empty()) return absl::InvalidArgumentError("db path must not be empty");
  if (auto s = changes.Validate(); !s.ok()) return s;
  if (auto s = retention.Validate(); !s.ok()) return s;
  if (keyframe_batch_max < 1 || keyframe_batch_max > 1024) {
    return absl::InvalidArgumentError(
        absl::StrCat("keyframe_batch_max must be within [1, 1024], got ", keyframe_batch_max));
  }
  if (!std::isfinite(max_future_s) || max_future_s <= 0) {
    return absl::InvalidArgumentError(absl::StrCat(
        "frames.max_future_s must be a positive number of seconds, got ", max_future_s));
  }
  if (!std::isfinite(max_gap_s) || max_gap_s <= 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("frames.max_gap_s must be a positive number of seconds, got ", max_gap_s));
  }
  if (color_jpeg_quality < 1 || color_jpeg_quality > 100) {
    return absl::InvalidArgumentError(absl::StrCat(
        "storage.color_jpeg_quality must be within [1, 100], got ", color_jpeg_quality));
  }
  if (auto s = pipeline.Validate(); !s.ok()) return s;
  if (auto s = appearance.Validate(); !s.ok()) return s;
  if (auto s = pose_graph.Validate(); !s.ok()) return s;
  if (odometry.downscale < 1 || odometry.downscale > 4) {
    return absl::InvalidArgumentError(
        absl::StrCat("tracking.downscale must be within [1, 4], got ", odometry.downscale));
  }
  if (auto s = odometry.Validate(); !s.ok()) return s;
  if (auto s = semantic.Validate(); !s.ok()) return s;
  if (semantic_render_stride < 1 || semantic_render_stride > 16) {
    return absl::InvalidArgumentError(absl::StrCat(
        "semantic.render_stride must be within [1, 16], got ", semantic_render_stride));
  }
  return absl::OkStatus();
}

}  // namespace lifemap::server
