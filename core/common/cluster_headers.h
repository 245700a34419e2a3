// The gRPC metadata a cluster of lifemapd shards routes on (issue 39, docs/OPERATIONS.md
// "Several servers"): one definition for the client libraries, the shards and the nginx table
// (nginx reads them as $http_lifemap_map, $http_lifemap_shard).
#pragma once

#include <optional>
#include <string>

#include "absl/strings/string_view.h"

namespace lifemap {

// Every call about one map carries the map's name (a lone server ignores it).
inline constexpr char kMapHeader[] = "lifemap-map";
// Calls a client fans out to every shard (ListMaps) name the shard they are meant for.
inline constexpr char kShardHeader[] = "lifemap-shard";
// Set by the cluster's nginx on every call it passes on: the caller came through the cluster.
inline constexpr char kRoutedByHeader[] = "lifemap-routed-by";

// A map name as the value of kMapHeader. Names are UTF-8 (store::ValidateMapName), but a gRPC
// header value may hold only printable ASCII (gRPC aborts the process on any other byte), so
// every byte outside [A-Za-z0-9._-] is percent-encoded (RFC 3986, upper-case hex): "Küche" ->
// "K%C3%BCche". Names of those characters alone (every name before issue 52) are unchanged, so
// routing tables and clients of either age agree on them. The nginx table's keys are written
// with the same function, so nginx matches and hashes the encoded form and never decodes.
std::string EncodeHeaderValue(absl::string_view utf8);
// The inverse; nullopt if `value` has a '%' not followed by two hex digits.
std::optional<std::string> DecodeHeaderValue(absl::string_view value);

}  // namespace lifemap
