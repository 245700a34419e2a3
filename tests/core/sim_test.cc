// Exact checks of the synthetic world where exact answers exist.
#include <filesystem>
#include <map>
#include <optional>
#include <set>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>

#include "core/io/tum_dataset.h"
#include "core/mapping/point_cloud.h"
#include "core/sim/generator.h"
#include "core/sim/renderer.h"
#include "core/sim/writer.h"
#include "tests/testing/test_util.h"

namespace lifemap::sim {
namespace {

const CameraIntrinsics kCamera{262.5, 262.5, 159.5, 119.5, 320, 240};

// A 4 m x 6 m room, 3 m high, nothing in it.
Place EmptyRoom() {
  Place p;
  p.id = "test";
  p.shape = "rect";
  p.footprint = {{0, 0}, {4, 0}, {4, 6}, {0, 6}};
  p.wall_height_m = 3.0;
  return p;
}

// A camera at (x, y, z) looking horizontally along +x (right = -y, down = -z).
Pose LookAlongX(double x, double y, double z) {
  Eigen::Matrix3d R;
  R.col(0) = Eigen::Vector3d(0, -1, 0);
  R.col(1) = Eigen::Vector3d(0, 0, -1);
  R.col(2) = Eigen::Vector3d(1, 0, 0);
  Pose pose;
  pose.translation = {x, y, z};
  pose.rotation = Eigen::Quaterniond(R);
  return pose;
}

SensorOptions Exact() {
  SensorOptions s;
  s.noise = false;
  return s;
}

TEST(Render, DepthOfAKnownWallAtAKnownPixel) {
  const RenderedFrame f =
      Render(EmptyRoom(), {}, {}, kCamera, LookAlongX(0.5, 3.0, 1.5), Exact(), 1);
  // The principal point looks straight at the wall x = 4: 3.5 m away.
  EXPECT_NEAR(f.depth_m.at<float>(119, 159), 3.5f, 1e-4);
  EXPECT_EQ(f.class_id.at<uint8_t>(119, 159), static_cast<uint8_t>(SemanticClass::kWall));
  // Row 219 looks down by 99.5/262.5: the floor 1.5 m below would be at depth 3.96, beyond the
  // wall, so it is still the wall at 3.5 m.
  EXPECT_NEAR(f.depth_m.at<float>(219, 159), 3.5f, 1e-4);
  // The bottom row (119.5/262.5 down) meets the floor first, at depth 1.5 / (119.5/262.5).
  EXPECT_EQ(f.class_id.at<uint8_t>(239, 159), static_cast<uint8_t>(SemanticClass::kFloor));
  EXPECT_NEAR(f.depth_m.at<float>(239, 159), 1.5 / (119.5 / 262.5), 1e-4);
}

TEST(Render, ClassAndInstanceWhereAKnownObjectProjects) {
  Solid box;
  box.cls = SemanticClass::kBox;
  box.instance = 9;
  box.center = {2.5, 3.0};
  box.base_z = 1.2;
  box.size = {0.4, 0.4, 0.6};  // spans z 1.2..1.8, its front face at x = 2.3
  const RenderedFrame f =
      Render(EmptyRoom(), {box}, {}, kCamera, LookAlongX(1.0, 3.0, 1.5), Exact(), 1);
  EXPECT_EQ(f.class_id.at<uint8_t>(119, 159), static_cast<uint8_t>(SemanticClass::kBox));
  EXPECT_EQ(f.instance_id.at<uint16_t>(119, 159), 9);
  EXPECT_NEAR(f.depth_m.at<float>(119, 159), 1.3f, 1e-4);
}

TEST(Render, WindowGivesNoDepthAndIsLabelled) {
  Place room = EmptyRoom();
  Opening window;
  window.type = OpeningType::kWindow;
  window.wall = 1;  // the wall x = 4, from (4, 0) to (4, 6)
  window.offset_m = 2.5;
  window.width_m = 1.0;
  window.sill_m = 1.2;
  window.top_m = 2.1;
  room.openings = {window};
  const RenderedFrame f = Render(room, {}, {}, kCamera, LookAlongX(1.0, 3.0, 1.5), Exact(), 1);
  EXPECT_EQ(f.class_id.at<uint8_t>(119, 159), static_cast<uint8_t>(SemanticClass::kWindow));
  EXPECT_EQ(f.depth_m.at<float>(119, 159), 0.0f);
}

// Stairs: a flight up stands on the floor; a flight down opens the floor and its treads are
// below floor level, one riser deeper per step.
TEST(Render, StairsGoingUpAndDown) {
  for (bool up : {true, false}) {
    Place room = EmptyRoom();
    Stairs st;
    st.up = up;
    st.origin = {1.5, 3.0};
    st.yaw = 0;  // the flight runs along +x from x = 1.5
    st.steps = 4;
    st.run_m = 0.3;
    st.rise_m = 0.2;
    room.stairs = {st};
    // A camera 1.5 m above the floor looking straight down at the third step (x = 2.25).
    Pose down;
    down.translation = {2.25, 3.0, 1.5};
    Eigen::Matrix3d R;
    R.col(0) = Eigen::Vector3d(0, -1, 0);
    R.col(1) = Eigen::Vector3d(-1, 0, 0);
    R.col(2) = Eigen::Vector3d(0, 0, -1);
    down.rotation = Eigen::Quaterniond(R);
    const RenderedFrame f = Render(room, StairSolids(st, 100), {}, kCamera, down, Exact(), 1);
    EXPECT_EQ(f.class_id.at<uint8_t>(119, 159), static_cast<uint8_t>(SemanticClass::kStairs))
        << (up ? "up" : "down");
    // Step 3's tread is 3 risers above (up) or below (down) the floor.
    EXPECT_NEAR(f.depth_m.at<float>(119, 159), up ? 1.5 - 0.6 : 1.5 + 0.6, 1e-4)
        << (up ? "up" : "down");
  }
}

TEST(Render, LampOnBrightensAndDepthIsUnchanged) {
  Lighting off, on;
  on.lamp_on = true;
  on.lamp = {3.2, 3.0, 1.7};  // near the wall the camera faces
  const Pose pose = LookAlongX(0.5, 3.0, 1.5);
  const RenderedFrame dark = Render(EmptyRoom(), {}, off, kCamera, pose, Exact(), 1);
  const RenderedFrame lit = Render(EmptyRoom(), {}, on, kCamera, pose, Exact(), 1);
  EXPECT_GT(cv::mean(lit.color_bgr)[2], cv::mean(dark.color_bgr)[2] + 5) << "red channel";
  EXPECT_EQ(cv::norm(lit.depth_m, dark.depth_m, cv::NORM_INF), 0.0);
}

// Two connected rooms: through the open door between them the camera sees the next room's far
// wall; with the door closed, the door panel.
TEST(Render, SeesTheNextRoomThroughAnOpenConnectingDoor) {
  Place place = EmptyRoom();                                   // x 0..4, y 0..6
  place.adjoining_rooms = {{{4, 0}, {7, 0}, {7, 6}, {4, 6}}};  // x 4..7: shares the wall x = 4
  Opening door;
  door.type = OpeningType::kDoor;
  door.connects = true;
  door.wall = 1;  // main room: (4, 0) -> (4, 6)
  door.offset_m = 2.5;
  door.width_m = 1.0;
  Opening twin = door;
  twin.room = 1;
  twin.wall = 3;  // next room: (4, 6) -> (4, 0), so the door is 6 - 3.5 = 2.5 m along it
  twin.offset_m = 2.5;
  place.openings = {door, twin};
  const Pose pose = LookAlongX(1.0, 3.0, 1.5);
  RenderedFrame f = Render(place, {}, {}, kCamera, pose, Exact(), 1);
  EXPECT_EQ(f.class_id.at<uint8_t>(119, 159), static_cast<uint8_t>(SemanticClass::kWall));
  EXPECT_NEAR(f.depth_m.at<float>(119, 159), 6.0f, 1e-4) << "the next room's far wall, x = 7";
  place.openings[0].open = place.openings[1].open = false;
  f = Render(place, {}, {}, kCamera, pose, Exact(), 1);
  EXPECT_EQ(f.class_id.at<uint8_t>(119, 159), static_cast<uint8_t>(SemanticClass::kDoor));
  EXPECT_NEAR(f.depth_m.at<float>(119, 159), 3.0f, 1e-4);
}

// Fusing noisy views of the same wall whose poses are known brings the reference view's depth
// closer to the truth: the multi-frame reconstruction the mesh variant is meant for.
// A ball (a blob without crumple) and a bottle (a lathe) in front of the camera: depth at the
// principal point is where their near surface is, exactly; class and instance as given.
TEST(Render, CurvedSolidsAtTheirExactDepth) {
  Solid ball;
  ball.shape = Solid::Shape::kBlob;
  ball.cls = SemanticClass::kBall;
  ball.instance = 4;
  ball.center = {2.5, 3.0};
  ball.base_z = 1.35;
  ball.size = {0.3, 0.3, 0.3};  // centre at z 1.5, the camera's height: near surface x = 2.35
  RenderedFrame f = Render(EmptyRoom(), {ball}, {}, kCamera, LookAlongX(1.0, 3.0, 1.5), Exact(), 1);
  EXPECT_EQ(f.class_id.at<uint8_t>(119, 159), static_cast<uint8_t>(SemanticClass::kBall));
  EXPECT_EQ(f.instance_id.at<uint16_t>(119, 159), 4);
  EXPECT_NEAR(f.depth_m.at<float>(119, 159), 1.35f, 2e-3);

  Solid bottle;
  bottle.shape = Solid::Shape::kLathe;
  bottle.cls = SemanticClass::kBottle;
  bottle.instance = 5;
  bottle.center = {2.5, 3.0};
  bottle.base_z = 1.3;
  // A body of radius 0.1 up to 0.3 m, a neck of radius 0.03 above: the camera at 1.5 m sees
  // the body 0.2 m above the base.
  bottle.profile = {{0, 0}, {0, 0.1}, {0.3, 0.1}, {0.35, 0.03}, {0.45, 0.03}, {0.45, 0}};
  bottle.size = {0.2, 0.2, 0.45};
  f = Render(EmptyRoom(), {bottle}, {}, kCamera, LookAlongX(1.0, 3.0, 1.5), Exact(), 1);
  EXPECT_EQ(f.class_id.at<uint8_t>(119, 159), static_cast<uint8_t>(SemanticClass::kBottle));
  EXPECT_NEAR(f.depth_m.at<float>(119, 159), 1.4f, 1e-4);
  // 0.2 m higher (0.4 m above the base): the neck, 0.07 m further back.
  const int neck_row = static_cast<int>(std::lround(119.5 - 262.5 * (1.7 - 1.5) / 1.47));
  EXPECT_NEAR(f.depth_m.at<float>(neck_row, 159), 1.47f, 5e-3);
  // Above the top (1.75 m) only the wall.
  EXPECT_EQ(f.class_id.at<uint8_t>(20, 159), static_cast<uint8_t>(SemanticClass::kWall));
}

// Crumple scatters a surface's normals: the depth across a crumpled blob is rough where a
// smooth one of the same size is not.
TEST(Render, CrumpleMakesTheSurfaceRough) {
  auto roughness = [](double crumple) {
    Solid heap;
    heap.shape = Solid::Shape::kBlob;
    heap.cls = SemanticClass::kClothes;
    heap.instance = 1;
    heap.center = {2.5, 3.0};
    heap.base_z = 1.0;
    heap.size = {0.8, 0.8, 0.8};
    heap.crumple = crumple;
    heap.crumple_frequency = 5;
    heap.texture_seed = 77;
    const RenderedFrame f =
        Render(EmptyRoom(), {heap}, {}, kCamera, LookAlongX(0.5, 3.0, 1.4), Exact(), 1);
    // Mean absolute second difference of depth along the middle row, on the heap only.
    double sum = 0;
    int n = 0;
    for (int c = 1; c + 1 < kCamera.width; ++c) {
      bool on = true;
      for (int d = -1; d <= 1; ++d) {
        on = on &&
             f.class_id.at<uint8_t>(119, c + d) == static_cast<uint8_t>(SemanticClass::kClothes);
      }
      if (!on) continue;
      const float z0 = f.depth_m.at<float>(119, c - 1), z1 = f.depth_m.at<float>(119, c),
                  z2 = f.depth_m.at<float>(119, c + 1);
      sum += std::abs(z0 - 2 * z1 + z2);
      ++n;
    }
    EXPECT_GT(n, 40) << "the heap covers the middle row (crumple " << crumple << ")";
    return sum / std::max(n, 1);
  };
  EXPECT_GT(roughness(0.3), 5 * roughness(0.0));
}

TEST(Generator, TheFirstWorldIsTheDefaultAndCurvedPropsComeWithTheBuilding) {
  auto rooms = ParseWorld("rooms", 7);
  ASSERT_TRUE(rooms.ok());
  EXPECT_FALSE(rooms->curved_props);
  EXPECT_EQ(rooms->building_seed, 0u);
  auto building = ParseWorld("building", 7);
  ASSERT_TRUE(building.ok());
  EXPECT_TRUE(building->curved_props);
  EXPECT_EQ(building->building_seed, 7u);
  auto bad = ParseWorld("castle", 7);
  EXPECT_EQ(bad.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(bad.status().message().find("building"), std::string::npos);

  auto first = GeneratePlace(3, "rect");
  auto same = GeneratePlace(3, "rect", *rooms);
  ASSERT_TRUE(first.ok() && same.ok());
  ASSERT_EQ(first->solids.size(), same->solids.size());
  for (const auto& s : first->solids) {
    EXPECT_NE(s.shape, Solid::Shape::kBlob);
    EXPECT_NE(s.shape, Solid::Shape::kLathe);
  }
  EXPECT_TRUE(first->materials.wall_per_segment);
}

TEST(Generator, PlacesOfOneBuildingShareMaterialsAndFurnitureButNotLayout) {
  const PlaceStyle building = *ParseWorld("building", 7);
  PlaceStyle other = building;
  other.building_seed = 8;
  auto a = GeneratePlace(7000, "rect", building);
  auto b = GeneratePlace(7001, "L", building);
  auto c = GeneratePlace(7000, "rect", other);
  ASSERT_TRUE(a.ok() && b.ok() && c.ok());
  EXPECT_EQ(a->materials.floor.texture_seed, b->materials.floor.texture_seed);
  EXPECT_EQ(a->materials.wall.texture_seed, b->materials.wall.texture_seed);
  EXPECT_GT(a->materials.floor.tile_m, 0);
  EXPECT_FALSE(a->materials.wall_per_segment);
  EXPECT_NE(a->materials.floor.texture_seed, c->materials.floor.texture_seed);
  // The same furniture model (texture and colour) for a class in both places.
  auto model = [](const Place& p, SemanticClass cls) {
    for (const auto& s : p.solids) {
      if (s.cls == cls) return std::optional<uint32_t>(s.texture_seed);
    }
    return std::optional<uint32_t>();
  };
  for (SemanticClass cls : {SemanticClass::kTable, SemanticClass::kChair}) {
    ASSERT_TRUE(model(*a, cls) && model(*b, cls)) << ClassName(cls);
    EXPECT_EQ(*model(*a, cls), *model(*b, cls)) << ClassName(cls);
    EXPECT_NE(*model(*a, cls), *model(*c, cls)) << ClassName(cls);
  }
  EXPECT_NE(a->footprint.size(), b->footprint.size());
}

TEST(Generator, CurvedPropsAreLabelledMovableAndMoveWholeBetweenVisits) {
  const PlaceStyle building = *ParseWorld("building", 5);
  auto place = GeneratePlace(5, "rect", building);
  ASSERT_TRUE(place.ok());
  std::set<SemanticClass> curved;
  std::map<int, std::vector<Solid>> groups;
  for (const auto& s : place->solids) {
    if (s.cls >= SemanticClass::kPlant) {
      curved.insert(s.cls);
      EXPECT_TRUE(s.movable);
      EXPECT_TRUE(MovableClass(s.cls));
      EXPECT_GT(s.group, 0);
    }
    if (s.group > 0) groups[s.group].push_back(s);
  }
  EXPECT_GE(curved.size(), 4u) << "plants, a heap of clothes, a bag, a ball, a lamp";
  EXPECT_TRUE(curved.count(SemanticClass::kPlant));
  // Deterministic: the same arguments, the same place.
  auto again = GeneratePlace(5, "rect", building);
  ASSERT_EQ(again->solids.size(), place->solids.size());
  for (size_t i = 0; i < place->solids.size(); ++i) {
    EXPECT_EQ(again->solids[i].center, place->solids[i].center);
    EXPECT_EQ(again->solids[i].texture_seed, place->solids[i].texture_seed);
  }
  // Over visits with scenery changes, a group's parts keep their offsets: they move as one.
  auto visits = GenerateVisits(*place, 5, 4, 6, *ParseConditions("scenery"), 10);
  ASSERT_TRUE(visits.ok());
  int moved_groups = 0;
  for (const auto& [group, parts] : groups) {
    if (parts.size() < 2) continue;
    for (const auto& v : *visits) {
      std::vector<Solid> now;
      for (const auto& s : v.solids) {
        if (s.group == group) now.push_back(s);
      }
      if (now.empty()) continue;  // vanished together
      ASSERT_EQ(now.size(), parts.size()) << "group " << group << " visit " << v.index;
      const double spread0 = (parts[1].center - parts[0].center).norm();
      const double spread1 = (now[1].center - now[0].center).norm();
      EXPECT_NEAR(spread0, spread1, 1e-9);
      EXPECT_NEAR(now[1].yaw - now[0].yaw, parts[1].yaw - parts[0].yaw, 1e-9);
      moved_groups += now[0].center != parts[0].center;
    }
  }
  EXPECT_GT(moved_groups, 0) << "some composite prop moved in four visits";
}

TEST(FuseDepth, AveragesNoisyViewsWithKnownPoses) {
  const Place room = EmptyRoom();
  SensorOptions noisy;
  noisy.edge_dropout = 0;
  std::vector<RgbdFrame> others;
  RgbdFrame reference;
  cv::Mat truth;
  for (int i = 0; i < 6; ++i) {
    const Pose pose = LookAlongX(0.5 + 0.05 * i, 3.0 + 0.03 * i, 1.5);
    const RenderedFrame r = Render(room, {}, {}, kCamera, pose, noisy, 100 + i);
    RgbdFrame f;
    f.intrinsics = kCamera;
    f.depth_m = r.depth_m;
    f.color_bgr = r.color_bgr;
    f.T_world_camera = pose;
    if (i == 0) {
      reference = f;
      truth = r.true_depth_m;
    } else {
      others.push_back(f);
    }
  }
  auto fused = mapping::FuseDepth(reference, others);
  ASSERT_TRUE(fused.ok()) << fused.status();
  auto rms = [&](const cv::Mat& depth) {
    cv::Mat diff = depth - truth;
    cv::Mat valid = (depth > 0) & (truth > 0);
    return std::sqrt(cv::mean(diff.mul(diff), valid)[0]);
  };
  EXPECT_LT(rms(*fused), 0.7 * rms(reference.depth_m));
  RgbdFrame unposed = reference;
  unposed.T_world_camera.reset();
  EXPECT_TRUE(absl::IsInvalidArgument(mapping::FuseDepth(unposed, others).status()));
}

TEST(Render, IsBitForBitDeterministicForASeed) {
  auto place = GeneratePlace(3, "L");
  ASSERT_TRUE(place.ok());
  auto visits = GenerateVisits(*place, 3, 1, 0, {}, 4);
  ASSERT_TRUE(visits.ok());
  const auto& pose = (*visits)[0].trajectory[2].T_world_camera;
  const RenderedFrame a = Render(*place, (*visits)[0].solids, {}, kCamera, pose, {}, 42);
  const RenderedFrame b = Render(*place, (*visits)[0].solids, {}, kCamera, pose, {}, 42);
  EXPECT_EQ(cv::norm(a.depth_m, b.depth_m, cv::NORM_INF), 0.0);
  EXPECT_EQ(cv::norm(a.color_bgr, b.color_bgr, cv::NORM_INF), 0.0);
  const RenderedFrame c = Render(*place, (*visits)[0].solids, {}, kCamera, pose, {}, 43);
  EXPECT_GT(cv::norm(a.depth_m, c.depth_m, cv::NORM_INF), 0.0) << "another seed, other noise";
  auto again = GeneratePlace(3, "L");
  EXPECT_EQ(again->footprint, place->footprint);
  EXPECT_EQ(again->solids.size(), place->solids.size());
}

// A person walking through on a "dynamic" visit shows up in the frames, labelled, and in the
// moved masks.
TEST(Generator, DynamicVisitsHaveWalkersThatRenderAsPeople) {
  auto place = GeneratePlace(4, "rect");
  ASSERT_TRUE(place.ok());
  Conditions dynamic;
  dynamic.dynamic = true;
  auto visits = GenerateVisits(*place, 4, 2, 1, dynamic, 20);
  ASSERT_TRUE(visits.ok());
  ASSERT_FALSE((*visits)[1].walkers.empty());
  EXPECT_TRUE((*visits)[0].walkers.empty()) << "the reference visit is quiet";
  const auto& w = (*visits)[1].walkers[0];
  const auto start = (*visits)[1].SolidsAt(0), end = (*visits)[1].SolidsAt(19);
  EXPECT_EQ(start.size(), (*visits)[1].solids.size() + (*visits)[1].walkers.size());
  EXPECT_NEAR((start.back().center - w.from).norm(), 0.0, 1e-9);
  EXPECT_NEAR((end.back().center - w.to).norm(), 0.0, 1e-9);
  EXPECT_EQ(start.back().cls, SemanticClass::kPerson);
}

TEST(Generator, TheCameraKeepsAWalkingPaceWhateverTheFrameCount) {
  // A U place has several loops: the move between them must be walked too.
  for (const char* shape : {"rect", "U"}) {
    auto place = GeneratePlace(7, shape);
    ASSERT_TRUE(place.ok());
    for (int frames : {30, 300, 1200}) {
      auto visits = GenerateVisits(*place, 7, 1, 0, {}, frames);
      ASSERT_TRUE(visits.ok());
      const auto& tr = (*visits)[0].trajectory;
      ASSERT_EQ(tr.size(), static_cast<size_t>(frames));
      int at_30hz = 0;
      for (size_t i = 1; i < tr.size(); ++i) {
        const double dt = tr[i].timestamp_s - tr[i - 1].timestamp_s;
        ASSERT_GE(dt, 1.0 / 30.0 - 1e-5) << shape << " " << frames << " frame " << i;
        EXPECT_LE(TranslationDistanceM(tr[i - 1].T_world_camera, tr[i].T_world_camera) / dt,
                  kMaxWalkSpeedMps * 1.001)
            << shape << " " << frames << " frame " << i;
        EXPECT_LE(RotationAngleRad(tr[i - 1].T_world_camera, tr[i].T_world_camera) / dt,
                  kMaxTurnRateRadps * 1.001)
            << shape << " " << frames << " frame " << i;
        at_30hz += dt < 1.0 / 30.0 + 1e-5;  // timestamps are Unix times: ~1e-7 s steps
      }
      // Fewer frames: the same path, so a visit as long in time.
      if (frames == 30) {
        EXPECT_GT(tr.back().timestamp_s - tr.front().timestamp_s, 5.0) << shape;
      }
      // Many frames: the camera's own rate (30 Hz) nearly throughout.
      if (frames == 1200) {
        EXPECT_GT(at_30hz, frames * 9 / 10) << shape;
      }
    }
  }
}

// The simulated wheel odometry (odometry.txt, issue 35): exact without noise, and with the
// default noise it drifts like a robot's wheels, ~1-2 % of the distance, never jumping, with the
// camera's height and tilt exact; deterministic in its seed.
TEST(WheelOdometry, DriftsAFewPercentOfTheDistanceAndNeverJumps) {
  auto place = GeneratePlace(7, "U");
  ASSERT_TRUE(place.ok());
  auto visits = GenerateVisits(*place, 7, 1, 0, {}, 900);
  ASSERT_TRUE(visits.ok());
  const auto& truth = (*visits)[0].trajectory;
  const auto exact = SimulateWheelOdometry(truth, {0, 0, 0, 0}, 1);
  ASSERT_EQ(exact.size(), truth.size());
  for (size_t i = 0; i < truth.size(); ++i) {
    EXPECT_LT(TranslationDistanceM(exact[i].T_world_camera, truth[i].T_world_camera), 1e-9) << i;
    EXPECT_LT(RotationAngleRad(exact[i].T_world_camera, truth[i].T_world_camera), 1e-9) << i;
  }
  double path_m = 0;
  for (size_t i = 1; i < truth.size(); ++i) {
    path_m += TranslationDistanceM(truth[i - 1].T_world_camera, truth[i].T_world_camera);
  }
  std::vector<double> end_error;
  for (uint64_t seed = 1; seed <= 8; ++seed) {
    const auto wheel = SimulateWheelOdometry(truth, {}, seed);
    ASSERT_EQ(wheel.size(), truth.size());
    for (size_t i = 1; i < wheel.size(); ++i) {
      const double step =
          TranslationDistanceM(wheel[i - 1].T_world_camera, wheel[i].T_world_camera);
      const double true_step =
          TranslationDistanceM(truth[i - 1].T_world_camera, truth[i].T_world_camera);
      ASSERT_LT(std::abs(step - true_step), 0.1 * true_step + 1e-3) << "seed " << seed << " " << i;
      ASSERT_NEAR(wheel[i].T_world_camera.translation.z(), truth[i].T_world_camera.translation.z(),
                  1e-9);
    }
    end_error.push_back(
        TranslationDistanceM(wheel.back().T_world_camera, truth.back().T_world_camera) / path_m);
    const auto again = SimulateWheelOdometry(truth, {}, seed);
    EXPECT_EQ(again.back().T_world_camera.translation, wheel.back().T_world_camera.translation);
  }
  std::sort(end_error.begin(), end_error.end());
  std::cerr << "wheel odometry over " << path_m << " m: end error " << end_error.front() * 100
            << "-" << end_error.back() * 100 << " % of the distance (median "
            << end_error[end_error.size() / 2] * 100 << " %)\n";
  EXPECT_GT(end_error[end_error.size() / 2], 0.002) << "it drifts";
  EXPECT_LT(end_error[end_error.size() / 2], 0.05) << "a few percent, not more";
}

TEST(Generator, RejectsBadArguments) {
  EXPECT_TRUE(absl::IsInvalidArgument(GeneratePlace(1, "octagon").status()));
  auto place = GeneratePlace(1, "rect");
  ASSERT_TRUE(place.ok());
  EXPECT_TRUE(absl::IsInvalidArgument(GenerateVisits(*place, 1, 0, 6, {}, 10).status()));
  EXPECT_TRUE(absl::IsInvalidArgument(GenerateVisits(*place, 1, 2, -1, {}, 10).status()));
  EXPECT_TRUE(absl::IsInvalidArgument(ParseConditions("weather").status()));
  auto c = ParseConditions("lighting,scenery,dynamic");
  ASSERT_TRUE(c.ok());
  EXPECT_TRUE(c->lighting && c->scenery && c->dynamic);
  for (const char* shape : {"rect", "square", "L", "T", "U"}) {
    auto p = GeneratePlace(11, shape);
    ASSERT_TRUE(p.ok()) << shape;
    // Counter-clockwise footprints: positive signed area.
    double area = 0;
    for (size_t i = 0; i < p->footprint.size(); ++i) {
      const auto& a = p->footprint[i];
      const auto& b = p->footprint[(i + 1) % p->footprint.size()];
      area += a.x() * b.y() - b.x() * a.y();
    }
    EXPECT_GT(area / 2, 9.0) << shape;
    EXPECT_LT(area / 2, 150.0) << shape;
  }
}

// Two visits that differ by one box: moved/ marks exactly the pixels where the box is now or
// was before, and the TUM folder reads back with its exact poses.
TEST(Writer, MovedMasksCoverExactlyTheMovedObjectAndTumReadsBack) {
  testing::TempDir tmp;
  const Place room = EmptyRoom();
  Solid box;
  box.cls = SemanticClass::kBox;
  box.instance = 5;
  box.movable = true;
  box.center = {3.0, 2.6};
  box.size = {0.4, 0.4, 0.8};
  Visit first, second;
  first.index = 0;
  first.solids = {box};
  second.index = 1;
  box.center = {3.0, 3.6};  // moved 1 m sideways
  second.solids = {box};
  for (Visit* v : {&first, &second}) {
    for (int f = 0; f < 3; ++f) {
      v->trajectory.push_back({1000.0 + v->index * 100 + f / 30.0, LookAlongX(0.5, 3.0, 1.2)});
    }
  }
  WriteOptions options;
  options.intrinsics = kCamera;
  options.sensor = Exact();
  auto summary = WriteVisit(tmp.File("v1"), room, second, &first, options);
  ASSERT_TRUE(summary.ok()) << summary.status();
  EXPECT_EQ(summary->frames, 3);

  auto seq = io::ReadTumSequence(tmp.File("v1"));
  ASSERT_TRUE(seq.ok()) << seq.status();
  ASSERT_EQ(seq->frames.size(), 3u);
  ASSERT_TRUE(seq->frames[0].T_world_camera.has_value());
  EXPECT_NEAR(seq->frames[0].T_world_camera->translation.x(), 0.5, 1e-6);
  ASSERT_TRUE(seq->intrinsics.has_value());
  EXPECT_DOUBLE_EQ(seq->intrinsics->fx, 262.5);
  // A simulated accelerometer: gravity within a degree of the truth's -z.
  EXPECT_EQ(seq->frames_with_gravity, 3);
  const Eigen::Vector3d down =
      seq->frames[0].T_world_camera->rotation.inverse() * -Eigen::Vector3d::UnitZ();
  EXPECT_GT(seq->frames[0].gravity_camera->dot(down), std::cos(M_PI / 180));

  const std::string name = std::filesystem::path(seq->frames[0].rgb_path).filename().string();
  const cv::Mat moved = cv::imread(tmp.File("v1/moved/" + name), cv::IMREAD_UNCHANGED);
  const cv::Mat now = cv::imread(tmp.File("v1/labels/instance/" + name), cv::IMREAD_UNCHANGED);
  const RenderedFrame before =
      Render(room, first.solids, {}, kCamera, LookAlongX(0.5, 3.0, 1.2), Exact(), 1);
  const cv::Mat box_now = now == 5;
  const cv::Mat box_before = before.instance_id == 5;
  ASSERT_GT(cv::countNonZero(box_now), 100);
  ASSERT_GT(cv::countNonZero(box_before), 100);
  cv::Mat expected = box_now | box_before;
  EXPECT_EQ(cv::countNonZero(moved != expected), 0) << "moved = where the box is or was";
  const cv::Mat depth = cv::imread(tmp.File("v1/depth/" + name), cv::IMREAD_UNCHANGED);
  EXPECT_EQ(depth.type(), CV_16UC1);
}

}  // namespace
}  // namespace lifemap::sim
