#include "server/semantic_export.h"

#include <optional>
#include <utility>

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "core/forest/forest.h"
#include "server/semantics.h"

namespace lifemap::server {
namespace {

// Where a visit's own frame lies in the map's; nullopt when it is not known (a tracked visit
// that no match has anchored yet).
std::optional<Pose> MapFromVisit(const store::VisitRecord& v) {
  if (v.anchor) return v.anchor->T_map_visit;
  if (v.first_of_map || v.tracked_keyframes == 0) return Pose{};
  return std::nullopt;
}

bool IsIdentity(const Pose& T) {
  return T.translation.isZero(0) && T.rotation.coeffs() == Eigen::Quaterniond::Identity().coeffs();
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
  struct Stored {
    store::VisitRecord visit;
    store::SemanticSnapshotRecord snapshot;
  };
  std::vector<Stored> stored;
  SemanticExport out;
  for (const auto& v : chosen) {
    auto snapshot = store->GetSemanticSnapshot(v.id);
    if (absl::IsNotFound(snapshot.status())) {
      out.left_out.push_back(absl::StrCat("visit ", v.id, ": no semantic octree"));
      continue;
    }
    if (!snapshot.ok()) return snapshot.status();
    stored.push_back({v, *std::move(snapshot)});
  }
  if (stored.empty()) {
    return absl::FailedPreconditionError(absl::StrCat(
        visit_id != 0 ? absl::StrCat("visit ", visit_id) : absl::StrCat("map '", map.name, "'"),
        " has no semantic octree: stream posed frames with a model active (lifemap models "
        "activate) and semantic.enabled in the server's config"));
  }
  // The most recently updated octree's model decides which octrees merge.
  const Stored* newest = &stored.front();
  for (const auto& s : stored) {
    if (s.snapshot.updated_time_s > newest->snapshot.updated_time_s) newest = &s;
  }
  out.model = newest->snapshot.model;
  options.resolution_m = newest->snapshot.resolution_m;
  for (const auto& s : stored) {
    if (s.snapshot.model != out.model || s.snapshot.resolution_m != options.resolution_m) {
      out.left_out.push_back(absl::StrCat(
          "visit ", s.visit.id, ": its octree holds model '", s.snapshot.model, "' at ",
          s.snapshot.resolution_m, " m, not '", out.model, "' at ", options.resolution_m, " m"));
      continue;
    }
    std::optional<Pose> T_map_visit = MapFromVisit(s.visit);
    if (!T_map_visit) {
      if (visit_id == 0) {
        out.left_out.push_back(absl::StrCat("visit ", s.visit.id,
                                            ": tracked and not anchored in the map's frame yet"));
        continue;
      }
      out.in_map_frame = false;  // the one visit asked for, in its own frame
      T_map_visit = Pose{};
    }
    auto octree = semantic::SemanticMap::Deserialize(s.snapshot.bytes, options);
    if (!octree.ok()) {
      return absl::DataLossError(absl::StrCat(
          "visit ", s.visit.id, "'s stored semantic octree: ", octree.status().message()));
    }
    if (out.map == nullptr && IsIdentity(*T_map_visit)) {
      out.map = *std::move(octree);
    } else {
      if (out.map == nullptr) {
        auto empty = semantic::SemanticMap::Create(
            (*octree)->class_count(),
            std::vector<double>(static_cast<size_t>((*octree)->class_count()), 1.0), options);
        if (!empty.ok()) return empty.status();
        out.map = *std::move(empty);
      }
      if (auto st = out.map->Merge(**octree, *T_map_visit); !st.ok()) return st;
    }
    out.visits.push_back(s.visit.id);
  }
  if (out.map == nullptr) {
    return absl::FailedPreconditionError(
        absl::StrCat("no semantic octree of map '", map.name, "' is in the map's frame yet (",
                     out.left_out.size(), " left out: ", out.left_out.front(),
                     "); export one visit with --visit to get it in its own frame"));
  }
  const int classes = out.map->class_count();
  auto model = store->GetModel(out.model);
  for (int c = 0; c < classes; ++c) {
    const bool named = model.ok() && static_cast<size_t>(c) < model->class_names.size();
    out.class_names.push_back(named ? model->class_names[static_cast<size_t>(c)]
                                    : absl::StrCat("class ", c));
    out.class_colors.push_back(named && static_cast<size_t>(c) < model->class_colors.size()
                                   ? model->class_colors[static_cast<size_t>(c)]
                                   : forest::DefaultClassColor(c));
  }
  return out;
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
  };
  return j.dump(2) + "\n";
}

}  // namespace lifemap::server
