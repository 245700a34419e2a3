#include "server/instance_lock.h"

#include <fcntl.h>
#include <sys/file.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <string>

#include "absl/strings/str_cat.h"
#include "absl/strings/strip.h"

namespace lifemap::server {
namespace {

// What the holder wrote into the lock file ("pid 123, listening on HOST:PORT"), or a note
// that it could not be read.
std::string HolderOf(int fd) {
  char buf[256] = {};
  const ssize_t n = pread(fd, buf, sizeof(buf) - 1, 0);
  if (n <= 0) return "a process that has not written its id yet";
  return std::string(absl::StripTrailingAsciiWhitespace(std::string(buf, static_cast<size_t>(n))));
}

}  // namespace

absl::StatusOr<std::unique_ptr<InstanceLock>> InstanceLock::Acquire(const std::string& db_path,
                                                                    const std::string& listen) {
  const std::string path = db_path + ".lock";
  const int fd = open(path.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644);
  if (fd < 0) {
    const int err = errno;
    if (err == ENOENT) {
      return absl::NotFoundError(
          absl::StrCat("the directory of database ", db_path, " does not exist"));
    }
    return absl::PermissionDeniedError(
        absl::StrCat("cannot create lock file ", path, ": ", std::strerror(err)));
  }
  if (flock(fd, LOCK_EX | LOCK_NB) != 0) {
    const int err = errno;
    std::string holder = HolderOf(fd);
    close(fd);
    if (err == EWOULDBLOCK) {
      return absl::FailedPreconditionError(absl::StrCat(
          "database ", db_path, " is open in another lifemapd (", holder, "; lock file ", path,
          "); stop that server first, or give this one another --db"));
    }
    return absl::UnavailableError(absl::StrCat("cannot lock ", path, ": ", std::strerror(err)));
  }
  const std::string who = absl::StrCat("pid ", getpid(), ", listening on ", listen, "\n");
  if (ftruncate(fd, 0) != 0 || pwrite(fd, who.data(), who.size(), 0) < 0) {
    const int err = errno;
    close(fd);
    return absl::UnavailableError(
        absl::StrCat("cannot write lock file ", path, ": ", std::strerror(err)));
  }
  return std::unique_ptr<InstanceLock>(new InstanceLock(fd, path));
}

InstanceLock::~InstanceLock() {
  // Emptied so that a reader never takes an old holder for a live one; the file stays (another
  // server may already wait to lock it).
  if (ftruncate(fd_, 0) != 0) {
    // Nothing to do: the lock is released below either way.
  }
  close(fd_);
}

}  // namespace lifemap::server
