// API keys, roles, maps a key is limited to, revocation and the audit log (issue 17), against a
// real server that requires keys.
#include <google/protobuf/descriptor.h>
#include <grpcpp/grpcpp.h>
#include <grpcpp/impl/codegen/client_unary_call.h>
#include <grpcpp/support/sync_stream.h>

#include <algorithm>
#include <chrono>
#include <fstream>
#include <iterator>
#include <map>
#include <sstream>
#include <thread>

#include "absl/strings/match.h"
#include "core/common/utf8.h"
#include "lifemap/v1/frame_service.grpc.pb.h"
#include "server/engine/clock.h"
#include "server/rpc/auth.h"
#include "server/store/store.h"
#include "tests/integration/server_fixture.h"

namespace lifemap {
namespace {

using server::Role;

class AuthTest : public testing::ServerTest {
 protected:
  void SetUp() override {
    // The bootstrap: the first admin key goes straight into the database, as `lifemapd keys
    // create` does, before the server starts.
    {
      auto store = store::Store::Open(tmp_.File("lifemap.db"), {});
      ASSERT_TRUE(store.ok()) << store.status();
      auto admin = server::CreateApiKey(store->get(), "root", Role::kAdmin, {}, {}, 1.0);
      ASSERT_TRUE(admin.ok()) << admin.status();
      secrets_["root"] = admin->first;
    }
    server::ServerConfig config;
    config.require_auth = true;
    StartServer(config);
    admin_ = ClientWith(secrets_["root"]);
    for (const char* map : {"lab", "hall"}) ASSERT_TRUE(admin_->CreateMap(map, "").ok());
    NewKey("robot", v1::ROLE_ROBOT);
    NewKey("operator", v1::ROLE_OPERATOR);
    NewKey("admin", v1::ROLE_ADMIN);
    NewKey("lab-robot", v1::ROLE_ROBOT, {"lab"});
  }

  // A key made by the admin over the API; its secret goes into secrets_.
  void NewKey(const std::string& name, v1::Role role, const std::vector<std::string>& maps = {},
              const v1::KeyLimits& limits = {}) {
    v1::CreateApiKeyRequest req;
    req.set_name(name);
    req.set_role(role);
    *req.mutable_limits() = limits;
    for (const auto& m : maps) req.add_maps(m);
    auto created = admin_->CreateApiKey(req);
    ASSERT_TRUE(created.ok()) << created.status();
    secrets_[name] = created->key();
  }

  std::unique_ptr<client::Client> ClientWith(const std::string& key) {
    client::ClientOptions options;
    options.target = target_;
    options.api_key = key;
    auto c = client::Client::Connect(options);
    EXPECT_TRUE(c.ok()) << c.status();
    return c.ok() ? *std::move(c) : nullptr;
  }

  // `method` ("Service/Method") called with an empty request, as raw bytes: every method
  // (streams too: one message, then the end) reaches its handler.
  grpc::Status RawCall(const std::string& method, const std::string& key) {
    auto channel = grpc::CreateChannel(target_, grpc::InsecureChannelCredentials());
    grpc::ClientContext ctx;
    if (!key.empty()) ctx.AddMetadata("authorization", "Bearer " + key);
    ctx.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(30));
    grpc::Slice empty(std::string(""));
    grpc::ByteBuffer request(&empty, 1), response;
    return grpc::internal::BlockingUnaryCall<grpc::ByteBuffer, grpc::ByteBuffer>(
        channel.get(),
        grpc::internal::RpcMethod(("/lifemap.v1." + method).c_str(),
                                  grpc::internal::RpcMethod::NORMAL_RPC),
        &ctx, request, &response);
  }

  // A stream into map "lab" that has sent `frame` and had it answered; null (with a test
  // failure) otherwise.
  std::unique_ptr<client::FrameStream> StreamOneFrame(client::Client* c, const v1::Frame& frame) {
    v1::StreamStart start;
    start.set_map("lab");
    auto stream = c->OpenStream(start);
    EXPECT_TRUE(stream.ok()) << stream.status();
    if (!stream.ok()) return nullptr;
    v1::FrameResult result;
    const bool answered = (*stream)->Send(frame) && (*stream)->Receive(&result);
    EXPECT_TRUE(answered);
    return answered ? *std::move(stream) : nullptr;
  }

  std::map<std::string, std::string> secrets_;
  std::unique_ptr<client::Client> admin_;
};

TEST_F(AuthTest, EveryMethodOfEveryServiceHasARole) {
  const auto* pool = google::protobuf::DescriptorPool::generated_pool();
  size_t methods = 0;
  for (const char* service : {"MapService", "VisitService", "FrameService", "PlaceService",
                              "ModelService", "AdminService"}) {
    const auto* s = pool->FindServiceByName(std::string("lifemap.v1.") + service);
    ASSERT_NE(s, nullptr) << service;
    for (int i = 0; i < s->method_count(); ++i) {
      const std::string name = std::string(service) + "/" + s->method(i)->name();
      EXPECT_TRUE(server::RequiredRole(name).has_value()) << name << " has no role";
      ++methods;
    }
  }
  EXPECT_EQ(server::MethodRoles().size(), methods) << "the policy names a method no service has";
}

// Every method, called without a key, with an unknown key, and with each role's key: refused
// (UNAUTHENTICATED, PERMISSION_DENIED naming the role needed) exactly when the policy says.
TEST_F(AuthTest, EveryMethodRefusesCallersWithoutTheRoleItNeeds) {
  const std::map<std::string, Role> roles = {
      {"robot", Role::kRobot}, {"operator", Role::kOperator}, {"admin", Role::kAdmin}};
  for (const auto& [method, needed] : server::MethodRoles()) {
    const std::string m(method);
    for (const std::string& key : {std::string(), std::string("lmk_not-a-key")}) {
      const grpc::Status s = RawCall(m, key);
      EXPECT_EQ(s.error_code(), grpc::StatusCode::UNAUTHENTICATED)
          << m << ": " << s.error_message();
      EXPECT_NE(s.error_message().find("authorization: Bearer"), std::string::npos)
          << s.error_message();
    }
    for (const auto& [name, role] : roles) {
      const grpc::Status s = RawCall(m, secrets_[name]);
      if (role < needed) {
        EXPECT_EQ(s.error_code(), grpc::StatusCode::PERMISSION_DENIED)
            << m << " with a " << name << " key: " << s.error_message();
        EXPECT_NE(s.error_message().find(std::string(server::RoleName(needed)) + " role"),
                  std::string::npos)
            << s.error_message();
      } else {
        EXPECT_NE(s.error_code(), grpc::StatusCode::PERMISSION_DENIED)
            << m << " with a " << name << " key: " << s.error_message();
        EXPECT_NE(s.error_code(), grpc::StatusCode::UNAUTHENTICATED)
            << m << " with a " << name << " key: " << s.error_message();
      }
    }
  }
}

TEST_F(AuthTest, HealthCheckingNeedsNoKey) {
  const testing::HealthAnswer health = testing::CheckHealth(target_);
  EXPECT_TRUE(health.status.ok()) << health.status.error_message();
  EXPECT_TRUE(health.serving);
}

// The reflection service's list_services on `target`: its status (UNIMPLEMENTED where the
// server offers no reflection).
grpc::Status ListServicesByReflection(const std::string& target) {
  auto channel = grpc::CreateChannel(target, grpc::InsecureChannelCredentials());
  grpc::ClientContext ctx;
  ctx.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
  std::unique_ptr<grpc::ClientReaderWriter<grpc::ByteBuffer, grpc::ByteBuffer>> call(
      grpc::internal::ClientReaderWriterFactory<grpc::ByteBuffer, grpc::ByteBuffer>::Create(
          channel.get(),
          grpc::internal::RpcMethod(
              "/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo",
              grpc::internal::RpcMethod::BIDI_STREAMING),
          &ctx));
  grpc::Slice list_services(std::string("\x3a\x00", 2));  // field 7, empty
  call->Write(grpc::ByteBuffer(&list_services, 1));
  call->WritesDone();
  grpc::ByteBuffer answer;
  while (call->Read(&answer)) {
  }
  return call->Finish();
}

// Reflection describes the API, so a server that requires keys does not offer it, even when a
// server without keys was built in the same process before it (gRPC's reflection plugin used
// to be registered for the whole process).
TEST_F(AuthTest, AServerThatRequiresKeysOffersNoReflection) {
  testing::TempDir other;
  server::ServerConfig open;
  open.listen = "127.0.0.1:0";
  open.db_path = other.File("open.db");
  auto without_keys = server::LifemapServer::Start(open);
  ASSERT_TRUE(without_keys.ok()) << without_keys.status();
  server::ServerConfig config;
  config.require_auth = true;
  StartServer(config);  // built after the one without keys
  const std::string open_target = "127.0.0.1:" + std::to_string((*without_keys)->port());
  EXPECT_TRUE(ListServicesByReflection(open_target).ok());
  EXPECT_EQ(ListServicesByReflection(target_).error_code(), grpc::StatusCode::UNIMPLEMENTED);
}

TEST_F(AuthTest, AKeyLimitedToMapsSeesAndWritesOnlyThose) {
  auto robot = ClientWith(secrets_["lab-robot"]);
  auto maps = robot->ListMaps();
  ASSERT_TRUE(maps.ok()) << maps.status();
  ASSERT_EQ(maps->maps_size(), 1);
  EXPECT_EQ(maps->maps(0).name(), "lab");
  EXPECT_TRUE(robot->GetMap("lab").ok());
  // Another map, existing or not: refused alike (the key learns nothing of other maps).
  for (const char* other : {"hall", "nowhere"}) {
    const auto s = robot->GetMap(other).status();
    EXPECT_TRUE(absl::IsPermissionDenied(s)) << s;
    EXPECT_NE(s.message().find("may use only the maps lab"), std::string::npos) << s;
  }
  v1::ProcessFrameRequest req;
  *req.mutable_frame() = testing::MakeFrame(320, 240);
  req.set_map("lab");
  EXPECT_TRUE(robot->ProcessFrame(req).ok());
  req.set_map("hall");
  EXPECT_TRUE(absl::IsPermissionDenied(robot->ProcessFrame(req).status()));
  v1::StreamStart start;
  start.set_map("hall");
  EXPECT_TRUE(absl::IsPermissionDenied(robot->OpenStream(start).status()));
  v1::StartVisitRequest visit;
  visit.set_map("hall");
  EXPECT_TRUE(absl::IsPermissionDenied(robot->StartVisit(visit).status()));
  EXPECT_TRUE(absl::IsPermissionDenied(robot->ListVisits("hall").status()));
  // A visit of another map, by id.
  visit.set_map("hall");
  auto hall_visit = admin_->StartVisit(visit);
  ASSERT_TRUE(hall_visit.ok());
  EXPECT_TRUE(absl::IsPermissionDenied(robot->EndVisit(hall_visit->id()).status()));
  auto places = robot->ListPlaces("");
  ASSERT_TRUE(places.ok()) << places.status();
  for (const auto& p : places->places()) EXPECT_EQ(p.map(), "lab");

  // An operator limited to a map may not touch what every map shares.
  NewKey("lab-operator", v1::ROLE_OPERATOR, {"lab"});
  auto lab_operator = ClientWith(secrets_["lab-operator"]);
  EXPECT_TRUE(absl::IsPermissionDenied(lab_operator->CreateMap("new", "").status()));
  EXPECT_TRUE(absl::IsPermissionDenied(lab_operator->ActivateModel("", "").status()));
  EXPECT_TRUE(absl::IsPermissionDenied(lab_operator->DeleteMap("hall").status()));
  EXPECT_TRUE(admin_->GetMap("hall").ok());

  // Issue 33, item 10: nothing of other maps leaks through errors or stats.
  // A stream naming its map and another map's visit: the other map is not named.
  start.set_map("lab");
  start.set_visit_id(hall_visit->id());
  const auto wrong_visit = robot->OpenStream(start).status();
  EXPECT_TRUE(absl::IsNotFound(wrong_visit)) << wrong_visit;
  EXPECT_EQ(wrong_visit.message().find("hall"), std::string::npos) << wrong_visit;
  // Renaming would learn from ALREADY_EXISTS which names are taken: not for a limited key.
  const auto renamed = lab_operator->RenameMap("lab", "hall");
  EXPECT_TRUE(absl::IsPermissionDenied(renamed.status())) << renamed.status();
  EXPECT_EQ(renamed.status().message().find("exists"), std::string::npos) << renamed.status();
  // Stats count its maps only and say nothing of the server's.
  auto stats = lab_operator->GetStats();
  ASSERT_TRUE(stats.ok()) << stats.status();
  EXPECT_TRUE(stats->limited_to_maps());
  EXPECT_EQ(stats->maps(), 1u);
  EXPECT_EQ(stats->db_bytes(), 0u);
  EXPECT_EQ(stats->frames_processed(), 0u);
  auto all = admin_->GetStats();
  ASSERT_TRUE(all.ok());
  EXPECT_EQ(all->maps(), 2u);
  EXPECT_FALSE(all->limited_to_maps());

  // Deleting its only map leaves the key limited (to nothing), never unlimited.
  ASSERT_TRUE(admin_->DeleteMap("lab").ok());
  auto none = robot->ListMaps();
  ASSERT_TRUE(none.ok());
  EXPECT_EQ(none->maps_size(), 0);
  EXPECT_TRUE(absl::IsPermissionDenied(robot->GetMap("hall").status()));
}

// Issue 52, item 7: kept ids bypass the renumbering that guards the store's id counters, so
// only an admin (a `maps move`) may ask for them; an operator imports with new ids.
TEST_F(AuthTest, OnlyAnAdminMayImportAMapKeepingItsIds) {
  v1::ExportMapRequest req;
  req.set_map("lab");
  req.set_format(v1::EXPORT_MAP_ARCHIVE);
  std::stringstream archive;
  ASSERT_TRUE(admin_->ExportMap(req, &archive).ok());
  ASSERT_TRUE(admin_->DeleteMap("lab").ok());
  auto op = ClientWith(secrets_["operator"]);
  std::istringstream kept(archive.str());
  auto refused = op->ImportMap(&kept, "lab", /*keep_ids=*/true);
  EXPECT_TRUE(absl::IsPermissionDenied(refused.status())) << refused.status();
  EXPECT_NE(refused.status().message().find("keep_ids needs an admin key"), std::string::npos)
      << refused.status();
  std::istringstream renumbered(archive.str());
  EXPECT_TRUE(op->ImportMap(&renumbered, "lab").ok()) << "without keep_ids an operator may";
  ASSERT_TRUE(op->DeleteMap("lab").ok());
  std::istringstream by_admin(archive.str());
  auto moved = admin_->ImportMap(&by_admin, "lab", /*keep_ids=*/true);
  EXPECT_TRUE(moved.ok()) << moved.status();
}

TEST_F(AuthTest, CreateApiKeyValidatesWhatItIsGiven) {
  v1::CreateApiKeyRequest req;
  req.set_name("x");
  EXPECT_TRUE(absl::IsInvalidArgument(admin_->CreateApiKey(req).status()));  // no role
  req.set_role(v1::ROLE_ADMIN);
  req.add_maps("lab");
  EXPECT_TRUE(absl::IsInvalidArgument(admin_->CreateApiKey(req).status()));  // admin on a map
  req.set_role(v1::ROLE_ROBOT);
  req.set_maps(0, "nowhere");
  EXPECT_TRUE(absl::IsNotFound(admin_->CreateApiKey(req).status()));
  // Issue 33, item 12: a map named twice was "no map with id 1 [NOT_FOUND]".
  req.set_maps(0, "lab");
  req.add_maps("lab");
  const auto twice = admin_->CreateApiKey(req).status();
  EXPECT_TRUE(absl::IsInvalidArgument(twice)) << twice;
  EXPECT_NE(twice.message().find("maps: 'lab' is named twice"), std::string::npos) << twice;
  req.mutable_maps()->RemoveLast();
  req.set_maps(0, "nowhere");
  req.set_name("../etc");
  EXPECT_TRUE(absl::IsInvalidArgument(admin_->CreateApiKey(req).status()));
  req.set_name("robot");
  req.set_maps(0, "lab");
  EXPECT_TRUE(absl::IsAlreadyExists(admin_->CreateApiKey(req).status()));
  EXPECT_TRUE(absl::IsNotFound(admin_->RevokeApiKey("nobody").status()));
}

TEST_F(AuthTest, OnlyTheSecretsHashIsStoredAndListingsNeverShowIt) {
  auto keys = admin_->ListApiKeys();
  ASSERT_TRUE(keys.ok()) << keys.status();
  EXPECT_EQ(keys->keys_size(), 5);
  EXPECT_EQ(secrets_.size(), 5u);
  for (const auto& [name, secret] : secrets_) {
    EXPECT_EQ(secret.rfind("lmk_", 0), 0u);
    EXPECT_EQ(secret.size(), 47u);
    EXPECT_EQ(keys->DebugString().find(secret), std::string::npos);
  }
  // The database holds each secret's SHA-256, never the secret.
  server_.reset();
  std::string db_bytes;
  for (const char* f : {"lifemap.db", "lifemap.db-wal"}) {
    std::ifstream in(tmp_.File(f), std::ios::binary);
    db_bytes += std::string(std::istreambuf_iterator<char>(in), {});
  }
  for (const auto& [name, secret] : secrets_) {
    EXPECT_EQ(db_bytes.find(secret), std::string::npos) << name;
    EXPECT_NE(db_bytes.find(server::ApiKeyHash(secret)), std::string::npos) << name;
  }
}

TEST_F(AuthTest, ARevokedKeyIsRefusedAndItsOpenStreamEnds) {
  auto robot = ClientWith(secrets_["robot"]);
  v1::Frame frame = testing::MakeFrame(320, 240);
  auto stream = StreamOneFrame(robot.get(), frame);
  ASSERT_NE(stream, nullptr);
  v1::FrameResult result;
  auto revoked = admin_->RevokeApiKey("robot");
  ASSERT_TRUE(revoked.ok()) << revoked.status();
  EXPECT_GT(revoked->revoked_time_s(), 0);
  frame.set_sequence(1);
  frame.set_timestamp_s(frame.timestamp_s() + 1);
  stream->Send(frame);
  stream->CloseSend();
  while (stream->Receive(&result)) {
  }
  const absl::Status ended = stream->Finish();
  EXPECT_TRUE(absl::IsUnauthenticated(ended)) << ended;
  const auto refused = robot->ListMaps().status();
  EXPECT_TRUE(absl::IsUnauthenticated(refused)) << refused;
  EXPECT_NE(refused.message().find("'robot' has been revoked"), std::string::npos) << refused;
  // Revoking twice keeps the first time.
  auto again = admin_->RevokeApiKey("robot");
  ASSERT_TRUE(again.ok());
  EXPECT_EQ(again->revoked_time_s(), revoked->revoked_time_s());
}

// Issue 33, item 4: a key revoked with `lifemapd keys revoke --db` beside the running server
// (another connection to the database, as that command is) ends the key's open stream within
// KeyRing::kReloadIntervalS, with no other call to make the server read the keys again.
TEST_F(AuthTest, AKeyRevokedBesideTheServerEndsItsOpenStreamWithinTwoSeconds) {
  auto robot = ClientWith(secrets_["robot"]);
  v1::Frame frame = testing::MakeFrame(320, 240);
  auto stream = StreamOneFrame(robot.get(), frame);
  ASSERT_NE(stream, nullptr);
  v1::FrameResult result;
  {
    auto store = store::Store::Open(tmp_.File("lifemap.db"), {});
    ASSERT_TRUE(store.ok()) << store.status();
    ASSERT_TRUE((*store)->RevokeApiKey("robot", server::NowSeconds()).ok());
  }
  const auto revoked_at = std::chrono::steady_clock::now();
  double answered_after_s = 0;
  for (int i = 1; i < 100; ++i) {
    frame.set_sequence(i);
    frame.set_timestamp_s(frame.timestamp_s() + 0.1);
    if (!stream->Send(frame) || !stream->Receive(&result)) break;
    answered_after_s =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - revoked_at).count();
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  stream->CloseSend();
  while (stream->Receive(&result)) {
  }
  const absl::Status ended = stream->Finish();
  EXPECT_TRUE(absl::IsUnauthenticated(ended)) << ended;
  EXPECT_LE(answered_after_s, server::KeyRing::kReloadIntervalS + 0.5)
      << "frames of a revoked key were answered this long after it was revoked";
}

// Issue 33, item 5: streams that never send StreamStart held every slot (an admin was refused
// 32 s later). Now a slot is taken only after a valid StreamStart, such streams are ended after
// stream_start_timeout_s, and one key holds at most max_streams_per_key of the slots.
class StreamSlotsTest : public AuthTest {
 protected:
  void Restart(int max_streams, int max_streams_per_key) {
    server::ServerConfig config = config_;
    config.max_streams = max_streams;
    config.max_streams_per_key = max_streams_per_key;
    config.stream_start_timeout_s = 1;
    config.stream_idle_timeout_s = 1;
    StartServer(config);
    admin_ = ClientWith(secrets_["root"]);
  }
  // A stream of `key` that sends nothing.
  struct SilentStream {
    grpc::ClientContext ctx;
    std::unique_ptr<grpc::ClientReaderWriter<v1::StreamFramesRequest, v1::StreamFramesResponse>>
        call;
  };
  std::unique_ptr<SilentStream> OpenSilent(const std::string& key) {
    auto s = std::make_unique<SilentStream>();
    s->ctx.AddMetadata("authorization", "Bearer " + key);
    s->ctx.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(30));
    if (stub_ == nullptr) {
      stub_ = v1::FrameService::NewStub(
          grpc::CreateChannel(target_, grpc::InsecureChannelCredentials()));
    }
    s->call = stub_->StreamFrames(&s->ctx);
    return s;
  }
  absl::StatusOr<std::unique_ptr<client::FrameStream>> Started(client::Client* c) {
    v1::StreamStart start;
    start.set_map("lab");
    return c->OpenStream(start);
  }
  std::unique_ptr<v1::FrameService::Stub> stub_;
};

TEST_F(StreamSlotsTest, StreamsThatNeverSayWhatTheyAreForHoldNoSlotAndAreEnded) {
  Restart(/*max_streams=*/2, /*max_streams_per_key=*/2);
  std::vector<std::unique_ptr<SilentStream>> silent;
  for (int i = 0; i < 6; ++i) silent.push_back(OpenSilent(secrets_["robot"]));
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  auto stream = Started(admin_.get());
  ASSERT_TRUE(stream.ok()) << stream.status() << ": silent streams took the slots";
  (*stream)->CloseSend();
  EXPECT_TRUE((*stream)->Finish().ok());
  // Each silent stream is ended within stream_start_timeout_s (+ the 1 s watchdog tick).
  const auto opened = std::chrono::steady_clock::now();
  for (auto& s : silent) {
    v1::StreamFramesResponse response;
    EXPECT_FALSE(s->call->Read(&response));
    const grpc::Status ended = s->call->Finish();
    EXPECT_FALSE(ended.ok());
  }
  EXPECT_LT(std::chrono::steady_clock::now() - opened, std::chrono::seconds(5));
}

TEST_F(StreamSlotsTest, OneKeyCannotTakeEverySlot) {
  Restart(/*max_streams=*/3, /*max_streams_per_key=*/2);
  auto robot = ClientWith(secrets_["robot"]);
  auto a = Started(robot.get());
  auto b = Started(robot.get());
  ASSERT_TRUE(a.ok() && b.ok());
  auto c = Started(robot.get());
  ASSERT_FALSE(c.ok());
  EXPECT_TRUE(absl::IsResourceExhausted(c.status())) << c.status();
  EXPECT_NE(c.status().message().find("max_streams_per_key"), std::string::npos) << c.status();
  auto op = ClientWith(secrets_["operator"]);
  auto other = Started(op.get());
  EXPECT_TRUE(other.ok()) << other.status() << ": another key must find the free slot";
}

TEST_F(StreamSlotsTest, AStreamThatStopsSendingIsEndedAfterTheIdleTimeout) {
  Restart(/*max_streams=*/2, /*max_streams_per_key=*/2);
  auto robot = ClientWith(secrets_["robot"]);
  auto stream = Started(robot.get());
  ASSERT_TRUE(stream.ok()) << stream.status();
  ASSERT_TRUE((*stream)->Send(testing::MakeFrame(320, 240)));
  v1::FrameResult result;
  ASSERT_TRUE((*stream)->Receive(&result));
  const auto sent = std::chrono::steady_clock::now();
  EXPECT_FALSE((*stream)->Receive(&result)) << "the stream must end, not wait for ever";
  EXPECT_LT(std::chrono::steady_clock::now() - sent, std::chrono::seconds(5));
  EXPECT_FALSE((*stream)->Finish().ok());
  // Its slot is free again.
  auto next = Started(robot.get());
  EXPECT_TRUE(next.ok()) << next.status();
}

// Refused calls are audited too, so the log is kept for security.audit_retention_days: older
// events go at start and every 1,000 events recorded.
TEST_F(AuthTest, AuditEventsOlderThanTheRetentionAreDeleted) {
  server_.reset();
  {
    auto store = store::Store::Open(tmp_.File("lifemap.db"), {});
    ASSERT_TRUE(store.ok()) << store.status();
    store::AuditEventRecord old;
    old.time_s = server::NowSeconds() - 40 * 86400.0;
    old.key_name = "root";
    old.method = "MapService/DeleteMap";
    old.request = "name=forty-days-ago";
    old.code = "OK";
    ASSERT_TRUE((*store)->AppendAuditEvent(old).ok());
  }
  server::ServerConfig config;
  config.require_auth = true;
  config.audit_retention_days = 30;
  StartServer(config);
  admin_ = ClientWith(secrets_["root"]);
  auto texts = [this] {
    v1::ListAuditEventsRequest all;
    all.set_limit(5000);
    auto events = admin_->ListAuditEvents(all);
    EXPECT_TRUE(events.ok()) << events.status();
    std::vector<std::string> out;
    if (events.ok()) {
      for (const auto& e : events->events()) out.push_back(e.request());
    }
    return out;
  };
  auto at_start = texts();
  EXPECT_EQ(std::count(at_start.begin(), at_start.end(), "name=forty-days-ago"), 0);
  EXPECT_GT(std::count(at_start.begin(), at_start.end(), "name=lab"), 0) << "SetUp's CreateMap";

  // Every 1,000th event prunes: a retention of 0.5 s, an event, a second, then 1,000 refusals.
  config.audit_retention_days = 0.5 / 86400.0;
  StartServer(config);
  admin_ = ClientWith(secrets_["root"]);
  auto robot = ClientWith(secrets_["robot"]);
  EXPECT_TRUE(absl::IsPermissionDenied(robot->DeleteMap("hall").status()));
  std::this_thread::sleep_for(std::chrono::seconds(1));
  for (int i = 0; i < 1000; ++i) {
    ASSERT_TRUE(absl::IsPermissionDenied(robot->DeleteMap("lab").status()));
  }
  const auto after = texts();
  EXPECT_EQ(std::count(after.begin(), after.end(), "name=hall"), 0) << "older than 0.5 s";
  EXPECT_GT(std::count(after.begin(), after.end(), "name=lab"), 0) << "the newest stay";
}

TEST_F(AuthTest, TheAuditLogRecordsAdministrativeCallsAndRefusals) {
  auto op = ClientWith(secrets_["operator"]);
  auto robot = ClientWith(secrets_["robot"]);
  ASSERT_TRUE(op->DeleteMap("hall").ok());
  EXPECT_TRUE(absl::IsPermissionDenied(robot->DeleteMap("lab").status()));
  EXPECT_TRUE(robot->ListMaps().ok());  // a robot's own work is not audited
  EXPECT_TRUE(absl::IsPermissionDenied(op->ListAuditEvents({}).status()));
  auto events = admin_->ListAuditEvents({});
  ASSERT_TRUE(events.ok()) << events.status();
  ASSERT_GE(events->events_size(), 3);
  // Newest first: the operator's refused look at the log, the robot's refused delete, the
  // operator's delete.
  EXPECT_EQ(events->events(0).key(), "operator");
  EXPECT_EQ(events->events(0).method(), "AdminService/ListAuditEvents");
  EXPECT_EQ(events->events(0).code(), "PERMISSION_DENIED");
  EXPECT_EQ(events->events(1).key(), "robot");
  EXPECT_EQ(events->events(1).method(), "MapService/DeleteMap");
  EXPECT_EQ(events->events(1).request(), "name=lab");
  EXPECT_EQ(events->events(1).code(), "PERMISSION_DENIED");
  EXPECT_EQ(events->events(2).key(), "operator");
  EXPECT_EQ(events->events(2).method(), "MapService/DeleteMap");
  EXPECT_EQ(events->events(2).request(), "name=hall");
  EXPECT_EQ(events->events(2).code(), "OK");
  for (const auto& e : events->events()) {
    EXPECT_NE(e.method(), "MapService/ListMaps");
    EXPECT_FALSE(e.peer().empty());
    // A key's secret never reaches the log (CreateApiKey's answer is not logged).
    for (const auto& [name, secret] : secrets_) {
      EXPECT_EQ(e.DebugString().find(secret), std::string::npos);
    }
  }
  v1::ListAuditEventsRequest limited;
  limited.set_limit(1);
  auto one = admin_->ListAuditEvents(limited);
  ASSERT_TRUE(one.ok());
  EXPECT_EQ(one->events_size(), 1);
}

// Issue 33, item 1: a refused call's request text was cut at 512 bytes inside a character, so
// every later listing of the audit log was invalid UTF-8 and no client could read it.
TEST_F(AuthTest, ARefusedCallWithLongTextLeavesTheAuditLogReadable) {
  auto robot = ClientWith(secrets_["robot"]);
  std::string description;
  for (int i = 0; i < 300; ++i) description += "\xC3\xA9";  // 300 x "é" = 600 bytes
  v1::UpdateMapRequest update;
  update.set_name("lab");
  update.set_description(description);
  EXPECT_TRUE(absl::IsPermissionDenied(robot->UpdateMap(update).status()));
  auto events = admin_->ListAuditEvents({});
  ASSERT_TRUE(events.ok()) << events.status();
  ASSERT_GE(events->events_size(), 1);
  const v1::AuditEvent& e = events->events(0);
  EXPECT_EQ(e.method(), "MapService/UpdateMap");
  EXPECT_TRUE(IsValidUtf8(e.request()));
  EXPECT_TRUE(absl::EndsWith(e.request(), "\xC3\xA9...")) << e.request();
}

// Text stored by an older lifemapd (or by hand) that is not UTF-8 is listed back readable:
// every text column is made valid as it is read.
TEST_F(AuthTest, AnAuditEventStoredWithInvalidUtf8IsListedReadable) {
  server_.reset();
  {
    auto store = store::Store::Open(tmp_.File("lifemap.db"), {});
    ASSERT_TRUE(store.ok()) << store.status();
    store::AuditEventRecord e;
    e.time_s = server::NowSeconds();
    e.key_name = "robot";
    e.method = "MapService/UpdateMap";
    e.request = "name=lab description=\xC3\xA9\xC3";  // cut inside the second "é"
    e.code = "PERMISSION_DENIED";
    e.message = "bad \xFF byte";
    e.peer = "ipv4:127.0.0.1:1";
    ASSERT_TRUE((*store)->AppendAuditEvent(e).ok());
  }
  StartServer(config_);
  admin_ = ClientWith(secrets_["root"]);
  auto events = admin_->ListAuditEvents({});
  ASSERT_TRUE(events.ok()) << events.status();
  ASSERT_GE(events->events_size(), 1);
  EXPECT_EQ(events->events(0).request(), "name=lab description=\xC3\xA9\xEF\xBF\xBD");
  EXPECT_EQ(events->events(0).message(), "bad \xEF\xBF\xBD byte");
}

// Hostile but valid text through every stored free-text field (map descriptions, visit robots
// and labels, the audit log's request text) comes back byte for byte, or cut on a character
// boundary where the log bounds it, and every listing stays readable.
TEST_F(AuthTest, HostileTextRoundTripsThroughEveryStoredTextField) {
  std::string long_e, euros;
  for (int i = 0; i < 2000; ++i) long_e += "\xC3\xA9";
  for (int i = 0; i < 85; ++i) euros += "\xE2\x82\xAC";  // 255 bytes
  const std::vector<std::string> hostile = {
      long_e,
      std::string("nul\0inside", 10),
      "\xF0\x9F\xA4\x96\xF0\x9F\x8F\xA0 robot at home",
      "\xE2\x80\xAE"
      "desrever\xE2\x80\xAC and \xEF\xBB\xBF BOM",
      "'; DROP TABLE maps; -- \" \\ %s %n",
      euros,
  };
  auto op = ClientWith(secrets_["operator"]);
  for (size_t i = 0; i < hostile.size(); ++i) {
    SCOPED_TRACE(i);
    const std::string& text = hostile[i];
    const std::string map = "hostile-" + std::to_string(i);
    ASSERT_TRUE(op->CreateMap(map, text).ok());
    v1::UpdateMapRequest update;
    update.set_name(map);
    update.set_description(text + "!");
    ASSERT_TRUE(op->UpdateMap(update).ok());
    auto got = op->GetMap(map);
    ASSERT_TRUE(got.ok()) << got.status();
    EXPECT_EQ(got->description(), text + "!");
    const std::string short_text(Utf8Prefix(text, 256));
    v1::StartVisitRequest start;
    start.set_map(map);
    start.set_robot(short_text);
    start.set_label(short_text);
    auto visit = op->StartVisit(start);
    ASSERT_TRUE(visit.ok()) << visit.status();
    auto visits = op->ListVisits(map);
    ASSERT_TRUE(visits.ok()) << visits.status();
    ASSERT_EQ(visits->visits_size(), 1);
    EXPECT_EQ(visits->visits(0).robot(), short_text);
    EXPECT_EQ(visits->visits(0).label(), short_text);
  }
  auto maps = op->ListMaps();
  ASSERT_TRUE(maps.ok()) << maps.status();
  auto events = admin_->ListAuditEvents({});
  ASSERT_TRUE(events.ok()) << events.status();
  for (const auto& e : events->events()) {
    EXPECT_TRUE(IsValidUtf8(e.request())) << e.method();
    EXPECT_LE(e.request().size(), 515u);
  }
}

TEST_F(AuthTest, EachKeysOwnLimitsHoldAndAreNamedWhenReached) {
  v1::KeyLimits limits;
  limits.set_max_maps(1);
  NewKey("maps-1", v1::ROLE_OPERATOR, {}, limits);
  auto maps_1 = ClientWith(secrets_["maps-1"]);
  ASSERT_TRUE(maps_1->CreateMap("a", "").ok());
  auto s = maps_1->CreateMap("b", "").status();
  EXPECT_TRUE(absl::IsResourceExhausted(s)) << s;
  EXPECT_NE(s.message().find("at most 1 maps (its max_maps limit)"), std::string::npos) << s;
  ASSERT_TRUE(maps_1->DeleteMap("a").ok());
  EXPECT_TRUE(maps_1->CreateMap("b", "").ok());

  limits = {};
  limits.set_max_streams(1);
  NewKey("streams-1", v1::ROLE_ROBOT, {}, limits);
  auto streams_1 = ClientWith(secrets_["streams-1"]);
  v1::StreamStart start;
  start.set_map("lab");
  auto first = streams_1->OpenStream(start);
  ASSERT_TRUE(first.ok()) << first.status();
  start.set_map("hall");
  s = streams_1->OpenStream(start).status();
  EXPECT_TRUE(absl::IsResourceExhausted(s)) << s;
  EXPECT_NE(s.message().find("max_streams"), std::string::npos) << s;
  (*first)->CloseSend();
  EXPECT_TRUE((*first)->Finish().ok());
  auto second = streams_1->OpenStream(start);  // the first one's slot is free again
  ASSERT_TRUE(second.ok()) << second.status();
  (*second)->CloseSend();
  EXPECT_TRUE((*second)->Finish().ok());

  limits = {};
  limits.set_max_frames_per_s(3);
  NewKey("fps-3", v1::ROLE_ROBOT, {}, limits);
  auto fps_3 = ClientWith(secrets_["fps-3"]);
  v1::ProcessFrameRequest req;
  *req.mutable_frame() = testing::MakeFrame(64, 48);
  int served = 0, refused = 0;
  for (int i = 0; i < 12; ++i) {
    s = fps_3->ProcessFrame(req).status();
    if (s.ok()) ++served;
    if (absl::IsResourceExhausted(s)) {
      ++refused;
      EXPECT_NE(s.message().find("max_frames_per_s"), std::string::npos) << s;
    }
  }
  EXPECT_GE(served, 3);
  EXPECT_GE(refused, 1);
  EXPECT_EQ(served + refused, 12);

  limits = {};
  limits.set_max_keyframes_per_map(2);
  NewKey("keyframes-2", v1::ROLE_ROBOT, {}, limits);
  auto keyframes_2 = ClientWith(secrets_["keyframes-2"]);
  req.set_map("lab");
  std::vector<v1::KeyframeDecision> decisions;
  for (int i = 0; i < 3; ++i) {  // 2 s apart: each one a keyframe
    *req.mutable_frame() = testing::MakeFrame(320, 240, 1.5, 1000.0 + 2 * i, i);
    auto r = keyframes_2->ProcessFrame(req);
    ASSERT_TRUE(r.ok()) << r.status();
    decisions.push_back(r->keyframe());
  }
  EXPECT_TRUE(decisions[0].committed() && decisions[1].committed());
  EXPECT_TRUE(decisions[2].selected());
  EXPECT_FALSE(decisions[2].committed());
  EXPECT_NE(decisions[2].reason().find("max_keyframes_per_map"), std::string::npos)
      << decisions[2].reason();
  EXPECT_EQ(admin_->GetMap("lab")->keyframe_count(), 2u);

  limits = {};
  limits.set_max_model_bytes(1000);
  NewKey("model-1k", v1::ROLE_OPERATOR, {}, limits);
  s = ClientWith(secrets_["model-1k"])->UploadModel("big", std::string(2000, 'x')).status();
  EXPECT_TRUE(absl::IsResourceExhausted(s)) << s;
  EXPECT_NE(s.message().find("max_model_bytes"), std::string::npos) << s;
  auto listed = admin_->ListApiKeys();
  ASSERT_TRUE(listed.ok());
  for (const auto& k : listed->keys()) {
    if (k.name() == "model-1k") {
      EXPECT_EQ(k.limits().max_model_bytes(), 1000u);
    }
  }
}

// Issue 33, item 14: a robot key started 1,000 visits in 4 s. Now a key starts at most its own
// max_visits_per_hour, else the server's security.max_visits_per_key_per_hour.
TEST_F(AuthTest, AKeyStartsAtMostItsVisitsPerHour) {
  v1::KeyLimits limits;
  limits.set_max_visits_per_hour(3);
  NewKey("slow-robot", v1::ROLE_ROBOT, {}, limits);
  auto robot = ClientWith(secrets_["slow-robot"]);
  v1::StartVisitRequest visit;
  visit.set_map("lab");
  for (int i = 0; i < 3; ++i) ASSERT_TRUE(robot->StartVisit(visit).ok()) << i;
  const auto refused = robot->StartVisit(visit).status();
  EXPECT_TRUE(absl::IsResourceExhausted(refused)) << refused;
  EXPECT_NE(refused.message().find("max_visits_per_hour"), std::string::npos) << refused;
  v1::StreamStart start;
  start.set_map("lab");
  EXPECT_TRUE(absl::IsResourceExhausted(robot->OpenStream(start).status()));
  auto keys = admin_->ListApiKeys();
  ASSERT_TRUE(keys.ok());
  for (const auto& k : keys->keys()) {
    if (k.name() == "slow-robot") {
      EXPECT_EQ(k.limits().max_visits_per_hour(), 3u);
    }
  }
  // The server's bound for keys without their own.
  server::ServerConfig config = config_;
  config.max_visits_per_key_per_hour = 2;
  StartServer(config);
  auto other = ClientWith(secrets_["robot"]);
  for (int i = 0; i < 2; ++i) ASSERT_TRUE(other->StartVisit(visit).ok()) << i;
  const auto bounded = other->StartVisit(visit).status();
  EXPECT_TRUE(absl::IsResourceExhausted(bounded)) << bounded;
  EXPECT_NE(bounded.message().find("max_visits_per_key_per_hour"), std::string::npos) << bounded;
}

TEST_F(AuthTest, ServerInfoSaysWhoIsCalling) {
  auto robot = ClientWith(secrets_["robot"]);
  auto info = robot->GetServerInfo();
  ASSERT_TRUE(info.ok()) << info.status();
  EXPECT_TRUE(info->auth_required());
  EXPECT_EQ(info->caller_key(), "robot");
  EXPECT_EQ(info->caller_role(), v1::ROLE_ROBOT);
  EXPECT_TRUE(info->db_path().empty());  // where the database is, is for operators
  auto admin_info = admin_->GetServerInfo();
  ASSERT_TRUE(admin_info.ok());
  EXPECT_FALSE(admin_info->db_path().empty());
}

TEST(AuthStartTest, AServerThatNeedsKeysRefusesToStartWithoutAnAdminKey) {
  testing::TempDir tmp;
  server::ServerConfig config;
  config.db_path = tmp.File("lifemap.db");
  config.listen = "0.0.0.0:0";  // beyond loopback: keys are required
  auto s = server::LifemapServer::Start(config);
  ASSERT_FALSE(s.ok());
  EXPECT_TRUE(absl::IsFailedPrecondition(s.status())) << s.status();
  EXPECT_NE(s.status().message().find("lifemapd keys create NAME --role admin --db"),
            std::string::npos)
      << s.status();
  EXPECT_NE(s.status().message().find("--insecure-no-auth"), std::string::npos) << s.status();
  config.insecure_no_auth = true;
  auto insecure = server::LifemapServer::Start(config);
  EXPECT_TRUE(insecure.ok()) << insecure.status();
}

}  // namespace
}  // namespace lifemap
