// `lifemap places ...`: the floor plans and architecture rankings of stored visits (paper 004).
#include <fstream>
#include <iostream>

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "client/cli/commands.h"
#include "client/cli/output.h"

namespace lifemap::cli {
namespace {

using nlohmann::json;

// A floor plan as SVG: walls black, doors brown, windows blue, stairs green; 100 px per metre,
// y up.
std::string FloorPlanSvg(const json& plan) {
  double lo_x = 1e9, lo_y = 1e9, hi_x = -1e9, hi_y = -1e9;
  for (const auto& w : plan["walls"]) {
    for (const char* end : {"start", "end"}) {
      lo_x = std::min(lo_x, w[end][0].get<double>()),
      hi_x = std::max(hi_x, w[end][0].get<double>());
      lo_y = std::min(lo_y, w[end][1].get<double>()),
      hi_y = std::max(hi_y, w[end][1].get<double>());
    }
  }
  const double scale = 100, margin = 0.5;
  auto X = [&](double x) { return (x - lo_x + margin) * scale; };
  auto Y = [&](double y) { return (hi_y - y + margin) * scale; };
  std::string svg = absl::StrFormat(
      "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"%.0f\" height=\"%.0f\">\n"
      "<rect width=\"100%%\" height=\"100%%\" fill=\"white\"/>\n",
      (hi_x - lo_x + 2 * margin) * scale, (hi_y - lo_y + 2 * margin) * scale);
  for (const auto& w : plan["walls"]) {
    const double ax = w["start"][0], ay = w["start"][1], bx = w["end"][0], by = w["end"][1];
    svg += absl::StrFormat(
        "<line x1=\"%.1f\" y1=\"%.1f\" x2=\"%.1f\" y2=\"%.1f\" stroke=\"black\" "
        "stroke-width=\"6\"/>\n",
        X(ax), Y(ay), X(bx), Y(by));
    const double len = std::hypot(bx - ax, by - ay);
    for (const auto& o : w["openings"]) {
      const double f = o["from_m"].get<double>() / len, t = o["to_m"].get<double>() / len;
      svg += absl::StrFormat(
          "<line x1=\"%.1f\" y1=\"%.1f\" x2=\"%.1f\" y2=\"%.1f\" stroke=\"%s\" "
          "stroke-width=\"10\"/>\n",
          X(ax + f * (bx - ax)), Y(ay + f * (by - ay)), X(ax + t * (bx - ax)),
          Y(ay + t * (by - ay)), o["type"] == "door" ? "saddlebrown" : "deepskyblue");
    }
  }
  for (const auto& s : plan["stairs"]) {
    svg += absl::StrFormat(
        "<circle cx=\"%.1f\" cy=\"%.1f\" r=\"%.1f\" fill=\"none\" stroke=\"green\" "
        "stroke-width=\"4\"/>\n",
        X(s["center"][0]), Y(s["center"][1]), 0.5 * scale * s["length_m"].get<double>());
  }
  return svg + "</svg>\n";
}

}  // namespace

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
                std::ofstream(path) << FloorPlanSvg(json::parse(p.floor_plan_json()));
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
