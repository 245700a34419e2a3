// `lifemap eval alignment`: visits months apart landing in one map frame (issue 15). Each
// place of a synthetic suite (lifemap sim suite) gets its own map: its reference visit is
// streamed first, without poses (the map's first visit: its frame is the map's), then each
// query visit, also without poses, which lifemapd should anchor into the map's frame by
// appearance. The anchoring error is measured against the suite's ground truth, in which every
// visit of a place shares one world frame: the reference's stored keyframes and the query's
// (moved into the map's frame by its anchor) are each aligned rigidly to their ground truth;
// with a perfect anchor (and perfect trajectories) the two alignments are the same, and their
// difference is the error. Last, one visit of another place is streamed into each map: it must
// stay unanchored (anchoring it is the wrong-place failure). Each visit is ended once streamed,
// as a robot ends its visit, and judged as it stands then.
#include <algorithm>
#include <ctime>
#include <filesystem>
#include <iostream>
#include <map>

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "client/cli/study.h"
#include "client/cli/unposed_stream.h"
#include "core/eval/place_study.h"
#include "core/eval/trajectory.h"

namespace lifemap::cli {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

struct AlignmentArgs {
  std::string suite, out;
  bool compact = false;
  bool send_gravity = true;    // --gravity accelerometer|none
  bool send_odometry = false;  // --odometry wheel|none
  double rate_hz = 0.0;
  bool keep_maps = false;
  // An anchor further than this from the truth has put the visit somewhere else in the room:
  // it counts as wrong, not as an inaccurate anchor.
  double wrong_cm = 50.0;
  double wrong_deg = 10.0;
};

// One visit streamed into a place's map and what became of it.
struct AlignmentTrial {
  std::string path, place_id, conditions;
  int subset = 0;            // 1..8; 0 for the cross-place trials
  bool cross_place = false;  // a visit of another place: must stay unanchored
  uint64_t visit_id = 0;
  int frames = 0, lost = 0, keyframes = 0;
  int by_odometry = 0;  // frames the server placed by the robot's odometry alone
  double ate_mm = -1;   // the visit's stored keyframes against its own ground truth (-1: none)
  std::string frame;    // the server's VisitFrame: map | anchored | unanchored
  std::string error;    // why the visit could not be scored
  uint64_t anchor_to = 0;
  // Seconds of streaming (server clock) before the anchor was set; -1 when not anchored.
  double anchored_after_s = -1, residual_cm = 0, residual_deg = 0;
  double error_cm = -1, error_deg = -1;  // against the truth (anchored visits of the place)
  std::string verdict;                   // correct | wrong | unanchored | error
};

struct Tally {
  int trials = 0, correct = 0, wrong = 0, unanchored = 0, errors = 0;
  std::vector<double> error_cm, error_deg, after_s;

  void Add(const AlignmentTrial& t) {
    ++trials;
    if (t.verdict == "correct") ++correct;
    if (t.verdict == "wrong") ++wrong;
    if (t.verdict == "unanchored") ++unanchored;
    if (t.verdict == "error") ++errors;
    if (t.error_cm >= 0) {
      error_cm.push_back(t.error_cm);
      error_deg.push_back(t.error_deg);
    }
    if (t.anchored_after_s >= 0) after_s.push_back(t.anchored_after_s);
  }
  static double Median(std::vector<double> v) {
    if (v.empty()) return -1;
    std::sort(v.begin(), v.end());
    return v.size() % 2 ? v[v.size() / 2] : 0.5 * (v[v.size() / 2 - 1] + v[v.size() / 2]);
  }
  json Json() const {
    return {{"visits", trials},
            {"anchored_correct", correct},
            {"anchored_wrong", wrong},
            {"unanchored", unanchored},
            {"not_scored", errors},
            {"anchor_error_cm", Median(error_cm)},
            {"anchor_error_deg", Median(error_deg)},
            {"anchored_after_s", Median(after_s)}};
  }
  std::string Row(const std::string& name) const {
    auto fmt = [](double v, const char* f) {
      return v < 0 ? std::string("-") : absl::StrFormat(f, v);
    };
    return absl::StrFormat("| %s | %d | %d | %d | %d | %d | %s | %s | %s |\n", name, trials,
                           correct, wrong, unanchored, errors, fmt(Median(error_cm), "%.1f"),
                           fmt(Median(error_deg), "%.2f"), fmt(Median(after_s), "%.1f"));
  }
};

std::string FrameName(v1::VisitFrame f) {
  switch (f) {
    case v1::VISIT_FRAME_MAP:
      return "map";
    case v1::VISIT_FRAME_ANCHORED:
      return "anchored";
    case v1::VISIT_FRAME_UNANCHORED:
      return "unanchored";
    default:
      return "unspecified";
  }
}

// Streams `dir` into `map` and fills what the server made of it: its frame, its anchor, its
// stored keyframes' alignment to the truth (`T_truth_estimate`, when there are 3 or more).
absl::Status StreamVisit(client::Client& client, const std::string& map, const std::string& dir,
                         const AlignmentArgs& a, AlignmentTrial* t,
                         std::optional<Eigen::Isometry3d>* T_truth_estimate) {
  auto seq = io::ReadTumSequence(dir);
  if (!seq.ok()) return seq.status();
  UnposedStreamOptions options;
  options.robot = "lifemap eval alignment";
  options.visit_label = t->path;
  options.compact = a.compact;
  options.send_gravity = a.send_gravity;
  options.send_odometry = a.send_odometry;
  options.rate_hz = a.rate_hz;
  auto streamed = StreamWithoutPoses(client, map, *seq, options);
  if (!streamed.ok()) return streamed.status();
  t->visit_id = streamed->visit_id;
  t->frames = static_cast<int>(streamed->frames.size());
  t->lost = streamed->lost;
  t->by_odometry = streamed->placed_by_odometry;
  // Ended, as a robot ends its visit: an anchor is re-checked then with the visit's final floor
  // plan (Engine::EndVisit), and what is read below is the visit as it stays.
  if (auto ended = client.EndVisit(t->visit_id); !ended.ok()) return ended.status();
  auto visits = client.ListVisits(map);
  if (!visits.ok()) return visits.status();
  for (const auto& v : visits->visits()) {
    if (v.id() != t->visit_id) continue;
    t->frame = FrameName(v.frame());
    if (v.frame() == v1::VISIT_FRAME_ANCHORED) {
      t->anchor_to = v.anchor().to_visit();
      t->residual_cm = v.anchor().residual_m() * 100;
      t->residual_deg = v.anchor().residual_deg();
      // Both on the server's clock: a streamed visit starts when its stream opens.
      t->anchored_after_s = std::max(0.0, v.anchor().anchored_time_s() - v.start_time_s());
    }
  }
  auto stored = StoredEstimatedKeyframes(client, map, t->visit_id);
  if (!stored.ok()) return stored.status();
  t->keyframes = static_cast<int>(stored->size());
  auto errors = eval::CompareTrajectories(*stored, eval::GroundTruth(*seq));
  if (errors.ok()) {
    t->ate_mm = errors->ate_rmse_m * 1000;
    *T_truth_estimate = errors->T_truth_estimate;
  }
  return absl::OkStatus();
}

int RunAlignmentEval(const CliContext& ctx, const AlignmentArgs& a) {
  if (auto s = PrepareOut(a.out); !s.ok()) return Fail(s);
  auto manifest = eval::ReadSuiteManifest(a.suite);
  if (!manifest.ok()) return Fail(manifest.status());
  // Places in manifest order, each with its reference and its queries by subset.
  std::vector<std::string> places;
  std::map<std::string, const eval::SuiteVisit*> reference;
  std::map<std::string, std::vector<const eval::SuiteVisit*>> queries;
  for (const auto& v : *manifest) {
    if (v.role == "reference") {
      reference[v.place_id] = &v;
      places.push_back(v.place_id);
    } else {
      queries[v.place_id].push_back(&v);
    }
  }
  for (const auto& p : places) {
    std::sort(queries[p].begin(), queries[p].end(),
              [](const auto* x, const auto* y) { return x->subset < y->subset; });
  }
  auto client = ctx.Connect();
  if (!client.ok()) return Fail(client.status());

  const fs::path root(a.suite);
  const std::time_t started = std::time(nullptr);
  std::vector<AlignmentTrial> trials;
  std::vector<std::string> maps;
  for (size_t p = 0; p < places.size(); ++p) {
    const std::string& place = places[p];
    const std::string map = absl::StrCat("eval-alignment-", started, "-", place);
    if (auto m = (*client)->CreateMap(map, "lifemap eval alignment"); !m.ok()) {
      return Fail(m.status());
    }
    maps.push_back(map);
    AlignmentTrial ref;
    ref.path = reference[place]->path;
    ref.place_id = place;
    std::optional<Eigen::Isometry3d> T_truth_reference;
    if (auto s =
            StreamVisit(**client, map, (root / ref.path).string(), a, &ref, &T_truth_reference);
        !s.ok()) {
      return Fail(s);
    }
    if (!ctx.json) {
      std::cerr << absl::StrFormat("%s: reference %s, %d keyframes, ATE %.1f mm\n", place,
                                   ref.frame, ref.keyframes, ref.ate_mm);
    }
    // The queries of this place, then one visit of the next place (the cross-place trial).
    std::vector<std::pair<const eval::SuiteVisit*, bool>> order;
    for (const auto* q : queries[place]) order.push_back({q, false});
    if (places.size() > 1) {
      const auto& other = queries[places[(p + 1) % places.size()]];
      if (!other.empty()) order.push_back({other.front(), true});
    }
    for (const auto& [visit, cross_place] : order) {
      AlignmentTrial t;
      t.path = visit->path;
      t.place_id = visit->place_id;
      t.conditions = visit->conditions;
      t.subset = cross_place ? 0 : visit->subset;
      t.cross_place = cross_place;
      std::optional<Eigen::Isometry3d> T_truth_query;
      if (auto s = StreamVisit(**client, map, (root / t.path).string(), a, &t, &T_truth_query);
          !s.ok()) {
        return Fail(s);
      }
      if (t.frame != "anchored") {
        t.verdict = "unanchored";
      } else if (cross_place) {
        t.verdict = "wrong";
      } else if (!T_truth_reference || !T_truth_query) {
        t.verdict = "error";
        t.error = "fewer than 3 stored keyframes to align with the truth";
      } else {
        const Eigen::Isometry3d diff = T_truth_reference->inverse() * *T_truth_query;
        t.error_cm = diff.translation().norm() * 100;
        t.error_deg = Eigen::AngleAxisd(diff.rotation()).angle() * 180 / M_PI;
        t.verdict = t.error_cm <= a.wrong_cm && t.error_deg <= a.wrong_deg ? "correct" : "wrong";
      }
      if (!ctx.json) {
        std::cerr << absl::StrFormat(
            "  %-28s %-10s %-10s ATE %6.1f mm  error %5.1f cm %5.2f deg  (%s)\n",
            t.cross_place ? t.path + " (other place)" : t.path, t.frame, t.verdict, t.ate_mm,
            t.error_cm, t.error_deg, t.error);
      }
      trials.push_back(std::move(t));
    }
  }
  if (!a.keep_maps) DeleteScratchMaps(**client, maps);

  Tally same_place, cross_place;
  std::map<int, Tally> by_subset;
  std::map<int, std::string> subset_names;
  std::string csv =
      "path,place,subset,conditions,cross_place,visit,frames,lost,by_odometry,keyframes,ate_mm,"
      "frame,"
      "anchor_to,anchored_after_s,residual_cm,residual_deg,error_cm,error_deg,verdict\n";
  for (const auto& t : trials) {
    (t.cross_place ? cross_place : same_place).Add(t);
    if (!t.cross_place) {
      by_subset[t.subset].Add(t);
      subset_names[t.subset] = t.conditions;
    }
    csv += absl::StrFormat(
        "%s,%s,%d,\"%s\",%d,%d,%d,%d,%d,%d,%.2f,%s,%d,%.2f,%.2f,%.3f,%.2f,%.3f,%s\n", t.path,
        t.place_id, t.subset, t.conditions, t.cross_place ? 1 : 0, t.visit_id, t.frames, t.lost,
        t.by_odometry, t.keyframes, t.ate_mm, t.frame, t.anchor_to, t.anchored_after_s,
        t.residual_cm, t.residual_deg, t.error_cm, t.error_deg, t.verdict);
  }
  json summary = same_place.Json();
  // A cross-place visit anchored is a wrong anchor too (to a wrong place).
  summary["anchored_wrong"] = same_place.wrong + cross_place.wrong;
  summary["anchored_wrong_place"] = cross_place.wrong;
  summary["cross_place"] = cross_place.Json();
  summary["suite"] = a.suite;
  summary["places"] = places.size();
  summary["sent"] = a.compact ? "compact" : "as-recorded";
  summary["gravity"] = a.send_gravity ? "accelerometer" : "none";
  summary["odometry"] = a.send_odometry ? "wheel" : "none";
  summary["wrong_beyond"] = {{"cm", a.wrong_cm}, {"deg", a.wrong_deg}};
  summary["subsets"] = json::object();
  std::string report = absl::StrFormat(
      "# Visit alignment: %s\n\n%zu places; each place's reference streamed first without poses, "
      "then its query visits without poses into the same map; one visit of another place per "
      "map must stay unanchored. An anchor more than %.0f cm or %.0f deg from the truth is "
      "wrong.\n\n| subset | visits | anchored correctly | wrongly | not anchored | not scored | "
      "median error (cm) | median error (deg) | anchored after (s of streaming, median) |\n"
      "|---|---|---|---|---|---|---|---|---|\n",
      a.suite, places.size(), a.wrong_cm, a.wrong_deg);
  for (const auto& [k, tally] : by_subset) {
    summary["subsets"][subset_names[k]] = tally.Json();
    report += tally.Row(absl::StrCat(k, " ", subset_names[k]));
  }
  report += same_place.Row("**all queries**");
  report += cross_place.Row("other place (must stay unanchored)");
  return FinishStudy(ctx, a.out, {{"visits.csv", csv}}, {}, summary, report);
}

}  // namespace

void AddAlignmentEvalCommand(CLI::App* eval, CliContext* ctx) {
  auto* cmd = eval->add_subcommand(
      "alignment",
      "Stream a synthetic suite's visits without poses, one map per place, and score how "
      "lifemapd anchors each query visit into its map's frame against the ground truth");
  auto a = std::make_shared<AlignmentArgs>();
  cmd->add_option("--suite", a->suite, "a lifemap sim suite folder (manifest.json)")
      ->required()
      ->check(CLI::ExistingDirectory);
  cmd->add_option("--out", a->out, "folder for summary.json, visits.csv, report.md")->required();
  AddSendOption(cmd, &a->compact);
  AddGravityOption(cmd, &a->send_gravity);
  AddOdometryOption(cmd, &a->send_odometry);
  cmd->add_option("--rate", a->rate_hz, "frames per second (default 0: as fast as served)")
      ->check(CLI::Range(0.0, 1000.0));
  cmd->add_flag("--keep-maps", a->keep_maps, "keep the per-place maps (default: deleted after)");
  cmd->add_option("--wrong-cm", a->wrong_cm,
                  "an anchor further than this from the truth counts as wrong (default 50)")
      ->check(CLI::Range(1.0, 1000.0));
  cmd->add_option("--wrong-deg", a->wrong_deg,
                  "an anchor turned more than this from the truth counts as wrong (default 10)")
      ->check(CLI::Range(0.1, 180.0));
  cmd->callback([ctx, a] { ctx->run = [ctx, a] { return RunAlignmentEval(*ctx, *a); }; });
}

}  // namespace lifemap::cli
