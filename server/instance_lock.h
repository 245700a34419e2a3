// One lifemapd per database file: an advisory lock (flock) on the database file itself, held
// for the server's lifetime. A second lifemapd on the same file would split the robots' writes
// and the operators' reads between two processes' caches, both handing out the same ids; it
// is refused instead. The lock belongs to the file (its device and inode), not to the path, so
// a hard link or a symbolic link to the database is the same database.
//
// flock and SQLite's own POSIX (fcntl) locks are independent on Linux, so holding one does not
// disturb the other. POSIX locks have one trap: closing *any* descriptor of a file drops every
// fcntl lock the process holds on it, SQLite's included. The lock's descriptor therefore stays
// open until the store is closed (the server destroys the lock last), and a second server in
// the same process is refused by device and inode before anything is opened.
#pragma once

#include <sys/types.h>

#include <memory>
#include <string>

#include "absl/status/statusor.h"

namespace lifemap::server {

class InstanceLock {
 public:
  // Locks the database file at `db_path` (creating it empty if missing: SQLite takes an empty
  // file for a new database). FAILED_PRECONDITION naming the file and the holder (pid and
  // command line, from /proc) when another process, or another server in this process, holds
  // it; NOT_FOUND when the directory does not exist; the OS's error otherwise. The lock is
  // released by the destructor, or by the OS when the process dies (a crash leaves no stale
  // lock).
  static absl::StatusOr<std::unique_ptr<InstanceLock>> Acquire(const std::string& db_path);
  ~InstanceLock();
  InstanceLock(const InstanceLock&) = delete;
  InstanceLock& operator=(const InstanceLock&) = delete;

 private:
  InstanceLock(int fd, dev_t dev, ino_t ino) : fd_(fd), dev_(dev), ino_(ino) {}
  int fd_;
  dev_t dev_;
  ino_t ino_;
};

}  // namespace lifemap::server
