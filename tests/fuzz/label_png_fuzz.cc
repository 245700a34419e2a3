// libFuzzer target (issue 17): any bytes as the class list and the label image of a labelled
// TUM-format folder (labels/classes.txt and labels/NAME.png, what `lifemap train` and
// `lifemap eval` read) beside a fixed 16x12 colour and depth image. The reader must refuse
// labels that are not an 8-bit PNG of the images' size with known classes, naming the file.
//
// Input: 2 bytes (little-endian) giving the length of classes.txt, classes.txt, then the PNG.
//
//   scripts/fuzz 0   # builds build-fuzz; then, for a long run:
//   LIFEMAP_FUZZ_SEEDS=/tmp/labels build-fuzz/bin/label_png_fuzz
//   build-fuzz/bin/label_png_fuzz -max_total_time=600 /tmp/labels
#include <stdlib.h>

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <filesystem>
#include <string>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

#include "core/forest/labeled_data.h"
#include "tests/fuzz/seeds.h"

namespace lifemap {
namespace {

namespace fs = std::filesystem;

constexpr int kWidth = 16, kHeight = 12;

std::string Png(const cv::Mat& image) {
  std::vector<uchar> bytes;
  if (!cv::imencode(".png", image, bytes)) std::abort();
  return std::string(bytes.begin(), bytes.end());
}

std::string Input(const std::string& classes, const std::string& png) {
  std::string out{static_cast<char>(classes.size() & 0xff), static_cast<char>(classes.size() >> 8)};
  return out + classes + png;
}

// A folder holding one frame's colour and depth; labels/ is written per input.
const std::string& Folder() {
  static const std::string* dir = [] {
    char pattern[] = "/tmp/lifemap-label-fuzz-XXXXXX";
    if (mkdtemp(pattern) == nullptr) std::abort();
    const fs::path d(pattern);
    fs::create_directories(d / "rgb");
    fs::create_directories(d / "depth");
    fs::create_directories(d / "labels");
    fuzz::WriteFile((d / "rgb.txt").string(), "# colour\n1.000000 rgb/1.000000.png\n");
    fuzz::WriteFile((d / "depth.txt").string(), "# depth\n1.000000 depth/1.000000.png\n");
    fuzz::WriteFile((d / "rgb" / "1.000000.png").string(),
                    Png(cv::Mat(kHeight, kWidth, CV_8UC3, cv::Scalar(20, 120, 220))));
    fuzz::WriteFile((d / "depth" / "1.000000.png").string(),
                    Png(cv::Mat(kHeight, kWidth, CV_16UC1, cv::Scalar(5000))));
    return new std::string(d.string());
  }();
  return *dir;
}

void WriteSeeds(const std::string& dir) {
  cv::Mat labels(kHeight, kWidth, CV_8UC1, cv::Scalar(0));
  labels(cv::Rect(4, 4, 6, 6)).setTo(1);
  labels(cv::Rect(10, 0, 6, 4)).setTo(2);
  labels(cv::Rect(0, 10, 16, 2)).setTo(255);
  const std::string classes = "background\nchair\n# a comment\ntable\n";
  fuzz::WriteFile(dir + "/three-classes", Input(classes, Png(labels)));
  fuzz::WriteFile(dir + "/wrong-size", Input(classes, Png(labels(cv::Rect(0, 0, 8, 8)))));
  cv::Mat wide;
  labels.convertTo(wide, CV_16UC1);
  fuzz::WriteFile(dir + "/sixteen-bit", Input(classes, Png(wide)));
}

}  // namespace
}  // namespace lifemap

extern "C" int LLVMFuzzerInitialize(int* /*argc*/, char*** /*argv*/) {
  lifemap::fuzz::WriteSeedsIfAsked(lifemap::WriteSeeds);
  std::atexit([] {
    std::error_code ignored;
    std::filesystem::remove_all(lifemap::Folder(), ignored);
  });
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace lifemap;
  if (size < 2) return 0;
  const size_t n = std::min<size_t>(data[0] | (size_t{data[1]} << 8), size - 2);
  const std::string labels = Folder() + "/labels";
  fuzz::WriteFile(labels + "/classes.txt", std::string(reinterpret_cast<const char*>(data + 2), n));
  fuzz::WriteFile(labels + "/1.000000.png",
                  std::string(reinterpret_cast<const char*>(data + 2 + n), size - 2 - n));
  (void)forest::ReadLabeledData({Folder()});
  return 0;
}
