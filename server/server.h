// LifemapServer: the store, the keyframe committer and the gRPC services, wired together.
// Used by lifemapd's main() and, in-process, by the integration tests.
#pragma once

#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "server/config.h"

namespace lifemap::server {

class LifemapServer {
 public:
  // Opens the store and starts listening. FailedPrecondition / NotFound from the store;
  // Unavailable when the address cannot be bound.
  static absl::StatusOr<std::unique_ptr<LifemapServer>> Start(const ServerConfig& config);
  ~LifemapServer();  // Shutdown() if not done

  // The port actually bound (useful with port 0).
  int port() const;
  // The browser view's port (config.http_listen), 0 when it is off.
  int http_port() const;
  // Blocks until Shutdown() completes.
  void Wait();
  // Stops accepting calls, lets running calls finish for up to config.shutdown_grace_s, then
  // cancels them; then commits every queued keyframe and closes the store. Idempotent.
  void Shutdown();

 private:
  struct Impl;
  explicit LifemapServer(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace lifemap::server
