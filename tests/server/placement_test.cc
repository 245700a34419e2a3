// The cluster's pieces that need no PostgreSQL or nginx (issue 39): nginx's routing table as
// written from a placement, shard names, ids kept by an import that moves a map, and the
// config's shard flags. The whole cluster runs in Cluster.* (tests/cluster).
#include <gtest/gtest.h>

#include <filesystem>

#include "absl/strings/match.h"
#include "server/config.h"
#include "server/placement/nginx_config.h"
#include "server/placement/placement.h"

namespace lifemap::placement {
namespace {

std::vector<Shard> TwoShards() {
  Shard a;
  a.name = "s1";
  a.address = "10.0.0.1:50051";
  a.state = "active";
  Shard b;
  b.name = "s2";
  b.address = "10.0.0.2:50051";
  b.state = "draining";
  return {a, b};
}

// The text between `open` and the next "}".
std::string Block(const std::string& conf, const std::string& open) {
  const size_t at = conf.find(open);
  if (at == std::string::npos) return "";
  return conf.substr(at, conf.find('}', at) - at);
}

TEST(NginxConfig, RoutesPlacedMapsToTheirShardAndNewMapsOverActiveShardsOnly) {
  MapPlacement lab;
  lab.map = "lab";
  lab.shard = "s2";
  lab.state = "active";
  MapPlacement moved;  // switched: the placement's shard is the target already
  moved.map = "hall";
  moved.shard = "s1";
  moved.state = "moving";
  moved.move_from = "s2";
  moved.move_phase = "switched";
  NginxOptions options;
  options.prefix = "/run/lifemap-nginx";
  const std::string conf = NginxConfig(TwoShards(), {lab, moved}, options);

  EXPECT_NE(conf.find("upstream lifemap_shard_s1 {\n  server 10.0.0.1:50051"), std::string::npos);
  EXPECT_NE(conf.find("upstream lifemap_shard_s2 {\n  server 10.0.0.2:50051"), std::string::npos);
  const std::string fresh = Block(conf, "upstream lifemap_new_maps {");
  EXPECT_NE(fresh.find("hash $http_lifemap_map consistent"), std::string::npos) << fresh;
  EXPECT_NE(fresh.find("10.0.0.1:50051"), std::string::npos) << fresh;
  EXPECT_EQ(fresh.find("10.0.0.2:50051"), std::string::npos) << "a draining shard takes no map";
  const std::string by_map = Block(conf, "map $http_lifemap_map $lifemap_by_map {");
  EXPECT_NE(by_map.find("\"lab\" lifemap_shard_s2;"), std::string::npos) << by_map;
  EXPECT_NE(by_map.find("\"hall\" lifemap_shard_s1;"), std::string::npos) << by_map;
  const std::string by_shard = Block(conf, "map $http_lifemap_shard $lifemap_by_shard {");
  EXPECT_NE(by_shard.find("\"s2\" lifemap_shard_s2;"), std::string::npos) << by_shard;
  // A shard nginx cannot reach: UNAVAILABLE naming it and its address.
  EXPECT_NE(conf.find("lifemap_shard_s2 \"shard s2 (10.0.0.2:50051) is unreachable"),
            std::string::npos);
  EXPECT_NE(conf.find("add_header grpc-status 14 always;"), std::string::npos);
  EXPECT_NE(conf.find("grpc_set_header lifemap-routed-by nginx;"), std::string::npos);
  EXPECT_NE(conf.find("pid /run/lifemap-nginx/nginx.pid;"), std::string::npos);
  EXPECT_NE(conf.find("listen 127.0.0.1:50050 http2;"), std::string::npos);
}

// Issue 52: the table's keys are what the clients send in lifemap-map (percent-encoded UTF-8),
// and a map named after one of nginx's special words is escaped, not taken as the word.
TEST(NginxConfig, KeysAreTheEncodedHeaderAndSpecialWordsAreEscaped) {
  std::vector<MapPlacement> maps(3);
  maps[0].map = "K\xC3\xBC" "che";
  maps[1].map = "B\xC3\xBCro 2";
  maps[2].map = "default";
  for (MapPlacement& m : maps) m.shard = "s1";
  const std::string conf = NginxConfig(TwoShards(), maps, NginxOptions{});
  const std::string by_map = Block(conf, "map $http_lifemap_map $lifemap_by_map {");
  EXPECT_NE(by_map.find("\"K%C3%BCche\" lifemap_shard_s1;"), std::string::npos) << by_map;
  EXPECT_NE(by_map.find("\"B%C3%BCro%202\" lifemap_shard_s1;"), std::string::npos) << by_map;
  EXPECT_NE(by_map.find("\"\\\\default\" lifemap_shard_s1;"), std::string::npos) << by_map;
  for (const char c : conf) EXPECT_TRUE(c == '\n' || (c >= 0x20 && c < 0x7F)) << int(c);
}

TEST(NginxConfig, IncludeOnlyAndTlsTermination) {
  NginxOptions options;
  options.standalone = false;
  options.listen = "0.0.0.0:443";
  options.tls_cert = "/etc/lifemap/cert.pem";
  options.tls_key = "/etc/lifemap/key.pem";
  const std::string conf = NginxConfig(TwoShards(), {}, options);
  EXPECT_EQ(conf.find("events"), std::string::npos);
  EXPECT_EQ(conf.find("http {"), std::string::npos);
  EXPECT_NE(conf.find("listen 0.0.0.0:443 ssl http2;"), std::string::npos);
  EXPECT_NE(conf.find("ssl_certificate /etc/lifemap/cert.pem;"), std::string::npos);
}

TEST(NginxConfig, WithoutShardsNewMapsHaveNowhereToGoAndSaySo) {
  const std::string conf = NginxConfig({}, {}, NginxOptions{});
  EXPECT_NE(conf.find("server 127.0.0.1:1 down;"), std::string::npos);
  EXPECT_NE(conf.find("no shard is reachable for a new map"), std::string::npos);
}

TEST(Placement, ShardNamesAreCheckedAndAnUnreachableDatabaseSaysSo) {
  EXPECT_TRUE(ValidateShardName("s-1.a_b").ok());
  EXPECT_FALSE(ValidateShardName("").ok());
  EXPECT_FALSE(ValidateShardName("s 1").ok());
  EXPECT_FALSE(ValidateShardName(std::string(65, 's')).ok());
  EXPECT_TRUE(absl::IsInvalidArgument(Placement::Open("").status()));
  // Nothing listens on port 1: UNAVAILABLE naming the placement database.
  auto closed = Placement::Open("postgresql://lifemap@127.0.0.1:1/lifemap?connect_timeout=2");
  ASSERT_FALSE(closed.ok());
  EXPECT_TRUE(absl::IsUnavailable(closed.status())) << closed.status();
  EXPECT_TRUE(absl::StrContains(closed.status().message(), "placement database"))
      << closed.status();
}

TEST(ServerConfig, AShardNeedsBothThePlacementAndItsName) {
  server::ServerConfig config;
  config.placement_uri = "postgresql://lifemap@127.0.0.1:5432/lifemap";
  auto half = config.Validate();
  EXPECT_TRUE(absl::IsInvalidArgument(half));
  EXPECT_TRUE(absl::StrContains(half.message(), "--shard")) << half;
  config.shard_name = "s 1";
  EXPECT_FALSE(config.Validate().ok());
  config.shard_name = "s1";
  EXPECT_TRUE(config.Validate().ok()) << config.Validate();
}

}  // namespace
}  // namespace lifemap::placement
