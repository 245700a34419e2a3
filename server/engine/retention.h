// Retention (issue 36): a map's store bounded over years of visits. Keyframes of older visits
// that add no view, and whose landmarks no later visit matched, are thinned; old visits are
// compacted to their octree, floor plan and a sparse set of keyframes.
//
// The rule, per map, over its ended visits in the map's frame that hold keyframes, ranked
// oldest first:
//  - The newest `keep_recent_visits` are kept whole (changes between the latest two and the
//    moved masks against the latest compare whole visits). Visits not in the map's frame
//    (tracked and not anchored) and open visits are kept whole and cover nothing: their poses
//    are not comparable.
//  - Kept whatever covers them: a keyframe without a pose, the first keyframe of each visit (its
//    start, and the root of its odometry), and a keyframe that an accepted pose edge names
//    (an anchor, tie or loop: its landmarks were matched — survived — by a later view, and its
//    edges stay in the graph), and a keyframe that one of the `recognised_within_visits` newest
//    visits recognised (a verified appearance match: the views of it that still work).
//  - Any other keyframe is thinned when a kept keyframe of its own visit or a later one covers
//    it: within cover_m and cover_deg of its pose (compact_cover_m / compact_cover_deg for a
//    visit with at least compact_after_visits later visits). A keyframe that covers thinned ones
//    is thinned only when one kept keyframe covers it and each of them, so every thinned
//    keyframe's view stays covered by a kept one (never by a chain drifting away), and the
//    views kept move to the newest visits.
// Visits are visited oldest first and each visit's keyframes in time order; each visit's
// keyframes are deleted in one transaction (a kill leaves each visit as it was or thinned).
// Its semantic octree and floor plan stay as they were fused; a later `maps rebuild-octree`
// fuses the keyframes that are left.
#pragma once

#include <cstdint>
#include <functional>
#include <map>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/types.h"
#include "server/engine/options.h"
#include "server/store/store.h"

namespace lifemap::server {

class AppearanceIndex;

// One keyframe as the planner sees it.
struct RetentionCandidate {
  int64_t keyframe_id = 0;
  int visit_rank = 0;    // among the map's visits in its frame, oldest 0
  Pose pose;             // in the map's frame
  bool protect = false;  // kept whatever covers it (the caller knows why)
};

// A keyframe to thin and the kept keyframe that covers its view.
struct ThinnedKeyframe {
  int64_t keyframe_id = 0;
  int64_t covered_by = 0;
  double distance_m = 0, angle_deg = 0;
};

// The rule above over `candidates` (visit rank, then time order) of `visit_count` ranked
// visits: the keyframes thinned, each with the kept keyframe covering it. About linear in the
// keyframes (a hash grid of the kept ones).
std::vector<ThinnedKeyframe> PlanThinning(const std::vector<RetentionCandidate>& candidates,
                                          int visit_count, const RetentionOptions& options);

struct RetentionReport {
  struct Visit {
    int64_t visit_id = 0;
    int64_t keyframes = 0;  // before
    int64_t thinned = 0;
    int64_t bytes_freed = 0;  // images and features (a dry run: the images' alone)
    bool compacted = false;   // covered at the compact thresholds
    // Why none of its keyframes may be thinned ("" when some may): one of the newest, open,
    // not in the map's frame.
    std::string kept_whole;
    // Why kept keyframes of a thinnable visit were kept: reason -> count.
    std::map<std::string, int64_t> kept_because;
  };
  struct Thinned {
    ThinnedKeyframe keyframe;
    int64_t visit_id = 0, covered_by_visit = 0;
  };
  std::vector<Visit> visits;  // oldest first
  std::vector<Thinned> thinned;
  store::MapStorage before, after;  // after == before on a dry run
  bool dry_run = false;
  double seconds = 0;
};

// Plans retention for `map` with `options` and, unless `dry_run`, deletes the keyframes it
// thins (one transaction per visit) and drops them from `appearance` (may be null). One run at a
// time in the process (a second waits). Errors are the store's; a keyframe gone meanwhile (its
// map deleted) ends the run with NOT_FOUND after the visits already thinned.
absl::StatusOr<RetentionReport> ApplyRetention(store::Store* store, AppearanceIndex* appearance,
                                               const store::MapRecord& map,
                                               const RetentionOptions& options, bool dry_run);

}  // namespace lifemap::server
