// A server interceptor that keeps every error explainable: gRPC answers a request that does not
// parse (most often a string field holding invalid UTF-8: protobuf refuses it before any
// handler runs) with INTERNAL and an empty message. This turns that into INVALID_ARGUMENT
// naming the method and the likely cause. lifemap's own handlers never send INTERNAL without a
// message, so no other status is changed.
#pragma once

#include <grpcpp/support/server_interceptor.h>

namespace lifemap::server {

class StatusInterceptorFactory : public grpc::experimental::ServerInterceptorFactoryInterface {
 public:
  grpc::experimental::Interceptor* CreateServerInterceptor(
      grpc::experimental::ServerRpcInfo* info) override;
};

}  // namespace lifemap::server
