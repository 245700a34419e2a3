#include "server/engine/model_registry.h"

#include <spdlog/spdlog.h>

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "server/engine/clock.h"

namespace lifemap::server {
namespace {

// What the server requires of a model beyond parsing: names it can print and store.
absl::Status ValidateDescription(const forest::ModelDescription& d) {
  for (size_t c = 0; c < d.class_names.size(); ++c) {
    const std::string& n = d.class_names[c];
    if (n.empty() || n.size() > 64) {
      return absl::InvalidArgumentError(
          absl::StrCat("class ", c, " has a name of ", n.size(), " bytes; names need 1 to 64"));
    }
    for (char ch : n) {
      if (static_cast<unsigned char>(ch) < 0x20 || ch == 0x7f) {
        return absl::InvalidArgumentError(
            absl::StrCat("class ", c, "'s name contains a control character"));
      }
    }
  }
  if (!nlohmann::json::accept(d.training_json)) {
    return absl::InvalidArgumentError("the model's training summary is not valid JSON");
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<store::ModelRecord> ModelRegistry::Add(const std::string& name,
                                                      const std::string& data) {
  if (auto s = store::ValidateName(name, "model"); !s.ok()) return s;
  forest::ModelDescription description;
  auto forest = forest::Forest::Deserialize(data, &description);
  if (!forest.ok()) {
    return absl::InvalidArgumentError(absl::StrCat("not a usable model file (", data.size(),
                                                   " bytes): ", forest.status().message(),
                                                   "; upload a file written by `lifemap train`"));
  }
  if (auto s = ValidateDescription(description); !s.ok()) return s;
  store::ModelRecord record;
  record.name = name;
  record.uploaded_time_s = NowSeconds();
  record.class_names = description.class_names;
  record.class_colors = description.class_colors;
  record.training_json = description.training_json;
  record.trees = forest->tree_count();
  record.nodes = static_cast<int64_t>(forest->node_count());
  auto stored = store_->InsertModel(record, data);
  if (!stored.ok()) return stored.status();
  spdlog::info("model '{}' uploaded: {} bytes, {} classes, {} trees", name, data.size(),
               description.class_names.size(), record.trees);
  return stored;
}

absl::StatusOr<std::string> ModelRegistry::Activate(const std::string& map,
                                                    const std::string& name) {
  if (!name.empty()) {
    if (auto s = store::ValidateName(name, "model"); !s.ok()) return s;
    // Loads it once now, so a model that would fail on every frame fails here instead.
    auto bytes = store_->GetModelData(name);
    if (!bytes.ok()) return bytes.status();
    if (auto f = forest::Forest::Deserialize(*bytes, nullptr); !f.ok()) {
      return absl::DataLossError(
          absl::StrCat("stored model '", name, "' does not load: ", f.status().message()));
    }
  }
  auto previous = store_->ActivateModel(map, name);
  if (!previous.ok()) return previous.status();
  InvalidateActivations();
  return previous;
}

absl::Status ModelRegistry::Delete(const std::string& name) {
  if (auto s = store::ValidateName(name, "model"); !s.ok()) return s;
  if (auto s = store_->DeleteModel(name); !s.ok()) return s;
  InvalidateActivations();
  return absl::OkStatus();
}

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
