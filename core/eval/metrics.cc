#include "core/eval/metrics.h"

#include <algorithm>
#include <cmath>

#include <opencv2/imgproc.hpp>

namespace lifemap::eval {

double RocAuc(const std::vector<double>& positives, const std::vector<double>& negatives) {
  if (positives.empty() || negatives.empty()) return 0.5;
  std::vector<std::pair<double, int>> all;
  all.reserve(positives.size() + negatives.size());
  for (double p : positives) all.emplace_back(p, 1);
  for (double n : negatives) all.emplace_back(n, 0);
  std::sort(all.begin(), all.end());
  // Sum of the positives' ranks, ties sharing their mean rank.
  double rank_sum = 0.0;
  for (size_t i = 0; i < all.size();) {
    size_t j = i;
    int tied_positives = 0;
    while (j < all.size() && all[j].first == all[i].first) tied_positives += all[j++].second;
    const double mean_rank = (static_cast<double>(i + 1) + static_cast<double>(j)) / 2.0;
    rank_sum += mean_rank * tied_positives;
    i = j;
  }
  const double np = static_cast<double>(positives.size()),
               nn = static_cast<double>(negatives.size());
  return (rank_sum - np * (np + 1) / 2.0) / (np * nn);
}

cv::Mat PlotCurves(const std::vector<Series>& series, const std::string& title,
                   const std::string& x_label, const std::string& y_label) {
  constexpr int kW = 640, kH = 480, kLeft = 70, kRight = 20, kTop = 40, kBottom = 60;
  cv::Mat img(kH, kW, CV_8UC3, cv::Scalar::all(255));
  auto px = [&](double x, double y) {
    return cv::Point(kLeft + static_cast<int>(std::lround(x * (kW - kLeft - kRight))),
                     kH - kBottom - static_cast<int>(std::lround(y * (kH - kTop - kBottom))));
  };
  for (int i = 0; i <= 10; ++i) {
    const double t = i / 10.0;
    cv::line(img, px(t, 0), px(t, 1), cv::Scalar::all(230));
    cv::line(img, px(0, t), px(1, t), cv::Scalar::all(230));
    cv::putText(img, cv::format("%.1f", t), px(t, 0) + cv::Point(-10, 20), cv::FONT_HERSHEY_SIMPLEX,
                0.4, cv::Scalar::all(0));
    cv::putText(img, cv::format("%.1f", t), px(0, t) + cv::Point(-35, 5), cv::FONT_HERSHEY_SIMPLEX,
                0.4, cv::Scalar::all(0));
  }
  cv::rectangle(img, px(0, 1), px(1, 0), cv::Scalar::all(0));
  cv::putText(img, title, cv::Point(kLeft + 60, 18), cv::FONT_HERSHEY_SIMPLEX, 0.55,
              cv::Scalar::all(0));
  cv::putText(img, x_label, cv::Point(kW / 2 - 40, kH - 15), cv::FONT_HERSHEY_SIMPLEX, 0.5,
              cv::Scalar::all(0));
  cv::putText(img, y_label, cv::Point(5, kTop - 6), cv::FONT_HERSHEY_SIMPLEX, 0.45,
              cv::Scalar::all(0));
  int legend_y = kTop + 20;
  for (const auto& s : series) {
    for (size_t i = 0; s.lines && i + 1 < s.x.size(); ++i) {
      cv::line(img, px(s.x[i], s.y[i]), px(s.x[i + 1], s.y[i + 1]), s.color, 2, cv::LINE_AA);
    }
    for (size_t i = 0; i < s.x.size(); ++i) {
      cv::circle(img, px(s.x[i], s.y[i]), s.lines ? 3 : 2, s.color, -1, cv::LINE_AA);
    }
    cv::line(img, cv::Point(kW - 200, legend_y), cv::Point(kW - 175, legend_y), s.color, 2);
    cv::putText(img, s.name, cv::Point(kW - 170, legend_y + 5), cv::FONT_HERSHEY_SIMPLEX, 0.45,
                cv::Scalar::all(0));
    legend_y += 20;
  }
  return img;
}

}  // namespace lifemap::eval
