#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "core/common/utf8.h"
#include "server/engine/anchor_retry.h"
#include "server/engine/appearance.h"
#include "server/engine/architecture.h"
#include "server/engine/keyframe_committer.h"
#include "server/engine/semantic_export.h"
#include "server/engine/visit_changes.h"
#include "server/rpc/convert.h"
#include "server/rpc/services.h"

namespace lifemap::server {
namespace {

constexpr size_t kLabelMaxBytes = 256;

// The request's visit id, required, and one of the caller's maps' (NOT_FOUND otherwise, as for
// an unknown visit).
absl::StatusOr<int64_t> CallersVisitId(store::Store* store, const Principal& caller, uint64_t raw) {
  const auto visit_id = IdFromProto(raw, "visit_id");
  if (!visit_id.ok()) return visit_id.status();
  if (*visit_id == 0) return absl::InvalidArgumentError("visit_id is required");
  if (!caller.every_map) {
    if (auto v = FindCallersVisit(store, caller, *visit_id); !v.ok()) return v.status();
  }
  return *visit_id;
}

}  // namespace

grpc::Status VisitServiceImpl::StartVisit(grpc::ServerContext* context,
                                          const v1::StartVisitRequest* req, v1::Visit* resp) {
  auto caller = ctx_->keys->Authorize(*context, "VisitService/StartVisit");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  if (auto m = FindCallersMap(ctx_->engine->store(), *caller, req->map()); !m.ok()) {
    return ToGrpcStatus(m.status());
  }
  if (req->robot().size() > kLabelMaxBytes || req->label().size() > kLabelMaxBytes) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        absl::StrCat("robot and label must be at most ", kLabelMaxBytes, " bytes"));
  }
  const double t = req->start_time_s();
  if (!std::isfinite(t) || t < 0) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        "start_time_s must be >= 0 seconds since the Unix epoch (0 = now)");
  }
  if (auto s = caller->TakeVisit(ctx_->config.max_visits_per_key_per_hour); !s.ok()) {
    return ToGrpcStatus(s);
  }
  auto visit = ctx_->engine->store()->StartVisit(req->map(), req->robot(), req->label(),
                                                 t > 0 ? t : NowSeconds());
  if (!visit.ok()) return ToGrpcStatus(visit.status());
  spdlog::info("started visit {} of map '{}' (robot '{}')", visit->id, visit->map_name,
               visit->robot);
  VisitToProto(*visit, resp);
  return grpc::Status::OK;
}

grpc::Status VisitServiceImpl::EndVisit(grpc::ServerContext* context,
                                        const v1::EndVisitRequest* req, v1::Visit* resp) {
  auto caller = ctx_->keys->Authorize(*context, "VisitService/EndVisit");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  const auto visit_id = CallersVisitId(ctx_->engine->store(), *caller, req->visit_id());
  if (!visit_id.ok()) return ToGrpcStatus(visit_id.status());
  const int64_t id = *visit_id;
  auto visit = ctx_->engine->EndVisit(id);
  if (!visit.ok()) return ToGrpcStatus(visit.status());
  VisitToProto(*visit, resp);
  return grpc::Status::OK;
}

grpc::Status VisitServiceImpl::DeleteVisit(grpc::ServerContext* context,
                                           const v1::DeleteVisitRequest* req,
                                           v1::DeleteVisitResponse* resp) {
  auto caller = ctx_->keys->Authorize(*context, "VisitService/DeleteVisit");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  const auto visit_id = CallersVisitId(ctx_->engine->store(), *caller, req->visit_id());
  if (!visit_id.ok()) return ToGrpcStatus(visit_id.status());
  const int64_t id = *visit_id;
  auto deleted = ctx_->engine->store()->DeleteVisit(id);
  if (!deleted.ok()) return ToGrpcStatus(deleted.status());
  // Its keyframes leave the appearance index; rankings forget its floor plan.
  ctx_->engine->appearance()->RemoveKeyframes(deleted->keyframe_ids);
  ctx_->engine->places()->Invalidate();
  spdlog::info("deleted visit {} of map '{}': {} keyframes", id, deleted->map_name,
               deleted->keyframe_ids.size());
  resp->set_map(deleted->map_name);
  resp->set_deleted_keyframes(deleted->keyframe_ids.size());
  return grpc::Status::OK;
}

grpc::Status VisitServiceImpl::ListVisits(grpc::ServerContext* context,
                                          const v1::ListVisitsRequest* req,
                                          v1::ListVisitsResponse* resp) {
  auto caller = ctx_->keys->Authorize(*context, "VisitService/ListVisits");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  if (auto m = FindCallersMap(ctx_->engine->store(), *caller, req->map()); !m.ok()) {
    return ToGrpcStatus(m.status());
  }
  auto visits = ctx_->engine->store()->ListVisits(req->map());
  if (!visits.ok()) return ToGrpcStatus(visits.status());
  for (const auto& v : *visits) VisitToProto(v, resp->add_visits());
  return grpc::Status::OK;
}

grpc::Status VisitServiceImpl::AnchorVisits(grpc::ServerContext* context,
                                            const v1::AnchorVisitsRequest* req,
                                            v1::AnchorVisitsResponse* resp) {
  auto caller = ctx_->keys->Authorize(*context, "VisitService/AnchorVisits");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  auto map = FindCallersMap(ctx_->engine->store(), *caller, req->map());
  if (!map.ok()) return ToGrpcStatus(map.status());
  const auto visit_id = IdFromProto(req->visit_id(), "visit_id");
  if (!visit_id.ok()) return ToGrpcStatus(visit_id.status());
  auto attempts = ctx_->engine->RetryAnchors(map->id, *visit_id, req->dry_run());
  if (!attempts.ok()) return ToGrpcStatus(attempts.status());
  for (const AnchorAttempt& a : *attempts) {
    v1::AnchorAttempt* out = resp->add_attempts();
    out->set_visit_id(static_cast<uint64_t>(a.visit_id));
    out->set_anchored(a.anchored);
    out->set_to_visit(static_cast<uint64_t>(a.to_visit));
    out->set_keyframes_queried(static_cast<uint32_t>(a.keyframes_queried));
    out->set_candidates(static_cast<uint32_t>(a.candidates));
    out->set_reason(ToValidUtf8(a.reason));
    for (const std::string& v : a.verdicts) out->add_verdicts(ToValidUtf8(v));
  }
  return grpc::Status::OK;
}

grpc::Status VisitServiceImpl::GetAnchorHistory(grpc::ServerContext* context,
                                                const v1::GetAnchorHistoryRequest* req,
                                                v1::AnchorHistory* resp) {
  auto caller = ctx_->keys->Authorize(*context, "VisitService/GetAnchorHistory");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  const auto visit_id = IdFromProto(req->visit_id(), "visit_id");
  if (!visit_id.ok()) return ToGrpcStatus(visit_id.status());
  if (*visit_id == 0) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "visit_id is required");
  }
  auto visit = FindCallersVisit(ctx_->engine->store(), *caller, *visit_id);
  if (!visit.ok()) return ToGrpcStatus(visit.status());
  auto entries = ctx_->engine->store()->ListAnchorRevisions(*visit_id);
  if (!entries.ok()) return ToGrpcStatus(entries.status());
  resp->set_visit_id(static_cast<uint64_t>(visit->id));
  resp->set_map(visit->map_name);
  for (const store::AnchorRevision& r : *entries) {
    v1::AnchorHistoryEntry* out = resp->add_entries();
    out->set_time_s(r.time_s);
    out->set_action(r.action);
    out->set_to_visit(static_cast<uint64_t>(r.to_visit_id));
    PoseToProto(r.T_map_visit, out->mutable_t_map_visit());
    out->set_reason(ToValidUtf8(r.reason));
  }
  return grpc::Status::OK;
}

}  // namespace lifemap::server

namespace lifemap::server {
namespace {

void ToProto(const Eigen::Vector3d& v, v1::Vector3* out) {
  out->set_x(v.x());
  out->set_y(v.y());
  out->set_z(v.z());
}

}  // namespace

grpc::Status VisitServiceImpl::GetChanges(grpc::ServerContext* context,
                                          const v1::GetChangesRequest* req,
                                          v1::VisitChanges* resp) {
  auto caller = ctx_->keys->Authorize(*context, "VisitService/GetChanges");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  auto map = FindCallersMap(ctx_->engine->store(), *caller, req->map());
  if (!map.ok()) return ToGrpcStatus(map.status());
  const auto from = IdFromProto(req->from_visit(), "from_visit");
  if (!from.ok()) return ToGrpcStatus(from.status());
  const auto to = IdFromProto(req->to_visit(), "to_visit");
  if (!to.ok()) return ToGrpcStatus(to.status());
  if (*from == 0 || *to == 0) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        "from_visit and to_visit are both required (lifemap visits list MAP)");
  }
  const VisitChangeOptions& options = ctx_->engine->options().changes;
  auto changes = CompareVisits(ctx_->engine->store(), ctx_->engine->visits(),
                               ctx_->engine->semantic_worker(), *map, *from, *to, options,
                               ctx_->config.semantic, [context] { return context->IsCancelled(); });
  if (!changes.ok()) return ToGrpcStatus(changes.status());
  resp->set_map(map->name);
  resp->set_from_visit(static_cast<uint64_t>(changes->from_visit));
  resp->set_to_visit(static_cast<uint64_t>(changes->to_visit));
  for (const ChangedObject& c : changes->objects) {
    v1::ObjectChange* out = resp->add_changes();
    out->set_kind(change::ChangeKindName(c.change.kind));
    ToProto(c.change.center, out->mutable_center());
    ToProto(c.change.from_center, out->mutable_from_center());
    ToProto(c.change.extent, out->mutable_extent());
    out->set_voxels(static_cast<uint32_t>(c.change.voxels));
    out->set_evidence_views(static_cast<uint32_t>(c.change.evidence_views));
    out->set_class_name(ToValidUtf8(c.class_name));
    out->set_displacement_m((c.change.center - c.change.from_center).norm());
  }
  resp->set_from_keyframes(static_cast<uint32_t>(changes->from_keyframes));
  resp->set_to_keyframes(static_cast<uint32_t>(changes->to_keyframes));
  resp->set_voxel_m(options.change.voxel_m);
  resp->set_candidate_voxels(static_cast<uint64_t>(changes->tallies.candidate_voxels));
  resp->set_changed_voxels(static_cast<uint64_t>(changes->tallies.changed_voxels));
  resp->set_transient_voxels(static_cast<uint64_t>(changes->tallies.transient_voxels));
  resp->set_unobserved_voxels(static_cast<uint64_t>(changes->tallies.unobserved_voxels));
  resp->set_classes(ToValidUtf8(changes->classes));
  resp->set_seconds(changes->seconds);
  return grpc::Status::OK;
}

}  // namespace lifemap::server
