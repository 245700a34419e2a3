// Map archives: one map copied whole between a store and an SQLite file of the same schema
// (Store::WriteMapArchive, Store::ReadMapArchive).
//
// An archive is a lifemap database holding one map's rows, so that the copy is SQLite's own
// INSERT ... SELECT over tables whose columns are the store's, an older archive is brought
// forward by the store's own migrations, and a reader needs nothing but SQLite. Reading one
// renumbers every id above the destination's (ids are never reused: schema 5) and rewrites the
// references between its rows.
#include <sqlite3.h>

#include <cctype>
#include <functional>
#include <map>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "server/store/sqlite.h"
#include "server/store/store.h"
#include "server/store/store_impl.h"

namespace lifemap::store {
namespace {

// Parameters every copy statement may use (bound when the statement has them).
enum Param : int {
  kMap = 1,      // export: the map's id in the store; import: the new map's id
  kModel = 2,    // import: the model's id in the store (NULL: none)
  kCreator = 3,  // import: the key that imported it (NULL: none)
  kName = 4,     // import: the new map's name (text)
  kParamCount = kName
};

// Values for the Params: integers (nullopt binds NULL) and the name.
struct Bindings {
  std::vector<std::optional<int64_t>> ints = std::vector<std::optional<int64_t>>(kParamCount + 1);
  std::string name;
};

// One table of an archive: which of its rows belong to map ?1 in the store (export) and how
// its columns change on import (column -> SQL expression over the archive's row; the others are
// copied as they are). `from` in the expressions is the schema rows are read from.
struct TableCopy {
  std::string table;
  std::string export_where;
  std::map<std::string, std::string> import_columns;
  std::string import_where = "1";  // which of the archive's rows are imported
};

constexpr char kMapVisits[] = "(SELECT id FROM src.visits WHERE map_id = ?1)";
constexpr char kMapKeyframes[] =
    "(SELECT k.id FROM src.keyframes k JOIN src.visits v ON k.visit_id = v.id "
    "WHERE v.map_id = ?1)";

// On import, every id of the tables an archive renumbers goes through temp.renumber_<table>
// (old INTEGER PRIMARY KEY, new): ids given out densely above the store's, never the archive's
// own numbers (issue 52: an archive's ids near 2^63-1 exhausted the store's counters). A
// reference that must resolve inside the archive (a keyframe's visit) maps through it, and an
// import whose references do not all resolve is refused before anything is copied
// (Dangling); `Ref` is for optional references, which become `missing` when the archive does
// not hold their row (an edge retention removed, a visit deleted), never a row of another map.
std::string Mapped(const std::string& column, const std::string& table) {
  return absl::StrCat("(SELECT new FROM temp.renumber_", table, " WHERE old = ", column, ")");
}

std::string Ref(const std::string& column, const std::string& table, const std::string& missing) {
  return absl::StrCat("COALESCE(", Mapped(column, table), ", ", missing, ")");
}

std::string Bound(Param p) { return absl::StrCat("?", static_cast<int>(p)); }

// Every table holding a map's rows, parents first (the import runs with foreign keys on). The
// map's merged semantic octree is left out on import: a cache named by its visits' ids, made
// again from the visits' octrees when first exported.
std::vector<TableCopy> Tables() {
  const std::string visits = kMapVisits, keyframes = kMapKeyframes;
  return {
      {"models", "id = (SELECT model_id FROM src.maps WHERE id = ?1)", {}},
      {"maps",
       "id = ?1",
       {{"id", Bound(kMap)},
        {"name", Bound(kName)},
        {"model_id", Bound(kModel)},
        {"created_by_key_id", Bound(kCreator)}}},
      {"visits",
       "map_id = ?1",
       {{"id", Mapped("id", "visits")},
        {"map_id", "?1"},
        {"anchor_visit_id", Ref("anchor_visit_id", "visits", "NULL")},
        {"anchor_edge_id", Ref("anchor_edge_id", "pose_edges", "NULL")}}},
      {"pose_optimisations",
       "map_id = ?1",
       {{"id", Mapped("id", "pose_optimisations")},
        {"map_id", "?1"},
        {"visit_id", Ref("visit_id", "visits", "0")}}},
      {"keyframes",
       "visit_id IN " + visits,
       {{"id", Mapped("id", "keyframes")},
        {"visit_id", Mapped("visit_id", "visits")},
        {"optimisation_id", Ref("optimisation_id", "pose_optimisations", "NULL")}}},
      {"keyframe_images",
       "keyframe_id IN " + keyframes,
       {{"keyframe_id", Mapped("keyframe_id", "keyframes")}}},
      {"keyframe_features",
       "keyframe_id IN " + keyframes,
       {{"keyframe_id", Mapped("keyframe_id", "keyframes")}}},
      // A sighting by a visit the archive does not hold is dropped (it names no visit there).
      {"keyframe_sightings",
       "keyframe_id IN " + keyframes,
       {{"keyframe_id", Mapped("keyframe_id", "keyframes")},
        {"visit_id", Mapped("visit_id", "visits")}},
       "visit_id IN (SELECT id FROM src.visits)"},
      {"pose_edges",
       "map_id = ?1",
       {{"id", Mapped("id", "pose_edges")},
        {"map_id", "?1"},
        {"from_keyframe", Mapped("from_keyframe", "keyframes")},
        {"to_keyframe", Mapped("to_keyframe", "keyframes")}}},
      {"anchor_revisions",
       "visit_id IN " + visits,
       {{"id", Mapped("id", "anchor_revisions")},
        {"visit_id", Mapped("visit_id", "visits")},
        {"to_visit_id", Ref("to_visit_id", "visits", "0")},
        {"edge_id", Ref("edge_id", "pose_edges", "NULL")}}},
      {"visit_places", "visit_id IN " + visits, {{"visit_id", Mapped("visit_id", "visits")}}},
      {"semantic_octrees", "visit_id IN " + visits, {{"visit_id", Mapped("visit_id", "visits")}}},
      {"semantic_octree_chunks",
       "visit_id IN " + visits,
       {{"visit_id", Mapped("visit_id", "visits")}}},
      {"annotations", "map_id = ?1", {{"id", Mapped("id", "annotations")}, {"map_id", "?1"}}},
      {"semantic_map_octrees", "map_id = ?1", {}},
      {"semantic_map_octree_chunks", "map_id = ?1", {}},
  };
}

bool ImportsTable(const TableCopy& t) {
  return t.table != "models" && t.table.rfind("semantic_map_octree", 0) != 0;
}

absl::StatusOr<std::vector<std::string>> ColumnsOf(Database* db, const std::string& table) {
  auto stmt = db->Prepare(absl::StrCat("SELECT name FROM pragma_table_info('", table, "')"));
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  std::vector<std::string> columns;
  while (true) {
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    columns.push_back(s->ColumnText(0));
  }
  if (columns.empty()) return absl::InternalError(absl::StrCat("no table ", table));
  return columns;
}

// INSERT INTO main.t (columns) SELECT expressions FROM src.t WHERE where, with `params` bound
// (index = Param; only those the statement uses). Table and column names are the schema's own;
// no value is ever part of the SQL.
absl::Status Copy(Database* db, const std::string& table, const std::string& where,
                  const std::map<std::string, std::string>& columns_changed,
                  const Bindings& params) {
  auto columns = ColumnsOf(db, table);
  if (!columns.ok()) return columns.status();
  std::vector<std::string> values;
  for (const std::string& c : *columns) {
    const auto it = columns_changed.find(c);
    values.push_back(it == columns_changed.end() ? c : it->second);
  }
  auto stmt = db->Prepare(
      absl::StrCat("INSERT INTO main.", table, " (", absl::StrJoin(*columns, ", "), ") SELECT ",
                   absl::StrJoin(values, ", "), " FROM src.", table, " WHERE ", where));
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  for (int p = 1; p <= s->ParameterCount(); ++p) {
    const auto& value = params.ints.at(static_cast<size_t>(p));
    if (p == kName) {
      s->Bind(p, params.name);
    } else if (value) {
      s->Bind(p, *value);
    } else {
      s->BindNull(p);
    }
  }
  return s->Run();
}

// Attaches a file as schema `src` for the scope (ATTACH cannot run inside a transaction).
class Attached {
 public:
  static absl::StatusOr<std::unique_ptr<Attached>> Open(Database* db, const std::string& path) {
    auto stmt = db->Prepare("ATTACH DATABASE ?1 AS src");
    if (!stmt.ok()) return stmt.status();
    StatementScope s(*stmt);
    s->Bind(1, path);
    if (auto st = s->Run(); !st.ok()) return st;
    return std::unique_ptr<Attached>(new Attached(db));
  }
  ~Attached() { db_->Exec("DETACH DATABASE src").IgnoreError(); }

 private:
  explicit Attached(Database* db) : db_(db) {}
  Database* db_;
};

absl::StatusOr<int64_t> QueryIntBound(Database* db, const std::string& sql, int64_t value) {
  auto stmt = db->Prepare(sql);
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  if (s->ParameterCount() > 0) s->Bind(1, value);
  auto row = s->Step();
  if (!row.ok()) return row.status();
  return *row ? s->ColumnInt(0) : 0;
}

absl::Status Cancelled() {
  return absl::CancelledError(
      "the import was cancelled (the client gave up or its deadline passed): nothing of it was "
      "stored; import again (with a longer deadline, if the client set one)");
}

absl::Status NotAnArchive(const std::string& why) {
  return absl::InvalidArgumentError(
      absl::StrCat("not a consistent lifemap map archive: ", why,
                   "; export the map again with `lifemap maps export`"));
}

}  // namespace

absl::StatusOr<ArchiveCounts> Store::WriteMapArchive(const std::string& name,
                                                     const std::string& path) {
  auto map = GetMap(name);
  if (!map.ok()) return map.status();
  auto archive = Database::Open(path, /*create=*/true, /*read_only=*/false, 5000);
  if (!archive.ok()) return archive.status();
  Database* db = archive->get();
  // Written once and read back whole: no journal needed; the file is checksummed afterwards.
  if (auto s = db->Exec("PRAGMA journal_mode=OFF; PRAGMA synchronous=OFF"); !s.ok()) return s;
  if (auto s = MigrateSchema(db, 0, path); !s.ok()) return s;
  auto attached = Attached::Open(db, path_);
  if (!attached.ok()) return attached.status();
  // One read transaction over the store: every table from the same snapshot.
  if (auto s = db->Exec("BEGIN"); !s.ok()) return s;
  Bindings params;
  params.ints[kMap] = map->id;
  for (const TableCopy& t : Tables()) {
    if (auto s = Copy(db, t.table, t.export_where, {}, params); !s.ok()) {
      db->Exec("ROLLBACK").IgnoreError();
      return s;
    }
  }
  if (auto s = db->Exec("COMMIT"); !s.ok()) return s;
  ArchiveCounts counts;
  counts.schema_version = kSchemaVersion;
  auto visits = db->QueryInt("SELECT COUNT(*) FROM main.visits");
  auto keyframes = db->QueryInt("SELECT COUNT(*) FROM main.keyframes");
  if (!visits.ok()) return visits.status();
  if (!keyframes.ok()) return keyframes.status();
  counts.visits = *visits;
  counts.keyframes = *keyframes;
  return counts;
}

namespace {

// The tables whose ids an import renumbers (temp.renumber_<table>).
constexpr const char* kRenumbered[] = {
    "visits", "keyframes", "pose_edges", "pose_optimisations", "anchor_revisions", "annotations"};

// Ids an archive may keep (keep_ids, a move between shards): a shard's range is its number
// << 40, so 2^56 leaves room for 65,536 shards and keeps every counter far from 2^63 - 1.
constexpr int64_t kMaxKeptId = int64_t{1} << 56;

// References an imported row must resolve inside the archive (the others are optional: Ref).
struct Required {
  const char* table;
  const char* column;
  const char* parent;
};
constexpr Required kRequired[] = {
    {"keyframes", "visit_id", "visits"},
    {"keyframe_images", "keyframe_id", "keyframes"},
    {"keyframe_features", "keyframe_id", "keyframes"},
    {"keyframe_sightings", "keyframe_id", "keyframes"},
    {"pose_edges", "from_keyframe", "keyframes"},
    {"pose_edges", "to_keyframe", "keyframes"},
    {"anchor_revisions", "visit_id", "visits"},
    {"visit_places", "visit_id", "visits"},
    {"semantic_octrees", "visit_id", "visits"},
    {"semantic_octree_chunks", "visit_id", "visits"},
};

// INVALID_ARGUMENT naming the first required reference of the archive (opened on its own
// connection, so that the writer is not held meanwhile) that names a row it does not hold
// (issue 52: such a keyframe, renumbered, landed in another map's visit).
absl::Status CheckReferencesResolve(Database* archive) {
  for (const Required& r : kRequired) {
    // By value, not rowid: some tables are WITHOUT ROWID.
    auto stmt = archive->Prepare(absl::StrCat(
        "SELECT COALESCE(CAST(", r.column, " AS TEXT), 'NULL') FROM ", r.table, " WHERE ", r.column,
        " IS NULL OR ", r.column, " NOT IN (SELECT id FROM ", r.parent, ") LIMIT 1"));
    if (!stmt.ok()) return stmt.status();
    StatementScope s(*stmt);
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (*row) {
      return NotAnArchive(absl::StrCat("a row of its ", r.table, " names ", r.parent, " ",
                                       s->ColumnText(0), " (", r.column,
                                       "), which the archive does not hold"));
    }
  }
  return absl::OkStatus();
}

// A store's own id range on a shard of a cluster (Store::RaiseIdFloor): ids in (floor, ceiling).
struct OwnIds {
  int64_t floor = 0;
  int64_t ceiling = 0;
};

// nullopt when the store has no floor (not a shard).
absl::StatusOr<std::optional<OwnIds>> OwnIdRange(Database* db) {
  auto floor = IntSetting(db, "id_floor");
  if (!floor.ok()) return floor.status();
  if (*floor <= 0) return std::optional<OwnIds>();
  return std::optional<OwnIds>(OwnIds{*floor, *floor + (int64_t{1} << Store::kIdRangeBits)});
}

// The largest id of `table` the store has given out in its own range (kept in settings as
// "ids.<table>", so that none is given out again after its row is deleted).
std::string GivenOutKey(const char* table) { return absl::StrCat("ids.", table); }

absl::Status SetGivenOut(Database* db, const char* table, int64_t last) {
  auto mark = db->Prepare(
      "INSERT INTO settings (key, value) VALUES (?1, ?2) ON CONFLICT(key) DO UPDATE SET value = "
      "excluded.value WHERE CAST(value AS INTEGER) < CAST(excluded.value AS INTEGER)");
  if (!mark.ok()) return mark.status();
  StatementScope m(*mark);
  m->Bind(1, GivenOutKey(table)).Bind(2, std::to_string(last));
  return m->Run();
}

// Ids an archive keeps inside this store's own range (a map moving back to the shard that gave
// them out) count as given out: deleted later, they are not given out again.
absl::Status NoteKeptIds(Database* db, const char* table) {
  auto own = OwnIdRange(db);
  if (!own.ok()) return own.status();
  if (!*own) return absl::OkStatus();
  auto stmt = db->Prepare(
      absl::StrCat("SELECT COALESCE(MAX(id), 0) FROM src.", table, " WHERE id > ?1 AND id < ?2"));
  if (!stmt.ok()) return stmt.status();
  int64_t kept = 0;
  {
    StatementScope s(*stmt);
    s->Bind(1, (*own)->floor).Bind(2, (*own)->ceiling);
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (*row) kept = s->ColumnInt(0);
  }
  return kept > 0 ? SetGivenOut(db, table, kept) : absl::OkStatus();
}

// Fills temp.renumber_<table> for every renumbered table: kept ids map to themselves (after
// checking they are in range and free here), others to the next ids above every id the store
// has used (sqlite_sequence keeps deleted ones' too), in the archive's order.
absl::Status Renumber(Database* db, bool keep_ids) {
  for (const char* table : kRenumbered) {
    const std::string map = absl::StrCat("temp.renumber_", table);
    if (auto s = db->Exec(absl::StrCat("DROP TABLE IF EXISTS ", map, "; CREATE TABLE ", map,
                                       " (old INTEGER PRIMARY KEY, new INTEGER NOT NULL)"));
        !s.ok()) {
      return s;
    }
    if (keep_ids) {
      auto out_of_range = QueryIntBound(db,
                                        absl::StrCat("SELECT COALESCE((SELECT id FROM src.", table,
                                                     " WHERE id < 1 OR id > ?1 LIMIT 1), 0)"),
                                        kMaxKeptId);
      if (!out_of_range.ok()) return out_of_range.status();
      if (*out_of_range != 0) {
        return NotAnArchive(absl::StrCat("its ", table, " id ", *out_of_range,
                                         " is outside 1..2^56, which no lifemapd gives out"));
      }
      auto clash =
          QueryIntBound(db,
                        absl::StrCat("SELECT COALESCE((SELECT a.id FROM src.", table,
                                     " a JOIN main.", table, " m ON m.id = a.id LIMIT 1), 0)"),
                        0);
      if (!clash.ok()) return clash.status();
      if (*clash != 0) {
        return absl::FailedPreconditionError(absl::StrCat(
            "the map cannot keep its ids here: ", table, " id ", *clash,
            " is in use on this server; import it with new ids (its open visits then end)"));
      }
      if (auto s = db->Exec(absl::StrCat("INSERT INTO ", map, " SELECT id, id FROM src.", table));
          !s.ok()) {
        return s;
      }
      if (auto s = NoteKeptIds(db, table); !s.ok()) return s;
      continue;
    }
    // On a shard: the next ids of its own range (ReserveRowIds), not above a moved map's; else
    // above every id the store has used.
    auto rows = QueryIntBound(db, absl::StrCat("SELECT COUNT(*) FROM src.", table), 0);
    if (!rows.ok()) return rows.status();
    if (*rows == 0) continue;
    auto reserved = ReserveRowIds(db, table, *rows);
    if (!reserved.ok()) return reserved.status();
    auto used = *reserved ? absl::StatusOr<int64_t>(**reserved - 1)
                          : QueryIntBound(db,
                                          absl::StrCat("SELECT MAX(COALESCE((SELECT MAX(id) FROM "
                                                       "main.",
                                                       table,
                                                       "), 0), COALESCE((SELECT seq FROM "
                                                       "main.sqlite_sequence WHERE name = '",
                                                       table, "'), 0))"),
                                          0);
    if (!used.ok()) return used.status();
    auto fill = db->Prepare(absl::StrCat("INSERT INTO ", map,
                                         " SELECT id, ?1 + ROW_NUMBER() OVER (ORDER BY id) FROM "
                                         "src.",
                                         table));
    if (!fill.ok()) return fill.status();
    StatementScope f(*fill);
    f->Bind(1, *used);
    if (auto s = f->Run(); !s.ok()) return s;
  }
  return absl::OkStatus();
}

void DropRenumbering(Database* db) {
  for (const char* table : kRenumbered) {
    db->Exec(absl::StrCat("DROP TABLE IF EXISTS temp.renumber_", table)).IgnoreError();
  }
}

// Evidence text names visits and keyframes by id ("anchors visit 12 to visit 3: agrees with
// keyframe 40's match"). On import those numbers are rewritten to the rows' new ids, so that
// the reasons a person reads name what `visits list` shows (issue 53); a number the archive
// does not hold (a visit deleted before the export) is left as written.
using IdMap = std::map<int64_t, int64_t>;

std::string RenumberedText(const std::string& text, const IdMap& visits, const IdMap& keyframes) {
  std::string out;
  out.reserve(text.size());
  size_t i = 0;
  while (i < text.size()) {
    const bool word_start = i == 0 || !std::isalnum(static_cast<unsigned char>(text[i - 1]));
    const IdMap* ids = nullptr;
    size_t word = 0;
    for (const auto& [name, map] : {std::pair<std::string_view, const IdMap*>{"visit ", &visits},
                                    {"keyframe ", &keyframes}}) {
      if (word_start && text.compare(i, name.size(), name) == 0) {
        ids = map;
        word = name.size();
      }
    }
    if (ids != nullptr) {
      size_t end = i + word;
      while (end < text.size() && std::isdigit(static_cast<unsigned char>(text[end]))) ++end;
      int64_t old = 0;
      if (end > i + word && end - (i + word) <= 18 &&
          absl::SimpleAtoi(absl::string_view(text).substr(i + word, end - i - word), &old)) {
        if (auto it = ids->find(old); it != ids->end()) {
          absl::StrAppend(&out, text.substr(i, word), it->second);
          i = end;
          continue;
        }
      }
    }
    out += text[i++];
  }
  return out;
}

absl::StatusOr<IdMap> ReadRenumbering(Database* db, const char* table) {
  auto stmt = db->Prepare(absl::StrCat("SELECT old, new FROM temp.renumber_", table));
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  IdMap ids;
  for (;;) {
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (!*row) return ids;
    ids[s->ColumnInt(0)] = s->ColumnInt(1);
  }
}

// Rewrites the reasons of the imported map `map_id`'s pose edges and anchor revisions.
absl::Status RenumberReasons(Database* db, int64_t map_id) {
  auto visits = ReadRenumbering(db, "visits");
  if (!visits.ok()) return visits.status();
  auto keyframes = ReadRenumbering(db, "keyframes");
  if (!keyframes.ok()) return keyframes.status();
  const std::pair<const char*, const char*> tables[] = {
      {"pose_edges", "map_id = ?1"},
      {"anchor_revisions", "visit_id IN (SELECT id FROM main.visits WHERE map_id = ?1)"}};
  for (const auto& [table, where] : tables) {
    std::vector<std::pair<int64_t, std::string>> rewritten;
    {
      auto stmt =
          db->Prepare(absl::StrCat("SELECT id, reason FROM main.", table, " WHERE ", where));
      if (!stmt.ok()) return stmt.status();
      StatementScope s(*stmt);
      s->Bind(1, map_id);
      for (;;) {
        auto row = s->Step();
        if (!row.ok()) return row.status();
        if (!*row) break;
        const std::string reason = s->ColumnText(1);
        std::string text = RenumberedText(reason, *visits, *keyframes);
        if (text != reason) rewritten.emplace_back(s->ColumnInt(0), std::move(text));
      }
    }
    auto update =
        db->Prepare(absl::StrCat("UPDATE main.", table, " SET reason = ?1 WHERE id = ?2"));
    if (!update.ok()) return update.status();
    for (const auto& [id, text] : rewritten) {
      StatementScope u(*update);
      u->Bind(1, text).Bind(2, id);
      if (auto st = u->Run(); !st.ok()) return st;
    }
  }
  return absl::OkStatus();
}

}  // namespace

absl::Status Store::RaiseIdFloor(int64_t floor) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  Transaction tx(db);
  if (auto s = tx.Begin(); !s.ok()) return s;
  for (const char* table : kRenumbered) {
    // AUTOINCREMENT takes the larger of sqlite_sequence and the largest id, plus one.
    auto stmt = db->Prepare(
        "INSERT INTO sqlite_sequence (name, seq) SELECT ?1, ?2 WHERE NOT EXISTS (SELECT 1 FROM "
        "sqlite_sequence WHERE name = ?1)");
    if (!stmt.ok()) return stmt.status();
    {
      StatementScope s(*stmt);
      s->Bind(1, std::string(table));
      s->Bind(2, floor);
      if (auto st = s->Run(); !st.ok()) return st;
    }
    auto raise = db->Prepare("UPDATE sqlite_sequence SET seq = ?2 WHERE name = ?1 AND seq < ?2");
    if (!raise.ok()) return raise.status();
    StatementScope r(*raise);
    r->Bind(1, std::string(table));
    r->Bind(2, floor);
    if (auto st = r->Run(); !st.ok()) return st;
  }
  auto keep = db->Prepare(
      "INSERT INTO settings (key, value) VALUES ('id_floor', ?1) ON CONFLICT(key) DO UPDATE SET "
      "value = excluded.value WHERE CAST(value AS INTEGER) < CAST(excluded.value AS INTEGER)");
  if (!keep.ok()) return keep.status();
  {
    StatementScope k(*keep);
    k->Bind(1, std::to_string(floor));
    if (auto st = k->Run(); !st.ok()) return st;
  }
  return tx.Commit();
}

absl::StatusOr<std::optional<int64_t>> ReserveRowIds(Database* db, const char* table,
                                                     int64_t count) {
  auto own = OwnIdRange(db);
  if (!own.ok()) return own.status();
  if (!*own) return std::optional<int64_t>();
  const OwnIds range = **own;
  auto given = IntSetting(db, GivenOutKey(table));
  if (!given.ok()) return given.status();
  // Rows of the range the settings do not know of (written before the range was kept there).
  auto in_range = db->Prepare(
      absl::StrCat("SELECT COALESCE(MAX(id), 0) FROM main.", table, " WHERE id > ?1 AND id < ?2"));
  if (!in_range.ok()) return in_range.status();
  int64_t highest = 0;
  {
    StatementScope s(*in_range);
    s->Bind(1, range.floor).Bind(2, range.ceiling);
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (*row) highest = s->ColumnInt(0);
  }
  const int64_t first = std::max({range.floor, *given, highest}) + 1;
  if (count < 1 || first > range.ceiling - count) {
    return absl::ResourceExhaustedError(absl::StrCat(
        "this shard has given out every id of its range for ", table, " (", range.floor + 1, " to ",
        range.ceiling - 1, "): give it a shard number of its own that no shard has used"));
  }
  if (auto s = SetGivenOut(db, table, first + count - 1); !s.ok()) return s;
  return std::optional<int64_t>(first);
}

void BindRowId(Statement* s, int index, const std::optional<int64_t>& id) {
  if (id) {
    s->Bind(index, *id);
  } else {
    s->BindNull(index);
  }
}

absl::StatusOr<MapRecord> Store::ReadMapArchive(const std::string& path, const std::string& name,
                                                const MapCreator& creator, bool keep_ids,
                                                const std::function<bool()>& cancelled) {
  // Checked and, when older, migrated on its own connection first.
  {
    auto archive = Database::Open(path, /*create=*/false, /*read_only=*/false, 5000);
    if (!archive.ok()) return archive.status();
    Database* db = archive->get();
    auto check = db->Prepare("PRAGMA quick_check(1)");
    if (!check.ok()) return NotAnArchive(std::string(check.status().message()));
    {
      StatementScope s(*check);
      auto row = s->Step();
      if (!row.ok()) return NotAnArchive(std::string(row.status().message()));
      if (*row && s->ColumnText(0) != "ok") return NotAnArchive(s->ColumnText(0));
    }
    auto version = db->QueryInt("PRAGMA user_version");
    if (!version.ok()) return NotAnArchive(std::string(version.status().message()));
    if (*version > kSchemaVersion) {
      return absl::FailedPreconditionError(
          absl::StrCat("the archive is of schema ", *version, ", newer than this lifemapd's (",
                       kSchemaVersion, "): import it into a newer lifemapd"));
    }
    if (*version < 1) return NotAnArchive("no lifemap schema");
    if (auto s = MigrateSchema(db, *version, path); !s.ok()) return s;
    auto maps = db->QueryInt("SELECT COUNT(*) FROM maps");
    if (!maps.ok()) return maps.status();
    if (*maps != 1) return NotAnArchive(absl::StrCat("it holds ", *maps, " maps, not one"));
    auto dangling = db->QueryInt("SELECT COUNT(*) FROM pragma_foreign_key_check");
    if (!dangling.ok()) return dangling.status();
    if (*dangling > 0) {
      return NotAnArchive(absl::StrCat(*dangling, " rows reference rows it does not hold"));
    }
    // Its schema is the archive's own (a crafted one may declare no foreign keys).
    if (auto s = CheckReferencesResolve(db); !s.ok()) return s;
  }
  if (cancelled && cancelled()) return Cancelled();

  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  if (creator.max_maps > 0) {
    auto created =
        QueryIntBound(db, "SELECT COUNT(*) FROM maps WHERE created_by_key_id = ?1", creator.key_id);
    if (!created.ok()) return created.status();
    if (*created >= creator.max_maps) {
      return absl::ResourceExhaustedError(
          absl::StrCat("API key '", creator.key_name, "' may create at most ", creator.max_maps,
                       " maps (its max_maps limit) and ", *created, " it created still exist"));
    }
  }
  auto attached = Attached::Open(db, path);
  if (!attached.ok()) return attached.status();
  Transaction tx(db);
  if (auto s = tx.Begin(); !s.ok()) return s;
  {
    auto stmt = db->Prepare("SELECT COUNT(*) FROM main.maps WHERE name = ?1");
    if (!stmt.ok()) return stmt.status();
    StatementScope s(*stmt);
    s->Bind(1, name);
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (*row && s->ColumnInt(0) > 0) {
      return absl::AlreadyExistsError(
          absl::StrCat("map '", name, "' exists: import under another name (--rename NAME)"));
    }
  }

  Bindings params;
  params.name = name;
  // The map's model: the store's model of that name when it is the same file, else a new one.
  auto has_model = db->QueryInt("SELECT COUNT(*) FROM src.models");
  if (!has_model.ok()) return has_model.status();
  if (*has_model > 0) {
    auto stmt = db->Prepare(
        "SELECT m.id, m.data = a.data, a.name FROM src.models a LEFT JOIN main.models m "
        "ON m.name = a.name LIMIT 1");
    if (!stmt.ok()) return stmt.status();
    StatementScope s(*stmt);
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (*row && !s->ColumnIsNull(0)) {
      if (s->ColumnInt(1) == 0) {
        return absl::FailedPreconditionError(absl::StrCat(
            "the archive's map uses model '", s->ColumnText(2),
            "' and this server holds another model of that name: rename one (upload it under "
            "another name, activate that, delete the old one) and import again"));
      }
      params.ints[kModel] = s->ColumnInt(0);
    }
  }
  if (*has_model > 0 && !params.ints[kModel]) {
    auto columns = ColumnsOf(db, "models");
    if (!columns.ok()) return columns.status();
    std::vector<std::string> copied;
    for (const std::string& c : *columns) {
      if (c != "id") copied.push_back(c);
    }
    const std::string list = absl::StrJoin(copied, ", ");
    if (auto s = db->Exec(absl::StrCat("INSERT INTO main.models (", list, ") SELECT ", list,
                                       " FROM src.models LIMIT 1"));
        !s.ok()) {
      return s;
    }
    params.ints[kModel] = db->LastInsertRowId();
  }
  if (creator.key_id > 0) params.ints[kCreator] = creator.key_id;

  struct DropOnExit {
    Database* db;
    ~DropOnExit() { DropRenumbering(db); }
  } drop_renumbering{db};
  if (auto s = Renumber(db, keep_ids); !s.ok()) return s;
  {
    auto next = QueryIntBound(
        db,
        "SELECT MAX(COALESCE((SELECT MAX(id) FROM main.maps), 0), COALESCE((SELECT seq FROM "
        "main.sqlite_sequence WHERE name = 'maps'), 0)) + 1",
        0);
    if (!next.ok()) return next.status();
    params.ints[kMap] = *next;
  }
  // A cancelled call (the client gave up, its deadline passed) interrupts the statement that
  // runs (SQLite's progress handler, every ~10,000 steps) and rolls back: nothing is stored.
  struct Interrupt {
    Database* db;
    Interrupt(Database* d, const std::function<bool()>* cancelled) : db(d) {
      if (*cancelled) {
        sqlite3_progress_handler(
            db->raw(), 10000,
            +[](void* c) { return (*static_cast<const std::function<bool()>*>(c))() ? 1 : 0; },
            const_cast<std::function<bool()>*>(cancelled));
      }
    }
    ~Interrupt() { sqlite3_progress_handler(db->raw(), 0, nullptr, nullptr); }
  } interrupt(db, &cancelled);
  for (const TableCopy& t : Tables()) {
    if (!ImportsTable(t)) continue;
    if (cancelled && cancelled()) return Cancelled();
    if (auto s = Copy(db, t.table, t.import_where, t.import_columns, params); !s.ok()) {
      if (cancelled && cancelled()) return Cancelled();
      if (IsConstraintViolation(s)) {
        return NotAnArchive(absl::StrCat("its ", t.table, " do not fit: ", s.message()));
      }
      return s;
    }
  }
  // Evidence text names the new ids, and nothing streams into an imported visit: one open when
  // exported arrives ended, at its last keyframe's time. A moved map keeps its ids, and its
  // open visits stay open: their streams resume here.
  if (!keep_ids) {
    if (auto s = RenumberReasons(db, *params.ints[kMap]); !s.ok()) return s;
    auto stmt = db->Prepare(
        "UPDATE visits SET ended = 1, end_time_s = MAX(start_time_s, COALESCE((SELECT "
        "MAX(timestamp_s) FROM keyframes k WHERE k.visit_id = visits.id), start_time_s)) "
        "WHERE map_id = ?1 AND ended = 0");
    if (!stmt.ok()) return stmt.status();
    StatementScope s(*stmt);
    s->Bind(1, *params.ints[kMap]);
    if (auto st = s->Run(); !st.ok()) return st;
  }
  if (cancelled && cancelled()) return Cancelled();
  if (auto s = tx.Commit(); !s.ok()) return s;
  return impl_->GetMapLocked(db, name);
}

}  // namespace lifemap::store
