#include "server/rpc/auth.h"

#include <openssl/rand.h>
#include <openssl/sha.h>

#include <algorithm>
#include <cmath>
#include <cstdio>

#include <grpcpp/server_context.h>
#include <spdlog/spdlog.h>

#include "absl/strings/escaping.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "core/common/cluster_headers.h"
#include "server/engine/clock.h"

namespace lifemap::server {
namespace {

constexpr absl::string_view kBearer = "Bearer ";
constexpr absl::string_view kSecretPrefix = "lmk_";

std::string HowToSendAKey() {
  return "send the metadata 'authorization: Bearer KEY' (lifemap: --api-key-file FILE, "
         "LIFEMAP_API_KEY or --api-key KEY); an admin creates keys with `lifemap keys create` "
         "(the first with `lifemapd keys create NAME --role admin --db FILE` on the "
         "server's machine)";
}

}  // namespace

absl::string_view RoleName(Role role) {
  switch (role) {
    case Role::kRobot:
      return "robot";
    case Role::kOperator:
      return "operator";
    case Role::kAdmin:
      return "admin";
  }
  return "unknown";
}

std::optional<Role> ParseRole(absl::string_view name) {
  for (Role r : {Role::kRobot, Role::kOperator, Role::kAdmin}) {
    if (name == RoleName(r)) return r;
  }
  return std::nullopt;
}

const std::vector<std::pair<absl::string_view, Role>>& MethodRoles() {
  static const auto* const kTable = new std::vector<std::pair<absl::string_view, Role>>{
      // Robots: their own frames and visits, places, reading maps.
      {"FrameService/StreamFrames", Role::kRobot},
      {"FrameService/ProcessFrame", Role::kRobot},
      {"VisitService/StartVisit", Role::kRobot},
      {"VisitService/EndVisit", Role::kRobot},
      {"VisitService/ListVisits", Role::kRobot},
      {"VisitService/GetAnchorHistory", Role::kRobot},
      {"VisitService/GetChanges", Role::kRobot},
      {"PlaceService/QueryPlace", Role::kRobot},
      {"PlaceService/ListPlaces", Role::kRobot},
      {"MapService/ListMaps", Role::kRobot},
      {"MapService/GetMap", Role::kRobot},
      {"MapService/ListKeyframes", Role::kRobot},
      {"MapService/GetKeyframe", Role::kRobot},
      {"ModelService/ListModels", Role::kRobot},
      {"ModelService/ListClasses", Role::kRobot},
      {"AdminService/GetServerInfo", Role::kRobot},
      // Operators: maps and models, exports, rebuilds, statistics.
      {"MapService/CreateMap", Role::kOperator},
      {"MapService/DeleteMap", Role::kOperator},
      {"MapService/RenameMap", Role::kOperator},
      {"MapService/UpdateMap", Role::kOperator},
      {"MapService/ExportMap", Role::kOperator},
      {"VisitService/AnchorVisits", Role::kOperator},
      {"VisitService/DeleteVisit", Role::kOperator},
      {"MapService/ImportMap", Role::kOperator},
      {"MapService/RebuildSemanticOctrees", Role::kOperator},
      {"ModelService/UploadModel", Role::kOperator},
      {"ModelService/ActivateModel", Role::kOperator},
      {"ModelService/DeleteModel", Role::kOperator},
      {"AdminService/GetStats", Role::kOperator},
      {"AdminService/CheckIntegrity", Role::kOperator},
      // Admins: keys, the audit log, the database file, the appearance index.
      {"AdminService/Backup", Role::kAdmin},
      {"AdminService/Vacuum", Role::kAdmin},
      {"AdminService/RebuildAppearanceIndex", Role::kAdmin},
      {"AdminService/ApplyRetention", Role::kAdmin},
      {"AdminService/CreateApiKey", Role::kAdmin},
      {"AdminService/ListApiKeys", Role::kAdmin},
      {"AdminService/RevokeApiKey", Role::kAdmin},
      {"AdminService/ListAuditEvents", Role::kAdmin},
      {"AdminService/RefreshPlacement", Role::kAdmin},
  };
  return *kTable;
}

std::optional<Role> RequiredRole(absl::string_view method) {
  for (const auto& [name, role] : MethodRoles()) {
    if (name == method) return role;
  }
  return std::nullopt;
}

bool Principal::MayUseMap(int64_t map_id) const {
  if (every_map) return true;
  for (int64_t id : map_ids) {
    if (id == map_id) return true;
  }
  return false;
}

absl::Status Principal::CheckMap(int64_t map_id, absl::string_view map_name) const {
  if (MayUseMap(map_id)) return absl::OkStatus();
  // A shard of a cluster knows the key's maps it holds, not those on other shards.
  const bool shard = gate != nullptr;
  return absl::PermissionDeniedError(absl::StrCat(
      "API key '", key_name, "' may use only the maps ",
      map_names.empty() ? std::string(shard ? "(none)" : "(none left)")
                        : absl::StrJoin(map_names, ", "),
      shard ? " on this shard" : "", ", not '", map_name, "': use a key for that map"));
}

absl::Status Principal::CheckEveryMap(absl::string_view what) const {
  if (every_map) return absl::OkStatus();
  return absl::PermissionDeniedError(absl::StrCat("API key '", key_name, "' is limited to maps (",
                                                  absl::StrJoin(map_names, ", "), "); ", what,
                                                  " needs a key for every map"));
}

absl::Status Principal::CheckNotRevoked() const {
  if (revoked == nullptr || !revoked->load()) return absl::OkStatus();
  return absl::UnauthenticatedError(
      absl::StrCat("API key '", key_name, "' was revoked during this call; ", HowToSendAKey()));
}

namespace {
// The server's gate on `map` for the caller's method; a write's lease is kept in the Principal.
absl::Status PassGate(const Principal& caller, const std::string& map) {
  if (caller.gate == nullptr) return absl::OkStatus();
  auto lease = caller.gate->CheckMap(map, caller.method, caller.routed_by_proxy);
  if (!lease.ok()) return lease.status();
  if (*lease) caller.write_lease = *std::move(lease);
  return absl::OkStatus();
}
}  // namespace

absl::StatusOr<store::MapRecord> FindCallersMap(store::Store* store, const Principal& caller,
                                                const std::string& name) {
  if (auto s = store::ValidateMapName(name); !s.ok()) return s;
  if (auto s = PassGate(caller, name); !s.ok()) return s;
  auto map = store->GetMap(name);
  if (!map.ok()) {
    if (absl::IsNotFound(map.status()) && !caller.every_map) return caller.CheckMap(-1, name);
    return map.status();
  }
  if (auto s = caller.CheckMap(map->id, map->name); !s.ok()) return s;
  return map;
}

absl::StatusOr<store::VisitRecord> FindCallersVisit(store::Store* store, const Principal& caller,
                                                    int64_t visit_id) {
  auto visit = store->GetVisit(visit_id);
  if (!visit.ok()) {
    if (absl::IsNotFound(visit.status()) && !caller.every_map) {
      return caller.CheckMap(-1, absl::StrCat("(the map of visit ", visit_id, ")"));
    }
    return visit.status();
  }
  if (auto s = PassGate(caller, visit->map_name); !s.ok()) return s;
  if (!caller.MayUseMap(visit->map_id)) {
    return caller.CheckMap(visit->map_id, absl::StrCat("(the map of visit ", visit_id, ")"));
  }
  return visit;
}

absl::StatusOr<std::pair<std::string, store::ApiKeyRecord>> NewApiKey(
    const std::string& name, Role role, const std::vector<std::string>& maps,
    const store::KeyLimits& limits, double now_s) {
  if (auto s = store::ValidateName(name, "API key"); !s.ok()) return s;
  if (auto s = ValidateKeyLimits(limits); !s.ok()) return s;
  if (role == Role::kAdmin && !maps.empty()) {
    return absl::InvalidArgumentError(
        "an admin key cannot be limited to maps (it manages keys for every map): give a robot "
        "or operator key the maps instead");
  }
  store::ApiKeyRecord record;
  record.name = name;
  record.role = std::string(RoleName(role));
  record.every_map = maps.empty();
  record.limits = limits;
  for (size_t i = 0; i < maps.size(); ++i) {
    const std::string& map_name = maps[i];
    if (auto s = store::ValidateMapName(map_name); !s.ok()) {
      return absl::InvalidArgumentError(absl::StrCat("maps: ", s.message()));
    }
    if (std::find(maps.begin(), maps.begin() + static_cast<std::ptrdiff_t>(i), map_name) !=
        maps.begin() + static_cast<std::ptrdiff_t>(i)) {
      // Stored twice, the key's second row failed the store's uniqueness as "no map with id".
      return absl::InvalidArgumentError(
          absl::StrCat("maps: '", map_name, "' is named twice; name each map once"));
    }
  }
  record.map_names = maps;
  std::string secret = NewApiKeySecret();
  record.secret_sha256 = ApiKeyHash(secret);
  record.created_time_s = now_s;
  return std::make_pair(std::move(secret), std::move(record));
}

absl::StatusOr<std::pair<std::string, store::ApiKeyRecord>> CreateApiKey(
    store::Store* store, const std::string& name, Role role, const std::vector<std::string>& maps,
    const store::KeyLimits& limits, double now_s) {
  auto key = NewApiKey(name, role, maps, limits, now_s);
  if (!key.ok()) return key.status();
  store::ApiKeyRecord& record = key->second;
  for (const std::string& map_name : maps) {
    auto map = store->GetMap(map_name);
    if (!map.ok())
      return absl::Status(map.status().code(), absl::StrCat("maps: ", map.status().message()));
    record.map_ids.push_back(map->id);
  }
  auto stored = store->InsertApiKey(record);
  if (!stored.ok()) return stored.status();
  return std::make_pair(std::move(key->first), *std::move(stored));
}

absl::Status ValidateKeyLimits(const store::KeyLimits& l) {
  if (l.max_streams < 0 || l.max_maps < 0 || l.max_keyframes_per_map < 0 || l.max_model_bytes < 0 ||
      !std::isfinite(l.max_frames_per_s) || l.max_frames_per_s < 0) {
    return absl::InvalidArgumentError("key limits must be >= 0 (0 = no limit of the key's own)");
  }
  return absl::OkStatus();
}

absl::Status KeyUsage::OpenStream(const std::string& key_name, int64_t max,
                                  absl::string_view limit_name) {
  absl::MutexLock lock(&mu_);
  if (max > 0 && streams_ >= max) {
    return absl::ResourceExhaustedError(absl::StrCat(
        "API key '", key_name, "' may have ", max, " streams open at once (", limit_name,
        ") and has: end one, or ask an admin for a key with a higher limit"));
  }
  ++streams_;
  return absl::OkStatus();
}

void KeyUsage::CloseStream() {
  absl::MutexLock lock(&mu_);
  --streams_;
}

absl::Status KeyUsage::TakeFrame(const std::string& key_name, double per_second) {
  if (per_second <= 0) return absl::OkStatus();
  const double now = NowSeconds();
  absl::MutexLock lock(&mu_);
  // A bucket of a second's frames, refilled at the limit's rate.
  const double capacity = std::max(1.0, per_second);
  if (tokens_ < 0) {
    tokens_ = capacity;
  } else {
    tokens_ = std::min(capacity, tokens_ + (now - refilled_s_) * per_second);
  }
  refilled_s_ = now;
  if (tokens_ < 1.0) {
    return absl::ResourceExhaustedError(absl::StrCat(
        "API key '", key_name, "' may send ", per_second,
        " frames a second (its max_frames_per_s limit, streams and ProcessFrame together): "
        "this frame was not processed; send fewer"));
  }
  tokens_ -= 1.0;
  return absl::OkStatus();
}

absl::Status KeyUsage::TakeVisit(const std::string& key_name, int64_t per_hour,
                                 absl::string_view limit_name) {
  if (per_hour <= 0) return absl::OkStatus();
  const double now = NowSeconds();
  absl::MutexLock lock(&mu_);
  while (!visits_started_s_.empty() && now - visits_started_s_.front() >= 3600.0) {
    visits_started_s_.pop_front();
  }
  if (static_cast<int64_t>(visits_started_s_.size()) >= per_hour) {
    return absl::ResourceExhaustedError(absl::StrCat(
        "API key '", key_name, "' may start ", per_hour, " visits in an hour (", limit_name,
        ") and has; resume a visit (visit_id) instead of starting new ones, or wait ",
        static_cast<int64_t>(std::ceil(3600.0 - (now - visits_started_s_.front()))), " s"));
  }
  visits_started_s_.push_back(now);
  return absl::OkStatus();
}

absl::Status Principal::TakeVisit(int64_t server_per_hour) const {
  if (usage == nullptr) return absl::OkStatus();
  if (limits.max_visits_per_hour > 0) {
    return usage->TakeVisit(key_name, limits.max_visits_per_hour, "its max_visits_per_hour limit");
  }
  return usage->TakeVisit(key_name, server_per_hour,
                          "the server's security.max_visits_per_key_per_hour");
}

absl::Status Principal::OpenStream(int64_t server_max_per_key) const {
  if (usage == nullptr) return absl::OkStatus();
  if (limits.max_streams > 0 && limits.max_streams <= server_max_per_key) {
    return usage->OpenStream(key_name, limits.max_streams, "its max_streams limit");
  }
  return usage->OpenStream(key_name, server_max_per_key, "the server's max_streams_per_key");
}

void Principal::CloseStream() const {
  if (usage != nullptr) usage->CloseStream();
}

absl::Status Principal::TakeFrame() const {
  return usage != nullptr ? usage->TakeFrame(key_name, limits.max_frames_per_s) : absl::OkStatus();
}

store::MapCreator Principal::AsMapCreator() const {
  return store::MapCreator{key_id, key_name, limits.max_maps};
}

absl::StatusOr<bool> HasLiveAdminKey(store::Store* store) {
  auto keys = store->ListApiKeys();
  if (!keys.ok()) return keys.status();
  for (const auto& k : *keys) {
    if (k.revoked_time_s == 0 && k.role == RoleName(Role::kAdmin)) return true;
  }
  return false;
}

std::string NewApiKeySecret() {
  unsigned char bytes[32];
  if (RAND_bytes(bytes, sizeof(bytes)) != 1) {
    // OpenSSL's generator is seeded from the kernel; failing here means no entropy at all.
    spdlog::critical("OpenSSL RAND_bytes failed: no API key can be made");
    std::abort();
  }
  return absl::StrCat(kSecretPrefix, absl::WebSafeBase64Escape(absl::string_view(
                                         reinterpret_cast<const char*>(bytes), sizeof(bytes))));
}

std::string ApiKeyHash(absl::string_view secret) {
  unsigned char digest[SHA256_DIGEST_LENGTH];
  SHA256(reinterpret_cast<const unsigned char*>(secret.data()), secret.size(), digest);
  return absl::BytesToHexString(
      absl::string_view(reinterpret_cast<const char*>(digest), sizeof(digest)));
}

KeyRing::KeyRing(store::Store* store, bool required) : store_(store), required_(required) {}

absl::Status KeyRing::Reload() {
  absl::MutexLock lock(&mu_);
  return ReloadLocked();
}

absl::Status KeyRing::ReloadLocked() {
  auto keys = store_->ListApiKeys();
  if (!keys.ok()) return keys.status();
  absl::flat_hash_map<std::string, std::shared_ptr<Entry>> next;
  for (auto& k : *keys) {
    // A new entry each time (calls read the record of theirs without the lock), with the
    // same `revoked` flag as before: open calls of a key revoked elsewhere see it set.
    auto entry = std::make_shared<Entry>();
    const auto it = by_hash_.find(k.secret_sha256);
    if (it != by_hash_.end()) {
      entry->revoked = it->second->revoked;
      entry->usage = it->second->usage;
      entry->touched_s = it->second->touched_s;
    } else {
      entry->revoked = std::make_shared<std::atomic<bool>>(false);
      entry->usage = std::make_shared<KeyUsage>();
    }
    if (k.revoked_time_s > 0) entry->revoked->store(true);
    entry->touched_s = std::max(entry->touched_s, k.last_used_time_s);
    entry->record = std::move(k);
    next.emplace(entry->record.secret_sha256, std::move(entry));
  }
  // A key gone from the store (its database restored from an older backup) is revoked for the
  // calls that hold it.
  for (const auto& [hash, entry] : by_hash_) {
    if (!next.contains(hash)) entry->revoked->store(true);
  }
  by_hash_ = std::move(next);
  loaded_s_ = NowSeconds();
  return absl::OkStatus();
}

absl::StatusOr<std::shared_ptr<KeyRing::Entry>> KeyRing::Find(
    std::optional<absl::string_view> authorization, absl::string_view method) {
  if (!authorization) {
    return absl::UnauthenticatedError(
        absl::StrCat(method, " needs an API key and the call carries none: ", HowToSendAKey()));
  }
  const absl::string_view value = *authorization;
  if (!absl::StartsWith(value, kBearer)) {
    return absl::UnauthenticatedError(absl::StrCat(
        "the 'authorization' metadata must be 'Bearer KEY' (a key from `lifemap keys create`)"));
  }
  const std::string hash = ApiKeyHash(value.substr(kBearer.size()));
  std::shared_ptr<Entry> entry;
  for (int attempt = 0; entry == nullptr; ++attempt) {
    {
      absl::MutexLock lock(&mu_);
      if (NowSeconds() - loaded_s_ > kReloadIntervalS) {
        if (auto s = ReloadLocked(); !s.ok()) {
          return absl::UnavailableError(absl::StrCat("API keys unreadable: ", s.message()));
        }
      }
      const auto found = by_hash_.find(hash);
      if (found != by_hash_.end()) {
        entry = found->second;
        break;
      }
    }
    // Not here: a key made on another shard of a cluster a moment ago is fetched once (the
    // source reloads this ring when it writes new keys), outside the lock.
    if (attempt > 0 || !fetch_new_keys_ || !fetch_new_keys_()) {
      return absl::UnauthenticatedError(absl::StrCat(
          "the API key is not one this server knows (mistyped, or made for another server; "
          "`lifemap keys list` shows the keys by name): ",
          HowToSendAKey()));
    }
  }
  if (entry->revoked->load()) {
    return absl::UnauthenticatedError(absl::StrCat("API key '", entry->record.name,
                                                   "' has been revoked: ask an admin for a new "
                                                   "one (`lifemap keys create`)"));
  }
  return entry;
}

namespace {
std::optional<absl::string_view> AuthorizationOf(const grpc::ServerContextBase& context) {
  const auto& metadata = context.client_metadata();
  const auto it = metadata.find("authorization");
  if (it == metadata.end()) return std::nullopt;
  return absl::string_view(it->second.data(), it->second.size());
}
}  // namespace

absl::StatusOr<Principal> KeyRing::Authorize(const grpc::ServerContextBase& context,
                                             absl::string_view method) {
  const std::optional<Role> needed = RequiredRole(method);
  if (!needed) {
    return absl::InternalError(absl::StrCat(method, " has no role in the server's policy"));
  }
  auto principal = AuthorizeBearer(AuthorizationOf(context), *needed, method);
  if (principal.ok()) {
    principal->routed_by_proxy = context.client_metadata().count(kRoutedByHeader) > 0;
  }
  return principal;
}

absl::StatusOr<Principal> KeyRing::AuthorizeBearer(std::optional<absl::string_view> authorization,
                                                   Role needed, absl::string_view what) {
  if (!required_) {
    Principal anyone;
    anyone.gate = gate_;
    anyone.method = std::string(what);
    return anyone;
  }
  auto entry = Find(authorization, what);
  if (!entry.ok()) return entry.status();
  const store::ApiKeyRecord& key = (*entry)->record;
  const std::optional<Role> role = ParseRole(key.role);
  if (!role) {
    return absl::PermissionDeniedError(
        absl::StrCat("API key '", key.name, "' has an unknown role '", key.role, "'"));
  }
  if (*role < needed) {
    return absl::PermissionDeniedError(absl::StrCat(what, " needs the ", RoleName(needed),
                                                    " role; API key '", key.name, "' is ",
                                                    RoleName(*role)));
  }
  const double now = NowSeconds();
  bool touch = false;
  {
    absl::MutexLock lock(&mu_);
    if (now - (*entry)->touched_s >= kTouchIntervalS) {
      (*entry)->touched_s = now;
      touch = true;
    }
  }
  // At most once a minute per key: a frame stream does not write to the store per call.
  if (touch) {
    if (auto s = store_->TouchApiKey(key.id, now); !s.ok()) {
      spdlog::warn("could not record the use of API key '{}': {}", key.name,
                   std::string(s.message()));
    }
  }
  Principal p;
  p.key_name = key.name;
  p.key_id = key.id;
  p.role = *role;
  p.every_map = key.every_map;
  p.map_ids = key.map_ids;
  p.map_names = key.map_names;
  p.revoked = (*entry)->revoked;
  p.limits = key.limits;
  p.usage = (*entry)->usage;
  p.gate = gate_;
  p.method = std::string(what);
  return p;
}

std::string KeyRing::KeyNameOf(const grpc::ServerContextBase& context) {
  if (!required_) return "";
  auto entry = Find(AuthorizationOf(context), "");
  return entry.ok() ? (*entry)->record.name : "";
}

}  // namespace lifemap::server
