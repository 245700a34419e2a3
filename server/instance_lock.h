// One lifemapd per database: an advisory lock (flock) on a file beside the database, held for
// the server's lifetime. A second lifemapd on the same database would split the robots'
// writes and the operators' reads between two processes' caches; it is refused instead.
#pragma once

#include <memory>
#include <string>

#include "absl/status/statusor.h"

namespace lifemap::server {

class InstanceLock {
 public:
  // Takes the lock on `db_path` + ".lock" and writes this process's id and `listen` into it.
  // FAILED_PRECONDITION naming the lock file and the holder's pid and address when another
  // process (or another server in this process) holds it; the OS's error otherwise. The lock
  // is released by the destructor, or by the OS when the process dies (a crash leaves no
  // stale lock).
  static absl::StatusOr<std::unique_ptr<InstanceLock>> Acquire(const std::string& db_path,
                                                               const std::string& listen);
  ~InstanceLock();
  InstanceLock(const InstanceLock&) = delete;
  InstanceLock& operator=(const InstanceLock&) = delete;

  const std::string& path() const { return path_; }

 private:
  InstanceLock(int fd, std::string path) : fd_(fd), path_(std::move(path)) {}
  int fd_;
  std::string path_;
};

}  // namespace lifemap::server
