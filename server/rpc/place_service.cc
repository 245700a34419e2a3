// PlaceService: place recognition over stored visits, by architecture (paper 004) and by
// appearance (paper 000).
#include <algorithm>
#include <map>

#include "absl/strings/str_cat.h"
#include "core/common/rgbd_frame.h"
#include "core/common/utf8.h"
#include "core/pipeline/keyframe.h"
#include "core/place/floor_plan.h"
#include "core/place/serialize.h"
#include "server/rpc/convert.h"
#include "server/rpc/services.h"

namespace lifemap::server {
namespace {

bool Better(const PlaceMatch& a, const PlaceMatch& b) {
  return a.score != b.score ? a.score > b.score : a.visit_id < b.visit_id;
}

// Stored visits ranked by their best keyframe match, at most `max`.
std::vector<PlaceMatch> BestPerVisit(const std::vector<PlaceMatch>& keyframe_matches, size_t max) {
  std::map<int64_t, PlaceMatch> best;
  for (const auto& m : keyframe_matches) {
    auto [it, inserted] = best.emplace(m.visit_id, m);
    if (!inserted && m.score > it->second.score) it->second = m;
  }
  std::vector<PlaceMatch> out;
  for (auto& [visit, m] : best) out.push_back(std::move(m));
  std::sort(out.begin(), out.end(), Better);
  if (out.size() > max) out.resize(max);
  return out;
}

// One ranking of visits from both methods: the mean of the two scores, a method that did not
// rank the visit counting 0.
std::vector<PlaceMatch> Fuse(const std::vector<PlaceMatch>& architecture,
                             const std::vector<PlaceMatch>& appearance, size_t max) {
  std::map<int64_t, PlaceMatch> fused;
  for (const auto* list : {&architecture, &appearance}) {
    for (const auto& m : *list) {
      auto [it, inserted] = fused.emplace(m.visit_id, m);
      if (inserted) {
        it->second.score = 0;
        it->second.keyframe_id = 0;
        it->second.T_match_query.reset();
      }
      it->second.score += 0.5 * m.score;
      it->second.method = PlaceMatch::Method::kFused;
    }
  }
  std::vector<PlaceMatch> out;
  for (auto& [visit, m] : fused) out.push_back(std::move(m));
  std::sort(out.begin(), out.end(), Better);
  if (out.size() > max) out.resize(max);
  return out;
}

}  // namespace

// What one method made of a query: its ranking, or why it has none.
struct PlaceServiceImpl::MethodOutcome {
  absl::Status status;
  std::vector<PlaceMatch> matches;  // best first
  std::string descriptor_text;      // architecture only
};

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
  MethodOutcome by_architecture, by_appearance;
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
    if (architecture) {
      auto s = ArchitectureOfFrames(*context, frames, max_results, &by_architecture);
      if (!s.ok()) return s;
    }
    if (appearance) {
      auto s =
          AppearanceOfFrames(*context, frames, max_results, &by_appearance, resp->mutable_frames());
      if (!s.ok()) return s;
    }
  } else {
    const auto visit_id = IdFromProto(req->visit_id(), "visit_id");
    if (!visit_id.ok()) return ToGrpcStatus(visit_id.status());
    auto visit = FindCallersVisit(ctx_->engine->store(), *caller, *visit_id);
    if (!visit.ok()) return ToGrpcStatus(visit.status());
    if (architecture) ArchitectureOfVisit(*visit, max_results, &by_architecture);
    if (appearance) AppearanceOfVisit(*visit, max_results, &by_appearance);
  }
  // A key limited to some maps sees matches in those only.
  for (auto* outcome : {&by_architecture, &by_appearance}) {
    auto& m = outcome->matches;
    m.erase(
        std::remove_if(m.begin(), m.end(),
                       [&](const PlaceMatch& match) { return !caller->MayUseMap(match.map_id); }),
        m.end());
  }
  for (auto& frame : *resp->mutable_frames()) KeepCallersMatches(*caller, frame.mutable_matches());
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
  if (by_architecture.status.ok() && by_appearance.status.ok() && architecture && appearance) {
    for (const auto& m : Fuse(by_architecture.matches, by_appearance.matches, max_results)) {
      PlaceMatchToProto(m, resp->add_matches());
    }
  }
  for (const auto* outcome : {&by_architecture, &by_appearance}) {
    for (const auto& m : outcome->matches) PlaceMatchToProto(m, resp->add_matches());
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

namespace {

// A long query stopped between frames because its deadline passed or its client left.
grpc::Status StoppedAfter(size_t done, size_t frames) {
  return grpc::Status(grpc::StatusCode::CANCELLED,
                      absl::StrCat("stopped after ", done, " of ", frames,
                                   " frames: the call's deadline passed or its client left"));
}

}  // namespace

grpc::Status PlaceServiceImpl::ArchitectureOfFrames(const grpc::ServerContext& context,
                                                    const std::vector<EncodedRgbdFrame>& frames,
                                                    size_t max_results, MethodOutcome* out) {
  // Nothing is stored: the frames fold into a plan of their own, ranked against stored visits.
  place::FloorPlanBuilder builder;
  for (size_t i = 0; i < frames.size(); ++i) {
    // Each frame costs its depth decoding and planes (a 2,000-frame query, minutes of CPU).
    if (context.IsCancelled()) return StoppedAfter(i, frames.size());
    if (!frames[i].T_world_camera) {
      out->status = absl::InvalidArgumentError(absl::StrCat(
          "frames[", i, "]: pose is missing; architecture needs each key frame's T_world_camera"));
      return grpc::Status::OK;
    }
    auto frame = DecodeRgbdFrame(frames[i], /*decode_color=*/false,
                                 ctx_->engine->pipeline()->options().frame_limits);
    auto s = frame.ok() ? builder.AddDepthKeyframe(frame->depth_m, frame->intrinsics,
                                                   *frames[i].T_world_camera)
                        : frame.status();
    if (!s.ok()) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                          absl::StrCat("frames[", i, "]: ", s.message()));
    }
  }
  if (context.IsCancelled()) return StoppedAfter(frames.size(), frames.size());
  auto plan = builder.Build();
  if (!plan.ok()) {
    out->status = absl::FailedPreconditionError(
        absl::StrCat("the frames give no floor plan: ", plan.status().message()));
    return grpc::Status::OK;
  }
  const place::PlaceDescriptor descriptor = place::Describe(*plan);
  auto ranked = ctx_->engine->places()->Rank(descriptor, /*exclude_visit=*/0, max_results);
  if (!ranked.ok()) return ToGrpcStatus(ranked.status());
  out->matches = *std::move(ranked);
  out->descriptor_text = place::DescriptorText(descriptor);
  return grpc::Status::OK;
}

void PlaceServiceImpl::ArchitectureOfVisit(const store::VisitRecord& visit, size_t max_results,
                                           MethodOutcome* out) {
  auto record = ctx_->engine->store()->GetVisitPlace(visit.id);
  if (absl::IsNotFound(record.status())) {
    // Say why, from the live visit when it is open.
    std::string why = "its floor plan has not closed yet (walls all around, floor seen)";
    if (!visit.ended) {
      auto state = ctx_->engine->visits()->Get(visit.id);
      if (state.ok()) {
        const absl::Status status = (*state)->architecture.Ranking().status;
        if (!status.ok()) why = std::string(status.message());
      }
    }
    out->status = absl::FailedPreconditionError(
        absl::StrCat("visit ", visit.id, " has no floor plan: ", why));
    return;
  }
  if (!record.ok()) {
    out->status = record.status();
    return;
  }
  auto descriptor = place::DescriptorFromJson(record->descriptor_json);
  if (!descriptor.ok()) {
    out->status = descriptor.status();
    return;
  }
  auto ranked = ctx_->engine->places()->Rank(*descriptor, visit.id, max_results);
  if (!ranked.ok()) {
    out->status = ranked.status();
    return;
  }
  out->matches = *std::move(ranked);
  out->descriptor_text = place::DescriptorText(*descriptor);
}

grpc::Status PlaceServiceImpl::AppearanceOfFrames(
    const grpc::ServerContext& context, const std::vector<EncodedRgbdFrame>& frames,
    size_t max_results, MethodOutcome* out,
    google::protobuf::RepeatedPtrField<v1::FrameAppearance>* per_frame) {
  MapNames names(ctx_->engine->store());
  std::vector<PlaceMatch> all;
  int answered = 0;
  absl::Status last_failure;
  for (size_t i = 0; i < frames.size(); ++i) {
    // Each frame costs its entropy mask, features and verification: a call whose deadline
    // passed (or whose client left) stops here instead of finishing for nobody.
    if (context.IsCancelled()) return StoppedAfter(i, frames.size());
    auto* entry = per_frame->Add();
    entry->set_index(static_cast<uint32_t>(i));
    if (frames[i].color.data.empty()) {
      entry->set_reason("no colour image: appearance needs colour and depth");
      last_failure = absl::InvalidArgumentError(entry->reason());
      continue;
    }
    // The frame's own entropy mask prunes its features, as for a streamed keyframe.
    auto analysis = ctx_->engine->pipeline()->Process(frames[i], {});
    if (!analysis.ok()) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                          absl::StrCat("frames[", i, "]: ", analysis.status().message()));
    }
    auto features = pipeline::ExtractKeyframeFeatures(*analysis, ctx_->config.appearance.features);
    absl::StatusOr<appearance::Recognition> recognition =
        features.ok() ? ctx_->engine->appearance()->Recognize(features->keypoints,
                                                              analysis->frame.intrinsics, {})
                      : absl::StatusOr<appearance::Recognition>(features.status());
    if (!recognition.ok()) {
      entry->set_reason(ToValidUtf8(recognition.status().message()));
      last_failure = recognition.status();
      continue;
    }
    ++answered;
    for (const auto& m : recognition->matches) {
      const PlaceMatch match = AppearancePlaceMatch(m, &names);
      if (entry->matches_size() < static_cast<int>(max_results)) {
        PlaceMatchToProto(match, entry->add_matches());
      }
      all.push_back(match);
    }
  }
  if (answered == 0) {
    out->status = absl::FailedPreconditionError(
        absl::StrCat("no frame could be matched: ", last_failure.message()));
    return grpc::Status::OK;
  }
  out->matches = BestPerVisit(all, max_results);
  return grpc::Status::OK;
}

void PlaceServiceImpl::AppearanceOfVisit(const store::VisitRecord& visit, size_t max_results,
                                         MethodOutcome* out) {
  auto keyframes = ctx_->engine->store()->ListKeyframes(visit.map_id, visit.id);
  if (!keyframes.ok()) {
    out->status = keyframes.status();
    return;
  }
  MapNames names(ctx_->engine->store());
  std::vector<PlaceMatch> all;
  int answered = 0;
  absl::Status last_failure = absl::FailedPreconditionError(
      absl::StrCat("visit ", visit.id, " has no keyframes with features"));
  const int64_t own = visit.id;
  for (const auto& k : *keyframes) {
    auto features = ctx_->engine->store()->GetKeyframeFeatures(k.id);
    if (!features.ok()) continue;  // stored without entropy masks: nothing to match
    auto recognition = ctx_->engine->appearance()->Recognize(
        features->keypoints, k.intrinsics,
        [own](const appearance::KeyframeRef& r) { return r.visit_id == own; });
    if (!recognition.ok()) {
      last_failure = recognition.status();
      continue;
    }
    ++answered;
    for (const auto& m : recognition->matches) all.push_back(AppearancePlaceMatch(m, &names));
  }
  if (answered == 0) {
    out->status = last_failure;
    return;
  }
  out->matches = BestPerVisit(all, max_results);
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
