// Per-stage benchmarks of the per-frame path that exists today: decoding and validating a
// 640x480 RGB-D frame, depth statistics, and the durable keyframe write (SQLite WAL,
// synchronous=FULL against NORMAL as the baseline in the same run).
//
//   build/bin/bench_frame [--benchmark_filter=...]
//
// Uses the first frame of ../shared/data/tum_fr1_xyz_subset (real Kinect data); falls back to
// a synthetic frame when it is absent.
#include <filesystem>

#include <benchmark/benchmark.h>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/ximgproc/segmentation.hpp>

#include "core/common/image_codec.h"
#include "core/common/rgbd_frame.h"
#include "core/entropy/entropy_mask.h"
#include "core/entropy/superjut_scores.h"
#include "core/io/tum_dataset.h"
#include "core/normals/normals.h"
#include "core/pipeline/frame_pipeline.h"
#include "core/segmentation/superjuts.h"
#include "core/sim/generator.h"
#include "core/sim/renderer.h"
#include "server/store/store.h"

namespace lifemap {
namespace {

struct Sample {
  std::string depth_png, color_png, color_jpeg;
  CameraIntrinsics k{517.3, 516.5, 318.6, 255.3, 640, 480};
};

const Sample& GetSample() {
  static const Sample sample = [] {
    Sample s;
    const std::string dir = std::string(LIFEMAP_SOURCE_DIR) + "/../shared/data/tum_fr1_xyz_subset";
    auto seq = io::ReadTumSequence(dir);
    cv::Mat color;
    if (seq.ok()) {
      s.depth_png = *ReadFileBytes(seq->frames[0].depth_path);
      s.color_png = *ReadFileBytes(seq->frames[0].rgb_path);
      color = cv::imread(seq->frames[0].rgb_path, cv::IMREAD_COLOR);
    } else {
      cv::Mat depth(480, 640, CV_16UC1);
      cv::randu(depth, 2000, 20000);
      color = cv::Mat(480, 640, CV_8UC3);
      cv::randu(color, 0, 255);
      s.depth_png = *EncodePng(depth);
      s.color_png = *EncodePng(color);
    }
    s.color_jpeg = *EncodeJpeg(color, 90);
    return s;
  }();
  return sample;
}

EncodedRgbdFrame Encoded(const Sample& s, bool jpeg) {
  EncodedRgbdFrame f;
  f.timestamp_s = 1.0;
  f.intrinsics = s.k;
  f.depth = {DepthEncoding::kPng16, s.depth_png, 0, 0, 5000.0};
  f.color = {jpeg ? ColorEncoding::kJpeg : ColorEncoding::kPng, jpeg ? s.color_jpeg : s.color_png,
             0, 0};
  return f;
}

void BM_DecodeFrame_Png16_Jpeg(benchmark::State& state) {
  const auto in = Encoded(GetSample(), true);
  for (auto _ : state) benchmark::DoNotOptimize(DecodeRgbdFrame(in));
}
BENCHMARK(BM_DecodeFrame_Png16_Jpeg)->Unit(benchmark::kMillisecond);

void BM_DecodeFrame_Png16_Png(benchmark::State& state) {
  const auto in = Encoded(GetSample(), false);
  for (auto _ : state) benchmark::DoNotOptimize(DecodeRgbdFrame(in));
}
BENCHMARK(BM_DecodeFrame_Png16_Png)->Unit(benchmark::kMillisecond);

void BM_ProbeOnly(benchmark::State& state) {
  const auto& s = GetSample();
  for (auto _ : state) {
    benchmark::DoNotOptimize(ProbeImage(s.depth_png));
    benchmark::DoNotOptimize(ProbeImage(s.color_jpeg));
  }
}
BENCHMARK(BM_ProbeOnly)->Unit(benchmark::kMicrosecond);

void BM_FramePipeline(benchmark::State& state) {
  const auto in = Encoded(GetSample(), true);
  pipeline::FramePipeline p;
  for (auto _ : state) benchmark::DoNotOptimize(p.Process(in));
}
BENCHMARK(BM_FramePipeline)->Unit(benchmark::kMillisecond);

void BM_EncodeDepthPng16(benchmark::State& state) {
  auto frame = DecodeRgbdFrame(Encoded(GetSample(), true));
  for (auto _ : state) benchmark::DoNotOptimize(EncodeDepthPng16(frame->depth_m, 5000.0));
}
BENCHMARK(BM_EncodeDepthPng16)->Unit(benchmark::kMillisecond);

// Stored keyframe depth, one codec per argument: 0 PNG-16 (level 1, what the store wrote
// before schema 7), 1 RVL, 2 paletted (the store's codec since). Encode time, and depth_kb: the
// mean size over every frame of the TUM subset (the first frame only without it).
const std::vector<cv::Mat>& TumDepths() {
  static const std::vector<cv::Mat> depths = [] {
    std::vector<cv::Mat> out;
    const std::string dir = std::string(LIFEMAP_SOURCE_DIR) + "/../shared/data/tum_fr1_xyz_subset";
    if (auto seq = io::ReadTumSequence(dir); seq.ok()) {
      for (const auto& f : seq->frames) {
        cv::Mat d = cv::imread(f.depth_path, cv::IMREAD_ANYDEPTH);
        cv::Mat metres;
        d.convertTo(metres, CV_32FC1, 1.0 / 5000.0);
        out.push_back(metres);
      }
    } else {
      out.push_back(DecodeRgbdFrame(Encoded(GetSample(), true))->depth_m);
    }
    return out;
  }();
  return depths;
}

absl::StatusOr<std::string> EncodeStoredDepth(int codec, const cv::Mat& depth_m) {
  if (codec == 0) return EncodeDepthPng16(depth_m, 5000.0);
  if (codec == 1) return EncodeDepthRvl(depth_m, 5000.0);
  return EncodeDepthPaletted(depth_m, 5000.0);
}

void BM_StoredDepthEncode(benchmark::State& state) {
  const auto& depths = TumDepths();
  const int codec = static_cast<int>(state.range(0));
  size_t i = 0;
  for (auto _ : state)
    benchmark::DoNotOptimize(EncodeStoredDepth(codec, depths[i++ % depths.size()]));
  double bytes = 0;
  for (const auto& d : depths) bytes += static_cast<double>(EncodeStoredDepth(codec, d)->size());
  state.counters["depth_kb"] = bytes / depths.size() / 1000.0;
}
BENCHMARK(BM_StoredDepthEncode)->Arg(0)->Arg(1)->Arg(2)->Unit(benchmark::kMillisecond);

void BM_StoredDepthDecode(benchmark::State& state) {
  const auto& d = TumDepths()[0];
  const int codec = static_cast<int>(state.range(0));
  const std::string bytes = *EncodeStoredDepth(codec, d);
  const DepthEncoding encoding = codec == 0   ? DepthEncoding::kPng16
                                 : codec == 1 ? DepthEncoding::kRvl
                                              : DepthEncoding::kPaletted;
  for (auto _ : state) {
    benchmark::DoNotOptimize(DecodeDepthMetres({encoding, bytes, d.cols, d.rows, 5000.0}));
  }
}
BENCHMARK(BM_StoredDepthDecode)->Arg(0)->Arg(1)->Arg(2)->Unit(benchmark::kMillisecond);

// Keyframe colour sent as PNG, re-encoded as JPEG at the quality given (the server's
// storage.color_jpeg_quality, default 90); color_kb against the PNG's size.
void BM_StoredColorJpeg(benchmark::State& state) {
  const auto& s = GetSample();
  const cv::Mat bgr = *DecodeColorBgr({ColorEncoding::kPng, s.color_png, s.k.width, s.k.height});
  const int quality = static_cast<int>(state.range(0));
  for (auto _ : state) benchmark::DoNotOptimize(EncodeJpeg(bgr, quality));
  state.counters["color_kb"] = static_cast<double>(EncodeJpeg(bgr, quality)->size()) / 1000.0;
  state.counters["png_kb"] = static_cast<double>(s.color_png.size()) / 1000.0;
}
BENCHMARK(BM_StoredColorJpeg)->Arg(75)->Arg(85)->Arg(90)->Arg(95)->Unit(benchmark::kMillisecond);

// One keyframe (real image sizes, ~600 KB) per transaction; arg 1 = synchronous FULL (the
// default, power-loss safe), arg 0 = NORMAL (baseline: safe against process crashes only).
void BM_CommitKeyframe(benchmark::State& state) {
  const auto& s = GetSample();
  const std::string dir = std::filesystem::temp_directory_path() / "lifemap-bench-store";
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  store::StoreOptions options;
  options.synchronous_full = state.range(0) == 1;
  auto st = store::Store::Open(dir + "/bench.db", options);
  auto map = (*st)->CreateMap("bench", "", 1.0);
  auto visit = (*st)->StartVisit("bench", "", "", 1.0);
  double t = 1.0;
  for (auto _ : state) {
    std::vector<store::KeyframeRecord> batch(1);
    batch[0].visit_id = visit->id;
    batch[0].timestamp_s = (t += 1.0);
    batch[0].intrinsics = s.k;
    batch[0].depth_scale = 5000;
    batch[0].depth = s.depth_png;
    batch[0].color = s.color_jpeg;
    if (!(*st)->InsertKeyframes(&batch, {}).ok()) state.SkipWithError("insert failed");
  }
  st->reset();
  std::filesystem::remove_all(dir);
}
BENCHMARK(BM_CommitKeyframe)->Arg(1)->Arg(0)->Unit(benchmark::kMillisecond);

// Entropy masks (paper 000) on the real frame, stage by stage and whole.
const RgbdFrame& DecodedSample() {
  static const RgbdFrame frame = *DecodeRgbdFrame(Encoded(GetSample(), true));
  return frame;
}

void BM_Normals(benchmark::State& state) {
  const auto& f = DecodedSample();
  for (auto _ : state) benchmark::DoNotOptimize(normals::ComputeNormals(f.depth_m, f.intrinsics));
}
BENCHMARK(BM_Normals)->Unit(benchmark::kMillisecond);

void BM_Superjuts(benchmark::State& state) {
  const auto& f = DecodedSample();
  const auto n = *normals::ComputeNormals(f.depth_m, f.intrinsics);
  for (auto _ : state) benchmark::DoNotOptimize(segmentation::SegmentSuperjuts(n));
}
BENCHMARK(BM_Superjuts)->Unit(benchmark::kMillisecond);

// Baseline in the same run: OpenCV ximgproc's Felzenszwalb-Huttenlocher on the normal map as a
// 3-channel image (std::sort of the edges, Euclidean weights; no eq. 1, no depth cuts).
void BM_XimgprocGraphSegmentation(benchmark::State& state) {
  const auto& f = DecodedSample();
  const auto n = *normals::ComputeNormals(f.depth_m, f.intrinsics);
  auto gs = cv::ximgproc::segmentation::createGraphSegmentation(0.0, 0.6f, 200);
  cv::Mat labels;
  for (auto _ : state) {
    gs->processImage(n.normals, labels);
    benchmark::DoNotOptimize(labels.data);
  }
}
BENCHMARK(BM_XimgprocGraphSegmentation)->Unit(benchmark::kMillisecond);

void BM_ScoreSuperjuts(benchmark::State& state) {
  const auto& f = DecodedSample();
  const auto n = *normals::ComputeNormals(f.depth_m, f.intrinsics);
  const auto s = *segmentation::SegmentSuperjuts(n);
  cv::Mat gray;
  if (state.range(0)) cv::cvtColor(f.color_bgr, gray, cv::COLOR_BGR2GRAY);
  for (auto _ : state) {
    benchmark::DoNotOptimize(entropy::ScoreSuperjuts(s, n, gray, {0, -1, 0}));
  }
}
BENCHMARK(BM_ScoreSuperjuts)->Arg(0)->Arg(1)->Unit(benchmark::kMillisecond);

// Everything from decoded depth + colour to the mask (what the server adds per frame).
void BM_EntropyMaskTotal(benchmark::State& state) {
  const auto& f = DecodedSample();
  for (auto _ : state) {
    cv::Mat gray;
    cv::cvtColor(f.color_bgr, gray, cv::COLOR_BGR2GRAY);
    const auto n = *normals::ComputeNormals(f.depth_m, f.intrinsics);
    const auto s = *segmentation::SegmentSuperjuts(n);
    const auto scores = *entropy::ScoreSuperjuts(s, n, gray, {0, -1, 0});
    benchmark::DoNotOptimize(entropy::EntropyMask(s, scores, 0.5f));
    state.counters["superjuts"] = static_cast<double>(s.count());
  }
}
BENCHMARK(BM_EntropyMaskTotal)->Unit(benchmark::kMillisecond);

// The served path, ComputeEntropyMask, at full resolution and every 2nd pixel (the default),
// image-grid and mesh variants.
void BM_ComputeEntropyMask(benchmark::State& state) {
  const auto& f = DecodedSample();
  entropy::EntropyMaskOptions options;
  options.downsample = static_cast<int>(state.range(0));
  options.mesh = state.range(1) != 0;
  for (auto _ : state) {
    auto r = entropy::ComputeEntropyMask(f.depth_m, f.color_bgr, f.intrinsics, {0, -1, 0}, options);
    if (!r.ok()) state.SkipWithError("entropy mask failed");
    state.counters["superjuts"] = static_cast<double>(r->superjuts.size());
  }
}
// Args: downsample, mesh variant (0 = image grid, 1 = organized mesh).
BENCHMARK(BM_ComputeEntropyMask)
    ->Args({1, 0})
    ->Args({2, 0})
    ->Args({1, 1})
    ->Args({2, 1})
    ->Unit(benchmark::kMillisecond);

// The two result images of the entropy output (score, mask) of a real frame as PNG: arg 0 =
// cv::imencode at level 1 (what the server used before session 9), arg 1 = EncodePng (libpng,
// up filter, zlib RLE: what it uses now). png_kb: both images' bytes.
void BM_EncodeResultPngs(benchmark::State& state) {
  const auto& f = DecodedSample();
  const auto r = *entropy::ComputeEntropyMask(f.depth_m, f.color_bgr, f.intrinsics, {0, -1, 0});
  const cv::Mat images[] = {r.score_image, r.mask};
  size_t bytes = 0;
  for (auto _ : state) {
    bytes = 0;
    for (const cv::Mat& image : images) {
      if (state.range(0) == 0) {
        std::vector<unsigned char> buf;
        cv::imencode(".png", image, buf, {cv::IMWRITE_PNG_COMPRESSION, 1});
        bytes += buf.size();
      } else {
        bytes += EncodePng(image)->size();
      }
    }
  }
  state.counters["png_kb"] = static_cast<double>(bytes) / 1000.0;
}
BENCHMARK(BM_EncodeResultPngs)->Arg(0)->Arg(1)->Unit(benchmark::kMillisecond);

// The synthetic world's renderer, one 640x480 frame of an L-shaped furnished room, with the
// sensor model (arg 1) and exact (arg 0).
void BM_SimRender(benchmark::State& state) {
  const auto place = *sim::GeneratePlace(7, "L");
  const auto visits = *sim::GenerateVisits(place, 7, 1, 0, {}, 30);
  sim::SensorOptions sensor;
  sensor.noise = state.range(0) != 0;
  const CameraIntrinsics k{525, 525, 319.5, 239.5, 640, 480};
  size_t f = 0;
  for (auto _ : state) {
    const auto& pose = visits[0].trajectory[f++ % visits[0].trajectory.size()].T_world_camera;
    benchmark::DoNotOptimize(sim::Render(place, visits[0].solids, {}, k, pose, sensor, f));
  }
}
BENCHMARK(BM_SimRender)->Arg(1)->Arg(0)->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace lifemap

BENCHMARK_MAIN();
