#include "server/engine/map_archive.h"

#include <openssl/evp.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cstdint>
#include <cstring>
#include <ctime>
#include <filesystem>
#include <stdexcept>
#include <vector>

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"

namespace lifemap::server {
namespace {

namespace fs = std::filesystem;

constexpr char kMagic[] = "lifemap-map-archive 1\n";
constexpr int kFormat = 1;
constexpr size_t kMaxHeaderBytes = 64 * 1024;  // the two lines; a manifest is ~250 bytes
// The largest archive an import takes (a map of ~10 million keyframes): a manifest claiming more
// is refused before any byte is written.
constexpr uint64_t kMaxArchiveBytes = uint64_t{1} << 40;

std::string ScratchPrefix(const store::Store& store) {
  return fs::path(store.path()).filename().string() + ".archive-";
}

std::string NewScratchPath(const store::Store& store) {
  static std::atomic<uint64_t> counter{0};
  return (fs::path(ArchiveScratchDir(store)) /
          absl::StrCat(ScratchPrefix(store), getpid(), "-", counter++, ".tmp"))
      .string();
}

absl::Status Errno(const std::string& what, const std::string& path) {
  return absl::UnavailableError(absl::StrCat(what, " ", path, ": ", std::strerror(errno)));
}

}  // namespace

// SHA-256 by OpenSSL's EVP interface, fed as bytes arrive.
class Sha256 {
 public:
  Sha256() : ctx(EVP_MD_CTX_new()) { EVP_DigestInit_ex(ctx, EVP_sha256(), nullptr); }
  ~Sha256() { EVP_MD_CTX_free(ctx); }
  Sha256(const Sha256&) = delete;
  Sha256& operator=(const Sha256&) = delete;
  void Add(std::string_view bytes) { EVP_DigestUpdate(ctx, bytes.data(), bytes.size()); }
  std::string Hex() {
    unsigned char digest[EVP_MAX_MD_SIZE];
    unsigned int n = 0;
    EVP_DigestFinal_ex(ctx, digest, &n);
    static constexpr char kHex[] = "0123456789abcdef";
    std::string hex;
    for (unsigned int i = 0; i < n; ++i) {
      hex += kHex[digest[i] >> 4];
      hex += kHex[digest[i] & 15];
    }
    return hex;
  }

 private:
  EVP_MD_CTX* ctx;
};

std::string ArchiveChecksum(std::string_view bytes) {
  Sha256 hasher;
  hasher.Add(bytes);
  return hasher.Hex();
}

std::string MapArchiveHeader(const MapArchiveManifest& manifest) {
  return absl::StrCat(kMagic,
                      nlohmann::json{{"format", manifest.format},
                                     {"schema", manifest.schema},
                                     {"map", manifest.map},
                                     {"visits", manifest.visits},
                                     {"keyframes", manifest.keyframes},
                                     {"bytes", manifest.bytes},
                                     {"sha256", manifest.sha256},
                                     {"created_time_s", manifest.created_time_s}}
                          .dump(),
                      "\n");
}

std::string ArchiveScratchDir(const store::Store& store) {
  return fs::absolute(store.path()).parent_path().string();
}

void RemoveStaleArchiveFiles(const store::Store& store) {
  std::error_code ec;
  const std::string prefix = ScratchPrefix(store);
  for (const auto& entry : fs::directory_iterator(ArchiveScratchDir(store), ec)) {
    const std::string name = entry.path().filename().string();
    if (name.rfind(prefix, 0) == 0 && entry.path().extension() == ".tmp") {
      fs::remove(entry.path(), ec);
    }
  }
}

absl::StatusOr<MapArchiveManifest> ExportMapArchive(
    store::Store* store, const std::string& name, size_t chunk_bytes,
    const std::function<bool(std::string_view)>& sink) {
  const std::string path = NewScratchPath(*store);
  struct Remove {
    std::string path;
    ~Remove() {
      std::error_code ec;
      fs::remove(path, ec);
    }
  } remove{path};
  auto counts = store->WriteMapArchive(name, path);
  if (!counts.ok()) return counts.status();

  // The checksum first (the manifest precedes the bytes), then the bytes.
  std::FILE* file = std::fopen(path.c_str(), "rb");
  if (file == nullptr) return Errno("cannot read", path);
  std::unique_ptr<std::FILE, int (*)(std::FILE*)> closer(file, &std::fclose);
  Sha256 hasher;
  std::vector<char> buffer(std::max<size_t>(chunk_bytes, 4096));
  uint64_t bytes = 0;
  for (size_t n; (n = std::fread(buffer.data(), 1, buffer.size(), file)) > 0;) {
    hasher.Add({buffer.data(), n});
    bytes += n;
  }
  if (std::ferror(file)) return Errno("cannot read", path);
  MapArchiveManifest manifest;
  manifest.format = kFormat;
  manifest.schema = counts->schema_version;
  manifest.map = name;
  manifest.visits = counts->visits;
  manifest.keyframes = counts->keyframes;
  manifest.bytes = bytes;
  manifest.sha256 = hasher.Hex();
  manifest.created_time_s = static_cast<double>(std::time(nullptr));
  const std::string header = MapArchiveHeader(manifest);
  if (!sink(header)) return absl::CancelledError("the client went away during the export");
  std::rewind(file);
  buffer.resize(chunk_bytes);
  for (size_t n; (n = std::fread(buffer.data(), 1, buffer.size(), file)) > 0;) {
    if (!sink({buffer.data(), n})) {
      return absl::CancelledError("the client went away during the export");
    }
  }
  if (std::ferror(file)) return Errno("cannot read", path);
  return manifest;
}

MapArchiveImport::MapArchiveImport(const store::Store& store)
    : scratch_(NewScratchPath(store)), hasher_(std::make_unique<Sha256>()) {}

MapArchiveImport::~MapArchiveImport() {
  if (file_ != nullptr) std::fclose(file_);
  std::error_code ec;
  fs::remove(scratch_, ec);
}

absl::Status MapArchiveImport::ParseHeader() {
  // Refused at its first bytes when they cannot begin an archive of any format.
  static constexpr char kFamily[] = "lifemap-map-archive ";
  const size_t known = std::min(header_.size(), sizeof(kFamily) - 1);
  if (header_.compare(0, known, kFamily, known) != 0) {
    return absl::InvalidArgumentError(
        "not a lifemap map archive (it does not start with 'lifemap-map-archive'): give a file "
        "`lifemap maps export` wrote");
  }
  const size_t first = header_.find('\n');
  if (first == std::string::npos) return absl::OkStatus();
  if (header_.compare(0, first + 1, kMagic) != 0) {
    if (header_.rfind(kFamily, 0) == 0) {
      return absl::FailedPreconditionError(
          absl::StrCat("the archive is of format '", header_.substr(0, first),
                       "'; this lifemapd reads format ", kFormat, ": import it into a newer one"));
    }
    return absl::InvalidArgumentError(
        "not a lifemap map archive (it does not start with 'lifemap-map-archive'): give a file "
        "`lifemap maps export` wrote");
  }
  const size_t second = header_.find('\n', first + 1);
  if (second == std::string::npos) return absl::OkStatus();
  const auto manifest =
      nlohmann::json::parse(header_.substr(first + 1, second - first - 1), nullptr, false);
  // A count must be a JSON integer from 0, at most `max`: nlohmann's get<int64_t> of 6.9e65 is
  // undefined behaviour (map_archive_fuzz found it), get<uint64_t> of -1 a huge number.
  const auto count = [&manifest](const char* key, uint64_t max = INT64_MAX) -> uint64_t {
    const auto& v = manifest.at(key);
    if (v.is_number_unsigned() || (v.is_number_integer() && v.get<int64_t>() >= 0)) {
      const uint64_t n = v.get<uint64_t>();
      if (n <= max) return n;
    }
    throw std::runtime_error(
        absl::StrCat("\"", key, "\" is ", v.dump(), ", not a count (a whole number from 0)"));
  };
  try {
    if (manifest.is_discarded() || !manifest.is_object()) throw std::runtime_error("not JSON");
    manifest_.format = static_cast<int>(count("format", INT32_MAX));
    manifest_.schema = static_cast<int64_t>(count("schema"));
    manifest_.map = manifest.at("map").get<std::string>();
    manifest_.visits = static_cast<int64_t>(count("visits"));
    manifest_.keyframes = static_cast<int64_t>(count("keyframes"));
    manifest_.bytes = count("bytes", UINT64_MAX);  // its limit is checked below, saying so
    manifest_.sha256 = manifest.at("sha256").get<std::string>();
    const auto created = manifest.value("created_time_s", nlohmann::json(0.0));
    if (!created.is_number()) throw std::runtime_error("\"created_time_s\" is not a number");
    manifest_.created_time_s = created.get<double>();
  } catch (const std::exception& e) {
    return absl::InvalidArgumentError(
        absl::StrCat("the archive's manifest is damaged (", e.what(), "): export the map again"));
  }
  if (manifest_.schema > store::Store::kSchemaVersion) {
    return absl::FailedPreconditionError(absl::StrCat(
        "the archive is of schema ", manifest_.schema, ", newer than this lifemapd's (",
        store::Store::kSchemaVersion, "): import it into a newer lifemapd"));
  }
  // The import copies the map into the database: room for the file and the copy.
  std::error_code ec;
  const auto space = fs::space(fs::path(scratch_).parent_path(), ec);
  if (manifest_.bytes > kMaxArchiveBytes) {
    return absl::InvalidArgumentError(
        absl::StrCat("the archive's manifest says ", manifest_.bytes, " bytes, more than the ",
                     kMaxArchiveBytes >> 30,
                     " GiB an archive may hold: the manifest is damaged or forged; "
                     "export the map again"));
  }
  // Checked arithmetic: bytes <= 1 TiB, so twice it cannot overflow (a forged 2^63 + 1000 did).
  if (!ec && space.available / 2 < manifest_.bytes) {
    return absl::FailedPreconditionError(absl::StrCat(
        "the archive holds ", manifest_.bytes, " bytes and its import needs about twice that; ",
        fs::path(scratch_).parent_path().string(), " has ", space.available,
        " bytes free: make room and import again"));
  }
  file_ = std::fopen(scratch_.c_str(), "wb");
  if (file_ == nullptr) return Errno("cannot write", scratch_);
  have_manifest_ = true;
  std::string rest = header_.substr(second + 1);
  header_.clear();
  return Add(rest);
}

absl::Status MapArchiveImport::Add(std::string_view bytes) {
  if (!have_manifest_) {
    header_.append(bytes);
    if (auto s = ParseHeader(); !s.ok()) return s;
    if (!have_manifest_ && header_.size() > kMaxHeaderBytes) {
      return absl::InvalidArgumentError(
          "not a lifemap map archive (no manifest in its first 64 KiB): give a file `lifemap "
          "maps export` wrote");
    }
    return absl::OkStatus();
  }
  if (bytes.empty()) return absl::OkStatus();
  if (received_ + bytes.size() > manifest_.bytes) {
    return absl::InvalidArgumentError(
        absl::StrCat("the archive holds more bytes than its manifest says (", manifest_.bytes,
                     "): it is damaged or two files were joined; export the map again"));
  }
  hasher_->Add(bytes);
  if (std::fwrite(bytes.data(), 1, bytes.size(), file_) != bytes.size()) {
    return Errno("cannot write", scratch_);
  }
  received_ += bytes.size();
  return absl::OkStatus();
}

absl::StatusOr<store::MapRecord> MapArchiveImport::Finish(store::Store* store,
                                                          const std::string& name,
                                                          const store::MapCreator& creator,
                                                          bool keep_ids,
                                                          const std::function<bool()>& cancelled) {
  if (!have_manifest_) {
    return absl::InvalidArgumentError(
        "the archive ended before its manifest: give a whole file `lifemap maps export` wrote");
  }
  if (received_ != manifest_.bytes) {
    return absl::DataLossError(absl::StrCat("the archive is cut short: ", received_, " of ",
                                            manifest_.bytes, " bytes; copy it again"));
  }
  if (std::fclose(file_) != 0) {
    file_ = nullptr;
    return Errno("cannot write", scratch_);
  }
  file_ = nullptr;
  const std::string sha256 = hasher_->Hex();
  if (sha256 != manifest_.sha256) {
    return absl::DataLossError(absl::StrCat("the archive is damaged: its checksum is ", sha256,
                                            ", its manifest says ", manifest_.sha256,
                                            "; copy it again or export the map again"));
  }
  return store->ReadMapArchive(scratch_, name.empty() ? manifest_.map : name, creator, keep_ids,
                               cancelled);
}

}  // namespace lifemap::server
