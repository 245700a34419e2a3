// Where each map lives when several lifemapd share the work (issue 39): the placement, kept in
// PostgreSQL so that every shard, the operators' CLI and the nginx configuration read one truth.
//
// A map is the unit of sharding (one writer per visit, one pose graph per map): each map is
// placed on exactly one shard. Names are unique across the cluster, ignoring case (nginx matches
// its routing table without case). Tables (created on first use, under an advisory lock so that
// shards starting together do not race):
//   lifemap_shards(name, number, address, state 'active'|'draining', added_s, seen_s)
//   lifemap_maps(name, shard, state 'active'|'moving', move_to, move_from, move_phase,
//                move_started_s, placed_s)
//   lifemap_keys(name, role, every_map, map_names, secret_sha256, created_s, revoked_s, limits)
//                the cluster's one key ring (ClusterKey)
// Times are seconds since the Unix epoch. `seen_s` is the shard's heartbeat (every
// kHeartbeatIntervalS while it runs): a shard not seen for kDownAfterS is reported down.
//
// Thread-safe: one connection behind a mutex, reopened when it breaks. Every call answers
// UNAVAILABLE (saying the placement database is unreachable) when PostgreSQL cannot be reached.
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace lifemap::placement {

inline constexpr double kHeartbeatIntervalS = 2.0;
inline constexpr double kDownAfterS = 10.0;

struct Shard {
  std::string name;     // 1-64 of [A-Za-z0-9._-]
  int64_t number = 0;   // 1, 2, ... in the order shards were added; never reused
  std::string address;  // HOST:PORT where nginx and `maps move` reach its gRPC port
  std::string state;    // "active" (takes new maps) | "draining" (keeps its maps, takes none)
  double added_s = 0;
  double seen_s = 0;  // last heartbeat; 0 = never started
  bool Up(double now_s) const { return seen_s > 0 && now_s - seen_s < kDownAfterS; }
};

// A move (`lifemap maps move`, MapMover) goes through phases, each recorded before the next
// step, so that a move killed anywhere is finished (or aborted) by running it again:
//   frozen    shard = source, move_to = target: the source refuses writes and drains; the map is
//             exported from it and imported into the target, which does not serve it yet
//   copied    the target holds the whole map
//   switched  shard = target, move_from = source: the target serves the map; the source answers
//             UNAVAILABLE (moved) until its copy is deleted; nginx's table follows
// and back to "active" once the source's copy is gone.
struct MapPlacement {
  std::string map;
  std::string shard;
  std::string state;       // "active" | "moving"
  std::string move_to;     // frozen, copied: the shard it goes to
  std::string move_from;   // switched: the shard it came from
  std::string move_phase;  // "frozen" | "copied" | "switched"; "" when active
  double move_started_s = 0;
  double placed_s = 0;
};

// An API key of the cluster's one key ring (the shards copy it into their stores: see
// server/rpc/shard_membership.h). Keys are named like a lone server's; a key limited to maps
// names them (map ids differ per shard). Never the secret, only its SHA-256 (hex).
struct ClusterKey {
  std::string name;
  std::string role;  // "robot" | "operator" | "admin"
  bool every_map = true;
  std::vector<std::string> map_names;  // when !every_map, by name
  std::string secret_sha256;
  double created_s = 0;
  double revoked_s = 0;  // 0 = live; once set, never cleared
  // The key's own limits (0: only the server's), as store::KeyLimits; each shard applies them
  // to the calls it serves.
  int64_t max_streams = 0;
  double max_frames_per_s = 0;
  int64_t max_maps = 0;
  int64_t max_keyframes_per_map = 0;
  int64_t max_model_bytes = 0;
  int64_t max_visits_per_hour = 0;
};

// Held while one process moves one map (a PostgreSQL session lock: released when the process
// dies, so a killed move never blocks the next).
class MoveLock {
 public:
  virtual ~MoveLock() = default;
};

class Placement {
 public:
  // Connects to `uri` (a libpq connection string or postgresql:// URI) and creates the tables
  // if they are missing. UNAVAILABLE if the database cannot be reached.
  static absl::StatusOr<std::unique_ptr<Placement>> Open(const std::string& uri);
  virtual ~Placement() = default;

  // INVALID_ARGUMENT for a bad name or address; ALREADY_EXISTS for a name in use.
  virtual absl::Status AddShard(const std::string& name, const std::string& address,
                                double now_s) = 0;
  virtual absl::StatusOr<std::vector<Shard>> ListShards() = 0;
  // NOT_FOUND for an unknown shard.
  virtual absl::StatusOr<Shard> GetShard(const std::string& name) = 0;
  // "active" or "draining"; NOT_FOUND for an unknown shard.
  virtual absl::Status SetShardState(const std::string& name, const std::string& state) = 0;
  // Removes a shard that holds no map; FAILED_PRECONDITION naming its maps otherwise.
  virtual absl::Status RemoveShard(const std::string& name) = 0;
  // The shard's heartbeat: seen_s = now_s. NOT_FOUND once the shard has been removed.
  virtual absl::Status Heartbeat(const std::string& shard, double now_s) = 0;

  // Every map's placement (`shard` empty), or one shard's, by name.
  virtual absl::StatusOr<std::vector<MapPlacement>> ListMaps(const std::string& shard) = 0;
  // The map's placement, matched without case; nullopt if it is placed nowhere.
  virtual absl::StatusOr<std::optional<MapPlacement>> FindMap(const std::string& map) = 0;
  // Places a new map on `shard`. ALREADY_EXISTS naming the shard when a map of that name
  // (ignoring case) is placed anywhere; FAILED_PRECONDITION when `shard` is unknown.
  virtual absl::Status PlaceMap(const std::string& map, const std::string& shard, double now_s) = 0;
  // Forgets the map if it is placed on `shard` (a deleted map), and takes it off the keys
  // limited to it; OK if it is not placed at all (a copy left by a move: no key changes).
  virtual absl::Status UnplaceMap(const std::string& map, const std::string& shard) = 0;

  // The key ring. AddKey: ALREADY_EXISTS for a name in use (revoked keys keep theirs).
  // RevokeKey: sets revoked_s once (a second call keeps the first time) and returns the key;
  // NOT_FOUND for an unknown name. ListKeys: every key, revoked too, by name.
  virtual absl::Status AddKey(const ClusterKey& key) = 0;
  virtual absl::StatusOr<ClusterKey> RevokeKey(const std::string& name, double now_s) = 0;
  virtual absl::StatusOr<std::vector<ClusterKey>> ListKeys() = 0;

  // Moves (see MapPlacement). ABORTED when another process moves the map now.
  virtual absl::StatusOr<std::unique_ptr<MoveLock>> LockMove(const std::string& map) = 0;
  // active -> frozen towards `to`. FAILED_PRECONDITION when the map is not active (another
  // move stands: say which) or unknown.
  virtual absl::Status BeginMove(const std::string& map, const std::string& to, double now_s) = 0;
  // frozen -> copied; copied -> switched (shard = target, move_from = source); switched ->
  // active. FAILED_PRECONDITION when the map is not in the phase before.
  virtual absl::Status AdvanceMove(const std::string& map, const std::string& from_phase) = 0;
  // frozen or copied -> active on the source (the target's copy is the caller's to delete).
  virtual absl::Status AbortMove(const std::string& map) = 0;
};

// OK for 1-64 of [A-Za-z0-9._-]; INVALID_ARGUMENT saying what is wrong otherwise.
absl::Status ValidateShardName(const std::string& name);

}  // namespace lifemap::placement
