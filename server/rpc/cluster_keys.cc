#include "server/rpc/cluster_keys.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <tuple>

#include "absl/container/flat_hash_map.h"
#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "server/engine/clock.h"

namespace lifemap::server {
namespace {

placement::ClusterKey ToRing(const store::ApiKeyRecord& k) {
  placement::ClusterKey c;
  c.name = k.name;
  c.role = k.role;
  c.every_map = k.every_map;
  c.map_names = k.map_names;
  c.secret_sha256 = k.secret_sha256;
  c.created_s = k.created_time_s;
  c.revoked_s = k.revoked_time_s;
  c.max_streams = k.limits.max_streams;
  c.max_frames_per_s = k.limits.max_frames_per_s;
  c.max_maps = k.limits.max_maps;
  c.max_keyframes_per_map = k.limits.max_keyframes_per_map;
  c.max_model_bytes = k.limits.max_model_bytes;
  c.max_visits_per_hour = k.limits.max_visits_per_hour;
  return c;
}

// The ring's key as a record: map names as the ring has them, map ids of those held here
// (`held`: id by lower-case name).
store::ApiKeyRecord FromRing(const placement::ClusterKey& c,
                             const absl::flat_hash_map<std::string, int64_t>& held) {
  store::ApiKeyRecord k;
  k.name = c.name;
  k.role = c.role;
  k.every_map = c.every_map;
  k.map_names = c.map_names;
  for (const std::string& name : c.map_names) {
    const auto it = held.find(absl::AsciiStrToLower(name));
    if (it != held.end()) k.map_ids.push_back(it->second);
  }
  std::sort(k.map_ids.begin(), k.map_ids.end());
  k.secret_sha256 = c.secret_sha256;
  k.created_time_s = c.created_s;
  k.revoked_time_s = c.revoked_s;
  k.limits.max_streams = c.max_streams;
  k.limits.max_frames_per_s = c.max_frames_per_s;
  k.limits.max_maps = c.max_maps;
  k.limits.max_keyframes_per_map = c.max_keyframes_per_map;
  k.limits.max_model_bytes = c.max_model_bytes;
  k.limits.max_visits_per_hour = c.max_visits_per_hour;
  return k;
}

// Whether the store's key already is the ring's (last use aside).
bool SameKey(const store::ApiKeyRecord& here, const store::ApiKeyRecord& ring) {
  std::vector<int64_t> ids = here.map_ids;
  std::sort(ids.begin(), ids.end());
  const auto fields = [](const store::ApiKeyRecord& k) {
    const store::KeyLimits& l = k.limits;
    return std::tie(k.role, k.every_map, k.secret_sha256, k.created_time_s, k.revoked_time_s,
                    l.max_streams, l.max_frames_per_s, l.max_maps, l.max_keyframes_per_map,
                    l.max_model_bytes, l.max_visits_per_hour);
  };
  return fields(here) == fields(ring) && ids == ring.map_ids;
}

}  // namespace

ClusterKeyRing::ClusterKeyRing(placement::Placement* placement, store::Store* store, KeyRing* keys)
    : placement_(placement), store_(store), keys_(keys) {}

absl::Status ClusterKeyRing::Sync() {
  absl::MutexLock lock(&mu_);
  return SyncLocked();
}

bool ClusterKeyRing::FetchNewKeys() {
  absl::MutexLock lock(&mu_);
  const double now = NowSeconds();
  if (fetched_s_ >= 0 && now - fetched_s_ < kFetchIntervalS) return false;
  fetched_s_ = now;
  if (auto s = SyncLocked(); !s.ok()) {
    spdlog::warn("fetching the cluster's API keys: {}", std::string(s.message()));
    return false;
  }
  return true;
}

absl::Status ClusterKeyRing::SyncLocked() {
  auto ring = placement_->ListKeys();
  if (!ring.ok()) return ring.status();
  auto local = store_->ListApiKeys();
  if (!local.ok()) return local.status();
  absl::flat_hash_map<std::string, const placement::ClusterKey*> in_ring;
  for (const auto& c : *ring) in_ring[c.name] = &c;

  // 1. What this store knows and the ring does not: keys made here, revocations made here.
  bool ring_changed = false;
  for (const store::ApiKeyRecord& k : *local) {
    const auto it = in_ring.find(k.name);
    if (it == in_ring.end()) {
      absl::Status s = placement_->AddKey(ToRing(k));
      if (!s.ok() && !absl::IsAlreadyExists(s)) return s;  // made elsewhere meanwhile: next sync
      spdlog::info("API key '{}' ({}) of this shard joined the cluster's key ring", k.name, k.role);
      ring_changed = true;
    } else if (k.revoked_time_s > 0 && it->second->revoked_s == 0 &&
               k.secret_sha256 == it->second->secret_sha256) {
      if (auto r = placement_->RevokeKey(k.name, k.revoked_time_s); !r.ok()) return r.status();
      spdlog::info("API key '{}' revoked on this shard: revoked in the cluster's key ring", k.name);
      ring_changed = true;
    }
  }
  if (ring_changed) {
    ring = placement_->ListKeys();
    if (!ring.ok()) return ring.status();
  }

  // 2. The ring into this store.
  auto maps = store_->ListMapNames();
  if (!maps.ok()) return maps.status();
  absl::flat_hash_map<std::string, int64_t> held;
  for (const auto& [id, name] : *maps) held[absl::AsciiStrToLower(name)] = id;
  absl::flat_hash_map<std::string, const store::ApiKeyRecord*> here;
  for (const auto& k : *local) here[k.name] = &k;
  bool store_changed = false;
  for (const placement::ClusterKey& c : *ring) {
    const store::ApiKeyRecord want = FromRing(c, held);
    const auto it = here.find(c.name);
    if (it != here.end() && SameKey(*it->second, want)) continue;
    if (it != here.end() && it->second->secret_sha256 != want.secret_sha256) {
      spdlog::warn(
          "API key '{}' of this shard has another secret than the cluster's key of that name: "
          "the cluster's is used from now on (give the key another name to keep both)",
          c.name);
    }
    if (auto s = store_->PutApiKey(want); !s.ok()) return s.status();
    store_changed = true;
  }
  if (store_changed && keys_ != nullptr) return keys_->Reload();
  return absl::OkStatus();
}

absl::StatusOr<std::pair<std::string, store::ApiKeyRecord>> ClusterKeyRing::Create(
    const std::string& name, Role role, const std::vector<std::string>& maps,
    const store::KeyLimits& limits, double now_s) {
  auto key = NewApiKey(name, role, maps, limits, now_s);
  if (!key.ok()) return key.status();
  store::ApiKeyRecord& record = key->second;
  record.map_names.clear();
  for (const std::string& map : maps) {
    auto placed = placement_->FindMap(map);
    if (!placed.ok()) return placed.status();
    if (!placed->has_value()) {
      return absl::NotFoundError(absl::StrCat("maps: no map named '", map,
                                              "' on any shard of the cluster (lifemap maps)"));
    }
    record.map_names.push_back((*placed)->map);  // as the cluster spells it
  }
  absl::MutexLock lock(&mu_);
  if (auto s = placement_->AddKey(ToRing(record)); !s.ok()) return s;
  if (auto s = SyncLocked(); !s.ok()) return s;
  return key;
}

absl::StatusOr<store::ApiKeyRecord> ClusterKeyRing::Revoke(const std::string& name, double now_s) {
  absl::MutexLock lock(&mu_);
  auto revoked = placement_->RevokeKey(name, now_s);
  if (!revoked.ok()) return revoked.status();
  if (auto s = SyncLocked(); !s.ok()) return s;
  return FromRing(*revoked, {});
}

absl::StatusOr<std::vector<store::ApiKeyRecord>> ClusterKeyRing::List() {
  auto ring = placement_->ListKeys();
  if (!ring.ok()) return ring.status();
  auto local = store_->ListApiKeys();
  if (!local.ok()) return local.status();
  absl::flat_hash_map<std::string, double> last_used;
  for (const auto& k : *local) last_used[k.name] = k.last_used_time_s;
  std::vector<store::ApiKeyRecord> keys;
  keys.reserve(ring->size());
  for (const placement::ClusterKey& c : *ring) {
    keys.push_back(FromRing(c, {}));
    const auto it = last_used.find(c.name);
    if (it != last_used.end()) keys.back().last_used_time_s = it->second;
  }
  return keys;
}

}  // namespace lifemap::server
