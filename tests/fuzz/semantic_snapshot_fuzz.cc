// libFuzzer target (issue 17): any bytes as a visit's stored semantic octree snapshot (paper 002;
// the store keeps one per visit and lifemapd reads it when a visit is resumed, rebuilt or
// exported). The fuzzer's bytes follow the snapshot's 8-byte magic and get a valid checksum
// appended, so that mutations reach the tree parser instead of stopping at the checksum (a
// wrong checksum and a wrong magic are one comparison each). A snapshot that loads must
// answer every read the server makes of it and save to bytes that load to the same bytes.
//
//   scripts/fuzz 0   # builds build-fuzz; then, for a long run:
//   LIFEMAP_FUZZ_SEEDS=/tmp/octree build-fuzz/bin/semantic_snapshot_fuzz
//   build-fuzz/bin/semantic_snapshot_fuzz -max_total_time=600 /tmp/octree
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <string>

#include "core/common/checksum.h"
#include "core/semantic/semantic_map.h"
#include "tests/fuzz/seeds.h"

namespace lifemap {
namespace {

constexpr char kMagic[] = "LMSEMOCT";  // core/semantic/semantic_map.cc
constexpr size_t kMagicBytes = sizeof(kMagic) - 1;

semantic::SemanticMapOptions Options() {
  semantic::SemanticMapOptions o;
  o.resolution_m = 0.05;  // a snapshot of another resolution is refused before its tree
  return o;
}

// A wall 1.2 m in front of the camera, left half class 1, right half class 2, seen from two
// poses: the octree has occupied, free and labelled voxels at several depths of the tree.
void WriteSeeds(const std::string& dir) {
  auto map = semantic::SemanticMap::Create(3, {0.5, 0.3, 0.2}, Options());
  if (!map.ok()) std::abort();
  const CameraIntrinsics k{40.0, 40.0, 15.5, 11.5, 32, 24};
  const cv::Mat depth(24, 32, CV_32FC1, cv::Scalar(1.2f));
  std::vector<cv::Mat> p(3, cv::Mat(24, 32, CV_32FC1, cv::Scalar(0.1f)));
  p[1] = cv::Mat(24, 32, CV_32FC1, cv::Scalar(0.1f));
  p[2] = cv::Mat(24, 32, CV_32FC1, cv::Scalar(0.1f));
  p[1](cv::Rect(0, 0, 16, 24)).setTo(0.8f);
  p[2](cv::Rect(16, 0, 16, 24)).setTo(0.8f);
  const std::string empty = (*map)->Serialize();
  fuzz::WriteFile(dir + "/empty", empty.substr(kMagicBytes, empty.size() - kMagicBytes - 8));
  for (int i = 0; i < 2; ++i) {
    auto pose = Pose::FromComponents(0.1 * i, 0, 0, 0, 0, 0, 1);
    if (!pose.ok() || !(*map)->Fuse(depth, k, *pose, p).ok()) std::abort();
  }
  const std::string fused = (*map)->Serialize();
  fuzz::WriteFile(dir + "/wall", fused.substr(kMagicBytes, fused.size() - kMagicBytes - 8));
}

}  // namespace
}  // namespace lifemap

extern "C" int LLVMFuzzerInitialize(int* /*argc*/, char*** /*argv*/) {
  lifemap::fuzz::WriteSeedsIfAsked(lifemap::WriteSeeds);
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace lifemap;
  std::string bytes(kMagic, kMagicBytes);
  bytes.append(reinterpret_cast<const char*>(data), size);
  AppendFnv1a64(&bytes);
  auto map = semantic::SemanticMap::Deserialize(bytes, Options());
  if (!map.ok()) return 0;
  // What lifemapd reads of a loaded snapshot: its summary, its voxels (export), its two
  // OctoMap files, renders (resumed visits) and point queries.
  (void)(*map)->Summarize();
  (void)(*map)->LabelledVoxels();
  (void)(*map)->LabelledVoxels(1);
  (void)(*map)->ToOctomapBinary();
  (void)(*map)->ToOctomapColor({0x808080, 0xff0000});
  (void)(*map)->BeliefAt(0.0, 0.0, 1.2);
  const CameraIntrinsics k{8.0, 8.0, 3.5, 2.5, 8, 6};
  (void)(*map)->Render(cv::Mat(6, 8, CV_32FC1, cv::Scalar(1.2f)), k, Pose(), 1);
  const std::string saved = (*map)->Serialize();
  auto again = semantic::SemanticMap::Deserialize(saved, Options());
  if (!again.ok() || (*again)->Serialize() != saved) std::abort();  // round trip
  return 0;
}
