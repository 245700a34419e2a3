// Who may call what (issue 17): API keys sent as `authorization: Bearer KEY`, each with a role
// (robot < operator < admin) and optionally limited to some maps. The store keeps only each
// secret's SHA-256; the KeyRing keeps the keys in memory and reads them again every few seconds
// (keys created or revoked by `lifemapd keys` beside a running server count within that time;
// by the RPCs, at once).
#pragma once

#include <atomic>
#include <cstdint>
#include <deque>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <vector>
#include "absl/strings/string_view.h"

#include "absl/container/flat_hash_map.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "server/store/store.h"

namespace grpc {
class ServerContextBase;
}

namespace lifemap::server {

// Each role may do what the ones before it may.
enum class Role { kRobot = 1, kOperator = 2, kAdmin = 3 };
absl::string_view RoleName(Role role);  // "robot", "operator", "admin"
std::optional<Role> ParseRole(absl::string_view name);

// Every lifemap method, "Service/Method" (e.g. "MapService/DeleteMap"), with the role it needs:
// the one table of the policy (docs/API.md prints it; the tests call every method with it).
const std::vector<std::pair<absl::string_view, Role>>& MethodRoles();
// The role `method` needs; nullopt for a method not in the table.
std::optional<Role> RequiredRole(absl::string_view method);

// A key's use of its limits while the server runs, shared by its calls: open streams and a
// token bucket of frames (a second's worth of burst).
class KeyUsage {
 public:
  // One more open stream, or RESOURCE_EXHAUSTED naming the limit (`limit_name`) when `max` are
  // open (0: none).
  absl::Status OpenStream(const std::string& key_name, int64_t max, absl::string_view limit_name);
  void CloseStream();
  // One more frame, or RESOURCE_EXHAUSTED naming the limit when the key has sent
  // `per_second` frames in the last second (0: no limit).
  absl::Status TakeFrame(const std::string& key_name, double per_second);
  // One more visit started, or RESOURCE_EXHAUSTED naming the limit (`limit_name`) when
  // `per_hour` were started in the last hour (0: no limit).
  absl::Status TakeVisit(const std::string& key_name, int64_t per_hour,
                         absl::string_view limit_name);

 private:
  absl::Mutex mu_;
  int64_t streams_ ABSL_GUARDED_BY(mu_) = 0;
  double tokens_ ABSL_GUARDED_BY(mu_) = -1;  // < 0: not started
  double refilled_s_ ABSL_GUARDED_BY(mu_) = 0;
  std::deque<double> visits_started_s_ ABSL_GUARDED_BY(mu_);  // within the last hour
};

// Whether this server may answer for a map at all, before its keys are looked at: a shard of a
// cluster refuses maps the placement puts on another shard (server/rpc/shard_membership.h).
class MapGate {
 public:
  virtual ~MapGate() = default;
  // OK, or why calls of `method` ("Service/Method") about `map` are refused here (naming where
  // the map lives, or that it is moving). A call that writes the map is given a lease, held
  // until the call ends (a move waits for every lease of the map before copying it); null for
  // a call that only reads. `routed_by_proxy`: the call came through the cluster's nginx (the
  // lifemap-routed-by header), so a map placed elsewhere means nginx's table is older than the
  // placement (reloading after a move): a refusal to retry, not the caller's mistake.
  virtual absl::StatusOr<std::shared_ptr<void>> CheckMap(const std::string& map,
                                                         absl::string_view method,
                                                         bool routed_by_proxy) const = 0;
};

// The caller of one call.
struct Principal {
  std::string key_name;  // "" when the server runs without auth
  int64_t key_id = 0;
  Role role = Role::kAdmin;
  bool every_map = true;
  std::vector<int64_t> map_ids;        // when !every_map
  std::vector<std::string> map_names;  // their names when the call began, same order
  // Set when the key is revoked while the call runs (a stream checks it at every frame).
  std::shared_ptr<const std::atomic<bool>> revoked;
  // The key's own limits (0: only the server's) and its use of them (null without auth).
  store::KeyLimits limits;
  std::shared_ptr<KeyUsage> usage;
  // The server's gate (KeyRing::set_map_gate); null for a lone server.
  const MapGate* gate = nullptr;
  std::string method;            // the call's "Service/Method" (what the gate judges)
  bool routed_by_proxy = false;  // it came through the cluster's nginx (lifemap-routed-by)
  // The gate's lease on the map this call writes (set by FindCallersMap/FindCallersVisit),
  // released with the Principal when the call's handler returns.
  mutable std::shared_ptr<void> write_lease;

  bool MayUseMap(int64_t map_id) const;
  // PERMISSION_DENIED naming the key's maps unless it may use the map.
  absl::Status CheckMap(int64_t map_id, absl::string_view map_name) const;
  // PERMISSION_DENIED unless the key may use every map: `what` ("creating maps") touches more
  // than one map or the whole server.
  absl::Status CheckEveryMap(absl::string_view what) const;
  // UNAUTHENTICATED once the key has been revoked.
  absl::Status CheckNotRevoked() const;
  // KeyUsage's checks for this key (OK without a key).
  // One more open stream of the key: at most its own max_streams, and at most
  // `server_max_per_key` (the server's max_streams_per_key) whatever the key's own limit.
  absl::Status OpenStream(int64_t server_max_per_key) const;
  void CloseStream() const;
  absl::Status TakeFrame() const;
  // One more visit started by the key: its own max_visits_per_hour, else `server_per_hour` (the
  // server's security.max_visits_per_key_per_hour; 0: none).
  absl::Status TakeVisit(int64_t server_per_hour) const;
  // Who creates a map, with the key's max_maps (store::Store::CreateMap).
  store::MapCreator AsMapCreator() const;
};

// The map named `name` if the caller may use it. INVALID_ARGUMENT for a bad name; the gate's
// refusal (a shard of a cluster: the map lives on another shard); for a key
// limited to other maps PERMISSION_DENIED whether the map exists or not (it learns nothing of
// them); NOT_FOUND.
absl::StatusOr<store::MapRecord> FindCallersMap(store::Store* store, const Principal& caller,
                                                const std::string& name);
// The visit if the caller may use its map: NOT_FOUND, the gate's refusal or PERMISSION_DENIED
// as above.
absl::StatusOr<store::VisitRecord> FindCallersVisit(store::Store* store, const Principal& caller,
                                                    int64_t visit_id);

// Whether the store holds a live (not revoked) admin key: a server that requires keys cannot be
// administered without one (lifemapd refuses to start, for gRPC and the browser view alike).
absl::StatusOr<bool> HasLiveAdminKey(store::Store* store);

// INVALID_ARGUMENT for a negative or non-finite limit.
absl::Status ValidateKeyLimits(const store::KeyLimits& limits);

// A new key's secret (shown this once) and record, not stored: validates the name (1-64 of
// [A-Za-z0-9._-]), the limits and the maps (names, each once; empty = every map; not for admin
// keys), INVALID_ARGUMENT saying what is wrong. map_names = `maps`; no id, no map ids yet.
absl::StatusOr<std::pair<std::string, store::ApiKeyRecord>> NewApiKey(
    const std::string& name, Role role, const std::vector<std::string>& maps,
    const store::KeyLimits& limits, double now_s);

// A new key: validates the name (1-64 of [A-Za-z0-9._-]) and the maps (names; empty = every
// map; not for admin keys, INVALID_ARGUMENT), stores its hash and returns the secret (shown
// this once) with the stored record. ALREADY_EXISTS for a name in use; NOT_FOUND for a map.
// Used by AdminService.CreateApiKey and by `lifemapd keys create` on the server's machine.
absl::StatusOr<std::pair<std::string, store::ApiKeyRecord>> CreateApiKey(
    store::Store* store, const std::string& name, Role role, const std::vector<std::string>& maps,
    const store::KeyLimits& limits, double now_s);

// A new secret: "lmk_" followed by 43 characters (32 random bytes from OpenSSL, base64url).
std::string NewApiKeySecret();
// The hex SHA-256 of a secret, as the store keeps it.
std::string ApiKeyHash(absl::string_view secret);

class KeyRing {
 public:
  // `required`: calls need a live key; otherwise every call is an unlimited admin's.
  KeyRing(store::Store* store, bool required);
  bool required() const { return required_; }
  // Every Principal this ring hands out carries `gate` (set once, before calls arrive).
  void set_map_gate(const MapGate* gate) { gate_ = gate; }
  // Asked when a call carries a key the store does not hold (a shard of a cluster fetches the
  // cluster's new keys: server/rpc/cluster_keys.h); true when it may have stored new ones (it
  // reloads this ring itself). Set once, before calls arrive.
  void set_key_fetcher(std::function<bool()> fetch) { fetch_new_keys_ = std::move(fetch); }

  // The caller of `method` ("Service/Method") from the call's `authorization` metadata.
  // UNAUTHENTICATED without a key, with an unknown or revoked one; PERMISSION_DENIED when the
  // key's role is below the method's (both say what to do). INTERNAL for a method missing from
  // MethodRoles() (a programming error the tests catch).
  absl::StatusOr<Principal> Authorize(const grpc::ServerContextBase& context,
                                      absl::string_view method);
  // The same for a request of another front end (lifemapd --http): `authorization` is its
  // "Bearer KEY" header (nullopt: none), `needed` the role it needs, `what` names it in errors.
  absl::StatusOr<Principal> AuthorizeBearer(std::optional<absl::string_view> authorization,
                                            Role needed, absl::string_view what);
  // The name of the live key the call carries, "" if none (for the audit log).
  std::string KeyNameOf(const grpc::ServerContextBase& context);
  // Reads the keys from the store now (after a key is created or revoked): a revoked key's
  // open calls see their principals' `revoked` set.
  absl::Status Reload();

  static constexpr double kReloadIntervalS = 2.0;
  static constexpr double kTouchIntervalS = 60.0;  // last_used written at most this often

 private:
  // Replaced whole at each reload; `record` is never changed after, so a call may read it
  // without the lock.
  struct Entry {
    store::ApiKeyRecord record;
    std::shared_ptr<std::atomic<bool>> revoked;
    std::shared_ptr<KeyUsage> usage;  // the same from reload to reload
    double touched_s = 0;             // last_used_time_s as last written; guarded by mu_
  };
  // The live entry of `authorization`'s key, or UNAUTHENTICATED.
  absl::StatusOr<std::shared_ptr<Entry>> Find(std::optional<absl::string_view> authorization,
                                              absl::string_view method);
  absl::Status ReloadLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);

  store::Store* const store_;
  const bool required_;
  const MapGate* gate_ = nullptr;
  std::function<bool()> fetch_new_keys_;
  absl::Mutex mu_;
  absl::flat_hash_map<std::string, std::shared_ptr<Entry>> by_hash_ ABSL_GUARDED_BY(mu_);
  double loaded_s_ ABSL_GUARDED_BY(mu_) = -1;
};

}  // namespace lifemap::server
