// Store: what the appearance index is built from (keyframe descriptors) and with (vocabularies).
#include <cstring>

#include "absl/strings/str_cat.h"
#include "server/store/store_impl.h"

namespace lifemap::store {

absl::Status Store::ForEachKeyframeDescriptors(
    int64_t map_id, const std::function<absl::Status(const KeyframeDescriptors&)>& fn) {
  absl::MutexLock lock(&impl_->read_mu);
  auto stmt = impl_->read_db->Prepare(
      "SELECT v.map_id, k.visit_id, k.id, k.timestamp_s, f.descriptor_bytes, f.descriptors "
      "FROM keyframe_features f JOIN keyframes k ON k.id = f.keyframe_id "
      "JOIN visits v ON v.id = k.visit_id WHERE ?1 = 0 OR v.map_id = ?1 ORDER BY k.id");
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, map_id);
  for (;;) {
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    KeyframeDescriptors k;
    k.map_id = s->ColumnInt(0);
    k.visit_id = s->ColumnInt(1);
    k.keyframe_id = s->ColumnInt(2);
    k.timestamp_s = s->ColumnDouble(3);
    const int64_t row_bytes = s->ColumnInt(4);
    const std::string blob = s->ColumnBlob(5);
    if (row_bytes > 0 && !blob.empty()) {
      if (blob.size() % static_cast<size_t>(row_bytes) != 0) {
        return absl::DataLossError(
            absl::StrCat("stored descriptors of keyframe ", k.keyframe_id, " are truncated"));
      }
      k.descriptors = cv::Mat(static_cast<int>(blob.size() / static_cast<size_t>(row_bytes)),
                              static_cast<int>(row_bytes), CV_8UC1);
      std::memcpy(k.descriptors.data, blob.data(), blob.size());
    }
    if (auto st = fn(k); !st.ok()) return st;
  }
  return absl::OkStatus();
}

absl::StatusOr<int64_t> Store::CountKeyframesWithFeatures() {
  absl::MutexLock lock(&impl_->read_mu);
  auto stmt = impl_->read_db->Prepare("SELECT COUNT(*) FROM keyframe_features");
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  auto row = s->Step();
  if (!row.ok()) return row.status();
  return *row ? s->ColumnInt(0) : 0;
}

absl::StatusOr<int64_t> Store::PutVocabulary(const VocabularyRecord& r) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  auto stmt = db->Prepare(
      "INSERT INTO appearance_vocabularies (created_time_s, source, training_keyframes, words, "
      "data) VALUES (?1, ?2, ?3, ?4, ?5)");
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, r.created_time_s).Bind(2, r.source).Bind(3, r.training_keyframes);
  s->Bind(4, r.words).BindBlob(5, r.data);
  if (auto st = s->Run(); !st.ok()) return st;
  return db->LastInsertRowId();
}

absl::StatusOr<std::optional<VocabularyRecord>> Store::LatestVocabulary() {
  absl::MutexLock lock(&impl_->read_mu);
  auto stmt = impl_->read_db->Prepare(
      "SELECT id, created_time_s, source, training_keyframes, words, data "
      "FROM appearance_vocabularies ORDER BY id DESC LIMIT 1");
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  auto row = s->Step();
  if (!row.ok()) return row.status();
  if (!*row) return std::nullopt;
  VocabularyRecord r;
  r.id = s->ColumnInt(0);
  r.created_time_s = s->ColumnDouble(1);
  r.source = s->ColumnText(2);
  r.training_keyframes = s->ColumnInt(3);
  r.words = s->ColumnInt(4);
  r.data = s->ColumnBlob(5);
  return r;
}

}  // namespace lifemap::store
