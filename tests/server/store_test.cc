#include "server/store/store.h"

#include <sqlite3.h>

#include <fstream>

#include <gtest/gtest.h>

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
  k.depth_png = "depth-bytes";
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
  std::vector<KeyframeRecord> batch = {Keyframe(visit->id, 2.0), Keyframe(visit->id, 1.0, false)};
  ASSERT_TRUE(store_->InsertKeyframes(&batch, {{visit->id, 17}}).ok());
  EXPECT_GT(batch[0].id, 0);
  EXPECT_GT(batch[1].id, batch[0].id);

  auto map = store_->GetMap("m");
  ASSERT_TRUE(map.ok());
  EXPECT_EQ(map->keyframe_count, 2);
  EXPECT_EQ(map->visit_count, 1);
  auto list = store_->ListKeyframes(map->id, 0);
  ASSERT_TRUE(list.ok());
  ASSERT_EQ(list->size(), 2u);
  EXPECT_DOUBLE_EQ((*list)[0].timestamp_s, 1.0) << "time order";
  EXPECT_FALSE((*list)[0].T_world_camera.has_value());
  EXPECT_TRUE((*list)[0].depth_png.empty()) << "listing carries no images";

  auto k = store_->GetKeyframe(map->id, batch[0].id);
  ASSERT_TRUE(k.ok());
  EXPECT_EQ(k->depth_png, "depth-bytes");
  EXPECT_EQ(k->color, "color-bytes");
  ASSERT_TRUE(k->T_world_camera.has_value());
  EXPECT_DOUBLE_EQ(k->T_world_camera->translation.z(), 6.0);

  auto v = store_->GetVisit(visit->id);
  ASSERT_TRUE(v.ok());
  EXPECT_EQ(v->frame_count, 17);
  EXPECT_EQ(v->keyframe_count, 2);
  auto last = store_->LastKeyframe(visit->id);
  ASSERT_TRUE(last.ok() && last->has_value());
  EXPECT_DOUBLE_EQ((*last)->timestamp_s, 2.0);
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
  ASSERT_TRUE(store_->EndVisit(visit->id, 2.0, 0).ok());
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

TEST_F(StoreTest, EndedVisitIsNotTheLatestOpenOne) {
  ASSERT_TRUE(store_->CreateMap("m", "", 1.0).ok());
  auto v1 = store_->StartVisit("m", "", "", 1.0);
  auto v2 = store_->StartVisit("m", "", "", 2.0);
  auto open = store_->LatestOpenVisit("m");
  ASSERT_TRUE(open.ok() && open->has_value());
  EXPECT_EQ((*open)->id, v2->id);
  ASSERT_TRUE(store_->EndVisit(v2->id, 3.0, 5).ok());
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

TEST_F(StoreTest, BackupIsAReadableCopy) {
  ASSERT_TRUE(store_->CreateMap("m", "", 1.0).ok());
  EXPECT_TRUE(absl::IsInvalidArgument(store_->Backup("relative.db")));
  ASSERT_TRUE(store_->Backup(tmp_.File("backup.db")).ok());
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

TEST(MapName, ValidatesCharactersAndLength) {
  EXPECT_TRUE(ValidateMapName("office_2-b.v1").ok());
  EXPECT_FALSE(ValidateMapName("").ok());
  EXPECT_FALSE(ValidateMapName(std::string(65, 'a')).ok());
  EXPECT_FALSE(ValidateMapName("has space").ok());
  EXPECT_FALSE(ValidateMapName("../etc").ok());
  EXPECT_FALSE(ValidateMapName(".hidden").ok());
}

}  // namespace
}  // namespace lifemap::store
