#include "server/server.h"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstring>
#include <fstream>
#include <sstream>
#include <vector>

#include <grpcpp/ext/proto_server_reflection_plugin.h>
#include <grpcpp/health_check_service_interface.h>
#include <grpcpp/impl/server_builder_option.h>
#include <grpcpp/security/server_credentials.h>
#include <grpcpp/server.h>
#include <grpcpp/server_builder.h>
#include <openssl/bio.h>
#include <openssl/evp.h>
#include <openssl/pem.h>
#include <openssl/x509.h>
#include <spdlog/spdlog.h>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/synchronization/mutex.h"
#include "server/engine/periodic_task.h"
#include "server/http/web_server.h"
#include "server/instance_lock.h"
#include "server/log_format.h"
#include "server/rpc/audit_interceptor.h"
#include "server/rpc/auth.h"
#include "server/rpc/services.h"
#include "server/rpc/status_interceptor.h"
#include "server/rpc/stream_watchdog.h"

namespace lifemap::server {
namespace {
class Housekeeper;
constexpr int kStreamLookaheadBytes = 1 << 20;
}  // namespace

struct LifemapServer::Impl {
  std::unique_ptr<InstanceLock> lock;  // declared first: released after the store is closed
  ServiceContext ctx;
  std::unique_ptr<Engine> engine;  // drained at Shutdown, after the calls have returned
  std::unique_ptr<KeyRing> keys;
  std::unique_ptr<ShardMembership> shard;  // a shard of a cluster (--placement), else null
  std::unique_ptr<PeriodicTask> shard_heartbeat;
  std::unique_ptr<MapServiceImpl> map_service;
  std::unique_ptr<VisitServiceImpl> visit_service;
  std::unique_ptr<FrameServiceImpl> frame_service;
  std::unique_ptr<PlaceServiceImpl> place_service;
  std::unique_ptr<ModelServiceImpl> model_service;
  std::unique_ptr<AdminServiceImpl> admin_service;
  std::unique_ptr<StreamWatchdog> stream_watchdog;  // outlives the handlers (grpc_server)
  std::unique_ptr<grpc::Server> grpc_server;
  int port = 0;
  std::unique_ptr<WebServer> web;  // the browser view, when config.http_listen is set
  // Runs the housekeeper every second; stopped first at shutdown.
  std::unique_ptr<Housekeeper> housekeeper;
  std::unique_ptr<PeriodicTask> housekeeping;
  absl::Mutex shutdown_mu;
  bool shut_down ABSL_GUARDED_BY(shutdown_mu) = false;
};

namespace {

// With auth required the store must hold a live key, or nobody could call anything; the first
// is made on the server's machine (no chicken-and-egg).
absl::Status CheckAuthCanWork(const ServerConfig& config, store::Store* store) {
  if (!config.AuthRequired()) return absl::OkStatus();
  auto admin = HasLiveAdminKey(store);
  if (!admin.ok()) return admin.status();
  if (*admin) return absl::OkStatus();
  return absl::FailedPreconditionError(absl::StrCat(
      "calls to ", config.listen,
      config.require_auth ? " need API keys (security.require_auth)"
                          : " need API keys (it is beyond loopback)",
      " and the database has no live admin key: create one on this machine with `lifemapd keys "
      "create NAME --role admin --db ",
      config.db_path, "` (it prints the key once)",
      config.placement_uri.empty()
          ? ""
          : " or on any other shard's machine (the shards share one key ring)",
      ", or, on a trusted network only, start with --insecure-no-auth"));
}

absl::StatusOr<std::string> ReadPemFile(const std::string& path, absl::string_view what) {
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    return absl::FailedPreconditionError(
        absl::StrCat("cannot read the ", what, " file ", path, " (", std::strerror(errno), ")"));
  }
  std::ostringstream data;
  data << in.rdbuf();
  if (data.str().find("-----BEGIN ") == std::string::npos) {
    return absl::InvalidArgumentError(
        absl::StrCat("the ", what, " file ", path, " holds no PEM block (-----BEGIN ...)"));
  }
  return data.str();
}

// "localhost" reaches 127.0.0.1 and [::1] alike: a server on one of them must not start while
// another process serves the same port on the other (clients would reach either, with another
// database). OK for other addresses, port 0, or when the other family is not available here.
absl::Status CheckLoopbackSiblingIsFree(const std::string& listen) {
  const size_t colon = listen.rfind(':');
  if (colon == std::string::npos) return absl::OkStatus();
  const std::string host = listen.substr(0, colon);
  int port = 0;
  if (!absl::SimpleAtoi(listen.substr(colon + 1), &port) || port <= 0 || port > 65535) {
    return absl::OkStatus();
  }
  const bool v4 = host == "127.0.0.1";
  const bool v6 = host == "[::1]";
  if (!v4 && !v6) return absl::OkStatus();
  const int fd = socket(v4 ? AF_INET6 : AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  if (fd < 0) return absl::OkStatus();  // no such family on this host
  const int one = 1;
  setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof(one));  // TIME_WAIT is no listener
  int rc = 0;
  if (v4) {
    setsockopt(fd, IPPROTO_IPV6, IPV6_V6ONLY, &one, sizeof(one));
    sockaddr_in6 a{};
    a.sin6_family = AF_INET6;
    a.sin6_port = htons(static_cast<uint16_t>(port));
    a.sin6_addr = in6addr_loopback;
    rc = bind(fd, reinterpret_cast<const sockaddr*>(&a), sizeof(a));
  } else {
    sockaddr_in a{};
    a.sin_family = AF_INET;
    a.sin_port = htons(static_cast<uint16_t>(port));
    a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    rc = bind(fd, reinterpret_cast<const sockaddr*>(&a), sizeof(a));
  }
  const int err = errno;
  close(fd);
  if (rc != 0 && err == EADDRINUSE) {
    return absl::UnavailableError(absl::StrCat(
        "cannot listen on ", listen, ": port ", port, " is in use on ", v4 ? "[::1]" : "127.0.0.1",
        " (the other loopback address; perhaps another lifemapd), so clients of localhost:", port,
        " would reach either server; stop that one, or choose another port"));
  }
  return absl::OkStatus();
}

// FAILED_PRECONDITION unless `key_pem` holds the private key of the certificate in `cert_pem`
// (gRPC would fail to listen and say nothing of why: the server reported the port in use).
absl::Status CheckKeyBelongsToCertificate(const std::string& cert_pem, const std::string& key_pem,
                                          const ServerConfig& config) {
  const auto bio = [](const std::string& pem) {
    return std::unique_ptr<BIO, decltype(&BIO_free)>(
        BIO_new_mem_buf(pem.data(), static_cast<int>(pem.size())), &BIO_free);
  };
  auto cert_bio = bio(cert_pem);
  std::unique_ptr<X509, decltype(&X509_free)> cert(
      PEM_read_bio_X509(cert_bio.get(), nullptr, nullptr, nullptr), &X509_free);
  if (cert == nullptr) {
    return absl::InvalidArgumentError(absl::StrCat("the TLS certificate file ", config.tls_cert,
                                                   " (--tls-cert) holds no readable certificate"));
  }
  auto key_bio = bio(key_pem);
  std::unique_ptr<EVP_PKEY, decltype(&EVP_PKEY_free)> key(
      PEM_read_bio_PrivateKey(key_bio.get(), nullptr, nullptr, nullptr), &EVP_PKEY_free);
  if (key == nullptr) {
    return absl::InvalidArgumentError(
        absl::StrCat("the TLS private key file ", config.tls_key,
                     " (--tls-key) holds no readable private key (a key protected by a "
                     "passphrase cannot be used: give lifemapd an unencrypted one, readable only "
                     "by its user)"));
  }
  if (X509_check_private_key(cert.get(), key.get()) != 1) {
    return absl::FailedPreconditionError(absl::StrCat(
        "the TLS private key ", config.tls_key, " (--tls-key) does not belong to the certificate ",
        config.tls_cert, " (--tls-cert): give the key the certificate was made for"));
  }
  return absl::OkStatus();
}

// Plaintext, or TLS from the configured PEM files (with client certificates required and
// verified against tls_client_ca when given).
absl::StatusOr<std::shared_ptr<grpc::ServerCredentials>> ServerCredentialsFor(
    const ServerConfig& config) {
  if (config.tls_cert.empty()) return grpc::InsecureServerCredentials();
  auto cert = ReadPemFile(config.tls_cert, "TLS certificate (--tls-cert)");
  if (!cert.ok()) return cert.status();
  auto key = ReadPemFile(config.tls_key, "TLS private key (--tls-key)");
  if (!key.ok()) return key.status();
  if (auto s = CheckKeyBelongsToCertificate(*cert, *key, config); !s.ok()) return s;
  grpc::SslServerCredentialsOptions options;
  options.pem_key_cert_pairs.push_back({*key, *cert});
  if (!config.tls_client_ca.empty()) {
    auto ca = ReadPemFile(config.tls_client_ca, "client CA (--tls-client-ca)");
    if (!ca.ok()) return ca.status();
    options.pem_root_certs = *ca;
    options.client_certificate_request = GRPC_SSL_REQUEST_AND_REQUIRE_CLIENT_CERTIFICATE_AND_VERIFY;
  }
  return grpc::SslServerCredentials(options);
}

// Offers gRPC's reflection service on one server, or not. Linking grpc++_reflection registers
// its plugin for every server the process builds (a static initializer, and
// InitProtoReflectionServerBuilderPlugin does the same): without this option a server that
// requires keys offered it too. The plugin is removed from, or added to, this builder's list.
class ReflectionOption : public grpc::ServerBuilderOption {
 public:
  explicit ReflectionOption(bool offer) : offer_(offer) {}
  void UpdateArguments(grpc::ChannelArguments* /*args*/) override {}
  void UpdatePlugins(std::vector<std::unique_ptr<grpc::ServerBuilderPlugin>>* plugins) override {
    const std::string reflection = grpc::reflection::ProtoServerReflectionPlugin().name();
    const auto is_reflection = [&reflection](const std::unique_ptr<grpc::ServerBuilderPlugin>& p) {
      return p->name() == reflection;
    };
    plugins->erase(std::remove_if(plugins->begin(), plugins->end(), is_reflection), plugins->end());
    if (offer_) {
      plugins->push_back(std::make_unique<grpc::reflection::ProtoServerReflectionPlugin>());
    }
  }

 private:
  bool offer_;
};

// Every second: is the database file still the one opened (a deleted or replaced file loses
// every later write at the next restart: the store refuses them, and this says so loudly and
// tells health checks), and the keys as the store has them now (a key revoked by `lifemapd keys
// revoke --db` beside the server ends its open streams at their next message).
class Housekeeper {
 public:
  Housekeeper(store::Store* store, KeyRing* keys, StreamWatchdog* streams, grpc::Server* server,
              std::string db_path)
      : store_(store),
        keys_(keys),
        streams_(streams),
        server_(server),
        db_path_(std::move(db_path)) {}

  void Tick() {
    const absl::Status files = store_->CheckFilesInPlace();
    const double now = NowSeconds();
    auto* health = server_->GetHealthCheckService();
    if (!files.ok()) {
      if (lost_logged_s_ < 0 || now - lost_logged_s_ >= 60) {
        spdlog::critical(
            "{}. Every write is refused with FAILED_PRECONDITION and health checks answer "
            "NOT_SERVING until the file is back where it was; stop lifemapd, restore the file "
            "(or a backup) and restart",
            std::string(files.message()));
        if (lost_logged_s_ < 0 && health != nullptr) health->SetServingStatus(false);
        lost_logged_s_ = now;
      }
    } else if (lost_logged_s_ >= 0) {
      spdlog::warn("the database file {} is back in place: writes are accepted again", db_path_);
      if (health != nullptr) health->SetServingStatus(true);
      lost_logged_s_ = -1;
    }
    if (auto s = keys_->Reload(); !s.ok()) {
      spdlog::warn("API keys could not be read again: {}", std::string(s.message()));
    }
    streams_->CancelExpired();
  }

 private:
  store::Store* store_;
  KeyRing* keys_;
  StreamWatchdog* streams_;
  grpc::Server* server_;
  const std::string db_path_;
  double lost_logged_s_ = -1;  // when the lost file was last logged; < 0 while in place
};

}  // namespace

LifemapServer::LifemapServer(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}

LifemapServer::~LifemapServer() { Shutdown(); }

absl::StatusOr<std::unique_ptr<LifemapServer>> LifemapServer::Start(const ServerConfig& config) {
  if (auto s = config.Validate(); !s.ok()) return s;
  spdlog::set_level(spdlog::level::from_str(config.log_level));
  EscapeDefaultLogMessages();
  auto impl = std::make_unique<Impl>();
  auto lock = InstanceLock::Acquire(config.db_path);
  if (!lock.ok()) return lock.status();
  impl->lock = *std::move(lock);
  auto engine = Engine::Open(config.engine_options());
  if (!engine.ok()) return engine.status();
  impl->engine = *std::move(engine);
  store::Store* store = impl->engine->store();
  impl->keys = std::make_unique<KeyRing>(store, config.AuthRequired());
  if (!config.placement_uri.empty()) {
    // Before the check below: a shard's keys are the cluster's (server/rpc/cluster_keys.h).
    auto shard = ShardMembership::Join(config.placement_uri, config.shard_name, impl->engine.get(),
                                       impl->keys.get());
    if (!shard.ok()) return shard.status();
    impl->shard = *std::move(shard);
    impl->keys->set_map_gate(impl->shard.get());
  }
  if (auto s = CheckAuthCanWork(config, store); !s.ok()) return s;
  auto credentials = ServerCredentialsFor(config);
  if (!credentials.ok()) return credentials.status();
  if (auto s = CheckLoopbackSiblingIsFree(config.listen); !s.ok()) return s;

  ServiceContext& ctx = impl->ctx;
  ctx.config = config;
  ctx.engine = impl->engine.get();
  impl->stream_watchdog = std::make_unique<StreamWatchdog>();
  ctx.stream_watchdog = impl->stream_watchdog.get();
  ctx.keys = impl->keys.get();
  ctx.shard = impl->shard.get();
  ctx.started_time_s = NowSeconds();

  impl->map_service = std::make_unique<MapServiceImpl>(&ctx);
  impl->visit_service = std::make_unique<VisitServiceImpl>(&ctx);
  impl->frame_service = std::make_unique<FrameServiceImpl>(&ctx);
  impl->place_service = std::make_unique<PlaceServiceImpl>(&ctx);
  impl->model_service = std::make_unique<ModelServiceImpl>(&ctx);
  impl->admin_service = std::make_unique<AdminServiceImpl>(&ctx);

  // Health checking answers anyone (load balancers, systemd probes carry no key).
  grpc::EnableDefaultHealthCheckService(true);
  grpc::ServerBuilder builder;
  // Reflection describes the API to anyone who asks, so it is served only without auth.
  builder.SetOption(std::make_unique<ReflectionOption>(!config.AuthRequired()));
  // No SO_REUSEPORT: a second server on a busy port must fail, not share the clients.
  builder.AddChannelArgument(GRPC_ARG_ALLOW_REUSEPORT, 0);
  // What the transport may hold of a stream's frames that no handler has read yet: 1 MiB,
  // fixed. gRPC's default grows each stream's window by probing the bandwidth-delay product,
  // and on loopback it grew to several raw frames per stream beyond the max_inflight_frames the
  // stream handler holds: the fast-sender test peaked at 115-116 MB with it, 103-105 MB
  // without, on the same busy machine (docs/BENCHMARKS.md, issue 34). A frame larger than the
  // window still arrives whole (a pending read opens the window to the message's size).
  builder.AddChannelArgument(GRPC_ARG_HTTP2_BDP_PROBE, 0);
  builder.AddChannelArgument(GRPC_ARG_HTTP2_STREAM_LOOKAHEAD_BYTES, kStreamLookaheadBytes);
  builder.AddListeningPort(config.listen, *credentials, &impl->port);
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
  interceptors.push_back(std::make_unique<AuditInterceptorFactory>(&ctx));
  PruneAuditLog(&ctx);
  builder.experimental().SetInterceptorCreators(std::move(interceptors));
  impl->grpc_server = builder.BuildAndStart();
  if (!impl->grpc_server || impl->port == 0) {
    return absl::UnavailableError(absl::StrCat(
        "cannot listen on ", config.listen,
        " (the port is in use, perhaps by another lifemapd, or the address is not one of this "
        "host's)"));
  }
  if (!config.http_listen.empty()) {
    auto web = WebServer::Start(config, impl->engine.get());
    if (!web.ok()) {
      impl->grpc_server->Shutdown();
      return web.status();
    }
    impl->web = *std::move(web);
  }
  impl->housekeeper =
      std::make_unique<Housekeeper>(store, impl->keys.get(), impl->stream_watchdog.get(),
                                    impl->grpc_server.get(), config.db_path);
  impl->housekeeping = std::make_unique<PeriodicTask>(absl::Seconds(1),
                                                      [h = impl->housekeeper.get()] { h->Tick(); });
  if (impl->shard) {
    impl->shard_heartbeat =
        std::make_unique<PeriodicTask>(absl::Seconds(placement::kHeartbeatIntervalS),
                                       [shard = impl->shard.get()] { shard->Tick(); });
  }
  spdlog::info("lifemapd {} listening on port {} ({}, {}) with database {}{}", LIFEMAP_VERSION,
               impl->port, config.tls_cert.empty() ? "plaintext" : "TLS",
               config.AuthRequired() ? "API keys required" : "no authentication", config.db_path,
               impl->shard ? absl::StrCat(", shard ", config.shard_name) : "");
  if (config.insecure_no_auth && !IsLoopbackAddress(config.listen)) {
    spdlog::warn(
        "--insecure-no-auth: anyone who can reach {} may call every method, delete "
        "maps included",
        config.listen);
  }
  return std::unique_ptr<LifemapServer>(new LifemapServer(std::move(impl)));
}

int LifemapServer::port() const { return impl_->port; }

int LifemapServer::http_port() const { return impl_->web ? impl_->web->port() : 0; }

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
  impl_->housekeeping.reset();
  impl_->shard_heartbeat.reset();
  if (impl_->web) impl_->web->Stop();  // its requests finish before the engine drains
  impl_->grpc_server->Shutdown(deadline);
  // Every handler has returned: the engine drains its workers (loops closed, octrees stored,
  // floor plans folded, keyframes committed) and closes the store.
  impl_->housekeeper.reset();
  impl_->keys.reset();
  impl_->engine.reset();
  impl_->lock.reset();
  spdlog::info("shutdown complete");
}

}  // namespace lifemap::server
