#include "core/eval/entropy_study.h"

#include <algorithm>
#include <cmath>
#include <numeric>
#include <random>

#include <opencv2/calib3d.hpp>
#include <opencv2/features2d.hpp>
#include <opencv2/imgproc.hpp>

#include "absl/strings/str_cat.h"
#include "core/eval/metrics.h"

namespace lifemap::eval {
namespace {

// A keypoint outside every superjut (no depth) is never masked: it scores above any threshold.
constexpr float kNoSuperjut = 2.0f;

absl::StatusOr<entropy::EntropyMaskResult> Entropy(const LabeledScene& s,
                                                   const entropy::EntropyMaskOptions& options) {
  auto r = entropy::ComputeEntropyMask(s.frame.depth_m, s.frame.color_bgr, s.frame.intrinsics,
                                       Eigen::Vector3f(0, -1, 0), options);
  if (!r.ok()) {
    return absl::Status(r.status().code(), absl::StrCat(s.name, ": ", r.status().message()));
  }
  return r;
}

FeatureAuc Aucs(const std::vector<std::array<double, 4>>& moved,
                const std::vector<std::array<double, 4>>& still) {
  // Features oriented so that "higher = more likely to move" under the paper's hypothesis.
  auto column = [](const std::vector<std::array<double, 4>>& v, int i) {
    std::vector<double> out;
    out.reserve(v.size());
    for (const auto& a : v) out.push_back(a[i]);
    return out;
  };
  FeatureAuc auc;
  auc.entropy = RocAuc(column(moved, 0), column(still, 0));
  auc.planarity = RocAuc(column(moved, 1), column(still, 1));
  auc.horizontality = RocAuc(column(moved, 2), column(still, 2));
  auc.textureness = RocAuc(column(moved, 3), column(still, 3));
  return auc;
}

std::array<double, 4> Oriented(const entropy::SuperjutScore& s) {
  return {s.entropy, -s.planarity, -s.horizontality, s.textureness};
}

struct SceneKeypoints {
  std::vector<cv::KeyPoint> keypoints;
  cv::Mat descriptors;
  std::vector<float> score, null_score;
  std::vector<bool> on_object;
};

absl::StatusOr<SceneKeypoints> Describe(const LabeledScene& s, const MatchingStudyOptions& o,
                                        std::mt19937* rng) {
  auto e = Entropy(s, o.entropy);
  if (!e.ok()) return e.status();
  cv::Mat gray;
  cv::cvtColor(s.frame.color_bgr, gray, cv::COLOR_BGR2GRAY);
  SceneKeypoints k;
  cv::Ptr<cv::Feature2D> detector;
  if (o.keypoints == Keypoints::kSift) {
    detector = cv::SIFT::create(o.max_keypoints);
  } else {
    detector = cv::ORB::create(o.max_keypoints);
  }
  detector->detectAndCompute(gray, cv::noArray(), k.keypoints, k.descriptors);
  std::vector<float> permuted(e->superjuts.size());
  for (size_t i = 0; i < permuted.size(); ++i) permuted[i] = e->superjuts[i].neg_entropy;
  std::shuffle(permuted.begin(), permuted.end(), *rng);
  for (const auto& kp : k.keypoints) {
    const int c = std::clamp(static_cast<int>(std::lround(kp.pt.x)), 0, gray.cols - 1);
    const int r = std::clamp(static_cast<int>(std::lround(kp.pt.y)), 0, gray.rows - 1);
    const int id = e->labels.at<int>(r, c);
    k.score.push_back(id >= 0 ? e->superjuts[id].neg_entropy : kNoSuperjut);
    k.null_score.push_back(id >= 0 ? permuted[id] : kNoSuperjut);
    k.on_object.push_back(!s.moved.empty() && s.moved.at<unsigned char>(r, c) != 0);
  }
  return k;
}

// Symmetric epipolar distance (the larger of the two point-to-line distances), pixels.
double EpipolarDistance(const cv::Mat& F, const cv::Point2f& a, const cv::Point2f& b) {
  const cv::Matx33d f(F);
  const cv::Vec3d xa(a.x, a.y, 1), xb(b.x, b.y, 1);
  const cv::Vec3d la = f * xa, lb = f.t() * xb;
  const double e = xb.dot(la);
  const double da = std::abs(e) / std::sqrt(la[0] * la[0] + la[1] * la[1]);
  const double db = std::abs(e) / std::sqrt(lb[0] * lb[0] + lb[1] * lb[1]);
  return std::max(da, db);
}

SweepPoint Sweep(double th, const std::vector<bool>& kept, const std::vector<bool>& inlier,
                 const std::vector<bool>& static_inlier, int inliers) {
  SweepPoint p;
  p.threshold = th;
  for (size_t i = 0; i < kept.size(); ++i) {
    if (!kept[i]) continue;
    ++p.kept;
    p.kept_inliers += inlier[i];
    p.kept_static_inliers += static_inlier[i];
  }
  p.precision = p.kept > 0 ? static_cast<double>(p.kept_inliers) / p.kept : 0.0;
  p.static_precision = p.kept > 0 ? static_cast<double>(p.kept_static_inliers) / p.kept : 0.0;
  p.recall = inliers > 0 ? static_cast<double>(p.kept_inliers) / inliers : 0.0;
  return p;
}

// The sweep point of best precision among those with recall >= min_recall (the lowest
// threshold on ties); the unmasked point when none qualifies.
const SweepPoint& Best(const std::vector<SweepPoint>& sweep, double min_recall) {
  const SweepPoint* best = &sweep.front();
  for (const auto& p : sweep) {
    if (p.recall >= min_recall && p.precision > best->precision) best = &p;
  }
  return *best;
}

double Mean(const std::vector<double>& v) {
  return v.empty() ? 0.0 : std::accumulate(v.begin(), v.end(), 0.0) / v.size();
}

}  // namespace

absl::StatusOr<FeatureStudy> RunFeatureStudy(const std::vector<LabeledScene>& scenes,
                                             const FeatureStudyOptions& options) {
  if (scenes.empty()) return absl::InvalidArgumentError("the feature study needs scenes");
  FeatureStudy study;
  std::vector<std::array<double, 4>> moved, still, moved_px, still_px;
  for (const auto& s : scenes) {
    if (s.labelled.empty() || s.moved.empty()) {
      return absl::InvalidArgumentError(
          absl::StrCat(s.name, " has no ground truth of what moved: the feature study needs it"));
    }
    auto e = Entropy(s, options.entropy);
    if (!e.ok()) return e.status();
    const int n = static_cast<int>(e->superjuts.size());
    std::vector<int> labelled(n, 0), moved_count(n, 0);
    for (int r = 0; r < e->labels.rows; ++r) {
      const int* id = e->labels.ptr<int>(r);
      const unsigned char* known = s.labelled.ptr<unsigned char>(r);
      const unsigned char* mv = s.moved.ptr<unsigned char>(r);
      for (int c = 0; c < e->labels.cols; ++c) {
        if (id[c] < 0 || !known[c]) continue;
        ++labelled[id[c]];
        moved_count[id[c]] += mv[c] != 0;
        (mv[c] ? moved_px : still_px).push_back(Oriented(e->superjuts[id[c]]));
      }
    }
    for (int i = 0; i < n; ++i) {
      if (labelled[i] == 0) continue;
      const auto& sc = e->superjuts[i];
      SuperjutSample sample{s.name,         i,
                            sc.size_px,     static_cast<double>(moved_count[i]) / labelled[i],
                            false,          sc.entropy,
                            sc.planarity,   sc.horizontality,
                            sc.textureness, sc.neg_entropy};
      sample.moved = sample.moved_fraction > 0.5;
      study.moved_superjuts += sample.moved;
      (sample.moved ? moved : still).push_back(Oriented(sc));
      study.superjuts.push_back(sample);
    }
  }
  study.superjut_auc = Aucs(moved, still);
  study.pixel_auc = Aucs(moved_px, still_px);
  return study;
}

absl::StatusOr<MatchingStudy> RunMatchingStudy(const std::vector<LabeledScene>& scenes,
                                               const MatchingStudyOptions& options,
                                               double fixed_threshold,
                                               std::vector<std::pair<size_t, size_t>> pairs) {
  if (scenes.size() < 2) return absl::InvalidArgumentError("the matching study needs >= 2 scenes");
  if (!(options.ratio > 0 && options.ratio <= 1)) {
    return absl::InvalidArgumentError("ratio must be within (0, 1]");
  }
  std::vector<double> thresholds = options.thresholds;
  if (thresholds.empty()) {
    for (int i = 0; i <= 20; ++i) thresholds.push_back(i * 0.05);
  }
  std::mt19937 rng(options.seed);
  std::vector<SceneKeypoints> described;
  for (const auto& s : scenes) {
    auto d = Describe(s, options, &rng);
    if (!d.ok()) return d.status();
    described.push_back(*std::move(d));
  }
  const int norm = options.keypoints == Keypoints::kSift ? cv::NORM_L2 : cv::NORM_HAMMING;
  cv::BFMatcher matcher(norm);
  MatchingStudy study;
  if (pairs.empty()) {
    for (size_t ia = 0; ia < scenes.size(); ++ia) {
      for (size_t ib = ia + 1; ib < scenes.size(); ++ib) pairs.emplace_back(ia, ib);
    }
  }
  for (const auto& [ia, ib] : pairs) {
    if (ia >= scenes.size() || ib >= scenes.size()) {
      return absl::InvalidArgumentError("a pair names a scene that does not exist");
    }
    {
      const auto& A = described[ia];
      const auto& B = described[ib];
      std::vector<std::vector<cv::DMatch>> knn;
      if (!A.descriptors.empty() && !B.descriptors.empty()) {
        matcher.knnMatch(A.descriptors, B.descriptors, knn, 2);
      }
      std::vector<cv::DMatch> matches;
      for (const auto& m : knn) {
        if (m.size() == 2 && m[0].distance < options.ratio * m[1].distance) matches.push_back(m[0]);
      }
      if (matches.size() < 8) {
        ++study.summary.skipped_pairs;
        continue;
      }
      std::vector<cv::Point2f> pa, pb, sa, sb;
      for (const auto& m : matches) {
        pa.push_back(A.keypoints[m.queryIdx].pt);
        pb.push_back(B.keypoints[m.trainIdx].pt);
        if (!A.on_object[m.queryIdx] && !B.on_object[m.trainIdx]) {
          sa.push_back(pa.back());
          sb.push_back(pb.back());
        }
      }
      PairResult pr;
      pr.a = scenes[ia].name;
      pr.b = scenes[ib].name;
      pr.matches = static_cast<int>(matches.size());
      std::vector<unsigned char> mask;
      cv::Mat F = cv::findFundamentalMat(pa, pb, cv::FM_RANSAC, options.ransac_threshold_px, 0.999,
                                         options.ransac_iterations, mask);
      std::vector<bool> inlier(matches.size(), false), static_inlier(matches.size(), false);
      if (!F.empty() && F.rows == 3) {
        for (size_t i = 0; i < matches.size(); ++i) inlier[i] = mask[i] != 0;
      }
      if (sa.size() >= 8) {
        cv::Mat Fs = cv::findFundamentalMat(sa, sb, cv::FM_RANSAC, options.ransac_threshold_px,
                                            0.999, options.ransac_iterations);
        if (!Fs.empty() && Fs.rows == 3) {
          for (size_t i = 0; i < matches.size(); ++i) {
            static_inlier[i] = EpipolarDistance(Fs, pa[i], pb[i]) <= options.ransac_threshold_px;
          }
        }
      }
      pr.inliers = static_cast<int>(std::count(inlier.begin(), inlier.end(), true));
      pr.static_inliers =
          static_cast<int>(std::count(static_inlier.begin(), static_inlier.end(), true));
      pr.raw_inlier_ratio = static_cast<double>(pr.inliers) / pr.matches;
      pr.raw_static_ratio = static_cast<double>(pr.static_inliers) / pr.matches;
      std::vector<bool> kept(matches.size());
      for (double th : thresholds) {
        for (size_t i = 0; i < matches.size(); ++i) {
          kept[i] = A.score[matches[i].queryIdx] >= th && B.score[matches[i].trainIdx] >= th;
        }
        pr.entropy_sweep.push_back(Sweep(th, kept, inlier, static_inlier, pr.inliers));
        for (size_t i = 0; i < matches.size(); ++i) {
          kept[i] =
              A.null_score[matches[i].queryIdx] >= th && B.null_score[matches[i].trainIdx] >= th;
        }
        pr.null_sweep.push_back(Sweep(th, kept, inlier, static_inlier, pr.inliers));
      }
      for (size_t i = 0; i < matches.size(); ++i) {
        kept[i] = !A.on_object[matches[i].queryIdx] && !B.on_object[matches[i].trainIdx];
      }
      pr.oracle = Sweep(-1, kept, inlier, static_inlier, pr.inliers);
      study.pairs.push_back(std::move(pr));
    }
  }
  MatchingSummary& m = study.summary;
  m.pairs = static_cast<int>(study.pairs.size());
  if (m.pairs == 0) {
    return absl::FailedPreconditionError(
        "no pair of scenes had 8 or more matches; nothing to evaluate");
  }
  std::vector<double> raw, best_th, masked, recall, null_masked, oracle, oracle_recall, sraw,
      smasked, snull, soracle;
  for (const auto& p : study.pairs) {
    const SweepPoint& best = Best(p.entropy_sweep, options.min_recall);
    raw.push_back(p.raw_inlier_ratio);
    best_th.push_back(best.threshold);
    masked.push_back(best.precision);
    recall.push_back(best.recall);
    null_masked.push_back(Best(p.null_sweep, options.min_recall).precision);
    oracle.push_back(p.oracle.precision);
    oracle_recall.push_back(p.oracle.recall);
    sraw.push_back(p.raw_static_ratio);
    // Against the static ground truth, each mask at its own best static precision.
    auto best_static = [&](const std::vector<SweepPoint>& sweep) {
      double b = sweep.front().static_precision;
      for (const auto& q : sweep) {
        if (q.recall >= options.min_recall) b = std::max(b, q.static_precision);
      }
      return b;
    };
    smasked.push_back(best_static(p.entropy_sweep));
    snull.push_back(best_static(p.null_sweep));
    soracle.push_back(p.oracle.static_precision);
  }
  m.raw_inlier_ratio = Mean(raw);
  m.best_threshold = Mean(best_th);
  m.masked_inlier_ratio = Mean(masked);
  m.inlier_ratio_gain = m.masked_inlier_ratio / m.raw_inlier_ratio - 1.0;
  m.recall_at_best = Mean(recall);
  m.null_inlier_ratio_gain = Mean(null_masked) / m.raw_inlier_ratio - 1.0;
  m.oracle_inlier_ratio_gain = Mean(oracle) / m.raw_inlier_ratio - 1.0;
  m.oracle_recall = Mean(oracle_recall);
  m.static_raw_ratio = Mean(sraw);
  m.static_masked_ratio = Mean(smasked);
  m.static_gain = m.static_masked_ratio / std::max(m.static_raw_ratio, 1e-9) - 1.0;
  m.static_null_gain = Mean(snull) / std::max(m.static_raw_ratio, 1e-9) - 1.0;
  m.static_oracle_gain = Mean(soracle) / std::max(m.static_raw_ratio, 1e-9) - 1.0;

  m.thresholds = thresholds;
  for (size_t t = 0; t < thresholds.size(); ++t) {
    std::vector<double> p, r, np, nr;
    for (const auto& pr : study.pairs) {
      p.push_back(pr.entropy_sweep[t].precision);
      r.push_back(pr.entropy_sweep[t].recall);
      np.push_back(pr.null_sweep[t].precision);
      nr.push_back(pr.null_sweep[t].recall);
    }
    m.mean_precision.push_back(Mean(p));
    m.mean_recall.push_back(Mean(r));
    m.null_precision.push_back(Mean(np));
    m.null_recall.push_back(Mean(nr));
  }
  size_t chosen = 0;
  if (fixed_threshold < 0) {
    for (size_t t = 0; t < thresholds.size(); ++t) {
      if (m.mean_recall[t] >= options.min_recall &&
          m.mean_precision[t] > m.mean_precision[chosen]) {
        chosen = t;
      }
    }
  } else {
    for (size_t t = 0; t < thresholds.size(); ++t) {
      if (std::abs(thresholds[t] - fixed_threshold) <
          std::abs(thresholds[chosen] - fixed_threshold)) {
        chosen = t;
      }
    }
  }
  m.fixed_threshold = thresholds[chosen];
  m.fixed_masked_ratio = m.mean_precision[chosen];
  m.fixed_gain = m.fixed_masked_ratio / m.raw_inlier_ratio - 1.0;
  m.fixed_recall = m.mean_recall[chosen];
  return study;
}

}  // namespace lifemap::eval
