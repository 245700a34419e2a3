// `lifemap train` and `lifemap eval segmentation`: the random-forest labeller of paper 002,
// trained and evaluated locally on labelled data (mOSD .pcd folders or synthetic visits).
#include <chrono>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iostream>

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

struct TrainArgs {
  std::vector<std::string> data;
  std::string out;
  int trees = 3, depth = 20, pixels = 2000, candidates = 2000, stride = 10;
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

int RunEvalSegmentation(const CliContext& ctx, const EvalArgs& a) {
  auto bytes = ReadFileBytes(a.model);
  if (!bytes.ok()) return Fail(bytes.status());
  forest::ModelDescription description;
  auto model = forest::Forest::Deserialize(*bytes, &description);
  if (!model.ok()) return Fail(model.status());
  const std::vector<std::string>& names = description.class_names;
  auto data = ReadData(a.data, a.frame_stride, a.sim_classes);
  if (!data.ok()) return Fail(data.status());
  if (data->class_names != names) {
    return Fail(absl::FailedPreconditionError(
        absl::StrCat("the model's classes [", absl::StrJoin(names, ", "), "] are not the data's [",
                     absl::StrJoin(data->class_names, ", "),
                     "]: evaluate on data of the kind it was trained on (or retrain)")));
  }
  // Scores a labeller over the data: pixels with a label and a depth reading count.
  const size_t n = names.size();
  auto score = [&](const std::function<absl::StatusOr<cv::Mat>(const forest::LabeledImage&)>& label)
      -> absl::StatusOr<json> {
    std::vector<std::vector<int64_t>> confusion(n, std::vector<int64_t>(n, 0));
    for (const auto& im : data->images) {
      auto predicted = label(im);
      if (!predicted.ok()) return predicted.status();
      for (int r = 0; r < im.labels.rows; ++r) {
        for (int c = 0; c < im.labels.cols; ++c) {
          const uint8_t truth = im.labels.at<uint8_t>(r, c);
          const uint8_t guess = predicted->at<uint8_t>(r, c);
          if (truth == forest::kIgnore || guess == forest::kIgnore || truth >= n || guess >= n) {
            continue;
          }
          ++confusion[truth][guess];
        }
      }
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
  if (!a.out.empty()) {
    std::error_code ec;
    fs::create_directories(a.out, ec);
    std::ofstream(fs::path(a.out) / "summary.json") << summary.dump(2) << "\n";
  }
  if (ctx.json) {
    std::cout << summary.dump() << "\n";
    return 0;
  }
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

}  // namespace

void AddForestCommands(CLI::App* app, CLI::App* eval, CliContext* ctx) {
  auto* train = app->add_subcommand(
      "train", "Train the random-forest labeller (paper 002) on labelled data, locally");
  auto t = std::make_shared<TrainArgs>();
  train->add_option("--data", t->data, "mOSD .pcd folders or lifemap sim visit folders")
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
  train->add_option("--seed", t->seed, "seed");
  train
      ->add_option("--sim-classes", t->sim_classes,
                   "synthetic visits: 'grouped' (structure, furniture, prop, person; default) or "
                   "'all' 18 classes")
      ->check(CLI::IsMember({"grouped", "all"}));
  train->callback([ctx, t] { ctx->run = [ctx, t] { return RunTrain(*ctx, *t); }; });

  auto* seg = eval->add_subcommand(
      "segmentation", "Paper 002's tables: accuracy, precision, recall of a model on data");
  auto e = std::make_shared<EvalArgs>();
  seg->add_option("--model", e->model, "model file (lifemap train)")
      ->required()
      ->check(CLI::ExistingFile);
  seg->add_option("--data", e->data, "mOSD .pcd folders or lifemap sim visit folders")
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
}

}  // namespace lifemap::cli
