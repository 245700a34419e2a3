// RGB-D odometry per frame (issue 15's budget: <= 15 ms at the server on 2 cores), and the
// trajectory it gives on TUM fr1_xyz (ATE, as a counter), per resolution.
//
//   build/bin/bench_tracking
#include <benchmark/benchmark.h>

#include "core/eval/trajectory.h"
#include "core/io/tum_dataset.h"
#include "core/tracking/keyframe_selector.h"
#include "core/tracking/odometry.h"

namespace lifemap {
namespace {

struct Recording {
  std::vector<RgbdFrame> frames;
  std::vector<eval::TimedPose> truth;
};

const Recording& Fr1Xyz() {
  static const Recording* r = [] {
    auto* out = new Recording;
    auto seq =
        io::ReadTumSequence(std::string(LIFEMAP_SOURCE_DIR) + "/../shared/data/tum_fr1_xyz_subset");
    if (!seq.ok()) return out;
    for (const auto& e : seq->frames) {
      auto f = io::DecodeTumFrame(*seq, e);
      if (!f.ok()) continue;
      out->frames.push_back(*std::move(f));
      if (e.T_world_camera) out->truth.push_back({e.timestamp_s, *e.T_world_camera});
    }
    return out;
  }();
  return *r;
}

// Arg: downscale. Each iteration tracks the whole recording as the server does (keyframes by
// estimated motion); time per frame = the iteration's time / frames.
void BM_TrackFr1Xyz(benchmark::State& state) {
  const Recording& r = Fr1Xyz();
  if (r.frames.empty()) {
    state.SkipWithError("needs ../shared/data/tum_fr1_xyz_subset");
    return;
  }
  tracking::OdometryOptions options;
  options.downscale = static_cast<int>(state.range(0));
  std::vector<eval::TimedPose> estimate;
  int lost = 0;
  for (auto _ : state) {
    tracking::Tracker tracker(options);
    tracking::KeyframeSelector selector;
    estimate.clear();
    lost = 0;
    for (const RgbdFrame& f : r.frames) {
      const auto t = tracker.Track(f);
      if (!t.T_world_camera) {
        ++lost;
        continue;
      }
      estimate.push_back({f.timestamp_s, *t.T_world_camera});
      if (selector.Decide(f.timestamp_s, t.T_world_camera).selected) {
        selector.Accept(f.timestamp_s, t.T_world_camera);
        tracker.PromoteLastToReference();
      }
    }
  }
  state.SetItemsProcessed(state.iterations() * static_cast<int64_t>(r.frames.size()));
  auto errors = eval::CompareTrajectories(estimate, r.truth);
  state.counters["ate_mm"] = errors.ok() ? errors->ate_rmse_m * 1000 : -1;
  state.counters["lost"] = lost;
}
BENCHMARK(BM_TrackFr1Xyz)->Arg(1)->Arg(2)->Arg(4)->Unit(benchmark::kMillisecond);

// The odometry's settings compared at half resolution (issue 15, third part): 0 = OpenCV's
// gradient threshold (10) without the feature check (the settings before), 1 = threshold 5
// without it, 2 = the defaults (threshold 5, feature check on).
tracking::OdometryOptions Variant(int64_t v) {
  tracking::OdometryOptions o;
  if (v == 0) o.min_gradient = 10;
  if (v <= 1) o.feature_keypoints = 0;
  return o;
}

// What the server does per frame on its pool, beside the frame's other analyses.
void BM_PrepareFr1Xyz(benchmark::State& state) {
  const Recording& r = Fr1Xyz();
  if (r.frames.empty()) {
    state.SkipWithError("needs ../shared/data/tum_fr1_xyz_subset");
    return;
  }
  const tracking::OdometryOptions options = Variant(state.range(0));
  size_t i = 0;
  for (auto _ : state) {
    benchmark::DoNotOptimize(
        tracking::PrepareForTracking(r.frames[i++ % r.frames.size()], options));
  }
  state.SetItemsProcessed(state.iterations());
}
BENCHMARK(BM_PrepareFr1Xyz)->DenseRange(0, 2)->Unit(benchmark::kMillisecond);

// What the server does per frame in the visit's order: the alignment of prepared frames.
void BM_AlignFr1Xyz(benchmark::State& state) {
  const Recording& r = Fr1Xyz();
  if (r.frames.empty()) {
    state.SkipWithError("needs ../shared/data/tum_fr1_xyz_subset");
    return;
  }
  const tracking::OdometryOptions options = Variant(state.range(0));
  std::vector<std::shared_ptr<tracking::TrackingInput>> prepared(r.frames.size());
  for (auto _ : state) {
    // The inputs carry caches the alignment fills: prepare again, untimed, for each pass.
    state.PauseTiming();
    for (size_t i = 0; i < r.frames.size(); ++i) {
      prepared[i] = tracking::PrepareForTracking(r.frames[i], options);
    }
    state.ResumeTiming();
    tracking::Tracker tracker(options);
    tracking::KeyframeSelector selector;
    for (size_t i = 0; i < r.frames.size(); ++i) {
      const auto t = tracker.Track(r.frames[i], prepared[i]);
      if (t.T_world_camera && selector.Decide(r.frames[i].timestamp_s, t.T_world_camera).selected) {
        selector.Accept(r.frames[i].timestamp_s, t.T_world_camera);
        tracker.PromoteLastToReference();
      }
    }
  }
  state.SetItemsProcessed(state.iterations() * static_cast<int64_t>(r.frames.size()));
}
BENCHMARK(BM_AlignFr1Xyz)->DenseRange(0, 2)->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace lifemap

BENCHMARK_MAIN();
