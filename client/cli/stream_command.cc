// `lifemap stream`: replays a TUM-format recording into a map as a robot would.
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <mutex>
#include <thread>

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "client/cli/commands.h"
#include "client/cli/output.h"
#include "client/cli/unposed_stream.h"
#include "core/common/image_codec.h"
#include "core/io/tum_dataset.h"

namespace lifemap::cli {
namespace {

using Clock = std::chrono::steady_clock;

struct StreamArgs {
  std::string map;
  std::string tum_dir;
  double rate_hz = -1.0;  // < 0: the recording's own timing; 0: as fast as the server takes
  bool use_groundtruth = false;
  bool send_odometry = false;  // --odometry wheel: Frame.odometry from odometry.txt
  bool send_gravity = false;   // --gravity accelerometer: Frame.gravity from accelerometer.txt
  std::string visit_label;
  std::string robot;
  uint64_t visit_id = 0;
  uint64_t moved_against = 0;  // --moved-against: FrameOptions.moved_against_visit
  std::string intrinsics;
  double depth_scale = 5000.0;
  int max_frames = 0;
  bool create_map = false;
  std::string associations;
  bool end_visit = false;  // --end-visit: end the visit once the recording is sent
  bool compact = false;    // --send compact: JPEG colour, paletted depth (client::CompactFrame)
  // --result-images: "png" (in the results, base64 in --json), "none", or a folder the PNGs
  // are written into (the JSON then names the files).
  std::string result_images = "png";
  // A stream that breaks with UNAVAILABLE (a shard's map moving, nginx or a server restarted)
  // is opened again on the same visit for up to this long, and the frames not yet answered are
  // sent again; 0 = never (the default: a script sees the break at once).
  double reconnect_s = 0.0;
};

// Writes a result's PNGs into `dir` as SEQUENCE_<what>.png, clears them from `result`, and
// returns the paths written.
absl::StatusOr<std::vector<std::string>> WriteResultImages(const std::string& dir,
                                                           v1::FrameResult* result) {
  std::vector<std::string> written;
  const std::string prefix = absl::StrFormat("%06d_", result->sequence());
  const std::pair<const char*, std::string*> images[] = {
      {"entropy_score", result->mutable_entropy()->mutable_score_png()},
      {"entropy_mask", result->mutable_entropy()->mutable_mask_png()},
      {"labels", result->mutable_labels()->mutable_label_png()},
      {"label_confidence", result->mutable_labels()->mutable_confidence_png()},
      {"fused_labels", result->mutable_fused_labels()->mutable_label_png()},
      {"fused_confidence", result->mutable_fused_labels()->mutable_confidence_png()},
      {"moved", result->mutable_moved()->mutable_mask_png()},
  };
  for (const auto& [what, bytes] : images) {
    if (bytes->empty()) continue;
    const std::string path = (std::filesystem::path(dir) / (prefix + what + ".png")).string();
    std::ofstream out(path, std::ios::binary);
    out.write(bytes->data(), static_cast<std::streamsize>(bytes->size()));
    if (!out) return absl::UnavailableError("cannot write " + path);
    written.push_back(path);
    bytes->clear();
  }
  return written;
}

int RunStream(const CliContext& ctx, const StreamArgs& a) {
  if (a.rate_hz > 1000.0) {
    return UsageError("--rate must be at most 1000 Hz (0 = as fast as the server takes)");
  }
  io::TumReadOptions read_options;
  read_options.associations_file = a.associations;
  auto seq = io::ReadTumSequence(a.tum_dir, read_options);
  if (!seq.ok()) return Fail(seq.status());
  if (a.use_groundtruth && seq->frames_with_pose == 0) {
    return Fail(absl::FailedPreconditionError(
        absl::StrCat(a.tum_dir, ": --use-groundtruth given but ",
                     seq->has_groundtruth ? "no frame lies within groundtruth.txt"
                                          : "there is no groundtruth.txt")));
  }
  if (auto s = CheckOdometryWanted(*seq, a.send_odometry); !s.ok()) return Fail(s);
  size_t n = seq->frames.size();
  if (a.max_frames > 0) n = std::min(n, static_cast<size_t>(a.max_frames));

  // Intrinsics: the flag, else the folder's intrinsics.txt, else TUM's calibration by name.
  auto first = ReadFileBytes(seq->frames[0].rgb_path);
  if (!first.ok()) return Fail(first.status());
  auto header = ProbeImage(*first);
  if (!header.ok()) {
    return Fail(absl::InvalidArgumentError(
        absl::StrCat(seq->frames[0].rgb_path, ": ", header.status().message())));
  }
  v1::CameraIntrinsics k;
  std::string intrinsics_source;
  if (!a.intrinsics.empty()) {
    auto parsed = ParseIntrinsicsFlag(a.intrinsics, header->width, header->height);
    if (!parsed.ok()) {
      return UsageError(std::string(parsed.status().message()));
    }
    k = *parsed;
    intrinsics_source = "--intrinsics";
  } else {
    k = IntrinsicsProto(
        io::TumSequenceIntrinsics(*seq, header->width, header->height, &intrinsics_source));
  }

  auto client = ctx.Connect();
  if (!client.ok()) return Fail(client.status());
  if (a.create_map) {
    auto created = (*client)->CreateMap(a.map, "");
    if (!created.ok() && !absl::IsAlreadyExists(created.status())) return Fail(created.status());
  } else if (auto m = (*client)->GetMap(a.map); !m.ok()) {
    if (absl::IsNotFound(m.status())) {
      return Fail(absl::NotFoundError(
          absl::StrCat("map '", a.map, "' does not exist: create it with 'lifemap maps create ",
                       a.map, "' (or pass --create-map)")));
    }
    return Fail(m.status());
  }

  v1::StreamStart start;
  start.set_map(a.map);
  start.set_visit_id(a.visit_id);
  start.set_visit_label(a.visit_label);
  if (a.moved_against != 0) start.mutable_options()->set_moved_against_visit(a.moved_against);
  const bool images_to_files = a.result_images != "png" && a.result_images != "none";
  if (a.result_images == "none") {
    start.mutable_options()->set_result_images(v1::RESULT_IMAGES_NONE);
  } else {
    start.mutable_options()->set_result_images(v1::RESULT_IMAGES_PNG);
  }
  if (images_to_files) {
    std::error_code ec;
    std::filesystem::create_directories(a.result_images, ec);
    if (ec) {
      return Fail(absl::UnavailableError(
          absl::StrCat("cannot make --result-images ", a.result_images, ": ", ec.message())));
    }
  }
  if (a.robot.empty()) {
    char host[256] = {0};
    gethostname(host, sizeof(host) - 1);
    start.set_robot(absl::StrCat("lifemap-cli@", host));
  } else {
    start.set_robot(a.robot);
  }
  auto stream = (*client)->OpenStream(start);
  if (!stream.ok()) return Fail(stream.status());
  const uint64_t visit_id = (*stream)->started().visit_id();
  // Reconnections resume this visit.
  start.set_visit_id(visit_id);
  const bool progress = !ctx.json && isatty(STDERR_FILENO);
  if (!ctx.json) {
    std::cerr << absl::StrFormat(
        "streaming %d frames of %s into map '%s', %s visit %d (intrinsics: %s%s)\n", n, a.tum_dir,
        a.map, (*stream)->started().new_visit() ? "new" : "resumed", visit_id, intrinsics_source,
        a.use_groundtruth ? "; poses from groundtruth.txt" : "");
    if (seq->listed_but_missing > 0) {
      std::cerr << absl::StrFormat(
          "  note: %d files named in %s are not on disk; only the %d complete colour/depth pairs "
          "are sent\n",
          seq->listed_but_missing, a.associations.empty() ? "rgb.txt/depth.txt" : a.associations,
          seq->frames.size());
    }
  }

  std::mutex sent_mu;
  std::map<uint64_t, Clock::time_point> sent_at;
  std::atomic<size_t> sent{0};
  std::atomic<size_t> sent_with_gravity{0};
  std::string send_error;
  const auto t0 = Clock::now();
  size_t answered_upto = 0;  // frames [0, answered_upto) have their results (they come in order)
  size_t reconnections = 0;
  // One stream session: sends frames from `from` on.
  const auto send_from = [&](size_t from) {
    const double first_ts = seq->frames[0].timestamp_s;
    for (size_t i = from; i < n; ++i) {
      const auto& e = seq->frames[i];
      if (a.rate_hz != 0.0) {
        const double offset_s = a.rate_hz < 0 ? e.timestamp_s - first_ts : i / a.rate_hz;
        std::this_thread::sleep_until(t0 + std::chrono::duration_cast<Clock::duration>(
                                               std::chrono::duration<double>(offset_s)));
      }
      auto frame =
          client::FrameFromFiles(e.rgb_path, e.depth_path, a.depth_scale, k, e.timestamp_s, i);
      if (frame.ok() && a.compact) {
        frame = client::CompactFrame(*frame);
        if (!frame.ok()) {
          frame = absl::Status(frame.status().code(),
                               absl::StrCat(e.rgb_path, ": ", frame.status().message()));
        }
      }
      if (!frame.ok()) {
        send_error = std::string(frame.status().message());
        (*stream)->Cancel();
        break;
      }
      if (a.use_groundtruth && e.T_world_camera) {
        *frame->mutable_pose() = PoseProto(*e.T_world_camera);
      }
      if (a.send_odometry && e.T_odom_camera) {
        *frame->mutable_odometry()->mutable_pose() = PoseProto(*e.T_odom_camera);
      }
      if (a.send_gravity && e.gravity_camera) {
        auto* g = frame->mutable_gravity();
        g->set_x(e.gravity_camera->x());
        g->set_y(e.gravity_camera->y());
        g->set_z(e.gravity_camera->z());
        sent_with_gravity.fetch_add(1);
      }
      {
        std::lock_guard<std::mutex> lock(sent_mu);
        sent_at[i] = Clock::now();
      }
      if (!(*stream)->Send(*frame)) break;
      sent.fetch_add(1);
    }
    (*stream)->CloseSend();
  };
  std::thread sender(send_from, 0);

  std::vector<double> latencies_ms;
  std::vector<uint64_t> keyframe_ids;
  std::map<std::string, size_t> keyframes_refused;  // by the server's reason
  size_t results = 0, rejected = 0;
  size_t tracked = 0, lost_by_tracker = 0;  // frames the server tracked (sent without a pose)
  v1::FrameResult result;
  absl::Status final_status;
  for (;;) {
    while ((*stream)->Receive(&result)) {
      // A frame refused because the way is closing (its map moving to another shard) is sent
      // again after the reconnection, not counted as answered.
      if (result.has_error() && a.reconnect_s > 0 &&
          result.error().code() == static_cast<int>(absl::StatusCode::kUnavailable)) {
        continue;
      }
      answered_upto = std::max(answered_upto, static_cast<size_t>(result.sequence()) + 1);
      const auto now = Clock::now();
      double latency_ms = 0.0;
      {
        std::lock_guard<std::mutex> lock(sent_mu);
        auto it = sent_at.find(result.sequence());
        if (it != sent_at.end()) {
          latency_ms = std::chrono::duration<double, std::milli>(now - it->second).count();
          sent_at.erase(it);
        }
      }
      ++results;
      latencies_ms.push_back(latency_ms);
      if (result.has_error()) {
        ++rejected;
        if (!ctx.json) {
          std::cerr << (progress ? "\n" : "") << "frame " << result.sequence()
                    << " rejected: " << result.error().message() << "\n";
        }
      }
      if (result.has_tracking()) {
        ++tracked;
        if (result.tracking().state() == v1::TRACKING_LOST) ++lost_by_tracker;
      }
      if (result.keyframe().committed()) {
        keyframe_ids.push_back(result.keyframe().keyframe_id());
      } else if (result.keyframe().selected()) {
        ++keyframes_refused[result.keyframe().reason()];
      }
      std::vector<std::string> image_files;
      if (images_to_files) {
        auto written = WriteResultImages(a.result_images, &result);
        if (!written.ok()) {
          (*stream)->Cancel();
          return Fail(written.status());
        }
        image_files = *std::move(written);
      }
      if (ctx.json) {
        nlohmann::json line = nlohmann::json::parse(ToJson(result, false));
        line["client_latency_ms"] = latency_ms;
        if (images_to_files) line["image_files"] = image_files;
        std::cout << line.dump() << std::endl;
      } else if (progress) {
        const double elapsed = std::chrono::duration<double>(now - t0).count();
        std::cerr << absl::StrFormat("\r  frames %d/%d  keyframes %d  %.1f frames/s   ", results, n,
                                     keyframe_ids.size(), results / std::max(elapsed, 1e-9));
      }
    }
    sender.join();
    final_status = (*stream)->Finish();
    // Broken by the way there, not by the server's judgement of the frames: open the visit
    // again and send what has no answer yet. Results already received are kept (a frame whose
    // answer was lost may be stored twice; an acknowledged one is never lost).
    if (!absl::IsUnavailable(final_status) || a.reconnect_s <= 0 || answered_upto >= n ||
        !send_error.empty()) {
      break;
    }
    const auto give_up = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                            std::chrono::duration<double>(a.reconnect_s));
    if (!ctx.json) {
      std::cerr << (progress ? "\n" : "") << "stream broke (" << final_status.message()
                << "): reconnecting to resume visit " << visit_id << " at frame " << answered_upto
                << "\n";
    }
    absl::StatusOr<std::unique_ptr<client::FrameStream>> again = final_status;
    for (int attempt = 0; Clock::now() < give_up; ++attempt) {
      std::this_thread::sleep_for(
          std::chrono::milliseconds(std::min(2000, 100 << std::min(attempt, 5))));
      again = (*client)->OpenStream(start);
      if (again.ok() || !absl::IsUnavailable(again.status())) break;
    }
    if (!again.ok()) {
      final_status = again.status();
      break;
    }
    ++reconnections;
    *stream = *std::move(again);
    {
      std::lock_guard<std::mutex> lock(sent_mu);
      sent_at.clear();
    }
    sent.store(answered_upto);
    sender = std::thread(send_from, answered_upto);
  }
  const double elapsed_s = std::chrono::duration<double>(Clock::now() - t0).count();
  if (progress) std::cerr << "\n";

  // Why the stream ended early, and whether the visit can be resumed.
  absl::Status ended = final_status;
  if (!send_error.empty()) ended = absl::InvalidArgumentError(send_error);
  std::string resume;
  if (!ended.ok() && !absl::IsNotFound(ended) && !absl::IsFailedPrecondition(ended) &&
      !absl::IsInvalidArgument(ended)) {
    resume =
        absl::StrFormat("lifemap stream --map %s --tum %s --visit %d", a.map, a.tum_dir, visit_id);
  }
  // The visit ended when asked (--end-visit), and where it stands: in the map's frame, anchored
  // to another visit, or in a frame of its own (issue 35: a visit says where it is).
  absl::Status end_status;
  const bool end_asked = a.end_visit && (ended.ok() || absl::IsCancelled(ended));
  if (end_asked) end_status = (*client)->EndVisit(visit_id).status();
  std::string visit_frame = "unknown";
  std::string visit_frame_text;
  if (auto listed = (*client)->ListVisits(a.map); listed.ok()) {
    for (const auto& v : listed->visits()) {
      if (v.id() != visit_id) continue;
      switch (v.frame()) {
        case v1::VISIT_FRAME_MAP:
          visit_frame = "map";
          visit_frame_text = "in the map's frame";
          break;
        case v1::VISIT_FRAME_ANCHORED:
          visit_frame = "anchored";
          visit_frame_text = absl::StrFormat("anchored to visit %d (residual %.3f m, %.2f deg)",
                                             v.anchor().to_visit(), v.anchor().residual_m(),
                                             v.anchor().residual_deg());
          break;
        case v1::VISIT_FRAME_UNANCHORED:
          visit_frame = "unanchored";
          visit_frame_text =
              "not anchored: its poses are in its own frame (no other visit of the map "
              "matched it yet)";
          break;
        default:
          break;
      }
    }
  }
  size_t refused = 0;
  for (const auto& [reason, count] : keyframes_refused) refused += count;
  const double fps = results / std::max(elapsed_s, 1e-9);
  const double p50 = Percentile(latencies_ms, 50), p99 = Percentile(latencies_ms, 99);
  if (ctx.json) {
    // 64-bit ids as strings, as protobuf's JSON mapping writes them in the per-frame results.
    std::vector<std::string> keyframe_id_strings;
    for (const uint64_t id : keyframe_ids) keyframe_id_strings.push_back(std::to_string(id));
    nlohmann::json summary = {
        {"map", a.map},
        {"visit_id", std::to_string(visit_id)},
        {"pairs_found", seq->frames.size()},
        {"files_missing", seq->listed_but_missing},
        {"frames_sent", sent.load()},
        {"frames_with_gravity", sent_with_gravity.load()},
        {"results", results},
        {"frames_rejected", rejected},
        {"keyframes_stored", keyframe_ids.size()},
        {"keyframe_ids", keyframe_id_strings},
        {"keyframes_refused", refused},
        {"keyframes_refused_by_reason", keyframes_refused},
        {"elapsed_s", elapsed_s},
        {"frames_per_s", fps},
        {"latency_ms", {{"p50", p50}, {"p99", p99}}},
        {"frames_tracked", tracked},
        {"frames_lost_by_tracker", lost_by_tracker},
        {"visit_frame", visit_frame},
        {"visit_ended", end_asked && end_status.ok()},
        {"reconnections", reconnections},
    };
    if (!end_status.ok()) summary["end_visit_error"] = std::string(end_status.message());
    if (!ended.ok()) {
      summary["error"] = {{"code", absl::StatusCodeToString(ended.code())},
                          {"message", std::string(ended.message())}};
      if (!resume.empty()) summary["resume_with"] = resume;
    }
    std::cout << nlohmann::json{{"summary", summary}}.dump() << std::endl;
  } else {
    std::cout << absl::StrFormat(
        "map '%s' visit %d: %d frames sent, %d answered (%d rejected), %d keyframes stored, %d "
        "refused\n%.1f frames/s over %.2f s; latency p50 %.1f ms, p99 %.1f ms\n",
        a.map, visit_id, sent.load(), results, rejected, keyframe_ids.size(), refused, fps,
        elapsed_s, p50, p99);
    for (const auto& [reason, count] : keyframes_refused) {
      std::cout << absl::StrFormat("  %d keyframes refused: %s\n", count, reason);
    }
    if (tracked > 0) {
      std::cout << absl::StrFormat("tracked by the server: %d frames lost of %d\n", lost_by_tracker,
                                   tracked);
    }
    if (!visit_frame_text.empty()) {
      std::cout << absl::StrFormat("visit %d %s%s\n", visit_id, visit_frame_text,
                                   a.end_visit && end_status.ok() ? "; ended" : "");
    }
    if (!end_status.ok()) {
      std::cout << "visit not ended: " << end_status.message() << "\n";
    }
  }
  if (!ended.ok()) {
    std::string what = absl::StrFormat(
        "the stream ended early after %d of %d frames: %s; %d keyframes of visit %d were stored "
        "before",
        sent.load(), n, ended.message(), keyframe_ids.size(), visit_id);
    if (!resume.empty()) absl::StrAppend(&what, "; resume the visit with: ", resume);
    // With --json the summary above already holds the error.
    std::cerr << "lifemap: " << what << " [" << absl::StatusCodeToString(ended.code()) << "]\n";
    return 1;
  }
  return rejected == 0 && refused == 0 && end_status.ok() ? 0 : 1;
}

}  // namespace

void AddStreamCommand(CLI::App* app, CliContext* ctx) {
  auto* stream = app->add_subcommand(
      "stream", "Replay a TUM-format RGB-D recording into a map, as a robot would");
  auto a = std::make_shared<StreamArgs>();
  stream->add_option("MAP,--map", a->map, "map to stream into (--map MAP: deprecated, as before)")
      ->required();
  stream->add_option("--tum", a->tum_dir, "TUM-format folder (rgb.txt, depth.txt, ...)")
      ->required()
      ->check(CLI::ExistingDirectory);
  stream->add_option("--rate", a->rate_hz,
                     "frames per second; 0 = as fast as the server takes them "
                     "(default: the recording's own timing)");
  stream->add_flag("--use-groundtruth", a->use_groundtruth,
                   "send poses from groundtruth.txt (interpolated to each frame)");
  stream->add_option("--visit-label", a->visit_label, "label of the new visit");
  stream->add_option("--visit", a->visit_id, "resume this open visit instead of starting one");
  stream->add_option("--moved-against", a->moved_against,
                     "each frame's moved mask compares against this ended visit of the map "
                     "(default: the map's latest earlier one in its frame)");
  stream->add_option("--robot", a->robot, "robot name (default lifemap-cli@HOST)");
  stream->add_option("--intrinsics", a->intrinsics,
                     "FX,FY,CX,CY (default: DIR/intrinsics.txt or the TUM camera's)");
  stream->add_option("--depth-scale", a->depth_scale, "depth units per metre (TUM: 5000)");
  stream->add_option("--max-frames", a->max_frames, "stop after N frames");
  stream->add_option("--associations", a->associations,
                     "file of 't_rgb rgb t_depth depth' pairs (default: pair rgb.txt/depth.txt)");
  AddOdometryOption(stream, &a->send_odometry);
  AddGravityOption(stream, &a->send_gravity);
  stream->add_flag("--create-map", a->create_map, "create the map if it does not exist");
  stream->add_flag("--end-visit", a->end_visit,
                   "end the visit once the recording is sent (else it stays open to resume)");
  stream
      ->add_option_function<std::string>(
          "--send", [a](const std::string& how) { a->compact = how == "compact"; },
          "how frames travel: as-recorded (the files as they are; the default) or compact "
          "(JPEG colour, lossless paletted depth: ~4x fewer bytes, ~6x cheaper for the server "
          "to decode)")
      ->check(CLI::IsMember({"as-recorded", "compact"}));
  stream->add_option(
      "--result-images", a->result_images,
      "png (the default: the result images inside each result, base64 in --json), none (the "
      "tables only: less server CPU, and --json lines without base64 images), or a "
      "folder: each result's PNGs written there as SEQUENCE_<what>.png (entropy_score, "
      "entropy_mask, labels, label_confidence, fused_labels, fused_confidence, moved) and "
      "named in --json's image_files");
  stream
      ->add_option("--reconnect-s", a->reconnect_s,
                   "when the stream breaks with UNAVAILABLE (a map moving between shards, a "
                   "restart), reopen the visit for up to this long and send again the frames "
                   "not yet answered; 0 = never")
      ->capture_default_str()
      ->check(CLI::Range(0.0, 86400.0));
  stream->callback([ctx, a] { ctx->run = [ctx, a] { return RunStream(*ctx, *a); }; });
}

}  // namespace lifemap::cli
