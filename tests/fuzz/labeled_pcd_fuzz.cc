// libFuzzer target (issue 17): any bytes as a labelled, organized point cloud file (mOSD's PCD,
// what `lifemap train` and `lifemap eval` read) through lifemap's reader and the class mapping
// after it. PCL parses the file (its code is not instrumented; ASan still sees its heap use); the
// reader must refuse what is not an organized cloud with x y z rgba and label.
//
//   scripts/fuzz 0   # builds build-fuzz; then, for a long run:
//   LIFEMAP_FUZZ_SEEDS=/tmp/pcd build-fuzz/bin/labeled_pcd_fuzz
//   build-fuzz/bin/labeled_pcd_fuzz -max_total_time=600 /tmp/pcd
#include <pcl/io/pcd_io.h>
#include <pcl/point_types.h>
#include <unistd.h>

#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <limits>
#include <string>

#include "core/io/labeled_pcd.h"
#include "tests/fuzz/seeds.h"

namespace lifemap {
namespace {

// An 8x6 organized cloud (a table at 1 m, an object on it, a few NaN points) in PCL's three
// encodings.
void WriteSeeds(const std::string& dir) {
  pcl::PointCloud<pcl::PointXYZRGBL> cloud(8, 6);
  for (int r = 0; r < 6; ++r) {
    for (int c = 0; c < 8; ++c) {
      auto& p = cloud.at(c, r);
      p.x = 0.05f * (c - 4), p.y = 0.05f * (r - 3), p.z = 1.0f;
      p.r = 200, p.g = 100, p.b = 50, p.a = 255;
      p.label = (c > 4 && r > 2) ? 21 : 1;
      if (r == 0 && c < 2) p.x = p.y = p.z = std::numeric_limits<float>::quiet_NaN(), p.label = 0;
    }
  }
  pcl::io::savePCDFileASCII(dir + "/ascii.pcd", cloud);
  pcl::io::savePCDFileBinary(dir + "/binary.pcd", cloud);
  pcl::io::savePCDFileBinaryCompressed(dir + "/compressed.pcd", cloud);
}

std::string& ScratchFile() {
  static std::string* path = [] {
    char pattern[] = "/tmp/lifemap-pcd-fuzz-XXXXXX";
    const int fd = mkstemp(pattern);
    if (fd < 0) std::abort();
    close(fd);
    return new std::string(pattern);
  }();
  return *path;
}

}  // namespace
}  // namespace lifemap

extern "C" int LLVMFuzzerInitialize(int* /*argc*/, char*** /*argv*/) {
  lifemap::fuzz::WriteSeedsIfAsked(lifemap::WriteSeeds);
  std::atexit([] { std::remove(lifemap::ScratchFile().c_str()); });
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace lifemap;
  // PCL reads files only.
  fuzz::WriteFile(ScratchFile(), std::string(reinterpret_cast<const char*>(data), size));
  auto frame = io::ReadLabeledPcd(ScratchFile());
  if (frame.ok()) (void)io::MosdTableObjectClasses(frame->labels);
  return 0;
}
