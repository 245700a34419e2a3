// The models that label frames, loaded from the store once and shared by every stream; which
// one applies to a map is cached until an activation or deletion changes it.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <unordered_map>

#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "core/forest/forest.h"
#include "server/store/store.h"

namespace lifemap::server {

struct LoadedModel {
  std::string name;
  forest::Forest forest;
  forest::ModelDescription description;
};

// Thread-safe.
class ModelRegistry {
 public:
  explicit ModelRegistry(store::Store* store) : store_(store) {}

  // The model labelling frames of `map_id` (its own, else the server default; map_id 0: the
  // default). nullptr when none applies. DataLoss when the stored file no longer parses.
  absl::StatusOr<std::shared_ptr<const LoadedModel>> ForMap(int64_t map_id);

  // Drops cached activations and parsed models (after ActivateModel, DeleteModel, DeleteMap);
  // models are parsed again on their next use. Frames in flight keep their own reference.
  void InvalidateActivations();

 private:
  absl::StatusOr<std::shared_ptr<const LoadedModel>> Load(const std::string& name);

  store::Store* const store_;
  absl::Mutex mu_;
  // map id -> model name ("" = none).
  std::unordered_map<int64_t, std::string> active_ ABSL_GUARDED_BY(mu_);
  std::unordered_map<std::string, std::shared_ptr<const LoadedModel>> loaded_ ABSL_GUARDED_BY(mu_);
};

}  // namespace lifemap::server
