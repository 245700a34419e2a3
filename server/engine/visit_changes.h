// What changed between two visits of one map (issue 36; GetChanges, `lifemap changes`): the
// visits' stored keyframes' depth, in the map's frame, compared by core/change, with each
// object's class from the visit's semantic octree where a model labelled it.
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/change/object_changes.h"
#include "core/semantic/semantic_map.h"
#include "server/engine/options.h"
#include "server/engine/serial_worker.h"
#include "server/engine/visit_registry.h"
#include "server/store/store.h"

namespace lifemap::server {

struct ChangedObject {
  change::ObjectChange change;
  std::string class_name;  // the most voted class of its voxels; "" where none is known
};

struct VisitChanges {
  int64_t from_visit = 0, to_visit = 0;
  std::vector<ChangedObject> objects;            // largest first
  change::ObjectChanges tallies;                 // the voxel counts (its `objects` are moved out)
  int64_t from_keyframes = 0, to_keyframes = 0;  // posed keyframes compared
  std::string classes;                           // "model 'M'", or why the objects have no class
  double seconds = 0;
};

// Compares visit `from_visit` (the earlier) with `to_visit` of `map`. NOT_FOUND for a visit that
// does not exist or is of another map; INVALID_ARGUMENT for the same visit twice;
// FAILED_PRECONDITION naming a visit not in the map's frame (and why) or without a posed
// keyframe; DATA_LOSS for a stored keyframe whose depth does not decode; CANCELLED when
// `cancelled` says so between keyframes. `visits` and `worker` (may be null) snapshot loaded
// visits' octrees first, as exports do (semantic_export.h).
absl::StatusOr<VisitChanges> CompareVisits(store::Store* store, VisitRegistry* visits,
                                           SerialWorker* worker, const store::MapRecord& map,
                                           int64_t from_visit, int64_t to_visit,
                                           const VisitChangeOptions& options,
                                           const semantic::SemanticMapOptions& semantic_options,
                                           const std::function<bool()>& cancelled);

// The posed keyframes of a visit, each its depth every `pixel_stride`-th pixel, at the pose
// stored. DATA_LOSS for a stored keyframe whose depth does not decode; CANCELLED when
// `cancelled` says so between keyframes.
absl::StatusOr<std::vector<change::PosedDepth>> LoadVisitDepth(
    store::Store* store, int64_t map_id, int64_t visit_id, int pixel_stride,
    const std::function<bool()>& cancelled);

}  // namespace lifemap::server
