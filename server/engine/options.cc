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
      {"loop_max_disagreement_deg_per_m", loop_max_disagreement_deg_per_m}};
  for (const auto& [name, v] : non_negative) {
    if (!(v >= 0) || !std::isfinite(v)) {
      return absl::InvalidArgumentError(
          absl::StrCat("pose_graph.", name, " must be a number >= 0, got ", v));
    }
  }
  if (!(layout_max_through_share >= 0 && layout_max_through_share <= 1)) {
    return absl::InvalidArgumentError(
        absl::StrCat("pose_graph.layout_max_through_share must be within [0, 1], got ",
                     layout_max_through_share));
  }
  return absl::OkStatus();
}

}  // namespace lifemap::server
