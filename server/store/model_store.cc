// Store: random-forest models, each map's model and the server default.
#include <algorithm>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "server/store/store_impl.h"

namespace lifemap::store {
namespace {

constexpr char kDefaultModelKey[] = "default_model_id";

// Class names are stored one per line (the service rejects names with control characters);
// colours as decimal numbers separated by spaces.
std::vector<std::string> SplitLines(const std::string& s) {
  if (s.empty()) return {};
  return absl::StrSplit(s, '\n');
}

std::vector<uint32_t> ParseColors(const std::string& s) {
  std::vector<uint32_t> out;
  for (absl::string_view part : absl::StrSplit(s, ' ', absl::SkipEmpty())) {
    uint32_t v = 0;
    out.push_back(absl::SimpleAtoi(part, &v) ? v : 0);
  }
  return out;
}

constexpr char kModelSelect[] =
    "SELECT id, name, uploaded_time_s, size_bytes, class_names, class_colors, training_json, "
    "trees, nodes FROM models ";

ModelRecord ReadModel(const Statement& s) {
  ModelRecord m;
  m.id = s.ColumnInt(0);
  m.name = s.ColumnText(1);
  m.uploaded_time_s = s.ColumnDouble(2);
  m.size_bytes = s.ColumnInt(3);
  m.class_names = SplitLines(s.ColumnText(4));
  m.class_colors = ParseColors(s.ColumnText(5));
  m.training_json = s.ColumnText(6);
  m.trees = static_cast<int>(s.ColumnInt(7));
  m.nodes = s.ColumnInt(8);
  return m;
}

absl::StatusOr<int64_t> DefaultModelId(Database* db) { return IntSetting(db, kDefaultModelKey); }

// Fills is_default and active_maps.
absl::Status AddActivations(Database* db, ModelRecord* m) {
  auto def = DefaultModelId(db);
  if (!def.ok()) return def.status();
  m->is_default = *def == m->id;
  auto stmt = db->Prepare("SELECT name FROM maps WHERE model_id = ?1 ORDER BY name");
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, m->id);
  for (;;) {
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    m->active_maps.push_back(s->ColumnText(0));
  }
  return absl::OkStatus();
}

absl::StatusOr<ModelRecord> GetModelLocked(Database* db, const std::string& name) {
  auto stmt = db->Prepare(absl::StrCat(kModelSelect, "WHERE name = ?1"));
  if (!stmt.ok()) return stmt.status();
  ModelRecord m;
  {
    StatementScope s(*stmt);
    s->Bind(1, name);
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (!*row) {
      return absl::NotFoundError(
          absl::StrCat("model '", name, "' does not exist (lifemap models list)"));
    }
    m = ReadModel(*s);
  }
  if (auto st = AddActivations(db, &m); !st.ok()) return st;
  return m;
}

absl::StatusOr<std::string> ModelNameById(Database* db, int64_t id) {
  if (id == 0) return std::string();
  auto stmt = db->Prepare("SELECT name FROM models WHERE id = ?1");
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, id);
  auto row = s->Step();
  if (!row.ok()) return row.status();
  return *row ? s->ColumnText(0) : std::string();
}

}  // namespace

absl::StatusOr<ModelRecord> Store::InsertModel(const ModelRecord& record, const std::string& data) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  auto stmt = db->Prepare(
      "INSERT INTO models (name, uploaded_time_s, size_bytes, class_names, class_colors, "
      "training_json, trees, nodes, data) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9)");
  if (!stmt.ok()) return stmt.status();
  {
    StatementScope s(*stmt);
    s->Bind(1, record.name)
        .Bind(2, record.uploaded_time_s)
        .Bind(3, static_cast<int64_t>(data.size()))
        .Bind(4, absl::StrJoin(record.class_names, "\n"))
        .Bind(5, absl::StrJoin(record.class_colors, " "))
        .Bind(6, record.training_json)
        .Bind(7, static_cast<int64_t>(record.trees))
        .Bind(8, record.nodes)
        .BindBlob(9, data);
    if (auto st = s->Run(); !st.ok()) {
      if (IsConstraintViolation(st)) {
        return absl::AlreadyExistsError(
            absl::StrCat("model '", record.name,
                         "' already exists: upload under a new name (models are "
                         "immutable, so frames labelled with it stay reproducible)"));
      }
      return st;
    }
  }
  return GetModelLocked(db, record.name);
}

absl::StatusOr<std::vector<ModelRecord>> Store::ListModels() {
  absl::MutexLock lock(&impl_->read_mu);
  Database* db = impl_->read_db.get();
  auto stmt = db->Prepare(absl::StrCat(kModelSelect, "ORDER BY name"));
  if (!stmt.ok()) return stmt.status();
  std::vector<ModelRecord> models;
  {
    StatementScope s(*stmt);
    for (;;) {
      auto row = s->Step();
      if (!row.ok()) return row.status();
      if (!*row) break;
      models.push_back(ReadModel(*s));
    }
  }
  for (auto& m : models) {
    if (auto st = AddActivations(db, &m); !st.ok()) return st;
  }
  return models;
}

absl::StatusOr<ModelRecord> Store::GetModel(const std::string& name) {
  absl::MutexLock lock(&impl_->read_mu);
  return GetModelLocked(impl_->read_db.get(), name);
}

absl::StatusOr<std::string> Store::GetModelData(const std::string& name) {
  absl::MutexLock lock(&impl_->read_mu);
  auto stmt = impl_->read_db->Prepare("SELECT data FROM models WHERE name = ?1");
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, name);
  auto row = s->Step();
  if (!row.ok()) return row.status();
  if (!*row) return absl::NotFoundError(absl::StrCat("model '", name, "' does not exist"));
  return s->ColumnBlob(0);
}

absl::StatusOr<std::string> Store::ActivateModel(const std::string& map, const std::string& model) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  Transaction tx(db);
  if (auto s = tx.Begin(); !s.ok()) return s;
  int64_t model_id = 0;
  if (!model.empty()) {
    auto m = GetModelLocked(db, model);
    if (!m.ok()) return m.status();
    model_id = m->id;
  }
  std::string previous;
  if (map.empty()) {
    auto def = DefaultModelId(db);
    if (!def.ok()) return def.status();
    auto name = ModelNameById(db, *def);
    if (!name.ok()) return name.status();
    previous = *name;
    auto stmt = model_id == 0 ? db->Prepare("DELETE FROM settings WHERE key = ?1")
                              : db->Prepare(
                                    "INSERT INTO settings (key, value) VALUES (?1, ?2) "
                                    "ON CONFLICT(key) DO UPDATE SET value = excluded.value");
    if (!stmt.ok()) return stmt.status();
    StatementScope s(*stmt);
    s->Bind(1, std::string_view(kDefaultModelKey));
    if (model_id != 0) s->Bind(2, absl::StrCat(model_id));
    if (auto st = s->Run(); !st.ok()) return st;
  } else {
    auto m = impl_->GetMapLocked(db, map);
    if (!m.ok()) return m.status();
    auto current = db->Prepare("SELECT COALESCE(model_id, 0) FROM maps WHERE id = ?1");
    if (!current.ok()) return current.status();
    int64_t current_id = 0;
    {
      StatementScope s(*current);
      s->Bind(1, m->id);
      auto row = s->Step();
      if (!row.ok()) return row.status();
      if (*row) current_id = s->ColumnInt(0);
    }
    auto name = ModelNameById(db, current_id);
    if (!name.ok()) return name.status();
    previous = *name;
    auto stmt = db->Prepare("UPDATE maps SET model_id = ?2 WHERE id = ?1");
    if (!stmt.ok()) return stmt.status();
    StatementScope s(*stmt);
    s->Bind(1, m->id);
    if (model_id != 0) {
      s->Bind(2, model_id);
    } else {
      s->BindNull(2);
    }
    if (auto st = s->Run(); !st.ok()) return st;
  }
  if (auto s = tx.Commit(); !s.ok()) return s;
  return previous;
}

absl::StatusOr<std::string> Store::ActiveModelName(int64_t map_id) {
  absl::MutexLock lock(&impl_->read_mu);
  Database* db = impl_->read_db.get();
  int64_t id = 0;
  if (map_id != 0) {
    auto stmt = db->Prepare("SELECT COALESCE(model_id, 0) FROM maps WHERE id = ?1");
    if (!stmt.ok()) return stmt.status();
    StatementScope s(*stmt);
    s->Bind(1, map_id);
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (*row) id = s->ColumnInt(0);
  }
  if (id == 0) {
    auto def = DefaultModelId(db);
    if (!def.ok()) return def.status();
    id = *def;
  }
  return ModelNameById(db, id);
}

absl::Status Store::DeleteModel(const std::string& name) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  Transaction tx(db);
  if (auto s = tx.Begin(); !s.ok()) return s;
  auto m = GetModelLocked(db, name);
  if (!m.ok()) return m.status();
  if (m->is_default || !m->active_maps.empty()) {
    std::vector<std::string> where = m->active_maps;
    if (m->is_default) where.insert(where.begin(), "the server default");
    return absl::FailedPreconditionError(
        absl::StrCat("model '", name, "' is active (", absl::StrJoin(where, ", "),
                     "); deactivate it first: lifemap models activate --none [--map MAP]"));
  }
  auto stmt = db->Prepare("DELETE FROM models WHERE id = ?1");
  if (!stmt.ok()) return stmt.status();
  {
    StatementScope s(*stmt);
    s->Bind(1, m->id);
    if (auto st = s->Run(); !st.ok()) return st;
  }
  return tx.Commit();
}

}  // namespace lifemap::store
