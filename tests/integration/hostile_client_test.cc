// Regression tests of defects found by trying lifemapd as a hostile client and a tired operator
// would (issue 12): absurd but finite frames, a map deleted under a running stream, a second
// server on a busy port or database, two writers to one visit.
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cstring>
#include <functional>
#include <limits>
#include <memory>
#include <sstream>
#include <thread>

#include <grpcpp/generic/generic_stub.h>
#include <grpcpp/grpcpp.h>
#include <grpcpp/impl/codegen/client_unary_call.h>
#include <grpcpp/support/sync_stream.h>
#include <gtest/gtest.h>
#include <spdlog/sinks/ostream_sink.h>
#include <spdlog/spdlog.h>

#include "tests/integration/model_fixture.h"
#include "tests/integration/server_fixture.h"

namespace lifemap {
namespace {

using testing::MakeFrame;
using testing::ServerTest;

// A frame whose depth is raw float32 metres, every pixel `depth_m`.
v1::Frame RawF32Frame(float depth_m, uint64_t sequence = 0) {
  v1::Frame f = MakeFrame(160, 120, 1.5, 1000.0 + sequence, sequence);
  std::string data(160 * 120 * sizeof(float), '\0');
  for (size_t i = 0; i < 160 * 120; ++i) std::memcpy(&data[i * sizeof(float)], &depth_m, 4);
  f.mutable_depth()->set_encoding(v1::DEPTH_RAW_F32);
  f.mutable_depth()->set_data(data);
  f.mutable_depth()->set_width(160);
  f.mutable_depth()->set_height(120);
  return f;
}

class HostileClientTest : public ServerTest {};

TEST_F(HostileClientTest, AbsurdButFiniteDepthIsNoReadingNotACrash) {
  // With a model active too: the labels' depth-normalised features see the same values.
  ASSERT_TRUE(client_->UploadModel("two", testing::TwoColorModel()).ok());
  ASSERT_TRUE(client_->ActivateModel("two", "").ok());
  for (float depth : {1e30f, std::numeric_limits<float>::max(), 1e-30f, 1e10f, 1e-3f, 60.0f}) {
    v1::ProcessFrameRequest req;
    *req.mutable_frame() = RawF32Frame(depth);
    auto r = client_->ProcessFrame(req);
    ASSERT_TRUE(r.ok()) << depth << ": " << r.status();
    EXPECT_EQ(r->valid_depth_fraction(), 0.0f) << depth << " m is outside the sensor's range";
  }
  // A mix: half the image a plane at 1.2 m, half absurd.
  v1::Frame mixed = RawF32Frame(1.2f);
  const float absurd = 3e38f;
  for (size_t i = 0; i < 160 * 60; ++i) {
    std::memcpy(&(*mixed.mutable_depth()->mutable_data())[i * 4], &absurd, 4);
  }
  v1::ProcessFrameRequest req;
  *req.mutable_frame() = mixed;
  auto r = client_->ProcessFrame(req);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_NEAR(r->valid_depth_fraction(), 0.5f, 0.01f);
  EXPECT_NEAR(r->median_depth_m(), 1.2f, 1e-3f);
  EXPECT_TRUE(client_->GetServerInfo().ok()) << "the server is still up";
}

TEST_F(HostileClientTest, DepthScaleOutsideItsRangeIsRefused) {
  for (double scale : {1e-18, 1e-3, 1e12}) {
    v1::Frame f = MakeFrame(160, 120);
    f.mutable_depth()->set_depth_scale(scale);
    const absl::Status s = Process(f);
    EXPECT_TRUE(absl::IsInvalidArgument(s)) << scale << ": " << s;
    EXPECT_NE(s.message().find("depth_scale"), std::string::npos) << s;
  }
  EXPECT_TRUE(client_->GetServerInfo().ok()) << "the server is still up";
}

TEST_F(HostileClientTest, FramesOverThePixelLimitAreRefusedBeforeDecoding) {
  server::ServerConfig config;
  config.pipeline.frame_limits.max_pixels = 320 * 240;
  StartServer(config);
  EXPECT_TRUE(Process(MakeFrame(320, 240)).ok());
  const absl::Status s = Process(MakeFrame(640, 480));
  EXPECT_TRUE(absl::IsInvalidArgument(s)) << s;
  EXPECT_NE(s.message().find("max_pixels"), std::string::npos) << s;
  EXPECT_NE(s.message().find("307200"), std::string::npos) << s;
}

TEST_F(HostileClientTest, AbsurdPosesAndIntrinsicsAreRefusedNotStored) {
  ASSERT_TRUE(client_->CreateMap("m", "").ok());
  struct Case {
    const char* name;
    std::function<void(v1::Frame*)> spoil;
    const char* message_part;
  };
  const Case cases[] = {
      {"translation 1e300",
       [](v1::Frame* f) {
         f->mutable_pose()->set_qw(1);
         f->mutable_pose()->set_tx(1e300);
       },
       "map's own origin"},
      {"fx 1e-300", [](v1::Frame* f) { f->mutable_intrinsics()->set_fx(1e-300); }, "not physical"},
      {"fy 1e12", [](v1::Frame* f) { f->mutable_intrinsics()->set_fy(1e12); }, "not physical"},
  };
  for (const auto& c : cases) {
    v1::Frame f = MakeFrame(160, 120);
    c.spoil(&f);
    const absl::Status s = Process(f, "m");
    EXPECT_TRUE(absl::IsInvalidArgument(s)) << c.name << ": " << s;
    EXPECT_NE(s.message().find(c.message_part), std::string::npos) << c.name << ": " << s;
  }
  EXPECT_EQ(client_->GetMap("m")->keyframe_count(), 0u);
}

// Sends one frame on an open stream and returns its result (false if the stream ended).
bool SendAndReceive(client::FrameStream* stream, const v1::Frame& frame, v1::FrameResult* result) {
  return stream->Send(frame) && stream->Receive(result);
}

// Closes the sending side, reads the remaining results and returns the stream's status.
absl::Status CloseAndFinish(client::FrameStream* stream) {
  stream->CloseSend();
  v1::FrameResult r;
  while (stream->Receive(&r)) {
  }
  return stream->Finish();
}

TEST_F(HostileClientTest, AStreamWhoseMapIsDeletedEndsAndNothingLandsInTheNextMap) {
  ASSERT_TRUE(client_->CreateMap("old", "").ok());
  v1::StreamStart start;
  start.set_map("old");
  auto orphan = client_->OpenStream(start);
  ASSERT_TRUE(orphan.ok()) << orphan.status();
  v1::FrameResult r;
  ASSERT_TRUE(SendAndReceive(orphan->get(), MakeFrame(160, 120, 1.5, 1000.0, 0), &r));
  EXPECT_TRUE(r.keyframe().committed());
  const auto old_map_id = client_->GetMap("old")->id();
  const auto old_visit = (*orphan)->started().visit_id();

  ASSERT_TRUE(client_->DeleteMap("old").ok());
  ASSERT_TRUE(client_->CreateMap("new", "").ok());
  EXPECT_NE(client_->GetMap("new")->id(), old_map_id) << "a deleted map's id is not reused";
  start.set_map("new");
  auto fresh = client_->OpenStream(start);
  ASSERT_TRUE(fresh.ok()) << fresh.status();
  const auto new_visit = (*fresh)->started().visit_id();
  EXPECT_NE(new_visit, old_visit) << "a deleted visit's id is not reused";
  ASSERT_TRUE(SendAndReceive(fresh->get(), MakeFrame(160, 120, 1.5, 2000.0, 0), &r));
  EXPECT_TRUE(r.keyframe().committed());

  // The orphaned stream's next frame (a keyframe by time) ends it; nothing is committed.
  (*orphan)->Send(MakeFrame(160, 120, 1.5, 1005.0, 1));
  EXPECT_FALSE((*orphan)->Receive(&r));
  const absl::Status ended = (*orphan)->Finish();
  EXPECT_TRUE(absl::IsNotFound(ended)) << ended;
  EXPECT_NE(ended.message().find("'old' was deleted"), std::string::npos) << ended;

  EXPECT_TRUE(CloseAndFinish(fresh->get()).ok());
  auto keyframes = client_->ListKeyframes("new", 0);
  ASSERT_TRUE(keyframes.ok());
  ASSERT_EQ(keyframes->keyframes_size(), 1);
  EXPECT_EQ(keyframes->keyframes(0).visit_id(), new_visit);
}

TEST_F(HostileClientTest, AStreamWhoseVisitIsEndedEndsWithFailedPrecondition) {
  ASSERT_TRUE(client_->CreateMap("m", "").ok());
  v1::StreamStart start;
  start.set_map("m");
  auto stream = client_->OpenStream(start);
  ASSERT_TRUE(stream.ok());
  v1::FrameResult r;
  ASSERT_TRUE(SendAndReceive(stream->get(), MakeFrame(160, 120, 1.5, 1000.0, 0), &r));
  const auto visit = (*stream)->started().visit_id();
  auto ended = client_->EndVisit(visit);
  ASSERT_TRUE(ended.ok()) << ended.status();
  EXPECT_EQ(ended->frame_count(), 1u) << "the frames streamed so far are counted";
  (*stream)->Send(MakeFrame(160, 120, 1.5, 1005.0, 1));
  EXPECT_FALSE((*stream)->Receive(&r));
  const absl::Status s = (*stream)->Finish();
  EXPECT_TRUE(absl::IsFailedPrecondition(s)) << s;
  EXPECT_NE(s.message().find("ended"), std::string::npos) << s;
  EXPECT_EQ(client_->GetMap("m")->keyframe_count(), 1u);
}

TEST_F(HostileClientTest, AVisitHasOneWriterAtATime) {
  ASSERT_TRUE(client_->CreateMap("m", "").ok());
  v1::StreamStart start;
  start.set_map("m");
  auto first = client_->OpenStream(start);
  ASSERT_TRUE(first.ok());
  const auto visit = (*first)->started().visit_id();
  v1::FrameResult r;
  ASSERT_TRUE(SendAndReceive(first->get(), MakeFrame(160, 120, 1.5, 1000.0, 0), &r));

  start.set_visit_id(visit);
  auto second = client_->OpenStream(start);
  EXPECT_TRUE(absl::IsFailedPrecondition(second.status())) << second.status();
  EXPECT_NE(second.status().message().find("visit " + std::to_string(visit)), std::string::npos)
      << second.status();
  v1::ProcessFrameRequest req;
  req.set_map("m");
  req.set_visit_id(visit);
  *req.mutable_frame() = MakeFrame(160, 120, 1.5, 1001.0, 1);
  EXPECT_TRUE(absl::IsFailedPrecondition(client_->ProcessFrame(req).status()));

  // The first writer goes on undisturbed; once it ends, the visit can be resumed.
  ASSERT_TRUE(SendAndReceive(first->get(), MakeFrame(160, 120, 1.5, 1002.0, 2), &r));
  EXPECT_TRUE(r.keyframe().committed());
  ASSERT_TRUE(CloseAndFinish(first->get()).ok());
  auto resumed = client_->OpenStream(start);
  ASSERT_TRUE(resumed.ok()) << resumed.status();
  EXPECT_EQ((*resumed)->started().visit_id(), visit);
  EXPECT_TRUE(CloseAndFinish(resumed->get()).ok());
  EXPECT_TRUE(client_->ProcessFrame(req).ok()) << "no writer: a unary frame may be added";
}

TEST_F(HostileClientTest, AColourImageOfTheWrongSizeIsNamedNotTheDepth) {
  v1::Frame f = MakeFrame(640, 480);
  *f.mutable_color() = MakeFrame(320, 240).color();
  f.mutable_color()->set_width(320);
  f.mutable_color()->set_height(240);
  f.mutable_depth()->set_width(640);
  f.mutable_depth()->set_height(480);
  const absl::Status s = Process(f);
  EXPECT_TRUE(absl::IsInvalidArgument(s)) << s;
  EXPECT_NE(s.message().find("colour is declared 320x240 and depth 640x480"), std::string::npos)
      << s;
  // Undeclared sizes: the colour image's own header is what is checked, and named.
  f.mutable_color()->clear_width();
  f.mutable_color()->clear_height();
  const absl::Status undeclared = Process(f);
  EXPECT_NE(undeclared.message().find("colour image is 320x240"), std::string::npos) << undeclared;
}

TEST_F(HostileClientTest, InvalidUtf8IsInvalidArgumentWithAMessage) {
  // CreateMapRequest{name: "\xff\xfe"} as raw bytes: field 1, length 2.
  auto channel = grpc::CreateChannel(target_, grpc::InsecureChannelCredentials());
  grpc::ClientContext ctx;
  grpc::Slice slice(std::string("\x0a\x02\xff\xfe", 4));
  grpc::ByteBuffer request(&slice, 1), response;
  const grpc::Status s = grpc::internal::BlockingUnaryCall<grpc::ByteBuffer, grpc::ByteBuffer>(
      channel.get(),
      grpc::internal::RpcMethod("/lifemap.v1.MapService/CreateMap",
                                grpc::internal::RpcMethod::NORMAL_RPC),
      &ctx, request, &response);
  EXPECT_EQ(s.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << s.error_message();
  EXPECT_NE(s.error_message().find("UTF-8"), std::string::npos) << s.error_message();
  EXPECT_NE(s.error_message().find("CreateMap"), std::string::npos) << s.error_message();
  EXPECT_TRUE(client_->ListMaps()->maps().empty());
}

// Issue 33, item 13: ids at or above 2^63 were printed negative (a cast), EndVisit(2^64-1) said
// "visit_id is required", and a height of 2^32-1 was shown as -1.
TEST_F(HostileClientTest, HugeIdsAndSizesAreNamedAsSent) {
  ASSERT_TRUE(client_->CreateMap("lab", "").ok());
  const uint64_t huge = std::numeric_limits<uint64_t>::max();
  const absl::Status ended = client_->EndVisit(huge).status();
  EXPECT_TRUE(absl::IsNotFound(ended)) << ended;
  EXPECT_NE(ended.message().find("visit_id 18446744073709551615"), std::string::npos) << ended;
  const absl::Status keyframe = client_->GetKeyframe("lab", uint64_t{1} << 63).status();
  EXPECT_TRUE(absl::IsNotFound(keyframe)) << keyframe;
  EXPECT_NE(keyframe.message().find("9223372036854775808"), std::string::npos) << keyframe;
  EXPECT_EQ(keyframe.message().find('-'), std::string::npos) << keyframe;
  v1::StreamStart start;
  start.set_map("lab");
  start.set_visit_id(huge);
  const absl::Status stream = client_->OpenStream(start).status();
  EXPECT_TRUE(absl::IsNotFound(stream)) << stream;
  EXPECT_NE(stream.message().find("18446744073709551615"), std::string::npos) << stream;
  v1::Frame f = MakeFrame(160, 120);
  f.mutable_intrinsics()->set_height(std::numeric_limits<uint32_t>::max());
  const absl::Status tall = Process(f);
  EXPECT_TRUE(absl::IsInvalidArgument(tall)) << tall;
  EXPECT_NE(tall.message().find("frame.intrinsics.height is 4294967295"), std::string::npos)
      << tall;
}

// Issue 33, item 14: a server on [::1]:P started while another served 127.0.0.1:P with another
// database, so localhost clients reached either. Each is refused while the other serves.
TEST_F(HostileClientTest, NoSecondServerOnTheOtherLoopbackAddressOfAPort) {
  {
    const int fd = socket(AF_INET6, SOCK_STREAM, 0);
    sockaddr_in6 a{};
    a.sin6_family = AF_INET6;
    a.sin6_addr = in6addr_loopback;
    const bool v6 = fd >= 0 && bind(fd, reinterpret_cast<const sockaddr*>(&a), sizeof(a)) == 0;
    if (fd >= 0) close(fd);
    if (!v6) GTEST_SKIP() << "this host has no IPv6 loopback ([::1]): nothing to share a port with";
  }
  const int port = server_->port();
  server::ServerConfig other;
  other.db_path = tmp_.File("other.db");
  other.listen = "[::1]:" + std::to_string(port);
  auto second = server::LifemapServer::Start(other);
  ASSERT_FALSE(second.ok()) << "served [::1]:" << port << " beside 127.0.0.1:" << port;
  EXPECT_NE(second.status().message().find("other loopback address"), std::string::npos)
      << second.status();
  EXPECT_TRUE(client_->ListMaps().ok()) << "the first server is unharmed";
}

// A client stream of raw messages (bytes as the client sends them, parsed or not).
using RawStream = grpc::ClientReaderWriter<grpc::ByteBuffer, grpc::ByteBuffer>;
std::unique_ptr<RawStream> OpenRawStream(grpc::Channel* channel, const char* method,
                                         grpc::ClientContext* ctx) {
  return std::unique_ptr<RawStream>(
      grpc::internal::ClientReaderWriterFactory<grpc::ByteBuffer, grpc::ByteBuffer>::Create(
          channel, grpc::internal::RpcMethod(method, grpc::internal::RpcMethod::BIDI_STREAMING),
          ctx));
}
grpc::ByteBuffer Bytes(const std::string& bytes) {
  grpc::Slice slice(bytes);
  return grpc::ByteBuffer(&slice, 1);
}

// Issue 33, item 11: a message that does not parse ended the stream with OK (the next frame
// never answered), and a StreamStart or an upload whose name held invalid UTF-8 was told
// "stream closed before its StreamStart" / "no chunks". Each is INVALID_ARGUMENT saying so.
TEST_F(HostileClientTest, AStreamMessageThatDoesNotParseEndsTheStreamSayingSo) {
  ASSERT_TRUE(client_->CreateMap("lab", "").ok());
  auto channel = grpc::CreateChannel(target_, grpc::InsecureChannelCredentials());
  {
    grpc::ClientContext ctx;
    auto stream = OpenRawStream(channel.get(), "/lifemap.v1.FrameService/StreamFrames", &ctx);
    v1::StreamFramesRequest start;
    start.mutable_start()->set_map("lab\xff\xfe");  // serialised as is: invalid UTF-8
    ASSERT_TRUE(stream->Write(Bytes(start.SerializeAsString())));
    stream->WritesDone();
    grpc::ByteBuffer answer;
    while (stream->Read(&answer)) {
    }
    const grpc::Status s = stream->Finish();
    EXPECT_EQ(s.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << s.error_message();
    EXPECT_NE(s.error_message().find("StreamStart"), std::string::npos) << s.error_message();
    EXPECT_NE(s.error_message().find("UTF-8"), std::string::npos) << s.error_message();
  }
  {
    grpc::ClientContext ctx;
    auto stream = OpenRawStream(channel.get(), "/lifemap.v1.FrameService/StreamFrames", &ctx);
    v1::StreamFramesRequest start, frame;
    start.mutable_start()->set_map("lab");
    *frame.mutable_frame() = MakeFrame(160, 120, 1.5, 1000.0, 0);
    ASSERT_TRUE(stream->Write(Bytes(start.SerializeAsString())));
    ASSERT_TRUE(stream->Write(Bytes(frame.SerializeAsString())));
    stream->Write(Bytes(std::string("\xff\xff\xff\xff\x0f", 5)));  // no protobuf at all
    *frame.mutable_frame() = MakeFrame(160, 120, 1.5, 1001.0, 1);
    stream->Write(Bytes(frame.SerializeAsString()));
    stream->WritesDone();
    int results = 0;
    grpc::ByteBuffer answer;
    while (stream->Read(&answer)) ++results;
    const grpc::Status s = stream->Finish();
    EXPECT_EQ(results, 2) << "StreamStarted and the first frame's result";
    EXPECT_EQ(s.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << s.error_message();
    EXPECT_NE(s.error_message().find("message 3 of the stream could not be parsed"),
              std::string::npos)
        << s.error_message();
  }
  {
    grpc::ClientContext ctx;
    auto stream = OpenRawStream(channel.get(), "/lifemap.v1.ModelService/UploadModel", &ctx);
    v1::UploadModelChunk chunk;
    chunk.set_name("model\xff");
    chunk.set_data(testing::TwoColorModel());
    stream->Write(Bytes(chunk.SerializeAsString()));
    stream->WritesDone();
    grpc::ByteBuffer answer;
    while (stream->Read(&answer)) {
    }
    const grpc::Status s = stream->Finish();
    EXPECT_EQ(s.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << s.error_message();
    EXPECT_NE(s.error_message().find("name"), std::string::npos) << s.error_message();
    EXPECT_NE(s.error_message().find("UTF-8"), std::string::npos) << s.error_message();
  }
  EXPECT_TRUE(client_->GetServerInfo().ok()) << "the server is still up";
}

// Issue 52, item 11: a robot's name, a visit's label or a refused call's text with newlines and
// ANSI escapes wrote forged lines into the server's log. Each event is one line, escaped.
TEST_F(HostileClientTest, ClientTextCannotForgeLogLinesOrEscapeTheTerminal) {
  std::ostringstream log;
  auto previous = spdlog::default_logger();
  auto capture = std::make_shared<spdlog::logger>(
      "capture", std::make_shared<spdlog::sinks::ostream_sink_mt>(log));
  spdlog::set_default_logger(capture);
  StartServer();  // installs the escaping formatter on the default logger
  const std::string forged = "bot\n[2026-12-06 00:00:00.000] [critical] FORGED\x1b[2J\r\x07";
  ASSERT_TRUE(client_->CreateMap("lab", "").ok());
  v1::StartVisitRequest visit;
  visit.set_map("lab");
  visit.set_robot(forged);
  visit.set_label(forged);
  EXPECT_TRUE(client_->StartVisit(visit).ok());
  EXPECT_FALSE(client_->CreateMap(forged, "").ok()) << "refused, and logged as refused";
  server_.reset();  // everything logged
  spdlog::set_default_logger(previous);

  const std::string text = log.str();
  EXPECT_EQ(text.find('\x1b'), std::string::npos) << "no raw ESC reaches the log";
  EXPECT_EQ(text.find('\x07'), std::string::npos);
  EXPECT_EQ(text.find('\r'), std::string::npos);
  size_t forged_lines = 0;
  std::istringstream lines(text);
  for (std::string line; std::getline(lines, line);) {
    EXPECT_EQ(line.rfind("[2026-12-06 00:00:00.000]", 0), std::string::npos)
        << "a forged line: " << line;
    if (line.find("FORGED") != std::string::npos) {
      ++forged_lines;
      EXPECT_NE(line.find("bot\\n[2026"), std::string::npos) << "escaped in place: " << line;
    }
  }
  EXPECT_GE(forged_lines, 1u) << "the visit's robot is logged: " << text;
}

}  // namespace
}  // namespace lifemap
