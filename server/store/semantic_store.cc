// Store: semantic octree snapshots (issue 16), each visit's and each map's, chunked. Both kinds
// have the same header columns and chunk table layout, keyed by their owner's id.
#include <functional>
#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "server/store/store_impl.h"

namespace lifemap::store {
namespace {

struct OctreeTables {
  const char* header;
  const char* chunks;
  const char* key;    // the owner's id column
  const char* owner;  // "visit" or "map", for messages
};
constexpr OctreeTables kVisitOctrees{"semantic_octrees", "semantic_octree_chunks", "visit_id",
                                     "visit"};
constexpr OctreeTables kMapOctrees{"semantic_map_octrees", "semantic_map_octree_chunks", "map_id",
                                   "map"};
constexpr char kHeaderColumns[] =
    "model, class_count, resolution_m, keyframes, bytes, updated_time_s";

// Reads kHeaderColumns from column `first` on into `r`; returns the stored byte count.
int64_t ReadHeader(const Statement& s, int first, SemanticSnapshotRecord* r) {
  r->model = s.ColumnText(first);
  r->class_count = static_cast<int>(s.ColumnInt(first + 1));
  r->resolution_m = s.ColumnDouble(first + 2);
  r->keyframes = s.ColumnInt(first + 3);
  r->updated_time_s = s.ColumnDouble(first + 5);
  return s.ColumnInt(first + 4);
}

// Replaces `key`'s header and chunks in one transaction. `extra` names columns after the common
// ones (", sources, merged") whose values `bind_extra` binds from parameter 8 on.
absl::Status PutOctree(Database* db, const OctreeTables& t, int64_t key,
                       const SemanticSnapshotRecord& r, const std::string& extra,
                       const std::function<void(Statement&)>& bind_extra) {
  Transaction tx(db);
  if (auto s = tx.Begin(); !s.ok()) return s;
  {
    const std::vector<std::string> columns =
        absl::StrSplit(absl::StrCat(kHeaderColumns, extra), ", ");
    std::string values = "?1", updates;
    for (size_t i = 0; i < columns.size(); ++i) {
      absl::StrAppend(&values, ", ?", i + 2);
      absl::StrAppend(&updates, i == 0 ? "" : ", ", columns[i], " = excluded.", columns[i]);
    }
    auto stmt = db->Prepare(absl::StrCat("INSERT INTO ", t.header, " (", t.key, ", ",
                                         kHeaderColumns, extra, ") VALUES (", values,
                                         ") ON CONFLICT(", t.key, ") DO UPDATE SET ", updates));
    if (!stmt.ok()) return stmt.status();
    StatementScope s(*stmt);
    s->Bind(1, key).Bind(2, r.model).Bind(3, int64_t{r.class_count});
    s->Bind(4, r.resolution_m).Bind(5, r.keyframes);
    s->Bind(6, static_cast<int64_t>(r.bytes.size())).Bind(7, r.updated_time_s);
    if (bind_extra) bind_extra(**stmt);
    if (auto st = s->Run(); !st.ok()) {
      if (IsConstraintViolation(st)) {
        return absl::NotFoundError(absl::StrCat(t.owner, " ", key, " does not exist"));
      }
      return st;
    }
  }
  {
    auto stmt = db->Prepare(absl::StrCat("DELETE FROM ", t.chunks, " WHERE ", t.key, " = ?1"));
    if (!stmt.ok()) return stmt.status();
    StatementScope s(*stmt);
    s->Bind(1, key);
    if (auto st = s->Run(); !st.ok()) return st;
  }
  auto insert = db->Prepare(
      absl::StrCat("INSERT INTO ", t.chunks, " (", t.key, ", chunk, data) VALUES (?1, ?2, ?3)"));
  if (!insert.ok()) return insert.status();
  const std::string_view bytes(r.bytes);
  for (size_t offset = 0, chunk = 0; offset < bytes.size();
       offset += Store::kSemanticChunkBytes, ++chunk) {
    StatementScope s(*insert);
    s->Bind(1, key).Bind(2, static_cast<int64_t>(chunk));
    s->BindBlob(3, bytes.substr(offset, Store::kSemanticChunkBytes));
    if (auto st = s->Run(); !st.ok()) return st;
  }
  return tx.Commit();
}

// Reads `key`'s header and chunks in one read transaction (the same snapshot of both); columns
// after the common ones (`extra`) are read by `read_extra` from column 6 on.
absl::StatusOr<SemanticSnapshotRecord> GetOctree(
    Database* db, const OctreeTables& t, int64_t key, const std::string& extra,
    const std::function<void(Statement&)>& read_extra) {
  if (auto s = db->Exec("BEGIN"); !s.ok()) return s;
  struct End {
    Database* db;
    ~End() { db->Exec("COMMIT").IgnoreError(); }
  } end{db};
  SemanticSnapshotRecord r;
  int64_t size = 0;
  {
    auto stmt = db->Prepare(absl::StrCat("SELECT ", kHeaderColumns, extra, " FROM ", t.header,
                                         " WHERE ", t.key, " = ?1"));
    if (!stmt.ok()) return stmt.status();
    StatementScope s(*stmt);
    s->Bind(1, key);
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (!*row) {
      return absl::NotFoundError(absl::StrCat(t.owner, " ", key, " has no semantic octree"));
    }
    size = ReadHeader(**stmt, 0, &r);
    if (read_extra) read_extra(**stmt);
  }
  auto stmt = db->Prepare(
      absl::StrCat("SELECT data FROM ", t.chunks, " WHERE ", t.key, " = ?1 ORDER BY chunk"));
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, key);
  for (;;) {
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    r.bytes += s->ColumnBlob(0);
  }
  if (static_cast<int64_t>(r.bytes.size()) != size) {
    return absl::DataLossError(absl::StrCat(t.owner, " ", key, "'s semantic octree has ",
                                            r.bytes.size(), " bytes of ", size));
  }
  return r;
}

}  // namespace

absl::Status Store::PutSemanticSnapshot(const SemanticSnapshotRecord& r) {
  absl::MutexLock lock(&impl_->write_mu);
  return PutOctree(impl_->write_db.get(), kVisitOctrees, r.visit_id, r, "", nullptr);
}

absl::StatusOr<SemanticSnapshotRecord> Store::GetSemanticSnapshot(int64_t visit_id) {
  absl::MutexLock lock(&impl_->read_mu);
  auto r = GetOctree(impl_->read_db.get(), kVisitOctrees, visit_id, "", nullptr);
  if (r.ok()) r->visit_id = visit_id;
  return r;
}

absl::StatusOr<std::vector<SemanticSnapshotRecord>> Store::ListSemanticSnapshots(int64_t map_id) {
  absl::MutexLock lock(&impl_->read_mu);
  auto stmt = impl_->read_db->Prepare(absl::StrCat(
      "SELECT o.visit_id, ", kHeaderColumns,
      " FROM semantic_octrees o JOIN visits v ON v.id = o.visit_id WHERE v.map_id = ?1 ORDER BY "
      "o.visit_id"));
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, map_id);
  std::vector<SemanticSnapshotRecord> out;
  for (;;) {
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    SemanticSnapshotRecord& r = out.emplace_back();
    r.visit_id = s->ColumnInt(0);
    ReadHeader(**stmt, 1, &r);
  }
  return out;
}

absl::Status Store::PutMapSemanticSnapshot(const MapSemanticSnapshotRecord& r) {
  absl::MutexLock lock(&impl_->write_mu);
  return PutOctree(impl_->write_db.get(), kMapOctrees, r.map_id, r.octree, ", sources, merged",
                   [&](Statement& s) { s.Bind(8, r.sources).Bind(9, r.merged); });
}

absl::StatusOr<MapSemanticSnapshotRecord> Store::GetMapSemanticSnapshot(int64_t map_id) {
  absl::MutexLock lock(&impl_->read_mu);
  MapSemanticSnapshotRecord r;
  r.map_id = map_id;
  auto octree =
      GetOctree(impl_->read_db.get(), kMapOctrees, map_id, ", sources, merged", [&](Statement& s) {
        r.sources = s.ColumnText(6);
        r.merged = s.ColumnText(7);
      });
  if (!octree.ok()) return octree.status();
  r.octree = *std::move(octree);
  return r;
}

}  // namespace lifemap::store
