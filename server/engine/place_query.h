// Place recognition asked of the stored maps (PlaceService.QueryPlace): which stored visits a
// recording's key frames, or a stored visit, show, by architecture (paper 004: the frames'
// floor plan against every stored visit's) and by appearance (paper 000: each frame's
// entropy-pruned features against every stored keyframe), and both fused.
#pragma once

#include <functional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/rgbd_frame.h"
#include "server/engine/architecture.h"
#include "server/engine/options.h"
#include "server/store/store.h"

namespace lifemap::pipeline {
class FramePipeline;
}

namespace lifemap::server {

class AppearanceIndex;
class VisitRegistry;

struct PlaceQuery {
  bool architecture = true;
  bool appearance = true;
  size_t max_results = 10;
  // Matches in maps this refuses are left out (a key limited to some maps); null: every map.
  std::function<bool(int64_t map_id)> may_use_map;
  // Polled between frames: true stops the query (its deadline passed, its client left).
  std::function<bool()> stopped;
};

// What one method made of a query: its ranking, best first, or why it has none.
struct MethodOutcome {
  absl::Status status = absl::FailedPreconditionError("not asked");
  std::vector<PlaceMatch> matches;
  std::string descriptor_text;  // architecture: the query's descriptor, for people
};

// One query frame's own appearance matches (at most max_results), or why it has none.
struct FrameAppearanceOutcome {
  size_t index = 0;
  std::string reason;
  std::vector<PlaceMatch> matches;
};

struct PlaceQueryResult {
  MethodOutcome architecture;
  MethodOutcome appearance;
  // Both methods answered: one ranking, the mean of the two scores (a method that did not rank
  // a visit counts 0).
  std::vector<PlaceMatch> fused;
  std::vector<FrameAppearanceOutcome> frames;  // appearance of frames, per frame
};

class PlaceQueries {
 public:
  PlaceQueries(store::Store* store, PlaceIndex* places, VisitRegistry* visits,
               AppearanceIndex* appearance, const pipeline::FramePipeline* pipeline,
               const EngineOptions& options);

  // Key frames of a recording, not stored (poses needed for architecture; colour for
  // appearance). INVALID_ARGUMENT for a frame that does not decode, CANCELLED when stopped; a
  // method that cannot answer says why in its outcome.
  absl::StatusOr<PlaceQueryResult> OfFrames(const std::vector<EncodedRgbdFrame>& frames,
                                            const PlaceQuery& query) const;
  // A stored visit against every other: its stored floor plan, its keyframes' features.
  PlaceQueryResult OfVisit(const store::VisitRecord& visit, const PlaceQuery& query) const;

 private:
  absl::Status ArchitectureOfFrames(const std::vector<EncodedRgbdFrame>& frames,
                                    const PlaceQuery& query, MethodOutcome* out) const;
  absl::Status AppearanceOfFrames(const std::vector<EncodedRgbdFrame>& frames,
                                  const PlaceQuery& query, MethodOutcome* out,
                                  std::vector<FrameAppearanceOutcome>* per_frame) const;
  void ArchitectureOfVisit(const store::VisitRecord& visit, size_t max_results,
                           MethodOutcome* out) const;
  void AppearanceOfVisit(const store::VisitRecord& visit, size_t max_results,
                         MethodOutcome* out) const;
  // Leaves out the matches the query's key may not see, then fuses.
  void Finish(const PlaceQuery& query, PlaceQueryResult* result) const;

  store::Store* store_;
  PlaceIndex* places_;
  VisitRegistry* visits_;
  AppearanceIndex* appearance_;
  const pipeline::FramePipeline* pipeline_;
  EngineOptions options_;
};

}  // namespace lifemap::server
