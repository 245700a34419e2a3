// Baseline for lifemap's normals (paper 000, eq. 2): PCL's IntegralImageNormalEstimation on the
// same real TUM frame, in the same binary run as lifemap's ComputeNormals.
//
//   build/bin/bench_pcl_normals
#include <pcl/features/integral_image_normal.h>
#include <pcl/point_cloud.h>
#include <pcl/point_types.h>

#include <string>

#include <benchmark/benchmark.h>
#include <opencv2/imgcodecs.hpp>

#include "core/io/tum_dataset.h"
#include "core/normals/normals.h"

namespace lifemap {
namespace {

struct Sample {
  cv::Mat depth_m;
  CameraIntrinsics k{517.3, 516.5, 318.6, 255.3, 640, 480};
  pcl::PointCloud<pcl::PointXYZ>::Ptr cloud;
};

const Sample& GetSample() {
  static const Sample sample = [] {
    Sample s;
    const std::string dir = std::string(LIFEMAP_SOURCE_DIR) + "/../shared/data/tum_fr1_xyz_subset";
    auto seq = io::ReadTumSequence(dir);
    cv::Mat raw;
    if (seq.ok()) {
      raw = cv::imread(seq->frames[0].depth_path, cv::IMREAD_ANYDEPTH);
    } else {
      raw = cv::Mat(480, 640, CV_16UC1);
      cv::randu(raw, 4000, 12000);
    }
    raw.convertTo(s.depth_m, CV_32FC1, 1.0 / 5000.0);
    s.cloud.reset(new pcl::PointCloud<pcl::PointXYZ>(640, 480));
    for (int v = 0; v < 480; ++v) {
      for (int u = 0; u < 640; ++u) {
        const float z = s.depth_m.at<float>(v, u);
        auto& p = s.cloud->at(u, v);
        if (z > 0) {
          p.x = static_cast<float>((u - s.k.cx) / s.k.fx) * z;
          p.y = static_cast<float>((v - s.k.cy) / s.k.fy) * z;
          p.z = z;
        } else {
          p.x = p.y = p.z = std::numeric_limits<float>::quiet_NaN();
        }
      }
    }
    s.cloud->is_dense = false;
    return s;
  }();
  return sample;
}

void BM_LifemapNormals(benchmark::State& state) {
  const auto& s = GetSample();
  normals::NormalOptions options;
  options.method =
      state.range(0) ? normals::NormalMethod::kMeshVertex : normals::NormalMethod::kCrossProduct;
  for (auto _ : state) benchmark::DoNotOptimize(normals::ComputeNormals(s.depth_m, s.k, options));
}
BENCHMARK(BM_LifemapNormals)->Arg(0)->Arg(1)->Unit(benchmark::kMillisecond);

// Args: PCL's method (0 COVARIANCE_MATRIX, 1 AVERAGE_3D_GRADIENT, 2 AVERAGE_DEPTH_CHANGE).
void BM_PclIntegralImageNormals(benchmark::State& state) {
  const auto& s = GetSample();
  pcl::IntegralImageNormalEstimation<pcl::PointXYZ, pcl::Normal> ne;
  static constexpr pcl::IntegralImageNormalEstimation<
      pcl::PointXYZ, pcl::Normal>::NormalEstimationMethod kMethods[3] = {
      pcl::IntegralImageNormalEstimation<pcl::PointXYZ, pcl::Normal>::COVARIANCE_MATRIX,
      pcl::IntegralImageNormalEstimation<pcl::PointXYZ, pcl::Normal>::AVERAGE_3D_GRADIENT,
      pcl::IntegralImageNormalEstimation<pcl::PointXYZ, pcl::Normal>::AVERAGE_DEPTH_CHANGE};
  ne.setNormalEstimationMethod(kMethods[state.range(0)]);
  ne.setMaxDepthChangeFactor(0.02f);
  ne.setNormalSmoothingSize(10.0f);
  ne.setInputCloud(s.cloud);
  pcl::PointCloud<pcl::Normal> normals;
  for (auto _ : state) {
    ne.compute(normals);
    benchmark::DoNotOptimize(normals.points.data());
  }
}
BENCHMARK(BM_PclIntegralImageNormals)->Arg(0)->Arg(1)->Arg(2)->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace lifemap

BENCHMARK_MAIN();
