#include "server/instance_lock.h"

#include <fcntl.h>
#include <sys/file.h>
#include <sys/stat.h>
#include <sys/sysmacros.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "absl/synchronization/mutex.h"

namespace lifemap::server {
namespace {

// The database files locked by servers of this process, by (device, inode).
absl::Mutex locked_mu;
std::set<std::pair<dev_t, ino_t>>& LockedFiles() ABSL_EXCLUSIVE_LOCKS_REQUIRED(locked_mu) {
  static auto* files = new std::set<std::pair<dev_t, ino_t>>;
  return *files;
}

// "pid 123: lifemapd --listen ... --db ..." for the process holding an flock on the file, from
// /proc/locks ("1: FLOCK ADVISORY WRITE 123 08:01:4567 0 EOF"; device numbers in hex), or a
// note that it could not be found (another mount namespace, /proc hidden).
std::string HolderOf(dev_t dev, ino_t ino) {
  std::ifstream locks("/proc/locks");
  // The kernel prints "%02x:%02x:%lu" (major, minor, inode).
  char padded[64];
  std::snprintf(padded, sizeof(padded), "%02x:%02x:%lu", major(dev), minor(dev),
                static_cast<unsigned long>(ino));
  for (std::string line; std::getline(locks, line);) {
    const std::vector<std::string> f = absl::StrSplit(line, ' ', absl::SkipEmpty());
    if (f.size() < 6 || f[1] != "FLOCK" || f[5] != padded) continue;
    std::string cmdline;
    std::ifstream in("/proc/" + f[4] + "/cmdline", std::ios::binary);
    std::getline(in, cmdline, '\0');
    for (std::string arg; std::getline(in, arg, '\0');) absl::StrAppend(&cmdline, " ", arg);
    return absl::StrCat("pid ", f[4], cmdline.empty() ? "" : ": ", cmdline);
  }
  return "a process this one cannot see";
}

}  // namespace

absl::StatusOr<std::unique_ptr<InstanceLock>> InstanceLock::Acquire(const std::string& db_path) {
  // Refused by device and inode first when a server of this process holds the file: opening
  // and closing a descriptor of it here would drop that server's SQLite locks (see the header).
  struct stat st {};
  if (stat(db_path.c_str(), &st) == 0) {
    absl::MutexLock lock(&locked_mu);
    if (LockedFiles().count({st.st_dev, st.st_ino}) != 0) {
      return absl::FailedPreconditionError(absl::StrCat(
          "database ", db_path, " is open in another lifemapd (pid ", getpid(),
          ", this process; the same file under this or another name); stop that server "
          "first, or give this one another --db"));
    }
  }
  // Read-only is enough for flock, and a read-only file is then refused by the store with a
  // message that says so. O_CREAT makes a new database's file.
  const int fd = open(db_path.c_str(), O_RDONLY | O_CREAT | O_CLOEXEC, 0644);
  if (fd < 0) {
    const int err = errno;
    if (err == ENOENT) {
      return absl::NotFoundError(
          absl::StrCat("the directory of database ", db_path, " does not exist"));
    }
    return absl::PermissionDeniedError(
        absl::StrCat("cannot open database ", db_path, " to lock it: ", std::strerror(err)));
  }
  if (fstat(fd, &st) != 0 || !S_ISREG(st.st_mode)) {
    close(fd);
    return absl::FailedPreconditionError(
        absl::StrCat("database ", db_path, " is not a regular file"));
  }
  if (flock(fd, LOCK_EX | LOCK_NB) != 0) {
    const int err = errno;
    close(fd);  // no server of this process has the file open (checked above)
    if (err == EWOULDBLOCK) {
      return absl::FailedPreconditionError(absl::StrCat(
          "database ", db_path, " is open in another lifemapd (", HolderOf(st.st_dev, st.st_ino),
          "; the same file under this or another name); stop that server first, or give this "
          "one another --db"));
    }
    return absl::UnavailableError(
        absl::StrCat("cannot lock database ", db_path, ": ", std::strerror(err)));
  }
  absl::MutexLock lock(&locked_mu);
  LockedFiles().insert({st.st_dev, st.st_ino});
  return std::unique_ptr<InstanceLock>(new InstanceLock(fd, st.st_dev, st.st_ino));
}

InstanceLock::~InstanceLock() {
  close(fd_);  // releases the flock; the store (and its POSIX locks) closed before
  absl::MutexLock lock(&locked_mu);
  LockedFiles().erase({dev_, ino_});
}

}  // namespace lifemap::server
