#include "core/place/serialize.h"

#include <cmath>
#include <functional>
#include <stdexcept>

#include <nlohmann/json.hpp>
#include <opencv2/imgproc.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"

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
  const FloorAgreement& a = plan.floor_agreement;
  auto vec = [](const Eigen::Vector3d& v) { return json::array({v.x(), v.y(), v.z()}); };
  return json{
      {"floor_height_m", plan.floor_height_m},
      {"up", vec(plan.up)},
      {"e1", vec(plan.e1)},
      {"e2", vec(plan.e2)},
      {"floor_agreement",
       {{"keyframes", a.keyframes}, {"tilt_deg_p90", a.tilt_deg_p90}, {"drift_m", a.drift_m}}},
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
    // Plans stored before issue 54 have none: nothing to judge the track by; those stored in
    // its first sessions have no drift_m (their offset_m_p90 was fooled by table tops): only
    // their tilt is judged.
    if (const auto a = j.find("floor_agreement"); a != j.end()) {
      plan.floor_agreement.keyframes = a->at("keyframes").get<int>();
      plan.floor_agreement.tilt_deg_p90 = a->at("tilt_deg_p90").get<double>();
      plan.floor_agreement.drift_m = a->value("drift_m", 0.0);
    }
    // Plans stored before issue 54 have no basis: they were built z up.
    if (const auto up = j.find("up"); up != j.end()) {
      auto vec = [&](const char* name) {
        const auto& a = j.at(name);
        const Eigen::Vector3d v(a.at(0).get<double>(), a.at(1).get<double>(),
                                a.at(2).get<double>());
        if (!v.allFinite() || std::abs(v.norm() - 1.0) > 1e-3) {
          throw std::invalid_argument(absl::StrCat(name, " must be a unit vector"));
        }
        return v;
      };
      plan.up = vec("up"), plan.e1 = vec("e1"), plan.e2 = vec("e2");
    }
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

namespace {

// Draws a plan (over the truth, when given) through line, circle and text callbacks in
// pixels, 100 px per metre, y up, 0.5 m margin, below a header with the title, a legend and a
// 1 m scale bar; returns the canvas size.
struct Painter {
  std::function<void(const Eigen::Vector2d&, const Eigen::Vector2d&, const char* colour,
                     double width_px, double opacity)>
      line;
  std::function<void(const Eigen::Vector2d&, double radius_px, double opacity)> circle;
  // Text with its baseline's left end at the point.
  std::function<void(const Eigen::Vector2d&, const std::string& text, double height_px)> text;
  std::function<void(const Eigen::Vector2d&, int64_t id)> marker;  // optional
};

// Wide enough for the legend (with the truth key) and the scale bar side by side.
constexpr double kHeaderPx = 64, kMinWidthPx = 700;

Eigen::Vector2d Paint(const FloorPlan& plan, const FloorPlan* truth, const std::string& title,
                      const Painter* painter, const std::vector<PlanMarker>* markers = nullptr) {
  Eigen::Vector2d lo(1e9, 1e9), hi(-1e9, -1e9);
  for (const FloorPlan* p : {&plan, truth}) {
    if (p == nullptr) continue;
    for (const auto& w : p->walls) {
      lo = lo.cwiseMin(w.start).cwiseMin(w.end);
      hi = hi.cwiseMax(w.start).cwiseMax(w.end);
    }
  }
  if (markers != nullptr) {
    for (const auto& m : *markers) {
      lo = lo.cwiseMin(m.at);
      hi = hi.cwiseMax(m.at);
    }
  }
  if (lo.x() > hi.x()) lo = hi = Eigen::Vector2d::Zero();
  const double scale = 100, margin = 0.5;
  Eigen::Vector2d size = (hi - lo + Eigen::Vector2d(2 * margin, 2 * margin)) * scale;
  size.x() = std::max(size.x(), kMinWidthPx);
  size.y() += kHeaderPx;
  if (painter == nullptr) return size;
  auto px = [&](const Eigen::Vector2d& p) {
    return Eigen::Vector2d((p.x() - lo.x() + margin) * scale,
                           kHeaderPx + (hi.y() - p.y() + margin) * scale);
  };
  auto draw = [&](const FloorPlan& p, double width, double opacity) {
    for (const auto& w : p.walls) {
      painter->line(px(w.start), px(w.end), "black", width, opacity);
      const Eigen::Vector2d d = (w.end - w.start).normalized();
      for (const auto& o : w.openings) {
        painter->line(px(w.start + o.from_m * d), px(w.start + o.to_m * d),
                      o.type == OpeningType::kDoor ? "saddlebrown" : "deepskyblue", width + 4,
                      opacity);
      }
    }
    for (const auto& s : p.stairs) painter->circle(px(s.center), 0.5 * scale * s.length_m, opacity);
  };
  if (truth != nullptr) draw(*truth, 18, 0.25);
  draw(plan, 6, 1.0);
  if (markers != nullptr && painter->marker) {
    for (const auto& m : *markers) painter->marker(px(m.at), m.id);
  }

  // Header: title; legend; scale bar.
  painter->text({10, 22}, title.empty() ? "floor plan (top view, y up)" : title, 16);
  double x = 10;
  const double y = 48;
  // One legend entry: its symbol drawn `symbol_px` wide at x, then its label.
  auto key = [&](double symbol_px, const std::function<void()>& symbol, const std::string& label) {
    symbol();
    painter->text({x + symbol_px + 6, y}, label, 12);
    x += symbol_px + 6 + 11.0 * static_cast<double>(label.size()) + 16;  // PNG: ~11 px a letter
  };
  auto stroke = [&](const char* colour, double width, double opacity) {
    return [=, &x] { painter->line({x, y - 5}, {x + 30, y - 5}, colour, width, opacity); };
  };
  key(30, stroke("black", 6, 1.0), "wall");
  key(30, stroke("saddlebrown", 10, 1.0), "door");
  key(30, stroke("deepskyblue", 10, 1.0), "window");
  key(
      16,
      [&] {
        painter->circle({x + 8, y - 5}, 8, 1.0);
      },
      "stairs");
  if (truth != nullptr) key(30, stroke("black", 18, 0.25), "truth");
  const double bar_right = size.x() - 12;
  painter->line({bar_right - scale, y - 5}, {bar_right, y - 5}, "black", 3, 1.0);
  painter->text({bar_right - scale, y - 12}, "1 m", 12);
  return size;
}

}  // namespace

std::string FloorPlanSvg(const FloorPlan& plan, const FloorPlan* truth, const std::string& title,
                         const std::vector<PlanMarker>* markers) {
  const Eigen::Vector2d size = Paint(plan, truth, title, nullptr, markers);
  std::string svg = absl::StrFormat(
      "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"%.0f\" height=\"%.0f\">\n"
      "<rect width=\"100%%\" height=\"100%%\" fill=\"white\"/>\n",
      size.x(), size.y());
  Painter painter;
  painter.line = [&](const Eigen::Vector2d& a, const Eigen::Vector2d& b, const char* colour,
                     double width, double opacity) {
    svg += absl::StrFormat(
        "<line x1=\"%.1f\" y1=\"%.1f\" x2=\"%.1f\" y2=\"%.1f\" stroke=\"%s\" "
        "stroke-width=\"%.0f\" stroke-opacity=\"%.2f\"/>\n",
        a.x(), a.y(), b.x(), b.y(), colour, width, opacity);
  };
  painter.circle = [&](const Eigen::Vector2d& c, double r, double opacity) {
    svg += absl::StrFormat(
        "<circle cx=\"%.1f\" cy=\"%.1f\" r=\"%.1f\" fill=\"none\" stroke=\"green\" "
        "stroke-width=\"4\" stroke-opacity=\"%.2f\"/>\n",
        c.x(), c.y(), r, opacity);
  };
  painter.text = [&](const Eigen::Vector2d& at, const std::string& text, double height) {
    std::string escaped;
    for (char c : text) {
      if (c == '<') {
        escaped += "&lt;";
      } else if (c == '>') {
        escaped += "&gt;";
      } else if (c == '&') {
        escaped += "&amp;";
      } else {
        escaped += c;
      }
    }
    svg += absl::StrFormat(
        "<text x=\"%.1f\" y=\"%.1f\" font-family=\"sans-serif\" font-size=\"%.0f\">%s</text>\n",
        at.x(), at.y(), height, escaped);
  };
  painter.marker = [&](const Eigen::Vector2d& c, int64_t id) {
    svg += absl::StrFormat(
        "<circle class=\"keyframe\" data-id=\"%d\" cx=\"%.1f\" cy=\"%.1f\" r=\"5\" "
        "fill=\"crimson\" fill-opacity=\"0.8\"><title>keyframe %d</title></circle>\n",
        id, c.x(), c.y(), id);
  };
  Paint(plan, truth, title, &painter, markers);
  return svg + "</svg>\n";
}

cv::Mat FloorPlanImage(const FloorPlan& plan, const FloorPlan* truth, const std::string& title) {
  const Eigen::Vector2d size = Paint(plan, truth, title, nullptr);
  cv::Mat image(static_cast<int>(std::ceil(size.y())), static_cast<int>(std::ceil(size.x())),
                CV_8UC3, cv::Scalar(255, 255, 255));
  auto bgr = [](const char* colour, double opacity) {
    const std::string c(colour);
    const cv::Scalar full = c == "saddlebrown"   ? cv::Scalar(19, 69, 139)
                            : c == "deepskyblue" ? cv::Scalar(255, 191, 0)
                                                 : cv::Scalar(0, 0, 0);
    return full * opacity + cv::Scalar(255, 255, 255) * (1 - opacity);  // on white
  };
  Painter painter;
  painter.line = [&](const Eigen::Vector2d& a, const Eigen::Vector2d& b, const char* colour,
                     double width, double opacity) {
    cv::line(image, cv::Point(static_cast<int>(a.x()), static_cast<int>(a.y())),
             cv::Point(static_cast<int>(b.x()), static_cast<int>(b.y())), bgr(colour, opacity),
             std::max(1, static_cast<int>(width)), cv::LINE_AA);
  };
  painter.circle = [&](const Eigen::Vector2d& c, double r, double opacity) {
    cv::circle(image, cv::Point(static_cast<int>(c.x()), static_cast<int>(c.y())),
               static_cast<int>(r),
               cv::Scalar(0, 128, 0) * opacity + cv::Scalar(255, 255, 255) * (1 - opacity), 4,
               cv::LINE_AA);
  };
  painter.text = [&](const Eigen::Vector2d& at, const std::string& text, double height) {
    // Hershey simplex is about 22 px tall at scale 1.
    cv::putText(image, text, cv::Point(static_cast<int>(at.x()), static_cast<int>(at.y())),
                cv::FONT_HERSHEY_SIMPLEX, height / 22.0, cv::Scalar(0, 0, 0), 1, cv::LINE_AA);
  };
  Paint(plan, truth, title, &painter);
  return image;
}

}  // namespace lifemap::place
