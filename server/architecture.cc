#include "server/architecture.h"

#include <algorithm>
#include <chrono>

#include "absl/strings/str_cat.h"
#include "core/place/serialize.h"

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

absl::StatusOr<std::vector<v1::PlaceMatch>> PlaceIndex::Rank(const place::PlaceDescriptor& query,
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
  std::vector<v1::PlaceMatch> out;
  for (size_t i = 0; i < scored.size() && i < max; ++i) {
    v1::PlaceMatch m;
    m.set_map(scored[i].second->second.map);
    m.set_visit_id(static_cast<uint64_t>(scored[i].second->first));
    m.set_score(scored[i].first);
    m.set_method(v1::MATCH_METHOD_ARCHITECTURE);
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

void PlaceIndex::Invalidate() {
  absl::MutexLock lock(&mu_);
  loaded_ = false;
  visits_.clear();
}

bool FoldArchitectureKeyframe(const cv::Mat& depth_m, const CameraIntrinsics& k,
                              const Pose& T_world_camera, VisitArchitecture* arch) {
  const absl::Status s = arch->builder.AddDepthKeyframe(depth_m, k, T_world_camera);
  if (!s.ok()) arch->status = s;
  return s.ok();
}

void UpdateArchitectureRanking(PlaceIndex* index, int64_t visit_id, int64_t map_id,
                               const std::string& map, bool store, VisitArchitecture* arch) {
  auto plan = arch->builder.Build();
  if (!plan.ok()) {
    arch->status = plan.status();
    return;
  }
  const place::PlaceDescriptor descriptor = place::Describe(*plan);
  if (store) {
    const double now =
        std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
    if (auto s = index->Put(visit_id, map_id, map, *plan, descriptor, now); !s.ok()) {
      arch->status = s;
      return;
    }
  }
  auto ranked = index->Rank(descriptor, visit_id, kFramePlaceMatches);
  if (!ranked.ok()) {
    arch->status = ranked.status();
    return;
  }
  arch->matches = *std::move(ranked);
  arch->status = absl::OkStatus();
}

}  // namespace lifemap::server
