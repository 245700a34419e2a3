#include "core/tracking/keyframe_selector.h"

#include <cmath>

#include "absl/strings/str_format.h"

namespace lifemap::tracking {

absl::Status KeyframeOptions::Validate() const {
  auto bad = [](double v) { return !std::isfinite(v) || v < 0.0; };
  if (bad(min_translation_m) || bad(min_rotation_rad) || bad(max_interval_s) ||
      max_interval_s == 0.0) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "keyframe options must be finite and >= 0 with a positive interval; got translation "
        "%g m, rotation %g rad, interval %g s",
        min_translation_m, min_rotation_rad, max_interval_s));
  }
  return absl::OkStatus();
}

KeyframeDecision KeyframeSelector::Decide(double timestamp_s,
                                          const std::optional<Pose>& pose) const {
  if (!has_last_) return {true, "first frame of the visit"};
  const double dt = timestamp_s - last_timestamp_s_;
  if (dt < 0.0) return {false, absl::StrFormat("time went back %.3f s", -dt)};
  if (pose && last_pose_) {
    const double moved = TranslationDistanceM(*pose, *last_pose_);
    if (moved >= options_.min_translation_m) {
      return {true, absl::StrFormat("moved %.3f m", moved)};
    }
    const double turned = RotationAngleRad(*pose, *last_pose_);
    if (turned >= options_.min_rotation_rad) {
      return {true, absl::StrFormat("turned %.1f deg", turned * 180.0 / M_PI)};
    }
  }
  if (dt >= options_.max_interval_s) {
    return {true, absl::StrFormat("%.2f s since the last keyframe", dt)};
  }
  return {false, "too close to the last keyframe"};
}

void KeyframeSelector::Accept(double timestamp_s, const std::optional<Pose>& pose) {
  has_last_ = true;
  last_timestamp_s_ = timestamp_s;
  if (pose) last_pose_ = pose;
}

}  // namespace lifemap::tracking
