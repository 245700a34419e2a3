// The cluster's one key ring (issue 39) against an in-memory placement: what a shard's store
// gives the ring and what it takes from it. The whole cluster, with PostgreSQL and nginx, runs
// in Cluster.* (tests/cluster).
#include "server/rpc/cluster_keys.h"

#include <gtest/gtest.h>

#include <map>

#include "absl/strings/match.h"
#include "tests/testing/test_util.h"

namespace lifemap::server {
namespace {

// The key ring and map names of a placement database, in memory; the rest is not needed here.
class MemoryPlacement final : public placement::Placement {
 public:
  std::map<std::string, placement::ClusterKey> keys;
  std::map<std::string, std::string> maps;  // name -> shard

  absl::Status AddShard(const std::string&, const std::string&, double) override {
    return absl::UnimplementedError("not here");
  }
  absl::StatusOr<std::vector<placement::Shard>> ListShards() override {
    return absl::UnimplementedError("not here");
  }
  absl::StatusOr<placement::Shard> GetShard(const std::string&) override {
    return absl::UnimplementedError("not here");
  }
  absl::Status SetShardState(const std::string&, const std::string&) override {
    return absl::UnimplementedError("not here");
  }
  absl::Status RemoveShard(const std::string&) override {
    return absl::UnimplementedError("not here");
  }
  absl::Status Heartbeat(const std::string&, double) override { return absl::OkStatus(); }
  absl::StatusOr<std::vector<placement::MapPlacement>> ListMaps(const std::string&) override {
    return absl::UnimplementedError("not here");
  }
  absl::StatusOr<std::optional<placement::MapPlacement>> FindMap(const std::string& map) override {
    const auto it = maps.find(map);
    if (it == maps.end()) return std::nullopt;
    placement::MapPlacement m;
    m.map = it->first;
    m.shard = it->second;
    m.state = "active";
    return m;
  }
  absl::Status PlaceMap(const std::string&, const std::string&, double) override {
    return absl::UnimplementedError("not here");
  }
  absl::Status UnplaceMap(const std::string&, const std::string&) override {
    return absl::UnimplementedError("not here");
  }
  absl::StatusOr<std::unique_ptr<placement::MoveLock>> LockMove(const std::string&) override {
    return absl::UnimplementedError("not here");
  }
  absl::Status BeginMove(const std::string&, const std::string&, double) override {
    return absl::UnimplementedError("not here");
  }
  absl::Status AdvanceMove(const std::string&, const std::string&) override {
    return absl::UnimplementedError("not here");
  }
  absl::Status AbortMove(const std::string&) override {
    return absl::UnimplementedError("not here");
  }
  absl::Status AddKey(const placement::ClusterKey& key) override {
    if (!keys.emplace(key.name, key).second) return absl::AlreadyExistsError(key.name);
    return absl::OkStatus();
  }
  absl::StatusOr<placement::ClusterKey> RevokeKey(const std::string& name, double now_s) override {
    const auto it = keys.find(name);
    if (it == keys.end()) return absl::NotFoundError(name);
    if (it->second.revoked_s == 0) it->second.revoked_s = now_s;
    return it->second;
  }
  absl::StatusOr<std::vector<placement::ClusterKey>> ListKeys() override {
    std::vector<placement::ClusterKey> out;
    for (const auto& [name, key] : keys) out.push_back(key);
    return out;
  }
};

const store::ApiKeyRecord* Find(const std::vector<store::ApiKeyRecord>& keys,
                                const std::string& name) {
  for (const auto& k : keys) {
    if (k.name == name) return &k;
  }
  return nullptr;
}

TEST(ClusterKeys, AShardsKeysJoinTheRingAndTheRingsKeysReachEveryShard) {
  testing::TempDir tmp;
  auto s1 = store::Store::Open(tmp.File("s1.db"));
  auto s2 = store::Store::Open(tmp.File("s2.db"));
  ASSERT_TRUE(s1.ok() && s2.ok());
  ASSERT_TRUE((*s1)->CreateMap("lab", "", 1.0).ok());
  ASSERT_TRUE((*s2)->CreateMap("office", "", 1.0).ok());
  MemoryPlacement ring;
  ring.maps = {{"lab", "s1"}, {"office", "s2"}};
  ClusterKeyRing k1(&ring, s1->get(), nullptr);
  ClusterKeyRing k2(&ring, s2->get(), nullptr);

  // A key made on s1's machine before (or while) it is a shard joins the ring at its sync...
  auto admin = CreateApiKey(s1->get(), "admin", Role::kAdmin, {}, {}, 10.0);
  ASSERT_TRUE(admin.ok()) << admin.status();
  ASSERT_TRUE(k1.Sync().ok());
  ASSERT_EQ(1u, ring.keys.count("admin"));
  EXPECT_EQ(ApiKeyHash(admin->first), ring.keys["admin"].secret_sha256);
  // ... and reaches s2, which had no key at all.
  ASSERT_TRUE(k2.Sync().ok());
  auto on_s2 = (*s2)->ListApiKeys();
  ASSERT_TRUE(on_s2.ok());
  ASSERT_NE(nullptr, Find(*on_s2, "admin"));
  EXPECT_EQ(ApiKeyHash(admin->first), Find(*on_s2, "admin")->secret_sha256);
  EXPECT_TRUE(HasLiveAdminKey(s2->get()).value());

  // A call with a key the store lacks fetches the ring's keys, at most once a second.
  EXPECT_TRUE(k2.FetchNewKeys());
  EXPECT_FALSE(k2.FetchNewKeys()) << "a second fetch within kFetchIntervalS";

  // A key limited to maps names them across the cluster; each shard lets it use those it holds.
  auto robot = k2.Create("robot", Role::kRobot, {"lab", "office"}, {}, 20.0);
  ASSERT_TRUE(robot.ok()) << robot.status();
  EXPECT_EQ((std::vector<std::string>{"lab", "office"}), robot->second.map_names);
  ASSERT_TRUE(k1.Sync().ok());
  const std::vector<store::ApiKeyRecord> keys_s1 = *(*s1)->ListApiKeys();
  const auto* on_s1 = Find(keys_s1, "robot");
  ASSERT_NE(nullptr, on_s1);
  EXPECT_FALSE(on_s1->every_map);
  EXPECT_EQ(std::vector<std::string>{"lab"}, on_s1->map_names);
  EXPECT_EQ(std::vector<int64_t>{(*s1)->GetMap("lab")->id}, on_s1->map_ids);
  const std::vector<store::ApiKeyRecord> keys_s2 = *(*s2)->ListApiKeys();
  const auto* robot_s2 = Find(keys_s2, "robot");
  ASSERT_NE(nullptr, robot_s2);
  EXPECT_EQ(std::vector<std::string>{"office"}, robot_s2->map_names);
  // The ring's listing names every map of the key, wherever it is.
  auto listed = k1.List();
  ASSERT_TRUE(listed.ok());
  EXPECT_EQ((std::vector<std::string>{"lab", "office"}), Find(*listed, "robot")->map_names);

  // A map unknown to the cluster, a name in use anywhere, an admin key with maps: refused.
  EXPECT_TRUE(absl::IsNotFound(k1.Create("r2", Role::kRobot, {"attic"}, {}, 21.0).status()));
  EXPECT_TRUE(absl::IsAlreadyExists(k1.Create("robot", Role::kRobot, {}, {}, 21.0).status()));
  EXPECT_TRUE(absl::IsInvalidArgument(k1.Create("a2", Role::kAdmin, {"lab"}, {}, 21.0).status()));

  // A map moved to s1 (imported there): the key may use it on s1 at the next sync.
  ASSERT_TRUE((*s1)->CreateMap("office", "", 30.0).ok());
  ASSERT_TRUE(k1.Sync().ok());
  EXPECT_EQ((std::vector<std::string>{"lab", "office"}),
            Find(*(*s1)->ListApiKeys(), "robot")->map_names);

  // Revoked through one shard: revoked in the ring and, at its next sync, on the other.
  auto revoked = k1.Revoke("robot", 40.0);
  ASSERT_TRUE(revoked.ok()) << revoked.status();
  EXPECT_EQ(40.0, revoked->revoked_time_s);
  EXPECT_EQ(40.0, Find(*(*s1)->ListApiKeys(), "robot")->revoked_time_s);
  ASSERT_TRUE(k2.Sync().ok());
  EXPECT_EQ(40.0, Find(*(*s2)->ListApiKeys(), "robot")->revoked_time_s);
  EXPECT_TRUE(absl::IsNotFound(k1.Revoke("nobody", 41.0).status()));

  // Revoked on a shard's machine (`lifemapd keys revoke --db`): revoked in the ring, then
  // everywhere; never made live again.
  ASSERT_TRUE((*s2)->RevokeApiKey("admin", 50.0).ok());
  ASSERT_TRUE(k2.Sync().ok());
  EXPECT_EQ(50.0, ring.keys["admin"].revoked_s);
  ASSERT_TRUE(k1.Sync().ok());
  EXPECT_EQ(50.0, Find(*(*s1)->ListApiKeys(), "admin")->revoked_time_s);
}

TEST(ClusterKeys, AShardsKeyWithTheRingsNameButAnotherSecretGivesWayToTheRings) {
  testing::TempDir tmp;
  auto s1 = store::Store::Open(tmp.File("s1.db"));
  auto s2 = store::Store::Open(tmp.File("s2.db"));
  ASSERT_TRUE(s1.ok() && s2.ok());
  MemoryPlacement ring;
  ClusterKeyRing k1(&ring, s1->get(), nullptr);
  ClusterKeyRing k2(&ring, s2->get(), nullptr);
  auto first = CreateApiKey(s1->get(), "ops", Role::kOperator, {}, {}, 10.0);
  auto second = CreateApiKey(s2->get(), "ops", Role::kAdmin, {}, {}, 11.0);
  ASSERT_TRUE(first.ok() && second.ok());
  ASSERT_TRUE(k1.Sync().ok());
  ASSERT_TRUE((*s2)->TouchApiKey(second->second.id, 12.0).ok());
  // s2's own revocation of its other key must not revoke the ring's.
  ASSERT_TRUE((*s2)->RevokeApiKey("ops", 13.0).ok());
  ASSERT_TRUE(k2.Sync().ok());
  EXPECT_EQ(0.0, ring.keys["ops"].revoked_s);
  const std::vector<store::ApiKeyRecord> keys = *(*s2)->ListApiKeys();
  const auto* ops = Find(keys, "ops");
  ASSERT_NE(nullptr, ops);
  EXPECT_EQ(ApiKeyHash(first->first), ops->secret_sha256);
  EXPECT_EQ("operator", ops->role);
  EXPECT_EQ(0.0, ops->revoked_time_s);
  EXPECT_EQ(12.0, ops->last_used_time_s) << "a shard's own record of use is kept";
}

}  // namespace
}  // namespace lifemap::server
