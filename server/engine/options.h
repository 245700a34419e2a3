// The map engine's options: structs with commented defaults and a Validate() each, filled by
// lifemapd's configuration (server/config.h) and used by the engine's workers.
#pragma once

#include <optional>
#include <string>

#include "absl/status/status.h"
#include "core/appearance/recognizer.h"
#include "core/change/moved_zones.h"
#include "core/change/object_changes.h"
#include "core/pipeline/frame_pipeline.h"
#include "core/pipeline/keyframe.h"
#include "core/semantic/semantic_map.h"
#include "core/tracking/odometry.h"

namespace lifemap::server {

// Appearance place recognition (server/engine/appearance.h).
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
  // Landmarks that survive visits weigh more (issue 36): a keyframe that n other visits
  // recognised (its best verified match, store: keyframe_sightings) is ranked among the
  // candidates by its index score × (1 + recognised_weight · min(n, 3)), [0, 10]; 0: by the score
  // alone. Which candidates are verified changes, not what verifies them. Chosen on building
  // seed 7's 20 visits (RESULTS.md "Issue 36: retention"): recall 0.852 -> 0.860 unthinned,
  // 0.809 -> 0.818 thinned; 1.0 was worse.
  double recognised_weight = 0.25;
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
  // An anchor is a hypothesis (issue 35): when at least this many matches of an anchored
  // visit's later keyframes (from as many keyframes) agree with each other on another place for
  // it, disagree with where the anchor put it, outnumber the matches that support the anchor
  // (its own two and every tie accepted since) and pass the floor-plan check there, the anchor
  // is revised: the visit's keyframes move and the history says why. [2, 100].
  int anchor_revision_min_matches = 3;
  // An anchored visit is re-checked against the floor plan as its keyframes double, and its
  // anchor dropped when more than this share of their readings lie beyond the walls (of the
  // plan it was anchored against and of the map's first visit's), [0, 1]. Above
  // layout_max_through_share: an anchor is a hypothesis that earned its place, and right anchors
  // of sparse visits re-checked at 6.7 % (building seed 9, 40 frames) while a wrong one (another
  // place) was at 13.1 % (building seed 12): RESULTS.md "Issue 35 (session 22)".
  double anchor_drop_through_share = 0.10;
  // The converse check (issue 54), where the visit has a floor plan of its own: the keyframes
  // of the visit it is anchored to, placed in the visit's plan, may have at most this share of
  // their readings beyond the walls the visit saw, [0, 1]; at the anchor and at each re-check.
  // Off (1) by default: it does not separate. On building seed 41 (40-frame visits, wheel
  // odometry) right anchors gave up to 19.9 % and an L room's visit anchored into a rectangular
  // room's map 65.6-77.3 %, and 0.30 refused the wrong one at no cost; on seed 42 right anchors
  // gave up to 47.6 % (the visit's partial plan, doors it found closed) and the same kind of
  // wrong anchor 9.4 %: 0.30 refused three right ones and not the wrong one (RESULTS.md
  // "Issue 54 (anchors)").
  double layout_max_own_plan_share = 1.0;
  // The two plans compared (issue 54), where the visit has a floor plan of its own: the walls
  // either saw, placed in the other's plan by the anchor, may have at most this share of their
  // length inside the other's outline and more than 0.5 m from its walls (a wall where the other
  // has floor: place::ComparePlans), [0, 1]; once the visit's plan is final (at its end: every
  // anchor is re-checked then, Engine::EndVisit; and on a retry of an ended visit). 1: off.
  // Chosen on building suite 41 (40-frame visits, wheel odometry), at the visits' ends: right
  // anchors 0 % (all 24), an L room's visit anchored into a rectangular room's map 51-72 %;
  // reported on suite 42: right anchors 0-7 % (23), none dropped (RESULTS.md "Issue 54 (anchors):
  // re-checked at the visit's end").
  double layout_max_plan_on_floor_share = 0.20;
  // A tracked visit that has lost more than this share of its frames (judged from 20 frames on)
  // is neither anchored nor anchored to, and an anchored one that comes to lose more has its
  // anchor dropped, [0, 1]: its keyframes are pieces, not one rigid body, and two of its
  // matches agreeing prove little. Chosen on rooms seed 15 without odometry (RESULTS.md
  // "Issue 35 (session 23)"): the L room's visits lost 36-61 % and were all anchored wrong; the
  // rect room's lost 0-3 %. 1 switches the hold off.
  double anchor_max_lost_share = 0.20;
  // A visit the server tracked whose floor, as its keyframes saw it, tilts more than this
  // (degrees; 90th percentile over at least 5 keyframes that saw it) or whose level drifts more
  // than this over the visit (metres; over thirds of at least 9 such keyframes: core/place
  // FloorAgreement::drift_m) is bent, and held like one that lost its frames (issue 54). Chosen on
  // building seed 11 with wheel odometry (rigid: 0.4-0.7 deg, 0.02 m) and seed 3 without (a visit
  // 78 cm off: 11.4 deg, 0.43 m, as first measured from the largest plane; from the lowest, seed 3
  // at 300 frames gives 20.0 / 7.3 deg, 0.70 / 0.32 m): RESULTS.md "Issue 54 (first step)" and
  // "(tracking)".
  double anchor_max_floor_tilt_deg = 3.0;
  double anchor_max_floor_offset_m = 0.10;
  // The two agreeing matches that anchor a visit come from keyframes at least this far apart
  // along its path (metres, >= 0; 0: any two keyframes): neighbouring keyframes agree even
  // where the visit's own track is bent, and its anchor is then wrong away from them. Off by
  // default: a short handheld recording (TUM fr1_xyz's desk) never travels 1.5 m, the figure
  // that took rooms seed 11's wrong anchors without odometry from 4 to 0 (RESULTS.md "Issue 35
  // (session 23)").
  double anchor_min_spread_m = 0.0;

  absl::Status Validate() const;
};

// The engine's options (server/engine/engine.h), filled from lifemapd's configuration; the
// names in comments are its keys.
// GetChanges and the per-frame moved mask (issue 36; config key `changes`).
struct VisitChangeOptions {
  change::ChangeOptions change;
  int pixel_stride = 4;  // every n-th pixel of each keyframe's depth is read
  // The per-frame moved mask (FrameResult.moved) against the map's previous visit.
  bool moved_enabled = true;
  change::MovedOptions moved;  // its max_range_m is change.max_range_m's

  // InvalidArgument naming the `changes.` key out of range.
  absl::Status Validate() const;
};

// Retention (issue 36; config key `retention`, AdminService.ApplyRetention, `lifemap admin
// retention`): which keyframes of a map's older visits are thinned so that the store stays
// bounded over years of visits (server/engine/retention.h says the rule).
struct RetentionOptions {
  // A keyframe is covered by another (of its own visit or a later one) within this distance
  // (metres) and rotation (degrees) of its pose.
  double cover_m = 0.3;
  double cover_deg = 15.0;
  // The newest visits in the map's frame are never thinned (changes between the two latest
  // and the moved masks against the latest compare whole visits), [1, 1000].
  int keep_recent_visits = 2;
  // A visit with at least this many later visits in the map's frame is compacted: covered at
  // compact_cover_m / compact_cover_deg instead, by its own keyframes too, leaving a sparse set
  // beside its octree and floor plan. [1, 100000].
  int compact_after_visits = 5;
  double compact_cover_m = 1.0;
  double compact_cover_deg = 45.0;
  // A keyframe that one of the map's this many newest visits recognised (its best verified
  // appearance match: its landmarks survived into that visit) is kept; 0: recognition keeps
  // nothing. [0, 1000]. Chosen on building seed 7's 20 visits (RESULTS.md "Issue 36:
  // retention"): 0, 1, 2, 3 gave 2.35, 2.75, 3.20, 3.69x the first visit's bytes and appearance
  // recall 0.805, 0.809, 0.817, 0.826 (0.852 without retention); 1 is the most within 3x.
  int recognised_within_visits = 1;
  // Retention runs for a visit's map after each visit ends (off the reply path); else only
  // when an operator runs it.
  bool after_visit_end = false;

  // InvalidArgument naming the `retention.` key out of range.
  absl::Status Validate() const;
};

struct EngineOptions {
  std::string db_path = "lifemap.db";  // db: the SQLite database, created if missing
  bool synchronous_full = true;        // synchronous: SQLite FULL (power-loss safe) or NORMAL
  int keyframe_batch_max = 32;         // keyframes committed in one transaction at most
  pipeline::PipelineOptions pipeline;  // per-frame outputs (entropy, labels, frames)
  bool labels_enabled = true;          // labels.enabled: label frames when a model is active
  AppearanceOptions appearance;
  PoseGraphOptions pose_graph;
  // How frames sent without a pose are tracked (tracking.downscale; the rest as tuned).
  tracking::OdometryOptions odometry;
  // Paper 002's semantic octree per visit: keyframes' class distributions fused, rendered into
  // every posed frame of the visit (semantic.enabled and the rest of `semantic`).
  bool semantic_enabled = true;
  semantic::SemanticMapOptions semantic;
  int semantic_render_stride = 8;  // semantic.render_stride: fused labels every n-th pixel
  // storage.color_jpeg_quality: keyframe colour sent as PNG or raw is stored as JPEG at this
  // quality, [1, 100] (unless its map keeps originals); JPEG is stored as it came.
  int color_jpeg_quality = 85;
  // frames.max_future_s, frames.max_gap_s: timestamps (seconds since the Unix epoch) more than
  // this ahead of the server's clock, or this far after the previous frame of their visit, are
  // refused before anything is stored.
  double max_future_s = 86400.0;
  double max_gap_s = 7 * 86400.0;
  VisitChangeOptions changes;
  RetentionOptions retention;  // retention: keyframes of older visits thinned

  // InvalidArgument naming the configuration key and its range.
  absl::Status Validate() const;
};

}  // namespace lifemap::server
