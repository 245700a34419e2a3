// Which frame a stored visit's keyframe poses are in: the map's (the map's first visit, a
// visit posed by its client, a tracked visit anchored into the map) or only its own (a tracked
// visit no match has anchored yet). Map-level exports hold the first kind only.
#pragma once

#include <cstdint>
#include <functional>
#include <optional>
#include <set>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/rgbd_frame.h"
#include "core/common/types.h"
#include "server/store/store.h"

namespace lifemap::server {

// Where visit `v`'s own frame lies in the map's (identity for visits in it from the start);
// nullopt for a tracked visit that no match has anchored yet.
std::optional<Pose> MapFromVisit(const store::VisitRecord& v);

// Why visit `v` is not in the map's frame (MapFromVisit is nullopt): not anchored yet, or its
// anchor dropped and why.
std::string WhyNotInMapFrame(const store::VisitRecord& v);

struct MapFrameVisits {
  std::set<int64_t> in_map_frame;     // visit ids
  std::vector<std::string> left_out;  // "visit N: why", for the others
};
absl::StatusOr<MapFrameVisits> VisitsInMapFrame(store::Store* store, const std::string& map_name);

// The posed keyframes a map-level export uses (visit_id 0: those of visits in the map's frame;
// else that visit's, in its own frame), each decoded and handed to `use` in store order.
// Returns the visits left out ("visit N: why"). FAILED_PRECONDITION naming `map_name` when no
// keyframe is posed (there), DATA_LOSS for one that does not decode, CANCELLED when `cancelled`
// says so between keyframes; `use`'s own error ends the walk.
// `keyframe_stride` > 1 uses every n-th posed keyframe only (a coarser level of detail; the
// others' images are not read).
struct PosedKeyframes {
  int64_t used = 0;
  std::vector<std::string> left_out;
};
absl::StatusOr<PosedKeyframes> ForEachPosedKeyframe(
    store::Store* store, int64_t map_id, const std::string& map_name, int64_t visit_id,
    const std::function<bool()>& cancelled,
    const std::function<absl::Status(const store::KeyframeRecord&, const RgbdFrame&)>& use,
    int64_t keyframe_stride = 1);

}  // namespace lifemap::server
