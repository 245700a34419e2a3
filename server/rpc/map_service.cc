#include <algorithm>
#include <cmath>

#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "core/common/rgbd_frame.h"
#include "core/common/utf8.h"
#include "core/io/tum_dataset.h"
#include "server/engine/cloud_export.h"
#include "server/engine/map_archive.h"
#include "server/engine/occupancy_export.h"
#include "server/engine/semantic_export.h"
#include "server/engine/semantic_rebuild.h"
#include "server/engine/visit_frame.h"
#include "server/rpc/convert.h"
#include "server/rpc/services.h"
#include "server/rpc/stream_read.h"

namespace lifemap::server {
namespace {

constexpr size_t kExportChunkBytes = 1 << 20;
constexpr size_t kDescriptionMaxBytes = 4096;

// OK when `visit_id` is 0 (every visit) or one of `map`'s visits; else NOT_FOUND.
absl::Status CheckVisitOfMap(store::Store* store, const store::MapRecord& map, int64_t visit_id) {
  if (visit_id == 0) return absl::OkStatus();
  auto visit = store->GetVisit(visit_id);
  if (!visit.ok()) return visit.status();
  if (visit->map_id != map.id) {
    return absl::NotFoundError(
        absl::StrCat("visit ", visit_id, " is not a visit of map '", map.name, "'"));
  }
  return absl::OkStatus();
}

v1::SemanticOctreeRebuild::Outcome OutcomeToProto(SemanticRebuild::Outcome o) {
  switch (o) {
    case SemanticRebuild::Outcome::kRebuilt:
      return v1::SemanticOctreeRebuild::OUTCOME_REBUILT;
    case SemanticRebuild::Outcome::kUpToDate:
      return v1::SemanticOctreeRebuild::OUTCOME_UP_TO_DATE;
    case SemanticRebuild::Outcome::kLeftOut:
      return v1::SemanticOctreeRebuild::OUTCOME_LEFT_OUT;
  }
  return v1::SemanticOctreeRebuild::OUTCOME_UNSPECIFIED;
}

// Sends `body` in chunks of at most kExportChunkBytes; the last chunk carries the item count.
grpc::Status SendChunks(const std::string& body, const std::string& content_type, uint64_t items,
                        grpc::ServerWriter<v1::ExportChunk>* writer,
                        const std::vector<std::string>& left_out = {},
                        const v1::OccupancyGridInfo* grid = nullptr) {
  size_t offset = 0;
  do {
    v1::ExportChunk chunk;
    const size_t n = std::min(kExportChunkBytes, body.size() - offset);
    chunk.set_data(body.substr(offset, n));
    if (offset == 0) chunk.set_content_type(content_type);
    offset += n;
    if (offset == body.size()) {
      chunk.set_last(true);
      chunk.set_item_count(items);
      for (const auto& l : left_out) chunk.add_left_out(ToValidUtf8(l));
      if (grid != nullptr) *chunk.mutable_grid() = *grid;
    }
    if (!writer->Write(chunk)) {
      return grpc::Status(grpc::StatusCode::CANCELLED, "client went away during export");
    }
  } while (offset < body.size());
  return grpc::Status::OK;
}

}  // namespace

absl::StatusOr<bool> MapServiceImpl::PlaceNewMap(const std::string& name) {
  if (ctx_->shard == nullptr) return false;
  return ctx_->shard->PlaceNew(name);
}

grpc::Status MapServiceImpl::CreateMap(grpc::ServerContext* context,
                                       const v1::CreateMapRequest* req, v1::Map* resp) {
  auto caller = ctx_->keys->Authorize(*context, "MapService/CreateMap");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  if (auto s = caller->CheckEveryMap("creating maps"); !s.ok()) return ToGrpcStatus(s);
  if (auto s = store::ValidateMapName(req->name()); !s.ok()) return ToGrpcStatus(s);
  if (req->description().size() > kDescriptionMaxBytes) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        absl::StrCat("description is ", req->description().size(),
                                     " bytes; at most ", kDescriptionMaxBytes));
  }
  auto threshold = EntropyThresholdFromProto(req->entropy_threshold(), "entropy_threshold");
  if (!threshold.ok()) return ToGrpcStatus(threshold.status());
  auto placed = PlaceNewMap(req->name());
  if (!placed.ok()) return ToGrpcStatus(placed.status());
  auto map =
      ctx_->engine->store()->CreateMap(req->name(), req->description(), NowSeconds(), *threshold,
                                       req->keep_original_color(), caller->AsMapCreator());
  if (!map.ok()) {
    if (*placed) ctx_->shard->Unplace(req->name());
    return ToGrpcStatus(map.status());
  }
  spdlog::info("created map '{}' (id {})", map->name, map->id);
  MapToProto(*map, resp);
  return grpc::Status::OK;
}

grpc::Status MapServiceImpl::ListMaps(grpc::ServerContext* context, const v1::ListMapsRequest*,
                                      v1::ListMapsResponse* resp) {
  auto caller = ctx_->keys->Authorize(*context, "MapService/ListMaps");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  // A fan-out meant for another shard that reached this one (a client connected to a shard
  // directly): answering would list this shard's maps as the other's.
  if (const auto meant = context->client_metadata().find(kShardHeader);
      ctx_->shard != nullptr && meant != context->client_metadata().end() &&
      std::string(meant->second.data(), meant->second.size()) != ctx_->shard->shard()) {
    return grpc::Status(grpc::StatusCode::FAILED_PRECONDITION,
                        absl::StrCat("this is shard '", ctx_->shard->shard(), "', not '",
                                     std::string(meant->second.data(), meant->second.size()),
                                     "': list a cluster's maps through its nginx"));
  }
  auto maps = ctx_->engine->store()->ListMaps();
  if (!maps.ok()) return ToGrpcStatus(maps.status());
  for (const auto& m : *maps) {
    // A shard lists only the maps it serves, not stale copies of maps that moved away.
    if (ctx_->shard != nullptr && !ctx_->shard->CheckMap(m.name, "MapService/ListMaps", false).ok())
      continue;
    if (caller->MayUseMap(m.id)) MapToProto(m, resp->add_maps());
  }
  return grpc::Status::OK;
}

grpc::Status MapServiceImpl::GetMap(grpc::ServerContext* context, const v1::GetMapRequest* req,
                                    v1::Map* resp) {
  auto caller = ctx_->keys->Authorize(*context, "MapService/GetMap");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  auto map = FindCallersMap(ctx_->engine->store(), *caller, req->name());
  if (!map.ok()) return ToGrpcStatus(map.status());
  MapToProto(*map, resp);
  auto in_frame = VisitsInMapFrame(ctx_->engine->store(), map->name);
  if (!in_frame.ok()) return ToGrpcStatus(in_frame.status());
  for (const std::string& why : in_frame->left_out) resp->add_left_out(why);
  return grpc::Status::OK;
}

grpc::Status MapServiceImpl::DeleteMap(grpc::ServerContext* context,
                                       const v1::DeleteMapRequest* req,
                                       v1::DeleteMapResponse* resp) {
  auto caller = ctx_->keys->Authorize(*context, "MapService/DeleteMap");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  auto map = FindCallersMap(ctx_->engine->store(), *caller, req->name());
  if (!map.ok()) return ToGrpcStatus(map.status());
  auto deleted = ctx_->engine->store()->DeleteMap(req->name());
  if (!deleted.ok()) return ToGrpcStatus(deleted.status());
  if (ctx_->shard != nullptr) ctx_->shard->Unplace(req->name());
  // Streams still writing its visits end with NOT_FOUND and commit nothing more.
  ctx_->engine->visits()->CloseMap(
      map->id, absl::NotFoundError(absl::StrCat(
                   "map '", req->name(), "' was deleted; nothing more is stored for its visits")));
  ctx_->engine->models()->InvalidateActivations();
  ctx_->engine->places()->Invalidate();
  ctx_->engine->appearance()->RemoveMap(map->id);
  spdlog::info("deleted map '{}': {} visits, {} keyframes", req->name(), deleted->first,
               deleted->second);
  resp->set_deleted_visits(static_cast<uint32_t>(deleted->first));
  resp->set_deleted_keyframes(static_cast<uint64_t>(deleted->second));
  return grpc::Status::OK;
}

grpc::Status MapServiceImpl::RenameMap(grpc::ServerContext* context,
                                       const v1::RenameMapRequest* req, v1::Map* resp) {
  auto caller = ctx_->keys->Authorize(*context, "MapService/RenameMap");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  if (auto m = FindCallersMap(ctx_->engine->store(), *caller, req->name()); !m.ok()) {
    return ToGrpcStatus(m.status());
  }
  if (ctx_->shard != nullptr) {
    return grpc::Status(grpc::StatusCode::FAILED_PRECONDITION,
                        "renaming a map of a cluster is not built yet (nginx routes by name): "
                        "export it, import it under the new name, delete the old one");
  }
  // Map names are one name space over every map: a key limited to some maps would learn from
  // ALREADY_EXISTS which names other maps have.
  if (auto s = caller->CheckEveryMap("renaming maps (names are shared by every map)"); !s.ok()) {
    return ToGrpcStatus(s);
  }
  if (auto s = store::ValidateMapName(req->new_name()); !s.ok()) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        absl::StrCat("new_name: ", s.message()));
  }
  auto map = ctx_->engine->store()->RenameMap(req->name(), req->new_name());
  if (!map.ok()) return ToGrpcStatus(map.status());
  ctx_->engine->visits()->RenameMap(map->id, map->name);
  ctx_->engine->places()->Invalidate();  // rankings name maps
  MapToProto(*map, resp);
  return grpc::Status::OK;
}

grpc::Status MapServiceImpl::UpdateMap(grpc::ServerContext* context,
                                       const v1::UpdateMapRequest* req, v1::Map* resp) {
  auto caller = ctx_->keys->Authorize(*context, "MapService/UpdateMap");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  auto map = FindCallersMap(ctx_->engine->store(), *caller, req->name());
  if (!map.ok()) return ToGrpcStatus(map.status());
  store::MapUpdate update;
  if (req->has_description()) {
    if (req->description().size() > kDescriptionMaxBytes) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                          absl::StrCat("description is ", req->description().size(),
                                       " bytes; at most ", kDescriptionMaxBytes));
    }
    update.description = req->description();
  }
  if (req->has_entropy_threshold()) {
    auto threshold = EntropyThresholdFromProto(req->entropy_threshold(), "entropy_threshold");
    if (!threshold.ok()) return ToGrpcStatus(threshold.status());
    update.set_entropy_threshold = true;
    update.entropy_threshold = *threshold;
  }
  if (req->has_keep_original_color()) update.keep_original_color = req->keep_original_color();
  auto updated = ctx_->engine->store()->UpdateMap(req->name(), update);
  if (!updated.ok()) return ToGrpcStatus(updated.status());
  ctx_->engine->visits()->ForgetMapSettings(map->id);
  MapToProto(*updated, resp);
  return grpc::Status::OK;
}

grpc::Status MapServiceImpl::ListKeyframes(grpc::ServerContext* context,
                                           const v1::ListKeyframesRequest* req,
                                           v1::ListKeyframesResponse* resp) {
  auto caller = ctx_->keys->Authorize(*context, "MapService/ListKeyframes");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  auto map = FindCallersMap(ctx_->engine->store(), *caller, req->map());
  if (!map.ok()) return ToGrpcStatus(map.status());
  const auto visit_id = IdFromProto(req->visit_id(), "visit_id");
  if (!visit_id.ok()) return ToGrpcStatus(visit_id.status());
  if (*visit_id != 0) {
    auto visit = ctx_->engine->store()->GetVisit(*visit_id);
    if (!visit.ok()) return ToGrpcStatus(visit.status());
    if (visit->map_id != map->id) {
      return grpc::Status(
          grpc::StatusCode::NOT_FOUND,
          absl::StrCat("visit ", req->visit_id(), " is not a visit of map '", req->map(), "'"));
    }
  }
  auto keyframes = ctx_->engine->store()->ListKeyframes(map->id, *visit_id);
  if (!keyframes.ok()) return ToGrpcStatus(keyframes.status());
  for (const auto& k : *keyframes) KeyframeSummaryToProto(k, resp->add_keyframes());
  return grpc::Status::OK;
}

grpc::Status MapServiceImpl::GetKeyframe(grpc::ServerContext* context,
                                         const v1::GetKeyframeRequest* req, v1::Keyframe* resp) {
  auto caller = ctx_->keys->Authorize(*context, "MapService/GetKeyframe");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  auto map = FindCallersMap(ctx_->engine->store(), *caller, req->map());
  if (!map.ok()) return ToGrpcStatus(map.status());
  const auto keyframe_id = IdFromProto(req->keyframe_id(), "keyframe_id");
  if (!keyframe_id.ok()) return ToGrpcStatus(keyframe_id.status());
  auto k = ctx_->engine->store()->GetKeyframe(map->id, *keyframe_id);
  if (!k.ok()) return ToGrpcStatus(k.status());
  KeyframeSummaryToProto(*k, resp->mutable_summary());
  auto* depth = resp->mutable_depth();
  depth->set_encoding(k->depth_encoding == store::StoredDepthEncoding::kPaletted
                          ? v1::DEPTH_PALETTED
                          : v1::DEPTH_PNG16);
  depth->set_data(k->depth);
  depth->set_width(static_cast<uint32_t>(k->intrinsics.width));
  depth->set_height(static_cast<uint32_t>(k->intrinsics.height));
  depth->set_depth_scale(k->depth_scale);
  auto* color = resp->mutable_color();
  color->set_encoding(k->color_encoding == store::StoredColorEncoding::kPng ? v1::COLOR_PNG
                                                                            : v1::COLOR_JPEG);
  color->set_data(k->color);
  color->set_width(static_cast<uint32_t>(k->intrinsics.width));
  color->set_height(static_cast<uint32_t>(k->intrinsics.height));
  if (k->features) {
    for (const auto& s : k->features->superjuts) {
      SuperjutToProto(s, k->features->entropy_threshold, resp->add_superjuts());
    }
  }
  return grpc::Status::OK;
}

grpc::Status MapServiceImpl::ExportMap(grpc::ServerContext* context,
                                       const v1::ExportMapRequest* req,
                                       grpc::ServerWriter<v1::ExportChunk>* writer) {
  auto caller = ctx_->keys->Authorize(*context, "MapService/ExportMap");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  auto map = FindCallersMap(ctx_->engine->store(), *caller, req->map());
  if (!map.ok()) return ToGrpcStatus(map.status());
  const auto id = IdFromProto(req->visit_id(), "visit_id");
  if (!id.ok()) return ToGrpcStatus(id.status());
  const int64_t visit_id = *id;
  if (auto s = CheckVisitOfMap(ctx_->engine->store(), *map, visit_id); !s.ok())
    return ToGrpcStatus(s);
  if (req->format() == v1::EXPORT_MAP_ARCHIVE) {
    if (visit_id != 0) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                          "an archive holds the whole map: leave visit_id 0");
    }
    bool first = true;
    auto manifest = ExportMapArchive(
        ctx_->engine->store(), map->name, kExportChunkBytes, [&](std::string_view bytes) {
          v1::ExportChunk chunk;
          chunk.set_data(std::string(bytes));
          if (first) chunk.set_content_type("application/x-lifemap-map-archive");
          first = false;
          return writer->Write(chunk);
        });
    if (!manifest.ok()) return ToGrpcStatus(manifest.status());
    v1::ExportChunk last;
    last.set_item_count(static_cast<uint64_t>(manifest->keyframes));
    last.set_last(true);
    if (!writer->Write(last)) {
      return grpc::Status(grpc::StatusCode::CANCELLED, "client went away during export");
    }
    return grpc::Status::OK;
  }
  if (req->visit_column() && req->format() != v1::EXPORT_POSES_TUM) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        "visit_column applies to poses only (lifemap export --what poses "
                        "--visit-column; ExportMap's format EXPORT_POSES_TUM)");
  }
  switch (req->format()) {
    case v1::EXPORT_POSES_TUM: {
      auto keyframes = ctx_->engine->store()->ListKeyframes(map->id, visit_id);
      if (!keyframes.ok()) return ToGrpcStatus(keyframes.status());
      // Map-level: the visits in the map's frame only, each under a "# visit N" line; one
      // visit alone is in its own frame.
      std::optional<MapFrameVisits> frame;
      if (visit_id == 0) {
        auto visits = VisitsInMapFrame(ctx_->engine->store(), map->name);
        if (!visits.ok()) return ToGrpcStatus(visits.status());
        frame = *std::move(visits);
      }
      std::stable_sort(keyframes->begin(), keyframes->end(),
                       [](const store::KeyframeRecord& a, const store::KeyframeRecord& b) {
                         return a.visit_id < b.visit_id;
                       });
      std::string body = absl::StrCat(
          "# lifemap keyframe poses (T_world_camera) of map '", map->name, "', ",
          visit_id == 0 ? std::string("in the map's frame")
                        : absl::StrCat("visit ", visit_id, " in its own frame"),
          req->visit_column()
              ? "\n# timestamp tx ty tz qx qy qz qw visit (TUM, then the keyframe's visit id); '# "
                "visit N' starts each visit's poses\n"
              : "\n# timestamp tx ty tz qx qy qz qw (TUM); '# visit N' starts each visit's "
                "poses\n");
      if (frame) {
        for (const auto& l : frame->left_out) absl::StrAppend(&body, "# left out: ", l, "\n");
      }
      uint64_t n = 0;
      int64_t current_visit = 0;
      for (const auto& k : *keyframes) {
        if (!k.T_world_camera) continue;
        if (frame && frame->in_map_frame.count(k.visit_id) == 0) continue;
        if (k.visit_id != current_visit) {
          current_visit = k.visit_id;
          absl::StrAppend(&body, "# visit ", current_visit, "\n");
        }
        body += io::FormatTumPoseLine(k.timestamp_s, *k.T_world_camera);
        if (req->visit_column()) absl::StrAppend(&body, " ", k.visit_id);
        body += '\n';
        ++n;
      }
      return SendChunks(body, "text/plain", n, writer,
                        frame ? frame->left_out : std::vector<std::string>{});
    }
    case v1::EXPORT_CLOUD_PLY: {
      const double voxel = req->voxel_size_m() == 0.0 ? 0.02 : req->voxel_size_m();
      const uint32_t stride = req->pixel_stride() == 0 ? 4 : req->pixel_stride();
      if (!(voxel >= 0.005 && voxel <= 1.0)) {
        return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                            absl::StrCat("voxel_size_m must be within [0.005, 1], got ", voxel));
      }
      if (stride < 1 || stride > 16) {
        return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                            absl::StrCat("pixel_stride must be within [1, 16], got ", stride));
      }
      auto cloud =
          ExportCloud(ctx_->engine->store(), map->id, req->map(), visit_id, voxel,
                      static_cast<int>(stride), [context] { return context->IsCancelled(); });
      if (!cloud.ok()) return ToGrpcStatus(cloud.status());
      return SendChunks(io::EncodePlyBinary(cloud->points), "application/ply", cloud->points.size(),
                        writer, cloud->left_out);
    }
    case v1::EXPORT_OCTREE_BT:
    case v1::EXPORT_OCTREE_OT:
    case v1::EXPORT_SEMANTIC_CLOUD_PLY:
    case v1::EXPORT_SEMANTIC_SUMMARY_JSON:
      return ExportSemantic(*map, *req, writer);
    case v1::EXPORT_OCCUPANCY_OCTREE_BT:
    case v1::EXPORT_OCCUPANCY_GRID_PGM:
      return ExportOccupancyOf(*map, visit_id, *req, context, writer);
    default:
      return grpc::Status(
          grpc::StatusCode::INVALID_ARGUMENT,
          absl::StrCat(
              "format must be one of EXPORT_POSES_TUM, EXPORT_CLOUD_PLY, EXPORT_OCTREE_BT, "
              "EXPORT_OCTREE_OT, EXPORT_SEMANTIC_CLOUD_PLY, EXPORT_SEMANTIC_SUMMARY_JSON, "
              "EXPORT_MAP_ARCHIVE, EXPORT_OCCUPANCY_OCTREE_BT, EXPORT_OCCUPANCY_GRID_PGM; got ",
              static_cast<int>(req->format())));
  }
}

grpc::Status MapServiceImpl::ExportOccupancyOf(const store::MapRecord& map, int64_t visit_id,
                                               const v1::ExportMapRequest& req,
                                               grpc::ServerContext* context,
                                               grpc::ServerWriter<v1::ExportChunk>* writer) {
  OccupancyOptions options;
  if (req.voxel_size_m() != 0.0) options.resolution_m = req.voxel_size_m();
  if (req.pixel_stride() != 0) options.pixel_stride = static_cast<int>(req.pixel_stride());
  if (!(options.resolution_m >= 0.01 && options.resolution_m <= 1.0)) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        absl::StrCat("voxel_size_m (the occupancy resolution) must be within "
                                     "[0.01, 1], got ",
                                     options.resolution_m));
  }
  if (req.pixel_stride() > 16) {
    return grpc::Status(
        grpc::StatusCode::INVALID_ARGUMENT,
        absl::StrCat("pixel_stride must be within [1, 16], got ", req.pixel_stride()));
  }
  const auto cancelled = [context] { return context->IsCancelled(); };
  if (req.format() == v1::EXPORT_OCCUPANCY_OCTREE_BT) {
    if (req.has_grid()) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                          "grid applies to the navigation grid only (lifemap export --what grid; "
                          "ExportMap's format EXPORT_OCCUPANCY_GRID_PGM)");
    }
    auto octree =
        ExportOccupancy(ctx_->engine->store(), map.id, map.name, visit_id, options, cancelled);
    if (!octree.ok()) return ToGrpcStatus(octree.status());
    return SendChunks(octree->octree_bt, "application/octet-stream", octree->occupied_voxels,
                      writer, octree->left_out);
  }
  OccupancyGridOptions grid;
  if (req.grid().has_floor_z()) {
    if (!std::isfinite(req.grid().floor_z())) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "grid.floor_z must be finite");
    }
    grid.floor_z = req.grid().floor_z();
  }
  if (req.grid().min_height_m() != 0.0) grid.min_height_m = req.grid().min_height_m();
  if (req.grid().max_height_m() != 0.0) grid.max_height_m = req.grid().max_height_m();
  if (!(grid.min_height_m >= 0.0 && grid.min_height_m < grid.max_height_m &&
        grid.max_height_m <= 10.0)) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        absl::StrCat("grid heights must satisfy 0 <= min_height_m < max_height_m "
                                     "<= 10 (metres above the floor), got ",
                                     grid.min_height_m, " and ", grid.max_height_m));
  }
  auto g = ExportOccupancyGrid(ctx_->engine->store(), map.id, map.name, visit_id, options, grid,
                               cancelled);
  if (!g.ok()) return ToGrpcStatus(g.status());
  v1::OccupancyGridInfo info;
  info.set_resolution_m(g->resolution_m);
  info.set_origin_x(g->origin_x);
  info.set_origin_y(g->origin_y);
  info.set_width(static_cast<uint32_t>(g->width));
  info.set_height(static_cast<uint32_t>(g->height));
  info.set_floor_z(g->floor_z);
  info.set_floor_estimated(g->floor_estimated);
  info.set_min_height_m(g->min_height_m);
  info.set_max_height_m(g->max_height_m);
  info.set_occupied_cells(g->occupied_cells);
  info.set_free_cells(g->free_cells);
  return SendChunks(g->ToPgm(), "image/x-portable-graymap", g->cells.size(), writer, g->left_out,
                    &info);
}

grpc::Status MapServiceImpl::ExportSemantic(const store::MapRecord& map,
                                            const v1::ExportMapRequest& req,
                                            grpc::ServerWriter<v1::ExportChunk>* writer) {
  // The visit id was checked by ExportMap (IdFromProto, CheckVisitOfMap).
  auto e = CollectSemanticExport(ctx_->engine->store(), ctx_->engine->visits(),
                                 ctx_->engine->semantic_worker(), map,
                                 static_cast<int64_t>(req.visit_id()), ctx_->config.semantic);
  if (!e.ok()) return ToGrpcStatus(e.status());
  int only_class = -1;
  if (!req.class_name().empty()) {
    for (size_t c = 0; c < e->class_names.size(); ++c) {
      if (e->class_names[c] == req.class_name()) only_class = static_cast<int>(c);
    }
    if (only_class < 0) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                          absl::StrCat("class '", req.class_name(), "' is not one of model '",
                                       e->model, "''s: ", absl::StrJoin(e->class_names, ", ")));
    }
    if (req.format() == v1::EXPORT_SEMANTIC_SUMMARY_JSON) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                          "class_name selects voxels of octrees and semantic clouds; the summary "
                          "covers every class (leave class_name empty)");
    }
  }
  const std::unique_ptr<semantic::SemanticMap> selected =
      only_class >= 0 ? e->map->OnlyClass(only_class) : nullptr;
  const semantic::SemanticMap& octree = selected ? *selected : *e->map;
  switch (req.format()) {
    case v1::EXPORT_OCTREE_BT:
      return SendChunks(octree.ToOctomapBinary(), "application/octet-stream",
                        static_cast<uint64_t>(octree.Summarize().occupied_voxels), writer);
    case v1::EXPORT_OCTREE_OT:
      return SendChunks(octree.ToOctomapColor(e->class_colors), "application/octet-stream",
                        static_cast<uint64_t>(octree.Summarize().occupied_voxels), writer);
    case v1::EXPORT_SEMANTIC_CLOUD_PLY: {
      const auto voxels = octree.LabelledVoxels();
      return SendChunks(semantic::LabelledVoxelsToPly(voxels, e->class_colors), "application/ply",
                        voxels.size(), writer);
    }
    default:
      return SendChunks(SemanticExportSummaryJson(*e), "application/json", e->visits.size(),
                        writer);
  }
}

grpc::Status MapServiceImpl::RebuildSemanticOctrees(
    grpc::ServerContext* context, const v1::RebuildSemanticOctreesRequest* req,
    grpc::ServerWriter<v1::SemanticOctreeRebuild>* writer) {
  auto caller = ctx_->keys->Authorize(*context, "MapService/RebuildSemanticOctrees");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  auto map = FindCallersMap(ctx_->engine->store(), *caller, req->map());
  if (!map.ok()) return ToGrpcStatus(map.status());
  const auto id = IdFromProto(req->visit_id(), "visit_id");
  if (!id.ok()) return ToGrpcStatus(id.status());
  const int64_t visit_id = *id;
  if (auto s = CheckVisitOfMap(ctx_->engine->store(), *map, visit_id); !s.ok())
    return ToGrpcStatus(s);
  if (!ctx_->config.semantic_enabled || ctx_->engine->semantic_worker() == nullptr) {
    return grpc::Status(grpc::StatusCode::FAILED_PRECONDITION,
                        "semantic fusion is disabled in this server's config (semantic.enabled): "
                        "enable it and restart the server to rebuild octrees");
  }
  auto model = ctx_->engine->models()->ForMap(map->id);
  if (!model.ok()) return ToGrpcStatus(model.status());
  if (*model == nullptr) {
    return grpc::Status(grpc::StatusCode::FAILED_PRECONDITION,
                        absl::StrCat("no model labels map '", map->name,
                                     "': activate one (lifemap models activate NAME --map ",
                                     map->name, ") to rebuild its octrees"));
  }
  const SemanticRebuildContext rebuild{ctx_->engine->store(), ctx_->engine->pipeline(),
                                       ctx_->engine->visits(), ctx_->engine->semantic_worker(),
                                       ctx_->config.semantic};
  bool client_gone = false;
  const absl::Status s = server::RebuildSemanticOctrees(
      rebuild, *map, visit_id, req->all(), **model,
      [&] { return client_gone || context->IsCancelled(); },
      [&](const SemanticRebuild& r) {
        v1::SemanticOctreeRebuild out;
        out.set_visit_id(static_cast<uint64_t>(r.visit_id));
        out.set_outcome(OutcomeToProto(r.outcome));
        out.set_reason(r.reason);
        out.set_model(r.model);
        out.set_keyframes_fused(static_cast<uint64_t>(r.keyframes_fused));
        out.set_keyframes_skipped(static_cast<uint64_t>(r.keyframes_skipped));
        out.set_labelled_voxels(static_cast<uint64_t>(r.labelled_voxels));
        out.set_bytes(static_cast<uint64_t>(r.bytes));
        out.set_seconds(r.seconds);
        client_gone = client_gone || !writer->Write(out);
      });
  return ToGrpcStatus(s);
}

grpc::Status MapServiceImpl::ImportMap(grpc::ServerContext* context,
                                       grpc::ServerReader<v1::ImportChunk>* reader, v1::Map* resp) {
  auto caller = ctx_->keys->Authorize(*context, "MapService/ImportMap");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  // Like CreateMap: map names are one name space over every map.
  if (auto s = caller->CheckEveryMap("importing maps"); !s.ok()) return ToGrpcStatus(s);
  store::Store* store = ctx_->engine->store();
  MapArchiveImport archive(*store);
  v1::ImportChunk chunk;
  std::string name;
  bool keep_ids = false;
  uint64_t chunks = 0;
  for (;;) {
    const ReadOutcome got = ReadMessage(reader, &chunk);
    if (got == ReadOutcome::kEnd) break;
    if (got == ReadOutcome::kUnparsable) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                          absl::StrCat("chunk ", chunks + 1,
                                       " of the import could not be parsed: most often the "
                                       "map's name holds bytes that are not valid UTF-8"));
    }
    if (chunks++ == 0) {
      name = chunk.name();
      keep_ids = chunk.keep_ids();
      // Kept ids bypass the renumbering that protects the store's counters: a move between
      // shards (an admin's `maps move`) asks for them, nobody else.
      if (keep_ids && caller->role < Role::kAdmin) {
        return grpc::Status(grpc::StatusCode::PERMISSION_DENIED,
                            "keep_ids needs an admin key (it is what `lifemap maps move` asks); "
                            "import without keep_ids and the map gets new ids");
      }
      if (!name.empty()) {
        if (auto s = store::ValidateMapName(name); !s.ok()) {
          return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                              absl::StrCat("name: ", s.message()));
        }
      }
    } else if (!chunk.name().empty()) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "only the first chunk names the map");
    }
    if (auto s = archive.Add(chunk.data()); !s.ok()) return ToGrpcStatus(s);
  }
  if (chunks == 0) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        "no chunks: send the archive `lifemap maps export` wrote");
  }
  if (name.empty()) {
    name = archive.manifest().map;
    if (auto s = store::ValidateMapName(name); !s.ok()) {
      return grpc::Status(
          grpc::StatusCode::INVALID_ARGUMENT,
          absl::StrCat("the archive's map name: ", s.message(), "; import it under another name"));
    }
  }
  auto placed = PlaceNewMap(name);
  if (!placed.ok()) return ToGrpcStatus(placed.status());
  // Cancellation (the client's deadline, a dropped connection) rolls the import back, so a
  // client told it failed never finds the map stored.
  auto map = archive.Finish(store, name, caller->AsMapCreator(), keep_ids,
                            [context] { return context->IsCancelled(); });
  if (!map.ok()) {
    if (*placed) ctx_->shard->Unplace(name);
    return ToGrpcStatus(map.status());
  }
  // The new map's keyframes join the appearance index; rankings and models see it.
  ctx_->engine->appearance()->AddMap(map->id);
  ctx_->engine->places()->Invalidate();
  ctx_->engine->models()->InvalidateActivations();
  spdlog::info("imported map '{}' (id {}) from an archive of map '{}': {} visits, {} keyframes",
               map->name, map->id, archive.manifest().map, archive.manifest().visits,
               archive.manifest().keyframes);
  MapToProto(*map, resp);
  return grpc::Status::OK;
}

}  // namespace lifemap::server
