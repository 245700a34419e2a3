#include "core/place/serialize.h"

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"

namespace lifemap::place {
namespace {

using nlohmann::json;

const char* TypeName(OpeningType t) { return t == OpeningType::kDoor ? "door" : "window"; }

OpeningType TypeFrom(const std::string& s) {
  if (s == "door") return OpeningType::kDoor;
  if (s == "window") return OpeningType::kWindow;
  throw std::invalid_argument("opening type must be \"door\" or \"window\", got \"" + s + "\"");
}

json Point(const Eigen::Vector2d& p) { return json::array({p.x(), p.y()}); }
Eigen::Vector2d PointFrom(const json& j) {
  if (!j.is_array() || j.size() != 2) throw std::invalid_argument("a point is [x, y]");
  return {j[0].get<double>(), j[1].get<double>()};
}

}  // namespace

std::string DescriptorToJson(const PlaceDescriptor& d) {
  json corners = json::array(), stairs = json::array();
  for (const auto& c : d.corners) {
    json openings = json::array();
    for (const auto& o : c.openings) {
      openings.push_back(
          {{"type", TypeName(o.type)}, {"length_m", o.length_m}, {"distance_m", o.distance_m}});
    }
    corners.push_back(
        {{"length_m", c.length_m}, {"angle_deg", c.angle_deg}, {"openings", openings}});
  }
  for (const auto& s : d.stairs) {
    stairs.push_back({{"ascending", s.ascending},
                      {"length_m", s.length_m},
                      {"width_m", s.width_m},
                      {"distance_to_wall_m", s.distance_to_wall_m}});
  }
  return json{{"corners", corners}, {"stairs", stairs}}.dump();
}

absl::StatusOr<PlaceDescriptor> DescriptorFromJson(const std::string& text) {
  try {
    const json j = json::parse(text);
    PlaceDescriptor d;
    for (const auto& c : j.at("corners")) {
      CornerEntry e;
      e.length_m = c.at("length_m").get<double>();
      e.angle_deg = c.at("angle_deg").get<double>();
      for (const auto& o : c.at("openings")) {
        e.openings.push_back({TypeFrom(o.at("type").get<std::string>()),
                              o.at("length_m").get<double>(), o.at("distance_m").get<double>()});
      }
      d.corners.push_back(std::move(e));
    }
    for (const auto& s : j.at("stairs")) {
      d.stairs.push_back({s.at("ascending").get<bool>(), s.at("length_m").get<double>(),
                          s.at("width_m").get<double>(), s.at("distance_to_wall_m").get<double>()});
    }
    return d;
  } catch (const std::exception& e) {
    return absl::InvalidArgumentError(absl::StrCat("place descriptor JSON: ", e.what()));
  }
}

std::string FloorPlanToJson(const FloorPlan& plan) {
  json walls = json::array(), stairs = json::array();
  for (const auto& w : plan.walls) {
    json openings = json::array();
    for (const auto& o : w.openings) {
      openings.push_back({{"type", TypeName(o.type)},
                          {"from_m", o.from_m},
                          {"to_m", o.to_m},
                          {"bottom_m", o.bottom_m},
                          {"top_m", o.top_m}});
    }
    walls.push_back({{"start", Point(w.start)},
                     {"end", Point(w.end)},
                     {"observed_m2", w.observed_m2},
                     {"openings", openings}});
  }
  for (const auto& s : plan.stairs) {
    stairs.push_back({{"ascending", s.ascending},
                      {"steps", s.steps},
                      {"rise_m", s.rise_m},
                      {"length_m", s.length_m},
                      {"width_m", s.width_m},
                      {"center", Point(s.center)},
                      {"distance_to_wall_m", s.distance_to_wall_m}});
  }
  return json{{"floor_height_m", plan.floor_height_m},
              {"keyframes", plan.keyframes},
              {"walls", walls},
              {"stairs", stairs}}
      .dump();
}

absl::StatusOr<FloorPlan> FloorPlanFromJson(const std::string& text) {
  try {
    const json j = json::parse(text);
    FloorPlan plan;
    plan.floor_height_m = j.at("floor_height_m").get<double>();
    plan.keyframes = j.at("keyframes").get<int>();
    for (const auto& w : j.at("walls")) {
      Wall wall;
      wall.start = PointFrom(w.at("start"));
      wall.end = PointFrom(w.at("end"));
      wall.observed_m2 = w.at("observed_m2").get<double>();
      for (const auto& o : w.at("openings")) {
        wall.openings.push_back({TypeFrom(o.at("type").get<std::string>()),
                                 o.at("from_m").get<double>(), o.at("to_m").get<double>(),
                                 o.at("bottom_m").get<double>(), o.at("top_m").get<double>()});
      }
      plan.walls.push_back(std::move(wall));
    }
    for (const auto& s : j.at("stairs")) {
      StairFlight f;
      f.ascending = s.at("ascending").get<bool>();
      f.steps = s.at("steps").get<int>();
      f.rise_m = s.at("rise_m").get<double>();
      f.length_m = s.at("length_m").get<double>();
      f.width_m = s.at("width_m").get<double>();
      f.center = PointFrom(s.at("center"));
      f.distance_to_wall_m = s.at("distance_to_wall_m").get<double>();
      plan.stairs.push_back(f);
    }
    return plan;
  } catch (const std::exception& e) {
    return absl::InvalidArgumentError(absl::StrCat("floor plan JSON: ", e.what()));
  }
}

}  // namespace lifemap::place
