#include "server/engine/frame_path.h"

#include <algorithm>
#include <cmath>
#include <functional>
#include <utility>

#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/depth_codec.h"
#include "core/common/image_codec.h"
#include "core/common/task_pool.h"
#include "core/common/utf8.h"
#include "server/engine/appearance.h"
#include "server/engine/clock.h"
#include "server/engine/keyframe_committer.h"
#include "server/engine/pose_graph_worker.h"
#include "server/engine/semantics.h"
#include "server/engine/serial_worker.h"
#include "server/engine/visit_registry.h"

namespace lifemap::server {
namespace {

using Clock = std::chrono::steady_clock;

// Depth of keyframes received as float metres is stored at this scale (0.2 mm steps, up to
// 13.1 m: covers indoor Kinect-class sensors).
constexpr double kStoredDepthScale = 5000.0;

double MsBetween(Clock::time_point a, Clock::time_point b) {
  return std::chrono::duration<double, std::milli>(b - a).count();
}

}  // namespace

Pose AnalysedFrame::T_visit_camera() const {
  return Pose::FromIsometry(T_visit_world.ToIsometry() *
                            analysis->frame.T_world_camera->ToIsometry());
}

ArchitectureWorker::Visit ArchitectureJobVisit(const std::shared_ptr<VisitState>& state,
                                               uint64_t frame_generation) {
  VisitState* v = state.get();
  return {v->visit_id,
          v->map_id,
          [v] {
            absl::MutexLock name_lock(&v->mu);
            return v->map_name;  // read when the plan is stored: renames follow
          },
          &v->architecture,
          state,
          frame_generation};
}

std::function<void(const Pose&, const std::optional<Pose>&)> FollowAnchor(
    std::shared_ptr<VisitState> state, ArchitectureWorker* architecture) {
  return [state = std::move(state), architecture](const Pose& moved_by,
                                                  const std::optional<Pose>& T_map_visit) {
    uint64_t generation = 0;
    {
      absl::MutexLock correction(&state->correction_mu);
      state->world_from_odom =
          Pose::FromIsometry(moved_by.ToIsometry() * state->world_from_odom.ToIsometry());
      state->T_map_visit = T_map_visit;
      generation = ++state->frame_generation;
    }
    // Its stored key frames moved into the map's frame: its floor plan follows them (the key
    // frames folded from now on are placed there; one posed before and queued after this rebuild
    // is not folded, and a later rebuild reads it from the store).
    architecture->SubmitRebuild(ArchitectureJobVisit(state, generation));
  };
}

absl::Status CheckWritable(VisitState* visit, uint64_t writer, std::string* map_name) {
  if (visit == nullptr) return absl::OkStatus();
  absl::MutexLock lock(&visit->mu);
  if (auto s = visit->CheckWritable(writer); !s.ok()) return s;
  *map_name = visit->map_name;
  return absl::OkStatus();
}

FramePath::FramePath(const FramePathParts& parts, const EngineOptions& options)
    : parts_(parts), options_(options) {}

AnalysedFrame FramePath::Refuse(uint64_t sequence, double timestamp_s, const absl::Status& why) {
  AnalysedFrame a;
  a.sequence = sequence;
  a.timestamp_s = timestamp_s;
  a.received = Clock::now();
  a.refused = why;
  frames_rejected_.fetch_add(1);
  spdlog::debug("frame {} rejected: {}", sequence, std::string(why.message()));
  return a;
}

AnalysedFrame FramePath::Analyse(const EncodedRgbdFrame& frame, int64_t map_id,
                                 const std::string& map_name, const FrameSettings& settings) {
  if (const double ahead = frame.timestamp_s - NowSeconds(); ahead > options_.max_future_s) {
    return Refuse(frame.sequence, frame.timestamp_s,
                  absl::InvalidArgumentError(absl::StrFormat(
                      "frame.timestamp_s %.6g is %.3g s ahead of the server's clock "
                      "(frames.max_future_s: %.0f): timestamps are seconds since the Unix "
                      "epoch, not milli- or nanoseconds",
                      frame.timestamp_s, ahead, options_.max_future_s)));
  }
  AnalysedFrame a;
  a.sequence = frame.sequence;
  a.timestamp_s = frame.timestamp_s;
  a.received = Clock::now();
  pipeline::FrameRequest effective = settings.request;
  // The map's own settings (cached); unreadable, the server's defaults apply.
  VisitRegistry::MapSettings map_settings;
  if (map_id != 0) {
    if (auto s = parts_.visits->SettingsOfMap(map_id); s.ok()) map_settings = *s;
  }
  a.keep_original_color = map_settings.keep_original_color;
  // The map's own threshold, when it has one, comes before the server's default.
  if (!effective.entropy_threshold && map_settings.entropy_threshold) {
    effective.entropy_threshold = static_cast<float>(*map_settings.entropy_threshold);
  }
  a.entropy_threshold = effective.entropy_threshold;
  // The model for the visit's map (else the server default) labels the frame; the reference
  // keeps it alive even if it is deactivated meanwhile.
  if (settings.skip_labels) {
    a.labeller = absl::FailedPreconditionError(pipeline::kNotRequested);
  } else if (!options_.labels_enabled) {
    a.labeller = absl::FailedPreconditionError(kLabelsDisabled);
  } else if (auto m = parts_.models->ForMap(map_id); !m.ok()) {
    a.labeller = absl::FailedPreconditionError(
        absl::StrCat("the active model failed: ", m.status().message()));
  } else if (!*m) {
    a.labeller = absl::FailedPreconditionError(absl::StrCat(
        "no model is active for ",
        map_id != 0 ? "map '" + map_name + "'" : std::string("frames without a map"),
        " or as the server default: lifemap models upload FILE NAME; lifemap models activate "
        "NAME"));
  } else {
    a.model = *std::move(m);
    effective.labeller = &a.model->forest;
  }
  auto analysis = parts_.pipeline->Process(frame, effective);
  if (!analysis.ok()) return Refuse(frame.sequence, frame.timestamp_s, analysis.status());
  frames_processed_.fetch_add(1);

  // The frame waits for its turn in the visit holding only what placing it needs: the sent
  // colour bytes only when a keyframe's record would keep them as they came, the per-class
  // probabilities only for frames of a visit with semantic fusion on (a keyframe's are fused).
  // A stream holds up to max_inflight_frames such frames.
  a.color_encoding = frame.color.encoding;
  if (frame.color.encoding == ColorEncoding::kJpeg ||
      (a.keep_original_color && frame.color.encoding == ColorEncoding::kPng)) {
    a.color_as_sent.assign(frame.color.data);
  }
  switch (frame.depth.encoding) {
    case DepthEncoding::kPng16:
    case DepthEncoding::kRawU16:
    case DepthEncoding::kRvl:
    case DepthEncoding::kPaletted:
      a.depth_scale_as_sent = frame.depth.depth_scale;
      break;
    default:
      a.depth_scale_as_sent = 0.0;
  }
  if (analysis->labels && (map_id == 0 || !options_.semantic_enabled)) {
    analysis->labels->probabilities = {};
  }
  const RgbdFrame& f = analysis->frame;
  if (map_id != 0 && (!f.T_world_camera || settings.refine_pose)) {
    // What tracking needs of the frame alone, made here beside other frames' analyses; the
    // visit's tracker then only aligns it, in order.
    a.tracking_input = tracking::PrepareForTracking(f, options_.odometry);
  }
  a.analysis = *std::move(analysis);
  return a;
}

// Builds what the store keeps of a keyframe. Depth: paletted (core/common/depth_codec.h) at the
// client's own scale, so the sensor's values are kept exactly (float metres at
// kStoredDepthScale). Colour: JPEG as it came; PNG and raw re-encoded as JPEG at the configured
// quality, unless the map keeps originals (PNG as it came, raw as PNG).
absl::StatusOr<store::KeyframeRecord> FramePath::MakeKeyframeRecord(AnalysedFrame& a,
                                                                    int64_t visit_id) const {
  const RgbdFrame& decoded = a.analysis->frame;
  store::KeyframeRecord k;
  k.visit_id = visit_id;
  k.sequence = decoded.sequence;
  k.timestamp_s = decoded.timestamp_s;
  k.T_world_camera = decoded.T_world_camera;  // pose_source: set by the caller
  k.intrinsics = decoded.intrinsics;
  k.depth_encoding = store::StoredDepthEncoding::kPaletted;
  k.depth_scale = a.depth_scale_as_sent > 0 ? a.depth_scale_as_sent : kStoredDepthScale;
  auto depth = EncodeDepthPaletted(decoded.depth_m, k.depth_scale);
  if (!depth.ok()) return depth.status();
  k.depth = *std::move(depth);
  if (a.color_encoding == ColorEncoding::kJpeg) {
    k.color = std::move(a.color_as_sent);
    k.color_encoding = store::StoredColorEncoding::kJpeg;
  } else if (a.keep_original_color && a.color_encoding == ColorEncoding::kPng) {
    k.color = std::move(a.color_as_sent);
    k.color_encoding = store::StoredColorEncoding::kPng;
  } else if (a.keep_original_color) {
    auto png = EncodePng(decoded.color_bgr);
    if (!png.ok()) return png.status();
    k.color = *std::move(png);
    k.color_encoding = store::StoredColorEncoding::kPng;
  } else {
    auto jpeg = EncodeJpeg(decoded.color_bgr, options_.color_jpeg_quality);
    if (!jpeg.ok()) return jpeg.status();
    k.color = *std::move(jpeg);
    k.color_encoding = store::StoredColorEncoding::kJpeg;
  }
  return k;
}

absl::Status FramePath::CheckKeyframeLimit(const FrameSettings& settings, int64_t map_id) const {
  if (settings.max_keyframes_per_map <= 0) return absl::OkStatus();
  auto map = parts_.store->GetMapById(map_id);
  if (!map.ok()) return map.status();
  if (map->keyframe_count < settings.max_keyframes_per_map) return absl::OkStatus();
  return absl::ResourceExhaustedError(
      absl::StrCat("map '", map->name, "' holds ", map->keyframe_count, " keyframes and API key '",
                   settings.key_name, "' may add keyframes only up to ",
                   settings.max_keyframes_per_map, " (its max_keyframes_per_map limit)"));
}

// Appearance matches of a frame (paper 000) into the placement: the view's pruned features
// against every stored keyframe but those of its own visit it has only just passed (closer than
// `exclude_recent_s` in time and `exclude_recent_m` along the visit's path). OK with no match
// (nothing recognised); otherwise why it could not be asked. With `loops`, the verified matches
// to earlier keyframes of the same visit are added there too (loop candidates); with `anchors`,
// those to other visits of the visit's map (anchor candidates); with `sighted`, the keyframes of
// another visit of the map that it verified best (its landmarks survived into this visit:
// retention.h).
absl::Status FramePath::AppearanceMatches(
    const absl::StatusOr<pipeline::KeyframeFeatures>& features, const RgbdFrame& f,
    const VisitState& visit, FramePlacement* out, std::vector<LoopCandidate>* loops,
    std::vector<AnchorCandidate>* anchors, std::vector<int64_t>* sighted) const {
  if (!features.ok()) return features.status();
  AppearanceIndex* index = parts_.appearance;
  const double recent_s = index->options().exclude_recent_s;
  const double recent_m = index->options().exclude_recent_m;
  const double t = f.timestamp_s;
  const int64_t visit_id = visit.visit_id;
  auto recognition =
      index->Recognize(features->keypoints, f.intrinsics, [&](const appearance::KeyframeRef& k) {
        if (k.visit_id != visit_id || std::abs(k.timestamp_s - t) >= recent_s) return false;
        const std::optional<double> since = visit.path.SinceKeyframe(k.timestamp_s);
        return !since || *since < recent_m;
      });
  if (!recognition.ok()) return recognition.status();
  const size_t n = std::min(recognition->matches.size(),
                            static_cast<size_t>(index->options().max_frame_matches));
  MapNames names(parts_.store);
  for (size_t i = 0; i < n; ++i) {
    out->place_matches.push_back(AppearancePlaceMatch(recognition->matches[i], &names));
  }
  if (loops != nullptr) {
    for (const auto& m : recognition->matches) {
      if (m.verification.verified && m.keyframe.visit_id == visit_id) {
        loops->push_back(LoopCandidateOf(m));
      }
    }
  }
  if (anchors == nullptr && sighted == nullptr) return absl::OkStatus();
  std::vector<AnchorCandidate> others = AnchorCandidatesOf(*recognition, visit.map_id, visit_id);
  // The best verified one (matches come best first).
  if (sighted != nullptr && !others.empty()) sighted->push_back(others.front().match.keyframe_id);
  if (anchors != nullptr) *anchors = std::move(others);
  return absl::OkStatus();
}

absl::StatusOr<pipeline::KeyframeFeatures> FramePath::QueryFeatures(AnalysedFrame& a,
                                                                    bool entropy_skipped) const {
  if (!a.analysis->entropy && entropy_skipped) {
    pipeline::FrameRequest masks;
    masks.entropy_threshold = a.entropy_threshold;
    parts_.pipeline->ComputeEntropy(&*a.analysis, masks);
  }
  return pipeline::ExtractKeyframeFeatures(*a.analysis, options_.appearance.features);
}

// Relocalisation (issue 15): a frame the tracker lost is matched by appearance against its own
// visit's stored keyframes; the best verified match, as strict as a loop closure
// (`pose_graph.loop_min_inliers`, `loop_max_reprojection_px`), places it in the visit's
// (corrected) frame through the matched keyframe's stored pose. Returns that pose and a line
// saying how, or why not.
absl::StatusOr<std::pair<Pose, std::string>> FramePath::PlaceByAppearance(
    AnalysedFrame& a, const FrameSettings& settings, int64_t visit_id, int64_t map_id) const {
  if (parts_.appearance == nullptr) {
    return absl::FailedPreconditionError("appearance is disabled");
  }
  auto features = QueryFeatures(a, !settings.request.entropy_masks);
  if (!features.ok()) return features.status();
  const RgbdFrame& f = a.analysis->frame;
  auto recognition = parts_.appearance->Recognize(
      features->keypoints, f.intrinsics,
      [visit_id](const appearance::KeyframeRef& k) { return k.visit_id != visit_id; });
  if (!recognition.ok()) return recognition.status();
  for (const auto& m : recognition->matches) {
    const appearance::Verification& v = m.verification;
    const LoopCandidate match{m.keyframe.keyframe_id, v.T_match_query, v.inliers,
                              v.reprojection_px};
    if (!v.verified || !WeakMatchReason(match, options_.pose_graph).empty()) continue;
    auto keyframe = parts_.store->GetKeyframe(map_id, match.keyframe_id);
    if (!keyframe.ok() || !keyframe->T_world_camera) continue;  // deleted since it was indexed
    return std::make_pair(
        Pose::FromIsometry(keyframe->T_world_camera->ToIsometry() *
                           match.T_match_query.ToIsometry()),
        absl::StrFormat("relocalised by a verified appearance match to keyframe %d (%d inliers, "
                        "%.2f px)",
                        match.keyframe_id, match.inliers, match.reprojection_px));
  }
  return absl::NotFoundError("no stored keyframe of the visit matched strictly enough");
}

// The visit's semantic octree rendered into the frame (paper 002's back-projection), into
// `out->fused_labels`; OK when rendered, else why not (for the output's status).
absl::Status FramePath::RenderFusedLabels(const AnalysedFrame& a, const FrameSettings& settings,
                                          VisitState* visit, FramePlacement* out) const {
  if (settings.skip_fusion) return absl::FailedPreconditionError(pipeline::kNotRequested);
  if (!options_.semantic_enabled) {
    return absl::FailedPreconditionError("disabled in this server's config (semantic.enabled)");
  }
  if (!a.labeller.ok()) {
    return absl::FailedPreconditionError(
        absl::StrCat("fused labels need the frame's model: ", a.labeller.message()));
  }
  const RgbdFrame& f = a.analysis->frame;
  if (!f.T_world_camera) {
    return absl::FailedPreconditionError(
        "the frame has no pose (send Frame.pose, or frames the server can track)");
  }
  auto rendered = visit->semantics.Render(a.model->name, f.depth_m, f.intrinsics,
                                          a.T_visit_camera(), options_.semantic_render_stride);
  if (!rendered.ok()) return rendered.status();
  if (rendered->labelled_pixels == 0) {
    return absl::FailedPreconditionError(
        "the visit's octree has no labelled voxel where this frame looks");
  }
  pipeline::FrameLabels& labels = out->fused_labels.emplace();
  labels.labels = std::move(rendered->labels);
  labels.confidence = std::move(rendered->confidence);
  labels.class_pixels = std::move(rendered->class_pixels);
  labels.class_mean_confidence = std::move(rendered->class_mean_confidence);
  labels.labelled_pixels = rendered->labelled_pixels;
  labels.mean_confidence = rendered->mean_confidence;
  labels.stride = rendered->stride;
  return absl::OkStatus();
}

absl::Status FramePath::CompareWithPrevious(const AnalysedFrame& a, const FrameSettings& settings,
                                            VisitState* visit, bool in_map_frame,
                                            FramePlacement* out) const {
  if (settings.skip_moved) return absl::FailedPreconditionError(pipeline::kNotRequested);
  if (!options_.changes.moved_enabled || parts_.previous_loader == nullptr) {
    return absl::FailedPreconditionError(
        "disabled in this server's config (changes.moved_enabled)");
  }
  const RgbdFrame& f = a.analysis->frame;
  if (!f.T_world_camera) {
    return absl::FailedPreconditionError(
        "the frame has no pose (send Frame.pose, or frames the server can track)");
  }
  if (!in_map_frame) {
    return absl::FailedPreconditionError(
        "the visit is tracked and not anchored in the map's frame yet: no earlier visit lines up");
  }
  auto previous =
      visit->previous.Get(parts_.store, parts_.previous_loader, visit->map_id, visit->visit_id,
                          settings.moved_against_visit, options_.changes);
  if (!previous.ok()) return previous.status();
  FrameMoved& moved = out->moved.emplace();
  moved.previous_visit = (*previous)->visit_id;
  moved.threshold_m = options_.changes.moved.threshold_m;
  moved.mask = change::MovedAgainst(f.depth_m, f.intrinsics, *f.T_world_camera,
                                    (*previous)->surface, options_.changes.moved);
  return absl::OkStatus();
}

// Queues a posed, labelled keyframe for fusion into its visit's octree (off the reply path, in
// keyframe order). The probabilities move to the job.
void FramePath::SubmitForFusion(AnalysedFrame& a, const std::shared_ptr<VisitState>& visit) const {
  if (!options_.semantic_enabled || parts_.semantic_worker == nullptr || !a.model ||
      !a.analysis->labels || a.analysis->labels->probabilities.empty()) {
    return;
  }
  const RgbdFrame& f = a.analysis->frame;
  if (!f.T_world_camera) return;
  auto keyframe = std::make_shared<SemanticKeyframe>();
  keyframe->model = a.model->name;
  keyframe->class_count = a.model->forest.class_count();
  keyframe->class_prior = a.model->forest.class_prior();
  keyframe->depth_m = f.depth_m;  // shared, not copied: the frame is not written afterwards
  keyframe->intrinsics = f.intrinsics;
  keyframe->T_visit_camera = a.T_visit_camera();
  keyframe->probabilities = std::move(a.analysis->labels->probabilities);
  parts_.semantic_worker->Submit(
      [visit, keyframe, options = options_.semantic, store = parts_.store] {
        visit->semantics.Fuse(*keyframe, options);
        StoreSemanticSnapshotIfDue(store, visit->visit_id, &visit->semantics,
                                   kSemanticSnapshotKeyframes);
      });
}

FramePlacement FramePath::Place(AnalysedFrame& a, const std::shared_ptr<VisitState>& visit_state,
                                uint64_t writer, const FrameSettings& settings) {
  FramePlacement p;
  if (!a.analysis) return p;
  RgbdFrame& f = a.analysis->frame;
  p.pose_source =
      f.T_world_camera ? store::StoredPoseSource::kClient : store::StoredPoseSource::kNone;
  OutputFacts& facts = p.facts;
  VisitState* visit = visit_state.get();
  facts.has_map = visit != nullptr;
  facts.labeller = a.labeller;
  facts.analysis = &*a.analysis;
  facts.entropy_skipped = !settings.request.entropy_masks;
  facts.labels_skipped = settings.skip_labels;
  if (visit == nullptr) {
    p.pose = f.T_world_camera;
    return p;
  }
  absl::MutexLock placing(&visit->place_mu);
  bool maybe_resent = false;
  const bool server_tracks = !f.T_world_camera || settings.refine_pose;
  // Odometry that jumped is refused before anything of the frame is tracked or stored.
  if (server_tracks && f.odometry) {
    if (auto s = visit->tracker.CheckOdometry(f); !s.ok()) {
      p.refused = std::move(s);
      frames_rejected_.fetch_add(1);
      return p;
    }
  }
  // Before anything of the frame is tracked or stored: a timestamp far after the visit's last
  // frame (ms or ns for s) would become the visit's latest and refuse every frame after it.
  {
    absl::MutexLock lock(&visit->mu);
    if (visit->last_frame_s && f.timestamp_s - *visit->last_frame_s > options_.max_gap_s) {
      p.refused = absl::InvalidArgumentError(absl::StrFormat(
          "frame.timestamp_s %.6f is %.3g s after the previous frame of visit %d (%.6f; "
          "frames.max_gap_s: %.0f): timestamps are seconds since the Unix epoch, not milli- or "
          "nanoseconds; for frames this far apart start a new visit",
          f.timestamp_s, f.timestamp_s - *visit->last_frame_s, visit->visit_id,
          *visit->last_frame_s, options_.max_gap_s));
      frames_rejected_.fetch_add(1);
      return p;  // its analysis is not answered: it belongs to no visit
    }
    maybe_resent = visit->last_frame_s && f.timestamp_s <= *visit->last_frame_s;
    if (!visit->last_frame_s || f.timestamp_s > *visit->last_frame_s) {
      visit->last_frame_s = f.timestamp_s;
    }
  }
  // A frame no newer than the visit's newest may be one resent after its reply was lost (a
  // reconnect, a map move: the client resends what was not acknowledged). If its first copy
  // was stored, it is answered with that keyframe and nothing of it is stored or fused again
  // (issue 52). The store refuses a second copy too (InsertKeyframes), for a resend that
  // reaches it first.
  std::optional<int64_t> resent_as;
  if (maybe_resent) {
    auto before = parts_.store->FindKeyframe(visit->visit_id, f.sequence, f.timestamp_s);
    if (before.ok()) resent_as = *before;
  }
  std::optional<Pose> odometry_pose;  // a tracked frame's pose in the tracker's own frame
  // The visit's frame generation the reported pose is in (VisitState::frame_generation).
  std::optional<uint64_t> pose_generation;
  if (server_tracks) {
    // No client pose (or one to refine): the server tracks the camera (issue 15); the estimate
    // then stands for the pose in keyframe selection, storage and the floor plan. A client pose
    // that cannot be refined is kept as it came.
    const auto track_start = Clock::now();
    FrameTracking& t = p.tracking.emplace();
    tracking::TrackedPose tracked = visit->tracker.Track(f, a.tracking_input, f.T_world_camera);
    if (tracked.state == tracking::TrackingState::kLost && !f.T_world_camera) {
      if (auto placed = PlaceByAppearance(a, settings, visit->visit_id, visit->map_id);
          placed.ok()) {
        Pose T_odom_camera;
        {
          absl::MutexLock correction(&visit->correction_mu);
          T_odom_camera = Pose::FromIsometry(visit->world_from_odom.ToIsometry().inverse() *
                                             placed->first.ToIsometry());
        }
        if (auto relocalised = visit->tracker.Relocalise(T_odom_camera);
            relocalised.T_world_camera) {
          tracked = relocalised;
          t.reason = placed->second;
        }
      }
    }
    odometry_pose = tracked.T_world_camera;
    t.track_ms = MsBetween(track_start, Clock::now());
    t.state = tracked.state;
    t.method = tracked.method;
    t.lost_frames = tracked.lost_frames;
    t.degenerate_axes = tracked.degenerate_axes;
    if (tracked.T_world_camera && f.T_world_camera) {
      // A refined client pose stays in the client's frame: no pose graph moves it.
      p.pose_source = store::StoredPoseSource::kRefined;
      f.T_world_camera = tracked.T_world_camera;
      odometry_pose.reset();
    } else if (tracked.T_world_camera) {
      // Reported in the visit's corrected frame (the latest pose-graph solve, issue 15).
      p.pose_source = store::StoredPoseSource::kEstimated;
      absl::MutexLock correction(&visit->correction_mu);
      f.T_world_camera = Pose::FromIsometry(visit->world_from_odom.ToIsometry() *
                                            tracked.T_world_camera->ToIsometry());
      pose_generation = visit->frame_generation;
      if (visit->T_map_visit) {
        a.T_visit_world = Pose::FromIsometry(visit->T_map_visit->ToIsometry().inverse());
      }
    } else {
      t.reason = tracked.reason;
      facts.tracking_lost_reason = tracked.reason;
    }
    facts.tracked = tracked.state;
  }
  p.pose = f.T_world_camera;
  // The path advances by the tracker's own frame where it tracked (a pose-graph correction
  // moves the reported pose, not the camera), else by the client's pose.
  if (odometry_pose) {
    visit->path.Advance(odometry_pose->translation);
  } else if (f.T_world_camera) {
    visit->path.Advance(f.T_world_camera->translation);
  }
  // Decided under the visit's lock; the keyframe's features and appearance query run outside it
  // (a visit has one writer and its frames come here one at a time, in order).
  bool query_appearance = false;
  tracking::KeyframeDecision& decision = p.keyframe.emplace();
  {
    absl::MutexLock lock(&visit->mu);
    if (auto s = visit->CheckWritable(writer); !s.ok()) {
      p.visit_closed = s;
      return p;
    }
    if (resent_as) {
      decision.selected = true;
      decision.reason = absl::StrCat("resent: stored before as keyframe ", *resent_as,
                                     " (same visit, sequence and timestamp); not stored again");
    } else {
      ++visit->frame_count;
      if (p.tracking && !p.pose) ++visit->lost_frame_count;
      visit->selector.set_options(settings.keyframe);
      decision = visit->selector.Decide(f.timestamp_s, f.T_world_camera);
    }
    query_appearance = decision.selected && !resent_as;
    if (!query_appearance && settings.appearance_interval_s &&
        (!visit->last_appearance_query_s ||
         f.timestamp_s - *visit->last_appearance_query_s >= *settings.appearance_interval_s)) {
      query_appearance = true;
    }
    if (query_appearance) visit->last_appearance_query_s = f.timestamp_s;
  }
  absl::StatusOr<store::KeyframeRecord> record = absl::FailedPreconditionError("not a keyframe");
  absl::StatusOr<pipeline::KeyframeFeatures> features =
      absl::FailedPreconditionError("not extracted");
  // The features and the stored images are independent: two tasks of the pool.
  std::vector<std::function<void()>> tasks;
  if (decision.selected || query_appearance) {
    tasks.push_back([&] { features = QueryFeatures(a, facts.entropy_skipped); });
  }
  const absl::Status keyframe_allowed = decision.selected && !resent_as
                                            ? CheckKeyframeLimit(settings, visit->map_id)
                                            : absl::OkStatus();
  if (!keyframe_allowed.ok()) record = keyframe_allowed;
  if (decision.selected && keyframe_allowed.ok() && !resent_as) {
    tasks.push_back([&] {
      record = MakeKeyframeRecord(a, visit->visit_id);
      if (record.ok()) {
        record->pose_source = p.pose_source;
        record->T_odom_camera = odometry_pose;
        record->odom_segment = visit->odom_segment;
      }
    });
  }
  TaskPool::Shared().RunAll(std::move(tasks));
  if (decision.selected) {
    // Keypoints in zones likely to move were dropped before they are stored for matching
    // (with entropy masks disabled, all are kept: appearance still works, unpruned).
    if (record.ok() && features.ok()) record->features = *features;
    if (!record.ok() && !resent_as) {
      decision.reason = ToValidUtf8(absl::StrCat("not stored: ", record.status().message()));
    }
  }
  // A tracked keyframe's verified matches to earlier keyframes of its visit are loop candidates;
  // its matches to other visits of the map may anchor the visit, or, once it is anchored, tie
  // it to them in its pose graph.
  std::vector<LoopCandidate> loops;
  std::vector<AnchorCandidate> anchors;
  const bool close_loops =
      decision.selected && record.ok() && odometry_pose && options_.pose_graph.enabled;
  if (query_appearance) {
    facts.appearance = AppearanceMatches(
        features, f, *visit, &p, close_loops ? &loops : nullptr, close_loops ? &anchors : nullptr,
        decision.selected && record.ok() ? &record->sighted_keyframes : nullptr);
  }
  absl::MutexLock lock(&visit->mu);
  if (auto s = visit->CheckWritable(writer); !s.ok()) {
    p.visit_closed = s;
    return p;
  }
  if (resent_as) {
    p.resent_as = resent_as;
    std::promise<absl::StatusOr<int64_t>> stored;
    stored.set_value(*resent_as);
    p.commit = stored.get_future().share();
  }
  if (decision.selected && record.ok()) {
    visit->selector.Accept(f.timestamp_s, f.T_world_camera);
    visit->path.MarkKeyframe(f.timestamp_s);
    // Later frames are aligned to this keyframe (a no-op for posed frames and lost ones).
    if (p.pose_source == store::StoredPoseSource::kEstimated ||
        p.pose_source == store::StoredPoseSource::kRefined) {
      visit->tracker.PromoteLastToReference();
    }
    // Submitted under the visit's lock: a visit's keyframes are committed in frame order.
    p.commit = parts_.committer
                   ->Submit(*std::move(record),
                            {visit->visit_id, visit->frame_count, visit->lost_frame_count})
                   .share();
    // An anchored visit's keyframes go to the worker even without candidates: its anchor is
    // re-checked as the visit grows (PoseGraphWorker::RecheckAnchor).
    bool anchored = false;
    if (close_loops) {
      absl::MutexLock correction(&visit_state->correction_mu);
      anchored = visit_state->T_map_visit.has_value();
    }
    if (!loops.empty() || !anchors.empty() || anchored) {
      PoseGraphWorker::Job job;
      job.map_id = visit->map_id;
      job.visit_id = visit->visit_id;
      job.committed = *p.commit;
      job.candidates = std::move(loops);
      job.anchors = std::move(anchors);
      job.on_corrected = [visit_state](const Pose& world_from_odom) {
        absl::MutexLock correction(&visit_state->correction_mu);
        visit_state->world_from_odom = world_from_odom;
      };
      job.on_anchored = FollowAnchor(visit_state, parts_.architecture);
      p.pose_graph_ticket = parts_.pose_graph->Submit(std::move(job));
    }
    if (f.T_world_camera) {
      // Folded, ranked and stored off the reply path, in key-frame order.
      if (!pose_generation) {
        absl::MutexLock correction(&visit_state->correction_mu);
        pose_generation = visit_state->frame_generation;
      }
      p.architecture_ticket =
          parts_.architecture->Submit(ArchitectureJobVisit(visit_state, *pose_generation),
                                      f.depth_m, f.intrinsics, *f.T_world_camera);
    }
  }
  // Rendered from the octree as fused so far (before this keyframe joins it); a keyframe's
  // class distributions then go to the fusion worker.
  facts.fusion = RenderFusedLabels(a, settings, visit, &p);
  if (!facts.fusion.ok()) p.fused_labels.reset();
  {
    bool in_map_frame = p.pose_source != store::StoredPoseSource::kEstimated;
    if (!in_map_frame) {
      absl::MutexLock correction(&visit_state->correction_mu);
      in_map_frame = visit_state->T_map_visit.has_value();
    }
    facts.moved = CompareWithPrevious(a, settings, visit, in_map_frame, &p);
    if (!facts.moved.ok()) p.moved.reset();
  }
  if (decision.selected && p.commit && !resent_as) SubmitForFusion(a, visit_state);
  // Every result carries the visit's ranking by architecture (paper 004) as known now.
  facts.architecture = visit->architecture.Ranking();
  for (const auto& m : facts.architecture->matches) p.place_matches.push_back(m);
  return p;
}

}  // namespace lifemap::server
