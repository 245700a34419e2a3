#include "server/config.h"

#include <cmath>
#include <fstream>
#include <functional>
#include <vector>

#include <gtest/gtest.h>

#include "tests/testing/test_util.h"

namespace lifemap::server {
namespace {

TEST(ServerConfig, DefaultsAreValid) { EXPECT_TRUE(ServerConfig().Validate().ok()); }

TEST(ServerConfig, TheBrowserViewNeedsAnAddressOfItsOwn) {
  ServerConfig c;
  c.http_listen = "127.0.0.1:8080";
  EXPECT_TRUE(c.Validate().ok());
  c.http_listen = "8080";
  EXPECT_NE(c.Validate().message().find("must be HOST:PORT"), std::string::npos);
  c.http_listen = c.listen;
  EXPECT_NE(c.Validate().message().find("different ports"), std::string::npos);
  c.listen = c.http_listen = "127.0.0.1:0";  // two free ports, picked apart
  EXPECT_TRUE(c.Validate().ok());
  // The names it answers to (issue 52): host names, domains, or "*".
  c.http_allowed_hosts = {"view.lab.example", ".robots.example", "*"};
  EXPECT_TRUE(c.Validate().ok());
  for (const char* bad : {"", "http://view.example", "view.example:8080", "a b", "."}) {
    c.http_allowed_hosts = {bad};
    EXPECT_NE(c.Validate().message().find("is not a host name"), std::string::npos) << bad;
  }
}

// A config file LoadConfigFile must refuse with InvalidArgument, and a phrase its message must
// hold ("" for any message).
struct Refused {
  const char* file;
  const char* text;
  const char* phrase = "";
};

void ExpectRefused(const testing::TempDir& tmp, const std::vector<Refused>& cases) {
  for (const Refused& c : cases) {
    std::ofstream(tmp.File(c.file)) << c.text;
    const absl::Status s = LoadConfigFile(tmp.File(c.file), ServerConfig()).status();
    EXPECT_TRUE(absl::IsInvalidArgument(s)) << c.file << ": " << s;
    EXPECT_NE(s.message().find(c.phrase), std::string::npos) << c.file << ": " << s;
  }
}

TEST(ServerConfig, RejectsOutOfRangeLimits) {
  ServerConfig c;
  c.max_streams = 0;
  EXPECT_NE(c.Validate().message().find("max_streams"), std::string::npos);
  c = ServerConfig();
  c.max_inflight_frames = 1000;
  EXPECT_FALSE(c.Validate().ok());
  c = ServerConfig();
  c.listen = "no-port";
  EXPECT_FALSE(c.Validate().ok());
  c = ServerConfig();
  c.log_level = "loud";
  EXPECT_FALSE(c.Validate().ok());
}

// The settings issue 33 added: each bad value is refused naming the setting.
TEST(ServerConfig, RejectsBadStreamTimestampAndVisitLimits) {
  const auto refused = [](const std::function<void(ServerConfig*)>& set, const char* name) {
    ServerConfig c;
    set(&c);
    const absl::Status s = c.Validate();
    EXPECT_TRUE(absl::IsInvalidArgument(s)) << name << ": " << s;
    EXPECT_NE(s.message().find(name), std::string::npos) << s;
  };
  refused([](ServerConfig* c) { c->max_streams_per_key = 0; }, "max_streams_per_key");
  refused([](ServerConfig* c) { c->stream_start_timeout_s = 0; }, "stream_start_timeout_s");
  refused([](ServerConfig* c) { c->stream_start_timeout_s = NAN; }, "stream_start_timeout_s");
  refused([](ServerConfig* c) { c->stream_idle_timeout_s = -1; }, "stream_idle_timeout_s");
  refused([](ServerConfig* c) { c->stream_idle_timeout_s = 1e9; }, "stream_idle_timeout_s");
  refused([](ServerConfig* c) { c->frame_max_future_s = 0; }, "frames.max_future_s");
  refused([](ServerConfig* c) { c->frame_max_gap_s = INFINITY; }, "frames.max_gap_s");
  refused([](ServerConfig* c) { c->max_visits_per_key_per_hour = -1; },
          "max_visits_per_key_per_hour");
}

TEST(ConfigFile, ReadsTheTrackingResolutionAndRefusesOneOutOfRange) {
  testing::TempDir tmp;
  std::ofstream(tmp.File("c.json")) << R"({"tracking": {"downscale": 4}})";
  auto c = LoadConfigFile(tmp.File("c.json"), ServerConfig());
  ASSERT_TRUE(c.ok()) << c.status();
  EXPECT_EQ(c->odometry.downscale, 4);
  EXPECT_EQ(c->engine_options().odometry.downscale, 4);
  std::ofstream(tmp.File("bad.json")) << R"({"tracking": {"downscale": 8}})";
  auto bad = LoadConfigFile(tmp.File("bad.json"), ServerConfig());
  ASSERT_FALSE(bad.ok());
  EXPECT_NE(bad.status().message().find("tracking.downscale must be within [1, 4], got 8"),
            std::string::npos)
      << bad.status();
  std::ofstream(tmp.File("typo.json")) << R"({"tracking": {"downscal": 4}})";
  auto typo = LoadConfigFile(tmp.File("typo.json"), ServerConfig());
  ASSERT_FALSE(typo.ok());
  EXPECT_NE(typo.status().message().find("tracking.downscal"), std::string::npos) << typo.status();
}

TEST(ConfigFile, ReadsKnownKeys) {
  testing::TempDir tmp;
  std::ofstream(tmp.File("c.json")) << R"({"listen": "0.0.0.0:6000", "db": "/x.db",
    "max_message_mb": 32, "synchronous": "normal", "keyframe": {"min_rotation_deg": 5},
    "entropy": {"threshold": 0.3, "downsample": 1, "k": 0.8}})";
  auto c = LoadConfigFile(tmp.File("c.json"), ServerConfig());
  ASSERT_TRUE(c.ok()) << c.status();
  EXPECT_EQ(c->listen, "0.0.0.0:6000");
  EXPECT_EQ(c->max_message_bytes, 32 << 20);
  EXPECT_FALSE(c->synchronous_full);
  EXPECT_NEAR(c->keyframe.min_rotation_rad, 5 * M_PI / 180, 1e-12);
  EXPECT_FLOAT_EQ(c->pipeline.entropy.threshold, 0.3f);
  EXPECT_EQ(c->pipeline.entropy.downsample, 1);
  EXPECT_FLOAT_EQ(c->pipeline.entropy.superjuts.k, 0.8f);
}

TEST(ConfigFile, RejectsUnknownKeysWrongTypesAndBadJson) {
  testing::TempDir tmp;
  std::ofstream(tmp.File("typo.json")) << R"({"max_stream": 3})";
  std::ofstream(tmp.File("type.json")) << R"({"max_streams": "many"})";
  std::ofstream(tmp.File("bad.json")) << R"({"listen": )";
  std::ofstream(tmp.File("range.json")) << R"({"max_streams": 0})";
  std::ofstream(tmp.File("entropy.json")) << R"({"entropy": {"threshold": 2}})";
  for (const char* f : {"typo.json", "type.json", "bad.json", "range.json", "entropy.json"}) {
    auto c = LoadConfigFile(tmp.File(f), ServerConfig());
    EXPECT_TRUE(absl::IsInvalidArgument(c.status())) << f << ": " << c.status();
  }
  EXPECT_NE(
      LoadConfigFile(tmp.File("typo.json"), ServerConfig()).status().message().find("max_stream"),
      std::string::npos);
  EXPECT_TRUE(absl::IsNotFound(LoadConfigFile(tmp.File("none.json"), ServerConfig()).status()));
}

TEST(ConfigFile, ReadsAndChecksTheAppearanceSection) {
  testing::TempDir tmp;
  std::ofstream(tmp.File("ok.json"))
      << R"({"appearance": {"min_training_keyframes": 5, "frame_interval_s": 2.5,
             "candidates": 4, "min_inliers": 20, "max_keypoints": 800, "detect_scale": 0.75, "pyramid_levels": 4,
             "pyramid_scale": 1.4, "exclude_recent_m": 5, "recognised_weight": 0.5}})";
  auto c = LoadConfigFile(tmp.File("ok.json"), ServerConfig());
  ASSERT_TRUE(c.ok()) << c.status();
  EXPECT_EQ(c->appearance.min_training_keyframes, 5);
  ASSERT_TRUE(c->appearance.frame_interval_s.has_value());
  EXPECT_DOUBLE_EQ(*c->appearance.frame_interval_s, 2.5);
  EXPECT_EQ(c->appearance.recognizer.candidates, 4);
  EXPECT_EQ(c->appearance.recognizer.verify.min_inliers, 20);
  EXPECT_EQ(c->appearance.features.orb.max_keypoints, 800);
  EXPECT_DOUBLE_EQ(c->appearance.features.orb.detect_scale, 0.75);
  EXPECT_EQ(c->appearance.features.orb.pyramid_levels, 4);
  EXPECT_DOUBLE_EQ(c->appearance.features.orb.pyramid_scale, 1.4);
  EXPECT_DOUBLE_EQ(c->appearance.exclude_recent_m, 5);
  EXPECT_DOUBLE_EQ(c->appearance.recognised_weight, 0.5);
  ExpectRefused(
      tmp, {
               {"train.json", R"({"appearance": {"min_training_keyframes": 1}})", "appearance"},
               {"interval.json", R"({"appearance": {"frame_interval_s": -1}})", "appearance"},
               {"candidates.json", R"({"appearance": {"candidates": 0}})", "appearance"},
               {"weight.json", R"({"appearance": {"recognised_weight": -1}})", "recognised_weight"},
               {"inliers.json", R"({"appearance": {"min_inliers": 3}})", "appearance"},
               {"levels.json", R"({"appearance": {"vocabulary_levels": 9}})", "appearance"},
               {"keypoints.json", R"({"appearance": {"max_keypoints": 5}})", "appearance"},
               {"scale.json", R"({"appearance": {"detect_scale": 1.5}})", "appearance"},
               {"levels0.json", R"({"appearance": {"pyramid_levels": 0}})", "appearance"},
               {"ratio.json", R"({"appearance": {"pyramid_scale": 1.0}})", "appearance"},
               {"key.json", R"({"appearance": {"candidate": 4}})", "appearance"},
               {"path.json", R"({"appearance": {"exclude_recent_m": -1}})", "appearance"},
           });
}

TEST(ConfigFile, ReadsAndChecksThePoseGraphSection) {
  testing::TempDir tmp;
  std::ofstream(tmp.File("ok.json")) << R"({"pose_graph": {"enabled": false, "loop_min_inliers": 40,
             "loop_max_reprojection_px": 1.5, "loop_max_disagreement_m": 0.3,
             "loop_max_disagreement_per_m": 0, "loop_max_disagreement_deg": 8,
             "loop_max_disagreement_deg_per_m": 2, "layout_max_through_share": 0.1,
             "anchor_drop_through_share": 0.2, "anchor_max_lost_share": 0.3,
             "layout_max_own_plan_share": 0.4, "layout_max_plan_on_floor_share": 0.25,
             "anchor_max_floor_tilt_deg": 4.5, "anchor_max_floor_offset_m": 0.2,
             "anchor_min_spread_m": 1.5}})";
  auto c = LoadConfigFile(tmp.File("ok.json"), ServerConfig());
  ASSERT_TRUE(c.ok()) << c.status();
  EXPECT_FALSE(c->pose_graph.enabled);
  EXPECT_EQ(c->pose_graph.loop_min_inliers, 40);
  EXPECT_DOUBLE_EQ(c->pose_graph.loop_max_reprojection_px, 1.5);
  EXPECT_DOUBLE_EQ(c->pose_graph.loop_max_disagreement_m, 0.3);
  EXPECT_DOUBLE_EQ(c->pose_graph.loop_max_disagreement_per_m, 0.0);
  EXPECT_DOUBLE_EQ(c->pose_graph.loop_max_disagreement_deg, 8.0);
  EXPECT_DOUBLE_EQ(c->pose_graph.loop_max_disagreement_deg_per_m, 2.0);
  EXPECT_DOUBLE_EQ(c->pose_graph.layout_max_through_share, 0.1);
  EXPECT_DOUBLE_EQ(c->pose_graph.anchor_drop_through_share, 0.2);
  EXPECT_DOUBLE_EQ(c->pose_graph.anchor_max_lost_share, 0.3);
  EXPECT_DOUBLE_EQ(c->pose_graph.layout_max_own_plan_share, 0.4);
  EXPECT_DOUBLE_EQ(c->pose_graph.layout_max_plan_on_floor_share, 0.25);
  EXPECT_DOUBLE_EQ(c->pose_graph.anchor_max_floor_tilt_deg, 4.5);
  EXPECT_DOUBLE_EQ(c->pose_graph.anchor_max_floor_offset_m, 0.2);
  EXPECT_DOUBLE_EQ(c->pose_graph.anchor_min_spread_m, 1.5);
  ExpectRefused(
      tmp,
      {
          {"layout.json", R"({"pose_graph": {"layout_max_through_share": 1.5}})", "pose_graph"},
          {"drop.json", R"({"pose_graph": {"anchor_drop_through_share": -0.1}})",
           "anchor_drop_through_share"},
          {"lost.json", R"({"pose_graph": {"anchor_max_lost_share": 1.5}})",
           "anchor_max_lost_share"},
          {"on_floor.json", R"({"pose_graph": {"layout_max_plan_on_floor_share": 1.5}})",
           "layout_max_plan_on_floor_share must be within [0, 1], got 1.5"},
          {"spread.json", R"({"pose_graph": {"anchor_min_spread_m": -1}})", "anchor_min_spread_m"},
          {"tilt.json", R"({"pose_graph": {"anchor_max_floor_tilt_deg": -1}})",
           "anchor_max_floor_tilt_deg"},
          {"inliers.json", R"({"pose_graph": {"loop_min_inliers": 5}})", "pose_graph"},
          {"reprojection.json", R"({"pose_graph": {"loop_max_reprojection_px": 0}})", "pose_graph"},
          {"metres.json", R"({"pose_graph": {"loop_max_disagreement_m": -0.1}})", "pose_graph"},
          {"per_m.json", R"({"pose_graph": {"loop_max_disagreement_per_m": -1}})", "pose_graph"},
          {"degrees.json", R"({"pose_graph": {"loop_max_disagreement_deg": 0}})", "pose_graph"},
          {"deg_per_m.json", R"({"pose_graph": {"loop_max_disagreement_deg_per_m": -2}})",
           "pose_graph"},
          {"key.json", R"({"pose_graph": {"loop_inliers": 30}})", "pose_graph"},
          {"type.json", R"({"pose_graph": {"enabled": "yes"}})"},
      });
}

TEST(ConfigFile, ReadsAndChecksTheChangesSection) {
  testing::TempDir tmp;
  std::ofstream(tmp.File("ok.json")) << R"({"changes": {"pixel_stride": 2, "voxel_m": 0.04,
             "max_range_m": 3.5, "seen_through_m": 0.08, "min_views": 3, "min_free_views": 1,
             "transient_min_views": 1, "cluster_gap_voxels": 2, "min_object_voxels": 20,
             "min_object_m": 0.2, "transient_share": 0.3, "max_move_m": 2, "max_volume_ratio": 4,
             "moved_enabled": false, "moved_stride": 2, "moved_window": 5,
             "moved_threshold_m": 0.05}})";
  auto c = LoadConfigFile(tmp.File("ok.json"), ServerConfig());
  ASSERT_TRUE(c.ok()) << c.status();
  EXPECT_EQ(c->changes.pixel_stride, 2);
  EXPECT_DOUBLE_EQ(c->changes.change.voxel_m, 0.04);
  EXPECT_DOUBLE_EQ(c->changes.change.max_range_m, 3.5);
  EXPECT_DOUBLE_EQ(c->changes.change.seen_through_m, 0.08);
  EXPECT_EQ(c->changes.change.min_views, 3);
  EXPECT_EQ(c->changes.change.min_free_views, 1);
  EXPECT_EQ(c->changes.change.transient_min_views, 1);
  EXPECT_EQ(c->changes.change.cluster_gap_voxels, 2);
  EXPECT_EQ(c->changes.change.min_object_voxels, 20);
  EXPECT_DOUBLE_EQ(c->changes.change.min_object_m, 0.2);
  EXPECT_DOUBLE_EQ(c->changes.change.transient_share, 0.3);
  EXPECT_DOUBLE_EQ(c->changes.change.max_move_m, 2.0);
  EXPECT_DOUBLE_EQ(c->changes.change.max_volume_ratio, 4.0);
  EXPECT_FALSE(c->changes.moved_enabled);
  EXPECT_EQ(c->changes.moved.stride, 2);
  EXPECT_EQ(c->changes.moved.window, 5);
  EXPECT_FLOAT_EQ(c->changes.moved.threshold_m, 0.05f);
  ExpectRefused(
      tmp, {
               {"stride.json", R"({"changes": {"pixel_stride": 0}})", "pixel_stride"},
               {"voxel.json", R"({"changes": {"voxel_m": 0}})", "changes.voxel_m"},
               {"share.json", R"({"changes": {"transient_share": 1.5}})", "transient_share"},
               {"ratio.json", R"({"changes": {"max_volume_ratio": 0.5}})", "max_volume_ratio"},
               {"gap.json", R"({"changes": {"cluster_gap_voxels": 9}})", "cluster_gap_voxels"},
               {"key.json", R"({"changes": {"voxels": 1}})", "changes.voxels"},
               {"window.json", R"({"changes": {"moved_window": 0}})", "moved_window"},
               {"threshold.json", R"({"changes": {"moved_threshold_m": -1}})", "moved_threshold_m"},
           });
}

TEST(ConfigFile, ReadsAndChecksTheRetentionSection) {
  testing::TempDir tmp;
  std::ofstream(tmp.File("ok.json")) << R"({"retention": {"cover_m": 0.2, "cover_deg": 10,
             "keep_recent_visits": 3, "compact_after_visits": 8, "compact_cover_m": 1.5,
             "compact_cover_deg": 60, "recognised_within_visits": 2,
             "after_visit_end": true}})";
  auto c = LoadConfigFile(tmp.File("ok.json"), ServerConfig());
  ASSERT_TRUE(c.ok()) << c.status();
  const RetentionOptions& r = c->engine_options().retention;
  EXPECT_DOUBLE_EQ(r.cover_m, 0.2);
  EXPECT_DOUBLE_EQ(r.cover_deg, 10);
  EXPECT_EQ(r.keep_recent_visits, 3);
  EXPECT_EQ(r.compact_after_visits, 8);
  EXPECT_DOUBLE_EQ(r.compact_cover_m, 1.5);
  EXPECT_DOUBLE_EQ(r.compact_cover_deg, 60);
  EXPECT_EQ(r.recognised_within_visits, 2);
  EXPECT_TRUE(r.after_visit_end);
  ExpectRefused(tmp,
                {
                    {"recent.json", R"({"retention": {"keep_recent_visits": 0}})",
                     "retention.keep_recent_visits"},
                    {"deg.json", R"({"retention": {"cover_deg": 200}})", "retention.cover_deg"},
                    {"m.json", R"({"retention": {"compact_cover_m": -1}})", "compact_cover_m"},
                    {"key.json", R"({"retention": {"keep": 1}})", "retention.keep"},
                });
}

TEST(ConfigFile, ReadsAndChecksTheLabelsSection) {
  testing::TempDir tmp;
  std::ofstream(tmp.File("ok.json"))
      << R"({"labels": {"enabled": false, "stride": 8, "decision": "prior_weighted",
             "max_model_mb": 64}})";
  auto c = LoadConfigFile(tmp.File("ok.json"), ServerConfig());
  ASSERT_TRUE(c.ok()) << c.status();
  EXPECT_FALSE(c->labels_enabled);
  EXPECT_EQ(c->pipeline.label_stride, 8);
  EXPECT_EQ(c->pipeline.label_decision, forest::Decision::kPriorWeighted);
  EXPECT_EQ(c->max_model_mb, 64);
  ExpectRefused(tmp,
                {
                    {"decision.json", R"({"labels": {"decision": "majority"}})", "prior_weighted"},
                    {"stride.json", R"({"labels": {"stride": 0}})"},
                    {"wide.json", R"({"labels": {"stride": 17}})"},
                    {"size.json", R"({"labels": {"max_model_mb": 0}})"},
                    {"key.json", R"({"labels": {"strid": 4}})", "labels.strid"},
                });
}

TEST(ConfigFile, ReadsAndChecksTheSemanticSection) {
  testing::TempDir tmp;
  std::ofstream(tmp.File("ok.json"))
      << R"({"semantic": {"enabled": false, "resolution_m": 0.1, "max_range_m": 4.0,
             "pixel_stride": 2, "free_space_stride": 8, "render_stride": 4}})";
  auto c = LoadConfigFile(tmp.File("ok.json"), ServerConfig());
  ASSERT_TRUE(c.ok()) << c.status();
  EXPECT_FALSE(c->semantic_enabled);
  EXPECT_DOUBLE_EQ(c->semantic.resolution_m, 0.1);
  EXPECT_DOUBLE_EQ(c->semantic.max_range_m, 4.0);
  EXPECT_EQ(c->semantic.pixel_stride, 2);
  EXPECT_EQ(c->semantic.free_space_stride, 8);
  EXPECT_EQ(c->semantic_render_stride, 4);
  ExpectRefused(tmp,
                {
                    {"resolution.json", R"({"semantic": {"resolution_m": 0}})"},
                    {"range.json", R"({"semantic": {"max_range_m": 50}})"},
                    {"free.json", R"({"semantic": {"free_space_stride": -1}})"},
                    {"render.json", R"({"semantic": {"render_stride": 0}})", "render_stride"},
                    {"key.json", R"({"semantic": {"resolution": 0.05}})", "semantic.resolution"},
                });
}

TEST(ConfigFile, ReadsAndChecksTheStorageSection) {
  testing::TempDir tmp;
  EXPECT_EQ(ServerConfig().keyframe_color_jpeg_quality, 85);
  std::ofstream(tmp.File("ok.json"))
      << R"({"storage": {"color_jpeg_quality": 70, "backup_dir": "/srv/lifemap-backups"}})";
  auto c = LoadConfigFile(tmp.File("ok.json"), ServerConfig());
  ASSERT_TRUE(c.ok()) << c.status();
  EXPECT_EQ(c->keyframe_color_jpeg_quality, 70);
  EXPECT_EQ(BackupDirectory(*c), "/srv/lifemap-backups");
  ServerConfig defaults;
  defaults.db_path = "/var/lib/lifemap/lifemap.db";
  EXPECT_EQ(BackupDirectory(defaults), "/var/lib/lifemap/backups") << "beside the database";
  defaults.db_path = "lifemap.db";
  EXPECT_EQ(BackupDirectory(defaults), "backups");
  ExpectRefused(tmp,
                {
                    {"zero.json", R"({"storage": {"color_jpeg_quality": 0}})"},
                    {"high.json", R"({"storage": {"color_jpeg_quality": 101}})",
                     "color_jpeg_quality must be within [1, 100]"},
                    {"type.json", R"({"storage": {"color_jpeg_quality": "high"}})"},
                    {"key.json", R"({"storage": {"jpeg_quality": 80}})", "storage.jpeg_quality"},
                });
}

TEST(ConfigFile, ReadsAndChecksTheSecuritySection) {
  testing::TempDir tmp;
  std::ofstream(tmp.File("ok.json"))
      << R"({"security": {"require_auth": true, "tls_cert": "c.pem", "tls_key": "k.pem",
             "tls_client_ca": "ca.pem"}})";
  auto c = LoadConfigFile(tmp.File("ok.json"), ServerConfig());
  ASSERT_TRUE(c.ok()) << c.status();
  EXPECT_TRUE(c->require_auth);
  EXPECT_EQ(c->tls_cert, "c.pem");
  EXPECT_EQ(c->tls_key, "k.pem");
  EXPECT_EQ(c->tls_client_ca, "ca.pem");
  ExpectRefused(
      tmp, {
               {"both.json", R"({"security": {"require_auth": true, "insecure_no_auth": true}})",
                "contradict"},
               {"nokey.json", R"({"security": {"tls_cert": "c.pem"}})", "private key"},
               {"noca.json", R"({"security": {"tls_client_ca": "ca.pem"}})", "--tls-cert"},
               {"typo.json", R"({"security": {"require_uath": true}})", "security.require_uath"},
               {"retention.json", R"({"security": {"audit_retention_days": -1}})",
                "audit_retention_days must be a number of days >= 0"},
           });
  std::ofstream(tmp.File("keep.json")) << R"({"security": {"audit_retention_days": 0}})";
  auto keep = LoadConfigFile(tmp.File("keep.json"), ServerConfig());
  ASSERT_TRUE(keep.ok()) << keep.status();
  EXPECT_EQ(keep->audit_retention_days, 0.0);
  EXPECT_EQ(ServerConfig().audit_retention_days, 365.0);
}

TEST(ServerConfig, KeysAreRequiredBeyondLoopbackUnlessToldOtherwise) {
  ServerConfig c;
  EXPECT_FALSE(c.AuthRequired());  // 127.0.0.1
  c.require_auth = true;
  EXPECT_TRUE(c.AuthRequired());
  c = ServerConfig();
  c.listen = "0.0.0.0:50051";
  EXPECT_TRUE(c.AuthRequired());
  c.insecure_no_auth = true;
  EXPECT_FALSE(c.AuthRequired());
}

TEST(ConfigFile, ReadsAndChecksTheFramesSection) {
  testing::TempDir tmp;
  std::ofstream(tmp.File("ok.json"))
      << R"({"frames": {"min_depth_m": 0.2, "max_depth_m": 8, "max_pixels": 307200}})";
  auto c = LoadConfigFile(tmp.File("ok.json"), ServerConfig());
  ASSERT_TRUE(c.ok()) << c.status();
  EXPECT_FLOAT_EQ(c->pipeline.frame_limits.depth_range.min_m, 0.2f);
  EXPECT_FLOAT_EQ(c->pipeline.frame_limits.depth_range.max_m, 8.0f);
  EXPECT_EQ(c->pipeline.frame_limits.max_pixels, 307200);
  EXPECT_EQ(ServerConfig().pipeline.frame_limits.max_pixels, 1280 * 1024)
      << "the default fits 1280x1024 depth";
  ExpectRefused(tmp, {
                         {"order.json", R"({"frames": {"min_depth_m": 5, "max_depth_m": 4}})"},
                         {"zero.json", R"({"frames": {"min_depth_m": 0}})"},
                         {"far.json", R"({"frames": {"max_depth_m": 1e6}})"},
                         {"pixels.json", R"({"frames": {"max_pixels": 10}})"},
                         {"huge.json", R"({"frames": {"max_pixels": 100000000}})"},
                         {"key.json", R"({"frames": {"max_depth": 4}})"},
                     });
}

}  // namespace
}  // namespace lifemap::server
