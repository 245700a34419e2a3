// Answers of several shards of a cluster (issue 39) merged into one, for the calls the client
// libraries fan out to every shard: QueryPlace by frames and GetStats (ListMaps merges by name
// in lifemap_client.cc). The Python client (client/python/lifemap/client.py) merges alike.
#pragma once

#include <cstddef>
#include <string>
#include <utility>
#include <vector>

#include "lifemap/v1/admin_service.pb.h"
#include "lifemap/v1/place_service.pb.h"

namespace lifemap::client {

// Every shard's figures summed (counts, bytes, CPU, memory, the appearance indexes' keyframes
// and memory); uptime_s the shortest; limited_to_maps if any says so; vocabulary_id 0 (each
// shard trains its own) unless there is one part.
v1::Stats MergeStats(const std::vector<v1::Stats>& parts);

// One ranking per method as one server holding every map would give it, assuming each shard's
// scores are comparable (they are: each is a visit's or keyframe's own score, in [0, 1]):
// matches by method (FUSED, ARCHITECTURE, APPEARANCE), best score first, at most `max_results`
// each; each query frame's matches likewise, its `reason` only when no shard matched it; a
// method computed when any shard computed it (else the shards' reasons, "NAME: why; ...").
// `parts` are (shard name, answer).
v1::QueryPlaceResponse MergePlaceAnswers(
    const std::vector<std::pair<std::string, v1::QueryPlaceResponse>>& parts, size_t max_results);

}  // namespace lifemap::client
