// The semantic octree (core/semantic): fusing one keyframe, rendering labels into one view, and
// the memory a whole visit's octree takes per square metre of floor. Frames are rendered from
// the synthetic world (seed 3, a rectangular room, 640x480, Kinect noise); class distributions
// are made from the renderer's true classes (0.7 on the grouped class, the rest shared), which
// costs the same as the forest's output.
#include <cmath>
#include <map>
#include <string>
#include <utility>
#include <vector>

#include <benchmark/benchmark.h>

#include "core/semantic/semantic_map.h"
#include "core/sim/generator.h"
#include "core/sim/renderer.h"

namespace lifemap::semantic {
namespace {

constexpr int kClasses = 4;

struct Keyframe {
  cv::Mat depth;
  std::vector<cv::Mat> probabilities;
  Pose pose;
};

struct Visit {
  CameraIntrinsics k{525, 525, 319.5, 239.5, 640, 480};
  std::vector<Keyframe> keyframes;
  double floor_m2 = 0.0;
};

double PolygonArea(const std::vector<Eigen::Vector2d>& p) {
  double a = 0.0;
  for (size_t i = 0; i < p.size(); ++i) {
    const auto& u = p[i];
    const auto& v = p[(i + 1) % p.size()];
    a += u.x() * v.y() - v.x() * u.y();
  }
  return std::abs(a) / 2.0;
}

// Every 3rd frame of a 90-frame walk round seed `seed`'s room.
const Visit& RenderedVisit(uint64_t seed, const char* shape) {
  static std::map<std::pair<uint64_t, std::string>, Visit> cache;
  auto [it, inserted] = cache.try_emplace({seed, shape});
  Visit& visit = it->second;
  if (!inserted) return visit;
  auto place = sim::GeneratePlace(seed, shape);
  auto visits = sim::GenerateVisits(*place, seed, 1, 0, sim::Conditions{}, 90);
  const auto& v = (*visits)[0];
  visit.floor_m2 = PolygonArea(place->footprint);
  for (const auto& room : place->adjoining_rooms) visit.floor_m2 += PolygonArea(room);
  for (size_t f = 0; f < v.trajectory.size(); f += 3) {
    const Pose& pose = v.trajectory[f].T_world_camera;
    const sim::RenderedFrame r =
        sim::Render(*place, v.solids, v.lighting, visit.k, pose, sim::SensorOptions{}, f + 1);
    Keyframe kf;
    kf.depth = r.depth_m;
    kf.pose = pose;
    for (int c = 0; c < kClasses; ++c) kf.probabilities.emplace_back(r.depth_m.size(), CV_32FC1);
    for (int y = 0; y < r.class_id.rows; ++y) {
      for (int x = 0; x < r.class_id.cols; ++x) {
        const int truth = r.class_id.at<uint8_t>(y, x) % kClasses;
        for (int c = 0; c < kClasses; ++c) {
          kf.probabilities[c].at<float>(y, x) = c == truth ? 0.7f : 0.1f;
        }
      }
    }
    visit.keyframes.push_back(std::move(kf));
  }
  return visit;
}

std::unique_ptr<SemanticMap> NewMap(const SemanticMapOptions& options) {
  return std::move(*SemanticMap::Create(kClasses, {0.7, 0.2, 0.08, 0.02}, options));
}

// One keyframe into a map that has the visit's first 10 keyframes.
void BM_SemanticFuse(benchmark::State& state) {
  const Visit& visit = RenderedVisit(3, "rect");
  SemanticMapOptions options;
  options.free_space_stride = static_cast<int>(state.range(0));
  options.free_space_band_m = static_cast<double>(state.range(1)) / 10.0;
  auto map = NewMap(options);
  for (size_t i = 0; i < 10; ++i) {
    const Keyframe& kf = visit.keyframes[i];
    map->Fuse(kf.depth, visit.k, kf.pose, kf.probabilities).IgnoreError();
  }
  size_t i = 10;
  double free_voxels = 0, occupied = 0, n = 0;
  for (auto _ : state) {
    const Keyframe& kf = visit.keyframes[i++ % visit.keyframes.size()];
    auto stats = map->Fuse(kf.depth, visit.k, kf.pose, kf.probabilities);
    free_voxels += static_cast<double>(stats->free_voxels);
    occupied += static_cast<double>(stats->occupied_voxels);
    ++n;
  }
  state.counters["free_voxels"] = free_voxels / n;
  state.counters["occupied_voxels"] = occupied / n;
}
// Args: free-space stride, band (decimetres; 0 = whole rays).
BENCHMARK(BM_SemanticFuse)
    ->Args({0, 0})
    ->Args({8, 0})
    ->Args({16, 0})
    ->Args({8, 10})
    ->Args({16, 10})
    ->Args({16, 20})
    ->Unit(benchmark::kMillisecond);

// A whole visit (30 keyframes round the room) fused into a new octree per iteration: the same
// work every run, for comparing builds (BM_SemanticFuse's keyframes depend on its iteration
// count). Reported per keyframe. Arg: free-space stride.
void BM_SemanticFuseVisit(benchmark::State& state) {
  const Visit& visit = RenderedVisit(3, "rect");
  SemanticMapOptions options;
  options.free_space_stride = static_cast<int>(state.range(0));
  for (auto _ : state) {
    auto map = NewMap(options);
    for (const Keyframe& kf : visit.keyframes) {
      map->Fuse(kf.depth, visit.k, kf.pose, kf.probabilities).IgnoreError();
    }
  }
  state.counters["ms_per_keyframe"] =
      benchmark::Counter(static_cast<double>(state.iterations() * visit.keyframes.size()) / 1e3,
                         benchmark::Counter::kIsRate | benchmark::Counter::kInvert);
}
BENCHMARK(BM_SemanticFuseVisit)->Arg(16)->Arg(8)->Unit(benchmark::kMillisecond);

// Labels of a whole visit rendered into one of its views. Arg: the render stride.
void BM_SemanticRender(benchmark::State& state) {
  const Visit& visit = RenderedVisit(3, "rect");
  auto map = NewMap({});
  for (const Keyframe& kf : visit.keyframes) {
    map->Fuse(kf.depth, visit.k, kf.pose, kf.probabilities).IgnoreError();
  }
  const Keyframe& view = visit.keyframes[7];
  double coverage = 0, n = 0;
  for (auto _ : state) {
    auto r = map->Render(view.depth, visit.k, view.pose, static_cast<int>(state.range(0)));
    coverage += static_cast<double>(r->labelled_pixels) / static_cast<double>(r->depth_pixels);
    ++n;
  }
  state.counters["coverage"] = coverage / n;
}
BENCHMARK(BM_SemanticRender)->Arg(1)->Arg(2)->Arg(4)->Unit(benchmark::kMillisecond);

// Memory of a whole visit's octree (30 keyframes round the room), per square metre of floor,
// and extrapolated linearly to a 1,000 m² floor (a floor of such rooms: the octree's size grows
// with the surfaces and the free space seen, both about proportional to floor area at one
// storey's height). Arg: 0 seed 3's rectangular room, 1 seed 7's L-shaped one.
void BM_SemanticMemory(benchmark::State& state) {
  const Visit& visit = state.range(0) == 0 ? RenderedVisit(3, "rect") : RenderedVisit(7, "L");
  SemanticSummary s;
  for (auto _ : state) {
    auto map = NewMap({});
    for (const Keyframe& kf : visit.keyframes) {
      map->Fuse(kf.depth, visit.k, kf.pose, kf.probabilities).IgnoreError();
    }
    s = map->Summarize();
  }
  state.counters["floor_m2"] = visit.floor_m2;
  state.counters["MB"] = static_cast<double>(s.memory_bytes) / 1e6;
  state.counters["kB_per_m2"] = static_cast<double>(s.memory_bytes) / 1e3 / visit.floor_m2;
  state.counters["MB_per_1000m2"] =
      static_cast<double>(s.memory_bytes) / 1e6 / visit.floor_m2 * 1000;
  state.counters["occupied_voxels"] = static_cast<double>(s.occupied_voxels);
  state.counters["nodes"] = static_cast<double>(s.nodes);
}
BENCHMARK(BM_SemanticMemory)->Arg(0)->Arg(1)->Unit(benchmark::kMillisecond)->Iterations(1);

}  // namespace
}  // namespace lifemap::semantic

BENCHMARK_MAIN();
