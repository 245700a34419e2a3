#include "server/config.h"

#include "server/placement/placement.h"

#include <arpa/inet.h>
#include <netinet/in.h>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <set>

#include <nlohmann/json.hpp>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "core/common/utf8.h"
#include "server/store/store.h"

namespace lifemap::server {
namespace {

// INVALID_ARGUMENT unless `name` is a host name (letters, digits, '-' and '.'; optionally
// starting with '.': a domain), or "*".
absl::Status ValidateAllowedHost(const std::string& name) {
  if (name == "*") return absl::OkStatus();
  const std::string_view body =
      !name.empty() && name.front() == '.' ? std::string_view(name).substr(1) : name;
  const bool ok =
      !body.empty() && body.size() <= 253 && std::all_of(body.begin(), body.end(), [](char c) {
        return std::isalnum(static_cast<unsigned char>(c)) || c == '-' || c == '.';
      });
  if (!ok) {
    return absl::InvalidArgumentError(
        absl::StrCat("http_allowed_hosts (--http-allowed-host): '", EscapeForLog(name),
                     "' is not a host name: give a name such as lifemap.lab.example, a domain as "
                     ".lab.example, or * (any; a proxy in front checks Host)"));
  }
  return absl::OkStatus();
}

}  // namespace

bool IsLoopbackAddress(absl::string_view listen) {
  if (absl::StartsWith(listen, "unix:") || absl::StartsWith(listen, "unix-abstract:")) return true;
  absl::string_view host = listen;
  if (const auto colon = host.rfind(':'); colon != absl::string_view::npos) {
    host = host.substr(0, colon);
  }
  if (host.size() >= 2 && host.front() == '[' && host.back() == ']') {
    host = host.substr(1, host.size() - 2);
  }
  if (absl::AsciiStrToLower(host) == "localhost") return true;
  const std::string h(host);
  in_addr v4{};
  if (inet_pton(AF_INET, h.c_str(), &v4) == 1) return (ntohl(v4.s_addr) >> 24) == 127;
  in6_addr v6{};
  if (inet_pton(AF_INET6, h.c_str(), &v6) == 1) return IN6_IS_ADDR_LOOPBACK(&v6);
  return false;  // a host name or an address beyond loopback (0.0.0.0, [::] included)
}

bool ServerConfig::AuthRequired() const {
  return require_auth || (!insecure_no_auth && !IsLoopbackAddress(listen));
}

absl::Status ServerConfig::Validate() const {
  if (require_auth && insecure_no_auth) {
    return absl::InvalidArgumentError(
        "security.require_auth and security.insecure_no_auth (--require-auth, "
        "--insecure-no-auth) contradict each other: choose one");
  }
  if (max_visits_per_key_per_hour < 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("security.max_visits_per_key_per_hour must be >= 0 (0: no bound), got ",
                     max_visits_per_key_per_hour));
  }
  if (!(audit_retention_days >= 0.0) || !std::isfinite(audit_retention_days)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "security.audit_retention_days must be a number of days >= 0 (0 keeps every event); "
        "got ",
        audit_retention_days));
  }
  if (tls_cert.empty() != tls_key.empty()) {
    return absl::InvalidArgumentError(
        "TLS needs both a certificate and its private key (security.tls_cert and "
        "security.tls_key, or --tls-cert and --tls-key)");
  }
  if (!tls_client_ca.empty() && tls_cert.empty()) {
    return absl::InvalidArgumentError(
        "security.tls_client_ca (--tls-client-ca) verifies clients over TLS: give the server's "
        "certificate and key too (--tls-cert, --tls-key)");
  }
  if (listen.empty() || listen.rfind(':') == std::string::npos) {
    return absl::InvalidArgumentError(
        absl::StrCat("listen address '", listen, "' must be HOST:PORT, e.g. 127.0.0.1:50051"));
  }
  if (!http_listen.empty() &&
      (http_listen.rfind(':') == std::string::npos || absl::StartsWith(http_listen, "unix:"))) {
    return absl::InvalidArgumentError(
        absl::StrCat("browser view address '", http_listen,
                     "' (http, --http) must be HOST:PORT, e.g. 127.0.0.1:8080 (port 0 picks one)"));
  }
  for (const auto& name : http_allowed_hosts) {
    if (auto s = ValidateAllowedHost(name); !s.ok()) return s;
  }
  if (!http_listen.empty() && http_listen == listen && !absl::EndsWith(listen, ":0")) {
    return absl::InvalidArgumentError(
        absl::StrCat("the browser view (--http) and gRPC (--listen) cannot share ", listen,
                     ": give them different ports"));
  }
  if (placement_uri.empty() != shard_name.empty()) {
    return absl::InvalidArgumentError(
        "a shard needs both the placement database (placement, --placement URI) and its name "
        "in it (shard, --shard NAME); give both, or neither for a lone server");
  }
  if (!shard_name.empty()) {
    if (auto s = placement::ValidateShardName(shard_name); !s.ok()) return s;
  }
  if (max_message_bytes < (1 << 20) || max_message_bytes > (256 << 20)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "max message size must be within [1, 256] MiB, got ", max_message_bytes >> 20, " MiB"));
  }
  if (max_streams < 1 || max_streams > 1024) {
    return absl::InvalidArgumentError(
        absl::StrCat("max_streams must be within [1, 1024], got ", max_streams));
  }
  if (max_streams_per_key < 1 || max_streams_per_key > 1024) {
    return absl::InvalidArgumentError(
        absl::StrCat("max_streams_per_key must be within [1, 1024], got ", max_streams_per_key));
  }
  if (!std::isfinite(stream_start_timeout_s) || stream_start_timeout_s <= 0 ||
      stream_start_timeout_s > 3600) {
    return absl::InvalidArgumentError(absl::StrCat(
        "stream_start_timeout_s must be within (0, 3600], got ", stream_start_timeout_s));
  }
  if (!std::isfinite(stream_idle_timeout_s) || stream_idle_timeout_s <= 0 ||
      stream_idle_timeout_s > 86400) {
    return absl::InvalidArgumentError(absl::StrCat(
        "stream_idle_timeout_s must be within (0, 86400], got ", stream_idle_timeout_s));
  }
  if (max_inflight_frames < 1 || max_inflight_frames > 64) {
    return absl::InvalidArgumentError(
        absl::StrCat("max_inflight_frames must be within [1, 64], got ", max_inflight_frames));
  }
  if (!std::isfinite(shutdown_grace_s) || shutdown_grace_s < 0 || shutdown_grace_s > 3600) {
    return absl::InvalidArgumentError(
        absl::StrCat("shutdown_grace_s must be within [0, 3600], got ", shutdown_grace_s));
  }
  static const std::set<std::string> kLevels = {"trace", "debug",    "info", "warn",
                                                "error", "critical", "off"};
  if (kLevels.count(log_level) == 0) {
    return absl::InvalidArgumentError(absl::StrCat(
        "log level '", log_level, "' is not one of trace, debug, info, warn, error, off"));
  }
  if (max_model_mb < 1 || max_model_mb > 1024) {
    return absl::InvalidArgumentError(
        absl::StrCat("labels.max_model_mb must be within [1, 1024], got ", max_model_mb));
  }
  // The map engine's own settings (frames, storage, entropy, labels, appearance, pose graph,
  // semantic): server/engine/options.h.
  if (auto s = engine_options().Validate(); !s.ok()) return s;
  return keyframe.Validate();
}

EngineOptions ServerConfig::engine_options() const {
  EngineOptions o;
  o.db_path = db_path;
  o.synchronous_full = synchronous_full;
  o.keyframe_batch_max = keyframe_batch_max;
  o.pipeline = pipeline;
  o.labels_enabled = labels_enabled;
  o.appearance = appearance;
  o.pose_graph = pose_graph;
  o.odometry = odometry;
  o.semantic_enabled = semantic_enabled;
  o.semantic = semantic;
  o.semantic_render_stride = semantic_render_stride;
  o.color_jpeg_quality = keyframe_color_jpeg_quality;
  o.max_future_s = frame_max_future_s;
  o.max_gap_s = frame_max_gap_s;
  o.changes = changes;
  o.changes.moved.max_range_m = changes.change.max_range_m;
  o.retention = retention;
  return o;
}

absl::StatusOr<ServerConfig> LoadConfigFile(const std::string& path, ServerConfig base) {
  std::ifstream in(path);
  if (!in) return absl::NotFoundError(absl::StrCat("config file ", path, " cannot be opened"));
  nlohmann::json j;
  try {
    in >> j;
  } catch (const nlohmann::json::parse_error& e) {
    return absl::InvalidArgumentError(absl::StrCat("config file ", path, ": ", e.what()));
  }
  if (!j.is_object()) {
    return absl::InvalidArgumentError(absl::StrCat("config file ", path, " must hold an object"));
  }
  ServerConfig c = std::move(base);
  try {
    for (const auto& [key, value] : j.items()) {
      if (key == "listen") {
        c.listen = value.get<std::string>();
      } else if (key == "http") {
        c.http_listen = value.get<std::string>();
      } else if (key == "http_allowed_hosts") {
        c.http_allowed_hosts = value.get<std::vector<std::string>>();
      } else if (key == "placement") {
        c.placement_uri = value.get<std::string>();
      } else if (key == "shard") {
        c.shard_name = value.get<std::string>();
      } else if (key == "db") {
        c.db_path = value.get<std::string>();
      } else if (key == "max_message_mb") {
        const int mb = value.get<int>();
        c.max_message_bytes = (mb > 0 && mb <= 1024) ? mb << 20 : 0;
      } else if (key == "max_streams") {
        c.max_streams = value.get<int>();
      } else if (key == "max_streams_per_key") {
        c.max_streams_per_key = value.get<int>();
      } else if (key == "stream_start_timeout_s") {
        c.stream_start_timeout_s = value.get<double>();
      } else if (key == "stream_idle_timeout_s") {
        c.stream_idle_timeout_s = value.get<double>();
      } else if (key == "max_inflight_frames") {
        c.max_inflight_frames = value.get<int>();
      } else if (key == "keyframe_batch_max") {
        c.keyframe_batch_max = value.get<int>();
      } else if (key == "shutdown_grace_s") {
        c.shutdown_grace_s = value.get<double>();
      } else if (key == "synchronous") {
        const auto mode = value.get<std::string>();
        if (mode != "full" && mode != "normal") {
          return absl::InvalidArgumentError(
              absl::StrCat("config file ", path, ": synchronous must be \"full\" or \"normal\""));
        }
        c.synchronous_full = mode == "full";
      } else if (key == "log_level") {
        c.log_level = value.get<std::string>();
      } else if (key == "keyframe") {
        for (const auto& [k, v] : value.items()) {
          if (k == "min_translation_m") {
            c.keyframe.min_translation_m = v.get<double>();
          } else if (k == "min_rotation_deg") {
            c.keyframe.min_rotation_rad = v.get<double>() * M_PI / 180.0;
          } else if (k == "max_interval_s") {
            c.keyframe.max_interval_s = v.get<double>();
          } else {
            return absl::InvalidArgumentError(
                absl::StrCat("config file ", path, ": unknown key keyframe.", k));
          }
        }
      } else if (key == "entropy") {
        for (const auto& [k, v] : value.items()) {
          if (k == "enabled") {
            c.pipeline.entropy_masks = v.get<bool>();
          } else if (k == "threshold") {
            c.pipeline.entropy.threshold = v.get<float>();
          } else if (k == "downsample") {
            c.pipeline.entropy.downsample = v.get<int>();
          } else if (k == "k") {
            c.pipeline.entropy.superjuts.k = v.get<float>();
          } else if (k == "mesh") {
            c.pipeline.entropy.mesh = v.get<bool>();
          } else if (k == "min_size_px") {
            c.pipeline.entropy.superjuts.min_size_px = v.get<int>();
          } else {
            return absl::InvalidArgumentError(
                absl::StrCat("config file ", path, ": unknown key entropy.", k));
          }
        }
      } else if (key == "frames") {
        for (const auto& [k, v] : value.items()) {
          if (k == "min_depth_m") {
            c.pipeline.frame_limits.depth_range.min_m = v.get<float>();
          } else if (k == "max_depth_m") {
            c.pipeline.frame_limits.depth_range.max_m = v.get<float>();
          } else if (k == "max_pixels") {
            c.pipeline.frame_limits.max_pixels = v.get<int64_t>();
          } else if (k == "max_future_s") {
            c.frame_max_future_s = v.get<double>();
          } else if (k == "max_gap_s") {
            c.frame_max_gap_s = v.get<double>();
          } else {
            return absl::InvalidArgumentError(
                absl::StrCat("config file ", path, ": unknown key frames.", k));
          }
        }
      } else if (key == "labels") {
        for (const auto& [k, v] : value.items()) {
          if (k == "enabled") {
            c.labels_enabled = v.get<bool>();
          } else if (k == "stride") {
            c.pipeline.label_stride = v.get<int>();
          } else if (k == "max_model_mb") {
            c.max_model_mb = v.get<int>();
          } else if (k == "decision") {
            const auto d = v.get<std::string>();
            if (d != "balanced" && d != "prior_weighted") {
              return absl::InvalidArgumentError(
                  absl::StrCat("config file ", path,
                               ": labels.decision must be \"balanced\" or "
                               "\"prior_weighted\""));
            }
            c.pipeline.label_decision =
                d == "balanced" ? forest::Decision::kBalanced : forest::Decision::kPriorWeighted;
          } else {
            return absl::InvalidArgumentError(
                absl::StrCat("config file ", path, ": unknown key labels.", k));
          }
        }
      } else if (key == "tracking") {
        for (const auto& [k, v] : value.items()) {
          if (k == "downscale") {
            c.odometry.downscale = v.get<int>();
          } else {
            return absl::InvalidArgumentError(
                absl::StrCat("config file ", path, ": unknown key tracking.", k));
          }
        }
      } else if (key == "semantic") {
        for (const auto& [k, v] : value.items()) {
          if (k == "enabled") {
            c.semantic_enabled = v.get<bool>();
          } else if (k == "resolution_m") {
            c.semantic.resolution_m = v.get<double>();
          } else if (k == "max_range_m") {
            c.semantic.max_range_m = v.get<double>();
          } else if (k == "pixel_stride") {
            c.semantic.pixel_stride = v.get<int>();
          } else if (k == "free_space_stride") {
            c.semantic.free_space_stride = v.get<int>();
          } else if (k == "render_stride") {
            c.semantic_render_stride = v.get<int>();
          } else {
            return absl::InvalidArgumentError(
                absl::StrCat("config file ", path, ": unknown key semantic.", k));
          }
        }
      } else if (key == "appearance") {
        for (const auto& [k, v] : value.items()) {
          auto& a = c.appearance;
          if (k == "enabled") {
            a.enabled = v.get<bool>();
          } else if (k == "min_training_keyframes") {
            a.min_training_keyframes = v.get<int>();
          } else if (k == "max_training_keyframes") {
            a.max_training_keyframes = v.get<int>();
          } else if (k == "exclude_recent_s") {
            a.exclude_recent_s = v.get<double>();
          } else if (k == "exclude_recent_m") {
            a.exclude_recent_m = v.get<double>();
          } else if (k == "recognised_weight") {
            a.recognised_weight = v.get<double>();
          } else if (k == "max_frame_matches") {
            a.max_frame_matches = v.get<int>();
          } else if (k == "frame_interval_s") {
            a.frame_interval_s =
                v.is_null() ? std::nullopt : std::optional<double>(v.get<double>());
          } else if (k == "candidates") {
            a.recognizer.candidates = v.get<int>();
          } else if (k == "min_inliers") {
            a.recognizer.verify.min_inliers = v.get<int>();
          } else if (k == "vocabulary_branching") {
            a.vocabulary.branching = v.get<int>();
          } else if (k == "vocabulary_levels") {
            a.vocabulary.levels = v.get<int>();
          } else if (k == "max_keypoints") {
            a.features.orb.max_keypoints = v.get<int>();
          } else if (k == "detect_scale") {
            a.features.orb.detect_scale = v.get<double>();
          } else if (k == "pyramid_levels") {
            a.features.orb.pyramid_levels = v.get<int>();
          } else if (k == "pyramid_scale") {
            a.features.orb.pyramid_scale = v.get<double>();
          } else {
            return absl::InvalidArgumentError(
                absl::StrCat("config file ", path, ": unknown key appearance.", k));
          }
        }
      } else if (key == "pose_graph") {
        for (const auto& [k, v] : value.items()) {
          auto& g = c.pose_graph;
          if (k == "enabled") {
            g.enabled = v.get<bool>();
          } else if (k == "loop_min_inliers") {
            g.loop_min_inliers = v.get<int>();
          } else if (k == "loop_max_reprojection_px") {
            g.loop_max_reprojection_px = v.get<double>();
          } else if (k == "loop_max_disagreement_m") {
            g.loop_max_disagreement_m = v.get<double>();
          } else if (k == "loop_max_disagreement_per_m") {
            g.loop_max_disagreement_per_m = v.get<double>();
          } else if (k == "loop_max_disagreement_deg") {
            g.loop_max_disagreement_deg = v.get<double>();
          } else if (k == "loop_max_disagreement_deg_per_m") {
            g.loop_max_disagreement_deg_per_m = v.get<double>();
          } else if (k == "layout_max_through_share") {
            g.layout_max_through_share = v.get<double>();
          } else if (k == "anchor_drop_through_share") {
            g.anchor_drop_through_share = v.get<double>();
          } else if (k == "layout_max_own_plan_share") {
            g.layout_max_own_plan_share = v.get<double>();
          } else if (k == "layout_max_plan_on_floor_share") {
            g.layout_max_plan_on_floor_share = v.get<double>();
          } else if (k == "anchor_max_lost_share") {
            g.anchor_max_lost_share = v.get<double>();
          } else if (k == "anchor_max_floor_tilt_deg") {
            g.anchor_max_floor_tilt_deg = v.get<double>();
          } else if (k == "anchor_max_floor_offset_m") {
            g.anchor_max_floor_offset_m = v.get<double>();
          } else if (k == "anchor_min_spread_m") {
            g.anchor_min_spread_m = v.get<double>();
          } else if (k == "anchor_revision_min_matches") {
            g.anchor_revision_min_matches = v.get<int>();
          } else {
            return absl::InvalidArgumentError(
                absl::StrCat("config file ", path, ": unknown key pose_graph.", k));
          }
        }
      } else if (key == "changes") {
        for (const auto& [k, v] : value.items()) {
          auto& o = c.changes.change;
          if (k == "pixel_stride") {
            c.changes.pixel_stride = v.get<int>();
          } else if (k == "voxel_m") {
            o.voxel_m = v.get<double>();
          } else if (k == "max_range_m") {
            o.max_range_m = v.get<double>();
          } else if (k == "seen_through_m") {
            o.seen_through_m = v.get<double>();
          } else if (k == "min_views") {
            o.min_views = v.get<int>();
          } else if (k == "min_free_views") {
            o.min_free_views = v.get<int>();
          } else if (k == "min_object_voxels") {
            o.min_object_voxels = v.get<int>();
          } else if (k == "min_object_m") {
            o.min_object_m = v.get<double>();
          } else if (k == "transient_min_views") {
            o.transient_min_views = v.get<int>();
          } else if (k == "cluster_gap_voxels") {
            o.cluster_gap_voxels = v.get<int>();
          } else if (k == "transient_share") {
            o.transient_share = v.get<double>();
          } else if (k == "max_move_m") {
            o.max_move_m = v.get<double>();
          } else if (k == "max_volume_ratio") {
            o.max_volume_ratio = v.get<double>();
          } else if (k == "moved_enabled") {
            c.changes.moved_enabled = v.get<bool>();
          } else if (k == "moved_stride") {
            c.changes.moved.stride = v.get<int>();
          } else if (k == "moved_window") {
            c.changes.moved.window = v.get<int>();
          } else if (k == "moved_threshold_m") {
            c.changes.moved.threshold_m = v.get<float>();
          } else {
            return absl::InvalidArgumentError(
                absl::StrCat("config file ", path, ": unknown key changes.", k));
          }
        }
      } else if (key == "retention") {
        for (const auto& [k, v] : value.items()) {
          auto& o = c.retention;
          if (k == "cover_m") {
            o.cover_m = v.get<double>();
          } else if (k == "cover_deg") {
            o.cover_deg = v.get<double>();
          } else if (k == "keep_recent_visits") {
            o.keep_recent_visits = v.get<int>();
          } else if (k == "compact_after_visits") {
            o.compact_after_visits = v.get<int>();
          } else if (k == "compact_cover_m") {
            o.compact_cover_m = v.get<double>();
          } else if (k == "compact_cover_deg") {
            o.compact_cover_deg = v.get<double>();
          } else if (k == "recognised_within_visits") {
            o.recognised_within_visits = v.get<int>();
          } else if (k == "after_visit_end") {
            o.after_visit_end = v.get<bool>();
          } else {
            return absl::InvalidArgumentError(
                absl::StrCat("config file ", path, ": unknown key retention.", k));
          }
        }
      } else if (key == "security") {
        for (const auto& [k, v] : value.items()) {
          if (k == "require_auth") {
            c.require_auth = v.get<bool>();
          } else if (k == "insecure_no_auth") {
            c.insecure_no_auth = v.get<bool>();
          } else if (k == "audit_retention_days") {
            c.audit_retention_days = v.get<double>();
          } else if (k == "max_visits_per_key_per_hour") {
            c.max_visits_per_key_per_hour = v.get<int>();
          } else if (k == "tls_cert") {
            c.tls_cert = v.get<std::string>();
          } else if (k == "tls_key") {
            c.tls_key = v.get<std::string>();
          } else if (k == "tls_client_ca") {
            c.tls_client_ca = v.get<std::string>();
          } else {
            return absl::InvalidArgumentError(
                absl::StrCat("config file ", path, ": unknown key security.", k));
          }
        }
      } else if (key == "storage") {
        for (const auto& [k, v] : value.items()) {
          if (k == "color_jpeg_quality") {
            c.keyframe_color_jpeg_quality = v.get<int>();
          } else if (k == "backup_dir") {
            c.backup_dir = v.get<std::string>();
          } else {
            return absl::InvalidArgumentError(
                absl::StrCat("config file ", path, ": unknown key storage.", k));
          }
        }
      } else {
        return absl::InvalidArgumentError(
            absl::StrCat("config file ", path, ": unknown key '", key, "'"));
      }
    }
  } catch (const nlohmann::json::exception& e) {
    return absl::InvalidArgumentError(
        absl::StrCat("config file ", path, ": a value has the wrong type: ", e.what()));
  }
  if (auto s = c.Validate(); !s.ok()) {
    return absl::InvalidArgumentError(absl::StrCat("config file ", path, ": ", s.message()));
  }
  return c;
}

std::string BackupDirectory(const ServerConfig& config) {
  if (!config.backup_dir.empty()) return config.backup_dir;
  const std::filesystem::path db(config.db_path);
  return (db.has_parent_path() ? db.parent_path() / "backups" : std::filesystem::path("backups"))
      .string();
}

absl::StatusOr<std::string> BackupPath(const ServerConfig& config, const std::string& name) {
  // The names maps and models follow, longer: a file name, never a path.
  if (auto s = store::ValidateName(name, "backup", 128); !s.ok()) {
    return absl::InvalidArgumentError(absl::StrCat(
        "backup name is not a file name: ", s.message(),
        " (use 1-128 characters of [A-Za-z0-9._-], not starting with '.'; the server writes it "
        "into its backup directory, storage.backup_dir)"));
  }
  std::error_code ec;
  const std::filesystem::path dir = std::filesystem::absolute(BackupDirectory(config), ec);
  if (ec) return absl::InternalError(absl::StrCat("backup directory: ", ec.message()));
  std::filesystem::create_directories(dir, ec);
  if (ec || !std::filesystem::is_directory(dir)) {
    return absl::FailedPreconditionError(
        absl::StrCat("the server's backup directory ", dir.string(), " cannot be created",
                     ec ? absl::StrCat(": ", ec.message()) : "", " (storage.backup_dir)"));
  }
  const std::filesystem::path path = dir / name;
  // symlink_status: a link of that name, even a dangling one, counts as taken.
  if (std::filesystem::symlink_status(path, ec).type() != std::filesystem::file_type::not_found) {
    return absl::AlreadyExistsError(absl::StrCat("backup '", name, "' exists already in ",
                                                 dir.string(), ": choose another name"));
  }
  return path.string();
}

}  // namespace lifemap::server
