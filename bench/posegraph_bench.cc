// Pose-graph optimisation (issue 15): a drifted chain of keyframes with loop closures, as a
// map's worker solves it after a loop is found. Args: keyframes, loops.
#include <cmath>
#include <random>

#include <benchmark/benchmark.h>

#include "core/posegraph/pose_graph.h"

namespace lifemap::posegraph {
namespace {

// Keyframes along a 3D spiral through a building (a turn every 100 keyframes, 0.15 m apart),
// odometry edges with noise and a heading bias, and `loops` loop edges from keyframes to ones a
// turn or more before them, measured with noise.
struct Graph {
  std::map<int64_t, Pose> initial;
  std::vector<Edge> edges;
};

Graph MakeGraph(int keyframes, int loops) {
  std::mt19937 rng(7);
  std::normal_distribution<double> noise(0.0, 1.0);
  std::vector<Pose> truth(keyframes);
  for (int i = 0; i < keyframes; ++i) {
    const double a = 2 * M_PI * i / 100.0;
    truth[i].translation = {2.4 * std::cos(a), 2.4 * std::sin(a), 0.002 * i};
    truth[i].rotation = Eigen::AngleAxisd(a + M_PI / 2, Eigen::Vector3d::UnitZ()) *
                        Eigen::AngleAxisd(-M_PI / 2, Eigen::Vector3d::UnitX());
  }
  auto noisy = [&](const Pose& p, double sm, double sr) {
    Pose q = p;
    q.translation += sm * Eigen::Vector3d(noise(rng), noise(rng), noise(rng));
    q.rotation = (q.rotation * Eigen::AngleAxisd(sr * noise(rng), Eigen::Vector3d::UnitX()) *
                  Eigen::AngleAxisd(sr * noise(rng), Eigen::Vector3d::UnitY()) *
                  Eigen::AngleAxisd(sr * noise(rng) + 0.002, Eigen::Vector3d::UnitZ()))
                     .normalized();
    return q;
  };
  Graph g;
  g.initial[0] = truth[0];
  for (int i = 1; i < keyframes; ++i) {
    const Pose step = noisy(Relative(truth[i - 1], truth[i]), 0.005, 0.002);
    g.edges.push_back({i - 1, i, step, EdgeKind::kOdometry, 0.01, 0.005});
    g.initial[i] = Pose::FromIsometry(g.initial[i - 1].ToIsometry() * step.ToIsometry());
  }
  for (int l = 0; l < loops; ++l) {
    const int to = 100 + static_cast<int>((keyframes - 101) * (l + 0.5) / loops);
    // Back one turn, or several for every other loop (a place seen on several passes).
    const int turns = 1 + l % (to / 100);
    const int from = to - 100 * turns;
    g.edges.push_back({from, to, noisy(Relative(truth[from], truth[to]), 0.01, 0.005),
                       EdgeKind::kLoop, 0.03, 0.02});
  }
  return g;
}

void BM_OptimisePoseGraph(benchmark::State& state) {
  const Graph g = MakeGraph(static_cast<int>(state.range(0)), static_cast<int>(state.range(1)));
  OptimiseOptions options;
  options.threads = static_cast<int>(state.range(2));
  double iterations = 0, correction = 0, rejected = 0;
  for (auto _ : state) {
    auto r = Optimise(g.initial, g.edges, {0}, options);
    if (!r.ok()) {
      state.SkipWithError(std::string(r.status().message()).c_str());
      return;
    }
    iterations = r->iterations;
    correction = r->max_correction_m;
    rejected = static_cast<double>(r->rejected.size());
    benchmark::DoNotOptimize(r->poses);
  }
  state.counters["iterations"] = iterations;
  state.counters["max_correction_m"] = correction;
  state.counters["loops_rejected"] = rejected;
}
BENCHMARK(BM_OptimisePoseGraph)
    ->Args({300, 30, 1})
    ->Args({1000, 100, 1})
    ->Args({1000, 100, 2})
    ->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace lifemap::posegraph

BENCHMARK_MAIN();
