#include <chrono>
#include <filesystem>

#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "server/convert.h"
#include "server/services.h"

namespace lifemap::server {

double NowSeconds() {
  return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}

void FillOutputStatuses(google::protobuf::RepeatedPtrField<v1::OutputStatus>* out,
                        const pipeline::PipelineOptions& options,
                        const pipeline::FrameAnalysis* analysis, bool stores_keyframes,
                        bool labels_available, const std::string& labels_reason) {
  auto add = [out](v1::FrameOutput o, bool computed, const std::string& reason) {
    auto* s = out->Add();
    s->set_output(o);
    s->set_computed(computed);
    if (!computed) s->set_reason(reason);
  };
  const bool pose_from_client = analysis && analysis->frame.T_world_camera.has_value();
  add(v1::FRAME_OUTPUT_POSE, pose_from_client,
      "no odometry in this server yet: send the robot's pose in Frame.pose");
  add(v1::FRAME_OUTPUT_KEYFRAME, stores_keyframes,
      "no map given: the frame is processed but nothing is stored");
  if (!options.entropy_masks) {
    add(v1::FRAME_OUTPUT_ENTROPY_MASK, false, "disabled in this server's config (entropy.enabled)");
  } else if (analysis && !analysis->entropy) {
    add(v1::FRAME_OUTPUT_ENTROPY_MASK, false,
        absl::StrCat("not computed for this frame: ", analysis->entropy_status.message()));
  } else {
    add(v1::FRAME_OUTPUT_ENTROPY_MASK, true, "");
  }
  if (analysis) {
    add(v1::FRAME_OUTPUT_CLASS_LABELS, analysis->labels.has_value(),
        std::string(analysis->labels_status.message()));
  } else {
    add(v1::FRAME_OUTPUT_CLASS_LABELS, labels_available, labels_reason);
  }
  // Per frame, the frame service refines this from the visit's architecture.
  add(v1::FRAME_OUTPUT_PLACE_MATCHES, stores_keyframes,
      "no map given: places are recognised per visit (architecture, paper 004)");
  add(v1::FRAME_OUTPUT_SEMANTIC_FUSION, false,
      "not implemented in this server yet (semantic octree, paper 002)");
}

grpc::Status AdminServiceImpl::GetServerInfo(grpc::ServerContext*, const v1::GetServerInfoRequest*,
                                             v1::ServerInfo* resp) {
  resp->set_version(LIFEMAP_VERSION);
  resp->set_api_version("lifemap.v1");
  // A server-level answer: poses count as computed only when the client sends them.
  // Labels: computed for frames of maps with an active model (or with a server default).
  bool labels = false;
  std::string reason;
  if (!ctx_->config.labels_enabled) {
    reason = "disabled in this server's config (labels.enabled)";
  } else if (auto models = ctx_->store->ListModels(); !models.ok()) {
    reason = absl::StrCat("models unreadable: ", models.status().message());
  } else {
    for (const auto& m : *models) labels = labels || m.is_default || !m.active_maps.empty();
    if (!labels) {
      reason = "no model is active: lifemap models upload FILE NAME; lifemap models activate NAME";
    }
  }
  FillOutputStatuses(resp->mutable_outputs(), ctx_->config.pipeline, nullptr, true, labels, reason);
  resp->set_max_message_bytes(static_cast<uint64_t>(ctx_->config.max_message_bytes));
  resp->set_max_streams(static_cast<uint32_t>(ctx_->config.max_streams));
  resp->set_max_inflight_frames(static_cast<uint32_t>(ctx_->config.max_inflight_frames));
  resp->set_db_path(std::filesystem::absolute(ctx_->config.db_path).string());
  resp->set_schema_version(static_cast<uint32_t>(ctx_->store->schema_version()));
  resp->set_started_time_s(ctx_->started_time_s);
  return grpc::Status::OK;
}

grpc::Status AdminServiceImpl::GetStats(grpc::ServerContext*, const v1::GetStatsRequest*,
                                        v1::Stats* resp) {
  auto st = ctx_->store->Stats();
  if (!st.ok()) return ToGrpcStatus(st.status());
  resp->set_maps(static_cast<uint32_t>(st->maps));
  resp->set_visits(static_cast<uint32_t>(st->visits));
  resp->set_keyframes(static_cast<uint64_t>(st->keyframes));
  resp->set_db_bytes(static_cast<uint64_t>(st->db_bytes));
  resp->set_wal_bytes(static_cast<uint64_t>(st->wal_bytes));
  resp->set_active_streams(static_cast<uint32_t>(ctx_->active_streams.load()));
  resp->set_frames_processed(ctx_->frames_processed.load());
  resp->set_frames_rejected(ctx_->frames_rejected.load());
  resp->set_keyframes_committed(ctx_->committer->committed());
  resp->set_uptime_s(NowSeconds() - ctx_->started_time_s);
  return grpc::Status::OK;
}

grpc::Status AdminServiceImpl::Backup(grpc::ServerContext*, const v1::BackupRequest* req,
                                      v1::BackupResponse* resp) {
  if (auto s = ctx_->store->Backup(req->path()); !s.ok()) return ToGrpcStatus(s);
  std::error_code ec;
  resp->set_path(req->path());
  resp->set_bytes(static_cast<uint64_t>(std::filesystem::file_size(req->path(), ec)));
  spdlog::info("backup written to {}", req->path());
  return grpc::Status::OK;
}

grpc::Status AdminServiceImpl::CheckIntegrity(grpc::ServerContext*,
                                              const v1::CheckIntegrityRequest*,
                                              v1::CheckIntegrityResponse* resp) {
  auto problems = ctx_->store->CheckIntegrity();
  if (!problems.ok()) return ToGrpcStatus(problems.status());
  resp->set_ok(problems->empty());
  for (auto& p : *problems) resp->add_problems(p);
  return grpc::Status::OK;
}

grpc::Status AdminServiceImpl::Vacuum(grpc::ServerContext*, const v1::VacuumRequest*,
                                      v1::VacuumResponse* resp) {
  auto before = ctx_->store->Stats();
  if (!before.ok()) return ToGrpcStatus(before.status());
  if (auto s = ctx_->store->Vacuum(); !s.ok()) return ToGrpcStatus(s);
  if (auto s = ctx_->store->Checkpoint(); !s.ok()) return ToGrpcStatus(s);
  auto after = ctx_->store->Stats();
  if (!after.ok()) return ToGrpcStatus(after.status());
  resp->set_bytes_before(static_cast<uint64_t>(before->db_bytes + before->wal_bytes));
  resp->set_bytes_after(static_cast<uint64_t>(after->db_bytes + after->wal_bytes));
  return grpc::Status::OK;
}

grpc::Status AdminServiceImpl::CreateApiKey(grpc::ServerContext*, const v1::CreateApiKeyRequest*,
                                            v1::CreateApiKeyResponse*) {
  return grpc::Status(grpc::StatusCode::UNIMPLEMENTED,
                      "API keys are not implemented yet: this server has no authentication; "
                      "listen on loopback or a private network only");
}

}  // namespace lifemap::server
