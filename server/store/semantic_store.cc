// Store: each visit's semantic octree snapshot (issue 16), chunked.
#include <algorithm>

#include "absl/strings/str_cat.h"
#include "server/store/store_impl.h"

namespace lifemap::store {

absl::Status Store::PutSemanticSnapshot(const SemanticSnapshotRecord& r) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  Transaction tx(db);
  if (auto s = tx.Begin(); !s.ok()) return s;
  {
    auto stmt = db->Prepare(
        "INSERT INTO semantic_octrees (visit_id, model, class_count, resolution_m, keyframes, "
        "bytes, updated_time_s) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7) ON CONFLICT(visit_id) DO "
        "UPDATE SET model = excluded.model, class_count = excluded.class_count, resolution_m = "
        "excluded.resolution_m, keyframes = excluded.keyframes, bytes = excluded.bytes, "
        "updated_time_s = excluded.updated_time_s");
    if (!stmt.ok()) return stmt.status();
    StatementScope s(*stmt);
    s->Bind(1, r.visit_id).Bind(2, r.model).Bind(3, int64_t{r.class_count});
    s->Bind(4, r.resolution_m).Bind(5, r.keyframes);
    s->Bind(6, static_cast<int64_t>(r.bytes.size())).Bind(7, r.updated_time_s);
    if (auto st = s->Run(); !st.ok()) {
      if (absl::IsFailedPrecondition(st)) {
        return absl::NotFoundError(absl::StrCat("visit ", r.visit_id, " does not exist"));
      }
      return st;
    }
  }
  {
    auto stmt = db->Prepare("DELETE FROM semantic_octree_chunks WHERE visit_id = ?1");
    if (!stmt.ok()) return stmt.status();
    StatementScope s(*stmt);
    s->Bind(1, r.visit_id);
    if (auto st = s->Run(); !st.ok()) return st;
  }
  auto insert =
      db->Prepare("INSERT INTO semantic_octree_chunks (visit_id, chunk, data) VALUES (?1, ?2, ?3)");
  if (!insert.ok()) return insert.status();
  const std::string_view bytes(r.bytes);
  for (size_t offset = 0, chunk = 0; offset < bytes.size();
       offset += kSemanticChunkBytes, ++chunk) {
    StatementScope s(*insert);
    s->Bind(1, r.visit_id).Bind(2, static_cast<int64_t>(chunk));
    s->BindBlob(3, bytes.substr(offset, kSemanticChunkBytes));
    if (auto st = s->Run(); !st.ok()) return st;
  }
  return tx.Commit();
}

absl::StatusOr<SemanticSnapshotRecord> Store::GetSemanticSnapshot(int64_t visit_id) {
  absl::MutexLock lock(&impl_->read_mu);
  Database* db = impl_->read_db.get();
  // One read transaction: the header and its chunks from the same snapshot.
  if (auto s = db->Exec("BEGIN"); !s.ok()) return s;
  struct End {
    Database* db;
    ~End() { db->Exec("COMMIT").IgnoreError(); }
  } end{db};
  SemanticSnapshotRecord r;
  int64_t size = 0;
  {
    auto stmt = db->Prepare(
        "SELECT model, class_count, resolution_m, keyframes, bytes, updated_time_s FROM "
        "semantic_octrees WHERE visit_id = ?1");
    if (!stmt.ok()) return stmt.status();
    StatementScope s(*stmt);
    s->Bind(1, visit_id);
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (!*row) {
      return absl::NotFoundError(absl::StrCat("visit ", visit_id, " has no semantic octree"));
    }
    r.visit_id = visit_id;
    r.model = s->ColumnText(0);
    r.class_count = static_cast<int>(s->ColumnInt(1));
    r.resolution_m = s->ColumnDouble(2);
    r.keyframes = s->ColumnInt(3);
    size = s->ColumnInt(4);
    r.updated_time_s = s->ColumnDouble(5);
  }
  auto stmt =
      db->Prepare("SELECT data FROM semantic_octree_chunks WHERE visit_id = ?1 ORDER BY chunk");
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, visit_id);
  for (;;) {
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    r.bytes += s->ColumnBlob(0);
  }
  if (static_cast<int64_t>(r.bytes.size()) != size) {
    return absl::DataLossError(absl::StrCat("visit ", visit_id, "'s semantic octree has ",
                                            r.bytes.size(), " bytes of ", size));
  }
  return r;
}

}  // namespace lifemap::store
