// Objects that appeared, vanished and moved between two renders of a synthetic room, doors, and
// what is not a change of the place (a person walking through; what was not seen).
#include "core/change/object_changes.h"
#include "core/change/moved_zones.h"

#include <cmath>
#include <vector>

#include <gtest/gtest.h>

#include "core/sim/renderer.h"
#include "core/sim/world.h"

namespace lifemap::change {
namespace {

const CameraIntrinsics kCamera{131.25, 131.25, 79.5, 59.5, 160, 120};

// A 4 m x 6 m room, 2.7 m high.
sim::Place Room() {
  sim::Place p;
  p.id = "test";
  p.shape = "rect";
  p.footprint = {{0, 0}, {4, 0}, {4, 6}, {0, 6}};
  return p;
}

sim::Solid Box(int instance, double x, double y, double side, double height) {
  sim::Solid s;
  s.instance = instance;
  s.movable = true;
  s.center = {x, y};
  s.size = {side, side, height};
  return s;
}

// Looking along yaw `yaw` (from +x, counter-clockwise), pitched down by `pitch` (radians).
Pose Camera(const Eigen::Vector3d& at, double yaw, double pitch) {
  const Eigen::Vector3d right(std::sin(yaw), -std::cos(yaw), 0);
  const Eigen::Vector3d forward(std::cos(pitch) * std::cos(yaw), std::cos(pitch) * std::sin(yaw),
                                -std::sin(pitch));
  Eigen::Matrix3d R;
  R.col(0) = right;
  R.col(1) = forward.cross(right);
  R.col(2) = forward;
  Pose pose;
  pose.translation = at;
  pose.rotation = Eigen::Quaterniond(R);
  return pose;
}

// A visit: the camera turns on the spot at three places along the room, 24 views each. `solids`
// gives the arrangement seen at view i (so a person can walk through).
std::vector<PosedDepth> Visit(const std::function<std::vector<sim::Solid>(int)>& solids) {
  sim::SensorOptions sensor;
  sensor.noise = true;
  std::vector<PosedDepth> views;
  int i = 0;
  for (double y : {1.5, 3.0, 4.5}) {
    for (int step = 0; step < 24; ++step, ++i) {
      const Pose pose = Camera({2.0, y, 1.3}, step * 2 * M_PI / 24, 0.25);
      const sim::RenderedFrame f = sim::Render(Room(), solids(i), {}, kCamera, pose, sensor, i + 1);
      views.push_back(Subsample(f.depth_m, kCamera, 1, pose));
    }
  }
  return views;
}

const std::vector<sim::Solid> kBefore = {Box(1, 1.0, 2.0, 0.5, 0.6), Box(2, 3.0, 4.0, 0.4, 0.5),
                                         Box(3, 3.2, 1.0, 0.3, 0.4)};

const ObjectChange* Find(const ObjectChanges& c, ChangeKind kind) {
  for (const auto& o : c.objects) {
    if (o.kind == kind) return &o;
  }
  return nullptr;
}

TEST(ObjectChanges, AppearedVanishedAndMovedAreFoundWhereTheyAre) {
  // Box 1 goes, box 2 moves 1.2 m, box 4 is new; box 3 stays.
  const std::vector<sim::Solid> after = {Box(2, 3.0, 2.8, 0.4, 0.5), Box(3, 3.2, 1.0, 0.3, 0.4),
                                         Box(4, 1.0, 4.6, 0.45, 0.7)};
  auto changes =
      DetectObjectChanges(Visit([](int) { return kBefore; }), Visit([&](int) { return after; }));
  ASSERT_TRUE(changes.ok()) << changes.status();
  ASSERT_EQ(changes->objects.size(), 3u);
  const ObjectChange* vanished = Find(*changes, ChangeKind::kVanished);
  const ObjectChange* appeared = Find(*changes, ChangeKind::kAppeared);
  const ObjectChange* moved = Find(*changes, ChangeKind::kMoved);
  ASSERT_NE(vanished, nullptr);
  ASSERT_NE(appeared, nullptr);
  ASSERT_NE(moved, nullptr);
  // The centroids of the voxels seen (the visible faces: the top and the sides in view).
  EXPECT_LT((vanished->center.head<2>() - Eigen::Vector2d(1.0, 2.0)).norm(), 0.15);
  EXPECT_LT((appeared->center.head<2>() - Eigen::Vector2d(1.0, 4.6)).norm(), 0.15);
  EXPECT_LT((moved->center.head<2>() - Eigen::Vector2d(3.0, 2.8)).norm(), 0.15);
  EXPECT_LT((moved->from_center.head<2>() - Eigen::Vector2d(3.0, 4.0)).norm(), 0.15);
  EXPECT_NEAR(appeared->extent.z(), 0.7, 0.1);
  EXPECT_GE(appeared->evidence_views, 2);
}

TEST(ObjectChanges, ADoorLeafThatGoesIsADoorOpenedNotAVanishedObject) {
  // A leaf 0.9 m wide, 5 cm thick, 2 m tall, turned 30 degrees from the axes, 1 m from the wall
  // behind it (the room beyond the doorway); with it gone the later visit sees that wall.
  sim::Solid leaf = Box(5, 1.0, 4.4, 0.9, 2.0);
  leaf.size.y() = 0.05;
  leaf.yaw = M_PI / 6;
  std::vector<sim::Solid> before = kBefore;
  before.push_back(leaf);
  auto changes =
      DetectObjectChanges(Visit([&](int) { return before; }), Visit([&](int) { return kBefore; }));
  ASSERT_TRUE(changes.ok()) << changes.status();
  ASSERT_EQ(changes->objects.size(), 1u);
  EXPECT_EQ(changes->objects[0].kind, ChangeKind::kDoorOpened);
  EXPECT_LT((changes->objects[0].center.head<2>() - Eigen::Vector2d(1.0, 4.4)).norm(), 0.15);
}

TEST(ObjectChanges, APartitionPutUpIsAWallNewAndTakenDownAWallGone) {
  // A partition 2.4 m long, 10 cm thick, 2.2 m tall across the room at y = 3.8 (the camera's
  // third place, at y = 4.5, sees it from the far side; the others from the near side).
  sim::Solid wall = Box(6, 2.0, 3.8, 2.4, 2.2);
  wall.size.y() = 0.10;
  wall.movable = false;
  std::vector<sim::Solid> with = kBefore;
  with.push_back(wall);
  for (const bool put_up : {true, false}) {
    auto changes = put_up ? DetectObjectChanges(Visit([&](int) { return kBefore; }),
                                                Visit([&](int) { return with; }))
                          : DetectObjectChanges(Visit([&](int) { return with; }),
                                                Visit([&](int) { return kBefore; }));
    ASSERT_TRUE(changes.ok()) << changes.status();
    const ChangeKind kind = put_up ? ChangeKind::kWallNew : ChangeKind::kWallGone;
    const ObjectChange* w = Find(*changes, kind);
    ASSERT_NE(w, nullptr) << ChangeKindName(kind) << ": " << changes->objects.size() << " objects";
    EXPECT_LT(std::abs(w->center.y() - 3.8), 0.15);
    EXPECT_GT(std::max(w->extent.x(), w->extent.y()), 1.5);
    for (const auto& o : changes->objects) {
      EXPECT_NE(o.kind, ChangeKind::kDoorOpened);
      EXPECT_NE(o.kind, ChangeKind::kDoorClosed);
    }
  }
}

TEST(ObjectChanges, APersonWalkingThroughIsNoChangeOfThePlace) {
  // Walking across while the camera turns at its first two places, gone by the third (which
  // looks at the whole room again). A passer-by last seen where its visit never looks again is
  // reported as appeared: nothing says it left.
  auto with_person = [](int view) {
    std::vector<sim::Solid> s = kBefore;
    if (view >= 48) return s;
    sim::Solid person;
    person.shape = sim::Solid::Shape::kCylinder;
    person.cls = sim::SemanticClass::kPerson;
    person.instance = 9;
    person.center = {0.3 + 3.4 * view / 47.0, 3.6};
    person.size = {0.45, 0.45, 1.7};
    s.push_back(person);
    return s;
  };
  auto changes = DetectObjectChanges(Visit([](int) { return kBefore; }), Visit(with_person));
  ASSERT_TRUE(changes.ok()) << changes.status();
  for (const auto& o : changes->objects) {
    ADD_FAILURE() << ChangeKindName(o.kind) << " at " << o.center.transpose() << ", " << o.voxels
                  << " voxels";
  }
  EXPECT_GT(changes->transient_voxels, 0);
}

TEST(ObjectChanges, NothingIsSaidOfWhatTheOtherVisitNeverSaw) {
  // The later visit looks only from the far end: box 1 (near the other end, hidden by nothing)
  // is out of its range or view in most frames; what it does not see through is not "vanished".
  std::vector<PosedDepth> later;
  for (int step = 0; step < 12; ++step) {
    const Pose pose = Camera({2.0, 5.5, 1.3}, M_PI / 2 + (step - 6) * 0.05, 0.2);
    const sim::RenderedFrame f = sim::Render(Room(), {}, {}, kCamera, pose, {}, step + 1);
    later.push_back(Subsample(f.depth_m, kCamera, 1, pose));
  }
  auto changes = DetectObjectChanges(Visit([](int) { return kBefore; }), later);
  ASSERT_TRUE(changes.ok()) << changes.status();
  EXPECT_TRUE(changes->objects.empty());
  EXPECT_GT(changes->unobserved_voxels, 0);
}

TEST(ObjectChanges, BadOptionsAndViewsAreRefusedSayingWhich) {
  ChangeOptions o;
  o.voxel_m = 0;
  EXPECT_NE(DetectObjectChanges({}, {}, o).status().message().find("voxel_m"), std::string::npos);
  PosedDepth bad;
  bad.depth_m = cv::Mat(10, 10, CV_16UC1, cv::Scalar(0));
  bad.intrinsics = kCamera;
  auto s = DetectObjectChanges({bad}, {});
  EXPECT_TRUE(absl::IsInvalidArgument(s.status()));
  EXPECT_NE(s.status().message().find("earlier visit's view 0"), std::string::npos);
}

TEST(ObjectChanges, SubsamplePicksPixelsAndScalesTheIntrinsics) {
  cv::Mat d(120, 160, CV_32FC1);
  for (int v = 0; v < d.rows; ++v) {
    for (int u = 0; u < d.cols; ++u) d.at<float>(v, u) = static_cast<float>(u + 1000 * v);
  }
  const PosedDepth s = Subsample(d, kCamera, 4, {});
  EXPECT_EQ(s.depth_m.cols, 40);
  EXPECT_EQ(s.depth_m.rows, 30);
  EXPECT_EQ(s.depth_m.at<float>(2, 3), d.at<float>(8, 12));
  EXPECT_DOUBLE_EQ(s.intrinsics.fx, kCamera.fx / 4);
  EXPECT_DOUBLE_EQ(s.intrinsics.cx, kCamera.cx / 4);
  EXPECT_EQ(s.intrinsics.width, 40);
}

// Eq. 3: a box on a table in view i, gone in view j. Its pixels are the zone of i that moved
// (D_j - D_i = the box's height > 50 mm); the table around it did not.
TEST(MovedZones, FindsExactlyTheMovedObject) {
  cv::Mat table(240, 320, CV_32FC1, cv::Scalar(1.50f));
  cv::Mat with_box = table.clone();
  const cv::Rect box(100, 70, 120, 90);
  with_box(box).setTo(1.30f);  // 20 cm closer
  const cv::Mat moved = MovedZones(with_box, {table});
  // The 10x10 median rounds the box's corners and, being even, shifts an edge by a pixel; the
  // mask is the box up to that.
  cv::Mat truth(moved.size(), CV_8UC1, cv::Scalar(0));
  truth(box).setTo(255);
  const int overlap = cv::countNonZero(moved & truth);
  const int either = cv::countNonZero(moved | truth);
  EXPECT_GT(static_cast<double>(overlap) / either, 0.95) << "intersection over union";
  cv::Mat near_box(moved.size(), CV_8UC1, cv::Scalar(0));
  near_box(cv::Rect(box.x - 1, box.y - 1, box.width + 2, box.height + 2)).setTo(255);
  EXPECT_EQ(cv::countNonZero(moved & ~near_box), 0) << "nothing away from the box";
  // The view without the box has nothing that moved in it (the box left, it did not arrive).
  EXPECT_EQ(cv::countNonZero(MovedZones(table, {with_box})), 0);
  // Differences below 50 mm (alignment noise) do not count.
  cv::Mat shifted = table + 0.03f;
  EXPECT_EQ(cv::countNonZero(MovedZones(table, {shifted})), 0);
}

TEST(MovedZones, MissingDepthIsNoDifference) {
  cv::Mat a(60, 80, CV_32FC1, cv::Scalar(1.0f));
  cv::Mat b(60, 80, CV_32FC1, cv::Scalar(0.0f));  // no readings
  EXPECT_EQ(cv::countNonZero(MovedZones(a, {b})), 0);
}

// A box that arrived since the earlier visit is the moved zone of a frame looking at it: the
// earlier visit's surfaces rendered at the frame's pose are the room without the box.
TEST(MovedAgainst, TheZoneOfANewBoxIsMovedAndTheRestIsNot) {
  const std::vector<sim::Solid> after = {kBefore[0], kBefore[1], kBefore[2],
                                         Box(4, 1.0, 4.6, 0.45, 0.7)};
  const SurfacePoints earlier = SurfaceOf(Visit([](int) { return kBefore; }), 0.05, 4.0);
  ASSERT_GT(earlier.points.size(), 1000u);
  // Looking at the new box from 1.2 m away.
  const Pose pose = Camera({1.0, 3.4, 1.3}, M_PI / 2, 0.5);
  sim::SensorOptions sensor;
  const sim::RenderedFrame f = sim::Render(Room(), after, {}, kCamera, pose, sensor, 77);
  const MovedMask m = MovedAgainst(f.depth_m, kCamera, pose, earlier, {2, 3, 0.10f, 4.0});
  ASSERT_GT(m.compared_pixels, 1000);
  int on_box = 0, box_pixels = 0, off_box = 0;
  for (int v = 0; v < m.mask.rows; ++v) {
    for (int u = 0; u < m.mask.cols; ++u) {
      const bool box = f.instance_id.at<uint16_t>(v * 2, u * 2) == 4;
      const bool moved = m.mask.at<uint8_t>(v, u) != 0;
      box_pixels += box;
      on_box += box && moved;
      off_box += !box && moved;
    }
  }
  ASSERT_GT(box_pixels, 100);
  EXPECT_GT(on_box, box_pixels * 8 / 10) << "most of the box is moved";
  EXPECT_LT(off_box, box_pixels / 10) << "little else is";
  // Against itself nothing moved.
  const Pose same = Camera({2.0, 3.0, 1.3}, 0.3, 0.25);
  const sim::RenderedFrame g = sim::Render(Room(), kBefore, {}, kCamera, same, sensor, 78);
  const MovedMask none = MovedAgainst(g.depth_m, kCamera, same, earlier, {2, 3, 0.10f, 4.0});
  EXPECT_LT(none.share(), 0.01);
}

}  // namespace
}  // namespace lifemap::change
