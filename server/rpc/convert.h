// Translation between lifemap.v1 protobuf messages and core / store types, and between
// absl::Status and grpc::Status (one-to-one codes). The only place that sees both worlds.
#pragma once

#include <grpcpp/support/status.h>

#include <map>
#include <string>

#include "absl/status/statusor.h"
#include "core/appearance/recognizer.h"
#include "core/common/rgbd_frame.h"
#include "core/pipeline/frame_pipeline.h"
#include "core/tracking/keyframe_selector.h"
#include "core/tracking/odometry.h"
#include "lifemap/v1/admin_service.pb.h"
#include "lifemap/v1/common.pb.h"
#include "lifemap/v1/frame_service.pb.h"
#include "lifemap/v1/map_service.pb.h"
#include "lifemap/v1/visit_service.pb.h"
#include "server/engine/architecture.h"
#include "server/engine/frame_path.h"
#include "server/rpc/auth.h"
#include "server/store/store.h"

namespace lifemap::server {

grpc::Status ToGrpcStatus(const absl::Status& status);

// An id from a request (uint64 on the wire) as the store keeps it (int64). lifemap never gives
// an id above 2^63-1: such a value is NOT_FOUND naming `field` and the value as sent (a cast
// printed it negative, and 2^64-1 read as -1 was "visit_id is required"). 0 stays 0 (unset).
absl::StatusOr<int64_t> IdFromProto(uint64_t id, absl::string_view field);

v1::Role RoleToProto(Role role);
std::optional<Role> RoleFromProto(v1::Role role);  // nullopt for ROLE_UNSPECIFIED or unknown
void ApiKeyToProto(const store::ApiKeyRecord& k, v1::ApiKey* out);

// Removes the place matches of maps a limited key may not use (by map name; server/auth.h).
void KeepCallersMatches(const Principal& caller,
                        google::protobuf::RepeatedPtrField<v1::PlaceMatch>* matches);

// Validates the message's fields and views its image bytes (the message must outlive the
// result). InvalidArgument names the field: "frame.intrinsics.fx must be > 0", ... Without
// `color_required` a frame may come without colour (uses of depth alone).
absl::StatusOr<EncodedRgbdFrame> FrameFromProto(const v1::Frame& frame, bool color_required = true);

absl::StatusOr<Pose> PoseFromProto(const v1::Pose& pose);
void PoseToProto(const Pose& pose, v1::Pose* out);
v1::TrackingState TrackingStateToProto(tracking::TrackingState state);
v1::TrackingMethod TrackingMethodToProto(tracking::TrackingMethod method);
// A stored keyframe's pose source as the API says it (KeyframeSummary, frame results).
v1::PoseSource StoredPoseSourceToProto(store::StoredPoseSource source);
CameraIntrinsics IntrinsicsFromProto(const v1::CameraIntrinsics& k);
void IntrinsicsToProto(const CameraIntrinsics& k, v1::CameraIntrinsics* out);

// Server defaults overridden by the non-zero fields of the request's options.
absl::StatusOr<tracking::KeyframeOptions> KeyframeOptionsFromProto(
    const v1::FrameOptions& options, const tracking::KeyframeOptions& defaults);

void MapToProto(const store::MapRecord& map, v1::Map* out);
void VisitToProto(const store::VisitRecord& visit, v1::Visit* out);
void KeyframeSummaryToProto(const store::KeyframeRecord& k, v1::KeyframeSummary* out);
void SuperjutToProto(const entropy::SuperjutScore& s, double threshold, v1::Superjut* out);
// A place match, by architecture (paper 004) or appearance (paper 000).
void PlaceMatchToProto(const PlaceMatch& m, v1::PlaceMatch* out);

// An 8-bit result image as the request asked: into `png` (PNG), `raw` (row-major bytes) or
// nowhere (RESULT_IMAGES_NONE).
void ResultImageToProto(const cv::Mat& image, v1::ResultImages how, std::string* png,
                        std::string* raw);
// A frame's labels (the forest's, or fused ones rendered from the octree) by `model`: images as
// asked, the classes present by pixel share.
void LabelsToProto(const pipeline::FrameLabels& labels, const LoadedModel& model,
                   v1::ResultImages images, v1::LabelOutput* out);
// The answer to a frame refused with `s`: its sequence and timestamp (from `of`) and the error,
// nothing of its analysis (the stream goes on unless the caller ends it).
v1::FrameResult ErrorResult(const v1::FrameResult& of, const absl::Status& s);
// A frame's result from the frame path's stages (server/engine/frame_path.h): what its analysis
// gave (or why it was refused), then what placing it in its visit gave (its pose among them). The
// keyframe's commit is reported by the caller once it completes.
void AnalysisToProto(const AnalysedFrame& a, v1::ResultImages images, v1::FrameResult* out);
void PlacementToProto(const AnalysedFrame& a, const FramePlacement& p,
                      const pipeline::PipelineOptions& options, v1::ResultImages images,
                      v1::FrameResult* out);

// The one place that decides each FrameOutput's status: computed, or why not.
void FillOutputStatuses(const pipeline::PipelineOptions& options, const OutputFacts& facts,
                        google::protobuf::RepeatedPtrField<v1::OutputStatus>* out);

// A neg-entropy threshold field: 0 = unset (nullopt), else within (0, 1]. InvalidArgument names
// the field otherwise (NaN included).
absl::StatusOr<std::optional<double>> EntropyThresholdFromProto(double value, const char* field);

}  // namespace lifemap::server
