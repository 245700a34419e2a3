#include "server/engine/previous_visit.h"

#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "server/engine/visit_changes.h"
#include "server/engine/visit_frame.h"

namespace lifemap::server {
namespace {

// Visit `against` of the map, or (0) the latest ended visit of the map other than `visit_id`
// that started before it, in the map's frame and with a keyframe; FAILED_PRECONDITION saying
// why there is none.
absl::StatusOr<store::VisitRecord> VisitToCompare(store::Store* store, int64_t visit_id,
                                                  int64_t against) {
  auto visit = store->GetVisit(visit_id);
  if (!visit.ok()) return visit.status();
  auto visits = store->ListVisits(visit->map_name);
  if (!visits.ok()) return visits.status();
  if (against != 0) {
    for (const auto& v : *visits) {
      if (v.id != against || v.id == visit_id) continue;
      if (!v.ended) {
        return absl::FailedPreconditionError(
            absl::StrCat("moved_against_visit ", against, " has not ended yet"));
      }
      if (!MapFromVisit(v)) {
        return absl::FailedPreconditionError(absl::StrCat(
            "moved_against_visit ", against, " is not in the map's frame (not anchored)"));
      }
      return v;
    }
    return absl::FailedPreconditionError(absl::StrCat(
        "moved_against_visit ", against, " is not another visit of map '", visit->map_name, "'"));
  }
  const store::VisitRecord* latest = nullptr;
  for (const auto& v : *visits) {
    if (v.id == visit_id || !v.ended || v.keyframe_count == 0 || !MapFromVisit(v)) continue;
    if (v.start_time_s > visit->start_time_s) continue;  // a later visit is not "previous"
    if (latest == nullptr || v.start_time_s > latest->start_time_s) latest = &v;
  }
  if (latest == nullptr) {
    return absl::FailedPreconditionError(absl::StrCat(
        "map '", visit->map_name,
        "' has no earlier ended visit in its frame to compare with (the first visit, or the "
        "earlier ones tracked and not anchored)"));
  }
  return *latest;
}

}  // namespace

absl::StatusOr<std::shared_ptr<const PreviousSurface>> PreviousVisit::Get(
    store::Store* store, SerialWorker* loader, int64_t map_id, int64_t visit_id, int64_t against,
    const VisitChangeOptions& options) {
  {
    absl::MutexLock lock(&state_->mu);
    if (state_->asked && state_->against == against) {
      if (state_->surface) return state_->surface;
      return state_->status;
    }
    // Asked for the first time, or a later stream of the visit asks for another visit: load.
    state_->asked = true;
    state_->against = against;
    state_->surface.reset();
    state_->status = absl::UnavailableError("the visit to compare with is being loaded");
  }
  loader->Submit([state = state_, store, map_id, visit_id, against, options] {
    absl::Status status;
    std::shared_ptr<PreviousSurface> loaded;
    auto previous = VisitToCompare(store, visit_id, against);
    if (!previous.ok()) {
      status = previous.status();
    } else {
      auto views = LoadVisitDepth(store, map_id, previous->id, options.pixel_stride, nullptr);
      if (!views.ok()) {
        status = absl::FailedPreconditionError(
            absl::StrCat("visit ", previous->id, " could not be read: ", views.status().message()));
      } else {
        loaded = std::make_shared<PreviousSurface>();
        loaded->visit_id = previous->id;
        loaded->surface =
            change::SurfaceOf(*views, options.change.voxel_m, options.change.max_range_m);
        spdlog::info("visit {}: moved zones against visit {} ({} keyframes, {} surface points)",
                     visit_id, previous->id, views->size(), loaded->surface.points.size());
      }
    }
    absl::MutexLock lock(&state->mu);
    if (state->against != against) return;  // another visit was asked for meanwhile
    state->status = status;
    state->surface = std::move(loaded);
  });
  absl::MutexLock lock(&state_->mu);
  if (state_->surface) return state_->surface;
  return state_->status;
}

}  // namespace lifemap::server
