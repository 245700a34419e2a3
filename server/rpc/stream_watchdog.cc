#include "server/rpc/stream_watchdog.h"

#include <grpcpp/server_context.h>
#include <spdlog/spdlog.h>

#include "server/engine/clock.h"

namespace lifemap::server {

StreamWatchdog::Watch::Watch(StreamWatchdog* owner, std::list<State>::iterator it)
    : owner_(owner), it_(it) {}

StreamWatchdog::Watch::~Watch() {
  absl::MutexLock lock(&owner_->mu_);
  owner_->watched_.erase(it_);
}

void StreamWatchdog::Watch::Waiting(double timeout_s) {
  const double now = NowSeconds();
  absl::MutexLock lock(&owner_->mu_);
  it_->waiting_since_s = now;
  it_->timeout_s = timeout_s;
}

void StreamWatchdog::Watch::Received() {
  absl::MutexLock lock(&owner_->mu_);
  it_->waiting_since_s = -1;
}

bool StreamWatchdog::Watch::timed_out() const {
  absl::MutexLock lock(&owner_->mu_);
  return it_->timed_out;
}

std::unique_ptr<StreamWatchdog::Watch> StreamWatchdog::Start(grpc::ServerContext* context) {
  absl::MutexLock lock(&mu_);
  watched_.push_front(Watch::State{context});
  return std::unique_ptr<Watch>(new Watch(this, watched_.begin()));
}

int StreamWatchdog::CancelExpired() {
  const double now = NowSeconds();
  int cancelled = 0;
  absl::MutexLock lock(&mu_);
  for (auto& w : watched_) {
    if (w.timed_out || w.waiting_since_s < 0 || now - w.waiting_since_s <= w.timeout_s) {
      continue;
    }
    spdlog::info("stream from {} sent nothing for {:.0f} s: ended", w.context->peer(),
                 now - w.waiting_since_s);
    w.timed_out = true;
    w.context->TryCancel();  // its Read returns false; the handler ends
    ++cancelled;
  }
  return cancelled;
}

}  // namespace lifemap::server
