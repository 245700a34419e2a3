// The lifelong map engine: the store and every part that turns frames into maps, owned in one
// place, started in dependency order and drained in the reverse. It knows no gRPC and no
// protobuf: lifemapd's services (server/rpc) call it, and so can a benchmark, a tool or a
// second front end.
//
//   store             maps, visits, keyframes, plans, octrees, models, keys (server/store)
//   frames            the frame path: analyse, then place in the visit (frame_path.h)
//   place_queries     which stored visits a recording or a visit shows (place_query.h)
//   (and functions over the store: cloud_export.h, semantic_export.h, semantic_rebuild.h)
//   visits            visits being written: tracker, keyframe selector, octree (visit_registry.h)
//   committer         keyframes into the store, batched, in order (keyframe_committer.h)
//   appearance        paper 000's place recognition index (appearance.h)
//   architecture      paper 004's floor plans folded and ranked (architecture.h)
//   pose_graph        loop closure and visit anchoring (pose_graph_worker.h)
//   semantic_worker   paper 002's fusion into each visit's octree (semantics.h)
//   models            the labelling forests, per map (model_registry.h)
//   pipeline          per-frame analyses: entropy masks, labels (core/pipeline)
#pragma once

#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "core/pipeline/frame_pipeline.h"
#include "server/engine/frame_path.h"
#include "server/engine/options.h"
#include "server/engine/place_query.h"
#include "server/store/store.h"

namespace lifemap::server {

struct AnchorAttempt;
class AppearanceIndex;
class KeyframeCommitter;
class ModelRegistry;
class PlaceIndex;
class VisitRegistry;
class Engine {
 public:
  // Opens the store (a damaged file is refused, saying so), loads the appearance index and
  // starts the workers. The caller holds the database's instance lock (server/instance_lock.h).
  static absl::StatusOr<std::unique_ptr<Engine>> Open(const EngineOptions& options);
  // Drains every worker in dependency order (loops closed, every loaded visit's octree stored,
  // floor plans folded, keyframes committed), then closes the store. Nothing acknowledged is
  // lost. No call may be running.
  ~Engine();
  Engine(const Engine&) = delete;
  Engine& operator=(const Engine&) = delete;

  // Ends visit `visit_id` (idempotent): a stream still writing it ends with
  // FAILED_PRECONDITION; the keyframes it had queued are committed, its floor plan folded and
  // its semantic octree stored before the visit is marked ended (its map's octree is merged
  // again off the reply path). An anchored visit's anchor is re-checked with its final floor plan
  // and every keyframe, and dropped where they disagree (RecheckAnchorAtEnd). NOT_FOUND for an
  // unknown visit.
  absl::StatusOr<store::VisitRecord> EndVisit(int64_t visit_id);

  // Retries anchoring map `map_id`'s visits not in its frame (one, or every ended one for 0;
  // anchor_retry.h), after any retry the engine queued itself (each new appearance vocabulary
  // queues one for every map). Blocks until done. A dry run stores nothing (anchor_retry.h).
  absl::StatusOr<std::vector<AnchorAttempt>> RetryAnchors(int64_t map_id, int64_t visit_id,
                                                          bool dry_run = false);

  const EngineOptions& options() const { return options_; }
  store::Store* store() const;
  FramePath* frames() const;
  PlaceQueries* place_queries() const;
  VisitRegistry* visits() const;
  KeyframeCommitter* committer() const;
  AppearanceIndex* appearance() const;
  PlaceIndex* places() const;
  ArchitectureWorker* architecture() const;
  PoseGraphWorker* pose_graph() const;
  SerialWorker* semantic_worker() const;
  ModelRegistry* models() const;
  const pipeline::FramePipeline* pipeline() const;

 private:
  struct Parts;
  Engine(const EngineOptions& options, std::unique_ptr<Parts> parts);
  // At the end of visit `state` (every keyframe committed): its anchor, if any, re-checked by the
  // pose-graph worker with the visit's final plan (PoseGraphWorker::Job::plan_at_end). Blocks.
  void RecheckAnchorAtEnd(const std::shared_ptr<VisitState>& state);

  EngineOptions options_;
  std::unique_ptr<Parts> parts_;
};

}  // namespace lifemap::server
