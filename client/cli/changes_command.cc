// `lifemap changes MAP --from V --to W`: what changed between two visits (issue 36), as a
// table, JSON, or a top-down plot (the later visit's floor plan, the objects coloured by kind of
// change, arrows for moves).
#include <algorithm>
#include <fstream>
#include <iostream>
#include <optional>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "client/cli/commands.h"
#include "client/cli/output.h"
#include "core/place/serialize.h"

namespace lifemap::cli {
namespace {

struct ChangesArgs {
  std::string map;
  uint64_t from = 0, to = 0;
  std::string svg, png;
};

// The colour of a kind of change, 0xRRGGBB.
uint32_t KindColor(const std::string& kind) {
  if (kind == "appeared") return 0x2ca02c;
  if (kind == "vanished") return 0xd62728;
  if (kind == "moved") return 0x1f77b4;
  if (kind == "wall_new" || kind == "wall_gone") return 0x7f7f7f;
  return 0x8c564b;  // doors
}

// What the plot draws, in ground-plane metres (x, y of the map's frame, z up).
struct Plot {
  std::vector<std::pair<Eigen::Vector2d, Eigen::Vector2d>> walls;
  struct Box {
    Eigen::Vector2d lo, hi;
    uint32_t color;
  };
  std::vector<Box> boxes;
  struct Arrow {
    Eigen::Vector2d from, to;
  };
  std::vector<Arrow> arrows;
  std::string title;
  Eigen::Vector2d lo{1e9, 1e9}, hi{-1e9, -1e9};
  void Grow(const Eigen::Vector2d& p) {
    lo = lo.cwiseMin(p);
    hi = hi.cwiseMax(p);
  }
};

Plot MakePlot(const v1::VisitChanges& r, const place::FloorPlan* plan) {
  Plot p;
  p.title = absl::StrFormat("map '%s': visit %d -> %d, %d changes", r.map(), r.from_visit(),
                            r.to_visit(), r.changes_size());
  if (plan != nullptr) {
    for (const auto& w : plan->walls) {
      p.walls.emplace_back(w.start, w.end);
      p.Grow(w.start);
      p.Grow(w.end);
    }
  }
  for (const auto& c : r.changes()) {
    const Eigen::Vector2d center(c.center().x(), c.center().y());
    const Eigen::Vector2d half(std::max(c.extent().x(), 0.05) / 2,
                               std::max(c.extent().y(), 0.05) / 2);
    p.boxes.push_back({center - half, center + half, KindColor(c.kind())});
    p.Grow(center - half);
    p.Grow(center + half);
    if (c.kind() == "moved") {
      const Eigen::Vector2d from(c.from_center().x(), c.from_center().y());
      p.arrows.push_back({from, center});
      p.Grow(from);
    }
  }
  if (p.lo.x() > p.hi.x()) p.lo = p.hi = Eigen::Vector2d::Zero();
  p.lo -= Eigen::Vector2d(0.5, 0.5);
  p.hi += Eigen::Vector2d(0.5, 0.5);
  return p;
}

constexpr double kPixelsPerMetre = 100;
constexpr int kHeader = 60;

// Pixel of a ground point: x right, y up (image rows grow down).
cv::Point2d ToPixel(const Plot& p, const Eigen::Vector2d& g) {
  return {(g.x() - p.lo.x()) * kPixelsPerMetre, kHeader + (p.hi.y() - g.y()) * kPixelsPerMetre};
}

const char* const kLegend =
    "appeared green, vanished red, moved blue (arrow from where it was), doors brown";

std::string ToSvg(const Plot& p) {
  const cv::Point2d size = ToPixel(p, {p.hi.x(), p.lo.y()});
  std::string s = absl::StrFormat(
      "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"%d\" height=\"%d\">\n"
      "<rect width=\"100%%\" height=\"100%%\" fill=\"white\"/>\n"
      "<defs><marker id=\"head\" markerWidth=\"8\" markerHeight=\"8\" refX=\"7\" refY=\"4\" "
      "orient=\"auto\"><path d=\"M0,0 L8,4 L0,8 z\" fill=\"#1f77b4\"/></marker></defs>\n"
      "<text x=\"8\" y=\"20\" font-family=\"sans-serif\" font-size=\"14\">%s</text>\n"
      "<text x=\"8\" y=\"40\" font-family=\"sans-serif\" font-size=\"11\">%s; 1 m = 100 "
      "px</text>\n",
      static_cast<int>(std::max(size.x, 420.0)), static_cast<int>(size.y), p.title, kLegend);
  for (const auto& [a, b] : p.walls) {
    const cv::Point2d pa = ToPixel(p, a), pb = ToPixel(p, b);
    s += absl::StrFormat(
        "<line x1=\"%.1f\" y1=\"%.1f\" x2=\"%.1f\" y2=\"%.1f\" stroke=\"black\" "
        "stroke-width=\"4\"/>\n",
        pa.x, pa.y, pb.x, pb.y);
  }
  for (const auto& b : p.boxes) {
    const cv::Point2d tl = ToPixel(p, {b.lo.x(), b.hi.y()}), br = ToPixel(p, {b.hi.x(), b.lo.y()});
    s += absl::StrFormat(
        "<rect x=\"%.1f\" y=\"%.1f\" width=\"%.1f\" height=\"%.1f\" fill=\"#%06x\" "
        "fill-opacity=\"0.6\" stroke=\"#%06x\"/>\n",
        tl.x, tl.y, br.x - tl.x, br.y - tl.y, b.color, b.color);
  }
  for (const auto& a : p.arrows) {
    const cv::Point2d pa = ToPixel(p, a.from), pb = ToPixel(p, a.to);
    s += absl::StrFormat(
        "<line x1=\"%.1f\" y1=\"%.1f\" x2=\"%.1f\" y2=\"%.1f\" stroke=\"#1f77b4\" "
        "stroke-width=\"2\" marker-end=\"url(#head)\"/>\n",
        pa.x, pa.y, pb.x, pb.y);
  }
  return s + "</svg>\n";
}

cv::Mat ToImage(const Plot& p) {
  const cv::Point2d size = ToPixel(p, {p.hi.x(), p.lo.y()});
  cv::Mat img(static_cast<int>(size.y), static_cast<int>(std::max(size.x, 640.0)), CV_8UC3,
              cv::Scalar(255, 255, 255));
  auto bgr = [](uint32_t c) { return cv::Scalar(c & 0xff, (c >> 8) & 0xff, (c >> 16) & 0xff); };
  cv::putText(img, p.title, {8, 20}, cv::FONT_HERSHEY_SIMPLEX, 0.5, {0, 0, 0}, 1, cv::LINE_AA);
  cv::putText(img, kLegend, {8, 42}, cv::FONT_HERSHEY_SIMPLEX, 0.4, {0, 0, 0}, 1, cv::LINE_AA);
  for (const auto& [a, b] : p.walls) cv::line(img, ToPixel(p, a), ToPixel(p, b), {0, 0, 0}, 4);
  for (const auto& b : p.boxes) {
    cv::rectangle(img, ToPixel(p, {b.lo.x(), b.hi.y()}), ToPixel(p, {b.hi.x(), b.lo.y()}),
                  bgr(b.color), cv::FILLED);
  }
  for (const auto& a : p.arrows) {
    cv::arrowedLine(img, ToPixel(p, a.from), ToPixel(p, a.to), bgr(0x1f77b4), 2, cv::LINE_AA, 0,
                    0.2);
  }
  return img;
}

void PrintTable(const v1::VisitChanges& r) {
  std::cout << absl::StrFormat(
      "map '%s': visit %d -> visit %d (%d and %d keyframes compared, %.1f s); classes: %s\n",
      r.map(), r.from_visit(), r.to_visit(), r.from_keyframes(), r.to_keyframes(), r.seconds(),
      r.classes());
  if (r.changes().empty()) {
    std::cout << "no change of the place seen\n";
  } else {
    std::cout << absl::StrFormat("%-11s  %-10s  %-22s  %-18s  %8s  %s\n", "KIND", "CLASS",
                                 "WHERE (m)", "SIZE (m)", "EVIDENCE", "MOVED FROM (m)");
    for (const auto& c : r.changes()) {
      std::string from;
      if (c.kind() == "moved") {
        from = absl::StrFormat("%.2f %.2f %.2f (%.2f m)", c.from_center().x(), c.from_center().y(),
                               c.from_center().z(), c.displacement_m());
      }
      std::cout << absl::StrFormat(
          "%-11s  %-10s  %6.2f %6.2f %6.2f    %4.2f %4.2f %4.2f    %8d  %s\n", c.kind(),
          Shown(c.class_name()), c.center().x(), c.center().y(), c.center().z(), c.extent().x(),
          c.extent().y(), c.extent().z(), c.evidence_views(), from);
    }
  }
  std::cout << absl::StrFormat(
      "voxels of %.2f m held by one visit only: %d; changed %d, passing by %d, unobserved %d "
      "(no evidence either way: not reported)\n",
      r.voxel_m(), r.candidate_voxels(), r.changed_voxels(), r.transient_voxels(),
      r.unobserved_voxels());
}

}  // namespace

void AddChangesCommand(CLI::App* app, CliContext* ctx) {
  auto* cmd = app->add_subcommand(
      "changes",
      "What changed between two visits of a map: objects appeared, vanished, moved; doors opened "
      "or closed (both visits in the map's frame)");
  auto a = std::make_shared<ChangesArgs>();
  cmd->add_option("MAP", a->map, "map name")->required();
  cmd->add_option("--from", a->from, "the earlier visit's id (lifemap visits list MAP)")
      ->required();
  cmd->add_option("--to", a->to, "the later visit's id")->required();
  cmd->add_option("--svg", a->svg, "write a top-down plot as SVG to this file");
  cmd->add_option("--png", a->png, "write a top-down plot as PNG to this file");
  cmd->callback([ctx, a] {
    ctx->run = [ctx, a] {
      auto c = ctx->Connect();
      if (!c.ok()) return Fail(c.status());
      auto r = (*c)->GetChanges(a->map, a->from, a->to);
      if (!r.ok()) return Fail(r.status());
      if (ctx->json) {
        std::cout << ToJson(*r) << "\n";
      } else {
        PrintTable(*r);
      }
      if (a->svg.empty() && a->png.empty()) return 0;
      // The later visit's floor plan under the objects, where it has one.
      std::optional<place::FloorPlan> plan;
      if (auto places = (*c)->ListPlaces(a->map); places.ok()) {
        for (const auto& p : places->places()) {
          if (p.visit_id() != a->to) continue;
          if (auto f = place::FloorPlanFromJson(p.floor_plan_json()); f.ok()) plan = *f;
        }
      }
      const Plot plot = MakePlot(*r, plan ? &*plan : nullptr);
      int code = 0;
      if (!a->svg.empty()) {
        std::ofstream out(a->svg);
        out << ToSvg(plot);
        if (!out) code = Fail(absl::PermissionDeniedError(absl::StrCat("cannot write ", a->svg)));
        if (out && !ctx->json) std::cout << "wrote " << a->svg << "\n";
      }
      if (!a->png.empty()) {
        if (!cv::imwrite(a->png, ToImage(plot))) {
          code = Fail(absl::PermissionDeniedError(absl::StrCat("cannot write ", a->png)));
        } else if (!ctx->json) {
          std::cout << "wrote " << a->png << "\n";
        }
      }
      return code;
    };
  });
}

}  // namespace lifemap::cli
