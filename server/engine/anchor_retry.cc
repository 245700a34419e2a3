#include "server/engine/anchor_retry.h"

#include <algorithm>
#include <future>

#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "server/engine/appearance.h"
#include "server/engine/pose_graph_worker.h"
#include "server/engine/visit_frame.h"
#include "server/store/store.h"

namespace lifemap::server {
namespace {

// Why `v` cannot be retried, or "" when it can.
std::string NotRetried(const store::VisitRecord& v) {
  if (MapFromVisit(v)) {
    return v.anchor ? absl::StrCat("anchored already (to visit ", v.anchor->to_visit_id, ")")
                    : "in the map's frame already";
  }
  if (!v.ended) return "still open: its own keyframes anchor it as they come";
  if (v.tracked_keyframes < 2) return "fewer than 2 tracked keyframes";
  return "";
}

std::shared_future<absl::StatusOr<int64_t>> Committed(int64_t keyframe_id) {
  std::promise<absl::StatusOr<int64_t>> p;
  p.set_value(keyframe_id);
  return p.get_future().share();
}

AnchorAttempt Retry(store::Store* store, AppearanceIndex* appearance, PoseGraphWorker* pose_graph,
                    const store::VisitRecord& visit, bool dry_run, int max_keyframes) {
  AnchorAttempt out;
  out.visit_id = visit.id;
  if (const std::string broken = UnanchorableTrack(store, visit, pose_graph->options());
      !broken.empty()) {
    out.reason = absl::StrCat(dry_run ? "dry run: would not anchor: " : "", "held: ", broken);
    return out;
  }
  auto keyframes = store->ListKeyframes(visit.map_id, visit.id);
  if (!keyframes.ok()) {
    out.reason = absl::StrCat("its keyframes could not be read: ", keyframes.status().message());
    return out;
  }
  std::vector<const store::KeyframeRecord*> tracked;
  for (const auto& k : *keyframes) {
    if (k.T_world_camera && k.T_odom_camera) tracked.push_back(&k);
  }
  // Spread over the visit: its beginning, middle and end see different things.
  std::vector<const store::KeyframeRecord*> queried;
  const size_t n = std::min<size_t>(tracked.size(), static_cast<size_t>(max_keyframes));
  for (size_t i = 0; i < n; ++i) queried.push_back(tracked[i * tracked.size() / n]);
  const LoopClosureStats before = pose_graph->Stats();
  std::string last_error;
  uint64_t ticket = 0;
  auto dry = dry_run ? std::make_shared<PoseGraphWorker::Job::DryRun>() : nullptr;
  for (const store::KeyframeRecord* k : queried) {
    auto features = store->GetKeyframeFeatures(k->id);
    if (!features.ok()) {
      last_error = absl::StrCat("keyframe ", k->id, ": ", features.status().message());
      continue;
    }
    auto recognition = appearance->Recognize(
        features->keypoints, k->intrinsics,
        [&](const appearance::KeyframeRef& r) { return r.visit_id == visit.id; });
    ++out.keyframes_queried;
    if (!recognition.ok()) {
      last_error = std::string(recognition.status().message());
      continue;
    }
    PoseGraphWorker::Job job;
    job.map_id = visit.map_id;
    job.visit_id = visit.id;
    job.committed = Committed(k->id);
    job.visit_ended = true;
    job.dry_run = dry;
    job.anchors = AnchorCandidatesOf(*recognition, visit.map_id, visit.id);
    if (job.anchors.empty()) continue;
    out.candidates += static_cast<int>(job.anchors.size());
    ticket = pose_graph->Submit(std::move(job));
  }
  if (ticket != 0) pose_graph->Wait(ticket);
  if (dry) {
    out.verdicts = dry->verdicts;
    out.reason =
        dry->would_anchor
            ? absl::StrCat("dry run: would anchor (", *dry->would_anchor, ")")
            : absl::StrCat("dry run: would not anchor: ", out.candidates,
                           " candidate matches from ", out.keyframes_queried, " keyframes queried",
                           last_error.empty() ? "" : absl::StrCat("; ", last_error));
    return out;
  }
  auto after = store->GetVisit(visit.id);
  if (after.ok() && after->anchor) {
    out.anchored = true;
    out.to_visit = after->anchor->to_visit_id;
    out.reason = after->anchor->evidence;
    return out;
  }
  if (out.candidates == 0) {
    out.reason = last_error.empty()
                     ? absl::StrCat("none of its ", out.keyframes_queried,
                                    " keyframes queried matched a visit in the map's frame")
                     : absl::StrCat("no candidate: ", last_error);
  } else {
    const LoopClosureStats now = pose_graph->Stats();
    out.reason = absl::StrCat(
        out.candidates, " candidate matches, no two keyframes' agreeing on where it lies",
        now.anchors_rejected > before.anchors_rejected
            ? " (or those that agreed were refused by the floor-plan check: pose_edges)"
            : "");
  }
  return out;
}

}  // namespace

absl::StatusOr<std::vector<AnchorAttempt>> RetryAnchors(store::Store* store,
                                                        AppearanceIndex* appearance,
                                                        PoseGraphWorker* pose_graph, int64_t map_id,
                                                        int64_t visit_id, bool dry_run,
                                                        int max_keyframes) {
  auto map = store->GetMapById(map_id);
  if (!map.ok()) return map.status();
  auto visits = store->ListVisits(map->name);
  if (!visits.ok()) return visits.status();
  std::vector<AnchorAttempt> out;
  bool found = visit_id == 0;
  for (const auto& v : *visits) {
    if (visit_id != 0 && v.id != visit_id) continue;
    found = true;
    if (const std::string why = NotRetried(v); !why.empty()) {
      if (visit_id != 0) {
        return absl::FailedPreconditionError(
            absl::StrCat("visit ", v.id, " is not retried: ", why));
      }
      continue;
    }
    out.push_back(Retry(store, appearance, pose_graph, v, dry_run, max_keyframes));
    spdlog::info("visit {}: anchor retried: {}", v.id, out.back().reason);
  }
  if (!found) {
    return absl::NotFoundError(
        absl::StrCat("visit ", visit_id, " is not a visit of map '", map->name, "'"));
  }
  return out;
}

}  // namespace lifemap::server
