// lifemapd's configuration: defaults, a JSON config file, command-line flags on top.
#pragma once

#include <cstdint>
#include <string>

#include <optional>

#include "absl/status/statusor.h"
#include "core/appearance/recognizer.h"
#include "core/pipeline/frame_pipeline.h"
#include "core/pipeline/keyframe.h"
#include "core/semantic/semantic_map.h"
#include "core/tracking/keyframe_selector.h"

namespace lifemap::server {

// Appearance place recognition (server/appearance.h).
struct AppearanceOptions {
  bool enabled = true;
  int min_training_keyframes = 30;    // stored keyframes before a vocabulary is trained, ≥ 2
  int max_training_keyframes = 3000;  // keyframes a vocabulary is trained on at most
  appearance::VocabularyOptions vocabulary;
  appearance::RecognizerOptions recognizer;
  pipeline::KeyframeFeatureOptions features;  // ORB per keyframe (and per queried frame)
  // A keyframe of the querying visit is not a match while it is both less than
  // `exclude_recent_s` from the query in time and less than `exclude_recent_m` of the camera's
  // path behind it (the same view a moment ago, not a recognised place). The path lets a walk
  // that returns to its start within seconds close its loop: the 300-frame synthetic walks pass
  // their start 8.6-11.4 s in, after 5-7 m, and a time window alone of 10 s excluded them.
  double exclude_recent_s = 10.0;
  double exclude_recent_m = 3.0;
  int max_frame_matches = 3;  // appearance matches a frame result lists, [1, 100]
  // Non-keyframes are queried too when a frame's options ask (FrameOptions.
  // appearance_interval_s); this is the default for frames that do not say: nullopt =
  // keyframes only; 0 = every frame; t > 0 = at most every t seconds per stream.
  std::optional<double> frame_interval_s;
  static constexpr double kMaxFrameIntervalS = 3600;  // for it and the per-stream option

  absl::Status Validate() const;
};

// Loop closure and the pose graph of tracked visits (issue 15; config key `pose_graph`).
struct PoseGraphOptions {
  bool enabled = true;  // verified appearance matches within a tracked visit close loops
  // A loop candidate (a verified appearance match to an earlier keyframe of the same visit)
  // needs at least this many PnP inliers and at most this RMS reprojection error (pixels at
  // 640 columns), stricter than a place match: a wrong loop bends the map.
  int loop_min_inliers = 25;
  double loop_max_reprojection_px = 2.5;
  // ... and must agree with the odometry up to the drift it can have accumulated since the
  // matched keyframe: base + per_m * (path length in between, metres).
  double loop_max_disagreement_m = 0.15;
  double loop_max_disagreement_per_m = 0.05;
  double loop_max_disagreement_deg = 5.0;
  double loop_max_disagreement_deg_per_m = 1.0;
  // The architecture check (paper 004's floor plans): a loop's query, or an anchored visit's
  // keyframes, placed where the matches put them, may have at most this share of their depth
  // readings beyond the walls of the matched visit's plan (where it has one), [0, 1].
  double layout_max_through_share = 0.05;

  absl::Status Validate() const;
};

struct ServerConfig {
  std::string listen = "127.0.0.1:50051";  // HOST:PORT; port 0 picks a free port
  std::string db_path = "lifemap.db";
  int max_message_bytes = 16 << 20;  // largest request or response; bigger gets RESOURCE_EXHAUSTED
  int max_streams = 16;              // concurrent StreamFrames calls
  // Of those, one API key's at most (a key's own max_streams may be lower); one key cannot
  // take every slot. Without auth there are no keys and only max_streams holds.
  int max_streams_per_key = 8;
  // A stream that sends no StreamStart within this is ended (it holds no slot meanwhile, but a
  // thread); one that then sends no message for stream_idle_timeout_s likewise.
  double stream_start_timeout_s = 10.0;
  double stream_idle_timeout_s = 120.0;
  // Frame timestamps (seconds since the Unix epoch) are refused, before anything is stored,
  // when more than max_future_s ahead of the server's clock or more than max_gap_s after the
  // previous frame of their visit: one frame stamped in ms or ns would otherwise stay the
  // visit's latest and every later frame would look as if time went back.
  double frame_max_future_s = 86400.0;
  double frame_max_gap_s = 7 * 86400.0;
  int max_inflight_frames = 4;     // per stream: frames read but not yet answered
  int keyframe_batch_max = 32;     // keyframes committed in one transaction at most
  double shutdown_grace_s = 10.0;  // on SIGTERM, time streams get to finish
  bool synchronous_full = true;    // SQLite synchronous=FULL (power-loss safe) or NORMAL
  std::string log_level = "info";  // trace, debug, info, warn, error, off
  int max_model_mb = 256;          // largest model file UploadModel accepts
  bool labels_enabled = true;      // label frames when a model is active
  tracking::KeyframeOptions keyframe;
  pipeline::PipelineOptions pipeline;  // per-frame outputs (entropy masks, labels, ...)
  AppearanceOptions appearance;
  PoseGraphOptions pose_graph;
  // Paper 002's semantic octree per visit: keyframes' class distributions fused, rendered into
  // every posed frame of the visit (FrameResult.fused_labels).
  bool semantic_enabled = true;
  semantic::SemanticMapOptions semantic;
  // Fused labels are looked up every n-th pixel (copied to the cell). 8: a 5 cm voxel spans 8
  // pixels or more of a 640-pixel-wide Kinect view up to 3.3 m away.
  int semantic_render_stride = 8;
  // Keyframe colour the client sent as PNG or raw is stored as JPEG at this quality, [1, 100]
  // (unless its map keeps originals); JPEG from the client is stored as it came.
  int keyframe_color_jpeg_quality = 85;
  // Where Backup writes (a client names only the file). Empty: "backups" beside the database
  // file. Created on the first backup.
  std::string backup_dir;
  // Security (issue 17; docs/OPERATIONS.md). Calls need an API key when `require_auth`, and
  // whenever `listen` is beyond loopback unless `insecure_no_auth` says the network is trusted.
  bool require_auth = false;
  bool insecure_no_auth = false;
  // Audit events older than this are deleted, at start and every 1,000 events recorded;
  // 0 keeps them for ever.
  double audit_retention_days = 365.0;
  // Visits one API key may start in any hour, unless the key has its own max_visits_per_hour;
  // 0: no bound. Counted while the server runs (a restart starts the count again).
  int max_visits_per_key_per_hour = 600;
  // TLS: the server's certificate chain and private key (PEM files; both or neither), and a
  // CA whose client certificates the server then requires (mTLS; optional).
  std::string tls_cert;
  std::string tls_key;
  std::string tls_client_ca;

  // Whether calls need an API key, from the three settings above.
  bool AuthRequired() const;
  // InvalidArgument naming the bad setting and its allowed range.
  absl::Status Validate() const;
};

// The server's backup directory: `backup_dir`, else "backups" beside the database file.
std::string BackupDirectory(const ServerConfig& config);
// Where a backup named `name` goes: inside BackupDirectory (created if missing). The name is a
// file name, never a path: 1-128 characters of [A-Za-z0-9._-], not starting with '.'
// (INVALID_ARGUMENT saying so); ALREADY_EXISTS when something (a file, a link) has that name.
absl::StatusOr<std::string> BackupPath(const ServerConfig& config, const std::string& name);

// Reads a JSON config file over `base`. Unknown keys are errors (they are usually typos).
// Keys: listen, db, max_message_mb, max_streams, max_streams_per_key, stream_start_timeout_s,
// stream_idle_timeout_s, max_inflight_frames, keyframe_batch_max,
// shutdown_grace_s, synchronous ("full" | "normal"), log_level,
// keyframe {min_translation_m, min_rotation_deg, max_interval_s},
// frames {min_depth_m, max_depth_m, max_pixels} (depth outside the range is no reading;
// larger frames are refused),
// entropy {enabled, threshold, downsample, k, min_size_px, mesh},
// labels {enabled, stride, decision ("balanced" | "prior_weighted"), max_model_mb},
// appearance {enabled, min_training_keyframes, max_training_keyframes, exclude_recent_s,
// max_frame_matches, frame_interval_s (null = keyframes only), candidates, min_inliers,
// vocabulary_branching, vocabulary_levels}, storage {color_jpeg_quality, backup_dir},
// semantic {enabled, resolution_m, max_range_m, pixel_stride, free_space_stride,
// render_stride}, security {require_auth, insecure_no_auth, tls_cert, tls_key, tls_client_ca}.
absl::StatusOr<ServerConfig> LoadConfigFile(const std::string& path, ServerConfig base);

}  // namespace lifemap::server
