// The audit log (issue 17): a server interceptor that records, in the store, every call of a
// method that needs the operator or admin role, and every call refused for its role or map
// (PERMISSION_DENIED): when, which key, which method, the request's scalar fields (never bytes,
// never secrets) and the answer's status. Calls without a valid key (UNAUTHENTICATED) are
// logged to stderr only, so that they cannot fill the database.
#pragma once

#include <grpcpp/support/server_interceptor.h>

#include <atomic>
#include <cstdint>

namespace lifemap::server {

struct ServiceContext;

class AuditInterceptorFactory : public grpc::experimental::ServerInterceptorFactoryInterface {
 public:
  explicit AuditInterceptorFactory(ServiceContext* ctx) : ctx_(ctx) {}
  grpc::experimental::Interceptor* CreateServerInterceptor(
      grpc::experimental::ServerRpcInfo* info) override;

 private:
  ServiceContext* ctx_;
  std::atomic<int64_t> recorded_{0};  // events recorded since start: every 1,000th prunes
};

// Deletes the audit events older than config.audit_retention_days (none when 0); logs how many.
void PruneAuditLog(ServiceContext* ctx);

}  // namespace lifemap::server
