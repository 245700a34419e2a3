// libFuzzer target (issue 52): the browser view's request path. Any bytes are sent, as they
// are, over a TCP connection to a scratch lifemapd's `--http` port (in this process, loopback,
// no keys required, so every route is reachable, annotating included): cpp-httplib's request
// parser, the pre-routing checks (server/http/request_guard.h: Host, Origin, Sec-Fetch-Site,
// content types), the routes and their handlers over a map with keyframes. The target then
// closes its sending side and reads the answer to the end. A crash, a sanitizer report or a
// connection the server neither answers nor closes within 20 s is a finding.
//
// The server keeps its state between inputs (annotations accumulate) and is replaced by a
// fresh one every kInputsPerServer inputs.
//
// Seeds: LIFEMAP_FUZZ_SEEDS=DIR http_fuzz writes a request for every route into DIR and exits;
// scripts/fuzz does.
#include <arpa/inet.h>
#include <grpcpp/grpcpp.h>
#include <netinet/in.h>
#include <spdlog/spdlog.h>
#include <stdlib.h>
#include <sys/socket.h>
#include <sys/time.h>
#include <unistd.h>

#include <cerrno>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "lifemap/v1/frame_service.grpc.pb.h"
#include "lifemap/v1/map_service.grpc.pb.h"
#include "server/server.h"
#include "tests/fuzz/seed_frame.h"
#include "tests/fuzz/seeds.h"

namespace lifemap {
namespace {

namespace fs = std::filesystem;

constexpr int kInputsPerServer = 20000;
constexpr int kAnswerTimeoutS = 20;

[[noreturn]] void Die(const std::string& why) {
  std::fprintf(stderr, "http_fuzz: %s\n", why.c_str());
  std::abort();
}

// A lifemapd with the browser view on a loopback port and a map "lab" of six keyframes
// streamed over gRPC (a unix socket), as a robot would.
class ScratchServer {
 public:
  ScratchServer() {
    char pattern[] = "/tmp/lifemap-http-fuzz-XXXXXX";
    if (mkdtemp(pattern) == nullptr) Die("mkdtemp failed");
    dir_ = pattern;
    server::ServerConfig config;
    config.listen = "unix:" + dir_ + "/lifemapd.sock";
    config.http_listen = "127.0.0.1:0";
    config.db_path = dir_ + "/lifemap.db";
    config.backup_dir = dir_ + "/backups";
    config.log_level = "off";
    config.shutdown_grace_s = 1;
    config.synchronous_full = false;  // the fuzzer never kills it; fsyncs would only slow it
    auto started = server::LifemapServer::Start(config);
    if (!started.ok()) Die("cannot start the scratch server: " + started.status().ToString());
    server_ = *std::move(started);

    auto channel = grpc::CreateChannel(config.listen, grpc::InsecureChannelCredentials());
    {
      grpc::ClientContext ctx;
      v1::CreateMapRequest req;
      req.set_name("lab");
      v1::Map map;
      const auto s = v1::MapService::NewStub(channel)->CreateMap(&ctx, req, &map);
      if (!s.ok()) Die("CreateMap: " + s.error_message());
    }
    grpc::ClientContext ctx;
    auto stream = v1::FrameService::NewStub(channel)->StreamFrames(&ctx);
    v1::StreamFramesRequest start;
    start.mutable_start()->set_map("lab");
    stream->Write(start);
    for (uint64_t s = 0; s < 6; ++s) {
      v1::StreamFramesRequest frame;
      *frame.mutable_frame() = fuzz::SeedFrame(s);
      frame.mutable_frame()->mutable_pose()->set_tx(0.05 * static_cast<double>(s));
      frame.mutable_frame()->mutable_pose()->set_qw(1.0);
      stream->Write(frame);
    }
    stream->WritesDone();
    v1::StreamFramesResponse answer;
    while (stream->Read(&answer)) {
    }
    if (const auto s = stream->Finish(); !s.ok()) Die("StreamFrames: " + s.error_message());
  }

  ~ScratchServer() {
    server_.reset();
    std::error_code ignored;
    fs::remove_all(dir_, ignored);
  }

  // Sends `request` as it is, closes the sending side and reads the answer to its end.
  void Exchange(const uint8_t* request, size_t size) {
    const int fd = socket(AF_INET, SOCK_STREAM, 0);
    if (fd < 0) Die("socket failed");
    timeval timeout{kAnswerTimeoutS, 0};
    setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &timeout, sizeof(timeout));
    setsockopt(fd, SOL_SOCKET, SO_SNDTIMEO, &timeout, sizeof(timeout));
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_port = htons(static_cast<uint16_t>(server_->http_port()));
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    if (connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) != 0) {
      Die(std::string("cannot connect to the browser view: ") + std::strerror(errno));
    }
    // The server may answer and close before it has read everything (a refused request):
    // a failed send is an answer, not a finding.
    for (size_t sent = 0; sent < size;) {
      const ssize_t n = send(fd, request + sent, size - sent, MSG_NOSIGNAL);
      if (n <= 0) break;
      sent += static_cast<size_t>(n);
    }
    shutdown(fd, SHUT_WR);
    char buffer[65536];
    for (;;) {
      const ssize_t n = recv(fd, buffer, sizeof(buffer), 0);
      if (n > 0) continue;
      if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) {
        Die("the browser view neither answered nor closed the connection within " +
            std::to_string(kAnswerTimeoutS) + " s");
      }
      break;  // closed (or reset)
    }
    close(fd);
  }

 private:
  std::string dir_;
  std::unique_ptr<server::LifemapServer> server_;
};

std::unique_ptr<ScratchServer>& Server() {
  static auto* server = new std::unique_ptr<ScratchServer>;
  return *server;
}

void WriteSeeds(const std::string& dir) {
  const std::string host = "Host: 127.0.0.1\r\n";
  const std::string annotation = R"({"class": "chair", "boxes": [[0, 0, 0, 0.5, 0.5, 0.5]]})";
  const std::vector<std::pair<std::string, std::string>> requests = {
      {"index", "GET / HTTP/1.1\r\n" + host + "\r\n"},
      {"page", "GET /app.js HTTP/1.1\r\n" + host + "Accept-Encoding: gzip\r\n\r\n"},
      {"session", "GET /api/session HTTP/1.1\r\n" + host + "\r\n"},
      {"maps", "GET /api/maps HTTP/1.1\r\n" + host + "Connection: close\r\n\r\n"},
      {"map", "GET /api/maps/lab HTTP/1.1\r\n" + host + "\r\n"},
      {"keyframes", "GET /api/maps/lab/keyframes?visit=1 HTTP/1.1\r\n" + host + "\r\n"},
      {"keyframe", "GET /api/maps/lab/keyframes/1 HTTP/1.1\r\n" + host + "\r\n"},
      {"image", "GET /api/maps/lab/keyframes/2/color HTTP/1.1\r\n" + host + "\r\n"},
      {"depth", "GET /api/maps/lab/keyframes/2/depth HTTP/1.1\r\n" + host + "\r\n"},
      {"plan", "GET /api/maps/lab/visits/1/plan.svg HTTP/1.1\r\n" + host + "\r\n"},
      {"scene", "GET /api/maps/lab/scene HTTP/1.1\r\n" + host + "\r\n"},
      {"cloud", "GET /api/maps/lab/cloud.bin?stride=8 HTTP/1.1\r\n" + host + "\r\n"},
      {"octree", "GET /api/maps/lab/octree HTTP/1.1\r\n" + host + "\r\n"},
      {"changes", "GET /api/maps/lab/changes?visit=1 HTTP/1.1\r\n" + host + "\r\n"},
      {"annotations", "GET /api/maps/lab/annotations HTTP/1.1\r\n" + host + "\r\n"},
      {"training", "GET /api/maps/lab/training.tar HTTP/1.1\r\n" + host + "\r\n"},
      {"annotate", "POST /api/maps/lab/annotations HTTP/1.1\r\n" + host +
                       "Content-Type: application/json\r\nContent-Length: " +
                       std::to_string(annotation.size()) + "\r\n\r\n" + annotation},
      {"annotate-chunked", "POST /api/maps/lab/annotations HTTP/1.1\r\n" + host +
                               "Content-Type: application/json\r\nTransfer-Encoding: "
                               "chunked\r\n\r\n10\r\n{\"class\": \"box\",\r\n0\r\n\r\n"},
      {"unannotate", "DELETE /api/maps/lab/annotations/1 HTTP/1.1\r\n" + host +
                         "Origin: http://127.0.0.1\r\nSec-Fetch-Site: same-origin\r\n\r\n"},
      {"cross-site",
       "POST /api/maps/lab/annotations HTTP/1.1\r\nHost: evil.example\r\n"
       "Origin: https://evil.example\r\nContent-Type: text/plain\r\n"
       "Content-Length: 2\r\n\r\n{}"},
      {"ranges",
       "GET /api/maps/lab/keyframes/1/color HTTP/1.1\r\n" + host + "Range: bytes=0-10,20-\r\n\r\n"},
      {"pipelined",
       "GET /api/maps HTTP/1.1\r\n" + host + "\r\nGET /api/maps/lab HTTP/1.1\r\n" + host + "\r\n"},
      {"unicode", "GET /api/maps/K%C3%BCche/keyframes HTTP/1.1\r\n" + host + "\r\n"},
  };
  for (const auto& [name, request] : requests) fuzz::WriteFile(dir + "/" + name, request);
}

}  // namespace
}  // namespace lifemap

extern "C" int LLVMFuzzerInitialize(int* /*argc*/, char*** /*argv*/) {
  spdlog::set_level(spdlog::level::off);
  lifemap::fuzz::WriteSeedsIfAsked(lifemap::WriteSeeds);
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace lifemap;
  static int inputs = 0;
  auto& server = Server();
  if (server == nullptr || ++inputs % kInputsPerServer == 0) {
    server.reset();
    server = std::make_unique<ScratchServer>();
  }
  server->Exchange(data, size);
  return 0;
}
