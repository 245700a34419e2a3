#include "server/engine/visit_changes.h"

#include <algorithm>
#include <chrono>
#include <map>
#include <utility>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "core/common/image_codec.h"
#include "server/engine/semantic_export.h"
#include "server/engine/visit_frame.h"

namespace lifemap::server {
namespace {

// Keyframes decoded in batches: bounded memory on long visits, both cores busy.
constexpr size_t kDecodeBatch = 32;

// The visit's octree in the map's frame, if a model labelled it; else why not.
struct Classes {
  SemanticExport octree;
  std::string why_not;
};
Classes ClassesOf(store::Store* store, VisitRegistry* visits, SerialWorker* worker,
                  const store::MapRecord& map, int64_t visit_id,
                  const semantic::SemanticMapOptions& options) {
  Classes out;
  auto e = CollectSemanticExport(store, visits, worker, map, visit_id, options);
  if (!e.ok()) {
    out.why_not = absl::StrCat("visit ", visit_id, ": ", e.status().message());
  } else {
    out.octree = *std::move(e);
  }
  return out;
}

// The class most of the voxels' beliefs put first ("" where none has one).
std::string VotedClass(const Classes& c, const std::vector<Eigen::Vector3d>& voxels) {
  if (c.octree.map == nullptr) return "";
  std::map<size_t, int> votes;
  for (const auto& p : voxels) {
    const std::vector<float> belief = c.octree.map->BeliefAt(p.x(), p.y(), p.z());
    if (belief.empty()) continue;
    ++votes[static_cast<size_t>(std::max_element(belief.begin(), belief.end()) - belief.begin())];
  }
  if (votes.empty()) return "";
  const auto best = std::max_element(
      votes.begin(), votes.end(), [](const auto& a, const auto& b) { return a.second < b.second; });
  return best->first < c.octree.class_names.size() ? c.octree.class_names[best->first]
                                                   : absl::StrCat("class ", best->first);
}

}  // namespace

absl::StatusOr<std::vector<change::PosedDepth>> LoadVisitDepth(
    store::Store* store, int64_t map_id, int64_t visit_id, int pixel_stride,
    const std::function<bool()>& cancelled) {
  std::vector<change::PosedDepth> out;
  std::vector<store::KeyframeRecord> batch;
  auto flush = [&]() -> absl::Status {
    std::vector<absl::StatusOr<change::PosedDepth>> decoded(batch.size(),
                                                            absl::UnknownError("not decoded"));
    cv::parallel_for_(cv::Range(0, static_cast<int>(batch.size())), [&](const cv::Range& r) {
      for (int i = r.start; i < r.end; ++i) {
        const store::KeyframeRecord& k = batch[static_cast<size_t>(i)];
        auto depth = DecodeDepthMetres(store::StoredDepth(k));
        if (!depth.ok()) {
          decoded[static_cast<size_t>(i)] = absl::DataLossError(absl::StrCat(
              "stored keyframe ", k.id, "'s depth cannot be decoded: ", depth.status().message()));
          continue;
        }
        decoded[static_cast<size_t>(i)] =
            change::Subsample(*depth, k.intrinsics, pixel_stride, *k.T_world_camera);
      }
    });
    for (auto& d : decoded) {
      if (!d.ok()) return d.status();
      out.push_back(*std::move(d));
    }
    batch.clear();
    return absl::OkStatus();
  };
  absl::Status st = store->ForEachKeyframeWithImages(
      map_id, visit_id, [&](const store::KeyframeRecord& k) -> absl::Status {
        if (cancelled && cancelled()) return absl::CancelledError("comparison cancelled");
        if (!k.T_world_camera) return absl::OkStatus();
        batch.push_back(k);
        return batch.size() >= kDecodeBatch ? flush() : absl::OkStatus();
      });
  if (st.ok()) st = flush();
  if (!st.ok()) return st;
  return out;
}

absl::StatusOr<VisitChanges> CompareVisits(store::Store* store, VisitRegistry* visits,
                                           SerialWorker* worker, const store::MapRecord& map,
                                           int64_t from_visit, int64_t to_visit,
                                           const VisitChangeOptions& options,
                                           const semantic::SemanticMapOptions& semantic_options,
                                           const std::function<bool()>& cancelled) {
  const auto start = std::chrono::steady_clock::now();
  if (from_visit == to_visit) {
    return absl::InvalidArgumentError(
        absl::StrCat("from and to are both visit ", from_visit, ": compare two visits"));
  }
  if (options.pixel_stride < 1 || options.pixel_stride > 16) {
    return absl::InvalidArgumentError(
        absl::StrCat("pixel_stride must lie in [1, 16], not ", options.pixel_stride));
  }
  if (auto s = options.change.Validate(); !s.ok()) return s;
  for (int64_t id : {from_visit, to_visit}) {
    // The same answer whether the visit is another map's or none at all: the caller's key may
    // not see the other map, so its name (or that it exists) is not told (issue 52).
    auto v = store->GetVisit(id);
    if ((!v.ok() && absl::IsNotFound(v.status())) || (v.ok() && v->map_id != map.id)) {
      return absl::NotFoundError(absl::StrCat("visit ", id, " is not a visit of map '", map.name,
                                              "': `lifemap visits list ", map.name,
                                              "` lists its visits"));
    }
    if (!v.ok()) return v.status();
  }
  auto frame = VisitsInMapFrame(store, map.name);
  if (!frame.ok()) return frame.status();
  for (int64_t id : {from_visit, to_visit}) {
    if (frame->in_map_frame.count(id) != 0) continue;
    std::string why = "it is not in the map's frame";
    for (const auto& l : frame->left_out) {
      if (absl::StartsWith(l, absl::StrCat("visit ", id, ":"))) why = l;
    }
    return absl::FailedPreconditionError(absl::StrCat(
        "visit ", id, " of map '", map.name, "' is not anchored, so its changes cannot be told (",
        why, "); anchor it first (lifemap visits anchor ", map.name, " ", id, ")"));
  }
  VisitChanges out;
  out.from_visit = from_visit;
  out.to_visit = to_visit;
  auto from = LoadVisitDepth(store, map.id, from_visit, options.pixel_stride, cancelled);
  if (!from.ok()) return from.status();
  auto to = LoadVisitDepth(store, map.id, to_visit, options.pixel_stride, cancelled);
  if (!to.ok()) return to.status();
  for (const auto& [id, views] : {std::pair{from_visit, &*from}, std::pair{to_visit, &*to}}) {
    if (views->empty()) {
      return absl::FailedPreconditionError(
          absl::StrCat("visit ", id, " of map '", map.name, "' has no posed keyframe to compare"));
    }
  }
  out.from_keyframes = static_cast<int64_t>(from->size());
  out.to_keyframes = static_cast<int64_t>(to->size());
  auto changes = change::DetectObjectChanges(*from, *to, options.change);
  if (!changes.ok()) return changes.status();

  // Classes: what is there now from the later visit's octree, what went from the earlier's.
  const Classes later = ClassesOf(store, visits, worker, map, to_visit, semantic_options);
  const Classes earlier = ClassesOf(store, visits, worker, map, from_visit, semantic_options);
  out.classes = later.octree.map != nullptr ? absl::StrCat("model '", later.octree.model, "'")
                                            : absl::StrCat("no classes: ", later.why_not);
  for (auto& o : changes->objects) {
    ChangedObject c;
    const bool gone =
        o.kind == change::ChangeKind::kVanished || o.kind == change::ChangeKind::kDoorOpened;
    c.class_name = VotedClass(gone ? earlier : later, o.voxel_centers);
    c.change = std::move(o);
    out.objects.push_back(std::move(c));
  }
  changes->objects.clear();
  out.tallies = *std::move(changes);
  out.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return out;
}

}  // namespace lifemap::server
