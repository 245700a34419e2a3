// Keyframe selection by motion and time.
#pragma once

#include <optional>
#include <string>

#include "absl/status/status.h"
#include "core/common/types.h"

namespace lifemap::tracking {

struct KeyframeOptions {
  double min_translation_m = 0.10;  // a frame this far from the last keyframe becomes one
  double min_rotation_rad = 0.17;   // ... or rotated this much (~10 degrees)
  double max_interval_s = 1.0;      // ... or this much later than the last keyframe

  // InvalidArgument for negative or non-finite values or a zero interval.
  absl::Status Validate() const;
};

struct KeyframeDecision {
  bool selected = false;
  std::string reason;  // why it was (or was not) selected, for people reading results
};

// Decides, frame by frame, which frames of one visit become keyframes. The first frame always
// does; then a frame does when its pose moved or turned enough since the last keyframe (when
// both have a pose) or when max_interval_s passed. Frames whose time goes backwards are not
// selected. Thread-compatible.
class KeyframeSelector {
 public:
  explicit KeyframeSelector(KeyframeOptions options = {}) : options_(options) {}

  // Decides for a frame without changing state.
  KeyframeDecision Decide(double timestamp_s, const std::optional<Pose>& pose) const;
  // Records that a frame became a keyframe.
  void Accept(double timestamp_s, const std::optional<Pose>& pose);

  void set_options(const KeyframeOptions& options) { options_ = options; }
  const KeyframeOptions& options() const { return options_; }

 private:
  KeyframeOptions options_;
  bool has_last_ = false;
  double last_timestamp_s_ = 0.0;
  std::optional<Pose> last_pose_;
};

}  // namespace lifemap::tracking
