// PlaceService: architecture-based place recognition (paper 004) over stored visits.
#include "absl/strings/str_cat.h"
#include "core/common/rgbd_frame.h"
#include "core/place/floor_plan.h"
#include "core/place/serialize.h"
#include "server/convert.h"
#include "server/services.h"

namespace lifemap::server {

grpc::Status PlaceServiceImpl::QueryPlace(grpc::ServerContext*, const v1::QueryPlaceRequest* req,
                                          v1::QueryPlaceResponse* resp) {
  bool architecture = req->methods().empty();
  for (int m : req->methods()) {
    if (m == v1::MATCH_METHOD_ARCHITECTURE) architecture = true;
    if (m != v1::MATCH_METHOD_ARCHITECTURE && m != v1::MATCH_METHOD_APPEARANCE) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                          absl::StrCat("unknown match method ", m));
    }
  }
  if (!architecture) {
    return grpc::Status(grpc::StatusCode::UNIMPLEMENTED,
                        "appearance place recognition (paper 000) is not implemented in this "
                        "server yet; ask for MATCH_METHOD_ARCHITECTURE");
  }
  if (req->max_results() > 1000) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "max_results must be at most 1000");
  }
  const size_t max_results = req->max_results() == 0 ? 10 : req->max_results();
  if (!req->frames().empty()) {
    if (req->visit_id() != 0) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "give frames or visit_id, not both");
    }
    return QueryFrames(*req, max_results, resp);
  }
  if (req->visit_id() == 0) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        "give visit_id (a stored visit) or frames (posed key frames)");
  }
  auto visit = ctx_->store->GetVisit(static_cast<int64_t>(req->visit_id()));
  if (!visit.ok()) return ToGrpcStatus(visit.status());
  auto record = ctx_->store->GetVisitPlace(visit->id);
  if (absl::IsNotFound(record.status())) {
    // Say why, from the live visit when it is open.
    std::string why = "its floor plan has not closed yet (walls all around, floor seen)";
    if (!visit->ended) {
      auto state = ctx_->visits->Get(visit->id);
      if (state.ok()) {
        const absl::Status status = (*state)->architecture.Ranking().status;
        if (!status.ok()) why = std::string(status.message());
      }
    }
    return grpc::Status(grpc::StatusCode::FAILED_PRECONDITION,
                        absl::StrCat("visit ", visit->id, " has no floor plan: ", why));
  }
  if (!record.ok()) return ToGrpcStatus(record.status());
  auto descriptor = place::DescriptorFromJson(record->descriptor_json);
  if (!descriptor.ok()) return ToGrpcStatus(descriptor.status());
  auto ranked = ctx_->places->Rank(*descriptor, visit->id, max_results);
  if (!ranked.ok()) return ToGrpcStatus(ranked.status());
  for (const auto& m : *ranked) PlaceMatchToProto(m, resp->add_matches());
  resp->set_descriptor_text(place::DescriptorText(*descriptor));
  return grpc::Status::OK;
}

grpc::Status PlaceServiceImpl::QueryFrames(const v1::QueryPlaceRequest& req, size_t max_results,
                                           v1::QueryPlaceResponse* resp) {
  if (req.frames_size() > kMaxQueryFrames) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        absl::StrCat(req.frames_size(), " frames; send at most ", kMaxQueryFrames,
                                     " (the key frames of a recording)"));
  }
  // Nothing is stored: the frames fold into a plan of their own, ranked against stored visits.
  place::FloorPlanBuilder builder;
  for (int i = 0; i < req.frames_size(); ++i) {
    auto fail = [&](const absl::Status& s) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                          absl::StrCat("frames[", i, "]: ", s.message()));
    };
    auto encoded = FrameFromProto(req.frames(i), /*color_required=*/false);
    if (!encoded.ok()) return fail(encoded.status());
    if (!encoded->T_world_camera) {
      return fail(absl::InvalidArgumentError(
          "pose is missing; architecture needs each key frame's T_world_camera"));
    }
    auto frame =
        DecodeRgbdFrame(*encoded, /*decode_color=*/false, ctx_->pipeline->options().frame_limits);
    if (!frame.ok()) return fail(frame.status());
    if (auto s =
            builder.AddDepthKeyframe(frame->depth_m, frame->intrinsics, *encoded->T_world_camera);
        !s.ok()) {
      return fail(s);
    }
  }
  auto plan = builder.Build();
  if (!plan.ok()) {
    return grpc::Status(grpc::StatusCode::FAILED_PRECONDITION,
                        absl::StrCat("the frames give no floor plan: ", plan.status().message()));
  }
  const place::PlaceDescriptor descriptor = place::Describe(*plan);
  auto ranked = ctx_->places->Rank(descriptor, /*exclude_visit=*/0, max_results);
  if (!ranked.ok()) return ToGrpcStatus(ranked.status());
  for (const auto& m : *ranked) PlaceMatchToProto(m, resp->add_matches());
  resp->set_descriptor_text(place::DescriptorText(descriptor));
  return grpc::Status::OK;
}

grpc::Status PlaceServiceImpl::ListPlaces(grpc::ServerContext*, const v1::ListPlacesRequest* req,
                                          v1::ListPlacesResponse* resp) {
  if (!req->map().empty()) {
    if (auto s = store::ValidateMapName(req->map()); !s.ok()) return ToGrpcStatus(s);
    if (auto m = ctx_->store->GetMap(req->map()); !m.ok()) return ToGrpcStatus(m.status());
  }
  auto stored = ctx_->store->ListVisitPlaces(req->map());
  if (!stored.ok()) return ToGrpcStatus(stored.status());
  for (const auto& r : *stored) {
    auto* p = resp->add_places();
    p->set_map(r.map_name);
    p->set_visit_id(static_cast<uint64_t>(r.visit_id));
    p->set_keyframes(static_cast<uint32_t>(r.keyframes));
    p->set_floor_plan_json(r.floor_plan_json);
    p->set_descriptor_json(r.descriptor_json);
    if (auto d = place::DescriptorFromJson(r.descriptor_json); d.ok()) {
      p->set_descriptor_text(place::DescriptorText(*d));
    }
    p->set_updated_time_s(r.updated_time_s);
  }
  return grpc::Status::OK;
}

}  // namespace lifemap::server
