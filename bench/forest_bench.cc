// Random-forest training and inference (paper 002) on the real mOSD scenes: training on the 14
// `learn` scenes with the paper's parameters (3 trees, depth 20, N = 2000, P = 2000), and
// inference on a 640x480 frame on both cores, every pixel and every 2nd/4th.
//
//   build/bin/bench_forest
#include <filesystem>
#include <string>

#include <benchmark/benchmark.h>

#include "core/forest/forest.h"
#include "core/io/labeled_pcd.h"

namespace lifemap {
namespace {

std::vector<forest::LabeledImage> Learn() {
  static const std::vector<forest::LabeledImage> images = [] {
    std::vector<forest::LabeledImage> out;
    const std::string dir =
        std::string(LIFEMAP_SOURCE_DIR) + "/../shared/data/pcl_mosd_labeled_subset/learn";
    if (!std::filesystem::is_directory(dir)) return out;
    for (const auto& e : std::filesystem::directory_iterator(dir)) {
      auto f = io::ReadLabeledPcd(e.path().string());
      if (!f.ok()) continue;
      forest::LabeledImage im;
      im.depth_m = f->frame.depth_m;
      im.color_bgr = f->frame.color_bgr;
      im.labels = io::MosdTableObjectClasses(f->labels);
      out.push_back(im);
    }
    return out;
  }();
  return images;
}

forest::TrainOptions PaperOptions() {
  forest::TrainOptions o;  // 3 trees, depth 20, N 2000, P 2000, both cores
  return o;
}

void BM_TrainMosdLearn(benchmark::State& state) {
  const auto images = Learn();
  if (images.empty()) {
    state.SkipWithError("needs ../shared/data/pcl_mosd_labeled_subset");
    return;
  }
  for (auto _ : state) {
    auto f = forest::Forest::Train(images, 2, PaperOptions());
    if (!f.ok()) state.SkipWithError("training failed");
    state.counters["nodes"] = static_cast<double>(f->node_count());
  }
}
BENCHMARK(BM_TrainMosdLearn)->Iterations(1)->Unit(benchmark::kSecond);

void BM_PredictFrame(benchmark::State& state) {
  const auto images = Learn();
  if (images.empty()) {
    state.SkipWithError("needs ../shared/data/pcl_mosd_labeled_subset");
    return;
  }
  static const auto model = *forest::Forest::Train(images, 2, PaperOptions());
  const int stride = static_cast<int>(state.range(0));
  for (auto _ : state) {
    benchmark::DoNotOptimize(
        model.Predict(images[0].depth_m, images[0].color_bgr, forest::Decision::kBalanced, stride));
  }
}
BENCHMARK(BM_PredictFrame)->Arg(1)->Arg(2)->Arg(4)->Unit(benchmark::kMillisecond)->UseRealTime();

}  // namespace
}  // namespace lifemap

BENCHMARK_MAIN();
