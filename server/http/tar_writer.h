// A POSIX ustar archive written in memory (the browser view's training-folder download): regular
// files only, paths up to 100 bytes (or 255 split at a '/'), sizes below 8 GiB. Internal to
// server_http; GNU tar, bsdtar and Python's tarfile read it. Written here rather than taken
// from libarchive: one header layout, ~50 lines, against a new dependency for one function.
#pragma once

#include <string>

#include "absl/status/status.h"

namespace lifemap::server::web {

class TarWriter {
 public:
  // INVALID_ARGUMENT for a path too long to store, or empty.
  absl::Status Add(const std::string& path, const std::string& bytes, double mtime_s);
  // The archive with its end-of-archive blocks; the writer is empty after.
  std::string Finish();

 private:
  std::string out_;
};

}  // namespace lifemap::server::web
