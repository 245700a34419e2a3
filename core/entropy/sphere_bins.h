// Binning of unit normals into M cells of nearly equal area (paper 000, section III-B-1): the
// Voronoi cells of M points on the golden-section spiral.
#pragma once

#include <vector>

#include <Eigen/Core>

namespace lifemap::entropy {

// Thread-safe after construction.
class SphereBins {
 public:
  // M points z_i = 1 - (2i + 1)/M, azimuth i * golden angle (Boucher's spiral, the paper's [1]).
  explicit SphereBins(int count = 80);

  int count() const { return static_cast<int>(centers_.size()); }
  const std::vector<Eigen::Vector3f>& centers() const { return centers_; }

  // The bin of a unit vector by brute force: the centre with the largest dot product.
  int BinExact(const Eigen::Vector3f& n) const;
  // The same through a cube-map lookup table (6 faces of kLutSide^2 cells, each cell holding
  // the bin of its centre): no trigonometry, one division. Agrees with BinExact except within
  // about half a LUT cell (< 1 degree) of a Voronoi border.
  int Bin(float x, float y, float z) const;

  static constexpr int kLutSide = 128;

 private:
  std::vector<Eigen::Vector3f> centers_;
  std::vector<unsigned char> lut_;  // face * side^2 + v * side + u
};

}  // namespace lifemap::entropy
