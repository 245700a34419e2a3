// Helpers shared by lifemap's tests: the real datasets beside the repository, temporary
// folders, and small synthetic frames for validation tests.
#pragma once

#include <string>

#include <opencv2/core.hpp>

#include "lifemap/v1/common.pb.h"

namespace lifemap::testing {

// ../shared/data relative to the source tree (or $LIFEMAP_DATA). Empty when absent.
std::string SharedDataDir();
// The path of one dataset folder, or empty when it is absent.
std::string SharedDataset(const std::string& name);

// A fresh empty directory under the system temp dir, removed by the destructor.
class TempDir {
 public:
  TempDir();
  ~TempDir();
  TempDir(const TempDir&) = delete;
  TempDir& operator=(const TempDir&) = delete;
  const std::string& path() const { return path_; }
  std::string File(const std::string& name) const { return path_ + "/" + name; }

 private:
  std::string path_;
};

// A synthetic scene: a plane at `depth_m` with a checker texture; PNG-16 depth (scale 5000) and
// JPEG colour; TUM-like intrinsics for the size.
v1::Frame MakeFrame(int width = 640, int height = 480, double depth_m = 1.5,
                    double timestamp_s = 1000.0, uint64_t sequence = 0);

// Writes a small TUM-format folder (rgb/, depth/, rgb.txt, depth.txt, groundtruth.txt) of
// `frames` synthetic frames, 30 Hz, the camera moving `step_m` along x per frame. For tests that
// must run without ../shared/data.
void WriteSyntheticTum(const std::string& dir, int frames, double step_m = 0.02, int width = 320,
                       int height = 240);

// Test certificates made with `openssl` (Debian's) in `dir`: ca.pem/ca.key (a CA),
// server.pem/server.key (signed by it, for localhost and 127.0.0.1), client.pem/client.key
// (signed by it, for mTLS) and other-ca.pem (a CA that signed none of them). False, with
// openssl's output on stderr, when openssl fails.
bool MakeTestCertificates(const std::string& dir);

// The PNG / JPEG bytes of an image.
std::string PngBytes(const cv::Mat& image);
std::string JpegBytes(const cv::Mat& image);

}  // namespace lifemap::testing

// Skips the current test with a reason when a dataset of ../shared/data is absent.
#define LIFEMAP_REQUIRE_DATASET(var, name)                                                   \
  const std::string var = ::lifemap::testing::SharedDataset(name);                           \
  if (var.empty()) {                                                                         \
    GTEST_SKIP() << "needs ../shared/data/" << name                                          \
                 << " (the real RGB-D recordings beside the repository); it is absent here"; \
  }
