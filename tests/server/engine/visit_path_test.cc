// The camera's path through a visit (server/engine/visit_registry.h): what the appearance query's
// own-visit exclusion measures keyframes by.
#include <gtest/gtest.h>

#include "server/engine/visit_registry.h"

namespace lifemap::server {
namespace {

TEST(VisitPath, MeasuresTheWayTravelledSinceEachKeyframe) {
  VisitPath path;
  path.Advance({0, 0, 0});
  path.MarkKeyframe(1.0);
  path.Advance({3, 0, 0});
  path.Advance({3, 4, 0});
  path.MarkKeyframe(2.0);
  // Back to the start: 3 + 4 + 5 m of path, though the camera is where it began.
  path.Advance({0, 0, 0});
  EXPECT_DOUBLE_EQ(path.travelled_m(), 12.0);
  ASSERT_TRUE(path.SinceKeyframe(1.0).has_value());
  EXPECT_DOUBLE_EQ(*path.SinceKeyframe(1.0), 12.0);
  EXPECT_DOUBLE_EQ(*path.SinceKeyframe(2.0), 5.0);
  EXPECT_FALSE(path.SinceKeyframe(1.5).has_value()) << "no keyframe was taken then";
}

TEST(VisitPath, AKeyframeFromTheStoreIsFoundByItsTimeAndAnOutOfOrderOneIsIgnored) {
  VisitPath path;
  path.Advance({0, 0, 0});
  path.MarkKeyframe(1700000000.033333);
  path.MarkKeyframe(1700000000.0);  // not after the last: ignored
  path.Advance({0, 0, 2});
  EXPECT_DOUBLE_EQ(*path.SinceKeyframe(1700000000.0333334), 2.0);
  EXPECT_FALSE(path.SinceKeyframe(1700000000.0).has_value());
}

}  // namespace
}  // namespace lifemap::server
