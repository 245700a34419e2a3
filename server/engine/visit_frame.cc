#include "server/engine/visit_frame.h"

#include <algorithm>

#include "absl/strings/str_cat.h"

namespace lifemap::server {

std::optional<Pose> MapFromVisit(const store::VisitRecord& v) {
  if (v.anchor) return v.anchor->T_map_visit;
  if (v.first_of_map || v.tracked_keyframes == 0) return Pose{};
  return std::nullopt;
}

std::string WhyNotInMapFrame(const store::VisitRecord& v) {
  return v.anchor_dropped.empty()
             ? "tracked and not anchored in the map's frame yet (its poses are in its own frame)"
             : absl::StrCat("its anchor was dropped (its poses are in its own frame again): ",
                            v.anchor_dropped);
}

absl::StatusOr<MapFrameVisits> VisitsInMapFrame(store::Store* store, const std::string& map_name) {
  auto visits = store->ListVisits(map_name);
  if (!visits.ok()) return visits.status();
  MapFrameVisits out;
  for (const auto& v : *visits) {
    if (MapFromVisit(v)) {
      out.in_map_frame.insert(v.id);
    } else {
      out.left_out.push_back(absl::StrCat("visit ", v.id, ": ", WhyNotInMapFrame(v)));
    }
  }
  return out;
}

absl::StatusOr<PosedKeyframes> ForEachPosedKeyframe(
    store::Store* store, int64_t map_id, const std::string& map_name, int64_t visit_id,
    const std::function<bool()>& cancelled,
    const std::function<absl::Status(const store::KeyframeRecord&, const RgbdFrame&)>& use,
    int64_t keyframe_stride) {
  PosedKeyframes out;
  std::optional<MapFrameVisits> frame;
  if (visit_id == 0) {
    auto visits = VisitsInMapFrame(store, map_name);
    if (!visits.ok()) return visits.status();
    frame = *std::move(visits);
    out.left_out = frame->left_out;
  }
  // The listing first (no images): keyframes without a pose or out of the map's frame are
  // passed over before their images are read; then one keyframe at a time, every
  // `keyframe_stride`-th of those used.
  auto listed = store->ListKeyframes(map_id, visit_id);
  if (!listed.ok()) return listed.status();
  const int64_t stride = std::max<int64_t>(1, keyframe_stride);
  int64_t usable = 0;
  for (const store::KeyframeRecord& summary : *listed) {
    if (cancelled && cancelled()) return absl::CancelledError("export cancelled");
    if (!summary.T_world_camera) continue;
    if (frame && frame->in_map_frame.count(summary.visit_id) == 0) continue;
    if (usable++ % stride != 0) continue;
    auto k = store->GetKeyframe(map_id, summary.id);
    if (absl::IsNotFound(k.status())) continue;  // deleted meanwhile
    if (!k.ok()) return k.status();
    if (!k->T_world_camera) continue;
    auto decoded = DecodeRgbdFrame(store::StoredFrame(*k));
    if (!decoded.ok()) {
      return absl::DataLossError(absl::StrCat("stored keyframe ", k->id,
                                              " cannot be decoded: ", decoded.status().message()));
    }
    ++out.used;
    if (auto s = use(*k, *decoded); !s.ok()) return s;
  }
  if (out.used == 0 && !out.left_out.empty()) {
    return absl::FailedPreconditionError(
        absl::StrCat("no posed keyframe of map '", map_name, "' is in the map's frame (",
                     out.left_out.size(), " visits left out: ", out.left_out.front(),
                     "); export one visit with --visit to get it in its own frame"));
  }
  if (out.used == 0) {
    return absl::FailedPreconditionError(absl::StrCat(
        "no keyframe of map '", map_name,
        "' has a pose; stream with poses (lifemap stream --use-groundtruth) to export it"));
  }
  return out;
}

}  // namespace lifemap::server
