// A vocabulary of visual words over 256-bit binary descriptors (ORB): a tree of k-majority
// clusters (Gálvez-López & Tardós's hierarchical bag of words), whose leaves are the words,
// weighted by inverse document frequency over the training images.
//
// Written here rather than taken from DBoW2/3, which Debian does not package; faiss's binary
// IVF (libfaiss-dev) would index descriptors rather than keyframes (32 bytes per descriptor,
// ~16 KB per keyframe against ~2.4 KB for a keyframe's word list here).
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "absl/status/statusor.h"

namespace lifemap::appearance {

using WordId = uint32_t;

// A keyframe's words: tf-idf weights, L1-normalised, sorted by word.
struct BowVector {
  std::vector<std::pair<WordId, float>> words;
};

struct VocabularyOptions {
  int branching = 10;   // children per node, [2, 64]
  int levels = 4;       // tree depth, [1, 8]: up to branching^levels words
  int iterations = 10;  // k-majority rounds per node, [1, 100]
  uint64_t seed = 1;

  absl::Status Validate() const;
};

class Vocabulary {
 public:
  static constexpr int kDescriptorBytes = 32;

  // Trains on the descriptors of some images (each a CV_8UC1 matrix with 32-byte rows, one per
  // keypoint). InvalidArgument when there are fewer than `branching` descriptors in all or a
  // matrix is not of that shape.
  static absl::StatusOr<Vocabulary> Train(const std::vector<cv::Mat>& images,
                                          const VocabularyOptions& options = {});

  // The word of one descriptor (32 bytes).
  WordId Word(const uint8_t* descriptor) const;
  // An image's words; InvalidArgument for a matrix not of 32-byte CV_8UC1 rows.
  absl::StatusOr<BowVector> Transform(const cv::Mat& descriptors) const;

  size_t words() const { return idf_.size(); }
  const VocabularyOptions& options() const { return options_; }
  int training_images() const { return training_images_; }

  // A compact binary form ("LMVOC1", little-endian) and back; DataLoss for a damaged blob.
  std::string Serialize() const;
  static absl::StatusOr<Vocabulary> Deserialize(const std::string& bytes);

 private:
  struct Node {
    std::array<uint64_t, 4> centroid{};
    int32_t first_child = -1;  // -1: a leaf
    int32_t children = 0;
    int32_t word = -1;  // leaves only
  };
  VocabularyOptions options_;
  std::vector<Node> nodes_;  // nodes_[0] is the root (no centroid)
  std::vector<float> idf_;   // per word
  int training_images_ = 0;

  friend class VocabularyTrainer;
};

// Hamming distance between two 256-bit descriptors.
int HammingDistance256(const uint8_t* a, const uint8_t* b);

}  // namespace lifemap::appearance
