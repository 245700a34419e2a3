// Per-visit state that outlives one stream: the keyframe selector and the frame counter, so a
// robot that reconnects (or sends unary ProcessFrame calls) continues where it stopped; who
// writes the visit; and whether it may still be written.
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <unordered_map>
#include <utility>
#include <vector>

#include <Eigen/Core>

#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "core/tracking/keyframe_selector.h"
#include "core/tracking/odometry.h"
#include "server/engine/architecture.h"
#include "server/engine/previous_visit.h"
#include "server/engine/semantics.h"
#include "server/engine/serial_worker.h"
#include "server/store/store.h"

namespace lifemap::server {

// The camera's path through a visit: metres travelled, and how far along it each keyframe was
// taken, so that an appearance query can leave out the keyframes it has only just passed
// (AppearanceOptions.exclude_recent_m). Lost frames add nothing; the first pose after them
// adds the straight line from the last one.
class VisitPath {
 public:
  void Advance(const Eigen::Vector3d& position_m);
  // Records a keyframe taken at `timestamp_s` (after the last one recorded) at the current
  // point of the path.
  void MarkKeyframe(double timestamp_s);
  // Metres travelled since the keyframe taken at `timestamp_s`; nullopt when this run of the
  // server did not see it taken.
  std::optional<double> SinceKeyframe(double timestamp_s) const;
  double travelled_m() const { return travelled_m_; }

 private:
  std::optional<Eigen::Vector3d> last_position_;
  double travelled_m_ = 0;
  std::vector<std::pair<double, double>> keyframes_;  // (timestamp s, travelled m), by time
};

struct VisitState {
  int64_t visit_id = 0;
  int64_t map_id = 0;
  // Serialises frames of one visit.
  absl::Mutex mu;
  std::string map_name ABSL_GUARDED_BY(mu);  // follows RenameMap
  // OK while frames may be added. Otherwise why not (FAILED_PRECONDITION: the visit was ended;
  // NOT_FOUND: its map was deleted): a stream writing it ends with this status, and nothing
  // more is committed to the visit.
  absl::Status closed ABSL_GUARDED_BY(mu);
  // The stream writing this visit (0: none) and its peer. A visit has one writer at a time: a
  // second stream, or a ProcessFrame into the visit, is refused while the first is open.
  uint64_t writer ABSL_GUARDED_BY(mu) = 0;
  std::string writer_peer ABSL_GUARDED_BY(mu);
  tracking::KeyframeSelector selector ABSL_GUARDED_BY(mu);
  int64_t frame_count ABSL_GUARDED_BY(mu) = 0;
  int64_t lost_frame_count ABSL_GUARDED_BY(mu) = 0;  // of frame_count, lost by the tracker
  // Timestamp of the visit's latest frame placed (or, resumed, of its last stored keyframe),
  // seconds; frames far after it are refused (ServerConfig::frame_max_gap_s).
  std::optional<double> last_frame_s ABSL_GUARDED_BY(mu);
  // Timestamp of the last frame whose appearance matches were sought (FrameOptions.
  // appearance_interval_s), seconds.
  std::optional<double> last_appearance_query_s ABSL_GUARDED_BY(mu);
  // Frames are placed in the visit one at a time (FramePath::Place holds this throughout): a stream
  // places them in order; concurrent unary ProcessFrame calls into one visit take turns.
  absl::Mutex place_mu ABSL_ACQUIRED_BEFORE(mu);
  // The camera of frames sent without a pose (issue 15): frame-to-keyframe odometry.
  tracking::Tracker tracker ABSL_GUARDED_BY(place_mu);
  VisitPath path ABSL_GUARDED_BY(place_mu);
  // This run of the tracker (stored with each tracked keyframe): keyframes of one run are
  // joined by its odometry in the pose graph; a resumed visit starts a new run.
  int64_t odom_segment = 0;
  // The visit's latest pose-graph solve as a correction of the tracker's frame: a tracked pose
  // T_odom_camera is reported and stored as world_from_odom * T_odom_camera. Identity until a
  // loop closes; set by the PoseGraphWorker.
  absl::Mutex correction_mu;
  Pose world_from_odom ABSL_GUARDED_BY(correction_mu);
  // Set when the visit was anchored during this server run (PoseGraphWorker): world_from_odom
  // then leads into the map's frame, and tracked poses are reported there. The visit's semantic
  // octree stays in the visit's own frame (T_map_visit⁻¹ brings a pose back into it).
  std::optional<Pose> T_map_visit ABSL_GUARDED_BY(correction_mu);
  // How many times the visit's frame changed under it (an anchor set, moved or dropped): a pose
  // reported in frame generation g is in the frame of the g-th change. The floor plan folds a
  // key frame only in its own generation (ArchitectureWorker::Visit::frame_generation).
  uint64_t frame_generation ABSL_GUARDED_BY(correction_mu) = 0;
  // Paper 004's floor plan and ranking; it guards itself (see VisitArchitecture): the
  // ArchitectureWorker folds key frames into it off the reply path, outside `mu`.
  VisitArchitecture architecture;
  // Paper 002's semantic octree of the visit; it guards itself (see VisitSemantics): the
  // semantic worker fuses keyframes into it, frames render from it.
  VisitSemantics semantics;
  // The map's previous visit, for each frame's moved mask (issue 36); it guards itself.
  PreviousVisit previous;

  // OK if a frame from `writer` (0: a unary ProcessFrame) may be added now; else the status
  // to answer: `closed`, or FAILED_PRECONDITION naming the stream that writes the visit.
  absl::Status CheckWritable(uint64_t writer) const ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu);
};

// Queues on `worker`, behind the keyframes already queued for fusion, storing the visit's octree
// however few keyframes were fused since its last snapshot (EndVisit, an export, shutdown).
// Returns the job's ticket for SerialWorker::Wait.
uint64_t QueueSemanticSnapshot(SerialWorker* worker, store::Store* store,
                               std::shared_ptr<VisitState> visit);

// Makes a stream the one writer of a visit for its lifetime. Movable, not copyable.
class VisitWriter {
 public:
  VisitWriter() = default;
  VisitWriter(VisitWriter&& other) noexcept;
  VisitWriter& operator=(VisitWriter&& other) noexcept;
  ~VisitWriter();
  VisitWriter(const VisitWriter&) = delete;
  VisitWriter& operator=(const VisitWriter&) = delete;

  uint64_t id() const { return id_; }

 private:
  friend class VisitRegistry;
  VisitWriter(std::shared_ptr<VisitState> state, uint64_t id) : state_(std::move(state)), id_(id) {}
  std::shared_ptr<VisitState> state_;
  uint64_t id_ = 0;
};

// Thread-safe.
class VisitRegistry {
 public:
  // `semantic`: the options a resumed visit's stored semantic octree is restored with (nullopt:
  // semantic fusion off, nothing restored).
  // `odometry`: how each visit's tracker aligns frames sent without a pose.
  VisitRegistry(store::Store* store, PlaceIndex* places,
                std::optional<semantic::SemanticMapOptions> semantic = std::nullopt,
                const tracking::OdometryOptions& odometry = {})
      : store_(store), places_(places), semantic_(std::move(semantic)), odometry_(odometry) {}

  // The state of an open visit, loaded from the store on first use (the selector resumes from
  // the visit's last keyframe; the architecture is rebuilt from its stored key frames).
  // NOT_FOUND for an unknown visit; FAILED_PRECONDITION if ended.
  absl::StatusOr<std::shared_ptr<VisitState>> Get(int64_t visit_id);
  // The state of a visit if it is loaded now (nullptr otherwise); never loads it.
  std::shared_ptr<VisitState> Loaded(int64_t visit_id);
  // Every visit loaded now.
  std::vector<std::shared_ptr<VisitState>> AllLoaded();

  // Claims `state` for a stream from `peer` until the returned writer is destroyed.
  // FAILED_PRECONDITION naming the visit and the stream that holds it, or the visit's
  // `closed` status.
  absl::StatusOr<VisitWriter> ClaimWriter(const std::shared_ptr<VisitState>& state,
                                          const std::string& peer);

  // Marks a visit closed with `why` (its stream ends with it) and forgets it. For EndVisit:
  // returns the visit's frame counts as of the close (zero when it was not loaded).
  store::VisitFrameCount CloseVisit(int64_t visit_id, const absl::Status& why);
  // Closes every loaded visit of a map (deleted) with `why` and forgets its settings.
  void CloseMap(int64_t map_id, const absl::Status& why);
  // A map renamed: its visits' states follow the new name.
  void RenameMap(int64_t map_id, const std::string& new_name);
  // Forgets a map's cached settings (updated).
  void ForgetMapSettings(int64_t map_id);

  // What a map's settings ask of its frames, cached.
  struct MapSettings {
    std::optional<double> entropy_threshold;  // nullopt = the server default
    bool keep_original_color = false;
  };
  absl::StatusOr<MapSettings> SettingsOfMap(int64_t map_id);

 private:
  store::Store* const store_;
  PlaceIndex* const places_;
  const std::optional<semantic::SemanticMapOptions> semantic_;
  const tracking::OdometryOptions odometry_;
  absl::Mutex mu_;
  std::unordered_map<int64_t, std::shared_ptr<VisitState>> visits_ ABSL_GUARDED_BY(mu_);
  std::unordered_map<int64_t, MapSettings> map_settings_ ABSL_GUARDED_BY(mu_);
  uint64_t next_writer_ ABSL_GUARDED_BY(mu_) = 1;
};

}  // namespace lifemap::server
