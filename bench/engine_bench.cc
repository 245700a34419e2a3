// The frame path without gRPC: the map engine (server/engine) driven directly, one visit, one
// frame at a time (analyse, place, wait for a keyframe's commit), as a stream drives it but
// without the transport, protobuf or the stream's threads. Beside the load generator's server
// CPU per frame (same frames, same settings) the difference is what the transport costs.
//
//   build/bin/bench_engine [--model=FILE] [--benchmark_filter=...]
//
// Frames: ../shared/data/tum_fr1_xyz_subset (real Kinect data), sent as compact frames would
// be (JPEG 90 colour, paletted depth) and replayed cyclically with fresh timestamps at 30 Hz;
// skipped with a reason when the folder is absent. --model=FILE (from `lifemap train`) turns
// labels and fusion on. Counters: cpu_ms_per_frame is the whole process's CPU (every thread:
// the task pool, the committer, the workers) per frame; keyframes per frame.
#include <sys/resource.h>

#include <cstring>
#include <filesystem>
#include <iostream>

#include <benchmark/benchmark.h>
#include <opencv2/imgcodecs.hpp>

#include "core/common/depth_codec.h"
#include "core/common/image_codec.h"
#include "core/io/tum_dataset.h"
#include "server/engine/clock.h"
#include "server/engine/engine.h"
#include "server/engine/model_registry.h"
#include "server/engine/visit_registry.h"
#include "server/store/store.h"

namespace lifemap::server {
namespace {

namespace fs = std::filesystem;

std::string g_model_path;  // --model

struct CompactFrame {
  std::string jpeg;
  std::string paletted;
  CameraIntrinsics intrinsics;
  std::optional<Pose> T_world_camera;
};

// The recording's frames, encoded once, before anything is measured.
const std::vector<CompactFrame>& Frames() {
  static const std::vector<CompactFrame> frames = [] {
    std::vector<CompactFrame> out;
    auto seq =
        io::ReadTumSequence(std::string(LIFEMAP_SOURCE_DIR) + "/../shared/data/tum_fr1_xyz_subset");
    if (!seq.ok()) return out;
    for (const auto& e : seq->frames) {
      const cv::Mat color = cv::imread(e.rgb_path, cv::IMREAD_COLOR);
      const cv::Mat depth = cv::imread(e.depth_path, cv::IMREAD_UNCHANGED);
      if (color.empty() || depth.type() != CV_16UC1) continue;
      CompactFrame f;
      f.jpeg = *EncodeJpeg(color, 90);
      f.paletted = EncodePalettedDepth(depth);
      std::string source;
      f.intrinsics = io::TumSequenceIntrinsics(*seq, color.cols, color.rows, &source);
      f.T_world_camera = e.T_world_camera;
      out.push_back(std::move(f));
    }
    return out;
  }();
  return frames;
}

double ProcessCpuSeconds() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return static_cast<double>(u.ru_utime.tv_sec + u.ru_stime.tv_sec) +
         static_cast<double>(u.ru_utime.tv_usec + u.ru_stime.tv_usec) * 1e-6;
}

// One visit of map "bench" on a fresh database, frames sent with or without poses (the server
// tracks them), labels and fusion on when a model is given.
void BM_FramePath(benchmark::State& state) {
  const bool posed = state.range(0) != 0;
  const bool labels = state.range(1) != 0;
  const auto& frames = Frames();
  if (frames.empty()) {
    state.SkipWithError("../shared/data/tum_fr1_xyz_subset is absent");
    return;
  }
  if (labels && g_model_path.empty()) {
    state.SkipWithError("labels need --model=FILE (lifemap train)");
    return;
  }
  const fs::path dir = fs::temp_directory_path() / "lifemap-bench-engine";
  fs::remove_all(dir);
  fs::create_directories(dir);
  EngineOptions options;
  options.db_path = (dir / "bench.db").string();
  auto engine = Engine::Open(options);
  if (!engine.ok()) {
    state.SkipWithError(std::string(engine.status().message()).c_str());
    return;
  }
  store::Store* store = (*engine)->store();
  auto map = store->CreateMap("bench", "", NowSeconds());
  auto visit = store->StartVisit("bench", "bench", "", NowSeconds());
  if (!map.ok() || !visit.ok()) {
    state.SkipWithError("cannot create the map and visit");
    return;
  }
  if (labels) {
    auto bytes = ReadFileBytes(g_model_path);
    if (!bytes.ok() || !(*engine)->models()->Add("bench", *bytes).ok() ||
        !(*engine)->models()->Activate("", "bench").ok()) {
      state.SkipWithError("--model: not a usable model file");
      return;
    }
  }
  auto visit_state = (*engine)->visits()->Get(visit->id);
  auto writer = (*engine)->visits()->ClaimWriter(*visit_state, "bench");
  const FrameSettings settings;
  FramePath* path = (*engine)->frames();

  const double start_s = NowSeconds();
  size_t i = 0;
  int64_t keyframes = 0;
  const double cpu_before = ProcessCpuSeconds();
  for (auto _ : state) {
    const CompactFrame& c = frames[i % frames.size()];
    EncodedRgbdFrame f;
    f.sequence = i;
    f.timestamp_s = start_s + static_cast<double>(i) / 30.0;
    f.intrinsics = c.intrinsics;
    f.color = {ColorEncoding::kJpeg, c.jpeg, c.intrinsics.width, c.intrinsics.height};
    f.depth = {DepthEncoding::kPaletted, c.paletted, c.intrinsics.width, c.intrinsics.height,
               5000.0};
    if (posed) f.T_world_camera = c.T_world_camera;
    AnalysedFrame a = path->Analyse(f, map->id, "bench", settings);
    FramePlacement p = path->Place(a, *visit_state, writer->id(), settings);
    if (p.commit && p.commit->get().ok()) ++keyframes;
    ++i;
  }
  const double cpu_s = ProcessCpuSeconds() - cpu_before;
  state.counters["cpu_ms_per_frame"] = 1000.0 * cpu_s / static_cast<double>(i);
  state.counters["keyframes_per_frame"] = static_cast<double>(keyframes) / static_cast<double>(i);
  state.counters["frames_per_s"] =
      benchmark::Counter(static_cast<double>(i), benchmark::Counter::kIsRate);
  engine->reset();
  fs::remove_all(dir);
}
BENCHMARK(BM_FramePath)
    ->ArgNames({"posed", "labels"})
    ->Args({0, 0})
    ->Args({1, 0})
    ->Args({0, 1})
    ->Args({1, 1})
    ->Iterations(300)
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime();

}  // namespace
}  // namespace lifemap::server

int main(int argc, char** argv) {
  // --model=FILE is ours; the rest is Google Benchmark's.
  std::vector<char*> rest;
  for (int i = 0; i < argc; ++i) {
    if (std::strncmp(argv[i], "--model=", 8) == 0) {
      lifemap::server::g_model_path = argv[i] + 8;
    } else {
      rest.push_back(argv[i]);
    }
  }
  int n = static_cast<int>(rest.size());
  benchmark::Initialize(&n, rest.data());
  if (benchmark::ReportUnrecognizedArguments(n, rest.data())) return 1;
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}
