// A visit's or a map's semantic octree for ExportMap (issue 16): read from the store's
// snapshots, in the map's frame where the visits' frames are known there.
//
// A visit's octree is kept in the visit's own frame (server/semantics.h). It lies in the map's
// frame when its poses came from the client (every visit of a map is then in one frame), when
// it is the map's first visit, or, tracked, once anchored (its T_map_visit). A map's octree
// merges every visit in the map's frame whose octree holds the same model as the most recently
// updated one; the others are listed as left out, with why. The map's octree is stored and kept
// current: merged again when a visit ends (RefreshMapSemanticOctree) or an export finds it out
// of date.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/semantic/semantic_map.h"
#include "server/engine/serial_worker.h"
#include "server/engine/visit_registry.h"
#include "server/store/store.h"

namespace lifemap::server {

struct SemanticExport {
  std::unique_ptr<semantic::SemanticMap> map;
  std::string model;                     // the model whose classes it holds
  std::vector<std::string> class_names;  // the model's ("class N" if it was deleted since)
  std::vector<uint32_t> class_colors;    // 0xRRGGBB per class
  bool in_map_frame = true;              // false: one visit, in its own frame (not anchored)
  std::vector<int64_t> visits;           // merged
  std::vector<std::string> left_out;     // visits not merged, each with why
  bool stored = false;  // the map's stored octree, current (else merged now, and stored)
};

// `visit_id` 0: the map's octree; else that visit's (which must be the map's). Visits loaded in
// `visits` are snapshotted first on `worker` (when given), so the export holds every keyframe
// fused so far. The map's octree is stored (schema 12) with what it was merged from: read back
// while no visit's snapshot or anchor has changed since, else merged again and stored.
// FAILED_PRECONDITION when no octree is stored (saying how to get one).
absl::StatusOr<SemanticExport> CollectSemanticExport(store::Store* store, VisitRegistry* visits,
                                                     SerialWorker* worker,
                                                     const store::MapRecord& map, int64_t visit_id,
                                                     semantic::SemanticMapOptions options);

// Merges the map's octree from its visits' snapshots and stores it, unless the stored one is
// current; failures are logged (the next export merges again). For the semantic worker, after a
// visit's final snapshot.
void RefreshMapSemanticOctree(store::Store* store, const std::string& map_name,
                              const semantic::SemanticMapOptions& options);

// The export as JSON: resolution, voxels, volume per class name, bytes, keyframes, frame,
// visits merged and left out.
std::string SemanticExportSummaryJson(const SemanticExport& e);

}  // namespace lifemap::server
