// Metrics shared by the evaluation tools and tests.
#pragma once

#include <string>
#include <vector>

#include <opencv2/core.hpp>

namespace lifemap::eval {

// Area under the ROC curve: the probability that a random positive scores above a random
// negative (ties count half), by the Mann–Whitney U statistic. 0.5 when either set is empty.
double RocAuc(const std::vector<double>& positives, const std::vector<double>& negatives);

// Eq. 3 of paper 000: the zones of depth map `depth_i` that moved, against every other aligned
// depth map of the same place: median-filtered (window x window) differences D_j - D_i above
// `threshold_m` in any j. Pixels where either map has no reading count as no difference.
// Returns CV_8UC1, 255 = moved.
cv::Mat MovedZones(const cv::Mat& depth_i, const std::vector<cv::Mat>& others, int window = 10,
                   float threshold_m = 0.05f);

struct Series {
  std::string name;
  std::vector<double> x, y;
  cv::Scalar color;
  bool lines = true;  // false: a scatter of points
};

// A line plot with axes from 0 to 1, as a BGR image (for PNG reports).
cv::Mat PlotCurves(const std::vector<Series>& series, const std::string& title,
                   const std::string& x_label, const std::string& y_label);

}  // namespace lifemap::eval
