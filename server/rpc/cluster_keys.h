// One key ring for every shard of a cluster (issue 39).
//
// The ring's truth is the placement database's lifemap_keys table (placement::ClusterKey). Each
// shard keeps a copy in its own store, because its KeyRing (server/rpc/auth.h) checks every
// call against the store without a round trip to PostgreSQL; Sync() brings the copy up to date
// at start, at every placement read (every kHeartbeatIntervalS), right after this shard
// creates or revokes a key, and when a call brings a key it does not know (FetchNewKeys). So a
// key created through any shard works on every shard at once; a revocation holds on the shard
// that took it at once and on the others within ~2 s.
//
// Sync, in order:
//   1. keys this store holds that the ring lacks join it (a lone server joining a cluster keeps
//      its keys; `lifemapd keys create --db` on a shard's machine still makes a cluster key);
//      a key revoked in this store but live in the ring is revoked in the ring (`lifemapd keys
//      revoke --db`). Revocation is never undone.
//   2. every key of the ring is written into the store as the ring has it (a key of the same
//      name but another secret here is replaced, with a warning). A key limited to maps names
//      them; here it may use those of them this shard holds (map ids differ per shard), so a
//      map moved here is usable by its keys once the move switches.
// Per-key use (last_used_time_s, rate and stream limits) is counted by each shard alone.
// Thread-safe.
#pragma once

#include <string>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "server/placement/placement.h"
#include "server/rpc/auth.h"
#include "server/store/store.h"

namespace lifemap::server {

class ClusterKeyRing {
 public:
  // `keys`: reloaded after a sync that changed the store (may be null in tests).
  ClusterKeyRing(placement::Placement* placement, store::Store* store, KeyRing* keys);

  // Brings the ring and this store together (above). UNAVAILABLE without the placement database
  // (the store's copy stands meanwhile: keys revoked elsewhere hold here only once it is back).
  absl::Status Sync();
  // A call came with a key this store lacks: syncs now, at most once per kFetchIntervalS (a
  // client sending unknown keys must not load PostgreSQL), so that a key made through another
  // shard works at once. True when it synced (KeyRing::set_key_fetcher).
  bool FetchNewKeys();
  static constexpr double kFetchIntervalS = 1.0;
  // AdminService.CreateApiKey on a shard: as CreateApiKey (auth.h), but the key goes into the
  // ring, and its maps are maps placed anywhere in the cluster (NOT_FOUND otherwise).
  absl::StatusOr<std::pair<std::string, store::ApiKeyRecord>> Create(
      const std::string& name, Role role, const std::vector<std::string>& maps,
      const store::KeyLimits& limits, double now_s);
  // AdminService.RevokeApiKey on a shard: revoked in the ring and here. NOT_FOUND for an
  // unknown name.
  absl::StatusOr<store::ApiKeyRecord> Revoke(const std::string& name, double now_s);
  // AdminService.ListApiKeys on a shard: the ring's keys (maps by name, across the cluster),
  // with their last use on this shard.
  absl::StatusOr<std::vector<store::ApiKeyRecord>> List();

 private:
  absl::Status SyncLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);

  placement::Placement* const placement_;
  store::Store* const store_;
  KeyRing* const keys_;
  absl::Mutex mu_;  // one sync at a time
  double fetched_s_ ABSL_GUARDED_BY(mu_) = -1;
};

}  // namespace lifemap::server
