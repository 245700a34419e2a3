#include "server/rpc/shard_membership.h"

#include <spdlog/spdlog.h>

#include <utility>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "server/engine/clock.h"

namespace lifemap::server {

absl::StatusOr<std::unique_ptr<ShardMembership>> ShardMembership::Join(const std::string& uri,
                                                                       const std::string& shard,
                                                                       store::Store* store) {
  auto placement = placement::Placement::Open(uri);
  if (!placement.ok()) return placement.status();
  auto self = (*placement)->GetShard(shard);
  if (!self.ok()) {
    if (!absl::IsNotFound(self.status())) return self.status();
    return absl::NotFoundError(
        absl::StrCat("shard '", shard,
                     "' is not in the placement database: add it first with `lifemap admin "
                     "shards add ",
                     shard,
                     " HOST:PORT --placement URI` (HOST:PORT: where nginx reaches this "
                     "server's gRPC port)"));
  }
  std::unique_ptr<ShardMembership> membership(
      new ShardMembership(shard, *std::move(placement), store));
  if (auto s = membership->Reconcile(); !s.ok()) return s;
  membership->Tick();
  return membership;
}

absl::Status ShardMembership::Reconcile() {
  auto local = store_->ListMaps();
  if (!local.ok()) return local.status();
  std::vector<std::string> adopted, stale;
  for (const store::MapRecord& m : *local) {
    auto placed = placement_->FindMap(m.name);
    if (!placed.ok()) return placed.status();
    if (!placed->has_value()) {
      if (auto s = placement_->PlaceMap(m.name, shard_, NowSeconds()); !s.ok()) return s;
      adopted.push_back(m.name);
    } else if ((*placed)->shard != shard_ && (*placed)->move_to != shard_) {
      stale.push_back(absl::StrCat(m.name, " (on ", (*placed)->shard, ")"));
    }
  }
  if (!adopted.empty()) {
    spdlog::info("shard {}: placed {} map(s) it holds that were placed nowhere: {}", shard_,
                 adopted.size(), absl::StrJoin(adopted, ", "));
  }
  if (!stale.empty()) {
    spdlog::warn(
        "shard {}: {} map(s) held here live on other shards (moved while this shard was away); "
        "calls about them are refused: {}",
        shard_, stale.size(), absl::StrJoin(stale, ", "));
  }
  return absl::OkStatus();
}

absl::Status ShardMembership::Refresh() {
  auto shards = placement_->ListShards();
  if (!shards.ok()) return shards.status();
  auto maps = placement_->ListMaps("");
  if (!maps.ok()) return maps.status();
  absl::flat_hash_map<std::string, placement::MapPlacement> elsewhere;
  for (placement::MapPlacement& m : *maps) {
    if (m.shard != shard_) elsewhere.emplace(absl::AsciiStrToLower(m.map), std::move(m));
  }
  absl::flat_hash_map<std::string, std::string> addresses;
  for (const placement::Shard& s : *shards) addresses[s.name] = s.address;
  absl::MutexLock lock(&mu_);
  elsewhere_ = std::move(elsewhere);
  addresses_ = std::move(addresses);
  return absl::OkStatus();
}

void ShardMembership::Tick() {
  if (auto s = placement_->Heartbeat(shard_, NowSeconds()); !s.ok()) {
    spdlog::warn("shard {}: heartbeat: {}", shard_, std::string(s.message()));
  }
  // Until a read succeeds the last one stands: a shard keeps serving its own maps while
  // PostgreSQL is away (maps only change shards through `lifemap maps move`, which needs it).
  if (auto s = Refresh(); !s.ok()) {
    spdlog::warn("shard {}: reading the placement: {}", shard_, std::string(s.message()));
  }
}

absl::Status ShardMembership::CheckMap(const std::string& map) const {
  placement::MapPlacement where;
  std::string address;
  {
    absl::MutexLock lock(&mu_);
    const auto it = elsewhere_.find(absl::AsciiStrToLower(map));
    if (it == elsewhere_.end()) return absl::OkStatus();
    where = it->second;
    const auto a = addresses_.find(where.shard);
    if (a != addresses_.end()) address = a->second;
  }
  const bool held_here = store_->GetMap(map).ok();
  return absl::FailedPreconditionError(absl::StrCat(
      "map '", where.map, "' lives on shard '", where.shard, "' (", address,
      "), not on this shard '", shard_, "'",
      held_here ? ": the copy here is stale (the map moved while this shard was away) and is "
                  "refused; delete it here once the map is safe where it lives"
                : ": connect through the cluster's nginx, which routes by the lifemap-map header"));
}

absl::StatusOr<bool> ShardMembership::PlaceNew(const std::string& map) {
  auto placed = placement_->FindMap(map);
  if (!placed.ok()) return placed.status();
  if (placed->has_value() && (*placed)->map == map &&
      ((*placed)->shard == shard_ || (*placed)->move_to == shard_)) {
    return false;
  }
  if (auto s = placement_->PlaceMap(map, shard_, NowSeconds()); !s.ok()) return s;
  absl::MutexLock lock(&mu_);
  elsewhere_.erase(absl::AsciiStrToLower(map));
  return true;
}

void ShardMembership::Unplace(const std::string& map) {
  if (auto s = placement_->UnplaceMap(map, shard_); !s.ok()) {
    spdlog::warn("shard {}: map {} was deleted here but is still placed here: {}", shard_, map,
                 std::string(s.message()));
  }
}

absl::StatusOr<std::vector<placement::Shard>> ShardMembership::Shards() const {
  return placement_->ListShards();
}

}  // namespace lifemap::server
