// A whole map moved between servers (issue 37): ExportMap's EXPORT_MAP_ARCHIVE and ImportMap.
//
// The archive's bytes, as they travel and as `lifemap maps export` keeps them:
//   "lifemap-map-archive 1\n"                        the format and its version
//   one line of JSON, the manifest:                    {"format":1,"schema":17,"map":"lab",
//     "visits":3,"keyframes":210,"bytes":N,"sha256":"...","created_time_s":...}
//   N bytes: an SQLite database of the store's schema holding the map's rows
//     (Store::WriteMapArchive: keyframes with images and features, visits, poses and their
//     revisions, anchors, pose edges, floor plans, octrees, sightings, the map's model)
// The checksum is SHA-256 over those N bytes. An archive of a newer schema is refused; an older
// one is migrated forward on import.
#pragma once

#include <cstdint>
#include <cstdio>
#include <functional>
#include <memory>
#include <string>
#include <string_view>

#include "absl/status/statusor.h"
#include "server/store/store.h"

namespace lifemap::server {

class Sha256;

struct MapArchiveManifest {
  int format = 0;
  int64_t schema = 0;
  std::string map;
  int64_t visits = 0;
  int64_t keyframes = 0;
  uint64_t bytes = 0;  // of the database that follows the manifest
  std::string sha256;  // of those bytes, lower-case hex
  double created_time_s = 0;
};

// The archive's first two lines for `manifest` (the format line and the manifest's JSON).
std::string MapArchiveHeader(const MapArchiveManifest& manifest);
// The checksum a manifest carries for the database `bytes`: SHA-256, lower-case hex.
std::string ArchiveChecksum(std::string_view bytes);

// Scratch files live beside the database (same file system, room for the map it holds) as
// "<database>.archive-*.tmp"; each is removed when done, and any a killed server left behind
// when the next one starts (RemoveStaleArchiveFiles).
std::string ArchiveScratchDir(const store::Store& store);
void RemoveStaleArchiveFiles(const store::Store& store);

// Writes map `name`'s archive and hands its bytes to `sink` in order, in pieces of at most
// `chunk_bytes`; `sink` returns false to stop (CANCELLED). NOT_FOUND for an unknown map.
absl::StatusOr<MapArchiveManifest> ExportMapArchive(
    store::Store* store, const std::string& name, size_t chunk_bytes,
    const std::function<bool(std::string_view)>& sink);

// An archive received in pieces (Add, in order), checked and imported (Finish).
class MapArchiveImport {
 public:
  explicit MapArchiveImport(const store::Store& store);
  ~MapArchiveImport();  // removes the scratch file
  MapArchiveImport(const MapArchiveImport&) = delete;
  MapArchiveImport& operator=(const MapArchiveImport&) = delete;

  // INVALID_ARGUMENT for bytes that are not an archive (header, manifest, more bytes than it
  // says), FAILED_PRECONDITION for a newer format or too little disk space, saying how much.
  absl::Status Add(std::string_view bytes);
  // Checks that every byte came and the checksum, then imports the map as `name` (empty: the
  // name it was exported under) in one transaction (Store::ReadMapArchive). DATA_LOSS for a
  // damaged archive.
  // `keep_ids`, `cancelled`: Store::ReadMapArchive's (a move between shards; the call's
  // cancellation, which rolls the import back: CANCELLED).
  absl::StatusOr<store::MapRecord> Finish(store::Store* store, const std::string& name,
                                          const store::MapCreator& creator, bool keep_ids = false,
                                          const std::function<bool()>& cancelled = {});
  const MapArchiveManifest& manifest() const { return manifest_; }

 private:
  absl::Status ParseHeader();
  std::string scratch_;
  std::string header_;  // bytes before the database, until both lines are in
  bool have_manifest_ = false;
  MapArchiveManifest manifest_;
  uint64_t received_ = 0;  // of the database
  std::unique_ptr<Sha256> hasher_;
  std::FILE* file_ = nullptr;
};

}  // namespace lifemap::server
