// Store: each visit's architecture (floor plan and descriptor, paper 004).
#include "absl/strings/str_cat.h"
#include "server/store/store_impl.h"

namespace lifemap::store {

absl::Status Store::PutVisitPlace(const VisitPlaceRecord& r) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  auto stmt = db->Prepare(
      "INSERT INTO visit_places (visit_id, keyframes, floor_plan, descriptor, updated_time_s) "
      "VALUES (?1, ?2, ?3, ?4, ?5) ON CONFLICT(visit_id) DO UPDATE SET "
      "keyframes = excluded.keyframes, floor_plan = excluded.floor_plan, "
      "descriptor = excluded.descriptor, updated_time_s = excluded.updated_time_s");
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, r.visit_id)
      .Bind(2, static_cast<int64_t>(r.keyframes))
      .Bind(3, r.floor_plan_json)
      .Bind(4, r.descriptor_json)
      .Bind(5, r.updated_time_s);
  if (auto st = s->Run(); !st.ok()) {
    // The only constraint that can fail is the visit's foreign key.
    if (IsConstraintViolation(st)) {
      return absl::NotFoundError(absl::StrCat("visit ", r.visit_id, " does not exist"));
    }
    return st;
  }
  return absl::OkStatus();
}

namespace {

constexpr char kVisitPlaceSelect[] =
    "SELECT p.visit_id, v.map_id, m.name, p.keyframes, p.floor_plan, p.descriptor, "
    "p.updated_time_s FROM visit_places p JOIN visits v ON v.id = p.visit_id "
    "JOIN maps m ON m.id = v.map_id ";

VisitPlaceRecord ReadVisitPlace(const Statement& s) {
  VisitPlaceRecord r;
  r.visit_id = s.ColumnInt(0);
  r.map_id = s.ColumnInt(1);
  r.map_name = s.ColumnText(2);
  r.keyframes = static_cast<int>(s.ColumnInt(3));
  r.floor_plan_json = s.ColumnText(4);
  r.descriptor_json = s.ColumnText(5);
  r.updated_time_s = s.ColumnDouble(6);
  return r;
}

}  // namespace

absl::StatusOr<std::vector<VisitPlaceRecord>> Store::ListVisitPlaces(const std::string& map_name) {
  absl::MutexLock lock(&impl_->read_mu);
  auto stmt = impl_->read_db->Prepare(
      absl::StrCat(kVisitPlaceSelect, "WHERE ?1 = '' OR m.name = ?1 ORDER BY p.visit_id"));
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, map_name);
  std::vector<VisitPlaceRecord> out;
  for (;;) {
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    out.push_back(ReadVisitPlace(*s));
  }
  return out;
}

absl::StatusOr<VisitPlaceRecord> Store::GetVisitPlace(int64_t visit_id) {
  absl::MutexLock lock(&impl_->read_mu);
  auto stmt = impl_->read_db->Prepare(absl::StrCat(kVisitPlaceSelect, "WHERE p.visit_id = ?1"));
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, visit_id);
  auto row = s->Step();
  if (!row.ok()) return row.status();
  if (!*row) {
    return absl::NotFoundError(absl::StrCat("visit ", visit_id, " has no stored floor plan"));
  }
  return ReadVisitPlace(*s);
}

}  // namespace lifemap::store
