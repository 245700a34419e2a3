// core/appearance: vocabulary, inverted index, PnP verification, recognition; on synthetic
// geometry (exact answers) and on TUM fr1 (real views of one desk against another desk).
#include <random>

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <opencv2/imgproc.hpp>

#include "core/appearance/recognizer.h"
#include "core/io/tum_dataset.h"
#include "core/pipeline/keyframe.h"
#include "tests/testing/test_util.h"

namespace lifemap::appearance {
namespace {

// `n` random 32-byte descriptors.
cv::Mat RandomDescriptors(int n, std::mt19937* rng) {
  cv::Mat d(n, 32, CV_8UC1);
  std::uniform_int_distribution<int> byte(0, 255);
  for (int r = 0; r < n; ++r) {
    for (int c = 0; c < 32; ++c) d.at<uint8_t>(r, c) = static_cast<uint8_t>(byte(*rng));
  }
  return d;
}

// Flips `bits` random bits of each row.
cv::Mat Perturb(const cv::Mat& d, int bits, std::mt19937* rng) {
  cv::Mat out = d.clone();
  std::uniform_int_distribution<int> bit(0, 255);
  for (int r = 0; r < out.rows; ++r) {
    for (int i = 0; i < bits; ++i) {
      const int b = bit(*rng);
      out.at<uint8_t>(r, b / 8) ^= static_cast<uint8_t>(1 << (b % 8));
    }
  }
  return out;
}

TEST(VocabularyTest, OptionsOutsideTheirRangesAreRefused) {
  EXPECT_TRUE(absl::IsInvalidArgument(VocabularyOptions{1, 4, 10, 1}.Validate()));
  EXPECT_TRUE(absl::IsInvalidArgument(VocabularyOptions{10, 0, 10, 1}.Validate()));
  EXPECT_TRUE(absl::IsInvalidArgument(VocabularyOptions{10, 4, 0, 1}.Validate()));
  EXPECT_TRUE(absl::IsInvalidArgument(Vocabulary::Train({cv::Mat(5, 32, CV_8UC1)}).status()));
  EXPECT_TRUE(absl::IsInvalidArgument(Vocabulary::Train({cv::Mat(50, 16, CV_8UC1)}).status()));
}

TEST(VocabularyTest, SimilarDescriptorsShareWordsAndTheBlobRoundTrips) {
  std::mt19937 rng(7);
  std::vector<cv::Mat> images;
  for (int i = 0; i < 20; ++i) images.push_back(RandomDescriptors(200, &rng));
  auto v = Vocabulary::Train(images, {8, 3, 10, 1});
  ASSERT_TRUE(v.ok()) << v.status();
  EXPECT_GT(v->words(), 200u);
  EXPECT_LE(v->words(), 512u);
  // An image's words against a perturbed copy (8 of 256 bits flipped) and against another.
  auto a = v->Transform(images[3]);
  auto b = v->Transform(Perturb(images[3], 8, &rng));
  auto c = v->Transform(images[4]);
  ASSERT_TRUE(a.ok() && b.ok() && c.ok());
  InvertedIndex index(v->words());
  for (int i = 0; i < 20; ++i) index.Add({1, 1, i + 1, 0.0}, *v->Transform(images[i]));
  const auto hits = index.Query(*b, 3);
  ASSERT_FALSE(hits.empty());
  EXPECT_EQ(hits[0].keyframe.keyframe_id, 4);
  EXPECT_GT(hits[0].score, 0.3f);
  const auto self = index.Query(*a, 1);
  ASSERT_EQ(self.size(), 1u);
  EXPECT_NEAR(self[0].score, 1.0f, 1e-4f);

  auto copy = Vocabulary::Deserialize(v->Serialize());
  ASSERT_TRUE(copy.ok()) << copy.status();
  EXPECT_EQ(copy->words(), v->words());
  for (int r = 0; r < images[5].rows; ++r) {
    EXPECT_EQ(copy->Word(images[5].ptr<uint8_t>(r)), v->Word(images[5].ptr<uint8_t>(r)));
  }
  std::string damaged = v->Serialize();
  damaged.resize(damaged.size() - 3);
  EXPECT_TRUE(absl::IsDataLoss(Vocabulary::Deserialize(damaged).status()));
  EXPECT_TRUE(absl::IsDataLoss(Vocabulary::Deserialize("LMVOC0").status()));
  // A child link pointing back at the root would loop forever: refused.
  damaged = v->Serialize();
  const size_t first_child = 6 + 24 + 8 + 32;  // magic, header, seed, root centroid
  const int32_t back = 0;
  std::memcpy(damaged.data() + first_child, &back, sizeof(back));
  EXPECT_TRUE(absl::IsDataLoss(Vocabulary::Deserialize(damaged).status()));
}

TEST(InvertedIndexTest, ExcludedAndRemovedKeyframesAreNeverCandidates) {
  InvertedIndex index(10);
  BowVector x{{{1, 0.5f}, {2, 0.5f}}};
  index.Add({1, 10, 100, 1.0}, x);
  index.Add({1, 11, 101, 2.0}, x);
  index.Add({2, 12, 102, 3.0}, BowVector{{{1, 0.25f}, {3, 0.75f}}});
  EXPECT_EQ(index.Query(x, 10).size(), 3u);
  const auto others = index.Query(x, 10, [](const KeyframeRef& k) { return k.visit_id == 10; });
  ASSERT_EQ(others.size(), 2u);
  EXPECT_EQ(others[0].keyframe.keyframe_id, 101);
  EXPECT_FLOAT_EQ(others[0].score, 1.0f);
  EXPECT_FLOAT_EQ(others[1].score, 0.25f);
  EXPECT_EQ(index.RemoveIf([](const KeyframeRef& k) { return k.map_id == 1; }), 2u);
  const auto left = index.Query(x, 10);
  ASSERT_EQ(left.size(), 1u);
  EXPECT_EQ(left[0].keyframe.keyframe_id, 102);
  EXPECT_EQ(index.Stats().keyframes, 1u);
  EXPECT_EQ(index.Stats().postings, 2u);
}

TEST(InvertedIndexTest, WeightsOrderCandidatesAndScoresStayTheIndexs) {
  InvertedIndex index(10);
  const BowVector q{{{1, 0.5f}, {2, 0.5f}}};
  index.Add({1, 10, 100, 1.0}, q);                                  // score 1
  index.Add({1, 11, 101, 2.0}, BowVector{{{1, 0.4f}, {3, 0.6f}}});  // score 0.4
  EXPECT_EQ(index.Query(q, 1)[0].keyframe.keyframe_id, 100);
  ASSERT_TRUE(index.SetWeight(101, 3.0f));
  EXPECT_FALSE(index.SetWeight(999, 2.0f));
  const auto ranked = index.Query(q, 2);
  ASSERT_EQ(ranked.size(), 2u);
  EXPECT_EQ(ranked[0].keyframe.keyframe_id, 101) << "0.4 x 3 ranks above 1 x 1";
  EXPECT_FLOAT_EQ(ranked[0].score, 0.4f);
  EXPECT_FLOAT_EQ(ranked[0].rank, 1.2f);
  EXPECT_EQ(index.Query(q, 1)[0].keyframe.keyframe_id, 101) << "and takes the only place";
  // Weights survive the renumbering of a removal.
  index.Add({1, 12, 102, 3.0}, q);
  EXPECT_EQ(index.RemoveIf([](const KeyframeRef& k) { return k.keyframe_id == 100; }), 1u);
  EXPECT_EQ(index.Query(q, 1)[0].keyframe.keyframe_id, 101);
}

// Points in front of a camera, their descriptors, and their projection into a second camera.
struct SyntheticPair {
  features::KeypointSet match, query;
  CameraIntrinsics k{525, 525, 319.5, 239.5, 640, 480};
  Eigen::Isometry3d T_match_query = Eigen::Isometry3d::Identity();
};

SyntheticPair MakePair(int n, double outlier_share, std::mt19937* rng) {
  SyntheticPair p;
  p.T_match_query.translate(Eigen::Vector3d(0.3, -0.05, 0.2));
  p.T_match_query.rotate(Eigen::AngleAxisd(0.2, Eigen::Vector3d(0.1, 1, 0.05).normalized()));
  const Eigen::Isometry3d T_query_match = p.T_match_query.inverse();
  std::uniform_real_distribution<double> u(-1, 1), z(1.0, 4.0), share(0, 1);
  const cv::Mat descriptors = RandomDescriptors(n, rng);
  p.match.descriptors = descriptors;
  p.query.descriptors = Perturb(descriptors, 10, rng);
  for (int i = 0; i < n; ++i) {
    const double depth = z(*rng);
    const Eigen::Vector3d X(u(*rng) * depth * 0.5, u(*rng) * depth * 0.4, depth);
    const Eigen::Vector3d Xq = T_query_match * X;
    auto project = [&](const Eigen::Vector3d& P) {
      return features::Keypoint{static_cast<float>(p.k.fx * P.x() / P.z() + p.k.cx),
                                static_cast<float>(p.k.fy * P.y() / P.z() + p.k.cy), 31, 0, 1};
    };
    p.match.keypoints.push_back(project(X));
    p.match.points.push_back(X.cast<float>());
    features::Keypoint q = project(Xq);
    if (share(*rng) < outlier_share) {  // a wrong match: anywhere in the image
      q.x = static_cast<float>(320 + 300 * u(*rng));
      q.y = static_cast<float>(240 + 220 * u(*rng));
    }
    p.query.keypoints.push_back(q);
  }
  return p;
}

TEST(VerifyTest, RecoversTheRelativePoseDespiteOutliers) {
  std::mt19937 rng(3);
  const SyntheticPair p = MakePair(300, 0.4, &rng);
  const Verification v = VerifyMatch(p.query, p.k, p.match);
  ASSERT_TRUE(v.verified) << v.reason;
  EXPECT_GT(v.inliers, 150);
  EXPECT_LT(v.inliers, 200);  // the 40 % moved are not inliers
  EXPECT_GT(v.score, 0.8);
  EXPECT_LT(v.reprojection_px, 0.5);
  const Eigen::Isometry3d error = p.T_match_query.inverse() * v.T_match_query.ToIsometry();
  EXPECT_LT(error.translation().norm(), 0.005);
  EXPECT_LT(Eigen::AngleAxisd(error.linear()).angle(), 0.002);
}

TEST(VerifyTest, UnrelatedViewsAndMissingPointsAreNotVerifiedAndSayWhy) {
  std::mt19937 rng(4);
  SyntheticPair p = MakePair(300, 0.0, &rng);
  SyntheticPair other = MakePair(300, 0.0, &rng);
  Verification v = VerifyMatch(other.query, p.k, p.match);
  EXPECT_FALSE(v.verified);
  EXPECT_EQ(v.score, 0.0);
  EXPECT_THAT(v.reason, ::testing::HasSubstr("fewer than"));
  p.match.points.clear();
  v = VerifyMatch(p.query, p.k, p.match);
  EXPECT_FALSE(v.verified);
  EXPECT_THAT(v.reason, ::testing::HasSubstr("no 3D points"));
}

// Keypoints detected on a resized image come back in the full image's pixels: on a scene of
// dark squares, those found at half resolution lie where full resolution finds them.
TEST(FeaturesTest, HalfResolutionKeypointsAreInFullResolutionPixels) {
  cv::Mat scene(480, 640, CV_8UC3, cv::Scalar::all(210));
  std::mt19937 rng(3);
  std::uniform_int_distribution<int> side(24, 60);
  for (int r = 20; r + 70 < scene.rows; r += 80) {
    for (int c = 20; c + 70 < scene.cols; c += 80) {
      cv::rectangle(scene, cv::Rect(c, r, side(rng), side(rng)), cv::Scalar::all(40), cv::FILLED);
    }
  }
  const features::KeypointSet full = features::ExtractOrb(scene, {500, 1.0});
  const features::KeypointSet half = features::ExtractOrb(scene, {500, 0.5});
  ASSERT_GT(full.size(), 20u);
  ASSERT_GT(half.size(), 20u);
  EXPECT_EQ(half.descriptors.rows, static_cast<int>(half.size()));
  std::vector<double> nearest;
  for (const auto& h : half.keypoints) {
    double best = 1e9;
    for (const auto& f : full.keypoints)
      best = std::min(best, static_cast<double>(std::hypot(h.x - f.x, h.y - f.y)));
    nearest.push_back(best);
  }
  std::nth_element(nearest.begin(), nearest.begin() + nearest.size() / 2, nearest.end());
  EXPECT_LT(nearest[nearest.size() / 2], 3.0) << "median distance to a full-resolution keypoint";
  pipeline::KeyframeFeatureOptions options;
  options.orb.detect_scale = 0;
  EXPECT_EQ(options.Validate().code(), absl::StatusCode::kInvalidArgument);
  options.orb.detect_scale = 0.5;
  EXPECT_TRUE(options.Validate().ok());
}

TEST(RecognizeTest, EmptyIndexAndPrunedQuerySaySo) {
  std::mt19937 rng(5);
  const SyntheticPair p = MakePair(100, 0.0, &rng);
  auto vocabulary = Vocabulary::Train({p.match.descriptors}, {8, 2, 5, 1});
  ASSERT_TRUE(vocabulary.ok());
  InvertedIndex index(vocabulary->words());
  const FeatureLoader load = [&](const KeyframeRef&) { return p.match; };
  auto r = Recognize(p.query, p.k, *vocabulary, index, load, {});
  EXPECT_TRUE(absl::IsFailedPrecondition(r.status()));
  EXPECT_THAT(std::string(r.status().message()), ::testing::HasSubstr("no keyframe is indexed"));
  features::KeypointSet pruned;
  pruned.detected = 50;
  pruned.masked = 50;
  r = Recognize(pruned, p.k, *vocabulary, index, load, {});
  EXPECT_THAT(std::string(r.status().message()), ::testing::HasSubstr("after pruning"));

  index.Add({1, 1, 7, 0}, *vocabulary->Transform(p.match.descriptors));
  r = Recognize(p.query, p.k, *vocabulary, index, load, {});
  ASSERT_TRUE(r.ok()) << r.status();
  ASSERT_EQ(r->matches.size(), 1u);
  EXPECT_EQ(r->matches[0].keyframe.keyframe_id, 7);
  EXPECT_TRUE(r->matches[0].verification.verified);
}

// Real views: frames of fr1_xyz (one desk, the camera moving a few cm) recognise each other
// with a pose close to the ground truth; fr1_desk (another desk) is not verified against them.
TEST(RecognizeTest, TumXyzFramesMatchEachOtherAndNotTheOtherDesk) {
  const std::string xyz = lifemap::testing::SharedDataset("tum_fr1_xyz_subset");
  const std::string desk = lifemap::testing::SharedDataset("tum_fr1_desk_subset");
  if (xyz.empty() || desk.empty()) GTEST_SKIP() << "../shared/data TUM fr1 subsets are absent";
  auto load_features = [](const std::string& dir, std::vector<RgbdFrame>* frames) {
    std::vector<features::KeypointSet> out;
    auto seq = io::ReadTumSequence(dir);
    EXPECT_TRUE(seq.ok()) << seq.status();
    for (const auto& e : seq->frames) {
      auto f = io::DecodeTumFrame(*seq, e);
      EXPECT_TRUE(f.ok()) << f.status();
      pipeline::FrameAnalysis a;
      a.frame = *f;
      auto k = pipeline::ExtractKeyframeFeatures(a, {});
      EXPECT_TRUE(k.ok());
      out.push_back(k->keypoints);
      frames->push_back(*std::move(f));
    }
    return out;
  };
  std::vector<RgbdFrame> xyz_frames, desk_frames;
  const auto xyz_features = load_features(xyz, &xyz_frames);
  const auto desk_features = load_features(desk, &desk_frames);
  ASSERT_GE(xyz_features.size(), 20u);
  // Reference: every 4th xyz frame; queries: the frames between, and every desk frame.
  std::vector<cv::Mat> training;
  for (const auto& f : xyz_features) training.push_back(f.descriptors);
  for (const auto& f : desk_features) training.push_back(f.descriptors);
  auto vocabulary = Vocabulary::Train(training, {10, 3, 10, 1});
  ASSERT_TRUE(vocabulary.ok());
  InvertedIndex index(vocabulary->words());
  for (size_t i = 0; i < xyz_features.size(); i += 4) {
    index.Add({1, 1, static_cast<int64_t>(i), xyz_frames[i].timestamp_s},
              *vocabulary->Transform(xyz_features[i].descriptors));
  }
  const FeatureLoader load = [&](const KeyframeRef& k) {
    return xyz_features[static_cast<size_t>(k.keyframe_id)];
  };
  int right = 0, queries = 0;
  for (size_t i = 1; i < xyz_features.size(); i += 4) {
    auto r = Recognize(xyz_features[i], xyz_frames[i].intrinsics, *vocabulary, index, load, {});
    ASSERT_TRUE(r.ok()) << r.status();
    ++queries;
    if (r->matches.empty()) continue;
    const auto& best = r->matches[0];
    const size_t m = static_cast<size_t>(best.keyframe.keyframe_id);
    ASSERT_TRUE(xyz_frames[i].T_world_camera && xyz_frames[m].T_world_camera);
    const Eigen::Isometry3d truth = xyz_frames[m].T_world_camera->ToIsometry().inverse() *
                                    xyz_frames[i].T_world_camera->ToIsometry();
    const Eigen::Isometry3d error = truth.inverse() * best.verification.T_match_query.ToIsometry();
    EXPECT_LT(error.translation().norm(), 0.05) << "query " << i << " against " << m;
    EXPECT_LT(Eigen::AngleAxisd(error.linear()).angle(), 0.05);
    if (m + 4 > i && m < i + 4) ++right;  // one of its two neighbouring references
  }
  EXPECT_GE(right, queries - 1);
  int verified_desk = 0;
  for (size_t i = 0; i < desk_features.size(); ++i) {
    auto r = Recognize(desk_features[i], desk_frames[i].intrinsics, *vocabulary, index, load, {});
    ASSERT_TRUE(r.ok()) << r.status();
    verified_desk += r->matches.empty() ? 0 : 1;
  }
  EXPECT_EQ(verified_desk, 0);
}

}  // namespace
}  // namespace lifemap::appearance
