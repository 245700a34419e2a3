// `lifemap eval places`: paper 004's evaluation on a synthetic suite (lifemap sim suite) —
// floor plans against the scenes' ground truth, and place recognition per condition subset by
// architecture next to an appearance-only baseline.
#include <fstream>
#include <iostream>
#include <map>

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "client/cli/study.h"
#include "core/eval/metrics.h"
#include "core/eval/place_study.h"
#include "core/place/serialize.h"

namespace lifemap::cli {
namespace {

using nlohmann::json;

const char* const kSubsetNames[8] = {
    "none",    "lighting",          "dynamic",          "lighting, dynamic",
    "scenery", "lighting, scenery", "dynamic, scenery", "lighting, dynamic, scenery"};

double Mean(const std::vector<double>& v) {
  double s = 0;
  for (double x : v) s += x;
  return v.empty() ? 0.0 : s / static_cast<double>(v.size());
}

// Floor-plan figures over a set of visits.
struct PlanTally {
  int visits = 0, plans = 0, outlines_right = 0, truth_walls = 0, walls_found = 0;
  int truth_openings = 0, openings_found = 0, extra_openings = 0, truth_stairs = 0,
      stairs_found = 0;
  std::vector<double> lengths, angles;

  void Add(const eval::SuiteVisit& v) {
    ++visits;
    if (!v.has_truth) return;
    const auto& e = v.error;
    truth_walls += e.truth_walls;
    truth_openings += e.truth_openings;
    truth_stairs += e.truth_stairs;
    if (!v.folded.plan_status.ok()) return;
    ++plans;
    outlines_right += e.outline_right ? 1 : 0;
    walls_found += e.walls_found;
    openings_found += e.openings_found;
    extra_openings += e.extra_openings;
    stairs_found += e.stairs_found;
    lengths.insert(lengths.end(), e.length_errors_m.begin(), e.length_errors_m.end());
    angles.insert(angles.end(), e.angle_errors_deg.begin(), e.angle_errors_deg.end());
  }
  double openings_share() const {
    return truth_openings > 0 ? static_cast<double>(openings_found) / truth_openings : 0.0;
  }
  std::string Row(const std::string& name) const {
    return absl::StrFormat("| %s | %d | %d | %d | %d/%d | %.3f | %.2f | %d/%d | %d | %d/%d |\n",
                           name, visits, plans, outlines_right, walls_found, truth_walls,
                           Mean(lengths), Mean(angles), openings_found, truth_openings,
                           extra_openings, stairs_found, truth_stairs);
  }
};

std::string Status(const eval::SuiteVisit& v) {
  if (v.folded.plan_status.ok()) return "ok";
  std::string m(v.folded.plan_status.message());
  std::replace(m.begin(), m.end(), ',', ';');
  return m;
}

struct PlaceEvalArgs {
  std::string suite, out;
  std::string thresholds_from;  // an earlier run's summary.json
  int threads = 0;
};

// The thresholds an earlier run chose (its summary.json), for a held-out evaluation.
absl::Status ReadThresholds(const std::string& path, eval::PlaceStudyOptions* options) {
  std::ifstream in(path);
  if (!in) return absl::NotFoundError(absl::StrCat("cannot read --thresholds-from ", path));
  const json s = json::parse(in, nullptr, /*allow_exceptions=*/false);
  for (const auto& [key, value] :
       {std::pair<const char*, double*>{"threshold", &options->architecture_threshold},
        {"baseline_threshold", &options->appearance_threshold}}) {
    if (!s.is_object() || !s.contains(key) || !s[key].is_number() || s[key].get<double>() < 0 ||
        s[key].get<double>() > 1) {
      return absl::InvalidArgumentError(absl::StrCat(
          path, " has no \"", key,
          "\" in [0, 1]: give the summary.json an earlier lifemap eval places run wrote"));
    }
    *value = s[key].get<double>();
  }
  return absl::OkStatus();
}

int RunPlaceEval(const CliContext& ctx, const PlaceEvalArgs& a) {
  if (auto s = PrepareOut(a.out); !s.ok()) return Fail(s);
  eval::PlaceStudyOptions options;
  options.threads = a.threads;
  if (!a.thresholds_from.empty()) {
    if (auto s = ReadThresholds(a.thresholds_from, &options); !s.ok()) return Fail(s);
  }
  auto study = eval::RunPlaceStudy(a.suite, options, [&](const std::string& line) {
    if (!ctx.json) std::cerr << line << "\n";
  });
  if (!study.ok()) return Fail(study.status());

  // Floor plans against the truth, per visit and per wall.
  std::string visits_csv =
      "path,place,shape,role,subset,frames,keyframes,plan,truth_walls,built_walls,walls_found,"
      "outline_right,mean_length_error_m,mean_angle_error_deg,truth_openings,openings_found,"
      "extra_openings,closed_doors,truth_stairs,stairs_found\n";
  std::string walls_csv = "path,shape,truth_wall,built_wall,truth_m,built_m,error_m\n";
  PlanTally all;
  std::map<std::string, PlanTally> by_shape;
  std::vector<std::pair<std::string, std::string>> texts;
  std::vector<std::pair<std::string, cv::Mat>> pngs;
  for (const auto& v : study->visits) {
    if (v.folded.plan_status.ok()) {
      std::string name = v.path;
      std::replace(name.begin(), name.end(), '/', '-');
      const place::FloorPlan* truth = v.has_truth ? &v.truth.plan : nullptr;
      const std::string title = absl::StrCat(v.path, " (", v.shape, "): built plan",
                                             truth != nullptr ? " over scene.json's truth" : "");
      texts.emplace_back("plans/" + name + ".svg",
                         place::FloorPlanSvg(v.folded.plan, truth, title));
      pngs.emplace_back("plans/" + name + ".png",
                        place::FloorPlanImage(v.folded.plan, truth, title));
    }
    all.Add(v);
    by_shape[v.shape].Add(v);
    const auto& e = v.error;
    visits_csv += absl::StrFormat(
        "%s,%s,%s,%s,%d,%d,%d,%s,%d,%d,%d,%d,%.4f,%.3f,%d,%d,%d,%d,%d,%d\n", v.path, v.place_id,
        v.shape, v.role, v.subset, v.folded.frames, v.folded.keyframes, Status(v), e.truth_walls,
        e.built_walls, e.walls_found, e.outline_right ? 1 : 0, Mean(e.length_errors_m),
        Mean(e.angle_errors_deg), e.truth_openings, e.openings_found, e.extra_openings,
        v.truth.closed_doors, e.truth_stairs, e.stairs_found);
    for (const auto& p : e.pairs) {
      walls_csv += absl::StrFormat("%s,%s,%d,%d,%.4f,%.4f,%.4f\n", v.path, v.shape, p.truth,
                                   p.built, p.truth_m, p.built_m, p.built_m - p.truth_m);
    }
  }

  // Recognition.
  std::string queries_csv = "method,path,place,subset,trial,predicted,score,correct\n";
  const eval::MethodResult* methods[2] = {&study->architecture, &study->appearance};
  for (const auto* m : methods) {
    for (const auto& t : m->trials) {
      const auto& q = study->visits[t.query];
      queries_csv +=
          absl::StrFormat("%s,%s,%s,%d,%s,%s,%.4f,%d\n", m->name, q.path, q.place_id, t.subset,
                          t.known ? "known" : "unknown", t.predicted, t.score, t.correct ? 1 : 0);
    }
  }
  std::string curve_csv = "method,threshold,precision,recall,f1\n";
  std::vector<eval::Series> pr, f1;
  const cv::Scalar colors[2] = {{40, 40, 200}, {200, 120, 30}};
  for (int i = 0; i < 2; ++i) {
    const auto* m = methods[i];
    eval::Series s{m->name, {}, {}, colors[i]};
    for (const auto& p : m->curve) {
      curve_csv += absl::StrFormat("%s,%.3f,%.4f,%.4f,%.4f\n", m->name, p.threshold, p.precision,
                                   p.recall, p.f1);
      s.x.push_back(p.recall);
      s.y.push_back(p.precision);
    }
    pr.push_back(s);
    eval::Series b{m->name + " F1", {}, {}, colors[i]};
    for (int k = 0; k < 8; ++k) {
      b.x.push_back((k + 0.5) / 8.0);
      b.y.push_back(m->subsets[static_cast<size_t>(k)].f1);
    }
    f1.push_back(b);
  }

  // Report.
  int places = 0, queries = 0;
  for (const auto& v : study->visits) {
    places += v.role == "reference" ? 1 : 0;
    queries += v.role == "query" ? 1 : 0;
  }
  std::string report = absl::StrFormat(
      "# Architecture place recognition (paper 004) on %s\n\n"
      "%d places (a reference visit each), %d query visits, %.0f s.\n\n"
      "## Floor plans against the scenes' ground truth (paper 004, Fig. 11)\n\n"
      "Every visit's plan, from its key frames and ground-truth poses, against the main room's "
      "walls and its open doors and windows (closed doors are flush with the wall). Length and "
      "angle errors are means over the walls and corners that pair with the truth.\n\n"
      "| shape | visits | plans | outline right | walls found | length error (m) | angle "
      "error (°) | openings found | extra openings | stairs found |\n"
      "|---|---|---|---|---|---|---|---|---|---|\n",
      a.suite, places, queries, study->seconds);
  for (const auto& [shape, tally] : by_shape) report += tally.Row(shape);
  report += all.Row("all");
  report += absl::StrFormat(
      "\n## Place recognition per condition subset (paper 004, Table 2)\n\n"
      "Open set: each query is tried against every reference (its own among them) and with its "
      "own place left out (to be rejected). One threshold per method: architecture %.3f, "
      "appearance %.3f (%s). Top-1: the best reference is the query's place, no "
      "threshold.\n\n"
      "| subset | conditions | architecture P / R / F1 | top-1 | appearance P / R / F1 | top-1 "
      "|\n|---|---|---|---|---|---|\n",
      study->architecture.operating.threshold, study->appearance.operating.threshold,
      a.thresholds_from.empty()
          ? "each the one of its best F1 over every subset together, chosen on this suite, so "
            "optimistic for both alike"
          : absl::StrCat("chosen on another suite, held out: ", a.thresholds_from));
  json f1_json = json::object(), baseline_json = json::object(), subsets = json::array();
  for (int k = 0; k < 8; ++k) {
    const auto& ar = study->architecture.subsets[static_cast<size_t>(k)];
    const auto& ap = study->appearance.subsets[static_cast<size_t>(k)];
    const double at1 = study->architecture.top1[static_cast<size_t>(k)];
    const double pt1 = study->appearance.top1[static_cast<size_t>(k)];
    report += absl::StrFormat(
        "| %d | %s | %.2f / %.2f / **%.2f** | %.2f | %.2f / %.2f / %.2f | %.2f |\n", k + 1,
        kSubsetNames[k], ar.precision, ar.recall, ar.f1, at1, ap.precision, ap.recall, ap.f1, pt1);
    const std::string key = absl::StrFormat("subset%d", k + 1);
    f1_json[key] = ar.f1;
    baseline_json[key] = ap.f1;
    subsets.push_back(
        {{"subset", k + 1},
         {"conditions", kSubsetNames[k]},
         {"architecture",
          {{"precision", ar.precision}, {"recall", ar.recall}, {"f1", ar.f1}, {"top1", at1}}},
         {"appearance",
          {{"precision", ap.precision}, {"recall", ap.recall}, {"f1", ap.f1}, {"top1", pt1}}}});
  }
  const auto& ao = study->architecture.operating;
  const auto& po = study->appearance.operating;
  report += absl::StrFormat(
      "| all | | %.2f / %.2f / **%.2f** | | %.2f / %.2f / %.2f | |\n\n"
      "Files: `visits.csv` (every visit's plan against the truth), `walls.csv` (every paired "
      "wall), `queries.csv` (every trial and method), `pr_curve.csv` and `pr_curve.png` "
      "(precision against recall as the threshold sweeps, every subset together), "
      "`f1_subsets.png` (F1 per subset, subsets 1..8 left to right), `plans/*.svg|png` (each "
      "visit's plan in black over the truth in grey), `summary.json`.\n",
      ao.precision, ao.recall, ao.f1, po.precision, po.recall, po.f1);

  json shapes = json::object();
  for (const auto& [shape, t] : by_shape) {
    shapes[shape] = {{"visits", t.visits},
                     {"plans", t.plans},
                     {"outlines_right", t.outlines_right},
                     {"length_m", Mean(t.lengths)},
                     {"angle_deg", Mean(t.angles)},
                     {"openings_found", t.openings_share()}};
  }
  const json summary = {
      {"suite", a.suite},
      {"places", places},
      {"queries", queries},
      {"seconds", study->seconds},
      {"f1", f1_json},
      {"baseline_f1", baseline_json},
      {"floorplan_error",
       {{"length_m", Mean(all.lengths)},
        {"angle_deg", Mean(all.angles)},
        {"openings_found", all.openings_share()},
        {"walls_found",
         all.truth_walls > 0 ? static_cast<double>(all.walls_found) / all.truth_walls : 0.0},
        {"plans", all.plans},
        {"outlines_right", all.outlines_right},
        {"visits", all.visits},
        {"extra_openings", all.extra_openings},
        {"stairs_found", all.stairs_found},
        {"truth_stairs", all.truth_stairs},
        {"by_shape", shapes}}},
      {"threshold", ao.threshold},
      {"baseline_threshold", po.threshold},
      {"thresholds_from", a.thresholds_from.empty() ? json(nullptr) : json(a.thresholds_from)},
      {"overall",
       {{"architecture", {{"precision", ao.precision}, {"recall", ao.recall}, {"f1", ao.f1}}},
        {"appearance", {{"precision", po.precision}, {"recall", po.recall}, {"f1", po.f1}}}}},
      {"subsets", subsets}};
  pngs.emplace_back("pr_curve.png",
                    eval::PlotCurves(pr, "place recognition, every subset", "recall", "precision"));
  pngs.emplace_back("f1_subsets.png", eval::PlotCurves(f1, "F1 per subset (1..8)", "subset", "F1"));
  texts.emplace_back("visits.csv", visits_csv);
  texts.emplace_back("walls.csv", walls_csv);
  texts.emplace_back("queries.csv", queries_csv);
  texts.emplace_back("pr_curve.csv", curve_csv);
  if (auto s = PrepareOut((std::filesystem::path(a.out) / "plans").string()); !s.ok()) {
    return Fail(s);
  }
  return FinishStudy(ctx, a.out, texts, pngs, summary, report);
}

}  // namespace

void AddPlaceEvalCommand(CLI::App* eval, CliContext* ctx) {
  auto a = std::make_shared<PlaceEvalArgs>();
  auto* cmd = eval->add_subcommand(
      "places",
      "Paper 004 on a synthetic suite (lifemap sim suite): floor plans against the ground truth "
      "and place recognition per condition subset, by architecture and by appearance");
  cmd->add_option("--suite", a->suite, "folder written by lifemap sim suite (manifest.json)")
      ->required()
      ->check(CLI::ExistingDirectory);
  cmd->add_option("--out", a->out, "output folder (created)")->required();
  cmd->add_option("--thresholds-from", a->thresholds_from,
                  "summary.json of an earlier run (another seed): accept matches at its "
                  "thresholds instead of choosing them on this suite (a held-out evaluation)")
      ->check(CLI::ExistingFile);
  cmd->add_option("--threads", a->threads, "worker threads (default: one per core)")
      ->check(CLI::Range(0, 256));
  cmd->callback([ctx, a] { ctx->run = [ctx, a] { return RunPlaceEval(*ctx, *a); }; });
}

}  // namespace lifemap::cli
