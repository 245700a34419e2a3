#include "server/http/web_views.h"

#include <algorithm>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

namespace lifemap::server::web {
namespace {

absl::StatusOr<std::string> Encode(const char* ext, const cv::Mat& image,
                                   const std::vector<int>& params = {}) {
  std::vector<uchar> bytes;
  if (!cv::imencode(ext, image, bytes, params)) {
    return absl::InternalError(std::string("could not encode a ") + ext + " image");
  }
  return std::string(bytes.begin(), bytes.end());
}

cv::Vec4b Rgba(uint32_t rgb, uint8_t alpha) {
  // OpenCV writes 4-channel PNGs from BGRA.
  return cv::Vec4b(static_cast<uint8_t>(rgb & 0xFF), static_cast<uint8_t>((rgb >> 8) & 0xFF),
                   static_cast<uint8_t>((rgb >> 16) & 0xFF), alpha);
}

}  // namespace

absl::StatusOr<std::string> ThumbnailJpeg(const cv::Mat& color_bgr, int width) {
  if (color_bgr.empty() || width < 1) return absl::InvalidArgumentError("no colour image");
  const int height = std::max(1, color_bgr.rows * width / std::max(1, color_bgr.cols));
  cv::Mat small;
  cv::resize(color_bgr, small, cv::Size(width, height), 0, 0, cv::INTER_AREA);
  return Encode(".jpg", small, {cv::IMWRITE_JPEG_QUALITY, 75});
}

absl::StatusOr<std::string> DepthPng(const cv::Mat& depth_m) {
  constexpr double kNearM = 0.5, kFarM = 5.0;
  cv::Mat scaled;
  depth_m.convertTo(scaled, CV_8UC1, -255.0 / (kFarM - kNearM), 255.0 * kFarM / (kFarM - kNearM));
  cv::Mat colour;
  cv::applyColorMap(scaled, colour, cv::COLORMAP_TURBO);
  colour.setTo(cv::Scalar(0, 0, 0), depth_m <= 0);
  return Encode(".png", colour);
}

absl::StatusOr<std::string> MaskOverlayPng(const cv::Mat& mask, uint32_t rgb, uint8_t alpha) {
  cv::Mat rgba(mask.size(), CV_8UC4, cv::Scalar(0, 0, 0, 0));
  rgba.setTo(Rgba(rgb, alpha), mask != 0);
  return Encode(".png", rgba);
}

absl::StatusOr<std::string> LabelOverlayPng(const cv::Mat& labels,
                                            const std::vector<uint32_t>& class_colors,
                                            uint8_t alpha) {
  cv::Mat rgba(labels.size(), CV_8UC4, cv::Scalar(0, 0, 0, 0));
  for (int v = 0; v < labels.rows; ++v) {
    const uint8_t* in = labels.ptr<uint8_t>(v);
    cv::Vec4b* out = rgba.ptr<cv::Vec4b>(v);
    for (int u = 0; u < labels.cols; ++u) {
      if (in[u] == 255) continue;
      out[u] = Rgba(in[u] < class_colors.size() ? class_colors[in[u]] : 0x808080, alpha);
    }
  }
  return Encode(".png", rgba);
}

}  // namespace lifemap::server::web
