#include "core/planes/planes.h"

#include <algorithm>
#include <array>
#include <cmath>

#include <Eigen/Eigenvalues>
#include <opencv2/imgproc.hpp>

#include "absl/strings/str_cat.h"

namespace lifemap::planes {
namespace {

// Moments are summed per cell of kCell × kCell pixels once; a quadtree region (always whole
// cells: the root size and every split are multiples of kCell) sums its cells through an
// integral image of the cell grid. Exact, and ~100× less memory traffic than per-pixel
// integral images of ten moments.
constexpr int kCell = 4;

// Point moments: count, Σx, Σy, Σz, Σxx, Σxy, Σxz, Σyy, Σyz, Σzz; plus depth-change pixels.
struct Moments {
  std::array<double, 10> m{};
  double edges = 0;

  Moments& operator+=(const Moments& o) {
    for (size_t i = 0; i < m.size(); ++i) m[i] += o.m[i];
    edges += o.edges;
    return *this;
  }
  void Add(const Eigen::Vector3d& p) {
    m[0] += 1;
    m[1] += p.x(), m[2] += p.y(), m[3] += p.z();
    m[4] += p.x() * p.x(), m[5] += p.x() * p.y(), m[6] += p.x() * p.z();
    m[7] += p.y() * p.y(), m[8] += p.y() * p.z(), m[9] += p.z() * p.z();
  }
};

Moments Sub(const Moments& a, const Moments& b) {
  Moments r = a;
  for (size_t i = 0; i < r.m.size(); ++i) r.m[i] -= b.m[i];
  r.edges -= b.edges;
  return r;
}

struct Fit {
  Eigen::Vector3f normal, centroid;
  float offset = 0, mse = 0, curvature = 0;
};

// Total-least-squares plane of the moments' points (n >= 3).
Fit FitPlane(const Moments& mo) {
  const double n = mo.m[0];
  const Eigen::Vector3d c(mo.m[1] / n, mo.m[2] / n, mo.m[3] / n);
  Eigen::Matrix3d cov;
  cov(0, 0) = mo.m[4] / n - c.x() * c.x();
  cov(0, 1) = cov(1, 0) = mo.m[5] / n - c.x() * c.y();
  cov(0, 2) = cov(2, 0) = mo.m[6] / n - c.x() * c.z();
  cov(1, 1) = mo.m[7] / n - c.y() * c.y();
  cov(1, 2) = cov(2, 1) = mo.m[8] / n - c.y() * c.z();
  cov(2, 2) = mo.m[9] / n - c.z() * c.z();
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig;
  eig.computeDirect(cov);
  const Eigen::Vector3d ev = eig.eigenvalues().cwiseMax(0.0);  // ascending
  Eigen::Vector3d normal = eig.eigenvectors().col(0).normalized();
  if (normal.dot(c) > 0) normal = -normal;  // towards the camera
  Fit f;
  f.normal = normal.cast<float>();
  f.centroid = c.cast<float>();
  f.offset = static_cast<float>(normal.dot(c));
  f.mse = static_cast<float>(ev(0));
  const double sum = ev.sum();
  f.curvature = sum > 0 ? static_cast<float>(ev(0) / sum) : 0.0f;
  return f;
}

class CellGrid {
 public:
  CellGrid(int cols, int rows) : cols_(cols), rows_(rows), integral_((cols + 1) * (rows + 1)) {}
  Moments& cell(int cx, int cy) { return integral_[Index(cx + 1, cy + 1)]; }
  // Turns per-cell sums into an integral image (in place).
  void Integrate() {
    for (int y = 1; y <= rows_; ++y) {
      Moments row;
      for (int x = 1; x <= cols_; ++x) {
        row += integral_[Index(x, y)];
        Moments v = integral_[Index(x, y - 1)];
        v += row;
        integral_[Index(x, y)] = v;
      }
    }
  }
  // Sum over cells [cx, cx + w) × [cy, cy + h).
  Moments Sum(int cx, int cy, int w, int h) const {
    Moments s = integral_[Index(cx + w, cy + h)];
    s = Sub(s, integral_[Index(cx, cy + h)]);
    s = Sub(s, integral_[Index(cx + w, cy)]);
    s += integral_[Index(cx, cy)];
    return s;
  }
  int cols() const { return cols_; }
  int rows() const { return rows_; }

 private:
  size_t Index(int x, int y) const {
    return static_cast<size_t>(y) * static_cast<size_t>(cols_ + 1) + static_cast<size_t>(x);
  }
  int cols_, rows_;
  std::vector<Moments> integral_;
};

// The rectangle's corners as a quad on the plane (nothing when a ray grazes it).
bool QuadOnPlane(const cv::Rect& r, const Eigen::Vector3f& n, float d, const CameraIntrinsics& k,
                 std::array<Eigen::Vector3f, 4>* quad) {
  const float us[4] = {static_cast<float>(r.x), static_cast<float>(r.x + r.width),
                       static_cast<float>(r.x + r.width), static_cast<float>(r.x)};
  const float vs[4] = {static_cast<float>(r.y), static_cast<float>(r.y),
                       static_cast<float>(r.y + r.height), static_cast<float>(r.y + r.height)};
  for (int i = 0; i < 4; ++i) {
    const Eigen::Vector3f ray((us[i] - static_cast<float>(k.cx)) / static_cast<float>(k.fx),
                              (vs[i] - static_cast<float>(k.cy)) / static_cast<float>(k.fy), 1.0f);
    const float denom = n.dot(ray);
    if (std::abs(denom) < 0.05f * ray.norm()) return false;
    (*quad)[static_cast<size_t>(i)] = ray * (d / denom);
  }
  return true;
}

}  // namespace

absl::Status PlaneOptions::Validate() const {
  if (median_kernel != 1 && median_kernel != 3 && median_kernel != 5) {
    return absl::InvalidArgumentError(
        absl::StrCat("median_kernel must be 1, 3 or 5, got ", median_kernel));
  }
  if (min_region_px < kCell || min_region_px % kCell != 0 || root_px < min_region_px ||
      root_px % min_region_px != 0 || root_px > 512) {
    return absl::InvalidArgumentError(absl::StrCat("min_region_px must be a multiple of ", kCell,
                                                   " and root_px a multiple of it (≤ 512); got ",
                                                   min_region_px, " and ", root_px));
  }
  if (!(min_valid > 0 && min_valid <= 1) || !(mse_rms_m > 0) || !(mse_quad >= 0) ||
      !(max_curvature > 0) || !(dci_relative > 0) || !(merge_angle_deg > 0) ||
      !(merge_offset_m > 0)) {
    return absl::InvalidArgumentError("plane thresholds must be positive (min_valid in (0, 1])");
  }
  return absl::OkStatus();
}

absl::StatusOr<PlaneSet> ExtractPlanes(const cv::Mat& depth_m, const CameraIntrinsics& k,
                                       const PlaneOptions& options) {
  if (auto s = options.Validate(); !s.ok()) return s;
  if (depth_m.empty() || depth_m.type() != CV_32FC1) {
    return absl::InvalidArgumentError("planes need a CV_32FC1 depth image in metres");
  }
  if (k.width != depth_m.cols || k.height != depth_m.rows || !(k.fx > 0) || !(k.fy > 0)) {
    return absl::InvalidArgumentError(absl::StrCat("intrinsics are for ", k.width, "x", k.height,
                                                   ", the depth is ", depth_m.cols, "x",
                                                   depth_m.rows));
  }
  PlaneSet out;
  if (options.median_kernel > 1) {
    cv::medianBlur(depth_m, out.smoothed_depth_m, options.median_kernel);
    out.smoothed_depth_m.setTo(0.0f, depth_m <= 0.0f);  // no depth stays no depth
  } else {
    out.smoothed_depth_m = depth_m.clone();
  }
  const cv::Mat& z = out.smoothed_depth_m;
  const int cols = (z.cols + kCell - 1) / kCell, rows = (z.rows + kCell - 1) / kCell;
  CellGrid grid(cols, rows);
  const double fx = k.fx, fy = k.fy, cx = k.cx, cy = k.cy;
  for (int v = 0; v < z.rows; ++v) {
    const float* row = z.ptr<float>(v);
    const float* below = v + 1 < z.rows ? z.ptr<float>(v + 1) : nullptr;
    for (int u = 0; u < z.cols; ++u) {
      const float d = row[u];
      if (!(d > 0)) continue;
      Moments& cell = grid.cell(u / kCell, v / kCell);
      cell.Add(Eigen::Vector3d((u - cx) * d / fx, (v - cy) * d / fy, d));
      // Eq. 2: a large jump to the right or below marks this pixel (N4, counted once per pair).
      const float t = options.dci_relative * d;
      if ((u + 1 < z.cols && row[u + 1] > 0 && std::abs(row[u + 1] - d) > t) ||
          (below != nullptr && below[u] > 0 && std::abs(below[u] - d) > t)) {
        cell.edges += 1;
      }
    }
  }
  grid.Integrate();

  // Quadtree over cells, iteratively (a stack of regions in cell units).
  const int root = options.root_px / kCell, min_side = options.min_region_px / kCell;
  std::vector<std::array<int, 3>> stack;  // cx, cy, side (cells)
  for (int y = 0; y < rows; y += root) {
    for (int x = 0; x < cols; x += root) stack.push_back({x, y, root});
  }
  while (!stack.empty()) {
    const auto [x, y, side] = stack.back();
    stack.pop_back();
    const int w = std::min(side, cols - x), h = std::min(side, rows - y);
    if (w <= 0 || h <= 0) continue;
    const cv::Rect rect(x * kCell, y * kCell, std::min(w * kCell, z.cols - x * kCell),
                        std::min(h * kCell, z.rows - y * kCell));
    const Moments m = grid.Sum(x, y, w, h);
    const bool enough = m.m[0] >= options.min_valid * rect.area() && m.m[0] >= 3;
    bool planar = false;
    Fit fit;
    if (enough && m.edges == 0) {  // eq. 3
      fit = FitPlane(m);
      const float zc = fit.centroid.z();
      const float rms = options.mse_rms_m + options.mse_quad * zc * zc;
      planar = fit.mse < rms * rms && fit.curvature < options.max_curvature;  // eq. 1
    }
    if (planar) {
      PlanarRegion r;
      r.rect = rect;
      r.normal = fit.normal;
      r.offset_m = fit.offset;
      r.centroid = fit.centroid;
      r.points = static_cast<int>(m.m[0]);
      r.rms_m = std::sqrt(fit.mse);
      r.curvature = fit.curvature;
      out.regions.push_back(r);
    } else if (side / 2 >= min_side && m.m[0] >= 3) {
      const int s = side / 2;
      stack.push_back({x, y, s});
      stack.push_back({x + s, y, s});
      stack.push_back({x, y + s, s});
      stack.push_back({x + s, y + s, s});
    }
  }

  // Eq. 4: regions join the first plane (largest first) whose normal and offset they share;
  // a plane's fit is refreshed from its summed moments as it grows.
  std::vector<size_t> order(out.regions.size());
  for (size_t i = 0; i < order.size(); ++i) order[i] = i;
  std::sort(order.begin(), order.end(),
            [&](size_t a, size_t b) { return out.regions[a].points > out.regions[b].points; });
  const float cos_max = std::cos(options.merge_angle_deg * static_cast<float>(M_PI) / 180.0f);
  std::vector<Moments> plane_moments;
  for (size_t i : order) {
    PlanarRegion& r = out.regions[i];
    const cv::Rect& c = r.rect;
    const Moments m = grid.Sum(c.x / kCell, c.y / kCell, (c.width + kCell - 1) / kCell,
                               (c.height + kCell - 1) / kCell);
    int joined = -1;
    for (size_t p = 0; p < out.planes.size(); ++p) {
      const Plane& pl = out.planes[p];
      if (pl.normal.dot(r.normal) > cos_max &&
          std::abs(pl.normal.dot(r.centroid) - pl.offset_m) < options.merge_offset_m) {
        joined = static_cast<int>(p);
        break;
      }
    }
    if (joined < 0) {
      out.planes.emplace_back();
      plane_moments.emplace_back();
      joined = static_cast<int>(out.planes.size()) - 1;
    }
    Plane& pl = out.planes[static_cast<size_t>(joined)];
    plane_moments[static_cast<size_t>(joined)] += m;
    const Fit f = FitPlane(plane_moments[static_cast<size_t>(joined)]);
    pl.normal = f.normal;
    pl.offset_m = f.offset;
    pl.centroid = f.centroid;
    pl.points += r.points;
    pl.regions.push_back(static_cast<int>(i));
    r.plane = joined;
  }
  for (auto& pl : out.planes) {
    for (int i : pl.regions) {
      std::array<Eigen::Vector3f, 4> q;
      if (!QuadOnPlane(out.regions[static_cast<size_t>(i)].rect, pl.normal, pl.offset_m, k, &q)) {
        continue;
      }
      pl.area_m2 += 0.5f * ((q[2] - q[0]).cross(q[3] - q[1])).norm();
      pl.quads.insert(pl.quads.end(), q.begin(), q.end());
    }
  }
  // Largest first, with region back-references renumbered.
  std::vector<size_t> by_area(out.planes.size());
  for (size_t i = 0; i < by_area.size(); ++i) by_area[i] = i;
  std::stable_sort(by_area.begin(), by_area.end(), [&](size_t a, size_t b) {
    return out.planes[a].area_m2 > out.planes[b].area_m2;
  });
  std::vector<Plane> sorted;
  std::vector<int> new_index(out.planes.size());
  for (size_t i = 0; i < by_area.size(); ++i) {
    new_index[by_area[i]] = static_cast<int>(i);
    sorted.push_back(std::move(out.planes[by_area[i]]));
  }
  out.planes = std::move(sorted);
  for (auto& r : out.regions) {
    if (r.plane >= 0) r.plane = new_index[static_cast<size_t>(r.plane)];
  }
  return out;
}

}  // namespace lifemap::planes
