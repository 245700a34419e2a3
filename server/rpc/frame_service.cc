#include <algorithm>
#include <chrono>
#include <cmath>
#include <deque>
#include <future>
#include <optional>
#include <thread>

#include <spdlog/spdlog.h>

#include "absl/cleanup/cleanup.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/image_codec.h"
#include "core/common/task_pool.h"
#include "core/common/utf8.h"
#include "core/pipeline/keyframe.h"
#include "server/engine/bounded_queue.h"
#include "server/rpc/convert.h"
#include "server/rpc/services.h"
#include "server/rpc/stream_read.h"
#include "server/rpc/stream_watchdog.h"

namespace lifemap::server {
namespace {

using Clock = std::chrono::steady_clock;

// Depth of keyframes received as float metres is stored at this scale (0.2 mm steps, up to
// 13.1 m: covers indoor Kinect-class sensors).
constexpr double kStoredDepthScale = 5000.0;

double MsBetween(Clock::time_point a, Clock::time_point b) {
  return std::chrono::duration<double, std::milli>(b - a).count();
}

// A frame processed but not yet answered: its result, and the commit it waits for.
struct PendingResult {
  uint64_t architecture_ticket = 0;  // the key frame's job on the ArchitectureWorker, if any
  uint64_t pose_graph_ticket = 0;    // its loop candidates' job on the PoseGraphWorker, if any
  v1::FrameResult result;
  std::optional<std::shared_future<absl::StatusOr<int64_t>>> commit;
  Clock::time_point received;
  // Set when the frame could not be added to its visit (ended, its map deleted, or written by
  // another stream): the call ends with this status and the frame gets no result.
  absl::Status visit_closed;
};

// The answer to a frame refused with `s`: its sequence and timestamp (from `of`) and the error,
// nothing of its analysis (the stream goes on unless the caller ends it).
v1::FrameResult ErrorResult(const v1::FrameResult& of, const absl::Status& s) {
  v1::FrameResult r;
  r.set_sequence(of.sequence());
  r.set_timestamp_s(of.timestamp_s());
  r.mutable_error()->set_code(static_cast<int>(s.code()));
  r.mutable_error()->set_message(ToValidUtf8(s.message()));
  return r;
}

// Builds what the store keeps of a keyframe. Depth: paletted (core/common/depth_codec.h) at the
// client's own scale, so the sensor's values are kept exactly (float metres at
// kStoredDepthScale). Colour: JPEG as it came; PNG and raw re-encoded as JPEG at
// `jpeg_quality`, unless the map keeps originals (PNG as it came, raw as PNG).
absl::StatusOr<store::KeyframeRecord> MakeKeyframeRecord(const v1::Frame& frame,
                                                         const RgbdFrame& decoded, int64_t visit_id,
                                                         bool keep_original_color,
                                                         int jpeg_quality) {
  store::KeyframeRecord k;
  k.visit_id = visit_id;
  k.sequence = decoded.sequence;
  k.timestamp_s = decoded.timestamp_s;
  k.T_world_camera = decoded.T_world_camera;  // pose_source: set by the caller
  k.intrinsics = decoded.intrinsics;
  k.depth_encoding = store::StoredDepthEncoding::kPaletted;
  switch (frame.depth().encoding()) {
    case v1::DEPTH_PNG16:
    case v1::DEPTH_RAW_U16:
    case v1::DEPTH_RVL:
    case v1::DEPTH_PALETTED:
      k.depth_scale = frame.depth().depth_scale();
      break;
    default:
      k.depth_scale = kStoredDepthScale;
  }
  auto depth = EncodeDepthPaletted(decoded.depth_m, k.depth_scale);
  if (!depth.ok()) return depth.status();
  k.depth = *std::move(depth);
  const auto encoding = frame.color().encoding();
  if (encoding == v1::COLOR_JPEG) {
    k.color = frame.color().data();
    k.color_encoding = store::StoredColorEncoding::kJpeg;
  } else if (keep_original_color && encoding == v1::COLOR_PNG) {
    k.color = frame.color().data();
    k.color_encoding = store::StoredColorEncoding::kPng;
  } else if (keep_original_color) {
    auto png = EncodePng(decoded.color_bgr);
    if (!png.ok()) return png.status();
    k.color = *std::move(png);
    k.color_encoding = store::StoredColorEncoding::kPng;
  } else {
    auto jpeg = EncodeJpeg(decoded.color_bgr, jpeg_quality);
    if (!jpeg.ok()) return jpeg.status();
    k.color = *std::move(jpeg);
    k.color_encoding = store::StoredColorEncoding::kJpeg;
  }
  return k;
}

// An 8-bit image as the request asked: into `png` (PNG), `raw` (row-major bytes) or nowhere.
void ResultImageToProto(const cv::Mat& image, v1::ResultImages how, std::string* png,
                        std::string* raw) {
  if (how == v1::RESULT_IMAGES_NONE) return;
  if (how == v1::RESULT_IMAGES_RAW) {
    const cv::Mat continuous = image.isContinuous() ? image : image.clone();
    raw->assign(reinterpret_cast<const char*>(continuous.data), continuous.total());
    return;
  }
  if (auto encoded = EncodePng(image); encoded.ok()) *png = *std::move(encoded);
}

// Fills the entropy output: score image and mask as asked, the per-superjut table.
void EntropyToProto(const entropy::EntropyMaskResult& e, v1::ResultImages images,
                    v1::EntropyOutput* out) {
  out->set_threshold(e.threshold);
  ResultImageToProto(e.score_image, images, out->mutable_score_png(), out->mutable_score_raw());
  ResultImageToProto(e.mask, images, out->mutable_mask_png(), out->mutable_mask_raw());
  for (const auto& s : e.superjuts) SuperjutToProto(s, e.threshold, out->add_superjuts());
}

// Fills the label output: label and confidence images as asked, classes present by pixel share.
void LabelsToProto(const pipeline::FrameLabels& l, const LoadedModel& model,
                   v1::ResultImages images, v1::LabelOutput* out) {
  out->set_model(model.name);
  out->set_stride(static_cast<uint32_t>(l.stride));
  out->set_mean_confidence(static_cast<float>(l.mean_confidence));
  ResultImageToProto(l.labels, images, out->mutable_label_png(), out->mutable_label_raw());
  ResultImageToProto(l.confidence, images, out->mutable_confidence_png(),
                     out->mutable_confidence_raw());
  std::vector<size_t> order;
  for (size_t c = 0; c < l.class_pixels.size(); ++c) {
    if (l.class_pixels[c] > 0) order.push_back(c);
  }
  std::sort(order.begin(), order.end(),
            [&](size_t a, size_t b) { return l.class_pixels[a] > l.class_pixels[b]; });
  for (size_t c : order) {
    auto* f = out->add_classes();
    f->set_class_id(static_cast<uint32_t>(c));
    if (c < model.description.class_names.size()) f->set_name(model.description.class_names[c]);
    f->set_pixel_fraction(static_cast<float>(static_cast<double>(l.class_pixels[c]) /
                                             static_cast<double>(l.labelled_pixels)));
    f->set_mean_confidence(static_cast<float>(l.class_mean_confidence[c]));
  }
}

// What a stream's (or a call's) options ask of each frame.
struct FrameSettings {
  tracking::KeyframeOptions keyframe;
  pipeline::FrameRequest request;
  std::optional<double> appearance_interval_s;  // nullopt: keyframes only
  v1::ResultImages result_images = kDefaultResultImages;
  bool skip_labels = false;  // FrameOptions.skip_outputs; the masks' switch is in `request`
  bool skip_fusion = false;  // no fused labels rendered (the visit's keyframes still fuse)
  bool refine_pose = false;  // FrameOptions.refine_pose: client poses refined by the tracker
  // The caller's key: a keyframe is not stored once its map holds this many (0: no limit).
  std::string key_name;
  int64_t max_keyframes_per_map = 0;
};

// RESOURCE_EXHAUSTED when the caller's key limits the keyframes of a map and `map_id` holds
// that many (stored; the few still being committed are not counted).
absl::Status CheckKeyframeLimit(ServiceContext* ctx, const FrameSettings& settings,
                                int64_t map_id) {
  if (settings.max_keyframes_per_map <= 0) return absl::OkStatus();
  auto map = ctx->store->GetMapById(map_id);
  if (!map.ok()) return map.status();
  if (map->keyframe_count < settings.max_keyframes_per_map) return absl::OkStatus();
  return absl::ResourceExhaustedError(
      absl::StrCat("map '", map->name, "' holds ", map->keyframe_count, " keyframes and API key '",
                   settings.key_name, "' may add keyframes only up to ",
                   settings.max_keyframes_per_map, " (its max_keyframes_per_map limit)"));
}

// Appearance matches of a frame (paper 000) into the result: the view's pruned features against
// every stored keyframe but those of its own visit it has only just passed (closer than
// `exclude_recent_s` in time and `exclude_recent_m` along `path`). OK with no match (nothing
// recognised); otherwise why it could not be asked. With `loops`, the verified matches to earlier
// keyframes of the same visit are added there too (loop candidates, issue 15); with `anchors`,
// those to other visits of map `map_id` (anchor candidates).
absl::Status AppearanceMatches(ServiceContext* ctx,
                               const absl::StatusOr<pipeline::KeyframeFeatures>& features,
                               const RgbdFrame& f, int64_t visit_id, const VisitPath& path,
                               v1::FrameResult* r, std::vector<LoopCandidate>* loops,
                               std::vector<AnchorCandidate>* anchors, int64_t map_id) {
  if (!features.ok()) return features.status();
  const double recent_s = ctx->appearance->options().exclude_recent_s;
  const double recent_m = ctx->appearance->options().exclude_recent_m;
  const double t = f.timestamp_s;
  auto recognition = ctx->appearance->Recognize(
      features->keypoints, f.intrinsics, [&](const appearance::KeyframeRef& k) {
        if (k.visit_id != visit_id || std::abs(k.timestamp_s - t) >= recent_s) return false;
        const std::optional<double> since = path.SinceKeyframe(k.timestamp_s);
        return !since || *since < recent_m;
      });
  if (!recognition.ok()) return recognition.status();
  const size_t n = std::min(recognition->matches.size(),
                            static_cast<size_t>(ctx->appearance->options().max_frame_matches));
  MapNames names(ctx->store);
  for (size_t i = 0; i < n; ++i) {
    PlaceMatchToProto(AppearancePlaceMatch(recognition->matches[i], &names),
                      r->add_place_matches());
  }
  for (const auto& m : recognition->matches) {
    if (!m.verification.verified) continue;
    const LoopCandidate c{m.keyframe.keyframe_id, m.verification.T_match_query,
                          m.verification.inliers, m.verification.reprojection_px};
    if (loops != nullptr && m.keyframe.visit_id == visit_id) loops->push_back(c);
    if (anchors != nullptr && m.keyframe.visit_id != visit_id && m.keyframe.map_id == map_id) {
      anchors->push_back({m.keyframe.visit_id, c});
    }
  }
  return absl::OkStatus();
}

// A frame analysed but not yet placed in its visit: the part of a frame's work that needs no
// visit state, run on the task pool, several frames of a stream at once.
struct AnalysedFrame {
  v1::Frame frame;  // as received: a keyframe's record keeps its bytes
  PendingResult pending;
  // Unset when the frame was rejected (pending.result.error says why).
  std::optional<pipeline::FrameAnalysis> analysis;
  std::shared_ptr<const LoadedModel> model;  // keeps the labelling model alive
  absl::Status labeller;                     // OK when the model labelled it; else why not
  bool keep_original_color = false;          // the map's setting, for a keyframe's record
  std::optional<float> entropy_threshold;    // the threshold in effect (request, map, server)
  // A frame of a visit sent without a pose, prepared for the visit's tracker (issue 15).
  std::shared_ptr<tracking::TrackingInput> tracking_input;
  // Brings the frame's pose into its visit's own frame (where the visit's semantic octree is):
  // identity, except for a tracked pose reported in the map's frame after the visit was
  // anchored during this run (then T_map_visit⁻¹).
  Pose T_visit_world;

  // The frame's camera in its visit's own frame (its pose must be set).
  Pose T_visit_camera() const {
    return Pose::FromIsometry(T_visit_world.ToIsometry() *
                              analysis->frame.T_world_camera->ToIsometry());
  }
};

// Reads the visit's writability and map name (a unary frame has neither to check).
// The visit as the architecture worker needs it (kept alive by its jobs).
ArchitectureWorker::Visit ArchitectureJobVisit(const std::shared_ptr<VisitState>& state) {
  VisitState* v = state.get();
  return {v->visit_id, v->map_id,
          [v] {
            absl::MutexLock name_lock(&v->mu);
            return v->map_name;  // read when the plan is stored: renames follow
          },
          &v->architecture, state};
}

absl::Status CheckWritable(VisitState* visit, uint64_t writer, std::string* map_name) {
  if (visit == nullptr) return absl::OkStatus();
  absl::MutexLock lock(&visit->mu);
  if (auto s = visit->CheckWritable(writer); !s.ok()) return s;
  *map_name = visit->map_name;
  return absl::OkStatus();
}

// Decodes and analyses one frame (masks, labels, result images) with its map's settings and
// model. Reads no visit state but the map: safe on any thread, in any order.
// `refused`: not OK when the frame is refused before any work (the key's frame rate).
AnalysedFrame AnalyseFrame(ServiceContext* ctx, v1::Frame frame, int64_t map_id,
                           const std::string& map_name, const FrameSettings& settings,
                           const absl::Status& refused = absl::OkStatus()) {
  AnalysedFrame a;
  a.frame = std::move(frame);
  PendingResult& p = a.pending;
  p.received = Clock::now();
  v1::FrameResult& r = p.result;
  r.set_sequence(a.frame.sequence());
  r.set_timestamp_s(a.frame.timestamp_s());
  auto reject = [&](const absl::Status& s) {
    ctx->frames_rejected.fetch_add(1);
    r = ErrorResult(r, s);
    spdlog::debug("frame {} rejected: {}", a.frame.sequence(), std::string(s.message()));
    return std::move(a);
  };
  if (!refused.ok()) return reject(refused);
  if (const double ahead = a.frame.timestamp_s() - NowSeconds();
      ahead > ctx->config.frame_max_future_s) {
    return reject(absl::InvalidArgumentError(absl::StrFormat(
        "frame.timestamp_s %.6g is %.3g s ahead of the server's clock (frames.max_future_s: "
        "%.0f): timestamps are seconds since the Unix epoch, not milli- or nanoseconds",
        a.frame.timestamp_s(), ahead, ctx->config.frame_max_future_s)));
  }
  auto encoded = FrameFromProto(a.frame);
  if (!encoded.ok()) return reject(encoded.status());
  pipeline::FrameRequest effective = settings.request;
  // The map's own settings (cached); unreadable, the server's defaults apply.
  VisitRegistry::MapSettings map_settings;
  if (map_id != 0) {
    if (auto s = ctx->visits->SettingsOfMap(map_id); s.ok()) map_settings = *s;
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
    a.labeller = absl::FailedPreconditionError(kNotRequested);
  } else if (!ctx->config.labels_enabled) {
    a.labeller = absl::FailedPreconditionError(kLabelsDisabled);
  } else if (auto m = ctx->models->ForMap(map_id); !m.ok()) {
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
  auto analysis = ctx->pipeline->Process(*encoded, effective);
  if (!analysis.ok()) return reject(analysis.status());
  ctx->frames_processed.fetch_add(1);

  const RgbdFrame& f = analysis->frame;
  r.set_width(static_cast<uint32_t>(f.intrinsics.width));
  r.set_height(static_cast<uint32_t>(f.intrinsics.height));
  r.set_valid_depth_fraction(analysis->depth_stats.valid_fraction);
  r.set_median_depth_m(analysis->depth_stats.median_m);
  if (f.T_world_camera) {
    r.set_pose_source(v1::POSE_SOURCE_CLIENT);
    PoseToProto(*f.T_world_camera, r.mutable_pose());
  } else {
    r.set_pose_source(v1::POSE_SOURCE_NONE);
  }
  if (analysis->entropy) {
    EntropyToProto(*analysis->entropy, settings.result_images, r.mutable_entropy());
  }
  if (analysis->labels) {
    LabelsToProto(*analysis->labels, *a.model, settings.result_images, r.mutable_labels());
  }
  r.mutable_timing()->set_decode_ms(analysis->decode_ms);
  r.mutable_timing()->set_process_ms(analysis->process_ms);
  // The frame waits for its turn in the visit holding only what placing it needs: the sent
  // depth bytes never (the record encodes the decoded depth), the sent colour bytes only when a
  // keyframe's record would keep them as they came, the per-class probabilities only for
  // frames of a visit with semantic fusion on (a keyframe's are fused). A stream holds up to
  // max_inflight_frames such frames.
  // (Swapped with an empty string: clearing keeps the capacity.)
  std::string().swap(*a.frame.mutable_depth()->mutable_data());
  const auto color_encoding = a.frame.color().encoding();
  if (!(color_encoding == v1::COLOR_JPEG ||
        (a.keep_original_color && color_encoding == v1::COLOR_PNG))) {
    std::string().swap(*a.frame.mutable_color()->mutable_data());
  }
  if (analysis->labels && (map_id == 0 || !ctx->config.semantic_enabled)) {
    analysis->labels->probabilities = {};
  }
  if (map_id != 0 && (!f.T_world_camera || settings.refine_pose)) {
    // What tracking needs of the frame alone, made here beside other frames' analyses; the
    // visit's tracker then only aligns it, in order.
    a.tracking_input = tracking::PrepareForTracking(f, tracking::OdometryOptions{});
  }
  a.analysis = *std::move(analysis);
  return a;
}

// The frame's appearance features (ORB, pruned by its entropy masks: a client that skipped the
// masks still gets features pruned by them, not reported).
absl::StatusOr<pipeline::KeyframeFeatures> QueryFeatures(ServiceContext* ctx, AnalysedFrame& a,
                                                         bool entropy_skipped) {
  if (!a.analysis->entropy && entropy_skipped) {
    pipeline::FrameRequest masks;
    masks.entropy_threshold = a.entropy_threshold;
    ctx->pipeline->ComputeEntropy(&*a.analysis, masks);
  }
  return pipeline::ExtractKeyframeFeatures(*a.analysis, ctx->config.appearance.features);
}

// Relocalisation (issue 15): a frame the tracker lost is matched by appearance against its own
// visit's stored keyframes; the best verified match, as strict as a loop closure
// (`pose_graph.loop_min_inliers`, `loop_max_reprojection_px`), places it in the visit's
// (corrected) frame through the matched keyframe's stored pose. Returns that pose and a line
// saying how, or why not.
absl::StatusOr<std::pair<Pose, std::string>> PlaceByAppearance(ServiceContext* ctx,
                                                               AnalysedFrame& a,
                                                               const FrameSettings& settings,
                                                               int64_t map_id, int64_t visit_id) {
  if (ctx->appearance == nullptr) return absl::FailedPreconditionError("appearance is disabled");
  auto features = QueryFeatures(ctx, a, !settings.request.entropy_masks);
  if (!features.ok()) return features.status();
  const RgbdFrame& f = a.analysis->frame;
  auto recognition = ctx->appearance->Recognize(
      features->keypoints, f.intrinsics,
      [visit_id](const appearance::KeyframeRef& k) { return k.visit_id != visit_id; });
  if (!recognition.ok()) return recognition.status();
  for (const auto& m : recognition->matches) {
    const appearance::Verification& v = m.verification;
    const LoopCandidate match{m.keyframe.keyframe_id, v.T_match_query, v.inliers,
                              v.reprojection_px};
    if (!v.verified || !WeakMatchReason(match, ctx->config.pose_graph).empty()) continue;
    auto keyframe = ctx->store->GetKeyframe(map_id, match.keyframe_id);
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
// `out`; OK when rendered, else why not (for the output's status).
absl::Status RenderFusedLabels(ServiceContext* ctx, const AnalysedFrame& a,
                               const FrameSettings& settings, VisitState* visit,
                               v1::LabelOutput* out) {
  if (settings.skip_fusion) return absl::FailedPreconditionError(kNotRequested);
  if (!ctx->config.semantic_enabled) {
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
                                          a.T_visit_camera(), ctx->config.semantic_render_stride);
  if (!rendered.ok()) return rendered.status();
  if (rendered->labelled_pixels == 0) {
    return absl::FailedPreconditionError(
        "the visit's octree has no labelled voxel where this frame looks");
  }
  pipeline::FrameLabels labels;
  labels.labels = std::move(rendered->labels);
  labels.confidence = std::move(rendered->confidence);
  labels.class_pixels = std::move(rendered->class_pixels);
  labels.class_mean_confidence = std::move(rendered->class_mean_confidence);
  labels.labelled_pixels = rendered->labelled_pixels;
  labels.mean_confidence = rendered->mean_confidence;
  labels.stride = rendered->stride;
  LabelsToProto(labels, *a.model, settings.result_images, out);
  return absl::OkStatus();
}

// Queues a posed, labelled keyframe for fusion into its visit's octree (off the reply path, in
// keyframe order). The probabilities move to the job.
void SubmitForFusion(ServiceContext* ctx, AnalysedFrame& a,
                     const std::shared_ptr<VisitState>& visit_state) {
  if (!ctx->config.semantic_enabled || ctx->semantic_worker == nullptr || !a.model ||
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
  ctx->semantic_worker->Submit(
      [visit_state, keyframe, options = ctx->config.semantic, store = ctx->store] {
        visit_state->semantics.Fuse(*keyframe, options);
        StoreSemanticSnapshotIfDue(store, visit_state->visit_id, &visit_state->semantics,
                                   kSemanticSnapshotKeyframes);
      });
}

// Places an analysed frame in its visit, in the visit's frame order: the keyframe decision, the
// keyframe's features, record and appearance query, the commit and the floor-plan fold, and
// the output statuses. `writer` is the stream's claim on the visit (0 for a unary
// ProcessFrame). A rejected frame passes through untouched.
PendingResult PlaceInVisit(ServiceContext* ctx, AnalysedFrame a,
                           const std::shared_ptr<VisitState>& visit_state, uint64_t writer,
                           const FrameSettings& settings) {
  PendingResult p = std::move(a.pending);
  if (!a.analysis) return p;
  v1::FrameResult& r = p.result;
  VisitState* visit = visit_state.get();
  OutputFacts facts;
  facts.has_map = visit != nullptr;
  facts.labeller = a.labeller;
  facts.analysis = &*a.analysis;
  facts.entropy_skipped = !settings.request.entropy_masks;
  facts.labels_skipped = settings.skip_labels;
  if (visit == nullptr) {
    FillOutputStatuses(ctx->pipeline->options(), facts, r.mutable_outputs());
    return p;
  }
  absl::MutexLock placing(&visit->place_mu);
  RgbdFrame& f = a.analysis->frame;
  // Before anything of the frame is tracked or stored: a timestamp far after the visit's last
  // frame (ms or ns for s) would become the visit's latest and refuse every frame after it.
  {
    absl::MutexLock lock(&visit->mu);
    if (visit->last_frame_s && f.timestamp_s - *visit->last_frame_s > ctx->config.frame_max_gap_s) {
      const absl::Status s = absl::InvalidArgumentError(absl::StrFormat(
          "frame.timestamp_s %.6f is %.3g s after the previous frame of visit %d (%.6f; "
          "frames.max_gap_s: %.0f): timestamps are seconds since the Unix epoch, not milli- or "
          "nanoseconds; for frames this far apart start a new visit",
          f.timestamp_s, f.timestamp_s - *visit->last_frame_s, visit->visit_id,
          *visit->last_frame_s, ctx->config.frame_max_gap_s));
      ctx->frames_rejected.fetch_add(1);
      r = ErrorResult(r, s);  // its analysis is not answered: it belongs to no visit
      return p;
    }
    if (!visit->last_frame_s || f.timestamp_s > *visit->last_frame_s) {
      visit->last_frame_s = f.timestamp_s;
    }
  }
  std::optional<Pose> odometry_pose;  // a tracked frame's pose in the tracker's own frame
  if (!f.T_world_camera || settings.refine_pose) {
    // No client pose (or one to refine): the server tracks the camera (issue 15); the estimate
    // then stands for the pose in keyframe selection, storage and the floor plan. A client pose
    // that cannot be refined is kept as it came.
    const auto track_start = Clock::now();
    tracking::TrackedPose tracked = visit->tracker.Track(f, a.tracking_input, f.T_world_camera);
    if (tracked.state == tracking::TrackingState::kLost && !f.T_world_camera) {
      if (auto placed = PlaceByAppearance(ctx, a, settings, visit->map_id, visit->visit_id);
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
          r.mutable_tracking()->set_reason(placed->second);
        }
      }
    }
    odometry_pose = tracked.T_world_camera;
    auto* t = r.mutable_tracking();
    t->set_track_ms(MsBetween(track_start, Clock::now()));
    t->set_state(TrackingStateToProto(tracked.state));
    t->set_method(TrackingMethodToProto(tracked.method));
    t->set_lost_frames(static_cast<uint32_t>(tracked.lost_frames));
    if (tracked.T_world_camera && f.T_world_camera) {
      // A refined client pose stays in the client's frame: no pose graph moves it.
      r.set_pose_source(v1::POSE_SOURCE_REFINED);
      f.T_world_camera = tracked.T_world_camera;
      odometry_pose.reset();
      PoseToProto(*f.T_world_camera, r.mutable_pose());
    } else if (tracked.T_world_camera) {
      // Reported in the visit's corrected frame (the latest pose-graph solve, issue 15).
      r.set_pose_source(v1::POSE_SOURCE_ESTIMATED);
      absl::MutexLock correction(&visit->correction_mu);
      f.T_world_camera = Pose::FromIsometry(visit->world_from_odom.ToIsometry() *
                                            tracked.T_world_camera->ToIsometry());
      if (visit->T_map_visit) {
        a.T_visit_world = Pose::FromIsometry(visit->T_map_visit->ToIsometry().inverse());
      }
      PoseToProto(*f.T_world_camera, r.mutable_pose());
    } else {
      t->set_reason(tracked.reason);
      facts.tracking_lost_reason = tracked.reason;
    }
    facts.tracked = tracked.state;
  }
  // The path advances by the tracker's own frame where it tracked (a pose-graph correction
  // moves the reported pose, not the camera), else by the client's pose.
  if (odometry_pose) {
    visit->path.Advance(odometry_pose->translation);
  } else if (f.T_world_camera) {
    visit->path.Advance(f.T_world_camera->translation);
  }
  const store::StoredPoseSource pose_source = StoredPoseSourceFromProto(r.pose_source());
  // Decided under the visit's lock; the keyframe's features and appearance query run outside it
  // (a visit has one writer and its frames come here one at a time, in order).
  tracking::KeyframeDecision decision;
  bool query_appearance = false;
  {
    absl::MutexLock lock(&visit->mu);
    if (auto s = visit->CheckWritable(writer); !s.ok()) {
      p.visit_closed = s;
      return p;
    }
    ++visit->frame_count;
    visit->selector.set_options(settings.keyframe);
    decision = visit->selector.Decide(f.timestamp_s, f.T_world_camera);
    query_appearance = decision.selected;
    if (!query_appearance && settings.appearance_interval_s &&
        (!visit->last_appearance_query_s ||
         f.timestamp_s - *visit->last_appearance_query_s >= *settings.appearance_interval_s)) {
      query_appearance = true;
    }
    if (query_appearance) visit->last_appearance_query_s = f.timestamp_s;
  }
  r.mutable_keyframe()->set_selected(decision.selected);
  r.mutable_keyframe()->set_reason(decision.reason);
  absl::StatusOr<store::KeyframeRecord> record = absl::FailedPreconditionError("not a keyframe");
  absl::StatusOr<pipeline::KeyframeFeatures> features =
      absl::FailedPreconditionError("not extracted");
  // The features and the stored images are independent: two tasks of the pool.
  std::vector<std::function<void()>> tasks;
  if (decision.selected || query_appearance) {
    tasks.push_back([&] { features = QueryFeatures(ctx, a, facts.entropy_skipped); });
  }
  const absl::Status keyframe_allowed =
      decision.selected ? CheckKeyframeLimit(ctx, settings, visit->map_id) : absl::OkStatus();
  if (!keyframe_allowed.ok()) record = keyframe_allowed;
  if (decision.selected && keyframe_allowed.ok()) {
    tasks.push_back([&] {
      record = MakeKeyframeRecord(a.frame, f, visit->visit_id, a.keep_original_color,
                                  ctx->config.keyframe_color_jpeg_quality);
      if (record.ok()) {
        record->pose_source = pose_source;
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
    if (!record.ok()) {
      r.mutable_keyframe()->set_reason(
          ToValidUtf8(absl::StrCat("not stored: ", record.status().message())));
    }
  }
  // A tracked keyframe's verified matches to earlier keyframes of its visit are loop candidates;
  // its matches to other visits of the map may anchor the visit, or, once it is anchored, tie
  // it to them in its pose graph.
  std::vector<LoopCandidate> loops;
  std::vector<AnchorCandidate> anchors;
  const bool close_loops =
      decision.selected && record.ok() && odometry_pose && ctx->config.pose_graph.enabled;
  if (query_appearance) {
    facts.appearance = AppearanceMatches(ctx, features, f, visit->visit_id, visit->path, &r,
                                         close_loops ? &loops : nullptr,
                                         close_loops ? &anchors : nullptr, visit->map_id);
  }
  absl::MutexLock lock(&visit->mu);
  if (auto s = visit->CheckWritable(writer); !s.ok()) {
    p.visit_closed = s;
    return p;
  }
  if (decision.selected && record.ok()) {
    visit->selector.Accept(f.timestamp_s, f.T_world_camera);
    visit->path.MarkKeyframe(f.timestamp_s);
    // Later frames are aligned to this keyframe (a no-op for posed frames and lost ones).
    if (r.pose_source() == v1::POSE_SOURCE_ESTIMATED ||
        r.pose_source() == v1::POSE_SOURCE_REFINED) {
      visit->tracker.PromoteLastToReference();
    }
    // Submitted under the visit's lock: a visit's keyframes are committed in frame order.
    p.commit =
        ctx->committer->Submit(*std::move(record), {visit->visit_id, visit->frame_count}).share();
    if (!loops.empty() || !anchors.empty()) {
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
      job.on_anchored = [visit_state, architecture = ctx->architecture](const Pose& T_map_visit) {
        {
          absl::MutexLock correction(&visit_state->correction_mu);
          visit_state->world_from_odom = Pose::FromIsometry(
              T_map_visit.ToIsometry() * visit_state->world_from_odom.ToIsometry());
          visit_state->T_map_visit = T_map_visit;
        }
        // Its stored key frames moved into the map's frame: its floor plan follows them (the
        // key frames folded from now on are placed there).
        architecture->SubmitRebuild(ArchitectureJobVisit(visit_state));
      };
      p.pose_graph_ticket = ctx->pose_graph->Submit(std::move(job));
    }
    if (f.T_world_camera) {
      // Folded, ranked and stored off the reply path, in key-frame order.
      p.architecture_ticket = ctx->architecture->Submit(ArchitectureJobVisit(visit_state),
                                                        f.depth_m, f.intrinsics, *f.T_world_camera);
    }
  }
  // Rendered from the octree as fused so far (before this keyframe joins it); a keyframe's
  // class distributions then go to the fusion worker.
  facts.fusion = RenderFusedLabels(ctx, a, settings, visit, r.mutable_fused_labels());
  if (!facts.fusion.ok()) r.clear_fused_labels();
  if (decision.selected && p.commit) SubmitForFusion(ctx, a, visit_state);
  // Every result carries the visit's ranking by architecture (paper 004) as known now.
  facts.architecture = visit->architecture.Ranking();
  for (const auto& m : facts.architecture->matches) PlaceMatchToProto(m, r.add_place_matches());
  FillOutputStatuses(ctx->pipeline->options(), facts, r.mutable_outputs());
  return p;
}

// Waits for the keyframe commit (if any) and completes the result: a keyframe is reported as
// committed only once the store has it.
void FinishResult(PendingResult* p) {
  auto* timing = p->result.mutable_timing();
  if (p->commit) {
    const auto wait_start = Clock::now();
    const absl::StatusOr<int64_t>& id = p->commit->get();
    timing->set_commit_wait_ms(MsBetween(wait_start, Clock::now()));
    auto* kf = p->result.mutable_keyframe();
    if (id.ok()) {
      kf->set_committed(true);
      kf->set_keyframe_id(static_cast<uint64_t>(*id));
    } else {
      kf->set_committed(false);
      kf->set_reason(ToValidUtf8(absl::StrCat("not stored: ", id.status().message())));
    }
  }
  timing->set_total_ms(MsBetween(p->received, Clock::now()));
}

// What a request's options ask, over the server's defaults. InvalidArgument for out-of-range
// values, naming the field.
absl::StatusOr<FrameSettings> FrameSettingsFromProto(const v1::FrameOptions& o,
                                                     const ServerConfig& config) {
  FrameSettings settings;
  auto keyframe = KeyframeOptionsFromProto(o, config.keyframe);
  if (!keyframe.ok()) return keyframe.status();
  settings.keyframe = *keyframe;
  auto threshold = EntropyThresholdFromProto(o.entropy_threshold(), "options.entropy_threshold");
  if (!threshold.ok()) return threshold.status();
  if (*threshold) settings.request.entropy_threshold = static_cast<float>(**threshold);
  settings.appearance_interval_s = config.appearance.frame_interval_s;
  if (o.has_appearance_interval_s()) {
    const double t = o.appearance_interval_s();
    if (!(t >= 0 && t <= AppearanceOptions::kMaxFrameIntervalS)) {
      return absl::InvalidArgumentError(
          absl::StrCat("options.appearance_interval_s must be within [0, ",
                       AppearanceOptions::kMaxFrameIntervalS, "] s (0 = every frame), got ", t));
    }
    settings.appearance_interval_s = t;
  }
  for (const int output : o.skip_outputs()) {
    if (output == v1::FRAME_OUTPUT_ENTROPY_MASK) {
      settings.request.entropy_masks = false;
    } else if (output == v1::FRAME_OUTPUT_CLASS_LABELS) {
      settings.skip_labels = true;
    } else if (output == v1::FRAME_OUTPUT_SEMANTIC_FUSION) {
      settings.skip_fusion = true;
    } else {
      return absl::InvalidArgumentError(absl::StrCat(
          "options.skip_outputs: ",
          v1::FrameOutput_IsValid(output) ? v1::FrameOutput_Name(output) : std::to_string(output),
          " cannot be skipped; only FRAME_OUTPUT_ENTROPY_MASK, FRAME_OUTPUT_CLASS_LABELS and "
          "FRAME_OUTPUT_SEMANTIC_FUSION can"));
    }
  }
  settings.refine_pose = o.refine_pose();
  switch (o.result_images()) {
    case v1::RESULT_IMAGES_DEFAULT:
      break;
    case v1::RESULT_IMAGES_PNG:
    case v1::RESULT_IMAGES_RAW:
    case v1::RESULT_IMAGES_NONE:
      settings.result_images = o.result_images();
      break;
    default:
      return absl::InvalidArgumentError(
          absl::StrCat("options.result_images ", o.result_images(),
                       " is not one of RESULT_IMAGES_PNG, RESULT_IMAGES_RAW, RESULT_IMAGES_NONE"));
  }
  return settings;
}

// Resolves the visit a stream or call writes to. visit_id 0: a new visit (or, with
// `reuse_open`, the map's latest open visit).
absl::StatusOr<store::VisitRecord> ResolveVisit(ServiceContext* ctx, const Principal& caller,
                                                const std::string& map, uint64_t visit_id,
                                                const std::string& robot, const std::string& label,
                                                bool reuse_open, bool* created) {
  *created = false;
  if (auto s = store::ValidateMapName(map); !s.ok()) return s;
  if (robot.size() > 256 || label.size() > 256) {
    return absl::InvalidArgumentError("robot and visit label must be at most 256 bytes");
  }
  auto m = ctx->store->GetMap(map);
  if (!m.ok()) return m.status();
  if (visit_id == 0) {
    if (reuse_open) {
      auto open = ctx->store->LatestOpenVisit(map);
      if (!open.ok()) return open.status();
      if (*open) return **open;
    }
    if (auto s = caller.TakeVisit(ctx->config.max_visits_per_key_per_hour); !s.ok()) return s;
    *created = true;
    return ctx->store->StartVisit(map, robot, label, NowSeconds());
  }
  const auto id = IdFromProto(visit_id, "visit_id");
  if (!id.ok()) return id.status();
  auto v = ctx->store->GetVisit(*id);
  if (!v.ok()) return v.status();
  if (v->map_id != m->id) {
    // The other map is not named: a key limited to some maps must learn nothing of others.
    return absl::NotFoundError(
        absl::StrCat("map '", map, "' has no visit ", visit_id, " (ListVisits names its visits)"));
  }
  if (v->ended) {
    return absl::FailedPreconditionError(
        absl::StrCat("visit ", visit_id, " has ended; start a new visit (visit_id 0)"));
  }
  return v;
}

}  // namespace

grpc::Status FrameServiceImpl::StreamFrames(
    grpc::ServerContext* context,
    grpc::ServerReaderWriter<v1::StreamFramesResponse, v1::StreamFramesRequest>* stream) {
  auto caller = ctx_->keys->Authorize(*context, "FrameService/StreamFrames");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  // A stream that goes quiet is ended by the watchdog (stream_start_timeout_s for its first
  // message, stream_idle_timeout_s for each one after).
  const auto watch = ctx_->stream_watchdog->Start(context);
  const auto read = [&](v1::StreamFramesRequest* message, double timeout_s) {
    watch->Waiting(timeout_s);
    const ReadOutcome got = ReadMessage(stream, message);
    watch->Received();
    return got;
  };

  v1::StreamFramesRequest request;
  const ReadOutcome first = read(&request, ctx_->config.stream_start_timeout_s);
  if (first == ReadOutcome::kUnparsable) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        "the stream's first message (StreamStart) could not be parsed: most often "
                        "a string (map, robot, visit_label) holds bytes that are not valid UTF-8; "
                        "send UTF-8 text");
  }
  if (first == ReadOutcome::kEnd) {
    if (watch->timed_out()) {
      return grpc::Status(
          grpc::StatusCode::DEADLINE_EXCEEDED,
          absl::StrCat("no StreamStart within ", ctx_->config.stream_start_timeout_s,
                       " s of opening the stream (stream_start_timeout_s)"));
    }
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        "stream closed before its StreamStart message");
  }
  if (!request.has_start()) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        "the first message of a stream must be StreamStart (map, visit)");
  }
  const v1::StreamStart start = request.start();
  if (auto m = FindCallersMap(ctx_->store, *caller, start.map()); !m.ok()) {
    return ToGrpcStatus(m.status());
  }
  // The slots are taken once the stream said what it is for: a client that opens streams and
  // sends nothing holds none (and the watchdog ends those).
  if (auto s = caller->OpenStream(ctx_->config.max_streams_per_key); !s.ok()) {
    return ToGrpcStatus(s);
  }
  absl::Cleanup close_stream = [&caller] { caller->CloseStream(); };
  if (ctx_->active_streams.fetch_add(1) >= ctx_->config.max_streams) {
    ctx_->active_streams.fetch_sub(1);
    return grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED,
                        absl::StrCat("this server already serves ", ctx_->config.max_streams,
                                     " streams (max_streams); retry later"));
  }
  absl::Cleanup release = [this] { ctx_->active_streams.fetch_sub(1); };
  auto settings = FrameSettingsFromProto(start.options(), ctx_->config);
  if (!settings.ok()) return ToGrpcStatus(settings.status());
  settings->key_name = caller->key_name;
  settings->max_keyframes_per_map = caller->limits.max_keyframes_per_map;
  bool created = false;
  auto visit = ResolveVisit(ctx_, *caller, start.map(), start.visit_id(), start.robot(),
                            start.visit_label(), false, &created);
  if (!visit.ok()) return ToGrpcStatus(visit.status());
  auto state = ctx_->visits->Get(visit->id);
  if (!state.ok()) return ToGrpcStatus(state.status());
  auto claim = ctx_->visits->ClaimWriter(*state, context->peer());
  if (!claim.ok()) return ToGrpcStatus(claim.status());
  spdlog::info("stream {} visit {} of map '{}' from {}", created ? "started" : "resumed", visit->id,
               visit->map_name, context->peer());

  v1::StreamFramesResponse started;
  started.mutable_started()->set_map(visit->map_name);
  started.mutable_started()->set_visit_id(static_cast<uint64_t>(visit->id));
  started.mutable_started()->set_new_visit(created);
  if (!stream->Write(started)) {
    return grpc::Status(grpc::StatusCode::CANCELLED, "client went away");
  }

  // Three stages, so that consecutive frames are analysed side by side while a visit still
  // sees its frames one at a time, in order:
  //  - this thread reads frames and queues each one's analysis on the task pool (decode, masks,
  //    labels, result images: no visit state);
  //  - `placer` takes the analyses in the order read and places each in the visit (keyframe
  //    decision, features, record, appearance, commit submission);
  //  - `writer` answers in that order, waiting for keyframe commits so that no acknowledgement
  //    precedes its commit.
  // A frame takes one of max_inflight_frames slots when it is read and gives it back once
  // answered: with none free this thread stops reading, and gRPC's flow control holds back the
  // robot, so a stream holds at most that many frames in all its stages together.
  VisitState* visit_state = state->get();
  const int64_t map_id = visit_state->map_id;
  const auto inflight = static_cast<size_t>(ctx_->config.max_inflight_frames);
  Slots slots(inflight);
  BoundedQueue<std::future<AnalysedFrame>> analysing(inflight);
  BoundedQueue<PendingResult> answering(inflight);
  std::atomic<bool> client_gone{false};
  // Set by `placer` when the visit could no longer be written (ended, its map deleted); this
  // thread ends the stream with it at its next read.
  absl::Mutex closed_mu;
  absl::Status closed;  // guarded by closed_mu
  std::atomic<bool> visit_closed{false};
  uint64_t last_architecture_ticket = 0;  // written by `placer`, read after it is joined
  uint64_t last_pose_graph_ticket = 0;    // likewise
  std::thread writer([&] {
    while (auto p = answering.Pop()) {
      FinishResult(&*p);
      if (!client_gone.load()) {  // else still wait for commits: they complete regardless
        v1::StreamFramesResponse response;
        *response.mutable_result() = std::move(p->result);
        KeepCallersMatches(*caller, response.mutable_result()->mutable_place_matches());
        if (!stream->Write(response)) client_gone.store(true);
      }
      slots.Release();
    }
  });
  std::thread placer([&] {
    while (auto analysed = analysing.Pop()) {
      AnalysedFrame a = analysed->get();
      if (visit_closed.load()) {  // the stream is ending: nothing more is placed
        slots.Release();
        continue;
      }
      PendingResult p = PlaceInVisit(ctx_, std::move(a), *state, claim->id(), *settings);
      last_architecture_ticket = std::max(last_architecture_ticket, p.architecture_ticket);
      last_pose_graph_ticket = std::max(last_pose_graph_ticket, p.pose_graph_ticket);
      if (!p.visit_closed.ok()) {
        // The frame was read before the visit closed: it is answered with the error (a robot
        // that waits for each result is not left waiting), and the stream ends with it.
        spdlog::info("stream for visit {} ends: {}", visit->id,
                     std::string(p.visit_closed.message()));
        {
          absl::MutexLock lock(&closed_mu);
          closed = p.visit_closed;
        }
        visit_closed.store(true);
        p.result = ErrorResult(p.result, p.visit_closed);
      }
      answering.Push(std::move(p));
    }
    answering.Close();
  });

  grpc::Status status = grpc::Status::OK;
  uint64_t frames = 0;
  for (;;) {
    slots.Acquire();
    const ReadOutcome got = visit_closed.load()
                                ? ReadOutcome::kEnd
                                : read(&request, ctx_->config.stream_idle_timeout_s);
    if (got == ReadOutcome::kUnparsable) {
      slots.Release();
      status = grpc::Status(
          grpc::StatusCode::INVALID_ARGUMENT,
          absl::StrCat("message ", frames + 2,
                       " of the stream could not be parsed (not a StreamFramesRequest, or a "
                       "string in it that is not valid UTF-8); the frames before it are answered "
                       "and the stream ends"));
      break;
    }
    if (got == ReadOutcome::kEnd) {
      slots.Release();
      if (watch->timed_out()) {
        status = grpc::Status(grpc::StatusCode::DEADLINE_EXCEEDED,
                              absl::StrCat("no frame for ", ctx_->config.stream_idle_timeout_s,
                                           " s (stream_idle_timeout_s)"));
      }
      break;
    }
    if (!request.has_frame()) {
      slots.Release();
      status = grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                            "only the first message of a stream may be StreamStart; send frames");
      break;
    }
    if (auto s = caller->CheckNotRevoked(); !s.ok()) {  // revoked while streaming
      slots.Release();
      status = ToGrpcStatus(s);
      break;
    }
    // Refused before any work when the visit can no longer be written (`placer` checks again
    // where the frame is added).
    std::string map_name;
    if (auto s = CheckWritable(visit_state, claim->id(), &map_name); !s.ok()) {
      slots.Release();
      status = ToGrpcStatus(s);
      spdlog::info("stream for visit {} ends: {}", visit->id, std::string(s.message()));
      break;
    }
    // Over the key's frame rate the frame is answered with the error, the stream goes on.
    analysing.Push(TaskPool::Shared().Submit([this, frame = std::move(*request.mutable_frame()),
                                              map_id, map_name = std::move(map_name), &settings,
                                              over_rate = caller->TakeFrame()]() mutable {
      return AnalyseFrame(ctx_, std::move(frame), map_id, map_name, *settings, over_rate);
    }));
    ++frames;
  }
  analysing.Close();
  placer.join();
  writer.join();
  if (visit_closed.load() && status.ok()) {
    absl::MutexLock lock(&closed_mu);
    status = ToGrpcStatus(closed);
  }
  // A stream that ends has its visit's floor plan folded, stored and ranked: a robot (or an
  // operator) that asks right after sees every key frame it sent.
  if (last_architecture_ticket > 0) ctx_->architecture->Wait(last_architecture_ticket);
  // Likewise its loops closed and its keyframes' poses corrected.
  if (last_pose_graph_ticket > 0) ctx_->pose_graph->Wait(last_pose_graph_ticket);

  // Persist the visit's frame counter (it rides on keyframe commits otherwise).
  int64_t frame_count = 0;
  {
    absl::MutexLock lock(&(*state)->mu);
    frame_count = (*state)->frame_count;
  }
  auto flushed = ctx_->committer->Submit(std::nullopt, {visit->id, frame_count}).get();
  if (!flushed.ok() && !absl::IsNotFound(flushed.status())) {
    spdlog::warn("visit {}: frame counter not stored: {}", visit->id, flushed.status().ToString());
  }
  spdlog::info("stream for visit {} ended after {} frames{}", visit->id, frames,
               context->IsCancelled() ? " (cancelled)" : "");
  if (client_gone.load() && status.ok()) {
    return grpc::Status(grpc::StatusCode::CANCELLED, "client went away");
  }
  return status;
}

grpc::Status FrameServiceImpl::ProcessFrame(grpc::ServerContext* context,
                                            const v1::ProcessFrameRequest* req,
                                            v1::FrameResult* resp) {
  auto caller = ctx_->keys->Authorize(*context, "FrameService/ProcessFrame");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  if (auto s = caller->TakeFrame(); !s.ok()) return ToGrpcStatus(s);
  auto settings = FrameSettingsFromProto(req->options(), ctx_->config);
  if (!settings.ok()) return ToGrpcStatus(settings.status());
  settings->key_name = caller->key_name;
  settings->max_keyframes_per_map = caller->limits.max_keyframes_per_map;
  std::shared_ptr<VisitState> state;
  if (!req->map().empty()) {
    if (!caller->every_map) {
      if (auto m = FindCallersMap(ctx_->store, *caller, req->map()); !m.ok()) {
        return ToGrpcStatus(m.status());
      }
    }
    bool created = false;
    auto visit = ResolveVisit(ctx_, *caller, req->map(), req->visit_id(), "", "", true, &created);
    if (!visit.ok()) return ToGrpcStatus(visit.status());
    auto s = ctx_->visits->Get(visit->id);
    if (!s.ok()) return ToGrpcStatus(s.status());
    state = *std::move(s);
  } else if (req->visit_id() != 0) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "visit_id needs map");
  }
  std::string map_name;
  if (auto s = CheckWritable(state.get(), /*writer=*/0, &map_name); !s.ok()) {
    return ToGrpcStatus(s);
  }
  PendingResult p = PlaceInVisit(
      ctx_, AnalyseFrame(ctx_, req->frame(), state ? state->map_id : 0, map_name, *settings), state,
      /*writer=*/0, *settings);
  if (!p.visit_closed.ok()) return ToGrpcStatus(p.visit_closed);
  if (p.result.has_error()) {
    return grpc::Status(static_cast<grpc::StatusCode>(p.result.error().code()),
                        p.result.error().message());
  }
  FinishResult(&p);
  *resp = std::move(p.result);
  KeepCallersMatches(*caller, resp->mutable_place_matches());
  return grpc::Status::OK;
}

}  // namespace lifemap::server
