// `lifemap sim`: generates a synthetic place and its visits months apart as TUM-format folders
// with full ground truth (see core/sim).
#include <algorithm>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <sstream>

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
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
  std::string intrinsics;  // FX,FY,CX,CY
  std::string size = "640x480";
  std::string world = "building";  // as `sim suite`
};

// The camera of --size WxH and --intrinsics FX,FY,CX,CY (default: Kinect v1's 525 px focal
// length, centred, scaled to the size).
absl::StatusOr<CameraIntrinsics> SimCamera(const SimArgs& a) {
  int w = 0, h = 0;
  char x = 0;
  std::istringstream size(a.size);
  if (!(size >> w >> x >> h) || x != 'x' || !size.eof()) {
    return absl::InvalidArgumentError(
        absl::StrCat("--size must be WIDTHxHEIGHT, e.g. 640x480, got '", a.size, "'"));
  }
  CameraIntrinsics k{525.0 * w / 640.0, 525.0 * h / 480.0, (w - 1) / 2.0, (h - 1) / 2.0, w, h};
  if (!a.intrinsics.empty()) {
    auto parsed = ParseIntrinsicsFlag(a.intrinsics, w, h);
    if (!parsed.ok()) return parsed.status();
    k = {parsed->fx(), parsed->fy(), parsed->cx(), parsed->cy(), w, h};
  }
  if (auto s = k.Validate(); !s.ok()) return s;
  return k;
}

int RunSim(const CliContext& ctx, const SimArgs& a) {
  auto conditions = sim::ParseConditions(a.conditions);
  if (!conditions.ok()) return Fail(conditions.status());
  auto style = sim::ParseWorld(a.world, a.seed);
  if (!style.ok()) return UsageError(std::string(style.status().message()));
  auto place = sim::GeneratePlace(a.seed, a.shape, *style);
  if (!place.ok()) return Fail(place.status());
  auto visits =
      sim::GenerateVisits(*place, a.seed, a.visits, a.months_apart, *conditions, a.frames);
  if (!visits.ok()) return Fail(visits.status());
  sim::WriteOptions options;
  options.seed = a.seed;
  options.sensor.noise = !a.no_noise;
  auto camera = SimCamera(a);
  if (!camera.ok()) {
    return UsageError(std::string(camera.status().message()));
  }
  options.intrinsics = *camera;
  nlohmann::json manifest = {
      {"seed", a.seed},   {"place_id", place->id},      {"shape", a.shape},
      {"world", a.world}, {"conditions", a.conditions}, {"visits", nlohmann::json::array()}};
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

struct SuiteArgs {
  uint64_t seed = 1;
  int places = 3;
  int frames = 60;
  std::string out;
  bool no_noise = false;
  std::string world = "building";
};

// Paper 004's Table 1 subsets: every combination of lighting, dynamic objects and scenery
// changes, the first with none (a plain revisit).
const char* const kSubsets[8] = {
    "none",    "lighting",         "dynamic",         "lighting,dynamic",
    "scenery", "lighting,scenery", "dynamic,scenery", "lighting,dynamic,scenery"};

int RunSuite(const CliContext& ctx, const SuiteArgs& a) {
  static const char* const kShapes[] = {"rect", "L", "T", "U", "square"};
  // One building per suite: its seed is the suite's.
  auto style = sim::ParseWorld(a.world, a.seed);
  if (!style.ok()) return UsageError(std::string(style.status().message()));
  nlohmann::json manifest = {{"seed", a.seed},
                             {"world", a.world},
                             {"places", nlohmann::json::array()},
                             {"visits", nlohmann::json::array()}};
  sim::WriteOptions options;
  options.sensor.noise = !a.no_noise;
  const auto start = std::chrono::steady_clock::now();
  int frames = 0;
  for (int p = 0; p < a.places; ++p) {
    const uint64_t place_seed = a.seed * 1000 + static_cast<uint64_t>(p);
    const std::string shape = kShapes[p % 5];
    auto place = sim::GeneratePlace(place_seed, shape, *style);
    if (!place.ok()) return Fail(place.status());
    options.seed = place_seed;
    const std::string place_dir = absl::StrFormat("place_%02d", p);
    auto reference = sim::GenerateVisits(*place, place_seed, 1, 0, {}, a.frames);
    if (!reference.ok()) return Fail(reference.status());
    const std::string ref_path = place_dir + "/reference";
    auto written = sim::WriteVisit((fs::path(a.out) / ref_path).string(), *place, (*reference)[0],
                                   nullptr, options);
    if (!written.ok()) return Fail(written.status());
    frames += written->frames;
    manifest["places"].push_back(
        {{"place_id", place->id}, {"shape", shape}, {"reference", ref_path}});
    manifest["visits"].push_back({{"path", ref_path},
                                  {"place_id", place->id},
                                  {"role", "reference"},
                                  {"subset", 0},
                                  {"conditions", "none"}});
    for (int k = 0; k < 8; ++k) {
      auto conditions = sim::ParseConditions(kSubsets[k]);
      if (!conditions.ok()) return Fail(conditions.status());
      // Two visits from the same arrangement: the second, months later, is the query.
      auto visits = sim::GenerateVisits(*place, place_seed * 16 + static_cast<uint64_t>(k) + 1, 2,
                                        6, *conditions, a.frames);
      if (!visits.ok()) return Fail(visits.status());
      std::string folder = kSubsets[k];
      std::replace(folder.begin(), folder.end(), ',', '+');  // no commas in paths
      const std::string path = absl::StrFormat("%s/subset%d_%s", place_dir, k + 1, folder);
      auto q = sim::WriteVisit((fs::path(a.out) / path).string(), *place, (*visits)[1],
                               &(*reference)[0], options);
      if (!q.ok()) return Fail(q.status());
      frames += q->frames;
      manifest["visits"].push_back({{"path", path},
                                    {"place_id", place->id},
                                    {"role", "query"},
                                    {"subset", k + 1},
                                    {"conditions", kSubsets[k]},
                                    {"mean_moved", q->mean_moved}});
    }
    if (!ctx.json) {
      std::cout << absl::StrFormat("%s (%s): reference + 8 query visits\n", place->id, shape);
    }
  }
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  manifest["render_frames_per_s"] = frames / std::max(seconds, 1e-9);
  std::error_code ec;
  fs::create_directories(a.out, ec);
  std::ofstream(fs::path(a.out) / "manifest.json") << manifest.dump(2) << "\n";
  if (ctx.json) {
    std::cout << manifest.dump() << "\n";
  } else {
    std::cout << absl::StrFormat("%d places x 8 subsets, %d frames in %.1f s; %s/manifest.json\n",
                                 a.places, frames, seconds, a.out);
  }
  return 0;
}

}  // namespace

void AddSimCommands(CLI::App* app, CliContext* ctx) {
  auto* sim = app->add_subcommand(
      "sim", "Generate a synthetic place and visits months apart (TUM folders + ground truth)");
  auto a = std::make_shared<SimArgs>();
  sim->add_option("--seed", a->seed, "seed: the same seed gives the same bits");
  sim->add_option("--place-shape", a->shape, "rect | square | L | T | U")
      ->check(CLI::IsMember({"rect", "square", "L", "T", "U"}));
  sim->add_option("--visits", a->visits, "visits of the place (default 2)")
      ->check(CLI::Range(1, 100));
  sim->add_option("--months-apart", a->months_apart, "months between visits (default 6)")
      ->check(CLI::Range(0.0, 120.0));
  sim->add_option("--conditions", a->conditions,
                  "what changes between visits: lighting, dynamic, scenery (comma-separated) or "
                  "none (default scenery)");
  sim->add_option("--frames", a->frames, "frames per visit at 30 Hz (default 90)")
      ->check(CLI::Range(2, 100000));
  sim->add_option("--out", a->out, "output folder (required)");
  sim->add_flag("--no-noise", a->no_noise, "exact depth and colour (no sensor model)");
  sim->add_option("--size", a->size, "image size WIDTHxHEIGHT (default 640x480)");
  sim->add_option("--intrinsics", a->intrinsics,
                  "FX,FY,CX,CY in pixels (default 525 px focal length, centred)");
  sim->add_option(
      "--world", a->world,
      "building (default, as `sim suite`: shared materials and furniture, curved and "
      "crumpled props) | rooms (its own textures, boxes and cylinders; renders faster)");
  sim->callback([ctx, a, sim] {
    if (sim->get_subcommands().empty()) {
      ctx->run = [ctx, a] {
        if (a->out.empty()) {
          return UsageError("sim needs --out DIR");
        }
        return RunSim(*ctx, *a);
      };
    }
  });
  auto* suite = sim->add_subcommand(
      "suite",
      "A benchmark: N places x paper 004's 8 condition subsets, each a query visit "
      "against the place's reference visit, with manifest.json");
  auto b = std::make_shared<SuiteArgs>();
  suite->add_option("--seed", b->seed, "seed");
  suite->add_option("--places", b->places, "places (shapes cycle rect, L, T, U, square)")
      ->check(CLI::Range(1, 100));
  suite->add_option("--frames", b->frames, "frames per visit (default 60)")
      ->check(CLI::Range(2, 100000));
  suite->add_option("--out", b->out, "output folder")->required();
  suite->add_flag("--no-noise", b->no_noise, "exact depth and colour");
  suite->add_option("--world", b->world,
                    "building (default: the places are rooms of one building sharing floor "
                    "covering, paint and furniture models, with curved and crumpled props) | "
                    "rooms (each place its own textures, boxes and cylinders: the suites before "
                    "issue 13)");
  suite->callback([ctx, b] { ctx->run = [ctx, b] { return RunSuite(*ctx, *b); }; });
}

}  // namespace lifemap::cli
