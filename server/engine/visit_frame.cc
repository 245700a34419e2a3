#include "server/engine/visit_frame.h"

#include "absl/strings/str_cat.h"

namespace lifemap::server {

std::optional<Pose> MapFromVisit(const store::VisitRecord& v) {
  if (v.anchor) return v.anchor->T_map_visit;
  if (v.first_of_map || v.tracked_keyframes == 0) return Pose{};
  return std::nullopt;
}

absl::StatusOr<MapFrameVisits> VisitsInMapFrame(store::Store* store, const std::string& map_name) {
  auto visits = store->ListVisits(map_name);
  if (!visits.ok()) return visits.status();
  MapFrameVisits out;
  for (const auto& v : *visits) {
    if (MapFromVisit(v)) {
      out.in_map_frame.insert(v.id);
    } else {
      out.left_out.push_back(
          v.anchor_dropped.empty()
              ? absl::StrCat("visit ", v.id,
                             ": tracked and not anchored in the map's frame yet (its poses are "
                             "in its own frame)")
              : absl::StrCat("visit ", v.id,
                             ": its anchor was dropped (its poses are in its own frame again): ",
                             v.anchor_dropped));
    }
  }
  return out;
}

absl::StatusOr<PosedKeyframes> ForEachPosedKeyframe(
    store::Store* store, int64_t map_id, const std::string& map_name, int64_t visit_id,
    const std::function<bool()>& cancelled,
    const std::function<absl::Status(const store::KeyframeRecord&, const RgbdFrame&)>& use) {
  PosedKeyframes out;
  std::optional<MapFrameVisits> frame;
  if (visit_id == 0) {
    auto visits = VisitsInMapFrame(store, map_name);
    if (!visits.ok()) return visits.status();
    frame = *std::move(visits);
    out.left_out = frame->left_out;
  }
  const absl::Status st = store->ForEachKeyframeWithImages(
      map_id, visit_id, [&](const store::KeyframeRecord& k) -> absl::Status {
        if (cancelled && cancelled()) return absl::CancelledError("export cancelled");
        if (!k.T_world_camera) return absl::OkStatus();
        if (frame && frame->in_map_frame.count(k.visit_id) == 0) return absl::OkStatus();
        auto decoded = DecodeRgbdFrame(store::StoredFrame(k));
        if (!decoded.ok()) {
          return absl::DataLossError(absl::StrCat(
              "stored keyframe ", k.id, " cannot be decoded: ", decoded.status().message()));
        }
        ++out.used;
        return use(k, *decoded);
      });
  if (!st.ok()) return st;
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
