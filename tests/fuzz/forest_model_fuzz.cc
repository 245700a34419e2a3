// libFuzzer target: arbitrary bytes as a forest model file (what UploadModel receives and the
// store keeps) must give a Status, never a crash, hang or out-of-bounds access; a model that
// loads must describe itself consistently and label an image (its trees walked to the leaves).
//
// The fuzzer's bytes get a valid checksum appended (the file's last 8 bytes), so that mutations
// reach the parser instead of stopping at the checksum (one comparison).
//
// Seeds: LIFEMAP_FUZZ_SEEDS=DIR forest_model_fuzz writes two small trained models (without
// their checksums) into DIR and exits; scripts/fuzz does.
#include <cstddef>
#include <cstdint>
#include <string>
#include <utility>

#include "core/common/checksum.h"
#include "core/forest/forest.h"
#include "tests/fuzz/seeds.h"
#include "tests/fuzz/tiny_forest.h"

namespace lifemap {
namespace {

void WriteSeeds(const std::string& dir) {
  forest::ModelDescription d{{"floor", "box"}, {0x808080, 0xff0000}, R"({"trees": 1})"};
  for (const auto& [name, reach] : {std::pair{"near", 200}, std::pair{"far", 5000}}) {
    const std::string file = fuzz::TrainTinyForest(reach).Serialize(d);
    fuzz::WriteFile(dir + "/" + name, file.substr(0, file.size() - 8));
  }
}

}  // namespace
}  // namespace lifemap

extern "C" int LLVMFuzzerInitialize(int* /*argc*/, char*** /*argv*/) {
  lifemap::fuzz::WriteSeedsIfAsked(lifemap::WriteSeeds);
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  std::string bytes(reinterpret_cast<const char*>(data), size);
  lifemap::AppendFnv1a64(&bytes);
  lifemap::forest::ModelDescription description;
  auto forest = lifemap::forest::Forest::Deserialize(bytes, &description);
  if (forest.ok()) {
    // What a server does with a loaded model: its metadata, and labels for a frame.
    (void)forest->tree_count();
    (void)forest->node_count();
    (void)forest->Serialize(description);
    const cv::Mat depth(12, 16, CV_32FC1, cv::Scalar(1.0f));
    const cv::Mat color(12, 16, CV_8UC3, cv::Scalar(40, 120, 200));
    (void)forest->Predict(depth, color, lifemap::forest::Decision::kBalanced, 1);
  }
  return 0;
}
