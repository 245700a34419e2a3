#include "server/store/store.h"

#include <signal.h>
#include <sqlite3.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <filesystem>
#include <iostream>
#include <limits>

#include <fstream>
#include <functional>
#include <thread>

#include <gtest/gtest.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"

#include "server/store/sqlite.h"
#include "tests/testing/test_util.h"

namespace lifemap::store {
namespace {

KeyframeRecord Keyframe(int64_t visit_id, double t, bool posed = true) {
  KeyframeRecord k;
  k.visit_id = visit_id;
  k.sequence = static_cast<uint64_t>(t * 10);
  k.timestamp_s = t;
  if (posed) {
    Pose p;
    p.translation = {t, 2 * t, 3 * t};
    k.T_world_camera = p;
  }
  k.intrinsics = {525, 525, 319.5, 239.5, 640, 480};
  k.depth_scale = 5000;
  k.depth = "depth-bytes";
  k.color = "color-bytes";
  return k;
}

class StoreTest : public ::testing::Test {
 protected:
  void SetUp() override {
    auto s = Store::Open(tmp_.File("lifemap.db"));
    ASSERT_TRUE(s.ok()) << s.status();
    store_ = *std::move(s);
  }
  testing::TempDir tmp_;
  std::unique_ptr<Store> store_;
};

TEST_F(StoreTest, CreatesListsRenamesAndDeletesMaps) {
  ASSERT_TRUE(store_->CreateMap("office", "desk area", 100.0).ok());
  ASSERT_TRUE(store_->CreateMap("lab", "", 101.0).ok());
  EXPECT_TRUE(absl::IsAlreadyExists(store_->CreateMap("office", "", 1.0).status()));
  auto maps = store_->ListMaps();
  ASSERT_TRUE(maps.ok());
  ASSERT_EQ(maps->size(), 2u);
  EXPECT_EQ((*maps)[0].name, "lab");  // by name
  auto renamed = store_->RenameMap("office", "office-2");
  ASSERT_TRUE(renamed.ok());
  EXPECT_EQ(renamed->description, "desk area");
  EXPECT_TRUE(absl::IsNotFound(store_->GetMap("office").status()));
  EXPECT_TRUE(absl::IsAlreadyExists(store_->RenameMap("lab", "office-2").status()));
  EXPECT_TRUE(absl::IsNotFound(store_->RenameMap("nope", "x").status()));
  ASSERT_TRUE(store_->DeleteMap("lab").ok());
  EXPECT_TRUE(absl::IsNotFound(store_->DeleteMap("lab").status()));
}

TEST_F(StoreTest, KeyframesRoundTripWithPosesAndImages) {
  ASSERT_TRUE(store_->CreateMap("m", "", 1.0).ok());
  auto visit = store_->StartVisit("m", "robot-1", "morning", 50.0);
  ASSERT_TRUE(visit.ok());
  std::vector<KeyframeRecord> batch = {Keyframe(visit->id, 2.0), Keyframe(visit->id, 1.0, false),
                                       Keyframe(visit->id, 3.0)};
  batch[2].pose_source = StoredPoseSource::kEstimated;
  ASSERT_TRUE(store_->InsertKeyframes(&batch, {{visit->id, 17}}).ok());
  EXPECT_GT(batch[0].id, 0);
  EXPECT_GT(batch[1].id, batch[0].id);

  auto map = store_->GetMap("m");
  ASSERT_TRUE(map.ok());
  EXPECT_EQ(map->keyframe_count, 3);
  EXPECT_EQ(map->visit_count, 1);
  auto list = store_->ListKeyframes(map->id, 0);
  ASSERT_TRUE(list.ok());
  ASSERT_EQ(list->size(), 3u);
  EXPECT_DOUBLE_EQ((*list)[0].timestamp_s, 1.0) << "time order";
  EXPECT_FALSE((*list)[0].T_world_camera.has_value());
  EXPECT_EQ((*list)[0].pose_source, StoredPoseSource::kNone);
  EXPECT_EQ((*list)[1].pose_source, StoredPoseSource::kClient);
  EXPECT_EQ((*list)[2].pose_source, StoredPoseSource::kEstimated) << "the server's estimate";
  EXPECT_TRUE((*list)[0].depth.empty()) << "listing carries no images";

  auto k = store_->GetKeyframe(map->id, batch[0].id);
  ASSERT_TRUE(k.ok());
  EXPECT_EQ(k->depth, "depth-bytes");
  EXPECT_EQ(k->color, "color-bytes");
  ASSERT_TRUE(k->T_world_camera.has_value());
  EXPECT_DOUBLE_EQ(k->T_world_camera->translation.z(), 6.0);

  auto v = store_->GetVisit(visit->id);
  ASSERT_TRUE(v.ok());
  EXPECT_EQ(v->frame_count, 17);
  EXPECT_EQ(v->keyframe_count, 3);
  // Issue 53: the data's own time (its keyframes' capture times) beside the server's.
  EXPECT_DOUBLE_EQ(v->start_time_s, 50.0);
  EXPECT_DOUBLE_EQ(v->data_start_time_s, 1.0);
  EXPECT_DOUBLE_EQ(v->data_end_time_s, 3.0);
  auto listed = store_->ListVisits("m");
  ASSERT_TRUE(listed.ok());
  ASSERT_EQ(listed->size(), 1u);
  EXPECT_DOUBLE_EQ((*listed)[0].data_start_time_s, 1.0);
  auto empty = store_->StartVisit("m", "robot-1", "no keyframes yet", 60.0);
  ASSERT_TRUE(empty.ok());
  EXPECT_EQ(store_->GetVisit(empty->id)->data_start_time_s, 0.0) << "none stored: 0";
  auto last = store_->LastKeyframe(visit->id);
  ASSERT_TRUE(last.ok() && last->has_value());
  EXPECT_DOUBLE_EQ((*last)->timestamp_s, 3.0);
}

// Issue 52: a frame resent after its reply was lost (same visit, sequence and timestamp) is
// stored once; the resend gets the stored keyframe's id.
TEST_F(StoreTest, AResentKeyframeIsStoredOnceAndGetsTheStoredId) {
  ASSERT_TRUE(store_->CreateMap("m", "", 1.0).ok());
  auto visit = store_->StartVisit("m", "", "", 1.0);
  ASSERT_TRUE(visit.ok());
  std::vector<KeyframeRecord> first = {Keyframe(visit->id, 1.0), Keyframe(visit->id, 2.0)};
  ASSERT_TRUE(store_->InsertKeyframes(&first, {}).ok());
  EXPECT_FALSE(first[0].resent);
  KeyframeRecord other_sequence = Keyframe(visit->id, 2.0);
  other_sequence.sequence += 1;  // same time, another frame: a keyframe of its own
  std::vector<KeyframeRecord> again = {Keyframe(visit->id, 2.0), other_sequence,
                                       Keyframe(visit->id, 3.0)};
  ASSERT_TRUE(store_->InsertKeyframes(&again, {}).ok());
  EXPECT_TRUE(again[0].resent);
  EXPECT_EQ(again[0].id, first[1].id);
  EXPECT_FALSE(again[1].resent);
  EXPECT_FALSE(again[2].resent);
  EXPECT_EQ(store_->GetVisit(visit->id)->keyframe_count, 4);
  EXPECT_EQ(store_->FindKeyframe(visit->id, first[1].sequence, 2.0).value(), first[1].id);
  EXPECT_FALSE(store_->FindKeyframe(visit->id, 999, 2.0).value().has_value());
}

TEST_F(StoreTest, KeyframeOfDeletedVisitIsNotFoundAndWritesNothing) {
  ASSERT_TRUE(store_->CreateMap("m", "", 1.0).ok());
  auto visit = store_->StartVisit("m", "", "", 1.0);
  ASSERT_TRUE(visit.ok());
  std::vector<KeyframeRecord> batch = {Keyframe(visit->id, 1.0), Keyframe(visit->id + 99, 2.0)};
  EXPECT_TRUE(absl::IsNotFound(store_->InsertKeyframes(&batch, {})));
  auto map = store_->GetMap("m");
  EXPECT_EQ(map->keyframe_count, 0) << "the transaction rolled back whole";
}

TEST_F(StoreTest, EndedVisitTakesNoMoreKeyframes) {
  ASSERT_TRUE(store_->CreateMap("m", "", 1.0).ok());
  auto visit = store_->StartVisit("m", "", "", 1.0);
  ASSERT_TRUE(store_->EndVisit(visit->id, 2.0, {visit->id, 0, 0}).ok());
  std::vector<KeyframeRecord> batch = {Keyframe(visit->id, 3.0)};
  EXPECT_TRUE(absl::IsFailedPrecondition(store_->InsertKeyframes(&batch, {})));
}

TEST_F(StoreTest, DeletingAMapCascadesToVisitsAndKeyframes) {
  ASSERT_TRUE(store_->CreateMap("m", "", 1.0).ok());
  auto visit = store_->StartVisit("m", "", "", 1.0);
  std::vector<KeyframeRecord> batch = {Keyframe(visit->id, 1.0)};
  ASSERT_TRUE(store_->InsertKeyframes(&batch, {}).ok());
  auto deleted = store_->DeleteMap("m");
  ASSERT_TRUE(deleted.ok());
  EXPECT_EQ(deleted->first, 1);
  EXPECT_EQ(deleted->second, 1);
  auto stats = store_->Stats();
  EXPECT_EQ(stats->keyframes, 0);
  EXPECT_EQ(stats->visits, 0);
  auto problems = store_->CheckIntegrity();
  ASSERT_TRUE(problems.ok());
  EXPECT_TRUE(problems->empty());
}

TEST_F(StoreTest, KeyframesAreThinnedOnlyFromEndedVisitsAndOnlyTheirOwn) {
  ASSERT_TRUE(store_->CreateMap("m", "", 1.0).ok());
  auto visit = store_->StartVisit("m", "", "", 1.0);
  auto other = store_->StartVisit("m", "", "", 1.5);
  std::vector<KeyframeRecord> batch = {Keyframe(visit->id, 1.0), Keyframe(visit->id, 2.0),
                                       Keyframe(visit->id, 3.0), Keyframe(other->id, 4.0)};
  ASSERT_TRUE(store_->InsertKeyframes(&batch, {}).ok());
  auto map = store_->GetMap("m");
  auto before = store_->GetMapStorage(map->id);
  ASSERT_TRUE(before.ok()) << before.status();
  EXPECT_EQ(before->keyframes, 4);
  EXPECT_EQ(before->image_bytes, 4 * (11 + 11));  // "depth-bytes", "color-bytes"

  // Open: refused, saying so.
  auto open = store_->DeleteKeyframes(visit->id, {batch[1].id});
  EXPECT_TRUE(absl::IsFailedPrecondition(open.status())) << open.status();
  EXPECT_NE(open.status().message().find("still open"), std::string::npos);
  ASSERT_TRUE(store_->EndVisit(visit->id, 5.0, {visit->id, 3, 0}).ok());
  // A keyframe of another visit among them: nothing is deleted.
  auto mixed = store_->DeleteKeyframes(visit->id, {batch[1].id, batch[3].id});
  EXPECT_TRUE(absl::IsNotFound(mixed.status())) << mixed.status();
  EXPECT_EQ(store_->ListKeyframes(map->id, visit->id)->size(), 3u);
  EXPECT_TRUE(absl::IsNotFound(store_->DeleteKeyframes(999, {batch[1].id}).status()));

  auto freed = store_->DeleteKeyframes(visit->id, {batch[1].id, batch[2].id});
  ASSERT_TRUE(freed.ok()) << freed.status();
  EXPECT_EQ(*freed, 2 * (11 + 11));
  auto left = store_->ListKeyframes(map->id, visit->id);
  ASSERT_EQ(left->size(), 1u);
  EXPECT_EQ((*left)[0].id, batch[0].id);
  EXPECT_TRUE(absl::IsNotFound(store_->GetKeyframe(map->id, batch[1].id).status()));
  auto after = store_->GetMapStorage(map->id);
  EXPECT_EQ(after->keyframes, 2);
  EXPECT_EQ(after->image_bytes, before->image_bytes - *freed);
  EXPECT_TRUE(store_->CheckIntegrity()->empty());
}

TEST_F(StoreTest, SightingsSayWhichVisitsRecognisedAKeyframeAndGoWithIt) {
  ASSERT_TRUE(store_->CreateMap("m", "", 1.0).ok());
  auto first = store_->StartVisit("m", "", "", 1.0);
  std::vector<KeyframeRecord> old = {Keyframe(first->id, 1.0), Keyframe(first->id, 2.0)};
  ASSERT_TRUE(store_->InsertKeyframes(&old, {}).ok());
  ASSERT_TRUE(store_->EndVisit(first->id, 3.0, {first->id, 2, 0}).ok());
  auto later = store_->StartVisit("m", "", "", 4.0);
  std::vector<KeyframeRecord> batch = {Keyframe(later->id, 5.0), Keyframe(later->id, 6.0)};
  batch[0].sighted_keyframes = {old[0].id, 999999};  // one that does not exist: skipped
  batch[1].sighted_keyframes = {old[0].id};          // the same visit twice: once
  ASSERT_TRUE(store_->InsertKeyframes(&batch, {}).ok());
  auto map = store_->GetMap("m");
  auto seen = store_->ListSightings(map->id);
  ASSERT_TRUE(seen.ok()) << seen.status();
  ASSERT_EQ(seen->size(), 1u);
  EXPECT_EQ(seen->at(old[0].id), std::vector<int64_t>{later->id});
  ASSERT_TRUE(store_->DeleteKeyframes(first->id, {old[0].id}).ok());
  EXPECT_TRUE(store_->ListSightings(map->id)->empty());
}

// Retention deletes each visit's keyframes in one transaction: a kill at any moment leaves every
// visit whole or thinned, the file passes its integrity check and every kept keyframe reads.
// Issue 37: a visit deleted with all that hangs on it, in one transaction; an open visit, one
// another visit is anchored to, and a map's first while tracked visits stand in its frame are
// refused, saying why.
TEST_F(StoreTest, DeleteVisitRemovesItWholeAndRefusesVisitsOthersStandOn) {
  ASSERT_TRUE(store_->CreateMap("lab", "", 1.0).ok());
  std::vector<int64_t> visits;
  for (int v = 0; v < 3; ++v) {
    auto visit = store_->StartVisit("lab", "", "", 1.0 + v);
    std::vector<KeyframeRecord> batch;
    for (int k = 0; k < 4; ++k) batch.push_back(Keyframe(visit->id, 10.0 * v + k));
    ASSERT_TRUE(store_->InsertKeyframes(&batch, {}).ok());
    visits.push_back(visit->id);
  }
  auto open = store_->DeleteVisit(visits[1]);
  EXPECT_EQ(open.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_NE(open.status().message().find("lifemap visits end"), std::string::npos);
  for (const int64_t v : visits) ASSERT_TRUE(store_->EndVisit(v, 50.0, {v, 4, 0}).ok());
  EXPECT_EQ(store_->DeleteVisit(9999).status().code(), absl::StatusCode::kNotFound);

  auto deleted = store_->DeleteVisit(visits[1]);
  ASSERT_TRUE(deleted.ok()) << deleted.status();
  EXPECT_EQ(deleted->map_name, "lab");
  EXPECT_EQ(deleted->keyframe_ids.size(), 4u);
  EXPECT_EQ(store_->GetVisit(visits[1]).status().code(), absl::StatusCode::kNotFound);
  const auto left = *store_->ListKeyframes(deleted->map_id, 0);
  EXPECT_EQ(left.size(), 8u);
  for (const auto& k : left) EXPECT_NE(k.visit_id, visits[1]);
  auto problems = store_->CheckIntegrity();
  ASSERT_TRUE(problems.ok());
  EXPECT_TRUE(problems->empty()) << problems->front();

  // A visit anchored to the third: the third is refused, naming it.
  sqlite3* db = nullptr;
  ASSERT_EQ(sqlite3_open(tmp_.File("lifemap.db").c_str(), &db), SQLITE_OK);
  const std::string anchor = "UPDATE visits SET anchor_visit_id = " + std::to_string(visits[2]) +
                             " WHERE id = " + std::to_string(visits[0]);
  ASSERT_EQ(sqlite3_exec(db, anchor.c_str(), nullptr, nullptr, nullptr), SQLITE_OK);
  sqlite3_close(db);
  auto refused = store_->DeleteVisit(visits[2]);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_NE(refused.status().message().find("anchored to visit"), std::string::npos)
      << refused.status();
  EXPECT_EQ(store_->ListKeyframes(deleted->map_id, 0)->size(), 8u) << "nothing deleted";
  // The third tracked by the server: the map's first visit, whose frame it stands in, is kept.
  ASSERT_EQ(sqlite3_open(tmp_.File("lifemap.db").c_str(), &db), SQLITE_OK);
  const std::string tracked =
      "UPDATE keyframes SET odom_tx = 0 WHERE visit_id = " + std::to_string(visits[2]);
  ASSERT_EQ(sqlite3_exec(db, tracked.c_str(), nullptr, nullptr, nullptr), SQLITE_OK);
  sqlite3_close(db);
  refused = store_->DeleteVisit(visits[0]);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_NE(refused.status().message().find("first visit"), std::string::npos) << refused.status();
}

// Issue 37: a map copied whole through an archive file into a store that has used other ids
// (and deleted some): every keyframe, visit and reference arrives renumbered, nothing of another
// map is touched, and a name in use, a second map in the file or a newer schema is refused.
TEST_F(StoreTest, MapArchivesCarryAMapWholeIntoAStoreWithOtherIds) {
  ASSERT_TRUE(store_->CreateMap("lab", "the lab", 1.0).ok());
  std::vector<int64_t> visits;
  for (int v = 0; v < 2; ++v) {
    auto visit = store_->StartVisit("lab", "bot", "v" + std::to_string(v), 10.0 + v);
    ASSERT_TRUE(visit.ok());
    std::vector<KeyframeRecord> batch;
    for (int k = 0; k < 5; ++k) batch.push_back(Keyframe(visit->id, 10.0 * v + k));
    ASSERT_TRUE(store_->InsertKeyframes(&batch, {}).ok());
    ASSERT_TRUE(store_->EndVisit(visit->id, 20.0 + v, {visit->id, 5, 0}).ok());
    visits.push_back(visit->id);
  }
  const auto keyframes = *store_->ListKeyframes(store_->GetMap("lab")->id, 0);
  // The second visit anchored to the first, the evidence naming both visits and keyframes.
  PoseEdgeRecord edge;
  edge.map_id = store_->GetMap("lab")->id;
  edge.kind = StoredEdgeKind::kAnchor;
  edge.from_keyframe = keyframes[0].id;
  edge.to_keyframe = keyframes[5].id;
  edge.accepted = true;
  const auto evidence = [](int64_t to, int64_t from, int64_t kf, int64_t other_kf) {
    return absl::StrCat("anchors visit ", from, " to visit ", to, ": keyframe ", kf,
                        " -> keyframe ", other_kf,
                        ", subvisit 3, visit 999999 (gone), visits 2,\n"
                        "Küche ✓ visit ",
                        from, "\tend");
  };
  edge.reason = evidence(visits[0], visits[1], keyframes[5].id, keyframes[0].id);
  VisitAnchor anchor;
  anchor.to_visit_id = visits[0];
  ASSERT_TRUE(store_->AnchorVisit(visits[1], edge, &anchor).ok());
  const std::string archive = tmp_.File("lab.archive");
  auto counts = store_->WriteMapArchive("lab", archive);
  ASSERT_TRUE(counts.ok()) << counts.status();
  EXPECT_EQ(counts->visits, 2);
  EXPECT_EQ(counts->keyframes, 10);
  EXPECT_EQ(store_->WriteMapArchive("nowhere", tmp_.File("x")).status().code(),
            absl::StatusCode::kNotFound);

  // Another store whose ids have moved on: maps, visits and keyframes made and deleted.
  auto other = Store::Open(tmp_.File("other.db"));
  ASSERT_TRUE(other.ok());
  ASSERT_TRUE((*other)->CreateMap("hall", "", 1.0).ok());
  ASSERT_TRUE((*other)->CreateMap("gone", "", 1.0).ok());
  for (const char* map : {"hall", "gone"}) {
    auto visit = (*other)->StartVisit(map, "", "", 1.0);
    std::vector<KeyframeRecord> batch;
    for (int k = 0; k < 7; ++k) batch.push_back(Keyframe(visit->id, 1.0 + k));
    ASSERT_TRUE((*other)->InsertKeyframes(&batch, {}).ok());
  }
  ASSERT_TRUE((*other)->DeleteMap("gone").ok());
  const auto hall_before = *(*other)->ListKeyframes((*other)->GetMap("hall")->id, 0);

  auto copy = (*other)->ReadMapArchive(archive, "lab", {});
  ASSERT_TRUE(copy.ok()) << copy.status();
  EXPECT_EQ(copy->description, "the lab");
  const auto copied = *(*other)->ListKeyframes(copy->id, 0);
  ASSERT_EQ(copied.size(), keyframes.size());
  for (size_t i = 0; i < copied.size(); ++i) {
    EXPECT_GT(copied[i].id, 14) << "ids above every id the store used, deleted ones too";
    EXPECT_EQ(copied[i].timestamp_s, keyframes[i].timestamp_s);
    ASSERT_TRUE(copied[i].T_world_camera.has_value());
    EXPECT_EQ(copied[i].T_world_camera->translation, keyframes[i].T_world_camera->translation);
    auto read = (*other)->GetKeyframe(copy->id, copied[i].id);
    ASSERT_TRUE(read.ok()) << read.status();
    EXPECT_EQ(read->depth, "depth-bytes");
    auto visit = (*other)->GetVisit(copied[i].visit_id);
    ASSERT_TRUE(visit.ok());
    EXPECT_EQ(visit->map_id, copy->id) << "a keyframe's visit is of the copy";
  }
  EXPECT_EQ((*other)->ListKeyframes((*other)->GetMap("hall")->id, 0)->size(), hall_before.size());
  // The anchor's evidence names the copy's visits and keyframes (issue 53), nothing else.
  const int64_t copied_first = copied[0].visit_id, copied_second = copied[5].visit_id;
  const std::string renamed = evidence(copied_first, copied_second, copied[5].id, copied[0].id);
  auto copied_edges = (*other)->ListPoseEdges(copy->id, copied_second);
  ASSERT_TRUE(copied_edges.ok()) << copied_edges.status();
  ASSERT_EQ(copied_edges->size(), 1u);
  EXPECT_EQ((*copied_edges)[0].reason, renamed);
  auto revisions = (*other)->ListAnchorRevisions(copied_second);
  ASSERT_TRUE(revisions.ok()) << revisions.status();
  ASSERT_EQ(revisions->size(), 1u);
  EXPECT_EQ((*revisions)[0].reason, renamed);
  auto problems = (*other)->CheckIntegrity();
  ASSERT_TRUE(problems.ok());
  EXPECT_TRUE(problems->empty()) << problems->front();

  // Refused, leaving nothing: the name in use; a file of another schema or with two maps.
  EXPECT_EQ((*other)->ReadMapArchive(archive, "lab", {}).status().code(),
            absl::StatusCode::kAlreadyExists);
  const std::string newer = tmp_.File("newer.archive");
  std::filesystem::copy_file(archive, newer);
  sqlite3* db = nullptr;
  ASSERT_EQ(sqlite3_open(newer.c_str(), &db), SQLITE_OK);
  ASSERT_EQ(sqlite3_exec(db, "PRAGMA user_version = 99", nullptr, nullptr, nullptr), SQLITE_OK);
  sqlite3_close(db);
  EXPECT_EQ((*other)->ReadMapArchive(newer, "newer", {}).status().code(),
            absl::StatusCode::kFailedPrecondition);
  const std::string two = tmp_.File("two.archive");
  std::filesystem::copy_file(archive, two);
  ASSERT_EQ(sqlite3_open(two.c_str(), &db), SQLITE_OK);
  ASSERT_EQ(sqlite3_exec(db, "INSERT INTO maps (name, created_time_s) VALUES ('x', 1)", nullptr,
                         nullptr, nullptr),
            SQLITE_OK);
  sqlite3_close(db);
  const auto refused = (*other)->ReadMapArchive(two, "two", {});
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument) << refused.status();
  EXPECT_EQ((*other)->ListMaps()->size(), 2u) << "hall and lab only";
}

// Issue 52, items 3, 4, 6: an operator's archive is untrusted. Ids near 2^63 - 1 are renumbered
// densely (they stopped every new visit of the whole store); a keyframe naming a visit the
// archive does not hold is refused (renumbered, it landed in another map's visit); a cancelled
// import stores nothing.
TEST_F(StoreTest, CraftedArchivesCannotExhaustIdsWriteIntoAnotherMapOrOutliveACancel) {
  ASSERT_TRUE(store_->CreateMap("lab", "", 1.0).ok());
  auto visit = store_->StartVisit("lab", "bot", "", 10.0);
  ASSERT_TRUE(visit.ok());
  std::vector<KeyframeRecord> batch = {Keyframe(visit->id, 10.0), Keyframe(visit->id, 11.0)};
  ASSERT_TRUE(store_->InsertKeyframes(&batch, {}).ok());
  ASSERT_TRUE(store_->EndVisit(visit->id, 12.0, {visit->id, 2, 0}).ok());
  const std::string archive = tmp_.File("lab.archive");
  ASSERT_TRUE(store_->WriteMapArchive("lab", archive).ok());
  const auto edit = [&](const std::string& name, const std::string& sql) {
    const std::string path = tmp_.File(name);
    std::filesystem::copy_file(archive, path);
    sqlite3* db = nullptr;
    EXPECT_EQ(sqlite3_open(path.c_str(), &db), SQLITE_OK);
    EXPECT_EQ(sqlite3_exec(db, sql.c_str(), nullptr, nullptr, nullptr), SQLITE_OK)
        << sqlite3_errmsg(db);
    sqlite3_close(db);
    return path;
  };
  auto target = Store::Open(tmp_.File("target.db"));
  ASSERT_TRUE(target.ok());
  ASSERT_TRUE((*target)->CreateMap("other", "", 1.0).ok());
  auto others = (*target)->StartVisit("other", "bot", "", 1.0);
  ASSERT_TRUE(others.ok());

  // 3. Ids at the top of the range: imported with small ids; new visits still start after it.
  const std::string huge = edit("huge.archive",
                                "PRAGMA foreign_keys = OFF;"
                                "UPDATE visits SET id = 9223372036854775800;"
                                "UPDATE keyframes SET visit_id = 9223372036854775800;"
                                "UPDATE keyframe_sightings SET visit_id = 9223372036854775800;"
                                "UPDATE keyframe_images SET keyframe_id = 9223372036854775806 "
                                "WHERE keyframe_id = (SELECT MAX(id) FROM keyframes);"
                                "UPDATE keyframe_features SET keyframe_id = 9223372036854775806 "
                                "WHERE keyframe_id = (SELECT MAX(id) FROM keyframes);"
                                "UPDATE keyframe_sightings SET keyframe_id = 9223372036854775806 "
                                "WHERE keyframe_id = (SELECT MAX(id) FROM keyframes);"
                                "UPDATE keyframes SET id = 9223372036854775806 WHERE id = "
                                "(SELECT MAX(id) FROM keyframes);");
  auto imported = (*target)->ReadMapArchive(huge, "huge", {});
  ASSERT_TRUE(imported.ok()) << imported.status();
  const auto copied = *(*target)->ListKeyframes(imported->id, 0);
  ASSERT_EQ(copied.size(), 2u);
  for (const auto& k : copied) EXPECT_LT(k.id, 100) << "renumbered densely";
  EXPECT_TRUE((*target)->StartVisit("other", "bot", "", 20.0).ok()) << "counters not exhausted";
  // ... and kept ids (a move between shards) must lie in 1..2^56.
  auto kept = (*target)->ReadMapArchive(huge, "huge-kept", {}, /*keep_ids=*/true);
  EXPECT_EQ(kept.status().code(), absl::StatusCode::kInvalidArgument) << kept.status();
  EXPECT_NE(kept.status().message().find("outside 1..2^56"), std::string::npos) << kept.status();

  // 4. A keyframe whose visit is not in the archive: refused, naming the row; no map gains it.
  // Both with the schema's foreign keys and with a schema edited to declare none (the
  // archive's own file says what it declares).
  const std::string foreign = edit(
      "foreign.archive",
      "PRAGMA foreign_keys = OFF; UPDATE keyframes SET visit_id = (SELECT MAX(id) FROM visits) "
      "+ 1 WHERE id = (SELECT MIN(id) FROM keyframes);");
  const size_t other_before = (*target)->ListKeyframes((*target)->GetMap("other")->id, 0)->size();
  auto refused = (*target)->ReadMapArchive(foreign, "foreign", {});
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument) << refused.status();
  EXPECT_NE(refused.status().message().find("does not hold"), std::string::npos)
      << refused.status();
  EXPECT_FALSE((*target)->GetMap("foreign").ok());
  const std::string no_keys = edit(
      "no-keys.archive",
      "PRAGMA foreign_keys = OFF; PRAGMA writable_schema = ON;"
      "UPDATE sqlite_schema SET sql = replace(sql, 'REFERENCES visits(id) ON DELETE CASCADE', '')"
      " WHERE name = 'keyframes';"
      "UPDATE keyframes SET visit_id = (SELECT MAX(id) FROM visits) + 1 WHERE id = "
      "(SELECT MIN(id) FROM keyframes);");
  auto undeclared = (*target)->ReadMapArchive(no_keys, "no-keys", {});
  EXPECT_EQ(undeclared.status().code(), absl::StatusCode::kInvalidArgument) << undeclared.status();
  EXPECT_NE(undeclared.status().message().find("names visits"), std::string::npos)
      << undeclared.status();
  EXPECT_FALSE((*target)->GetMap("no-keys").ok());
  EXPECT_EQ((*target)->ListKeyframes((*target)->GetMap("other")->id, 0)->size(), other_before);

  // 6. Cancelled: rolled back, CANCELLED, nothing stored.
  int asked = 0;
  auto cancelled = (*target)->ReadMapArchive(archive, "late", {}, false, [&] {
    return ++asked > 3;  // a few steps in
  });
  EXPECT_EQ(cancelled.status().code(), absl::StatusCode::kCancelled) << cancelled.status();
  EXPECT_FALSE((*target)->GetMap("late").ok()) << "nothing of a cancelled import is stored";
  EXPECT_TRUE((*target)->ReadMapArchive(archive, "late", {}).ok()) << "and it imports again";
  auto problems = (*target)->CheckIntegrity();
  ASSERT_TRUE(problems.ok());
  EXPECT_TRUE(problems->empty()) << problems->front();
}

// `admin check` names rows whose references resolve into another map, and id counters near
// their end (issue 52).
TEST_F(StoreTest, IntegrityCheckNamesCrossMapReferencesAndExhaustedCounters) {
  ASSERT_TRUE(store_->CreateMap("a", "", 1.0).ok());
  ASSERT_TRUE(store_->CreateMap("b", "", 1.0).ok());
  auto va = store_->StartVisit("a", "", "", 1.0);
  auto vb = store_->StartVisit("b", "", "", 1.0);
  ASSERT_TRUE(va.ok() && vb.ok());
  {
    sqlite3* db = nullptr;
    ASSERT_EQ(sqlite3_open(tmp_.File("lifemap.db").c_str(), &db), SQLITE_OK);
    const std::string sql = absl::StrCat(
        "UPDATE visits SET anchor_visit_id = ", vb->id, " WHERE id = ", va->id,
        "; UPDATE sqlite_sequence SET seq = 9223372036854775807 WHERE name = 'visits';");
    ASSERT_EQ(sqlite3_exec(db, sql.c_str(), nullptr, nullptr, nullptr), SQLITE_OK)
        << sqlite3_errmsg(db);
    sqlite3_close(db);
  }
  auto problems = store_->CheckIntegrity();
  ASSERT_TRUE(problems.ok());
  const std::string all = absl::StrJoin(*problems, "\n");
  EXPECT_NE(all.find(absl::StrCat("visit ", va->id, " of map id")), std::string::npos) << all;
  EXPECT_NE(all.find("table visits's id counter"), std::string::npos) << all;
  // A write past the counter's end says what it is, not "the disk is full".
  auto next = store_->StartVisit("a", "", "", 2.0);
  ASSERT_FALSE(next.ok());
  EXPECT_EQ(next.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(next.status().message().find("SQLite's own limits"), std::string::npos)
      << next.status();
  EXPECT_EQ(next.status().message().find("the disk is full"), std::string::npos);
}

// Issue 39: a map moved between shards keeps its ids and its open visit; each store mints new
// ids in its own range (RaiseIdFloor), so the moved ids do not collide; a collision is refused.
TEST_F(StoreTest, AMovedMapKeepsItsIdsAndOpenVisitsAboveTheTargetsFloor) {
  ASSERT_TRUE(store_->RaiseIdFloor(int64_t{1} << 40).ok());
  ASSERT_TRUE(store_->CreateMap("lab", "", 1.0).ok());
  auto ended = store_->StartVisit("lab", "bot", "ended", 1.0);
  ASSERT_TRUE(ended.ok());
  EXPECT_GT(ended->id, int64_t{1} << 40) << "new ids start above the floor";
  std::vector<KeyframeRecord> batch;
  for (int k = 0; k < 3; ++k) batch.push_back(Keyframe(ended->id, 1.0 + k));
  ASSERT_TRUE(store_->InsertKeyframes(&batch, {}).ok());
  ASSERT_TRUE(store_->EndVisit(ended->id, 5.0, {ended->id, 3, 0}).ok());
  auto open = store_->StartVisit("lab", "bot", "open", 6.0);
  ASSERT_TRUE(open.ok());
  const auto keyframes = *store_->ListKeyframes(store_->GetMap("lab")->id, 0);
  const std::string archive = tmp_.File("lab.archive");
  ASSERT_TRUE(store_->WriteMapArchive("lab", archive).ok());

  auto target = Store::Open(tmp_.File("target.db"));
  ASSERT_TRUE(target.ok());
  ASSERT_TRUE((*target)->RaiseIdFloor(int64_t{2} << 40).ok());
  ASSERT_TRUE((*target)->RaiseIdFloor(int64_t{1} << 40).ok()) << "lowers nothing";
  ASSERT_TRUE((*target)->CreateMap("hall", "", 1.0).ok());
  auto own = (*target)->StartVisit("hall", "", "", 1.0);
  ASSERT_TRUE(own.ok());
  EXPECT_GT(own->id, int64_t{2} << 40);

  auto moved = (*target)->ReadMapArchive(archive, "lab", {}, /*keep_ids=*/true);
  ASSERT_TRUE(moved.ok()) << moved.status();
  const auto arrived = *(*target)->ListKeyframes(moved->id, 0);
  ASSERT_EQ(arrived.size(), keyframes.size());
  for (size_t i = 0; i < arrived.size(); ++i) {
    EXPECT_EQ(arrived[i].id, keyframes[i].id);
    EXPECT_EQ(arrived[i].visit_id, keyframes[i].visit_id);
  }
  auto still_open = (*target)->GetVisit(open->id);
  ASSERT_TRUE(still_open.ok()) << still_open.status();
  EXPECT_FALSE(still_open->ended) << "its stream resumes it on the target";
  EXPECT_TRUE((*target)->GetVisit(ended->id)->ended);
  // The target's own new ids stay in its range, above the moved ones.
  auto next = (*target)->StartVisit("hall", "", "", 2.0);
  ASSERT_TRUE(next.ok());
  EXPECT_GT(next->id, own->id);
  // The same ids again (a second copy under another name): refused, naming the table.
  auto clash = (*target)->ReadMapArchive(archive, "lab2", {}, /*keep_ids=*/true);
  EXPECT_EQ(clash.status().code(), absl::StatusCode::kFailedPrecondition) << clash.status();
  EXPECT_NE(clash.status().message().find("visits id"), std::string::npos) << clash.status();
  EXPECT_FALSE((*target)->GetMap("lab2").ok()) << "nothing of it stored";
  auto problems = (*target)->CheckIntegrity();
  ASSERT_TRUE(problems.ok());
  EXPECT_TRUE(problems->empty()) << problems->front();
}

// Issue 52 (the cluster test): a map moved from shard 3 into shard 1 keeps shard 3's ids, above
// shard 1's range; AUTOINCREMENT went on above them, so shard 1's next visit took an id shard 3
// then gave out too, and moving that map to shard 1 was refused. New ids stay in the store's
// own range, are never given out twice (even after their row is deleted), and an import with
// new ids takes them from the range as well.
TEST_F(StoreTest, AShardGivesOutIdsOfItsOwnRangeWhateverAMovedMapKeeps) {
  constexpr int64_t kRange = int64_t{1} << Store::kIdRangeBits;
  ASSERT_TRUE(store_->RaiseIdFloor(3 * kRange).ok());  // shard 3
  ASSERT_TRUE(store_->CreateMap("lab", "", 1.0).ok());
  auto visit = store_->StartVisit("lab", "bot", "", 1.0);
  ASSERT_TRUE(visit.ok());
  std::vector<KeyframeRecord> batch;
  for (int k = 0; k < 3; ++k) batch.push_back(Keyframe(visit->id, 1.0 + k));
  ASSERT_TRUE(store_->InsertKeyframes(&batch, {}).ok());
  ASSERT_TRUE(store_->EndVisit(visit->id, 5.0, {visit->id, 3, 0}).ok());
  const std::string archive = tmp_.File("lab.archive");
  ASSERT_TRUE(store_->WriteMapArchive("lab", archive).ok());

  auto shard1 = Store::Open(tmp_.File("shard1.db"));
  ASSERT_TRUE(shard1.ok());
  ASSERT_TRUE((*shard1)->RaiseIdFloor(kRange).ok());
  ASSERT_TRUE((*shard1)->ReadMapArchive(archive, "lab", {}, /*keep_ids=*/true).ok());
  ASSERT_TRUE((*shard1)->CreateMap("hall", "", 1.0).ok());
  const auto in_range = [&](int64_t id) { return id > kRange && id < 2 * kRange; };
  auto own = (*shard1)->StartVisit("hall", "", "", 2.0);
  ASSERT_TRUE(own.ok());
  EXPECT_TRUE(in_range(own->id)) << own->id << ": not above the moved map's ids";
  std::vector<KeyframeRecord> more = {Keyframe(own->id, 3.0)};
  ASSERT_TRUE((*shard1)->InsertKeyframes(&more, {}).ok());
  EXPECT_TRUE(in_range(more[0].id)) << more[0].id;
  PoseEdgeRecord edge;
  edge.map_id = (*shard1)->GetMap("hall")->id;
  edge.from_keyframe = edge.to_keyframe = more[0].id;
  auto edge_id = (*shard1)->InsertPoseEdge(edge);
  ASSERT_TRUE(edge_id.ok()) << edge_id.status();
  EXPECT_TRUE(in_range(*edge_id)) << *edge_id;
  // A deleted visit's id is not given out again.
  ASSERT_TRUE((*shard1)->EndVisit(own->id, 4.0, {own->id, 1, 0}).ok());
  auto newest = (*shard1)->StartVisit("hall", "", "", 5.0);
  ASSERT_TRUE(newest.ok());
  ASSERT_TRUE((*shard1)->EndVisit(newest->id, 6.0, {newest->id, 0, 0}).ok());
  ASSERT_TRUE((*shard1)->DeleteVisit(newest->id).ok());
  auto after = (*shard1)->StartVisit("hall", "", "", 7.0);
  ASSERT_TRUE(after.ok());
  EXPECT_GT(after->id, newest->id);
  EXPECT_TRUE(in_range(after->id));
  // An import with new ids: from shard 1's range too.
  auto copy = (*shard1)->ReadMapArchive(archive, "lab-copy", {});
  ASSERT_TRUE(copy.ok()) << copy.status();
  auto copied = (*shard1)->ListVisits("lab-copy");
  ASSERT_TRUE(copied.ok()) << copied.status();
  ASSERT_FALSE(copied->empty());
  for (const auto& v : *copied) EXPECT_TRUE(in_range(v.id)) << v.id;
  // Shard 3 goes on in its own range: its next visit moves to shard 1 without a clash.
  auto later = store_->StartVisit("lab", "bot", "", 8.0);
  ASSERT_TRUE(later.ok());
  ASSERT_TRUE(store_->EndVisit(later->id, 9.0, {later->id, 0, 0}).ok());
  ASSERT_TRUE(store_->CreateMap("Küche", "", 1.0).ok());
  auto kitchen = store_->StartVisit("Küche", "", "", 1.0);
  ASSERT_TRUE(kitchen.ok());
  ASSERT_TRUE(store_->EndVisit(kitchen->id, 2.0, {kitchen->id, 0, 0}).ok());
  ASSERT_TRUE(store_->WriteMapArchive("Küche", tmp_.File("k.archive")).ok());
  auto moved = (*shard1)->ReadMapArchive(tmp_.File("k.archive"), "Küche", {}, true);
  EXPECT_TRUE(moved.ok()) << moved.status();
  // A map moving back to the shard that gave out its ids (a rebuilt shard 3 here): once it is
  // deleted there, its ids are not given out again.
  auto home = Store::Open(tmp_.File("home3.db"));
  ASSERT_TRUE(home.ok());
  ASSERT_TRUE((*home)->RaiseIdFloor(3 * kRange).ok());
  ASSERT_TRUE((*home)->ReadMapArchive(archive, "lab", {}, /*keep_ids=*/true).ok());
  ASSERT_TRUE((*home)->DeleteMap("lab").ok());
  ASSERT_TRUE((*home)->CreateMap("again", "", 1.0).ok());
  auto fresh = (*home)->StartVisit("again", "", "", 1.0);
  ASSERT_TRUE(fresh.ok());
  EXPECT_GT(fresh->id, visit->id) << "the moved map's visit id is not given out again";
  auto problems = (*shard1)->CheckIntegrity();
  ASSERT_TRUE(problems.ok());
  EXPECT_TRUE(problems->empty()) << problems->front();
}

// Issue 37: an import killed at any moment leaves the map whole or absent.
TEST_F(StoreTest, AKillDuringAMapImportLeavesItWholeOrAbsent) {
  ASSERT_TRUE(store_->CreateMap("big", "", 1.0).ok());
  for (int v = 0; v < 10; ++v) {
    auto visit = store_->StartVisit("big", "", "", 1.0 + v);
    std::vector<KeyframeRecord> batch;
    for (int k = 0; k < 40; ++k) {
      batch.push_back(Keyframe(visit->id, 100.0 * v + k));
      batch.back().depth = std::string(50000, static_cast<char>('a' + k % 26));
    }
    ASSERT_TRUE(store_->InsertKeyframes(&batch, {}).ok());
  }
  const std::string archive = tmp_.File("big.archive");
  ASSERT_TRUE(store_->WriteMapArchive("big", archive).ok());
  const std::string path = tmp_.File("import.db");
  ASSERT_TRUE(Store::Open(path).ok());
  int whole = 0;
  for (const int delay_ms : {5, 20, 50, 100, 200, 400}) {
    const pid_t child = fork();
    ASSERT_GE(child, 0);
    if (child == 0) {
      auto store = Store::Open(path);
      if (!store.ok()) _exit(2);
      std::filesystem::copy_file(archive, archive + ".child",
                                 std::filesystem::copy_options::overwrite_existing);
      auto map = (*store)->ReadMapArchive(archive + ".child", "big" + std::to_string(delay_ms), {});
      _exit(map.ok() ? 0 : 3);
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(delay_ms));
    kill(child, SIGKILL);
    int status = 0;
    waitpid(child, &status, 0);
    ASSERT_FALSE(WIFEXITED(status) && WEXITSTATUS(status) != 0) << WEXITSTATUS(status);
    auto store = Store::Open(path);
    ASSERT_TRUE(store.ok()) << store.status();
    auto problems = (*store)->CheckIntegrity();
    ASSERT_TRUE(problems.ok());
    EXPECT_TRUE(problems->empty()) << problems->front();
    auto map = (*store)->GetMap("big" + std::to_string(delay_ms));
    if (map.ok()) {
      EXPECT_EQ((*store)->ListKeyframes(map->id, 0)->size(), 400u) << "whole, or not at all";
      ++whole;
    } else {
      EXPECT_EQ(map.status().code(), absl::StatusCode::kNotFound);
    }
  }
  std::cout << whole << " of 6 imports finished before the kill\n";
}

TEST_F(StoreTest, AKillDuringThinningLeavesEachVisitWholeOrThinned) {
  const std::string path = tmp_.File("kill.db");
  std::vector<int64_t> visits;
  {
    auto store = Store::Open(path);
    ASSERT_TRUE(store.ok());
    ASSERT_TRUE((*store)->CreateMap("m", "", 1.0).ok());
    for (int v = 0; v < 40; ++v) {
      auto visit = (*store)->StartVisit("m", "", "", 1.0 + v);
      std::vector<KeyframeRecord> batch;
      for (int k = 0; k < 50; ++k) {
        batch.push_back(Keyframe(visit->id, 100.0 * v + k));
        batch.back().depth = std::string(20000, static_cast<char>('a' + k % 26));
      }
      ASSERT_TRUE((*store)->InsertKeyframes(&batch, {}).ok());
      ASSERT_TRUE((*store)->EndVisit(visit->id, 2.0 + v, {visit->id, 50, 0}).ok());
      visits.push_back(visit->id);
    }
  }
  // Killed at growing delays; each child resumes where the last was killed.
  for (const int delay_ms : {10, 25, 50, 100, 200}) {
    const pid_t child = fork();
    ASSERT_GE(child, 0);
    if (child == 0) {
      auto store = Store::Open(path);
      if (!store.ok()) _exit(2);
      auto map = (*store)->GetMap("m");
      for (const int64_t v : visits) {
        auto keyframes = (*store)->ListKeyframes(map->id, v);
        std::vector<int64_t> ids;
        for (size_t k = 1; k < keyframes->size(); ++k) ids.push_back((*keyframes)[k].id);
        if (!(*store)->DeleteKeyframes(v, ids).ok()) _exit(3);
      }
      _exit(0);
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(delay_ms));
    kill(child, SIGKILL);
    int status = 0;
    waitpid(child, &status, 0);
    ASSERT_FALSE(WIFEXITED(status) && WEXITSTATUS(status) != 0) << WEXITSTATUS(status);
    auto store = Store::Open(path);
    ASSERT_TRUE(store.ok()) << store.status();
    auto problems = (*store)->CheckIntegrity();
    ASSERT_TRUE(problems.ok());
    EXPECT_TRUE(problems->empty()) << problems->front();
    auto map = (*store)->GetMap("m");
    int thinned = 0;
    for (const int64_t v : visits) {
      auto keyframes = (*store)->ListKeyframes(map->id, v);
      ASSERT_TRUE(keyframes.ok());
      ASSERT_TRUE(keyframes->size() == 50 || keyframes->size() == 1)
          << "visit " << v << " was left with " << keyframes->size() << " keyframes";
      thinned += keyframes->size() == 1 ? 1 : 0;
      for (const auto& k : *keyframes) {
        auto read = (*store)->GetKeyframe(map->id, k.id);
        ASSERT_TRUE(read.ok()) << read.status();
        EXPECT_EQ(read->depth.size(), 20000u);
      }
    }
    std::cout << "killed after " << delay_ms << " ms: " << thinned << " of " << visits.size()
              << " visits thinned\n";
  }
}

TEST_F(StoreTest, IdsOfDeletedRowsAreNeverReused) {
  // The newest map, visit, keyframe and model deleted: their successors get new ids, also
  // after the store is reopened. (A reused visit id let a stream for the deleted visit commit
  // keyframes into its successor.)
  auto map = store_->CreateMap("m", "", 1.0);
  auto visit = store_->StartVisit("m", "", "", 1.0);
  std::vector<KeyframeRecord> batch = {Keyframe(visit->id, 1.0)};
  ASSERT_TRUE(store_->InsertKeyframes(&batch, {}).ok());
  ModelRecord model;
  model.name = "forest";
  model.class_names = {"a", "b"};
  model.class_colors = {1, 2};
  auto m1 = store_->InsertModel(model, "bytes");
  ASSERT_TRUE(map.ok() && visit.ok() && m1.ok());
  ASSERT_TRUE(store_->DeleteMap("m").ok());
  ASSERT_TRUE(store_->DeleteModel("forest").ok());
  store_.reset();
  auto reopened = Store::Open(tmp_.File("lifemap.db"));
  ASSERT_TRUE(reopened.ok()) << reopened.status();
  store_ = *std::move(reopened);

  auto map2 = store_->CreateMap("m", "", 2.0);
  auto visit2 = store_->StartVisit("m", "", "", 2.0);
  std::vector<KeyframeRecord> batch2 = {Keyframe(visit2->id, 2.0)};
  ASSERT_TRUE(store_->InsertKeyframes(&batch2, {}).ok());
  auto m2 = store_->InsertModel(model, "bytes");
  ASSERT_TRUE(map2.ok() && visit2.ok() && m2.ok());
  EXPECT_GT(map2->id, map->id);
  EXPECT_GT(visit2->id, visit->id);
  EXPECT_GT(batch2[0].id, batch[0].id);
  EXPECT_GT(m2->id, m1->id);
  // The deleted visit stays deleted: a keyframe for it is refused, not given to the new one.
  std::vector<KeyframeRecord> orphan = {Keyframe(visit->id, 3.0)};
  EXPECT_TRUE(absl::IsNotFound(store_->InsertKeyframes(&orphan, {})));
  EXPECT_EQ(store_->GetMap("m")->keyframe_count, 1);
}

TEST_F(StoreTest, EndedVisitIsNotTheLatestOpenOne) {
  ASSERT_TRUE(store_->CreateMap("m", "", 1.0).ok());
  auto v1 = store_->StartVisit("m", "", "", 1.0);
  auto v2 = store_->StartVisit("m", "", "", 2.0);
  auto open = store_->LatestOpenVisit("m");
  ASSERT_TRUE(open.ok() && open->has_value());
  EXPECT_EQ((*open)->id, v2->id);
  // Frame counts only grow: the end's and the last commit's, whichever is larger.
  std::vector<KeyframeRecord> none;
  ASSERT_TRUE(store_->InsertKeyframes(&none, {{v2->id, 7, 3}}).ok());
  auto ended = store_->EndVisit(v2->id, 3.0, {v2->id, 5, 4});
  ASSERT_TRUE(ended.ok()) << ended.status();
  EXPECT_EQ(ended->frame_count, 7);
  EXPECT_EQ(ended->lost_frame_count, 4);
  open = store_->LatestOpenVisit("m");
  EXPECT_EQ((*open)->id, v1->id);
}

TEST_F(StoreTest, DataSurvivesReopen) {
  ASSERT_TRUE(store_->CreateMap("persist", "", 1.0).ok());
  store_.reset();
  auto reopened = Store::Open(tmp_.File("lifemap.db"));
  ASSERT_TRUE(reopened.ok());
  EXPECT_TRUE((*reopened)->GetMap("persist").ok());
}

// Issue 33, item 13: a read-only database was reported as "the disk is full", and clients saw
// the SQL that failed. Operational errors say what to do and show no SQL; only an INTERNAL
// error (a bug) names the statement.
TEST(SqliteError, SaysWhatToDoAndShowsNoSqlToClients) {
  const char* sql = "INSERT INTO maps (name) VALUES (?1)";
  const absl::Status read_only = SqliteError(nullptr, SQLITE_READONLY, "the database", sql);
  EXPECT_TRUE(absl::IsFailedPrecondition(read_only)) << read_only;
  EXPECT_NE(read_only.message().find("read-only"), std::string::npos) << read_only;
  EXPECT_EQ(read_only.message().find("full"), std::string::npos) << read_only;
  const absl::Status full = SqliteError(nullptr, SQLITE_FULL, "the database", sql);
  EXPECT_TRUE(absl::IsResourceExhausted(full)) << full;
  const absl::Status busy = SqliteError(nullptr, SQLITE_BUSY, "the database", sql);
  for (const auto& s : {read_only, full, busy}) {
    EXPECT_EQ(s.message().find("INSERT"), std::string::npos) << s;
  }
  const absl::Status bug = SqliteError(nullptr, SQLITE_ERROR, "the database", sql);
  EXPECT_TRUE(absl::IsInternal(bug));
  EXPECT_NE(bug.message().find("INSERT"), std::string::npos) << bug;
}

TEST_F(StoreTest, AWriteToAReadOnlyConnectionSaysReadOnly) {
  auto db = Database::Open(tmp_.File("lifemap.db"), false, /*read_only=*/true, 1000);
  ASSERT_TRUE(db.ok()) << db.status();
  const absl::Status s = (*db)->Exec("CREATE TABLE intruder (x)");
  EXPECT_TRUE(absl::IsFailedPrecondition(s)) << s;
  EXPECT_NE(s.message().find("read-only"), std::string::npos) << s;
  EXPECT_EQ(s.message().find("CREATE"), std::string::npos) << s;
}

TEST_F(StoreTest, BackupIsAReadableCopy) {
  ASSERT_TRUE(store_->CreateMap("m", "", 1.0).ok());
  EXPECT_TRUE(absl::IsInvalidArgument(store_->Backup("relative.db")));
  // Issue 33, item 8: a backup named NAME deleted the backup named NAME.partial (and its
  // -wal/-shm), which it took for its own leftover.
  for (const char* other : {"backup.db.partial", "backup.db.partial-wal"}) {
    std::ofstream(tmp_.File(other)) << "another backup's bytes";
  }
  ASSERT_TRUE(store_->Backup(tmp_.File("backup.db")).ok());
  for (const char* other : {"backup.db.partial", "backup.db.partial-wal"}) {
    std::ifstream in(tmp_.File(other));
    std::string kept;
    std::getline(in, kept);
    EXPECT_EQ(kept, "another backup's bytes") << other << " was touched";
  }
  // Nothing of the backup's own partial file is left.
  for (const auto& e : std::filesystem::directory_iterator(tmp_.path())) {
    EXPECT_EQ(e.path().filename().string().rfind(".backup.db.partial", 0), std::string::npos)
        << e.path();
  }
  EXPECT_TRUE(absl::IsAlreadyExists(store_->Backup(tmp_.File("backup.db"))));
  auto copy = Store::Open(tmp_.File("backup.db"));
  ASSERT_TRUE(copy.ok()) << copy.status();
  EXPECT_TRUE((*copy)->GetMap("m").ok());
}

TEST(StoreOpen, RefusesNewerSchemaAndForeignFiles) {
  testing::TempDir tmp;
  {
    sqlite3* db = nullptr;
    sqlite3_open(tmp.File("newer.db").c_str(), &db);
    sqlite3_exec(db, "PRAGMA user_version = 99", nullptr, nullptr, nullptr);
    sqlite3_close(db);
    sqlite3_open(tmp.File("foreign.db").c_str(), &db);
    sqlite3_exec(db, "CREATE TABLE t(x)", nullptr, nullptr, nullptr);
    sqlite3_close(db);
  }
  auto newer = Store::Open(tmp.File("newer.db"));
  EXPECT_TRUE(absl::IsFailedPrecondition(newer.status()));
  EXPECT_NE(newer.status().message().find("newer"), std::string::npos);
  EXPECT_TRUE(absl::IsFailedPrecondition(Store::Open(tmp.File("foreign.db")).status()));
  std::ofstream(tmp.File("garbage.db")) << std::string(8192, 'x');
  EXPECT_FALSE(Store::Open(tmp.File("garbage.db")).ok());
  EXPECT_TRUE(absl::IsNotFound(Store::Open("/nonexistent-dir/x.db").status()));
}

TEST(StoreOpen, MigratesAnEmptyFileToTheCurrentSchema) {
  testing::TempDir tmp;
  ASSERT_TRUE(Store::Open(tmp.File("a.db")).ok());
  sqlite3* db = nullptr;
  sqlite3_open(tmp.File("a.db").c_str(), &db);
  sqlite3_stmt* stmt = nullptr;
  sqlite3_prepare_v2(db, "PRAGMA user_version", -1, &stmt, nullptr);
  ASSERT_EQ(sqlite3_step(stmt), SQLITE_ROW);
  EXPECT_EQ(sqlite3_column_int(stmt, 0), Store::kSchemaVersion);
  sqlite3_finalize(stmt);
  sqlite3_close(db);
}

TEST_F(StoreTest, KeyframeFeaturesRoundTrip) {
  ASSERT_TRUE(store_->CreateMap("m", "", 1.0).ok());
  auto visit = store_->StartVisit("m", "", "", 1.0);
  KeyframeRecord k = Keyframe(visit->id, 1.0);
  KeyframeFeatures f;
  f.entropy_threshold = 0.4;
  f.superjuts = {{0, 1200, 0.1f, 0.9f, 0.95f, 0.01f, 0.97f},
                 {1, 300, 3.0f, 0.1f, 0.2f, 0.3f, 0.3f}};
  f.keypoints.type = "orb";
  f.keypoints.keypoints = {{10.5f, 20.25f, 31, 90, 0.5f}, {100.3f, 200.7f, 44.6f, 45.37f, 0.25f}};
  // A point 1.2 m ahead, and one without depth.
  f.keypoints.points = {{0.1234f, -0.5f, 1.2f},
                        Eigen::Vector3f::Constant(std::numeric_limits<float>::quiet_NaN())};
  f.keypoints.descriptors = cv::Mat(2, 32, CV_8UC1);
  cv::randu(f.keypoints.descriptors, 0, 255);
  f.keypoints.masked = 5;
  k.features = f;
  std::vector<KeyframeRecord> batch = {k, Keyframe(visit->id, 2.0)};
  ASSERT_TRUE(store_->InsertKeyframes(&batch, {}).ok());

  auto map = store_->GetMap("m");
  auto list = store_->ListKeyframes(map->id, 0);
  ASSERT_TRUE(list.ok());
  ASSERT_TRUE((*list)[0].feature_counts.has_value());
  EXPECT_EQ((*list)[0].feature_counts->superjuts, 2);
  EXPECT_EQ((*list)[0].feature_counts->keypoints_stored, 2);
  EXPECT_EQ((*list)[0].feature_counts->keypoints_masked, 5);
  EXPECT_FALSE((*list)[1].feature_counts.has_value()) << "a keyframe without features";

  auto got = store_->GetKeyframe(map->id, batch[0].id);
  ASSERT_TRUE(got.ok() && got->features.has_value());
  ASSERT_EQ(got->features->superjuts.size(), 2u);
  EXPECT_FLOAT_EQ(got->features->superjuts[1].entropy, 3.0f);
  EXPECT_EQ(got->features->superjuts[0].size_px, 1200);

  auto features = store_->GetKeyframeFeatures(batch[0].id);
  ASSERT_TRUE(features.ok()) << features.status();
  EXPECT_DOUBLE_EQ(features->entropy_threshold, 0.4);
  ASSERT_EQ(features->keypoints.keypoints.size(), 2u);
  EXPECT_FLOAT_EQ(features->keypoints.keypoints[0].y, 20.25f);
  // Compact records: 1/8 px and 1/100 degree, response exact; points to the millimetre.
  const auto& second = features->keypoints.keypoints[1];
  EXPECT_NEAR(second.x, 100.3f, 1.0f / 16);
  EXPECT_NEAR(second.y, 200.7f, 1.0f / 16);
  EXPECT_NEAR(second.size, 44.6f, 1.0f / 16);
  EXPECT_NEAR(second.angle, 45.37f, 0.005f);
  EXPECT_FLOAT_EQ(second.response, 0.25f);
  ASSERT_EQ(features->keypoints.points.size(), 2u);
  EXPECT_LT((features->keypoints.points[0] - f.keypoints.points[0]).norm(), 0.001f);
  EXPECT_TRUE(std::isnan(features->keypoints.points[1].z())) << "no depth stays no depth";
  EXPECT_EQ(cv::norm(features->keypoints.descriptors, f.keypoints.descriptors, cv::NORM_L1), 0);
  EXPECT_EQ(features->keypoints.detected, 7);
  EXPECT_TRUE(absl::IsNotFound(store_->GetKeyframeFeatures(batch[1].id).status()));

  // Rows written before schema 7 (float32 records, record_format 1) are read as they were.
  store_.reset();
  sqlite3* db = nullptr;
  ASSERT_EQ(sqlite3_open(tmp_.File("lifemap.db").c_str(), &db), SQLITE_OK);
  const float old_keypoints[10] = {1.5f, 2.5f, 31, 90, 0.5f, 3.25f, 4.75f, 31, 45, 0.25f};
  const float old_points[6] = {0.1f, 0.2f, 1.5f, 0.3f, 0.4f, 2.5f};
  sqlite3_stmt* stmt = nullptr;
  ASSERT_EQ(sqlite3_prepare_v2(db,
                               "UPDATE keyframe_features SET record_format = 1, keypoints = ?1, "
                               "points = ?2 WHERE keyframe_id = ?3",
                               -1, &stmt, nullptr),
            SQLITE_OK);
  sqlite3_bind_blob(stmt, 1, old_keypoints, sizeof(old_keypoints), SQLITE_STATIC);
  sqlite3_bind_blob(stmt, 2, old_points, sizeof(old_points), SQLITE_STATIC);
  sqlite3_bind_int64(stmt, 3, batch[0].id);
  ASSERT_EQ(sqlite3_step(stmt), SQLITE_DONE);
  sqlite3_finalize(stmt);
  sqlite3_close(db);
  auto reopened = Store::Open(tmp_.File("lifemap.db"));
  ASSERT_TRUE(reopened.ok()) << reopened.status();
  auto old = (*reopened)->GetKeyframeFeatures(batch[0].id);
  ASSERT_TRUE(old.ok()) << old.status();
  ASSERT_EQ(old->keypoints.keypoints.size(), 2u);
  EXPECT_FLOAT_EQ(old->keypoints.keypoints[1].x, 3.25f);
  EXPECT_FLOAT_EQ(old->keypoints.keypoints[1].y, 4.75f);
  ASSERT_EQ(old->keypoints.points.size(), 2u);
  EXPECT_FLOAT_EQ(old->keypoints.points[1].z(), 2.5f);
}

TEST_F(StoreTest, MapEntropyThresholdIsSetAndReset) {
  auto m = store_->CreateMap("m", "d", 1.0, 0.3);
  ASSERT_TRUE(m.ok());
  EXPECT_EQ(m->entropy_threshold, 0.3);
  MapUpdate update;
  update.set_entropy_threshold = true;
  update.entropy_threshold = std::nullopt;
  auto reset = store_->UpdateMap("m", update);
  ASSERT_TRUE(reset.ok());
  EXPECT_FALSE(reset->entropy_threshold.has_value());
  EXPECT_EQ(reset->description, "d") << "unset fields keep their values";
  update = {};
  update.description = "new";
  EXPECT_EQ(store_->UpdateMap("m", update)->description, "new");
  EXPECT_TRUE(absl::IsNotFound(store_->UpdateMap("nope", update).status()));
  EXPECT_EQ(store_->GetMapById(m->id)->name, "m");
}

// A database written by the first release (schema 1) opens, migrates to the current schema and
// keeps its data. The SQL below is schema 1 as it shipped.
TEST(StoreOpen, MigratesASchemaOneDatabaseForward) {
  testing::TempDir tmp;
  {
    sqlite3* db = nullptr;
    sqlite3_open(tmp.File("v1.db").c_str(), &db);
    const char* v1 = R"sql(
CREATE TABLE maps (id INTEGER PRIMARY KEY, name TEXT NOT NULL UNIQUE,
  description TEXT NOT NULL DEFAULT '', created_time_s REAL NOT NULL);
CREATE TABLE visits (id INTEGER PRIMARY KEY,
  map_id INTEGER NOT NULL REFERENCES maps(id) ON DELETE CASCADE, robot TEXT NOT NULL DEFAULT '',
  label TEXT NOT NULL DEFAULT '', start_time_s REAL NOT NULL, end_time_s REAL NOT NULL DEFAULT 0,
  ended INTEGER NOT NULL DEFAULT 0, frame_count INTEGER NOT NULL DEFAULT 0);
CREATE INDEX visits_by_map ON visits(map_id, start_time_s);
CREATE TABLE keyframes (id INTEGER PRIMARY KEY,
  visit_id INTEGER NOT NULL REFERENCES visits(id) ON DELETE CASCADE, sequence INTEGER NOT NULL,
  timestamp_s REAL NOT NULL, has_pose INTEGER NOT NULL,
  tx REAL, ty REAL, tz REAL, qx REAL, qy REAL, qz REAL, qw REAL,
  fx REAL NOT NULL, fy REAL NOT NULL, cx REAL NOT NULL, cy REAL NOT NULL,
  width INTEGER NOT NULL, height INTEGER NOT NULL, depth_scale REAL NOT NULL,
  color_encoding INTEGER NOT NULL, depth_bytes INTEGER NOT NULL, color_bytes INTEGER NOT NULL);
CREATE INDEX keyframes_by_visit ON keyframes(visit_id, timestamp_s);
CREATE TABLE keyframe_images (
  keyframe_id INTEGER PRIMARY KEY REFERENCES keyframes(id) ON DELETE CASCADE,
  depth_png BLOB NOT NULL, color BLOB NOT NULL);
INSERT INTO maps (name, description, created_time_s) VALUES ('old', 'from v1', 5.0);
INSERT INTO visits (map_id, start_time_s) VALUES (1, 6.0);
INSERT INTO keyframes VALUES (1, 1, 0, 7.0, 0, NULL, NULL, NULL, NULL, NULL, NULL, NULL,
  525, 525, 319.5, 239.5, 640, 480, 5000, 1, 3, 3);
INSERT INTO keyframe_images VALUES (1, 'dep', 'col');
PRAGMA user_version = 1;
)sql";
    ASSERT_EQ(sqlite3_exec(db, v1, nullptr, nullptr, nullptr), SQLITE_OK);
    sqlite3_close(db);
  }
  auto store = Store::Open(tmp.File("v1.db"));
  ASSERT_TRUE(store.ok()) << store.status();
  auto map = (*store)->GetMap("old");
  ASSERT_TRUE(map.ok());
  EXPECT_EQ(map->description, "from v1");
  EXPECT_FALSE(map->entropy_threshold.has_value());
  EXPECT_EQ(map->keyframe_count, 1);
  auto k = (*store)->GetKeyframe(map->id, 1);
  ASSERT_TRUE(k.ok()) << k.status();
  EXPECT_EQ(k->depth, "dep");
  EXPECT_EQ(k->depth_encoding, StoredDepthEncoding::kPng16) << "stored before RVL: PNG-16";
  EXPECT_EQ(k->pose_source, StoredPoseSource::kNone) << "stored without a pose";
  EXPECT_FALSE(map->keep_original_color);
  EXPECT_FALSE(k->features.has_value());
  auto problems = (*store)->CheckIntegrity();
  EXPECT_TRUE(problems.ok() && problems->empty());
  // The migrated tables keep their ids and never reuse them.
  auto visits = (*store)->ListVisits("old");
  ASSERT_TRUE(visits.ok() && visits->size() == 1u);
  EXPECT_EQ((*visits)[0].id, 1);
  ASSERT_TRUE((*store)->DeleteMap("old").ok());
  auto fresh = (*store)->CreateMap("new", "", 8.0);
  ASSERT_TRUE(fresh.ok());
  EXPECT_EQ(fresh->id, 2);
  EXPECT_EQ((*store)->StartVisit("new", "", "", 9.0)->id, 2);
}

TEST_F(StoreTest, ModelsAreStoredActivatedPerMapOrAsDefaultAndGuardedOnDelete) {
  ModelRecord m;
  m.name = "forest-a";
  m.uploaded_time_s = 5;
  m.class_names = {"table", "object"};
  m.class_colors = {0x808080, 0xE6194B};
  m.training_json = R"({"images":14})";
  m.trees = 3;
  m.nodes = 457;
  auto a = store_->InsertModel(m, "model-bytes");
  ASSERT_TRUE(a.ok()) << a.status();
  EXPECT_EQ(a->class_names, m.class_names);
  EXPECT_EQ(a->class_colors, m.class_colors);
  EXPECT_EQ(a->size_bytes, 11);
  EXPECT_TRUE(absl::IsAlreadyExists(store_->InsertModel(m, "again").status()));
  m.name = "forest-b";
  ASSERT_TRUE(store_->InsertModel(m, "other-bytes").ok());
  EXPECT_EQ(*store_->GetModelData("forest-a"), "model-bytes");

  auto lab = store_->CreateMap("lab", "", 1);
  auto hall = store_->CreateMap("hall", "", 1);
  ASSERT_TRUE(lab.ok() && hall.ok());
  EXPECT_EQ(*store_->ActiveModelName(lab->id), "") << "nothing active yet";
  EXPECT_EQ(*store_->ActivateModel("", "forest-a"), "");
  EXPECT_EQ(*store_->ActiveModelName(lab->id), "forest-a") << "the default applies";
  EXPECT_EQ(*store_->ActiveModelName(0), "forest-a");
  EXPECT_EQ(*store_->ActivateModel("lab", "forest-b"), "");
  EXPECT_EQ(*store_->ActiveModelName(lab->id), "forest-b") << "the map's own comes first";
  EXPECT_EQ(*store_->ActiveModelName(hall->id), "forest-a");
  EXPECT_EQ(*store_->ActivateModel("", "forest-b"), "forest-a") << "returns the previous";

  auto b = store_->GetModel("forest-b");
  ASSERT_TRUE(b.ok());
  EXPECT_TRUE(b->is_default);
  EXPECT_EQ(b->active_maps, std::vector<std::string>{"lab"});
  EXPECT_TRUE(absl::IsFailedPrecondition(store_->DeleteModel("forest-b")));
  EXPECT_TRUE(absl::IsNotFound(store_->ActivateModel("nowhere", "forest-a").status()));
  EXPECT_TRUE(absl::IsNotFound(store_->ActivateModel("lab", "missing").status()));

  // Deactivating and deleting the map both release it.
  EXPECT_EQ(*store_->ActivateModel("", ""), "forest-b");
  ASSERT_TRUE(store_->DeleteMap("lab").ok());
  ASSERT_TRUE(store_->DeleteModel("forest-b").ok());
  EXPECT_TRUE(absl::IsNotFound(store_->GetModel("forest-b").status()));
  EXPECT_EQ(*store_->ActiveModelName(hall->id), "");
  EXPECT_EQ(store_->ListModels()->size(), 1u);
  EXPECT_TRUE(store_->CheckIntegrity()->empty());
}

TEST_F(StoreTest, PoseGraphSolvesRewriteTrackedPosesInOneTransaction) {
  ASSERT_TRUE(store_->CreateMap("m", "", 1.0).ok());
  auto visit = store_->StartVisit("m", "", "", 1.0);
  ASSERT_TRUE(visit.ok());
  // Four tracked keyframes: the odometry pose is kept beside the pose in the map.
  std::vector<KeyframeRecord> batch;
  for (int i = 0; i < 4; ++i) {
    KeyframeRecord k = Keyframe(visit->id, 1.0 + i);
    k.pose_source = StoredPoseSource::kEstimated;
    k.T_odom_camera = k.T_world_camera;
    k.odom_segment = 42;
    batch.push_back(k);
  }
  ASSERT_TRUE(store_->InsertKeyframes(&batch, {}).ok());
  const int64_t map_id = visit->map_id;

  PoseEdgeRecord loop;
  loop.map_id = map_id;
  loop.from_keyframe = batch[0].id;
  loop.to_keyframe = batch[2].id;
  loop.T_from_to.translation = {0.5, 0, 0};
  loop.inliers = 80;
  loop.reprojection_px = 1.2;
  loop.accepted = true;
  loop.reason = "fine";
  auto loop_id = store_->InsertPoseEdge(loop);
  ASSERT_TRUE(loop_id.ok()) << loop_id.status();
  PoseEdgeRecord refused = loop;
  refused.accepted = false;
  refused.reason = "12 PnP inliers, a loop needs 25";
  ASSERT_TRUE(store_->InsertPoseEdge(refused).ok());
  PoseEdgeRecord dangling = loop;
  dangling.to_keyframe = 999999;
  EXPECT_TRUE(absl::IsNotFound(store_->InsertPoseEdge(dangling).status()));

  auto v = store_->GetVisit(visit->id);
  ASSERT_TRUE(v.ok());
  EXPECT_EQ(v->loops_accepted, 1);
  EXPECT_EQ(v->loops_rejected, 1);
  EXPECT_EQ(v->pose_graph_solves, 0);

  // A solve over the first three: they move; the fourth (tracked meanwhile) follows the
  // correction from its odometry pose; the loop was outvoted.
  std::map<int64_t, Pose> solved;
  for (int i = 0; i < 3; ++i) {
    Pose p = *batch[i].T_world_camera;
    p.translation.x() += 0.1 * i;
    solved[batch[i].id] = p;
  }
  Pose correction;
  correction.translation = {0.2, 0, 0};
  PoseOptimisationRecord record;
  record.map_id = map_id;
  record.visit_id = visit->id;
  record.keyframes = 3;
  record.loop_edges = 1;
  record.loops_rejected = 1;
  auto solve_id = store_->ApplyPoseOptimisation(record, solved, {*loop_id}, "outvoted", correction);
  ASSERT_TRUE(solve_id.ok()) << solve_id.status();
  auto listed = store_->ListKeyframes(map_id, visit->id);
  ASSERT_TRUE(listed.ok());
  ASSERT_EQ(listed->size(), 4u);
  for (int i = 0; i < 4; ++i) {
    const KeyframeRecord& k = (*listed)[i];
    EXPECT_EQ(k.optimisation_id, *solve_id);
    ASSERT_TRUE(k.T_odom_camera.has_value());
    EXPECT_DOUBLE_EQ(k.T_odom_camera->translation.x(), 1.0 + i) << "odometry never rewritten";
    EXPECT_EQ(k.odom_segment, 42);
    EXPECT_NEAR(k.T_world_camera->translation.x(), 1.0 + i + (i < 3 ? 0.1 * i : 0.2), 1e-9);
  }
  auto edges = store_->ListPoseEdges(map_id, visit->id);
  ASSERT_TRUE(edges.ok());
  ASSERT_EQ(edges->size(), 2u);
  EXPECT_FALSE((*edges)[0].accepted);
  EXPECT_EQ((*edges)[0].reason, "outvoted");
  EXPECT_EQ((*edges)[0].inliers, 80);
  v = store_->GetVisit(visit->id);
  ASSERT_TRUE(v.ok());
  EXPECT_EQ(v->loops_accepted, 0);
  EXPECT_EQ(v->loops_rejected, 2);
  EXPECT_EQ(v->pose_graph_solves, 1);
  auto solves = store_->ListPoseOptimisations(map_id, 0);
  ASSERT_TRUE(solves.ok());
  ASSERT_EQ(solves->size(), 1u);
  EXPECT_EQ((*solves)[0].loops_rejected, 1);

  // Deleting the map takes its edges and solves with it.
  ASSERT_TRUE(store_->DeleteMap("m").ok());
  auto gone = store_->ListPoseOptimisations(map_id, 0);
  ASSERT_TRUE(gone.ok());
  EXPECT_TRUE(gone->empty());
}

TEST(MapName, ValidatesCharactersAndLength) {
  EXPECT_TRUE(ValidateMapName("office_2-b.v1").ok());
  EXPECT_FALSE(ValidateMapName("").ok());
  EXPECT_FALSE(ValidateMapName(std::string(65, 'a')).ok());
  EXPECT_FALSE(ValidateMapName("../etc").ok());
  EXPECT_FALSE(ValidateMapName(".hidden").ok());
}

// Names are UTF-8 (issue 52): letters of any script and single inner spaces; nothing that hides
// or reorders text, splits a log line or reads as a path.
TEST(MapName, TakesLettersOfAnyScriptAndRefusesInvisibleCharacters) {
  for (const char* ok : {"K\u00fcche", "B\u00fcro 2", "\u6771\u4eac", "caf\u00e9-\u00e9t\u00e9"}) {
    EXPECT_TRUE(ValidateMapName(ok).ok()) << ok;
  }
  for (const std::string& bad :
       {std::string("has  two spaces"), std::string(" lead"), std::string("trail "),
        std::string("line\nbreak"), std::string("esc\x1b[31m"), std::string("a/b"),
        std::string("\xff\xfe"), std::string("bidi\u202eevil"), std::string("zero\u200bwidth"),
        std::string("nbsp\u00a0x"), std::string("c1\u0085x"), std::string("tab\tx")}) {
    const absl::Status s = ValidateMapName(bad);
    EXPECT_TRUE(absl::IsInvalidArgument(s)) << bad;
    EXPECT_EQ(s.message().find('\n'), std::string::npos) << s.message();
    EXPECT_EQ(s.message().find('\x1b'), std::string::npos) << s.message();
  }
  // 64 bytes, not characters: 21 three-byte characters fit, 22 do not.
  std::string tokyo21;
  for (int i = 0; i < 21; ++i) tokyo21 += "\u6771";
  EXPECT_TRUE(ValidateMapName(tokyo21).ok());
  EXPECT_FALSE(ValidateMapName(tokyo21 + "\u6771").ok());
}

}  // namespace
}  // namespace lifemap::store

namespace lifemap::store {
namespace {

TEST(SemanticSnapshotStore, ReplacesWholeSnapshotsInChunksAndCascades) {
  testing::TempDir tmp;
  auto store = Store::Open(tmp.File("db"));
  ASSERT_TRUE(store.ok()) << store.status();
  Store& s = **store;
  ASSERT_TRUE(s.CreateMap("m", "", 1.0).ok());
  auto visit = s.StartVisit("m", "", "", 1.0);
  ASSERT_TRUE(visit.ok());
  EXPECT_TRUE(absl::IsNotFound(s.GetSemanticSnapshot(visit->id).status()));

  SemanticSnapshotRecord r;
  r.visit_id = visit->id;
  r.model = "desk";
  r.class_count = 4;
  r.resolution_m = 0.05;
  r.keyframes = 12;
  r.bytes = std::string(Store::kSemanticChunkBytes * 2 + 17, 'a');  // three chunks
  r.bytes[Store::kSemanticChunkBytes] = 'b';
  r.updated_time_s = 5.0;
  ASSERT_TRUE(s.PutSemanticSnapshot(r).ok());
  auto got = s.GetSemanticSnapshot(visit->id);
  ASSERT_TRUE(got.ok()) << got.status();
  EXPECT_TRUE(got->bytes == r.bytes);
  EXPECT_EQ(got->model, "desk");
  EXPECT_EQ(got->class_count, 4);
  EXPECT_EQ(got->keyframes, 12);

  // A smaller snapshot replaces it whole (no chunk of the old one left behind).
  r.bytes = "small";
  r.keyframes = 13;
  ASSERT_TRUE(s.PutSemanticSnapshot(r).ok());
  got = s.GetSemanticSnapshot(visit->id);
  ASSERT_TRUE(got.ok()) << got.status();
  EXPECT_EQ(got->bytes, "small");
  EXPECT_EQ(got->keyframes, 13);

  r.visit_id = 999;
  EXPECT_TRUE(absl::IsNotFound(s.PutSemanticSnapshot(r)));
  ASSERT_TRUE(s.DeleteMap("m").ok());  // its visits, and their snapshots, go with it
  EXPECT_TRUE(absl::IsNotFound(s.GetSemanticSnapshot(visit->id).status()));
}

// Issue 16: a crash while a snapshot is written leaves the previous snapshot readable. A child
// process writes snapshots (three chunks each, every one its own size and filler) until it is
// killed; the one read afterwards is one of them, whole.
// Issue 17: a backup killed half-way leaves no file under its name (only a hidden partial), and
// every backup under its name is whole.
TEST(StoreBackup, AKillDuringABackupNeverLeavesATornBackupUnderItsName) {
  testing::TempDir tmp;
  const std::string data(24 << 20, 'm');  // a 24 MB model: each backup takes a while
  {
    auto store = Store::Open(tmp.File("db"));
    ASSERT_TRUE(store.ok()) << store.status();
    ModelRecord model;
    model.name = "big";
    ASSERT_TRUE((*store)->InsertModel(model, data).ok());
  }
  int whole = 0;
  for (int kill_after_ms : {30, 120, 300}) {
    const std::string prefix = tmp.File("backup-" + std::to_string(kill_after_ms) + "-");
    const pid_t child = fork();
    ASSERT_GE(child, 0);
    if (child == 0) {
      auto store = Store::Open(tmp.File("db"));
      if (!store.ok()) _exit(3);
      for (int n = 0;; ++n) {
        if (!(*store)->Backup(prefix + std::to_string(n)).ok()) _exit(4);
      }
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(kill_after_ms));
    kill(child, SIGKILL);
    int status = 0;
    ASSERT_EQ(waitpid(child, &status, 0), child);
    ASSERT_TRUE(WIFSIGNALED(status)) << "the backups stopped by themselves: status " << status;
    for (int n = 0; std::filesystem::exists(prefix + std::to_string(n)); ++n) {
      auto backup = Store::Open(prefix + std::to_string(n));
      ASSERT_TRUE(backup.ok()) << backup.status();
      auto problems = (*backup)->CheckIntegrity();
      ASSERT_TRUE(problems.ok());
      EXPECT_TRUE(problems->empty()) << prefix << n << ": " << problems->front();
      auto got = (*backup)->GetModelData("big");
      ASSERT_TRUE(got.ok()) << got.status();
      EXPECT_TRUE(*got == data) << prefix << n << " is not whole";
      ++whole;
    }
  }
  EXPECT_GT(whole, 0) << "no backup finished: the kill times are too short for this machine";
}

// Runs write(store, n) for n = 0, 1, 2, ... in a child process and SIGKILLs it after each of
// `kill_after_ms`; after each kill, `check` reads the file in this process and returns the n
// it found whole (-1: none written yet), failing the test for anything torn. The n found never
// goes back (what was committed stays).
void KillWhileWriting(const std::string& db, std::initializer_list<int> kill_after_ms,
                      const std::function<absl::Status(Store&, int64_t)>& write,
                      const std::function<int64_t(Store&)>& check) {
  int64_t last = -1;
  for (int ms : kill_after_ms) {
    const pid_t child = fork();
    ASSERT_GE(child, 0);
    if (child == 0) {
      auto store = Store::Open(db);
      if (!store.ok()) _exit(3);
      for (int64_t n = last + 1;; ++n) {
        if (!write(**store, n).ok()) _exit(4);
      }
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(ms));
    kill(child, SIGKILL);
    int status = 0;
    ASSERT_EQ(waitpid(child, &status, 0), child);
    ASSERT_TRUE(WIFSIGNALED(status)) << "the writer stopped by itself: status " << status;
    auto store = Store::Open(db);
    ASSERT_TRUE(store.ok()) << store.status();
    const int64_t found = check(**store);
    EXPECT_GE(found, last) << "a committed write was lost";
    last = found;
  }
  EXPECT_GT(last, 0) << "nothing was ever written: the kill times are too short here";
}

// Issue 17: a kill while a visit's floor plan, or an appearance vocabulary, is written leaves
// the previous one whole.
TEST(StoreKills, AKillWhileAFloorPlanIsWrittenLeavesThePreviousOneWhole) {
  testing::TempDir tmp;
  int64_t visit_id = 0;
  {
    auto store = Store::Open(tmp.File("db"));
    ASSERT_TRUE(store.ok());
    ASSERT_TRUE((*store)->CreateMap("m", "", 1.0).ok());
    visit_id = (*store)->StartVisit("m", "", "", 1.0)->id;
  }
  auto plan = [visit_id](int64_t n) {
    VisitPlaceRecord r;
    r.visit_id = visit_id;
    r.keyframes = static_cast<int>(n);
    r.floor_plan_json = std::string(2 << 20, static_cast<char>('a' + n % 26));
    r.descriptor_json = std::to_string(n);
    r.updated_time_s = 1.0 + n;
    return r;
  };
  KillWhileWriting(
      tmp.File("db"), {40, 150, 350}, [&](Store& s, int64_t n) { return s.PutVisitPlace(plan(n)); },
      [&](Store& s) -> int64_t {
        auto got = s.GetVisitPlace(visit_id);
        if (absl::IsNotFound(got.status())) return -1;
        EXPECT_TRUE(got.ok()) << got.status();
        if (!got.ok()) return -1;
        const VisitPlaceRecord expected = plan(got->keyframes);
        EXPECT_TRUE(got->floor_plan_json == expected.floor_plan_json &&
                    got->descriptor_json == expected.descriptor_json)
            << "floor plan " << got->keyframes << " is torn";
        return got->keyframes;
      });
}

TEST(StoreKills, AKillWhileAVocabularyIsWrittenLeavesTheOneInUseWhole) {
  testing::TempDir tmp;
  auto vocabulary = [](int64_t n) {
    VocabularyRecord r;
    r.source = "test";
    r.training_keyframes = n;
    r.words = n;
    r.data = std::string(4 << 20, static_cast<char>('a' + n % 26));
    return r;
  };
  KillWhileWriting(
      tmp.File("db"), {40, 150, 350},
      [&](Store& s, int64_t n) { return s.PutVocabulary(vocabulary(n)).status(); },
      [&](Store& s) -> int64_t {
        auto got = s.LatestVocabulary();
        EXPECT_TRUE(got.ok()) << got.status();
        if (!got.ok() || !*got) return -1;
        EXPECT_TRUE((*got)->data == vocabulary((*got)->training_keyframes).data)
            << "vocabulary " << (*got)->training_keyframes << " is torn";
        return (*got)->training_keyframes;
      });
}

TEST(SemanticSnapshotStore, AKillWhileASnapshotIsWrittenLeavesThePreviousOneWhole) {
  testing::TempDir tmp;
  int64_t visit_id = 0;
  {
    auto store = Store::Open(tmp.File("db"));
    ASSERT_TRUE(store.ok()) << store.status();
    ASSERT_TRUE((*store)->CreateMap("m", "", 1.0).ok());
    auto visit = (*store)->StartVisit("m", "", "", 1.0);
    ASSERT_TRUE(visit.ok());
    visit_id = visit->id;
  }
  auto snapshot = [visit_id](int64_t n) {
    SemanticSnapshotRecord r;
    r.visit_id = visit_id;
    r.model = "desk";
    r.class_count = 4;
    r.resolution_m = 0.05;
    r.keyframes = n;
    r.bytes = std::string(Store::kSemanticChunkBytes * 2 + static_cast<size_t>(n),
                          static_cast<char>('a' + n % 26));
    return r;
  };
  KillWhileWriting(
      tmp.File("db"), {40, 150, 350},
      [&](Store& s, int64_t n) { return s.PutSemanticSnapshot(snapshot(n)); },
      [&](Store& s) -> int64_t {
        auto got = s.GetSemanticSnapshot(visit_id);
        if (absl::IsNotFound(got.status())) return -1;
        EXPECT_TRUE(got.ok()) << got.status();
        if (!got.ok()) return -1;
        EXPECT_TRUE(got->bytes == snapshot(got->keyframes).bytes)
            << "snapshot " << got->keyframes << " is not whole: " << got->bytes.size() << " bytes";
        return got->keyframes;
      });
}

// Issue 35: an anchor revision is one transaction. One that fails part-way (an edge to a
// keyframe that is gone) changes nothing; and a kill while revisions are written leaves the
// visit's keyframes, its anchor and its history all at the same revision; so does a drop.
TEST(StoreKills, AKillDuringAnAnchorRevisionOrDropLeavesTheLastConsistentPoses) {
  testing::TempDir tmp;
  int64_t visit_id = 0, reference_keyframe = 0;
  std::vector<int64_t> keyframe_ids;
  {
    auto store = Store::Open(tmp.File("db"));
    ASSERT_TRUE(store.ok());
    ASSERT_TRUE((*store)->CreateMap("m", "", 1.0).ok());
    auto first = (*store)->StartVisit("m", "", "", 1.0);
    std::vector<KeyframeRecord> reference = {Keyframe(first->id, 1.0)};
    ASSERT_TRUE((*store)->InsertKeyframes(&reference, {}).ok());
    reference_keyframe = reference[0].id;
    auto second = (*store)->StartVisit("m", "", "", 2.0);
    visit_id = second->id;
    // Enough keyframes that a revision takes a while to write.
    std::vector<KeyframeRecord> batch;
    for (int i = 0; i < 3000; ++i) {
      KeyframeRecord k = Keyframe(visit_id, 10.0 + i * 0.01);
      k.T_world_camera->translation = {0.0, 0.001 * i, 0.0};
      k.pose_source = StoredPoseSource::kEstimated;
      k.T_odom_camera = k.T_world_camera;
      batch.push_back(k);
    }
    ASSERT_TRUE((*store)->InsertKeyframes(&batch, {}).ok());
    for (const auto& k : batch) keyframe_ids.push_back(k.id);
    PoseEdgeRecord edge;
    edge.map_id = second->map_id;
    edge.kind = StoredEdgeKind::kAnchor;
    edge.from_keyframe = reference_keyframe;
    edge.to_keyframe = keyframe_ids[0];
    edge.accepted = true;
    edge.reason = "anchors it";
    VisitAnchor anchor;
    anchor.to_visit_id = first->id;
    ASSERT_TRUE((*store)->AnchorVisit(visit_id, edge, &anchor).ok());
    // A revision resting on an edge to a keyframe that does not exist fails and changes nothing.
    PoseEdgeRecord dangling = edge;
    dangling.to_keyframe = 999999;
    Pose moved;
    moved.translation = {5, 0, 0};
    VisitAnchor revised = anchor;
    revised.T_map_visit = moved;
    const absl::Status failed =
        (*store)->ReviseAnchor(visit_id, moved, {edge, dangling}, "test", &revised);
    EXPECT_TRUE(absl::IsNotFound(failed)) << failed;
    auto kept = (*store)->ListKeyframes(second->map_id, visit_id);
    ASSERT_TRUE(kept.ok());
    EXPECT_NEAR(kept->back().T_world_camera->translation.x(), 0.0, 1e-12) << "nothing moved";
    EXPECT_EQ((*store)->ListAnchorRevisions(visit_id)->size(), 1u);
    auto edges = (*store)->ListPoseEdges(second->map_id, visit_id);
    ASSERT_TRUE(edges.ok());
    ASSERT_EQ(edges->size(), 1u);
    EXPECT_TRUE((*edges)[0].accepted) << "the anchor's edge was not superseded";
  }
  // Revision n moves the visit 1 m further along x: after a kill, every keyframe, the anchor
  // and the history say the same n.
  auto revise = [&](Store& s, int64_t n) {
    Pose step;
    step.translation = {1.0, 0, 0};
    PoseEdgeRecord edge;
    edge.map_id = 1;
    edge.kind = StoredEdgeKind::kAnchor;
    edge.from_keyframe = reference_keyframe;
    edge.to_keyframe = keyframe_ids[static_cast<size_t>(n) % keyframe_ids.size()];
    edge.accepted = true;
    edge.reason = absl::StrCat("revision ", n + 1);
    VisitAnchor anchor;
    anchor.to_visit_id = 1;
    anchor.T_map_visit.translation = {static_cast<double>(n + 1), 0, 0};
    return s.ReviseAnchor(visit_id, step, {edge}, absl::StrCat("test revision ", n + 1), &anchor);
  };
  KillWhileWriting(tmp.File("db"), {150, 400, 900}, revise, [&](Store& s) -> int64_t {
    auto history = s.ListAnchorRevisions(visit_id);
    EXPECT_TRUE(history.ok()) << history.status();
    if (!history.ok()) return -1;
    const int64_t revisions = static_cast<int64_t>(history->size()) - 1;
    auto visit = s.GetVisit(visit_id);
    EXPECT_TRUE(visit.ok() && visit->anchor);
    if (!visit.ok() || !visit->anchor) return -1;
    EXPECT_EQ(visit->anchor->revisions, revisions);
    EXPECT_NEAR(visit->anchor->T_map_visit.translation.x(), static_cast<double>(revisions), 1e-9);
    auto keyframes = s.ListKeyframes(visit->map_id, visit_id);
    EXPECT_TRUE(keyframes.ok());
    if (!keyframes.ok()) return -1;
    for (const auto& k : *keyframes) {
      if (std::abs(k.T_world_camera->translation.x() - static_cast<double>(revisions)) > 1e-9) {
        ADD_FAILURE() << "keyframe " << k.id << " at x = " << k.T_world_camera->translation.x()
                      << " after " << revisions << " revisions: torn";
        break;
      }
    }
    return revisions - 1;  // the last n written whole
  });

  // Drops and anchors in turn (n even: the anchor dropped, its keyframes back in the visit's
  // own frame at x = 0; n odd: anchored anew at x = 1): after a kill, the keyframes, the visit
  // and the history's last entry agree.
  size_t base = 0;
  {
    auto store = Store::Open(tmp.File("db"));
    ASSERT_TRUE(store.ok());
    base = (*store)->ListAnchorRevisions(visit_id)->size();
    EXPECT_TRUE(absl::IsNotFound((*store)->DropAnchor(999999, "test", 1.0).status()));
  }
  auto drop_or_anchor = [&](Store& s, int64_t n) -> absl::Status {
    if (n % 2 == 0) return s.DropAnchor(visit_id, absl::StrCat("test drop ", n), 1.0).status();
    PoseEdgeRecord edge;
    edge.map_id = 1;
    edge.kind = StoredEdgeKind::kAnchor;
    edge.from_keyframe = reference_keyframe;
    edge.to_keyframe = keyframe_ids[0];
    edge.accepted = true;
    edge.reason = absl::StrCat("anchor ", n);
    VisitAnchor anchor;
    anchor.to_visit_id = 1;
    anchor.T_map_visit.translation = {1.0, 0, 0};
    return s.AnchorVisit(visit_id, edge, &anchor);
  };
  KillWhileWriting(tmp.File("db"), {150, 400, 900}, drop_or_anchor, [&](Store& s) -> int64_t {
    auto history = s.ListAnchorRevisions(visit_id);
    EXPECT_TRUE(history.ok()) << history.status();
    if (!history.ok() || history->size() < base) return -1;
    const int64_t done = static_cast<int64_t>(history->size() - base);
    auto visit = s.GetVisit(visit_id);
    EXPECT_TRUE(visit.ok());
    if (!visit.ok() || done == 0) return -1;
    const bool dropped = history->back().action == "dropped";
    EXPECT_EQ(dropped, done % 2 == 1);
    EXPECT_EQ(visit->anchor.has_value(), !dropped);
    EXPECT_EQ(visit->anchor_dropped.empty(), !dropped) << visit->anchor_dropped;
    if (dropped) {
      EXPECT_TRUE(absl::IsFailedPrecondition(s.DropAnchor(visit_id, "again", 1.0).status()))
          << "an unanchored visit has no anchor to drop";
    }
    auto keyframes = s.ListKeyframes(visit->map_id, visit_id);
    EXPECT_TRUE(keyframes.ok());
    if (!keyframes.ok()) return -1;
    const double x = dropped ? 0.0 : 1.0;
    for (const auto& k : *keyframes) {
      if (std::abs(k.T_world_camera->translation.x() - x) > 1e-9) {
        ADD_FAILURE() << "keyframe " << k.id << " at x = " << k.T_world_camera->translation.x()
                      << " after " << history->back().action << ": torn";
        break;
      }
    }
    return done - 1;
  });
}

}  // namespace
}  // namespace lifemap::store
