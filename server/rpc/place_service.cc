// PlaceService: place recognition over stored visits, by architecture (paper 004) and by
// appearance (paper 000).
#include "absl/strings/str_cat.h"
#include "core/common/rgbd_frame.h"
#include "core/common/utf8.h"
#include "core/pipeline/keyframe.h"
#include "core/place/floor_plan.h"
#include "core/place/serialize.h"
#include "server/rpc/convert.h"
#include "server/rpc/services.h"

namespace lifemap::server {

grpc::Status PlaceServiceImpl::QueryPlace(grpc::ServerContext* context,
                                          const v1::QueryPlaceRequest* req,
                                          v1::QueryPlaceResponse* resp) {
  auto caller = ctx_->keys->Authorize(*context, "PlaceService/QueryPlace");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  bool architecture = req->methods().empty();
  bool appearance = req->methods().empty();
  for (int m : req->methods()) {
    if (m == v1::MATCH_METHOD_ARCHITECTURE) {
      architecture = true;
    } else if (m == v1::MATCH_METHOD_APPEARANCE) {
      appearance = true;
    } else {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                          absl::StrCat("unknown match method ", m,
                                       "; ask for MATCH_METHOD_ARCHITECTURE and/or "
                                       "MATCH_METHOD_APPEARANCE (empty = both)"));
    }
  }
  if (req->max_results() > 1000) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "max_results must be at most 1000");
  }
  const size_t max_results = req->max_results() == 0 ? 10 : req->max_results();
  if (!req->frames().empty() && req->visit_id() != 0) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "give frames or visit_id, not both");
  }
  if (req->frames().empty() && req->visit_id() == 0) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        "give visit_id (a stored visit) or frames (key frames of a recording)");
  }
  PlaceQuery query;
  query.architecture = architecture;
  query.appearance = appearance;
  query.max_results = max_results;
  query.may_use_map = [&caller](int64_t map_id) { return caller->MayUseMap(map_id); };
  query.stopped = [context] { return context->IsCancelled(); };
  absl::StatusOr<PlaceQueryResult> result;
  if (!req->frames().empty()) {
    if (req->frames_size() > kMaxQueryFrames) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                          absl::StrCat(req->frames_size(), " frames; send at most ",
                                       kMaxQueryFrames, " (the key frames of a recording)"));
    }
    if (appearance && req->frames_size() > kMaxAppearanceQueryFrames) {
      return grpc::Status(
          grpc::StatusCode::INVALID_ARGUMENT,
          absl::StrCat(req->frames_size(), " frames; appearance matches at most ",
                       kMaxAppearanceQueryFrames,
                       " per query (each costs its entropy mask, features and verification): "
                       "send key frames, or ask for MATCH_METHOD_ARCHITECTURE alone"));
    }
    // Every frame must decode whichever method is asked: a malformed frame fails the call.
    std::vector<EncodedRgbdFrame> frames;
    for (int i = 0; i < req->frames_size(); ++i) {
      auto encoded = FrameFromProto(req->frames(i), /*color_required=*/false);
      if (!encoded.ok()) {
        return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                            absl::StrCat("frames[", i, "]: ", encoded.status().message()));
      }
      frames.push_back(*std::move(encoded));
    }
    result = ctx_->engine->place_queries()->OfFrames(frames, query);
  } else {
    const auto visit_id = IdFromProto(req->visit_id(), "visit_id");
    if (!visit_id.ok()) return ToGrpcStatus(visit_id.status());
    auto visit = FindCallersVisit(ctx_->engine->store(), *caller, *visit_id);
    if (!visit.ok()) return ToGrpcStatus(visit.status());
    result = ctx_->engine->place_queries()->OfVisit(*visit, query);
  }
  if (!result.ok()) return ToGrpcStatus(result.status());
  const MethodOutcome& by_architecture = result->architecture;
  const MethodOutcome& by_appearance = result->appearance;
  // A single method's failure is the call's; with both, the call fails only when neither
  // answered.
  const bool any =
      (architecture && by_architecture.status.ok()) || (appearance && by_appearance.status.ok());
  if (!any) {
    if (architecture && appearance) {
      return grpc::Status(
          grpc::StatusCode::FAILED_PRECONDITION,
          absl::StrCat("architecture (paper 004): ", by_architecture.status.message(),
                       "; appearance (paper 000): ", by_appearance.status.message()));
    }
    return ToGrpcStatus(architecture ? by_architecture.status : by_appearance.status);
  }
  for (const auto& m : result->fused) PlaceMatchToProto(m, resp->add_matches());
  for (const auto* outcome : {&by_architecture, &by_appearance}) {
    for (const auto& m : outcome->matches) PlaceMatchToProto(m, resp->add_matches());
  }
  for (const auto& f : result->frames) {
    auto* entry = resp->add_frames();
    entry->set_index(static_cast<uint32_t>(f.index));
    entry->set_reason(f.reason);
    for (const auto& m : f.matches) PlaceMatchToProto(m, entry->add_matches());
  }
  resp->set_descriptor_text(by_architecture.descriptor_text);
  auto status = [resp](v1::MatchMethod method, const MethodOutcome& o) {
    auto* s = resp->add_method_status();
    s->set_method(method);
    s->set_computed(o.status.ok());
    if (!o.status.ok()) s->set_reason(ToValidUtf8(o.status.message()));
  };
  if (architecture) status(v1::MATCH_METHOD_ARCHITECTURE, by_architecture);
  if (appearance) status(v1::MATCH_METHOD_APPEARANCE, by_appearance);
  return grpc::Status::OK;
}

grpc::Status PlaceServiceImpl::ListPlaces(grpc::ServerContext* context,
                                          const v1::ListPlacesRequest* req,
                                          v1::ListPlacesResponse* resp) {
  auto caller = ctx_->keys->Authorize(*context, "PlaceService/ListPlaces");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  if (!req->map().empty()) {
    if (auto m = FindCallersMap(ctx_->engine->store(), *caller, req->map()); !m.ok()) {
      return ToGrpcStatus(m.status());
    }
  }
  auto stored = ctx_->engine->store()->ListVisitPlaces(req->map());
  if (!stored.ok()) return ToGrpcStatus(stored.status());
  for (const auto& r : *stored) {
    if (!caller->MayUseMap(r.map_id)) continue;
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
