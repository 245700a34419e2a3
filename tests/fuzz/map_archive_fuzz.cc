// libFuzzer target (issue 52): ImportMap's archive reader. An operator's archive file is
// untrusted input: its header and manifest (MapArchiveImport::Add) and the SQLite database
// that follows (Store::ReadMapArchive: schema migration, renumbering, reference checks).
//
// Input: byte 0 picks how the rest is read:
//   bit 0 clear: the rest is an archive as a client sends it, handed to Add in pieces of
//     (byte 1 + 1) * 97 bytes, then Finish. Mutations of the database fail the checksum, so
//     this reaches the header and manifest parser and the checks on the byte counts;
//   bit 0 set: the rest is the database alone; the target writes a true header and manifest
//     (bytes, checksum) before it, so that mutations reach SQLite and ReadMapArchive.
//   bit 1: keep_ids (a move between shards).
// Every input must end with a status. An import that succeeds must leave the store consistent
// (Store::CheckIntegrity finds nothing) and the map already there ("home") untouched; either
// failing is a finding. The imported map is then deleted, so that the store stays small.
//
// Seeds: LIFEMAP_FUZZ_SEEDS=DIR map_archive_fuzz writes the archive of a small map (two visits
// of keyframes, both ways above) into DIR and exits; scripts/fuzz does.
#include <spdlog/spdlog.h>
#include <stdlib.h>

#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "server/engine/map_archive.h"
#include "server/store/store.h"
#include "tests/fuzz/seeds.h"

namespace lifemap {
namespace {

namespace fs = std::filesystem;
using store::Store;

[[noreturn]] void Die(const std::string& why) {
  std::fprintf(stderr, "map_archive_fuzz: %s\n", why.c_str());
  std::abort();
}

// A store in a fresh directory holding map "home": two visits of three keyframes each.
class ScratchStore {
 public:
  explicit ScratchStore(const std::string& map = "home") {
    char pattern[] = "/tmp/lifemap-archive-fuzz-XXXXXX";
    if (mkdtemp(pattern) == nullptr) Die("mkdtemp failed");
    dir_ = pattern;
    store::StoreOptions options;
    options.synchronous_full = false;  // the fuzzer never kills it; fsyncs would only slow it
    auto opened = Store::Open(dir_ + "/lifemap.db", options);
    if (!opened.ok()) Die(opened.status().ToString());
    store_ = *std::move(opened);
    if (auto m = store_->CreateMap(map, "a map already there", 1.0); !m.ok()) {
      Die(m.status().ToString());
    }
    for (int v = 0; v < 2; ++v) {
      auto visit = store_->StartVisit(map, "bot", "visit " + std::to_string(v), 10.0 + v);
      if (!visit.ok()) Die(visit.status().ToString());
      std::vector<store::KeyframeRecord> batch;
      for (int k = 0; k < 3; ++k) {
        store::KeyframeRecord r;
        r.visit_id = visit->id;
        r.sequence = static_cast<uint64_t>(k);
        r.timestamp_s = 10.0 * v + k;
        Pose pose;
        pose.translation = {0.1 * k, 0.0, 0.0};
        r.T_world_camera = pose;
        r.intrinsics = {26.25, 26.25, 15.5, 11.5, 32, 24};
        r.depth_scale = 5000;
        r.depth = "depth";
        r.color = "color";
        batch.push_back(r);
      }
      if (auto s = store_->InsertKeyframes(&batch, {}); !s.ok()) Die(s.ToString());
      if (auto e = store_->EndVisit(visit->id, 20.0 + v, {visit->id, 3, 0}); !e.ok()) {
        Die(e.status().ToString());
      }
    }
    home_ = Shape(map);
  }
  ~ScratchStore() {
    store_.reset();
    std::error_code ignored;
    fs::remove_all(dir_, ignored);
  }

  Store* store() { return store_.get(); }
  // The home map's visits and keyframes, as a string to compare.
  std::string Shape(const std::string& map) {
    auto record = store_->GetMap(map);
    if (!record.ok()) Die("the map '" + map + "' went away: " + record.status().ToString());
    auto keyframes = store_->ListKeyframes(record->id, 0);
    if (!keyframes.ok()) Die(keyframes.status().ToString());
    std::string shape = std::to_string(record->visit_count);
    for (const auto& k : *keyframes) {
      shape += " " + std::to_string(k.id) + "@" + std::to_string(k.visit_id);
    }
    return shape;
  }
  const std::string& home() const { return home_; }

 private:
  std::string dir_;
  std::unique_ptr<Store> store_;
  std::string home_;
};

ScratchStore& Scratch() {
  static auto* scratch = new ScratchStore;
  return *scratch;
}

// A true header for the database `bytes`: its length and checksum.
std::string HeaderFor(std::string_view bytes) {
  server::MapArchiveManifest manifest;
  manifest.format = 1;
  manifest.schema = Store::kSchemaVersion;
  manifest.map = "fuzzed";
  manifest.bytes = bytes.size();
  manifest.sha256 = server::ArchiveChecksum(bytes);
  return server::MapArchiveHeader(manifest);
}

void WriteSeeds(const std::string& dir) {
  ScratchStore source("lab");
  std::string archive;
  auto manifest = server::ExportMapArchive(source.store(), "lab", 4096, [&](std::string_view b) {
    archive.append(b);
    return true;
  });
  if (!manifest.ok()) Die("seeds: " + manifest.status().ToString());
  const std::string database = archive.substr(archive.size() - manifest->bytes);
  fuzz::WriteFile(dir + "/archive", std::string{'\0', '\x10'} + archive);
  fuzz::WriteFile(dir + "/archive-keep-ids", std::string{'\2', '\x10'} + archive);
  fuzz::WriteFile(dir + "/database", std::string{'\1'} + database);
  fuzz::WriteFile(dir + "/database-keep-ids", std::string{'\3'} + database);
}

}  // namespace
}  // namespace lifemap

extern "C" int LLVMFuzzerInitialize(int* /*argc*/, char*** /*argv*/) {
  spdlog::set_level(spdlog::level::off);
  lifemap::fuzz::WriteSeedsIfAsked(lifemap::WriteSeeds);
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace lifemap;
  if (size < 2) return 0;
  auto& scratch = Scratch();
  const uint8_t mode = data[0];
  const bool keep_ids = (mode & 2) != 0;
  std::string_view rest(reinterpret_cast<const char*>(data + 1), size - 1);
  std::string whole;
  size_t piece = 1 << 20;
  if ((mode & 1) != 0) {
    whole = HeaderFor(rest) + std::string(rest);
  } else {
    piece = (static_cast<size_t>(data[1]) + 1) * 97;
    whole = std::string(rest.substr(1));
  }
  server::MapArchiveImport import(*scratch.store());
  absl::Status added;
  for (size_t at = 0; at < whole.size() && added.ok(); at += piece) {
    added = import.Add(std::string_view(whole).substr(at, piece));
  }
  if (!added.ok()) return 0;
  auto map = import.Finish(scratch.store(), "imported", {}, keep_ids);
  if (!map.ok()) return 0;
  auto problems = scratch.store()->CheckIntegrity();
  if (!problems.ok()) Die("admin check failed after an import: " + problems.status().ToString());
  if (!problems->empty()) Die("an import left the store inconsistent: " + problems->front());
  if (scratch.Shape("home") != scratch.home()) Die("an import changed the map 'home'");
  if (auto deleted = scratch.store()->DeleteMap("imported"); !deleted.ok()) {
    Die("cannot delete the imported map: " + deleted.status().ToString());
  }
  return 0;
}
