#include <sys/resource.h>

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

grpc::Status AdminServiceImpl::GetServerInfo(grpc::ServerContext*, const v1::GetServerInfoRequest*,
                                             v1::ServerInfo* resp) {
  resp->set_version(LIFEMAP_VERSION);
  resp->set_api_version("lifemap.v1");
  // A server-level answer: poses count as computed only when the client sends them.
  // Labels: computed for frames of maps with an active model (or with a server default).
  OutputFacts facts;
  if (!ctx_->config.labels_enabled) {
    facts.labeller = absl::FailedPreconditionError(kLabelsDisabled);
  } else if (auto models = ctx_->store->ListModels(); !models.ok()) {
    facts.labeller = absl::FailedPreconditionError(
        absl::StrCat("models unreadable: ", models.status().message()));
  } else {
    bool active = false;
    for (const auto& m : *models) active = active || m.is_default || !m.active_maps.empty();
    if (!active) {
      facts.labeller = absl::FailedPreconditionError(
          "no model is active: lifemap models upload FILE NAME; lifemap models activate NAME");
    }
  }
  // Fused labels: for posed frames of a visit labelled by a model, once a keyframe is fused.
  if (!ctx_->config.semantic_enabled) {
    facts.fusion =
        absl::FailedPreconditionError("disabled in this server's config (semantic.enabled)");
  } else if (!facts.labeller.ok()) {
    facts.fusion = absl::FailedPreconditionError(
        absl::StrCat("fused labels need a model: ", facts.labeller.message()));
  } else {
    facts.fusion = absl::OkStatus();
  }
  FillOutputStatuses(ctx_->config.pipeline, facts, resp->mutable_outputs());
  resp->set_max_message_bytes(static_cast<uint64_t>(ctx_->config.max_message_bytes));
  resp->set_max_streams(static_cast<uint32_t>(ctx_->config.max_streams));
  resp->set_max_inflight_frames(static_cast<uint32_t>(ctx_->config.max_inflight_frames));
  resp->set_db_path(std::filesystem::absolute(ctx_->config.db_path).string());
  resp->set_schema_version(static_cast<uint32_t>(ctx_->store->schema_version()));
  resp->set_started_time_s(ctx_->started_time_s);
  resp->set_default_result_images(kDefaultResultImages);
  return grpc::Status::OK;
}

namespace {

// User + system CPU time of this process, seconds.
double ProcessCpuSeconds() {
  rusage usage{};
  if (getrusage(RUSAGE_SELF, &usage) != 0) return 0.0;
  auto seconds = [](const timeval& t) { return t.tv_sec + t.tv_usec * 1e-6; };
  return seconds(usage.ru_utime) + seconds(usage.ru_stime);
}

}  // namespace

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
  resp->set_process_cpu_s(ProcessCpuSeconds());
  AppearanceInfoToProto(ctx_->appearance->Stats(), resp->mutable_appearance());
  return grpc::Status::OK;
}

void AdminServiceImpl::AppearanceInfoToProto(const AppearanceIndexStats& s,
                                             v1::AppearanceIndexInfo* out) const {
  out->set_enabled(ctx_->appearance->options().enabled);
  out->set_has_vocabulary(s.has_vocabulary);
  out->set_vocabulary_id(static_cast<uint64_t>(s.vocabulary_id));
  out->set_words(s.words);
  out->set_keyframes(s.keyframes);
  out->set_memory_bytes(s.memory_bytes);
  out->set_stored_keyframes(static_cast<uint64_t>(s.stored_with_features));
  out->set_min_training_keyframes(
      static_cast<uint32_t>(ctx_->appearance->options().min_training_keyframes));
}

grpc::Status AdminServiceImpl::RebuildAppearanceIndex(grpc::ServerContext*,
                                                      const v1::RebuildAppearanceIndexRequest* req,
                                                      v1::AppearanceIndexInfo* resp) {
  auto stats = ctx_->appearance->Rebuild(req->retrain());
  if (!stats.ok()) return ToGrpcStatus(stats.status());
  spdlog::info("appearance index rebuilt{}: {} keyframes", req->retrain() ? " (retrained)" : "",
               stats->keyframes);
  AppearanceInfoToProto(*stats, resp);
  return grpc::Status::OK;
}

grpc::Status AdminServiceImpl::Backup(grpc::ServerContext*, const v1::BackupRequest* req,
                                      v1::BackupResponse* resp) {
  auto path = BackupPath(ctx_->config, req->name());
  if (!path.ok()) return ToGrpcStatus(path.status());
  if (auto s = ctx_->store->Backup(*path); !s.ok()) return ToGrpcStatus(s);
  std::error_code ec;
  resp->set_path(*path);
  resp->set_bytes(static_cast<uint64_t>(std::filesystem::file_size(*path, ec)));
  spdlog::info("backup written to {}", *path);
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
