// Planar regions (paper 004, section 3.1): lifemap's quadtree decomposition against PCL's
// OrganizedMultiPlaneSegmentation (integral-image normals + connected planar regions), the
// library a reader would reach for, on the same 640×480 frames in the same run:
// a rendered room of the synthetic world (walls, floor, furniture; Kinect noise) and a real
// TUM fr1 office frame. Counters: planes of at least 2000 points (PCL: inliers), and the share
// of depth pixels they cover.
//
// Also the floor plan's incremental update per key frame (planes + folding them in) and a
// descriptor match against 1,000 stored places.
//
//   build/bin/bench_planes
#include <pcl/features/integral_image_normal.h>
#include <pcl/point_cloud.h>
#include <pcl/point_types.h>
#include <pcl/segmentation/organized_multi_plane_segmentation.h>

#include <random>
#include <string>

#include <benchmark/benchmark.h>
#include <opencv2/imgcodecs.hpp>

#include "core/common/image_codec.h"
#include "core/io/tum_dataset.h"
#include "core/place/descriptor.h"
#include "core/place/floor_plan.h"
#include "core/place/layout_check.h"
#include "core/planes/planes.h"
#include "core/sim/generator.h"
#include "core/sim/renderer.h"

namespace lifemap {
namespace {

struct Sample {
  cv::Mat depth_m;
  CameraIntrinsics k;
  pcl::PointCloud<pcl::PointXYZ>::Ptr cloud;
};

pcl::PointCloud<pcl::PointXYZ>::Ptr ToCloud(const cv::Mat& depth, const CameraIntrinsics& k) {
  pcl::PointCloud<pcl::PointXYZ>::Ptr cloud(new pcl::PointCloud<pcl::PointXYZ>(
      static_cast<uint32_t>(depth.cols), static_cast<uint32_t>(depth.rows)));
  for (int v = 0; v < depth.rows; ++v) {
    for (int u = 0; u < depth.cols; ++u) {
      const float z = depth.at<float>(v, u);
      auto& p = cloud->at(u, v);
      if (z > 0) {
        p.x = static_cast<float>((u - k.cx) / k.fx) * z;
        p.y = static_cast<float>((v - k.cy) / k.fy) * z;
        p.z = z;
      } else {
        p.x = p.y = p.z = std::numeric_limits<float>::quiet_NaN();
      }
    }
  }
  cloud->is_dense = false;
  return cloud;
}

// 0: a rendered room; 1: TUM fr1_xyz's first frame (synthetic room again if absent).
const Sample& GetSample(int which) {
  static const Sample samples[2] = {
      [] {
        Sample s;
        s.k = {525, 525, 319.5, 239.5, 640, 480};
        auto place = sim::GeneratePlace(7, "L");
        auto visits = sim::GenerateVisits(*place, 7, 1, 0, sim::Conditions{}, 30);
        const auto frame =
            sim::Render(*place, (*visits)[0].solids, sim::Lighting{}, s.k,
                        (*visits)[0].trajectory[10].T_world_camera, sim::SensorOptions{}, 1);
        s.depth_m = frame.depth_m;
        s.cloud = ToCloud(s.depth_m, s.k);
        return s;
      }(),
      [] {
        Sample s;
        s.k = {517.3, 516.5, 318.6, 255.3, 640, 480};
        auto seq = io::ReadTumSequence(std::string(LIFEMAP_SOURCE_DIR) +
                                       "/../shared/data/tum_fr1_xyz_subset");
        if (!seq.ok()) return GetSample(0);
        cv::Mat raw = cv::imread(seq->frames[0].depth_path, cv::IMREAD_ANYDEPTH);
        raw.convertTo(s.depth_m, CV_32FC1, 1.0 / 5000.0);
        s.cloud = ToCloud(s.depth_m, s.k);
        return s;
      }()};
  return samples[which];
}

void BM_QuadtreePlanes(benchmark::State& state) {
  const Sample& s = GetSample(static_cast<int>(state.range(0)));
  planes::PlaneSet set;
  for (auto _ : state) set = *planes::ExtractPlanes(s.depth_m, s.k);
  int big = 0, covered = 0;
  for (const auto& p : set.planes) {
    if (p.points >= 2000) ++big, covered += p.points;
  }
  state.counters["planes"] = big;
  state.counters["coverage"] = covered / static_cast<double>(cv::countNonZero(s.depth_m > 0));
}
BENCHMARK(BM_QuadtreePlanes)->Arg(0)->Arg(1)->Unit(benchmark::kMillisecond);

void BM_PclOrganizedMultiPlane(benchmark::State& state) {
  const Sample& s = GetSample(static_cast<int>(state.range(0)));
  std::vector<pcl::PlanarRegion<pcl::PointXYZ>,
              Eigen::aligned_allocator<pcl::PlanarRegion<pcl::PointXYZ>>>
      regions;
  for (auto _ : state) {
    pcl::PointCloud<pcl::Normal>::Ptr normals(new pcl::PointCloud<pcl::Normal>);
    pcl::IntegralImageNormalEstimation<pcl::PointXYZ, pcl::Normal> ne;
    ne.setNormalEstimationMethod(ne.AVERAGE_DEPTH_CHANGE);
    ne.setMaxDepthChangeFactor(0.02f);
    ne.setNormalSmoothingSize(10.0f);
    ne.setInputCloud(s.cloud);
    ne.compute(*normals);
    pcl::OrganizedMultiPlaneSegmentation<pcl::PointXYZ, pcl::Normal, pcl::Label> mps;
    mps.setMinInliers(2000);
    mps.setAngularThreshold(8.0 * M_PI / 180.0);
    mps.setDistanceThreshold(0.02);
    mps.setInputNormals(normals);
    mps.setInputCloud(s.cloud);
    regions.clear();
    mps.segmentAndRefine(regions);
  }
  double covered = 0;
  for (const auto& r : regions) covered += static_cast<double>(r.getCount());
  state.counters["planes"] = static_cast<double>(regions.size());
  state.counters["coverage"] = covered / cv::countNonZero(s.depth_m > 0);
}
BENCHMARK(BM_PclOrganizedMultiPlane)->Arg(0)->Arg(1)->Unit(benchmark::kMillisecond);

// One key frame of a rendered visit: its planes and the fold into a floor plan that has seen
// 20 key frames of the place already.
void BM_FloorPlanUpdate(benchmark::State& state) {
  const CameraIntrinsics k{525, 525, 319.5, 239.5, 640, 480};
  auto place = sim::GeneratePlace(3, "rect");
  auto visits = sim::GenerateVisits(*place, 3, 1, 0, sim::Conditions{}, 90);
  const auto& v = (*visits)[0];
  std::vector<cv::Mat> depths;
  for (size_t f = 0; f < v.trajectory.size(); f += 3) {
    depths.push_back(sim::Render(*place, v.solids, v.lighting, k, v.trajectory[f].T_world_camera,
                                 sim::SensorOptions{}, f + 1)
                         .depth_m);
  }
  place::FloorPlanBuilder warm;
  for (size_t i = 0; i < 20; ++i) {
    warm.AddKeyframe(*planes::ExtractPlanes(depths[i], k), k, v.trajectory[3 * i].T_world_camera)
        .IgnoreError();
  }
  size_t i = 20;
  for (auto _ : state) {
    state.PauseTiming();
    place::FloorPlanBuilder builder = [&] {
      place::FloorPlanBuilder b;
      for (size_t j = 0; j < 20; ++j) {
        b.AddKeyframe(*planes::ExtractPlanes(depths[j], k), k, v.trajectory[3 * j].T_world_camera)
            .IgnoreError();
      }
      return b;
    }();
    state.ResumeTiming();
    const size_t f = i++ % (depths.size() - 20) + 20;
    auto planes = planes::ExtractPlanes(depths[f], k);
    builder.AddKeyframe(*planes, k, v.trajectory[3 * f].T_world_camera).IgnoreError();
    if (state.range(0) == 1) benchmark::DoNotOptimize(builder.Build());
  }
}
BENCHMARK(BM_FloorPlanUpdate)->Arg(0)->Arg(1)->Unit(benchmark::kMillisecond)->Iterations(20);

// The architecture check of one keyframe (issue 15): a rendered view of seed 3's room placed in
// its plan (from 30 key frames) and its depth checked against the walls (0: the depth decoded
// from the 16-bit PNG the store keeps, as the pose-graph worker does; 1: the rays alone).
void BM_LayoutCheck(benchmark::State& state) {
  const CameraIntrinsics k{525, 525, 319.5, 239.5, 640, 480};
  auto place = sim::GeneratePlace(3, "rect");
  auto visits = sim::GenerateVisits(*place, 3, 1, 0, sim::Conditions{}, 90);
  const auto& v = (*visits)[0];
  place::FloorPlanBuilder builder;
  for (size_t f = 0; f < v.trajectory.size(); f += 3) {
    const cv::Mat d = sim::Render(*place, v.solids, v.lighting, k, v.trajectory[f].T_world_camera,
                                  sim::SensorOptions{}, f + 1)
                          .depth_m;
    builder.AddDepthKeyframe(d, k, v.trajectory[f].T_world_camera).IgnoreError();
  }
  const auto plan = builder.Build();
  const Pose& pose = v.trajectory[40].T_world_camera;
  const cv::Mat depth =
      sim::Render(*place, v.solids, v.lighting, k, pose, sim::SensorOptions{}, 99).depth_m;
  const std::string png = *EncodeDepthPng16(depth, 5000);
  for (auto _ : state) {
    const cv::Mat d = state.range(0) == 0
                          ? *DecodeDepthMetres({DepthEncoding::kPng16, png, 640, 480, 5000})
                          : depth;
    benchmark::DoNotOptimize(place::CheckLayout(*plan, d, k, pose));
  }
}
BENCHMARK(BM_LayoutCheck)->Arg(0)->Arg(1)->Unit(benchmark::kMillisecond);

// A query against 1,000 stored descriptors of 4–8 corners with openings and stairs.
void BM_MatchAgainst1000Places(benchmark::State& state) {
  std::mt19937 rng(1);
  std::uniform_real_distribution<double> len(2.0, 9.0), pos(0.0, 1.0);
  auto make = [&] {
    place::PlaceDescriptor d;
    const int corners = 4 + static_cast<int>(rng() % 5);
    for (int c = 0; c < corners; ++c) {
      place::CornerEntry e{len(rng), rng() % 4 == 0 ? 270.0 : 90.0, {}};
      for (int o = 0; o < static_cast<int>(rng() % 3); ++o) {
        e.openings.push_back({rng() % 2 ? place::OpeningType::kDoor : place::OpeningType::kWindow,
                              0.9, pos(rng) * (e.length_m - 1)});
      }
      d.corners.push_back(e);
    }
    if (rng() % 2) d.stairs.push_back({true, 1.7, 1.0, 0.4});
    return d;
  };
  std::vector<place::PlaceDescriptor> stored;
  for (int i = 0; i < 1000; ++i) stored.push_back(make());
  const place::PlaceDescriptor query = stored[417];
  for (auto _ : state) {
    double best = 1e18;
    for (const auto& s : stored)
      best = std::min(best, place::MatchDescriptors(query, s).difference);
    benchmark::DoNotOptimize(best);
  }
}
BENCHMARK(BM_MatchAgainst1000Places)->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace lifemap

BENCHMARK_MAIN();
