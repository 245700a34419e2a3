#include "client/cli/change_truth.h"

#include <algorithm>
#include <fstream>
#include <map>
#include <optional>

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>

#include "absl/strings/str_cat.h"
#include "lifemap/v1/visit_service.pb.h"

namespace lifemap::cli {
namespace {

namespace fs = std::filesystem;
using json = nlohmann::json;

absl::StatusOr<json> ReadJson(const fs::path& path) {
  std::ifstream in(path);
  if (!in) return absl::NotFoundError(absl::StrCat("cannot read ", path.string()));
  json j = json::parse(in, nullptr, false);
  if (j.is_discarded())
    return absl::InvalidArgumentError(absl::StrCat(path.string(), ": not JSON"));
  return j;
}

// Pixels per instance id over every frame of a visit (labels/instance/*.png).
std::map<int, int64_t> SeenPixels(const fs::path& visit) {
  std::map<int, int64_t> out;
  std::error_code ec;
  for (const auto& e : fs::directory_iterator(visit / "labels" / "instance", ec)) {
    const cv::Mat ids = cv::imread(e.path().string(), cv::IMREAD_UNCHANGED);
    if (ids.type() != CV_16UC1) continue;
    for (int r = 0; r < ids.rows; ++r) {
      const uint16_t* p = ids.ptr<uint16_t>(r);
      for (int c = 0; c < ids.cols; ++c) {
        if (p[c] != 0) ++out[p[c]];
      }
    }
  }
  return out;
}

// Where a door of a scene's floor plan is: the middle of its gap on its wall.
std::optional<Eigen::Vector2d> DoorCentre(const json& plan, const json& opening) {
  for (const auto& room : plan.at("rooms")) {
    if (room.at("room").get<int>() != opening.at("room").get<int>()) continue;
    for (const auto& w : room.at("walls")) {
      if (w.at("index").get<int>() != opening.at("wall").get<int>()) continue;
      const Eigen::Vector2d a(w.at("start")[0].get<double>(), w.at("start")[1].get<double>());
      const Eigen::Vector2d b(w.at("end")[0].get<double>(), w.at("end")[1].get<double>());
      const double along =
          opening.at("offset_m").get<double>() + 0.5 * opening.at("width_m").get<double>();
      return a + (b - a).normalized() * along;
    }
  }
  return std::nullopt;
}

}  // namespace

void AddChangeScoringOptions(CLI::App* cmd, ChangeScoring* scoring) {
  cmd->add_option("--min-size", scoring->min_size_m,
                  "props at least this large (largest side, m) count for recall (default 0.2)")
      ->check(CLI::Range(0.0, 10.0));
  cmd->add_option("--tolerance", scoring->tolerance_m,
                  "a report this close (m, ground plane) to a true change matches it (default 0.3)")
      ->check(CLI::Range(0.01, 5.0));
}

ReportedChange ReportOf(const v1::ObjectChange& c, const Eigen::Isometry3d& T_world_map) {
  auto to_world = [&](const v1::Vector3& p) {
    const Eigen::Vector3d w = T_world_map * Eigen::Vector3d(p.x(), p.y(), p.z());
    return Eigen::Vector2d(w.x(), w.y());
  };
  ReportedChange rep;
  rep.kind = c.kind();
  rep.class_name = c.class_name();
  rep.at = to_world(c.center());
  rep.from = to_world(c.from_center());
  rep.size_m = std::max({c.extent().x(), c.extent().y(), c.extent().z()});
  return rep;
}

absl::StatusOr<std::vector<TrueChange>> TrueChanges(const fs::path& reference,
                                                    const fs::path& query, const ChangeScoring& a) {
  auto ref = ReadJson(reference / "scene.json");
  if (!ref.ok()) return ref.status();
  auto q = ReadJson(query / "scene.json");
  if (!q.ok()) return q.status();
  std::map<int, json> before, after;
  for (const auto& o : ref->at("objects")) before[o.at("instance").get<int>()] = o;
  for (const auto& o : q->at("objects")) after[o.at("instance").get<int>()] = o;
  std::map<int, int64_t> seen_before, seen_after;
  std::vector<TrueChange> out;
  auto centre = [](const json& o) {
    return Eigen::Vector2d(o.at("center")[0].get<double>(), o.at("center")[1].get<double>());
  };
  auto largest = [](const json& o) {
    const auto& s = o.at("size_m");
    return std::max({s[0].get<double>(), s[1].get<double>(), s[2].get<double>()});
  };
  bool doors = false;
  for (const auto& c : q->at("changes")) {
    TrueChange t;
    t.kind = c.at("kind").get<std::string>();
    t.detail = c.at("detail").get<std::string>();
    t.instance = c.at("instance").get<int>();
    if (t.kind == "door_opened" || t.kind == "door_closed") {
      doors = true;
      continue;  // located below, from the two floor plans
    }
    if (t.kind != "appeared" && t.kind != "vanished" && t.kind != "moved") continue;
    if (seen_before.empty()) seen_before = SeenPixels(reference);
    if (seen_after.empty()) seen_after = SeenPixels(query);
    const bool was = before.count(t.instance) != 0, is = after.count(t.instance) != 0;
    const json& o = is ? after[t.instance] : before[t.instance];
    if (!was && !is) continue;
    t.size_m = largest(o);
    t.at = centre(o);
    t.from = was ? centre(before[t.instance]) : t.at;
    if (t.kind == "vanished") t.at = t.from;
    const bool seen_then = seen_before[t.instance] >= a.min_seen_pixels;
    const bool seen_now = seen_after[t.instance] >= a.min_seen_pixels;
    const bool seen = t.kind == "appeared"   ? seen_now
                      : t.kind == "vanished" ? seen_then
                                             : seen_then && seen_now;
    t.counted = seen && t.size_m >= a.min_size_m;
    out.push_back(t);
  }
  if (doors) {
    const auto& ro = ref->at("floor_plan").at("openings");
    const auto& qo = q->at("floor_plan").at("openings");
    for (size_t i = 0; i < std::min(ro.size(), qo.size()); ++i) {
      if (qo[i].at("type").get<std::string>() != "door") continue;
      const bool was_open = ro[i].at("open").get<bool>(), is_open = qo[i].at("open").get<bool>();
      if (was_open == is_open) continue;
      auto at = DoorCentre(q->at("floor_plan"), qo[i]);
      if (!at) continue;
      TrueChange t;
      t.kind = is_open ? "door_opened" : "door_closed";
      t.detail = qo[i].at("connects").get<bool>() ? "door to the next room" : "outer door";
      t.at = t.from = *at;
      t.size_m = qo[i].at("width_m").get<double>();
      t.counted = true;
      out.push_back(t);
    }
  }
  return out;
}

void MatchReports(std::vector<ReportedChange>* reported, std::vector<TrueChange>* truth,
                  double tolerance_m) {
  for (auto& r : *reported) {
    TrueChange* best = nullptr;
    double best_d = 1e9;
    for (auto& c : *truth) {
      if (c.found || c.kind != r.kind) continue;
      const double tol = std::max(tolerance_m, 0.5 * c.size_m);
      double d = (c.at - r.at).norm();
      if (r.kind == "moved") d = std::min(d, (c.from - r.from).norm());
      if (d <= tol && d < best_d) best = &c, best_d = d;
    }
    if (best != nullptr) {
      best->found = true;
      r.matched = absl::StrCat(best->kind, " ", best->instance);
    }
  }
}

}  // namespace lifemap::cli
