#include "server/http/tar_writer.h"

#include <cstdio>
#include <cstring>

#include "absl/strings/str_cat.h"

namespace lifemap::server::web {
namespace {

constexpr size_t kBlock = 512;

// An octal field of `width` bytes: digits, then NUL.
void Octal(char* field, size_t width, unsigned long long value) {
  std::snprintf(field, width, "%0*llo", static_cast<int>(width - 1), value);
}

}  // namespace

absl::Status TarWriter::Add(const std::string& path, const std::string& bytes, double mtime_s) {
  std::string name = path, prefix;
  if (name.empty()) return absl::InvalidArgumentError("a tar entry needs a path");
  if (name.size() > 100) {
    const size_t cut = path.rfind('/', 155);
    if (cut == std::string::npos || path.size() - cut - 1 > 100 || cut == 0) {
      return absl::InvalidArgumentError(absl::StrCat("path too long for a tar entry: ", path));
    }
    prefix = path.substr(0, cut);
    name = path.substr(cut + 1);
  }
  char header[kBlock] = {};
  std::memcpy(header, name.data(), name.size());
  Octal(header + 100, 8, 0644);           // mode
  Octal(header + 108, 8, 0);              // uid
  Octal(header + 116, 8, 0);              // gid
  Octal(header + 124, 12, bytes.size());  // size
  Octal(header + 136, 12, mtime_s > 0 ? static_cast<unsigned long long>(mtime_s) : 0);
  std::memset(header + 148, ' ', 8);      // checksum, counted as spaces
  header[156] = '0';                      // a regular file
  std::memcpy(header + 257, "ustar", 6);  // magic with its NUL
  std::memcpy(header + 263, "00", 2);     // version
  std::memcpy(header + 345, prefix.data(), prefix.size());
  unsigned sum = 0;
  for (unsigned char c : header) sum += c;
  std::snprintf(header + 148, 8, "%06o", sum);  // six digits, NUL, then the space kept
  header[155] = ' ';
  out_.append(header, kBlock);
  out_.append(bytes);
  out_.append((kBlock - bytes.size() % kBlock) % kBlock, '\0');
  return absl::OkStatus();
}

std::string TarWriter::Finish() {
  out_.append(2 * kBlock, '\0');
  std::string out;
  out.swap(out_);
  return out;
}

}  // namespace lifemap::server::web
