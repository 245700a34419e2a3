#include "core/tracking/keyframe_selector.h"

#include <gtest/gtest.h>

namespace lifemap::tracking {
namespace {

Pose At(double x) {
  Pose p;
  p.translation = {x, 0, 0};
  return p;
}

TEST(KeyframeSelector, FirstFrameIsAKeyframe) {
  KeyframeSelector s;
  EXPECT_TRUE(s.Decide(1.0, std::nullopt).selected);
}

TEST(KeyframeSelector, SelectsByTranslationWhenPosed) {
  KeyframeSelector s({0.10, 1.0, 10.0});
  s.Accept(1.0, At(0.0));
  EXPECT_FALSE(s.Decide(1.1, At(0.05)).selected);
  const auto d = s.Decide(1.2, At(0.15));
  EXPECT_TRUE(d.selected);
  EXPECT_NE(d.reason.find("moved"), std::string::npos);
}

TEST(KeyframeSelector, SelectsByRotation) {
  KeyframeSelector s({1.0, 0.17, 10.0});
  Pose turned;
  turned.rotation = Eigen::Quaterniond(Eigen::AngleAxisd(0.2, Eigen::Vector3d::UnitY()));
  s.Accept(1.0, Pose());
  EXPECT_TRUE(s.Decide(1.1, turned).selected);
}

TEST(KeyframeSelector, SelectsByTimeWithoutPoses) {
  KeyframeSelector s({0.1, 0.17, 1.0});
  s.Accept(1.0, std::nullopt);
  EXPECT_FALSE(s.Decide(1.5, std::nullopt).selected);
  EXPECT_TRUE(s.Decide(2.0, std::nullopt).selected);
}

TEST(KeyframeSelector, NeverSelectsWhenTimeGoesBack) {
  KeyframeSelector s;
  s.Accept(5.0, At(0));
  EXPECT_FALSE(s.Decide(4.0, At(10)).selected);
}

TEST(KeyframeOptions, RejectsNegativeAndZeroInterval) {
  EXPECT_TRUE(KeyframeOptions{}.Validate().ok());
  EXPECT_FALSE((KeyframeOptions{-1, 0.1, 1}).Validate().ok());
  EXPECT_FALSE((KeyframeOptions{0.1, 0.1, 0}).Validate().ok());
}

}  // namespace
}  // namespace lifemap::tracking
