// The wall clock as the store keeps times: seconds since the Unix epoch.
#pragma once

#include <chrono>

namespace lifemap::server {

inline double NowSeconds() {
  return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}

}  // namespace lifemap::server
