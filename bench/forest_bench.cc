// Random-forest training and inference (paper 002) on the real mOSD scenes: training on the 14
// `learn` scenes with the paper's parameters (3 trees, depth 20, N = 2000, P = 2000), and
// inference on a 640x480 frame on both cores, every pixel and every 2nd/4th; and the served
// per-frame path (decode, entropy masks, labels at stride 4) against the same path without
// labels, in the same run.
//
//   build/bin/bench_forest
#include <string>

#include <benchmark/benchmark.h>

#include "core/common/image_codec.h"
#include "core/forest/forest.h"
#include "core/forest/labeled_data.h"
#include "core/io/labeled_pcd.h"
#include "core/pipeline/frame_pipeline.h"

namespace lifemap {
namespace {

// The 14 mOSD `learn` scenes (empty when ../shared/data is absent), read as `lifemap train`
// reads them.
std::vector<forest::LabeledImage> Learn() {
  static const std::vector<forest::LabeledImage> images = [] {
    auto data = forest::ReadLabeledData(
        {std::string(LIFEMAP_SOURCE_DIR) + "/../shared/data/pcl_mosd_labeled_subset/learn"});
    return data.ok() ? std::move(data->images) : std::vector<forest::LabeledImage>();
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

const forest::Forest& PaperModel() {
  static const auto model = *forest::Forest::Train(Learn(), 2, PaperOptions());
  return model;
}

// The served path for one frame: first argument 0 without labels, 1 with the paper-sized model
// at the server's default stride 4, 2 the labels plus their PNGs (what a FrameResult carries);
// second argument 0 an mOSD frame (PNG-16 depth + JPEG colour), 1 a TUM fr1_xyz frame as the
// load generator sends it (PNG-16 + PNG).
void BM_ServedFrame(benchmark::State& state) {
  const auto images = Learn();
  if (images.empty()) {
    state.SkipWithError("needs ../shared/data/pcl_mosd_labeled_subset");
    return;
  }
  const forest::Forest* model = state.range(0) > 0 ? &PaperModel() : nullptr;
  EncodedRgbdFrame in;
  in.timestamp_s = 1.0;
  in.intrinsics = io::KinectDefaultIntrinsics(640, 480);
  std::string depth_png = *EncodeDepthPng16(images[0].depth_m, 5000.0);
  std::string color_jpeg = *EncodeJpeg(images[0].color_bgr, 90);
  if (state.range(1) == 1) {  // a TUM office frame as the load generator sends it
    const std::string tum = std::string(LIFEMAP_SOURCE_DIR) + "/../shared/data/tum_fr1_xyz_subset";
    depth_png = ReadFileBytes(tum + "/depth/1305031102.160407.png").value_or("");
    color_jpeg = ReadFileBytes(tum + "/rgb/1305031102.175304.png").value_or("");
  }
  in.depth = {DepthEncoding::kPng16, depth_png, 0, 0, 5000.0};
  in.color = {state.range(1) == 1 ? ColorEncoding::kPng : ColorEncoding::kJpeg, color_jpeg, 0, 0};
  pipeline::FramePipeline pipeline;
  pipeline::FrameRequest request;
  request.labeller = model;
  for (auto _ : state) {
    auto a = pipeline.Process(in, request);
    if (!a.ok() || (model != nullptr && !a->labels)) state.SkipWithError("no labels");
    if (state.range(0) == 2) {
      benchmark::DoNotOptimize(EncodePng(a->labels->labels));
      benchmark::DoNotOptimize(EncodePng(a->labels->confidence));
    }
  }
}
BENCHMARK(BM_ServedFrame)
    ->ArgsProduct({{0, 1, 2}, {0, 1}})
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime();

}  // namespace
}  // namespace lifemap

BENCHMARK_MAIN();
