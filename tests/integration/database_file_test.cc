// The database file under a running server (issue 33, items 2 and 3): the lock is the file's,
// not the path's, and a file deleted or replaced beneath the server refuses every write
// instead of acknowledging writes a restart would not find.
#include <chrono>
#include <filesystem>
#include <thread>

#include "tests/integration/server_fixture.h"

namespace lifemap {
namespace {

namespace fs = std::filesystem;

class DatabaseFileTest : public testing::ServerTest {
 protected:
  // A frame of map "lab" that the server selects as a keyframe (the visit's first, or one
  // `seconds` later than the last).
  absl::StatusOr<v1::FrameResult> Keyframe(double timestamp_s) {
    v1::ProcessFrameRequest req;
    req.set_map("lab");
    *req.mutable_frame() = testing::MakeFrame(320, 240, 1.5, timestamp_s);
    return client_->ProcessFrame(req);
  }

  bool Serving() { return testing::CheckHealth(target_).serving; }

  // Polls Serving() until it is `want` or `seconds` passed.
  bool ServingBecomes(bool want, double seconds) {
    const auto until = std::chrono::steady_clock::now() + std::chrono::duration<double>(seconds);
    while (std::chrono::steady_clock::now() < until) {
      if (Serving() == want) return true;
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
    return Serving() == want;
  }

  // Deleting the database under the server and what it must then do: refuse writes naming the
  // file, report the problem in CheckIntegrity and health, and after a restart hold nothing
  // that was acknowledged since.
  void ExpectWritesRefusedAfterDeleting(const std::vector<std::string>& suffixes) {
    ASSERT_TRUE(client_->CreateMap("lab", "").ok());
    auto first = Keyframe(1000);
    ASSERT_TRUE(first.ok()) << first.status();
    ASSERT_TRUE(first->keyframe().committed());
    ASSERT_TRUE(Serving());
    for (const auto& suffix : suffixes) fs::remove(config_.db_path + suffix);

    const absl::Status created = client_->CreateMap("hall", "").status();
    EXPECT_TRUE(absl::IsFailedPrecondition(created)) << created;
    EXPECT_NE(created.message().find("deleted, moved or replaced"), std::string::npos) << created;
    auto later = Keyframe(1010);
    ASSERT_TRUE(later.ok()) << later.status();
    EXPECT_TRUE(later->keyframe().selected());
    EXPECT_FALSE(later->keyframe().committed()) << "acknowledged onto a deleted file";
    EXPECT_NE(later->keyframe().reason().find("deleted"), std::string::npos)
        << later->keyframe().reason();
    auto check = client_->CheckIntegrity();
    ASSERT_TRUE(check.ok()) << check.status();
    EXPECT_FALSE(check->ok());
    ASSERT_GE(check->problems_size(), 1);
    EXPECT_NE(check->problems(0).find(config_.db_path), std::string::npos) << check->problems(0);
    EXPECT_TRUE(ServingBecomes(false, 3.0)) << "health checks must say the server cannot write";
  }
};

TEST_F(DatabaseFileTest, ADeletedDatabaseRefusesEveryWriteAndSaysSo) {
  ExpectWritesRefusedAfterDeleting({"", "-wal", "-shm"});
  // A restart opens what is at the path now: a new, empty database. Nothing was acknowledged
  // after the deletion, so nothing acknowledged is missing from it.
  RestartServer();
  auto maps = client_->ListMaps();
  ASSERT_TRUE(maps.ok()) << maps.status();
  EXPECT_EQ(maps->maps_size(), 0);
}

TEST_F(DatabaseFileTest, ADeletedWriteAheadLogRefusesEveryWrite) {
  ExpectWritesRefusedAfterDeleting({"-wal"});
}

TEST_F(DatabaseFileTest, AReplacedDatabaseRefusesEveryWrite) {
  ASSERT_TRUE(client_->CreateMap("lab", "").ok());
  // An operator restores a copy over the live file (rename: a new inode at the path).
  fs::copy_file(config_.db_path, tmp_.File("copy.db"));
  fs::rename(tmp_.File("copy.db"), config_.db_path);
  const absl::Status created = client_->CreateMap("hall", "").status();
  EXPECT_TRUE(absl::IsFailedPrecondition(created)) << created;
}

TEST_F(DatabaseFileTest, TheLockIsTheFilesSoALinkToItIsRefused) {
  const std::string hard = tmp_.File("hard-link.db");
  const std::string soft = tmp_.File("symbolic-link.db");
  fs::create_hard_link(config_.db_path, hard);
  fs::create_symlink(config_.db_path, soft);
  for (const std::string& path : {config_.db_path, hard, soft}) {
    server::ServerConfig second = config_;
    second.db_path = path;
    second.listen = "127.0.0.1:0";
    auto s = server::LifemapServer::Start(second);
    ASSERT_FALSE(s.ok()) << path << " opened beside the running server";
    EXPECT_TRUE(absl::IsFailedPrecondition(s.status())) << s.status();
    EXPECT_NE(s.status().message().find("open in another lifemapd"), std::string::npos)
        << s.status();
  }
  // The first server is unharmed (a refused start must not drop its SQLite locks).
  ASSERT_TRUE(client_->CreateMap("lab", "").ok());
  auto r = Keyframe(1000);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_TRUE(r->keyframe().committed());
}

}  // namespace
}  // namespace lifemap
