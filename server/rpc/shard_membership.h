// lifemapd as one shard of a cluster (issue 39): `--placement URI --shard NAME`.
//
// On start the shard must be in the placement (`lifemap admin shards add`); maps it holds that
// are placed nowhere are placed on it (a lone server joining a cluster keeps its maps), and
// maps it holds that the placement puts on another shard are stale copies (the map moved while
// this shard was away): every call about them is refused with FAILED_PRECONDITION saying where
// the map lives. Every kHeartbeatIntervalS the shard writes its heartbeat and reads the
// placement again. Thread-safe.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "core/common/cluster_headers.h"
#include "server/placement/placement.h"
#include "server/rpc/auth.h"
#include "server/store/store.h"

namespace lifemap::server {

class ShardMembership final : public MapGate {
 public:
  // UNAVAILABLE when the placement database cannot be reached; NOT_FOUND (saying how to add
  // it) when `shard` is not in it.
  static absl::StatusOr<std::unique_ptr<ShardMembership>> Join(const std::string& uri,
                                                               const std::string& shard,
                                                               store::Store* store);

  const std::string& shard() const { return shard_; }
  // MapGate: FAILED_PRECONDITION naming the map's shard when the placement puts it elsewhere.
  absl::Status CheckMap(const std::string& map) const override;
  // A map about to be created or imported here: placed on this shard (ALREADY_EXISTS naming
  // the shard that holds it, UNAVAILABLE without the placement database). True when placed
  // now; false when it already was placed here or is being moved here (`lifemap maps move`).
  absl::StatusOr<bool> PlaceNew(const std::string& map);
  // A map deleted here (or whose creation failed): forgotten by the placement. Logged, not
  // returned, when the placement cannot be reached (the next start reconciles).
  void Unplace(const std::string& map);
  // The cluster's shards, for GetServerInfo (clients fan calls over every map out to them).
  absl::StatusOr<std::vector<placement::Shard>> Shards() const;
  // Heartbeat and a fresh read of where other shards' maps are. Run every kHeartbeatIntervalS.
  void Tick();

 private:
  ShardMembership(std::string shard, std::unique_ptr<placement::Placement> placement,
                  store::Store* store)
      : shard_(std::move(shard)), placement_(std::move(placement)), store_(store) {}
  absl::Status Reconcile();
  absl::Status Refresh();

  const std::string shard_;
  const std::unique_ptr<placement::Placement> placement_;
  store::Store* const store_;
  mutable absl::Mutex mu_;
  // Maps the placement puts on another shard, by lower-case name: where they live.
  absl::flat_hash_map<std::string, placement::MapPlacement> elsewhere_ ABSL_GUARDED_BY(mu_);
  absl::flat_hash_map<std::string, std::string> addresses_ ABSL_GUARDED_BY(mu_);  // by shard
};

}  // namespace lifemap::server
