#include "core/eval/appearance_study.h"

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <mutex>
#include <random>

#include <opencv2/imgcodecs.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/io/labeled_pcd.h"
#include "core/io/tum_dataset.h"
#include "core/place/descriptor.h"
#include "core/sim/world.h"

namespace lifemap::eval {
namespace fs = std::filesystem;

namespace {

using features::KeypointSet;
constexpr size_t kVariants = kFeatureVariants.size();

// The entropy mask of a decoded frame (empty when it cannot be computed: nothing pruned).
cv::Mat EntropyMask(const RgbdFrame& f, const AppearanceStudyOptions& options) {
  auto mask = entropy::ComputeEntropyMask(
      f.depth_m, f.color_bgr, f.intrinsics,
      pipeline::UpInCamera(f.T_world_camera, Eigen::Vector3f::UnitZ()), options.entropy);
  return mask.ok() ? mask->mask : cv::Mat();
}

// The four feature sets of a view: pruned by the entropy mask, all, the same number dropped at
// random, and those on movable objects dropped (unpruned when there is no movable mask).
std::array<KeypointSet, kVariants> Variants(const KeypointSet& all, const cv::Mat& entropy_mask,
                                            const cv::Mat& movable, uint64_t seed) {
  std::array<KeypointSet, kVariants> out;
  out[0] = features::PruneByMask(all, entropy_mask);
  out[1] = all;
  std::vector<bool> keep(all.size(), true);
  std::vector<size_t> order(all.size());
  for (size_t i = 0; i < order.size(); ++i) order[i] = i;
  std::mt19937_64 rng(seed);
  std::shuffle(order.begin(), order.end(), rng);
  for (int i = 0; i < out[0].masked && i < static_cast<int>(order.size()); ++i) {
    keep[order[static_cast<size_t>(i)]] = false;
  }
  out[2] = features::Select(all, keep);
  out[3] = features::PruneByMask(all, movable);
  return out;
}

RealView MakeView(const std::string& name, const RgbdFrame& f, const cv::Mat& movable,
                  const AppearanceStudyOptions& options) {
  RealView v;
  v.name = name;
  v.all = features::ExtractOrb(f.color_bgr, options.features.orb);
  features::AttachPoints(f.depth_m, f.intrinsics, &v.all);
  v.entropy_mask = EntropyMask(f, options);
  v.movable = movable;
  v.intrinsics = f.intrinsics;
  return v;
}

// The movable-object mask of a synthetic frame from its class labels (chairs and the props
// that move between visits), or empty without the label image.
cv::Mat SimMovable(const fs::path& visit_dir, const std::string& rgb_path) {
  const fs::path labels = visit_dir / "labels" / "class" / fs::path(rgb_path).filename();
  cv::Mat classes = cv::imread(labels.string(), cv::IMREAD_UNCHANGED);
  if (classes.empty() || classes.type() != CV_8UC1) return cv::Mat();
  cv::Mat movable(classes.size(), CV_8UC1, cv::Scalar(0));
  for (int r = 0; r < classes.rows; ++r) {
    for (int c = 0; c < classes.cols; ++c) {
      const auto k = static_cast<sim::SemanticClass>(classes.at<uint8_t>(r, c));
      if (sim::MovableClass(k)) movable.at<uint8_t>(r, c) = 255;
    }
  }
  return movable;
}

struct VisitKeyframes {
  std::vector<std::array<KeypointSet, kVariants>> sets;
  std::vector<Pose> poses;
  std::vector<CameraIntrinsics> intrinsics;
  std::vector<double> timestamps;
  int detected = 0, pruned = 0;
};

absl::StatusOr<VisitKeyframes> ExtractVisit(const fs::path& dir,
                                            const AppearanceStudyOptions& options, uint64_t seed) {
  auto seq = io::ReadTumSequence(dir.string());
  if (!seq.ok()) return seq.status();
  tracking::KeyframeSelector selector(options.places.keyframes);
  VisitKeyframes out;
  for (const auto& e : seq->frames) {
    if (!e.T_world_camera || !selector.Decide(e.timestamp_s, e.T_world_camera).selected) continue;
    selector.Accept(e.timestamp_s, e.T_world_camera);
    auto f = io::DecodeTumFrame(*seq, e);
    if (!f.ok()) return f.status();
    const RealView v = MakeView(e.rgb_path, *f, SimMovable(dir, e.rgb_path), options);
    out.sets.push_back(Variants(v.all, v.entropy_mask, v.movable, seed + out.sets.size()));
    out.detected += v.all.detected;
    out.pruned += out.sets.back()[0].masked;
    out.poses.push_back(*e.T_world_camera);
    out.intrinsics.push_back(f->intrinsics);
    out.timestamps.push_back(e.timestamp_s);
  }
  return out;
}

// A vocabulary and an index over `gallery` (descriptors of each entry's feature set).
struct GalleryIndex {
  std::unique_ptr<appearance::Vocabulary> vocabulary;
  std::unique_ptr<appearance::InvertedIndex> index;
};
absl::StatusOr<GalleryIndex> IndexGallery(const std::vector<const KeypointSet*>& gallery,
                                          const std::vector<appearance::KeyframeRef>& refs,
                                          const AppearanceStudyOptions& options) {
  std::vector<cv::Mat> training;
  for (const auto* k : gallery) {
    if (!k->descriptors.empty()) training.push_back(k->descriptors);
  }
  auto vocabulary = appearance::Vocabulary::Train(training, options.vocabulary);
  if (!vocabulary.ok()) return vocabulary.status();
  GalleryIndex g;
  g.vocabulary = std::make_unique<appearance::Vocabulary>(*std::move(vocabulary));
  g.index = std::make_unique<appearance::InvertedIndex>(g.vocabulary->words());
  for (size_t i = 0; i < gallery.size(); ++i) {
    if (gallery[i]->size() == 0) continue;
    auto bow = g.vocabulary->Transform(gallery[i]->descriptors);
    if (!bow.ok()) return bow.status();
    g.index->Add(refs[i], *bow);
  }
  return g;
}

double Median(std::vector<double> v) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

// The best score per place (map_id) among a recognition's verified matches.
std::map<int64_t, double> BestPerPlace(const appearance::Recognition& r) {
  std::map<int64_t, double> best;
  for (const auto& m : r.matches) {
    double& b = best[m.keyframe.map_id];
    b = std::max(b, m.verification.score);
  }
  return best;
}

// The method's summary (SummariseTrials) and its recall at precision 1 per subset.
void FillSubsetMetrics(AppearanceMethod* m, double threshold) {
  SummariseTrials(threshold, &m->result);
  for (int k = 0; k < 8; ++k) {
    double best = 0;
    for (int step = 0; step <= 200; ++step) {
      const PrPoint p = EvaluateTrials(m->result.trials, step / 200.0, k + 1);
      if (p.precision >= 1.0) best = std::max(best, p.recall);
    }
    m->recall_at_full_precision[static_cast<size_t>(k)] = best;
  }
}

}  // namespace

absl::StatusOr<AppearanceStudy> RunAppearanceStudy(
    const std::string& suite_dir, const AppearanceStudyOptions& options,
    const std::function<void(const std::string&)>& progress) {
  const auto start = std::chrono::steady_clock::now();
  const fs::path root(suite_dir);
  AppearanceStudy study;
  auto visits = ReadSuiteManifest(suite_dir);
  if (!visits.ok()) return visits.status();
  study.visits = *std::move(visits);
  std::map<std::string, int64_t> place_ids;
  for (const auto& v : study.visits) place_ids.emplace(v.place_id, place_ids.size() + 1);

  // Every visit's keyframes and features, and its floor plan (architecture), in parallel.
  std::vector<VisitKeyframes> extracted(study.visits.size());
  std::mutex mu;
  absl::Status failed;
  size_t done = 0;
  // The floor plans only: the place study's ORB baseline is not needed here (0 keyframes kept
  // for it, so no colour is decoded for the fold).
  PlaceStudyOptions fold_options = options.places;
  fold_options.appearance_keyframes = 0;
  ParallelFor(study.visits.size(), options.threads, [&](size_t i) {
    SuiteVisit& v = study.visits[i];
    auto k = ExtractVisit(root / v.path, options, options.seed + 1000 * i);
    auto folded = FoldVisit((root / v.path).string(), fold_options);
    std::lock_guard<std::mutex> lock(mu);
    if (!k.ok() || !folded.ok()) {
      if (failed.ok()) failed = !k.ok() ? k.status() : folded.status();
      return;
    }
    extracted[i] = *std::move(k);
    v.folded = *std::move(folded);
    ++done;
    if (progress) {
      progress(absl::StrFormat("[%d/%d] %s: %d keyframes, %d of %d keypoints pruned", done,
                               study.visits.size(), v.path, extracted[i].sets.size(),
                               extracted[i].pruned, extracted[i].detected));
    }
  });
  if (!failed.ok()) return failed;

  // Keyframes numbered over the suite; references make the gallery.
  std::vector<size_t> refs, queries;             // into study.keyframes
  std::vector<std::pair<size_t, size_t>> where;  // keyframe -> (visit, index in visit)
  int64_t detected = 0, pruned = 0;
  for (size_t vi = 0; vi < study.visits.size(); ++vi) {
    detected += extracted[vi].detected;
    pruned += extracted[vi].pruned;
    for (size_t k = 0; k < extracted[vi].sets.size(); ++k) {
      const bool reference = study.visits[vi].role == "reference";
      if (!reference && k % static_cast<size_t>(std::max(1, options.query_stride)) != 0) continue;
      (reference ? refs : queries).push_back(study.keyframes.size());
      study.keyframes.push_back({vi, extracted[vi].timestamps[k]});
      where.emplace_back(vi, k);
    }
  }
  study.reference_keyframes = static_cast<int>(refs.size());
  study.query_keyframes = static_cast<int>(queries.size());
  study.pruned_share = detected > 0 ? static_cast<double>(pruned) / detected : 0.0;
  auto set_of = [&](size_t keyframe, size_t variant) -> const KeypointSet& {
    return extracted[where[keyframe].first].sets[where[keyframe].second][variant];
  };
  auto place_of = [&](size_t keyframe) {
    return place_ids.at(study.visits[where[keyframe].first].place_id);
  };
  std::map<int64_t, std::string> place_names;
  for (const auto& [name, id] : place_ids) place_names[id] = name;

  // Architecture: each query visit's plan against each reference visit's; per place the best.
  auto architecture_best = [&](size_t query_visit, bool own_place) {
    std::map<int64_t, double> best;
    const SuiteVisit& q = study.visits[query_visit];
    for (const auto& r : study.visits) {
      if (r.role != "reference" || (!own_place && r.place_id == q.place_id)) continue;
      double score = 0;
      if (q.folded.plan_status.ok() && r.folded.plan_status.ok()) {
        score = place::MatchDescriptors(q.folded.descriptor, r.folded.descriptor,
                                        options.places.weights)
                    .score;
      }
      double& b = best[place_ids.at(r.place_id)];
      b = std::max(b, score);
    }
    return best;
  };
  auto trial_from = [&](size_t keyframe, bool known, const std::map<int64_t, double>& scores) {
    RecognitionTrial t;
    t.query = keyframe;
    const SuiteVisit& v = study.visits[where[keyframe].first];
    t.subset = v.subset;
    t.known = known;
    double best = 0;
    for (const auto& [place, score] : scores) {
      if (score > best) best = score, t.predicted = place_names[place];
    }
    t.score = best;
    t.correct = known && !t.predicted.empty() && t.predicted == v.place_id;
    return t;
  };

  // Per variant: vocabulary and index on the references, each query recognised twice.
  std::vector<std::array<std::map<int64_t, double>, 2>> pruned_scores(queries.size());
  for (size_t variant = 0; variant < kVariants; ++variant) {
    std::vector<const KeypointSet*> gallery;
    std::vector<appearance::KeyframeRef> gallery_refs;
    for (size_t k : refs) {
      gallery.push_back(&set_of(k, variant));
      gallery_refs.push_back({place_of(k), static_cast<int64_t>(where[k].first),
                              static_cast<int64_t>(k), study.keyframes[k].timestamp_s});
    }
    auto g = IndexGallery(gallery, gallery_refs, options);
    if (!g.ok()) return g.status();
    const appearance::FeatureLoader load = [&](const appearance::KeyframeRef& r) {
      return absl::StatusOr<KeypointSet>(set_of(static_cast<size_t>(r.keyframe_id), variant));
    };
    AppearanceMethod& method = study.methods[kFeatureVariants[variant]];
    method.result.name = kFeatureVariants[variant];
    std::vector<std::array<RecognitionTrial, 2>> trials(queries.size());
    std::vector<std::optional<std::pair<double, double>>> pose_errors(queries.size());
    double keypoints = 0;
    ParallelFor(queries.size(), options.threads, [&](size_t qi) {
      const size_t k = queries[qi];
      const KeypointSet& q = set_of(k, variant);
      const auto& [vi, index_in_visit] = where[k];
      const int64_t own = place_of(k);
      for (int pass = 0; pass < 2; ++pass) {
        const bool known = pass == 0;
        auto r = appearance::Recognize(
            q, extracted[vi].intrinsics[index_in_visit], *g->vocabulary, *g->index, load,
            [&](const appearance::KeyframeRef& ref) { return !known && ref.map_id == own; },
            options.recognizer);
        std::map<int64_t, double> scores;
        if (r.ok()) scores = BestPerPlace(*r);
        trials[qi][static_cast<size_t>(pass)] = trial_from(k, known, scores);
        if (variant == 0) pruned_scores[qi][static_cast<size_t>(pass)] = scores;
        if (known && r.ok() && !r->matches.empty() && r->matches[0].keyframe.map_id == own) {
          // The verified pose against the ground truth (visits of a place share its frame).
          const auto& best = r->matches[0];
          const size_t m = static_cast<size_t>(best.keyframe.keyframe_id);
          const Pose& Tm = extracted[where[m].first].poses[where[m].second];
          const Pose& Tq = extracted[vi].poses[index_in_visit];
          const Eigen::Isometry3d truth = Tm.ToIsometry().inverse() * Tq.ToIsometry();
          const Eigen::Isometry3d error =
              truth.inverse() * best.verification.T_match_query.ToIsometry();
          pose_errors[qi] = std::make_pair(100.0 * error.translation().norm(),
                                           Eigen::AngleAxisd(error.linear()).angle() * 180 / M_PI);
        }
      }
    });
    std::vector<double> cm, deg;
    for (size_t qi = 0; qi < queries.size(); ++qi) {
      method.result.trials.push_back(trials[qi][0]);
      method.result.trials.push_back(trials[qi][1]);
      keypoints += static_cast<double>(set_of(queries[qi], variant).size());
      if (pose_errors[qi]) {
        cm.push_back(pose_errors[qi]->first);
        deg.push_back(pose_errors[qi]->second);
      }
    }
    method.pose_error_cm = Median(cm);
    method.pose_error_deg = Median(deg);
    method.poses_compared = static_cast<int>(cm.size());
    method.mean_keypoints = queries.empty() ? 0 : keypoints / static_cast<double>(queries.size());
    auto t = options.thresholds.find(method.result.name);
    FillSubsetMetrics(&method, t != options.thresholds.end() ? t->second : -1);
    if (progress) {
      progress(absl::StrFormat("%s: F1 %.3f at %.3f", method.result.name,
                               method.result.operating.f1, method.result.operating.threshold));
    }
  }
  // Architecture alone, and fused with the pruned appearance scores.
  AppearanceMethod& arch = study.methods["architecture"];
  AppearanceMethod& fused = study.methods["fused"];
  arch.result.name = "architecture";
  fused.result.name = "fused";
  for (size_t qi = 0; qi < queries.size(); ++qi) {
    const size_t k = queries[qi];
    for (int pass = 0; pass < 2; ++pass) {
      const bool known = pass == 0;
      const auto a = architecture_best(where[k].first, known);
      arch.result.trials.push_back(trial_from(k, known, a));
      std::map<int64_t, double> f;
      for (const auto& [place, score] : a) f[place] += 0.5 * score;
      for (const auto& [place, score] : pruned_scores[qi][static_cast<size_t>(pass)]) {
        f[place] += 0.5 * score;
      }
      fused.result.trials.push_back(trial_from(k, known, f));
    }
  }
  for (auto* m : {&arch, &fused}) {
    auto t = options.thresholds.find(m->result.name);
    FillSubsetMetrics(m, t != options.thresholds.end() ? t->second : -1);
  }
  study.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return study;
}

std::map<std::string, std::vector<RealTrial>> RecogniseRealViews(
    const std::vector<RealView>& gallery, const std::vector<RealView>& queries,
    bool exclude_same_index, const AppearanceStudyOptions& options) {
  std::map<std::string, std::vector<RealTrial>> out;
  const bool oracle = std::all_of(gallery.begin(), gallery.end(),
                                  [](const RealView& v) { return !v.movable.empty(); }) &&
                      std::all_of(queries.begin(), queries.end(),
                                  [](const RealView& v) { return !v.movable.empty(); });
  auto variants_of = [&](const std::vector<RealView>& views, uint64_t seed) {
    std::vector<std::array<KeypointSet, kVariants>> sets;
    for (size_t i = 0; i < views.size(); ++i) {
      sets.push_back(Variants(views[i].all, views[i].entropy_mask, views[i].movable, seed + i));
    }
    return sets;
  };
  const auto g = variants_of(gallery, options.seed);
  const auto q = variants_of(queries, options.seed + 100000);
  for (size_t variant = 0; variant < kVariants; ++variant) {
    if (variant == 3 && !oracle) continue;
    std::vector<const KeypointSet*> sets;
    std::vector<appearance::KeyframeRef> refs;
    for (size_t i = 0; i < g.size(); ++i) {
      sets.push_back(&g[i][variant]);
      refs.push_back({1, 1, static_cast<int64_t>(i), 0.0});
    }
    auto index = IndexGallery(sets, refs, options);
    if (!index.ok()) continue;
    const appearance::FeatureLoader load = [&](const appearance::KeyframeRef& r) {
      return absl::StatusOr<KeypointSet>(g[static_cast<size_t>(r.keyframe_id)][variant]);
    };
    auto& trials = out[kFeatureVariants[variant]];
    trials.resize(queries.size());
    ParallelFor(queries.size(), options.threads, [&](size_t i) {
      RealTrial& t = trials[i];
      t.query = queries[i].name;
      auto r = appearance::Recognize(
          q[i][variant], queries[i].intrinsics, *index->vocabulary, *index->index, load,
          [&](const appearance::KeyframeRef& ref) {
            return exclude_same_index && static_cast<size_t>(ref.keyframe_id) == i;
          },
          options.recognizer);
      if (!r.ok() || r->matches.empty()) return;
      t.best = gallery[static_cast<size_t>(r->matches[0].keyframe.keyframe_id)].name;
      t.score = r->matches[0].verification.score;
      t.inliers = r->matches[0].verification.inliers;
    });
  }
  return out;
}

absl::StatusOr<std::vector<RealView>> ReadMosdViews(const std::string& dir,
                                                    const AppearanceStudyOptions& options) {
  std::vector<std::string> paths;
  for (const char* sub : {"learn", "test"}) {
    std::error_code ec;
    for (const auto& e : fs::directory_iterator(fs::path(dir) / sub, ec)) {
      if (e.path().extension() == ".pcd") paths.push_back(e.path().string());
    }
  }
  if (paths.empty()) {
    return absl::NotFoundError(absl::StrCat(dir, ": no learn/*.pcd or test/*.pcd (mOSD)"));
  }
  std::sort(paths.begin(), paths.end());
  std::vector<RealView> views(paths.size());
  absl::Status failed;
  std::mutex mu;
  ParallelFor(paths.size(), options.threads, [&](size_t i) {
    auto f = io::ReadLabeledPcd(paths[i]);
    if (!f.ok()) {
      std::lock_guard<std::mutex> lock(mu);
      failed = f.status();
      return;
    }
    cv::Mat objects = io::MosdTableObjectClasses(f->labels);
    cv::Mat movable = objects == 1;
    views[i] = MakeView(fs::path(paths[i]).stem().string(), f->frame, movable, options);
  });
  if (!failed.ok()) return failed;
  return views;
}

absl::StatusOr<std::vector<RealView>> ReadTumViews(const std::string& dir,
                                                   const AppearanceStudyOptions& options) {
  auto seq = io::ReadTumSequence(dir);
  if (!seq.ok()) return seq.status();
  tracking::KeyframeSelector selector(options.places.keyframes);
  std::vector<RealView> views;
  for (const auto& e : seq->frames) {
    if (!selector.Decide(e.timestamp_s, e.T_world_camera).selected) continue;
    selector.Accept(e.timestamp_s, e.T_world_camera);
    auto f = io::DecodeTumFrame(*seq, e);
    if (!f.ok()) return f.status();
    views.push_back(MakeView(fs::path(e.rgb_path).stem().string(), *f, cv::Mat(), options));
  }
  return views;
}

}  // namespace lifemap::eval
