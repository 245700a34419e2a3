// The steps of FloorPlanBuilder::Build (core/place/floor_plan_steps.h) on hand-made evidence,
// and FloorPlanOptions::Validate.
#include <gtest/gtest.h>

#include <cstdint>

#include "core/place/floor_plan_steps.h"

namespace lifemap::place::steps {
namespace {

Patch Horizontal(double height, Eigen::Vector2d centroid, double area) {
  Patch p;
  p.height = height;
  p.centroid = centroid;
  p.lo = p.hi = centroid;
  p.area = area;
  return p;
}

// Issue 54: the floor's level over a visit. A key frame that saw only a table top reports a
// plane 0.75 m up, now and then (a rigid track: no drift); a bent track's floor rises from key
// frame to key frame.
TEST(AgreeOnFloor, ATableTopNowAndThenIsNoDriftButARisingFloorIs) {
  std::vector<FloorSighting> rigid, rising;
  for (int i = 0; i < 18; ++i) {
    const bool table = i % 4 == 1 || i == 10;  // 6 of 18, two in one third
    rigid.push_back({0.3, table ? 0.75 : 0.002 * (i % 3)});
    rising.push_back({0.3, 0.02 * i});
  }
  const FloorAgreement a = AgreeOnFloor(rigid);
  EXPECT_EQ(a.keyframes, 18);
  EXPECT_LT(a.drift_m, 0.01);
  EXPECT_NEAR(a.tilt_deg_p90, 0.3, 1e-9);
  const FloorAgreement b = AgreeOnFloor(rising);
  EXPECT_GT(b.drift_m, 0.15);
  EXPECT_EQ(AgreeOnFloor({}).keyframes, 0);
  EXPECT_EQ(AgreeOnFloor({}).drift_m, 0.0);
}

// Cells left of or below a wall's origin have negative keys (their packing shifted a negative
// int left, undefined behaviour found by tests/fuzz/rpc_fuzz under UBSan).
TEST(CellKey, EveryColumnAndRowComesBack) {
  for (int s : {0, 1, -1, -3, 1 << 20, -(1 << 20), INT32_MAX, INT32_MIN}) {
    for (int h : {0, 2, -1, -7, INT32_MAX, INT32_MIN}) {
      EXPECT_EQ(KeyS(Key(s, h)), s) << s << ", " << h;
      EXPECT_EQ(KeyH(Key(s, h)), h) << s << ", " << h;
    }
  }
  EXPECT_NE(Key(-1, 0), Key(0, -1));
}

TEST(FloorPlanOptions, DefaultsAreValidAndBadSettingsAreNamed) {
  EXPECT_TRUE(FloorPlanOptions{}.Validate().ok());
  FloorPlanOptions o;
  o.cell_m = 0;
  EXPECT_NE(o.Validate().message().find("cell_m"), absl::string_view::npos);
  o = {};
  o.window_sill_m = 2.5;  // above the door top
  EXPECT_NE(o.Validate().message().find("window_sill_m"), absl::string_view::npos);
  o = {};
  o.min_riser_m = 0.3;
  EXPECT_FALSE(o.Validate().ok());
  o = {};
  o.world_up = Eigen::Vector3d::Zero();
  EXPECT_FALSE(o.Validate().ok());
}

TEST(FindFloor, TheLargestUpwardAreaBelowTheCamerasOrWhyNot) {
  const FloorPlanOptions o;
  std::vector<Patch> patches = {Horizontal(0.01, {0, 0}, 3.0), Horizontal(0.75, {1, 1}, 2.0),
                                Horizontal(0.0, {2, 0}, 1.0)};
  auto floor = FindFloor(patches, 1.5, o);
  ASSERT_TRUE(floor.ok()) << floor.status();
  EXPECT_NEAR(*floor, 0.0075, 1e-6);  // area-weighted over the floor's bins (the table apart)
  patches[0].faces_up = false;        // a ceiling
  patches[2].area = 0.5;
  auto none = FindFloor(patches, 1.2, o);  // the table is less than 0.5 m below the cameras
  EXPECT_TRUE(absl::IsFailedPrecondition(none.status()));
  EXPECT_NE(none.status().message().find("no floor seen"), absl::string_view::npos);
}

TEST(MergeCollinearWalls, CollinearNeighboursBecomeOneWallWithTheirOpenings) {
  // A square room whose bottom wall was built in two pieces; the second has a door.
  std::vector<Wall> walls(5);
  walls[0].start = {0, 0}, walls[0].end = {2, 0};
  walls[1].start = {2, 0}, walls[1].end = {4, 0};
  walls[1].openings.push_back({OpeningType::kDoor, 0.5, 1.4, 0, 2.1});
  walls[2].start = {4, 0}, walls[2].end = {4, 4};
  walls[3].start = {4, 4}, walls[3].end = {0, 4};
  walls[4].start = {0, 4}, walls[4].end = {0, 0};
  MergeCollinearWalls(&walls, {});
  ASSERT_EQ(walls.size(), 4u);
  EXPECT_TRUE(walls[0].end.isApprox(Eigen::Vector2d(4, 0)));
  ASSERT_EQ(walls[0].openings.size(), 1u);
  EXPECT_DOUBLE_EQ(walls[0].openings[0].from_m, 2.5);  // measured from the merged wall's start
  EXPECT_DOUBLE_EQ(walls[0].openings[0].to_m, 3.4);
}

TEST(FindStairs, RegularTreadsMakeAFlightAndScatteredShelvesDoNot) {
  const FloorPlanOptions o;
  std::vector<Patch> patches;
  for (int k = 1; k <= 5; ++k) {  // five treads rising 0.17 m every 0.28 m along x
    patches.push_back(Horizontal(0.17 * k, {0.28 * k, 1.0}, 0.25));
  }
  patches.push_back(Horizontal(0.9, {3.0, 3.0}, 0.4));  // a shelf top
  std::vector<Wall> walls(1);
  walls[0].start = {0, 0}, walls[0].end = {4, 0};
  const auto flights = FindStairs(patches, 0.0, walls, o);
  ASSERT_EQ(flights.size(), 1u);
  EXPECT_TRUE(flights[0].ascending);
  EXPECT_EQ(flights[0].steps, 5);
  EXPECT_NEAR(flights[0].rise_m, 0.17, 1e-9);
  EXPECT_NEAR(flights[0].distance_to_wall_m, 1.0, 1e-9);
  patches.resize(2);  // two treads are not a flight
  EXPECT_TRUE(FindStairs(patches, 0.0, walls, o).empty());
}

}  // namespace
}  // namespace lifemap::place::steps
