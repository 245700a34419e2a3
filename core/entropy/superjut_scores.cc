#include "core/entropy/superjut_scores.h"

#include <cmath>
#include <memory>

#include <Eigen/Eigenvalues>

#include "absl/strings/str_cat.h"
#include "core/entropy/sphere_bins.h"

namespace lifemap::entropy {
namespace {

const SphereBins& BinsFor(int count) {
  static const SphereBins kDefault(80);
  if (count == 80) return kDefault;
  thread_local std::unique_ptr<SphereBins> other;
  if (!other || other->count() != count) other = std::make_unique<SphereBins>(count);
  return *other;
}

}  // namespace

absl::Status EntropyOptions::Validate() const {
  if (bins < 2 || bins > 255) {
    return absl::InvalidArgumentError(absl::StrCat("bins must be within [2, 255], got ", bins));
  }
  if (texture_stride_px < 0 || texture_stride_px > 256) {
    return absl::InvalidArgumentError(
        absl::StrCat("texture_stride_px must be within [0, 256], got ", texture_stride_px));
  }
  if (texture_window_px < 4 || texture_window_px > 64) {
    return absl::InvalidArgumentError(
        absl::StrCat("texture_window_px must be within [4, 64], got ", texture_window_px));
  }
  return absl::OkStatus();
}

cv::Mat EigenTransformGrid(const cv::Mat& gray, int window_px, int stride_px) {
  const int grid_rows = (gray.rows + stride_px - 1) / stride_px;
  const int grid_cols = (gray.cols + stride_px - 1) / stride_px;
  cv::Mat grid(grid_rows, grid_cols, CV_32FC1, cv::Scalar(0.0f));
  const int w = window_px;
  Eigen::MatrixXf block(w, w);
  Eigen::SelfAdjointEigenSolver<Eigen::MatrixXf> solver(w);
  for (int gr = 0; gr < grid_rows; ++gr) {
    for (int gc = 0; gc < grid_cols; ++gc) {
      const int r0 = std::clamp(gr * stride_px + stride_px / 2 - w / 2, 0, gray.rows - w);
      const int c0 = std::clamp(gc * stride_px + stride_px / 2 - w / 2, 0, gray.cols - w);
      if (r0 < 0 || c0 < 0) continue;  // image smaller than a window
      for (int r = 0; r < w; ++r) {
        const unsigned char* row = gray.ptr<unsigned char>(r0 + r) + c0;
        for (int c = 0; c < w; ++c) block(r, c) = row[c] * (1.0f / 255.0f);
      }
      // Singular values of the block = square roots of the eigenvalues of B^T B (ascending).
      solver.compute(block.transpose() * block, Eigen::EigenvaluesOnly);
      const auto& ev = solver.eigenvalues();
      float sum = 0.0f;
      for (int i = 0; i < w - 2; ++i) sum += std::sqrt(std::max(ev(i), 0.0f));
      grid.at<float>(gr, gc) = sum / static_cast<float>((w - 2) * w);
    }
  }
  return grid;
}

absl::StatusOr<std::vector<SuperjutScore>> ScoreSuperjuts(const segmentation::Superjuts& superjuts,
                                                          const normals::NormalMap& normals,
                                                          const cv::Mat& gray,
                                                          const Eigen::Vector3f& up_camera,
                                                          const EntropyOptions& options) {
  if (auto s = options.Validate(); !s.ok()) return s;
  if (superjuts.labels.size() != normals.normals.size()) {
    return absl::InvalidArgumentError("superjut labels and normals differ in size");
  }
  if (!gray.empty() && (gray.size() != superjuts.labels.size() || gray.type() != CV_8UC1)) {
    return absl::InvalidArgumentError("grey image must be CV_8UC1 of the labels' size");
  }
  const SphereBins& bins = BinsFor(options.bins);
  const int m = bins.count(), count = superjuts.count();
  std::vector<int> histograms(static_cast<size_t>(count) * m, 0);
  std::vector<double> texture_sum(static_cast<size_t>(count), 0.0);
  const bool texture = !gray.empty() && options.texture_stride_px > 0;
  cv::Mat grid;
  if (texture)
    grid = EigenTransformGrid(gray, options.texture_window_px, options.texture_stride_px);

  // Pass 1: histograms (and textureness sums); each pixel's bin is kept for pass 2.
  cv::Mat pixel_bin(superjuts.labels.size(), CV_8UC1);
  for (int r = 0; r < superjuts.labels.rows; ++r) {
    const int* label = superjuts.labels.ptr<int>(r);
    const cv::Vec3f* n = normals.normals.ptr<cv::Vec3f>(r);
    unsigned char* bin_row = pixel_bin.ptr<unsigned char>(r);
    const float* grid_row = texture ? grid.ptr<float>(r / options.texture_stride_px) : nullptr;
    for (int c = 0; c < superjuts.labels.cols; ++c) {
      if (label[c] < 0) continue;
      bin_row[c] = static_cast<unsigned char>(bins.Bin(n[c][0], n[c][1], n[c][2]));
      ++histograms[static_cast<size_t>(label[c]) * m + bin_row[c]];
      if (texture) texture_sum[label[c]] += grid_row[c / options.texture_stride_px];
    }
  }
  std::vector<int> mode(static_cast<size_t>(count), 0);
  for (int id = 0; id < count; ++id) {
    const int* h = &histograms[static_cast<size_t>(id) * m];
    for (int b = 1; b < m; ++b) {
      if (h[b] > h[mode[id]]) mode[id] = b;
    }
  }
  // Pass 2: the dominant normal n_mode is the mean of the normals in the mode bin (bins are
  // ~23 degrees apart at M = 80: a bin centre is too coarse for horizontality).
  std::vector<Eigen::Vector3f> mode_sum(static_cast<size_t>(count), Eigen::Vector3f::Zero());
  for (int r = 0; r < superjuts.labels.rows; ++r) {
    const int* label = superjuts.labels.ptr<int>(r);
    const cv::Vec3f* n = normals.normals.ptr<cv::Vec3f>(r);
    const unsigned char* bin_row = pixel_bin.ptr<unsigned char>(r);
    for (int c = 0; c < superjuts.labels.cols; ++c) {
      if (label[c] >= 0 && bin_row[c] == mode[label[c]]) {
        mode_sum[label[c]] += Eigen::Vector3f(n[c][0], n[c][1], n[c][2]);
      }
    }
  }

  const float log_m = std::log(static_cast<float>(m));
  std::vector<SuperjutScore> scores(static_cast<size_t>(count));
  for (int id = 0; id < count; ++id) {
    SuperjutScore& s = scores[id];
    s.id = id;
    s.size_px = superjuts.sizes_px[id];
    const int* h = &histograms[static_cast<size_t>(id) * m];
    const float total = static_cast<float>(s.size_px);
    for (int b = 0; b < m; ++b) {
      if (h[b] == 0) continue;
      const float p = h[b] / total;
      s.entropy -= p * std::log(p);
    }
    s.planarity = h[mode[id]] / total;
    s.horizontality = std::abs(up_camera.dot(mode_sum[id].normalized()));
    s.textureness = texture ? static_cast<float>(texture_sum[id] / s.size_px) : 0.0f;
    s.neg_entropy = std::clamp(1.0f - s.entropy / log_m, 0.0f, 1.0f);
  }
  return scores;
}

cv::Mat NegEntropyImage(const segmentation::Superjuts& superjuts,
                        const std::vector<SuperjutScore>& scores) {
  cv::Mat out(superjuts.labels.size(), CV_8UC1, cv::Scalar(0));
  std::vector<unsigned char> value(scores.size());
  for (size_t i = 0; i < scores.size(); ++i) {
    value[i] = static_cast<unsigned char>(std::lround(scores[i].neg_entropy * 255.0f));
  }
  for (int r = 0; r < out.rows; ++r) {
    const int* label = superjuts.labels.ptr<int>(r);
    unsigned char* dst = out.ptr<unsigned char>(r);
    for (int c = 0; c < out.cols; ++c) {
      if (label[c] >= 0) dst[c] = value[label[c]];
    }
  }
  return out;
}

cv::Mat EntropyMask(const segmentation::Superjuts& superjuts,
                    const std::vector<SuperjutScore>& scores, float threshold) {
  cv::Mat out(superjuts.labels.size(), CV_8UC1, cv::Scalar(0));
  std::vector<unsigned char> masked(scores.size());
  for (size_t i = 0; i < scores.size(); ++i)
    masked[i] = scores[i].neg_entropy < threshold ? 255 : 0;
  for (int r = 0; r < out.rows; ++r) {
    const int* label = superjuts.labels.ptr<int>(r);
    unsigned char* dst = out.ptr<unsigned char>(r);
    for (int c = 0; c < out.cols; ++c) {
      if (label[c] >= 0) dst[c] = masked[label[c]];
    }
  }
  return out;
}

}  // namespace lifemap::entropy
