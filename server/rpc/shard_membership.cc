#include "server/rpc/shard_membership.h"

#include <spdlog/spdlog.h>

#include <utility>

#include "absl/container/flat_hash_set.h"
#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/time/clock.h"
#include "server/engine/clock.h"
#include "server/engine/engine.h"
#include "server/engine/visit_registry.h"

namespace lifemap::server {
namespace {

// Calls that change a map's rows: refused while the map is frozen for a move, and counted
// (a lease each) so that the move waits for them before copying.
bool Writes(absl::string_view method) {
  static const auto* writes = new absl::flat_hash_set<absl::string_view>{
      "FrameService/StreamFrames",  "FrameService/ProcessFrame",
      "VisitService/StartVisit",    "VisitService/EndVisit",
      "VisitService/DeleteVisit",   "VisitService/AnchorVisits",
      "MapService/UpdateMap",       "MapService/RenameMap",
      "MapService/DeleteMap",       "MapService/RebuildSemanticOctrees",
      "ModelService/ActivateModel", "AdminService/ApplyRetention",
  };
  return writes->contains(method);
}

std::string Key(const std::string& map) { return absl::AsciiStrToLower(map); }

}  // namespace

ShardMembership::ShardMembership(std::string shard, std::unique_ptr<placement::Placement> placement,
                                 Engine* engine, KeyRing* keys)
    : shard_(std::move(shard)),
      placement_(std::move(placement)),
      engine_(engine),
      keys_(placement_.get(), engine->store(), keys) {}

absl::StatusOr<std::unique_ptr<ShardMembership>> ShardMembership::Join(const std::string& uri,
                                                                       const std::string& shard,
                                                                       Engine* engine,
                                                                       KeyRing* keys) {
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
  if (auto s = engine->store()->RaiseIdFloor(self->number << kIdRangeBits); !s.ok()) return s;
  std::unique_ptr<ShardMembership> membership(
      new ShardMembership(shard, *std::move(placement), engine, keys));
  if (keys != nullptr) {
    keys->set_key_fetcher([ring = &membership->keys_] { return ring->FetchNewKeys(); });
  }
  if (auto s = membership->Reconcile(); !s.ok()) return s;  // reads the placement
  membership->Beat();
  return membership;
}

absl::Status ShardMembership::Reconcile() {
  auto local = engine_->store()->ListMaps();
  if (!local.ok()) return local.status();
  if (auto s = ReadPlacement(); !s.ok()) return s;
  std::vector<std::string> unplaced, adopted, elsewhere;
  {
    absl::MutexLock lock(&mu_);
    for (const store::MapRecord& m : *local) {
      const auto it = placed_.find(Key(m.name));
      if (it == placed_.end()) {
        unplaced.push_back(m.name);
      } else if (it->second.shard != shard_) {
        elsewhere.push_back(absl::StrCat(m.name, " (placed on ", it->second.shard,
                                         it->second.state == "moving" ? ", moving" : "", ")"));
      }
    }
  }
  for (const std::string& name : unplaced) {
    auto placed = PlaceNew(name);
    if (!placed.ok()) return placed.status();
    adopted.push_back(name);
  }
  if (!adopted.empty()) {
    spdlog::info("shard {}: placed {} map(s) it holds that were placed nowhere: {}", shard_,
                 adopted.size(), absl::StrJoin(adopted, ", "));
  }
  if (!elsewhere.empty()) {
    spdlog::warn(
        "shard {}: {} map(s) held here are placed on other shards (moved, or moving); calls "
        "about them are refused here: {}",
        shard_, elsewhere.size(), absl::StrJoin(elsewhere, ", "));
  }
  return keys_.Sync();
}

absl::Status ShardMembership::ReadPlacement() {
  auto shards = placement_->ListShards();
  if (!shards.ok()) return shards.status();
  auto maps = placement_->ListMaps("");
  if (!maps.ok()) return maps.status();
  absl::flat_hash_map<std::string, placement::MapPlacement> placed;
  for (placement::MapPlacement& m : *maps) placed.emplace(Key(m.map), std::move(m));
  absl::flat_hash_map<std::string, std::string> addresses;
  for (const placement::Shard& s : *shards) addresses[s.name] = s.address;
  absl::MutexLock lock(&mu_);
  placed_ = std::move(placed);
  addresses_ = std::move(addresses);
  return absl::OkStatus();
}

void ShardMembership::Beat() {
  if (auto s = placement_->Heartbeat(shard_, NowSeconds()); !s.ok()) {
    spdlog::warn("shard {}: heartbeat: {}", shard_, std::string(s.message()));
  }
}

void ShardMembership::Tick() {
  Beat();
  // Until a read succeeds the last one stands: a shard keeps serving its own maps while
  // PostgreSQL is away (maps only change shards through `lifemap maps move`, which needs it).
  if (auto s = ReadPlacement(); !s.ok()) {
    spdlog::warn("shard {}: reading the placement: {}", shard_, std::string(s.message()));
    return;
  }
  if (auto s = keys_.Sync(); !s.ok()) {
    spdlog::warn("shard {}: syncing the cluster's API keys: {}", shard_, std::string(s.message()));
  }
}

std::string ShardMembership::AddressOf(const std::string& shard) const {
  const auto it = addresses_.find(shard);
  return it == addresses_.end() ? "address unknown" : it->second;
}

std::string ShardMembership::PhaseLocked(const placement::MapPlacement& m) const {
  if (m.state != "moving") return m.shard == shard_ ? "serving" : "elsewhere";
  if (m.move_phase == "switched") {
    if (m.shard == shard_) return "serving";
    return m.move_from == shard_ ? "moved" : "elsewhere";
  }
  if (m.shard == shard_) return "frozen";
  return m.move_to == shard_ ? "arriving" : "elsewhere";
}

absl::StatusOr<std::shared_ptr<void>> ShardMembership::CheckMap(const std::string& map,
                                                                absl::string_view method,
                                                                bool routed_by_proxy) const {
  const std::string key = Key(map);
  const bool writes = Writes(method);
  std::string phase;
  placement::MapPlacement m;
  std::string address;  // of the shard the refusal names
  {
    absl::MutexLock lock(&mu_);
    const auto it = placed_.find(key);
    phase = it == placed_.end() ? "unplaced" : PhaseLocked(it->second);
    if (phase == "serving" || phase == "unplaced" || (phase == "frozen" && !writes)) {
      if (!writes) return std::shared_ptr<void>();
      ++writers_[key];
      // The lease: one writer fewer when the call ends.
      return std::shared_ptr<void>(nullptr, [this, key](void*) {
        absl::MutexLock release(&mu_);
        if (--writers_[key] == 0) writers_.erase(key);
      });
    }
    // A copy left here may be deleted whatever the placement says (the move deletes it so).
    if (method == "MapService/DeleteMap" && phase != "frozen") return std::shared_ptr<void>();
    m = it->second;
    address = AddressOf(m.shard);
  }
  if (phase == "frozen") {
    return absl::UnavailableError(absl::StrCat(
        "map '", m.map, "' is moving from shard '", shard_, "' to shard '", m.move_to,
        "': writes are refused until it is there (seconds to minutes); retry, the client "
        "libraries reconnect and resume the visit"));
  }
  if (phase == "arriving") {
    return absl::UnavailableError(absl::StrCat("map '", m.map, "' is being moved to this shard '",
                                               shard_, "' from shard '", m.shard,
                                               "' and is served here once the move switches"));
  }
  if (phase == "moved") {
    return absl::UnavailableError(absl::StrCat(
        "map '", m.map, "' moved to shard '", m.shard, "' (", address,
        "): reconnect through the cluster's nginx, which routes there once its table is reloaded"));
  }
  if (routed_by_proxy) {
    // nginx still routes by a table older than the placement: a move just switched (nginx's
    // old workers serve open connections until they close) or its table was not reloaded.
    return absl::UnavailableError(absl::StrCat(
        "nginx sent the call about map '", m.map, "' to shard '", shard_,
        "', but the map lives on shard '", m.shard, "' (", address,
        "): nginx's table is older than the placement (it is reloading after a move); retry. "
        "If this lasts, write nginx's table again (lifemap admin shards nginx-config) and "
        "reload nginx"));
  }
  const bool held_here = engine_->store()->GetMap(map).ok();
  return absl::FailedPreconditionError(absl::StrCat(
      "map '", m.map, "' lives on shard '", m.shard, "' (", address, "), not on this shard '",
      shard_, "'",
      held_here ? ": the copy here is stale (the map moved while this shard was away) and is "
                  "refused; delete it here once the map is safe where it lives"
                : ": connect through the cluster's nginx, which routes by the lifemap-map header"));
}

absl::StatusOr<std::string> ShardMembership::Refresh(const std::string& map) {
  if (auto s = ReadPlacement(); !s.ok()) return s;
  // A map that arrives is usable by its keys from the switch on.
  if (auto s = keys_.Sync(); !s.ok()) {
    spdlog::warn("shard {}: syncing the cluster's API keys: {}", shard_, std::string(s.message()));
  }
  const std::string key = Key(map);
  std::string phase;
  {
    absl::MutexLock lock(&mu_);
    const auto it = placed_.find(key);
    phase = it == placed_.end() ? "unplaced" : PhaseLocked(it->second);
  }
  if (phase != "frozen" && phase != "moved") return phase;
  // No new write is admitted now; end the map's streams and wait for the writes running.
  auto record = engine_->store()->GetMap(map);
  if (record.ok()) {
    engine_->visits()->CloseMap(
        record->id,
        absl::UnavailableError(absl::StrCat("map '", map,
                                            "' is moving to another shard: reconnect; the client "
                                            "libraries resume the visit there")));
  }
  const absl::Time deadline = absl::Now() + absl::Seconds(kDrainTimeoutS);
  absl::MutexLock lock(&mu_);
  const auto drained = [this, &key]()
                           ABSL_SHARED_LOCKS_REQUIRED(mu_) { return !writers_.contains(key); };
  if (!mu_.AwaitWithDeadline(absl::Condition(&drained), deadline)) {
    return absl::DeadlineExceededError(absl::StrCat(
        writers_[key], " call(s) still write map '", map, "' after ", kDrainTimeoutS,
        " s (a long RebuildSemanticOctrees?): the move waits for them; run it again later"));
  }
  return phase;
}

absl::StatusOr<bool> ShardMembership::PlaceNew(const std::string& map) {
  auto placed = placement_->FindMap(map);
  if (!placed.ok()) return placed.status();
  if (placed->has_value() && (*placed)->map == map &&
      ((*placed)->shard == shard_ || (*placed)->move_to == shard_)) {
    return false;
  }
  const double now = NowSeconds();
  if (auto s = placement_->PlaceMap(map, shard_, now); !s.ok()) return s;
  // Served here from now on, whatever the cache held for the name (a map of that name deleted
  // elsewhere since the last read); the next read of the placement says the same.
  placement::MapPlacement here;
  here.map = map;
  here.shard = shard_;
  here.state = "active";
  here.placed_s = now;
  absl::MutexLock lock(&mu_);
  placed_[Key(map)] = std::move(here);
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
