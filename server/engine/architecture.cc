#include "server/engine/architecture.h"

#include <algorithm>

#include "absl/strings/str_cat.h"
#include "core/common/image_codec.h"
#include "core/place/serialize.h"
#include "server/engine/clock.h"

namespace lifemap::server {

absl::Status PlaceIndex::LoadLocked() {
  if (loaded_) return absl::OkStatus();
  auto stored = store_->ListVisitPlaces("");
  if (!stored.ok()) return stored.status();
  visits_.clear();
  for (const auto& r : *stored) {
    auto d = place::DescriptorFromJson(r.descriptor_json);
    if (!d.ok()) continue;  // a damaged record is skipped, not fatal; the visit rebuilds it
    visits_[r.visit_id] = {r.map_id, r.map_name, *std::move(d)};
  }
  loaded_ = true;
  return absl::OkStatus();
}

ArchitectureRanking VisitArchitecture::Ranking() const {
  absl::MutexLock lock(&mu);
  return ranking;
}

void VisitArchitecture::SetStatus(const absl::Status& status) {
  absl::MutexLock lock(&mu);
  ranking.status = status;
}

absl::StatusOr<std::vector<PlaceMatch>> PlaceIndex::Rank(const place::PlaceDescriptor& query,
                                                         int64_t exclude_visit, size_t max) {
  absl::MutexLock lock(&mu_);
  if (auto s = LoadLocked(); !s.ok()) return s;
  std::vector<std::pair<double, const std::pair<const int64_t, Entry>*>> scored;
  for (const auto& entry : visits_) {
    if (entry.first == exclude_visit) continue;
    scored.emplace_back(place::MatchDescriptors(query, entry.second.descriptor).score, &entry);
  }
  std::sort(scored.begin(), scored.end(), [](const auto& a, const auto& b) {
    return a.first > b.first || (a.first == b.first && a.second->first < b.second->first);
  });
  std::vector<PlaceMatch> out;
  for (size_t i = 0; i < scored.size() && i < max; ++i) {
    const auto& [visit_id, entry] = *scored[i].second;
    PlaceMatch m;
    m.map_id = entry.map_id;
    m.map = entry.map;
    m.visit_id = visit_id;
    m.score = scored[i].first;
    out.push_back(std::move(m));
  }
  return out;
}

absl::Status PlaceIndex::Put(int64_t visit_id, int64_t map_id, const std::string& map,
                             const place::FloorPlan& plan, const place::PlaceDescriptor& descriptor,
                             double now_s) {
  store::VisitPlaceRecord r;
  r.visit_id = visit_id;
  r.keyframes = plan.keyframes;
  r.floor_plan_json = place::FloorPlanToJson(plan);
  r.descriptor_json = place::DescriptorToJson(descriptor);
  r.updated_time_s = now_s;
  if (auto s = store_->PutVisitPlace(r); !s.ok()) return s;
  absl::MutexLock lock(&mu_);
  if (loaded_) visits_[visit_id] = {map_id, map, descriptor};
  return absl::OkStatus();
}

place::FloorPlanOptions ServedPlanOptions() {
  place::FloorPlanOptions o;
  o.up_from_floor = true;
  return o;
}

void PlaceIndex::Invalidate() {
  absl::MutexLock lock(&mu_);
  loaded_ = false;
  visits_.clear();
}

bool FoldArchitectureKeyframe(const cv::Mat& depth_m, const CameraIntrinsics& k,
                              const Pose& T_world_camera, VisitArchitecture* arch) {
  const absl::Status s = arch->builder.AddDepthKeyframe(depth_m, k, T_world_camera);
  if (!s.ok()) arch->SetStatus(s);
  return s.ok();
}

void UpdateArchitectureRanking(PlaceIndex* index, int64_t visit_id, int64_t map_id,
                               const std::string& map, bool store, VisitArchitecture* arch) {
  auto plan = arch->builder.Build();
  if (!plan.ok()) {
    arch->SetStatus(plan.status());
    return;
  }
  const place::PlaceDescriptor descriptor = place::Describe(*plan);
  if (store) {
    const double now = NowSeconds();
    if (auto s = index->Put(visit_id, map_id, map, *plan, descriptor, now); !s.ok()) {
      arch->SetStatus(s);
      return;
    }
  }
  auto ranked = index->Rank(descriptor, visit_id, kFramePlaceMatches);
  if (!ranked.ok()) {
    arch->SetStatus(ranked.status());
    return;
  }
  absl::MutexLock lock(&arch->mu);
  arch->ranking.matches = *std::move(ranked);
  arch->ranking.status = absl::OkStatus();
}

void RebuildArchitecture(store::Store* store, PlaceIndex* index, int64_t map_id, int64_t visit_id,
                         const std::string& map, bool store_plan, VisitArchitecture* arch) {
  arch->builder = place::FloorPlanBuilder(ServedPlanOptions());
  int folded = 0;
  auto s = store->ForEachKeyframeWithImages(
      map_id, visit_id, [&](const store::KeyframeRecord& k) -> absl::Status {
        if (!k.T_world_camera) return absl::OkStatus();
        auto d = DecodeDepthMetres(store::StoredDepth(k));
        // A damaged image does not stop the others.
        if (d.ok() && FoldArchitectureKeyframe(*d, k.intrinsics, *k.T_world_camera, arch)) {
          ++folded;
        }
        return absl::OkStatus();
      });
  if (!s.ok()) {
    arch->SetStatus(s);
    return;
  }
  if (folded > 0) UpdateArchitectureRanking(index, visit_id, map_id, map, store_plan, arch);
}

ArchitectureWorker::ArchitectureWorker(store::Store* store, PlaceIndex* index)
    : store_(store), index_(index) {}

uint64_t ArchitectureWorker::Submit(Visit visit, cv::Mat depth_m, const CameraIntrinsics& k,
                                    const Pose& T_world_camera) {
  return worker_.Submit([this, v = std::move(visit), depth = std::move(depth_m), k,
                         T_world_camera] {
    // A pose from before the visit's frame changed would mix two frames in one plan.
    if (v.frame_generation < v.arch->frame_generation) {
      ++v.arch->stale_key_frames;
      return;
    }
    v.arch->frame_generation = v.frame_generation;
    if (FoldArchitectureKeyframe(depth, k, T_world_camera, v.arch)) {
      UpdateArchitectureRanking(index_, v.visit_id, v.map_id, v.map_name(), /*store=*/true, v.arch);
    }
  });
}

uint64_t ArchitectureWorker::SubmitRebuild(Visit visit) {
  return worker_.Submit([this, v = std::move(visit)] {
    v.arch->frame_generation = std::max(v.arch->frame_generation, v.frame_generation);
    RebuildArchitecture(store_, index_, v.map_id, v.visit_id, v.map_name(), /*store_plan=*/true,
                        v.arch);
  });
}

absl::StatusOr<place::FloorPlan> ArchitectureWorker::PlanAtEnd(Visit visit) {
  absl::StatusOr<place::FloorPlan> plan = absl::UnknownError("not built");
  worker_.Wait(worker_.Submit([this, &plan, v = std::move(visit)] {
    if (v.arch->frame_generation != v.frame_generation || v.arch->stale_key_frames > 0) {
      v.arch->frame_generation = v.frame_generation;
      v.arch->stale_key_frames = 0;
      RebuildArchitecture(store_, index_, v.map_id, v.visit_id, v.map_name(), /*store_plan=*/true,
                          v.arch);
    }
    plan = v.arch->builder.Build();
  }));
  return plan;
}

void ArchitectureWorker::Wait(uint64_t ticket) { worker_.Wait(ticket); }

uint64_t ArchitectureWorker::last_ticket() const { return worker_.last_ticket(); }

}  // namespace lifemap::server
