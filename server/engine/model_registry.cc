#include "server/engine/model_registry.h"

#include "absl/strings/str_cat.h"

namespace lifemap::server {

absl::StatusOr<std::shared_ptr<const LoadedModel>> ModelRegistry::ForMap(int64_t map_id) {
  std::string name;
  bool cached = false;
  {
    absl::MutexLock lock(&mu_);
    if (auto it = active_.find(map_id); it != active_.end()) {
      name = it->second;
      cached = true;
    }
  }
  if (!cached) {
    auto active = store_->ActiveModelName(map_id);
    if (!active.ok()) return active.status();
    name = *active;
    absl::MutexLock lock(&mu_);
    active_[map_id] = name;
  }
  if (name.empty()) return std::shared_ptr<const LoadedModel>();
  return Load(name);
}

absl::StatusOr<std::shared_ptr<const LoadedModel>> ModelRegistry::Load(const std::string& name) {
  {
    absl::MutexLock lock(&mu_);
    if (auto it = loaded_.find(name); it != loaded_.end()) return it->second;
  }
  // Parsed outside the lock: a large model takes a while, and other maps' frames go on.
  auto bytes = store_->GetModelData(name);
  if (!bytes.ok()) return bytes.status();
  auto model = std::make_shared<LoadedModel>();
  model->name = name;
  auto forest = forest::Forest::Deserialize(*bytes, &model->description);
  if (!forest.ok()) {
    return absl::DataLossError(
        absl::StrCat("stored model '", name, "' does not load: ", forest.status().message()));
  }
  model->forest = *std::move(forest);
  absl::MutexLock lock(&mu_);
  auto [it, inserted] = loaded_.emplace(name, std::move(model));
  return it->second;
}

void ModelRegistry::InvalidateActivations() {
  absl::MutexLock lock(&mu_);
  active_.clear();
  loaded_.clear();
}

}  // namespace lifemap::server
