// libFuzzer target (issue 17): any bytes as the request messages of any RPC, sent by an admin,
// an operator, a robot limited to one map or a caller without a key, to a scratch lifemapd
// (in this process, over a unix socket, keys required, its own database). Every call must end
// with a status: a crash, a sanitizer report, a hang (libFuzzer's -timeout) or a leak is a
// finding. The server's whole request path runs: gRPC parsing, the audit and status
// interceptors, key checks, validation, the handlers, the store, the frame pipeline.
//
// Input: byte 0 picks the method (the six services' methods in the protos' order), byte 1 the
// caller; the rest is the request. For a method that reads a stream (StreamFrames, ImportMap,
// UploadModel) it is up to 16 records of a 2-byte little-endian length and that many bytes,
// each one message; for any other method it is one message.
//
// The server keeps its state between inputs (maps, visits, keyframes and models accumulate as
// a long-lived server's do) and is replaced by a fresh one every kInputsPerServer inputs, so a
// finding may need the inputs before it: libFuzzer saves the last one; rerun the corpus.
//
// Seeds: LIFEMAP_FUZZ_SEEDS=DIR rpc_fuzz writes valid requests for every method (and a
// stream of frames, a model upload and a map import) into DIR and exits; scripts/fuzz does.
//
//   scripts/fuzz 0   # builds build-fuzz; then, for a long run:
//   LIFEMAP_FUZZ_SEEDS=/tmp/rpc build-fuzz/bin/rpc_fuzz
//   build-fuzz/bin/rpc_fuzz -timeout=60 -max_total_time=3600 /tmp/rpc
#include <google/protobuf/descriptor.h>
#include <google/protobuf/message.h>
#include <google/protobuf/stubs/logging.h>
#include <grpcpp/grpcpp.h>
#include <grpcpp/support/sync_stream.h>
#include <spdlog/spdlog.h>
#include <stdlib.h>

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "lifemap/v1/admin_service.pb.h"
#include "lifemap/v1/frame_service.pb.h"
#include "lifemap/v1/map_service.pb.h"
#include "lifemap/v1/model_service.pb.h"
#include "server/rpc/auth.h"
#include "server/server.h"
#include "server/store/store.h"
#include "tests/fuzz/seed_frame.h"
#include "tests/fuzz/seeds.h"
#include "tests/fuzz/tiny_forest.h"

namespace lifemap {
namespace {

namespace fs = std::filesystem;
namespace pb = google::protobuf;

constexpr int kInputsPerServer = 20000;
constexpr int kMaxRecords = 16;
constexpr size_t kMaxRecordBytes = 65535;

struct Method {
  std::string path;  // "/lifemap.v1.MapService/CreateMap"
  std::string name;  // "MapService/CreateMap"
  bool reads_stream = false;
  const pb::Descriptor* request = nullptr;
};

// Every method of the six services, in the protos' order (byte 0 of an input indexes it).
const std::vector<Method>& Methods() {
  static const std::vector<Method>* methods = [] {
    auto* out = new std::vector<Method>;
    const auto* pool = pb::DescriptorPool::generated_pool();
    for (const char* service : {"MapService", "VisitService", "FrameService", "PlaceService",
                                "ModelService", "AdminService"}) {
      const auto* s = pool->FindServiceByName(std::string("lifemap.v1.") + service);
      if (s == nullptr) std::abort();
      for (int i = 0; i < s->method_count(); ++i) {
        const auto* m = s->method(i);
        const std::string name = std::string(service) + "/" + m->name();
        out->push_back({"/lifemap.v1." + name, name, m->client_streaming(), m->input_type()});
      }
    }
    return out;
  }();
  return *methods;
}

enum Caller { kAdmin, kOperator, kLabRobot, kNobody, kCallerCount };

// A lifemapd on a unix socket in a fresh directory, with keys for every kind of caller and a
// map "lab" the robot's key is limited to.
class ScratchServer {
 public:
  ScratchServer() {
    char pattern[] = "/tmp/lifemap-rpc-fuzz-XXXXXX";
    if (mkdtemp(pattern) == nullptr) Die("mkdtemp failed");
    dir_ = pattern;
    const std::string db = dir_ + "/lifemap.db";
    {
      auto store = store::Store::Open(db, {});
      if (!store.ok()) Die(store.status().ToString());
      auto admin = server::CreateApiKey(store->get(), "root", server::Role::kAdmin, {}, {}, 1.0);
      if (!admin.ok()) Die(admin.status().ToString());
      keys_[kAdmin] = admin->first;
    }
    server::ServerConfig config;
    config.listen = "unix:" + dir_ + "/lifemapd.sock";
    config.db_path = db;
    config.backup_dir = dir_ + "/backups";
    config.require_auth = true;
    config.log_level = "off";
    config.shutdown_grace_s = 1;
    config.synchronous_full = false;  // the fuzzer never kills it; fsyncs would only slow it
    fs::create_directories(config.backup_dir);
    auto started = server::LifemapServer::Start(config);
    if (!started.ok()) Die(started.status().ToString());
    server_ = *std::move(started);
    channel_ = grpc::CreateChannel(config.listen, grpc::InsecureChannelCredentials());

    v1::CreateMapRequest lab;
    lab.set_name("lab");
    Expect(Call("/lifemap.v1.MapService/CreateMap", kAdmin, {lab.SerializeAsString()}));
    keys_[kOperator] = NewKey("operator", v1::ROLE_OPERATOR, "");
    keys_[kLabRobot] = NewKey("lab-robot", v1::ROLE_ROBOT, "lab");
  }

  ~ScratchServer() {
    channel_.reset();
    server_.reset();
    std::error_code ignored;
    fs::remove_all(dir_, ignored);
  }

  // Sends `messages` (serialized requests) to `path` as `caller`, reads every answer into
  // `answers` (if given) and returns the call's status. Every method is called as a
  // bidirectional stream: on the wire all four kinds are alike, and the handler decides.
  grpc::Status Call(const std::string& path, Caller caller,
                    const std::vector<std::string>& messages,
                    std::vector<std::string>* answers = nullptr) {
    grpc::ClientContext ctx;
    ctx.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(30));
    if (!keys_[caller].empty()) ctx.AddMetadata("authorization", "Bearer " + keys_[caller]);
    std::unique_ptr<grpc::ClientReaderWriter<grpc::ByteBuffer, grpc::ByteBuffer>> stream(
        grpc::internal::ClientReaderWriterFactory<grpc::ByteBuffer, grpc::ByteBuffer>::Create(
            channel_.get(),
            grpc::internal::RpcMethod(path.c_str(), grpc::internal::RpcMethod::BIDI_STREAMING),
            &ctx));
    for (const std::string& m : messages) {
      grpc::Slice slice(m);
      grpc::ByteBuffer buffer(&slice, 1);
      if (!stream->Write(buffer)) break;
    }
    stream->WritesDone();
    grpc::ByteBuffer answer;
    while (stream->Read(&answer)) {
      if (answers == nullptr) continue;
      std::vector<grpc::Slice> slices;
      if (!answer.Dump(&slices).ok()) continue;
      std::string bytes;
      for (const auto& s : slices) bytes.append(reinterpret_cast<const char*>(s.begin()), s.size());
      answers->push_back(std::move(bytes));
    }
    const grpc::Status status = stream->Finish();
    if (path == "/lifemap.v1.AdminService/Backup") ClearBackups();
    return status;
  }

 private:
  [[noreturn]] static void Die(const std::string& why) {
    std::fprintf(stderr, "rpc_fuzz: cannot start the scratch server: %s\n", why.c_str());
    std::abort();
  }
  static void Expect(const grpc::Status& s) {
    if (!s.ok()) Die(s.error_message());
  }

  std::string NewKey(const std::string& name, v1::Role role, const std::string& map) {
    v1::CreateApiKeyRequest req;
    req.set_name(name);
    req.set_role(role);
    if (!map.empty()) req.add_maps(map);
    std::vector<std::string> answers;
    Expect(
        Call("/lifemap.v1.AdminService/CreateApiKey", kAdmin, {req.SerializeAsString()}, &answers));
    v1::CreateApiKeyResponse created;
    if (answers.size() != 1 || !created.ParseFromString(answers[0])) Die("no key answered");
    return created.key();
  }

  // Backups would fill the disk over a million inputs.
  void ClearBackups() {
    std::error_code ignored;
    for (const auto& e : fs::directory_iterator(dir_ + "/backups", ignored)) {
      fs::remove(e.path(), ignored);
    }
  }

  std::string dir_;
  std::string keys_[kCallerCount];  // kNobody's stays empty
  std::unique_ptr<server::LifemapServer> server_;
  std::shared_ptr<grpc::Channel> channel_;
};

std::unique_ptr<ScratchServer>& Server() {
  static auto* server = new std::unique_ptr<ScratchServer>;
  return *server;
}

// The request messages an input holds for `method` (see the top of the file).
std::vector<std::string> Messages(const Method& method, const uint8_t* data, size_t size) {
  if (!method.reads_stream) return {std::string(reinterpret_cast<const char*>(data), size)};
  std::vector<std::string> out;
  while (size >= 2 && out.size() < kMaxRecords) {
    const size_t n = std::min<size_t>(data[0] | (size_t{data[1]} << 8), size - 2);
    out.emplace_back(reinterpret_cast<const char*>(data + 2), n);
    data += 2 + n;
    size -= 2 + n;
  }
  return out;
}

// ---- Seeds ----------------------------------------------------------------------------------

// Sets every field of `m` to something plausible: strings naming map "lab" where a map is
// meant, numbers 1, enums their first named value, frames a SeedFrame, nested messages alike.
void FillPlausibly(pb::Message* m, int depth) {
  const auto* d = m->GetDescriptor();
  const auto* r = m->GetReflection();
  for (int i = 0; i < d->field_count(); ++i) {
    const auto* f = d->field(i);
    if (f->containing_oneof() != nullptr && f->index_in_oneof() != 0) continue;
    if (f->is_repeated() && f->cpp_type() != pb::FieldDescriptor::CPPTYPE_STRING &&
        f->cpp_type() != pb::FieldDescriptor::CPPTYPE_MESSAGE) {
      continue;
    }
    switch (f->cpp_type()) {
      case pb::FieldDescriptor::CPPTYPE_STRING: {
        if (f->type() == pb::FieldDescriptor::TYPE_BYTES) break;
        const std::string v = f->name().find("map") != std::string::npos ? "lab" : "fuzz";
        if (f->is_repeated()) {
          r->AddString(m, f, v);
        } else {
          r->SetString(m, f, v);
        }
        break;
      }
      case pb::FieldDescriptor::CPPTYPE_INT32:
        r->SetInt32(m, f, 1);
        break;
      case pb::FieldDescriptor::CPPTYPE_INT64:
        r->SetInt64(m, f, 1);
        break;
      case pb::FieldDescriptor::CPPTYPE_UINT32:
        r->SetUInt32(m, f, 1);
        break;
      case pb::FieldDescriptor::CPPTYPE_UINT64:
        r->SetUInt64(m, f, 1);
        break;
      case pb::FieldDescriptor::CPPTYPE_DOUBLE:
        r->SetDouble(m, f, 1.0);
        break;
      case pb::FieldDescriptor::CPPTYPE_FLOAT:
        r->SetFloat(m, f, 1.0f);
        break;
      case pb::FieldDescriptor::CPPTYPE_BOOL:
        r->SetBool(m, f, true);
        break;
      case pb::FieldDescriptor::CPPTYPE_ENUM:
        if (f->enum_type()->value_count() > 1) r->SetEnum(m, f, f->enum_type()->value(1));
        break;
      case pb::FieldDescriptor::CPPTYPE_MESSAGE: {
        if (f->message_type() != v1::Frame::descriptor() && depth >= 3) break;
        pb::Message* child = f->is_repeated() ? r->AddMessage(m, f) : r->MutableMessage(m, f);
        if (f->message_type() == v1::Frame::descriptor()) {
          child->CopyFrom(fuzz::SeedFrame(0));
        } else {
          FillPlausibly(child, depth + 1);
        }
        break;
      }
    }
  }
}

std::string Records(const std::vector<std::string>& messages) {
  std::string out;
  for (const std::string& m : messages) {
    if (m.size() > kMaxRecordBytes) std::abort();
    out.push_back(static_cast<char>(m.size() & 0xff));
    out.push_back(static_cast<char>(m.size() >> 8));
    out += m;
  }
  return out;
}

void WriteSeed(const std::string& dir, const std::string& name, size_t method, Caller caller,
               const std::string& body) {
  fuzz::WriteFile(dir + "/" + name,
                  std::string{static_cast<char>(method), static_cast<char>(caller)} + body);
}

// For each method an empty and a plausibly filled request; also a visit of frames to "lab"
// (streamed to a scratch server here first: the seeds must be requests it accepts), a model
// upload and an export of "lab" in every format.
void WriteSeeds(const std::string& dir) {
  ScratchServer server;
  std::vector<std::string> frames;
  v1::StreamFramesRequest start;
  start.mutable_start()->set_map("lab");
  frames.push_back(start.SerializeAsString());
  for (uint64_t s = 0; s < 6; ++s) {
    v1::StreamFramesRequest frame;
    *frame.mutable_frame() = fuzz::SeedFrame(s);
    frames.push_back(frame.SerializeAsString());
  }
  const auto streamed = server.Call("/lifemap.v1.FrameService/StreamFrames", kAdmin, frames);
  if (!streamed.ok()) {
    std::fprintf(stderr, "rpc_fuzz: seeds: streaming frames: %s\n",
                 streamed.error_message().c_str());
    std::exit(1);
  }
  std::string model_bytes = fuzz::TrainTinyForest(200).Serialize({{"floor", "box"}, {}, "{}"});

  const auto& methods = Methods();
  for (size_t i = 0; i < methods.size(); ++i) {
    const Method& m = methods[i];
    const std::string base = std::to_string(i) + "-" + m.request->name();
    std::unique_ptr<pb::Message> request(
        pb::MessageFactory::generated_factory()->GetPrototype(m.request)->New());
    WriteSeed(dir, base + "-empty", i, kAdmin, m.reads_stream ? Records({""}) : "");
    FillPlausibly(request.get(), 0);
    const std::string filled = request->SerializeAsString();
    WriteSeed(dir, base + "-filled", i, kAdmin, m.reads_stream ? Records({filled}) : filled);
    if (m.name == "FrameService/StreamFrames") {
      WriteSeed(dir, base + "-visit", i, kLabRobot, Records(frames));
    } else if (m.name == "ModelService/UploadModel") {
      v1::UploadModelChunk first, second;
      first.set_name("tiny");
      first.set_data(model_bytes.substr(0, model_bytes.size() / 2));
      second.set_data(model_bytes.substr(model_bytes.size() / 2));
      WriteSeed(dir, base + "-model", i, kOperator,
                Records({first.SerializeAsString(), second.SerializeAsString()}));
    } else if (m.name == "MapService/ExportMap") {
      const auto* formats = v1::ExportFormat_descriptor();
      for (int f = 1; f < formats->value_count(); ++f) {
        v1::ExportMapRequest req;
        req.set_map("lab");
        req.set_format(static_cast<v1::ExportFormat>(formats->value(f)->number()));
        WriteSeed(dir, base + "-" + formats->value(f)->name(), i, kOperator,
                  req.SerializeAsString());
      }
    }
  }
}

}  // namespace
}  // namespace lifemap

extern "C" int LLVMFuzzerInitialize(int* /*argc*/, char*** /*argv*/) {
  namespace pb = google::protobuf;
  spdlog::set_level(spdlog::level::off);
  // Protobuf logs every string field with invalid UTF-8 it refuses to parse.
  pb::SetLogHandler(nullptr);
  lifemap::fuzz::WriteSeedsIfAsked(lifemap::WriteSeeds);
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace lifemap;
  static int inputs = 0;
  if (size < 2) return 0;
  auto& server = Server();
  if (server == nullptr || ++inputs % kInputsPerServer == 0) {
    server.reset();
    server = std::make_unique<ScratchServer>();
  }
  const auto& methods = Methods();
  const Method& method = methods[data[0] % methods.size()];
  const auto caller = static_cast<Caller>(data[1] % kCallerCount);
  server->Call(method.path, caller, Messages(method, data + 2, size - 2));
  return 0;
}
