// Streaming a recording to lifemapd without poses, as a robot without its own localisation
// would, and reading back what the server made of it: the evaluations of issue 15
// (`lifemap eval trajectory`, `lifemap eval alignment`) share it.
#pragma once

#include <cstdint>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>

#include "absl/status/statusor.h"
#include "client/lifemap_client.h"
#include "core/common/types.h"
#include "core/io/tum_dataset.h"

namespace lifemap::cli {

// One frame's answer.
struct TrackedFrame {
  double timestamp_s = 0;
  bool tracked = false;  // the server estimated a pose (`pose`)
  bool keyframe = false;
  Pose pose;
  std::string state;  // started | ok | lost | regained | none | error
  // dense | refit | features | relocalised | odometry, or "" (lost, started, error)
  std::string method;
  std::optional<Pose> truth;  // the recording's ground truth for the frame, if it has one
  size_t index = 0;           // in the recording
  std::string moved_png;      // FrameResult.moved's mask, when asked for and computed
  uint64_t keyframe_id = 0;   // when the frame became a stored keyframe
  double total_ms = 0;        // the server's time from receipt to reply
  // Its appearance matches (keyframes, best first), each with the relative pose verified.
  struct AppearanceHit {
    uint64_t visit_id = 0, keyframe_id = 0;
    double score = 0;
    Pose T_match_query;
  };
  std::vector<AppearanceHit> appearance;
};

struct UnposedStreamOptions {
  std::string robot = "lifemap eval";
  std::string visit_label;
  bool compact = false;  // JPEG colour + paletted depth, as a robot on a network would send
  double rate_hz = 0.0;  // 0: as fast as the server answers
  int max_frames = 0;    // 0: every frame
  // Frame.gravity from the recording's accelerometer.txt where it has one (the server levels
  // the visit's frame by the first frame's).
  bool send_gravity = true;
  // Frame.odometry from the recording's odometry.txt where it has one (a robot's wheels).
  bool send_odometry = false;
  // Frame.pose from the recording's ground truth, as a robot with its own localisation sends
  // it (`lifemap eval changes --poses truth`: changes judged apart from the server's alignment).
  bool send_truth_poses = false;
  // Each frame's moved mask against this visit (FrameOptions.moved_against_visit), kept in
  // TrackedFrame::moved_png; 0: none asked for (results carry no images).
  uint64_t moved_against_visit = 0;
};

// Adds `--gravity accelerometer|none` to a command, setting `*send_gravity`
// (UnposedStreamOptions::send_gravity); its value when called is the default the help names.
void AddGravityOption(CLI::App* cmd, bool* send_gravity);
// Adds `--odometry wheel|none` (UnposedStreamOptions::send_odometry; default none).
void AddOdometryOption(CLI::App* cmd, bool* send_odometry);
// Adds `--send as-recorded|compact` (UnposedStreamOptions::compact; default as-recorded).
void AddSendOption(CLI::App* cmd, bool* compact);

// Deletes an evaluation's scratch maps; one that cannot be deleted is named on stderr, with why.
void DeleteScratchMaps(client::Client& client, const std::vector<std::string>& maps);

struct StreamedVisit {
  uint64_t visit_id = 0;
  std::vector<TrackedFrame> frames;  // in frame order, one per answer
  int lost = 0;                      // frames answered TRACKING_LOST
  int rejected = 0;                  // frames answered with a per-frame error
  std::vector<double> track_ms;      // the server's tracking time per answered frame
  std::string intrinsics_source;     // where the camera intrinsics sent came from
  int frames_with_gravity = 0;       // frames sent with Frame.gravity
  int frames_with_odometry = 0;      // frames sent with Frame.odometry
  int placed_by_odometry = 0;        // frames answered TRACKING_METHOD_ODOMETRY
  // Tracked frames whose reference's depth left a direction free (Tracking.degenerate_axes),
  // and how many frames named each direction ("translation along y").
  int with_free_directions = 0;
  std::map<std::string, int> free_directions;
};

// FailedPrecondition naming the folder when `--odometry wheel` was asked of a recording with no
// usable odometry.txt (none, or no frame within it): never a silent run without odometry.
absl::Status CheckOdometryWanted(const io::TumSequence& sequence, bool send_odometry);

// Streams `sequence` into `map` (which must exist) without poses and collects every answer.
// Returns once the server ended the stream, i.e. after the visit's loop closures, pose-graph
// solves and anchoring have finished. A frame file that cannot be read: InvalidArgument naming
// it; odometry asked of a recording without it: CheckOdometryWanted's error; a stream the
// server broke: its status.
absl::StatusOr<StreamedVisit> StreamWithoutPoses(client::Client& client, const std::string& map,
                                                 const io::TumSequence& sequence,
                                                 const UnposedStreamOptions& options);

// The visit's keyframes as stored now, with the poses the server estimated (loop-closed, and in
// the map's frame once the visit is anchored), in timestamp order.
absl::StatusOr<std::vector<io::TimedPose>> StoredEstimatedKeyframes(client::Client& client,
                                                                    const std::string& map,
                                                                    uint64_t visit_id);
// The same with every stored pose, the client's too (visits streamed with poses).
absl::StatusOr<std::vector<io::TimedPose>> StoredPosedKeyframes(client::Client& client,
                                                                const std::string& map,
                                                                uint64_t visit_id);

}  // namespace lifemap::cli
