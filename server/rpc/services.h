// The gRPC service implementations. Each is thin: validate, call store / core, convert.
#pragma once

#include <atomic>
#include <chrono>
#include <memory>

#include "core/pipeline/frame_pipeline.h"
#include "lifemap/v1/admin_service.grpc.pb.h"
#include "lifemap/v1/frame_service.grpc.pb.h"
#include "lifemap/v1/map_service.grpc.pb.h"
#include "lifemap/v1/model_service.grpc.pb.h"
#include "lifemap/v1/place_service.grpc.pb.h"
#include "lifemap/v1/visit_service.grpc.pb.h"
#include "server/config.h"
#include "server/engine/appearance.h"
#include "server/engine/clock.h"
#include "server/engine/engine.h"
#include "server/engine/visit_registry.h"
#include "server/rpc/auth.h"
#include "server/rpc/shard_membership.h"
#include "server/rpc/stream_watchdog.h"
#include "server/store/store.h"

namespace lifemap::server {

// What FrameOptions.result_images RESULT_IMAGES_DEFAULT means (GetServerInfo says it).
inline constexpr v1::ResultImages kDefaultResultImages = v1::RESULT_IMAGES_PNG;

// What the services share: the engine, the key ring, the stream watchdog; owned by
// LifemapServer.
struct ServiceContext {
  ServerConfig config;
  Engine* engine = nullptr;                   // the lifelong map (server/engine/engine.h)
  KeyRing* keys = nullptr;                    // who may call what (server/rpc/auth.h)
  StreamWatchdog* stream_watchdog = nullptr;  // ends streams that went quiet
  ShardMembership* shard = nullptr;  // a shard of a cluster (--placement); null when alone
  double started_time_s = 0.0;
  std::atomic<int> active_streams{0};
};

class MapServiceImpl final : public v1::MapService::Service {
 public:
  explicit MapServiceImpl(ServiceContext* ctx) : ctx_(ctx) {}
  grpc::Status CreateMap(grpc::ServerContext*, const v1::CreateMapRequest*, v1::Map*) override;
  grpc::Status ListMaps(grpc::ServerContext*, const v1::ListMapsRequest*,
                        v1::ListMapsResponse*) override;
  grpc::Status GetMap(grpc::ServerContext*, const v1::GetMapRequest*, v1::Map*) override;
  grpc::Status DeleteMap(grpc::ServerContext*, const v1::DeleteMapRequest*,
                         v1::DeleteMapResponse*) override;
  grpc::Status RenameMap(grpc::ServerContext*, const v1::RenameMapRequest*, v1::Map*) override;
  grpc::Status UpdateMap(grpc::ServerContext*, const v1::UpdateMapRequest*, v1::Map*) override;
  grpc::Status ListKeyframes(grpc::ServerContext*, const v1::ListKeyframesRequest*,
                             v1::ListKeyframesResponse*) override;
  grpc::Status GetKeyframe(grpc::ServerContext*, const v1::GetKeyframeRequest*,
                           v1::Keyframe*) override;
  grpc::Status ExportMap(grpc::ServerContext*, const v1::ExportMapRequest*,
                         grpc::ServerWriter<v1::ExportChunk>*) override;
  grpc::Status ImportMap(grpc::ServerContext*, grpc::ServerReader<v1::ImportChunk>*,
                         v1::Map*) override;
  grpc::Status RebuildSemanticOctrees(grpc::ServerContext*,
                                      const v1::RebuildSemanticOctreesRequest*,
                                      grpc::ServerWriter<v1::SemanticOctreeRebuild>*) override;

 private:
  // ExportMap's semantic octree formats (server/engine/semantic_export.h).
  grpc::Status ExportSemantic(const store::MapRecord& map, const v1::ExportMapRequest& req,
                              grpc::ServerWriter<v1::ExportChunk>* writer);
  // ExportMap's occupancy formats, without a model (server/engine/occupancy_export.h).
  grpc::Status ExportOccupancyOf(const store::MapRecord& map, int64_t visit_id,
                                 const v1::ExportMapRequest& req, grpc::ServerContext* context,
                                 grpc::ServerWriter<v1::ExportChunk>* writer);

  // A shard of a cluster places a map it is about to hold (true: placed now, to be undone if
  // the map is not made after all); a lone server places nothing (false).
  absl::StatusOr<bool> PlaceNewMap(const std::string& name);
  ServiceContext* ctx_;
};

class VisitServiceImpl final : public v1::VisitService::Service {
 public:
  explicit VisitServiceImpl(ServiceContext* ctx) : ctx_(ctx) {}
  grpc::Status StartVisit(grpc::ServerContext*, const v1::StartVisitRequest*, v1::Visit*) override;
  grpc::Status EndVisit(grpc::ServerContext*, const v1::EndVisitRequest*, v1::Visit*) override;
  grpc::Status ListVisits(grpc::ServerContext*, const v1::ListVisitsRequest*,
                          v1::ListVisitsResponse*) override;
  grpc::Status AnchorVisits(grpc::ServerContext*, const v1::AnchorVisitsRequest*,
                            v1::AnchorVisitsResponse*) override;
  grpc::Status GetAnchorHistory(grpc::ServerContext*, const v1::GetAnchorHistoryRequest*,
                                v1::AnchorHistory*) override;
  grpc::Status GetChanges(grpc::ServerContext*, const v1::GetChangesRequest*,
                          v1::VisitChanges*) override;
  grpc::Status DeleteVisit(grpc::ServerContext*, const v1::DeleteVisitRequest*,
                           v1::DeleteVisitResponse*) override;

 private:
  ServiceContext* ctx_;
};

class FrameServiceImpl final : public v1::FrameService::Service {
 public:
  explicit FrameServiceImpl(ServiceContext* ctx) : ctx_(ctx) {}
  grpc::Status StreamFrames(
      grpc::ServerContext* context,
      grpc::ServerReaderWriter<v1::StreamFramesResponse, v1::StreamFramesRequest>* stream) override;
  grpc::Status ProcessFrame(grpc::ServerContext*, const v1::ProcessFrameRequest*,
                            v1::FrameResult*) override;

 private:
  ServiceContext* ctx_;
};

class PlaceServiceImpl final : public v1::PlaceService::Service {
 public:
  explicit PlaceServiceImpl(ServiceContext* ctx) : ctx_(ctx) {}
  grpc::Status QueryPlace(grpc::ServerContext*, const v1::QueryPlaceRequest*,
                          v1::QueryPlaceResponse*) override;
  grpc::Status ListPlaces(grpc::ServerContext*, const v1::ListPlacesRequest*,
                          v1::ListPlacesResponse*) override;

 private:
  static constexpr int kMaxQueryFrames = 2000;
  static constexpr int kMaxAppearanceQueryFrames = 200;
  ServiceContext* ctx_;
};

class ModelServiceImpl final : public v1::ModelService::Service {
 public:
  explicit ModelServiceImpl(ServiceContext* ctx) : ctx_(ctx) {}
  grpc::Status UploadModel(grpc::ServerContext*, grpc::ServerReader<v1::UploadModelChunk>*,
                           v1::ModelInfo*) override;
  grpc::Status ListModels(grpc::ServerContext*, const v1::ListModelsRequest*,
                          v1::ListModelsResponse*) override;
  grpc::Status ActivateModel(grpc::ServerContext*, const v1::ActivateModelRequest*,
                             v1::ActivateModelResponse*) override;
  grpc::Status DeleteModel(grpc::ServerContext*, const v1::DeleteModelRequest*,
                           v1::DeleteModelResponse*) override;
  grpc::Status ListClasses(grpc::ServerContext*, const v1::ListClassesRequest*,
                           v1::ListClassesResponse*) override;

 private:
  ServiceContext* ctx_;
};

class AdminServiceImpl final : public v1::AdminService::Service {
 public:
  explicit AdminServiceImpl(ServiceContext* ctx) : ctx_(ctx) {}
  grpc::Status GetServerInfo(grpc::ServerContext*, const v1::GetServerInfoRequest*,
                             v1::ServerInfo*) override;
  grpc::Status GetStats(grpc::ServerContext*, const v1::GetStatsRequest*, v1::Stats*) override;
  grpc::Status Backup(grpc::ServerContext*, const v1::BackupRequest*, v1::BackupResponse*) override;
  grpc::Status CheckIntegrity(grpc::ServerContext*, const v1::CheckIntegrityRequest*,
                              v1::CheckIntegrityResponse*) override;
  grpc::Status Vacuum(grpc::ServerContext*, const v1::VacuumRequest*, v1::VacuumResponse*) override;
  grpc::Status CreateApiKey(grpc::ServerContext*, const v1::CreateApiKeyRequest*,
                            v1::CreateApiKeyResponse*) override;
  grpc::Status ListApiKeys(grpc::ServerContext*, const v1::ListApiKeysRequest*,
                           v1::ListApiKeysResponse*) override;
  grpc::Status RevokeApiKey(grpc::ServerContext*, const v1::RevokeApiKeyRequest*,
                            v1::ApiKey*) override;
  grpc::Status ListAuditEvents(grpc::ServerContext*, const v1::ListAuditEventsRequest*,
                               v1::ListAuditEventsResponse*) override;
  grpc::Status RefreshPlacement(grpc::ServerContext*, const v1::RefreshPlacementRequest*,
                                v1::RefreshPlacementResponse*) override;
  grpc::Status RebuildAppearanceIndex(grpc::ServerContext*,
                                      const v1::RebuildAppearanceIndexRequest*,
                                      v1::AppearanceIndexInfo*) override;
  grpc::Status ApplyRetention(grpc::ServerContext*, const v1::ApplyRetentionRequest*,
                              v1::RetentionReport*) override;

 private:
  void AppearanceInfoToProto(const AppearanceIndexStats& s, v1::AppearanceIndexInfo* out) const;
  ServiceContext* ctx_;
};

}  // namespace lifemap::server
