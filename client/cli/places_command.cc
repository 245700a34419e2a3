// `lifemap places ...`: the floor plans and architecture rankings of stored visits (paper 004).
#include <fstream>
#include <iostream>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "client/cli/commands.h"
#include "client/cli/output.h"
#include "core/place/serialize.h"

namespace lifemap::cli {

void AddPlaceCommands(CLI::App* app, CliContext* ctx) {
  auto* places = app->add_subcommand(
      "places", "Floor plans of stored visits and which stored place a visit is (paper 004)");
  places->require_subcommand(1);

  auto* show = places->add_subcommand("show", "A map's floor plans (one per visit)");
  auto map = std::make_shared<std::string>();
  auto svg = std::make_shared<std::string>();
  show->add_option("MAP", *map, "map name")->required();
  show->add_option("--svg", *svg, "write each plan as PREFIX-visit-ID.svg");
  show->callback([ctx, map, svg] {
    ctx->run = [ctx, map, svg] {
      return RunCall<v1::ListPlacesResponse>(
          *ctx, [&](client::Client& c) { return c.ListPlaces(*map); },
          [&](const v1::ListPlacesResponse& r) {
            if (r.places().empty()) {
              std::cout << "no floor plans in map '" << *map
                        << "' yet (visits streamed with poses build them)\n";
            }
            for (const auto& p : r.places()) {
              std::cout << absl::StrFormat("visit %d: %d key frames, updated %s\n", p.visit_id(),
                                           p.keyframes(), HumanTime(p.updated_time_s()))
                        << p.descriptor_text();
              if (!svg->empty()) {
                const std::string path = absl::StrCat(*svg, "-visit-", p.visit_id(), ".svg");
                auto plan = place::FloorPlanFromJson(p.floor_plan_json());
                if (!plan.ok()) {
                  std::cerr << "lifemap: visit " << p.visit_id()
                            << ": stored floor plan unreadable: " << plan.status().message()
                            << "\n";
                  continue;
                }
                std::ofstream(path) << place::FloorPlanSvg(*plan);
                std::cout << "wrote " << path << "\n";
              }
            }
          });
    };
  });

  auto* query =
      places->add_subcommand("query", "Rank stored visits by architecture against a stored visit");
  auto visit = std::make_shared<uint64_t>(0);
  auto max = std::make_shared<uint32_t>(5);
  query->add_option("--visit", *visit, "visit id (streamed with poses)")->required();
  query->add_option("--max", *max, "results (default 5)")->check(CLI::Range(1, 1000));
  query->callback([ctx, visit, max] {
    ctx->run = [ctx, visit, max] {
      v1::QueryPlaceRequest req;
      req.set_visit_id(*visit);
      req.set_max_results(*max);
      req.add_methods(v1::MATCH_METHOD_ARCHITECTURE);
      return RunCall<v1::QueryPlaceResponse>(
          *ctx, [&](client::Client& c) { return c.QueryPlace(req); },
          [&](const v1::QueryPlaceResponse& r) {
            std::cout << "visit " << *visit << ":\n" << r.descriptor_text();
            if (r.matches().empty()) std::cout << "no other stored visit has a floor plan\n";
            for (const auto& m : r.matches()) {
              std::cout << absl::StrFormat("  %-20s visit %-6d score %.3f\n", m.map(), m.visit_id(),
                                           m.score());
            }
          });
    };
  });
}

}  // namespace lifemap::cli
