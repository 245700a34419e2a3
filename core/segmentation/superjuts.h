// Superjut segmentation (paper 000, section III-A): Felzenszwalb–Huttenlocher graph
// segmentation of the normal map on the 8-connected image grid, with eq. 1 edge weights.
#pragma once

#include <vector>

#include <opencv2/core.hpp>

#include "absl/status/statusor.h"
#include "core/normals/normals.h"

namespace lifemap::segmentation {

// The graph whose vertices (pixels with a normal) are segmented.
enum class SuperjutGraph {
  kImageGrid,  // the paper's image-domain variant: 8-connected pixels
  kMesh,       // the mesh variant: edges between vertices sharing a triangle of the organized
               // mesh (see normals::UpperTriangle / LowerTriangle)
};

struct SuperjutOptions {
  SuperjutGraph graph = SuperjutGraph::kImageGrid;
  // FH's scale: a component C absorbs an edge of weight w while w <= Int(C) + k / |C|. Larger k,
  // larger superjuts. The paper uses 0.6 for all its experiments.
  float k = 0.6f;
  // Components smaller than this are merged into a neighbour afterwards (FH's post-process).
  int min_size_px = 200;
  // Neighbours whose depths differ by more than this fraction of the depth get no edge: an
  // object standing in front of a wall is cut from it (the paper's mesh has no such edges).
  float max_depth_jump_ratio = 0.05f;
  // Eq. 1: convex edges weigh (1 - ni.nj)^2, concave ones 1 - ni.nj. false: always 1 - ni.nj.
  bool convex_squared = true;

  absl::Status Validate() const;
};

struct Superjuts {
  cv::Mat labels;             // CV_32SC1, superjut id per pixel, -1 where there is no normal
  std::vector<int> sizes_px;  // per id
  int count() const { return static_cast<int>(sizes_px.size()); }
};

// Edge weight of eq. 1 between points xi, xj with unit normals ni, nj facing the camera.
float EdgeWeight(const cv::Vec3f& xi, const cv::Vec3f& ni, const cv::Vec3f& xj, const cv::Vec3f& nj,
                 bool convex_squared);

// InvalidArgument for bad options or a normal map without points/normals.
absl::StatusOr<Superjuts> SegmentSuperjuts(const normals::NormalMap& normals,
                                           const SuperjutOptions& options = {});

}  // namespace lifemap::segmentation
