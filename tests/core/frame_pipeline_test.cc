// The per-frame pipeline against frames that pass validation but hold extreme values: every
// stage must give a result or a Status, never a crash (issue 12: a depth of 1e30 or a
// depth_scale of 1e-18 crashed SegmentSuperjuts through a float-to-int bin index).
#include <cmath>
#include <cstring>
#include <limits>
#include <random>

#include <gtest/gtest.h>

#include "core/common/rgbd_frame.h"
#include "core/forest/forest.h"
#include "core/pipeline/frame_pipeline.h"

namespace lifemap {
namespace {

// A small forest whose features reach far (offsets and sizes much larger than the images), so
// that depth-normalised offsets at the nearest allowed depth overflow any image.
forest::Forest FarReachingForest() {
  forest::LabeledImage im;
  im.depth_m = cv::Mat(24, 32, CV_32FC1, cv::Scalar(1.0f));
  im.color_bgr = cv::Mat(24, 32, CV_8UC3, cv::Scalar(10, 200, 30));
  im.color_bgr(cv::Rect(16, 0, 16, 24)).setTo(cv::Scalar(200, 10, 30));
  im.labels = cv::Mat(24, 32, CV_8UC1, cv::Scalar(0));
  im.labels(cv::Rect(16, 0, 16, 24)).setTo(1);
  forest::TrainOptions o;
  o.trees = 2;
  o.max_depth = 6;
  o.candidates = 50;
  o.max_offset = 5000;
  o.max_size = 5000;
  auto f = forest::Forest::Train({im}, 2, o);
  EXPECT_TRUE(f.ok()) << f.status();
  return *std::move(f);
}

// A float drawn over the whole finite range, with the special values mixed in.
float ExtremeFloat(std::mt19937* rng) {
  switch ((*rng)() % 10) {
    case 0:
      return 0.0f;
    case 1:
      return std::numeric_limits<float>::quiet_NaN();
    case 2:
      return std::numeric_limits<float>::infinity();
    case 3:
      return std::numeric_limits<float>::max();
    case 4:
      return std::numeric_limits<float>::denorm_min();
    case 5:
      return -std::pow(10.0f, std::uniform_real_distribution<float>(-38, 38)(*rng));
    case 6:
    case 7:  // within a sensor's range, smooth enough to make surfaces
      return std::uniform_real_distribution<float>(0.3f, 4.0f)(*rng);
    default:
      return std::pow(10.0f, std::uniform_real_distribution<float>(-38, 38)(*rng));
  }
}

// "Up" for the masks' horizontality: the pose's, else against the IMU's gravity, else the
// image's up.
TEST(UpInCamera, ComesFromThePoseThenGravityThenTheImage) {
  const Eigen::Vector3f z = Eigen::Vector3f::UnitZ();
  EXPECT_TRUE(pipeline::UpInCamera(std::nullopt, z).isApprox(Eigen::Vector3f(0, -1, 0)));
  const Eigen::Vector3d gravity(0.0, 3.0, 4.0);  // any length
  EXPECT_TRUE(
      pipeline::UpInCamera(std::nullopt, z, gravity).isApprox(Eigen::Vector3f(0, -0.6f, -0.8f)));
  Pose level;  // camera z forward along world x, y down: up is -y whatever the IMU says
  Eigen::Matrix3d R;
  R << 0, 0, 1, -1, 0, 0, 0, -1, 0;
  level.rotation = Eigen::Quaterniond(R);
  EXPECT_TRUE(pipeline::UpInCamera(level, z, gravity).isApprox(Eigen::Vector3f(0, -1, 0)));
}

TEST(FramePipeline, ExtremeButFiniteFramesGiveAResultOrAStatusNeverACrash) {
  const forest::Forest labeller = FarReachingForest();
  std::mt19937 rng(12);
  int analysed = 0, refused = 0;
  for (int trial = 0; trial < 300; ++trial) {
    const int w = 8 + static_cast<int>(rng() % 57), h = 8 + static_cast<int>(rng() % 41);
    EncodedRgbdFrame in;
    in.sequence = static_cast<uint64_t>(trial);
    in.timestamp_s = 1000.0 + trial;
    auto uniform = [&](double lo, double hi) {
      return std::uniform_real_distribution<double>(lo, hi)(rng);
    };
    // Intrinsics anywhere within (and now and then just beyond) what validation allows.
    const double reach = trial % 10 == 0 ? 1.5 : 1.0;
    in.intrinsics.fx = w * uniform(CameraIntrinsics::kMinFocalPerSide / reach,
                                   CameraIntrinsics::kMaxFocalPerSide * reach);
    in.intrinsics.fy = h * uniform(CameraIntrinsics::kMinFocalPerSide / reach,
                                   CameraIntrinsics::kMaxFocalPerSide * reach);
    in.intrinsics.cx = uniform(0, w - 1e-3);
    in.intrinsics.cy = uniform(0, h - 1e-3);
    in.intrinsics.width = w;
    in.intrinsics.height = h;
    std::string depth;
    if (trial % 3 == 0) {
      cv::Mat raw(h, w, CV_16UC1);
      cv::randu(raw, 0, 65536);
      in.depth.encoding = DepthEncoding::kRawU16;
      in.depth.depth_scale = std::pow(10.0, uniform(-20, 20));  // often out of range
      depth.assign(reinterpret_cast<const char*>(raw.data), raw.total() * 2);
    } else {
      in.depth.encoding = DepthEncoding::kRawF32;
      depth.resize(static_cast<size_t>(w) * h * sizeof(float));
      const float base = ExtremeFloat(&rng);
      for (size_t i = 0; i < static_cast<size_t>(w) * h; ++i) {
        // Mostly one value with a slope (a surface), some pixels anything at all.
        const float v = rng() % 4 == 0 ? ExtremeFloat(&rng)
                                       : base * (1.0f + 0.001f * static_cast<float>(i % w));
        std::memcpy(&depth[i * sizeof(float)], &v, sizeof(float));
      }
    }
    in.depth.data = depth;
    cv::Mat rgb(h, w, CV_8UC3);
    cv::randu(rgb, 0, 256);
    const std::string color(reinterpret_cast<const char*>(rgb.data), rgb.total() * 3);
    in.color = {ColorEncoding::kRawRgb8, color, w, h};
    if (trial % 2 == 0) {
      auto pose = Pose::FromComponents(uniform(-1e4, 1e4), uniform(-1e4, 1e4), uniform(-1e4, 1e4),
                                       uniform(-1, 1), uniform(-1, 1), uniform(-1, 1),
                                       uniform(-1, 1) + 2.0);
      ASSERT_TRUE(!pose.ok() || std::isfinite(pose->translation.norm()));
      if (pose.ok()) in.T_world_camera = *pose;
    }
    pipeline::PipelineOptions options;
    options.entropy.mesh = trial % 4 == 1;
    options.entropy.downsample = 1 + trial % 2;
    options.label_stride = 1 + static_cast<int>(rng() % 4);
    const pipeline::FramePipeline pipeline(options);
    pipeline::FrameRequest request;
    request.labeller = &labeller;
    auto out = pipeline.Process(in, request);
    if (!out.ok()) {
      EXPECT_TRUE(absl::IsInvalidArgument(out.status())) << out.status();
      ++refused;
      continue;
    }
    ++analysed;
    // Every depth the stages saw is no reading or within the sensor's range.
    const DepthRange range = options.frame_limits.depth_range;
    for (int r = 0; r < h; ++r) {
      for (int c = 0; c < w; ++c) {
        const float d = out->frame.depth_m.at<float>(r, c);
        ASSERT_TRUE(d == 0.0f || (d >= range.min_m && d <= range.max_m)) << d;
      }
    }
    if (out->labels) {
      EXPECT_EQ(out->labels->labels.size(), cv::Size(w, h));
    }
  }
  // Both paths were exercised.
  EXPECT_GT(analysed, 100);
  EXPECT_GT(refused, 20);
}

}  // namespace
}  // namespace lifemap
