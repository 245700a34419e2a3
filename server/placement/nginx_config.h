// nginx's routing table for a cluster of lifemapd shards, written from the placement (issue 39).
//
// Clients send the map a call is about in the `lifemap-map` header and, for calls that span maps
// and fan out, the shard they are meant for in `lifemap-shard` (core/common/cluster_headers.h;
// nginx reads them as $http_lifemap_map and $http_lifemap_shard).
// nginx (>= 1.13.10, grpc_pass over HTTP/2) routes:
//   1. `lifemap-shard` naming a shard          -> that shard;
//   2. `lifemap-map` naming a placed map       -> the shard the placement puts it on;
//   3. anything else (a map not placed yet: CreateMap, ImportMap; no header at all)
//                                               -> consistent hashing of `lifemap-map` over the
//                                                  active shards (a new map's home).
// The shard that creates a map records it in the placement, so the hash only decides where a new
// map goes; regenerating the table (after adding a shard, a drain or a move) pins every placed
// map by name. A shard nginx cannot reach answers UNAVAILABLE naming the shard and its address.
#pragma once

#include <string>
#include <vector>

#include "server/placement/placement.h"

namespace lifemap::placement {

struct NginxOptions {
  std::string listen = "127.0.0.1:50050";  // where robots and the CLI connect
  // A whole nginx.conf (events, http, pid and temporary files under `prefix`) for
  // `nginx -p PREFIX -c FILE`; otherwise only what goes inside an existing http { } block.
  bool standalone = true;
  std::string prefix;  // standalone: directory for the pid, logs and temporary files
  // TLS termination at nginx (both or neither, PEM); the shards are then reached in plaintext
  // on their (private) addresses.
  std::string tls_cert;
  std::string tls_key;
  double stream_timeout_s = 600;  // a stream may be idle this long before nginx cuts it
};

// The configuration for `shards` and the placed `maps`. Draining shards keep their maps but are
// left out of the hash for new maps. INVALID_ARGUMENT-free: names were validated when placed.
std::string NginxConfig(const std::vector<Shard>& shards, const std::vector<MapPlacement>& maps,
                        const NginxOptions& options);

}  // namespace lifemap::placement
