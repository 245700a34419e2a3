// Images the browser view shows of a stored keyframe (server/http/web_server.h): thumbnails,
// depth in false colour, and overlays (entropy mask, labels, fused labels) as RGBA PNGs the page
// lays over the colour image. Internal to server_http.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/rgbd_frame.h"

namespace lifemap::server::web {

// A JPEG of `color_bgr` scaled to `width` pixels (height in proportion), quality 75.
absl::StatusOr<std::string> ThumbnailJpeg(const cv::Mat& color_bgr, int width);
// Depth (CV_32FC1 metres) as a PNG in false colour (turbo, near red to far blue over
// [0.5, 5] m), black where there is no reading.
absl::StatusOr<std::string> DepthPng(const cv::Mat& depth_m);
// An RGBA PNG: `mask` (CV_8UC1, non-zero = set) in `rgb` (0xRRGGBB) at `alpha`, clear elsewhere.
absl::StatusOr<std::string> MaskOverlayPng(const cv::Mat& mask, uint32_t rgb, uint8_t alpha);
// An RGBA PNG: class ids (CV_8UC1) in their class's colour (`class_colors`, 0xRRGGBB) at
// `alpha`; 255 (no label) clear.
absl::StatusOr<std::string> LabelOverlayPng(const cv::Mat& labels,
                                            const std::vector<uint32_t>& class_colors,
                                            uint8_t alpha);

}  // namespace lifemap::server::web
