// Rebuilding visits' semantic octrees from their stored keyframes (issue 16): when a snapshot is
// missing (semantic fusion was off, no model was active, the server was killed between two
// snapshots), stale (another model labels the map now, another resolution in the config), or
// fused at poses a pose-graph solve has corrected since.
//
// Each posed keyframe of the visit is read from the store, labelled again by the map's model
// and fused in keyframe order into a new octree in the visit's own frame (stored poses of an
// anchored visit are in the map's frame: T_map_visit⁻¹ brings them back). The new octree
// replaces the stored snapshot and, for a visit open in this server, the one frames render
// from. A visit being streamed is left out: its keyframes arrive while the rebuild reads.
#pragma once

#include <cstdint>
#include <functional>
#include <optional>
#include <string>

#include "absl/status/status.h"
#include "core/semantic/semantic_map.h"
#include "server/engine/model_registry.h"
#include "server/engine/serial_worker.h"
#include "server/engine/visit_registry.h"
#include "server/store/store.h"

namespace lifemap::pipeline {
class FramePipeline;
}

namespace lifemap::server {

struct SemanticRebuild {
  enum class Outcome { kRebuilt, kUpToDate, kLeftOut };
  int64_t visit_id = 0;
  Outcome outcome = Outcome::kLeftOut;
  std::string reason;  // why rebuilt, why up to date, or why left out
  std::string model;
  int64_t keyframes_fused = 0;
  int64_t keyframes_skipped = 0;  // posed keyframes that could not be decoded, labelled or fused
  int64_t labelled_voxels = 0;
  int64_t bytes = 0;  // the stored snapshot's
  double seconds = 0;
};

// What a rebuild reads and writes. `worker` is the semantic worker: the new octree is put in
// place on it, so no live fusion of the visit runs in between.
struct SemanticRebuildContext {
  store::Store* store = nullptr;
  const pipeline::FramePipeline* pipeline = nullptr;
  VisitRegistry* visits = nullptr;
  SerialWorker* worker = nullptr;
  semantic::SemanticMapOptions options;
};

// Why a visit's stored octree does not hold what a rebuild would fuse ("" when it does):
// none stored, another model or resolution, or fewer keyframes than the visit has posed.
std::string SemanticStaleness(const std::optional<store::SemanticSnapshotRecord>& snapshot,
                              int64_t posed_keyframes, const std::string& model,
                              double resolution_m);

// Rebuilds the octree of each visit of `map` (or only `visit_id`, when not 0) that is stale, or
// every one with `all`; calls `done` with each visit's outcome as it is decided. Stops with
// CANCELLED when `cancelled` says so (the visit under way keeps its old snapshot), NOT_FOUND for
// a visit not of the map; a store error ends it.
absl::Status RebuildSemanticOctrees(const SemanticRebuildContext& ctx, const store::MapRecord& map,
                                    int64_t visit_id, bool all, const LoadedModel& model,
                                    const std::function<bool()>& cancelled,
                                    const std::function<void(const SemanticRebuild&)>& done);

}  // namespace lifemap::server
