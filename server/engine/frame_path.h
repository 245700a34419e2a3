// The frame path: what the engine does with each RGB-D frame a robot sends, in two stages.
//
//   Analyse   any thread, several frames of a stream side by side; reads no visit state:
//             timestamp check → decode → entropy masks and labels (core/pipeline) → the frame
//             made ready for tracking.
//   Place     one frame of a visit at a time, in the order sent (a visit has one writer):
//             tracking (relocalised by appearance when lost) → keyframe decision → features and
//             the keyframe's record → appearance query (loop and anchor candidates) → commit
//             submitted → floor-plan fold, pose-graph job, fused labels rendered, fusion queued.
//
// The results are typed (AnalysedFrame, FramePlacement); the RPC layer (server/rpc) converts
// them. A placement's keyframe is acknowledged only once its commit completed.
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <future>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/rgbd_frame.h"
#include "core/pipeline/frame_pipeline.h"
#include "core/pipeline/keyframe.h"
#include "core/tracking/keyframe_selector.h"
#include "core/tracking/odometry.h"
#include "server/engine/architecture.h"
#include "server/engine/model_registry.h"
#include "server/engine/options.h"
#include "server/engine/pose_graph_worker.h"
#include "server/store/store.h"

namespace lifemap::server {

class AppearanceIndex;
class KeyframeCommitter;
class SerialWorker;
class VisitRegistry;
struct VisitState;

inline constexpr char kLabelsDisabled[] = "disabled in this server's config (labels.enabled)";

// What a stream's (or a call's) options ask of each frame.
struct FrameSettings {
  tracking::KeyframeOptions keyframe;
  pipeline::FrameRequest request;
  std::optional<double> appearance_interval_s;  // nullopt: keyframes only
  bool skip_labels = false;         // FrameOptions.skip_outputs; the masks' switch is in `request`
  bool skip_fusion = false;         // no fused labels rendered (the visit's keyframes still fuse)
  bool skip_moved = false;          // no moved mask against the previous visit
  int64_t moved_against_visit = 0;  // 0: the map's latest earlier ended visit in its frame
  bool refine_pose = false;         // client poses refined by the tracker
  // The caller's key: a keyframe is not stored once its map holds this many (0: no limit).
  std::string key_name;
  int64_t max_keyframes_per_map = 0;
};

// What decides whether each per-frame output was computed (the RPC layer says which, and why
// not, in FrameResult.outputs).
struct OutputFacts {
  // The frame's analysis; null for the server-wide answer (GetServerInfo). Points into the
  // AnalysedFrame placed: valid while it lives.
  const pipeline::FrameAnalysis* analysis = nullptr;
  // Frames sent with a map may become keyframes and get place matches.
  bool has_map = true;
  // OK when a model labels this frame (server-wide: some map's); else why not.
  absl::Status labeller;
  // The visit's ranking by architecture, per frame of a visit.
  std::optional<ArchitectureRanking> architecture;
  // Whether appearance matches were sought for this frame (nullopt: not asked) and, if they
  // could not be, why (an empty list of verified matches is OK: nothing recognised).
  std::optional<absl::Status> appearance;
  // The server's tracking of a frame (unset: a client pose used as sent, or no visit).
  std::optional<tracking::TrackingState> tracked;
  std::string tracking_lost_reason;
  // The client skipped these outputs: "not requested", whatever was computed for the server's
  // own use.
  bool entropy_skipped = false;
  bool labels_skipped = false;
  // Fused labels (the visit's semantic octree rendered into the frame): OK, or why not.
  absl::Status fusion =
      absl::FailedPreconditionError("frames of a visit only: send the frame into a visit");
  // The moved mask against the map's previous visit (issue 36): OK, or why not.
  absl::Status moved =
      absl::FailedPreconditionError("frames of a visit only: send the frame into a visit");
};

// What moved since the map's previous visit, in one frame (paper 000's eq. 3).
struct FrameMoved {
  change::MovedMask mask;
  int64_t previous_visit = 0;
  float threshold_m = 0.0f;  // eq. 3's threshold used
};

// Stage 1's result: a frame analysed, not yet placed in its visit.
struct AnalysedFrame {
  uint64_t sequence = 0;
  double timestamp_s = 0.0;
  std::chrono::steady_clock::time_point received;
  // Not OK when the frame was refused (nothing below is set); the stream goes on.
  absl::Status refused;
  std::optional<pipeline::FrameAnalysis> analysis;
  std::shared_ptr<const LoadedModel> model;  // keeps the labelling model alive
  absl::Status labeller;                     // OK when the model labelled it; else why not
  // The sent colour bytes a keyframe's record keeps as they came (JPEG; PNG when the map keeps
  // originals); empty otherwise: the record re-encodes the decoded image.
  std::string color_as_sent;
  ColorEncoding color_encoding = ColorEncoding::kJpeg;
  double depth_scale_as_sent = 0.0;        // units per metre of integer depth encodings, else 0
  bool keep_original_color = false;        // the map's setting
  std::optional<float> entropy_threshold;  // in effect (request, map, server)
  // A frame of a visit sent without a pose, prepared for the visit's tracker.
  std::shared_ptr<tracking::TrackingInput> tracking_input;
  // Brings the frame's pose into its visit's own frame (where the visit's semantic octree is):
  // identity, except for a tracked pose reported in the map's frame after the visit was
  // anchored during this run (then T_map_visit⁻¹).
  Pose T_visit_world;

  // The frame's camera in its visit's own frame (its pose must be set).
  Pose T_visit_camera() const;
};

// How the server tracked a frame sent without a pose (or with one to refine).
struct FrameTracking {
  tracking::TrackingState state = tracking::TrackingState::kLost;
  tracking::TrackingMethod method = tracking::TrackingMethod::kNone;
  int lost_frames = 0;
  std::string reason;  // why lost, or how it was relocalised
  double track_ms = 0.0;
  std::vector<std::string> degenerate_axes;  // tracking::TrackedPose::degenerate_axes
};

// Stage 2's result: the frame placed in its visit.
struct FramePlacement {
  // Not OK when the frame was refused where it was placed (its timestamp too far after the
  // visit's last frame); nothing else is set. The stream goes on.
  absl::Status refused;
  // Not OK when the visit could no longer be written (ended, its map deleted, written by
  // another stream): the call ends with this status and the frame gets no result.
  absl::Status visit_closed;
  // The frame's pose as reported: the client's, refined, estimated (in the visit's corrected
  // frame) or none.
  std::optional<Pose> pose;
  store::StoredPoseSource pose_source = store::StoredPoseSource::kNone;
  std::optional<FrameTracking> tracking;               // set when the server tracked the frame
  std::optional<tracking::KeyframeDecision> keyframe;  // frames of a visit
  // The frame was stored before as this keyframe (a resend after a lost reply; `commit` holds
  // its id): nothing was stored or fused again.
  std::optional<int64_t> resent_as;
  // Appearance matches (best first, at most appearance.max_frame_matches), then the visit's
  // ranking by architecture (paper 004) as known now.
  std::vector<PlaceMatch> place_matches;
  std::optional<pipeline::FrameLabels> fused_labels;  // the visit's octree rendered
  std::optional<FrameMoved> moved;                    // against the map's previous visit
  OutputFacts facts;
  // The keyframe's commit, when one was submitted: its id once the store has it.
  std::optional<std::shared_future<absl::StatusOr<int64_t>>> commit;
  uint64_t architecture_ticket = 0;  // the keyframe's job on the ArchitectureWorker, if any
  uint64_t pose_graph_ticket = 0;    // its loop candidates' job on the PoseGraphWorker, if any
};

// The parts of the engine the frame path uses (not owned; they outlive it). `appearance` may
// be null (appearance disabled); `semantic_worker` may be null (semantic fusion disabled).
struct FramePathParts {
  store::Store* store = nullptr;
  const pipeline::FramePipeline* pipeline = nullptr;
  VisitRegistry* visits = nullptr;
  ModelRegistry* models = nullptr;
  KeyframeCommitter* committer = nullptr;
  AppearanceIndex* appearance = nullptr;
  ArchitectureWorker* architecture = nullptr;
  PoseGraphWorker* pose_graph = nullptr;
  SerialWorker* semantic_worker = nullptr;
  SerialWorker* previous_loader = nullptr;  // loads the previous visit for moved masks
};

class FramePath {
 public:
  FramePath(const FramePathParts& parts, const EngineOptions& options);

  // Stage 1. Analyses `frame` (its bytes need live only during the call) with the settings and
  // model of map `map_id` (0: a frame without a map). Reads no visit state: safe on any thread.
  AnalysedFrame Analyse(const EncodedRgbdFrame& frame, int64_t map_id, const std::string& map_name,
                        const FrameSettings& settings);
  // A frame refused before its analysis (invalid, over its key's rate), counted as rejected.
  AnalysedFrame Refuse(uint64_t sequence, double timestamp_s, const absl::Status& why);

  // Stage 2. Places `frame` in `visit` (null: a frame without a map, which only gets its
  // outputs' statuses), in the visit's frame order. `writer` is the stream's claim on the visit
  // (0 for a single call). `frame` is changed (its pose becomes the reported one; a keyframe's
  // class probabilities go to fusion) and must outlive the placement's `facts`.
  FramePlacement Place(AnalysedFrame& frame, const std::shared_ptr<VisitState>& visit,
                       uint64_t writer, const FrameSettings& settings);

  // Frames analysed (or refused) since the start.
  uint64_t frames_processed() const { return frames_processed_.load(); }
  uint64_t frames_rejected() const { return frames_rejected_.load(); }
  const pipeline::FramePipeline& pipeline() const { return *parts_.pipeline; }

 private:
  // RESOURCE_EXHAUSTED when the settings' key limits the keyframes of map `map_id` and it
  // holds that many.
  absl::Status CheckKeyframeLimit(const FrameSettings& settings, int64_t map_id) const;
  // The frame's appearance features (ORB, pruned by its entropy masks: a client that skipped
  // the masks still gets features pruned by them, not reported).
  absl::StatusOr<pipeline::KeyframeFeatures> QueryFeatures(AnalysedFrame& a,
                                                           bool entropy_skipped) const;
  absl::StatusOr<std::pair<Pose, std::string>> PlaceByAppearance(AnalysedFrame& a,
                                                                 const FrameSettings& settings,
                                                                 int64_t visit_id,
                                                                 int64_t map_id) const;
  absl::Status AppearanceMatches(const absl::StatusOr<pipeline::KeyframeFeatures>& features,
                                 const RgbdFrame& f, const VisitState& visit, FramePlacement* out,
                                 std::vector<LoopCandidate>* loops,
                                 std::vector<AnchorCandidate>* anchors,
                                 std::vector<int64_t>* sighted) const;
  absl::Status RenderFusedLabels(const AnalysedFrame& a, const FrameSettings& settings,
                                 VisitState* visit, FramePlacement* out) const;
  void SubmitForFusion(AnalysedFrame& a, const std::shared_ptr<VisitState>& visit) const;
  // The frame against the map's previous visit, into `out->moved`; OK when compared, else why
  // not. `in_map_frame`: the frame's pose is in the map's frame.
  absl::Status CompareWithPrevious(const AnalysedFrame& a, const FrameSettings& settings,
                                   VisitState* visit, bool in_map_frame, FramePlacement* out) const;
  // Takes the frame's sent colour bytes (color_as_sent is empty afterwards).
  absl::StatusOr<store::KeyframeRecord> MakeKeyframeRecord(AnalysedFrame& a,
                                                           int64_t visit_id) const;

  FramePathParts parts_;
  EngineOptions options_;
  std::atomic<uint64_t> frames_processed_{0};
  std::atomic<uint64_t> frames_rejected_{0};
};

// The visit as the architecture worker needs it (kept alive by its jobs), for a key frame posed
// or a rebuild reading key frames stored in `frame_generation` (VisitState::frame_generation).
ArchitectureWorker::Visit ArchitectureJobVisit(const std::shared_ptr<VisitState>& state,
                                               uint64_t frame_generation);

// What a visit's frames follow when the PoseGraphWorker anchors it, revises or drops its anchor
// (PoseGraphWorker::Job::on_anchored): later poses are moved with its stored keyframes, its frame
// generation advances, and its floor plan is rebuilt in its new frame.
std::function<void(const Pose& moved_by, const std::optional<Pose>& T_map_visit)> FollowAnchor(
    std::shared_ptr<VisitState> state, ArchitectureWorker* architecture);

// OK when `writer` may still add frames to `visit` (null: a frame without a map), and its
// map's name then.
absl::Status CheckWritable(VisitState* visit, uint64_t writer, std::string* map_name);

}  // namespace lifemap::server
