// `lifemap eval ...`: the papers' experiments, run locally on datasets (no server needed).
#include <filesystem>
#include <fstream>
#include <iostream>

#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "client/cli/commands.h"
#include "client/cli/output.h"
#include "client/cli/study.h"
#include "core/change/moved_zones.h"
#include "core/common/image_codec.h"
#include "core/eval/entropy_study.h"
#include "core/eval/metrics.h"
#include "core/io/labeled_pcd.h"
#include "core/io/tum_dataset.h"
#include "core/mapping/point_cloud.h"

namespace lifemap::cli {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

// mOSD ground truth: labels 1-9 are the supporting table, 20 and above objects (object id =
// label / 10), 0 no point.
absl::StatusOr<std::vector<eval::LabeledScene>> ReadPcdFolder(const std::string& dir) {
  if (!fs::is_directory(dir)) return absl::NotFoundError(absl::StrCat(dir, ": not a directory"));
  std::vector<std::string> files;
  for (const auto& e : fs::directory_iterator(dir)) {
    if (e.path().extension() == ".pcd") files.push_back(e.path().string());
  }
  std::sort(files.begin(), files.end());
  if (files.empty()) {
    return absl::NotFoundError(absl::StrCat(dir,
                                            ": no .pcd files (expected labelled organized "
                                            "clouds such as mOSD's)"));
  }
  std::vector<eval::LabeledScene> scenes;
  for (const auto& f : files) {
    auto frame = io::ReadLabeledPcd(f);
    if (!frame.ok()) return frame.status();
    eval::LabeledScene s;
    s.name = fs::path(f).stem().string();
    s.frame = std::move(frame->frame);
    s.moved = frame->labels >= 20;
    s.labelled = frame->labels >= 1;
    scenes.push_back(std::move(s));
  }
  return scenes;
}

// Ground truth a synthetic visit folder carries (lifemap sim): which pixels count as "moved".
enum class SimTruth {
  kNone,        // a real recording, or ignore the labels
  kMovedZones,  // moved/: what changed since the previous visit, exactly
  kEq3,         // eq. 3 of paper 000 on the depth and previous_depth/ (the aligned depth map
                // of the previous visit at the same pose), as the paper built its ground truth
  kMovable,     // labels/instance of the objects scene.json marks movable (props)
};

// The instance ids scene.json marks movable; empty when there is no scene.json.
std::vector<int> MovableInstances(const std::string& dir) {
  std::vector<int> ids;
  std::ifstream in(fs::path(dir) / "scene.json");
  if (!in) return ids;
  try {
    json scene;
    in >> scene;
    for (const auto& o : scene.at("objects")) {
      if (o.at("movable").get<bool>()) ids.push_back(o.at("instance").get<int>());
    }
  } catch (const json::exception&) {
  }
  return ids;
}

// Agreement of eq. 3's masks with the exact ones, pixels summed over frames.
struct MaskAgreement {
  int64_t intersection = 0, union_ = 0;
  double iou() const { return union_ > 0 ? static_cast<double>(intersection) / union_ : 1.0; }
};

// Every `stride`-th frame of a TUM-format folder; with `truth`, the synthetic world's ground
// truth as the scenes' moved/labelled masks; with `fuse` > 0, each frame's depth fused with
// its `fuse` neighbours on either side (a multi-frame reconstruction from the ground-truth
// poses, for the mesh variant).
absl::StatusOr<std::vector<eval::LabeledScene>> ReadTumScenes(const std::string& dir, int stride,
                                                              SimTruth truth = SimTruth::kNone,
                                                              int fuse = 0,
                                                              MaskAgreement* agreement = nullptr) {
  auto seq = io::ReadTumSequence(dir);
  if (!seq.ok()) return seq.status();
  if (fuse > 0 && seq->frames_with_pose < static_cast<int>(seq->frames.size())) {
    return absl::FailedPreconditionError(
        absl::StrCat(dir, ": --fuse needs a pose for every frame (groundtruth.txt)"));
  }
  const std::vector<int> movable = MovableInstances(dir);
  std::vector<eval::LabeledScene> scenes;
  for (size_t i = 0; i < seq->frames.size(); i += static_cast<size_t>(stride)) {
    const auto& e = seq->frames[i];
    auto frame = io::DecodeTumFrame(*seq, e);
    if (!frame.ok()) return frame.status();
    if (fuse > 0) {
      std::vector<RgbdFrame> neighbours;
      for (int j = std::max(0, static_cast<int>(i) - fuse);
           j <= std::min(static_cast<int>(seq->frames.size()) - 1, static_cast<int>(i) + fuse);
           ++j) {
        if (j == static_cast<int>(i)) continue;
        auto other = io::DecodeTumFrame(*seq, seq->frames[static_cast<size_t>(j)]);
        if (!other.ok()) return other.status();
        neighbours.push_back(*std::move(other));
      }
      auto fused = mapping::FuseDepth(*frame, neighbours);
      if (!fused.ok()) return fused.status();
      frame->depth_m = *fused;
    }
    eval::LabeledScene s;
    s.name = absl::StrFormat("%s@%.3f", fs::path(dir).filename().string(), e.timestamp_s);
    s.frame = *std::move(frame);
    if (truth != SimTruth::kNone) {
      const std::string file = fs::path(e.rgb_path).filename().string();
      if (truth == SimTruth::kMovedZones) {
        s.moved = cv::imread((fs::path(dir) / "moved" / file).string(), cv::IMREAD_GRAYSCALE);
      } else if (truth == SimTruth::kEq3) {
        const cv::Mat previous =
            cv::imread((fs::path(dir) / "previous_depth" / file).string(), cv::IMREAD_UNCHANGED);
        if (previous.empty()) {
          return absl::NotFoundError(absl::StrCat(dir, ": no previous_depth/", file,
                                                  " (eq. 3 needs a query visit of lifemap sim)"));
        }
        cv::Mat previous_m;
        previous.convertTo(previous_m, CV_32FC1, 1.0 / 5000.0);
        s.moved = change::MovedZones(s.frame.depth_m, {previous_m});
        const cv::Mat exact =
            cv::imread((fs::path(dir) / "moved" / file).string(), cv::IMREAD_GRAYSCALE);
        if (agreement && !exact.empty()) {
          agreement->intersection += cv::countNonZero(s.moved & exact);
          agreement->union_ += cv::countNonZero(s.moved | exact);
        }
      } else {
        const cv::Mat instance = cv::imread((fs::path(dir) / "labels" / "instance" / file).string(),
                                            cv::IMREAD_UNCHANGED);
        if (!instance.empty()) {
          s.moved = cv::Mat(instance.size(), CV_8UC1, cv::Scalar(0));
          for (int id : movable) s.moved |= (instance == id);
        }
      }
      if (s.moved.empty() || s.moved.size() != s.frame.depth_m.size()) {
        return absl::NotFoundError(
            absl::StrCat(dir, ": no ground truth for ", file,
                         " (expected moved/ and labels/instance/ of a lifemap sim visit)"));
      }
      s.labelled = s.frame.depth_m > 0;
    }
    scenes.push_back(std::move(s));
  }
  return scenes;
}

// A folder of .pcd scenes, or a synthetic visit (TUM folder with moved/): the feature study's
// input.
absl::StatusOr<std::vector<eval::LabeledScene>> ReadLabeledFolder(const std::string& dir,
                                                                  int stride, int fuse, bool eq3,
                                                                  MaskAgreement* agreement) {
  if (fs::exists(fs::path(dir) / "moved") && fs::exists(fs::path(dir) / "rgb.txt")) {
    return ReadTumScenes(dir, stride, eq3 ? SimTruth::kEq3 : SimTruth::kMovedZones, fuse,
                         agreement);
  }
  if (eq3) {
    return absl::InvalidArgumentError(
        absl::StrCat(dir, ": --moved eq3 needs synthetic visits (previous_depth/)"));
  }
  return ReadPcdFolder(dir);
}

json AucJson(const eval::FeatureAuc& a) {
  return {{"entropy", a.entropy},
          {"planarity", a.planarity},
          {"horizontality", a.horizontality},
          {"textureness", a.textureness}};
}

struct EvalArgs {
  std::vector<std::string> data;
  std::string out;
  float k = 0.6f;
  int downsample = 1;
  bool mesh = false;
  std::string keypoints = "sift";
  std::string tum_a, tum_b;
  int frame_stride = 4;
  int fuse = 0;
  std::string moved = "exact";
  int min_gap = 8;
  double min_recall = 0.8;
  int iterations = 10000;
};

int RunFeatures(const CliContext& ctx, const EvalArgs& a) {
  if (auto s = PrepareOut(a.out); !s.ok()) return Fail(s);
  std::vector<eval::LabeledScene> scenes;
  MaskAgreement agreement;
  for (const auto& dir : a.data) {
    auto more = ReadLabeledFolder(dir, a.frame_stride, a.fuse, a.moved == "eq3", &agreement);
    if (!more.ok()) return Fail(more.status());
    for (auto& s : *more) scenes.push_back(std::move(s));
  }
  eval::FeatureStudyOptions options;
  options.entropy.superjuts.k = a.k;
  options.entropy.downsample = a.downsample;
  options.entropy.mesh = a.mesh;
  auto study = eval::RunFeatureStudy(scenes, options);
  if (!study.ok()) return Fail(study.status());

  std::string csv =
      "scene,superjut,size_px,moved_fraction,moved,entropy,planarity,"
      "horizontality,textureness,neg_entropy\n";
  eval::Series moved{"moved", {}, {}, cv::Scalar(200, 80, 0), false};
  eval::Series still{"static", {}, {}, cv::Scalar(0, 0, 220), false};
  const double log_m = std::log(80.0);
  for (const auto& s : study->superjuts) {
    csv += absl::StrFormat("%s,%d,%d,%.4f,%d,%.5f,%.5f,%.5f,%.5f,%.5f\n", s.scene, s.id, s.size_px,
                           s.moved_fraction, s.moved, s.entropy, s.planarity, s.horizontality,
                           s.textureness, s.neg_entropy);
    auto& series = s.moved ? moved : still;
    series.x.push_back(s.entropy / log_m);
    series.y.push_back(s.planarity);
  }
  const json summary = {{"scenes", scenes.size()},
                        {"superjuts", study->superjuts.size()},
                        {"moved_superjuts", study->moved_superjuts},
                        {"k", a.k},
                        {"downsample", a.downsample},
                        {"variant", a.mesh ? "mesh" : "image grid"},
                        {"fused_neighbours", a.fuse},
                        {"moved_ground_truth", a.moved},
                        {"auc", AucJson(study->superjut_auc)},
                        {"pixel_auc", AucJson(study->pixel_auc)}};
  const auto& sa = study->superjut_auc;
  const auto& pa = study->pixel_auc;
  const std::string report = absl::StrFormat(
      "# Entropy feature study (paper 000, Fig. 6)\n\n"
      "%d scenes from %s; %d superjuts with ground truth, %d of them moved.\n"
      "Superjuts: %s variant, k = %.2f, working resolution 1/%d, depth fused with %d "
      "neighbours per side.%s\n\n"
      "Area under the ROC curve for telling moved from static, oriented as the paper's "
      "hypothesis (entropy and textureness higher on moved, planarity and horizontality lower); "
      "0.5 is chance.\n\n"
      "| feature | per superjut | per pixel |\n|---|---|---|\n"
      "| entropy | %.3f | %.3f |\n| planarity | %.3f | %.3f |\n| horizontality | %.3f | %.3f |\n"
      "| textureness | %.3f | %.3f |\n\n"
      "Files: `superjuts.csv` (every superjut), `entropy_planarity.png` (the paper's Fig. 6c), "
      "`summary.json`.\n",
      scenes.size(), absl::StrJoin(a.data, ", "), study->superjuts.size(), study->moved_superjuts,
      a.mesh ? "mesh" : "image-grid", a.k, a.downsample, a.fuse,
      a.moved == "eq3"
          ? absl::StrFormat(" Moved zones by eq. 3 (10x10 median, 50 mm) on aligned depth maps; "
                            "they agree with the exact masks at IoU %.3f.",
                            agreement.iou())
          : std::string(),
      sa.entropy, pa.entropy, sa.planarity, pa.planarity, sa.horizontality, pa.horizontality,
      sa.textureness, pa.textureness);
  return FinishStudy(
      ctx, a.out, {{"superjuts.csv", csv}},
      {{"entropy_planarity.png", eval::PlotCurves({still, moved}, "superjuts: entropy vs planarity",
                                                  "entropy / log M", "planarity")}},
      summary, report);
}

int RunMatching(const CliContext& ctx, const EvalArgs& a) {
  if (auto s = PrepareOut(a.out); !s.ok()) return Fail(s);
  eval::MatchingStudyOptions options;
  options.entropy.superjuts.k = a.k;
  options.entropy.downsample = a.downsample;
  options.entropy.mesh = a.mesh;
  options.keypoints = a.keypoints == "orb" ? eval::Keypoints::kOrb : eval::Keypoints::kSift;
  options.min_recall = a.min_recall;
  options.ransac_iterations = a.iterations;
  json sets = json::array();
  std::string pairs_csv =
      "set,a,b,mask,threshold,matches,inliers,kept,kept_inliers,precision,recall,"
      "static_precision\n";
  std::string report = absl::StrFormat(
      "# Entropy matching study (paper 000, eqs. 5-6, Figs. 9-10)\n\n"
      "Keypoints %s, ratio test %.2f, ground-truth inliers by RANSAC on F (%d iterations, %.1f "
      "px); the best threshold per pair keeps recall >= %.2f. Null mask: each scene's superjut "
      "scores randomly permuted. Oracle: the labelled objects masked. Static GT: F fitted on "
      "matches off the objects. Gain = masked / raw - 1.\n\n"
      "| set | pairs | raw inlier ratio | best th (mean) | masked | gain | recall | null gain | "
      "oracle gain | fixed th | fixed gain | fixed recall | static raw | static gain | static "
      "null | static oracle |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
      a.keypoints, options.ratio, options.ransac_iterations, options.ransac_threshold_px,
      options.min_recall);
  double fixed = -1.0;
  std::vector<eval::Series> curves;
  const cv::Scalar colors[] = {cv::Scalar(200, 80, 0), cv::Scalar(0, 140, 0), cv::Scalar(0, 0, 200),
                               cv::Scalar(150, 0, 150)};
  json first_summary;
  struct Set {
    std::string name;
    std::vector<eval::LabeledScene> scenes;
    std::vector<std::pair<size_t, size_t>> pairs;  // empty = every pair
  };
  std::vector<Set> inputs;
  for (const auto& dir : a.data) {
    auto scenes = ReadPcdFolder(dir);
    if (!scenes.ok()) return Fail(scenes.status());
    inputs.push_back({fs::path(dir).filename().string(), *std::move(scenes), {}});
  }
  if (!a.tum_a.empty()) {
    // Two TUM recordings of one place (or one recording against itself, frames far apart).
    const bool same = fs::equivalent(a.tum_a, a.tum_b);
    // Synthetic visits carry labels: their movable props are the oracle's objects.
    const SimTruth truth = fs::exists(fs::path(a.tum_a) / "labels" / "instance") &&
                                   fs::exists(fs::path(a.tum_b) / "labels" / "instance")
                               ? SimTruth::kMovable
                               : SimTruth::kNone;
    auto scenes_a = ReadTumScenes(a.tum_a, a.frame_stride, truth, a.fuse);
    if (!scenes_a.ok()) return Fail(scenes_a.status());
    Set set{fs::path(a.tum_a).filename().string(), *std::move(scenes_a), {}};
    const size_t na = set.scenes.size();
    if (same) {
      for (size_t i = 0; i < na; ++i) {
        for (size_t j = i + 1; j < na; ++j) {
          if ((j - i) * static_cast<size_t>(a.frame_stride) >= static_cast<size_t>(a.min_gap)) {
            set.pairs.emplace_back(i, j);
          }
        }
      }
    } else {
      auto scenes_b = ReadTumScenes(a.tum_b, a.frame_stride, truth, a.fuse);
      if (!scenes_b.ok()) return Fail(scenes_b.status());
      set.name += "+" + fs::path(a.tum_b).filename().string();
      for (auto& s : *scenes_b) set.scenes.push_back(std::move(s));
      for (size_t i = 0; i < na; ++i) {
        for (size_t j = na; j < set.scenes.size(); ++j) set.pairs.emplace_back(i, j);
      }
    }
    if (set.pairs.empty()) {
      return UsageError(absl::StrCat("no frame pair is ", a.min_gap,
                                     " frames apart; lower --min-gap or --frame-stride"));
    }
    report +=
        "\nThe TUM set has no labels: its oracle and static figures equal the unmasked "
        "ones.\n\n";
    inputs.push_back(std::move(set));
  }
  if (inputs.empty()) {
    return UsageError("give --data DIR (labelled .pcd scenes) or --a DIR --b DIR (TUM)");
  }
  for (size_t set = 0; set < inputs.size(); ++set) {
    // The first set picks one threshold for every pair; later sets reuse it (cross-set check).
    auto study = eval::RunMatchingStudy(inputs[set].scenes, options, set == 0 ? -1.0 : fixed,
                                        inputs[set].pairs);
    if (!study.ok()) return Fail(study.status());
    const auto& m = study->summary;
    if (set == 0) fixed = m.fixed_threshold;
    const std::string& name = inputs[set].name;
    for (const auto& p : study->pairs) {
      for (const auto* sweep : {&p.entropy_sweep, &p.null_sweep}) {
        for (const auto& q : *sweep) {
          pairs_csv += absl::StrFormat("%s,%s,%s,%s,%.2f,%d,%d,%d,%d,%.4f,%.4f,%.4f\n", name, p.a,
                                       p.b, sweep == &p.entropy_sweep ? "entropy" : "null",
                                       q.threshold, p.matches, p.inliers, q.kept, q.kept_inliers,
                                       q.precision, q.recall, q.static_precision);
        }
      }
      pairs_csv += absl::StrFormat("%s,%s,%s,oracle,,%d,%d,%d,%d,%.4f,%.4f,%.4f\n", name, p.a, p.b,
                                   p.matches, p.inliers, p.oracle.kept, p.oracle.kept_inliers,
                                   p.oracle.precision, p.oracle.recall, p.oracle.static_precision);
    }
    report += absl::StrFormat(
        "| %s | %d | %.3f | %.2f | %.3f | %+.1f%% | %.2f | %+.1f%% | %+.1f%% | %.2f%s | %+.1f%% | "
        "%.2f | %.3f | %+.1f%% | %+.1f%% | %+.1f%% |\n",
        name, m.pairs, m.raw_inlier_ratio, m.best_threshold, m.masked_inlier_ratio,
        100 * m.inlier_ratio_gain, m.recall_at_best, 100 * m.null_inlier_ratio_gain,
        100 * m.oracle_inlier_ratio_gain, m.fixed_threshold,
        set == 0 ? " (chosen here)" : " (from the first set)", 100 * m.fixed_gain, m.fixed_recall,
        m.static_raw_ratio, 100 * m.static_gain, 100 * m.static_null_gain,
        100 * m.static_oracle_gain);
    const json summary = {{"set", name},
                          {"pairs", m.pairs},
                          {"skipped_pairs", m.skipped_pairs},
                          {"raw_inlier_ratio", m.raw_inlier_ratio},
                          {"best_threshold", m.best_threshold},
                          {"masked_inlier_ratio", m.masked_inlier_ratio},
                          {"inlier_ratio_gain", m.inlier_ratio_gain},
                          {"recall_at_best", m.recall_at_best},
                          {"null_inlier_ratio_gain", m.null_inlier_ratio_gain},
                          {"oracle_inlier_ratio_gain", m.oracle_inlier_ratio_gain},
                          {"oracle_recall", m.oracle_recall},
                          {"fixed_threshold", m.fixed_threshold},
                          {"fixed_threshold_gain", m.fixed_gain},
                          {"fixed_threshold_recall", m.fixed_recall},
                          {"static_gt",
                           {{"raw_inlier_ratio", m.static_raw_ratio},
                            {"masked_inlier_ratio", m.static_masked_ratio},
                            {"inlier_ratio_gain", m.static_gain},
                            {"null_inlier_ratio_gain", m.static_null_gain},
                            {"oracle_inlier_ratio_gain", m.static_oracle_gain}}}};
    if (set == 0) first_summary = summary;
    sets.push_back(summary);
    curves.push_back({name + " entropy", m.mean_recall, m.mean_precision, colors[(2 * set) % 4]});
    curves.push_back({name + " null", m.null_recall, m.null_precision, colors[(2 * set + 1) % 4]});
  }
  json summary = first_summary;  // the headline figures are the first set's
  summary["sets"] = sets;
  summary["keypoints"] = a.keypoints;
  summary["k"] = a.k;
  summary["variant"] = a.mesh ? "mesh" : "image grid";
  summary["fused_neighbours"] = a.fuse;
  report +=
      "\nFiles: `pairs.csv` (every pair and threshold), `pr_curve.png` (mean precision "
      "against mean recall as the threshold sweeps), `summary.json`.\n";
  return FinishStudy(
      ctx, a.out, {{"pairs.csv", pairs_csv}},
      {{"pr_curve.png", eval::PlotCurves(curves, "matches kept by neg-entropy threshold", "recall",
                                         "precision (inlier ratio)")}},
      summary, report);
}

absl::Status WriteText(const fs::path& path, const std::string& text) {
  std::ofstream out(path);
  out << text;
  return out ? absl::OkStatus()
             : absl::PermissionDeniedError(absl::StrCat("cannot write ", path.string()));
}

absl::Status WritePng(const fs::path& path, const cv::Mat& image) {
  return cv::imwrite(path.string(), image)
             ? absl::OkStatus()
             : absl::PermissionDeniedError(absl::StrCat("cannot write ", path.string()));
}

}  // namespace

absl::Status PrepareOut(const std::string& out) {
  std::error_code ec;
  fs::create_directories(out, ec);
  if (ec)
    return absl::PermissionDeniedError(absl::StrCat("cannot create ", out, ": ", ec.message()));
  return absl::OkStatus();
}

int FinishStudy(const CliContext& ctx, const fs::path& out,
                const std::vector<std::pair<std::string, std::string>>& texts,
                const std::vector<std::pair<std::string, cv::Mat>>& pngs, const json& summary,
                const std::string& report) {
  for (const auto& [name, text] : texts) {
    if (auto s = WriteText(out / name, text); !s.ok()) return Fail(s);
  }
  for (const auto& [name, png] : pngs) {
    if (auto s = WritePng(out / name, png); !s.ok()) return Fail(s);
  }
  for (auto s : {WriteText(out / "summary.json", summary.dump(2) + "\n"),
                 WriteText(out / "report.md", report)}) {
    if (!s.ok()) return Fail(s);
  }
  if (ctx.json) {
    std::cout << summary.dump() << "\n";
  } else {
    std::cout << report;
  }
  return 0;
}

void AddEvalCommands(CLI::App* app, CliContext* ctx) {
  auto* ev = app->add_subcommand("eval", "Run the papers' experiments locally on datasets");
  ev->require_subcommand(1);
  auto a = std::make_shared<EvalArgs>();
  auto common = [a](CLI::App* cmd, bool data_required) {
    auto* data =
        cmd->add_option("--data", a->data,
                        "folder of labelled organized .pcd files (mOSD), or for entropy-features "
                        "a synthetic visit (lifemap sim visit_NN, its moved/ masks)")
            ->check(CLI::ExistingDirectory);
    if (data_required) data->required();
    cmd->add_option("--out", a->out, "output folder (created)")->required();
    cmd->add_option("--k", a->k, "superjut scale k (paper: 0.6)")->check(CLI::Range(0.01, 100.0));
    cmd->add_option("--downsample", a->downsample, "working resolution 1/N (default 1)")
        ->check(CLI::Range(1, 8));
    cmd->add_option("--fuse", a->fuse,
                    "TUM/synthetic folders: fuse each frame's depth with N neighbours on either "
                    "side using the ground-truth poses (a multi-frame reconstruction; pair "
                    "with --mesh for the paper's mesh variant)")
        ->check(CLI::Range(0, 30));
    cmd->add_option("--frame-stride", a->frame_stride,
                    "TUM/synthetic folders: use every N-th frame (default 4)")
        ->check(CLI::Range(1, 1000));
    cmd->add_flag("--mesh", a->mesh,
                  "the paper's mesh variant (organized-mesh vertex normals and triangle edges) "
                  "instead of the image-domain one");
  };
  auto* features = ev->add_subcommand(
      "entropy-features", "Paper 000 Fig. 6: which superjut features tell moved from static");
  common(features, true);
  features
      ->add_option("--moved", a->moved,
                   "synthetic visits: ground truth of what moved, exact (moved/) or eq3 "
                   "(eq. 3 on the aligned depth maps, as the paper)")
      ->check(CLI::IsMember({"exact", "eq3"}));
  features->callback([ctx, a] { ctx->run = [ctx, a] { return RunFeatures(*ctx, *a); }; });
  auto* matching = ev->add_subcommand(
      "entropy-matching",
      "Paper 000 Figs. 9-10: match precision/recall as neg-entropy masks prune keypoints; a "
      "second --data set reuses the first set's threshold");
  common(matching, false);
  auto* tum_a = matching->add_option("--a", a->tum_a, "TUM-format folder of one visit")
                    ->check(CLI::ExistingDirectory);
  auto* tum_b = matching
                    ->add_option("--b", a->tum_b,
                                 "TUM-format folder of another visit "
                                 "(or the same folder: frames far apart)")
                    ->check(CLI::ExistingDirectory);
  tum_a->needs(tum_b);
  tum_b->needs(tum_a);

  matching
      ->add_option("--min-gap", a->min_gap,
                   "TUM, same folder: pair frames at least N frames apart (default 8)")
      ->check(CLI::Range(1, 100000));
  matching->add_option("--keypoints", a->keypoints, "sift | orb")
      ->check(CLI::IsMember({"sift", "orb"}));
  matching->add_option("--min-recall", a->min_recall, "recall the best threshold keeps")
      ->check(CLI::Range(0.0, 1.0));
  matching->add_option("--ransac-iterations", a->iterations, "RANSAC iterations for F")
      ->check(CLI::Range(100, 1000000));
  matching->callback([ctx, a] { ctx->run = [ctx, a] { return RunMatching(*ctx, *a); }; });
  AddForestCommands(app, ev, ctx);
  AddPlaceEvalCommand(ev, ctx);
  AddAppearanceEvalCommand(ev, ctx);
  AddTrajectoryEvalCommand(ev, ctx);
  AddAlignmentEvalCommand(ev, ctx);
  AddChangesEvalCommand(ev, ctx);
  AddRetentionEvalCommand(ev, ctx);
  AddMapEvalCommand(ev, ctx);
}

}  // namespace lifemap::cli
