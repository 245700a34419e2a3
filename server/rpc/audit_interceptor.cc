#include "server/rpc/audit_interceptor.h"

#include <string>

#include <google/protobuf/descriptor.h>
#include <google/protobuf/message.h>
#include <google/protobuf/reflection.h>
#include <spdlog/spdlog.h>

#include "absl/status/status.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/string_view.h"
#include "core/common/utf8.h"
#include "server/engine/clock.h"
#include "server/rpc/auth.h"
#include "server/rpc/services.h"

namespace lifemap::server {
namespace {

using google::protobuf::FieldDescriptor;
using grpc::experimental::InterceptionHookPoints;

constexpr size_t kMaxRequestText = 512;

// "name=lab visit_id=3": the request's set scalar fields at the top level (strings, numbers,
// booleans, enums, repeated strings); bytes and nested messages (frames, model data) left out.
std::string RequestText(const google::protobuf::Message& m) {
  const auto* reflection = m.GetReflection();
  std::vector<const FieldDescriptor*> fields;
  reflection->ListFields(m, &fields);
  std::string out;
  for (const FieldDescriptor* f : fields) {
    if (f->type() == FieldDescriptor::TYPE_BYTES || f->type() == FieldDescriptor::TYPE_MESSAGE ||
        f->type() == FieldDescriptor::TYPE_GROUP) {
      continue;
    }
    std::string value;
    if (f->is_repeated()) {
      if (f->type() != FieldDescriptor::TYPE_STRING) continue;
      for (int i = 0; i < reflection->FieldSize(m, f); ++i) {
        absl::StrAppend(&value, i ? "," : "", reflection->GetRepeatedString(m, f, i));
      }
    } else {
      switch (f->cpp_type()) {
        case FieldDescriptor::CPPTYPE_STRING:
          value = reflection->GetString(m, f);
          break;
        case FieldDescriptor::CPPTYPE_INT32:
          value = absl::StrCat(reflection->GetInt32(m, f));
          break;
        case FieldDescriptor::CPPTYPE_INT64:
          value = absl::StrCat(reflection->GetInt64(m, f));
          break;
        case FieldDescriptor::CPPTYPE_UINT32:
          value = absl::StrCat(reflection->GetUInt32(m, f));
          break;
        case FieldDescriptor::CPPTYPE_UINT64:
          value = absl::StrCat(reflection->GetUInt64(m, f));
          break;
        case FieldDescriptor::CPPTYPE_DOUBLE:
          value = absl::StrCat(reflection->GetDouble(m, f));
          break;
        case FieldDescriptor::CPPTYPE_FLOAT:
          value = absl::StrCat(reflection->GetFloat(m, f));
          break;
        case FieldDescriptor::CPPTYPE_BOOL:
          value = reflection->GetBool(m, f) ? "true" : "false";
          break;
        case FieldDescriptor::CPPTYPE_ENUM:
          value = reflection->GetEnum(m, f)->name();
          break;
        default:
          continue;
      }
    }
    absl::StrAppend(&out, out.empty() ? "" : " ", f->name(), "=", value);
  }
  // Cut on a character boundary: half an "é" would make every later listing of the event
  // invalid UTF-8, which gRPC clients refuse to read.
  if (out.size() > kMaxRequestText) out = absl::StrCat(Utf8Prefix(out, kMaxRequestText), "...");
  return out;
}

class AuditInterceptor : public grpc::experimental::Interceptor {
 public:
  AuditInterceptor(ServiceContext* ctx, grpc::experimental::ServerRpcInfo* info, std::string method,
                   Role role, std::atomic<int64_t>* recorded)
      : ctx_(ctx), info_(info), method_(std::move(method)), role_(role), recorded_(recorded) {}

  void Intercept(grpc::experimental::InterceptorBatchMethods* methods) override {
    if (methods->QueryInterceptionHookPoint(InterceptionHookPoints::POST_RECV_MESSAGE) &&
        !have_request_) {
      // The first message only (a stream's first names what it is about).
      if (const void* message = methods->GetRecvMessage(); message != nullptr) {
        request_ = RequestText(*static_cast<const google::protobuf::Message*>(message));
        have_request_ = true;
      }
    }
    if (methods->QueryInterceptionHookPoint(InterceptionHookPoints::PRE_SEND_STATUS)) {
      Record(methods->GetSendStatus());
    }
    methods->Proceed();
  }

 private:
  void Record(const grpc::Status& status) {
    const grpc::StatusCode code = status.error_code();
    grpc::ServerContextBase* context = info_->server_context();
    if (code == grpc::StatusCode::UNAUTHENTICATED) {
      spdlog::warn("{} from {} refused: {}", method_, context->peer(), status.error_message());
      return;
    }
    if (role_ == Role::kRobot && code != grpc::StatusCode::PERMISSION_DENIED) return;
    store::AuditEventRecord e;
    e.time_s = NowSeconds();
    e.key_name = ctx_->keys->KeyNameOf(*context);
    e.method = method_;
    e.request = request_;
    // gRPC's codes are absl's, number for number.
    e.code = absl::StatusCodeToString(static_cast<absl::StatusCode>(code));
    if (code != grpc::StatusCode::OK) e.message = status.error_message();
    e.peer = context->peer();
    if (auto s = ctx_->engine->store()->AppendAuditEvent(e); !s.ok()) {
      spdlog::error("audit log: could not record {} by '{}': {}", method_, e.key_name,
                    std::string(s.message()));
      return;
    }
    // Refused calls are recorded too, so a key could grow the log without end: old events go.
    if (recorded_->fetch_add(1) % kEventsPerPrune == kEventsPerPrune - 1) PruneAuditLog(ctx_);
  }

  static constexpr int64_t kEventsPerPrune = 1000;

  ServiceContext* ctx_;
  grpc::experimental::ServerRpcInfo* info_;
  const std::string method_;
  const Role role_;
  std::atomic<int64_t>* recorded_;
  bool have_request_ = false;
  std::string request_;
};

}  // namespace

grpc::experimental::Interceptor* AuditInterceptorFactory::CreateServerInterceptor(
    grpc::experimental::ServerRpcInfo* info) {
  // "/lifemap.v1.MapService/DeleteMap" -> "MapService/DeleteMap"; other services (health,
  // reflection) are not audited.
  constexpr absl::string_view kPrefix = "/lifemap.v1.";
  const absl::string_view full = info->method();
  if (!absl::StartsWith(full, kPrefix)) return nullptr;
  const std::string method(full.substr(kPrefix.size()));
  const std::optional<Role> role = RequiredRole(method);
  if (!role) return nullptr;
  return new AuditInterceptor(ctx_, info, method, *role, &recorded_);
}

void PruneAuditLog(ServiceContext* ctx) {
  const double days = ctx->config.audit_retention_days;
  if (days <= 0.0) return;
  auto pruned = ctx->engine->store()->PruneAuditEvents(NowSeconds() - days * 86400.0);
  if (!pruned.ok()) {
    spdlog::error("audit log: could not delete events older than {} days: {}", days,
                  std::string(pruned.status().message()));
  } else if (*pruned > 0) {
    spdlog::info("audit log: deleted {} events older than {} days", *pruned, days);
  }
}

}  // namespace lifemap::server
