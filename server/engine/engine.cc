#include "server/engine/engine.h"

#include <utility>

#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "server/engine/anchor_retry.h"
#include "server/engine/appearance.h"
#include "server/engine/clock.h"
#include "server/engine/keyframe_committer.h"
#include "server/engine/map_archive.h"
#include "server/engine/model_registry.h"
#include "server/engine/pose_graph_worker.h"
#include "server/engine/retention.h"
#include "server/engine/semantic_export.h"
#include "server/engine/semantics.h"
#include "server/engine/serial_worker.h"
#include "server/engine/visit_registry.h"
#include "server/store/store.h"

namespace lifemap::server {

// Declared in the order they are made; ~Engine drains them in an order of its own.
struct Engine::Parts {
  std::unique_ptr<store::Store> store;
  std::unique_ptr<AppearanceIndex> appearance;  // the committer calls it: after it goes
  std::unique_ptr<KeyframeCommitter> committer;
  std::unique_ptr<PlaceIndex> places;
  std::unique_ptr<ArchitectureWorker> architecture;  // writes to the store: before it goes
  // Waits for commits (before the committer goes) and queues rebuilds on the architecture
  // worker (before it goes).
  std::unique_ptr<PoseGraphWorker> pose_graph;
  std::unique_ptr<SerialWorker> semantic_worker;  // fuses keyframes into visits' octrees
  std::unique_ptr<VisitRegistry> visits;
  std::unique_ptr<ModelRegistry> models;
  std::unique_ptr<pipeline::FramePipeline> pipeline;
  std::unique_ptr<FramePath> frames;            // uses the parts above
  std::unique_ptr<PlaceQueries> place_queries;  // likewise
  // Retries unanchored visits after each new vocabulary (anchor_retry.h), and runs retention
  // after a visit ends when the config asks (retention.h): uses the appearance index and the
  // pose-graph worker, so it goes before them.
  std::unique_ptr<SerialWorker> anchor_retries;
  // Loads the previous visit's surfaces for moved masks (reads the store: before it goes).
  std::unique_ptr<SerialWorker> previous_loader;
};

absl::StatusOr<std::unique_ptr<Engine>> Engine::Open(const EngineOptions& options) {
  if (auto s = options.Validate(); !s.ok()) return s;
  auto p = std::make_unique<Parts>();
  store::StoreOptions store_options;
  store_options.synchronous_full = options.synchronous_full;
  store_options.quick_check = true;  // a damaged file is refused at start, saying so
  auto store = store::Store::Open(options.db_path, store_options);
  if (!store.ok()) return store.status();
  p->store = *std::move(store);
  RemoveStaleArchiveFiles(*p->store);  // scratch files of map archives a killed server left
  p->appearance = std::make_unique<AppearanceIndex>(p->store.get(), options.appearance);
  if (auto s = p->appearance->Load(); !s.ok()) return s;
  p->committer = std::make_unique<KeyframeCommitter>(
      p->store.get(), options.keyframe_batch_max,
      [appearance = p->appearance.get()](const store::KeyframeRecord& k) {
        appearance->OnCommitted(k);
      });
  p->places = std::make_unique<PlaceIndex>(p->store.get());
  p->architecture = std::make_unique<ArchitectureWorker>(p->store.get(), p->places.get());
  p->pose_graph = std::make_unique<PoseGraphWorker>(p->store.get(), options.pose_graph);
  p->semantic_worker = std::make_unique<SerialWorker>();
  p->visits = std::make_unique<VisitRegistry>(
      p->store.get(), p->places.get(),
      options.semantic_enabled ? std::optional(options.semantic) : std::nullopt, options.odometry);
  p->models = std::make_unique<ModelRegistry>(p->store.get());
  p->pipeline = std::make_unique<pipeline::FramePipeline>(options.pipeline);
  FramePathParts parts;
  parts.store = p->store.get();
  parts.pipeline = p->pipeline.get();
  parts.visits = p->visits.get();
  parts.models = p->models.get();
  parts.committer = p->committer.get();
  parts.appearance = p->appearance.get();
  parts.architecture = p->architecture.get();
  parts.pose_graph = p->pose_graph.get();
  parts.semantic_worker = p->semantic_worker.get();
  p->previous_loader = std::make_unique<SerialWorker>();
  parts.previous_loader = p->previous_loader.get();
  p->frames = std::make_unique<FramePath>(parts, options);
  p->place_queries =
      std::make_unique<PlaceQueries>(p->store.get(), p->places.get(), p->visits.get(),
                                     p->appearance.get(), p->pipeline.get(), options);
  p->anchor_retries = std::make_unique<SerialWorker>();
  p->appearance->SetOnTrained([store = p->store.get(), appearance = p->appearance.get(),
                               pose_graph = p->pose_graph.get(),
                               retries = p->anchor_retries.get()] {
    // Off the index's thread: a retry queries the index and waits for the pose-graph worker.
    retries->Submit([store, appearance, pose_graph] {
      auto maps = store->ListMaps();
      if (!maps.ok()) return;
      for (const auto& m : *maps) {
        auto attempts = server::RetryAnchors(store, appearance, pose_graph, m.id, 0);
        if (!attempts.ok()) continue;
        int anchored = 0;
        for (const auto& a : *attempts) anchored += a.anchored;
        if (!attempts->empty()) {
          spdlog::info("map '{}': new appearance vocabulary: {} of {} unanchored visits anchored",
                       m.name, anchored, attempts->size());
        }
      }
    });
  });
  return std::unique_ptr<Engine>(new Engine(options, std::move(p)));
}

Engine::Engine(const EngineOptions& options, std::unique_ptr<Parts> parts)
    : options_(options), parts_(std::move(parts)) {}

Engine::~Engine() {
  Parts& p = *parts_;
  // Anchor retries before the pose-graph worker and the index they use.
  p.appearance->SetOnTrained(nullptr);
  p.anchor_retries.reset();
  p.previous_loader.reset();
  // The pose-graph worker first: an anchor queues a rebuild on the architecture worker.
  p.pose_graph.reset();
  // Every open visit's octree into the store once its queued keyframes are fused (the periodic
  // snapshot may be up to 9 keyframes behind): a restart resumes with all of them.
  for (const auto& visit : p.visits->AllLoaded()) {
    QueueSemanticSnapshot(p.semantic_worker.get(), p.store.get(), visit);
  }
  p.semantic_worker.reset();
  // Fold the key frames still queued for architecture, commit what is still queued, then close
  // the store.
  p.architecture.reset();
  p.committer.reset();
  p.appearance.reset();
  p.place_queries.reset();
  p.frames.reset();
  p.visits.reset();
  p.models.reset();
  p.store.reset();
}

absl::StatusOr<std::vector<AnchorAttempt>> Engine::RetryAnchors(int64_t map_id, int64_t visit_id,
                                                                bool dry_run) {
  Parts& p = *parts_;
  absl::StatusOr<std::vector<AnchorAttempt>> out = absl::InternalError("not run");
  // On the retries' worker, after any retry a new vocabulary queued: one at a time.
  p.anchor_retries->Wait(p.anchor_retries->Submit([&] {
    out = server::RetryAnchors(p.store.get(), p.appearance.get(), p.pose_graph.get(), map_id,
                               visit_id, dry_run);
  }));
  return out;
}

absl::StatusOr<store::VisitRecord> Engine::EndVisit(int64_t id) {
  Parts& p = *parts_;
  auto state = p.visits->Get(id);
  if (!state.ok() && !absl::IsFailedPrecondition(state.status())) {  // ended already: idempotent
    return state.status();
  }
  // A stream still writing the visit ends with FAILED_PRECONDITION; keyframes it had already
  // queued are committed before the visit is marked ended, nothing after.
  const store::VisitFrameCount counts = p.visits->CloseVisit(
      id, absl::FailedPreconditionError(absl::StrCat(
              "visit ", id, " was ended (EndVisit); start a new visit (visit_id 0) to go on")));
  // Its floor plan too: what was sent before the end is folded, stored and ranked.
  p.architecture->Wait(p.architecture->last_ticket());
  // And its semantic octree: the keyframes queued are fused, then the snapshot is stored.
  // The map's octree is merged again with it afterwards, off the reply path.
  if (state.ok()) {
    p.semantic_worker->Wait(QueueSemanticSnapshot(p.semantic_worker.get(), p.store.get(), *state));
    std::string map_name;
    {
      absl::MutexLock lock(&(*state)->mu);
      map_name = (*state)->map_name;
    }
    p.semantic_worker->Submit([store = p.store.get(), map_name, options = options_.semantic] {
      RefreshMapSemanticOctree(store, map_name, options);
    });
  }
  auto drained = p.committer->Submit(std::nullopt, counts).get();
  if (!drained.ok()) return drained.status();
  if (state.ok()) RecheckAnchorAtEnd(*state);
  auto ended = p.store->EndVisit(id, NowSeconds(), counts);
  if (ended.ok() && options_.retention.after_visit_end) {
    p.anchor_retries->Submit([store = p.store.get(), appearance = p.appearance.get(),
                              map_id = ended->map_id, options = options_.retention] {
      auto map = store->GetMapById(map_id);
      if (!map.ok()) return;  // deleted meanwhile
      auto report = ApplyRetention(store, appearance, *map, options, /*dry_run=*/false);
      if (!report.ok()) {
        spdlog::warn("retention of map '{}': {}", map->name, report.status().ToString());
      } else if (!report->thinned.empty()) {
        spdlog::info(
            "retention of map '{}' after a visit ended: {} keyframes thinned, {} -> {} bytes",
            map->name, report->thinned.size(), report->before.total(), report->after.total());
      }
    });
  }
  return ended;
}

void Engine::RecheckAnchorAtEnd(const std::shared_ptr<VisitState>& state) {
  Parts& p = *parts_;
  // Every keyframe is committed: the pose-graph jobs queued for them (an anchor among them) are
  // done first, then the plan is taken in the frame the visit is in after them.
  p.pose_graph->Wait(p.pose_graph->last_ticket());
  auto visit = p.store->GetVisit(state->visit_id);
  if (!visit.ok() || !visit->anchor) return;
  uint64_t generation = 0;
  {
    absl::MutexLock correction(&state->correction_mu);
    generation = state->frame_generation;
  }
  auto plan = p.architecture->PlanAtEnd(ArchitectureJobVisit(state, generation));
  if (!plan.ok()) {
    spdlog::info("visit {}: anchor not re-checked at its end: no floor plan ({})", visit->id,
                 plan.status().ToString());
    return;
  }
  PoseGraphWorker::Job job;
  job.map_id = visit->map_id;
  job.visit_id = visit->id;
  job.visit_ended = true;
  job.plan_at_end = std::make_shared<const place::FloorPlan>(*std::move(plan));
  job.on_anchored = FollowAnchor(state, p.architecture.get());
  p.pose_graph->Wait(p.pose_graph->Submit(std::move(job)));
  // A dropped anchor moved the keyframes back: the plan that follows them is stored before the
  // visit is marked ended.
  p.architecture->Wait(p.architecture->last_ticket());
}

store::Store* Engine::store() const { return parts_->store.get(); }
FramePath* Engine::frames() const { return parts_->frames.get(); }
PlaceQueries* Engine::place_queries() const { return parts_->place_queries.get(); }
VisitRegistry* Engine::visits() const { return parts_->visits.get(); }
KeyframeCommitter* Engine::committer() const { return parts_->committer.get(); }
AppearanceIndex* Engine::appearance() const { return parts_->appearance.get(); }
PlaceIndex* Engine::places() const { return parts_->places.get(); }
ArchitectureWorker* Engine::architecture() const { return parts_->architecture.get(); }
PoseGraphWorker* Engine::pose_graph() const { return parts_->pose_graph.get(); }
SerialWorker* Engine::semantic_worker() const { return parts_->semantic_worker.get(); }
ModelRegistry* Engine::models() const { return parts_->models.get(); }
const pipeline::FramePipeline* Engine::pipeline() const { return parts_->pipeline.get(); }

}  // namespace lifemap::server
