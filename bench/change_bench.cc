// What changed between visits (core/change, issue 36): the per-frame moved mask (the previous
// visit's surfaces rendered at the frame's pose, eq. 3 of paper 000) and the comparison of two
// whole visits (GetChanges' core). Visits are rendered from the synthetic world (seed 3, a
// rectangular room, scenery changing, Kinect noise); the frame compared is 640x480.
#include <map>

#include <benchmark/benchmark.h>

#include "core/change/moved_zones.h"
#include "core/change/object_changes.h"
#include "core/sim/generator.h"
#include "core/sim/renderer.h"

namespace lifemap::change {
namespace {

struct Rendered {
  std::vector<PosedDepth> earlier, later;  // every 4th pixel, as the server keeps them
  cv::Mat frame;                           // a full 640x480 frame of the later visit
  Pose frame_pose;
  CameraIntrinsics k{525, 525, 319.5, 239.5, 640, 480};
};

// Two visits of `frames` keyframes each; rendered at 160x120 (what the server reads of a
// 640x480 keyframe at stride 4) to keep the set-up short.
const Rendered& Visits(int frames) {
  static std::map<int, Rendered> cache;
  auto it = cache.find(frames);
  if (it != cache.end()) return it->second;
  Rendered& r = cache[frames];
  auto place = sim::GeneratePlace(3, "rect");
  sim::Conditions scenery;
  scenery.scenery = true;
  auto visits = sim::GenerateVisits(*place, 3, 2, 6, scenery, frames);
  const CameraIntrinsics small{525.0 / 4, 525.0 / 4, 319.5 / 4, 239.5 / 4, 160, 120};
  for (int v = 0; v < 2; ++v) {
    const sim::Visit& visit = (*visits)[static_cast<size_t>(v)];
    for (size_t f = 0; f < visit.trajectory.size(); ++f) {
      const Pose& pose = visit.trajectory[f].T_world_camera;
      auto frame = sim::Render(*place, visit.SolidsAt(f), visit.lighting, small, pose, {}, f + 1);
      (v == 0 ? r.earlier : r.later).push_back(Subsample(frame.depth_m, small, 1, pose));
    }
  }
  const sim::Visit& later = (*visits)[1];
  r.frame_pose = later.trajectory[later.trajectory.size() / 3].T_world_camera;
  r.frame =
      sim::Render(*place, later.SolidsAt(0), later.lighting, r.k, r.frame_pose, {}, 99).depth_m;
  return r;
}

// The per-frame moved mask against a previous visit of N keyframes (issue 36: at most 5 ms).
void BM_MovedAgainst(benchmark::State& state) {
  const Rendered& r = Visits(static_cast<int>(state.range(0)));
  const SurfacePoints previous = SurfaceOf(r.earlier, 0.05, 4.0);
  for (auto _ : state) {
    MovedMask m = MovedAgainst(r.frame, r.k, r.frame_pose, previous);
    benchmark::DoNotOptimize(m.moved_pixels);
  }
  state.counters["surface_points"] = static_cast<double>(previous.points.size());
}
BENCHMARK(BM_MovedAgainst)->Arg(60)->Arg(300)->Unit(benchmark::kMillisecond);

// Building the previous visit's surfaces (once per visit, off the reply path).
void BM_SurfaceOf(benchmark::State& state) {
  const Rendered& r = Visits(static_cast<int>(state.range(0)));
  for (auto _ : state) benchmark::DoNotOptimize(SurfaceOf(r.earlier, 0.05, 4.0).points.size());
}
BENCHMARK(BM_SurfaceOf)->Arg(60)->Arg(300)->Unit(benchmark::kMillisecond);

// Two whole visits compared (GetChanges without the store's decoding).
void BM_DetectObjectChanges(benchmark::State& state) {
  const Rendered& r = Visits(static_cast<int>(state.range(0)));
  for (auto _ : state) {
    auto c = DetectObjectChanges(r.earlier, r.later);
    benchmark::DoNotOptimize(c->objects.size());
  }
}
BENCHMARK(BM_DetectObjectChanges)->Arg(60)->Arg(300)->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace lifemap::change
BENCHMARK_MAIN();
