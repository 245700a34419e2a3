// The gRPC metadata a cluster of lifemapd shards routes on (issue 39, docs/OPERATIONS.md
// "Several servers"): one definition for the client libraries, the shards and the nginx table
// (nginx reads them as $http_lifemap_map, $http_lifemap_shard).
#pragma once

namespace lifemap {

// Every call about one map carries the map's name (a lone server ignores it).
inline constexpr char kMapHeader[] = "lifemap-map";
// Calls a client fans out to every shard (ListMaps) name the shard they are meant for.
inline constexpr char kShardHeader[] = "lifemap-shard";
// Set by the cluster's nginx on every call it passes on: the caller came through the cluster.
inline constexpr char kRoutedByHeader[] = "lifemap-routed-by";

}  // namespace lifemap
