// `lifemap eval changes --suite DIR --out OUT` (issue 36): each place's reference and query
// visits streamed into one map, GetChanges asked of (reference, query), and the answer scored
// against the synthetic world's change records (scene.json) per kind of change and condition
// subset. The none, lighting and dynamic subsets hold no change of the place: whatever is
// reported there is a false change.
#include <algorithm>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <set>

#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "client/cli/change_truth.h"
#include "client/cli/commands.h"
#include "client/cli/study.h"
#include "client/cli/unposed_stream.h"
#include "core/eval/place_study.h"
#include "core/eval/trajectory.h"
#include "core/io/tum_dataset.h"

namespace lifemap::cli {
namespace {

namespace fs = std::filesystem;
using json = nlohmann::json;

struct ChangesEvalArgs {
  std::string suite, out;
  bool compact = false;
  bool truth_poses = true;  // --poses truth|server
  bool keep_maps = false;
  ChangeScoring scoring;
  bool masks = true;           // --masks: score each frame's moved mask too
  bool send_odometry = false;  // --odometry wheel|none (with --poses server)
};

// The synthetic world never moves a wall: every wall reported is a false change.
const char* const kKinds[] = {"appeared",    "vanished", "moved",    "door_opened",
                              "door_closed", "wall_new", "wall_gone"};

struct Trial {
  std::string not_compared;  // why GetChanges could not compare (a visit not anchored)
  std::string path, conditions;
  int subset = 0;
  uint64_t visit = 0;
  std::vector<TrueChange> truth;
  std::vector<ReportedChange> reported;
  double seconds = 0;
  // The per-frame moved masks against the reference (FrameResult.moved), in pixels of the
  // frames compared: marked and truly arrived, marked elsewhere, arrived and not marked.
  int64_t mask_tp = 0, mask_fp = 0, mask_fn = 0;
  int frames_with_mask = 0;

  // Reports matched to a true change; true changes that count for recall, and of those found.
  struct Tally {
    int right = 0, counted = 0, found = 0;
  };
  Tally Count() const {
    Tally n;
    for (const auto& r : reported) n.right += !r.matched.empty();
    for (const auto& c : truth) n.counted += c.counted, n.found += c.counted && c.found;
    return n;
  }
};

// Scores each frame's moved mask against the world's truth: a pixel truly arrived where the
// truth marks it changed (moved/) and the frame's surface is nearer than the reference's there
// (previous_depth/) by more than 2 cm: what eq. 3 can see. Pixels without a depth reading or
// beyond `max_range_m` are not scored.
void ScoreMasks(const io::TumSequence& seq, const StreamedVisit& streamed, double max_range_m,
                Trial* t) {
  for (const TrackedFrame& f : streamed.frames) {
    if (f.moved_png.empty() || f.index >= seq.frames.size()) continue;
    const fs::path depth_path(seq.frames[f.index].depth_path);
    const fs::path dir = depth_path.parent_path().parent_path();
    const std::vector<uint8_t> bytes(f.moved_png.begin(), f.moved_png.end());
    const cv::Mat mask = cv::imdecode(bytes, cv::IMREAD_UNCHANGED);
    const cv::Mat truth =
        cv::imread((dir / "moved" / depth_path.filename()).string(), cv::IMREAD_UNCHANGED);
    const cv::Mat now = cv::imread(depth_path.string(), cv::IMREAD_UNCHANGED);
    const cv::Mat then =
        cv::imread((dir / "previous_depth" / depth_path.filename()).string(), cv::IMREAD_UNCHANGED);
    if (mask.empty() || truth.empty() || now.empty() || then.empty() ||
        mask.size() != truth.size() || now.size() != truth.size() || then.size() != now.size()) {
      continue;
    }
    ++t->frames_with_mask;
    constexpr double kScale = 5000.0;  // the sim's depth PNGs, units per metre
    for (int r = 0; r < mask.rows; ++r) {
      for (int c = 0; c < mask.cols; ++c) {
        const double d = now.at<uint16_t>(r, c) / kScale, p = then.at<uint16_t>(r, c) / kScale;
        if (d <= 0 || d > max_range_m) continue;
        const bool arrived = truth.at<uint8_t>(r, c) != 0 && p > 0 && p - d > 0.02;
        const bool marked = mask.at<uint8_t>(r, c) != 0;
        t->mask_tp += marked && arrived;
        t->mask_fp += marked && !arrived;
        t->mask_fn += !marked && arrived;
      }
    }
  }
}

struct Score {
  std::map<std::string, int> reported, correct, counted, found;
  int false_changes = 0;  // reports on a visit whose place did not change
  int64_t mask_tp = 0, mask_fp = 0, mask_fn = 0;
  int frames_with_mask = 0;
  void Add(const Trial& t, bool place_changed) {
    mask_tp += t.mask_tp;
    mask_fp += t.mask_fp;
    mask_fn += t.mask_fn;
    frames_with_mask += t.frames_with_mask;
    for (const auto& r : t.reported) {
      ++reported[r.kind];
      if (!r.matched.empty()) ++correct[r.kind];
      if (!place_changed) ++false_changes;
    }
    for (const auto& c : t.truth) {
      if (!c.counted) continue;
      ++counted[c.kind];
      if (c.found) ++found[c.kind];
    }
  }
  json Json() const {
    json precision = json::object(), recall = json::object(), counts = json::object();
    for (const char* k : kKinds) {
      auto get = [](const std::map<std::string, int>& m, const char* key) {
        auto it = m.find(key);
        return it == m.end() ? 0 : it->second;
      };
      const int rep = get(reported, k), ok = get(correct, k), n = get(counted, k),
                f = get(found, k);
      precision[k] = rep > 0 ? json(static_cast<double>(ok) / rep) : json(nullptr);
      recall[k] = n > 0 ? json(static_cast<double>(f) / n) : json(nullptr);
      counts[k] = {{"reported", rep}, {"correct", ok}, {"true", n}, {"found", f}};
    }
    auto ratio = [](int64_t x, int64_t n) {
      return n > 0 ? json(static_cast<double>(x) / static_cast<double>(n)) : json(nullptr);
    };
    return {{"precision", precision},
            {"recall", recall},
            {"counts", counts},
            {"false_changes", false_changes},
            {"moved_mask",
             {{"frames", frames_with_mask},
              {"precision", ratio(mask_tp, mask_tp + mask_fp)},
              {"recall", ratio(mask_tp, mask_tp + mask_fn)},
              {"marked_pixels", mask_tp + mask_fp},
              {"arrived_pixels", mask_tp + mask_fn}}}};
  }
};

bool PlaceChanges(const std::string& conditions) {
  return conditions.find("scenery") != std::string::npos;
}

int RunChangesEval(const CliContext& ctx, const ChangesEvalArgs& a) {
  if (auto s = PrepareOut(a.out); !s.ok()) return Fail(s);
  auto manifest = eval::ReadSuiteManifest(a.suite);
  if (!manifest.ok()) return Fail(manifest.status());
  auto client = ctx.Connect();
  if (!client.ok()) return Fail(client.status());
  const fs::path root(a.suite);
  const std::time_t started = std::time(nullptr);
  std::vector<Trial> trials;
  std::map<std::string, std::string> reference_of;
  for (const auto& v : *manifest) {
    if (v.role == "reference") reference_of[v.place_id] = v.path;
  }
  UnposedStreamOptions stream;
  stream.robot = "lifemap eval changes";
  stream.compact = a.compact;
  stream.send_truth_poses = a.truth_poses;
  stream.send_odometry = a.send_odometry;
  std::vector<std::string> maps;
  for (const auto& [place, ref_path] : reference_of) {
    const std::string map = absl::StrCat("eval-changes-", started, "-", place);
    if (auto m = (*client)->CreateMap(map, "lifemap eval changes"); !m.ok())
      return Fail(m.status());
    maps.push_back(map);
    auto ref_seq = io::ReadTumSequence((root / ref_path).string());
    if (!ref_seq.ok()) return Fail(ref_seq.status());
    stream.visit_label = ref_path;
    auto ref = StreamWithoutPoses(**client, map, *ref_seq, stream);
    if (!ref.ok()) return Fail(ref.status());
    // Ended, as a robot's visit is: the query frames' moved masks compare against it.
    if (auto e = (*client)->EndVisit(ref->visit_id); !e.ok()) return Fail(e.status());
    // The map's frame in the world's: the server's (the reference's tracked frame) aligned to
    // the truth by the reference's stored keyframes, as `eval alignment` does; the world's own
    // with truth poses.
    Eigen::Isometry3d T_world_map = Eigen::Isometry3d::Identity();
    if (!a.truth_poses) {
      auto stored = StoredEstimatedKeyframes(**client, map, ref->visit_id);
      if (!stored.ok()) return Fail(stored.status());
      auto aligned = eval::CompareTrajectories(*stored, eval::GroundTruth(*ref_seq));
      if (!aligned.ok()) {
        return Fail(absl::FailedPreconditionError(
            absl::StrCat(ref_path, ": the reference's track cannot be aligned to its truth: ",
                         aligned.status().message())));
      }
      T_world_map = aligned->T_truth_estimate;
    }
    for (const auto& v : *manifest) {
      if (v.place_id != place || v.role == "reference") continue;
      Trial t;
      t.path = v.path;
      t.conditions = v.conditions;
      t.subset = v.subset;
      auto truth = TrueChanges(root / ref_path, root / v.path, a.scoring);
      if (!truth.ok()) return Fail(truth.status());
      t.truth = *std::move(truth);
      auto seq = io::ReadTumSequence((root / v.path).string());
      if (!seq.ok()) return Fail(seq.status());
      stream.visit_label = v.path;
      stream.moved_against_visit = a.masks ? ref->visit_id : 0;
      auto q = StreamWithoutPoses(**client, map, *seq, stream);
      stream.moved_against_visit = 0;
      if (!q.ok()) return Fail(q.status());
      ScoreMasks(*seq, *q, 4.0, &t);
      if (auto e = (*client)->EndVisit(q->visit_id); !e.ok()) return Fail(e.status());
      t.visit = q->visit_id;
      auto r = (*client)->GetChanges(map, ref->visit_id, q->visit_id);
      if (absl::IsFailedPrecondition(r.status()) && !a.truth_poses) {
        // The server did not anchor the visit (--poses server): nothing to compare; counted
        // apart, not as changes missed.
        t.not_compared = std::string(r.status().message());
        if (!ctx.json) std::cerr << "  " << t.path << ": not compared: " << t.not_compared << "\n";
        trials.push_back(std::move(t));
        continue;
      }
      if (!r.ok()) return Fail(r.status());
      t.seconds = r->seconds();
      for (const auto& c : r->changes()) t.reported.push_back(ReportOf(c, T_world_map));
      MatchReports(&t.reported, &t.truth, a.scoring.tolerance_m);
      if (!ctx.json) {
        const Trial::Tally n = t.Count();
        std::cerr << absl::StrFormat(
            "  %-34s %2d reported (%d right), %d of %d true changes found\n", t.path,
            t.reported.size(), n.right, n.found, n.counted);
      }
      trials.push_back(std::move(t));
    }
  }
  if (!a.keep_maps) DeleteScratchMaps(**client, maps);
  Score all;
  std::map<std::string, Score> by_subset;
  std::string csv =
      "path,subset,conditions,visit,what,kind,instance_or_class,x,y,from_x,from_y,size_m,counted,"
      "matched\n";
  std::vector<double> seconds;
  int not_compared = 0;
  for (const auto& t : trials) {
    if (!t.not_compared.empty()) {
      ++not_compared;
      csv += absl::StrFormat("%s,%d,\"%s\",%d,not compared,,,,,,,,,\"%s\"\n", t.path, t.subset,
                             t.conditions, t.visit, t.not_compared);
      continue;
    }
    all.Add(t, PlaceChanges(t.conditions));
    by_subset[t.conditions].Add(t, PlaceChanges(t.conditions));
    seconds.push_back(t.seconds);
    for (const auto& c : t.truth) {
      csv +=
          absl::StrFormat("%s,%d,\"%s\",%d,true,%s,%d %s,%.3f,%.3f,%.3f,%.3f,%.3f,%d,%d\n", t.path,
                          t.subset, t.conditions, t.visit, c.kind, c.instance, c.detail, c.at.x(),
                          c.at.y(), c.from.x(), c.from.y(), c.size_m, c.counted, c.found);
    }
    for (const auto& r : t.reported) {
      csv += absl::StrFormat("%s,%d,\"%s\",%d,reported,%s,%s,%.3f,%.3f,%.3f,%.3f,%.3f,,%s\n",
                             t.path, t.subset, t.conditions, t.visit, r.kind, r.class_name,
                             r.at.x(), r.at.y(), r.from.x(), r.from.y(), r.size_m, r.matched);
    }
  }
  json summary = all.Json();
  summary["suite"] = a.suite;
  summary["poses"] = a.truth_poses ? "truth" : "server";
  summary["odometry"] = a.send_odometry ? "wheel" : "none";
  summary["not_compared"] = not_compared;
  summary["min_size_m"] = a.scoring.min_size_m;
  summary["tolerance_m"] = a.scoring.tolerance_m;
  summary["false_changes"] = json::object();
  summary["subsets"] = json::object();
  for (const auto& [name, s] : by_subset) {
    summary["subsets"][name] = s.Json();
    if (!PlaceChanges(name)) summary["false_changes"][name] = s.false_changes;
  }
  std::sort(seconds.begin(), seconds.end());
  summary["get_changes_s_median"] = seconds.empty() ? 0.0 : seconds[seconds.size() / 2];
  std::string report = absl::StrFormat(
      "# Changes between visits: %s\n\nEach place's reference, then its query visits, streamed "
      "into one map (poses: %s); GetChanges(reference, query) scored against scene.json. Recall "
      "counts props of at least %.2f m seen in %d pixels or more (doors: every toggled one); a "
      "report within %.2f m (or half the prop's size) of a true change of its kind is right.\n\n"
      "| kind | reported | right | precision | true | found | recall "
      "|\n|---|---|---|---|---|---|---|\n",
      a.suite, a.truth_poses ? "the ground truth's" : "the server's own", a.scoring.min_size_m,
      a.scoring.min_seen_pixels, a.scoring.tolerance_m);
  const json counts = summary["counts"];
  for (const char* k : kKinds) {
    const auto& c = counts[k];
    auto ratio = [](int x, int n) {
      return n > 0 ? absl::StrFormat("%.2f", double(x) / n) : std::string("-");
    };
    report += absl::StrFormat("| %s | %d | %d | %s | %d | %d | %s |\n", k, c["reported"].get<int>(),
                              c["correct"].get<int>(),
                              ratio(c["correct"].get<int>(), c["reported"].get<int>()),
                              c["true"].get<int>(), c["found"].get<int>(),
                              ratio(c["found"].get<int>(), c["true"].get<int>()));
  }
  report += absl::StrFormat(
      "\nPer-frame moved masks against the reference (eq. 3): %d frames; pixel precision %s, "
      "recall %s of the pixels where something truly arrived.\n\n| subset | frames | mask "
      "precision | mask recall | marked pixels |\n|---|---|---|---|---|\n",
      all.frames_with_mask, summary["moved_mask"]["precision"].dump(),
      summary["moved_mask"]["recall"].dump());
  for (const auto& [name, sc] : by_subset) {
    const json m = sc.Json()["moved_mask"];
    report += absl::StrFormat("| %s | %d | %s | %s | %d |\n", name, m["frames"].get<int>(),
                              m["precision"].dump(), m["recall"].dump(),
                              m["marked_pixels"].get<int64_t>());
  }
  report += "\nReports on visits whose place did not change (false changes): ";
  for (const auto& [name, n] : summary["false_changes"].items()) {
    report += absl::StrFormat("%s %d; ", name, n.get<int>());
  }
  report += "\n";
  if (not_compared > 0) {
    report += absl::StrFormat(
        "\n%d query visits were not compared (not anchored by the server: changes.csv says "
        "why); the figures above are of the others.\n",
        not_compared);
  }
  return FinishStudy(ctx, a.out, {{"changes.csv", csv}}, {}, summary, report);
}

struct RetentionEvalArgs {
  std::string visits, out;
  bool retention = true;  // --retention on|off
  bool keep_map = false;
  bool compact = false;
  double right_m = 0.5, right_deg = 15.0;  // an appearance match this near the truth is right
  ChangeScoring scoring;                   // what counts as a change found
};

// Percentile `q` in [0, 1] of `v` (sorted here); 0 for none.
double Percentile(std::vector<double> v, double q) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  return v[std::min(v.size() - 1, static_cast<size_t>(q * static_cast<double>(v.size())))];
}

// `lifemap eval retention`: the visits of one place (a `lifemap sim --visits N` folder) streamed
// one after another into one map with their true poses, retention applied after each (or only
// dry-run: the baseline), and after each visit: the map's bytes, how many of the visit's
// keyframes appearance recognised right among the earlier visits, the keyframes' reply times,
// and GetChanges(previous, this) scored against the visit's change records.
int RunRetentionEval(const CliContext& ctx, const RetentionEvalArgs& a) {
  if (auto s = PrepareOut(a.out); !s.ok()) return Fail(s);
  std::vector<fs::path> dirs;
  for (const auto& e : fs::directory_iterator(a.visits)) {
    if (e.is_directory() && e.path().filename().string().rfind("visit_", 0) == 0) {
      dirs.push_back(e.path());
    }
  }
  std::sort(dirs.begin(), dirs.end());
  if (dirs.size() < 2) {
    return Fail(absl::InvalidArgumentError(
        absl::StrCat(a.visits, " holds ", dirs.size(),
                     " visit_* folders; make one with `lifemap sim --visits 20 --out DIR`")));
  }
  auto client = ctx.Connect();
  if (!client.ok()) return Fail(client.status());
  const std::string map = absl::StrCat("eval-retention-", std::time(nullptr));
  if (auto m = (*client)->CreateMap(map, "lifemap eval retention"); !m.ok()) {
    return Fail(m.status());
  }
  UnposedStreamOptions stream;
  stream.robot = "lifemap eval retention";
  stream.compact = a.compact;
  stream.send_truth_poses = true;
  std::map<uint64_t, Pose> keyframe_truth;  // every keyframe stored so far, thinned or not
  std::vector<uint64_t> visit_ids;
  json per_visit = json::array();
  Score changes;
  int queried = 0, right = 0;
  std::vector<double> keyframe_ms;
  std::string csv =
      "visit,keyframes_stored,map_keyframes,map_bytes,thinned,queried,recognised,right,"
      "keyframe_ms_p50,keyframe_ms_p95,changes_reported,changes_right,changes_true,"
      "changes_found\n";
  for (size_t i = 0; i < dirs.size(); ++i) {
    auto seq = io::ReadTumSequence(dirs[i].string());
    if (!seq.ok()) return Fail(seq.status());
    stream.visit_label = dirs[i].filename().string();
    auto streamed = StreamWithoutPoses(**client, map, *seq, stream);
    if (!streamed.ok()) return Fail(streamed.status());
    if (auto e = (*client)->EndVisit(streamed->visit_id); !e.ok()) return Fail(e.status());
    const uint64_t visit = streamed->visit_id;
    // Appearance: each keyframe's best match of an earlier visit, right when the pose it gives
    // (the matched keyframe's true pose and the verified relative pose) is near the truth.
    int v_queried = 0, v_recognised = 0, v_right = 0, stored = 0;
    std::vector<double> ms;
    for (const auto& f : streamed->frames) {
      if (f.keyframe_id == 0 || !f.truth) continue;
      ++stored;
      ms.push_back(f.total_ms);
      if (i == 0) continue;
      ++v_queried;
      for (const auto& hit : f.appearance) {
        if (hit.visit_id == visit) continue;
        ++v_recognised;
        auto k = keyframe_truth.find(hit.keyframe_id);
        if (k != keyframe_truth.end()) {
          const Pose estimate =
              Pose::FromIsometry(k->second.ToIsometry() * hit.T_match_query.ToIsometry());
          v_right += TranslationDistanceM(estimate, *f.truth) <= a.right_m &&
                     RotationAngleRad(estimate, *f.truth) * 180 / M_PI <= a.right_deg;
        }
        break;
      }
    }
    for (const auto& f : streamed->frames) {
      if (f.keyframe_id != 0 && f.truth) keyframe_truth[f.keyframe_id] = *f.truth;
    }
    queried += v_queried;
    right += v_right;
    keyframe_ms.insert(keyframe_ms.end(), ms.begin(), ms.end());
    // Changes since the previous visit (both kept whole by the default policy).
    Trial t;
    if (i > 0) {
      auto truth = TrueChanges(dirs[i - 1], dirs[i], a.scoring);
      if (!truth.ok()) return Fail(truth.status());
      t.truth = *std::move(truth);
      auto r = (*client)->GetChanges(map, visit_ids.back(), visit);
      if (!r.ok()) return Fail(r.status());
      for (const auto& c : r->changes()) {
        t.reported.push_back(ReportOf(c, Eigen::Isometry3d::Identity()));  // truth poses
      }
      MatchReports(&t.reported, &t.truth, a.scoring.tolerance_m);
      changes.Add(t, true);
    }
    visit_ids.push_back(visit);
    v1::ApplyRetentionRequest req;
    req.set_map(map);
    req.set_dry_run(!a.retention);
    auto report = (*client)->ApplyRetention(req);
    if (!report.ok()) return Fail(report.status());
    const Trial::Tally n = t.Count();
    const double p50 = Percentile(ms, 0.5), p95 = Percentile(ms, 0.95);
    per_visit.push_back(
        {{"visit", visit},
         {"folder", dirs[i].filename().string()},
         {"keyframes_stored", stored},
         {"map_keyframes", report->after().keyframes()},
         {"map_bytes", report->after().total_bytes()},
         {"image_bytes", report->after().image_bytes()},
         {"feature_bytes", report->after().feature_bytes()},
         {"octree_bytes", report->after().octree_bytes()},
         {"plan_bytes", report->after().plan_bytes()},
         {"thinned", a.retention ? report->thinned_size() : 0},
         {"would_thin", report->thinned_size()},
         {"appearance", {{"queried", v_queried}, {"recognised", v_recognised}, {"right", v_right}}},
         {"keyframe_ms_p50", p50},
         {"keyframe_ms_p95", p95},
         {"changes",
          {{"reported", t.reported.size()},
           {"right", n.right},
           {"true", n.counted},
           {"found", n.found}}}});
    csv += absl::StrFormat("%d,%d,%d,%d,%d,%d,%d,%d,%.1f,%.1f,%d,%d,%d,%d\n", visit, stored,
                           report->after().keyframes(), report->after().total_bytes(),
                           a.retention ? report->thinned_size() : 0, v_queried, v_recognised,
                           v_right, p50, p95, t.reported.size(), n.right, n.counted, n.found);
    if (!ctx.json) {
      std::cerr << absl::StrFormat(
          "  %s: %d keyframes; map %d keyframes, %s; appearance %d/%d right; changes %d "
          "reported (%d right), %d of %d found\n",
          dirs[i].filename().string(), stored, report->after().keyframes(),
          HumanBytes(report->after().total_bytes()), v_right, v_queried, t.reported.size(), n.right,
          n.found, n.counted);
    }
  }
  // The first and the last visit compared (months apart; a thinned first visit against a whole
  // last one): what is reported, by kind (the world records changes visit to visit only).
  json first_last = json::object();
  auto fl = (*client)->GetChanges(map, visit_ids.front(), visit_ids.back());
  if (!fl.ok()) return Fail(fl.status());
  for (const auto& c : fl->changes()) first_last[c.kind()] = first_last.value(c.kind(), 0) + 1;
  if (!a.keep_map) DeleteScratchMaps(**client, {map});

  const double first_bytes = per_visit.front()["map_bytes"].get<double>();
  const double last_bytes = per_visit.back()["map_bytes"].get<double>();
  json summary = {{"visits_folder", a.visits},
                  {"retention", a.retention},
                  {"visits", dirs.size()},
                  {"bytes_first_visit", first_bytes},
                  {"bytes_last_visit", last_bytes},
                  {"bytes_ratio", first_bytes > 0 ? last_bytes / first_bytes : 0.0},
                  {"appearance",
                   {{"queried", queried},
                    {"right", right},
                    {"recall", queried > 0 ? static_cast<double>(right) / queried : 0.0},
                    {"right_within_m", a.right_m},
                    {"right_within_deg", a.right_deg}}},
                  {"keyframe_ms_p50", Percentile(keyframe_ms, 0.5)},
                  {"keyframe_ms_p95", Percentile(keyframe_ms, 0.95)},
                  {"changes", changes.Json()},
                  {"first_last_changes", first_last},
                  {"per_visit", per_visit}};
  std::string report = absl::StrFormat(
      "# Retention over %d visits: %s\n\nRetention %s. The map's bytes (images, features, "
      "octrees, plans) after the first visit %s, after the last %s: %.2f×. Appearance: %d of %d "
      "keyframes of visits 2-%d recognised right among the earlier visits (within %.2f m and "
      "%.0f°): %.3f. Keyframe replies p50 %.1f ms, p95 %.1f ms.\n\n",
      dirs.size(), a.visits, a.retention ? "applied after each visit" : "off (dry runs only)",
      HumanBytes(static_cast<uint64_t>(first_bytes)), HumanBytes(static_cast<uint64_t>(last_bytes)),
      summary["bytes_ratio"].get<double>(), right, queried, dirs.size(), a.right_m, a.right_deg,
      summary["appearance"]["recall"].get<double>(), summary["keyframe_ms_p50"].get<double>(),
      summary["keyframe_ms_p95"].get<double>());
  report += "| kind | reported | right | true | found |\n|---|---|---|---|---|\n";
  const json counts = summary["changes"]["counts"];
  for (const char* k : kKinds) {
    const auto& c = counts[k];
    report += absl::StrFormat("| %s | %d | %d | %d | %d |\n", k, c["reported"].get<int>(),
                              c["correct"].get<int>(), c["true"].get<int>(), c["found"].get<int>());
  }
  report += absl::StrFormat("\nFirst against last visit: %s\n", first_last.dump());
  return FinishStudy(ctx, a.out, {{"visits.csv", csv}}, {}, summary, report);
}

}  // namespace

void AddChangesEvalCommand(CLI::App* eval, CliContext* ctx) {
  auto* cmd = eval->add_subcommand(
      "changes",
      "Stream a synthetic suite, one map per place, and score GetChanges(reference, query) "
      "against the world's change records per kind and condition subset");
  auto a = std::make_shared<ChangesEvalArgs>();
  cmd->add_option("--suite", a->suite, "a lifemap sim suite folder (manifest.json)")
      ->required()
      ->check(CLI::ExistingDirectory);
  cmd->add_option("--out", a->out, "folder for summary.json, changes.csv, report.md")->required();
  AddSendOption(cmd, &a->compact);
  cmd->add_option_function<std::string>(
         "--poses", [a](const std::string& how) { a->truth_poses = how == "truth"; },
         "truth (default: the recording's ground truth, as a localised robot sends) or server "
         "(the server tracks and anchors each visit)")
      ->check(CLI::IsMember({"truth", "server"}));
  cmd->add_flag("--keep-maps", a->keep_maps, "keep the per-place maps (default: deleted after)");
  AddOdometryOption(cmd, &a->send_odometry);
  cmd->add_flag("--masks,!--no-masks", a->masks,
                "score each query frame's moved mask against the reference (default on)");
  AddChangeScoringOptions(cmd, &a->scoring);
  cmd->callback([ctx, a] { ctx->run = [ctx, a] { return RunChangesEval(*ctx, *a); }; });
}

void AddRetentionEvalCommand(CLI::App* eval, CliContext* ctx) {
  auto* cmd = eval->add_subcommand(
      "retention",
      "Stream a place's visits (lifemap sim --visits N) into one map with retention after each "
      "(or dry runs: the baseline) and measure bytes, appearance recall, reply times and changes");
  auto a = std::make_shared<RetentionEvalArgs>();
  cmd->add_option("--visits", a->visits, "a `lifemap sim --visits N` folder (visit_* folders)")
      ->required()
      ->check(CLI::ExistingDirectory);
  cmd->add_option("--out", a->out, "folder for summary.json, visits.csv, report.md")->required();
  cmd->add_option_function<std::string>(
         "--retention", [a](const std::string& v) { a->retention = v == "on"; },
         "on (default: applied after each visit) or off (dry runs only: the baseline)")
      ->check(CLI::IsMember({"on", "off"}));
  AddSendOption(cmd, &a->compact);
  cmd->add_flag("--keep-map", a->keep_map, "keep the map (default: deleted after)");
  cmd->callback([ctx, a] { ctx->run = [ctx, a] { return RunRetentionEval(*ctx, *a); }; });
}

}  // namespace lifemap::cli
