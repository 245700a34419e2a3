// core/eval/appearance_study: the real-data checks of `lifemap eval appearance` (the suite run
// itself is exercised by the e2e test of the CLI and documented in docs/RESULTS.md).
#include <gtest/gtest.h>

#include "core/eval/appearance_study.h"
#include "tests/testing/test_util.h"

namespace lifemap::eval {
namespace {

TEST(RunAppearanceStudy, AMissingManifestSaysHowToMakeOne) {
  lifemap::testing::TempDir tmp;
  auto study = RunAppearanceStudy(tmp.path(), {}, {});
  EXPECT_TRUE(absl::IsNotFound(study.status()));
  EXPECT_NE(study.status().message().find("lifemap sim suite"), std::string::npos);
}

TEST(RecogniseRealViews, TumKeyframesFindTheirNeighboursAndNotAnotherDesk) {
  const std::string xyz = lifemap::testing::SharedDataset("tum_fr1_xyz_subset");
  const std::string desk = lifemap::testing::SharedDataset("tum_fr1_desk_subset");
  if (xyz.empty() || desk.empty()) GTEST_SKIP() << "../shared/data TUM fr1 subsets are absent";
  AppearanceStudyOptions options;
  options.places.keyframes.max_interval_s = 0.3;  // more key frames from the 1.2 s subset
  auto reference = ReadTumViews(xyz, options);
  auto other = ReadTumViews(desk, options);
  ASSERT_TRUE(reference.ok() && other.ok());
  ASSERT_GE(reference->size(), 4u);
  for (const auto& v : *reference) {
    EXPECT_FALSE(v.entropy_mask.empty()) << v.name;
    EXPECT_TRUE(v.movable.empty());  // no labels: no oracle
    EXPECT_GT(v.all.with_points(), 100);
  }
  const auto self = RecogniseRealViews(*reference, *reference, true, options);
  EXPECT_EQ(self.count("oracle"), 0u);
  for (const char* variant : {"pruned", "unpruned", "null"}) {
    ASSERT_EQ(self.count(variant), 1u) << variant;
    for (const auto& t : self.at(variant)) {
      EXPECT_FALSE(t.best.empty()) << variant << " " << t.query;
      EXPECT_NE(t.best, t.query);  // its own entry is left out
    }
  }
  const auto cross = RecogniseRealViews(*reference, *other, false, options);
  for (const auto& [variant, trials] : cross) {
    for (const auto& t : trials) EXPECT_TRUE(t.best.empty()) << variant << " " << t.query;
  }
}

}  // namespace
}  // namespace lifemap::eval
