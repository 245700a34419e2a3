// Architecture-based place recognition served (paper 004): each visit's floor plan is built as
// its posed key frames arrive, stored with the visit, and ranked against every other stored
// visit's descriptor; frame results carry the ranking.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <unordered_map>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "core/common/rgbd_frame.h"
#include "core/place/descriptor.h"
#include "core/place/floor_plan.h"
#include "lifemap/v1/frame_service.pb.h"
#include "server/store/store.h"

namespace lifemap::server {

// One visit's architecture in the making. Guarded by its VisitState's mutex.
struct VisitArchitecture {
  place::FloorPlanBuilder builder;
  absl::Status status = absl::FailedPreconditionError(
      "no posed key frame yet (architecture needs the robot's poses)");
  std::vector<v1::PlaceMatch> matches;  // best first, as of the last key frame
};

// The descriptors of every stored visit, for ranking. Thread-safe.
class PlaceIndex {
 public:
  explicit PlaceIndex(store::Store* store) : store_(store) {}

  // Ranks stored visits (all but `exclude_visit`) by architecture, best first, at most `max`.
  absl::StatusOr<std::vector<v1::PlaceMatch>> Rank(const place::PlaceDescriptor& query,
                                                   int64_t exclude_visit, size_t max);
  // Stores the visit's plan with its descriptor (Describe(plan)) and indexes it.
  absl::Status Put(int64_t visit_id, int64_t map_id, const std::string& map,
                   const place::FloorPlan& plan, const place::PlaceDescriptor& descriptor,
                   double now_s);
  // Drops a deleted or renamed map's visits (reloaded from the store on next use).
  void Invalidate();

 private:
  struct Entry {
    int64_t map_id = 0;
    std::string map;
    place::PlaceDescriptor descriptor;
  };
  absl::Status LoadLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);

  store::Store* const store_;
  absl::Mutex mu_;
  bool loaded_ ABSL_GUARDED_BY(mu_) = false;
  std::unordered_map<int64_t, Entry> visits_ ABSL_GUARDED_BY(mu_);
};

// Folds one key frame (depth in metres, with its pose) into the visit's architecture: its
// planes, then the builder. On error sets `arch->status` and returns false.
bool FoldArchitectureKeyframe(const cv::Mat& depth_m, const CameraIntrinsics& k,
                              const Pose& T_world_camera, VisitArchitecture* arch);

// Derives the visit's plan from what was folded in; when it closes, stores it (with `store`;
// a resumed visit's stored plan is already there) and ranks the other visits against it.
// Errors only change `arch->status` (and the results' outputs say so): a frame is never
// rejected for them.
void UpdateArchitectureRanking(PlaceIndex* index, int64_t visit_id, int64_t map_id,
                               const std::string& map, bool store, VisitArchitecture* arch);

// How many places a frame result lists.
constexpr size_t kFramePlaceMatches = 3;

}  // namespace lifemap::server
