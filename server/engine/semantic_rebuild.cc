#include "server/engine/semantic_rebuild.h"

#include <chrono>
#include <memory>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "core/pipeline/frame_pipeline.h"
#include "server/engine/semantic_export.h"
#include "server/engine/semantics.h"
#include "spdlog/spdlog.h"

namespace lifemap::server {
namespace {

using Clock = std::chrono::steady_clock;

// The visit's octree fused anew from its posed keyframes.
struct Fused {
  std::unique_ptr<semantic::SemanticMap> map;
  int64_t fused = 0;
  int64_t skipped = 0;
};

absl::StatusOr<Fused> FuseStoredKeyframes(const SemanticRebuildContext& ctx,
                                          const store::MapRecord& map,
                                          const store::VisitRecord& visit,
                                          const std::vector<const store::KeyframeRecord*>& posed,
                                          const LoadedModel& model,
                                          const std::function<bool()>& cancelled) {
  auto created = semantic::SemanticMap::Create(model.forest.class_count(),
                                               model.forest.class_prior(), ctx.options);
  if (!created.ok()) return created.status();
  Fused out{*std::move(created)};
  // Stored poses of an anchored visit were moved into the map's frame; its octree is in its own.
  const Eigen::Isometry3d T_visit_stored = visit.anchor
                                               ? visit.anchor->T_map_visit.ToIsometry().inverse()
                                               : Eigen::Isometry3d::Identity();
  pipeline::FrameRequest request;
  request.labeller = &model.forest;
  request.entropy_masks = false;
  for (const store::KeyframeRecord* listed : posed) {
    if (cancelled()) {
      return absl::CancelledError(absl::StrCat("rebuild of visit ", visit.id, " cancelled"));
    }
    // One keyframe's images at a time: a visit's images can be far larger than memory allows.
    auto k = ctx.store->GetKeyframe(map.id, listed->id);
    if (absl::IsNotFound(k.status())) continue;  // deleted meanwhile
    if (!k.ok()) return k.status();
    auto analysis = ctx.pipeline->Process(store::StoredFrame(*k), request);
    absl::Status why = analysis.status();
    if (analysis.ok() && !analysis->labels) why = analysis->labels_status;
    if (why.ok()) {
      const Pose T_visit_camera =
          Pose::FromIsometry(T_visit_stored * k->T_world_camera->ToIsometry());
      why = out.map
                ->Fuse(analysis->frame.depth_m, analysis->frame.intrinsics, T_visit_camera,
                       analysis->labels->probabilities)
                .status();
    }
    if (!why.ok()) {
      spdlog::warn("visit {}: keyframe {} not fused in the rebuild: {}", visit.id, k->id,
                   std::string(why.message()));
      ++out.skipped;
      continue;
    }
    ++out.fused;
  }
  return out;
}

// Rebuilds one visit's octree (or says why not) into `r`.
absl::Status RebuildVisit(const SemanticRebuildContext& ctx, const store::MapRecord& map,
                          const store::VisitRecord& visit, bool all, const LoadedModel& model,
                          const std::function<bool()>& cancelled, SemanticRebuild* r) {
  const auto start = Clock::now();
  r->visit_id = visit.id;
  r->model = model.name;
  std::shared_ptr<VisitState> live = ctx.visits->Loaded(visit.id);
  if (live != nullptr) {
    absl::MutexLock lock(&live->mu);
    if (live->writer != 0) {
      r->reason = absl::StrCat("being streamed (by ", live->writer_peer,
                               "): rebuild it once that stream has ended");
      return absl::OkStatus();
    }
  }
  auto listed = ctx.store->ListKeyframes(map.id, visit.id);
  if (!listed.ok()) return listed.status();
  std::vector<const store::KeyframeRecord*> posed;
  for (const auto& k : *listed) {
    if (k.T_world_camera) posed.push_back(&k);
  }
  if (posed.empty()) {
    r->reason = absl::StrCat("none of its ", listed->size(),
                             " keyframes has a pose: there is nothing to fuse");
    return absl::OkStatus();
  }
  std::optional<store::SemanticSnapshotRecord> snapshot;
  if (auto s = ctx.store->GetSemanticSnapshot(visit.id); s.ok()) {
    snapshot = *std::move(s);
  } else if (!absl::IsNotFound(s.status())) {
    snapshot = store::SemanticSnapshotRecord{};  // unreadable: stale, whatever it held
    snapshot->model = absl::StrCat("(unreadable: ", s.status().message(), ")");
  }
  const std::string stale = SemanticStaleness(snapshot, static_cast<int64_t>(posed.size()),
                                              model.name, ctx.options.resolution_m);
  if (stale.empty() && !all) {
    r->outcome = SemanticRebuild::Outcome::kUpToDate;
    r->reason =
        absl::StrCat("its octree holds all ", posed.size(), " posed keyframes, labelled by '",
                     model.name, "' at ", ctx.options.resolution_m, " m");
    r->keyframes_fused = snapshot->keyframes;
    r->bytes = static_cast<int64_t>(snapshot->bytes.size());
    return absl::OkStatus();
  }
  // Fusions the open visit has had so far (after those still queued from its last stream): any
  // more by the time the rebuild is put in place came in while it ran, and the rebuild would
  // drop them.
  if (live != nullptr) ctx.worker->Wait(ctx.worker->last_ticket());
  const int64_t fusions_before = live != nullptr ? live->semantics.fusions() : 0;
  auto fused = FuseStoredKeyframes(ctx, map, visit, posed, model, cancelled);
  if (!fused.ok()) return fused.status();
  r->keyframes_fused = fused->fused;
  r->keyframes_skipped = fused->skipped;
  if (fused->fused == 0) {
    r->reason = absl::StrCat("none of its ", posed.size(),
                             " posed keyframes could be fused (the server's log says why)");
    return absl::OkStatus();
  }
  r->labelled_voxels = fused->map->Summarize().labelled_voxels;
  store::SemanticSnapshotRecord record = SemanticSnapshotOf(visit.id, model.name, *fused->map);
  r->bytes = static_cast<int64_t>(record.bytes.size());
  // Put in place on the semantic worker: no fusion of the visit runs between the check and the
  // swap. A visit loaded since the rebuild began counts from its restored snapshot (0 fusions).
  absl::Status stored;
  bool raced = false;
  ctx.worker->Wait(ctx.worker->Submit([&] {
    std::shared_ptr<VisitState> now = ctx.visits->Loaded(visit.id);
    if (now != nullptr && now->semantics.fusions() != (now == live ? fusions_before : 0)) {
      raced = true;
      return;
    }
    stored = ctx.store->PutSemanticSnapshot(record);
    if (stored.ok() && now != nullptr) now->semantics.Replace(std::move(fused->map), model.name);
  }));
  if (!stored.ok()) return stored;
  r->seconds = std::chrono::duration<double>(Clock::now() - start).count();
  if (raced) {
    r->reason =
        "keyframes were fused into it while it was rebuilt: rebuild it again once the "
        "robot has stopped";
    return absl::OkStatus();
  }
  r->outcome = SemanticRebuild::Outcome::kRebuilt;
  r->reason = stale.empty() ? "every visit asked for" : stale;
  spdlog::info("visit {}: semantic octree rebuilt from {} keyframes ({} skipped) in {:.1f} s: {}",
               visit.id, r->keyframes_fused, r->keyframes_skipped, r->seconds, r->reason);
  return absl::OkStatus();
}

}  // namespace

std::string SemanticStaleness(const std::optional<store::SemanticSnapshotRecord>& snapshot,
                              int64_t posed_keyframes, const std::string& model,
                              double resolution_m) {
  if (!snapshot) return "no octree stored";
  if (snapshot->model != model) {
    return absl::StrCat("its octree holds model '", snapshot->model, "', the map's is '", model,
                        "'");
  }
  if (snapshot->resolution_m != resolution_m) {
    return absl::StrCat("its octree's voxels are ", snapshot->resolution_m,
                        " m, the server's semantic.resolution_m is ", resolution_m);
  }
  if (snapshot->keyframes < posed_keyframes) {
    return absl::StrCat("its octree holds ", snapshot->keyframes, " of its ", posed_keyframes,
                        " posed keyframes");
  }
  return "";
}

absl::Status RebuildSemanticOctrees(const SemanticRebuildContext& ctx, const store::MapRecord& map,
                                    int64_t visit_id, bool all, const LoadedModel& model,
                                    const std::function<bool()>& cancelled,
                                    const std::function<void(const SemanticRebuild&)>& done) {
  auto visits = ctx.store->ListVisits(map.name);
  if (!visits.ok()) return visits.status();
  bool found = visit_id == 0, rebuilt = false;
  for (const auto& v : *visits) {
    if (visit_id != 0 && v.id != visit_id) continue;
    found = true;
    SemanticRebuild r;
    if (auto s = RebuildVisit(ctx, map, v, all, model, cancelled, &r); !s.ok()) return s;
    rebuilt = rebuilt || r.outcome == SemanticRebuild::Outcome::kRebuilt;
    done(r);
  }
  // The map's octree merged again from the new snapshots.
  if (rebuilt) RefreshMapSemanticOctree(ctx.store, map.name, ctx.options);
  if (!found) {
    return absl::NotFoundError(
        absl::StrCat("visit ", visit_id, " is not a visit of map '", map.name, "'"));
  }
  return absl::OkStatus();
}

}  // namespace lifemap::server
