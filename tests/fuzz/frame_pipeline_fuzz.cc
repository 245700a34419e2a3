// libFuzzer target: frames that may pass validation but hold any values at all (intrinsics at
// and beyond their bounds, depth scales, raw float32 depths over the whole finite range, NaN,
// infinities, denormals) through the whole per-frame pipeline: decoding, depth range,
// normals, superjuts, entropy scores and forest labels. Each input gives a result or a
// Status; ASan and UBSan (float-cast-overflow included) report anything else.
//
//   CC=clang CXX=clang++ cmake -S . -B build-fuzz -G Ninja -DLIFEMAP_BUILD_FUZZERS=ON \
//       -DLIFEMAP_BUILD_TESTS=OFF -DLIFEMAP_BUILD_BENCHMARKS=OFF
//   cmake --build build-fuzz --target frame_pipeline_fuzz
//   mkdir -p /tmp/frames && build-fuzz/bin/frame_pipeline_fuzz -max_total_time=600 /tmp/frames
#include <fuzzer/FuzzedDataProvider.h>

#include <cstddef>
#include <cstdint>
#include <cstring>
#include <string>

#include "core/forest/forest.h"
#include "core/pipeline/frame_pipeline.h"
#include "tests/fuzz/tiny_forest.h"

namespace {

// A two-class forest whose features reach far beyond the image, trained once.
const lifemap::forest::Forest& Labeller() {
  static const lifemap::forest::Forest* forest =
      new lifemap::forest::Forest(lifemap::fuzz::TrainTinyForest(5000));
  return *forest;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  FuzzedDataProvider in(data, size);
  lifemap::EncodedRgbdFrame frame;
  frame.timestamp_s = 1000.0;
  const int w = in.ConsumeIntegralInRange(8, 40), h = in.ConsumeIntegralInRange(8, 40);
  frame.intrinsics.width = w;
  frame.intrinsics.height = h;
  // Half the time near the accepted range (scaled by the side), else any double.
  auto focal = [&](int side) {
    return in.ConsumeBool() ? side * in.ConsumeFloatingPointInRange(0.03, 70.0)
                            : in.ConsumeFloatingPoint<double>();
  };
  frame.intrinsics.fx = focal(w);
  frame.intrinsics.fy = focal(h);
  frame.intrinsics.cx = in.ConsumeFloatingPointInRange(-1.0, w + 1.0);
  frame.intrinsics.cy = in.ConsumeFloatingPointInRange(-1.0, h + 1.0);
  const size_t pixels = static_cast<size_t>(w) * h;
  std::string depth;
  if (in.ConsumeBool()) {
    frame.depth.encoding = lifemap::DepthEncoding::kRawU16;
    frame.depth.depth_scale = in.ConsumeFloatingPoint<double>();
    depth = in.ConsumeBytesAsString(pixels * 2);
    depth.resize(pixels * 2, '\x10');
  } else {
    frame.depth.encoding = lifemap::DepthEncoding::kRawF32;
    depth.resize(pixels * sizeof(float));
    // A surface (one value, a slope) with some pixels anything at all.
    const float base = in.ConsumeFloatingPoint<float>();
    for (size_t i = 0; i < pixels; ++i) {
      const float v = in.ConsumeBool() ? in.ConsumeFloatingPoint<float>()
                                       : base * (1.0f + 0.01f * static_cast<float>(i % w));
      std::memcpy(&depth[i * sizeof(float)], &v, sizeof(float));
    }
  }
  frame.depth.data = depth;
  std::string color = in.ConsumeBytesAsString(pixels * 3);
  color.resize(pixels * 3, '\x80');
  frame.color = {lifemap::ColorEncoding::kRawRgb8, color, w, h};
  if (in.ConsumeBool()) {
    auto pose = lifemap::Pose::FromComponents(in.ConsumeFloatingPoint<double>(),
                                              in.ConsumeFloatingPoint<double>(),
                                              in.ConsumeFloatingPoint<double>(), 0.0, 0.0,
                                              in.ConsumeFloatingPointInRange(-1.0, 1.0), 1.0);
    if (pose.ok()) frame.T_world_camera = *pose;
  }
  lifemap::pipeline::PipelineOptions options;
  options.entropy.mesh = in.ConsumeBool();
  options.entropy.downsample = in.ConsumeIntegralInRange(1, 2);
  options.label_stride = in.ConsumeIntegralInRange(1, 4);
  const lifemap::pipeline::FramePipeline pipeline(options);
  lifemap::pipeline::FrameRequest request;
  request.labeller = &Labeller();
  (void)pipeline.Process(frame, request);
  return 0;
}
