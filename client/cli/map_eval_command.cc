// `lifemap eval map MAP --sim DIR --out OUT`: what the server made of a place's visits, against
// the truth of the `lifemap sim --visits N` folder they were streamed from. Nothing is streamed
// here: the visits are the map's own, streamed beforehand as a robot would (`lifemap stream`,
// with or without poses). Each visit is paired with the visit folder its label names (else the
// map's visits and DIR's folders in order); for each, the server's frame (the map's, anchored,
// unanchored), its stored keyframes against its own truth (ATE), and for an anchored visit how
// far the anchor put it from the truth, measured as `lifemap eval alignment` does; for each
// pair of consecutive visits both in the map's frame, GetChanges scored against scene.json as
// `lifemap eval changes` does.
#include <algorithm>
#include <filesystem>
#include <iostream>
#include <map>
#include <optional>

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "client/cli/change_truth.h"
#include "client/cli/commands.h"
#include "client/cli/study.h"
#include "client/cli/unposed_stream.h"
#include "core/eval/trajectory.h"
#include "core/io/tum_dataset.h"

namespace lifemap::cli {
namespace {

namespace fs = std::filesystem;
using json = nlohmann::json;

struct MapEvalArgs {
  std::string map, sim, out;
  // An anchor further than this from the truth has put the visit somewhere else (as
  // `eval alignment`'s --wrong-cm / --wrong-deg).
  double wrong_cm = 50.0, wrong_deg = 10.0;
  ChangeScoring scoring;
};

// One visit of the map with its folder's truth.
struct VisitScore {
  uint64_t id = 0;
  std::string label, folder, frame;  // frame: map | anchored | unanchored
  uint64_t anchor_to = 0;
  std::string anchor_dropped;
  int keyframes = 0;
  double ate_cm = -1;  // stored keyframes against the folder's truth (-1: fewer than 3)
  std::optional<Eigen::Isometry3d> T_truth_estimate;
  double error_cm = -1, error_deg = -1;  // anchored: against the truth
  std::string verdict;                   // reference | correct | wrong | unanchored | not scored
};

std::string FrameName(v1::VisitFrame f) {
  return f == v1::VISIT_FRAME_MAP        ? "map"
         : f == v1::VISIT_FRAME_ANCHORED ? "anchored"
                                         : "unanchored";
}

// The visit_* folders of a `lifemap sim --visits N` folder, in order.
absl::StatusOr<std::vector<fs::path>> VisitFolders(const std::string& sim) {
  std::vector<fs::path> dirs;
  std::error_code ec;
  for (const auto& e : fs::directory_iterator(sim, ec)) {
    if (e.is_directory() && e.path().filename().string().rfind("visit_", 0) == 0) {
      dirs.push_back(e.path());
    }
  }
  if (ec) return absl::NotFoundError(absl::StrCat("cannot read ", sim, ": ", ec.message()));
  std::sort(dirs.begin(), dirs.end());
  if (dirs.empty()) {
    return absl::InvalidArgumentError(absl::StrCat(
        sim, " holds no visit_* folder; make one with `lifemap sim --visits 3 --out DIR`"));
  }
  return dirs;
}

// A CSV field in double quotes (RFC 4180): a visit's label is the robot's text, quotes and
// line breaks included.
std::string CsvQuoted(const std::string& text) {
  std::string out = "\"";
  for (char c : text) out += c == '"' ? std::string("\"\"") : std::string(1, c);
  return out + "\"";
}

std::string Cm(double v, const char* f = "%.1f cm") {
  return v < 0 ? std::string("-") : absl::StrFormat(f, v);
}

int RunMapEval(const CliContext& ctx, const MapEvalArgs& a) {
  auto dirs = VisitFolders(a.sim);
  if (!dirs.ok()) return Fail(dirs.status());
  if (auto s = PrepareOut(a.out); !s.ok()) return Fail(s);
  auto client = ctx.Connect();
  if (!client.ok()) return Fail(client.status());
  auto listed = (*client)->ListVisits(a.map);
  if (!listed.ok()) return Fail(listed.status());
  std::vector<v1::Visit> visits(listed->visits().begin(), listed->visits().end());
  std::sort(visits.begin(), visits.end(),
            [](const auto& x, const auto& y) { return x.id() < y.id(); });
  if (visits.empty()) {
    return Fail(absl::FailedPreconditionError(
        absl::StrCat("map '", a.map, "' has no visit; stream the folders of ", a.sim,
                     " into it first (lifemap stream ", a.map, " --tum DIR/visit_00 ...)")));
  }
  // Pairs by label (a visit labelled "visit_01" is that folder), else in order.
  std::map<std::string, fs::path> by_name;
  for (const auto& d : *dirs) by_name[d.filename().string()] = d;
  const bool labelled = std::any_of(visits.begin(), visits.end(), [&](const v1::Visit& v) {
    return by_name.count(v.label()) != 0;
  });
  std::vector<VisitScore> scores;
  for (size_t i = 0; i < visits.size(); ++i) {
    const v1::Visit& v = visits[i];
    fs::path dir;
    if (labelled) {
      auto it = by_name.find(v.label());
      if (it == by_name.end()) continue;  // not one of DIR's visits
      dir = it->second;
    } else if (i < dirs->size()) {
      dir = (*dirs)[i];
    } else {
      continue;
    }
    VisitScore s;
    s.id = v.id();
    s.label = v.label();
    s.folder = dir.filename().string();
    s.frame = FrameName(v.frame());
    s.anchor_to = v.frame() == v1::VISIT_FRAME_ANCHORED ? v.anchor().to_visit() : 0;
    s.anchor_dropped = v.anchor_dropped();
    auto seq = io::ReadTumSequence(dir.string());
    if (!seq.ok()) return Fail(seq.status());
    auto stored = StoredPosedKeyframes(**client, a.map, v.id());
    if (!stored.ok()) return Fail(stored.status());
    s.keyframes = static_cast<int>(stored->size());
    auto aligned = eval::CompareTrajectories(*stored, eval::GroundTruth(*seq));
    if (aligned.ok()) {
      s.ate_cm = aligned->ate_rmse_m * 100;
      s.T_truth_estimate = aligned->T_truth_estimate;
    }
    scores.push_back(std::move(s));
  }
  if (scores.empty()) {
    return Fail(absl::FailedPreconditionError(
        absl::StrCat("no visit of map '", a.map, "' is labelled after a visit folder of ", a.sim)));
  }
  // The map's frame in the world's: its first visit in the map's frame, aligned to its truth
  // by its stored keyframes (every visit of a sim place shares one world frame).
  const VisitScore* reference = nullptr;
  for (auto& s : scores) {
    if (s.frame == "map" && reference == nullptr) {
      s.verdict = "reference";
      reference = &s;
    }
  }
  for (auto& s : scores) {
    if (&s == reference) continue;
    if (s.frame == "unanchored") {
      s.verdict = "unanchored";
    } else if (reference == nullptr || !reference->T_truth_estimate || !s.T_truth_estimate) {
      s.verdict = "not scored";  // fewer than 3 keyframes to align, or no visit in the map frame
    } else {
      const Eigen::Isometry3d diff = reference->T_truth_estimate->inverse() * *s.T_truth_estimate;
      s.error_cm = diff.translation().norm() * 100;
      s.error_deg = Eigen::AngleAxisd(diff.rotation()).angle() * 180 / M_PI;
      s.verdict = s.error_cm <= a.wrong_cm && s.error_deg <= a.wrong_deg ? "correct" : "wrong";
    }
  }

  std::string report = absl::StrFormat(
      "# Map %s against %s\n\n| visit | folder | frame | keyframes | track ATE | anchor error "
      "against the truth | verdict |\n|---|---|---|---|---|---|---|\n",
      a.map, a.sim);
  std::string csv =
      "visit,label,folder,frame,anchor_to,keyframes,ate_cm,error_cm,error_deg,verdict\n";
  json per_visit = json::array();
  int correct = 0, wrong = 0, unanchored = 0;
  for (const auto& s : scores) {
    correct += s.verdict == "correct";
    wrong += s.verdict == "wrong";
    unanchored += s.verdict == "unanchored";
    std::string frame = s.frame == "anchored" ? absl::StrCat("anchored to ", s.anchor_to) : s.frame;
    if (!s.anchor_dropped.empty())
      absl::StrAppend(&frame, " (anchor dropped: ", s.anchor_dropped, ")");
    report += absl::StrFormat(
        "| %d | %s | %s | %d | %s | %s | %s |\n", s.id, s.folder, frame, s.keyframes, Cm(s.ate_cm),
        s.error_cm < 0 ? "-" : absl::StrFormat("%.1f cm, %.2f deg", s.error_cm, s.error_deg),
        s.verdict);
    csv += absl::StrFormat("%d,%s,%s,%s,%d,%d,%.2f,%.2f,%.3f,%s\n", s.id, CsvQuoted(s.label),
                           s.folder, s.frame, s.anchor_to, s.keyframes, s.ate_cm, s.error_cm,
                           s.error_deg, s.verdict);
    per_visit.push_back({{"visit", s.id},
                         {"folder", s.folder},
                         {"frame", s.frame},
                         {"anchor_to", s.anchor_to},
                         {"keyframes", s.keyframes},
                         {"ate_cm", s.ate_cm},
                         {"error_cm", s.error_cm},
                         {"error_deg", s.error_deg},
                         {"verdict", s.verdict}});
  }

  // Changes between consecutive visits both in the map's frame, in the world's frame.
  const Eigen::Isometry3d T_world_map = reference != nullptr && reference->T_truth_estimate
                                            ? *reference->T_truth_estimate
                                            : Eigen::Isometry3d::Identity();
  std::string changes_csv =
      "from_visit,to_visit,what,kind,instance_or_class,x,y,from_x,from_y,size_m,counted,matched\n";
  json comparisons = json::array();
  int reported = 0, right = 0, counted = 0, found = 0;
  for (size_t i = 1; i < scores.size(); ++i) {
    const VisitScore& from = scores[i - 1];
    const VisitScore& to = scores[i];
    report += absl::StrFormat("\n## Changes from visit %d (%s) to %d (%s)\n\n", from.id,
                              from.folder, to.id, to.folder);
    if (from.frame == "unanchored" || to.frame == "unanchored" || reference == nullptr ||
        !reference->T_truth_estimate) {
      report += "Not compared: a visit is not in the map's frame.\n";
      comparisons.push_back({{"from_visit", from.id}, {"to_visit", to.id}, {"compared", false}});
      continue;
    }
    auto truth = TrueChanges(fs::path(a.sim) / from.folder, fs::path(a.sim) / to.folder, a.scoring);
    if (!truth.ok()) return Fail(truth.status());
    auto r = (*client)->GetChanges(a.map, from.id, to.id);
    if (!r.ok()) {
      report += absl::StrCat("Not compared: ", r.status().message(), "\n");
      comparisons.push_back({{"from_visit", from.id},
                             {"to_visit", to.id},
                             {"compared", false},
                             {"why", std::string(r.status().message())}});
      continue;
    }
    std::vector<ReportedChange> reports;
    for (const auto& c : r->changes()) reports.push_back(ReportOf(c, T_world_map));
    MatchReports(&reports, &*truth, a.scoring.tolerance_m);
    int n_right = 0, n_counted = 0, n_found = 0;
    report +=
        "| reported | class | where (world, m) | size (m) | against the truth |\n"
        "|---|---|---|---|---|\n";
    for (const auto& rep : reports) {
      n_right += !rep.matched.empty();
      report += absl::StrFormat("| %s | %s | (%.2f, %.2f) | %.2f | %s |\n", rep.kind,
                                rep.class_name.empty() ? "-" : rep.class_name, rep.at.x(),
                                rep.at.y(), rep.size_m,
                                rep.matched.empty() ? "no such change" : "right: " + rep.matched);
      changes_csv += absl::StrFormat("%d,%d,reported,%s,%s,%.3f,%.3f,%.3f,%.3f,%.3f,,%s\n", from.id,
                                     to.id, rep.kind, rep.class_name, rep.at.x(), rep.at.y(),
                                     rep.from.x(), rep.from.y(), rep.size_m, rep.matched);
    }
    if (reports.empty()) report += "| (none) | | | | |\n";
    std::string missed;
    for (const auto& c : *truth) {
      n_counted += c.counted;
      n_found += c.counted && c.found;
      if (c.counted && !c.found) {
        absl::StrAppend(&missed,
                        absl::StrFormat("- missed: %s %d (%s, %.2f m) at (%.2f, %.2f)\n", c.kind,
                                        c.instance, c.detail, c.size_m, c.at.x(), c.at.y()));
      }
      changes_csv +=
          absl::StrFormat("%d,%d,true,%s,%d %s,%.3f,%.3f,%.3f,%.3f,%.3f,%d,%d\n", from.id, to.id,
                          c.kind, c.instance, c.detail, c.at.x(), c.at.y(), c.from.x(), c.from.y(),
                          c.size_m, c.counted, c.found);
    }
    report += absl::StrFormat(
        "\n%d reported, %d of them right; %d of %d true changes found "
        "(props of %.2f m or more, seen; doors)\n%s",
        reports.size(), n_right, n_found, n_counted, a.scoring.min_size_m, missed);
    reported += static_cast<int>(reports.size());
    right += n_right;
    counted += n_counted;
    found += n_found;
    comparisons.push_back({{"from_visit", from.id},
                           {"to_visit", to.id},
                           {"compared", true},
                           {"reported", reports.size()},
                           {"right", n_right},
                           {"true", n_counted},
                           {"found", n_found}});
  }
  json summary = {{"map", a.map},
                  {"sim", a.sim},
                  {"visits", per_visit},
                  {"anchored_correct", correct},
                  {"anchored_wrong", wrong},
                  {"unanchored", unanchored},
                  {"changes",
                   {{"comparisons", comparisons},
                    {"reported", reported},
                    {"right", right},
                    {"true", counted},
                    {"found", found}}},
                  {"wrong_beyond", {{"cm", a.wrong_cm}, {"deg", a.wrong_deg}}},
                  {"min_size_m", a.scoring.min_size_m},
                  {"tolerance_m", a.scoring.tolerance_m}};
  return FinishStudy(ctx, a.out, {{"visits.csv", csv}, {"changes.csv", changes_csv}}, {}, summary,
                     report);
}

}  // namespace

void AddMapEvalCommand(CLI::App* eval, CliContext* ctx) {
  auto* cmd = eval->add_subcommand(
      "map",
      "Score a map's visits against the truth of the `lifemap sim --visits N` folder they were "
      "streamed from: each visit's frame, track and anchor error, and the changes between "
      "consecutive visits (nothing is streamed)");
  auto a = std::make_shared<MapEvalArgs>();
  cmd->add_option("MAP", a->map,
                  "the map (its visits labelled visit_00, visit_01, ... or in "
                  "DIR's order)")
      ->required();
  cmd->add_option("--sim", a->sim, "the `lifemap sim --visits N --out DIR` folder")
      ->required()
      ->check(CLI::ExistingDirectory);
  cmd->add_option("--out", a->out, "folder for summary.json, visits.csv, changes.csv, report.md")
      ->required();
  cmd->add_option("--wrong-cm", a->wrong_cm,
                  "an anchor further than this from the truth is wrong (default 50)")
      ->check(CLI::PositiveNumber);
  cmd->add_option("--wrong-deg", a->wrong_deg,
                  "an anchor turned more than this from the truth is wrong (default 10)")
      ->check(CLI::PositiveNumber);
  AddChangeScoringOptions(cmd, &a->scoring);
  cmd->callback([ctx, a] { ctx->run = [ctx, a] { return RunMapEval(*ctx, *a); }; });
}

}  // namespace lifemap::cli
