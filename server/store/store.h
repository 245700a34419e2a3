// lifemap's durable store: one SQLite file in WAL mode holding maps ⊃ visits ⊃ keyframes.
//
// Durability contract: every method that changes data returns only after its transaction has
// committed (synchronous=FULL by default: the commit survives a process crash and a power
// loss). Callers acknowledge a write to a client only after the method returned OK.
//
// Thread-safe. Writes go through one connection, reads through another, so reads (listing,
// export) do not wait for a writer's fsync (WAL lets them see the last committed state).
#pragma once

#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "core/common/image_codec.h"
#include "core/common/rgbd_frame.h"
#include "core/common/types.h"
#include "core/entropy/superjut_scores.h"
#include "core/features/keypoints.h"
#include "core/pipeline/keyframe.h"

namespace lifemap::store {

class Database;

struct StoreOptions {
  bool synchronous_full = true;  // false: synchronous=NORMAL (safe on a process crash only)
  int busy_timeout_ms = 5000;
  bool create_if_missing = true;
  // PRAGMA quick_check before use: a damaged file is refused (DATA_LOSS naming the first
  // problem) instead of failing later on the page that is damaged. Reads every page once.
  bool quick_check = false;
};

struct MapRecord {
  int64_t id = 0;
  std::string name;
  std::string description;
  double created_time_s = 0.0;
  int64_t visit_count = 0;
  int64_t keyframe_count = 0;
  int64_t stored_bytes = 0;                 // keyframe image bytes
  std::optional<double> entropy_threshold;  // nullopt = the server's default
  // Keyframe colour kept as the client sent it (PNG or JPEG; raw as PNG) instead of re-encoded
  // as JPEG at the server's storage.color_jpeg_quality.
  bool keep_original_color = false;
};

// Fields of a map to change; unset ones keep their values.
struct MapUpdate {
  std::optional<std::string> description;
  bool set_entropy_threshold = false;
  std::optional<double> entropy_threshold;  // with set_entropy_threshold: nullopt = default
  std::optional<bool> keep_original_color;
};

struct VisitAnchor {
  int64_t to_visit_id = 0;
  int64_t edge_id = 0;
  Pose T_map_visit;
  double residual_m = 0;
  double residual_deg = 0;
  double anchored_time_s = 0;  // of the current anchor (the last revision's, if revised)
  int revisions = 0;           // times the anchor was revised since the visit was anchored
  std::string evidence;        // the current anchor edge's reason: the matches and checks
};

// One entry of a visit's anchor history (issue 35).
struct AnchorRevision {
  int64_t id = 0;
  int64_t visit_id = 0;
  double time_s = 0;
  std::string action;  // "anchored" | "revised" | "dropped"
  int64_t to_visit_id = 0;
  int64_t edge_id = 0;  // the anchor edge it rests on (0: none recorded)
  Pose T_map_visit;     // after this entry ("dropped": the anchor that was dropped)
  std::string reason;
};

struct VisitRecord {
  int64_t id = 0;
  int64_t map_id = 0;
  std::string map_name;
  std::string robot;
  std::string label;
  double start_time_s = 0.0;  // the server's clock (or StartVisit's start_time_s): receipt
  double end_time_s = 0.0;
  // The data's own time: the capture times (Frame.timestamp_s, as the robot stamped its
  // frames) of the visit's earliest and latest stored keyframes; 0 while it has none. Visits
  // recorded months apart and streamed minutes apart differ here, not in start_time_s.
  double data_start_time_s = 0.0;
  double data_end_time_s = 0.0;
  bool ended = false;
  int64_t keyframe_count = 0;
  int64_t frame_count = 0;
  int64_t lost_frame_count = 0;  // of frame_count, lost by the server's tracker (issue 35)
  // Loop closure within the visit (issue 15): loop edges accepted into its pose graph (and
  // not outvoted since), rejected ones, and pose-graph solves.
  int64_t loops_accepted = 0;
  int64_t loops_rejected = 0;
  int64_t pose_graph_solves = 0;
  // Anchoring (issue 15): set once a tracked visit's keyframes matched, by appearance, keyframes
  // of a visit already in the map's frame: that visit, the anchor edge (pose_edges, kind
  // anchor), where this visit's frame lies in the map's (T_map_visit), and how far the two
  // agreeing matches that anchored it were apart.
  std::optional<VisitAnchor> anchor;
  int64_t tracked_keyframes = 0;  // keyframes posed by the server's tracker
  bool first_of_map = false;      // the map's first visit: its frame is the map's
  // Why the visit's latest anchor was dropped (issue 35), while it is unanchored; else empty.
  std::string anchor_dropped;
};

enum class StoredColorEncoding : int { kJpeg = 1, kPng = 2 };
// Keyframes stored before schema 7 are PNG-16; later ones paletted (core/common/depth_codec.h).
enum class StoredDepthEncoding : int { kPng16 = 1, kPaletted = 2 };

// What the keyframe step made of a keyframe (core/pipeline/keyframe.h), stored with it.
using KeyframeFeatures = pipeline::KeyframeFeatures;

// Counts of KeyframeFeatures, for listings (no blobs read).
struct KeyframeFeatureCounts {
  int superjuts = 0;
  double entropy_threshold = 0;
  std::string keypoint_type;
  int keypoints_stored = 0;
  int keypoints_masked = 0;
};

// Where a stored keyframe's pose came from (keyframes.pose_source).
enum class StoredPoseSource { kNone = 0, kClient = 1, kEstimated = 2, kRefined = 3 };

struct KeyframeRecord {
  int64_t id = 0;  // assigned by InsertKeyframes
  int64_t visit_id = 0;
  uint64_t sequence = 0;
  double timestamp_s = 0.0;
  // Set by InsertKeyframes: the visit held this (sequence, timestamp) already, `id` is that
  // keyframe's and nothing was written.
  bool resent = false;
  std::optional<Pose> T_world_camera;
  StoredPoseSource pose_source = StoredPoseSource::kClient;  // kNone without a pose
  // A tracked keyframe's pose in its visit's odometry frame, as the tracker gave it (never
  // rewritten: consecutive keyframes' odometry poses are the pose graph's odometry edges);
  // unset for client poses.
  std::optional<Pose> T_odom_camera;
  int64_t odom_segment = 0;     // which run of the tracker (one visit may have several)
  int64_t optimisation_id = 0;  // the pose-graph solve that wrote T_world_camera (0: none)
  CameraIntrinsics intrinsics;
  double depth_scale = 0.0;  // units per metre of `depth`'s uint16 values
  StoredDepthEncoding depth_encoding = StoredDepthEncoding::kPaletted;
  std::string depth;  // PNG-16 or RVL bytes (empty when listed without images)
  StoredColorEncoding color_encoding = StoredColorEncoding::kJpeg;
  std::string color;  // JPEG or PNG bytes (empty when listed without images)
  int64_t depth_bytes = 0;
  int64_t color_bytes = 0;
  // Written with the keyframe when entropy masks were computed. GetKeyframe returns the
  // superjuts (keypoints: GetKeyframeFeatures); listings return only the counts.
  std::optional<KeyframeFeatures> features;
  std::optional<KeyframeFeatureCounts> feature_counts;
  // Written with it (schema 17): keyframes of other visits this keyframe's appearance query
  // verified, each then recognised by this keyframe's visit (ListSightings). Not read back.
  std::vector<int64_t> sighted_keyframes;
};

// A stored keyframe's images as the codecs take them (views into `k`, which must outlive them).
EncodedDepth StoredDepth(const KeyframeRecord& k);
EncodedColor StoredColor(const KeyframeRecord& k);
// The keyframe as a frame to decode: its images, intrinsics, time and pose.
EncodedRgbdFrame StoredFrame(const KeyframeRecord& k);

// A visit's frame counter, written in the same transaction as its keyframes.
// A visit's frames processed so far, and how many of them the server's tracker lost (no pose).
struct VisitFrameCount {
  int64_t visit_id = 0;
  int64_t frame_count = 0;
  int64_t lost_frame_count = 0;
};

// What one map holds, in bytes of the values stored (its keyframes' images and features, its
// visits' octrees and floor plans, its own octree): about what the map would take in a file of
// its own. SQLite's pages add their overhead, and deleted rows' pages stay in the file as free
// pages until a vacuum.
struct MapStorage {
  int64_t keyframes = 0;
  int64_t image_bytes = 0;    // depth and colour
  int64_t feature_bytes = 0;  // superjuts, keypoints, descriptors, points
  int64_t octree_bytes = 0;   // visits' and the map's semantic octrees
  int64_t plan_bytes = 0;     // visits' floor plans and architecture descriptors
  int64_t total() const { return image_bytes + feature_bytes + octree_bytes + plan_bytes; }
};

struct StoreStats {
  int64_t maps = 0;
  int64_t visits = 0;
  int64_t keyframes = 0;
  int64_t db_bytes = 0;
  int64_t wal_bytes = 0;
};

// A stored random-forest model (the file itself is read with GetModelData).
struct ModelRecord {
  int64_t id = 0;
  std::string name;
  double uploaded_time_s = 0.0;
  int64_t size_bytes = 0;
  std::vector<std::string> class_names;
  std::vector<uint32_t> class_colors;  // 0xRRGGBB
  std::string training_json;
  int trees = 0;
  int64_t nodes = 0;
  bool is_default = false;               // the server default
  std::vector<std::string> active_maps;  // maps whose own model this is
};

// Which API key creates a map, and how many maps it may have created (0: no limit).
// What DeleteVisit removed.
struct VisitDeletion {
  int64_t map_id = 0;
  std::string map_name;
  std::vector<int64_t> keyframe_ids;
};

// What a map archive holds.
struct ArchiveCounts {
  int64_t visits = 0;
  int64_t keyframes = 0;
  int64_t schema_version = 0;
};

struct MapCreator {
  int64_t key_id = 0;  // 0: none (auth off, or the store used directly)
  std::string key_name;
  int64_t max_maps = 0;
};

// An API key's own limits (0: only the server's): concurrent streams, frames a second (streams
// and ProcessFrame together), maps it may have created at once, keyframes a map it writes may
// hold, model size (server/rpc/auth.h enforces them).
struct KeyLimits {
  int64_t max_streams = 0;
  double max_frames_per_s = 0;
  int64_t max_maps = 0;
  int64_t max_keyframes_per_map = 0;
  int64_t max_model_bytes = 0;
  int64_t max_visits_per_hour = 0;  // visits it may start in any hour (schema 14)
};

// An API key as stored: never the secret, only its SHA-256 (hex).
struct ApiKeyRecord {
  int64_t id = 0;
  std::string name;
  std::string role;  // "robot" | "operator" | "admin" (server/rpc/auth.h)
  bool every_map = true;
  std::vector<int64_t> map_ids;        // when !every_map: the maps it may use
  std::vector<std::string> map_names;  // their current names (List), same order
  std::string secret_sha256;
  double created_time_s = 0;
  double last_used_time_s = 0;  // 0 = never
  double revoked_time_s = 0;    // 0 = live
  KeyLimits limits;
};

// One administrative call in the audit log.
struct AuditEventRecord {
  double time_s = 0;
  std::string key_name;
  std::string method;
  std::string request;
  std::string code;
  std::string message;
  std::string peer;
};

// A stored keyframe's descriptors as the appearance index needs them (no images, no points).
struct KeyframeDescriptors {
  int64_t map_id = 0;
  int64_t visit_id = 0;
  int64_t keyframe_id = 0;
  double timestamp_s = 0;
  cv::Mat descriptors;  // CV_8UC1, one row per kept keypoint
};

// A vocabulary of visual words for the appearance index (core/appearance/vocabulary.h), as
// stored: the newest one is in use.
struct VocabularyRecord {
  int64_t id = 0;
  double created_time_s = 0;
  std::string source;  // what it was trained on, for listings
  int64_t training_keyframes = 0;
  int64_t words = 0;
  std::string data;  // Vocabulary::Serialize()
};

// A loop closure (two keyframes of one visit) or a visit anchor (a keyframe of another visit)
// from a verified appearance match (issue 15), accepted into the pose graph or rejected with
// the reason.
enum class StoredEdgeKind { kLoop = 2, kAnchor = 3 };
struct PoseEdgeRecord {
  int64_t id = 0;  // assigned by InsertPoseEdge
  int64_t map_id = 0;
  StoredEdgeKind kind = StoredEdgeKind::kLoop;
  int64_t from_keyframe = 0;  // the matched, earlier keyframe
  int64_t to_keyframe = 0;    // the querying keyframe
  Pose T_from_to;             // the querying camera in the matched camera's frame
  int inliers = 0;
  double reprojection_px = 0;
  bool accepted = false;
  std::string reason;  // why rejected (or what accepted it), for people reading listings
  double created_time_s = 0;
};

// One pose-graph solve over a visit's keyframes: what it was given and what it did.
struct PoseOptimisationRecord {
  int64_t id = 0;  // assigned by ApplyPoseOptimisation
  int64_t map_id = 0;
  int64_t visit_id = 0;
  double created_time_s = 0;
  int keyframes = 0;
  int odometry_edges = 0;
  int loop_edges = 0;      // accepted loop and anchor edges given to the solve
  int loops_rejected = 0;  // of those, switched off by the solve
  int iterations = 0;
  double initial_cost = 0;
  double final_cost = 0;
  double solve_ms = 0;
  double max_correction_m = 0;
};

// A visit's architecture (paper 004) as last derived from its key frames.
struct VisitPlaceRecord {
  int64_t visit_id = 0;
  int64_t map_id = 0;  // filled when read
  std::string map_name;
  int keyframes = 0;
  std::string floor_plan_json;
  std::string descriptor_json;
  double updated_time_s = 0;
};

// A visit's semantic octree (core/semantic's snapshot bytes) and what made it.
struct SemanticSnapshotRecord {
  int64_t visit_id = 0;
  std::string model;  // the model whose classes it holds
  int class_count = 0;
  double resolution_m = 0.0;
  int64_t keyframes = 0;  // keyframes fused
  std::string bytes;      // SemanticMap::Serialize
  double updated_time_s = 0.0;
};

// A map's semantic octree: its visits' merged in the map's frame (server/engine/semantic_export.h).
struct MapSemanticSnapshotRecord {
  int64_t map_id = 0;
  SemanticSnapshotRecord octree;  // octree.visit_id is 0
  // What it was merged from, as its writer describes it (kept as is): a reader compares it
  // with what it would merge now to tell whether the stored one is current.
  std::string sources;
  std::string merged;  // its writer's account of the visits merged and left out
};

// An axis-aligned box of a map's frame, metres.
struct AnnotationBox {
  double min[3] = {0, 0, 0};
  double max[3] = {0, 0, 0};
};

// A class given to a region of a map's frame (issue 38, paper 002's annotation tool): one or
// more boxes (a selected voxel is a box of its size). Projected into every keyframe that sees
// it for a training folder (server/engine/annotation_export.h).
struct AnnotationRecord {
  int64_t id = 0;  // assigned by InsertAnnotation
  int64_t map_id = 0;
  std::string class_name;
  std::vector<AnnotationBox> boxes;
  std::string author;  // the API key's name ("" without keys)
  double created_time_s = 0.0;
};

class Store {
 public:
  // Opens or creates the database and migrates its schema forward. FailedPrecondition when the
  // file's schema is newer than this build knows, or the file is not a lifemap database.
  static absl::StatusOr<std::unique_ptr<Store>> Open(const std::string& path,
                                                     const StoreOptions& options = {});
  ~Store();
  Store(const Store&) = delete;
  Store& operator=(const Store&) = delete;

  static constexpr int kSchemaVersion = 18;
  int schema_version() const { return kSchemaVersion; }
  const std::string& path() const { return path_; }

  // Maps. Names are validated by the caller (ValidateMapName). ALREADY_EXISTS / NOT_FOUND.
  // `creator`: the API key creating it; with max_maps > 0, RESOURCE_EXHAUSTED when the maps it
  // created that still exist number that many.
  absl::StatusOr<MapRecord> CreateMap(const std::string& name, const std::string& description,
                                      double created_time_s,
                                      std::optional<double> entropy_threshold = std::nullopt,
                                      bool keep_original_color = false,
                                      const MapCreator& creator = {});
  absl::StatusOr<MapRecord> UpdateMap(const std::string& name, const MapUpdate& update);
  absl::StatusOr<std::vector<MapRecord>> ListMaps();
  // Every map's id and name, by name: ListMaps without its counts (which read every keyframe
  // row), for callers that run often (a shard's key sync, every 2 s).
  absl::StatusOr<std::vector<std::pair<int64_t, std::string>>> ListMapNames();
  absl::StatusOr<MapRecord> GetMap(const std::string& name);
  absl::StatusOr<MapRecord> GetMapById(int64_t map_id);
  // Deletes the map with its visits and keyframes; returns the counts deleted.
  absl::StatusOr<std::pair<int64_t, int64_t>> DeleteMap(const std::string& name);

  // Deletes ended visit `visit_id` with everything that hangs on it (keyframes with images,
  // features and sightings, floor plan, octree, anchor history, pose edges, solves, the
  // sightings it made of other visits' keyframes) in one transaction; returns its map and the
  // keyframes deleted. NOT_FOUND; FAILED_PRECONDITION, saying why, for an open visit, a visit
  // other visits are anchored to, or a map's first visit while tracked visits of the map stand
  // in its frame (the next visit would become the map's frame under them).
  absl::StatusOr<VisitDeletion> DeleteVisit(int64_t visit_id);

  // Map archives (issue 37; server/engine/map_archive.h frames them with a manifest and a
  // checksum). WriteMapArchive copies map `name` whole, from one consistent snapshot, into a
  // new SQLite file at `path` with this store's schema: the map and its model, visits (anchors,
  // anchor history), keyframes (images, features, sightings), pose edges and solves, floor
  // plans and semantic octrees. NOT_FOUND for an unknown map.
  absl::StatusOr<ArchiveCounts> WriteMapArchive(const std::string& name, const std::string& path);
  // Adds the map in the archive file at `path` as a new map `name`, in one transaction (nothing
  // of it is stored unless all of it is). Every id is new and every reference follows; visits
  // still open when exported arrive ended; the map's merged semantic octree (a cache) is made
  // again when first exported. An archive of an older schema is migrated first (the file is
  // changed). ALREADY_EXISTS for a name in use; FAILED_PRECONDITION for a newer schema or a
  // model of the same name with other contents; INVALID_ARGUMENT for a file that is not a
  // consistent archive of one map.
  // `keep_ids` (a map moved between the shards of a cluster, issue 39): visits, keyframes and
  // the other renumbered rows keep their ids, so that clients' references stay true, and open
  // visits stay open, so that their streams resume on this store; FAILED_PRECONDITION naming
  // the table when an id is in use here.
  // Every id is given out anew, densely, whatever the archive's numbers; kept ids must lie in
  // 1..2^56. Every reference of a keyframe, image, edge, octree... must resolve inside the
  // archive, or INVALID_ARGUMENT names the row. `cancelled` (may be empty) is asked between
  // steps and while a copy runs: when it says true, the import rolls back and answers CANCELLED.
  absl::StatusOr<MapRecord> ReadMapArchive(const std::string& path, const std::string& name,
                                           const MapCreator& creator, bool keep_ids = false,
                                           const std::function<bool()>& cancelled = {});
  // New ids of visits, keyframes and the other rows an archive renumbers lie in
  // [floor + 1, floor + 2^kIdRangeBits) from now on, whatever ids maps moved here from other
  // shards keep (a shard's own range, so that maps moved between shards keep their ids). Kept
  // in the database; lowers nothing (the highest floor given stands).
  static constexpr int kIdRangeBits = 40;  // ~10^12 ids per shard
  absl::Status RaiseIdFloor(int64_t floor);
  absl::StatusOr<MapRecord> RenameMap(const std::string& name, const std::string& new_name);

  // Visits. NOT_FOUND for an unknown map or visit.
  absl::StatusOr<VisitRecord> StartVisit(const std::string& map_name, const std::string& robot,
                                         const std::string& label, double start_time_s);
  absl::StatusOr<VisitRecord> GetVisit(int64_t visit_id);
  // Marks the visit ended; its frame counts only grow (MAX with what was committed).
  absl::StatusOr<VisitRecord> EndVisit(int64_t visit_id, double end_time_s, VisitFrameCount counts);
  absl::StatusOr<std::vector<VisitRecord>> ListVisits(const std::string& map_name);
  // The map's most recently started visit that is still open, if any.
  absl::StatusOr<std::optional<VisitRecord>> LatestOpenVisit(const std::string& map_name);

  // Inserts the keyframes and updates the visits' frame counters in one transaction; assigns
  // ids. On error nothing is written. NOT_FOUND when a visit no longer exists (map deleted);
  // FAILED_PRECONDITION when it has ended.
  // A keyframe whose visit already holds one of the same sequence and timestamp (a frame resent
  // after its reply was lost) is not stored again: it gets the stored keyframe's id and
  // `resent` = true (issue 52).
  absl::Status InsertKeyframes(std::vector<KeyframeRecord>* keyframes,
                               const std::vector<VisitFrameCount>& frame_counts);
  // The id of visit `visit_id`'s keyframe of this sequence and timestamp, if it has one: the
  // frame path's check for a resent frame before it does a keyframe's work again.
  absl::StatusOr<std::optional<int64_t>> FindKeyframe(int64_t visit_id, uint64_t sequence,
                                                      double timestamp_s);

  // Deletes keyframes `ids` of ended visit `visit_id` with their images, features and the pose
  // edges that name them, in one transaction (retention, issue 36): a kill leaves all of them
  // or none. NOT_FOUND for an unknown visit or an id that is not one of its keyframes (then
  // nothing is deleted); FAILED_PRECONDITION for a visit still open. Returns the bytes of
  // images and features deleted.
  absl::StatusOr<int64_t> DeleteKeyframes(int64_t visit_id, const std::vector<int64_t>& ids);
  // Which other visits recognised each keyframe of map `map_id` (every map for 0): keyframe id
  // -> visit ids, for keyframes recognised at least once (KeyframeRecord::sighted_keyframes).
  absl::StatusOr<std::map<int64_t, std::vector<int64_t>>> ListSightings(int64_t map_id);
  // What map `map_id` holds (MapStorage); zeros for an unknown map.
  absl::StatusOr<MapStorage> GetMapStorage(int64_t map_id);

  // Keyframes of a map (all visits, or one when visit_id != 0) by visit, then in time order,
  // without images; `limit` of them (< 0: all) after skipping `offset` (a page of them).
  absl::StatusOr<std::vector<KeyframeRecord>> ListKeyframes(int64_t map_id, int64_t visit_id,
                                                            int64_t offset = 0, int64_t limit = -1);
  // Calls `fn` for each keyframe with its images, one at a time (bounded memory); stops early
  // when `fn` returns a non-OK status and returns it.
  absl::Status ForEachKeyframeWithImages(
      int64_t map_id, int64_t visit_id,
      const std::function<absl::Status(const KeyframeRecord&)>& fn);
  // One keyframe of the map with its images. NOT_FOUND if it is not in that map.
  absl::StatusOr<KeyframeRecord> GetKeyframe(int64_t map_id, int64_t keyframe_id);
  // A keyframe's stored features (superjuts and keypoints). NOT_FOUND if it has none.
  absl::StatusOr<KeyframeFeatures> GetKeyframeFeatures(int64_t keyframe_id);
  // Calls `fn` for every stored keyframe that has features (of one map, or every map for
  // map_id 0; by keyframe id) with its descriptors; stops early when `fn` returns a non-OK
  // status and returns it. The read lock is held throughout: `fn` must not call the store.
  absl::Status ForEachKeyframeDescriptors(
      int64_t map_id, const std::function<absl::Status(const KeyframeDescriptors&)>& fn);
  // How many stored keyframes have features (every map), without reading them.
  absl::StatusOr<int64_t> CountKeyframesWithFeatures();
  // The visit's latest keyframe (without images), to resume keyframe selection.
  absl::StatusOr<std::optional<KeyframeRecord>> LastKeyframe(int64_t visit_id);

  // Models. Names are validated by the caller (ValidateMapName's rules); the file is
  // validated by the caller too (the store keeps bytes). `data` and metadata of `record`
  // (class names/colours, training JSON, trees, nodes) are stored; ALREADY_EXISTS for a name
  // in use.
  absl::StatusOr<ModelRecord> InsertModel(const ModelRecord& record, const std::string& data);
  absl::StatusOr<std::vector<ModelRecord>> ListModels();
  absl::StatusOr<ModelRecord> GetModel(const std::string& name);  // NOT_FOUND
  absl::StatusOr<std::string> GetModelData(const std::string& name);
  // Makes `model` the model of `map` (empty map: the server default); an empty `model`
  // deactivates. Returns the model active there before ("" = none). NOT_FOUND for an unknown
  // map or model.
  absl::StatusOr<std::string> ActivateModel(const std::string& map, const std::string& model);
  // The name of the model that labels frames of `map_id`: the map's own, else the server
  // default; "" when neither (map_id 0: the default only).
  absl::StatusOr<std::string> ActiveModelName(int64_t map_id);
  // FAILED_PRECONDITION while it is active anywhere; NOT_FOUND for an unknown name.
  absl::Status DeleteModel(const std::string& name);

  // Visit architectures. Put replaces the visit's record (NOT_FOUND for an unknown visit);
  // List returns those of one map (or every map for ""), by visit id; Get one visit's
  // (NOT_FOUND when it has none).
  absl::Status PutVisitPlace(const VisitPlaceRecord& record);
  absl::StatusOr<std::vector<VisitPlaceRecord>> ListVisitPlaces(const std::string& map_name);
  absl::StatusOr<VisitPlaceRecord> GetVisitPlace(int64_t visit_id);

  // Semantic octree snapshots (issue 16). Put replaces the visit's snapshot in one transaction
  // (its bytes in chunks of kSemanticChunkBytes): a crash leaves the previous one whole.
  // NOT_FOUND for an unknown visit (Put) or a visit without a snapshot (Get).
  absl::Status PutSemanticSnapshot(const SemanticSnapshotRecord& record);
  absl::StatusOr<SemanticSnapshotRecord> GetSemanticSnapshot(int64_t visit_id);
  // The map's visits' snapshots without their bytes (what each holds, and when it was made).
  absl::StatusOr<std::vector<SemanticSnapshotRecord>> ListSemanticSnapshots(int64_t map_id);
  // The map's own octree (schema 12), replaced whole like a visit's. NOT_FOUND for an unknown
  // map (Put) or a map without one (Get).
  absl::Status PutMapSemanticSnapshot(const MapSemanticSnapshotRecord& record);
  absl::StatusOr<MapSemanticSnapshotRecord> GetMapSemanticSnapshot(int64_t map_id);
  static constexpr size_t kSemanticChunkBytes = 4 << 20;

  // Appearance vocabularies. Put stores a new one (it becomes the one in use; its id is
  // returned); Latest returns the one in use, nullopt when none was stored.
  absl::StatusOr<int64_t> PutVocabulary(const VocabularyRecord& record);
  absl::StatusOr<std::optional<VocabularyRecord>> LatestVocabulary();

  // Pose graphs (issue 15). InsertPoseEdge stores an edge (NOT_FOUND when either keyframe is
  // gone) and returns its id. ListPoseEdges: a map's edges whose querying keyframe is in
  // `visit_id` (0: every visit), by id.
  absl::StatusOr<int64_t> InsertPoseEdge(const PoseEdgeRecord& edge);
  absl::StatusOr<std::vector<PoseEdgeRecord>> ListPoseEdges(int64_t map_id, int64_t visit_id);
  // Writes a solve in one transaction: `poses` (T_world_camera of keyframes, with the record's
  // id as their optimisation_id); the edges in `rejected` marked rejected with `reject_reason`;
  // and each keyframe of the visit newer than every keyframe in `poses` (tracked while the
  // graph was solved) moved to `later_correction` * its odometry pose. A crash leaves the poses
  // of the previous solve. Returns the record's id; NOT_FOUND when the visit's map is gone.
  absl::StatusOr<int64_t> ApplyPoseOptimisation(PoseOptimisationRecord record,
                                                const std::map<int64_t, Pose>& poses,
                                                const std::vector<int64_t>& rejected,
                                                const std::string& reject_reason,
                                                const Pose& later_correction);
  // Anchors a visit (issue 15): stores the anchor edge (accepted) and the visit's anchor, and
  // moves the visit's posed keyframes into the map's frame (T_map_visit * pose), in one
  // transaction; sets anchor.edge_id. FAILED_PRECONDITION when the visit is anchored already;
  // NOT_FOUND when it or a keyframe is gone.
  absl::Status AnchorVisit(int64_t visit_id, const PoseEdgeRecord& edge, VisitAnchor* anchor);
  // Revises an anchored visit's anchor (issue 35), in one transaction: the visit's accepted
  // anchor and tie edges are marked rejected ("superseded by anchor revision: <reason>"),
  // `edges` (the matches that agree on the new anchor) are stored accepted, the first being the
  // anchor edge; its keyframes move by `T_moved_by` (left-multiplied: T_map_visit becomes
  // T_moved_by * T_map_visit, given in `anchor` with the visit it is anchored to and the
  // residual); the history gains a "revised" entry with `reason`. FAILED_PRECONDITION for a
  // visit that is not anchored, NOT_FOUND for one that does not exist. A kill leaves the
  // poses before or after, never between.
  absl::Status ReviseAnchor(int64_t visit_id, const Pose& T_moved_by,
                            const std::vector<PoseEdgeRecord>& edges, const std::string& reason,
                            VisitAnchor* anchor);
  // Drops an anchored visit's anchor (issue 35: a later check found it wrong), in one
  // transaction: its accepted anchor and tie edges are marked rejected ("anchor dropped:
  // <reason>"), its posed keyframes move back into its own frame (T_map_visit⁻¹ * pose), its
  // anchor is cleared and the history gains a "dropped" entry at `time_s` with `reason`.
  // Returns the T_map_visit dropped. FAILED_PRECONDITION for a visit that is not anchored,
  // NOT_FOUND for one that does not exist. A kill leaves the poses before or after, never
  // between.
  absl::StatusOr<Pose> DropAnchor(int64_t visit_id, const std::string& reason, double time_s);
  // A visit's anchor history, oldest first.
  absl::StatusOr<std::vector<AnchorRevision>> ListAnchorRevisions(int64_t visit_id);
  // A map's solves (of one visit, or all for 0), oldest first.
  absl::StatusOr<std::vector<PoseOptimisationRecord>> ListPoseOptimisations(int64_t map_id,
                                                                            int64_t visit_id);

  // Annotations (schema 18). Insert assigns the id (NOT_FOUND for an unknown map); List: a
  // map's, oldest first; Delete: NOT_FOUND unless the map holds annotation `id`.
  absl::StatusOr<AnnotationRecord> InsertAnnotation(const AnnotationRecord& record);
  absl::StatusOr<std::vector<AnnotationRecord>> ListAnnotations(int64_t map_id);
  absl::Status DeleteAnnotation(int64_t map_id, int64_t id);

  // API keys (issue 17). Insert: ALREADY_EXISTS for a name in use (revoked keys keep theirs),
  // NOT_FOUND for an unknown map id; assigns the id. List: every key (revoked too) by name,
  // with the current names of the maps a limited key may use. Revoke: sets revoked_time_s once
  // (a second call keeps the first time); NOT_FOUND for an unknown name. Touch: last_used.
  absl::StatusOr<ApiKeyRecord> InsertApiKey(const ApiKeyRecord& record);
  absl::StatusOr<std::vector<ApiKeyRecord>> ListApiKeys();
  absl::StatusOr<ApiKeyRecord> RevokeApiKey(const std::string& name, double time_s);
  absl::Status TouchApiKey(int64_t key_id, double time_s);
  // A key of a cluster's key ring as one shard keeps it (server/rpc/shard_membership.h):
  // inserted, or its row replaced by name (last_used_time_s kept) with exactly
  // `record.map_ids`. NOT_FOUND for an unknown map id.
  absl::StatusOr<ApiKeyRecord> PutApiKey(const ApiKeyRecord& record);
  // The audit log: Append one event; List the newest `limit` at or after `since_time_s`,
  // newest first.
  absl::Status AppendAuditEvent(const AuditEventRecord& event);
  // Deletes the events older than `before_time_s`; returns how many.
  absl::StatusOr<int64_t> PruneAuditEvents(double before_time_s);
  absl::StatusOr<std::vector<AuditEventRecord>> ListAuditEvents(double since_time_s, int limit);

  // Administration.
  absl::StatusOr<StoreStats> Stats();
  // Online backup to a new file (sqlite3 backup API), written as a hidden ".NAME.partial-XXXXXX"
  // beside it (unique; nothing existing is removed) and linked to
  // `path` once whole: a crash leaves no file at `path` or a whole one. ALREADY_EXISTS if `path`
  // exists (also when it appears meanwhile: never overwritten).
  absl::Status Backup(const std::string& path);
  // OK while the database file and its WAL are the files this store opened; FAILED_PRECONDITION
  // saying what happened once one was deleted, moved or replaced (then every write is refused:
  // a restart would not find it). Two stat() calls; safe from any thread.
  absl::Status CheckFilesInPlace();
  // CheckFilesInPlace + PRAGMA integrity_check + foreign_key_check; returns the problems
  // (empty = ok).
  absl::StatusOr<std::vector<std::string>> CheckIntegrity();
  absl::Status Vacuum();
  // Moves the WAL into the main file (PRAGMA wal_checkpoint(TRUNCATE)).
  absl::Status Checkpoint();

 private:
  struct Impl;
  explicit Store(std::unique_ptr<Impl> impl, std::string path);
  std::unique_ptr<Impl> impl_;
  std::string path_;
};

// InvalidArgument unless the name is 1–max_length characters of [A-Za-z0-9._-] not starting
// with '.'; the message calls it a `kind` name ("map", "model", "backup").
absl::Status ValidateName(const std::string& name, absl::string_view kind, size_t max_length = 64);
// InvalidArgument unless a map name is 1-64 bytes of UTF-8: ASCII letters, digits, '.', '_', '-',
// single inner spaces, and any non-ASCII character that is seen (letters of any script, "Küche",
// "東京"; no controls, invisible or bidirectional characters); not starting with '.'.
absl::Status ValidateMapName(const std::string& name);

}  // namespace lifemap::store
