#include "server/store/store.h"

#include <sqlite3.h>
#include <unistd.h>

#include <cerrno>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <functional>
#include <limits>
#include <optional>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_replace.h"
#include "absl/synchronization/mutex.h"
#include "core/common/utf8.h"
#include "server/store/sqlite.h"
#include "server/store/store_impl.h"

namespace lifemap::store {
namespace {

namespace fs = std::filesystem;

// Forward migrations: kMigrations[i] takes the schema from version i to i + 1. Never edit a
// migration that has shipped; append a new one and bump Store::kSchemaVersion.
const char* const kMigrations[] = {
    // 0 -> 1: maps, visits, keyframes. Images live in their own table so that listing
    // keyframes never pages through image blobs.
    R"sql(
CREATE TABLE maps (
  id INTEGER PRIMARY KEY,
  name TEXT NOT NULL UNIQUE,
  description TEXT NOT NULL DEFAULT '',
  created_time_s REAL NOT NULL
);
CREATE TABLE visits (
  id INTEGER PRIMARY KEY,
  map_id INTEGER NOT NULL REFERENCES maps(id) ON DELETE CASCADE,
  robot TEXT NOT NULL DEFAULT '',
  label TEXT NOT NULL DEFAULT '',
  start_time_s REAL NOT NULL,
  end_time_s REAL NOT NULL DEFAULT 0,
  ended INTEGER NOT NULL DEFAULT 0,
  frame_count INTEGER NOT NULL DEFAULT 0
);
CREATE INDEX visits_by_map ON visits(map_id, start_time_s);
CREATE TABLE keyframes (
  id INTEGER PRIMARY KEY,
  visit_id INTEGER NOT NULL REFERENCES visits(id) ON DELETE CASCADE,
  sequence INTEGER NOT NULL,
  timestamp_s REAL NOT NULL,
  has_pose INTEGER NOT NULL,
  tx REAL, ty REAL, tz REAL, qx REAL, qy REAL, qz REAL, qw REAL,
  fx REAL NOT NULL, fy REAL NOT NULL, cx REAL NOT NULL, cy REAL NOT NULL,
  width INTEGER NOT NULL, height INTEGER NOT NULL,
  depth_scale REAL NOT NULL,
  color_encoding INTEGER NOT NULL,
  depth_bytes INTEGER NOT NULL,
  color_bytes INTEGER NOT NULL
);
CREATE INDEX keyframes_by_visit ON keyframes(visit_id, timestamp_s);
CREATE TABLE keyframe_images (
  keyframe_id INTEGER PRIMARY KEY REFERENCES keyframes(id) ON DELETE CASCADE,
  depth_png BLOB NOT NULL,
  color BLOB NOT NULL
);
)sql",
    // 1 -> 2: per-map entropy threshold; per-keyframe entropy-mask features (superjut table,
    // threshold, keypoints kept after masking). Blobs are little-endian packed records.
    R"sql(
ALTER TABLE maps ADD COLUMN entropy_threshold REAL;
CREATE TABLE keyframe_features (
  keyframe_id INTEGER PRIMARY KEY REFERENCES keyframes(id) ON DELETE CASCADE,
  entropy_threshold REAL NOT NULL,
  superjut_count INTEGER NOT NULL,
  superjuts BLOB NOT NULL,
  keypoint_type TEXT NOT NULL,
  keypoints_stored INTEGER NOT NULL,
  keypoints_masked INTEGER NOT NULL,
  keypoints BLOB NOT NULL,
  descriptor_bytes INTEGER NOT NULL,
  descriptors BLOB NOT NULL
);
)sql",
    // 2 -> 3: random-forest models (the file as uploaded, plus what listing needs without
    // reading it), each map's model, and server-wide settings (the default model).
    R"sql(
CREATE TABLE models (
  id INTEGER PRIMARY KEY,
  name TEXT NOT NULL UNIQUE,
  uploaded_time_s REAL NOT NULL,
  size_bytes INTEGER NOT NULL,
  class_names TEXT NOT NULL,
  class_colors TEXT NOT NULL,
  training_json TEXT NOT NULL,
  trees INTEGER NOT NULL,
  nodes INTEGER NOT NULL,
  data BLOB NOT NULL
);
ALTER TABLE maps ADD COLUMN model_id INTEGER REFERENCES models(id);
CREATE TABLE settings (
  key TEXT PRIMARY KEY,
  value TEXT NOT NULL
);
)sql",
    // 3 -> 4: each visit's architecture (paper 004): its floor plan and descriptor as JSON,
    // rewritten as key frames arrive.
    R"sql(
CREATE TABLE visit_places (
  visit_id INTEGER PRIMARY KEY REFERENCES visits(id) ON DELETE CASCADE,
  keyframes INTEGER NOT NULL,
  floor_plan TEXT NOT NULL,
  descriptor TEXT NOT NULL,
  updated_time_s REAL NOT NULL
);
)sql",
    // 4 -> 5: ids of maps, visits, keyframes and models are never reused (AUTOINCREMENT):
    // reusing a deleted map's or visit's id let a stream still running for the deleted one
    // commit into its successor. SQLite cannot add AUTOINCREMENT to a table, so each is
    // rebuilt (SQLite's documented procedure: new table, copy, drop, rename; run with
    // foreign_keys off, so the rows that reference them are kept as they are).
    R"sql(
CREATE TABLE models_new (
  id INTEGER PRIMARY KEY AUTOINCREMENT,
  name TEXT NOT NULL UNIQUE,
  uploaded_time_s REAL NOT NULL,
  size_bytes INTEGER NOT NULL,
  class_names TEXT NOT NULL,
  class_colors TEXT NOT NULL,
  training_json TEXT NOT NULL,
  trees INTEGER NOT NULL,
  nodes INTEGER NOT NULL,
  data BLOB NOT NULL
);
INSERT INTO models_new (id, name, uploaded_time_s, size_bytes, class_names, class_colors,
                        training_json, trees, nodes, data)
  SELECT id, name, uploaded_time_s, size_bytes, class_names, class_colors, training_json, trees,
         nodes, data FROM models;
DROP TABLE models;
ALTER TABLE models_new RENAME TO models;

CREATE TABLE maps_new (
  id INTEGER PRIMARY KEY AUTOINCREMENT,
  name TEXT NOT NULL UNIQUE,
  description TEXT NOT NULL DEFAULT '',
  created_time_s REAL NOT NULL,
  entropy_threshold REAL,
  model_id INTEGER REFERENCES models(id)
);
INSERT INTO maps_new (id, name, description, created_time_s, entropy_threshold, model_id)
  SELECT id, name, description, created_time_s, entropy_threshold, model_id FROM maps;
DROP TABLE maps;
ALTER TABLE maps_new RENAME TO maps;

CREATE TABLE visits_new (
  id INTEGER PRIMARY KEY AUTOINCREMENT,
  map_id INTEGER NOT NULL REFERENCES maps(id) ON DELETE CASCADE,
  robot TEXT NOT NULL DEFAULT '',
  label TEXT NOT NULL DEFAULT '',
  start_time_s REAL NOT NULL,
  end_time_s REAL NOT NULL DEFAULT 0,
  ended INTEGER NOT NULL DEFAULT 0,
  frame_count INTEGER NOT NULL DEFAULT 0
);
INSERT INTO visits_new (id, map_id, robot, label, start_time_s, end_time_s, ended, frame_count)
  SELECT id, map_id, robot, label, start_time_s, end_time_s, ended, frame_count FROM visits;
DROP TABLE visits;
ALTER TABLE visits_new RENAME TO visits;
CREATE INDEX visits_by_map ON visits(map_id, start_time_s);

CREATE TABLE keyframes_new (
  id INTEGER PRIMARY KEY AUTOINCREMENT,
  visit_id INTEGER NOT NULL REFERENCES visits(id) ON DELETE CASCADE,
  sequence INTEGER NOT NULL,
  timestamp_s REAL NOT NULL,
  has_pose INTEGER NOT NULL,
  tx REAL, ty REAL, tz REAL, qx REAL, qy REAL, qz REAL, qw REAL,
  fx REAL NOT NULL, fy REAL NOT NULL, cx REAL NOT NULL, cy REAL NOT NULL,
  width INTEGER NOT NULL, height INTEGER NOT NULL,
  depth_scale REAL NOT NULL,
  color_encoding INTEGER NOT NULL,
  depth_bytes INTEGER NOT NULL,
  color_bytes INTEGER NOT NULL
);
INSERT INTO keyframes_new SELECT * FROM keyframes;
DROP TABLE keyframes;
ALTER TABLE keyframes_new RENAME TO keyframes;
CREATE INDEX keyframes_by_visit ON keyframes(visit_id, timestamp_s);
)sql",
    // 5 -> 6: appearance place recognition. Each keypoint's 3D point in its camera's frame
    // (float32 x, y, z; NaN without depth; NULL for keyframes stored before), and the
    // vocabularies the appearance index was built with (the newest is in use).
    R"sql(
ALTER TABLE keyframe_features ADD COLUMN points BLOB;
CREATE TABLE appearance_vocabularies (
  id INTEGER PRIMARY KEY AUTOINCREMENT,
  created_time_s REAL NOT NULL,
  source TEXT NOT NULL,
  training_keyframes INTEGER NOT NULL,
  words INTEGER NOT NULL,
  data BLOB NOT NULL
);
)sql",
    // 6 -> 7: keyframe depth paletted (earlier keyframes keep their PNG-16, depth_encoding 1);
    // maps may ask to keep the colour bytes a client sent instead of a JPEG re-encoding;
    // keypoints and points in compact records (record_format 2; earlier rows are format 1).
    R"sql(
ALTER TABLE keyframes ADD COLUMN depth_encoding INTEGER NOT NULL DEFAULT 1;
ALTER TABLE keyframe_images RENAME COLUMN depth_png TO depth;
ALTER TABLE maps ADD COLUMN keep_original_color INTEGER NOT NULL DEFAULT 0;
ALTER TABLE keyframe_features ADD COLUMN record_format INTEGER NOT NULL DEFAULT 1;
)sql",
    // 7 -> 8: where a keyframe's pose came from (issue 15: the server tracks frames sent
    // without one): 0 none, 1 the client, 2 the server's odometry. Earlier poses were the
    // client's. 3: the client's pose refined by the server (FrameOptions.refine_pose).
    R"sql(
ALTER TABLE keyframes ADD COLUMN pose_source INTEGER NOT NULL DEFAULT 1;
UPDATE keyframes SET pose_source = 0 WHERE has_pose = 0;
)sql",
    // 8 -> 9: pose graphs (issue 15). A tracked keyframe keeps the tracker's own pose (odom_*:
    // the odometry's frame, never changed afterwards; consecutive ones of a visit give the
    // graph's odometry edges, within one odom_segment: one run of the tracker, a new one after a
    // restart) beside its pose in the map (tx..qw), which pose-graph solves
    // rewrite; optimisation_id says which solve wrote it (NULL: as tracked or sent). Loop and
    // anchor edges from verified appearance matches, accepted or rejected with the reason, and
    // each solve's record.
    R"sql(
ALTER TABLE keyframes ADD COLUMN odom_tx REAL;
ALTER TABLE keyframes ADD COLUMN odom_ty REAL;
ALTER TABLE keyframes ADD COLUMN odom_tz REAL;
ALTER TABLE keyframes ADD COLUMN odom_qx REAL;
ALTER TABLE keyframes ADD COLUMN odom_qy REAL;
ALTER TABLE keyframes ADD COLUMN odom_qz REAL;
ALTER TABLE keyframes ADD COLUMN odom_qw REAL;
ALTER TABLE keyframes ADD COLUMN odom_segment INTEGER;
ALTER TABLE keyframes ADD COLUMN optimisation_id INTEGER;
CREATE TABLE pose_edges (
  id INTEGER PRIMARY KEY AUTOINCREMENT,
  map_id INTEGER NOT NULL REFERENCES maps(id) ON DELETE CASCADE,
  kind INTEGER NOT NULL,
  from_keyframe INTEGER NOT NULL REFERENCES keyframes(id) ON DELETE CASCADE,
  to_keyframe INTEGER NOT NULL REFERENCES keyframes(id) ON DELETE CASCADE,
  tx REAL NOT NULL, ty REAL NOT NULL, tz REAL NOT NULL,
  qx REAL NOT NULL, qy REAL NOT NULL, qz REAL NOT NULL, qw REAL NOT NULL,
  inliers INTEGER NOT NULL,
  reprojection_px REAL NOT NULL,
  accepted INTEGER NOT NULL,
  reason TEXT NOT NULL,
  created_time_s REAL NOT NULL
);
CREATE INDEX pose_edges_by_map ON pose_edges(map_id, to_keyframe);
CREATE TABLE pose_optimisations (
  id INTEGER PRIMARY KEY AUTOINCREMENT,
  map_id INTEGER NOT NULL REFERENCES maps(id) ON DELETE CASCADE,
  visit_id INTEGER NOT NULL,
  created_time_s REAL NOT NULL,
  keyframes INTEGER NOT NULL,
  odometry_edges INTEGER NOT NULL,
  loop_edges INTEGER NOT NULL,
  loops_rejected INTEGER NOT NULL,
  iterations INTEGER NOT NULL,
  initial_cost REAL NOT NULL,
  final_cost REAL NOT NULL,
  solve_ms REAL NOT NULL,
  max_correction_m REAL NOT NULL
);
)sql",
    // 9 -> 10: a tracked visit anchored into its map's frame (issue 15): the visit it was
    // anchored to, the anchor edge (pose_edges, kind 3), T_map_visit, and the residual between
    // the two matches that agreed on it. NULL anchor_visit_id: not anchored.
    R"sql(
ALTER TABLE visits ADD COLUMN anchor_visit_id INTEGER;
ALTER TABLE visits ADD COLUMN anchor_edge_id INTEGER;
ALTER TABLE visits ADD COLUMN map_tx REAL;
ALTER TABLE visits ADD COLUMN map_ty REAL;
ALTER TABLE visits ADD COLUMN map_tz REAL;
ALTER TABLE visits ADD COLUMN map_qx REAL;
ALTER TABLE visits ADD COLUMN map_qy REAL;
ALTER TABLE visits ADD COLUMN map_qz REAL;
ALTER TABLE visits ADD COLUMN map_qw REAL;
ALTER TABLE visits ADD COLUMN anchor_residual_m REAL;
ALTER TABLE visits ADD COLUMN anchor_residual_deg REAL;
ALTER TABLE visits ADD COLUMN anchored_time_s REAL;
)sql",
    // 10 -> 11: each visit's semantic octree (issue 16): a header and the snapshot's bytes in
    // chunks (a snapshot is replaced whole, in one transaction).
    R"sql(
CREATE TABLE semantic_octrees (
  visit_id INTEGER PRIMARY KEY REFERENCES visits(id) ON DELETE CASCADE,
  model TEXT NOT NULL,
  class_count INTEGER NOT NULL,
  resolution_m REAL NOT NULL,
  keyframes INTEGER NOT NULL,
  bytes INTEGER NOT NULL,
  updated_time_s REAL NOT NULL
);
CREATE TABLE semantic_octree_chunks (
  visit_id INTEGER NOT NULL REFERENCES semantic_octrees(visit_id) ON DELETE CASCADE,
  chunk INTEGER NOT NULL,
  data BLOB NOT NULL,
  PRIMARY KEY (visit_id, chunk)
);
)sql",
    // 11 -> 12: each map's own semantic octree (issue 16), its visits' merged in the map's
    // frame, stored like a visit's, with what it was merged from.
    R"sql(
CREATE TABLE semantic_map_octrees (
  map_id INTEGER PRIMARY KEY REFERENCES maps(id) ON DELETE CASCADE,
  model TEXT NOT NULL,
  class_count INTEGER NOT NULL,
  resolution_m REAL NOT NULL,
  keyframes INTEGER NOT NULL,
  bytes INTEGER NOT NULL,
  updated_time_s REAL NOT NULL,
  sources TEXT NOT NULL,
  merged TEXT NOT NULL
);
CREATE TABLE semantic_map_octree_chunks (
  map_id INTEGER NOT NULL REFERENCES semantic_map_octrees(map_id) ON DELETE CASCADE,
  chunk INTEGER NOT NULL,
  data BLOB NOT NULL,
  PRIMARY KEY (map_id, chunk)
);
)sql",
    // 12 -> 13: API keys (only each secret's SHA-256) with their limits (0 = none of the
    // key's own), the maps a key is limited to, which key created each map, and the audit log
    // of administrative calls (issue 17).
    R"sql(
CREATE TABLE api_keys (
  id INTEGER PRIMARY KEY,
  name TEXT NOT NULL UNIQUE,
  role TEXT NOT NULL,
  every_map INTEGER NOT NULL,
  secret_sha256 TEXT NOT NULL UNIQUE,
  created_time_s REAL NOT NULL,
  last_used_time_s REAL NOT NULL DEFAULT 0,
  revoked_time_s REAL NOT NULL DEFAULT 0,
  max_streams INTEGER NOT NULL DEFAULT 0,
  max_frames_per_s REAL NOT NULL DEFAULT 0,
  max_maps INTEGER NOT NULL DEFAULT 0,
  max_keyframes_per_map INTEGER NOT NULL DEFAULT 0,
  max_model_bytes INTEGER NOT NULL DEFAULT 0
);
ALTER TABLE maps ADD COLUMN created_by_key_id INTEGER;
CREATE TABLE api_key_maps (
  key_id INTEGER NOT NULL REFERENCES api_keys(id) ON DELETE CASCADE,
  map_id INTEGER NOT NULL REFERENCES maps(id) ON DELETE CASCADE,
  PRIMARY KEY (key_id, map_id)
);
CREATE TABLE audit_log (
  id INTEGER PRIMARY KEY,
  time_s REAL NOT NULL,
  key_name TEXT NOT NULL,
  method TEXT NOT NULL,
  request TEXT NOT NULL,
  code TEXT NOT NULL,
  message TEXT NOT NULL,
  peer TEXT NOT NULL
);
CREATE INDEX audit_log_time ON audit_log(time_s);
)sql",
    // 13 -> 14: visits a key may start in an hour (issue 33: 1,000 in 4 s had no bound).
    R"sql(
ALTER TABLE api_keys ADD COLUMN max_visits_per_hour INTEGER NOT NULL DEFAULT 0;
)sql",
    // 14 -> 15: each visit's anchor history (issue 35): anchored, revised (the visit's
    // keyframes moved again, by T_moved_by) with the visit it is anchored to after, its
    // T_map_visit after and why. Visits anchored before have their anchor as the first entry.
    R"sql(
CREATE TABLE anchor_revisions (
  id INTEGER PRIMARY KEY,
  visit_id INTEGER NOT NULL REFERENCES visits(id) ON DELETE CASCADE,
  time_s REAL NOT NULL,
  action TEXT NOT NULL,
  to_visit_id INTEGER NOT NULL,
  edge_id INTEGER,
  map_tx REAL NOT NULL, map_ty REAL NOT NULL, map_tz REAL NOT NULL,
  map_qx REAL NOT NULL, map_qy REAL NOT NULL, map_qz REAL NOT NULL, map_qw REAL NOT NULL,
  reason TEXT NOT NULL
);
CREATE INDEX anchor_revisions_visit ON anchor_revisions(visit_id);
INSERT INTO anchor_revisions (visit_id, time_s, action, to_visit_id, edge_id, map_tx, map_ty,
  map_tz, map_qx, map_qy, map_qz, map_qw, reason)
  SELECT id, anchored_time_s, 'anchored', anchor_visit_id, anchor_edge_id, map_tx, map_ty, map_tz,
    map_qx, map_qy, map_qz, map_qw, 'anchored before anchor revisions were recorded'
  FROM visits WHERE anchor_visit_id IS NOT NULL;
)sql",
    // 15 -> 16: frames the server's tracker lost, per visit (issue 35: a visit that lost a
    // large share of its frames is not one rigid body and is neither anchored nor anchored to).
    R"sql(
ALTER TABLE visits ADD COLUMN lost_frame_count INTEGER NOT NULL DEFAULT 0;
)sql",
    // 16 -> 17: which other visits recognised a keyframe (issue 36): a keyframe of a later (or
    // earlier) visit verified an appearance match to it, so its landmarks survived into that
    // visit. Retention keeps keyframes that recent visits recognised; they weigh more in the
    // appearance ranking.
    R"sql(
CREATE TABLE keyframe_sightings (
  keyframe_id INTEGER NOT NULL REFERENCES keyframes(id) ON DELETE CASCADE,
  visit_id INTEGER NOT NULL,
  time_s REAL NOT NULL,
  PRIMARY KEY (keyframe_id, visit_id)
) WITHOUT ROWID;
)sql",
    // 17 -> 18: annotations (issue 38, paper 002's tool): a class given to regions of a map's
    // frame, boxes packed as 6 little-endian doubles each (min xyz, max xyz; metres).
    R"sql(
CREATE TABLE annotations (
  id INTEGER PRIMARY KEY AUTOINCREMENT,
  map_id INTEGER NOT NULL REFERENCES maps(id) ON DELETE CASCADE,
  class_name TEXT NOT NULL,
  boxes BLOB NOT NULL,
  author TEXT NOT NULL,
  created_time_s REAL NOT NULL
);
CREATE INDEX annotations_map ON annotations(map_id);
-- The counts and sizes maps and visits are listed with, read from an index instead of the
-- keyframes' rows: a map of 100,000 keyframes was listed in 0.7 s (issue 38's browser view).
CREATE INDEX keyframes_sizes ON keyframes(visit_id, depth_bytes, color_bytes, odom_tx);
)sql",
};
static_assert(sizeof(kMigrations) / sizeof(kMigrations[0]) == Store::kSchemaVersion,
              "one migration per schema version");
}  // namespace

absl::Status MigrateSchema(Database* db, int64_t from, const std::string& path) {
  for (int64_t v = from; v < Store::kSchemaVersion; ++v) {
    Transaction tx(db);
    if (auto s = tx.Begin(); !s.ok()) return s;
    if (auto s = db->Exec(kMigrations[v]); !s.ok()) return s;
    // The migration must leave every reference intact (foreign keys are off while it runs).
    auto dangling = db->QueryInt("SELECT COUNT(*) FROM pragma_foreign_key_check");
    if (!dangling.ok()) return dangling.status();
    if (*dangling > 0) {
      return absl::DataLossError(
          absl::StrCat(path, ": migrating to schema ", v + 1, " would leave ", *dangling,
                       " rows referencing rows that do not exist; the file stays at schema ", v,
                       " (run an older lifemapd, or restore a backup)"));
    }
    if (auto s = db->Exec(absl::StrCat("PRAGMA user_version = ", v + 1)); !s.ok()) return s;
    if (auto s = tx.Commit(); !s.ok()) return s;
  }
  return absl::OkStatus();
}

namespace {

constexpr char kKeyframeColumns[] =
    "k.id, k.visit_id, k.sequence, k.timestamp_s, k.has_pose, k.tx, k.ty, k.tz, k.qx, k.qy, "
    "k.qz, k.qw, k.fx, k.fy, k.cx, k.cy, k.width, k.height, k.depth_scale, k.color_encoding, "
    "k.depth_bytes, k.color_bytes, k.depth_encoding, k.pose_source, k.odom_tx, k.odom_ty, "
    "k.odom_tz, k.odom_qx, k.odom_qy, k.odom_qz, k.odom_qw, k.optimisation_id, k.odom_segment";
constexpr int kKeyframeColumnCount = 33;

// Superjut records: int32 id, int32 size_px, float32 entropy, planarity, horizontality,
// textureness, neg_entropy (28 bytes). Keypoints: float32 x, y, size, angle, response (20 bytes).
static_assert(__BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__, "blobs are written little-endian");
constexpr size_t kSuperjutRecord = 28;
constexpr size_t kKeypointRecord = 20;
constexpr size_t kPointRecord = 12;  // float32 x, y, z
// Record format 2 (schema 7 on): a keypoint in 12 bytes, uint16 x, y and size in 1/8 px,
// uint16 angle in 1/100 degree, float32 response; a point in 6 bytes, int16 x, y, z in mm,
// INT16_MIN for none (no depth, or beyond +-32.7 m). 50 bytes a keypoint with its descriptor
// instead of 64: ~9 KB less per keyframe, at 1/16 px and 0.5 mm of rounding (far below ORB's
// and the sensor's own error).
constexpr int kRecordFormat = 2;
constexpr size_t kCompactKeypointRecord = 12;
constexpr size_t kCompactPointRecord = 6;
constexpr int16_t kNoPoint = INT16_MIN;

std::string EncodeSuperjuts(const std::vector<entropy::SuperjutScore>& superjuts) {
  std::string out(superjuts.size() * kSuperjutRecord, '\0');
  char* p = out.data();
  for (const auto& j : superjuts) {
    const int32_t ints[2] = {j.id, j.size_px};
    const float floats[5] = {j.entropy, j.planarity, j.horizontality, j.textureness, j.neg_entropy};
    std::memcpy(p, ints, 8);
    std::memcpy(p + 8, floats, 20);
    p += kSuperjutRecord;
  }
  return out;
}

absl::StatusOr<std::vector<entropy::SuperjutScore>> DecodeSuperjuts(const std::string& blob) {
  if (blob.size() % kSuperjutRecord != 0) {
    return absl::DataLossError("stored superjut table has a truncated record");
  }
  std::vector<entropy::SuperjutScore> out(blob.size() / kSuperjutRecord);
  const char* p = blob.data();
  for (auto& j : out) {
    int32_t ints[2];
    float floats[5];
    std::memcpy(ints, p, 8);
    std::memcpy(floats, p + 8, 20);
    j.id = ints[0];
    j.size_px = ints[1];
    j.entropy = floats[0];
    j.planarity = floats[1];
    j.horizontality = floats[2];
    j.textureness = floats[3];
    j.neg_entropy = floats[4];
    p += kSuperjutRecord;
  }
  return out;
}

// v * scale rounded into [0, 65535]; NaN and negatives to 0.
uint16_t Fixed(float v, float scale) {
  const float units = std::round(v * scale);
  if (!(units > 0.0f)) return 0;
  return static_cast<uint16_t>(std::min(units, 65535.0f));
}

std::string EncodePoints(const std::vector<Eigen::Vector3f>& points) {
  std::string out(points.size() * kCompactPointRecord, '\0');
  for (size_t i = 0; i < points.size(); ++i) {
    int16_t mm[3] = {kNoPoint, kNoPoint, kNoPoint};
    const Eigen::Vector3f scaled = points[i] * 1000.0f;
    if (scaled.allFinite() && scaled.cwiseAbs().maxCoeff() < 32767.0f) {
      for (int a = 0; a < 3; ++a) mm[a] = static_cast<int16_t>(std::lround(scaled[a]));
    }
    std::memcpy(out.data() + i * kCompactPointRecord, mm, kCompactPointRecord);
  }
  return out;
}

std::string EncodeKeypoints(const std::vector<features::Keypoint>& keypoints) {
  std::string out(keypoints.size() * kCompactKeypointRecord, '\0');
  char* p = out.data();
  for (const auto& k : keypoints) {
    const uint16_t fixed[4] = {Fixed(k.x, 8.0f), Fixed(k.y, 8.0f), Fixed(k.size, 8.0f),
                               Fixed(k.angle, 100.0f)};
    std::memcpy(p, fixed, 8);
    std::memcpy(p + 8, &k.response, 4);
    p += kCompactKeypointRecord;
  }
  return out;
}

}  // namespace

absl::StatusOr<int64_t> IntSetting(Database* db, std::string_view key) {
  auto stmt = db->Prepare("SELECT CAST(value AS INTEGER) FROM settings WHERE key = ?1");
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, key);
  auto row = s->Step();
  if (!row.ok()) return row.status();
  return *row ? s->ColumnInt(0) : 0;
}

void BindPose(Statement* s, int first, const Pose& p) {
  s->Bind(first, p.translation.x()).Bind(first + 1, p.translation.y());
  s->Bind(first + 2, p.translation.z());
  s->Bind(first + 3, p.rotation.x()).Bind(first + 4, p.rotation.y());
  s->Bind(first + 5, p.rotation.z()).Bind(first + 6, p.rotation.w());
}

Pose ReadPose(const Statement& s, int first) {
  Pose p;
  p.translation = {s.ColumnDouble(first), s.ColumnDouble(first + 1), s.ColumnDouble(first + 2)};
  p.rotation = Eigen::Quaterniond(s.ColumnDouble(first + 6), s.ColumnDouble(first + 3),
                                  s.ColumnDouble(first + 4), s.ColumnDouble(first + 5))
                   .normalized();
  return p;
}

namespace {

KeyframeRecord ReadKeyframe(const Statement& s) {
  KeyframeRecord k;
  k.id = s.ColumnInt(0);
  k.visit_id = s.ColumnInt(1);
  k.sequence = static_cast<uint64_t>(s.ColumnInt(2));
  k.timestamp_s = s.ColumnDouble(3);
  if (s.ColumnInt(4) != 0) k.T_world_camera = ReadPose(s, 5);
  k.intrinsics.fx = s.ColumnDouble(12);
  k.intrinsics.fy = s.ColumnDouble(13);
  k.intrinsics.cx = s.ColumnDouble(14);
  k.intrinsics.cy = s.ColumnDouble(15);
  k.intrinsics.width = static_cast<int>(s.ColumnInt(16));
  k.intrinsics.height = static_cast<int>(s.ColumnInt(17));
  k.depth_scale = s.ColumnDouble(18);
  k.color_encoding = static_cast<StoredColorEncoding>(s.ColumnInt(19));
  k.depth_bytes = s.ColumnInt(20);
  k.color_bytes = s.ColumnInt(21);
  k.depth_encoding = static_cast<StoredDepthEncoding>(s.ColumnInt(22));
  k.pose_source =
      k.T_world_camera ? static_cast<StoredPoseSource>(s.ColumnInt(23)) : StoredPoseSource::kNone;
  if (!s.ColumnIsNull(24)) k.T_odom_camera = ReadPose(s, 24);
  k.optimisation_id = s.ColumnIsNull(31) ? 0 : s.ColumnInt(31);
  k.odom_segment = s.ColumnIsNull(32) ? 0 : s.ColumnInt(32);
  return k;
}

// The five feature-count columns starting at `c`: superjut_count, entropy_threshold,
// keypoint_type, keypoints_stored, keypoints_masked.
KeyframeFeatureCounts ReadFeatureCounts(const Statement& s, int c) {
  return {static_cast<int>(s.ColumnInt(c)), s.ColumnDouble(c + 1), s.ColumnText(c + 2),
          static_cast<int>(s.ColumnInt(c + 3)), static_cast<int>(s.ColumnInt(c + 4))};
}

VisitRecord ReadVisit(const Statement& s) {
  VisitRecord v;
  v.id = s.ColumnInt(0);
  v.map_id = s.ColumnInt(1);
  v.map_name = s.ColumnText(2);
  v.robot = s.ColumnText(3);
  v.label = s.ColumnText(4);
  v.start_time_s = s.ColumnDouble(5);
  v.end_time_s = s.ColumnDouble(6);
  v.ended = s.ColumnInt(7) != 0;
  v.frame_count = s.ColumnInt(8);
  v.keyframe_count = s.ColumnInt(9);
  v.loops_accepted = s.ColumnInt(10);
  v.loops_rejected = s.ColumnInt(11);
  v.pose_graph_solves = s.ColumnInt(12);
  if (!s.ColumnIsNull(13)) {
    VisitAnchor a;
    a.to_visit_id = s.ColumnInt(13);
    a.edge_id = s.ColumnInt(14);
    a.T_map_visit = ReadPose(s, 15);
    a.residual_m = s.ColumnDouble(22);
    a.residual_deg = s.ColumnDouble(23);
    a.anchored_time_s = s.ColumnDouble(24);
    a.revisions = static_cast<int>(s.ColumnInt(27));
    a.evidence = s.ColumnText(28);
    v.anchor = a;
  }
  v.tracked_keyframes = s.ColumnInt(25);
  v.first_of_map = s.ColumnInt(26) != 0;
  v.anchor_dropped = s.ColumnText(29);
  v.lost_frame_count = s.ColumnInt(30);
  if (!s.ColumnIsNull(31)) v.data_start_time_s = s.ColumnDouble(31);
  if (!s.ColumnIsNull(32)) v.data_end_time_s = s.ColumnDouble(32);
  return v;
}

// Loop edges are counted by their querying keyframe's visit.
constexpr char kVisitSelect[] =
    "SELECT v.id, v.map_id, m.name, v.robot, v.label, v.start_time_s, v.end_time_s, v.ended, "
    "v.frame_count, (SELECT COUNT(*) FROM keyframes k WHERE k.visit_id = v.id), "
    "(SELECT COUNT(*) FROM pose_edges e JOIN keyframes k ON k.id = e.to_keyframe WHERE "
    "e.map_id = v.map_id AND k.visit_id = v.id AND e.kind = 2 AND e.accepted = 1), "
    "(SELECT COUNT(*) FROM pose_edges e JOIN keyframes k ON k.id = e.to_keyframe WHERE "
    "e.map_id = v.map_id AND k.visit_id = v.id AND e.kind = 2 AND e.accepted = 0), "
    "(SELECT COUNT(*) FROM pose_optimisations o WHERE o.map_id = v.map_id AND "
    "o.visit_id = v.id), v.anchor_visit_id, v.anchor_edge_id, v.map_tx, v.map_ty, v.map_tz, "
    "v.map_qx, v.map_qy, v.map_qz, v.map_qw, v.anchor_residual_m, v.anchor_residual_deg, "
    "v.anchored_time_s, (SELECT COUNT(*) FROM keyframes k WHERE k.visit_id = v.id AND "
    "k.odom_tx IS NOT NULL), v.id = (SELECT MIN(w.id) FROM visits w WHERE w.map_id = v.map_id), "
    "(SELECT COUNT(*) FROM anchor_revisions r WHERE r.visit_id = v.id AND r.action = 'revised'), "
    "COALESCE((SELECT e.reason FROM pose_edges e WHERE e.id = v.anchor_edge_id), ''), "
    "CASE WHEN v.anchor_visit_id IS NULL THEN COALESCE((SELECT r.reason FROM anchor_revisions r "
    "WHERE r.visit_id = v.id AND r.action = 'dropped' ORDER BY r.id DESC LIMIT 1), '') ELSE '' "
    "END, v.lost_frame_count, "
    "(SELECT MIN(k.timestamp_s) FROM keyframes k WHERE k.visit_id = v.id), "
    "(SELECT MAX(k.timestamp_s) FROM keyframes k WHERE k.visit_id = v.id) "
    "FROM visits v JOIN maps m ON m.id = v.map_id ";

constexpr char kMapSelect[] =
    "SELECT m.id, m.name, m.description, m.created_time_s, "
    "(SELECT COUNT(*) FROM visits v WHERE v.map_id = m.id), "
    "(SELECT COUNT(*) FROM keyframes k JOIN visits v ON v.id = k.visit_id WHERE v.map_id = m.id), "
    "(SELECT COALESCE(SUM(k.depth_bytes + k.color_bytes), 0) FROM keyframes k "
    " JOIN visits v ON v.id = k.visit_id WHERE v.map_id = m.id), m.entropy_threshold, "
    "m.keep_original_color "
    "FROM maps m ";

MapRecord ReadMap(const Statement& s) {
  MapRecord m;
  m.id = s.ColumnInt(0);
  m.name = s.ColumnText(1);
  m.description = s.ColumnText(2);
  m.created_time_s = s.ColumnDouble(3);
  m.visit_count = s.ColumnInt(4);
  m.keyframe_count = s.ColumnInt(5);
  m.stored_bytes = s.ColumnInt(6);
  if (!s.ColumnIsNull(7)) m.entropy_threshold = s.ColumnDouble(7);
  m.keep_original_color = s.ColumnInt(8) != 0;
  return m;
}

}  // namespace

absl::Status ValidateName(const std::string& name, absl::string_view kind, size_t max_length) {
  if (name.empty() || name.size() > max_length) {
    return absl::InvalidArgumentError(
        absl::StrCat(kind, " name must be 1 to ", max_length, " characters, got ", name.size()));
  }
  if (name[0] == '.') {
    return absl::InvalidArgumentError(absl::StrCat(kind, " name must not start with '.'"));
  }
  for (char c : name) {
    const bool ok = (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') ||
                    c == '.' || c == '_' || c == '-';
    if (!ok) {
      return absl::InvalidArgumentError(
          absl::StrCat(kind, " name '", name, "' may only use letters, digits, '.', '_' and '-'"));
    }
  }
  return absl::OkStatus();
}

absl::Status ValidateMapName(const std::string& name) {
  constexpr size_t kMaxBytes = 64;
  if (name.empty() || name.size() > kMaxBytes) {
    return absl::InvalidArgumentError(absl::StrCat("map name must be 1 to ", kMaxBytes,
                                                   " bytes of UTF-8, got ", name.size(), " bytes"));
  }
  const auto code_points = Utf8CodePoints(name);
  if (!code_points) {
    return absl::InvalidArgumentError(
        "map name is not valid UTF-8: send the name as UTF-8 text (e.g. set LANG=C.UTF-8)");
  }
  const std::u32string& cps = *code_points;
  if (cps.front() == U'.' || cps.front() == U' ' || cps.back() == U' ') {
    return absl::InvalidArgumentError(
        absl::StrCat("map name '", EscapeForLog(name),
                     "' must not start with '.' or start or end with a space"));
  }
  for (size_t i = 0; i < cps.size(); ++i) {
    const char32_t c = cps[i];
    const bool ascii_ok = (c >= U'a' && c <= U'z') || (c >= U'A' && c <= U'Z') ||
                          (c >= U'0' && c <= U'9') || c == U'.' || c == U'_' || c == U'-' ||
                          c == U' ';
    // Beyond ASCII: letters of any script, accents, CJK, symbols; never controls, invisible or
    // direction-changing characters (a name must read as what it is), nor the no-break space.
    const bool other_ok = c > 0xA0 && !IsInvisibleOrControl(c);
    if (!(ascii_ok || other_ok) || (c == U' ' && i > 0 && cps[i - 1] == U' ')) {
      return absl::InvalidArgumentError(absl::StrCat(
          "map name '", EscapeForLog(name),
          "' may only use letters and digits (any script), '.', '_', '-' and single spaces"));
    }
  }
  return absl::OkStatus();
}

absl::StatusOr<MapRecord> Store::Impl::GetMapLocked(Database* db, const std::string& name) {
  auto stmt = db->Prepare(absl::StrCat(kMapSelect, "WHERE m.name = ?1"));
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, name);
  auto row = s->Step();
  if (!row.ok()) return row.status();
  if (!*row) return absl::NotFoundError(absl::StrCat("map '", name, "' does not exist"));
  return ReadMap(*s);
}

absl::StatusOr<VisitRecord> Store::Impl::GetVisitLocked(Database* db, int64_t visit_id) {
  auto stmt = db->Prepare(absl::StrCat(kVisitSelect, "WHERE v.id = ?1"));
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, visit_id);
  auto row = s->Step();
  if (!row.ok()) return row.status();
  if (!*row) return absl::NotFoundError(absl::StrCat("visit ", visit_id, " does not exist"));
  return ReadVisit(*s);
}

Store::Store(std::unique_ptr<Impl> impl, std::string path)
    : impl_(std::move(impl)), path_(std::move(path)) {}

Store::~Store() {
  // Fold the WAL back into the main file so a cleanly stopped server leaves one file.
  absl::MutexLock lock(&impl_->write_mu);
  if (impl_->write_db) impl_->write_db->Exec("PRAGMA wal_checkpoint(TRUNCATE)").IgnoreError();
}

absl::StatusOr<std::unique_ptr<Store>> Store::Open(const std::string& path,
                                                   const StoreOptions& options) {
  if (path.empty()) return absl::InvalidArgumentError("database path is empty");
  const fs::path parent = fs::absolute(path).parent_path();
  if (!fs::is_directory(parent)) {
    return absl::NotFoundError(
        absl::StrCat("directory ", parent.string(), " for the database does not exist"));
  }
  auto impl = std::make_unique<Impl>();
  auto write_db = Database::Open(path, options.create_if_missing, false, options.busy_timeout_ms);
  if (!write_db.ok()) return write_db.status();
  Database* db = write_db->get();
  // SQLite opens a file it may not write read-only, silently: every write would fail later.
  if (sqlite3_db_readonly(db->raw(), "main") == 1) {
    return absl::FailedPreconditionError(absl::StrCat(
        "database ", path,
        " is read-only to lifemapd: give its user write permission on the file and its "
        "directory (for the -wal and -shm files), or remount it read-write"));
  }
  // WAL: readers never block the writer; FULL syncs the WAL on every commit.
  auto mode = db->Prepare("PRAGMA journal_mode=WAL");
  if (!mode.ok()) {
    return absl::FailedPreconditionError(
        absl::StrCat(path, " is not a usable SQLite database: ", mode.status().message(),
                     "; restore a backup (lifemap admin backup makes them)"));
  }
  {
    StatementScope s(*mode);
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (!*row || s->ColumnText(0) != "wal") {
      return absl::FailedPreconditionError(
          absl::StrCat(path, ": could not switch to WAL mode (is the file system local?)"));
    }
  }
  if (auto s = db->Exec(
          absl::StrCat("PRAGMA synchronous=", options.synchronous_full ? "FULL" : "NORMAL"));
      !s.ok()) {
    return s;
  }

  auto version = db->QueryInt("PRAGMA user_version");
  if (!version.ok()) return version.status();
  if (*version > kSchemaVersion) {
    return absl::FailedPreconditionError(
        absl::StrCat(path, " has schema version ", *version, ", newer than this lifemapd knows (",
                     kSchemaVersion, "); run a newer lifemapd or restore a backup"));
  }
  if (*version == 0) {
    // A new file, or one that is not lifemap's: refuse files that already hold other tables.
    auto tables = db->QueryInt("SELECT COUNT(*) FROM sqlite_master WHERE type = 'table'");
    if (!tables.ok()) return tables.status();
    if (*tables > 0) {
      return absl::FailedPreconditionError(
          absl::StrCat(path, " holds tables but is not a lifemap database"));
    }
  }
  if (auto s = MigrateSchema(db, *version, path); !s.ok()) return s;
  if (options.quick_check) {
    auto check = db->Prepare("PRAGMA quick_check(1)");
    if (!check.ok()) return check.status();
    StatementScope s(*check);
    auto row = s->Step();
    if (!row.ok()) {
      return absl::DataLossError(absl::StrCat(path, " is damaged (", row.status().message(),
                                              "): restore a backup, or try `sqlite3 ", path,
                                              " .recover` on a copy"));
    }
    if (*row && s->ColumnText(0) != "ok") {
      return absl::DataLossError(
          absl::StrCat(path, " is damaged: ", absl::StrReplaceAll(s->ColumnText(0), {{"\n", " "}}),
                       "; restore a backup, or try `sqlite3 ", path, " .recover` on a copy"));
    }
  }
  // Foreign keys are enforced from here on (migrations ran without them: a table rebuild must
  // not cascade).
  if (auto s = db->Exec("PRAGMA foreign_keys=ON"); !s.ok()) return s;

  auto read_db = Database::Open(path, false, true, options.busy_timeout_ms);
  if (!read_db.ok()) return read_db.status();
  // From here on, a commit to a database file that was deleted or replaced is refused (the
  // WAL exists now: the connection has read in WAL mode).
  db->GuardCommits();
  {
    absl::MutexLock w(&impl->write_mu);
    impl->write_db = *std::move(write_db);
  }
  {
    absl::MutexLock r(&impl->read_mu);
    impl->read_db = *std::move(read_db);
  }
  return std::unique_ptr<Store>(new Store(std::move(impl), path));
}

absl::StatusOr<MapRecord> Store::CreateMap(const std::string& name, const std::string& description,
                                           double created_time_s,
                                           std::optional<double> entropy_threshold,
                                           bool keep_original_color, const MapCreator& creator) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  // Counted under the write lock: two creates by one key cannot both pass the limit.
  if (creator.max_maps > 0) {
    auto count = db->Prepare("SELECT COUNT(*) FROM maps WHERE created_by_key_id = ?1");
    if (!count.ok()) return count.status();
    StatementScope s(*count);
    s->Bind(1, creator.key_id);
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (s->ColumnInt(0) >= creator.max_maps) {
      return absl::ResourceExhaustedError(absl::StrCat(
          "API key '", creator.key_name, "' may create at most ", creator.max_maps,
          " maps (its max_maps limit) and ", s->ColumnInt(0),
          " it created still exist: delete one, or ask an admin for a key with a higher limit"));
    }
  }
  auto stmt = db->Prepare(
      "INSERT INTO maps (name, description, created_time_s, entropy_threshold, "
      "keep_original_color, created_by_key_id) VALUES (?1, ?2, ?3, ?4, ?5, ?6)");
  if (!stmt.ok()) return stmt.status();
  {
    StatementScope s(*stmt);
    s->Bind(1, name).Bind(2, description).Bind(3, created_time_s);
    if (entropy_threshold) {
      s->Bind(4, *entropy_threshold);
    } else {
      s->BindNull(4);
    }
    s->Bind(5, int64_t{keep_original_color});
    if (creator.key_id > 0) {
      s->Bind(6, creator.key_id);
    } else {
      s->BindNull(6);
    }
    if (auto st = s->Run(); !st.ok()) {
      if (IsConstraintViolation(st)) {
        return absl::AlreadyExistsError(absl::StrCat("map '", name, "' already exists"));
      }
      return st;
    }
  }
  return impl_->GetMapLocked(db, name);
}

absl::StatusOr<MapRecord> Store::UpdateMap(const std::string& name, const MapUpdate& update) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  Transaction tx(db);
  if (auto s = tx.Begin(); !s.ok()) return s;
  auto map = impl_->GetMapLocked(db, name);
  if (!map.ok()) return map.status();
  if (update.description) {
    auto stmt = db->Prepare("UPDATE maps SET description = ?2 WHERE id = ?1");
    if (!stmt.ok()) return stmt.status();
    StatementScope s(*stmt);
    s->Bind(1, map->id).Bind(2, *update.description);
    if (auto st = s->Run(); !st.ok()) return st;
  }
  if (update.set_entropy_threshold) {
    auto stmt = db->Prepare("UPDATE maps SET entropy_threshold = ?2 WHERE id = ?1");
    if (!stmt.ok()) return stmt.status();
    StatementScope s(*stmt);
    s->Bind(1, map->id);
    if (update.entropy_threshold) {
      s->Bind(2, *update.entropy_threshold);
    } else {
      s->BindNull(2);
    }
    if (auto st = s->Run(); !st.ok()) return st;
  }
  if (update.keep_original_color) {
    auto stmt = db->Prepare("UPDATE maps SET keep_original_color = ?2 WHERE id = ?1");
    if (!stmt.ok()) return stmt.status();
    StatementScope s(*stmt);
    s->Bind(1, map->id).Bind(2, int64_t{*update.keep_original_color});
    if (auto st = s->Run(); !st.ok()) return st;
  }
  if (auto s = tx.Commit(); !s.ok()) return s;
  return impl_->GetMapLocked(db, name);
}

absl::StatusOr<std::vector<MapRecord>> Store::ListMaps() {
  absl::MutexLock lock(&impl_->read_mu);
  auto stmt = impl_->read_db->Prepare(absl::StrCat(kMapSelect, "ORDER BY m.name"));
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  std::vector<MapRecord> maps;
  for (;;) {
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    maps.push_back(ReadMap(*s));
  }
  return maps;
}

absl::StatusOr<std::vector<std::pair<int64_t, std::string>>> Store::ListMapNames() {
  absl::MutexLock lock(&impl_->read_mu);
  auto stmt = impl_->read_db->Prepare("SELECT id, name FROM maps ORDER BY name");
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  std::vector<std::pair<int64_t, std::string>> maps;
  for (;;) {
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    maps.emplace_back(s->ColumnInt(0), s->ColumnText(1));
  }
  return maps;
}

absl::StatusOr<MapRecord> Store::GetMap(const std::string& name) {
  absl::MutexLock lock(&impl_->read_mu);
  return impl_->GetMapLocked(impl_->read_db.get(), name);
}

absl::StatusOr<MapRecord> Store::GetMapById(int64_t map_id) {
  absl::MutexLock lock(&impl_->read_mu);
  auto stmt = impl_->read_db->Prepare(absl::StrCat(kMapSelect, "WHERE m.id = ?1"));
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, map_id);
  auto row = s->Step();
  if (!row.ok()) return row.status();
  if (!*row) return absl::NotFoundError(absl::StrCat("map ", map_id, " does not exist"));
  return ReadMap(*s);
}

absl::StatusOr<std::pair<int64_t, int64_t>> Store::DeleteMap(const std::string& name) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  Transaction tx(db);
  if (auto s = tx.Begin(); !s.ok()) return s;
  auto map = impl_->GetMapLocked(db, name);
  if (!map.ok()) return map.status();
  auto stmt = db->Prepare("DELETE FROM maps WHERE id = ?1");
  if (!stmt.ok()) return stmt.status();
  {
    StatementScope s(*stmt);
    s->Bind(1, map->id);
    if (auto st = s->Run(); !st.ok()) return st;
  }
  if (auto s = tx.Commit(); !s.ok()) return s;
  return std::make_pair(map->visit_count, map->keyframe_count);
}

absl::StatusOr<VisitDeletion> Store::DeleteVisit(int64_t visit_id) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  Transaction tx(db);
  if (auto s = tx.Begin(); !s.ok()) return s;
  auto visit = impl_->GetVisitLocked(db, visit_id);
  if (!visit.ok()) return visit.status();
  if (!visit->ended) {
    return absl::FailedPreconditionError(absl::StrCat("visit ", visit_id,
                                                      " is open: end it first (lifemap visits "
                                                      "end ",
                                                      visit_id, ")"));
  }
  // Ids of visits of the map matching `where` (?1 = the visit, ?2 = its map).
  const auto visits_where = [&](const char* where) -> absl::StatusOr<std::vector<int64_t>> {
    auto stmt = db->Prepare(absl::StrCat(
        "SELECT id FROM visits WHERE map_id = ?2 AND id <> ?1 AND ", where, " ORDER BY id"));
    if (!stmt.ok()) return stmt.status();
    StatementScope s(*stmt);
    s->Bind(1, visit_id).Bind(2, visit->map_id);
    std::vector<int64_t> ids;
    while (true) {
      auto row = s->Step();
      if (!row.ok()) return row.status();
      if (!*row) break;
      ids.push_back(s->ColumnInt(0));
    }
    return ids;
  };
  auto anchored = visits_where("anchor_visit_id = ?1");
  if (!anchored.ok()) return anchored.status();
  if (!anchored->empty()) {
    return absl::FailedPreconditionError(absl::StrCat(
        "visits ", absl::StrJoin(*anchored, ", "), " of map '", visit->map_name,
        "' are anchored to visit ", visit_id, ": their frame is its; delete them first"));
  }
  if (visit->first_of_map) {
    auto tracked = visits_where(
        "EXISTS (SELECT 1 FROM keyframes k WHERE k.visit_id = visits.id AND k.odom_tx IS NOT "
        "NULL)");
    if (!tracked.ok()) return tracked.status();
    if (!tracked->empty()) {
      return absl::FailedPreconditionError(
          absl::StrCat("visit ", visit_id, " is map '", visit->map_name,
                       "''s first visit, whose frame is the map's, and the tracked visits ",
                       absl::StrJoin(*tracked, ", "),
                       " stand in it: delete them first (or the map), or keep it"));
    }
  }
  VisitDeletion out;
  out.map_id = visit->map_id;
  out.map_name = visit->map_name;
  {
    auto stmt = db->Prepare("SELECT id FROM keyframes WHERE visit_id = ?1 ORDER BY id");
    if (!stmt.ok()) return stmt.status();
    StatementScope s(*stmt);
    s->Bind(1, visit_id);
    while (true) {
      auto row = s->Step();
      if (!row.ok()) return row.status();
      if (!*row) break;
      out.keyframe_ids.push_back(s->ColumnInt(0));
    }
  }
  // What names the visit without a foreign key; the rest cascades from the visit's row.
  for (const char* sql :
       {"DELETE FROM keyframe_sightings WHERE visit_id = ?1",
        "DELETE FROM pose_optimisations WHERE visit_id = ?1", "DELETE FROM visits WHERE id = ?1"}) {
    auto stmt = db->Prepare(sql);
    if (!stmt.ok()) return stmt.status();
    StatementScope s(*stmt);
    s->Bind(1, visit_id);
    if (auto st = s->Run(); !st.ok()) return st;
  }
  if (auto s = tx.Commit(); !s.ok()) return s;
  return out;
}

absl::StatusOr<MapRecord> Store::RenameMap(const std::string& name, const std::string& new_name) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  auto stmt = db->Prepare("UPDATE maps SET name = ?2 WHERE name = ?1");
  if (!stmt.ok()) return stmt.status();
  {
    StatementScope s(*stmt);
    s->Bind(1, name).Bind(2, new_name);
    if (auto st = s->Run(); !st.ok()) {
      if (IsConstraintViolation(st)) {
        return absl::AlreadyExistsError(absl::StrCat("map '", new_name, "' already exists"));
      }
      return st;
    }
  }
  if (db->Changes() == 0)
    return absl::NotFoundError(absl::StrCat("map '", name, "' does not exist"));
  return impl_->GetMapLocked(db, new_name);
}

absl::StatusOr<VisitRecord> Store::StartVisit(const std::string& map_name, const std::string& robot,
                                              const std::string& label, double start_time_s) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  auto map = impl_->GetMapLocked(db, map_name);
  if (!map.ok()) return map.status();
  auto id = ReserveRowIds(db, "visits");
  if (!id.ok()) return id.status();
  auto stmt = db->Prepare(
      "INSERT INTO visits (map_id, robot, label, start_time_s, id) VALUES (?1, ?2, ?3, ?4, ?5)");
  if (!stmt.ok()) return stmt.status();
  {
    StatementScope s(*stmt);
    s->Bind(1, map->id).Bind(2, robot).Bind(3, label).Bind(4, start_time_s);
    BindRowId(&*s, 5, *id);
    if (auto st = s->Run(); !st.ok()) return st;
  }
  return impl_->GetVisitLocked(db, db->LastInsertRowId());
}

absl::StatusOr<VisitRecord> Store::GetVisit(int64_t visit_id) {
  absl::MutexLock lock(&impl_->read_mu);
  return impl_->GetVisitLocked(impl_->read_db.get(), visit_id);
}

absl::StatusOr<std::optional<int64_t>> Store::FindKeyframe(int64_t visit_id, uint64_t sequence,
                                                           double timestamp_s) {
  absl::MutexLock lock(&impl_->read_mu);
  auto stmt = impl_->read_db->Prepare(
      "SELECT id FROM keyframes WHERE visit_id = ?1 AND timestamp_s = ?2 AND sequence = ?3");
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, visit_id).Bind(2, timestamp_s).Bind(3, static_cast<int64_t>(sequence));
  auto row = s->Step();
  if (!row.ok()) return row.status();
  if (!*row) return std::optional<int64_t>();
  return std::optional<int64_t>(s->ColumnInt(0));
}

absl::StatusOr<VisitRecord> Store::EndVisit(int64_t visit_id, double end_time_s,
                                            VisitFrameCount counts) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  auto stmt = db->Prepare(
      "UPDATE visits SET ended = 1, end_time_s = ?2, frame_count = MAX(frame_count, ?3), "
      "lost_frame_count = MAX(lost_frame_count, ?4) WHERE id = ?1");
  if (!stmt.ok()) return stmt.status();
  {
    StatementScope s(*stmt);
    s->Bind(1, visit_id)
        .Bind(2, end_time_s)
        .Bind(3, counts.frame_count)
        .Bind(4, counts.lost_frame_count);
    if (auto st = s->Run(); !st.ok()) return st;
  }
  if (db->Changes() == 0)
    return absl::NotFoundError(absl::StrCat("visit ", visit_id, " does not exist"));
  return impl_->GetVisitLocked(db, visit_id);
}

absl::StatusOr<std::vector<VisitRecord>> Store::ListVisits(const std::string& map_name) {
  absl::MutexLock lock(&impl_->read_mu);
  Database* db = impl_->read_db.get();
  auto map = impl_->GetMapLocked(db, map_name);
  if (!map.ok()) return map.status();
  auto stmt = db->Prepare(absl::StrCat(kVisitSelect, "WHERE v.map_id = ?1 ORDER BY v.id"));
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, map->id);
  std::vector<VisitRecord> visits;
  for (;;) {
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    visits.push_back(ReadVisit(*s));
  }
  return visits;
}

absl::StatusOr<std::optional<VisitRecord>> Store::LatestOpenVisit(const std::string& map_name) {
  absl::MutexLock lock(&impl_->read_mu);
  Database* db = impl_->read_db.get();
  auto map = impl_->GetMapLocked(db, map_name);
  if (!map.ok()) return map.status();
  auto stmt = db->Prepare(
      absl::StrCat(kVisitSelect, "WHERE v.map_id = ?1 AND v.ended = 0 ORDER BY v.id DESC LIMIT 1"));
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, map->id);
  auto row = s->Step();
  if (!row.ok()) return row.status();
  if (!*row) return std::optional<VisitRecord>();
  return std::optional<VisitRecord>(ReadVisit(*s));
}

EncodedDepth StoredDepth(const KeyframeRecord& k) {
  return {k.depth_encoding == StoredDepthEncoding::kPaletted ? DepthEncoding::kPaletted
                                                             : DepthEncoding::kPng16,
          k.depth, k.intrinsics.width, k.intrinsics.height, k.depth_scale};
}

EncodedColor StoredColor(const KeyframeRecord& k) {
  return {
      k.color_encoding == StoredColorEncoding::kPng ? ColorEncoding::kPng : ColorEncoding::kJpeg,
      k.color, k.intrinsics.width, k.intrinsics.height};
}

EncodedRgbdFrame StoredFrame(const KeyframeRecord& k) {
  EncodedRgbdFrame f;
  f.sequence = k.sequence;
  f.timestamp_s = k.timestamp_s;
  f.intrinsics = k.intrinsics;
  f.depth = StoredDepth(k);
  f.color = StoredColor(k);
  f.T_world_camera = k.T_world_camera;
  return f;
}

absl::Status Store::InsertKeyframes(std::vector<KeyframeRecord>* keyframes,
                                    const std::vector<VisitFrameCount>& frame_counts) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  Transaction tx(db);
  if (auto s = tx.Begin(); !s.ok()) return s;
  auto insert = db->Prepare(
      "INSERT INTO keyframes (visit_id, sequence, timestamp_s, has_pose, tx, ty, tz, qx, qy, qz, "
      "qw, fx, fy, cx, cy, width, height, depth_scale, color_encoding, depth_bytes, color_bytes, "
      "depth_encoding, pose_source, odom_tx, odom_ty, odom_tz, odom_qx, odom_qy, odom_qz, "
      "odom_qw, odom_segment, id) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, "
      "?13, ?14, ?15, ?16, ?17, ?18, ?19, ?20, ?21, ?22, ?23, ?24, ?25, ?26, ?27, ?28, ?29, ?30, "
      "?31, ?32)");
  if (!insert.ok()) return insert.status();
  auto insert_images =
      db->Prepare("INSERT INTO keyframe_images (keyframe_id, depth, color) VALUES (?1, ?2, ?3)");
  if (!insert_images.ok()) return insert_images.status();
  auto visit_exists = db->Prepare("SELECT ended FROM visits WHERE id = ?1");
  if (!visit_exists.ok()) return visit_exists.status();
  auto stored_before = db->Prepare(
      "SELECT id FROM keyframes WHERE visit_id = ?1 AND timestamp_s = ?2 AND sequence = ?3");
  if (!stored_before.ok()) return stored_before.status();

  for (auto& k : *keyframes) {
    {
      StatementScope v(*visit_exists);
      v->Bind(1, k.visit_id);
      auto row = v->Step();
      if (!row.ok()) return row.status();
      if (!*row) {
        return absl::NotFoundError(absl::StrCat(
            "visit ", k.visit_id, " no longer exists (its map was deleted); keyframe not stored"));
      }
      if (v->ColumnInt(0) != 0) {
        return absl::FailedPreconditionError(absl::StrCat(
            "visit ", k.visit_id, " has ended; keyframe not stored (start a new visit)"));
      }
    }
    {
      StatementScope s(*stored_before);
      s->Bind(1, k.visit_id).Bind(2, k.timestamp_s).Bind(3, static_cast<int64_t>(k.sequence));
      auto row = s->Step();
      if (!row.ok()) return row.status();
      if (*row) {
        k.id = s->ColumnInt(0);
        k.resent = true;
        continue;
      }
    }
    auto id = ReserveRowIds(db, "keyframes");
    if (!id.ok()) return id.status();
    {
      StatementScope s(*insert);
      BindRowId(&*s, 32, *id);
      s->Bind(1, k.visit_id).Bind(2, static_cast<int64_t>(k.sequence)).Bind(3, k.timestamp_s);
      s->Bind(4, int64_t{k.T_world_camera.has_value()});
      if (k.T_world_camera) {
        BindPose(&*s, 5, *k.T_world_camera);
      } else {
        for (int i = 5; i <= 11; ++i) s->BindNull(i);
      }
      s->Bind(12, k.intrinsics.fx).Bind(13, k.intrinsics.fy);
      s->Bind(14, k.intrinsics.cx).Bind(15, k.intrinsics.cy);
      s->Bind(16, int64_t{k.intrinsics.width}).Bind(17, int64_t{k.intrinsics.height});
      s->Bind(18, k.depth_scale).Bind(19, static_cast<int64_t>(k.color_encoding));
      k.depth_bytes = static_cast<int64_t>(k.depth.size());
      k.color_bytes = static_cast<int64_t>(k.color.size());
      s->Bind(20, k.depth_bytes).Bind(21, k.color_bytes);
      s->Bind(22, static_cast<int64_t>(k.depth_encoding));
      s->Bind(23, static_cast<int64_t>(k.T_world_camera ? k.pose_source : StoredPoseSource::kNone));
      if (k.T_odom_camera) {
        BindPose(&*s, 24, *k.T_odom_camera);
        s->Bind(31, k.odom_segment);
      } else {
        for (int i = 24; i <= 31; ++i) s->BindNull(i);
      }
      if (auto st = s->Run(); !st.ok()) return st;
    }
    k.id = db->LastInsertRowId();
    {
      StatementScope s(*insert_images);
      s->Bind(1, k.id).BindBlob(2, k.depth).BindBlob(3, k.color);
      if (auto st = s->Run(); !st.ok()) return st;
    }
    for (const int64_t seen : k.sighted_keyframes) {
      // A keyframe deleted meanwhile (its map, or retention) is skipped, not an error.
      auto sight = db->Prepare(
          "INSERT OR IGNORE INTO keyframe_sightings (keyframe_id, visit_id, time_s) SELECT ?1, "
          "?2, ?3 WHERE EXISTS (SELECT 1 FROM keyframes WHERE id = ?1)");
      if (!sight.ok()) return sight.status();
      StatementScope s(*sight);
      s->Bind(1, seen).Bind(2, k.visit_id).Bind(3, k.timestamp_s);
      if (auto st = s->Run(); !st.ok()) return st;
    }
    if (k.features) {
      const auto& f = *k.features;
      const std::string superjuts = EncodeSuperjuts(f.superjuts);
      const std::string keypoints = EncodeKeypoints(f.keypoints.keypoints);
      const cv::Mat& d = f.keypoints.descriptors;
      const size_t row_bytes = d.empty() ? 0 : d.cols * d.elemSize();
      std::string descriptors;
      for (int r = 0; r < d.rows; ++r) descriptors.append(d.ptr<char>(r), row_bytes);
      auto insert_features = db->Prepare(
          "INSERT INTO keyframe_features (keyframe_id, entropy_threshold, superjut_count, "
          "superjuts, keypoint_type, keypoints_stored, keypoints_masked, keypoints, "
          "descriptor_bytes, descriptors, points, record_format) VALUES (?1, ?2, ?3, ?4, ?5, ?6, "
          "?7, ?8, ?9, ?10, ?11, ?12)");
      if (!insert_features.ok()) return insert_features.status();
      StatementScope s(*insert_features);
      s->Bind(1, k.id).Bind(2, f.entropy_threshold);
      s->Bind(3, static_cast<int64_t>(f.superjuts.size())).BindBlob(4, superjuts);
      s->Bind(5, f.keypoints.type).Bind(6, static_cast<int64_t>(f.keypoints.keypoints.size()));
      s->Bind(7, int64_t{f.keypoints.masked}).BindBlob(8, keypoints);
      s->Bind(9, static_cast<int64_t>(row_bytes)).BindBlob(10, descriptors);
      if (f.keypoints.points.size() == f.keypoints.keypoints.size()) {
        s->BindBlob(11, EncodePoints(f.keypoints.points));
      } else {
        s->BindNull(11);
      }
      s->Bind(12, int64_t{kRecordFormat});
      if (auto st = s->Run(); !st.ok()) return st;
    }
  }
  auto update_count = db->Prepare(
      "UPDATE visits SET frame_count = MAX(frame_count, ?2), "
      "lost_frame_count = MAX(lost_frame_count, ?3) WHERE id = ?1");
  if (!update_count.ok()) return update_count.status();
  for (const auto& c : frame_counts) {
    StatementScope s(*update_count);
    s->Bind(1, c.visit_id).Bind(2, c.frame_count).Bind(3, c.lost_frame_count);
    if (auto st = s->Run(); !st.ok()) return st;
  }
  auto committed = tx.Commit();
  if (!committed.ok()) {
    for (auto& k : *keyframes) k.id = 0;
  }
  return committed;
}

absl::StatusOr<std::vector<KeyframeRecord>> Store::ListKeyframes(int64_t map_id, int64_t visit_id,
                                                                 int64_t offset, int64_t limit) {
  absl::MutexLock lock(&impl_->read_mu);
  auto stmt = impl_->read_db->Prepare(
      absl::StrCat("SELECT ", kKeyframeColumns,
                   ", f.superjut_count, f.entropy_threshold, f.keypoint_type, f.keypoints_stored, "
                   "f.keypoints_masked FROM keyframes k "
                   "LEFT JOIN keyframe_features f ON f.keyframe_id = k.id "
                   // Driven by keyframes_by_visit, in its order: no sort of the map's keyframes
                   // for a page of them (0.8 s for 100,000 as a join from visits).
                   "WHERE k.visit_id IN (SELECT id FROM visits WHERE map_id = ?1) "
                   "AND (?2 = 0 OR k.visit_id = ?2) ORDER BY k.visit_id, k.timestamp_s, k.id "
                   "LIMIT ?3 OFFSET ?4"));
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, map_id).Bind(2, visit_id).Bind(3, limit).Bind(4, std::max<int64_t>(offset, 0));
  std::vector<KeyframeRecord> out;
  for (;;) {
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    out.push_back(ReadKeyframe(*s));
    constexpr int c = kKeyframeColumnCount;
    if (!s->ColumnIsNull(c)) {
      out.back().feature_counts = ReadFeatureCounts(*s, c);
    }
  }
  return out;
}

absl::Status Store::ForEachKeyframeWithImages(
    int64_t map_id, int64_t visit_id,
    const std::function<absl::Status(const KeyframeRecord&)>& fn) {
  // Ids first, then one keyframe at a time: the read lock is not held while `fn` runs.
  auto list = ListKeyframes(map_id, visit_id);
  if (!list.ok()) return list.status();
  for (const auto& summary : *list) {
    auto k = GetKeyframe(map_id, summary.id);
    if (absl::IsNotFound(k.status())) continue;  // deleted meanwhile
    if (!k.ok()) return k.status();
    if (auto s = fn(*k); !s.ok()) return s;
  }
  return absl::OkStatus();
}

absl::StatusOr<KeyframeRecord> Store::GetKeyframe(int64_t map_id, int64_t keyframe_id) {
  absl::MutexLock lock(&impl_->read_mu);
  auto stmt = impl_->read_db->Prepare(absl::StrCat(
      "SELECT ", kKeyframeColumns,
      ", i.depth, i.color FROM keyframes k JOIN visits v ON v.id = k.visit_id "
      "JOIN keyframe_images i ON i.keyframe_id = k.id WHERE v.map_id = ?1 AND k.id = ?2"));
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, map_id).Bind(2, keyframe_id);
  auto row = s->Step();
  if (!row.ok()) return row.status();
  if (!*row) {
    return absl::NotFoundError(absl::StrCat("keyframe ", keyframe_id, " is not in this map"));
  }
  KeyframeRecord k = ReadKeyframe(*s);
  k.depth = s->ColumnBlob(kKeyframeColumnCount);
  k.color = s->ColumnBlob(kKeyframeColumnCount + 1);
  auto features = impl_->read_db->Prepare(
      "SELECT superjut_count, entropy_threshold, keypoint_type, keypoints_stored, "
      "keypoints_masked, superjuts FROM keyframe_features WHERE keyframe_id = ?1");
  if (!features.ok()) return features.status();
  StatementScope f(*features);
  f->Bind(1, keyframe_id);
  auto frow = f->Step();
  if (!frow.ok()) return frow.status();
  if (*frow) {
    k.feature_counts = ReadFeatureCounts(*f, 0);
    auto superjuts = DecodeSuperjuts(f->ColumnBlob(5));
    if (!superjuts.ok()) return superjuts.status();
    k.features = KeyframeFeatures{f->ColumnDouble(1), *std::move(superjuts), {}};
  }
  return k;
}

absl::StatusOr<KeyframeFeatures> Store::GetKeyframeFeatures(int64_t keyframe_id) {
  absl::MutexLock lock(&impl_->read_mu);
  auto stmt = impl_->read_db->Prepare(
      "SELECT entropy_threshold, superjuts, keypoint_type, keypoints_masked, keypoints, "
      "descriptor_bytes, descriptors, points, record_format FROM keyframe_features "
      "WHERE keyframe_id = ?1");
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, keyframe_id);
  auto row = s->Step();
  if (!row.ok()) return row.status();
  if (!*row) {
    return absl::NotFoundError(absl::StrCat("keyframe ", keyframe_id, " has no stored features"));
  }
  KeyframeFeatures f;
  f.entropy_threshold = s->ColumnDouble(0);
  auto superjuts = DecodeSuperjuts(s->ColumnBlob(1));
  if (!superjuts.ok()) return superjuts.status();
  f.superjuts = *std::move(superjuts);
  f.keypoints.type = s->ColumnText(2);
  f.keypoints.masked = static_cast<int>(s->ColumnInt(3));
  const std::string keypoints = s->ColumnBlob(4);
  const int64_t row_bytes = s->ColumnInt(5);
  const std::string descriptors = s->ColumnBlob(6);
  const bool compact = s->ColumnInt(8) == kRecordFormat;
  const size_t keypoint_record = compact ? kCompactKeypointRecord : kKeypointRecord;
  const size_t point_record = compact ? kCompactPointRecord : kPointRecord;
  const size_t n = keypoints.size() / keypoint_record;
  if (keypoints.size() % keypoint_record != 0 ||
      descriptors.size() != n * static_cast<size_t>(row_bytes)) {
    return absl::DataLossError(
        absl::StrCat("stored keypoints of keyframe ", keyframe_id, " are truncated"));
  }
  f.keypoints.keypoints.resize(n);
  for (size_t i = 0; i < n; ++i) {
    const char* at = keypoints.data() + i * keypoint_record;
    if (compact) {
      uint16_t fixed[4];
      float response = 0;
      std::memcpy(fixed, at, 8);
      std::memcpy(&response, at + 8, 4);
      f.keypoints.keypoints[i] = {fixed[0] / 8.0f, fixed[1] / 8.0f, fixed[2] / 8.0f,
                                  fixed[3] / 100.0f, response};
    } else {
      float v[5];
      std::memcpy(v, at, kKeypointRecord);
      f.keypoints.keypoints[i] = {v[0], v[1], v[2], v[3], v[4]};
    }
  }
  f.keypoints.detected = static_cast<int>(n) + f.keypoints.masked;
  if (n > 0) {
    f.keypoints.descriptors = cv::Mat(static_cast<int>(n), static_cast<int>(row_bytes), CV_8UC1);
    std::memcpy(f.keypoints.descriptors.data, descriptors.data(), descriptors.size());
  }
  if (!s->ColumnIsNull(7)) {
    const std::string points = s->ColumnBlob(7);
    if (points.size() != n * point_record) {
      return absl::DataLossError(
          absl::StrCat("stored 3D points of keyframe ", keyframe_id, " are truncated"));
    }
    f.keypoints.points.resize(n);
    for (size_t i = 0; i < n; ++i) {
      if (!compact) {
        std::memcpy(f.keypoints.points[i].data(), points.data() + i * kPointRecord, kPointRecord);
        continue;
      }
      int16_t mm[3];
      std::memcpy(mm, points.data() + i * kCompactPointRecord, kCompactPointRecord);
      f.keypoints.points[i] =
          mm[0] == kNoPoint
              ? Eigen::Vector3f(Eigen::Vector3f::Constant(std::numeric_limits<float>::quiet_NaN()))
              : Eigen::Vector3f(Eigen::Vector3f(mm[0], mm[1], mm[2]) / 1000.0f);
    }
  }
  return f;
}

absl::StatusOr<std::optional<KeyframeRecord>> Store::LastKeyframe(int64_t visit_id) {
  absl::MutexLock lock(&impl_->read_mu);
  auto stmt = impl_->read_db->Prepare(absl::StrCat(
      "SELECT ", kKeyframeColumns,
      " FROM keyframes k WHERE k.visit_id = ?1 ORDER BY k.timestamp_s DESC, k.id DESC LIMIT 1"));
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, visit_id);
  auto row = s->Step();
  if (!row.ok()) return row.status();
  if (!*row) return std::optional<KeyframeRecord>();
  return std::optional<KeyframeRecord>(ReadKeyframe(*s));
}

absl::StatusOr<int64_t> Store::DeleteKeyframes(int64_t visit_id, const std::vector<int64_t>& ids) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  Transaction tx(db);
  if (auto s = tx.Begin(); !s.ok()) return s;
  auto ended = db->Prepare("SELECT ended FROM visits WHERE id = ?1");
  if (!ended.ok()) return ended.status();
  {
    StatementScope s(*ended);
    s->Bind(1, visit_id);
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (!*row) return absl::NotFoundError(absl::StrCat("visit ", visit_id, " does not exist"));
    if (s->ColumnInt(0) == 0) {
      return absl::FailedPreconditionError(absl::StrCat(
          "visit ", visit_id, " is still open: only ended visits' keyframes are thinned"));
    }
  }
  auto bytes = db->Prepare(
      "SELECT k.visit_id, COALESCE(length(i.depth), 0) + COALESCE(length(i.color), 0) + "
      "COALESCE(length(f.superjuts), 0) + COALESCE(length(f.keypoints), 0) + "
      "COALESCE(length(f.descriptors), 0) + COALESCE(length(f.points), 0) FROM keyframes k "
      "LEFT JOIN keyframe_images i ON i.keyframe_id = k.id "
      "LEFT JOIN keyframe_features f ON f.keyframe_id = k.id WHERE k.id = ?1");
  auto erase = db->Prepare("DELETE FROM keyframes WHERE id = ?1");
  if (!bytes.ok()) return bytes.status();
  if (!erase.ok()) return erase.status();
  int64_t freed = 0;
  for (const int64_t id : ids) {
    {
      StatementScope s(*bytes);
      s->Bind(1, id);
      auto row = s->Step();
      if (!row.ok()) return row.status();
      if (!*row || s->ColumnInt(0) != visit_id) {
        return absl::NotFoundError(
            absl::StrCat("keyframe ", id, " is not a keyframe of visit ", visit_id));
      }
      freed += s->ColumnInt(1);
    }
    StatementScope s(*erase);
    s->Bind(1, id);
    if (auto st = s->Run(); !st.ok()) return st;
  }
  if (auto s = tx.Commit(); !s.ok()) return s;
  return freed;
}

absl::StatusOr<std::map<int64_t, std::vector<int64_t>>> Store::ListSightings(int64_t map_id) {
  absl::MutexLock lock(&impl_->read_mu);
  auto stmt = impl_->read_db->Prepare(
      "SELECT s.keyframe_id, s.visit_id FROM keyframe_sightings s JOIN keyframes k ON k.id = "
      "s.keyframe_id JOIN visits v ON v.id = k.visit_id WHERE (?1 = 0 OR v.map_id = ?1) ORDER "
      "BY s.keyframe_id, s.visit_id");
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, map_id);
  std::map<int64_t, std::vector<int64_t>> out;
  while (true) {
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    out[s->ColumnInt(0)].push_back(s->ColumnInt(1));
  }
  return out;
}

absl::StatusOr<MapStorage> Store::GetMapStorage(int64_t map_id) {
  absl::MutexLock lock(&impl_->read_mu);
  Database* db = impl_->read_db.get();
  const std::string visits = absl::StrCat("(SELECT id FROM visits WHERE map_id = ", map_id, ")");
  const std::string keyframes =
      absl::StrCat("(SELECT id FROM keyframes WHERE visit_id IN ", visits, ")");
  MapStorage m;
  const std::pair<int64_t*, std::string> queries[] = {
      {&m.keyframes, absl::StrCat("SELECT COUNT(*) FROM keyframes WHERE visit_id IN ", visits)},
      {&m.image_bytes, absl::StrCat("SELECT COALESCE(SUM(length(depth) + length(color)), 0) FROM "
                                    "keyframe_images WHERE keyframe_id IN ",
                                    keyframes)},
      {&m.feature_bytes, absl::StrCat("SELECT COALESCE(SUM(length(superjuts) + length(keypoints) + "
                                      "length(descriptors) + COALESCE(length(points), 0)), 0) FROM "
                                      "keyframe_features WHERE keyframe_id IN ",
                                      keyframes)},
      {&m.octree_bytes,
       absl::StrCat("SELECT COALESCE((SELECT SUM(length(data)) FROM semantic_octree_chunks "
                    "WHERE visit_id IN ",
                    visits,
                    "), 0) + COALESCE((SELECT SUM(length(data)) FROM "
                    "semantic_map_octree_chunks WHERE map_id = ",
                    map_id, "), 0)")},
      {&m.plan_bytes,
       absl::StrCat("SELECT COALESCE(SUM(length(floor_plan) + length(descriptor)), 0) FROM "
                    "visit_places WHERE visit_id IN ",
                    visits)},
  };
  for (const auto& [out, sql] : queries) {
    auto v = db->QueryInt(sql);
    if (!v.ok()) return v.status();
    *out = *v;
  }
  return m;
}

absl::StatusOr<StoreStats> Store::Stats() {
  StoreStats st;
  {
    absl::MutexLock lock(&impl_->read_mu);
    Database* db = impl_->read_db.get();
    auto maps = db->QueryInt("SELECT COUNT(*) FROM maps");
    auto visits = db->QueryInt("SELECT COUNT(*) FROM visits");
    auto keyframes = db->QueryInt("SELECT COUNT(*) FROM keyframes");
    if (!maps.ok()) return maps.status();
    if (!visits.ok()) return visits.status();
    if (!keyframes.ok()) return keyframes.status();
    st.maps = *maps;
    st.visits = *visits;
    st.keyframes = *keyframes;
  }
  std::error_code ec;
  st.db_bytes = static_cast<int64_t>(fs::file_size(path_, ec));
  if (ec) st.db_bytes = 0;
  st.wal_bytes = static_cast<int64_t>(fs::file_size(path_ + "-wal", ec));
  if (ec) st.wal_bytes = 0;
  return st;
}

absl::Status Store::Backup(const std::string& path) {
  if (path.empty() || path[0] != '/') {
    return absl::InvalidArgumentError("backup path must be an absolute path on the server");
  }
  if (fs::exists(path)) {
    return absl::AlreadyExistsError(absl::StrCat(path, " exists; choose a new file name"));
  }
  if (!fs::is_directory(fs::path(path).parent_path())) {
    return absl::NotFoundError(
        absl::StrCat("directory ", fs::path(path).parent_path().string(), " does not exist"));
  }
  // Written under another name and linked into place when whole and closed (its WAL folded
  // in): a kill meanwhile leaves only the partial file, never a torn backup under `path`. The
  // partial name is hidden and unique (".NAME.partial-XXXXXX", made by mkstemp): no backup name
  // may start with '.', so no backup's partial file is ever another backup, and two backups at
  // once never share one. Nothing existing is removed first.
  const fs::path target(path);
  std::string partial =
      (target.parent_path() / ("." + target.filename().string() + ".partial-XXXXXX")).string();
  const int partial_fd = mkstemp(partial.data());
  if (partial_fd < 0) {
    const int err = errno;
    return absl::FailedPreconditionError(absl::StrCat("backup: cannot create a file in ",
                                                      target.parent_path().string(), ": ",
                                                      std::strerror(err)));
  }
  close(partial_fd);  // an empty file: SQLite takes it for a new database
  std::error_code ec;
  {
    auto dest = Database::Open(partial, true, false, 5000);
    if (!dest.ok()) {
      fs::remove(partial, ec);
      return dest.status();
    }
    absl::MutexLock lock(&impl_->read_mu);
    sqlite3_backup* backup =
        sqlite3_backup_init((*dest)->raw(), "main", impl_->read_db->raw(), "main");
    if (backup == nullptr) {
      return SqliteError((*dest)->raw(), sqlite3_errcode((*dest)->raw()), "backup");
    }
    const int rc = sqlite3_backup_step(backup, -1);
    sqlite3_backup_finish(backup);
    if (rc != SQLITE_DONE) {
      dest->reset();
      fs::remove(partial, ec);
      return SqliteError(nullptr, rc, "backup");
    }
    // Everything in the main file (journal_mode=DELETE), synced, before it gets its name.
    if (auto s = (*dest)->Exec("PRAGMA journal_mode=DELETE"); !s.ok()) {
      dest->reset();
      fs::remove(partial, ec);
      return s;
    }
  }
  // link() fails rather than replace a file that appeared under `path` meanwhile.
  if (link(partial.c_str(), path.c_str()) != 0) {
    const int err = errno;
    fs::remove(partial, ec);
    if (err == EEXIST) {
      return absl::AlreadyExistsError(absl::StrCat(path, " exists; choose a new file name"));
    }
    return absl::InternalError(
        absl::StrCat("backup: cannot name it ", path, ": ", std::strerror(err)));
  }
  fs::remove(partial, ec);
  return absl::OkStatus();
}

absl::Status Store::CheckFilesInPlace() {
  // The guarded connection's file ids are fixed once Open returned: no lock needed.
  return impl_->write_db->CheckFilesInPlace();
}

namespace {

// Runs `sql` (with `bind` as ?1 when given) and hands each row's statement to `on_row`.
absl::Status ForEachRow(Database* db, const char* sql, std::optional<int64_t> bind,
                        const std::function<void(Statement&)>& on_row) {
  auto stmt = db->Prepare(sql);
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  if (bind) s->Bind(1, *bind);
  for (;;) {
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (!*row) return absl::OkStatus();
    on_row(**stmt);
  }
}

}  // namespace

absl::StatusOr<std::vector<std::string>> Store::CheckIntegrity() {
  std::vector<std::string> problems;
  if (auto s = CheckFilesInPlace(); !s.ok()) problems.emplace_back(s.message());
  absl::MutexLock lock(&impl_->read_mu);
  Database* db = impl_->read_db.get();
  if (auto s = ForEachRow(db, "PRAGMA integrity_check", std::nullopt,
                          [&](Statement& row) {
                            if (row.ColumnText(0) != "ok") problems.push_back(row.ColumnText(0));
                          });
      !s.ok()) {
    return s;
  }
  if (auto s = ForEachRow(db, "PRAGMA foreign_key_check", std::nullopt,
                          [&](Statement& row) {
                            problems.push_back(
                                absl::StrCat("foreign key violation in ", row.ColumnText(0),
                                             " row ", row.ColumnInt(1), " -> ", row.ColumnText(2)));
                          });
      !s.ok()) {
    return s;
  }
  // Rows whose references resolve, but into another map (issue 52: an archive's keyframes
  // landed in another map's visit). Each query gives a row id, what it names and the two maps.
  static constexpr const char* kCrossMap[][2] = {
      {"pose edge",
       "SELECT e.id, k.id, e.map_id, v.map_id FROM pose_edges e JOIN keyframes k ON k.id IN "
       "(e.from_keyframe, e.to_keyframe) JOIN visits v ON v.id = k.visit_id WHERE v.map_id != "
       "e.map_id LIMIT 20"},
      {"visit",
       "SELECT v.id, a.id, v.map_id, a.map_id FROM visits v JOIN visits a ON a.id = "
       "v.anchor_visit_id WHERE a.map_id != v.map_id LIMIT 20"},
      {"pose solve",
       "SELECT o.id, v.id, o.map_id, v.map_id FROM pose_optimisations o JOIN visits v ON v.id = "
       "o.visit_id WHERE v.map_id != o.map_id LIMIT 20"},
      {"keyframe",
       "SELECT k.id, o.id, v.map_id, o.map_id FROM keyframes k JOIN visits v ON v.id = "
       "k.visit_id JOIN pose_optimisations o ON o.id = k.optimisation_id WHERE o.map_id != "
       "v.map_id LIMIT 20"},
  };
  for (const auto& [what, sql] : kCrossMap) {
    if (auto s = ForEachRow(db, sql, std::nullopt,
                            [&, what = what](Statement& row) {
                              problems.push_back(absl::StrCat(
                                  what, " ", row.ColumnInt(0), " of map id ", row.ColumnInt(2),
                                  " names ", row.ColumnInt(1), " of map id ", row.ColumnInt(3)));
                            });
        !s.ok()) {
      return s;
    }
  }
  // AUTOINCREMENT counters near their end: past 2^63 - 1 every new row of the table fails.
  if (auto s = ForEachRow(
          db, "SELECT name, seq FROM sqlite_sequence WHERE seq > ?1", int64_t{1} << 62,
          [&](Statement& row) {
            problems.push_back(absl::StrCat(
                "table ", row.ColumnText(0), "'s id counter is at ", row.ColumnInt(1),
                ", near its maximum 2^63 - 1: new rows will fail (docs/OPERATIONS.md \"Id "
                "counters\")"));
          });
      !s.ok()) {
    return s;
  }
  return problems;
}

absl::Status Store::Vacuum() {
  absl::MutexLock lock(&impl_->write_mu);
  return impl_->write_db->Exec("VACUUM");
}

absl::Status Store::Checkpoint() {
  absl::MutexLock lock(&impl_->write_mu);
  return impl_->write_db->Exec("PRAGMA wal_checkpoint(TRUNCATE)");
}

}  // namespace lifemap::store
