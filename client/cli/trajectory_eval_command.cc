// `lifemap eval trajectory`: streams a TUM-format recording to lifemapd without poses, as a
// robot without its own localisation would, and scores the server's estimated trajectory
// against the recording's ground truth in the TUM benchmark's convention (ATE RMSE after a
// rigid alignment, RPE over one second).
#include <algorithm>
#include <cmath>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <map>

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "client/cli/commands.h"
#include "client/cli/unposed_stream.h"
#include "core/eval/trajectory.h"
#include "core/io/tum_dataset.h"

namespace lifemap::cli {
namespace {

namespace fs = std::filesystem;

struct TrajectoryArgs {
  std::string tum_dir;
  std::string out;
  std::string map;  // empty: a scratch map, deleted afterwards
  bool keep_map = false;
  bool compact = false;
  bool send_gravity = true;    // --gravity accelerometer|none
  bool send_odometry = false;  // --odometry wheel|none
  double rate_hz = 0.0;
  int max_frames = 0;
};

// Top-down (x, y of the ground truth's frame) plot of the truth, the aligned estimate as
// answered frame by frame, and the stored keyframes after the visit's pose-graph solves
// (`stored`, aligned by `stored_align`).
std::string TopDownSvg(const std::vector<TrackedFrame>& frames, const Eigen::Isometry3d& align,
                       const std::vector<eval::TimedPose>& stored,
                       const Eigen::Isometry3d& stored_align) {
  std::vector<Eigen::Vector2d> truth, estimate, corrected;
  for (const auto& f : frames) {
    if (f.truth) truth.push_back(f.truth->translation.head<2>());
    if (f.tracked) estimate.push_back((align * f.pose.translation).head<2>());
  }
  for (const auto& k : stored) corrected.push_back((stored_align * k.pose.translation).head<2>());
  Eigen::Vector2d lo(1e9, 1e9), hi(-1e9, -1e9);
  for (const auto* set : {&truth, &estimate, &corrected}) {
    for (const auto& p : *set) {
      lo = lo.cwiseMin(p);
      hi = hi.cwiseMax(p);
    }
  }
  const double span = std::max({hi.x() - lo.x(), hi.y() - lo.y(), 0.05});
  const double scale = 500.0 / span, margin = 40.0;
  auto polyline = [&](const std::vector<Eigen::Vector2d>& pts, const char* colour) {
    std::string s = absl::StrCat("<polyline fill=\"none\" stroke=\"", colour,
                                 "\" stroke-width=\"2\" points=\"");
    for (const auto& p : pts) {
      absl::StrAppend(&s, absl::StrFormat("%.1f,%.1f ", margin + (p.x() - lo.x()) * scale,
                                          margin + (hi.y() - p.y()) * scale));
    }
    return s + "\"/>\n";
  };
  const double bar_px = std::pow(10.0, std::floor(std::log10(span))) * scale;
  std::string svg = absl::StrFormat(
      "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"%d\" height=\"%d\">\n"
      "<rect width=\"100%%\" height=\"100%%\" fill=\"white\"/>\n",
      static_cast<int>(2 * margin + (hi.x() - lo.x()) * scale) + 160,
      static_cast<int>(2 * margin + (hi.y() - lo.y()) * scale) + 40);
  svg +=
      polyline(truth, "#2b8a3e") + polyline(estimate, "#c92a2a") + polyline(corrected, "#1864ab");
  svg += absl::StrFormat(
      "<text x=\"10\" y=\"18\" font-family=\"sans-serif\" font-size=\"13\">top view (x, y): "
      "<tspan fill=\"#2b8a3e\">ground truth</tspan>, <tspan fill=\"#c92a2a\">lifemapd's "
      "estimate as answered</tspan>, <tspan fill=\"#1864ab\">keyframes as stored (loops "
      "closed)</tspan>, aligned</text>\n"
      "<line x1=\"%.1f\" y1=\"%.1f\" x2=\"%.1f\" y2=\"%.1f\" stroke=\"black\" "
      "stroke-width=\"2\"/><text x=\"%.1f\" y=\"%.1f\" font-family=\"sans-serif\" "
      "font-size=\"12\">%g m</text>\n</svg>\n",
      margin, margin + (hi.y() - lo.y()) * scale + 20, margin + bar_px,
      margin + (hi.y() - lo.y()) * scale + 20, margin + bar_px + 6,
      margin + (hi.y() - lo.y()) * scale + 24, bar_px / scale);
  return svg;
}

nlohmann::json ErrorsJson(const absl::StatusOr<eval::TrajectoryErrors>& e) {
  if (!e.ok()) return {{"error", std::string(e.status().message())}};
  return {{"associated", e->associated},   {"ate_rmse_m", e->ate_rmse_m},
          {"ate_max_m", e->ate_max_m},     {"rpe_trans_m", e->rpe_trans_m},
          {"rpe_rot_deg", e->rpe_rot_deg}, {"rpe_delta_s", e->rpe_delta_s}};
}

int RunTrajectoryEval(const CliContext& ctx, const TrajectoryArgs& a) {
  auto seq = io::ReadTumSequence(a.tum_dir);
  if (!seq.ok()) return Fail(seq.status());
  if (seq->frames_with_pose < 3) {
    return Fail(absl::FailedPreconditionError(
        absl::StrCat(a.tum_dir, ": needs a groundtruth.txt covering the frames to score against (",
                     seq->frames_with_pose, " frames have a ground-truth pose)")));
  }
  if (auto s = CheckOdometryWanted(*seq, a.send_odometry); !s.ok()) return Fail(s);
  std::error_code ec;
  fs::create_directories(a.out, ec);
  if (ec) {
    return Fail(absl::PermissionDeniedError(absl::StrCat(a.out, ": ", ec.message())));
  }
  auto client = ctx.Connect();
  if (!client.ok()) return Fail(client.status());
  const std::string map =
      a.map.empty() ? absl::StrCat("eval-trajectory-", std::time(nullptr)) : a.map;
  if (auto m = (*client)->CreateMap(map, "lifemap eval trajectory");
      !m.ok() && !absl::IsAlreadyExists(m.status())) {
    return Fail(m.status());
  }
  UnposedStreamOptions options;
  options.robot = "lifemap eval trajectory";
  options.compact = a.compact;
  options.send_gravity = a.send_gravity;
  options.send_odometry = a.send_odometry;
  options.rate_hz = a.rate_hz;
  options.max_frames = a.max_frames;
  auto streamed = StreamWithoutPoses(**client, map, *seq, options);
  if (!streamed.ok()) return Fail(streamed.status());
  const std::vector<TrackedFrame>& frames = streamed->frames;
  const uint64_t visit = streamed->visit_id;
  const int lost = streamed->lost;
  std::vector<double> track_ms = streamed->track_ms;

  const std::vector<eval::TimedPose> truth = eval::GroundTruth(*seq);
  std::vector<eval::TimedPose> all, keyframes;
  for (const auto& f : frames) {
    if (!f.tracked) continue;
    all.push_back({f.timestamp_s, f.pose});
    if (f.keyframe) keyframes.push_back({f.timestamp_s, f.pose});
  }
  // The keyframes as stored once the stream ended: the server waits for the visit's loop
  // closures and pose-graph solves before it ends a stream.
  auto stored = StoredEstimatedKeyframes(**client, map, visit);
  if (!stored.ok()) return Fail(stored.status());
  const auto stored_errors = eval::CompareTrajectories(*stored, truth);
  const auto kf_errors = eval::CompareTrajectories(keyframes, truth);
  const auto all_errors = eval::CompareTrajectories(all, truth);
  // How many tracked frames each estimate gave (docs/API.md "Tracking").
  nlohmann::json by_method = {
      {"dense", 0}, {"refit", 0}, {"features", 0}, {"relocalised", 0}, {"odometry", 0}};
  for (const auto& f : frames) {
    if (!f.method.empty()) by_method[f.method] = by_method.value(f.method, 0) + 1;
  }
  std::sort(track_ms.begin(), track_ms.end());
  const double track_p50 = track_ms.empty() ? 0.0 : track_ms[track_ms.size() / 2];

  nlohmann::json summary = {
      {"recording", a.tum_dir},
      {"map", map},
      {"visit", visit},
      {"frames", frames.size()},
      {"lost_frames", lost},
      {"rejected_frames", streamed->rejected},
      {"keyframes", keyframes.size()},
      {"intrinsics", streamed->intrinsics_source},
      {"sent", a.compact ? "compact" : "as-recorded"},
      {"frames_with_gravity", streamed->frames_with_gravity},
      {"frames_with_odometry", streamed->frames_with_odometry},
      {"track_ms_p50", track_p50},
      {"frames_by_method", by_method},
      {"frames_with_free_directions", streamed->with_free_directions},
      {"free_directions", streamed->free_directions},
      {"keyframe_trajectory", ErrorsJson(kf_errors)},
      {"stored_keyframes", ErrorsJson(stored_errors)},
      {"all_frames", ErrorsJson(all_errors)},
  };
  // The headline figures: the keyframes as stored (loops closed), else every tracked
  // frame as answered when there are too few keyframes to align.
  const auto& headline = stored_errors.ok() ? stored_errors : all_errors;
  if (headline.ok()) {
    summary["ate_rmse_m"] = headline->ate_rmse_m;
    summary["rpe_trans_m"] = headline->rpe_trans_m;
    summary["rpe_rot_deg"] = headline->rpe_rot_deg;
    summary["scored"] =
        stored_errors.ok() ? "stored keyframes" : "all frames (fewer than 3 keyframes)";
  }
  std::ofstream(fs::path(a.out) / "summary.json") << summary.dump(2) << "\n";
  {
    std::ofstream csv(fs::path(a.out) / "trajectory.csv");
    csv << "timestamp_s,state,method,keyframe,est_x,est_y,est_z,truth_x,truth_y,truth_z\n";
    const Eigen::Isometry3d align =
        all_errors.ok() ? all_errors->T_truth_estimate : Eigen::Isometry3d::Identity();
    for (const auto& f : frames) {
      csv << absl::StrFormat("%.6f,%s,%s,%d,", f.timestamp_s, f.state, f.method,
                             f.keyframe ? 1 : 0);
      if (f.tracked) {
        const Eigen::Vector3d p = align * f.pose.translation;
        csv << absl::StrFormat("%.5f,%.5f,%.5f,", p.x(), p.y(), p.z());
      } else {
        csv << ",,,";
      }
      if (f.truth) {
        csv << absl::StrFormat("%.5f,%.5f,%.5f", f.truth->translation.x(), f.truth->translation.y(),
                               f.truth->translation.z());
      } else {
        csv << ",,";
      }
      csv << "\n";
    }
    if (all_errors.ok()) {
      std::ofstream(fs::path(a.out) / "trajectory.svg") << TopDownSvg(
          frames, all_errors->T_truth_estimate, *stored,
          stored_errors.ok() ? stored_errors->T_truth_estimate : all_errors->T_truth_estimate);
    }
  }
  if (a.map.empty() && !a.keep_map) DeleteScratchMaps(**client, {map});
  if (ctx.json) {
    std::cout << summary.dump() << "\n";
  } else {
    std::cout << absl::StrFormat(
        "%s: %d frames sent without poses, %d lost, %d keyframes; tracking p50 %.1f ms\n",
        a.tum_dir, frames.size(), lost, keyframes.size(), track_p50);
    for (const auto& [name, e] :
         {std::pair{"stored", &stored_errors}, std::pair{"keyframes", &kf_errors},
          std::pair{"all frames", &all_errors}}) {
      if (e->ok()) {
        std::cout << absl::StrFormat(
            "  %-10s ATE RMSE %.1f mm (max %.1f), RPE %.1f mm / %.2f deg over %.2f s (%d poses)\n",
            name, (*e)->ate_rmse_m * 1000, (*e)->ate_max_m * 1000, (*e)->rpe_trans_m * 1000,
            (*e)->rpe_rot_deg, (*e)->rpe_delta_s, (*e)->associated);
      } else {
        std::cout << "  " << name << ": " << e->status().message() << "\n";
      }
    }
    std::cout << "wrote " << a.out << "/summary.json, trajectory.csv, trajectory.svg\n";
  }
  return 0;
}

}  // namespace

void AddTrajectoryEvalCommand(CLI::App* eval, CliContext* ctx) {
  auto* cmd = eval->add_subcommand(
      "trajectory",
      "Stream a TUM recording to lifemapd without poses and score the server's tracked "
      "trajectory against the ground truth (ATE, RPE)");
  auto a = std::make_shared<TrajectoryArgs>();
  cmd->add_option("--tum", a->tum_dir, "TUM-format folder with groundtruth.txt")
      ->required()
      ->check(CLI::ExistingDirectory);
  cmd->add_option("--out", a->out, "folder for summary.json, trajectory.csv, trajectory.svg")
      ->required();
  cmd->add_option("--map", a->map,
                  "map to stream into (created if missing; default: a scratch map, deleted after)");
  cmd->add_flag("--keep-map", a->keep_map, "keep the scratch map");
  cmd->add_option("--rate", a->rate_hz, "frames per second (default 0: as fast as served)")
      ->check(CLI::Range(0.0, 1000.0));
  cmd->add_option("--max-frames", a->max_frames, "stop after N frames")
      ->check(CLI::Range(1, 10000000));
  AddSendOption(cmd, &a->compact);
  AddGravityOption(cmd, &a->send_gravity);
  AddOdometryOption(cmd, &a->send_odometry);
  cmd->callback([ctx, a] { ctx->run = [ctx, a] { return RunTrajectoryEval(*ctx, *a); }; });
}

}  // namespace lifemap::cli
