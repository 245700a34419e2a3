#include <sys/resource.h>
#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <fstream>

#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "core/common/utf8.h"
#include "server/engine/keyframe_committer.h"
#include "server/engine/retention.h"
#include "server/rpc/auth.h"
#include "server/rpc/convert.h"
#include "server/rpc/services.h"

namespace lifemap::server {

grpc::Status AdminServiceImpl::GetServerInfo(grpc::ServerContext* context,
                                             const v1::GetServerInfoRequest*,
                                             v1::ServerInfo* resp) {
  auto caller = ctx_->keys->Authorize(*context, "AdminService/GetServerInfo");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  resp->set_version(LIFEMAP_VERSION);
  resp->set_api_version("lifemap.v1");
  // A server-level answer: poses count as computed only when the client sends them.
  // Labels: computed for frames of maps with an active model (or with a server default).
  OutputFacts facts;
  if (!ctx_->config.labels_enabled) {
    facts.labeller = absl::FailedPreconditionError(kLabelsDisabled);
  } else if (auto models = ctx_->engine->store()->ListModels(); !models.ok()) {
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
  // Moved masks: for posed frames in the map's frame once the map has an earlier ended visit.
  facts.moved = ctx_->config.changes.moved_enabled
                    ? absl::OkStatus()
                    : absl::FailedPreconditionError(
                          "disabled in this server's config (changes.moved_enabled)");
  FillOutputStatuses(ctx_->config.pipeline, facts, resp->mutable_outputs());
  resp->set_max_message_bytes(static_cast<uint64_t>(ctx_->config.max_message_bytes));
  resp->set_max_streams(static_cast<uint32_t>(ctx_->config.max_streams));
  resp->set_max_inflight_frames(static_cast<uint32_t>(ctx_->config.max_inflight_frames));
  // Where the database lives is for those who administer it.
  if (caller->role >= Role::kOperator) {
    resp->set_db_path(ToValidUtf8(std::filesystem::absolute(ctx_->config.db_path).string()));
  }
  resp->set_schema_version(static_cast<uint32_t>(ctx_->engine->store()->schema_version()));
  resp->set_started_time_s(ctx_->started_time_s);
  resp->set_default_result_images(kDefaultResultImages);
  if (ctx_->shard != nullptr) {
    resp->set_shard(ctx_->shard->shard());
  }
  // The cluster's shards only to a caller that came through the cluster's nginx (its table
  // sets lifemap-routed-by): a client connected to one shard directly talks to that shard
  // alone, and must not fan calls out to the others through it.
  if (ctx_->shard != nullptr && caller->routed_by_proxy) {
    auto shards = ctx_->shard->Shards();
    if (!shards.ok()) return ToGrpcStatus(shards.status());
    const double now = NowSeconds();
    for (const placement::Shard& s : *shards) {
      v1::ShardInfo* info = resp->add_shards();
      info->set_name(s.name);
      info->set_address(s.address);
      info->set_state(s.state);
      info->set_up(s.Up(now));
      info->set_seen_age_s(s.seen_s > 0 ? now - s.seen_s : -1);
    }
  }
  resp->set_auth_required(ctx_->keys->required());
  if (ctx_->keys->required()) {
    resp->set_caller_key(caller->key_name);
    resp->set_caller_role(RoleToProto(caller->role));
  }
  resp->set_tls(!ctx_->config.tls_cert.empty());
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

// Resident memory of this process, bytes (0 when /proc is not there).
uint64_t ResidentBytes() {
  std::ifstream statm("/proc/self/statm");
  uint64_t pages = 0, resident = 0;
  if (!(statm >> pages >> resident)) return 0;
  return resident * static_cast<uint64_t>(sysconf(_SC_PAGESIZE));
}

}  // namespace

grpc::Status AdminServiceImpl::GetStats(grpc::ServerContext* context, const v1::GetStatsRequest*,
                                        v1::Stats* resp) {
  auto caller = ctx_->keys->Authorize(*context, "AdminService/GetStats");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  if (!caller->every_map) {
    // A key limited to some maps sees the counts of those only, and nothing of the server's
    // (its file, its streams, its other robots' frames).
    auto maps = ctx_->engine->store()->ListMaps();
    if (!maps.ok()) return ToGrpcStatus(maps.status());
    uint64_t visits = 0, keyframes = 0, count = 0;
    for (const auto& m : *maps) {
      if (!caller->MayUseMap(m.id)) continue;
      ++count;
      visits += static_cast<uint64_t>(m.visit_count);
      keyframes += static_cast<uint64_t>(m.keyframe_count);
    }
    resp->set_maps(static_cast<uint32_t>(count));
    resp->set_visits(static_cast<uint32_t>(visits));
    resp->set_keyframes(keyframes);
    resp->set_limited_to_maps(true);
    return grpc::Status::OK;
  }
  auto st = ctx_->engine->store()->Stats();
  if (!st.ok()) return ToGrpcStatus(st.status());
  resp->set_maps(static_cast<uint32_t>(st->maps));
  resp->set_visits(static_cast<uint32_t>(st->visits));
  resp->set_keyframes(static_cast<uint64_t>(st->keyframes));
  resp->set_db_bytes(static_cast<uint64_t>(st->db_bytes));
  resp->set_wal_bytes(static_cast<uint64_t>(st->wal_bytes));
  resp->set_active_streams(static_cast<uint32_t>(ctx_->active_streams.load()));
  resp->set_frames_processed(ctx_->engine->frames()->frames_processed());
  resp->set_frames_rejected(ctx_->engine->frames()->frames_rejected());
  resp->set_keyframes_committed(ctx_->engine->committer()->committed());
  resp->set_uptime_s(NowSeconds() - ctx_->started_time_s);
  resp->set_process_cpu_s(ProcessCpuSeconds());
  resp->set_resident_bytes(ResidentBytes());
  AppearanceInfoToProto(ctx_->engine->appearance()->Stats(), resp->mutable_appearance());
  return grpc::Status::OK;
}

void AdminServiceImpl::AppearanceInfoToProto(const AppearanceIndexStats& s,
                                             v1::AppearanceIndexInfo* out) const {
  out->set_enabled(ctx_->engine->appearance()->options().enabled);
  out->set_has_vocabulary(s.has_vocabulary);
  out->set_vocabulary_id(static_cast<uint64_t>(s.vocabulary_id));
  out->set_words(s.words);
  out->set_keyframes(s.keyframes);
  out->set_memory_bytes(s.memory_bytes);
  out->set_stored_keyframes(static_cast<uint64_t>(s.stored_with_features));
  out->set_min_training_keyframes(
      static_cast<uint32_t>(ctx_->engine->appearance()->options().min_training_keyframes));
}

grpc::Status AdminServiceImpl::RebuildAppearanceIndex(grpc::ServerContext* context,
                                                      const v1::RebuildAppearanceIndexRequest* req,
                                                      v1::AppearanceIndexInfo* resp) {
  auto caller = ctx_->keys->Authorize(*context, "AdminService/RebuildAppearanceIndex");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  auto stats = ctx_->engine->appearance()->Rebuild(req->retrain());
  if (!stats.ok()) return ToGrpcStatus(stats.status());
  spdlog::info("appearance index rebuilt{}: {} keyframes", req->retrain() ? " (retrained)" : "",
               stats->keyframes);
  AppearanceInfoToProto(*stats, resp);
  return grpc::Status::OK;
}

namespace {

// The config's policy with the request's fields over it; INVALID_ARGUMENT naming a value out of
// range.
absl::StatusOr<RetentionOptions> RetentionPolicy(const RetentionOptions& config,
                                                 const v1::RetentionPolicy& p) {
  RetentionOptions o = config;
  if (p.has_cover_m()) o.cover_m = p.cover_m();
  if (p.has_cover_deg()) o.cover_deg = p.cover_deg();
  if (p.has_keep_recent_visits())
    o.keep_recent_visits = static_cast<int>(std::min<uint32_t>(p.keep_recent_visits(), 1u << 30));
  if (p.has_compact_after_visits())
    o.compact_after_visits =
        static_cast<int>(std::min<uint32_t>(p.compact_after_visits(), 1u << 30));
  if (p.has_recognised_within_visits()) {
    o.recognised_within_visits =
        static_cast<int>(std::min<uint32_t>(p.recognised_within_visits(), 1u << 30));
  }
  if (p.has_compact_cover_m()) o.compact_cover_m = p.compact_cover_m();
  if (p.has_compact_cover_deg()) o.compact_cover_deg = p.compact_cover_deg();
  if (auto s = o.Validate(); !s.ok()) {
    return absl::InvalidArgumentError(absl::StrCat("policy: ", s.message()));
  }
  return o;
}

void ToProto(const store::MapStorage& m, v1::MapStorage* out) {
  out->set_keyframes(static_cast<uint64_t>(m.keyframes));
  out->set_image_bytes(static_cast<uint64_t>(m.image_bytes));
  out->set_feature_bytes(static_cast<uint64_t>(m.feature_bytes));
  out->set_octree_bytes(static_cast<uint64_t>(m.octree_bytes));
  out->set_plan_bytes(static_cast<uint64_t>(m.plan_bytes));
  out->set_total_bytes(static_cast<uint64_t>(m.total()));
}

}  // namespace

grpc::Status AdminServiceImpl::ApplyRetention(grpc::ServerContext* context,
                                              const v1::ApplyRetentionRequest* req,
                                              v1::RetentionReport* resp) {
  auto caller = ctx_->keys->Authorize(*context, "AdminService/ApplyRetention");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  auto map = FindCallersMap(ctx_->engine->store(), *caller, req->map());
  if (!map.ok()) return ToGrpcStatus(map.status());
  auto options = RetentionPolicy(ctx_->engine->options().retention, req->policy());
  if (!options.ok()) return ToGrpcStatus(options.status());
  auto report = server::ApplyRetention(ctx_->engine->store(), ctx_->engine->appearance(), *map,
                                       *options, req->dry_run());
  if (!report.ok()) return ToGrpcStatus(report.status());
  resp->set_map(map->name);
  resp->set_dry_run(report->dry_run);
  v1::RetentionPolicy* p = resp->mutable_policy();
  p->set_cover_m(options->cover_m);
  p->set_cover_deg(options->cover_deg);
  p->set_keep_recent_visits(static_cast<uint32_t>(options->keep_recent_visits));
  p->set_compact_after_visits(static_cast<uint32_t>(options->compact_after_visits));
  p->set_compact_cover_m(options->compact_cover_m);
  p->set_compact_cover_deg(options->compact_cover_deg);
  p->set_recognised_within_visits(static_cast<uint32_t>(options->recognised_within_visits));
  for (const auto& v : report->visits) {
    v1::VisitRetention* out = resp->add_visits();
    out->set_visit_id(static_cast<uint64_t>(v.visit_id));
    out->set_keyframes(static_cast<uint64_t>(v.keyframes));
    out->set_thinned(static_cast<uint64_t>(v.thinned));
    out->set_bytes_freed(static_cast<uint64_t>(v.bytes_freed));
    out->set_compacted(v.compacted);
    out->set_kept_whole(v.kept_whole);
    for (const auto& [why, n] : v.kept_because)
      (*out->mutable_kept_because())[why] = static_cast<uint64_t>(n);
  }
  for (const auto& t : report->thinned) {
    v1::ThinnedKeyframe* out = resp->add_thinned();
    out->set_keyframe_id(static_cast<uint64_t>(t.keyframe.keyframe_id));
    out->set_visit_id(static_cast<uint64_t>(t.visit_id));
    out->set_covered_by(static_cast<uint64_t>(t.keyframe.covered_by));
    out->set_covered_by_visit(static_cast<uint64_t>(t.covered_by_visit));
    out->set_distance_m(t.keyframe.distance_m);
    out->set_angle_deg(t.keyframe.angle_deg);
  }
  ToProto(report->before, resp->mutable_before());
  ToProto(report->after, resp->mutable_after());
  resp->set_seconds(report->seconds);
  spdlog::info("retention{} of map '{}': {} keyframes thinned, {} -> {} bytes in {:.2f} s",
               report->dry_run ? " (dry run)" : "", map->name, report->thinned.size(),
               report->before.total(), report->after.total(), report->seconds);
  return grpc::Status::OK;
}

grpc::Status AdminServiceImpl::Backup(grpc::ServerContext* context, const v1::BackupRequest* req,
                                      v1::BackupResponse* resp) {
  auto caller = ctx_->keys->Authorize(*context, "AdminService/Backup");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  auto path = BackupPath(ctx_->config, req->name());
  if (!path.ok()) return ToGrpcStatus(path.status());
  if (auto s = ctx_->engine->store()->Backup(*path); !s.ok()) return ToGrpcStatus(s);
  std::error_code ec;
  resp->set_path(ToValidUtf8(*path));
  resp->set_bytes(static_cast<uint64_t>(std::filesystem::file_size(*path, ec)));
  spdlog::info("backup written to {}", *path);
  return grpc::Status::OK;
}

grpc::Status AdminServiceImpl::CheckIntegrity(grpc::ServerContext* context,
                                              const v1::CheckIntegrityRequest*,
                                              v1::CheckIntegrityResponse* resp) {
  auto caller = ctx_->keys->Authorize(*context, "AdminService/CheckIntegrity");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  auto problems = ctx_->engine->store()->CheckIntegrity();
  if (!problems.ok()) return ToGrpcStatus(problems.status());
  resp->set_ok(problems->empty());
  for (auto& p : *problems) resp->add_problems(ToValidUtf8(p));
  return grpc::Status::OK;
}

grpc::Status AdminServiceImpl::Vacuum(grpc::ServerContext* context, const v1::VacuumRequest*,
                                      v1::VacuumResponse* resp) {
  auto caller = ctx_->keys->Authorize(*context, "AdminService/Vacuum");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  auto before = ctx_->engine->store()->Stats();
  if (!before.ok()) return ToGrpcStatus(before.status());
  if (auto s = ctx_->engine->store()->Vacuum(); !s.ok()) return ToGrpcStatus(s);
  if (auto s = ctx_->engine->store()->Checkpoint(); !s.ok()) return ToGrpcStatus(s);
  auto after = ctx_->engine->store()->Stats();
  if (!after.ok()) return ToGrpcStatus(after.status());
  resp->set_bytes_before(static_cast<uint64_t>(before->db_bytes + before->wal_bytes));
  resp->set_bytes_after(static_cast<uint64_t>(after->db_bytes + after->wal_bytes));
  return grpc::Status::OK;
}

grpc::Status AdminServiceImpl::CreateApiKey(grpc::ServerContext* context,
                                            const v1::CreateApiKeyRequest* req,
                                            v1::CreateApiKeyResponse* resp) {
  auto caller = ctx_->keys->Authorize(*context, "AdminService/CreateApiKey");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  const std::optional<Role> role = RoleFromProto(req->role());
  if (!role) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        "role is required: ROLE_ROBOT, ROLE_OPERATOR or ROLE_ADMIN");
  }
  const std::vector<std::string> maps(req->maps().begin(), req->maps().end());
  store::KeyLimits limits;
  limits.max_streams = req->limits().max_streams();
  limits.max_frames_per_s = req->limits().max_frames_per_s();
  limits.max_maps = req->limits().max_maps();
  limits.max_keyframes_per_map =
      static_cast<int64_t>(std::min<uint64_t>(req->limits().max_keyframes_per_map(), INT64_MAX));
  limits.max_model_bytes =
      static_cast<int64_t>(std::min<uint64_t>(req->limits().max_model_bytes(), INT64_MAX));
  limits.max_visits_per_hour = req->limits().max_visits_per_hour();
  // A shard's keys are the cluster's (server/rpc/cluster_keys.h).
  auto created = ctx_->shard != nullptr
                     ? ctx_->shard->keys()->Create(req->name(), *role, maps, limits, NowSeconds())
                     : server::CreateApiKey(ctx_->engine->store(), req->name(), *role, maps, limits,
                                            NowSeconds());
  if (!created.ok()) return ToGrpcStatus(created.status());
  if (auto s = ctx_->keys->Reload(); !s.ok()) return ToGrpcStatus(s);
  spdlog::info("API key '{}' ({}) created by '{}'", req->name(), std::string(RoleName(*role)),
               caller->key_name);
  resp->set_key(created->first);
  ApiKeyToProto(created->second, resp->mutable_info());
  return grpc::Status::OK;
}

grpc::Status AdminServiceImpl::ListApiKeys(grpc::ServerContext* context,
                                           const v1::ListApiKeysRequest*,
                                           v1::ListApiKeysResponse* resp) {
  auto caller = ctx_->keys->Authorize(*context, "AdminService/ListApiKeys");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  auto keys =
      ctx_->shard != nullptr ? ctx_->shard->keys()->List() : ctx_->engine->store()->ListApiKeys();
  if (!keys.ok()) return ToGrpcStatus(keys.status());
  for (const auto& k : *keys) ApiKeyToProto(k, resp->add_keys());
  return grpc::Status::OK;
}

grpc::Status AdminServiceImpl::RevokeApiKey(grpc::ServerContext* context,
                                            const v1::RevokeApiKeyRequest* req, v1::ApiKey* resp) {
  auto caller = ctx_->keys->Authorize(*context, "AdminService/RevokeApiKey");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  if (auto s = store::ValidateName(req->name(), "API key"); !s.ok()) return ToGrpcStatus(s);
  auto revoked = ctx_->shard != nullptr
                     ? ctx_->shard->keys()->Revoke(req->name(), NowSeconds())
                     : ctx_->engine->store()->RevokeApiKey(req->name(), NowSeconds());
  if (!revoked.ok()) return ToGrpcStatus(revoked.status());
  if (auto s = ctx_->keys->Reload(); !s.ok()) return ToGrpcStatus(s);
  spdlog::info("API key '{}' revoked by '{}'", req->name(), caller->key_name);
  ApiKeyToProto(*revoked, resp);
  return grpc::Status::OK;
}

grpc::Status AdminServiceImpl::ListAuditEvents(grpc::ServerContext* context,
                                               const v1::ListAuditEventsRequest* req,
                                               v1::ListAuditEventsResponse* resp) {
  auto caller = ctx_->keys->Authorize(*context, "AdminService/ListAuditEvents");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  constexpr uint32_t kMaxEvents = 10000;
  if (req->limit() > kMaxEvents) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        absl::StrCat("limit must be at most ", kMaxEvents, " (0 = 100)"));
  }
  if (!std::isfinite(req->since_time_s()) || req->since_time_s() < 0) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        "since_time_s must be >= 0 seconds since the Unix epoch");
  }
  auto events = ctx_->engine->store()->ListAuditEvents(
      req->since_time_s(), req->limit() == 0 ? 100 : static_cast<int>(req->limit()));
  if (!events.ok()) return ToGrpcStatus(events.status());
  for (const auto& e : *events) {
    auto* out = resp->add_events();
    out->set_time_s(e.time_s);
    out->set_key(e.key_name);
    out->set_method(e.method);
    out->set_request(e.request);
    out->set_code(e.code);
    out->set_message(e.message);
    out->set_peer(e.peer);
  }
  return grpc::Status::OK;
}

grpc::Status AdminServiceImpl::RefreshPlacement(grpc::ServerContext* context,
                                                const v1::RefreshPlacementRequest* req,
                                                v1::RefreshPlacementResponse* resp) {
  auto caller = ctx_->keys->Authorize(*context, "AdminService/RefreshPlacement");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  if (ctx_->shard == nullptr) {
    return grpc::Status(grpc::StatusCode::FAILED_PRECONDITION,
                        "this server is not a shard of a cluster (lifemapd --placement --shard)");
  }
  if (!req->map().empty()) {
    if (auto s = store::ValidateMapName(req->map()); !s.ok()) return ToGrpcStatus(s);
  }
  auto phase = ctx_->shard->Refresh(req->map());
  if (!phase.ok()) return ToGrpcStatus(phase.status());
  resp->set_shard(ctx_->shard->shard());
  if (!req->map().empty()) resp->set_map_phase(*phase);
  return grpc::Status::OK;
}

}  // namespace lifemap::server
