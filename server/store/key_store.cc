// Store: API keys (their secrets' SHA-256 only), the maps a key may use, and the audit log.
#include "absl/strings/str_cat.h"
#include "server/store/store_impl.h"

namespace lifemap::store {
namespace {

constexpr char kKeySelect[] =
    "SELECT id, name, role, every_map, secret_sha256, created_time_s, last_used_time_s, "
    "revoked_time_s, max_streams, max_frames_per_s, max_maps, max_keyframes_per_map, "
    "max_model_bytes, max_visits_per_hour FROM api_keys ";

ApiKeyRecord ReadKey(const Statement& s) {
  ApiKeyRecord k;
  k.id = s.ColumnInt(0);
  k.name = s.ColumnText(1);
  k.role = s.ColumnText(2);
  k.every_map = s.ColumnInt(3) != 0;
  k.secret_sha256 = s.ColumnText(4);
  k.created_time_s = s.ColumnDouble(5);
  k.last_used_time_s = s.ColumnDouble(6);
  k.revoked_time_s = s.ColumnDouble(7);
  k.limits.max_streams = s.ColumnInt(8);
  k.limits.max_frames_per_s = s.ColumnDouble(9);
  k.limits.max_maps = s.ColumnInt(10);
  k.limits.max_keyframes_per_map = s.ColumnInt(11);
  k.limits.max_model_bytes = s.ColumnInt(12);
  k.limits.max_visits_per_hour = s.ColumnInt(13);
  return k;
}

// Fills map_ids and map_names of a limited key (maps deleted since are gone from both).
absl::Status AddKeyMaps(Database* db, ApiKeyRecord* k) {
  if (k->every_map) return absl::OkStatus();
  auto stmt = db->Prepare(
      "SELECT m.id, m.name FROM api_key_maps a JOIN maps m ON m.id = a.map_id "
      "WHERE a.key_id = ?1 ORDER BY m.name");
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, k->id);
  for (;;) {
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (!*row) return absl::OkStatus();
    k->map_ids.push_back(s->ColumnInt(0));
    k->map_names.push_back(s->ColumnText(1));
  }
}

absl::StatusOr<ApiKeyRecord> GetKeyLocked(Database* db, const std::string& name) {
  auto stmt = db->Prepare(absl::StrCat(kKeySelect, "WHERE name = ?1"));
  if (!stmt.ok()) return stmt.status();
  ApiKeyRecord k;
  {
    StatementScope s(*stmt);
    s->Bind(1, name);
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (!*row) {
      return absl::NotFoundError(
          absl::StrCat("no API key named '", name, "' (lifemap keys list shows them)"));
    }
    k = ReadKey(**stmt);
  }
  if (auto st = AddKeyMaps(db, &k); !st.ok()) return st;
  return k;
}

// The maps a limited key may use: exactly `map_ids` (a key's earlier rows are the caller's to
// delete). NOT_FOUND for an unknown map id.
absl::Status InsertKeyMaps(Database* db, int64_t key_id, const std::vector<int64_t>& map_ids) {
  auto stmt = db->Prepare("INSERT INTO api_key_maps (key_id, map_id) VALUES (?1, ?2)");
  if (!stmt.ok()) return stmt.status();
  for (int64_t map_id : map_ids) {
    StatementScope s(*stmt);
    s->Bind(1, key_id).Bind(2, map_id);
    if (auto st = s->Run(); !st.ok()) {
      if (IsConstraintViolation(st)) {
        return absl::NotFoundError(absl::StrCat("no map with id ", map_id));
      }
      return st;
    }
  }
  return absl::OkStatus();
}

// Binds ?2.. ?12 of the key statements below: role .. max_visits_per_hour.
void BindKeyFields(Statement* s, const ApiKeyRecord& record) {
  s->Bind(2, record.role)
      .Bind(3, static_cast<int64_t>(record.every_map ? 1 : 0))
      .Bind(4, record.secret_sha256)
      .Bind(5, record.created_time_s)
      .Bind(6, record.limits.max_streams)
      .Bind(7, record.limits.max_frames_per_s)
      .Bind(8, record.limits.max_maps)
      .Bind(9, record.limits.max_keyframes_per_map)
      .Bind(10, record.limits.max_model_bytes)
      .Bind(11, record.limits.max_visits_per_hour)
      .Bind(12, record.revoked_time_s);
}

constexpr char kKeyInsert[] =
    "INSERT INTO api_keys (name, role, every_map, secret_sha256, created_time_s, max_streams, "
    "max_frames_per_s, max_maps, max_keyframes_per_map, max_model_bytes, max_visits_per_hour, "
    "revoked_time_s) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12)";

}  // namespace

absl::StatusOr<ApiKeyRecord> Store::InsertApiKey(const ApiKeyRecord& record) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  Transaction txn(db);
  if (auto st = txn.Begin(); !st.ok()) return st;
  {
    auto stmt = db->Prepare(kKeyInsert);
    if (!stmt.ok()) return stmt.status();
    StatementScope s(*stmt);
    s->Bind(1, record.name);
    BindKeyFields(&**stmt, record);
    if (auto st = s->Run(); !st.ok()) {
      if (IsConstraintViolation(st)) {
        return absl::AlreadyExistsError(
            absl::StrCat("an API key named '", record.name,
                         "' exists (revoked keys keep their names): choose another name"));
      }
      return st;
    }
  }
  if (!record.every_map) {
    if (auto st = InsertKeyMaps(db, db->LastInsertRowId(), record.map_ids); !st.ok()) return st;
  }
  if (auto st = txn.Commit(); !st.ok()) return st;
  return GetKeyLocked(db, record.name);
}

absl::StatusOr<std::vector<ApiKeyRecord>> Store::ListApiKeys() {
  absl::MutexLock lock(&impl_->read_mu);
  Database* db = impl_->read_db.get();
  auto stmt = db->Prepare(absl::StrCat(kKeySelect, "ORDER BY name"));
  if (!stmt.ok()) return stmt.status();
  std::vector<ApiKeyRecord> keys;
  {
    StatementScope s(*stmt);
    for (;;) {
      auto row = s->Step();
      if (!row.ok()) return row.status();
      if (!*row) break;
      keys.push_back(ReadKey(**stmt));
    }
  }
  for (auto& k : keys) {
    if (auto st = AddKeyMaps(db, &k); !st.ok()) return st;
  }
  return keys;
}

absl::StatusOr<ApiKeyRecord> Store::RevokeApiKey(const std::string& name, double time_s) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  auto stmt =
      db->Prepare("UPDATE api_keys SET revoked_time_s = ?2 WHERE name = ?1 AND revoked_time_s = 0");
  if (!stmt.ok()) return stmt.status();
  {
    StatementScope s(*stmt);
    s->Bind(1, name).Bind(2, time_s);
    if (auto st = s->Run(); !st.ok()) return st;
  }
  return GetKeyLocked(db, name);
}

absl::StatusOr<ApiKeyRecord> Store::PutApiKey(const ApiKeyRecord& record) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  Transaction txn(db);
  if (auto st = txn.Begin(); !st.ok()) return st;
  int64_t key_id = 0;
  {
    auto stmt = db->Prepare(
        "UPDATE api_keys SET role = ?2, every_map = ?3, secret_sha256 = ?4, created_time_s = ?5, "
        "max_streams = ?6, max_frames_per_s = ?7, max_maps = ?8, max_keyframes_per_map = ?9, "
        "max_model_bytes = ?10, max_visits_per_hour = ?11, revoked_time_s = ?12 "
        "WHERE name = ?1 RETURNING id");
    if (!stmt.ok()) return stmt.status();
    StatementScope s(*stmt);
    s->Bind(1, record.name);
    BindKeyFields(&**stmt, record);
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (*row) key_id = s->ColumnInt(0);
  }
  if (key_id == 0) {
    auto stmt = db->Prepare(kKeyInsert);
    if (!stmt.ok()) return stmt.status();
    StatementScope s(*stmt);
    s->Bind(1, record.name);
    BindKeyFields(&**stmt, record);
    if (auto st = s->Run(); !st.ok()) return st;
    key_id = db->LastInsertRowId();
  } else {
    auto stmt = db->Prepare("DELETE FROM api_key_maps WHERE key_id = ?1");
    if (!stmt.ok()) return stmt.status();
    StatementScope s(*stmt);
    s->Bind(1, key_id);
    if (auto st = s->Run(); !st.ok()) return st;
  }
  if (!record.every_map) {
    if (auto st = InsertKeyMaps(db, key_id, record.map_ids); !st.ok()) return st;
  }
  if (auto st = txn.Commit(); !st.ok()) return st;
  return GetKeyLocked(db, record.name);
}

absl::Status Store::TouchApiKey(int64_t key_id, double time_s) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  auto stmt = db->Prepare("UPDATE api_keys SET last_used_time_s = ?2 WHERE id = ?1");
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, key_id).Bind(2, time_s);
  return s->Run();
}

absl::Status Store::AppendAuditEvent(const AuditEventRecord& e) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  auto stmt = db->Prepare(
      "INSERT INTO audit_log (time_s, key_name, method, request, code, message, peer) "
      "VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7)");
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, e.time_s)
      .Bind(2, e.key_name)
      .Bind(3, e.method)
      .Bind(4, e.request)
      .Bind(5, e.code)
      .Bind(6, e.message)
      .Bind(7, e.peer);
  return s->Run();
}

absl::StatusOr<int64_t> Store::PruneAuditEvents(double before_time_s) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  auto stmt = db->Prepare("DELETE FROM audit_log WHERE time_s < ?1");
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, before_time_s);
  if (absl::Status run = s->Run(); !run.ok()) return run;
  return static_cast<int64_t>(db->Changes());
}

absl::StatusOr<std::vector<AuditEventRecord>> Store::ListAuditEvents(double since_time_s,
                                                                     int limit) {
  absl::MutexLock lock(&impl_->read_mu);
  Database* db = impl_->read_db.get();
  auto stmt = db->Prepare(
      "SELECT time_s, key_name, method, request, code, message, peer FROM audit_log "
      "WHERE time_s >= ?1 ORDER BY time_s DESC, id DESC LIMIT ?2");
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, since_time_s).Bind(2, static_cast<int64_t>(limit));
  std::vector<AuditEventRecord> out;
  for (;;) {
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (!*row) return out;
    AuditEventRecord e;
    e.time_s = s->ColumnDouble(0);
    e.key_name = s->ColumnText(1);
    e.method = s->ColumnText(2);
    e.request = s->ColumnText(3);
    e.code = s->ColumnText(4);
    e.message = s->ColumnText(5);
    e.peer = s->ColumnText(6);
    out.push_back(std::move(e));
  }
}

}  // namespace lifemap::store
