// Internal to server/store: the state behind Store, shared by its translation units
// (store.cc: maps, visits, keyframes, administration; model_store.cc: models).
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <string>

#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "server/store/sqlite.h"
#include "server/store/store.h"

namespace lifemap::store {

struct Store::Impl {
  // One connection writes (serialised by write_mu), one reads: WAL lets reads run during a
  // write transaction.
  absl::Mutex write_mu;
  std::unique_ptr<Database> write_db ABSL_GUARDED_BY(write_mu);
  absl::Mutex read_mu;
  std::unique_ptr<Database> read_db ABSL_GUARDED_BY(read_mu);

  // NOT_FOUND naming the map / visit. `db` is the connection whose mutex the caller holds.
  absl::StatusOr<MapRecord> GetMapLocked(Database* db, const std::string& name);
  absl::StatusOr<VisitRecord> GetVisitLocked(Database* db, int64_t visit_id);
};

// Runs the schema migrations from version `from` up to Store::kSchemaVersion, each in its own
// transaction (foreign keys must be off); `path` names the file in errors.
absl::Status MigrateSchema(Database* db, int64_t from, const std::string& path);

// The integer value of the `settings` row `key` (0 when there is none).
absl::StatusOr<int64_t> IntSetting(Database* db, std::string_view key);

// Ids of the tables a map archive renumbers (visits, keyframes, pose_edges, pose_optimisations,
// anchor_revisions, annotations) on a shard of a cluster (Store::RaiseIdFloor): `count` new
// ids in the store's own range [floor + 1, floor + 2^kIdRangeBits), above every id it has given
// out there (kept in `settings`, so an id is never given out twice even after its row is
// deleted), the first returned; nullopt without a floor (SQLite's AUTOINCREMENT picks). Rows of
// a map moved in from another shard keep that shard's ids, above this store's range, and
// AUTOINCREMENT would go on above them, into that shard's range: the cluster test found a
// visit id given out twice that way (issue 52). RESOURCE_EXHAUSTED when the range is used up.
absl::StatusOr<std::optional<int64_t>> ReserveRowIds(Database* db, const char* table,
                                                     int64_t count = 1);
// Binds parameter `index` to `id`, or NULL (SQLite picks) when there is none.
void BindRowId(Statement* s, int index, const std::optional<int64_t>& id);

// A pose as seven columns: tx, ty, tz, qx, qy, qz, qw, bound from parameter `first` (1-based)
// or read from column `first` (0-based; the quaternion normalised).
void BindPose(Statement* s, int first, const Pose& p);
Pose ReadPose(const Statement& s, int first);

}  // namespace lifemap::store
