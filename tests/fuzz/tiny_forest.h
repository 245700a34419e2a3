// A two-class forest trained in a few milliseconds on one 16x16 image (left half green class 0,
// right half red class 1, one metre away), for fuzz targets that need a model.
#pragma once

#include "core/forest/forest.h"

namespace lifemap::fuzz {

// `reach`: the largest feature offset and box size in pixel metres (scaled by 1/depth); large
// values make features probe far beyond the image.
inline forest::Forest TrainTinyForest(int reach) {
  forest::LabeledImage im;
  im.depth_m = cv::Mat(16, 16, CV_32FC1, cv::Scalar(1.0f));
  im.color_bgr = cv::Mat(16, 16, CV_8UC3, cv::Scalar(10, 200, 30));
  im.color_bgr(cv::Rect(8, 0, 8, 16)).setTo(cv::Scalar(200, 10, 30));
  im.labels = cv::Mat(16, 16, CV_8UC1, cv::Scalar(0));
  im.labels(cv::Rect(8, 0, 8, 16)).setTo(1);
  forest::TrainOptions o;
  o.trees = 1;
  o.max_depth = 5;
  o.candidates = 40;
  o.max_offset = reach;
  o.max_size = reach;
  o.threads = 1;
  return *forest::Forest::Train({im}, 2, o);
}

}  // namespace lifemap::fuzz
