// `lifemap train`, `lifemap eval segmentation` and `lifemap eval fusion`: the random-forest
// labeller of paper 002 and its semantic octree, trained and evaluated locally on labelled data
// (mOSD .pcd folders, synthetic visits, TUM-format folders with label PNGs).
#include <algorithm>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iostream>
#include <map>

#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "client/cli/commands.h"
#include "client/cli/output.h"
#include "core/common/image_codec.h"
#include "core/forest/baselines.h"
#include "core/forest/forest.h"
#include "core/forest/labeled_data.h"
#include "core/io/labeled_pcd.h"
#include "core/semantic/semantic_map.h"
#include "core/sim/world.h"

namespace lifemap::cli {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

absl::StatusOr<forest::LabeledDataset> ReadData(const std::vector<std::string>& dirs,
                                                int frame_stride, const std::string& sim_classes) {
  forest::LabeledDataOptions o;
  o.frame_stride = frame_stride;
  o.sim_classes = sim_classes == "all" ? forest::SimClasses::kAll : forest::SimClasses::kGrouped;
  return forest::ReadLabeledData(dirs, o);
}

absl::StatusOr<forest::Forest> LoadModel(const std::string& path,
                                         forest::ModelDescription* description) {
  auto bytes = ReadFileBytes(path);
  if (!bytes.ok()) return bytes.status();
  return forest::Forest::Deserialize(*bytes, description);
}

absl::Status SameClasses(const std::vector<std::string>& names,
                         const forest::LabeledDataset& data) {
  if (data.class_names == names) return absl::OkStatus();
  return absl::FailedPreconditionError(
      absl::StrCat("the model's classes [", absl::StrJoin(names, ", "), "] are not the data's [",
                   absl::StrJoin(data.class_names, ", "),
                   "]: evaluate on data of the kind it was trained on (or retrain)"));
}

// Writes OUT/summary.json when `out` is set; with --json prints the summary and returns true
// (the caller prints nothing more).
bool WriteSummary(const CliContext& ctx, const std::string& out, const json& summary) {
  if (!out.empty()) {
    std::error_code ec;
    fs::create_directories(out, ec);
    std::ofstream(fs::path(out) / "summary.json") << summary.dump(2) << "\n";
  }
  if (ctx.json) std::cout << summary.dump() << "\n";
  return ctx.json;
}

struct TrainArgs {
  std::vector<std::string> data;
  std::string out;
  int trees = 3, depth = 20, pixels = 2000, candidates = 2000, stride = 10;
  float max_offset = 80.0f, max_size = 40.0f, depth_share = 0.8f;
  bool global_balance = false;
  uint64_t seed = 1;
  std::string sim_classes = "grouped";
};

int RunTrain(const CliContext& ctx, const TrainArgs& a) {
  auto data = ReadData(a.data, a.stride, a.sim_classes);
  if (!data.ok()) return Fail(data.status());
  forest::TrainOptions o;
  o.trees = a.trees;
  o.max_depth = a.depth;
  o.pixels_per_image = a.pixels;
  o.candidates = a.candidates;
  o.max_offset = a.max_offset;
  o.max_size = a.max_size;
  o.depth_feature_share = a.depth_share;
  o.global_balance = a.global_balance;
  o.seed = a.seed;
  const auto start = std::chrono::steady_clock::now();
  o.progress = [&](int done, int total) {
    if (ctx.json) return;
    const double s =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    std::cerr << absl::StrFormat("  tree %d of %d trained (%.1f s)\n", done, total, s);
  };
  if (!ctx.json) {
    std::cerr << absl::StrFormat("training %d trees of depth <= %d on %d images...\n", a.trees,
                                 a.depth, data->images.size());
  }
  auto model = forest::Forest::Train(data->images, static_cast<int>(data->class_names.size()), o);
  if (!model.ok()) return Fail(model.status());
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  // The training summary travels in the model file: what it learned from and how.
  std::vector<int64_t> class_pixels(data->class_names.size(), 0);
  for (const auto& im : data->images) {
    for (size_t c = 0; c < class_pixels.size(); ++c) {
      class_pixels[c] += cv::countNonZero(im.labels == static_cast<int>(c));
    }
  }
  forest::ModelDescription description;
  description.class_names = data->class_names;
  description.class_colors = data->class_colors;
  description.training_json = json{{"data",
                                    {{"kind", data->kind},
                                     {"folders", data->sources},
                                     {"images", data->images.size()},
                                     {"frame_stride", a.stride},
                                     {"class_pixels", class_pixels}}},
                                   {"options",
                                    {{"trees", o.trees},
                                     {"max_depth", o.max_depth},
                                     {"min_samples", o.min_samples},
                                     {"pixels_per_image", o.pixels_per_image},
                                     {"candidates", o.candidates},
                                     {"max_offset", o.max_offset},
                                     {"max_size", o.max_size},
                                     {"depth_feature_share", o.depth_feature_share},
                                     {"global_balance", o.global_balance},
                                     {"seed", o.seed}}},
                                   {"nodes", model->node_count()},
                                   {"seconds", seconds},
                                   {"trained_by", "lifemap train " LIFEMAP_VERSION}}
                                  .dump();
  std::ofstream out(a.out, std::ios::binary);
  out << model->Serialize(description);
  if (!out) return Fail(absl::PermissionDeniedError(absl::StrCat("cannot write ", a.out)));
  json summary = {{"model", a.out},
                  {"images", data->images.size()},
                  {"classes", data->class_names},
                  {"nodes", model->node_count()},
                  {"seconds", seconds}};
  if (ctx.json) {
    std::cout << summary.dump() << "\n";
  } else {
    std::cout << absl::StrFormat("wrote %s: %d trees, %d nodes, %d classes, %.1f s\n", a.out,
                                 model->tree_count(), model->node_count(), data->class_names.size(),
                                 seconds);
  }
  return 0;
}

struct EvalArgs {
  std::string model;
  std::vector<std::string> data;
  std::vector<std::string> baseline_train;  // with it, the baselines run in the same evaluation
  std::string out;
  int stride = 2;
  int frame_stride = 10;
  std::string sim_classes = "grouped";
};

// The paper's tables: pixel accuracy, and precision and recall averaged over classes, with
// and without the background class (class 0), and per class.
json Scores(const std::vector<std::vector<int64_t>>& confusion,
            const std::vector<std::string>& names) {
  const size_t n = confusion.size();
  auto table = [&](size_t first) {
    int64_t correct = 0, total = 0;
    double precision = 0, recall = 0;
    int counted = 0;
    for (size_t c = first; c < n; ++c) {
      int64_t tp = confusion[c][c], predicted = 0, actual = 0;
      for (size_t o = 0; o < n; ++o) {
        predicted += confusion[o][c];
        actual += confusion[c][o];
      }
      correct += tp;
      total += actual;
      if (actual == 0) continue;
      precision += predicted > 0 ? static_cast<double>(tp) / predicted : 0.0;
      recall += static_cast<double>(tp) / actual;
      ++counted;
    }
    return std::make_tuple(total > 0 ? static_cast<double>(correct) / total : 0.0,
                           counted ? precision / counted : 0.0, counted ? recall / counted : 0.0);
  };
  const auto [accuracy, precision, recall] = table(0);
  const auto [accuracy_nb, precision_nb, recall_nb] = table(1);
  json per_class = json::object();
  for (size_t c = 0; c < n; ++c) {
    int64_t tp = confusion[c][c], predicted = 0, actual = 0;
    for (size_t o = 0; o < n; ++o) predicted += confusion[o][c], actual += confusion[c][o];
    if (actual == 0 && predicted == 0) continue;
    per_class[names[c]] = {{"precision", predicted ? static_cast<double>(tp) / predicted : 0.0},
                           {"recall", actual ? static_cast<double>(tp) / actual : 0.0},
                           {"pixels", actual}};
  }
  return {{"accuracy", accuracy},
          {"precision", precision},
          {"recall", recall},
          {"accuracy_no_bg", accuracy_nb},
          {"precision_no_bg", precision_nb},
          {"recall_no_bg", recall_nb},
          {"per_class", per_class}};
}

// Counts every pixel that has a class in both `truth` and `guess` (CV_8UC1; kIgnore, and ids
// beyond the matrix, are skipped) into a confusion matrix (rows: truth, columns: guess).
void Tally(const cv::Mat& truth, const cv::Mat& guess,
           std::vector<std::vector<int64_t>>* confusion) {
  const size_t n = confusion->size();
  for (int r = 0; r < truth.rows; ++r) {
    const uint8_t* t = truth.ptr<uint8_t>(r);
    const uint8_t* g = guess.ptr<uint8_t>(r);
    for (int c = 0; c < truth.cols; ++c) {
      if (t[c] >= n || g[c] >= n) continue;
      ++(*confusion)[t[c]][g[c]];
    }
  }
}

int RunEvalSegmentation(const CliContext& ctx, const EvalArgs& a) {
  forest::ModelDescription description;
  auto model = LoadModel(a.model, &description);
  if (!model.ok()) return Fail(model.status());
  const std::vector<std::string>& names = description.class_names;
  auto data = ReadData(a.data, a.frame_stride, a.sim_classes);
  if (!data.ok()) return Fail(data.status());
  if (auto c = SameClasses(names, *data); !c.ok()) return Fail(c);
  // Scores a labeller over the data: pixels with a label and a depth reading count.
  const size_t n = names.size();
  auto score = [&](const std::function<absl::StatusOr<cv::Mat>(const forest::LabeledImage&)>& label)
      -> absl::StatusOr<json> {
    std::vector<std::vector<int64_t>> confusion(n, std::vector<int64_t>(n, 0));
    for (const auto& im : data->images) {
      auto predicted = label(im);
      if (!predicted.ok()) return predicted.status();
      Tally(im.labels, *predicted, &confusion);
    }
    return Scores(confusion, names);
  };
  json result = json::object();
  for (auto decision : {forest::Decision::kBalanced, forest::Decision::kPriorWeighted}) {
    auto s = score([&](const forest::LabeledImage& im) -> absl::StatusOr<cv::Mat> {
      auto p = model->Predict(im.depth_m, im.color_bgr, decision, a.stride);
      if (!p.ok()) return p.status();
      return p->labels;
    });
    if (!s.ok()) return Fail(s.status());
    result[decision == forest::Decision::kBalanced ? "balanced" : "prior_weighted"] = *s;
  }
  json baselines = json::object();
  if (!a.baseline_train.empty()) {
    auto train = ReadData(a.baseline_train, a.frame_stride, a.sim_classes);
    if (!train.ok()) return Fail(train.status());
    auto trees = forest::PixelTreesBaseline::Train(train->images, static_cast<int>(n));
    if (!trees.ok()) return Fail(trees.status());
    auto s = score([&](const forest::LabeledImage& im) -> absl::StatusOr<cv::Mat> {
      return trees->Predict(im.depth_m, im.color_bgr, a.stride);
    });
    if (!s.ok()) return Fail(s.status());
    baselines["pixel_rtrees"] = *s;
    if (n == 2 && names[0] == "table") {
      // Table vs objects: a RANSAC plane and everything 1.5 cm above it.
      auto plane = score([&](const forest::LabeledImage& im) -> absl::StatusOr<cv::Mat> {
        return forest::PlaneBaseline(im.depth_m,
                                     io::KinectDefaultIntrinsics(im.depth_m.cols, im.depth_m.rows));
      });
      if (!plane.ok()) return Fail(plane.status());
      baselines["ransac_plane"] = *plane;
    }
  }
  json summary = result["balanced"];
  summary["prior_weighted"] = result["prior_weighted"];
  if (!baselines.empty()) summary["baselines"] = baselines;
  summary["model"] = a.model;
  summary["images"] = data->images.size();
  summary["stride"] = a.stride;
  if (WriteSummary(ctx, a.out, summary)) return 0;
  std::cout << absl::StrFormat("%d images, every %d-th pixel, background = %s\n",
                               data->images.size(), a.stride, names[0]);
  std::cout << absl::StrFormat("%-16s %9s %9s %9s   %s\n", "decision", "accuracy", "precision",
                               "recall", "(without background: accuracy precision recall)");
  json rows = result;
  for (const auto& [name, b] : baselines.items()) rows[name] = b;
  for (const auto& [d, s] : rows.items()) {
    std::cout << absl::StrFormat(
        "%-16s %9.3f %9.3f %9.3f   %.3f %.3f %.3f\n", d.c_str(), s["accuracy"].get<double>(),
        s["precision"].get<double>(), s["recall"].get<double>(), s["accuracy_no_bg"].get<double>(),
        s["precision_no_bg"].get<double>(), s["recall_no_bg"].get<double>());
  }
  for (const auto& [name, c] : result["balanced"]["per_class"].items()) {
    std::cout << absl::StrFormat("  %-14s precision %.3f recall %.3f (%d px)\n", name,
                                 c["precision"].get<double>(), c["recall"].get<double>(),
                                 c["pixels"].get<int64_t>());
  }
  return 0;
}

struct FusionArgs {
  std::string model;
  std::vector<std::string> data;
  std::string out;
  int stride = 2;
  int frame_stride = 5;
  std::string sim_classes = "grouped";
  semantic::SemanticMapOptions map;
};

// Scores as `eval fusion` reports them: precision and recall per class name (their means
// beside), the confusion matrix (rows: truth, columns: labels).
json FusionScores(const std::vector<std::vector<int64_t>>& confusion,
                  const std::vector<std::string>& names) {
  json s = Scores(confusion, names);
  json out = {{"accuracy", s["accuracy"]},
              {"accuracy_no_bg", s["accuracy_no_bg"]},
              {"mean_precision", s["precision"]},
              {"mean_recall", s["recall"]},
              {"mean_precision_no_bg", s["precision_no_bg"]},
              {"mean_recall_no_bg", s["recall_no_bg"]},
              {"precision", json::object()},
              {"recall", json::object()},
              {"pixels", json::object()},
              {"confusion", confusion}};
  for (const auto& [name, c] : s["per_class"].items()) {
    out["precision"][name] = c["precision"];
    out["recall"][name] = c["recall"];
    out["pixels"][name] = c["pixels"];
  }
  return out;
}

// Paper 002's Tables I-IV: per visit, every image is labelled alone (single), all of the
// visit's images are fused into a semantic octree at their ground-truth poses, and the octree's
// labels are rendered back into every image (fused; where the octree has no label the image's
// own label stands, and the share the octree labelled is reported as coverage).
int RunEvalFusion(const CliContext& ctx, const FusionArgs& a) {
  forest::ModelDescription description;
  auto model = LoadModel(a.model, &description);
  if (!model.ok()) return Fail(model.status());
  const std::vector<std::string>& names = description.class_names;
  if (auto s = a.map.Validate(); !s.ok()) return Fail(s);
  auto data = ReadData(a.data, a.frame_stride, a.sim_classes);
  if (!data.ok()) return Fail(data.status());
  if (auto c = SameClasses(names, *data); !c.ok()) return Fail(c);
  std::map<size_t, std::vector<size_t>> images_of;  // source -> image indices, in time order
  for (size_t i = 0; i < data->images.size(); ++i) {
    const forest::LabeledView& v = data->views[i];
    if (!v.T_world_camera) {
      return Fail(absl::FailedPreconditionError(absl::StrCat(
          data->sources[v.source],
          ": fusion needs every image's pose (a TUM-format folder with groundtruth.txt, e.g. a "
          "lifemap sim visit); this image has none")));
    }
    images_of[v.source].push_back(i);
  }
  const size_t n = names.size();
  using Confusion = std::vector<std::vector<int64_t>>;
  Confusion single(n, std::vector<int64_t>(n, 0)), prior = single, fused = single,
                                                   fused_only = single;
  std::vector<double> fuse_ms, render_ms;
  int64_t depth_pixels = 0, rendered_pixels = 0;
  json visits = json::array();
  for (const auto& [source, images] : images_of) {
    auto map = semantic::SemanticMap::Create(static_cast<int>(n), model->class_prior(), a.map);
    if (!map.ok()) return Fail(map.status());
    std::vector<cv::Mat> single_labels;
    for (size_t i : images) {
      const forest::LabeledImage& im = data->images[i];
      const forest::LabeledView& v = data->views[i];
      auto p = model->Predict(im.depth_m, im.color_bgr, forest::Decision::kBalanced, a.stride);
      if (!p.ok()) return Fail(p.status());
      auto pw =
          model->Predict(im.depth_m, im.color_bgr, forest::Decision::kPriorWeighted, a.stride);
      if (!pw.ok()) return Fail(pw.status());
      Tally(im.labels, p->labels, &single);
      Tally(im.labels, pw->labels, &prior);
      auto stats = (*map)->Fuse(im.depth_m, v.intrinsics, *v.T_world_camera, p->probabilities);
      if (!stats.ok()) {
        return Fail(absl::Status(stats.status().code(), absl::StrCat(data->sources[source], ": ",
                                                                     stats.status().message())));
      }
      fuse_ms.push_back(stats->ms);
      single_labels.push_back(p->labels);
    }
    for (size_t k = 0; k < images.size(); ++k) {
      const forest::LabeledImage& im = data->images[images[k]];
      const forest::LabeledView& v = data->views[images[k]];
      const auto start = std::chrono::steady_clock::now();
      auto r = (*map)->Render(im.depth_m, v.intrinsics, *v.T_world_camera, a.stride);
      render_ms.push_back(
          std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start)
              .count());
      if (!r.ok()) return Fail(r.status());
      Tally(im.labels, r->labels, &fused_only);
      cv::Mat labels = single_labels[k].clone();
      r->labels.copyTo(labels, r->labels != forest::kIgnore);
      Tally(im.labels, labels, &fused);
      depth_pixels += r->depth_pixels;
      rendered_pixels += r->labelled_pixels;
    }
    const semantic::SemanticSummary s = (*map)->Summarize();
    json volume = json::object();
    for (size_t c = 0; c < n; ++c) volume[names[c]] = s.class_volume_m3[c];
    visits.push_back({{"folder", data->sources[source]},
                      {"images", images.size()},
                      {"occupied_voxels", s.occupied_voxels},
                      {"labelled_voxels", s.labelled_voxels},
                      {"nodes", s.nodes},
                      {"memory_bytes", s.memory_bytes},
                      {"class_volume_m3", volume}});
  }
  json summary = {
      {"model", a.model},
      {"classes", names},
      {"images", data->images.size()},
      {"stride", a.stride},
      {"frame_stride", a.frame_stride},
      {"resolution_m", a.map.resolution_m},
      {"single", FusionScores(single, names)},
      {"single_prior_weighted", FusionScores(prior, names)},
      {"fused", FusionScores(fused, names)},
      {"fused_where_rendered", FusionScores(fused_only, names)},
      {"fused_coverage",
       depth_pixels > 0 ? static_cast<double>(rendered_pixels) / static_cast<double>(depth_pixels)
                        : 0.0},
      {"fusion_ms", {{"p50", Percentile(fuse_ms, 50)}, {"max", Percentile(fuse_ms, 100)}}},
      {"render_ms", {{"p50", Percentile(render_ms, 50)}, {"max", Percentile(render_ms, 100)}}},
      {"visits", visits}};
  summary["gain_no_bg"] = summary["fused"]["accuracy_no_bg"].get<double>() -
                          summary["single"]["accuracy_no_bg"].get<double>();
  summary["gain"] =
      summary["fused"]["accuracy"].get<double>() - summary["single"]["accuracy"].get<double>();
  if (WriteSummary(ctx, a.out, summary)) return 0;
  std::cout << absl::StrFormat(
      "%d images in %d visits, every %d-th pixel, %.3g m voxels; the octree labels %.1f %% of "
      "the depth pixels\n",
      data->images.size(), images_of.size(), a.stride, a.map.resolution_m,
      100.0 * summary["fused_coverage"].get<double>());
  std::cout << absl::StrFormat("%-22s %9s %9s   per class recall / precision\n", "labels",
                               "accuracy", "no bg");
  for (const char* row : {"single", "single_prior_weighted", "fused", "fused_where_rendered"}) {
    const json& s = summary[row];
    std::string per_class;
    for (const auto& [name, r] : s["recall"].items()) {
      per_class += absl::StrFormat("  %s %.2f/%.2f", name, r.get<double>(),
                                   s["precision"][name].get<double>());
    }
    std::cout << absl::StrFormat("%-22s %9.3f %9.3f %s\n", row, s["accuracy"].get<double>(),
                                 s["accuracy_no_bg"].get<double>(), per_class);
  }
  std::cout << absl::StrFormat(
      "gain without background: %+.3f; fusion %.1f ms (p50), render %.1f ms (p50)\n",
      summary["gain_no_bg"].get<double>(), Percentile(fuse_ms, 50), Percentile(render_ms, 50));
  return 0;
}

}  // namespace

void AddForestCommands(CLI::App* app, CLI::App* eval, CliContext* ctx) {
  auto* train = app->add_subcommand(
      "train", "Train the random-forest labeller (paper 002) on labelled data, locally");
  auto t = std::make_shared<TrainArgs>();
  train
      ->add_option("--data", t->data,
                   "mOSD .pcd folders, lifemap sim visit folders, or TUM folders with "
                   "labels/classes.txt and labels/NAME.png (8-bit class per pixel, 255 none)")
      ->required()
      ->check(CLI::ExistingDirectory);
  train->add_option("--out", t->out, "model file to write")->required();
  train->add_option("--trees", t->trees, "trees (default 3)")->check(CLI::Range(1, 64));
  train->add_option("--depth", t->depth, "maximum depth (default 20)")->check(CLI::Range(1, 40));
  train->add_option("--pixels", t->pixels, "training pixels per image, N (default 2000)")
      ->check(CLI::Range(10, 1000000));
  train->add_option("--candidates", t->candidates, "features tried per node, P (default 2000)")
      ->check(CLI::Range(1, 100000));
  train->add_option("--frame-stride", t->stride, "synthetic visits: every N-th frame (default 10)")
      ->check(CLI::Range(1, 1000));
  train
      ->add_option("--max-offset", t->max_offset,
                   "largest feature offset, pixels at 1 m depth (default 80)")
      ->check(CLI::Range(0.0f, 10000.0f));
  train
      ->add_option("--max-size", t->max_size,
                   "largest feature rectangle side, pixels at 1 m depth (default 40)")
      ->check(CLI::Range(1.0f, 10000.0f));
  train
      ->add_option("--depth-features", t->depth_share,
                   "share of features comparing depth, the rest colour (default 0.8)")
      ->check(CLI::Range(0.0f, 1.0f));
  train->add_flag("--global-balance", t->global_balance,
                  "weigh every class equally across all images, not only within each image");
  train->add_option("--seed", t->seed, "seed");
  train
      ->add_option("--sim-classes", t->sim_classes,
                   absl::StrCat("synthetic visits: 'grouped' (structure, furniture, prop, "
                                "person; default) or 'all' ",
                                sim::kClassCount - 1, " classes (every class of `lifemap sim`)"))
      ->check(CLI::IsMember({"grouped", "all"}));
  train->callback([ctx, t] { ctx->run = [ctx, t] { return RunTrain(*ctx, *t); }; });

  auto* seg = eval->add_subcommand(
      "segmentation", "Paper 002's tables: accuracy, precision, recall of a model on data");
  auto e = std::make_shared<EvalArgs>();
  seg->add_option("--model", e->model, "model file (lifemap train)")
      ->required()
      ->check(CLI::ExistingFile);
  seg->add_option("--data", e->data,
                  "mOSD .pcd folders, lifemap sim visit folders, or TUM folders with "
                  "labels/classes.txt and labels/NAME.png")
      ->required()
      ->check(CLI::ExistingDirectory);
  seg->add_option("--out", e->out, "folder for summary.json");
  seg->add_option("--baseline-train", e->baseline_train,
                  "training data for the baselines run in the same evaluation (OpenCV RTrees on "
                  "per-pixel depth and L*a*b*; and, for table vs objects, a RANSAC plane)")
      ->check(CLI::ExistingDirectory);
  seg->add_option("--stride", e->stride, "predict every N-th pixel (default 2)")
      ->check(CLI::Range(1, 16));
  seg->add_option("--frame-stride", e->frame_stride, "synthetic visits: every N-th frame")
      ->check(CLI::Range(1, 1000));
  seg->add_option("--sim-classes", e->sim_classes,
                  "synthetic visits: 'grouped' (default) or 'all'; as the model was trained")
      ->check(CLI::IsMember({"grouped", "all"}));
  seg->callback([ctx, e] { ctx->run = [ctx, e] { return RunEvalSegmentation(*ctx, *e); }; });

  auto* fusion = eval->add_subcommand(
      "fusion",
      "Paper 002's fusion tables: single-frame labels vs labels fused in a semantic octree and "
      "rendered back, per visit (needs ground-truth poses)");
  auto f = std::make_shared<FusionArgs>();
  fusion->add_option("--model", f->model, "model file (lifemap train)")
      ->required()
      ->check(CLI::ExistingFile);
  fusion->add_option("--data", f->data, "visit folders with poses (lifemap sim visits)")
      ->required()
      ->check(CLI::ExistingDirectory);
  fusion->add_option("--out", f->out, "folder for summary.json");
  fusion->add_option("--stride", f->stride, "label and render every N-th pixel (default 2)")
      ->check(CLI::Range(1, 16));
  fusion->add_option("--frame-stride", f->frame_stride, "every N-th frame of a visit (default 5)")
      ->check(CLI::Range(1, 1000));
  fusion->add_option("--sim-classes", f->sim_classes, "synthetic visits: 'grouped' or 'all'")
      ->check(CLI::IsMember({"grouped", "all"}));
  fusion->add_option("--resolution", f->map.resolution_m, "voxel edge, metres (default 0.05)");
  fusion->add_option("--uniform-mix", f->map.observation_uniform_mix,
                     "weight of a uniform distribution mixed into each observation (default 0.1)");
  fusion->add_option("--prior-weight", f->map.prior_weight,
                     "the training prior's weight in each voxel's initial belief, 0..1");
  fusion->add_option("--fuse-stride", f->map.pixel_stride, "every N-th pixel is fused (default 4)");
  fusion->callback([ctx, f] { ctx->run = [ctx, f] { return RunEvalFusion(*ctx, *f); }; });
}

}  // namespace lifemap::cli
