// lifemapd as one shard of a cluster (issue 39): `--placement URI --shard NAME`.
//
// On start the shard must be in the placement (`lifemap admin shards add`); maps it holds that
// are placed nowhere are placed on it (a lone server joining a cluster keeps its maps). Every
// kHeartbeatIntervalS, and whenever `lifemap maps move` asks (Refresh), the shard writes its
// heartbeat and reads the whole placement again. Calls about a map are judged against it
// (CheckMap):
//   placed here                      served
//   placed on another shard          FAILED_PRECONDITION naming the shard and its address (the
//                                    copy here, if any, is stale: it moved while this shard
//                                    was away); DeleteMap of that copy is allowed. Through
//                                    nginx UNAVAILABLE instead: its table is older than the
//                                    placement (it reloads after a move), so a retry goes right
//   moving away, frozen or copied    reads served; writes UNAVAILABLE (retry: the client
//                                    libraries reconnect and resume)
//   moving here, not switched yet    UNAVAILABLE; ImportMap (the move's copy) and DeleteMap
//                                    allowed
//   moved away, source copy left     UNAVAILABLE naming where it went; DeleteMap allowed
// New ids start in this shard's own range (its number << kIdRangeBits), so that a map moved
// here keeps its ids. API keys are the cluster's one key ring (server/rpc/cluster_keys.h),
// synced at start, at every read of the placement and at every Refresh. Thread-safe.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "core/common/cluster_headers.h"
#include "server/placement/placement.h"
#include "server/rpc/auth.h"
#include "server/rpc/cluster_keys.h"
#include "server/store/store.h"

namespace lifemap::server {

class Engine;

class ShardMembership final : public MapGate {
 public:
  static constexpr int kIdRangeBits = store::Store::kIdRangeBits;  // ~10^12 ids per shard
  static constexpr double kDrainTimeoutS = 60.0;

  // UNAVAILABLE when the placement database cannot be reached; NOT_FOUND (saying how to add
  // it) when `shard` is not in it. `keys`: the server's key ring, reloaded when the cluster's
  // keys change (may be null).
  static absl::StatusOr<std::unique_ptr<ShardMembership>> Join(const std::string& uri,
                                                               const std::string& shard,
                                                               Engine* engine, KeyRing* keys);

  const std::string& shard() const { return shard_; }
  // MapGate, as the table above says.
  absl::StatusOr<std::shared_ptr<void>> CheckMap(const std::string& map, absl::string_view method,
                                                 bool routed_by_proxy) const override;
  // A map about to be created or imported here: placed on this shard (ALREADY_EXISTS naming
  // the shard that holds it, UNAVAILABLE without the placement database). True when placed
  // now; false when it already was placed here or is being moved here (`lifemap maps move`).
  absl::StatusOr<bool> PlaceNew(const std::string& map);
  // A map deleted here (or whose creation failed): forgotten by the placement. Logged, not
  // returned, when the placement cannot be reached (the next start reconciles).
  void Unplace(const std::string& map);
  // The cluster's one key ring (AdminService's key calls on a shard go through it).
  ClusterKeyRing* keys() { return &keys_; }
  // The cluster's shards, for GetServerInfo (clients fan calls over every map out to them).
  absl::StatusOr<std::vector<placement::Shard>> Shards() const;
  // Reads the placement now. When `map` is moving away from this shard, ends its streams
  // (UNAVAILABLE: they reconnect) and waits until no call writes it any more, so that what
  // the move copies next holds every acknowledged write. Returns the map's placement phase
  // here ("serving", "frozen", "moved", "elsewhere", "arriving", "unplaced").
  absl::StatusOr<std::string> Refresh(const std::string& map);
  // Heartbeat and a fresh read of the placement. Run every kHeartbeatIntervalS.
  void Tick();

 private:
  ShardMembership(std::string shard, std::unique_ptr<placement::Placement> placement,
                  Engine* engine, KeyRing* keys);
  // Reads the placement, places the maps held here that are placed nowhere, syncs the keys.
  absl::Status Reconcile();
  void Beat();  // the heartbeat; logged, not returned, when it fails
  absl::Status ReadPlacement();
  // Where `map` stands for this shard (Refresh's words), under mu_.
  std::string PhaseLocked(const placement::MapPlacement& m) const ABSL_SHARED_LOCKS_REQUIRED(mu_);
  std::string AddressOf(const std::string& shard) const ABSL_SHARED_LOCKS_REQUIRED(mu_);

  const std::string shard_;
  const std::unique_ptr<placement::Placement> placement_;
  Engine* const engine_;
  ClusterKeyRing keys_;
  mutable absl::Mutex mu_;
  // Every placed map, by lower-case name.
  absl::flat_hash_map<std::string, placement::MapPlacement> placed_ ABSL_GUARDED_BY(mu_);
  absl::flat_hash_map<std::string, std::string> addresses_ ABSL_GUARDED_BY(mu_);  // by shard
  // Calls writing each map now, by lower-case name.
  mutable absl::flat_hash_map<std::string, int> writers_ ABSL_GUARDED_BY(mu_);
};

}  // namespace lifemap::server
