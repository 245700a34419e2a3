// Anchoring again, on demand (issue 35): a tracked visit that could not be anchored while it
// was captured (no appearance vocabulary yet, too few keyframes stored in the map then, or no
// two matches that agreed) is retried against the appearance index as it is now. Its stored
// keyframes' features are queried like a new keyframe's; their verified matches to visits in
// the map's frame go to the pose-graph worker as anchor candidates and are judged exactly as at
// capture (two keyframes agreeing, the floor-plan check). `lifemap visits anchor` calls it, and
// so does the engine each time a new appearance vocabulary is trained.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"

namespace lifemap::store {
class Store;
}  // namespace lifemap::store

namespace lifemap::server {

class AppearanceIndex;
class PoseGraphWorker;

// What one visit's retry found.
struct AnchorAttempt {
  int64_t visit_id = 0;
  bool anchored = false;  // anchored by this attempt
  int64_t to_visit = 0;   // when anchored: the visit it is anchored to
  int keyframes_queried = 0;
  int candidates = 0;  // verified matches to visits in the map's frame
  std::string reason;  // what happened, for people: why not, or the anchor's evidence
  // A dry run's verdict on each candidate match, in the order judged: where it puts the visit
  // and what the checks made of it (PoseGraphWorker::Job::dry_run).
  std::vector<std::string> verdicts;
};

// Retries anchoring visit `visit_id` of map `map_id`, or (0) every ended visit of the map that is
// tracked and not in its frame, querying at most `max_keyframes` keyframes of each (spread over
// the visit). A visit still open is not retried: its own keyframes anchor it as they come
// (NOT_FOUND for a visit of another map, FAILED_PRECONDITION naming why one visit asked for
// cannot be retried). Blocks until the worker has judged every candidate. A `dry_run` judges
// them the same way but stores and anchors nothing, and says what it would have done.
absl::StatusOr<std::vector<AnchorAttempt>> RetryAnchors(store::Store* store,
                                                        AppearanceIndex* appearance,
                                                        PoseGraphWorker* pose_graph, int64_t map_id,
                                                        int64_t visit_id, bool dry_run = false,
                                                        int max_keyframes = 24);

}  // namespace lifemap::server
