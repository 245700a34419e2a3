// The map's previous visit as a frame of a later visit compares against it (issue 36's moved
// mask, paper 000's eq. 3): the surfaces of the latest ended visit of the map in the map's
// frame, loaded once per visit off the reply path.
#pragma once

#include <cstdint>
#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "core/change/moved_zones.h"
#include "server/engine/options.h"
#include "server/engine/serial_worker.h"
#include "server/store/store.h"

namespace lifemap::server {

struct PreviousSurface {
  int64_t visit_id = 0;  // the previous visit
  change::SurfacePoints surface;
};

// Thread-safe: frames ask from their visit's thread, the loader fills it on its worker.
class PreviousVisit {
 public:
  // The surfaces of visit `against` (0: the map's latest ended visit in its frame that started
  // before `visit_id`) for frames of visit `visit_id` of map `map_id`, once loaded. The first
  // call for a visit to compare against queues its load on `loader` and answers UNAVAILABLE
  // ("being loaded"); FAILED_PRECONDITION when there is none (saying why), or the load failed.
  absl::StatusOr<std::shared_ptr<const PreviousSurface>> Get(store::Store* store,
                                                             SerialWorker* loader, int64_t map_id,
                                                             int64_t visit_id, int64_t against,
                                                             const VisitChangeOptions& options);

 private:
  struct State {
    absl::Mutex mu;
    bool asked ABSL_GUARDED_BY(mu) = false;
    int64_t against ABSL_GUARDED_BY(mu) = 0;  // what was asked for (0: the latest earlier)
    absl::Status status ABSL_GUARDED_BY(mu) =
        absl::UnavailableError("the visit to compare with is being loaded");
    std::shared_ptr<const PreviousSurface> surface ABSL_GUARDED_BY(mu);
  };
  std::shared_ptr<State> state_ = std::make_shared<State>();
};

}  // namespace lifemap::server
