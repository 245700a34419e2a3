// Reader for organized, labelled point clouds (PCD) such as the mOSD table-top scenes: one
// point per pixel with x y z (metres, camera frame), rgba and a label.
#pragma once

#include <string>

#include <opencv2/core.hpp>

#include "absl/status/statusor.h"
#include "core/common/rgbd_frame.h"

namespace lifemap::io {

struct LabeledFrame {
  RgbdFrame frame;  // depth_m from z (0 where NaN), colour from rgba, intrinsics below
  cv::Mat labels;   // CV_32SC1, the file's label per pixel
};

// The Kinect defaults the mOSD clouds were back-projected with (fx = fy = 525, centre
// (319.5, 239.5)), scaled to the cloud's size.
CameraIntrinsics KinectDefaultIntrinsics(int width, int height);

// Reads an organized PCD with fields x y z rgba label (any order; ascii, binary or
// binary_compressed). NotFound for a missing file; InvalidArgument when the cloud is not
// organized or lacks a field.
absl::StatusOr<LabeledFrame> ReadLabeledPcd(const std::string& path);

// mOSD's labels as two classes: 0 = the supporting table (labels 1-9), 1 = objects (20 and
// above, object id = label / 10), 255 = unlabelled (0). CV_8UC1.
cv::Mat MosdTableObjectClasses(const cv::Mat& labels);

}  // namespace lifemap::io
