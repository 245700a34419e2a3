#include "server/config.h"
#include "server/rpc/auth.h"

#include <set>

#include <gtest/gtest.h>

#include "tests/testing/test_util.h"

namespace lifemap::server {
namespace {

TEST(Auth, LoopbackAddressesAreTheOnlyOnesExemptFromKeys) {
  for (const char* local : {"127.0.0.1:50051", "127.1.2.3:0", "localhost:50051", "LOCALHOST:1",
                            "[::1]:50051", "unix:/run/lifemap.sock"}) {
    EXPECT_TRUE(IsLoopbackAddress(local)) << local;
  }
  for (const char* remote :
       {"0.0.0.0:50051", "[::]:50051", "192.168.1.5:50051", "10.0.0.1:1", "robot-server.lan:50051",
        "[fe80::1]:50051", "128.0.0.1:50051", ":50051"}) {
    EXPECT_FALSE(IsLoopbackAddress(remote)) << remote;
  }
}

TEST(Auth, SecretsAreRandomAndOnlyTheirSha256IsKept) {
  std::set<std::string> seen;
  for (int i = 0; i < 100; ++i) {
    const std::string secret = NewApiKeySecret();
    EXPECT_EQ(secret.size(), 47u);
    EXPECT_EQ(secret.rfind("lmk_", 0), 0u);
    EXPECT_EQ(secret.find_first_not_of("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz"
                                       "0123456789-_",
                                       4),
              std::string::npos)
        << secret;
    EXPECT_TRUE(seen.insert(secret).second);
  }
  // FIPS 180-2's test vector.
  EXPECT_EQ(ApiKeyHash("abc"), "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");
}

TEST(Auth, RolesAreOrderedAndNamed) {
  EXPECT_LT(Role::kRobot, Role::kOperator);
  EXPECT_LT(Role::kOperator, Role::kAdmin);
  for (Role r : {Role::kRobot, Role::kOperator, Role::kAdmin}) {
    EXPECT_EQ(ParseRole(RoleName(r)), r);
  }
  EXPECT_FALSE(ParseRole("root").has_value());
  EXPECT_EQ(RequiredRole("MapService/DeleteMap"), Role::kOperator);
  EXPECT_EQ(RequiredRole("AdminService/Backup"), Role::kAdmin);
  EXPECT_EQ(RequiredRole("FrameService/StreamFrames"), Role::kRobot);
  EXPECT_FALSE(RequiredRole("MapService/Nothing").has_value());
}

TEST(Auth, APrincipalLimitedToMapsNamesThemWhenRefusing) {
  Principal p;
  p.key_name = "lab-robot";
  p.role = Role::kRobot;
  p.every_map = false;
  p.map_ids = {3};
  p.map_names = {"lab"};
  EXPECT_TRUE(p.CheckMap(3, "lab").ok());
  const absl::Status s = p.CheckMap(4, "hall");
  EXPECT_TRUE(absl::IsPermissionDenied(s));
  EXPECT_NE(s.message().find("may use only the maps lab, not 'hall'"), std::string::npos) << s;
  EXPECT_TRUE(absl::IsPermissionDenied(p.CheckEveryMap("creating maps")));
  EXPECT_TRUE(Principal().CheckEveryMap("creating maps").ok());
}

TEST(Auth, KeysAreCreatedListedAndRevokedInTheStore) {
  testing::TempDir tmp;
  auto store = store::Store::Open(tmp.File("lifemap.db"));
  ASSERT_TRUE(store.ok());
  ASSERT_TRUE((*store)->CreateMap("lab", "", 1.0).ok());
  auto robot = CreateApiKey(store->get(), "r1", Role::kRobot, {"lab"}, {}, 10.0);
  ASSERT_TRUE(robot.ok()) << robot.status();
  EXPECT_EQ(robot->second.secret_sha256, ApiKeyHash(robot->first));
  EXPECT_FALSE(robot->second.every_map);
  EXPECT_EQ(robot->second.map_names, std::vector<std::string>{"lab"});
  EXPECT_TRUE(
      absl::IsAlreadyExists(CreateApiKey(store->get(), "r1", Role::kRobot, {}, {}, 11.0).status()));
  EXPECT_TRUE(absl::IsNotFound(
      CreateApiKey(store->get(), "r2", Role::kRobot, {"nowhere"}, {}, 11.0).status()));
  EXPECT_TRUE(absl::IsInvalidArgument(
      CreateApiKey(store->get(), "a", Role::kAdmin, {"lab"}, {}, 11.0).status()));
  EXPECT_TRUE(absl::IsInvalidArgument(
      CreateApiKey(store->get(), "a/b", Role::kAdmin, {}, {}, 11.0).status()));
  // A failed create leaves nothing behind.
  auto keys = (*store)->ListApiKeys();
  ASSERT_TRUE(keys.ok());
  ASSERT_EQ(keys->size(), 1u);
  auto revoked = (*store)->RevokeApiKey("r1", 20.0);
  ASSERT_TRUE(revoked.ok());
  EXPECT_EQ(revoked->revoked_time_s, 20.0);
  EXPECT_EQ((*store)->RevokeApiKey("r1", 30.0)->revoked_time_s, 20.0);
  EXPECT_TRUE(absl::IsNotFound((*store)->RevokeApiKey("nobody", 30.0).status()));
  ASSERT_TRUE((*store)->TouchApiKey(revoked->id, 25.0).ok());
  EXPECT_EQ((*store)->ListApiKeys()->at(0).last_used_time_s, 25.0);
  // Its map deleted, the key stays limited (to nothing).
  ASSERT_TRUE((*store)->DeleteMap("lab").ok());
  keys = (*store)->ListApiKeys();
  ASSERT_TRUE(keys.ok());
  EXPECT_FALSE(keys->at(0).every_map);
  EXPECT_TRUE(keys->at(0).map_ids.empty());
}

TEST(Auth, TheAuditLogListsNewestFirstFromATime) {
  testing::TempDir tmp;
  auto store = store::Store::Open(tmp.File("lifemap.db"));
  ASSERT_TRUE(store.ok());
  for (int i = 0; i < 5; ++i) {
    store::AuditEventRecord e;
    e.time_s = 100.0 + i;
    e.key_name = "k";
    e.method = "MapService/DeleteMap";
    e.request = "name=m" + std::to_string(i);
    e.code = "OK";
    ASSERT_TRUE((*store)->AppendAuditEvent(e).ok());
  }
  auto events = (*store)->ListAuditEvents(102.0, 2);
  ASSERT_TRUE(events.ok());
  ASSERT_EQ(events->size(), 2u);
  EXPECT_EQ(events->at(0).request, "name=m4");
  EXPECT_EQ(events->at(1).request, "name=m3");
  EXPECT_EQ((*store)->ListAuditEvents(102.0, 100)->size(), 3u);
  // Retention: events before a time go, the rest stay.
  auto pruned = (*store)->PruneAuditEvents(103.0);
  ASSERT_TRUE(pruned.ok()) << pruned.status();
  EXPECT_EQ(*pruned, 3);
  auto left = (*store)->ListAuditEvents(0.0, 100);
  ASSERT_TRUE(left.ok());
  ASSERT_EQ(left->size(), 2u);
  EXPECT_EQ(left->at(1).request, "name=m3");
  EXPECT_EQ(*(*store)->PruneAuditEvents(103.0), 0);
}

}  // namespace
}  // namespace lifemap::server
