// `lifemap sim`: generates a synthetic place and its visits months apart as TUM-format folders
// with full ground truth (see core/sim).
#include <chrono>
#include <filesystem>
#include <fstream>
#include <iostream>

#include <nlohmann/json.hpp>

#include "absl/strings/str_format.h"
#include "client/cli/commands.h"
#include "client/cli/output.h"
#include "core/sim/generator.h"
#include "core/sim/writer.h"

namespace lifemap::cli {
namespace {

namespace fs = std::filesystem;

struct SimArgs {
  uint64_t seed = 7;
  std::string shape = "rect";
  int visits = 2;
  double months_apart = 6;
  std::string conditions = "scenery";
  int frames = 90;
  std::string out;
  bool no_noise = false;
};

int RunSim(const CliContext& ctx, const SimArgs& a) {
  auto conditions = sim::ParseConditions(a.conditions);
  if (!conditions.ok()) return Fail(conditions.status());
  auto place = sim::GeneratePlace(a.seed, a.shape);
  if (!place.ok()) return Fail(place.status());
  auto visits =
      sim::GenerateVisits(*place, a.seed, a.visits, a.months_apart, *conditions, a.frames);
  if (!visits.ok()) return Fail(visits.status());
  sim::WriteOptions options;
  options.seed = a.seed;
  options.sensor.noise = !a.no_noise;
  nlohmann::json manifest = {{"seed", a.seed},
                             {"place_id", place->id},
                             {"shape", a.shape},
                             {"conditions", a.conditions},
                             {"visits", nlohmann::json::array()}};
  const auto start = std::chrono::steady_clock::now();
  int frames = 0;
  for (size_t i = 0; i < visits->size(); ++i) {
    const auto& v = (*visits)[i];
    const std::string name = absl::StrFormat("visit_%02d", v.index);
    const std::string dir = (fs::path(a.out) / name).string();
    auto summary = sim::WriteVisit(dir, *place, v, i > 0 ? &(*visits)[i - 1] : nullptr, options);
    if (!summary.ok()) return Fail(summary.status());
    frames += summary->frames;
    manifest["visits"].push_back({{"path", name},
                                  {"visit", v.index},
                                  {"place_id", place->id},
                                  {"months_since_first", v.months_since_first},
                                  {"frames", summary->frames},
                                  {"changes", v.changes.size()},
                                  {"mean_valid_depth", summary->mean_valid_depth},
                                  {"mean_moved", summary->mean_moved}});
    if (!ctx.json) {
      std::cout << absl::StrFormat(
          "%s: %d frames, %.0f%% valid depth, %.1f%% of pixels changed since the last visit, "
          "%d changes\n",
          dir, summary->frames, 100 * summary->mean_valid_depth, 100 * summary->mean_moved,
          v.changes.size());
    }
  }
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  manifest["render_frames_per_s"] = frames / std::max(seconds, 1e-9);
  std::ofstream(fs::path(a.out) / "manifest.json") << manifest.dump(2) << "\n";
  if (ctx.json) {
    std::cout << manifest.dump() << "\n";
  } else {
    std::cout << absl::StrFormat("%s (%s): %d visits, %d frames in %.1f s; %s/manifest.json\n",
                                 place->id, a.shape, visits->size(), frames, seconds, a.out);
  }
  return 0;
}

}  // namespace

void AddSimCommands(CLI::App* app, CliContext* ctx) {
  auto* sim = app->add_subcommand(
      "sim", "Generate a synthetic place and visits months apart (TUM folders + ground truth)");
  auto a = std::make_shared<SimArgs>();
  sim->add_option("--seed", a->seed, "seed: the same seed gives the same bits");
  sim->add_option("--place-shape", a->shape, "rect | square | L")
      ->check(CLI::IsMember({"rect", "square", "L"}));
  sim->add_option("--visits", a->visits, "visits of the place (default 2)")
      ->check(CLI::Range(1, 100));
  sim->add_option("--months-apart", a->months_apart, "months between visits (default 6)")
      ->check(CLI::Range(0.0, 120.0));
  sim->add_option("--conditions", a->conditions,
                  "what changes between visits: lighting,scenery or none (default scenery)");
  sim->add_option("--frames", a->frames, "frames per visit at 30 Hz (default 90)")
      ->check(CLI::Range(2, 100000));
  sim->add_option("--out", a->out, "output folder")->required();
  sim->add_flag("--no-noise", a->no_noise, "exact depth and colour (no sensor model)");
  sim->callback([ctx, a] { ctx->run = [ctx, a] { return RunSim(*ctx, *a); }; });
}

}  // namespace lifemap::cli
