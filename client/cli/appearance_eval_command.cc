// `lifemap eval appearance`: paper 000's purpose evaluated — appearance place recognition with
// the entropy pruning against no pruning, random pruning (the null) and oracle pruning, next to
// architecture and the fused ranking, on a synthetic suite and on real recordings.
#include <fstream>
#include <iostream>
#include <map>

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "client/cli/study.h"
#include "core/eval/appearance_study.h"
#include "core/eval/metrics.h"

namespace lifemap::cli {
namespace {

using nlohmann::json;

struct AppearanceEvalArgs {
  std::string suite, out, thresholds_from, mosd, tum_reference, tum_query;
  int threads = 0;
  int query_stride = 1;
  features::OrbOptions orb;  // the server's defaults
};

const char* const kSubsetNames[8] = {
    "none",    "lighting",          "dynamic",          "lighting, dynamic",
    "scenery", "lighting, scenery", "dynamic, scenery", "lighting, dynamic, scenery"};
const char* const kMethods[6] = {"pruned", "unpruned", "null", "oracle", "architecture", "fused"};

json PerSubset(const std::array<double, 8>& v) {
  json j = json::object();
  for (int k = 0; k < 8; ++k) j[absl::StrFormat("subset%d", k + 1)] = v[static_cast<size_t>(k)];
  return j;
}

// Real views recognised per variant: the share accepted at each variant's threshold.
json RealSummary(const std::map<std::string, std::vector<eval::RealTrial>>& by_variant,
                 const std::map<std::string, double>& thresholds, std::string* report) {
  json out = json::object();
  for (const auto& [variant, trials] : by_variant) {
    const auto t = thresholds.find(variant);
    const double threshold = t != thresholds.end() ? t->second : 0.0;
    int accepted = 0, verified = 0;
    double max_score = 0;
    std::vector<double> inliers;
    for (const auto& r : trials) {
      if (r.best.empty()) continue;
      ++verified;
      accepted += r.score >= threshold ? 1 : 0;
      max_score = std::max(max_score, r.score);
      inliers.push_back(r.inliers);
    }
    std::sort(inliers.begin(), inliers.end());
    const double median = inliers.empty() ? 0 : inliers[inliers.size() / 2];
    out[variant] = {{"views", trials.size()}, {"verified", verified},   {"accepted", accepted},
                    {"threshold", threshold}, {"max_score", max_score}, {"median_inliers", median}};
    *report += absl::StrFormat("| %s | %d | %d | %d (at %.3f) | %.3f | %.0f |\n", variant,
                               trials.size(), verified, accepted, threshold, max_score, median);
  }
  return out;
}

int RunAppearanceEval(const CliContext& ctx, const AppearanceEvalArgs& a) {
  if (a.suite.empty() && a.mosd.empty() && a.tum_reference.empty()) {
    return UsageError("eval appearance needs --suite DIR, --mosd DIR or --tum-reference DIR");
  }
  if (a.tum_reference.empty() != a.tum_query.empty()) {
    return UsageError("--tum-reference and --tum-query go together");
  }
  eval::AppearanceStudyOptions options;
  options.features.orb = a.orb;
  if (auto s = options.features.Validate(); !s.ok()) return UsageError(std::string(s.message()));
  if (auto s = PrepareOut(a.out); !s.ok()) return Fail(s);
  options.threads = a.threads;
  options.query_stride = a.query_stride;
  options.places.threads = a.threads;
  if (!a.thresholds_from.empty()) {
    std::ifstream in(a.thresholds_from);
    try {
      json j;
      in >> j;
      for (const auto& [method, t] : j.at("threshold").items()) {
        options.thresholds[method] = t.get<double>();
      }
    } catch (const json::exception& e) {
      return Fail(absl::InvalidArgumentError(
          absl::StrCat(a.thresholds_from,
                       ": not an `eval appearance` summary (threshold per method): ", e.what())));
    }
  }
  std::vector<std::pair<std::string, std::string>> texts;
  std::vector<std::pair<std::string, cv::Mat>> pngs;
  json summary = {
      {"thresholds_from", a.thresholds_from.empty() ? json(nullptr) : json(a.thresholds_from)}};
  std::string report = "# Appearance place recognition with entropy pruning (paper 000)\n\n";
  std::map<std::string, double> thresholds = options.thresholds;
  auto progress = [&ctx](const std::string& line) {
    if (!ctx.json) std::cerr << line << "\n";
  };

  if (!a.suite.empty()) {
    auto study = eval::RunAppearanceStudy(a.suite, options, progress);
    if (!study.ok()) return Fail(study.status());
    report += absl::StrFormat(
        "Suite %s: %d reference and %d query keyframes (%d visits), %.0f s. The entropy masks "
        "dropped %.1f %% of the detected keypoints; the null drops as many at random, the oracle "
        "those on movable objects (chairs and props, from the scene's labels).\n\n"
        "Per query keyframe: recognised against every reference keyframe (known trial) and with "
        "its own place left out (unknown trial, to be rejected). Thresholds: %s.\n\n"
        "| method | threshold | P / R / F1 (all) | mean keypoints | pose error (median cm / deg, "
        "n) |\n|---|---|---|---|---|\n",
        a.suite, study->reference_keyframes, study->query_keyframes, study->visits.size(),
        study->seconds, 100 * study->pruned_share,
        a.thresholds_from.empty() ? "each method's best F1 over every subset, chosen here "
                                    "(optimistic for all alike)"
                                  : absl::StrCat("held out, from ", a.thresholds_from));
    json threshold = json::object(), top1 = json::object(), full_precision = json::object();
    std::vector<eval::Series> pr, f1;
    const cv::Scalar colors[6] = {{40, 40, 200}, {200, 120, 30}, {120, 120, 120},
                                  {40, 160, 40}, {160, 40, 160}, {30, 30, 30}};
    std::string queries_csv = "method,keyframe,visit,subset,trial,predicted,score,correct\n";
    std::string table = "\n| subset | conditions |";
    for (const char* m : kMethods) table += absl::StrCat(" ", m, " F1 |");
    table += " pruned top-1 | pruned R@P=1 |\n|---|---|";
    for (int i = 0; i < 6; ++i) table += "---|";
    table += "---|---|\n";
    for (int i = 0; i < 6; ++i) {
      const std::string name = kMethods[i];
      const eval::AppearanceMethod& m = study->methods.at(name);
      const auto& o = m.result.operating;
      thresholds[name] = o.threshold;
      threshold[name] = o.threshold;
      std::array<double, 8> f1s{};
      for (int k = 0; k < 8; ++k)
        f1s[static_cast<size_t>(k)] = m.result.subsets[static_cast<size_t>(k)].f1;
      summary[name == "pruned" ? std::string("f1") : "f1_" + name] = PerSubset(f1s);
      top1[name] = PerSubset(m.result.top1);
      full_precision[name] = PerSubset(m.recall_at_full_precision);
      report += absl::StrFormat("| %s | %.3f | %.2f / %.2f / **%.2f** | %.0f | %s |\n", name,
                                o.threshold, o.precision, o.recall, o.f1, m.mean_keypoints,
                                i < 4 ? absl::StrFormat("%.1f / %.2f (%d)", m.pose_error_cm,
                                                        m.pose_error_deg, m.poses_compared)
                                      : std::string("—"));
      eval::Series s{name, {}, {}, colors[i]};
      for (const auto& p : m.result.curve) {
        s.x.push_back(p.recall);
        s.y.push_back(p.precision);
      }
      pr.push_back(s);
      eval::Series b{name, {}, {}, colors[i]};
      for (int k = 0; k < 8; ++k) {
        b.x.push_back((k + 0.5) / 8.0);
        b.y.push_back(f1s[static_cast<size_t>(k)]);
      }
      f1.push_back(b);
      for (const auto& t : m.result.trials) {
        const auto& v = study->visits[study->keyframes[t.query].visit];
        queries_csv +=
            absl::StrFormat("%s,%d,%s,%d,%s,%s,%.4f,%d\n", name, t.query, v.path, t.subset,
                            t.known ? "known" : "unknown", t.predicted, t.score, t.correct ? 1 : 0);
      }
    }
    for (int k = 0; k < 8; ++k) {
      table += absl::StrFormat("| %d | %s |", k + 1, kSubsetNames[k]);
      for (const char* m : kMethods) {
        table += absl::StrFormat(" %.2f |",
                                 study->methods.at(m).result.subsets[static_cast<size_t>(k)].f1);
      }
      const auto& p = study->methods.at("pruned");
      table += absl::StrFormat(" %.2f | %.2f |\n", p.result.top1[static_cast<size_t>(k)],
                               p.recall_at_full_precision[static_cast<size_t>(k)]);
    }
    report += table;
    const auto& pruned = study->methods.at("pruned");
    summary["suite"] = a.suite;
    summary["orb"] = {{"max_keypoints", a.orb.max_keypoints},
                      {"detect_scale", a.orb.detect_scale},
                      {"pyramid_levels", a.orb.pyramid_levels},
                      {"pyramid_scale", a.orb.pyramid_scale}};
    summary["threshold"] = threshold;
    summary["top1"] = top1;
    summary["recall_at_full_precision"] = full_precision;
    summary["pose_error_cm"] = pruned.pose_error_cm;
    summary["pose_error_deg"] = pruned.pose_error_deg;
    summary["pruned_share"] = study->pruned_share;
    summary["reference_keyframes"] = study->reference_keyframes;
    summary["query_keyframes"] = study->query_keyframes;
    summary["seconds"] = study->seconds;
    texts.emplace_back("queries.csv", queries_csv);
    pngs.emplace_back(
        "pr_curves.png",
        eval::PlotCurves(pr, "appearance, every subset: PR per method", "recall", "precision"));
    pngs.emplace_back("f1_subsets.png",
                      eval::PlotCurves(f1, "F1 per subset (1..8) per method", "subset", "F1"));
  }

  const std::string real_header =
      "| variant | views | verified | accepted | max score | median inliers |\n"
      "|---|---|---|---|---|---|\n";
  if (!a.mosd.empty()) {
    auto views = eval::ReadMosdViews(a.mosd, options);
    if (!views.ok()) return Fail(views.status());
    report += absl::StrFormat(
        "\n## mOSD: one table, objects changed between %d scenes\n\nEach scene against all the "
        "others (the same table under other objects): it should be recognised with a verified "
        "pose. The oracle drops keypoints on the labelled objects.\n\n",
        views->size());
    report += real_header;
    summary["mosd"] =
        RealSummary(eval::RecogniseRealViews(*views, *views, true, options), thresholds, &report);
  }
  if (!a.tum_reference.empty()) {
    auto reference = eval::ReadTumViews(a.tum_reference, options);
    if (!reference.ok()) return Fail(reference.status());
    auto query = eval::ReadTumViews(a.tum_query, options);
    if (!query.ok()) return Fail(query.status());
    report += absl::StrFormat(
        "\n## TUM: %s against itself (each key frame's neighbours must be found)\n\n",
        a.tum_reference);
    report += real_header;
    summary["tum_self"] = RealSummary(
        eval::RecogniseRealViews(*reference, *reference, true, options), thresholds, &report);
    report += absl::StrFormat("\n## TUM: %s against %s (another desk: nothing may be accepted)\n\n",
                              a.tum_query, a.tum_reference);
    report += real_header;
    summary["tum_other"] = RealSummary(eval::RecogniseRealViews(*reference, *query, false, options),
                                       thresholds, &report);
  }
  return FinishStudy(ctx, a.out, texts, pngs, summary, report);
}

}  // namespace

void AddAppearanceEvalCommand(CLI::App* eval, CliContext* ctx) {
  auto a = std::make_shared<AppearanceEvalArgs>();
  auto* cmd = eval->add_subcommand(
      "appearance",
      "Paper 000's purpose: appearance place recognition with entropy pruning against no, random "
      "and oracle pruning, architecture and fused, on a sim suite and real recordings");
  cmd->add_option("--suite", a->suite, "folder written by lifemap sim suite (manifest.json)")
      ->check(CLI::ExistingDirectory);
  cmd->add_option("--out", a->out, "output folder (created)")->required();
  cmd->add_option("--thresholds-from", a->thresholds_from,
                  "summary.json of an earlier run (another seed): accept matches at its "
                  "thresholds (a held-out evaluation)")
      ->check(CLI::ExistingFile);
  cmd->add_option("--mosd", a->mosd, "the mOSD folder (learn/ and test/ PCDs)")
      ->check(CLI::ExistingDirectory);
  cmd->add_option("--tum-reference", a->tum_reference, "a TUM folder stored as the gallery")
      ->check(CLI::ExistingDirectory);
  cmd->add_option("--tum-query", a->tum_query,
                  "a TUM folder of another place, matched against the reference")
      ->check(CLI::ExistingDirectory);
  cmd->add_option("--threads", a->threads, "worker threads (default: one per core)")
      ->check(CLI::Range(0, 256));
  cmd->add_option("--query-stride", a->query_stride,
                  "try every N-th query keyframe of each visit (default 1: all; a quicker look)")
      ->check(CLI::Range(1, 1000));
  cmd->add_option("--detect-scale", a->orb.detect_scale,
                  "ORB runs on the colour image resized by this factor (default: the server's)");
  cmd->add_option("--pyramid-levels", a->orb.pyramid_levels,
                  "ORB's scale pyramid levels (default: the server's)");
  cmd->add_option("--pyramid-scale", a->orb.pyramid_scale,
                  "ORB's ratio between pyramid levels (default: the server's)");
  cmd->callback([ctx, a] { ctx->run = [ctx, a] { return RunAppearanceEval(*ctx, *a); }; });
}

}  // namespace lifemap::cli
