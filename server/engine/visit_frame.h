// Which frame a stored visit's keyframe poses are in: the map's (the map's first visit, a
// visit posed by its client, a tracked visit anchored into the map) or only its own (a tracked
// visit no match has anchored yet). Map-level exports hold the first kind only.
#pragma once

#include <cstdint>
#include <optional>
#include <set>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/types.h"
#include "server/store/store.h"

namespace lifemap::server {

// Where visit `v`'s own frame lies in the map's (identity for visits in it from the start);
// nullopt for a tracked visit that no match has anchored yet.
std::optional<Pose> MapFromVisit(const store::VisitRecord& v);

struct MapFrameVisits {
  std::set<int64_t> in_map_frame;     // visit ids
  std::vector<std::string> left_out;  // "visit N: why", for the others
};
absl::StatusOr<MapFrameVisits> VisitsInMapFrame(store::Store* store, const std::string& map_name);

}  // namespace lifemap::server
