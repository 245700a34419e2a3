#include "server/server.h"

#include <chrono>
#include <vector>

#include <grpcpp/ext/proto_server_reflection_plugin.h>
#include <grpcpp/health_check_service_interface.h>
#include <grpcpp/server.h>
#include <grpcpp/server_builder.h>
#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "absl/synchronization/mutex.h"
#include "server/instance_lock.h"
#include "server/services.h"
#include "server/status_interceptor.h"

namespace lifemap::server {

struct LifemapServer::Impl {
  std::unique_ptr<InstanceLock> lock;  // declared first: released after the store is closed
  ServiceContext ctx;
  std::unique_ptr<store::Store> store;
  std::unique_ptr<AppearanceIndex> appearance;  // the committer calls it: after it goes
  std::unique_ptr<KeyframeCommitter> committer;
  std::unique_ptr<PlaceIndex> places;
  std::unique_ptr<ArchitectureWorker> architecture;  // writes to the store: before it goes
  // Waits for commits (before the committer goes) and queues rebuilds on the architecture
  // worker (before it goes).
  std::unique_ptr<PoseGraphWorker> pose_graph;
  std::unique_ptr<SerialWorker> semantic_worker;  // fuses keyframes into visits' octrees
  std::unique_ptr<VisitRegistry> visits;
  std::unique_ptr<ModelRegistry> models;
  std::unique_ptr<pipeline::FramePipeline> pipeline;
  std::unique_ptr<MapServiceImpl> map_service;
  std::unique_ptr<VisitServiceImpl> visit_service;
  std::unique_ptr<FrameServiceImpl> frame_service;
  std::unique_ptr<PlaceServiceImpl> place_service;
  std::unique_ptr<ModelServiceImpl> model_service;
  std::unique_ptr<AdminServiceImpl> admin_service;
  std::unique_ptr<grpc::Server> grpc_server;
  int port = 0;
  absl::Mutex shutdown_mu;
  bool shut_down ABSL_GUARDED_BY(shutdown_mu) = false;
};

LifemapServer::LifemapServer(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}

LifemapServer::~LifemapServer() { Shutdown(); }

absl::StatusOr<std::unique_ptr<LifemapServer>> LifemapServer::Start(const ServerConfig& config) {
  if (auto s = config.Validate(); !s.ok()) return s;
  spdlog::set_level(spdlog::level::from_str(config.log_level));
  auto impl = std::make_unique<Impl>();
  auto lock = InstanceLock::Acquire(config.db_path, config.listen);
  if (!lock.ok()) return lock.status();
  impl->lock = *std::move(lock);
  store::StoreOptions store_options;
  store_options.synchronous_full = config.synchronous_full;
  auto store = store::Store::Open(config.db_path, store_options);
  if (!store.ok()) return store.status();
  impl->store = *std::move(store);
  impl->appearance = std::make_unique<AppearanceIndex>(impl->store.get(), config.appearance);
  if (auto s = impl->appearance->Load(); !s.ok()) return s;
  impl->committer = std::make_unique<KeyframeCommitter>(
      impl->store.get(), config.keyframe_batch_max,
      [appearance = impl->appearance.get()](const store::KeyframeRecord& k) {
        appearance->OnCommitted(k);
      });
  impl->places = std::make_unique<PlaceIndex>(impl->store.get());
  impl->architecture = std::make_unique<ArchitectureWorker>(impl->store.get(), impl->places.get());
  impl->pose_graph = std::make_unique<PoseGraphWorker>(impl->store.get(), config.pose_graph);
  impl->semantic_worker = std::make_unique<SerialWorker>();
  impl->visits = std::make_unique<VisitRegistry>(
      impl->store.get(), impl->places.get(),
      config.semantic_enabled ? std::optional(config.semantic) : std::nullopt);
  impl->models = std::make_unique<ModelRegistry>(impl->store.get());

  ServiceContext& ctx = impl->ctx;
  ctx.config = config;
  ctx.store = impl->store.get();
  ctx.committer = impl->committer.get();
  ctx.appearance = impl->appearance.get();
  ctx.visits = impl->visits.get();
  ctx.places = impl->places.get();
  ctx.architecture = impl->architecture.get();
  ctx.pose_graph = impl->pose_graph.get();
  ctx.semantic_worker = impl->semantic_worker.get();
  ctx.models = impl->models.get();
  impl->pipeline = std::make_unique<pipeline::FramePipeline>(config.pipeline);
  ctx.pipeline = impl->pipeline.get();
  ctx.started_time_s = NowSeconds();

  impl->map_service = std::make_unique<MapServiceImpl>(&ctx);
  impl->visit_service = std::make_unique<VisitServiceImpl>(&ctx);
  impl->frame_service = std::make_unique<FrameServiceImpl>(&ctx);
  impl->place_service = std::make_unique<PlaceServiceImpl>(&ctx);
  impl->model_service = std::make_unique<ModelServiceImpl>(&ctx);
  impl->admin_service = std::make_unique<AdminServiceImpl>(&ctx);

  grpc::EnableDefaultHealthCheckService(true);
  grpc::reflection::InitProtoReflectionServerBuilderPlugin();
  grpc::ServerBuilder builder;
  // No SO_REUSEPORT: a second server on a busy port must fail, not share the clients.
  builder.AddChannelArgument(GRPC_ARG_ALLOW_REUSEPORT, 0);
  builder.AddListeningPort(config.listen, grpc::InsecureServerCredentials(), &impl->port);
  builder.SetMaxReceiveMessageSize(config.max_message_bytes);
  builder.SetMaxSendMessageSize(config.max_message_bytes);
  builder.RegisterService(impl->map_service.get());
  builder.RegisterService(impl->visit_service.get());
  builder.RegisterService(impl->frame_service.get());
  builder.RegisterService(impl->place_service.get());
  builder.RegisterService(impl->model_service.get());
  builder.RegisterService(impl->admin_service.get());
  std::vector<std::unique_ptr<grpc::experimental::ServerInterceptorFactoryInterface>> interceptors;
  interceptors.push_back(std::make_unique<StatusInterceptorFactory>());
  builder.experimental().SetInterceptorCreators(std::move(interceptors));
  impl->grpc_server = builder.BuildAndStart();
  if (!impl->grpc_server || impl->port == 0) {
    return absl::UnavailableError(absl::StrCat(
        "cannot listen on ", config.listen,
        " (the port is in use, perhaps by another lifemapd, or the address is not one of this "
        "host's)"));
  }
  spdlog::info("lifemapd {} listening on port {} with database {}", LIFEMAP_VERSION, impl->port,
               config.db_path);
  return std::unique_ptr<LifemapServer>(new LifemapServer(std::move(impl)));
}

int LifemapServer::port() const { return impl_->port; }

void LifemapServer::Wait() { impl_->grpc_server->Wait(); }

void LifemapServer::Shutdown() {
  {
    absl::MutexLock lock(&impl_->shutdown_mu);
    if (impl_->shut_down) return;
    impl_->shut_down = true;
  }
  spdlog::info("shutting down: letting streams finish for up to {} s",
               impl_->ctx.config.shutdown_grace_s);
  const auto deadline =
      std::chrono::system_clock::now() +
      std::chrono::milliseconds(static_cast<int64_t>(impl_->ctx.config.shutdown_grace_s * 1000));
  impl_->grpc_server->Shutdown(deadline);
  // Every handler has returned; fold the key frames still queued for architecture, commit
  // what is still queued, then close the store.
  // The pose-graph worker first: an anchor queues a rebuild on the architecture worker.
  impl_->pose_graph.reset();
  // Every open visit's octree into the store once its queued keyframes are fused (the periodic
  // snapshot may be up to 9 keyframes behind): a restart resumes with all of them.
  for (const auto& visit : impl_->visits->AllLoaded()) {
    QueueSemanticSnapshot(impl_->semantic_worker.get(), impl_->store.get(), visit);
  }
  impl_->semantic_worker.reset();
  impl_->architecture.reset();
  impl_->committer.reset();
  impl_->appearance.reset();
  impl_->store.reset();
  impl_->lock.reset();
  spdlog::info("shutdown complete");
}

}  // namespace lifemap::server
