#include "server/engine/visit_frame.h"

#include "absl/strings/str_cat.h"

namespace lifemap::server {

std::optional<Pose> MapFromVisit(const store::VisitRecord& v) {
  if (v.anchor) return v.anchor->T_map_visit;
  if (v.first_of_map || v.tracked_keyframes == 0) return Pose{};
  return std::nullopt;
}

absl::StatusOr<MapFrameVisits> VisitsInMapFrame(store::Store* store, const std::string& map_name) {
  auto visits = store->ListVisits(map_name);
  if (!visits.ok()) return visits.status();
  MapFrameVisits out;
  for (const auto& v : *visits) {
    if (MapFromVisit(v)) {
      out.in_map_frame.insert(v.id);
    } else {
      out.left_out.push_back(
          v.anchor_dropped.empty()
              ? absl::StrCat("visit ", v.id,
                             ": tracked and not anchored in the map's frame yet (its poses are "
                             "in its own frame)")
              : absl::StrCat("visit ", v.id,
                             ": its anchor was dropped (its poses are in its own frame again): ",
                             v.anchor_dropped));
    }
  }
  return out;
}

}  // namespace lifemap::server
