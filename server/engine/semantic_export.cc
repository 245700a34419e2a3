#include "server/engine/semantic_export.h"

#include <algorithm>
#include <optional>
#include <utility>

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/forest/forest.h"
#include "server/engine/semantics.h"
#include "server/engine/visit_frame.h"
#include "spdlog/spdlog.h"

namespace lifemap::server {
namespace {

bool IsIdentity(const Pose& T) {
  return T.translation.isZero(0) && T.rotation.coeffs() == Eigen::Quaterniond::Identity().coeffs();
}

// The listed snapshot header of visit `visit_id`, or nullptr when it has none.
const store::SemanticSnapshotRecord* HeaderOf(
    const std::vector<store::SemanticSnapshotRecord>& headers, int64_t visit_id) {
  auto h =
      std::find_if(headers.begin(), headers.end(),
                   [&](const store::SemanticSnapshotRecord& r) { return r.visit_id == visit_id; });
  return h == headers.end() ? nullptr : &*h;
}

// What a map's octree is merged from: each visit's snapshot (when it was made, what it holds)
// and where the visit's frame lies in the map's. A stored map octree whose sources differ is
// out of date.
std::string Sources(const std::vector<store::VisitRecord>& visits,
                    const std::vector<store::SemanticSnapshotRecord>& headers) {
  std::string out;
  for (const auto& v : visits) {
    const store::SemanticSnapshotRecord* h = HeaderOf(headers, v.id);
    if (h == nullptr) continue;
    absl::StrAppend(&out, v.id, "@", absl::StrFormat("%.6f", h->updated_time_s), " ", h->model, " ",
                    h->resolution_m, " ");
    if (std::optional<Pose> T = MapFromVisit(v); !T) {
      absl::StrAppend(&out, "unanchored");
    } else {
      const Eigen::Quaterniond& q = T->rotation;
      absl::StrAppend(&out, absl::StrFormat("%.6f %.6f %.6f %.9f %.9f %.9f %.9f",
                                            T->translation.x(), T->translation.y(),
                                            T->translation.z(), q.x(), q.y(), q.z(), q.w()));
    }
    out += ";";
  }
  return out;
}

// Merges the chosen visits' stored octrees into `out` (see CollectSemanticExport).
absl::Status MergeVisits(store::Store* store, const store::MapRecord& map,
                         const std::vector<store::VisitRecord>& chosen,
                         const std::vector<store::SemanticSnapshotRecord>& headers,
                         int64_t visit_id, semantic::SemanticMapOptions options,
                         SemanticExport* out) {
  struct Stored {
    store::VisitRecord visit;
    store::SemanticSnapshotRecord header;
  };
  std::vector<Stored> stored;
  for (const auto& v : chosen) {
    const store::SemanticSnapshotRecord* h = HeaderOf(headers, v.id);
    if (h == nullptr) {
      out->left_out.push_back(absl::StrCat("visit ", v.id, ": no semantic octree"));
      continue;
    }
    stored.push_back({v, *h});
  }
  if (stored.empty()) {
    return absl::FailedPreconditionError(absl::StrCat(
        visit_id != 0 ? absl::StrCat("visit ", visit_id) : absl::StrCat("map '", map.name, "'"),
        " has no semantic octree: stream posed frames with a model active (lifemap models "
        "activate) and semantic.enabled in the server's config, or rebuild it from the stored "
        "keyframes (lifemap maps rebuild-octree); for occupancy alone, without a model: "
        "lifemap export --what occupancy (ExportMap's format EXPORT_OCCUPANCY_OCTREE_BT)"));
  }
  // The most recently updated octree's model decides which octrees merge.
  const Stored* newest = &stored.front();
  for (const auto& s : stored) {
    if (s.header.updated_time_s > newest->header.updated_time_s) newest = &s;
  }
  out->model = newest->header.model;
  options.resolution_m = newest->header.resolution_m;
  for (const auto& s : stored) {
    if (s.header.model != out->model || s.header.resolution_m != options.resolution_m) {
      out->left_out.push_back(absl::StrCat(
          "visit ", s.visit.id, ": its octree holds model '", s.header.model, "' at ",
          s.header.resolution_m, " m, not '", out->model, "' at ", options.resolution_m, " m"));
      continue;
    }
    std::optional<Pose> T_map_visit = MapFromVisit(s.visit);
    if (!T_map_visit) {
      if (visit_id == 0) {
        out->left_out.push_back(absl::StrCat("visit ", s.visit.id,
                                             ": tracked and not anchored in the map's frame yet"));
        continue;
      }
      out->in_map_frame = false;  // the one visit asked for, in its own frame
      T_map_visit = Pose{};
    }
    auto snapshot = store->GetSemanticSnapshot(s.visit.id);
    if (!snapshot.ok()) return snapshot.status();
    auto octree = semantic::SemanticMap::Deserialize(snapshot->bytes, options);
    if (!octree.ok()) {
      return absl::DataLossError(absl::StrCat(
          "visit ", s.visit.id, "'s stored semantic octree: ", octree.status().message()));
    }
    if (out->map == nullptr && IsIdentity(*T_map_visit)) {
      out->map = *std::move(octree);
    } else {
      if (out->map == nullptr) {
        auto empty = semantic::SemanticMap::Create(
            (*octree)->class_count(),
            std::vector<double>(static_cast<size_t>((*octree)->class_count()), 1.0), options);
        if (!empty.ok()) return empty.status();
        out->map = *std::move(empty);
      }
      if (auto st = out->map->Merge(**octree, *T_map_visit); !st.ok()) return st;
    }
    out->visits.push_back(s.visit.id);
  }
  if (out->map == nullptr) {
    return absl::FailedPreconditionError(
        absl::StrCat("no semantic octree of map '", map.name, "' is in the map's frame yet (",
                     out->left_out.size(), " left out: ", out->left_out.front(),
                     "); export one visit with --visit to get it in its own frame"));
  }
  return absl::OkStatus();
}

// The class names and colours of the export's model ("class N" if it was deleted since).
void NameClasses(store::Store* store, SemanticExport* out) {
  const int classes = out->map->class_count();
  auto model = store->GetModel(out->model);
  for (int c = 0; c < classes; ++c) {
    const bool named = model.ok() && static_cast<size_t>(c) < model->class_names.size();
    out->class_names.push_back(named ? model->class_names[static_cast<size_t>(c)]
                                     : absl::StrCat("class ", c));
    out->class_colors.push_back(named && static_cast<size_t>(c) < model->class_colors.size()
                                    ? model->class_colors[static_cast<size_t>(c)]
                                    : forest::DefaultClassColor(c));
  }
}

}  // namespace

absl::StatusOr<SemanticExport> CollectSemanticExport(store::Store* store, VisitRegistry* visits,
                                                     SerialWorker* worker,
                                                     const store::MapRecord& map, int64_t visit_id,
                                                     semantic::SemanticMapOptions options) {
  auto records = store->ListVisits(map.name);
  if (!records.ok()) return records.status();
  std::vector<store::VisitRecord> chosen;
  for (const auto& v : *records) {
    if (visit_id == 0 || v.id == visit_id) chosen.push_back(v);
  }
  // Live visits: their latest fusions into the store first.
  if (worker != nullptr) {
    for (const auto& v : chosen) {
      if (auto state = visits->Loaded(v.id); state != nullptr) {
        worker->Wait(QueueSemanticSnapshot(worker, store, state));
      }
    }
  }
  auto headers = store->ListSemanticSnapshots(map.id);
  if (!headers.ok()) return headers.status();
  // Only the map's octree is stored, with what it was merged from.
  const std::string sources = visit_id == 0 ? Sources(chosen, *headers) : "";
  SemanticExport out;
  if (visit_id == 0) {
    // The map's stored octree, when merged from the snapshots there are now.
    auto stored = store->GetMapSemanticSnapshot(map.id);
    if (stored.ok() && stored->sources == sources) {
      auto octree = semantic::SemanticMap::Deserialize(stored->octree.bytes, options);
      const auto merged =
          nlohmann::json::parse(stored->merged, nullptr, /*allow_exceptions=*/false);
      if (octree.ok() && merged.is_object()) {
        out.map = *std::move(octree);
        out.model = stored->octree.model;
        out.visits = merged.value("visits", std::vector<int64_t>{});
        out.left_out = merged.value("left_out", std::vector<std::string>{});
        out.stored = true;
        NameClasses(store, &out);
        return out;
      }
      spdlog::warn("map '{}': stored semantic octree unreadable; merged again", map.name);
    } else if (!stored.ok() && !absl::IsNotFound(stored.status())) {
      spdlog::warn("map '{}': stored semantic octree unreadable ({}); merged again", map.name,
                   std::string(stored.status().message()));
    }
  }
  if (auto s = MergeVisits(store, map, chosen, *headers, visit_id, options, &out); !s.ok()) {
    return s;
  }
  NameClasses(store, &out);
  if (visit_id == 0) {
    store::MapSemanticSnapshotRecord record;
    record.map_id = map.id;
    record.octree = SemanticSnapshotOf(0, out.model, *out.map);
    record.sources = sources;
    record.merged = nlohmann::json{{"visits", out.visits}, {"left_out", out.left_out}}.dump();
    if (auto s = store->PutMapSemanticSnapshot(record); !s.ok()) {
      spdlog::warn("map '{}': semantic octree not stored: {}", map.name, std::string(s.message()));
    }
  }
  return out;
}

void RefreshMapSemanticOctree(store::Store* store, const std::string& map_name,
                              const semantic::SemanticMapOptions& options) {
  auto map = store->GetMap(map_name);
  if (!map.ok()) return;  // deleted or renamed meanwhile: the next export merges
  auto merged = CollectSemanticExport(store, nullptr, nullptr, *map, 0, options);
  if (!merged.ok() && !absl::IsFailedPrecondition(merged.status())) {
    spdlog::warn("map '{}': semantic octree not merged: {}", map_name,
                 std::string(merged.status().message()));
  }
}

std::string SemanticExportSummaryJson(const SemanticExport& e) {
  const semantic::SemanticSummary s = e.map->Summarize();
  nlohmann::json volume = nlohmann::json::object();
  for (size_t c = 0; c < s.class_volume_m3.size() && c < e.class_names.size(); ++c) {
    volume[e.class_names[c]] = s.class_volume_m3[c];
  }
  nlohmann::json j = {
      {"model", e.model},
      {"frame", e.in_map_frame ? "map" : "visit"},
      {"resolution_m", s.resolution_m},
      {"classes", e.class_names},
      {"nodes", s.nodes},
      {"occupied_voxels", s.occupied_voxels},
      {"labelled_voxels", s.labelled_voxels},
      {"free_voxels", s.free_voxels},
      {"class_volume_m3", volume},
      {"memory_bytes", s.memory_bytes},
      {"keyframes", s.keyframes},
      {"bounds_m",
       {{"min", {s.min_m[0], s.min_m[1], s.min_m[2]}},
        {"max", {s.max_m[0], s.max_m[1], s.max_m[2]}}}},
      {"visits", e.visits},
      {"left_out", e.left_out},
      {"map_octree", e.stored ? "stored" : "merged now"},
  };
  return j.dump(2) + "\n";
}

}  // namespace lifemap::server
