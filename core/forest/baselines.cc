#include "core/forest/baselines.h"

#include <random>

#include <Eigen/Dense>
#include <opencv2/imgproc.hpp>
#include <opencv2/ml.hpp>

namespace lifemap::forest {

cv::Mat PlaneBaseline(const cv::Mat& depth_m, const CameraIntrinsics& k, float height_m,
                      uint64_t seed) {
  std::vector<Eigen::Vector3f> points;
  std::vector<cv::Point> pixels;
  for (int v = 0; v < depth_m.rows; v += 2) {
    for (int u = 0; u < depth_m.cols; u += 2) {
      const float z = depth_m.at<float>(v, u);
      if (!(z > 0)) continue;
      points.emplace_back(static_cast<float>((u - k.cx) / k.fx) * z,
                          static_cast<float>((v - k.cy) / k.fy) * z, z);
    }
  }
  cv::Mat labels(depth_m.size(), CV_8UC1, cv::Scalar(kIgnore));
  if (points.size() < 3) return labels;
  std::mt19937_64 rng(seed);
  std::uniform_int_distribution<size_t> pick(0, points.size() - 1);
  Eigen::Vector3f best_n(0, 0, -1);
  float best_d = 0;
  size_t best_inliers = 0;
  for (int it = 0; it < 300; ++it) {
    const Eigen::Vector3f a = points[pick(rng)], b = points[pick(rng)], c = points[pick(rng)];
    Eigen::Vector3f n = (b - a).cross(c - a);
    if (n.norm() < 1e-9f) continue;
    n.normalize();
    if (n.dot(a) > 0) n = -n;  // normal towards the camera
    const float d = -n.dot(a);
    size_t inliers = 0;
    for (size_t i = 0; i < points.size(); i += 4) inliers += std::abs(n.dot(points[i]) + d) < 0.01f;
    if (inliers > best_inliers) best_inliers = inliers, best_n = n, best_d = d;
  }
  for (int v = 0; v < depth_m.rows; ++v) {
    for (int u = 0; u < depth_m.cols; ++u) {
      const float z = depth_m.at<float>(v, u);
      if (!(z > 0)) continue;
      const Eigen::Vector3f p(static_cast<float>((u - k.cx) / k.fx) * z,
                              static_cast<float>((v - k.cy) / k.fy) * z, z);
      labels.at<uint8_t>(v, u) = best_n.dot(p) + best_d > height_m ? 1 : 0;
    }
  }
  return labels;
}

struct PixelTreesBaseline::Impl {
  cv::Ptr<cv::ml::RTrees> trees;
};

namespace {

cv::Mat Lab(const cv::Mat& bgr) {
  cv::Mat lab;
  cv::cvtColor(bgr, lab, cv::COLOR_BGR2Lab);
  return lab;
}

}  // namespace

absl::StatusOr<PixelTreesBaseline> PixelTreesBaseline::Train(
    const std::vector<LabeledImage>& images, int class_count, int pixels_per_image, uint64_t seed) {
  if (images.empty() || class_count < 2) {
    return absl::InvalidArgumentError("the baseline needs images and at least two classes");
  }
  std::mt19937_64 rng(seed);
  cv::Mat samples(0, 4, CV_32FC1), responses(0, 1, CV_32SC1);
  for (const auto& im : images) {
    const cv::Mat lab = Lab(im.color_bgr);
    std::vector<cv::Point> usable;
    for (int v = 0; v < im.labels.rows; ++v) {
      for (int u = 0; u < im.labels.cols; ++u) {
        const uint8_t l = im.labels.at<uint8_t>(v, u);
        if (l != kIgnore && l < class_count && im.depth_m.at<float>(v, u) > 0)
          usable.emplace_back(u, v);
      }
    }
    if (usable.empty()) continue;
    std::uniform_int_distribution<size_t> pick(0, usable.size() - 1);
    for (int i = 0; i < pixels_per_image; ++i) {
      const cv::Point p = usable[pick(rng)];
      const cv::Vec3b c = lab.at<cv::Vec3b>(p);
      cv::Mat row = (cv::Mat_<float>(1, 4) << im.depth_m.at<float>(p), c[0], c[1], c[2]);
      samples.push_back(row);
      responses.push_back(static_cast<int>(im.labels.at<uint8_t>(p)));
    }
  }
  if (samples.empty()) return absl::InvalidArgumentError("no labelled pixel with depth");
  PixelTreesBaseline out;
  out.impl_ = std::make_shared<Impl>();
  out.impl_->trees = cv::ml::RTrees::create();
  out.impl_->trees->setMaxDepth(20);
  out.impl_->trees->setMinSampleCount(10);
  out.impl_->trees->setTermCriteria(cv::TermCriteria(cv::TermCriteria::MAX_ITER, 30, 0));
  cv::theRNG().state = seed;
  out.impl_->trees->train(samples, cv::ml::ROW_SAMPLE, responses);
  return out;
}

cv::Mat PixelTreesBaseline::Predict(const cv::Mat& depth_m, const cv::Mat& color_bgr,
                                    int stride) const {
  cv::Mat labels(depth_m.size(), CV_8UC1, cv::Scalar(kIgnore));
  const cv::Mat lab = Lab(color_bgr);
  cv::Mat features(0, 4, CV_32FC1);
  std::vector<cv::Point> where;
  for (int v = 0; v < depth_m.rows; v += stride) {
    for (int u = 0; u < depth_m.cols; u += stride) {
      const float z = depth_m.at<float>(v, u);
      if (!(z > 0)) continue;
      const cv::Vec3b c = lab.at<cv::Vec3b>(v, u);
      cv::Mat row = (cv::Mat_<float>(1, 4) << z, c[0], c[1], c[2]);
      features.push_back(row);
      where.emplace_back(u, v);
    }
  }
  if (features.empty()) return labels;
  cv::Mat out;
  impl_->trees->predict(features, out);
  for (size_t i = 0; i < where.size(); ++i) {
    const int cls = static_cast<int>(std::lround(out.at<float>(static_cast<int>(i))));
    const cv::Rect block(where[i].x, where[i].y, std::min(stride, depth_m.cols - where[i].x),
                         std::min(stride, depth_m.rows - where[i].y));
    labels(block).setTo(cls);
  }
  return labels;
}

}  // namespace lifemap::forest
