#include "client/lifemap_client.h"

#include <netdb.h>
#include <sys/socket.h>
#include <sys/types.h>

#include <algorithm>
#include <chrono>
#include <cstdlib>
#include <thread>

#include <grpcpp/grpcpp.h>
#include <opencv2/imgcodecs.hpp>

#include "absl/container/flat_hash_map.h"
#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/synchronization/mutex.h"
#include "client/cluster_merge.h"
#include "core/common/depth_codec.h"
#include "core/common/image_codec.h"
#include "lifemap/v1/admin_service.grpc.pb.h"
#include "lifemap/v1/frame_service.grpc.pb.h"
#include "lifemap/v1/map_service.grpc.pb.h"
#include "lifemap/v1/model_service.grpc.pb.h"
#include "lifemap/v1/place_service.grpc.pb.h"
#include "lifemap/v1/visit_service.grpc.pb.h"

namespace lifemap::client {
namespace {

// The map name in a map archive's manifest (its second line, JSON with "map":"NAME"; names are
// [A-Za-z0-9._-], never escaped), "" if the bytes do not hold one. The server parses the archive
// properly; this only routes the call.
std::string ArchiveMapName(std::string_view head) {
  const size_t line = head.find('\n');
  if (line == std::string_view::npos) return "";
  head = head.substr(line + 1, head.find('\n', line + 1) - line - 1);
  constexpr std::string_view kKey = "\"map\":\"";
  const size_t at = head.find(kKey);
  if (at == std::string_view::npos) return "";
  const size_t start = at + kKey.size(), end = head.find('"', start);
  if (end == std::string_view::npos) return "";
  return std::string(head.substr(start, end - start));
}

absl::Status FromGrpc(const grpc::Status& s) {
  if (s.ok()) return absl::OkStatus();
  return absl::Status(static_cast<absl::StatusCode>(s.error_code()), s.error_message());
}

class GrpcFrameStream final : public FrameStream {
 public:
  GrpcFrameStream(
      std::unique_ptr<grpc::ClientContext> context,
      std::unique_ptr<grpc::ClientReaderWriter<v1::StreamFramesRequest, v1::StreamFramesResponse>>
          stream,
      v1::StreamStarted started)
      : context_(std::move(context)), stream_(std::move(stream)), started_(std::move(started)) {}

  ~GrpcFrameStream() override {
    if (!finished_) {
      context_->TryCancel();
      v1::StreamFramesResponse drain;
      while (stream_->Read(&drain)) {
      }
      stream_->Finish().ok();
    }
  }

  const v1::StreamStarted& started() const override { return started_; }

  bool Send(const v1::Frame& frame) override {
    v1::StreamFramesRequest request;
    *request.mutable_frame() = frame;
    return stream_->Write(request);
  }

  bool CloseSend() override { return stream_->WritesDone(); }

  bool Receive(v1::FrameResult* result) override {
    v1::StreamFramesResponse response;
    while (stream_->Read(&response)) {
      if (response.has_result()) {
        *result = std::move(*response.mutable_result());
        return true;
      }
    }
    return false;
  }

  absl::Status Finish() override {
    finished_ = true;
    return FromGrpc(stream_->Finish());
  }

  void Cancel() override { context_->TryCancel(); }

 private:
  std::unique_ptr<grpc::ClientContext> context_;
  std::unique_ptr<grpc::ClientReaderWriter<v1::StreamFramesRequest, v1::StreamFramesResponse>>
      stream_;
  v1::StreamStarted started_;
  bool finished_ = false;
};

class GrpcClient final : public Client {
 public:
  GrpcClient(std::shared_ptr<grpc::Channel> channel, const ClientOptions& options)
      : options_(options),
        maps_(v1::MapService::NewStub(channel)),
        visits_(v1::VisitService::NewStub(channel)),
        frames_(v1::FrameService::NewStub(channel)),
        models_(v1::ModelService::NewStub(channel)),
        places_(v1::PlaceService::NewStub(channel)),
        admin_(v1::AdminService::NewStub(channel)) {}

  absl::StatusOr<v1::ModelInfo> UploadModel(const std::string& name,
                                            const std::string& bytes) override {
    constexpr size_t kChunk = 1 << 20;
    grpc::ClientContext context;
    AddKey(&context);
    // The unary deadline plus a second per MiB: large models on slow links still make it.
    context.set_deadline(
        std::chrono::system_clock::now() +
        std::chrono::milliseconds(static_cast<int64_t>(
            (options_.call_timeout_s + static_cast<double>(bytes.size() >> 20)) * 1000)));
    v1::ModelInfo info;
    auto writer = models_->UploadModel(&context, &info);
    for (size_t offset = 0; offset == 0 || offset < bytes.size(); offset += kChunk) {
      v1::UploadModelChunk chunk;
      if (offset == 0) chunk.set_name(name);
      chunk.set_data(bytes.substr(offset, kChunk));
      if (!writer->Write(chunk)) break;  // the server answered early; Finish() says why
    }
    writer->WritesDone();
    if (auto s = FromGrpc(writer->Finish()); !s.ok()) return s;
    return info;
  }
  // By a stored visit: routed to the visit's map. By frames through a cluster: every shard is
  // asked at once and the rankings merged by score (cluster_merge.h); a shard with nothing to
  // match (FAILED_PRECONDITION) adds its reason, one that does not answer is listed in
  // unreachable_shards; FAILED_PRECONDITION only when no shard computed any method.
  absl::StatusOr<v1::QueryPlaceResponse> QueryPlace(const v1::QueryPlaceRequest& request) override {
    if (request.visit_id() != 0) {
      return Unary(&v1::PlaceService::Stub::QueryPlace, places_.get(), request,
                   MapOfVisit(request.visit_id()));
    }
    auto shards = ClusterShards();
    if (!shards.ok()) return shards.status();
    if (shards->empty()) return Unary(&v1::PlaceService::Stub::QueryPlace, places_.get(), request);
    auto answers = FanOut<v1::QueryPlaceResponse>(*shards, [&](const std::string& shard) {
      return Unary(&v1::PlaceService::Stub::QueryPlace, places_.get(), request, "", shard);
    });
    std::vector<std::pair<std::string, v1::QueryPlaceResponse>> parts;
    std::vector<std::string> unreachable;
    absl::Status refused;  // the first FAILED_PRECONDITION
    for (size_t i = 0; i < shards->size(); ++i) {
      const std::string& shard = (*shards)[i];
      if (answers[i].ok()) {
        parts.emplace_back(shard, *std::move(answers[i]));
        continue;
      }
      const absl::Status& s = answers[i].status();
      if (absl::IsUnavailable(s) || absl::IsDeadlineExceeded(s)) {
        unreachable.push_back(absl::StrCat(shard, ": ", s.message()));
      } else if (absl::IsFailedPrecondition(s)) {
        if (refused.ok())
          refused = absl::FailedPreconditionError(absl::StrCat(shard, ": ", s.message()));
        v1::QueryPlaceResponse nothing;  // no method computed there, saying why
        for (int m : {v1::MATCH_METHOD_ARCHITECTURE, v1::MATCH_METHOD_APPEARANCE}) {
          const bool asked = request.methods().empty() ||
                             std::find(request.methods().begin(), request.methods().end(), m) !=
                                 request.methods().end();
          if (!asked) continue;
          auto* status = nothing.add_method_status();
          status->set_method(static_cast<v1::MatchMethod>(m));
          status->set_reason(std::string(s.message()));
        }
        parts.emplace_back(shard, std::move(nothing));
      } else {
        return s;  // a bad request or key: every shard says the same
      }
    }
    v1::QueryPlaceResponse merged =
        MergePlaceAnswers(parts, request.max_results() == 0 ? 10 : request.max_results());
    for (std::string& u : unreachable) merged.add_unreachable_shards(std::move(u));
    const bool computed = std::any_of(merged.method_status().begin(), merged.method_status().end(),
                                      [](const v1::MethodStatus& m) { return m.computed(); });
    if (!computed && !refused.ok()) return refused;
    if (parts.empty()) {
      return absl::UnavailableError(
          absl::StrCat("no shard answered: ", absl::StrJoin(merged.unreachable_shards(), "; ")));
    }
    return merged;
  }
  absl::StatusOr<v1::ListPlacesResponse> ListPlaces(const std::string& map) override {
    v1::ListPlacesRequest req;
    req.set_map(map);
    return Unary(&v1::PlaceService::Stub::ListPlaces, places_.get(), req, map);
  }
  absl::StatusOr<v1::ListModelsResponse> ListModels() override {
    return Unary(&v1::ModelService::Stub::ListModels, models_.get(), v1::ListModelsRequest());
  }
  absl::StatusOr<v1::ActivateModelResponse> ActivateModel(const std::string& name,
                                                          const std::string& map) override {
    v1::ActivateModelRequest req;
    req.set_name(name);
    req.set_map(map);
    return Unary(&v1::ModelService::Stub::ActivateModel, models_.get(), req, map);
  }
  absl::StatusOr<v1::DeleteModelResponse> DeleteModel(const std::string& name) override {
    v1::DeleteModelRequest req;
    req.set_name(name);
    return Unary(&v1::ModelService::Stub::DeleteModel, models_.get(), req);
  }
  absl::StatusOr<v1::ListClassesResponse> ListClasses(const std::string& map) override {
    v1::ListClassesRequest req;
    req.set_map(map);
    return Unary(&v1::ModelService::Stub::ListClasses, models_.get(), req, map);
  }

  absl::StatusOr<v1::ServerInfo> GetServerInfo() override {
    return Unary(&v1::AdminService::Stub::GetServerInfo, admin_.get(), v1::GetServerInfoRequest());
  }
  // Through a cluster: every shard's, summed (cluster_merge.h); shards that do not answer are
  // listed in unreachable_shards.
  absl::StatusOr<v1::Stats> GetStats() override {
    auto shards = ClusterShards();
    if (!shards.ok()) return shards.status();
    if (shards->empty()) {
      return Unary(&v1::AdminService::Stub::GetStats, admin_.get(), v1::GetStatsRequest());
    }
    auto answers = FanOut<v1::Stats>(*shards, [&](const std::string& shard) {
      return Unary(&v1::AdminService::Stub::GetStats, admin_.get(), v1::GetStatsRequest(), "",
                   shard);
    });
    std::vector<v1::Stats> parts;
    std::vector<std::string> unreachable;
    for (size_t i = 0; i < shards->size(); ++i) {
      if (answers[i].ok()) {
        parts.push_back(*std::move(answers[i]));
      } else if (absl::IsUnavailable(answers[i].status()) ||
                 absl::IsDeadlineExceeded(answers[i].status())) {
        unreachable.push_back(absl::StrCat((*shards)[i], ": ", answers[i].status().message()));
      } else {
        return answers[i].status();
      }
    }
    if (parts.empty()) {
      return absl::UnavailableError(
          absl::StrCat("no shard answered: ", absl::StrJoin(unreachable, "; ")));
    }
    v1::Stats merged = MergeStats(parts);
    for (std::string& u : unreachable) merged.add_unreachable_shards(std::move(u));
    return merged;
  }
  absl::StatusOr<v1::BackupResponse> Backup(const std::string& name) override {
    v1::BackupRequest req;
    req.set_name(name);
    return Unary(&v1::AdminService::Stub::Backup, admin_.get(), req);
  }
  absl::StatusOr<v1::CheckIntegrityResponse> CheckIntegrity() override {
    return Unary(&v1::AdminService::Stub::CheckIntegrity, admin_.get(),
                 v1::CheckIntegrityRequest());
  }
  absl::StatusOr<v1::VacuumResponse> Vacuum() override {
    return Unary(&v1::AdminService::Stub::Vacuum, admin_.get(), v1::VacuumRequest());
  }
  absl::StatusOr<v1::AppearanceIndexInfo> RebuildAppearanceIndex(bool retrain) override {
    v1::RebuildAppearanceIndexRequest req;
    req.set_retrain(retrain);
    return Unary(&v1::AdminService::Stub::RebuildAppearanceIndex, admin_.get(), req);
  }
  absl::StatusOr<v1::RetentionReport> ApplyRetention(
      const v1::ApplyRetentionRequest& request) override {
    return Unary(&v1::AdminService::Stub::ApplyRetention, admin_.get(), request);
  }
  absl::StatusOr<v1::CreateApiKeyResponse> CreateApiKey(
      const v1::CreateApiKeyRequest& request) override {
    return Unary(&v1::AdminService::Stub::CreateApiKey, admin_.get(), request);
  }
  absl::StatusOr<v1::ListApiKeysResponse> ListApiKeys() override {
    return Unary(&v1::AdminService::Stub::ListApiKeys, admin_.get(), v1::ListApiKeysRequest());
  }
  absl::StatusOr<v1::ApiKey> RevokeApiKey(const std::string& name) override {
    v1::RevokeApiKeyRequest req;
    req.set_name(name);
    return Unary(&v1::AdminService::Stub::RevokeApiKey, admin_.get(), req);
  }
  absl::StatusOr<v1::ListAuditEventsResponse> ListAuditEvents(
      const v1::ListAuditEventsRequest& request) override {
    return Unary(&v1::AdminService::Stub::ListAuditEvents, admin_.get(), request);
  }
  absl::StatusOr<v1::RefreshPlacementResponse> RefreshPlacement(const std::string& map) override {
    v1::RefreshPlacementRequest req;
    req.set_map(map);
    // Waits for the map's writes to drain on a source shard: up to a minute.
    return Unary(&v1::AdminService::Stub::RefreshPlacement, admin_.get(), req, map, "",
                 std::max(options_.call_timeout_s, 90.0));
  }

  absl::StatusOr<v1::Map> CreateMap(const std::string& name,
                                    const std::string& description) override {
    v1::CreateMapRequest req;
    req.set_name(name);
    req.set_description(description);
    return Unary(&v1::MapService::Stub::CreateMap, maps_.get(), req, name);
  }
  // Through a cluster, every shard is asked (named in kShardHeader) and the answers merged by
  // name; a shard that does not answer is listed in unreachable_shards, not an error.
  absl::StatusOr<v1::ListMapsResponse> ListMaps() override {
    auto shards = ClusterShards();
    if (!shards.ok()) return shards.status();
    if (shards->empty()) {
      return Unary(&v1::MapService::Stub::ListMaps, maps_.get(), v1::ListMapsRequest());
    }
    auto answers = FanOut<v1::ListMapsResponse>(*shards, [&](const std::string& shard) {
      return Unary(&v1::MapService::Stub::ListMaps, maps_.get(), v1::ListMapsRequest(), "", shard);
    });
    v1::ListMapsResponse merged;
    for (size_t i = 0; i < shards->size(); ++i) {
      if (!answers[i].ok()) {
        merged.add_unreachable_shards(
            absl::StrCat((*shards)[i], ": ", answers[i].status().message()));
        continue;
      }
      for (v1::Map& m : *answers[i]->mutable_maps()) *merged.add_maps() = std::move(m);
    }
    std::sort(merged.mutable_maps()->begin(), merged.mutable_maps()->end(),
              [](const v1::Map& a, const v1::Map& b) { return a.name() < b.name(); });
    return merged;
  }
  absl::StatusOr<v1::Map> GetMap(const std::string& name) override {
    v1::GetMapRequest req;
    req.set_name(name);
    return Unary(&v1::MapService::Stub::GetMap, maps_.get(), req, name);
  }
  absl::StatusOr<v1::Map> RenameMap(const std::string& name, const std::string& new_name) override {
    v1::RenameMapRequest req;
    req.set_name(name);
    req.set_new_name(new_name);
    return Unary(&v1::MapService::Stub::RenameMap, maps_.get(), req, name);
  }
  absl::StatusOr<v1::DeleteMapResponse> DeleteMap(const std::string& name) override {
    v1::DeleteMapRequest req;
    req.set_name(name);
    return Unary(&v1::MapService::Stub::DeleteMap, maps_.get(), req, name);
  }
  absl::StatusOr<v1::Map> UpdateMap(const v1::UpdateMapRequest& request) override {
    return Unary(&v1::MapService::Stub::UpdateMap, maps_.get(), request, request.name());
  }
  absl::StatusOr<v1::ListKeyframesResponse> ListKeyframes(const std::string& map,
                                                          uint64_t visit_id) override {
    v1::ListKeyframesRequest req;
    req.set_map(map);
    req.set_visit_id(visit_id);
    return Unary(&v1::MapService::Stub::ListKeyframes, maps_.get(), req, map);
  }
  absl::StatusOr<v1::Keyframe> GetKeyframe(const std::string& map, uint64_t keyframe_id) override {
    v1::GetKeyframeRequest req;
    req.set_map(map);
    req.set_keyframe_id(keyframe_id);
    return Unary(&v1::MapService::Stub::GetKeyframe, maps_.get(), req, map);
  }
  absl::StatusOr<uint64_t> ExportMap(const v1::ExportMapRequest& request, std::ostream* out,
                                     std::vector<std::string>* left_out,
                                     v1::OccupancyGridInfo* grid) override {
    grpc::ClientContext context;
    AddKey(&context);
    AddRoute(&context, request.map());
    auto reader = maps_->ExportMap(&context, request);
    v1::ExportChunk chunk;
    uint64_t items = 0;
    bool last = false;
    while (reader->Read(&chunk)) {
      out->write(chunk.data().data(), static_cast<std::streamsize>(chunk.data().size()));
      if (chunk.last()) {
        items = chunk.item_count();
        last = true;
        if (left_out != nullptr) left_out->assign(chunk.left_out().begin(), chunk.left_out().end());
        if (grid != nullptr) *grid = chunk.grid();
      }
    }
    if (auto s = FromGrpc(reader->Finish()); !s.ok()) return s;
    if (!last) return absl::DataLossError("export ended without its last chunk");
    if (!*out) return absl::DataLossError("writing the export failed");
    return items;
  }
  absl::StatusOr<v1::Map> ImportMap(std::istream* in, const std::string& name,
                                    bool keep_ids) override {
    constexpr size_t kChunk = 1 << 20;
    // The first chunk is read before the call starts: through a cluster the call is routed by
    // the map's name, which without `name` is the one in the archive's manifest.
    std::string buffer(kChunk, '\0');
    in->read(buffer.data(), static_cast<std::streamsize>(buffer.size()));
    size_t n = static_cast<size_t>(in->gcount());
    grpc::ClientContext context;
    AddKey(&context);
    AddRoute(&context, name.empty() ? ArchiveMapName(std::string_view(buffer.data(), n)) : name);
    v1::Map map;
    auto writer = maps_->ImportMap(&context, &map);
    for (bool first = true;; first = false) {
      if (n == 0 && !first) break;
      v1::ImportChunk chunk;
      if (first) {
        chunk.set_name(name);
        chunk.set_keep_ids(keep_ids);
      }
      chunk.set_data(buffer.substr(0, n));
      if (!writer->Write(chunk)) break;  // the server answered early; Finish() says why
      if (!*in) break;
      in->read(buffer.data(), static_cast<std::streamsize>(buffer.size()));
      n = static_cast<size_t>(in->gcount());
    }
    const bool read_failed = in->bad();
    writer->WritesDone();
    if (auto s = FromGrpc(writer->Finish()); !s.ok()) return s;
    if (read_failed) return absl::DataLossError("reading the archive failed");
    return map;
  }
  absl::Status RebuildSemanticOctrees(
      const v1::RebuildSemanticOctreesRequest& request,
      const std::function<void(const v1::SemanticOctreeRebuild&)>& on_visit) override {
    grpc::ClientContext context;
    AddKey(&context);
    AddRoute(&context, request.map());
    auto reader = maps_->RebuildSemanticOctrees(&context, request);
    v1::SemanticOctreeRebuild visit;
    while (reader->Read(&visit)) on_visit(visit);
    return FromGrpc(reader->Finish());
  }

  absl::StatusOr<v1::Visit> StartVisit(const v1::StartVisitRequest& request) override {
    auto visit = Unary(&v1::VisitService::Stub::StartVisit, visits_.get(), request, request.map());
    if (visit.ok()) RememberVisit(visit->id(), visit->map());
    return visit;
  }
  absl::StatusOr<v1::Visit> EndVisit(uint64_t visit_id) override {
    v1::EndVisitRequest req;
    req.set_visit_id(visit_id);
    return Unary(&v1::VisitService::Stub::EndVisit, visits_.get(), req, MapOfVisit(visit_id));
  }
  absl::StatusOr<v1::DeleteVisitResponse> DeleteVisit(uint64_t visit_id) override {
    v1::DeleteVisitRequest req;
    req.set_visit_id(visit_id);
    return Unary(&v1::VisitService::Stub::DeleteVisit, visits_.get(), req, MapOfVisit(visit_id));
  }
  absl::StatusOr<v1::ListVisitsResponse> ListVisits(const std::string& map) override {
    v1::ListVisitsRequest req;
    req.set_map(map);
    auto visits = Unary(&v1::VisitService::Stub::ListVisits, visits_.get(), req, map);
    if (visits.ok()) {
      for (const v1::Visit& v : visits->visits()) RememberVisit(v.id(), v.map());
    }
    return visits;
  }
  absl::StatusOr<v1::AnchorVisitsResponse> AnchorVisits(const std::string& map, uint64_t visit_id,
                                                        bool dry_run) override {
    v1::AnchorVisitsRequest req;
    req.set_map(map);
    req.set_visit_id(visit_id);
    req.set_dry_run(dry_run);
    return Unary(&v1::VisitService::Stub::AnchorVisits, visits_.get(), req, map);
  }
  absl::StatusOr<v1::AnchorHistory> GetAnchorHistory(uint64_t visit_id) override {
    v1::GetAnchorHistoryRequest req;
    req.set_visit_id(visit_id);
    return Unary(&v1::VisitService::Stub::GetAnchorHistory, visits_.get(), req,
                 MapOfVisit(visit_id));
  }
  absl::StatusOr<v1::VisitChanges> GetChanges(const std::string& map, uint64_t from_visit,
                                              uint64_t to_visit) override {
    v1::GetChangesRequest req;
    req.set_map(map);
    req.set_from_visit(from_visit);
    req.set_to_visit(to_visit);
    return Unary(&v1::VisitService::Stub::GetChanges, visits_.get(), req, map);
  }

  absl::StatusOr<v1::FrameResult> ProcessFrame(const v1::ProcessFrameRequest& request) override {
    return Unary(&v1::FrameService::Stub::ProcessFrame, frames_.get(), request, request.map());
  }

  absl::StatusOr<std::unique_ptr<FrameStream>> OpenStream(const v1::StreamStart& start) override {
    auto context = std::make_unique<grpc::ClientContext>();
    AddKey(context.get());
    AddRoute(context.get(), start.map());
    auto stream = frames_->StreamFrames(context.get());
    v1::StreamFramesRequest request;
    *request.mutable_start() = start;
    v1::StreamFramesResponse response;
    if (!stream->Write(request) || !stream->Read(&response) || !response.has_started()) {
      stream->WritesDone();
      grpc::Status s = stream->Finish();
      if (s.ok()) return absl::InternalError("server did not acknowledge the stream start");
      return FromGrpc(s);
    }
    RememberVisit(response.started().visit_id(), response.started().map());
    return std::unique_ptr<FrameStream>(new GrpcFrameStream(
        std::move(context), std::move(stream), std::move(*response.mutable_started())));
  }

 private:
  // The cluster's shard names (GetServerInfo through nginx); empty for a lone server or a
  // client connected straight to one shard.
  absl::StatusOr<std::vector<std::string>> ClusterShards() {
    auto info = GetServerInfo();
    if (!info.ok()) return info.status();
    std::vector<std::string> names;
    for (const v1::ShardInfo& shard : info->shards()) names.push_back(shard.name());
    return names;
  }

  // `call(shard)` for every shard at once (a thread each); the answers in the shards' order.
  template <typename Response, typename Call>
  std::vector<absl::StatusOr<Response>> FanOut(const std::vector<std::string>& shards,
                                               const Call& call) {
    std::vector<absl::StatusOr<Response>> answers(shards.size(), absl::UnknownError("not asked"));
    std::vector<std::thread> threads;
    threads.reserve(shards.size());
    for (size_t i = 0; i < shards.size(); ++i) {
      threads.emplace_back([&, i] { answers[i] = call(shards[i]); });
    }
    for (std::thread& t : threads) t.join();
    return answers;
  }

  template <typename Stub, typename Request, typename Response>
  absl::StatusOr<Response> Unary(grpc::Status (Stub::*method)(grpc::ClientContext*, const Request&,
                                                              Response*),
                                 Stub* stub, const Request& request, const std::string& map = "",
                                 const std::string& shard = "", double timeout_s = 0) {
    grpc::ClientContext context;
    AddKey(&context);
    AddRoute(&context, map);
    if (!shard.empty()) context.AddMetadata(kShardHeader, shard);
    if (timeout_s <= 0) timeout_s = options_.call_timeout_s;
    context.set_deadline(std::chrono::system_clock::now() +
                         std::chrono::milliseconds(static_cast<int64_t>(timeout_s * 1000)));
    Response response;
    if (auto s = FromGrpc((stub->*method)(&context, request, &response)); !s.ok()) return s;
    return response;
  }

  // The API key, if any, as `authorization: Bearer KEY` (gRPC's call credentials would not be
  // sent over a plaintext channel, which a server on loopback may use with keys).
  void AddKey(grpc::ClientContext* context) const {
    if (!options_.api_key.empty())
      context->AddMetadata("authorization", "Bearer " + options_.api_key);
  }

  // The map a call is about, for a cluster's nginx to route on (harmless to a lone server);
  // percent-encoded, since a header value that is not printable ASCII aborts gRPC.
  static void AddRoute(grpc::ClientContext* context, const std::string& map) {
    if (!map.empty()) context->AddMetadata(kMapHeader, EncodeHeaderValue(map));
  }
  // Calls that name only a visit are routed by the map the visit was seen in (StartVisit,
  // OpenStream, ListVisits); "" if this client has not seen it.
  void RememberVisit(uint64_t visit_id, const std::string& map) {
    if (visit_id == 0 || map.empty()) return;
    absl::MutexLock lock(&visits_mu_);
    visit_maps_[visit_id] = map;
  }
  std::string MapOfVisit(uint64_t visit_id) {
    absl::MutexLock lock(&visits_mu_);
    const auto it = visit_maps_.find(visit_id);
    return it == visit_maps_.end() ? "" : it->second;
  }

  ClientOptions options_;
  absl::Mutex visits_mu_;
  absl::flat_hash_map<uint64_t, std::string> visit_maps_ ABSL_GUARDED_BY(visits_mu_);
  std::unique_ptr<v1::MapService::Stub> maps_;
  std::unique_ptr<v1::VisitService::Stub> visits_;
  std::unique_ptr<v1::FrameService::Stub> frames_;
  std::unique_ptr<v1::ModelService::Stub> models_;
  std::unique_ptr<v1::PlaceService::Stub> places_;
  std::unique_ptr<v1::AdminService::Stub> admin_;
};

}  // namespace

absl::StatusOr<std::string> ResolveApiKey(const std::string& key, const std::string& key_file) {
  if (!key.empty()) return key;
  if (!key_file.empty()) {
    auto bytes = ReadFileBytes(key_file);
    if (!bytes.ok()) {
      return absl::InvalidArgumentError(absl::StrCat("API key file: ", bytes.status().message()));
    }
    const std::string line(absl::StripAsciiWhitespace(bytes->substr(0, bytes->find('\n'))));
    if (line.empty()) {
      return absl::InvalidArgumentError(
          absl::StrCat("API key file ", key_file, " is empty: its first line must be the key"));
    }
    return line;
  }
  const char* env = std::getenv("LIFEMAP_API_KEY");
  return std::string(env != nullptr ? env : "");
}

absl::Status ValidateTarget(const std::string& target) {
  for (const char* scheme : {"unix:", "unix-abstract:", "dns:", "ipv4:", "ipv6:"}) {
    if (target.rfind(scheme, 0) == 0) return absl::OkStatus();
  }
  const auto bad = [&](const std::string& why) {
    return absl::InvalidArgumentError(absl::StrCat("server address '", target, "' ", why,
                                                   ": give HOST:PORT, e.g. 127.0.0.1:50051"));
  };
  const auto colon = target.rfind(':');
  if (target.empty() || colon == std::string::npos) return bad("has no port");
  const std::string host = target.substr(0, colon), port = target.substr(colon + 1);
  if (host.empty()) return bad("has no host");
  if (port.empty() || port.size() > 5 ||
      port.find_first_not_of("0123456789") != std::string::npos || std::stoi(port) < 1 ||
      std::stoi(port) > 65535) {
    return bad("has no port number in 1-65535 after its last ':'");
  }
  if (host.front() == '[' ? host.back() != ']' : host.find(':') != std::string::npos) {
    return bad("has an IPv6 address without brackets ([::1]:50051)");
  }
  for (const char c : host) {
    if (!(absl::ascii_isalnum(static_cast<unsigned char>(c)) || c == '.' || c == '-' || c == '_' ||
          c == '[' || c == ']' || c == ':' || c == '%')) {
      return bad(absl::StrCat("holds '", std::string(1, c), "', which no host name has"));
    }
  }
  return absl::OkStatus();
}

namespace {

// Empty when `target`'s host resolves (or is not a name); else why not, for the user.
std::string ResolveFailure(const std::string& target) {
  const auto colon = target.rfind(':');
  if (colon == std::string::npos || target.find('/') != std::string::npos) return "";
  std::string host = target.substr(0, colon);
  if (host.rfind("dns:", 0) == 0 || host.rfind("unix", 0) == 0 || host.front() == '[') return "";
  addrinfo hints{};
  hints.ai_family = AF_UNSPEC;
  addrinfo* found = nullptr;
  const int rc = getaddrinfo(host.c_str(), nullptr, &hints, &found);
  if (found != nullptr) freeaddrinfo(found);
  if (rc == 0) return "";
  return absl::StrCat("the host name '", host, "' does not resolve (", gai_strerror(rc),
                      "): check --server or LIFEMAP_SERVER");
}

}  // namespace

absl::StatusOr<std::unique_ptr<Client>> Client::Connect(const ClientOptions& options) {
  if (auto s = ValidateTarget(options.target); !s.ok()) return s;
  grpc::ChannelArguments args;
  args.SetMaxReceiveMessageSize(options.max_message_bytes);
  args.SetMaxSendMessageSize(options.max_message_bytes);
  const bool tls = options.tls || !options.tls_ca_file.empty() || !options.tls_cert_file.empty() ||
                   !options.tls_key_file.empty();
  std::shared_ptr<grpc::ChannelCredentials> credentials = grpc::InsecureChannelCredentials();
  if (tls) {
    if (options.tls_cert_file.empty() != options.tls_key_file.empty()) {
      return absl::InvalidArgumentError(
          "a client certificate needs its private key: give both --tls-cert and --tls-key");
    }
    grpc::SslCredentialsOptions ssl;
    for (auto [file, pem] : {std::pair{&options.tls_ca_file, &ssl.pem_root_certs},
                             std::pair{&options.tls_cert_file, &ssl.pem_cert_chain},
                             std::pair{&options.tls_key_file, &ssl.pem_private_key}}) {
      if (file->empty()) continue;
      auto bytes = ReadFileBytes(*file);
      if (!bytes.ok()) return bytes.status();
      *pem = *std::move(bytes);
    }
    credentials = grpc::SslCredentials(ssl);
  }
  auto channel = grpc::CreateCustomChannel(options.target, credentials, args);
  const auto deadline =
      std::chrono::system_clock::now() +
      std::chrono::milliseconds(static_cast<int64_t>(options.connect_timeout_s * 1000));
  if (!channel->WaitForConnected(deadline)) {
    if (const std::string why = ResolveFailure(options.target); !why.empty()) {
      return absl::UnavailableError(
          absl::StrCat("cannot reach lifemapd at ", options.target, ": ", why));
    }
    return absl::UnavailableError(absl::StrCat(
        "cannot reach lifemapd at ", options.target, " within ", options.connect_timeout_s,
        " s: is it running? (set --server or LIFEMAP_SERVER)",
        tls ? "; over TLS: does the server speak TLS, and is its certificate signed by the CA "
              "given (--tls-ca) for this host name?"
            : "; if the server speaks TLS, connect with --tls-ca FILE"));
  }
  return std::unique_ptr<Client>(new GrpcClient(std::move(channel), options));
}

absl::StatusOr<v1::Frame> FrameFromFiles(const std::string& rgb_path, const std::string& depth_path,
                                         double depth_scale, const v1::CameraIntrinsics& intrinsics,
                                         double timestamp_s, uint64_t sequence) {
  const bool with_color = !rgb_path.empty();
  absl::StatusOr<std::string> rgb = std::string();
  if (with_color) rgb = ReadFileBytes(rgb_path);
  if (!rgb.ok()) return rgb.status();
  auto depth = ReadFileBytes(depth_path);
  if (!depth.ok()) return depth.status();
  absl::StatusOr<ImageHeader> rgb_header = ImageHeader();
  if (with_color) rgb_header = ProbeImage(*rgb);
  if (!rgb_header.ok()) {
    return absl::InvalidArgumentError(absl::StrCat(rgb_path, ": ", rgb_header.status().message()));
  }
  auto depth_header = ProbeImage(*depth);
  if (!depth_header.ok()) {
    return absl::InvalidArgumentError(
        absl::StrCat(depth_path, ": ", depth_header.status().message()));
  }
  if (depth_header->format != ImageFormat::kPng || depth_header->bit_depth != 16 ||
      depth_header->channels != 1) {
    return absl::InvalidArgumentError(
        absl::StrCat(depth_path, ": depth must be a 16-bit single-channel PNG"));
  }
  if (with_color &&
      (rgb_header->width != depth_header->width || rgb_header->height != depth_header->height)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "colour ", rgb_path, " is ", rgb_header->width, "x", rgb_header->height, " but depth ",
        depth_path, " is ", depth_header->width, "x", depth_header->height,
        "; a frame's colour and depth must be the same size (depth registered to the colour "
        "camera)"));
  }
  v1::Frame frame;
  frame.set_sequence(sequence);
  frame.set_timestamp_s(timestamp_s);
  *frame.mutable_intrinsics() = intrinsics;
  if (intrinsics.width() == 0 && intrinsics.height() == 0) {
    const ImageHeader& sized = with_color ? *rgb_header : *depth_header;
    frame.mutable_intrinsics()->set_width(static_cast<uint32_t>(sized.width));
    frame.mutable_intrinsics()->set_height(static_cast<uint32_t>(sized.height));
  }
  auto* d = frame.mutable_depth();
  d->set_encoding(v1::DEPTH_PNG16);
  d->set_width(static_cast<uint32_t>(depth_header->width));
  d->set_height(static_cast<uint32_t>(depth_header->height));
  d->set_depth_scale(depth_scale);
  d->set_data(*std::move(depth));
  if (!with_color) return frame;
  auto* c = frame.mutable_color();
  c->set_encoding(rgb_header->format == ImageFormat::kPng ? v1::COLOR_PNG : v1::COLOR_JPEG);
  c->set_width(static_cast<uint32_t>(rgb_header->width));
  c->set_height(static_cast<uint32_t>(rgb_header->height));
  c->set_data(*std::move(rgb));
  return frame;
}

absl::StatusOr<v1::Frame> CompactFrame(const v1::Frame& frame, int jpeg_quality) {
  v1::Frame out = frame;
  const auto& color = frame.color();
  if (color.encoding() == v1::COLOR_PNG || color.encoding() == v1::COLOR_RAW_RGB8) {
    auto bgr = DecodeColorBgr(
        {color.encoding() == v1::COLOR_PNG ? ColorEncoding::kPng : ColorEncoding::kRawRgb8,
         color.data(), static_cast<int>(color.width()), static_cast<int>(color.height())});
    if (!bgr.ok()) return bgr.status();
    auto jpeg = EncodeJpeg(*bgr, jpeg_quality);
    if (!jpeg.ok()) return jpeg.status();
    out.mutable_color()->set_encoding(v1::COLOR_JPEG);
    out.mutable_color()->set_width(static_cast<uint32_t>(bgr->cols));
    out.mutable_color()->set_height(static_cast<uint32_t>(bgr->rows));
    out.mutable_color()->set_data(*std::move(jpeg));
  }
  const auto& depth = frame.depth();
  cv::Mat u16;
  if (depth.encoding() == v1::DEPTH_PNG16) {
    auto header = ProbeImage(depth.data());
    if (!header.ok()) return header.status();
    if (header->bit_depth != 16 || header->channels != 1) {
      return absl::InvalidArgumentError("depth PNG must be 16-bit single-channel");
    }
    const std::vector<uchar> bytes(depth.data().begin(), depth.data().end());
    u16 = cv::imdecode(bytes, cv::IMREAD_UNCHANGED);
    if (u16.type() != CV_16UC1) return absl::InvalidArgumentError("depth PNG could not be decoded");
  } else if (depth.encoding() == v1::DEPTH_RAW_U16) {
    const size_t n = size_t{depth.width()} * depth.height();
    if (n == 0 || depth.data().size() != 2 * n) {
      return absl::InvalidArgumentError("raw depth size does not match width x height");
    }
    u16 = cv::Mat(static_cast<int>(depth.height()), static_cast<int>(depth.width()), CV_16UC1,
                  const_cast<char*>(depth.data().data()))
              .clone();
  }
  if (!u16.empty()) {
    out.mutable_depth()->set_encoding(v1::DEPTH_PALETTED);
    out.mutable_depth()->set_width(static_cast<uint32_t>(u16.cols));
    out.mutable_depth()->set_height(static_cast<uint32_t>(u16.rows));
    out.mutable_depth()->set_data(EncodePalettedDepth(u16));
  }
  return out;
}

}  // namespace lifemap::client
