#include "core/io/labeled_pcd.h"

#include <filesystem>

#include <pcl/io/pcd_io.h>
#include <pcl/point_types.h>

#include "absl/strings/str_cat.h"

namespace lifemap::io {

CameraIntrinsics KinectDefaultIntrinsics(int width, int height) {
  const double sx = width / 640.0, sy = height / 480.0;
  return {525.0 * sx, 525.0 * sy, 319.5 * sx, 239.5 * sy, width, height};
}

absl::StatusOr<LabeledFrame> ReadLabeledPcd(const std::string& path) {
  if (!std::filesystem::exists(path))
    return absl::NotFoundError(absl::StrCat(path, ": no such file"));
  pcl::PCLPointCloud2 header_only;
  pcl::PCDReader reader;
  Eigen::Vector4f origin;
  Eigen::Quaternionf orientation;
  int version = 0, data_type = 0;
  unsigned int data_idx = 0;
  if (reader.readHeader(path, header_only, origin, orientation, version, data_type, data_idx) !=
      0) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": not a readable PCD file"));
  }
  bool has_label = false, has_rgba = false;
  for (const auto& f : header_only.fields) {
    has_label |= f.name == "label";
    has_rgba |= f.name == "rgba" || f.name == "rgb";
  }
  if (!has_label || !has_rgba) {
    return absl::InvalidArgumentError(
        absl::StrCat(path, ": needs the fields x y z rgba label (a labelled RGB-D cloud)"));
  }
  if (header_only.height <= 1) {
    return absl::InvalidArgumentError(
        absl::StrCat(path, ": the cloud is not organized (height 1): no pixel grid"));
  }
  pcl::PointCloud<pcl::PointXYZRGBL> cloud;
  if (pcl::io::loadPCDFile(path, cloud) != 0) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": could not be read as PCD"));
  }
  const int w = static_cast<int>(cloud.width), h = static_cast<int>(cloud.height);
  LabeledFrame out;
  out.frame.intrinsics = KinectDefaultIntrinsics(w, h);
  out.frame.timestamp_s = 1.0;
  out.frame.depth_m = cv::Mat(h, w, CV_32FC1, cv::Scalar(0.0f));
  out.frame.color_bgr = cv::Mat(h, w, CV_8UC3, cv::Scalar::all(0));
  out.labels = cv::Mat(h, w, CV_32SC1, cv::Scalar(0));
  for (int r = 0; r < h; ++r) {
    float* depth = out.frame.depth_m.ptr<float>(r);
    cv::Vec3b* bgr = out.frame.color_bgr.ptr<cv::Vec3b>(r);
    int* label = out.labels.ptr<int>(r);
    for (int c = 0; c < w; ++c) {
      const auto& p = cloud.at(c, r);
      depth[c] = std::isfinite(p.z) && p.z > 0 ? p.z : 0.0f;
      bgr[c] = cv::Vec3b(p.b, p.g, p.r);
      label[c] = static_cast<int>(p.label);
    }
  }
  return out;
}

cv::Mat MosdTableObjectClasses(const cv::Mat& labels) {
  cv::Mat classes(labels.size(), CV_8UC1, cv::Scalar(255));
  classes.setTo(0, (labels >= 1) & (labels < 10));
  classes.setTo(1, labels >= 20);
  return classes;
}

}  // namespace lifemap::io
