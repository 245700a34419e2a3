#include "server/rpc/status_interceptor.h"

#include <string>

#include "absl/strings/str_cat.h"

namespace lifemap::server {
namespace {

using grpc::experimental::InterceptionHookPoints;

class StatusInterceptor : public grpc::experimental::Interceptor {
 public:
  explicit StatusInterceptor(std::string method) : method_(std::move(method)) {}

  void Intercept(grpc::experimental::InterceptorBatchMethods* methods) override {
    if (methods->QueryInterceptionHookPoint(InterceptionHookPoints::PRE_SEND_STATUS)) {
      const grpc::Status status = methods->GetSendStatus();
      if (status.error_code() == grpc::StatusCode::INTERNAL && status.error_message().empty()) {
        methods->ModifySendStatus(grpc::Status(
            grpc::StatusCode::INVALID_ARGUMENT,
            absl::StrCat(method_,
                         ": the request could not be parsed; most often a string field (a name, "
                         "label, robot or description) holds bytes that are not valid UTF-8: "
                         "send UTF-8 text")));
      }
    }
    methods->Proceed();
  }

 private:
  const std::string method_;
};

}  // namespace

grpc::experimental::Interceptor* StatusInterceptorFactory::CreateServerInterceptor(
    grpc::experimental::ServerRpcInfo* info) {
  return new StatusInterceptor(info->method());
}

}  // namespace lifemap::server
