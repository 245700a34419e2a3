#include "client/cli/unposed_stream.h"

#include <algorithm>
#include <chrono>
#include <iostream>
#include <thread>

#include "absl/strings/str_cat.h"
#include "client/cli/commands.h"
#include "core/common/image_codec.h"

namespace lifemap::cli {
namespace {

// A pose as the server sent it, checked as any pose is (Pose::FromComponents).
absl::StatusOr<Pose> PoseOf(const v1::Pose& p) {
  return Pose::FromComponents(p.tx(), p.ty(), p.tz(), p.qx(), p.qy(), p.qz(), p.qw());
}

std::string TrackingName(v1::TrackingState s) {
  switch (s) {
    case v1::TRACKING_STARTED:
      return "started";
    case v1::TRACKING_OK:
      return "ok";
    case v1::TRACKING_LOST:
      return "lost";
    case v1::TRACKING_REGAINED:
      return "regained";
    default:
      return "none";
  }
}

std::string MethodName(v1::TrackingMethod m) {
  switch (m) {
    case v1::TRACKING_METHOD_DENSE:
      return "dense";
    case v1::TRACKING_METHOD_REFIT:
      return "refit";
    case v1::TRACKING_METHOD_FEATURES:
      return "features";
    case v1::TRACKING_METHOD_RELOCALISED:
      return "relocalised";
    case v1::TRACKING_METHOD_ODOMETRY:
      return "odometry";
    default:
      return "";
  }
}

}  // namespace

void AddGravityOption(CLI::App* cmd, bool* send_gravity) {
  const std::string accelerometer =
      "accelerometer (each frame's Frame.gravity from the recording's accelerometer.txt, where "
      "it has one)";
  cmd->add_option_function<std::string>(
         "--gravity",
         [send_gravity](const std::string& how) { *send_gravity = how == "accelerometer"; },
         *send_gravity ? accelerometer + ", the default, or none"
                       : accelerometer +
                             " or none "
                             "(the default)")
      ->check(CLI::IsMember({"accelerometer", "none"}));
}

void AddOdometryOption(CLI::App* cmd, bool* send_odometry) {
  cmd->add_option_function<std::string>(
         "--odometry", [send_odometry](const std::string& how) { *send_odometry = how == "wheel"; },
         "wheel (each frame's Frame.odometry from the recording's odometry.txt, where it has "
         "one: a robot's wheel odometry) or none (default)")
      ->check(CLI::IsMember({"wheel", "none"}));
}

void AddSendOption(CLI::App* cmd, bool* compact) {
  cmd->add_option_function<std::string>(
         "--send", [compact](const std::string& how) { *compact = how == "compact"; },
         "as-recorded (default) or compact (JPEG colour, paletted depth)")
      ->check(CLI::IsMember({"as-recorded", "compact"}));
}

void DeleteScratchMaps(client::Client& client, const std::vector<std::string>& maps) {
  for (const auto& m : maps) {
    if (auto d = client.DeleteMap(m); !d.ok()) {
      std::cerr << "lifemap: the scratch map '" << m << "' was not deleted: " << d.status() << "\n";
    }
  }
}

absl::Status CheckOdometryWanted(const io::TumSequence& sequence, bool send_odometry) {
  if (!send_odometry || sequence.frames_with_odometry > 0) return absl::OkStatus();
  return absl::FailedPreconditionError(absl::StrCat(
      sequence.dir, ": --odometry wheel given but ",
      sequence.has_odometry ? "no frame lies within odometry.txt" : "there is no odometry.txt"));
}

absl::StatusOr<StreamedVisit> StreamWithoutPoses(client::Client& client, const std::string& map,
                                                 const io::TumSequence& sequence,
                                                 const UnposedStreamOptions& options) {
  if (auto s = CheckOdometryWanted(sequence, options.send_odometry); !s.ok()) return s;
  size_t n = sequence.frames.size();
  if (options.max_frames > 0) n = std::min(n, static_cast<size_t>(options.max_frames));
  if (n == 0) return absl::InvalidArgumentError(absl::StrCat(sequence.dir, ": no frames"));
  auto first = ReadFileBytes(sequence.frames[0].rgb_path);
  if (!first.ok()) return first.status();
  auto header = ProbeImage(*first);
  if (!header.ok()) return header.status();
  StreamedVisit visit;
  const v1::CameraIntrinsics k = IntrinsicsProto(
      io::TumSequenceIntrinsics(sequence, header->width, header->height, &visit.intrinsics_source));

  v1::StreamStart start;
  start.set_map(map);
  start.set_robot(options.robot);
  start.set_visit_label(options.visit_label.empty() ? sequence.dir : options.visit_label);
  if (options.moved_against_visit != 0) {
    // The moved masks as PNG; the outputs not looked at are not computed.
    auto* o = start.mutable_options();
    o->set_moved_against_visit(options.moved_against_visit);
    o->set_result_images(v1::RESULT_IMAGES_PNG);
    o->add_skip_outputs(v1::FRAME_OUTPUT_ENTROPY_MASK);
    o->add_skip_outputs(v1::FRAME_OUTPUT_CLASS_LABELS);
    o->add_skip_outputs(v1::FRAME_OUTPUT_SEMANTIC_FUSION);
  } else {
    start.mutable_options()->set_result_images(v1::RESULT_IMAGES_NONE);
  }
  auto stream = client.OpenStream(start);
  if (!stream.ok()) return stream.status();

  std::string send_error;
  const auto t0 = std::chrono::steady_clock::now();
  std::thread sender([&] {
    for (size_t i = 0; i < n; ++i) {
      const auto& e = sequence.frames[i];
      if (options.rate_hz > 0) {
        std::this_thread::sleep_until(
            t0 + std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                     std::chrono::duration<double>(i / options.rate_hz)));
      }
      auto f = client::FrameFromFiles(e.rgb_path, e.depth_path, 5000.0, k, e.timestamp_s, i);
      if (f.ok() && options.compact) f = client::CompactFrame(*f);
      if (!f.ok()) {
        send_error = absl::StrCat(e.rgb_path, ": ", f.status().message());
        (*stream)->Cancel();
        break;
      }
      if (options.send_gravity && e.gravity_camera) {
        auto* g = f->mutable_gravity();
        g->set_x(e.gravity_camera->x());
        g->set_y(e.gravity_camera->y());
        g->set_z(e.gravity_camera->z());
        ++visit.frames_with_gravity;
      }
      if (options.send_odometry && e.T_odom_camera) {
        *f->mutable_odometry()->mutable_pose() = PoseProto(*e.T_odom_camera);
        ++visit.frames_with_odometry;
      }
      if (options.send_truth_poses && e.T_world_camera) {
        *f->mutable_pose() = PoseProto(*e.T_world_camera);
      }
      if (!(*stream)->Send(*f)) break;  // without a pose the server tracks the camera
    }
    (*stream)->CloseSend();
  });
  v1::FrameResult r;
  while ((*stream)->Receive(&r)) {
    TrackedFrame o;
    o.timestamp_s = r.timestamp_s();
    if (r.sequence() < sequence.frames.size()) {
      o.truth = sequence.frames[r.sequence()].T_world_camera;
      o.index = static_cast<size_t>(r.sequence());
    }
    if (r.has_moved()) o.moved_png = r.moved().mask_png();
    if (r.has_error()) {
      ++visit.rejected;
      o.state = "error";
    } else {
      o.state = TrackingName(r.tracking().state());
      o.method = MethodName(r.tracking().method());
      visit.placed_by_odometry += r.tracking().method() == v1::TRACKING_METHOD_ODOMETRY;
      visit.with_free_directions += r.tracking().degenerate_axes_size() > 0;
      for (const std::string& axis : r.tracking().degenerate_axes()) {
        ++visit.free_directions[axis.substr(0, axis.find(" ("))];
      }
      visit.lost += r.tracking().state() == v1::TRACKING_LOST;
      visit.track_ms.push_back(r.tracking().track_ms());
      if (r.pose_source() == v1::POSE_SOURCE_ESTIMATED) {
        if (auto pose = PoseOf(r.pose()); pose.ok()) {
          o.tracked = true;
          o.pose = *pose;
        }
      }
      o.keyframe = r.keyframe().committed();
      if (o.keyframe) o.keyframe_id = r.keyframe().keyframe_id();
      o.total_ms = r.timing().total_ms();
      for (const auto& m : r.place_matches()) {
        if (m.method() != v1::MATCH_METHOD_APPEARANCE) continue;
        auto T = PoseOf(m.t_match_query());
        if (!T.ok()) continue;
        o.appearance.push_back({m.visit_id(), m.keyframe_id(), m.score(), *T});
      }
    }
    visit.frames.push_back(o);
  }
  sender.join();
  const absl::Status finished = (*stream)->Finish();
  visit.visit_id = (*stream)->started().visit_id();
  if (!send_error.empty()) return absl::InvalidArgumentError(send_error);
  if (!finished.ok()) return finished;
  return visit;
}

namespace {

absl::StatusOr<std::vector<io::TimedPose>> StoredKeyframePoses(client::Client& client,
                                                               const std::string& map,
                                                               uint64_t visit_id,
                                                               bool estimated_only) {
  auto listed = client.ListKeyframes(map, visit_id);
  if (!listed.ok()) return listed.status();
  std::vector<io::TimedPose> stored;
  for (const auto& kf : listed->keyframes()) {
    if (estimated_only && kf.pose_source() != v1::POSE_SOURCE_ESTIMATED) continue;
    if (auto pose = PoseOf(kf.pose()); pose.ok()) stored.push_back({kf.timestamp_s(), *pose});
  }
  std::sort(stored.begin(), stored.end(), [](const io::TimedPose& a, const io::TimedPose& b) {
    return a.timestamp_s < b.timestamp_s;
  });
  return stored;
}

}  // namespace

absl::StatusOr<std::vector<io::TimedPose>> StoredEstimatedKeyframes(client::Client& client,
                                                                    const std::string& map,
                                                                    uint64_t visit_id) {
  return StoredKeyframePoses(client, map, visit_id, /*estimated_only=*/true);
}

absl::StatusOr<std::vector<io::TimedPose>> StoredPosedKeyframes(client::Client& client,
                                                                const std::string& map,
                                                                uint64_t visit_id) {
  return StoredKeyframePoses(client, map, visit_id, /*estimated_only=*/false);
}

}  // namespace lifemap::cli
