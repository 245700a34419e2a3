// Ends streams that went quiet (issue 33): a StreamFrames call blocked in Read holds one of
// gRPC's threads for as long as its client keeps the connection, so a client that opens
// streams and sends nothing could hold them all. Each stream says when it starts waiting for a
// message and for how long it may; the server's housekeeping cancels those that waited longer.
// Thread-safe.
#pragma once

#include <list>
#include <memory>

#include "absl/synchronization/mutex.h"

namespace grpc {
class ServerContext;
}

namespace lifemap::server {

class StreamWatchdog {
 public:
  // One stream's watch; unregisters itself when destroyed.
  class Watch {
   public:
    ~Watch();
    Watch(const Watch&) = delete;
    Watch& operator=(const Watch&) = delete;
    // About to wait for the client's next message for at most `timeout_s` seconds.
    void Waiting(double timeout_s);
    // A message arrived (or the stream stopped waiting).
    void Received();
    // True once the watchdog cancelled the call for waiting too long.
    bool timed_out() const;

   private:
    friend class StreamWatchdog;
    struct State {
      grpc::ServerContext* context = nullptr;
      double waiting_since_s = -1;  // < 0: not waiting
      double timeout_s = 0;
      bool timed_out = false;
    };
    Watch(StreamWatchdog* owner, std::list<State>::iterator it);
    StreamWatchdog* owner_;
    std::list<State>::iterator it_;  // a list's elements stay put while others come and go
  };

  // Watches the call of `context` until the returned Watch is destroyed.
  std::unique_ptr<Watch> Start(grpc::ServerContext* context);
  // Cancels every call that has been waiting longer than it may (the housekeeping's tick);
  // returns how many.
  int CancelExpired();

 private:
  absl::Mutex mu_;
  std::list<Watch::State> watched_ ABSL_GUARDED_BY(mu_);
};

}  // namespace lifemap::server
