// lifemapd's configuration: defaults, a JSON config file, command-line flags on top.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include <optional>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "core/appearance/recognizer.h"
#include "core/pipeline/frame_pipeline.h"
#include "core/pipeline/keyframe.h"
#include "core/semantic/semantic_map.h"
#include "core/tracking/keyframe_selector.h"
#include "server/engine/options.h"
#include "server/engine/visit_changes.h"

namespace lifemap::server {

// True for a HOST:PORT on loopback (localhost, 127.0.0.0/8, [::1]) and for unix: sockets.
bool IsLoopbackAddress(absl::string_view listen);

struct ServerConfig {
  std::string listen = "127.0.0.1:50051";  // HOST:PORT; port 0 picks a free port
  // The browser view (issue 38, server/http/web_server.h): HOST:PORT, empty = off (config key
  // `http`, flag --http).
  std::string http_listen;
  // Names the browser view answers to besides IP literals, localhost, the listen address's
  // name and this machine's (a request with another Host is refused: DNS rebinding; config
  // key `http_allowed_hosts`, flag --http-allowed-host, repeated). ".example.org" takes every
  // name under it, "*" any (a proxy in front checks Host).
  std::vector<std::string> http_allowed_hosts;
  // A shard of a cluster (issue 39): the placement database (libpq URI) and this shard's name
  // in it (`lifemap admin shards add NAME ADDRESS`); both or neither. Empty: a lone server.
  std::string placement_uri;
  std::string shard_name;
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
  tracking::OdometryOptions odometry;  // frames sent without a pose (config key `tracking`)
  // Paper 002's semantic octree per visit: keyframes' class distributions fused, rendered into
  // every posed frame of the visit (FrameResult.fused_labels).
  bool semantic_enabled = true;
  semantic::SemanticMapOptions semantic;
  // GetChanges (config key `changes`, issue 36): how two visits' depth is compared.
  VisitChangeOptions changes;
  // Retention (config key `retention`, issue 36): keyframes of older visits thinned.
  RetentionOptions retention;
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

  // The map engine's settings (server/engine/options.h), from the fields above.
  EngineOptions engine_options() const;
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
// Keys: listen, http, http_allowed_hosts (names), db, max_message_mb, max_streams,
// max_streams_per_key, stream_start_timeout_s, stream_idle_timeout_s, max_inflight_frames,
// keyframe_batch_max, shutdown_grace_s, synchronous ("full" | "normal"), log_level, keyframe
// {min_translation_m, min_rotation_deg, max_interval_s}, frames {min_depth_m, max_depth_m,
// max_pixels} (depth outside the range is no reading; larger frames are refused), entropy {enabled,
// threshold, downsample, k, min_size_px, mesh}, labels {enabled, stride, decision ("balanced" |
// "prior_weighted"), max_model_mb}, appearance {enabled, min_training_keyframes,
// max_training_keyframes, exclude_recent_s, max_frame_matches, frame_interval_s (null = keyframes
// only), candidates, min_inliers, vocabulary_branching, vocabulary_levels}, storage
// {color_jpeg_quality, backup_dir}, tracking {downscale}, semantic {enabled, resolution_m,
// max_range_m, pixel_stride, free_space_stride, render_stride}, security {require_auth,
// insecure_no_auth, tls_cert, tls_key, tls_client_ca}.
absl::StatusOr<ServerConfig> LoadConfigFile(const std::string& path, ServerConfig base);

}  // namespace lifemap::server
