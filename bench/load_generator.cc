// End-to-end load generator: N concurrent frame streams × M frames against a real lifemapd on
// loopback, reporting frames/s and latency percentiles, with a baseline in the same run
// (unary ProcessFrame without storage, one call at a time).
//
//   build/bin/load_generator --streams 4 --frames 300 --rate 30
//   build/bin/load_generator --server 127.0.0.1:50051 ...   (an external lifemapd; an API key
//                                                            in $LIFEMAP_API_KEY when it needs one)
//   build/bin/load_generator --soak-s 600 --streams 4 ...   (the soak: see --help)
//
// Without --server it starts lifemapd in-process on a temporary database. Frames are the real
// TUM recording (default ../shared/data/tum_fr1_xyz_subset), loaded into memory first and
// replayed cyclically with fresh timestamps, so disk reads are not measured. Each run also
// reports the server's CPU per answered frame (GetStats.process_cpu_s before and after; JSON
// `server_cpu_ms_per_frame`): the server alone with --server, with the generator's own CPU
// included in-process.
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdlib>
#include <ctime>
#include <filesystem>
#include <iostream>
#include <map>
#include <mutex>
#include <set>
#include <sstream>
#include <thread>

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include "absl/strings/str_format.h"
#include "client/lifemap_client.h"
#include "core/common/image_codec.h"
#include "core/io/tum_dataset.h"
#include "server/server.h"

namespace {

using Clock = std::chrono::steady_clock;
namespace fs = std::filesystem;

struct Latencies {
  std::vector<double> ms;
  double Percentile(double p) const {
    if (ms.empty()) return 0.0;
    std::vector<double> v = ms;
    std::sort(v.begin(), v.end());
    return v[std::min(v.size() - 1, static_cast<size_t>(p / 100.0 * (v.size() - 1) + 0.5))];
  }
};

struct RunReport {
  std::string name;
  size_t frames = 0;
  size_t errors = 0;
  size_t keyframes = 0;
  double seconds = 0;
  Latencies latency;
  Latencies keyframe_latency;      // the robot's latency of frames that became keyframes
  Latencies keyframe_commit_wait;  // server time keyframes waited for their commit
  double server_total_p50_ms = 0;
  double server_cpu_s = -1;  // the server's CPU time over the run (GetStats), < 0 unknown

  // Server CPU per answered frame, milliseconds; < 0 unknown.
  double CpuMsPerFrame() const {
    return server_cpu_s < 0 || frames == 0 ? -1.0 : 1000.0 * server_cpu_s / frames;
  }

  nlohmann::json ToJson() const {
    return {{"name", name},
            {"frames", frames},
            {"errors", errors},
            {"keyframes_committed", keyframes},
            {"seconds", seconds},
            {"frames_per_s", frames / std::max(seconds, 1e-9)},
            {"latency_ms",
             {{"p50", latency.Percentile(50)},
              {"p90", latency.Percentile(90)},
              {"p99", latency.Percentile(99)},
              {"max", latency.Percentile(100)}}},
            {"keyframe_latency_ms",
             {{"p50", keyframe_latency.Percentile(50)}, {"p99", keyframe_latency.Percentile(99)}}},
            {"keyframe_commit_wait_p50_ms", keyframe_commit_wait.Percentile(50)},
            {"server_time_p50_ms", server_total_p50_ms},
            {"server_cpu_ms_per_frame",
             CpuMsPerFrame() < 0 ? nlohmann::json() : nlohmann::json(CpuMsPerFrame())}};
  }
  void Print() const {
    std::cout << absl::StrFormat(
        "%-34s %6d frames %4d errors %5d keyframes %8.1f frames/s  latency p50 %6.1f  p90 %6.1f  "
        "p99 %6.1f ms (server %.1f ms, CPU %s per frame)\n",
        name, frames, errors, keyframes, frames / std::max(seconds, 1e-9), latency.Percentile(50),
        latency.Percentile(90), latency.Percentile(99), server_total_p50_ms,
        CpuMsPerFrame() < 0 ? std::string("?") : absl::StrFormat("%.1f ms", CpuMsPerFrame()));
  }
};

// Client options for `target`, with the API key in $LIFEMAP_API_KEY when set (a server that
// requires keys: the key needs the operator role for the runs, admin for nothing).
// The maps the streams write (--maps; a cluster's figures spread them over shards): stream s
// writes maps[s % size].
std::vector<std::string>& StreamMaps() {
  static auto* maps = new std::vector<std::string>{"load"};
  return *maps;
}
const std::string& MapFor(int stream) {
  return StreamMaps()[static_cast<size_t>(stream) % StreamMaps().size()];
}

lifemap::client::ClientOptions OptionsFor(const std::string& target) {
  auto options = lifemap::client::ClientOptions::At(target);
  if (const char* key = std::getenv("LIFEMAP_API_KEY"); key != nullptr) options.api_key = key;
  return options;
}

lifemap::v1::Frame WithTime(lifemap::v1::Frame f, double t, uint64_t seq) {
  f.set_timestamp_s(t);
  f.set_sequence(seq);
  return f;
}

// The server process's CPU seconds so far (AdminService.GetStats), or -1 when not answered.
double ServerCpuSeconds(const std::string& target) {
  auto client = lifemap::client::Client::Connect(OptionsFor(target));
  if (!client.ok()) return -1;
  auto stats = (*client)->GetStats();
  return stats.ok() ? stats->process_cpu_s() : -1;
}

// Runs `run` and sets its report's server CPU time from GetStats before and after.
template <typename Run>
RunReport WithServerCpu(const std::string& target, Run run) {
  const double before = ServerCpuSeconds(target);
  RunReport report = run();
  const double after = ServerCpuSeconds(target);
  if (before >= 0 && after >= before) report.server_cpu_s = after - before;
  return report;
}

RunReport RunBaseline(const std::string& target, const std::vector<lifemap::v1::Frame>& frames,
                      int count, const lifemap::v1::FrameOptions& options) {
  RunReport report;
  report.name = "baseline: ProcessFrame, no store";
  auto client = lifemap::client::Client::Connect(OptionsFor(target));
  if (!client.ok()) {
    std::cerr << client.status() << "\n";
    std::exit(1);
  }
  Latencies server;
  const auto start = Clock::now();
  for (int i = 0; i < count; ++i) {
    lifemap::v1::ProcessFrameRequest req;
    *req.mutable_options() = options;
    *req.mutable_frame() = WithTime(frames[i % frames.size()], 1000.0 + i / 30.0, i);
    const auto t0 = Clock::now();
    auto r = (*client)->ProcessFrame(req);
    report.latency.ms.push_back(
        std::chrono::duration<double, std::milli>(Clock::now() - t0).count());
    if (!r.ok()) {
      ++report.errors;
    } else {
      server.ms.push_back(r->timing().total_ms());
    }
    ++report.frames;
  }
  report.seconds = std::chrono::duration<double>(Clock::now() - start).count();
  report.server_total_p50_ms = server.Percentile(50);
  return report;
}

RunReport RunStreams(const std::string& target, const std::vector<lifemap::v1::Frame>& frames,
                     int streams, int count, double rate_hz,
                     const lifemap::v1::FrameOptions& options) {
  RunReport report;
  report.name = absl::StrFormat("%d stream(s) at %s, keyframes stored", streams,
                                rate_hz > 0 ? absl::StrFormat("%.0f Hz", rate_hz) : "max rate");
  std::mutex mu;
  Latencies server;
  std::vector<std::thread> threads;
  const auto start = Clock::now();
  for (int s = 0; s < streams; ++s) {
    threads.emplace_back([&, s] {
      auto client = lifemap::client::Client::Connect(OptionsFor(target));
      if (!client.ok()) return;
      lifemap::v1::StreamStart st;
      st.set_map(MapFor(s));
      *st.mutable_options() = options;
      st.set_robot(absl::StrFormat("load-%d", s));
      auto stream = (*client)->OpenStream(st);
      if (!stream.ok()) {
        std::cerr << "stream " << s << ": " << stream.status() << "\n";
        return;
      }
      std::vector<Clock::time_point> sent(static_cast<size_t>(count));
      const auto t0 = Clock::now();
      std::thread sender([&] {
        for (int i = 0; i < count; ++i) {
          if (rate_hz > 0) {
            std::this_thread::sleep_until(t0 + std::chrono::duration_cast<Clock::duration>(
                                                   std::chrono::duration<double>(i / rate_hz)));
          }
          sent[static_cast<size_t>(i)] = Clock::now();
          if (!(*stream)->Send(WithTime(frames[i % frames.size()], 1000.0 + i / 30.0, i))) break;
        }
        (*stream)->CloseSend();
      });
      lifemap::v1::FrameResult r;
      std::vector<double> local, local_server, local_keyframe, local_commit_wait;
      size_t errors = 0, keyframes = 0;
      while ((*stream)->Receive(&r)) {
        local.push_back(std::chrono::duration<double, std::milli>(
                            Clock::now() - sent[static_cast<size_t>(r.sequence())])
                            .count());
        local_server.push_back(r.timing().total_ms());
        if (r.keyframe().selected()) {
          local_keyframe.push_back(local.back());
          local_commit_wait.push_back(r.timing().commit_wait_ms());
        }
        errors += r.has_error();
        keyframes += r.keyframe().committed();
      }
      sender.join();
      const auto status = (*stream)->Finish();
      std::lock_guard<std::mutex> lock(mu);
      if (!status.ok()) std::cerr << "stream " << s << ": " << status << "\n";
      report.frames += local.size();
      report.errors += errors;
      report.keyframes += keyframes;
      report.latency.ms.insert(report.latency.ms.end(), local.begin(), local.end());
      server.ms.insert(server.ms.end(), local_server.begin(), local_server.end());
      report.keyframe_latency.ms.insert(report.keyframe_latency.ms.end(), local_keyframe.begin(),
                                        local_keyframe.end());
      report.keyframe_commit_wait.ms.insert(report.keyframe_commit_wait.ms.end(),
                                            local_commit_wait.begin(), local_commit_wait.end());
    });
  }
  for (auto& t : threads) t.join();
  report.seconds = std::chrono::duration<double>(Clock::now() - start).count();
  report.server_total_p50_ms = server.Percentile(50);
  return report;
}

// Uploads the model file as "<prefix>-<time>" and makes it the server's default.
absl::Status UploadAsDefault(const std::string& target, const std::string& file,
                             const std::string& prefix) {
  auto bytes = lifemap::ReadFileBytes(file);
  if (!bytes.ok()) return bytes.status();
  auto client = lifemap::client::Client::Connect(OptionsFor(target));
  if (!client.ok()) return client.status();
  const std::string name = prefix + "-" + std::to_string(std::time(nullptr));
  if (auto s = (*client)->UploadModel(name, *bytes).status(); !s.ok()) return s;
  return (*client)->ActivateModel(name, "").status();
}

// The soak (issue 17): `robots` streams of one visit each for `seconds`, an operator listing and
// exporting meanwhile, the server's resident memory sampled every `sample_s`; afterwards every
// acknowledged keyframe must be listed by the store.
struct SoakReport {
  RunReport run;
  size_t operator_calls = 0;
  size_t operator_errors = 0;
  size_t acknowledged = 0;
  size_t missing = 0;  // acknowledged keyframes the store does not list
  // The server's resident memory and its appearance index's memory (which grows with every
  // keyframe, by design: the map grows), sampled by the operator.
  struct Sample {
    double t_s;
    uint64_t resident_bytes;
    uint64_t index_bytes;
  };
  std::vector<Sample> samples;

  // The sample of highest resident memory within [from_s, to_s].
  Sample PeakIn(double from_s, double to_s) const {
    Sample peak{0, 0, 0};
    for (const auto& s : samples) {
      if (s.t_s >= from_s && s.t_s <= to_s && s.resident_bytes >= peak.resident_bytes) peak = s;
    }
    return peak;
  }
  // The early window: the first third after the warm-up (the first minute, or third when
  // shorter); the late window: the last third.
  Sample Early(double seconds) const {
    const double warm = std::min(60.0, seconds / 3);
    return PeakIn(warm, warm + (seconds - warm) / 3);
  }
  Sample Late(double seconds) const {
    const double warm = std::min(60.0, seconds / 3);
    return PeakIn(seconds - (seconds - warm) / 3, 1e9);
  }
  // Resident memory gained from the early to the late peak beyond what the appearance index
  // gained, as a share of the early peak: what a leak would show.
  double UnexplainedGrowth(double seconds) const {
    const Sample early = Early(seconds), late = Late(seconds);
    if (early.resident_bytes == 0) return 0;
    const double gained = static_cast<double>(late.resident_bytes) - early.resident_bytes -
                          (static_cast<double>(late.index_bytes) - early.index_bytes);
    return gained / static_cast<double>(early.resident_bytes);
  }
  nlohmann::json ToJson(double seconds) const {
    nlohmann::json list = nlohmann::json::array();
    for (const auto& s : samples) list.push_back({s.t_s, s.resident_bytes, s.index_bytes});
    return {{"run", run.ToJson()},
            {"operator_calls", operator_calls},
            {"operator_errors", operator_errors},
            {"keyframes_acknowledged", acknowledged},
            {"keyframes_missing", missing},
            {"rss_peak_bytes", PeakIn(0, 1e9).resident_bytes},
            {"rss_peak_early_bytes", Early(seconds).resident_bytes},
            {"rss_peak_late_bytes", Late(seconds).resident_bytes},
            {"index_bytes_early", Early(seconds).index_bytes},
            {"index_bytes_late", Late(seconds).index_bytes},
            {"rss_unexplained_growth", UnexplainedGrowth(seconds)},
            {"samples_t_rss_index", list}};
  }
};

SoakReport RunSoak(const std::string& target, const std::vector<lifemap::v1::Frame>& frames,
                   int robots, double seconds, double rate_hz,
                   const lifemap::v1::FrameOptions& options, double sample_s) {
  SoakReport soak;
  RunReport& report = soak.run;
  report.name = absl::StrFormat("soak: %d robot(s) x %.0f s at %s + an operator", robots, seconds,
                                rate_hz > 0 ? absl::StrFormat("%.0f Hz", rate_hz) : "max rate");
  std::mutex mu;
  std::set<uint64_t> acknowledged;
  Latencies server;
  const auto start = Clock::now();
  const auto end =
      start + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(seconds));
  std::atomic<bool> done{false};
  std::vector<std::thread> threads;
  for (int s = 0; s < robots; ++s) {
    threads.emplace_back([&, s] {
      auto client = lifemap::client::Client::Connect(OptionsFor(target));
      if (!client.ok()) {
        std::lock_guard<std::mutex> lock(mu);
        ++report.errors;
        return;
      }
      lifemap::v1::StreamStart st;
      st.set_map(MapFor(s));
      *st.mutable_options() = options;
      st.set_robot(absl::StrFormat("soak-%d", s));
      auto stream = (*client)->OpenStream(st);
      if (!stream.ok()) {
        std::lock_guard<std::mutex> lock(mu);
        std::cerr << "robot " << s << ": " << stream.status() << "\n";
        ++report.errors;
        return;
      }
      std::mutex sent_mu;
      std::map<uint64_t, Clock::time_point> sent;
      const auto t0 = Clock::now();
      std::thread sender([&] {
        for (uint64_t i = 0; Clock::now() < end; ++i) {
          if (rate_hz > 0) {
            std::this_thread::sleep_until(t0 + std::chrono::duration_cast<Clock::duration>(
                                                   std::chrono::duration<double>(i / rate_hz)));
          }
          {
            std::lock_guard<std::mutex> lock(sent_mu);
            sent[i] = Clock::now();
          }
          if (!(*stream)->Send(WithTime(frames[i % frames.size()], 1000.0 + i / 30.0, i))) break;
        }
        (*stream)->CloseSend();
      });
      lifemap::v1::FrameResult r;
      std::vector<double> local, local_server;
      std::vector<uint64_t> local_acks;
      size_t errors = 0;
      while ((*stream)->Receive(&r)) {
        Clock::time_point when;
        {
          std::lock_guard<std::mutex> lock(sent_mu);
          when = sent[r.sequence()];
          sent.erase(r.sequence());
        }
        local.push_back(std::chrono::duration<double, std::milli>(Clock::now() - when).count());
        local_server.push_back(r.timing().total_ms());
        errors += r.has_error();
        if (r.keyframe().committed()) local_acks.push_back(r.keyframe().keyframe_id());
      }
      sender.join();
      const auto status = (*stream)->Finish();
      std::lock_guard<std::mutex> lock(mu);
      if (!status.ok()) {
        std::cerr << "robot " << s << ": " << status << "\n";
        ++errors;
      }
      report.frames += local.size();
      report.errors += errors;
      report.keyframes += local_acks.size();
      acknowledged.insert(local_acks.begin(), local_acks.end());
      report.latency.ms.insert(report.latency.ms.end(), local.begin(), local.end());
      server.ms.insert(server.ms.end(), local_server.begin(), local_server.end());
    });
  }
  // The operator: lists, exports and samples the server's memory while the robots stream.
  std::thread operator_thread([&] {
    auto client = lifemap::client::Client::Connect(OptionsFor(target));
    if (!client.ok()) {
      ++soak.operator_errors;
      return;
    }
    while (!done.load()) {
      auto stats = (*client)->GetStats();
      const double t = std::chrono::duration<double>(Clock::now() - start).count();
      bool ok = stats.ok();
      if (ok) {
        soak.samples.push_back({t, stats->resident_bytes(), stats->appearance().memory_bytes()});
      }
      ok = ok && (*client)->ListMaps().ok();
      ok = ok && (*client)->ListKeyframes("load", 0).ok();
      lifemap::v1::ExportMapRequest req;
      req.set_map("load");
      req.set_format(lifemap::v1::EXPORT_POSES_TUM);
      std::ostringstream exported;
      ok = ok && (*client)->ExportMap(req, &exported).ok();
      soak.operator_calls += 4;
      if (!ok) ++soak.operator_errors;
      for (int i = 0; i < static_cast<int>(sample_s * 10) && !done.load(); ++i) {
        std::this_thread::sleep_for(std::chrono::milliseconds(100));
      }
    }
  });
  for (auto& t : threads) t.join();
  done.store(true);
  operator_thread.join();
  report.seconds = std::chrono::duration<double>(Clock::now() - start).count();
  report.server_total_p50_ms = server.Percentile(50);
  // Every acknowledged keyframe is in the store.
  soak.acknowledged = acknowledged.size();
  auto client = lifemap::client::Client::Connect(OptionsFor(target));
  auto listed = client.ok() ? (*client)->ListKeyframes("load", 0)
                            : absl::StatusOr<lifemap::v1::ListKeyframesResponse>(client.status());
  if (!listed.ok()) {
    std::cerr << "soak: keyframes not listed: " << listed.status() << "\n";
    soak.missing = acknowledged.size();
  } else {
    std::set<uint64_t> stored;
    for (const auto& k : listed->keyframes()) stored.insert(k.id());
    for (uint64_t id : acknowledged) soak.missing += stored.count(id) == 0;
  }
  return soak;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"lifemap load generator: N streams x M frames against lifemapd"};
  std::string server_address;
  std::string tum = std::string(LIFEMAP_SOURCE_DIR) + "/../shared/data/tum_fr1_xyz_subset";
  int streams = 2, frames = 300;
  double rate = 30.0;
  bool json = false;
  app.add_option("--server", server_address, "external lifemapd HOST:PORT (default: in-process)");
  app.add_option("--tum", tum, "TUM folder whose frames are replayed")
      ->check(CLI::ExistingDirectory);
  app.add_option("--streams", streams, "concurrent streams")->check(CLI::Range(1, 256));
  app.add_option("--maps", StreamMaps(),
                 "maps the streams write, stream s the (s mod N)-th (created if missing; "
                 "default load)")
      ->delimiter(',');
  app.add_option("--frames", frames, "frames per stream")->check(CLI::Range(1, 1000000));
  app.add_option("--rate", rate, "frames/s per stream; 0 = as fast as possible")
      ->check(CLI::Range(0.0, 1000.0));
  app.add_flag("--json", json, "print the report as JSON");
  std::string model;
  app.add_option("--model", model,
                 "model file (lifemap train): one stream runs without labels, then the model is "
                 "uploaded and activated as the server default and the runs repeat with labels")
      ->check(CLI::ExistingFile);
  std::string result_images = "png";
  app.add_option("--result-images", result_images,
                 "how results carry their per-pixel images (FrameOptions.result_images)")
      ->check(CLI::IsMember({"png", "raw", "none"}));
  std::string send = "as-recorded";
  app.add_option("--send", send,
                 "how frames travel: as-recorded (the TUM files: PNG colour, PNG-16 depth) or "
                 "compact (JPEG 90 colour, paletted depth: client::CompactFrame, on the robot "
                 "before the run)")
      ->check(CLI::IsMember({"as-recorded", "compact"}));
  bool no_poses = false;
  app.add_flag("--no-poses", no_poses,
               "send frames without the ground-truth pose: the server tracks the camera");
  std::vector<std::string> skip;
  app.add_option("--skip", skip, "outputs the robot does not want (FrameOptions.skip_outputs)")
      ->check(CLI::IsMember({"entropy", "labels"}));
  double soak_s = 0, sample_s = 5, max_rss_growth = 1.25;
  app.add_option("--soak-s", soak_s,
                 "soak instead of the runs: --streams robots for this many seconds with an "
                 "operator listing and exporting; exit 1 on any error, a lost acknowledged "
                 "keyframe or memory growth")
      ->check(CLI::Range(1.0, 86400.0));
  app.add_option("--sample-s", sample_s, "soak: seconds between the operator's rounds")
      ->check(CLI::Range(0.5, 600.0));
  app.add_option("--max-rss-growth", max_rss_growth,
                 "soak: the late peak of resident memory may exceed the early one by at most "
                 "(this - 1) x the early peak, beyond what the appearance index grew")
      ->check(CLI::Range(1.0, 100.0));
  CLI11_PARSE(app, argc, argv);
  lifemap::v1::FrameOptions options;
  options.set_result_images(result_images == "raw"    ? lifemap::v1::RESULT_IMAGES_RAW
                            : result_images == "none" ? lifemap::v1::RESULT_IMAGES_NONE
                                                      : lifemap::v1::RESULT_IMAGES_PNG);
  for (const auto& s : skip) {
    options.add_skip_outputs(s == "entropy" ? lifemap::v1::FRAME_OUTPUT_ENTROPY_MASK
                                            : lifemap::v1::FRAME_OUTPUT_CLASS_LABELS);
  }

  if (app.count("--tum") == 0 && !fs::is_directory(tum)) {
    // The default recording lives in ../shared/data, which a checkout may not have: ctest
    // counts exit code 77 as skipped.
    std::cerr << "load_generator: skipped: no recording at " << tum
              << " (../shared/data is absent; give --tum DIR)\n";
    return 77;
  }
  auto seq = lifemap::io::ReadTumSequence(tum);
  if (!seq.ok()) {
    std::cerr << "load_generator: " << seq.status().message() << "\n";
    return 1;
  }
  std::vector<lifemap::v1::Frame> loaded;
  lifemap::v1::CameraIntrinsics k;
  const auto guess = lifemap::io::TumIntrinsicsFor(tum, 640, 480, nullptr);
  k.set_fx(guess.fx), k.set_fy(guess.fy), k.set_cx(guess.cx), k.set_cy(guess.cy);
  for (const auto& e : seq->frames) {
    auto f = lifemap::client::FrameFromFiles(e.rgb_path, e.depth_path, 5000.0, k, e.timestamp_s, 0);
    if (!f.ok()) {
      std::cerr << "load_generator: " << f.status().message() << "\n";
      return 1;
    }
    if (e.T_world_camera && !no_poses) {
      auto* p = f->mutable_pose();
      p->set_tx(e.T_world_camera->translation.x());
      p->set_ty(e.T_world_camera->translation.y());
      p->set_tz(e.T_world_camera->translation.z());
      p->set_qx(e.T_world_camera->rotation.x());
      p->set_qy(e.T_world_camera->rotation.y());
      p->set_qz(e.T_world_camera->rotation.z());
      p->set_qw(e.T_world_camera->rotation.w());
    }
    if (send == "compact") {
      f = lifemap::client::CompactFrame(*f);
      if (!f.ok()) {
        std::cerr << "load_generator: " << f.status().message() << "\n";
        return 1;
      }
    }
    loaded.push_back(*std::move(f));
  }

  std::unique_ptr<lifemap::server::LifemapServer> server;
  std::string target = server_address;
  const fs::path dir = fs::temp_directory_path() / "lifemap-load";
  if (target.empty()) {
    fs::remove_all(dir);
    fs::create_directories(dir);
    lifemap::server::ServerConfig config;
    config.listen = "127.0.0.1:0";
    config.db_path = (dir / "load.db").string();
    config.log_level = "warn";
    config.max_streams = std::max(16, streams);
    auto s = lifemap::server::LifemapServer::Start(config);
    if (!s.ok()) {
      std::cerr << "load_generator: " << s.status().message() << "\n";
      return 1;
    }
    server = *std::move(s);
    target = "127.0.0.1:" + std::to_string(server->port());
  }
  {
    auto client = lifemap::client::Client::Connect(OptionsFor(target));
    if (!client.ok()) {
      std::cerr << "load_generator: " << client.status().message() << "\n";
      return 1;
    }
    for (const std::string& name : StreamMaps()) {
      auto m = (*client)->CreateMap(name, "load generator");
      if (!m.ok() && !absl::IsAlreadyExists(m.status())) {
        std::cerr << "load_generator: " << m.status().message() << "\n";
        return 1;
      }
    }
  }

  if (soak_s > 0) {
    if (!model.empty()) {
      if (auto s = UploadAsDefault(target, model, "soak"); !s.ok()) {
        std::cerr << "load_generator: --model: " << s.message() << "\n";
        return 1;
      }
    }
    SoakReport soak = RunSoak(target, loaded, streams, soak_s, rate, options, sample_s);
    const nlohmann::json j = soak.ToJson(soak_s);
    const double early = static_cast<double>(soak.Early(soak_s).resident_bytes);
    const double late = static_cast<double>(soak.Late(soak_s).resident_bytes);
    const bool grew = soak.UnexplainedGrowth(soak_s) > max_rss_growth - 1;
    if (json) {
      std::cout << j.dump(2) << "\n";
    } else {
      soak.run.Print();
      std::cout << absl::StrFormat(
          "operator: %d calls, %d errors; keyframes acknowledged %d, missing from the store %d; "
          "resident memory peak %.1f MB (early %.1f MB, late %.1f MB; the appearance index "
          "%.1f -> %.1f MB; growth beyond the index %+.1f%% of the early peak)\n",
          soak.operator_calls, soak.operator_errors, soak.acknowledged, soak.missing,
          static_cast<double>(j["rss_peak_bytes"].get<uint64_t>()) / 1e6, early / 1e6, late / 1e6,
          soak.Early(soak_s).index_bytes / 1e6, soak.Late(soak_s).index_bytes / 1e6,
          100 * soak.UnexplainedGrowth(soak_s));
    }
    server.reset();
    if (server_address.empty()) fs::remove_all(dir);
    const bool failed = soak.run.errors > 0 || soak.operator_errors > 0 || soak.missing > 0 ||
                        soak.acknowledged == 0 || grew;
    if (failed) {
      std::cerr << "soak FAILED: " << soak.run.errors << " frame/stream errors, "
                << soak.operator_errors << " operator errors, " << soak.missing
                << " acknowledged keyframes missing"
                << (grew ? ", resident memory grew beyond --max-rss-growth" : "") << "\n";
    }
    return failed ? 1 : 0;
  }

  std::vector<RunReport> runs;
  if (!model.empty()) {
    // The same-run baseline for labels: one stream before any model is active.
    runs.push_back(WithServerCpu(
        target, [&] { return RunStreams(target, loaded, 1, frames, rate, options); }));
    runs.back().name += ", no labels";
    if (auto s = UploadAsDefault(target, model, "load"); !s.ok()) {
      std::cerr << "load_generator: --model: " << s.message() << "\n";
      return 1;
    }
  }
  runs.push_back(WithServerCpu(
      target, [&] { return RunBaseline(target, loaded, std::min(frames, 200), options); }));
  runs.push_back(
      WithServerCpu(target, [&] { return RunStreams(target, loaded, 1, frames, rate, options); }));
  runs.push_back(WithServerCpu(
      target, [&] { return RunStreams(target, loaded, streams, frames, rate, options); }));
  if (!model.empty()) {
    for (size_t i = 1; i < runs.size(); ++i) runs[i].name += ", labels";
  }
  const std::string sent =
      std::string(send == "compact" ? "JPEG 90 colour + paletted depth (compact)"
                                    : "PNG colour + PNG-16 depth (as recorded)") +
      (no_poses ? ", no poses (tracked by the server)" : ", posed (ground truth)");
  if (json) {
    nlohmann::json reports = nlohmann::json::array();
    for (const auto& r : runs) reports.push_back(r.ToJson());
    std::cout << nlohmann::json{{"target", target},
                                {"frame", "640x480 TUM, " + sent},
                                {"result_images", result_images},
                                {"server_cpu",
                                 server_address.empty()
                                     ? "in-process server: CPU per frame includes the load "
                                       "generator's own (an upper bound); use --server for the "
                                       "server alone"
                                     : "the server process alone (GetStats.process_cpu_s)"},
                                {"runs", reports}}
                     .dump(2)
              << "\n";
  } else {
    std::cout << "target " << target << ", " << loaded.size() << " distinct 640x480 TUM frames, "
              << sent << "\n";
    for (const auto& r : runs) r.Print();
  }
  server.reset();
  if (server_address.empty()) fs::remove_all(dir);
  return 0;
}
