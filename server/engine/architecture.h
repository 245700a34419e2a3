// Architecture-based place recognition served (paper 004): each visit's floor plan is built as
// its posed key frames arrive, stored with the visit, and ranked against every other stored
// visit's descriptor; frame results carry the ranking.
//
// The work runs off the reply path: a frame that becomes a key frame queues its depth on the
// ArchitectureWorker (planes, fold, derive the plan, store it, rank), and every frame result
// reports the ranking as known when it is answered (one or two key frames behind at most).
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <unordered_map>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "core/common/rgbd_frame.h"
#include "core/place/descriptor.h"
#include "core/place/floor_plan.h"
#include "server/engine/serial_worker.h"
#include "server/store/store.h"

namespace lifemap::server {

// A stored visit (architecture) or keyframe (appearance) matched to a query (the proto's
// PlaceMatch is made in server/convert).
struct PlaceMatch {
  enum class Method { kArchitecture, kAppearance, kFused };
  Method method = Method::kArchitecture;
  int64_t map_id = 0;
  std::string map;
  int64_t visit_id = 0;
  int64_t keyframe_id = 0;  // appearance: the matched keyframe
  double score = 0.0;       // [0, 1]: paper 004's descriptor match, or the verified PnP score
  std::optional<Pose> T_match_query;  // appearance: the query camera in the keyframe's frame
};

// What a frame result reports of its visit's architecture.
struct ArchitectureRanking {
  absl::Status status = absl::FailedPreconditionError(
      "no posed key frame yet (architecture needs the robot's poses)");
  std::vector<PlaceMatch> matches;  // best first, as of the last key frame folded
};

// How the server builds every floor plan (a visit's, and a place query's): levelled by the floor
// it sees (FloorPlanOptions::up_from_floor), since a tracked visit's frame is as tilted as its
// first camera where that frame came without gravity and showed no floor (issue 54).
place::FloorPlanOptions ServedPlanOptions();

// One visit's architecture in the making. The builder is used by one thread at a time: the
// registry while it loads the visit, then only the ArchitectureWorker.
struct VisitArchitecture {
  place::FloorPlanBuilder builder{ServedPlanOptions()};
  // The frame generation the builder's key frames are in (VisitState::frame_generation; 0 until
  // an anchor changes the visit's frame); only the ArchitectureWorker's thread reads or writes it.
  uint64_t frame_generation = 0;
  // Key frames not folded because their pose was in an older frame than the plan's (posed before
  // an anchor, queued after its rebuild): a later rebuild, which reads them from the store,
  // folds them in the right frame.
  int64_t stale_key_frames = 0;
  mutable absl::Mutex mu;
  ArchitectureRanking ranking ABSL_GUARDED_BY(mu);

  ArchitectureRanking Ranking() const;
  void SetStatus(const absl::Status& status);
};

// The descriptors of every stored visit, for ranking. Thread-safe.
class PlaceIndex {
 public:
  explicit PlaceIndex(store::Store* store) : store_(store) {}

  // Ranks stored visits (all but `exclude_visit`) by architecture, best first, at most `max`.
  absl::StatusOr<std::vector<PlaceMatch>> Rank(const place::PlaceDescriptor& query,
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
// planes, then the builder. On error sets the ranking's status and returns false.
bool FoldArchitectureKeyframe(const cv::Mat& depth_m, const CameraIntrinsics& k,
                              const Pose& T_world_camera, VisitArchitecture* arch);

// Derives the visit's plan from what was folded in; when it closes, stores it (with `store`;
// a resumed visit's stored plan is already there) and ranks the other visits against it.
// Errors only change the ranking's status (and the results' outputs say so): a frame is never
// rejected for them.
void UpdateArchitectureRanking(PlaceIndex* index, int64_t visit_id, int64_t map_id,
                               const std::string& map, bool store, VisitArchitecture* arch);

// Folds a visit's stored posed key frames into `arch` afresh (its builder reset), then derives
// and ranks its plan, storing it with `store_plan`. For a resumed visit (before its state is
// shared), and on the ArchitectureWorker for a visit anchored into its map's frame (its stored
// key frames moved there, and the plan must follow them). Damaged images are skipped.
void RebuildArchitecture(store::Store* store, PlaceIndex* index, int64_t map_id, int64_t visit_id,
                         const std::string& map, bool store_plan, VisitArchitecture* arch);

// Folds posed key frames into their visits' architecture on one thread, in the order they
// were submitted (so a visit's key frames fold in frame order), off the reply path.
// Thread-safe.
class ArchitectureWorker {
 public:
  ArchitectureWorker(store::Store* store, PlaceIndex* index);
  // Finishes every queued key frame, then stops (the worker member goes first).
  ~ArchitectureWorker() = default;
  ArchitectureWorker(const ArchitectureWorker&) = delete;
  ArchitectureWorker& operator=(const ArchitectureWorker&) = delete;

  // The visit a key frame belongs to, as the worker needs it. `arch` must stay alive until the
  // job is done (the caller's shared_ptr to the visit state is kept in `keep_alive`).
  struct Visit {
    int64_t visit_id = 0;
    int64_t map_id = 0;
    std::function<std::string()> map_name;  // read when the plan is stored (renames follow)
    VisitArchitecture* arch = nullptr;
    std::shared_ptr<const void> keep_alive;
    // The frame generation of the key frame's pose (Submit), or of the stored key frames a
    // rebuild reads (SubmitRebuild). A key frame older than the plan's generation is not folded.
    uint64_t frame_generation = 0;
  };
  // Queues a posed key frame; returns its ticket for Wait(). `depth_m` is shared, not copied
  // (cv::Mat reference counting): the caller must not write to it afterwards.
  uint64_t Submit(Visit visit, cv::Mat depth_m, const CameraIntrinsics& k,
                  const Pose& T_world_camera);
  // Queues a rebuild of the visit's architecture from its stored key frames (RebuildArchitecture,
  // stored), after the key frames queued before it; returns its ticket.
  uint64_t SubmitRebuild(Visit visit);
  // The visit's floor plan as the visit ends (PoseGraphWorker::Job::plan_at_end), once the key
  // frames queued before are folded: in the frame of `visit.frame_generation` (its current one),
  // rebuilt from its stored key frames (and stored) where some were folded in an older frame or
  // not folded at all (stale). Blocks. Not OK where no plan closes.
  absl::StatusOr<place::FloorPlan> PlanAtEnd(Visit visit);
  // Blocks until the key frame with `ticket` (and all before it) is folded and ranked.
  void Wait(uint64_t ticket);
  // The ticket of the last key frame submitted (0: none yet).
  uint64_t last_ticket() const;

 private:
  store::Store* const store_;
  PlaceIndex* const index_;
  SerialWorker worker_;  // last: destroyed (drained) first, while store_ and index_ are valid
};

// How many places a frame result lists.
constexpr size_t kFramePlaceMatches = 3;

}  // namespace lifemap::server
