// Metrics shared by the evaluation tools and tests.
#pragma once

#include <string>
#include <vector>

#include <opencv2/core.hpp>

namespace lifemap::eval {

// Area under the ROC curve: the probability that a random positive scores above a random
// negative (ties count half), by the Mann–Whitney U statistic. 0.5 when either set is empty.
double RocAuc(const std::vector<double>& positives, const std::vector<double>& negatives);

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
