// Store: annotations, classes given to regions of a map's frame (issue 38, paper 002's tool).
#include <cstring>

#include "absl/strings/str_cat.h"
#include "server/store/store_impl.h"

namespace lifemap::store {
namespace {

// Boxes as 6 doubles each (min xyz, max xyz) in the machine's byte order: little-endian on
// every platform lifemapd builds for (x86-64, arm64), as the other blobs of the store.
std::string PackBoxes(const std::vector<AnnotationBox>& boxes) {
  std::string bytes(boxes.size() * 6 * sizeof(double), '\0');
  char* out = bytes.data();
  for (const AnnotationBox& b : boxes) {
    std::memcpy(out, b.min, sizeof(b.min));
    std::memcpy(out + sizeof(b.min), b.max, sizeof(b.max));
    out += sizeof(b.min) + sizeof(b.max);
  }
  return bytes;
}

absl::StatusOr<std::vector<AnnotationBox>> UnpackBoxes(const std::string& bytes, int64_t id) {
  constexpr size_t kBoxBytes = 6 * sizeof(double);
  if (bytes.size() % kBoxBytes != 0) {
    return absl::DataLossError(absl::StrCat("annotation ", id, " has ", bytes.size(),
                                            " bytes of boxes, not a multiple of ", kBoxBytes));
  }
  std::vector<AnnotationBox> boxes(bytes.size() / kBoxBytes);
  const char* in = bytes.data();
  for (AnnotationBox& b : boxes) {
    std::memcpy(b.min, in, sizeof(b.min));
    std::memcpy(b.max, in + sizeof(b.min), sizeof(b.max));
    in += kBoxBytes;
  }
  return boxes;
}

}  // namespace

absl::StatusOr<AnnotationRecord> Store::InsertAnnotation(const AnnotationRecord& record) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  auto id = ReserveRowIds(db, "annotations");
  if (!id.ok()) return id.status();
  auto stmt = db->Prepare(
      "INSERT INTO annotations (map_id, class_name, boxes, author, created_time_s, id) "
      "VALUES (?1, ?2, ?3, ?4, ?5, ?6)");
  if (!stmt.ok()) return stmt.status();
  // Bound without a copy (SQLITE_STATIC): the bytes must outlive the statement's run.
  const std::string boxes = PackBoxes(record.boxes);
  StatementScope s(*stmt);
  s->Bind(1, record.map_id)
      .Bind(2, record.class_name)
      .BindBlob(3, boxes)
      .Bind(4, record.author)
      .Bind(5, record.created_time_s);
  BindRowId(&*s, 6, *id);
  if (auto st = s->Run(); !st.ok()) {
    if (IsConstraintViolation(st)) {
      return absl::NotFoundError(absl::StrCat("no map with id ", record.map_id));
    }
    return st;
  }
  AnnotationRecord out = record;
  out.id = db->LastInsertRowId();
  return out;
}

absl::StatusOr<std::vector<AnnotationRecord>> Store::ListAnnotations(int64_t map_id) {
  absl::MutexLock lock(&impl_->read_mu);
  auto stmt = impl_->read_db->Prepare(
      "SELECT id, map_id, class_name, boxes, author, created_time_s FROM annotations "
      "WHERE map_id = ?1 ORDER BY id");
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, map_id);
  std::vector<AnnotationRecord> out;
  while (true) {
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    AnnotationRecord r;
    r.id = s->ColumnInt(0);
    r.map_id = s->ColumnInt(1);
    r.class_name = s->ColumnText(2);
    auto boxes = UnpackBoxes(s->ColumnBlob(3), r.id);
    if (!boxes.ok()) return boxes.status();
    r.boxes = *std::move(boxes);
    r.author = s->ColumnText(4);
    r.created_time_s = s->ColumnDouble(5);
    out.push_back(std::move(r));
  }
  return out;
}

absl::Status Store::DeleteAnnotation(int64_t map_id, int64_t id) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  auto stmt = db->Prepare("DELETE FROM annotations WHERE map_id = ?1 AND id = ?2");
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, map_id).Bind(2, id);
  if (auto st = s->Run(); !st.ok()) return st;
  if (db->Changes() == 0) {
    return absl::NotFoundError(absl::StrCat("the map holds no annotation ", id));
  }
  return absl::OkStatus();
}

}  // namespace lifemap::store
