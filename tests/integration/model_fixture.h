// A tiny random-forest model and frames it labels, for integration tests of served labels.
#pragma once

#include <string>

#include <gtest/gtest.h>
#include <opencv2/core.hpp>

#include "core/forest/forest.h"
#include "tests/testing/test_util.h"

namespace lifemap::testing {

constexpr int kModelWidth = 160, kModelHeight = 120;

// A plane at 1.5 m, red on the left, blue on the right (so a colour feature separates them).
inline cv::Mat TwoColors() {
  cv::Mat bgr(kModelHeight, kModelWidth, CV_8UC3, cv::Scalar(0, 0, 220));
  bgr(cv::Rect(kModelWidth / 2, 0, kModelWidth / 2, kModelHeight)).setTo(cv::Scalar(220, 0, 0));
  return bgr;
}

inline v1::Frame TwoColorFrame(uint64_t sequence) {
  v1::Frame f = MakeFrame(kModelWidth, kModelHeight, 1.5, 1000.0 + sequence, sequence);
  f.mutable_color()->set_encoding(v1::COLOR_PNG);
  f.mutable_color()->set_data(PngBytes(TwoColors()));
  return f;
}

// A model file that calls the left half "wall" and the right half "door"; `swap` the other way.
inline std::string TwoColorModel(bool swap = false) {
  forest::LabeledImage im;
  im.depth_m = cv::Mat(kModelHeight, kModelWidth, CV_32FC1, cv::Scalar(1.5f));
  im.color_bgr = TwoColors();
  im.labels = cv::Mat(kModelHeight, kModelWidth, CV_8UC1, cv::Scalar(swap ? 1 : 0));
  im.labels(cv::Rect(kModelWidth / 2, 0, kModelWidth / 2, kModelHeight)).setTo(swap ? 0 : 1);
  im.labels(cv::Rect(kModelWidth / 2 - 6, 0, 12, kModelHeight)).setTo(forest::kIgnore);
  forest::TrainOptions o;
  o.trees = 1;
  o.max_depth = 6;
  o.candidates = 100;
  o.max_offset = 4;
  o.max_size = 3;
  auto model = forest::Forest::Train({im}, 2, o);
  EXPECT_TRUE(model.ok()) << model.status();
  forest::ModelDescription d;
  d.class_names = {"wall", "door"};
  d.class_colors = {0x808080, 0x00FF00};
  d.training_json = R"({"test":true})";
  return model->Serialize(d);
}

}  // namespace lifemap::testing
