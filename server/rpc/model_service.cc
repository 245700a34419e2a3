// ModelService: upload, list, activate and delete random-forest models (paper 002).
#include <spdlog/spdlog.h>

#include <nlohmann/json.hpp>

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

// What the server requires of a model beyond parsing: names it can print and store.
absl::Status ValidateDescription(const forest::ModelDescription& d) {
  for (size_t c = 0; c < d.class_names.size(); ++c) {
    const std::string& n = d.class_names[c];
    if (n.empty() || n.size() > 64) {
      return absl::InvalidArgumentError(
          absl::StrCat("class ", c, " has a name of ", n.size(), " bytes; names need 1 to 64"));
    }
    for (char ch : n) {
      if (static_cast<unsigned char>(ch) < 0x20 || ch == 0x7f) {
        return absl::InvalidArgumentError(
            absl::StrCat("class ", c, "'s name contains a control character"));
      }
    }
  }
  if (!nlohmann::json::accept(d.training_json)) {
    return absl::InvalidArgumentError("the model's training summary is not valid JSON");
  }
  return absl::OkStatus();
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
  store::ModelRecord record;
  forest::ModelDescription description;
  auto forest = forest::Forest::Deserialize(data, &description);
  if (!forest.ok()) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        absl::StrCat("not a usable model file (", data.size(),
                                     " bytes): ", forest.status().message(),
                                     "; upload a file written by `lifemap train`"));
  }
  if (auto s = ValidateDescription(description); !s.ok()) return ToGrpcStatus(s);
  record.name = name;
  record.uploaded_time_s = NowSeconds();
  record.class_names = description.class_names;
  record.class_colors = description.class_colors;
  record.training_json = description.training_json;
  record.trees = forest->tree_count();
  record.nodes = static_cast<int64_t>(forest->node_count());
  auto stored = ctx_->engine->store()->InsertModel(record, data);
  if (!stored.ok()) return ToGrpcStatus(stored.status());
  spdlog::info("model '{}' uploaded: {} bytes, {} classes, {} trees", name, data.size(),
               description.class_names.size(), record.trees);
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
  if (!req->name().empty()) {
    if (auto s = store::ValidateName(req->name(), "model"); !s.ok()) return ToGrpcStatus(s);
    // Loads it once now, so a model that would fail on every frame fails here instead.
    auto bytes = ctx_->engine->store()->GetModelData(req->name());
    if (!bytes.ok()) return ToGrpcStatus(bytes.status());
    if (auto f = forest::Forest::Deserialize(*bytes, nullptr); !f.ok()) {
      return ToGrpcStatus(absl::DataLossError(
          absl::StrCat("stored model '", req->name(), "' does not load: ", f.status().message())));
    }
  }
  auto previous = ctx_->engine->store()->ActivateModel(req->map(), req->name());
  if (!previous.ok()) return ToGrpcStatus(previous.status());
  ctx_->engine->models()->InvalidateActivations();
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
  if (auto s = store::ValidateName(req->name(), "model"); !s.ok()) return ToGrpcStatus(s);
  if (auto s = ctx_->engine->store()->DeleteModel(req->name()); !s.ok()) return ToGrpcStatus(s);
  ctx_->engine->models()->InvalidateActivations();
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
