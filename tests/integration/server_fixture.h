// The in-process server fixture of the integration tests: a real lifemapd on loopback and a
// client connected to it.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include <grpcpp/grpcpp.h>
#include <grpcpp/impl/codegen/client_unary_call.h>
#include <gtest/gtest.h>

#include "client/lifemap_client.h"
#include "core/io/tum_dataset.h"
#include "server/server.h"
#include "tests/testing/test_util.h"

namespace lifemap::testing {

// The first frame of a TUM fr1 folder as a Frame (fr1 calibration, PNG bytes as on disk).
inline absl::StatusOr<v1::Frame> FirstTumFrame(const std::string& dir) {
  auto seq = io::ReadTumSequence(dir);
  if (!seq.ok()) return seq.status();
  v1::CameraIntrinsics k;
  k.set_fx(517.3), k.set_fy(516.5), k.set_cx(318.6), k.set_cy(255.3);
  const auto& e = seq->frames[0];
  return client::FrameFromFiles(e.rgb_path, e.depth_path, 5000.0, k, e.timestamp_s, 0);
}

// A TUM fr1 recording's frames as a robot without localisation sends them (fr1 calibration,
// PNG bytes as on disk, no pose; sequence numbers from 0), and each frame's ground truth.
struct TumFrames {
  std::vector<v1::Frame> frames;
  std::vector<std::optional<Pose>> truth;
};
inline TumFrames ReadTumFrames(const std::string& dir) {
  TumFrames out;
  auto seq = io::ReadTumSequence(dir);
  EXPECT_TRUE(seq.ok()) << seq.status();
  if (!seq.ok()) return out;
  v1::CameraIntrinsics k;
  k.set_fx(517.3), k.set_fy(516.5), k.set_cx(318.6), k.set_cy(255.3);
  uint64_t sequence = 0;
  for (const auto& e : seq->frames) {
    auto f = client::FrameFromFiles(e.rgb_path, e.depth_path, 5000.0, k, e.timestamp_s, sequence++);
    EXPECT_TRUE(f.ok()) << f.status();
    if (!f.ok()) continue;
    out.frames.push_back(*f);
    out.truth.push_back(e.T_world_camera);
  }
  return out;
}

// grpc.health.v1.Health/Check on `target` with an empty request (no key): the call's status
// and, when OK, whether the answer is SERVING (field 1 = 1, bytes 08 01).
struct HealthAnswer {
  grpc::Status status;
  bool serving = false;
};
inline HealthAnswer CheckHealth(const std::string& target) {
  auto channel = grpc::CreateChannel(target, grpc::InsecureChannelCredentials());
  grpc::ClientContext ctx;
  grpc::Slice empty(std::string(""));
  grpc::ByteBuffer request(&empty, 1), response;
  HealthAnswer answer;
  answer.status = grpc::internal::BlockingUnaryCall<grpc::ByteBuffer, grpc::ByteBuffer>(
      channel.get(),
      grpc::internal::RpcMethod("/grpc.health.v1.Health/Check",
                                grpc::internal::RpcMethod::NORMAL_RPC),
      &ctx, request, &response);
  std::vector<grpc::Slice> slices;
  if (!answer.status.ok() || !response.Dump(&slices).ok()) return answer;
  std::string bytes;
  for (const auto& s : slices) bytes.append(reinterpret_cast<const char*>(s.begin()), s.size());
  answer.serving = bytes == std::string("\x08\x01", 2);
  return answer;
}

class ServerTest : public ::testing::Test {
 protected:
  // Starts a server on the fixture's database, stopping the running one first (one server
  // per database).
  void StartServer(server::ServerConfig config = {}) {
    client_.reset();
    server_.reset();
    config.listen = "127.0.0.1:0";
    config.db_path = tmp_.File("lifemap.db");
    config.shutdown_grace_s = 2;
    config_ = config;
    auto s = server::LifemapServer::Start(config);
    ASSERT_TRUE(s.ok()) << s.status();
    server_ = *std::move(s);
    target_ = "127.0.0.1:" + std::to_string(server_->port());
    auto c = client::Client::Connect(client::ClientOptions::At(target_));
    ASSERT_TRUE(c.ok()) << c.status();
    client_ = *std::move(c);
  }
  void SetUp() override { StartServer(); }
  // Stops the server and starts it again on the same database with the last config.
  void RestartServer() { StartServer(config_); }

  // ProcessFrame's status for a frame, against map "m" (created on demand).
  absl::Status Process(const v1::Frame& frame, const std::string& map = "") {
    v1::ProcessFrameRequest req;
    req.set_map(map);
    *req.mutable_frame() = frame;
    return client_->ProcessFrame(req).status();
  }

  testing::TempDir tmp_;
  server::ServerConfig config_;
  std::unique_ptr<server::LifemapServer> server_;
  std::string target_;
  std::unique_ptr<client::Client> client_;
};

}  // namespace lifemap::testing
