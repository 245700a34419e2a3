#include "server/visit_registry.h"

#include "absl/strings/str_cat.h"
#include "core/common/image_codec.h"

namespace lifemap::server {

absl::StatusOr<std::shared_ptr<VisitState>> VisitRegistry::Get(int64_t visit_id) {
  {
    absl::MutexLock lock(&mu_);
    auto it = visits_.find(visit_id);
    if (it != visits_.end()) return it->second;
  }
  auto visit = store_->GetVisit(visit_id);
  if (!visit.ok()) return visit.status();
  if (visit->ended) {
    return absl::FailedPreconditionError(
        absl::StrCat("visit ", visit_id, " has ended; start a new visit to stream more frames"));
  }
  auto last = store_->LastKeyframe(visit_id);
  if (!last.ok()) return last.status();
  auto state = std::make_shared<VisitState>();
  state->visit_id = visit_id;
  state->map_id = visit->map_id;
  state->map_name = visit->map_name;
  {
    absl::MutexLock lock(&state->mu);
    state->frame_count = visit->frame_count;
    if (*last) state->selector.Accept((*last)->timestamp_s, (*last)->T_world_camera);
    RebuildArchitecture(state.get());
  }
  absl::MutexLock lock(&mu_);
  auto [it, inserted] = visits_.emplace(visit_id, std::move(state));
  return it->second;  // another thread may have loaded it first: use that one
}

void VisitRegistry::RebuildArchitecture(VisitState* state) {
  VisitArchitecture& arch = state->architecture;
  int folded = 0;
  auto s = store_->ForEachKeyframeWithImages(
      state->map_id, state->visit_id, [&](const store::KeyframeRecord& k) -> absl::Status {
        if (!k.T_world_camera) return absl::OkStatus();
        EncodedDepth depth{DepthEncoding::kPng16, k.depth_png, k.intrinsics.width,
                           k.intrinsics.height, k.depth_scale};
        auto d = DecodeDepthMetres(depth);
        // A damaged image does not stop the others.
        if (d.ok() && FoldArchitectureKeyframe(*d, k.intrinsics, *k.T_world_camera, &arch)) {
          ++folded;
        }
        return absl::OkStatus();
      });
  if (!s.ok()) {
    arch.status = s;
    return;
  }
  if (folded > 0) {
    UpdateArchitectureRanking(places_, state->visit_id, state->map_id, state->map_name,
                              /*store=*/false, &arch);
  }
}

void VisitRegistry::Forget(int64_t visit_id) {
  absl::MutexLock lock(&mu_);
  visits_.erase(visit_id);
}

absl::StatusOr<std::optional<double>> VisitRegistry::MapEntropyThreshold(int64_t map_id) {
  {
    absl::MutexLock lock(&mu_);
    auto it = map_thresholds_.find(map_id);
    if (it != map_thresholds_.end()) return it->second;
  }
  auto map = store_->GetMapById(map_id);
  if (!map.ok()) return map.status();
  absl::MutexLock lock(&mu_);
  map_thresholds_[map_id] = map->entropy_threshold;
  return map->entropy_threshold;
}

void VisitRegistry::ForgetMap(int64_t map_id) {
  absl::MutexLock lock(&mu_);
  map_thresholds_.erase(map_id);
  for (auto it = visits_.begin(); it != visits_.end();) {
    it = it->second->map_id == map_id ? visits_.erase(it) : std::next(it);
  }
}

}  // namespace lifemap::server
