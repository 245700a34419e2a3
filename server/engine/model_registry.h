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

  // Stores model file `data` as `name` (a valid name; ALREADY_EXISTS when taken) once it
  // parses and its class names and training summary can be listed back (INVALID_ARGUMENT saying
  // what is wrong and that `lifemap train` writes usable files).
  absl::StatusOr<store::ModelRecord> Add(const std::string& name, const std::string& data);
  // Makes model `name` label the frames of `map` ("" : the server default); `name` "" clears
  // it. The model is loaded once first, so one that would fail on every frame fails here
  // (DATA_LOSS). Returns the model it replaced ("" : none).
  absl::StatusOr<std::string> Activate(const std::string& map, const std::string& name);
  // Deletes model `name` (NOT_FOUND; FAILED_PRECONDITION while it is active somewhere).
  absl::Status Delete(const std::string& name);

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
