// Random decision forest for per-pixel object-class labels on RGB-D images (paper 002,
// section III): depth-normalised region features (eq. 1), class-balanced training by
// information gain (eqs. 2, 3), leaves re-weighted by the class prior (eq. 9).
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "absl/status/statusor.h"

namespace lifemap::forest {

// One training or test image: depth in metres (0 = no reading), colour, and a class id per
// pixel (CV_8UC1; kIgnore = unlabelled).
struct LabeledImage {
  cv::Mat depth_m;    // CV_32FC1
  cv::Mat color_bgr;  // CV_8UC3
  cv::Mat labels;     // CV_8UC1
};
constexpr uint8_t kIgnore = 255;

// Eq. 1: the mean of channel c1 over rectangle R1 minus the mean of c2 over R2, both placed
// around the query pixel with offsets and sizes divided by its depth (so a feature covers the
// same metric area at any distance). Channels: 0 depth (valid readings only), 1-3 CIE L*a*b*.
struct Feature {
  float offset1_x, offset1_y, size1_x, size1_y;  // pixel metres: pixels at a depth of 1 m
  float offset2_x, offset2_y, size2_x, size2_y;
  uint8_t channel1, channel2;  // depth with depth, or colour with colour
};

struct TrainOptions {
  int trees = 3;
  int max_depth = 20;
  int min_samples = 10;         // a node with fewer training pixels becomes a leaf
  int pixels_per_image = 2000;  // N, balanced across the classes present
  int candidates = 2000;        // P (feature, threshold) pairs tried per node
  float max_offset = 80.0f;     // pixel metres
  float max_size = 40.0f;       // pixel metres
  // Share of candidate features comparing depth with depth (the rest compare colours). 0.8,
  // not an even split: chosen on synthetic place 5 and mOSD (docs/RESULTS.md, issue 16): shape
  // carries over to unseen places and cluttered tables better than colour does.
  float depth_feature_share = 0.8f;
  // Balancing the N pixels per image evens the classes within an image; a class present in
  // few images (props, people) still holds few of all the samples. `global_balance` also
  // weighs every sample by the inverse of its class's share of all samples, in the gain
  // (eq. 3) and the leaves, so that every class weighs the same in each tree.
  bool global_balance = false;
  uint64_t seed = 1;
  int threads = 2;
  // Called after each tree is trained with (trees done, trees in all), one call at a time
  // (from the training threads).
  std::function<void(int, int)> progress;

  absl::Status Validate() const;
};

enum class Decision {
  kBalanced,       // uniform class prior: p(c | l) as measured on balanced training pixels
  kPriorWeighted,  // eq. 9: re-weighted by the class frequencies of the full training set
};

struct Prediction {
  cv::Mat labels;                      // CV_8UC1, arg-max class, kIgnore where not predicted
  std::vector<cv::Mat> probabilities;  // one CV_32FC1 per class (0 where not predicted)
};

// What a model file says about itself besides the trees.
struct ModelDescription {
  std::vector<std::string> class_names;  // one per class; class 0 is the background
  std::vector<uint32_t> class_colors;    // 0xRRGGBB per class, for label images
  // How it was trained: options and a data summary, as a JSON object (free-form for readers).
  std::string training_json = "{}";
};

// A distinct colour per class (class 0 grey), for models that do not name their own.
uint32_t DefaultClassColor(int class_id);

class Forest {
 public:
  // Trains on `images` with `class_count` classes (ids 0..class_count-1). Deterministic for a
  // seed. InvalidArgument for empty data, bad sizes or options, labels >= class_count.
  static absl::StatusOr<Forest> Train(const std::vector<LabeledImage>& images, int class_count,
                                      const TrainOptions& options);

  // Per-pixel class probabilities on every `stride`-th pixel with a depth reading (other
  // pixels copy their stride cell's prediction). InvalidArgument for bad images.
  absl::StatusOr<Prediction> Predict(const cv::Mat& depth_m, const cv::Mat& color_bgr,
                                     Decision decision = Decision::kBalanced, int stride = 1) const;

  int class_count() const { return class_count_; }
  const std::vector<double>& class_prior() const { return prior_; }
  int tree_count() const { return static_cast<int>(trees_.size()); }
  size_t node_count() const;

  // Versioned, little-endian binary model file with a checksum; the description travels
  // with it. InvalidArgument from Serialize's callers is not possible: a description whose
  // class count differs from the forest's is written with default names (see Describe).
  std::string Serialize(const ModelDescription& description) const;
  // Reads version 1 (class names only; colours get the default palette) and version 2.
  // InvalidArgument: not a model; DataLoss: corrupt or truncated; FailedPrecondition: a newer
  // version than this build reads.
  static absl::StatusOr<Forest> Deserialize(const std::string& bytes,
                                            ModelDescription* description);

  struct Node {
    Feature feature{};
    float threshold = 0;
    int32_t left = -1, right = -1;  // children; -1 for leaves
    int32_t leaf = -1;              // index into the tree's leaf distributions
  };
  struct Tree {
    std::vector<Node> nodes;
    std::vector<float> leaves;  // class_count balanced probabilities per leaf
  };

 private:
  int class_count_ = 0;
  std::vector<double> prior_;  // p(c) over the full training set
  std::vector<Tree> trees_;
};

// Shannon entropy (nats) of a class histogram; information gain of eq. 3 for a split.
double HistogramEntropy(const std::vector<double>& counts);
double InformationGain(const std::vector<double>& parent, const std::vector<double>& left,
                       const std::vector<double>& right);

}  // namespace lifemap::forest
