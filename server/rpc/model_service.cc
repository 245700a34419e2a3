// ModelService: upload, list, activate and delete random-forest models (paper 002).
#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "server/rpc/convert.h"
#include "server/rpc/services.h"
#include "server/rpc/stream_read.h"

namespace lifemap::server {
namespace {

void ModelToProto(const store::ModelRecord& m, v1::ModelInfo* out) {
  out->set_name(m.name);
  out->set_size_bytes(static_cast<uint64_t>(m.size_bytes));
  for (const auto& n : m.class_names) out->add_class_names(n);
  for (uint32_t c : m.class_colors) out->add_class_colors(c);
  out->set_active(m.is_default || !m.active_maps.empty());
  for (const auto& map : m.active_maps) out->add_active_maps(map);
  out->set_is_default(m.is_default);
  out->set_uploaded_time_s(m.uploaded_time_s);
  out->set_training_json(m.training_json);
  out->set_trees(static_cast<uint32_t>(m.trees));
  out->set_nodes(static_cast<uint64_t>(m.nodes));
}

}  // namespace

grpc::Status ModelServiceImpl::UploadModel(grpc::ServerContext* context,
                                           grpc::ServerReader<v1::UploadModelChunk>* reader,
                                           v1::ModelInfo* resp) {
  auto caller = ctx_->keys->Authorize(*context, "ModelService/UploadModel");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  // Models are shared by every map (any map may activate one).
  if (auto s = caller->CheckEveryMap("uploading models"); !s.ok()) return ToGrpcStatus(s);
  size_t limit = static_cast<size_t>(ctx_->config.max_model_mb) << 20;
  std::string limit_name = absl::StrCat(ctx_->config.max_model_mb, " MiB (labels.max_model_mb)");
  if (caller->limits.max_model_bytes > 0 &&
      static_cast<size_t>(caller->limits.max_model_bytes) < limit) {
    limit = static_cast<size_t>(caller->limits.max_model_bytes);
    limit_name =
        absl::StrCat(limit, " bytes (API key '", caller->key_name, "''s max_model_bytes limit)");
  }
  v1::UploadModelChunk chunk;
  std::string name, data;
  bool first = true;
  for (;;) {
    const ReadOutcome got = ReadMessage(reader, &chunk);
    if (got == ReadOutcome::kEnd) break;
    if (got == ReadOutcome::kUnparsable) {
      return grpc::Status(
          grpc::StatusCode::INVALID_ARGUMENT,
          absl::StrCat("chunk ", first ? 1 : 2, first ? "" : " or later",
                       " of the upload could not be parsed: most often the model's name holds "
                       "bytes that are not valid UTF-8; send UTF-8 text"));
    }
    if (first) {
      name = chunk.name();
      if (auto s = store::ValidateName(name, "model"); !s.ok()) return ToGrpcStatus(s);
      first = false;
    } else if (!chunk.name().empty() && chunk.name() != name) {
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                          "only the first chunk names the model");
    }
    if (data.size() + chunk.data().size() > limit) {
      return grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED,
                          absl::StrCat("model is larger than the limit of ", limit_name));
    }
    data += chunk.data();
  }
  if (first) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        "no chunks: send the model's name and bytes");
  }
  auto stored = ctx_->engine->models()->Add(name, data);
  if (!stored.ok()) return ToGrpcStatus(stored.status());
  ModelToProto(*stored, resp);
  return grpc::Status::OK;
}

grpc::Status ModelServiceImpl::ListModels(grpc::ServerContext* context,
                                          const v1::ListModelsRequest*,
                                          v1::ListModelsResponse* resp) {
  auto caller = ctx_->keys->Authorize(*context, "ModelService/ListModels");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  auto models = ctx_->engine->store()->ListModels();
  if (!models.ok()) return ToGrpcStatus(models.status());
  for (const auto& m : *models) ModelToProto(m, resp->add_models());
  return grpc::Status::OK;
}

grpc::Status ModelServiceImpl::ActivateModel(grpc::ServerContext* context,
                                             const v1::ActivateModelRequest* req,
                                             v1::ActivateModelResponse* resp) {
  auto caller = ctx_->keys->Authorize(*context, "ModelService/ActivateModel");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  if (!req->map().empty()) {
    if (auto m = FindCallersMap(ctx_->engine->store(), *caller, req->map()); !m.ok()) {
      return ToGrpcStatus(m.status());
    }
  } else if (auto s = caller->CheckEveryMap("the server's default model"); !s.ok()) {
    return ToGrpcStatus(s);
  }
  auto previous = ctx_->engine->models()->Activate(req->map(), req->name());
  if (!previous.ok()) return ToGrpcStatus(previous.status());
  const std::string where = req->map().empty() ? "the server default" : "map '" + req->map() + "'";
  spdlog::info("{}: model '{}' (was '{}')", where, req->name(), *previous);
  resp->set_map(req->map());
  resp->set_name(req->name());
  resp->set_previous(*previous);
  return grpc::Status::OK;
}

grpc::Status ModelServiceImpl::DeleteModel(grpc::ServerContext* context,
                                           const v1::DeleteModelRequest* req,
                                           v1::DeleteModelResponse*) {
  auto caller = ctx_->keys->Authorize(*context, "ModelService/DeleteModel");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  if (auto s = caller->CheckEveryMap("deleting models"); !s.ok()) return ToGrpcStatus(s);
  if (auto s = ctx_->engine->models()->Delete(req->name()); !s.ok()) return ToGrpcStatus(s);
  spdlog::info("model '{}' deleted", req->name());
  return grpc::Status::OK;
}

grpc::Status ModelServiceImpl::ListClasses(grpc::ServerContext* context,
                                           const v1::ListClassesRequest* req,
                                           v1::ListClassesResponse* resp) {
  auto caller = ctx_->keys->Authorize(*context, "ModelService/ListClasses");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  int64_t map_id = 0;
  if (!req->map().empty()) {
    auto map = FindCallersMap(ctx_->engine->store(), *caller, req->map());
    if (!map.ok()) return ToGrpcStatus(map.status());
    map_id = map->id;
  }
  auto model = ctx_->engine->models()->ForMap(map_id);
  if (!model.ok()) return ToGrpcStatus(model.status());
  if (!*model) {
    return grpc::Status(
        grpc::StatusCode::FAILED_PRECONDITION,
        absl::StrCat("no model is active for ",
                     req->map().empty() ? "the server default" : "map '" + req->map() + "'",
                     ": lifemap models upload FILE NAME, then lifemap models activate NAME"));
  }
  resp->set_model((*model)->name);
  for (const auto& n : (*model)->description.class_names) resp->add_class_names(n);
  for (uint32_t c : (*model)->description.class_colors) resp->add_class_colors(c);
  return grpc::Status::OK;
}

}  // namespace lifemap::server
