#include <gtest/gtest.h>

#include "core/eval/entropy_study.h"
#include "core/eval/metrics.h"
#include "core/io/labeled_pcd.h"
#include "tests/testing/test_util.h"

namespace lifemap::eval {
namespace {

TEST(RocAuc, PerfectChanceAndTies) {
  EXPECT_DOUBLE_EQ(RocAuc({3, 4, 5}, {0, 1, 2}), 1.0);
  EXPECT_DOUBLE_EQ(RocAuc({0, 1}, {2, 3}), 0.0);
  EXPECT_DOUBLE_EQ(RocAuc({1, 1}, {1, 1}), 0.5);
  EXPECT_DOUBLE_EQ(RocAuc({2, 1}, {1, 0}), 0.875);  // 3.5 of 4 pairs ordered
  EXPECT_DOUBLE_EQ(RocAuc({}, {1}), 0.5);
}

std::vector<LabeledScene> Mosd(const std::string& dir, int limit) {
  std::vector<LabeledScene> scenes;
  for (const char* name : {"learn0", "learn4", "learn8", "learn12", "learn33", "learn38"}) {
    if (static_cast<int>(scenes.size()) >= limit) break;
    auto f = io::ReadLabeledPcd(dir + "/learn/" + name + ".pcd");
    EXPECT_TRUE(f.ok()) << f.status();
    if (!f.ok()) continue;
    LabeledScene s{name, f->frame, f->labels >= 20, f->labels >= 1};
    scenes.push_back(std::move(s));
  }
  return scenes;
}

TEST(LabeledPcd, ReadsMosdSceneAsRgbdFrameWithLabels) {
  LIFEMAP_REQUIRE_DATASET(dir, "pcl_mosd_labeled_subset");
  auto f = io::ReadLabeledPcd(dir + "/learn/learn0.pcd");
  ASSERT_TRUE(f.ok()) << f.status();
  EXPECT_EQ(f->frame.depth_m.cols, 640);
  EXPECT_EQ(f->labels.rows, 480);
  // learn0: a table and two boxes (labels 1-9 table, 20+ objects).
  EXPECT_GT(cv::countNonZero(f->labels >= 20), 5000);
  EXPECT_GT(cv::countNonZero((f->labels >= 1) & (f->labels < 10)), 20000);
  EXPECT_TRUE(absl::IsNotFound(io::ReadLabeledPcd(dir + "/nope.pcd").status()));
}

// On real table-top scenes, entropy of normals separates objects from the table far better
// than chance (the paper's Fig. 6 claim).
TEST(FeatureStudy, EntropySeparatesObjectsFromTableOnMosd) {
  LIFEMAP_REQUIRE_DATASET(dir, "pcl_mosd_labeled_subset");
  auto study = RunFeatureStudy(Mosd(dir, 6));
  ASSERT_TRUE(study.ok()) << study.status();
  EXPECT_GT(study->moved_superjuts, 5);
  EXPECT_GT(study->pixel_auc.entropy, 0.8);
  EXPECT_GT(study->superjut_auc.entropy, 0.6);
}

TEST(MatchingStudy, SweepsAreConsistentAndOracleHelpsOnMosd) {
  LIFEMAP_REQUIRE_DATASET(dir, "pcl_mosd_labeled_subset");
  MatchingStudyOptions options;
  options.ransac_iterations = 2000;
  auto study = RunMatchingStudy(Mosd(dir, 4), options);
  ASSERT_TRUE(study.ok()) << study.status();
  EXPECT_EQ(study->summary.pairs + study->summary.skipped_pairs, 6);
  for (const auto& p : study->pairs) {
    ASSERT_EQ(p.entropy_sweep.size(), 21u);
    // Threshold 0 masks nothing: precision is the raw inlier ratio, recall 1.
    EXPECT_DOUBLE_EQ(p.entropy_sweep[0].precision, p.raw_inlier_ratio);
    EXPECT_DOUBLE_EQ(p.entropy_sweep[0].recall, 1.0);
    for (size_t i = 1; i < p.entropy_sweep.size(); ++i) {
      EXPECT_LE(p.entropy_sweep[i].kept, p.entropy_sweep[i - 1].kept) << "monotone pruning";
    }
  }
  EXPECT_GT(study->summary.static_oracle_gain, 0.0)
      << "masking the objects raises the share of matches consistent with the static scene";
}

TEST(MatchingStudy, RejectsTooFewScenes) {
  EXPECT_TRUE(absl::IsInvalidArgument(RunMatchingStudy({}, MatchingStudyOptions()).status()));
}

}  // namespace
}  // namespace lifemap::eval
