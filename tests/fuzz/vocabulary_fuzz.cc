// libFuzzer target: arbitrary bytes as a stored appearance vocabulary (paper 000) must give a
// Status, never a crash or an out-of-bounds access; a vocabulary that loads must give words
// for descriptors and save to the same bytes.
//
// Seeds: LIFEMAP_FUZZ_SEEDS=DIR vocabulary_fuzz writes vocabularies trained on random
// descriptors (3 levels of 4, and 2 of 8) into DIR and exits; scripts/fuzz does.
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <string>

#include <opencv2/core.hpp>

#include "core/appearance/vocabulary.h"
#include "tests/fuzz/seeds.h"

namespace lifemap {
namespace {

void WriteSeeds(const std::string& dir) {
  cv::RNG rng(7);
  std::vector<cv::Mat> images;
  for (int i = 0; i < 3; ++i) {
    cv::Mat d(60, appearance::Vocabulary::kDescriptorBytes, CV_8UC1);
    rng.fill(d, cv::RNG::UNIFORM, 0, 256);
    images.push_back(d);
  }
  for (const auto& [branching, levels] : {std::pair{4, 3}, std::pair{8, 2}}) {
    appearance::VocabularyOptions o;
    o.branching = branching;
    o.levels = levels;
    auto v = appearance::Vocabulary::Train(images, o);
    if (!v.ok()) std::abort();
    fuzz::WriteFile(dir + "/k" + std::to_string(branching) + "-l" + std::to_string(levels),
                    v->Serialize());
  }
}

}  // namespace
}  // namespace lifemap

extern "C" int LLVMFuzzerInitialize(int* /*argc*/, char*** /*argv*/) {
  lifemap::fuzz::WriteSeedsIfAsked(lifemap::WriteSeeds);
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using lifemap::appearance::Vocabulary;
  const std::string bytes(reinterpret_cast<const char*>(data), size);
  auto vocabulary = Vocabulary::Deserialize(bytes);
  if (!vocabulary.ok()) return 0;
  // What the server does with a loaded vocabulary: words for a keyframe's descriptors.
  cv::Mat descriptors(4, Vocabulary::kDescriptorBytes, CV_8UC1);
  for (int r = 0; r < descriptors.rows; ++r) {
    for (int c = 0; c < descriptors.cols; ++c) {
      descriptors.at<uint8_t>(r, c) = static_cast<uint8_t>(r * 67 + c * 13);
    }
  }
  (void)vocabulary->Transform(descriptors);
  if (vocabulary->Serialize() != bytes) std::abort();  // loads only what it would save
  return 0;
}
