// Appearance place recognition (paper 000), per stage: a keyframe's features (ORB + 3D points +
// entropy pruning), PnP verification of one candidate, and a query against an index of N
// keyframes, with brute force over the same keyframes as the baseline in the same run.
//
//   build/bin/bench_appearance [--benchmark_filter=...]
//
// Features and verification use real frames (../shared/data/tum_fr1_xyz_subset; the benchmarks
// that need them are skipped, saying why, without it). The index is filled with synthetic word
// lists: each keyframe draws 500 distinct words from the vocabulary's 10,000 by a Zipf(1) law
// (common words are common, as in real images, which lengthens their postings: a conservative
// stand-in), weights uniform, L1-normalised.
#include <algorithm>
#include <map>
#include <random>

#include <benchmark/benchmark.h>

#include "core/appearance/recognizer.h"
#include "core/io/tum_dataset.h"
#include "core/pipeline/keyframe.h"

namespace lifemap::appearance {
namespace {

struct RealFrames {
  std::vector<pipeline::FrameAnalysis> analyses;  // with entropy masks
  std::vector<features::KeypointSet> features;    // pruned, with points
  std::string error;
};

const RealFrames& GetRealFrames() {
  static const RealFrames frames = [] {
    RealFrames out;
    const std::string dir = std::string(LIFEMAP_SOURCE_DIR) + "/../shared/data/tum_fr1_xyz_subset";
    auto seq = io::ReadTumSequence(dir);
    if (!seq.ok()) {
      out.error = std::string(seq.status().message());
      return out;
    }
    pipeline::FramePipeline pipeline;
    for (size_t i = 0; i < seq->frames.size() && i < 12; i += 3) {
      auto f = io::DecodeTumFrame(*seq, seq->frames[i]);
      if (!f.ok()) continue;
      pipeline::FrameAnalysis a;
      a.frame = *f;
      auto mask = entropy::ComputeEntropyMask(
          f->depth_m, f->color_bgr, f->intrinsics,
          pipeline::UpInCamera(f->T_world_camera, Eigen::Vector3f::UnitZ()));
      if (mask.ok()) a.entropy = *std::move(mask);
      auto k = pipeline::ExtractKeyframeFeatures(a, {});
      if (!k.ok()) continue;
      out.features.push_back(k->keypoints);
      out.analyses.push_back(std::move(a));
    }
    if (out.features.size() < 2) out.error = "fewer than two frames decoded";
    return out;
  }();
  return frames;
}

void BM_KeyframeFeatures(benchmark::State& state) {
  const auto& real = GetRealFrames();
  if (!real.error.empty()) return state.SkipWithError(real.error.c_str());
  pipeline::KeyframeFeatureOptions options;
  options.orb.max_keypoints = static_cast<int>(state.range(0));
  options.orb.detect_scale = static_cast<double>(state.range(1)) / 100.0;
  options.orb.pyramid_levels = static_cast<int>(state.range(2));
  options.orb.pyramid_scale = static_cast<double>(state.range(3)) / 100.0;
  size_t kept = 0;
  for (auto _ : state) {
    auto k = pipeline::ExtractKeyframeFeatures(real.analyses[0], options);
    kept = k->keypoints.size();
    benchmark::DoNotOptimize(k);
  }
  state.counters["kept"] = static_cast<double>(kept);
}
// Args: keypoints, detection scale in per cent (100: full resolution; 50: half), pyramid
// levels, ratio between levels in per cent.
BENCHMARK(BM_KeyframeFeatures)
    ->Args({1000, 100, 8, 120})
    ->Args({500, 100, 8, 120})
    ->Args({1000, 100, 4, 120})
    ->Args({1000, 100, 4, 140})
    ->Args({1000, 100, 3, 150})
    ->Args({1000, 50, 8, 120})
    ->Unit(benchmark::kMillisecond);

void BM_VerifyCandidate(benchmark::State& state) {
  const auto& real = GetRealFrames();
  if (!real.error.empty()) return state.SkipWithError(real.error.c_str());
  const auto& query = real.features[1];
  const auto& match = real.features[0];
  int inliers = 0;
  for (auto _ : state) {
    const Verification v = VerifyMatch(query, real.analyses[1].frame.intrinsics, match);
    inliers = v.inliers;
    benchmark::DoNotOptimize(v);
  }
  state.counters["inliers"] = inliers;
  state.counters["query_kp"] = static_cast<double>(query.size());
  state.counters["match_kp"] = static_cast<double>(match.size());
}
BENCHMARK(BM_VerifyCandidate)->Unit(benchmark::kMillisecond);

constexpr size_t kWords = 10000;
constexpr size_t kWordsPerKeyframe = 500;

BowVector SyntheticBow(std::mt19937* rng) {
  // Zipf(1) over word ranks by inverse-CDF on the harmonic numbers.
  static const std::vector<double> cdf = [] {
    std::vector<double> c(kWords);
    double sum = 0;
    for (size_t i = 0; i < kWords; ++i) c[i] = (sum += 1.0 / static_cast<double>(i + 1));
    for (double& v : c) v /= sum;
    return c;
  }();
  std::uniform_real_distribution<double> u(0, 1);
  std::vector<WordId> words;
  while (words.size() < kWordsPerKeyframe) {
    const auto w =
        static_cast<WordId>(std::lower_bound(cdf.begin(), cdf.end(), u(*rng)) - cdf.begin());
    if (std::find(words.begin(), words.end(), w) == words.end()) words.push_back(w);
  }
  std::sort(words.begin(), words.end());
  BowVector bow;
  for (WordId w : words) bow.words.emplace_back(w, 1.0f / kWordsPerKeyframe);
  return bow;
}

struct SyntheticIndex {
  std::unique_ptr<InvertedIndex> index;
  std::vector<BowVector> keyframes;  // for the brute-force baseline
};

// `stop_list`: the default stop-word share, else none.
const SyntheticIndex& GetIndex(size_t n, bool stop_list = true) {
  static std::map<std::pair<size_t, bool>, SyntheticIndex> cache;
  auto it = cache.find({n, stop_list});
  if (it != cache.end()) return it->second;
  SyntheticIndex s;
  s.index =
      std::make_unique<InvertedIndex>(kWords, stop_list ? InvertedIndex::kStopWordShare : 1.0);
  std::mt19937 rng(1);
  for (size_t i = 0; i < n; ++i) {
    BowVector bow = SyntheticBow(&rng);
    s.index->Add({1, static_cast<int64_t>(i / 100 + 1), static_cast<int64_t>(i + 1), 0.0}, bow);
    s.keyframes.push_back(std::move(bow));
  }
  return cache.emplace(std::make_pair(n, stop_list), std::move(s)).first->second;
}

// range(1): 1 = with the stop list (the default), 0 = every word scored.
void BM_IndexQuery(benchmark::State& state) {
  const auto& s = GetIndex(static_cast<size_t>(state.range(0)), state.range(1) != 0);
  std::mt19937 rng(99);
  const BowVector query = SyntheticBow(&rng);
  for (auto _ : state) benchmark::DoNotOptimize(s.index->Query(query, 8));
  const auto stats = s.index->Stats();
  state.counters["index_MB"] = static_cast<double>(stats.memory_bytes) / 1e6;
  state.counters["bytes_per_keyframe"] =
      static_cast<double>(stats.memory_bytes) / static_cast<double>(stats.keyframes);
}
BENCHMARK(BM_IndexQuery)
    ->ArgsProduct({{1000, 10000, 100000}, {1, 0}})
    ->Unit(benchmark::kMillisecond);

// The baseline: every keyframe's word list scored against the query (the same L1 score).
void BM_BruteForceQuery(benchmark::State& state) {
  const auto& s = GetIndex(static_cast<size_t>(state.range(0)));
  std::mt19937 rng(99);
  const BowVector query = SyntheticBow(&rng);
  for (auto _ : state) {
    float best = 0;
    for (const auto& k : s.keyframes) {
      float score = 0;
      auto a = query.words.begin();
      auto b = k.words.begin();
      while (a != query.words.end() && b != k.words.end()) {
        if (a->first < b->first) {
          ++a;
        } else if (b->first < a->first) {
          ++b;
        } else {
          score += std::min(a->second, b->second);
          ++a, ++b;
        }
      }
      best = std::max(best, score);
    }
    benchmark::DoNotOptimize(best);
  }
}
BENCHMARK(BM_BruteForceQuery)->Arg(1000)->Arg(10000)->Arg(100000)->Unit(benchmark::kMillisecond);

// The other baseline: descriptors matched against every stored keyframe's (no index).
void BM_BruteForceDescriptors(benchmark::State& state) {
  const auto& real = GetRealFrames();
  if (!real.error.empty()) return state.SkipWithError(real.error.c_str());
  const size_t n = static_cast<size_t>(state.range(0));
  const auto& query = real.features[1];
  for (auto _ : state) {
    int best = 0;
    for (size_t i = 0; i < n; ++i) {
      const auto& stored = real.features[i % real.features.size()];
      int close = 0;
      for (int q = 0; q < query.descriptors.rows; ++q) {
        int nearest = 256;
        for (int m = 0; m < stored.descriptors.rows; ++m) {
          nearest = std::min(nearest, HammingDistance256(query.descriptors.ptr<uint8_t>(q),
                                                         stored.descriptors.ptr<uint8_t>(m)));
        }
        close += nearest < 50 ? 1 : 0;
      }
      best = std::max(best, close);
    }
    benchmark::DoNotOptimize(best);
  }
}
BENCHMARK(BM_BruteForceDescriptors)->Arg(10)->Arg(100)->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace lifemap::appearance

BENCHMARK_MAIN();
