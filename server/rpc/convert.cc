#include "server/rpc/convert.h"

#include <limits>

#include <algorithm>
#include <cmath>

#include "absl/strings/str_cat.h"
#include "core/common/image_codec.h"
#include "core/common/utf8.h"
#include "server/engine/visit_frame.h"

namespace lifemap::server {

using pipeline::kNotRequested;

absl::StatusOr<int64_t> IdFromProto(uint64_t id, absl::string_view field) {
  if (id > static_cast<uint64_t>(std::numeric_limits<int64_t>::max())) {
    return absl::NotFoundError(
        absl::StrCat(field, " ", id, " is no id lifemap gives (ids are below 2^63)"));
  }
  return static_cast<int64_t>(id);
}

grpc::Status ToGrpcStatus(const absl::Status& status) {
  if (status.ok()) return grpc::Status::OK;
  // absl::StatusCode and grpc::StatusCode share the canonical numbering.
  return grpc::Status(static_cast<grpc::StatusCode>(status.code()), std::string(status.message()));
}

absl::StatusOr<Pose> PoseFromProto(const v1::Pose& p) {
  return Pose::FromComponents(p.tx(), p.ty(), p.tz(), p.qx(), p.qy(), p.qz(), p.qw());
}

void PoseToProto(const Pose& pose, v1::Pose* out) {
  out->set_tx(pose.translation.x());
  out->set_ty(pose.translation.y());
  out->set_tz(pose.translation.z());
  out->set_qx(pose.rotation.x());
  out->set_qy(pose.rotation.y());
  out->set_qz(pose.rotation.z());
  out->set_qw(pose.rotation.w());
}

CameraIntrinsics IntrinsicsFromProto(const v1::CameraIntrinsics& k) {
  CameraIntrinsics out;
  out.fx = k.fx();
  out.fy = k.fy();
  out.cx = k.cx();
  out.cy = k.cy();
  // Sizes beyond int range are clamped to an invalid value that Validate() rejects.
  out.width = k.width() > 1u << 20 ? -1 : static_cast<int>(k.width());
  out.height = k.height() > 1u << 20 ? -1 : static_cast<int>(k.height());
  return out;
}

void IntrinsicsToProto(const CameraIntrinsics& k, v1::CameraIntrinsics* out) {
  out->set_fx(k.fx);
  out->set_fy(k.fy);
  out->set_cx(k.cx);
  out->set_cy(k.cy);
  out->set_width(static_cast<uint32_t>(k.width));
  out->set_height(static_cast<uint32_t>(k.height));
}

absl::StatusOr<EncodedRgbdFrame> FrameFromProto(const v1::Frame& frame, bool color_required) {
  auto prefixed = [](const absl::Status& s, const char* field) {
    return absl::Status(s.code(), absl::StrCat("frame.", field, ": ", s.message()));
  };
  EncodedRgbdFrame out;
  out.sequence = frame.sequence();
  out.timestamp_s = frame.timestamp_s();
  if (!frame.has_intrinsics()) {
    return absl::InvalidArgumentError(
        "frame.intrinsics is missing; send fx, fy, cx, cy, width, height of the colour camera");
  }
  // Sizes are checked as sent (uint32) before any becomes an int: 2^32-1 was reported as -1.
  constexpr uint32_t kMaxSide = 1u << 20;
  for (const auto& [field, value] :
       {std::pair<const char*, uint32_t>{"intrinsics.width", frame.intrinsics().width()},
        {"intrinsics.height", frame.intrinsics().height()},
        {"depth.width", frame.depth().width()},
        {"depth.height", frame.depth().height()},
        {"color.width", frame.color().width()},
        {"color.height", frame.color().height()}}) {
    if (value > kMaxSide) {
      return absl::InvalidArgumentError(
          absl::StrCat("frame.", field, " is ", value, "; an image side is at most ", kMaxSide));
    }
  }
  out.intrinsics = IntrinsicsFromProto(frame.intrinsics());
  if (auto s = out.intrinsics.Validate(); !s.ok()) return prefixed(s, "intrinsics");

  if (!frame.has_depth() || frame.depth().data().empty()) {
    return absl::InvalidArgumentError("frame.depth is missing or empty");
  }
  const auto& d = frame.depth();
  switch (d.encoding()) {
    case v1::DEPTH_PNG16:
      out.depth.encoding = DepthEncoding::kPng16;
      break;
    case v1::DEPTH_RAW_U16:
      out.depth.encoding = DepthEncoding::kRawU16;
      break;
    case v1::DEPTH_RAW_F32:
      out.depth.encoding = DepthEncoding::kRawF32;
      break;
    case v1::DEPTH_RVL:
      out.depth.encoding = DepthEncoding::kRvl;
      break;
    case v1::DEPTH_PALETTED:
      out.depth.encoding = DepthEncoding::kPaletted;
      break;
    default:
      return absl::InvalidArgumentError(absl::StrCat(
          "frame.depth.encoding ", d.encoding(),
          " is not supported; use DEPTH_PNG16, DEPTH_RAW_U16, DEPTH_RAW_F32, DEPTH_RVL or "
          "DEPTH_PALETTED"));
  }
  out.depth.data = d.data();
  out.depth.width = static_cast<int>(std::min<uint32_t>(d.width(), 1u << 20));
  out.depth.height = static_cast<int>(std::min<uint32_t>(d.height(), 1u << 20));
  out.depth.depth_scale = d.depth_scale();

  const bool no_color = !frame.has_color() || frame.color().data().empty();
  if (no_color && color_required) {
    return absl::InvalidArgumentError("frame.color is missing or empty");
  }
  if (!no_color) {
    const auto& c = frame.color();
    switch (c.encoding()) {
      case v1::COLOR_JPEG:
        out.color.encoding = ColorEncoding::kJpeg;
        break;
      case v1::COLOR_PNG:
        out.color.encoding = ColorEncoding::kPng;
        break;
      case v1::COLOR_RAW_RGB8:
        out.color.encoding = ColorEncoding::kRawRgb8;
        break;
      default:
        return absl::InvalidArgumentError(
            absl::StrCat("frame.color.encoding ", c.encoding(),
                         " is not supported; use COLOR_JPEG, COLOR_PNG or COLOR_RAW_RGB8"));
    }
    out.color.data = c.data();
    out.color.width = static_cast<int>(std::min<uint32_t>(c.width(), 1u << 20));
    out.color.height = static_cast<int>(std::min<uint32_t>(c.height(), 1u << 20));
  }

  if (frame.has_pose()) {
    auto pose = PoseFromProto(frame.pose());
    if (!pose.ok()) return prefixed(pose.status(), "pose");
    out.T_world_camera = *pose;
  }
  if (frame.has_gravity()) {
    const Eigen::Vector3d g(frame.gravity().x(), frame.gravity().y(), frame.gravity().z());
    if (!g.allFinite() || !(g.norm() > 1e-6) || g.norm() > 1e6) {
      return absl::InvalidArgumentError(absl::StrCat(
          "frame.gravity must be a finite, non-zero vector (gravity in the camera frame, e.g. an "
          "IMU's accelerometer at rest; any length up to 1e6), got (",
          g.x(), ", ", g.y(), ", ", g.z(), ")"));
    }
    out.gravity_camera = g.normalized();
  }
  if (frame.has_odometry()) {
    if (!frame.odometry().has_pose()) {
      return absl::InvalidArgumentError(
          "frame.odometry.pose is missing: send the camera's pose in the odometry frame, or no "
          "odometry");
    }
    auto pose = PoseFromProto(frame.odometry().pose());
    if (!pose.ok()) return prefixed(pose.status(), "odometry.pose");
    const auto& c = frame.odometry().covariance();
    auto reading = OdometryReading::Make(*pose, std::vector<double>(c.begin(), c.end()));
    if (!reading.ok()) return prefixed(reading.status(), "odometry");
    out.odometry = *std::move(reading);
  }
  return out;
}

absl::StatusOr<tracking::KeyframeOptions> KeyframeOptionsFromProto(
    const v1::FrameOptions& o, const tracking::KeyframeOptions& defaults) {
  tracking::KeyframeOptions k = defaults;
  if (o.keyframe_min_translation_m() != 0.0) k.min_translation_m = o.keyframe_min_translation_m();
  if (o.keyframe_min_rotation_rad() != 0.0) k.min_rotation_rad = o.keyframe_min_rotation_rad();
  if (o.keyframe_max_interval_s() != 0.0) k.max_interval_s = o.keyframe_max_interval_s();
  if (auto s = k.Validate(); !s.ok()) {
    return absl::InvalidArgumentError(absl::StrCat("options: ", s.message()));
  }
  return k;
}

void MapToProto(const store::MapRecord& map, v1::Map* out) {
  out->set_id(static_cast<uint64_t>(map.id));
  out->set_name(map.name);
  out->set_description(map.description);
  out->set_created_time_s(map.created_time_s);
  out->set_visit_count(static_cast<uint32_t>(map.visit_count));
  out->set_keyframe_count(static_cast<uint64_t>(map.keyframe_count));
  out->set_stored_bytes(static_cast<uint64_t>(map.stored_bytes));
  out->set_entropy_threshold(map.entropy_threshold.value_or(0.0));
  out->set_keep_original_color(map.keep_original_color);
}

void VisitToProto(const store::VisitRecord& v, v1::Visit* out) {
  out->set_id(static_cast<uint64_t>(v.id));
  out->set_map(v.map_name);
  out->set_robot(v.robot);
  out->set_label(v.label);
  out->set_start_time_s(v.start_time_s);
  out->set_data_start_time_s(v.data_start_time_s);
  out->set_data_end_time_s(v.data_end_time_s);
  out->set_end_time_s(v.end_time_s);
  out->set_ended(v.ended);
  out->set_keyframe_count(static_cast<uint64_t>(v.keyframe_count));
  out->set_frame_count(static_cast<uint64_t>(v.frame_count));
  out->set_frames_lost(static_cast<uint64_t>(v.lost_frame_count));
  out->set_loops_accepted(static_cast<uint64_t>(v.loops_accepted));
  out->set_loops_rejected(static_cast<uint64_t>(v.loops_rejected));
  out->set_pose_graph_solves(static_cast<uint64_t>(v.pose_graph_solves));
  if (v.anchor) {
    out->set_frame(v1::VISIT_FRAME_ANCHORED);
    auto* a = out->mutable_anchor();
    a->set_to_visit(static_cast<uint64_t>(v.anchor->to_visit_id));
    PoseToProto(v.anchor->T_map_visit, a->mutable_t_map_visit());
    a->set_residual_m(v.anchor->residual_m);
    a->set_residual_deg(v.anchor->residual_deg);
    a->set_anchored_time_s(v.anchor->anchored_time_s);
    a->set_revisions(static_cast<uint32_t>(v.anchor->revisions));
    a->set_evidence(v.anchor->evidence);
  } else if (MapFromVisit(v)) {
    out->set_frame(v1::VISIT_FRAME_MAP);
  } else {
    out->set_frame(v1::VISIT_FRAME_UNANCHORED);
    out->set_anchor_dropped(ToValidUtf8(v.anchor_dropped));
  }
}

void KeyframeSummaryToProto(const store::KeyframeRecord& k, v1::KeyframeSummary* out) {
  out->set_id(static_cast<uint64_t>(k.id));
  out->set_visit_id(static_cast<uint64_t>(k.visit_id));
  out->set_sequence(k.sequence);
  out->set_timestamp_s(k.timestamp_s);
  if (k.T_world_camera) PoseToProto(*k.T_world_camera, out->mutable_pose());
  out->set_pose_source(StoredPoseSourceToProto(k.pose_source));
  IntrinsicsToProto(k.intrinsics, out->mutable_intrinsics());
  out->set_color_bytes(static_cast<uint32_t>(k.color_bytes));
  out->set_depth_bytes(static_cast<uint32_t>(k.depth_bytes));
  if (k.feature_counts) {
    out->set_superjut_count(static_cast<uint32_t>(k.feature_counts->superjuts));
    out->set_entropy_threshold(k.feature_counts->entropy_threshold);
    out->set_keypoint_type(k.feature_counts->keypoint_type);
    out->set_keypoints_stored(static_cast<uint32_t>(k.feature_counts->keypoints_stored));
    out->set_keypoints_masked(static_cast<uint32_t>(k.feature_counts->keypoints_masked));
  }
}

void SuperjutToProto(const entropy::SuperjutScore& s, double threshold, v1::Superjut* out) {
  out->set_id(static_cast<uint32_t>(s.id));
  out->set_size_px(static_cast<uint32_t>(s.size_px));
  out->set_entropy(s.entropy);
  out->set_planarity(s.planarity);
  out->set_horizontality(s.horizontality);
  out->set_textureness(s.textureness);
  out->set_neg_entropy(s.neg_entropy);
  out->set_masked(s.neg_entropy < threshold);
}

absl::StatusOr<std::optional<double>> EntropyThresholdFromProto(double value, const char* field) {
  if (value == 0.0) return std::optional<double>();
  if (!(value > 0.0 && value <= 1.0)) {
    return absl::InvalidArgumentError(
        absl::StrCat(field, " must be within [0, 1] (0 = the server default), got ", value));
  }
  return std::optional<double>(value);
}

v1::Role RoleToProto(Role role) {
  switch (role) {
    case Role::kRobot:
      return v1::ROLE_ROBOT;
    case Role::kOperator:
      return v1::ROLE_OPERATOR;
    case Role::kAdmin:
      return v1::ROLE_ADMIN;
  }
  return v1::ROLE_UNSPECIFIED;
}

std::optional<Role> RoleFromProto(v1::Role role) {
  switch (role) {
    case v1::ROLE_ROBOT:
      return Role::kRobot;
    case v1::ROLE_OPERATOR:
      return Role::kOperator;
    case v1::ROLE_ADMIN:
      return Role::kAdmin;
    default:
      return std::nullopt;
  }
}

void ApiKeyToProto(const store::ApiKeyRecord& k, v1::ApiKey* out) {
  out->set_name(k.name);
  if (auto role = ParseRole(k.role)) out->set_role(RoleToProto(*role));
  out->set_every_map(k.every_map);
  for (const auto& m : k.map_names) out->add_maps(m);
  out->set_created_time_s(k.created_time_s);
  out->set_last_used_time_s(k.last_used_time_s);
  out->set_revoked_time_s(k.revoked_time_s);
  auto* limits = out->mutable_limits();
  limits->set_max_streams(static_cast<uint32_t>(k.limits.max_streams));
  limits->set_max_frames_per_s(k.limits.max_frames_per_s);
  limits->set_max_maps(static_cast<uint32_t>(k.limits.max_maps));
  limits->set_max_keyframes_per_map(static_cast<uint64_t>(k.limits.max_keyframes_per_map));
  limits->set_max_model_bytes(static_cast<uint64_t>(k.limits.max_model_bytes));
  limits->set_max_visits_per_hour(static_cast<uint32_t>(k.limits.max_visits_per_hour));
}

void KeepCallersMatches(const Principal& caller,
                        google::protobuf::RepeatedPtrField<v1::PlaceMatch>* matches) {
  if (caller.every_map) return;
  const auto& names = caller.map_names;
  matches->erase(std::remove_if(matches->begin(), matches->end(),
                                [&names](const v1::PlaceMatch& m) {
                                  return std::find(names.begin(), names.end(), m.map()) ==
                                         names.end();
                                }),
                 matches->end());
}

void PlaceMatchToProto(const PlaceMatch& m, v1::PlaceMatch* out) {
  out->set_map(m.map);
  out->set_visit_id(static_cast<uint64_t>(m.visit_id));
  out->set_keyframe_id(static_cast<uint64_t>(m.keyframe_id));
  out->set_score(m.score);
  switch (m.method) {
    case PlaceMatch::Method::kArchitecture:
      out->set_method(v1::MATCH_METHOD_ARCHITECTURE);
      break;
    case PlaceMatch::Method::kAppearance:
      out->set_method(v1::MATCH_METHOD_APPEARANCE);
      break;
    case PlaceMatch::Method::kFused:
      out->set_method(v1::MATCH_METHOD_FUSED);
      break;
  }
  if (m.T_match_query) PoseToProto(*m.T_match_query, out->mutable_t_match_query());
}

v1::PoseSource StoredPoseSourceToProto(store::StoredPoseSource source) {
  switch (source) {
    case store::StoredPoseSource::kClient:
      return v1::POSE_SOURCE_CLIENT;
    case store::StoredPoseSource::kEstimated:
      return v1::POSE_SOURCE_ESTIMATED;
    case store::StoredPoseSource::kRefined:
      return v1::POSE_SOURCE_REFINED;
    case store::StoredPoseSource::kNone:
      break;
  }
  return v1::POSE_SOURCE_NONE;
}

v1::TrackingState TrackingStateToProto(tracking::TrackingState state) {
  switch (state) {
    case tracking::TrackingState::kStarted:
      return v1::TRACKING_STARTED;
    case tracking::TrackingState::kTracking:
      return v1::TRACKING_OK;
    case tracking::TrackingState::kLost:
      return v1::TRACKING_LOST;
    case tracking::TrackingState::kRegained:
      return v1::TRACKING_REGAINED;
  }
  return v1::TRACKING_STATE_UNSPECIFIED;
}

v1::TrackingMethod TrackingMethodToProto(tracking::TrackingMethod method) {
  switch (method) {
    case tracking::TrackingMethod::kDense:
      return v1::TRACKING_METHOD_DENSE;
    case tracking::TrackingMethod::kRefit:
      return v1::TRACKING_METHOD_REFIT;
    case tracking::TrackingMethod::kFeatures:
      return v1::TRACKING_METHOD_FEATURES;
    case tracking::TrackingMethod::kRelocalised:
      return v1::TRACKING_METHOD_RELOCALISED;
    case tracking::TrackingMethod::kOdometry:
      return v1::TRACKING_METHOD_ODOMETRY;
    case tracking::TrackingMethod::kNone:
      break;
  }
  return v1::TRACKING_METHOD_UNSPECIFIED;
}

void FillOutputStatuses(const pipeline::PipelineOptions& options, const OutputFacts& facts,
                        google::protobuf::RepeatedPtrField<v1::OutputStatus>* out) {
  auto add = [out](v1::FrameOutput o, bool computed, absl::string_view reason) {
    auto* s = out->Add();
    s->set_output(o);
    s->set_computed(computed);
    if (!computed) s->set_reason(std::string(reason));
  };
  const pipeline::FrameAnalysis* a = facts.analysis;
  add(v1::FRAME_OUTPUT_POSE, a == nullptr || a->frame.T_world_camera.has_value(),
      facts.tracked ? absl::StrCat("tracking lost: ", facts.tracking_lost_reason)
                    : std::string("frames without a map are not tracked: send them into a "
                                  "visit (with a map), or with Frame.pose"));
  add(v1::FRAME_OUTPUT_KEYFRAME, facts.has_map,
      "no map given: the frame is processed but nothing is stored");
  if (!options.entropy_masks) {
    add(v1::FRAME_OUTPUT_ENTROPY_MASK, false, "disabled in this server's config (entropy.enabled)");
  } else if (facts.entropy_skipped) {
    add(v1::FRAME_OUTPUT_ENTROPY_MASK, false, kNotRequested);
  } else if (a != nullptr && !a->entropy) {
    add(v1::FRAME_OUTPUT_ENTROPY_MASK, false,
        absl::StrCat("not computed for this frame: ", a->entropy_status.message()));
  } else {
    add(v1::FRAME_OUTPUT_ENTROPY_MASK, true, "");
  }
  if (facts.labels_skipped) {
    add(v1::FRAME_OUTPUT_CLASS_LABELS, false, kNotRequested);
  } else if (!facts.labeller.ok()) {
    add(v1::FRAME_OUTPUT_CLASS_LABELS, false, facts.labeller.message());
  } else if (a != nullptr && !a->labels) {
    add(v1::FRAME_OUTPUT_CLASS_LABELS, false,
        absl::StrCat("the model failed on this frame: ", a->labels_status.message()));
  } else {
    add(v1::FRAME_OUTPUT_CLASS_LABELS, true, "");
  }
  if (!facts.has_map) {
    add(v1::FRAME_OUTPUT_PLACE_MATCHES, false,
        "no map given: places are recognised for frames of a visit");
  } else if (facts.analysis == nullptr) {
    add(v1::FRAME_OUTPUT_PLACE_MATCHES, true, "");  // server-wide: both methods are served
  } else {
    // Computed when either method answered; otherwise why neither did.
    const bool by_architecture = facts.architecture && facts.architecture->status.ok();
    const bool by_appearance = facts.appearance && facts.appearance->ok();
    add(v1::FRAME_OUTPUT_PLACE_MATCHES, by_architecture || by_appearance,
        absl::StrCat("architecture (paper 004): ",
                     facts.architecture ? facts.architecture->status.message() : "not asked",
                     "; appearance (paper 000): ",
                     facts.appearance
                         ? facts.appearance->message()
                         : "queried on keyframes only (FrameOptions.appearance_interval_s "
                           "asks for other frames)"));
  }
  add(v1::FRAME_OUTPUT_SEMANTIC_FUSION, facts.fusion.ok(), facts.fusion.message());
  add(v1::FRAME_OUTPUT_MOVED_ZONES, facts.moved.ok(), facts.moved.message());
}

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

namespace {

// The entropy output: score image and mask as asked, the per-superjut table.
void EntropyToProto(const entropy::EntropyMaskResult& e, v1::ResultImages images,
                    v1::EntropyOutput* out) {
  out->set_threshold(e.threshold);
  ResultImageToProto(e.score_image, images, out->mutable_score_png(), out->mutable_score_raw());
  ResultImageToProto(e.mask, images, out->mutable_mask_png(), out->mutable_mask_raw());
  for (const auto& s : e.superjuts) SuperjutToProto(s, e.threshold, out->add_superjuts());
}

}  // namespace

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

v1::FrameResult ErrorResult(const v1::FrameResult& of, const absl::Status& s) {
  v1::FrameResult r;
  r.set_sequence(of.sequence());
  r.set_timestamp_s(of.timestamp_s());
  r.mutable_error()->set_code(static_cast<int>(s.code()));
  r.mutable_error()->set_message(ToValidUtf8(s.message()));
  return r;
}

void AnalysisToProto(const AnalysedFrame& a, v1::ResultImages images, v1::FrameResult* r) {
  r->set_sequence(a.sequence);
  r->set_timestamp_s(a.timestamp_s);
  if (!a.refused.ok()) {
    *r = ErrorResult(*r, a.refused);
    return;
  }
  const pipeline::FrameAnalysis& analysis = *a.analysis;
  const RgbdFrame& f = analysis.frame;
  r->set_width(static_cast<uint32_t>(f.intrinsics.width));
  r->set_height(static_cast<uint32_t>(f.intrinsics.height));
  r->set_valid_depth_fraction(analysis.depth_stats.valid_fraction);
  r->set_median_depth_m(analysis.depth_stats.median_m);
  if (analysis.entropy) EntropyToProto(*analysis.entropy, images, r->mutable_entropy());
  if (analysis.labels) LabelsToProto(*analysis.labels, *a.model, images, r->mutable_labels());
  r->mutable_timing()->set_decode_ms(analysis.decode_ms);
  r->mutable_timing()->set_process_ms(analysis.process_ms);
}

void PlacementToProto(const AnalysedFrame& a, const FramePlacement& p,
                      const pipeline::PipelineOptions& options, v1::ResultImages images,
                      v1::FrameResult* r) {
  r->set_pose_source(StoredPoseSourceToProto(p.pose_source));
  if (p.pose) PoseToProto(*p.pose, r->mutable_pose());
  if (p.tracking) {
    auto* t = r->mutable_tracking();
    t->set_track_ms(p.tracking->track_ms);
    t->set_state(TrackingStateToProto(p.tracking->state));
    t->set_method(TrackingMethodToProto(p.tracking->method));
    t->set_lost_frames(static_cast<uint32_t>(p.tracking->lost_frames));
    t->set_reason(p.tracking->reason);
    for (const auto& axis : p.tracking->degenerate_axes) t->add_degenerate_axes(axis);
  }
  if (p.keyframe) {
    r->mutable_keyframe()->set_selected(p.keyframe->selected);
    r->mutable_keyframe()->set_reason(p.keyframe->reason);
    r->mutable_keyframe()->set_resent(p.resent_as.has_value());
  }
  for (const auto& m : p.place_matches) PlaceMatchToProto(m, r->add_place_matches());
  if (p.fused_labels) LabelsToProto(*p.fused_labels, *a.model, images, r->mutable_fused_labels());
  if (p.moved) {
    v1::MovedOutput* m = r->mutable_moved();
    const change::MovedMask& mask = p.moved->mask;
    m->set_stride(static_cast<uint32_t>(mask.stride));
    m->set_moved_share(static_cast<float>(mask.share()));
    m->set_compared_pixels(static_cast<uint32_t>(mask.compared_pixels));
    m->set_previous_visit(static_cast<uint64_t>(p.moved->previous_visit));
    m->set_threshold_m(p.moved->threshold_m);
    const RgbdFrame& f = a.analysis->frame;
    ResultImageToProto(change::FullSizeMask(mask, f.depth_m.cols, f.depth_m.rows), images,
                       m->mutable_mask_png(), m->mutable_mask_raw());
  }
  FillOutputStatuses(options, p.facts, r->mutable_outputs());
}

}  // namespace lifemap::server
