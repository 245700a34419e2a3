#include "core/eval/place_study.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <map>
#include <mutex>
#include <thread>

#include <nlohmann/json.hpp>
#include <opencv2/calib3d.hpp>
#include <opencv2/features2d.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/io/tum_dataset.h"

namespace lifemap::eval {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

Eigen::Vector2d Point(const json& j) { return {j.at(0).get<double>(), j.at(1).get<double>()}; }

// Runs job(i) for i in [0, n) on `threads` threads (0 = one per core).
}  // namespace

void ParallelFor(size_t n, int threads, const std::function<void(size_t)>& job) {
  const unsigned workers = std::max(
      1u, std::min<unsigned>(threads > 0 ? static_cast<unsigned>(threads)
                                         : std::max(1u, std::thread::hardware_concurrency()),
                             static_cast<unsigned>(n)));
  std::atomic<size_t> next{0};
  std::vector<std::thread> pool;
  for (unsigned w = 0; w < workers; ++w) {
    pool.emplace_back([&] {
      for (size_t i = next++; i < n; i = next++) job(i);
    });
  }
  for (auto& t : pool) t.join();
}

namespace {}  // namespace

absl::StatusOr<TruthPlan> ReadTruthPlan(const std::string& path) {
  std::ifstream in(path);
  if (!in) return absl::NotFoundError(absl::StrCat(path, ": cannot open (a lifemap sim visit?)"));
  TruthPlan t;
  try {
    json scene;
    in >> scene;
    t.place_id = scene.at("place_id").get<std::string>();
    t.shape = scene.at("shape").get<std::string>();
    const json& fp = scene.at("floor_plan");
    t.plan.up = Eigen::Vector3d::UnitZ(), t.plan.e1 = Eigen::Vector3d::UnitX();
    t.plan.e2 = Eigen::Vector3d::UnitY();
    for (const auto& w : fp.at("walls")) {
      place::Wall wall;
      wall.start = Point(w.at("start"));
      wall.end = Point(w.at("end"));
      t.plan.walls.push_back(wall);
    }
    for (const auto& o : fp.at("openings")) {
      if (o.value("room", 0) != 0) continue;  // in an adjoining room
      const bool door = o.at("type").get<std::string>() == "door";
      if (door && !o.at("open").get<bool>()) {
        ++t.closed_doors;
        continue;
      }
      const int w = o.at("wall").get<int>();
      if (w < 0 || w >= static_cast<int>(t.plan.walls.size())) {
        return absl::InvalidArgumentError(
            absl::StrCat(path, ": opening on wall ", w, " of ", t.plan.walls.size()));
      }
      place::WallOpening opening;
      opening.type = door ? place::OpeningType::kDoor : place::OpeningType::kWindow;
      opening.from_m = o.at("offset_m").get<double>();
      opening.to_m = opening.from_m + o.at("width_m").get<double>();
      opening.bottom_m = o.at("sill_m").get<double>();
      opening.top_m = o.at("top_m").get<double>();
      t.plan.walls[static_cast<size_t>(w)].openings.push_back(opening);
    }
    for (const auto& s : fp.at("stairs")) {
      place::StairFlight f;
      f.ascending = s.at("type").get<std::string>() == "up";
      f.steps = s.at("steps").get<int>();
      f.rise_m = s.at("rise_m").get<double>();
      f.length_m = s.at("length_m").get<double>();
      f.width_m = s.at("width_m").get<double>();
      const double yaw = s.at("yaw_rad").get<double>();
      f.center = Point(s.at("origin")) +
                 Eigen::Vector2d(std::cos(yaw), std::sin(yaw)) * (0.5 * f.length_m);
      f.distance_to_wall_m = s.at("centre_distance_to_nearest_wall_m").get<double>();
      t.plan.stairs.push_back(f);
    }
  } catch (const json::exception& e) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": not a lifemap scene: ", e.what()));
  }
  if (t.plan.walls.size() < 3) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": fewer than 3 walls"));
  }
  return t;
}

FloorPlanError CompareFloorPlans(const place::FloorPlan& built, const place::FloorPlan& truth) {
  FloorPlanError e;
  const size_t nt = truth.walls.size(), nb = built.walls.size();
  e.truth_walls = static_cast<int>(nt);
  e.built_walls = static_cast<int>(nb);
  struct Candidate {
    double overlap;
    size_t t, b;
  };
  std::vector<Candidate> cands;
  for (size_t t = 0; t < nt; ++t) {
    const place::Wall& tw = truth.walls[t];
    const Eigen::Vector2d dt = (tw.end - tw.start).normalized();
    const Eigen::Vector2d nrm(-dt.y(), dt.x());
    for (size_t b = 0; b < nb; ++b) {
      const place::Wall& bw = built.walls[b];
      if (bw.length() <= 0 || dt.dot((bw.end - bw.start).normalized()) < std::cos(M_PI / 18)) {
        continue;
      }
      if (std::abs(nrm.dot(0.5 * (bw.start + bw.end) - tw.start)) > 0.3) continue;
      const double s0 = dt.dot(bw.start - tw.start), s1 = dt.dot(bw.end - tw.start);
      const double overlap = std::min(s1, tw.length()) - std::max(s0, 0.0);
      if (overlap > 0.5 * std::min(tw.length(), bw.length())) cands.push_back({overlap, t, b});
    }
  }
  std::sort(cands.begin(), cands.end(),
            [](const Candidate& a, const Candidate& b) { return a.overlap > b.overlap; });
  std::vector<int> pair_of_truth(nt, -1), pair_of_built(nb, -1);
  for (const auto& c : cands) {
    if (pair_of_truth[c.t] >= 0 || pair_of_built[c.b] >= 0) continue;
    pair_of_truth[c.t] = static_cast<int>(c.b);
    pair_of_built[c.b] = static_cast<int>(c.t);
  }
  const place::PlaceDescriptor dt = place::Describe(truth), db = place::Describe(built);
  std::vector<std::vector<bool>> used(nb);
  for (size_t b = 0; b < nb; ++b) used[b].assign(built.walls[b].openings.size(), false);
  bool in_order = true;
  for (size_t t = 0; t < nt; ++t) {
    const place::Wall& tw = truth.walls[t];
    e.truth_openings += static_cast<int>(tw.openings.size());
    const int b = pair_of_truth[t];
    if (b < 0) {
      in_order = false;
      continue;
    }
    const place::Wall& bw = built.walls[static_cast<size_t>(b)];
    ++e.walls_found;
    e.pairs.push_back({static_cast<int>(t), b, tw.length(), bw.length()});
    e.length_errors_m.push_back(std::abs(bw.length() - tw.length()));
    const int next = pair_of_truth[(t + 1) % nt];
    if (next >= 0 && static_cast<size_t>(next) == (static_cast<size_t>(b) + 1) % nb) {
      e.angle_errors_deg.push_back(
          std::abs(dt.corners[t].angle_deg - db.corners[static_cast<size_t>(b)].angle_deg));
    } else {
      in_order = false;
    }
    // Openings in the truth wall's coordinate (metres from its start).
    const Eigen::Vector2d dir_t = (tw.end - tw.start).normalized();
    const Eigen::Vector2d dir_b = (bw.end - bw.start).normalized();
    for (const auto& to : tw.openings) {
      const double mid_t = 0.5 * (to.from_m + to.to_m);
      int best = -1;
      double best_d = std::max(0.3, 0.5 * to.length());
      for (size_t k = 0; k < bw.openings.size(); ++k) {
        const auto& bo = bw.openings[k];
        if (used[static_cast<size_t>(b)][k] || bo.type != to.type) continue;
        const double mid_b = dir_t.dot(bw.start + dir_b * (0.5 * (bo.from_m + bo.to_m)) - tw.start);
        if (std::abs(mid_b - mid_t) <= best_d)
          best_d = std::abs(mid_b - mid_t), best = static_cast<int>(k);
      }
      if (best >= 0) {
        used[static_cast<size_t>(b)][static_cast<size_t>(best)] = true;
        ++e.openings_found;
      }
    }
  }
  for (size_t b = 0; b < nb; ++b) {
    for (bool u : used[b]) e.extra_openings += u ? 0 : 1;
  }
  e.outline_right = in_order && e.walls_found == e.truth_walls && nb == nt;
  e.truth_stairs = static_cast<int>(truth.stairs.size());
  std::vector<bool> stair_used(built.stairs.size(), false);
  for (const auto& ts : truth.stairs) {
    for (size_t k = 0; k < built.stairs.size(); ++k) {
      const auto& bs = built.stairs[k];
      if (!stair_used[k] && bs.ascending == ts.ascending && (bs.center - ts.center).norm() < 1.0) {
        stair_used[k] = true;
        ++e.stairs_found;
        break;
      }
    }
  }
  return e;
}

absl::StatusOr<FoldedVisit> FoldVisit(const std::string& tum_dir,
                                      const PlaceStudyOptions& options) {
  auto seq = io::ReadTumSequence(tum_dir);
  if (!seq.ok()) return seq.status();
  if (seq->frames_with_pose < static_cast<int>(seq->frames.size())) {
    return absl::FailedPreconditionError(absl::StrCat(
        tum_dir, ": ", seq->frames.size() - seq->frames_with_pose, " of ", seq->frames.size(),
        " frames have no ground-truth pose (groundtruth.txt); "
        "a floor plan needs every key frame's pose"));
  }
  FoldedVisit v;
  v.frames = static_cast<int>(seq->frames.size());
  tracking::KeyframeSelector selector(options.keyframes);
  std::vector<size_t> keyframes;
  for (size_t i = 0; i < seq->frames.size(); ++i) {
    const auto& e = seq->frames[i];
    if (!selector.Decide(e.timestamp_s, e.T_world_camera).selected) continue;
    selector.Accept(e.timestamp_s, e.T_world_camera);
    keyframes.push_back(i);
  }
  v.keyframes = static_cast<int>(keyframes.size());
  // The appearance baseline keeps evenly spaced key frames.
  std::vector<bool> keep(keyframes.size(), false);
  const size_t kept = std::min(keyframes.size(), static_cast<size_t>(options.appearance_keyframes));
  for (size_t j = 0; j < kept; ++j) keep[j * keyframes.size() / kept] = true;

  place::FloorPlanBuilder builder(options.floor_plan);
  for (size_t j = 0; j < keyframes.size(); ++j) {
    // Colour only where the appearance baseline keeps the frame.
    auto frame = io::DecodeTumFrame(*seq, seq->frames[keyframes[j]], /*decode_color=*/keep[j]);
    if (!frame.ok()) return frame.status();
    if (auto s =
            builder.AddDepthKeyframe(frame->depth_m, frame->intrinsics, *frame->T_world_camera);
        !s.ok()) {
      return absl::Status(s.code(),
                          absl::StrCat(seq->frames[keyframes[j]].depth_path, ": ", s.message()));
    }
    if (keep[j]) {
      v.appearance.push_back(features::ExtractOrb(frame->color_bgr, {options.orb_keypoints}));
    }
  }
  auto plan = builder.Build();
  if (plan.ok()) {
    v.plan = *std::move(plan);
    v.descriptor = place::Describe(v.plan);
  } else {
    v.plan_status = plan.status();
  }
  return v;
}

double AppearanceSimilarity(const FoldedVisit& query, const FoldedVisit& reference,
                            const PlaceStudyOptions& options) {
  if (query.appearance.empty()) return 0;
  cv::BFMatcher matcher(cv::NORM_HAMMING);
  double sum = 0;
  for (const auto& q : query.appearance) {
    double best = 0;
    if (q.keypoints.empty()) continue;
    for (const auto& r : reference.appearance) {
      if (r.keypoints.size() < 8) continue;
      std::vector<std::vector<cv::DMatch>> knn;
      matcher.knnMatch(q.descriptors, r.descriptors, knn, 2);
      std::vector<cv::Point2f> pa, pb;
      for (const auto& m : knn) {
        if (m.size() == 2 && m[0].distance < options.ratio_test * m[1].distance) {
          const auto& a = q.keypoints[static_cast<size_t>(m[0].queryIdx)];
          const auto& b = r.keypoints[static_cast<size_t>(m[0].trainIdx)];
          pa.emplace_back(a.x, a.y);
          pb.emplace_back(b.x, b.y);
        }
      }
      if (pa.size() < 8) continue;
      std::vector<uchar> inliers;
      const cv::Mat F =
          cv::findFundamentalMat(pa, pb, cv::FM_RANSAC, options.ransac_px, 0.99, inliers);
      if (F.empty()) continue;
      const double share =
          static_cast<double>(cv::countNonZero(inliers)) / static_cast<double>(q.keypoints.size());
      best = std::max(best, share);
    }
    sum += best;
  }
  return sum / static_cast<double>(query.appearance.size());
}

PrPoint EvaluateTrials(const std::vector<RecognitionTrial>& trials, double threshold, int subset) {
  int accepted = 0, right = 0, known = 0;
  for (const auto& t : trials) {
    if (subset > 0 && t.subset != subset) continue;
    known += t.known ? 1 : 0;
    if (t.predicted.empty() || t.score < threshold) continue;
    ++accepted;
    right += t.correct ? 1 : 0;
  }
  PrPoint p;
  p.threshold = threshold;
  p.precision = accepted > 0 ? static_cast<double>(right) / accepted : 1.0;
  p.recall = known > 0 ? static_cast<double>(right) / known : 0.0;
  p.f1 = p.precision + p.recall > 0 ? 2 * p.precision * p.recall / (p.precision + p.recall) : 0.0;
  return p;
}

namespace {

// Trials of one method from its query × reference score matrix.
MethodResult Evaluate(const std::string& name, const std::vector<SuiteVisit>& visits,
                      const std::vector<size_t>& queries, const std::vector<size_t>& references,
                      const std::vector<std::vector<double>>& scores, double threshold) {
  MethodResult m;
  m.name = name;
  for (size_t qi = 0; qi < queries.size(); ++qi) {
    const SuiteVisit& q = visits[queries[qi]];
    for (bool with_own : {true, false}) {
      RecognitionTrial t;
      t.query = queries[qi];
      t.subset = q.subset;
      t.known = with_own;
      double best = -1;
      for (size_t ri = 0; ri < references.size(); ++ri) {
        const SuiteVisit& r = visits[references[ri]];
        if (!with_own && r.place_id == q.place_id) continue;
        if (scores[qi][ri] > best) best = scores[qi][ri], t.predicted = r.place_id;
      }
      if (best <= 0) t.predicted.clear();  // nothing alike: no candidate at all
      t.score = std::max(best, 0.0);
      t.correct = with_own && !t.predicted.empty() && t.predicted == q.place_id;
      m.trials.push_back(t);
    }
  }
  SummariseTrials(threshold, &m);
  return m;
}

}  // namespace

void SummariseTrials(double threshold, MethodResult* m) {
  m->curve.clear();
  m->operating = PrPoint();
  for (int step = 0; step <= 200; ++step) {
    const PrPoint p = EvaluateTrials(m->trials, step / 200.0);
    m->curve.push_back(p);
    if (p.f1 > m->operating.f1) m->operating = p;
  }
  if (threshold >= 0) m->operating = EvaluateTrials(m->trials, threshold);
  // Top-1: the known trials whose best reference is their own place, per subset.
  std::array<int, 8> known{}, right{};
  for (const auto& t : m->trials) {
    if (!t.known || t.subset < 1 || t.subset > 8) continue;
    ++known[static_cast<size_t>(t.subset - 1)];
    right[static_cast<size_t>(t.subset - 1)] += t.correct ? 1 : 0;
  }
  for (int k = 0; k < 8; ++k) {
    const auto i = static_cast<size_t>(k);
    m->subsets[i] = EvaluateTrials(m->trials, m->operating.threshold, k + 1);
    m->top1[i] = known[i] > 0 ? static_cast<double>(right[i]) / known[i] : 0.0;
  }
}

absl::StatusOr<std::vector<SuiteVisit>> ReadSuiteManifest(const std::string& suite_dir) {
  const fs::path root(suite_dir);
  std::ifstream in(root / "manifest.json");
  if (!in) {
    return absl::NotFoundError(absl::StrCat((root / "manifest.json").string(),
                                            ": cannot open (make a suite with lifemap sim suite)"));
  }
  std::vector<SuiteVisit> visits;
  try {
    json manifest;
    in >> manifest;
    std::map<std::string, std::string> shapes;
    for (const auto& p : manifest.at("places")) {
      shapes[p.at("place_id").get<std::string>()] = p.value("shape", "");
    }
    for (const auto& v : manifest.at("visits")) {
      SuiteVisit s;
      s.path = v.at("path").get<std::string>();
      s.place_id = v.at("place_id").get<std::string>();
      s.shape = shapes[s.place_id];
      s.role = v.at("role").get<std::string>();
      s.subset = v.at("subset").get<int>();
      s.conditions = v.value("conditions", "");
      if (s.role != "reference" && s.role != "query") {
        return absl::InvalidArgumentError(
            absl::StrCat("manifest.json: visit ", s.path, " has role '", s.role, "'"));
      }
      if (s.role == "query" && (s.subset < 1 || s.subset > 8)) {
        return absl::InvalidArgumentError(
            absl::StrCat("manifest.json: query ", s.path, " has subset ", s.subset, " (1..8)"));
      }
      visits.push_back(std::move(s));
    }
  } catch (const json::exception& e) {
    return absl::InvalidArgumentError(
        absl::StrCat((root / "manifest.json").string(), ": not a suite manifest: ", e.what()));
  }
  if (visits.empty()) return absl::InvalidArgumentError("manifest.json lists no visits");

  return visits;
}

absl::StatusOr<PlaceStudy> RunPlaceStudy(const std::string& suite_dir,
                                         const PlaceStudyOptions& options,
                                         const std::function<void(const std::string&)>& progress) {
  const auto start = std::chrono::steady_clock::now();
  const fs::path root(suite_dir);
  PlaceStudy study;
  auto visits = ReadSuiteManifest(suite_dir);
  if (!visits.ok()) return visits.status();
  study.visits = *std::move(visits);

  // Fold every visit (the expensive part) in parallel.
  std::mutex mu;
  absl::Status failed;
  size_t done = 0;
  ParallelFor(study.visits.size(), options.threads, [&](size_t i) {
    SuiteVisit& v = study.visits[i];
    const std::string dir = (root / v.path).string();
    auto folded = FoldVisit(dir, options);
    auto truth = ReadTruthPlan((root / v.path / "scene.json").string());
    std::lock_guard<std::mutex> lock(mu);
    if (!folded.ok()) {
      if (failed.ok()) failed = folded.status();
      return;
    }
    v.folded = *std::move(folded);
    if (truth.ok()) {
      v.has_truth = true;
      v.truth = *std::move(truth);
      // A visit without a plan compares as an empty one: the truth's counts, nothing found.
      v.error = CompareFloorPlans(v.folded.plan_status.ok() ? v.folded.plan : place::FloorPlan(),
                                  v.truth.plan);
    }
    ++done;
    if (progress) {
      progress(absl::StrFormat(
          "[%d/%d] %s: %d key frames, %s", done, study.visits.size(), v.path, v.folded.keyframes,
          v.folded.plan_status.ok() ? absl::StrFormat("%d walls", v.folded.plan.walls.size())
                                    : std::string(v.folded.plan_status.message())));
    }
  });
  if (!failed.ok()) return failed;

  std::vector<size_t> queries, references;
  for (size_t i = 0; i < study.visits.size(); ++i) {
    (study.visits[i].role == "query" ? queries : references).push_back(i);
  }
  std::vector<std::vector<double>> arch(queries.size(), std::vector<double>(references.size(), 0));
  std::vector<std::vector<double>> look = arch;
  ParallelFor(queries.size(), options.threads, [&](size_t qi) {
    const FoldedVisit& q = study.visits[queries[qi]].folded;
    for (size_t ri = 0; ri < references.size(); ++ri) {
      const FoldedVisit& r = study.visits[references[ri]].folded;
      if (q.plan_status.ok() && r.plan_status.ok()) {
        arch[qi][ri] = place::MatchDescriptors(q.descriptor, r.descriptor, options.weights).score;
      }
      look[qi][ri] = AppearanceSimilarity(q, r, options);
    }
  });
  study.architecture = Evaluate("architecture", study.visits, queries, references, arch,
                                options.architecture_threshold);
  study.appearance =
      Evaluate("appearance", study.visits, queries, references, look, options.appearance_threshold);
  study.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return study;
}

}  // namespace lifemap::eval
