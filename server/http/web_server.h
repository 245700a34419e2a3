// lifemapd's browser view (issue 38, `lifemapd --http ADDR`): an embedded HTTP server serving
// the viewer's static pages (server/http/www, three.js from Debian's libjs-three, all built
// into the binary: the pages work offline) and JSON / image endpoints over the same engine the
// gRPC services call (docs/API.md "Browser view" lists them).
//
// Keys and roles are gRPC's (server/rpc/auth.h): a request sends `Authorization: Bearer KEY`;
// reading needs the robot role, annotating the operator role. Keys are required when
// security.require_auth, or when ADDR is beyond loopback unless --insecure-no-auth. With TLS on
// the gRPC port the pages are served over HTTPS with the same certificate.
#pragma once

#include <memory>
#include <string>

#include "absl/status/statusor.h"

namespace lifemap::server {

class Engine;
struct ServerConfig;

class WebServer {
 public:
  // Binds `config.http_listen` (HOST:PORT; port 0 picks one) and serves from a thread of its
  // own. UNAVAILABLE when the address cannot be bound; FAILED_PRECONDITION when keys are
  // required and the database has no live admin key.
  static absl::StatusOr<std::unique_ptr<WebServer>> Start(const ServerConfig& config,
                                                          Engine* engine);
  ~WebServer();  // Stop()
  WebServer(const WebServer&) = delete;
  WebServer& operator=(const WebServer&) = delete;

  int port() const;
  bool auth_required() const;
  // Stops accepting requests and waits for the running ones. Idempotent.
  void Stop();

 private:
  struct Impl;
  explicit WebServer(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace lifemap::server
