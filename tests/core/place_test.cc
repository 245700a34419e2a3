#include <algorithm>
#include <cmath>

#include <fstream>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>

#include "core/place/descriptor.h"
#include "core/place/floor_plan.h"
#include "core/place/layout_check.h"
#include "core/place/serialize.h"
#include "core/planes/planes.h"
#include "core/sim/generator.h"
#include "core/sim/renderer.h"
#include "tests/testing/test_util.h"

namespace lifemap::place {
namespace {

CameraIntrinsics Kinect() { return {525, 525, 319.5, 239.5, 640, 480}; }

// A visit of a synthetic place rendered and folded into a floor plan, every `stride`-th frame.
struct Built {
  sim::Place place;
  absl::StatusOr<FloorPlan> plan = absl::UnknownError("not built");
};

// `bend_deg`: the track as a drifting tracker would report it, pitched by up to this much
// about the first camera and rising 5 cm a degree by the last frame (issue 54). `tilt_deg`: the
// whole track rigidly tilted about the first camera, as a visit's frame is when its first
// camera was taken as level while it looked down (issue 54).
Built BuildVisit(uint64_t seed, const std::string& shape, int frames = 90, int stride = 3,
                 double bend_deg = 0, double tilt_deg = 0, const FloorPlanOptions& options = {}) {
  Built b;
  b.place = *sim::GeneratePlace(seed, shape);
  auto visits = sim::GenerateVisits(b.place, seed, 1, 0, sim::Conditions{}, frames);
  EXPECT_TRUE(visits.ok());
  FloorPlanBuilder builder(options);
  const auto& v = (*visits)[0];
  for (size_t f = 0; f < v.trajectory.size(); f += static_cast<size_t>(stride)) {
    const auto frame = sim::Render(b.place, v.SolidsAt(f), v.lighting, Kinect(),
                                   v.trajectory[f].T_world_camera, sim::SensorOptions{}, f + 1);
    Pose reported = v.trajectory[f].T_world_camera;
    if (bend_deg > 0) {
      const double share = static_cast<double>(f) / static_cast<double>(v.trajectory.size());
      const Eigen::Vector3d pivot = v.trajectory[0].T_world_camera.translation;
      const Eigen::AngleAxisd bend(share * bend_deg * M_PI / 180.0, Eigen::Vector3d::UnitX());
      reported.translation = pivot + bend * (reported.translation - pivot) +
                             Eigen::Vector3d(0, 0, 0.05 * share * bend_deg);
      reported.rotation = Eigen::Quaterniond(bend) * reported.rotation;
    }
    if (tilt_deg != 0) {
      const Eigen::Vector3d pivot = v.trajectory[0].T_world_camera.translation;
      const Eigen::AngleAxisd tilt(tilt_deg * M_PI / 180.0, Eigen::Vector3d(1, 1, 0).normalized());
      reported.translation = pivot + tilt * (reported.translation - pivot);
      reported.rotation = Eigen::Quaterniond(tilt) * reported.rotation;
    }
    EXPECT_TRUE(builder.AddDepthKeyframe(frame.depth_m, Kinect(), reported).ok());
  }
  b.plan = builder.Build();
  return b;
}

TEST(FloorPlan, RectangularRoomGivesFourWallsOfTheRightLengthsAtRightAngles) {
  const Built b = BuildVisit(3, "rect");
  ASSERT_TRUE(b.plan.ok()) << b.plan.status();
  const auto d = Describe(*b.plan);
  std::cerr << DescriptorText(d);
  ASSERT_EQ(b.plan->walls.size(), 4u);
  EXPECT_NEAR(b.plan->floor_height_m, 0.0, 0.03);
  // The footprint's edge lengths, in some rotation.
  std::vector<double> truth;
  const auto& fp = b.place.footprint;
  for (size_t i = 0; i < fp.size(); ++i) truth.push_back((fp[(i + 1) % fp.size()] - fp[i]).norm());
  std::vector<double> got;
  for (const auto& c : d.corners) {
    got.push_back(c.length_m);
    EXPECT_NEAR(c.angle_deg, 90.0, 3.0);
  }
  std::sort(truth.begin(), truth.end());
  std::sort(got.begin(), got.end());
  for (size_t i = 0; i < 4; ++i) EXPECT_NEAR(got[i], truth[i], 0.15) << i;

  // Every door and window of the room is found on its wall, of its type, where it is. (The
  // connecting door is open: through it the next room shows.)
  int found = 0, expected = 0;
  for (const auto& o : b.place.openings) {
    if (o.room != 0) continue;
    ++expected;
    const Eigen::Vector2d start = fp[static_cast<size_t>(o.wall)];
    for (const auto& w : b.plan->walls) {
      if ((w.start - start).norm() > 0.3) continue;
      for (const auto& got_o : w.openings) {
        const bool type = (got_o.type == OpeningType::kDoor) == (o.type == sim::OpeningType::kDoor);
        if (type && std::abs(got_o.from_m - o.offset_m) < 0.2 &&
            std::abs(got_o.length() - o.width_m) < 0.25) {
          ++found;
        }
      }
    }
  }
  EXPECT_EQ(found, expected);
  EXPECT_EQ(expected, 3) << "seed 3's rect room: a door and two windows";

  // A rigid track sees one level floor (issue 54).
  EXPECT_GE(b.plan->floor_agreement.keyframes, 10);
  EXPECT_LT(b.plan->floor_agreement.tilt_deg_p90, 1.5);
  EXPECT_LT(b.plan->floor_agreement.drift_m, 0.04);

  // The stored forms round-trip.
  auto plan = FloorPlanFromJson(FloorPlanToJson(*b.plan));
  ASSERT_TRUE(plan.ok()) << plan.status();
  EXPECT_EQ(plan->floor_agreement.keyframes, b.plan->floor_agreement.keyframes);
  EXPECT_DOUBLE_EQ(plan->floor_agreement.tilt_deg_p90, b.plan->floor_agreement.tilt_deg_p90);
  EXPECT_EQ(DescriptorText(Describe(*plan)), DescriptorText(d));
  auto desc = DescriptorFromJson(DescriptorToJson(d));
  ASSERT_TRUE(desc.ok()) << desc.status();
  EXPECT_NEAR(MatchDescriptors(*desc, d).difference, 0.0, 1e-9);
  EXPECT_TRUE(absl::IsInvalidArgument(DescriptorFromJson("{\"corners\": 3}").status()));
  EXPECT_TRUE(absl::IsInvalidArgument(FloorPlanFromJson("not json").status()));
}

// Issue 54: the same visit as a drifting tracker reports it, its floor tilting and rising.
TEST(FloorPlan, ABentTrackSeesItsFloorTiltAndRise) {
  const Built b = BuildVisit(3, "rect", 90, 3, 8.0);
  ASSERT_TRUE(b.plan.ok()) << b.plan.status();
  std::cerr << "bent 8 deg: tilt p90 " << b.plan->floor_agreement.tilt_deg_p90
            << " deg, level drift " << b.plan->floor_agreement.drift_m << " m of "
            << b.plan->floor_agreement.keyframes << " key frames\n";
  EXPECT_GE(b.plan->floor_agreement.keyframes, 10);
  EXPECT_GT(b.plan->floor_agreement.tilt_deg_p90, 5.0);
  EXPECT_GT(b.plan->floor_agreement.drift_m, 0.15);
}

// Issue 54: a visit whose frame is tilted 20 degrees (its first camera looked down at a lamp,
// came without gravity and was taken as level) gets no plan, unless the plan takes its up from
// the floor it sees; then the walls are the untilted visit's.
TEST(FloorPlan, ATiltedFrameIsLevelledByTheFloorItSees) {
  const Built tilted = BuildVisit(3, "rect", 90, 3, 0, 20.0);
  EXPECT_FALSE(tilted.plan.ok() && tilted.plan->walls.size() == 4u)
      << "a 20 degree tilt left the rect room's four walls standing: the test shows nothing";
  FloorPlanOptions levelled;
  levelled.up_from_floor = true;
  const Built b = BuildVisit(3, "rect", 90, 3, 0, 20.0, levelled);
  ASSERT_TRUE(b.plan.ok()) << b.plan.status();
  ASSERT_EQ(b.plan->walls.size(), 4u);
  const Eigen::Vector3d true_up =
      Eigen::AngleAxisd(20.0 * M_PI / 180.0, Eigen::Vector3d(1, 1, 0).normalized()) *
      Eigen::Vector3d::UnitZ();
  EXPECT_LT(std::acos(std::min(1.0, b.plan->up.dot(true_up))) * 180 / M_PI, 1.0);
  EXPECT_LT(b.plan->floor_agreement.tilt_deg_p90, 1.5);
  std::vector<double> got, want;
  for (const auto& c : Describe(*b.plan).corners) got.push_back(c.length_m);
  const auto& fp = b.place.footprint;
  for (size_t i = 0; i < fp.size(); ++i) want.push_back((fp[(i + 1) % fp.size()] - fp[i]).norm());
  std::sort(got.begin(), got.end());
  std::sort(want.begin(), want.end());
  for (size_t i = 0; i < 4; ++i) EXPECT_NEAR(got[i], want[i], 0.15) << i;
  // The plan's basis is stored with it: the layout check of a stored plan reads heights along it.
  auto stored = FloorPlanFromJson(FloorPlanToJson(*b.plan));
  ASSERT_TRUE(stored.ok()) << stored.status();
  EXPECT_TRUE(stored->up.isApprox(b.plan->up, 1e-9));
  EXPECT_TRUE(stored->e1.isApprox(b.plan->e1, 1e-9));
  // A stored basis that is not one is refused, naming the field.
  std::string bad = FloorPlanToJson(*b.plan);
  const size_t at = bad.find("\"up\":[");
  ASSERT_NE(at, std::string::npos) << bad;
  bad.replace(at, bad.find(']', at) - at + 1, "\"up\":[0,0,2]");
  const auto refused = FloorPlanFromJson(bad);
  EXPECT_TRUE(absl::IsInvalidArgument(refused.status())) << refused.status();
  EXPECT_NE(refused.status().message().find("up must be a unit vector"), std::string::npos)
      << refused.status();
}

// Where no key frame shows a floor, the plan waits, then takes world_up.
TEST(FloorPlan, LevellingWaitsForAFloorThenGivesUp) {
  FloorPlanOptions o;
  o.up_from_floor = true;
  o.level_max_wait_keyframes = 3;
  FloorPlanBuilder builder(o);
  // A wall 1 m ahead filling the view: no floor.
  cv::Mat wall(480, 640, CV_32F, cv::Scalar(1.0f));
  Pose level = Pose::FromIsometry(Eigen::Isometry3d::Identity());
  ASSERT_TRUE(builder.AddDepthKeyframe(wall, Kinect(), level).ok());
  ASSERT_TRUE(builder.AddDepthKeyframe(wall, Kinect(), level).ok());
  auto waiting = builder.Build();
  EXPECT_TRUE(absl::IsFailedPrecondition(waiting.status()));
  EXPECT_NE(waiting.status().message().find("2 key frames waiting"), std::string::npos)
      << waiting.status();
  EXPECT_EQ(builder.keyframes(), 2);
  ASSERT_TRUE(builder.AddDepthKeyframe(wall, Kinect(), level).ok());
  EXPECT_EQ(builder.keyframes(), 3);
  auto plan = builder.Build();  // world_up taken: now it fails for the floor it never saw
  EXPECT_EQ(plan.status().message().find("waiting"), std::string::npos) << plan.status();
  EXPECT_NE(plan.status().message().find("no floor"), std::string::npos) << plan.status();
}

TEST(FloorPlan, AWallSeenInPartOrNotAtAllStillClosesTheOutline) {
  // Seed 3's rectangular room (6.65 × 4.09 m) walked round, but without the key frames that
  // look towards the wall at the top of the footprint: the outline still closes, across that
  // wall where it was never seen, along it where it was seen in part.
  const auto place = *sim::GeneratePlace(3, "rect");
  const auto visits = sim::GenerateVisits(place, 3, 1, 0, sim::Conditions{}, 90);
  ASSERT_TRUE(visits.ok());
  const auto& v = (*visits)[0];
  double top = 0;
  for (const auto& p : place.footprint) top = std::max(top, p.y());
  auto build = [&](double max_forward_y) {
    FloorPlanBuilder builder;
    for (size_t f = 0; f < v.trajectory.size(); f += 3) {
      const Pose& pose = v.trajectory[f].T_world_camera;
      if ((pose.rotation * Eigen::Vector3d::UnitZ()).y() > max_forward_y) continue;
      const auto frame = sim::Render(place, v.SolidsAt(f), v.lighting, Kinect(), pose,
                                     sim::SensorOptions{}, f + 1);
      EXPECT_TRUE(builder.AddDepthKeyframe(frame.depth_m, Kinect(), pose).ok());
    }
    return builder.Build();
  };
  for (double max_forward_y : {0.2, 0.6}) {
    SCOPED_TRACE(max_forward_y);
    const auto plan = build(max_forward_y);
    ASSERT_TRUE(plan.ok()) << plan.status();
    std::cerr << DescriptorText(Describe(*plan));
    ASSERT_EQ(plan->walls.size(), 4u);
    int unseen = 0;
    for (const auto& w : plan->walls) {
      EXPECT_TRUE(std::abs(w.length() - 6.653) < 0.15 || std::abs(w.length() - 4.093) < 0.15)
          << w.length();
      if (w.observed_m2 > 0) continue;
      ++unseen;
      EXPECT_TRUE(w.openings.empty());
      EXPECT_NEAR(0.5 * (w.start.y() + w.end.y()), top, 0.1);
    }
    EXPECT_EQ(unseen, max_forward_y < 0.5 ? 1 : 0);
  }
}

TEST(LayoutCheck, AViewAgreesWithItsPlaceOnlyWhereItWasTaken) {
  // Seed 3's room and its plan from 30 key frames; every 10th frame of the walk checked at its
  // true pose, and at the same pose turned 90 degrees or moved 1.5 m forward. At the truth no
  // reading lies beyond a wall; each view placed wrongly sees through the plan's walls or
  // stands outside them in at least one of the two.
  const Built b = BuildVisit(3, "rect");
  ASSERT_TRUE(b.plan.ok()) << b.plan.status();
  const auto visits = sim::GenerateVisits(b.place, 3, 1, 0, sim::Conditions{}, 90);
  ASSERT_TRUE(visits.ok());
  const auto& v = (*visits)[0];
  auto contradicts = [](const LayoutAgreement& a) {
    return !a.camera_inside || a.ThroughShare() > 0.1;
  };
  for (size_t f = 5; f < v.trajectory.size(); f += 10) {
    SCOPED_TRACE(f);
    const Pose& truth = v.trajectory[f].T_world_camera;
    const auto frame = sim::Render(b.place, v.SolidsAt(f), v.lighting, Kinect(), truth,
                                   sim::SensorOptions{}, f + 7);
    const LayoutAgreement at_truth = CheckLayout(*b.plan, frame.depth_m, Kinect(), truth);
    EXPECT_GT(at_truth.readings, 3000);
    EXPECT_TRUE(at_truth.camera_inside);
    EXPECT_LT(at_truth.ThroughShare(), 0.01);
    Pose turned = truth;
    turned.rotation =
        Eigen::Quaterniond(Eigen::AngleAxisd(M_PI / 2, Eigen::Vector3d::UnitZ())) * truth.rotation;
    Pose moved = truth;
    moved.translation += truth.rotation * Eigen::Vector3d(0, 0, 1.5);  // forward
    EXPECT_TRUE(contradicts(CheckLayout(*b.plan, frame.depth_m, Kinect(), turned)) ||
                contradicts(CheckLayout(*b.plan, frame.depth_m, Kinect(), moved)));
  }
}

TEST(LayoutCheck, AnotherRoomsViewsSeeThroughThePlan) {
  // Seed 3's plan against views of seed 5's L-shaped room at their own poses, as matches to
  // shared furniture would place them. One view alone passes about half the time (its readings
  // stop short of the walls that are not there); a visit's views together do not: the server
  // checks every keyframe of a visit.
  const Built b = BuildVisit(3, "rect");
  ASSERT_TRUE(b.plan.ok()) << b.plan.status();
  const auto other = *sim::GeneratePlace(5, "L");
  const auto visits = sim::GenerateVisits(other, 5, 1, 0, sim::Conditions{}, 90);
  ASSERT_TRUE(visits.ok());
  const auto& v = (*visits)[0];
  int readings = 0, through = 0, passing = 0, views = 0;
  for (size_t f = 5; f < v.trajectory.size(); f += 10) {
    const Pose& pose = v.trajectory[f].T_world_camera;
    const auto frame =
        sim::Render(other, v.SolidsAt(f), v.lighting, Kinect(), pose, sim::SensorOptions{}, f + 7);
    const LayoutAgreement a = CheckLayout(*b.plan, frame.depth_m, Kinect(), pose);
    readings += a.readings;
    through += a.through_walls;
    passing += a.camera_inside && a.ThroughShare() < 0.01;
    ++views;
  }
  EXPECT_GE(passing, 2) << "of " << views;  // what one view can pass
  EXPECT_GT(static_cast<double>(through) / readings, 0.1);
}

TEST(LayoutCheck, NoReadingsNoWallsNoCrossings) {
  FloorPlan empty;
  cv::Mat depth(480, 640, CV_32FC1, cv::Scalar(2.0f));
  const LayoutAgreement a = CheckLayout(empty, depth, Kinect(), Pose{});
  EXPECT_EQ(a.readings, 60 * 80);
  EXPECT_EQ(a.through_walls, 0);
  EXPECT_FALSE(a.camera_inside);
  const LayoutAgreement none =
      CheckLayout(empty, cv::Mat(480, 640, CV_32FC1, cv::Scalar(0.0f)), Kinect(), Pose{});
  EXPECT_EQ(none.readings, 0);
  EXPECT_EQ(none.ThroughShare(), 0.0);
}

// A plan whose walls run counter-clockwise through `corners`, each seen (1 m² of it).
FloorPlan PlanThrough(const std::vector<Eigen::Vector2d>& corners) {
  FloorPlan plan;
  for (size_t i = 0; i < corners.size(); ++i) {
    Wall w;
    w.start = corners[i];
    w.end = corners[(i + 1) % corners.size()];
    w.observed_m2 = 1.0;
    plan.walls.push_back(w);
  }
  return plan;
}

TEST(ComparePlans, AnLRoomsInnerCornerStandsOnARectangularRoomsFloor) {
  // A 6 m × 4 m room, and an L room of the same outer size whose corner (2.5 m × 2 m) is cut.
  const FloorPlan rect = PlanThrough({{0, 0}, {6, 0}, {6, 4}, {0, 4}});
  const FloorPlan l_room = PlanThrough({{0, 0}, {6, 0}, {6, 2}, {3.5, 2}, {3.5, 4}, {0, 4}});
  // The same room placed where it is: every wall on a wall.
  const PlanAgreement same = ComparePlans(rect, rect, Pose{});
  EXPECT_NEAR(same.seen_wall_m, 20.0, 1e-6);
  EXPECT_EQ(same.on_floor_m, 0.0);
  // The L room's inner corner walls (2.5 m and 2 m) lie on the rectangle's floor, except their
  // ends within 0.5 m of its walls; the rectangle's walls lie outside or on the L room's.
  const PlanAgreement l_in_rect = ComparePlans(l_room, rect, Pose{});
  EXPECT_NEAR(l_in_rect.on_floor_m, 2.0 + 1.5, 0.11);
  EXPECT_NEAR(l_in_rect.OnFloorShare(), 3.5 / 20.0, 0.01);
  EXPECT_EQ(ComparePlans(rect, l_room, Pose{}).on_floor_m, 0.0);
  // The rectangle placed 1 m off along x: its wall at x = 1 (inside by 1 m) stands on the floor.
  Pose shifted;
  shifted.translation = Eigen::Vector3d(1, 0, 0);
  EXPECT_NEAR(ComparePlans(rect, rect, shifted).on_floor_m, 3.0, 0.11);
  // A wall not seen says nothing; fewer than 3 walls, no outline.
  FloorPlan unseen = l_room;
  unseen.walls[2].observed_m2 = 0;
  unseen.walls[3].observed_m2 = 0;
  EXPECT_EQ(ComparePlans(unseen, rect, Pose{}).on_floor_m, 0.0);
  FloorPlan two = rect;
  two.walls.resize(2);
  EXPECT_EQ(ComparePlans(l_room, two, Pose{}).seen_wall_m, 0.0);
  EXPECT_EQ(ComparePlans(two, rect, Pose{}).OnFloorShare(), 0.0);
}

TEST(FloorPlan, AscendingStairsAreFoundNearTheirWall) {
  // Seed 1's square room has a flight of 7 steps up (run 0.29 m, rise 0.18 m, 1.0 m wide, its
  // centre 0.52 m from the nearest wall).
  const Built b = BuildVisit(1, "square");
  ASSERT_TRUE(b.plan.ok()) << b.plan.status();
  ASSERT_EQ(b.place.stairs.size(), 1u);
  ASSERT_EQ(b.plan->stairs.size(), 1u);
  const StairFlight& f = b.plan->stairs[0];
  const sim::Stairs& truth = b.place.stairs[0];
  EXPECT_EQ(f.ascending, truth.up);
  EXPECT_NEAR(f.rise_m, truth.rise_m, 0.02);
  // The top tread is seen least; the flight's length and width come out short by up to a step.
  EXPECT_NEAR(f.length_m, truth.run_m * truth.steps, 0.4);
  EXPECT_NEAR(f.width_m, truth.width_m, 0.3);
  EXPECT_NEAR(f.distance_to_wall_m, 0.52, 0.15);
}

TEST(FloorPlan, DescendingStairsAreFoundWhenLookedInto) {
  // Seed 19's square room has a flight of 5 steps down (rise 0.19 m, run 0.30 m) in a hole in
  // the floor. The simulated loop looks out at the walls and never into the hole, so the visit
  // adds key frames from the top of the flight looking down it, as a small robot would before
  // going down (camera 1.0 m high). Of each lower tread only a strip shows past the one above;
  // from 1.5 m the strips of the deeper ones, over 2 m away, are within the sensor's noise at
  // the quadtree's 8-pixel regions and only 2 treads are found, too few for a flight.
  const auto place = *sim::GeneratePlace(19, "square");
  ASSERT_EQ(place.stairs.size(), 1u);
  const sim::Stairs& truth = place.stairs[0];
  ASSERT_FALSE(truth.up);
  const auto visits = sim::GenerateVisits(place, 19, 1, 0, sim::Conditions{}, 90);
  ASSERT_TRUE(visits.ok());
  const auto& v = (*visits)[0];
  FloorPlanBuilder builder;
  auto add = [&](const Pose& pose, uint64_t seed) {
    const auto frame =
        sim::Render(place, v.SolidsAt(0), v.lighting, Kinect(), pose, sim::SensorOptions{}, seed);
    ASSERT_TRUE(builder.AddDepthKeyframe(frame.depth_m, Kinect(), pose).ok());
  };
  for (size_t f = 0; f < v.trajectory.size(); f += 3) add(v.trajectory[f].T_world_camera, f + 1);
  const Eigen::Vector2d dir(std::cos(truth.yaw), std::sin(truth.yaw));
  const Eigen::Vector2d side(-dir.y(), dir.x());
  for (int i = 0; i < 5; ++i) {
    // 0.3 m before the first step, 1.0 m high, pitched 60° down, a little to either side.
    const Eigen::Vector2d at = truth.origin - 0.3 * dir + (0.1 * (i - 2)) * side;
    const Eigen::Vector3d forward =
        Eigen::Vector3d(dir.x(), dir.y(), -std::sqrt(3.0)).normalized();  // 60° down the flight
    const Eigen::Vector3d right = forward.cross(Eigen::Vector3d::UnitZ()).normalized();
    Eigen::Matrix3d R;
    R.col(0) = right;
    R.col(1) = forward.cross(right);
    R.col(2) = forward;
    Pose pose;
    pose.translation = Eigen::Vector3d(at.x(), at.y(), 1.0);
    pose.rotation = Eigen::Quaterniond(R);
    add(pose, 1000 + static_cast<uint64_t>(i));
  }
  const auto plan = builder.Build();
  ASSERT_TRUE(plan.ok()) << plan.status();
  ASSERT_EQ(plan->stairs.size(), 1u);
  const StairFlight& f = plan->stairs[0];
  EXPECT_FALSE(f.ascending);
  EXPECT_NEAR(f.rise_m, truth.rise_m, 0.02);
  EXPECT_GE(f.steps, 3);
  EXPECT_LE(f.steps, truth.steps);
  const Eigen::Vector2d centre = truth.origin + 0.5 * truth.run_m * truth.steps * dir;
  EXPECT_LT((f.center - centre).norm(), 0.5);
}

TEST(Descriptor, RotatedOrMirroredStartMatchesTheSamePlace) {
  PlaceDescriptor d;
  d.corners = {{5.0, 90, {{OpeningType::kDoor, 0.9, 1.0}}},
               {3.0, 90, {}},
               {5.0, 90, {{OpeningType::kWindow, 1.2, 2.0}}},
               {3.0, 90, {}}};
  PlaceDescriptor other = d;
  other.corners[0].length_m = 6.0;
  other.corners[2].length_m = 6.0;
  // Start at corner 2 of d.
  PlaceDescriptor rotated;
  for (size_t i = 0; i < 4; ++i) rotated.corners.push_back(d.corners[(i + 2) % 4]);
  const auto same = MatchDescriptors(rotated, d);
  EXPECT_NEAR(same.difference, 0.0, 1e-9);
  EXPECT_EQ(same.start, 2);
  EXPECT_NEAR(same.score, 1.0, 1e-9);
  // Walked the other way round (a mirrored start): walls reversed and read from their ends.
  PlaceDescriptor mirrored;
  for (size_t k = 0; k < 4; ++k) {
    CornerEntry e = d.corners[3 - k];
    e.angle_deg = 90;
    for (auto& o : e.openings) o.distance_m = e.length_m - o.distance_m - o.length_m;
    mirrored.corners.push_back(e);
  }
  const auto m = MatchDescriptors(mirrored, d);
  EXPECT_NEAR(m.difference, 0.0, 1e-9);
  EXPECT_TRUE(m.reversed);
  // A different room scores worse; a closed door costs little, a missing window more.
  EXPECT_GT(MatchDescriptors(rotated, other).difference, 1.9);
  PlaceDescriptor closed = d;
  closed.corners[0].openings.clear();
  PlaceDescriptor no_window = d;
  no_window.corners[2].openings.clear();
  const double closed_cost = MatchDescriptors(closed, d).difference;
  EXPECT_GT(closed_cost, 0.0);
  EXPECT_LT(closed_cost, MatchDescriptors(no_window, d).difference);
}

TEST(FloorPlan, BadInputsGiveClearStatuses) {
  FloorPlanBuilder builder;
  planes::PlaneSet empty;
  Pose bad;
  bad.rotation = Eigen::Quaterniond(2, 0, 0, 0);
  EXPECT_TRUE(absl::IsInvalidArgument(builder.AddKeyframe(empty, Kinect(), bad)));
  bad.rotation = Eigen::Quaterniond::Identity();
  bad.translation.x() = std::nan("");
  EXPECT_TRUE(absl::IsInvalidArgument(builder.AddKeyframe(empty, Kinect(), bad)));
  // A single frame: not enough.
  ASSERT_TRUE(builder.AddKeyframe(empty, Kinect(), Pose{}).ok());
  auto one = builder.Build();
  EXPECT_TRUE(absl::IsFailedPrecondition(one.status()));
  EXPECT_NE(one.status().message().find("key frames"), std::string::npos) << one.status();
  // Frames that never see the floor (a camera looking at the ceiling plane).
  planes::PlaneSet ceiling;
  ceiling.planes.emplace_back();
  ceiling.planes[0].normal = Eigen::Vector3f(0, 0, -1);  // camera looking up at it: z up in world
  ceiling.planes[0].offset_m = -1.5f;
  ceiling.planes[0].centroid = Eigen::Vector3f(0, 0, 1.5f);
  ceiling.planes[0].area_m2 = 8;
  Pose up;  // camera z axis along world z: looks at the ceiling
  ASSERT_TRUE(builder.AddKeyframe(ceiling, Kinect(), up).ok());
  auto none = builder.Build();
  EXPECT_TRUE(absl::IsFailedPrecondition(none.status()));
  EXPECT_NE(none.status().message().find("no floor"), std::string::npos) << none.status();
}

}  // namespace
}  // namespace lifemap::place

namespace lifemap::place {
namespace {

TEST(FloorPlan, RealDiningRoomGivesItsFloorAndWalls) {
  // Five posed Kinect frames of a dining room (NYU Depth V2 raw via slambook2; poses camera to
  // world in the first camera's frame, depth in millimetres). No ground truth: the check is that
  // the real data gives a floor at a hand-held camera's height, and walls.
  LIFEMAP_REQUIRE_DATASET(dir, "nyu_raw_slambook2_rgbd5");
  const CameraIntrinsics k{518.0, 519.0, 325.5, 253.5, 640, 480};
  std::ifstream poses(dir + "/pose.txt");
  std::vector<planes::PlaneSet> frames;
  std::vector<Pose> world_camera;
  for (int i = 1; i <= 5; ++i) {
    double t[7];
    for (double& x : t) ASSERT_TRUE(poses >> x) << "pose.txt line " << i;
    Pose pose;
    pose.translation = Eigen::Vector3d(t[0], t[1], t[2]);
    pose.rotation = Eigen::Quaterniond(t[6], t[3], t[4], t[5]).normalized();
    const cv::Mat raw =
        cv::imread(dir + "/depth/" + std::to_string(i) + ".pgm", cv::IMREAD_UNCHANGED);
    ASSERT_EQ(raw.type(), CV_16UC1);
    cv::Mat depth;
    raw.convertTo(depth, CV_32F, 1.0 / 1000);
    auto planes = planes::ExtractPlanes(depth, k);
    ASSERT_TRUE(planes.ok()) << planes.status();
    frames.push_back(*std::move(planes));
    world_camera.push_back(pose);
  }
  // The world's up is not given: take it from the first frame's largest plane facing up in
  // the camera (y down), the floor — as a robot would from its IMU.
  FloorPlanOptions options;
  for (const auto& p : frames[0].planes) {
    if (p.normal.y() < -0.8) {
      options.world_up = world_camera[0].rotation * p.normal.cast<double>();
      break;
    }
  }
  FloorPlanBuilder builder(options);
  for (size_t i = 0; i < frames.size(); ++i) {
    ASSERT_TRUE(builder.AddKeyframe(frames[i], k, world_camera[i]).ok());
  }
  const auto plan = builder.Build();
  ASSERT_TRUE(plan.ok()) << plan.status();
  std::cerr << FloorPlanToJson(*plan) << "\n" << DescriptorText(Describe(*plan));
  const double camera_height =
      world_camera[0].translation.dot(options.world_up.normalized()) - plan->floor_height_m;
  EXPECT_GT(camera_height, 1.0);
  EXPECT_LT(camera_height, 1.8);
  // Vertical planes large enough for walls are found and closed into an outline; whether it is
  // the room's cannot be told without its plan (docs/RESULTS.md shows what comes out).
  EXPECT_GE(plan->walls.size(), 3u);
}

}  // namespace
}  // namespace lifemap::place
