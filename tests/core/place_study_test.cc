#include "core/eval/place_study.h"

#include <filesystem>
#include <fstream>

#include <gtest/gtest.h>

#include "tests/testing/test_util.h"

namespace lifemap::eval {
namespace {

namespace fs = std::filesystem;

// A counter-clockwise rectangle w × h from `origin`, its walls starting at corner `first`.
place::FloorPlan Rectangle(double w, double h, Eigen::Vector2d origin = {0, 0}, int first = 0) {
  const std::vector<Eigen::Vector2d> c = {origin, origin + Eigen::Vector2d(w, 0),
                                          origin + Eigen::Vector2d(w, h),
                                          origin + Eigen::Vector2d(0, h)};
  place::FloorPlan p;
  for (int i = 0; i < 4; ++i) {
    place::Wall wall;
    wall.start = c[static_cast<size_t>((first + i) % 4)];
    wall.end = c[static_cast<size_t>((first + i + 1) % 4)];
    p.walls.push_back(wall);
  }
  return p;
}

place::WallOpening Opening(place::OpeningType type, double from, double to) {
  place::WallOpening o;
  o.type = type;
  o.from_m = from;
  o.to_m = to;
  return o;
}

TEST(CompareFloorPlans, SamePlaceFromAnotherCornerPairsEveryWallAndOpening) {
  place::FloorPlan truth = Rectangle(4.0, 3.0);
  truth.walls[0].openings.push_back(Opening(place::OpeningType::kDoor, 1.0, 1.9));
  truth.walls[2].openings.push_back(Opening(place::OpeningType::kWindow, 0.5, 1.5));
  // Built 5 cm off, 10 cm longer on x, starting at truth corner 2; the door found 10 cm late.
  place::FloorPlan built = Rectangle(4.1, 3.0, {0.05, -0.05}, 2);
  built.walls[0].openings.push_back(Opening(place::OpeningType::kWindow, 0.6, 1.5));  // truth 2
  built.walls[2].openings.push_back(Opening(place::OpeningType::kDoor, 1.05, 1.95));  // truth 0
  built.walls[3].openings.push_back(Opening(place::OpeningType::kDoor, 1.0, 2.0));    // not there
  const FloorPlanError e = CompareFloorPlans(built, truth);
  EXPECT_EQ(e.walls_found, 4);
  EXPECT_TRUE(e.outline_right);
  ASSERT_EQ(e.length_errors_m.size(), 4u);
  double sum = 0;
  for (double x : e.length_errors_m) sum += x;
  EXPECT_NEAR(sum, 0.2, 1e-9);  // the two x walls, 10 cm each
  ASSERT_EQ(e.angle_errors_deg.size(), 4u);
  for (double a : e.angle_errors_deg) EXPECT_NEAR(a, 0.0, 1e-9);
  EXPECT_EQ(e.truth_openings, 2);
  EXPECT_EQ(e.openings_found, 2);
  EXPECT_EQ(e.extra_openings, 1);
}

TEST(CompareFloorPlans, MissingWallWrongTypeAndFarOffWallsAreCounted) {
  place::FloorPlan truth = Rectangle(4.0, 3.0);
  truth.walls[0].openings.push_back(Opening(place::OpeningType::kDoor, 1.0, 1.9));
  place::FloorPlan built = Rectangle(4.0, 3.0);
  built.walls[0].openings.push_back(Opening(place::OpeningType::kWindow, 1.0, 1.9));
  built.walls.erase(built.walls.begin() + 3);  // the wall x = 0 not seen
  built.walls[1].start.x() += 1.0;             // a wall 1 m inside: not the truth's
  built.walls[1].end.x() += 1.0;
  const FloorPlanError e = CompareFloorPlans(built, truth);
  EXPECT_EQ(e.walls_found, 2);
  EXPECT_FALSE(e.outline_right);
  EXPECT_EQ(e.openings_found, 0);  // a window where the door is
  EXPECT_EQ(e.extra_openings, 1);
  EXPECT_TRUE(e.angle_errors_deg.empty());  // no two consecutive truth walls paired in order
}

TEST(CompareFloorPlans, AnLShapedRoomHasOneReflexCorner) {
  place::FloorPlan truth;
  const std::vector<Eigen::Vector2d> c = {{0, 0}, {5, 0}, {5, 2}, {2, 2}, {2, 4}, {0, 4}};
  for (size_t i = 0; i < c.size(); ++i) {
    place::Wall w;
    w.start = c[i];
    w.end = c[(i + 1) % c.size()];
    truth.walls.push_back(w);
  }
  place::FloorPlan built = truth;
  built.walls[2].end = {2.2, 2};  // the reflex corner found 20 cm off, at 270° still
  built.walls[3].start = {2.2, 2};
  built.walls[3].end = {2.2, 4};
  built.walls[4].start = {2.2, 4};
  const FloorPlanError e = CompareFloorPlans(built, truth);
  EXPECT_TRUE(e.outline_right);
  EXPECT_EQ(e.angle_errors_deg.size(), 6u);
  for (double a : e.angle_errors_deg) EXPECT_NEAR(a, 0.0, 1e-6);
}

TEST(EvaluateTrials, OpenSetPrecisionAndRecall) {
  std::vector<RecognitionTrial> t;
  auto add = [&](int subset, bool known, const std::string& predicted, double score, bool correct) {
    RecognitionTrial r;
    r.subset = subset, r.known = known, r.predicted = predicted, r.score = score;
    r.correct = correct;
    t.push_back(r);
  };
  add(1, true, "a", 0.9, true);    // right
  add(1, false, "b", 0.3, false);  // its place left out: rejected at 0.5
  add(1, true, "c", 0.8, false);   // wrong place accepted
  add(1, false, "c", 0.7, false);  // unknown accepted: wrong
  add(2, true, "a", 0.4, true);    // right but below 0.5
  add(2, true, "", 0.0, false);    // nothing to compare
  const PrPoint p = EvaluateTrials(t, 0.5);
  EXPECT_NEAR(p.precision, 1.0 / 3.0, 1e-12);  // 1 right of 3 accepted
  EXPECT_NEAR(p.recall, 1.0 / 4.0, 1e-12);     // of 4 known trials
  EXPECT_NEAR(p.f1, 2 * (1.0 / 3) * 0.25 / (1.0 / 3 + 0.25), 1e-12);
  const PrPoint s2 = EvaluateTrials(t, 0.3, 2);
  EXPECT_NEAR(s2.precision, 1.0, 1e-12);
  EXPECT_NEAR(s2.recall, 0.5, 1e-12);
  const PrPoint none = EvaluateTrials(t, 0.95);
  EXPECT_EQ(none.precision, 1.0);  // nothing accepted
  EXPECT_EQ(none.recall, 0.0);
  EXPECT_EQ(none.f1, 0.0);
}

TEST(ReadTruthPlan, MainRoomWallsWithOpenOpeningsAndStairs) {
  testing::TempDir dir;
  const std::string path = (fs::path(dir.path()) / "scene.json").string();
  std::ofstream(path) << R"({"place_id": "p", "shape": "rect", "floor_plan": {
    "walls": [{"start": [0, 0], "end": [4, 0]}, {"start": [4, 0], "end": [4, 3]},
              {"start": [4, 3], "end": [0, 3]}, {"start": [0, 3], "end": [0, 0]}],
    "openings": [
      {"type": "door", "room": 0, "wall": 1, "offset_m": 1.0, "width_m": 0.9, "sill_m": 0,
       "top_m": 2.1, "open": true},
      {"type": "door", "room": 0, "wall": 2, "offset_m": 1.0, "width_m": 0.9, "sill_m": 0,
       "top_m": 2.1, "open": false},
      {"type": "window", "room": 1, "wall": 0, "offset_m": 1.0, "width_m": 0.9, "sill_m": 1.2,
       "top_m": 2.1, "open": true}],
    "stairs": [{"type": "down", "origin": [1, 1], "yaw_rad": 0, "steps": 5, "rise_m": 0.17,
                "length_m": 1.4, "width_m": 1.0, "centre_distance_to_nearest_wall_m": 1.0}]}})";
  auto t = ReadTruthPlan(path);
  ASSERT_TRUE(t.ok()) << t.status();
  EXPECT_EQ(t->shape, "rect");
  ASSERT_EQ(t->plan.walls.size(), 4u);
  ASSERT_EQ(t->plan.walls[1].openings.size(), 1u);
  EXPECT_NEAR(t->plan.walls[1].openings[0].to_m, 1.9, 1e-9);
  EXPECT_TRUE(t->plan.walls[2].openings.empty());  // closed: counted apart
  EXPECT_EQ(t->closed_doors, 1);
  EXPECT_TRUE(t->plan.walls[0].openings.empty());  // room 1's window
  ASSERT_EQ(t->plan.stairs.size(), 1u);
  EXPECT_FALSE(t->plan.stairs[0].ascending);
  EXPECT_NEAR(t->plan.stairs[0].center.x(), 1.7, 1e-9);

  EXPECT_TRUE(absl::IsNotFound(ReadTruthPlan(path + ".missing").status()));
  std::ofstream(path) << R"({"place_id": "p", "shape": "rect", "floor_plan": {"walls": 3}})";
  auto bad = ReadTruthPlan(path);
  EXPECT_TRUE(absl::IsInvalidArgument(bad.status()));
  EXPECT_NE(bad.status().message().find("scene.json"), std::string::npos);
}

TEST(RunPlaceStudy, AMissingOrMalformedManifestSaysWhatToDo) {
  testing::TempDir dir;
  auto missing = RunPlaceStudy(dir.path(), {}, {});
  EXPECT_TRUE(absl::IsNotFound(missing.status()));
  EXPECT_NE(missing.status().message().find("lifemap sim suite"), std::string::npos);
  std::ofstream(fs::path(dir.path()) / "manifest.json")
      << R"({"places": [], "visits": [{"path": "x", "place_id": "p", "role": "query",
              "subset": 9}]})";
  auto bad = RunPlaceStudy(dir.path(), {}, {});
  EXPECT_TRUE(absl::IsInvalidArgument(bad.status()));
  EXPECT_NE(bad.status().message().find("subset 9"), std::string::npos);
}

}  // namespace
}  // namespace lifemap::eval
