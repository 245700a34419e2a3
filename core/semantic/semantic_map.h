// The semantic octree (paper 002, section IV): an OctoMap occupancy octree whose occupied
// voxels also keep a distribution over the labelling model's classes, fused over keyframes by
// eq. 16, and rendered back into any view with a pose.
//
// Belief per voxel, in log space: Bel_0(c) ∝ p(c | D)^w, the class frequencies of the training
// set (eq. 9's prior, applied once) with a weight w (`prior_weight`, 0 by default: a uniform
// start, see docs/RESULTS.md); each keyframe that sees the voxel multiplies in its
// per-pixel class distribution p(c | q, F) as the forest predicts it on balanced classes, then
// renormalises (eq. 16's η). The pixels of one keyframe that fall into one voxel are averaged
// first, so a voxel seen by many pixels of one view counts once per view (views are the
// independent observations, not pixels of one view). Each observation is mixed with a uniform
// distribution (weight `observation_uniform_mix`) and the belief is floored at
// `min_class_probability`, so a voxel can change its class when the scene changes, as OctoMap
// clamps occupancy for the same reason.
//
// Occupancy follows OctoMap's sensor model: endpoints are hits, the voxels their rays cross are
// misses. A voxel that turns free forgets its class. Not thread-safe: one writer (the map's
// worker); Render and the read-only calls may run concurrently with each other, not with Fuse.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "absl/status/statusor.h"
#include "core/common/types.h"

namespace lifemap::semantic {

struct SemanticMapOptions {
  double resolution_m = 0.05;  // leaf voxel edge
  double max_range_m = 4.5;    // readings farther are not fused (rays stop there)
  int pixel_stride = 4;        // every n-th pixel in x and y is an endpoint
  // Every n-th pixel casts a free-space ray (0 = none), from a different quarter point of its
  // cell each keyframe. 16 keeps a keyframe near 25 ms (docs/BENCHMARKS.md); at 4.5 m its
  // rays are 14 cm apart in one keyframe, 7 cm over four.
  int free_space_stride = 16;
  // Free space is cleared only along the last `free_space_band_m` of each ray (0 = the whole
  // ray): objects move near surfaces, and the space near the camera is cleared by the rays of
  // every keyframe anyway.
  double free_space_band_m = 0.0;
  double observation_uniform_mix = 0.1;  // α: p' = (1 - α) p + α / C
  double min_class_probability = 1e-4;   // belief floor per class
  // Bel_0 ∝ p(c | D)^prior_weight: 1 is eq. 9's prior as is, 0 (default) a uniform start; see
  // docs/RESULTS.md for why 0 (chosen on one synthetic place, reported on another).
  double prior_weight = 0.0;

  // InvalidArgument naming the field and its range.
  absl::Status Validate() const;
};

// What one keyframe changed.
struct FusionStats {
  int64_t endpoints = 0;        // sampled pixels with a depth reading in range
  int64_t occupied_voxels = 0;  // distinct voxels the endpoints fell into
  int64_t labelled_voxels = 0;  // of those, voxels whose class belief was updated
  int64_t free_voxels = 0;      // distinct voxels updated as free
  double ms = 0.0;
};

// Labels rendered from the octree into a view.
struct RenderedLabels {
  cv::Mat labels;      // CV_8UC1 class id; 255 where the octree has no label (or no depth)
  cv::Mat confidence;  // CV_8UC1, the winning class's belief × 255 (0 where no label)
  std::vector<int64_t> class_pixels;          // labelled pixels per class
  std::vector<double> class_mean_confidence;  // mean winning belief per class
  int64_t labelled_pixels = 0;
  int64_t depth_pixels = 0;  // pixels with a depth reading: the share labelled is the coverage
  double mean_confidence = 0.0;
  int stride = 1;
};

// The whole map at a glance.
struct SemanticSummary {
  double resolution_m = 0.0;
  int class_count = 0;
  int64_t nodes = 0;                    // octree nodes, inner and leaf
  int64_t occupied_voxels = 0;          // occupied leaves, counted at leaf resolution
  int64_t labelled_voxels = 0;          // occupied leaves with a class belief
  int64_t free_voxels = 0;              // free leaves at leaf resolution
  std::vector<double> class_volume_m3;  // labelled volume per arg-max class
  size_t memory_bytes = 0;              // the octree's nodes and beliefs in RAM
  int64_t keyframes = 0;                // keyframes fused
  double min_m[3] = {0, 0, 0};          // bounding box of the occupied voxels (metres)
  double max_m[3] = {0, 0, 0};
};

// One occupied, labelled voxel.
struct LabelledVoxel {
  float x, y, z;  // centre, metres (map frame)
  float size_m;   // edge (larger than the resolution where the octree pruned 8 equal leaves)
  uint8_t class_id;
  float confidence;  // the arg-max class's belief
};

// Binary little-endian PLY of labelled voxels: x y z (float, metres), class (uchar), red green
// blue (uchar, `class_colors[class]` 0xRRGGBB, grey beyond them), confidence (float, the
// class's belief), size (float, voxel edge in metres).
std::string LabelledVoxelsToPly(const std::vector<LabelledVoxel>& voxels,
                                const std::vector<uint32_t>& class_colors);

class SemanticMap {
 public:
  // A map for a model with `class_count` classes (2..254) whose training prior is
  // `class_prior` (class_count positive values; normalised here). InvalidArgument otherwise.
  static absl::StatusOr<std::unique_ptr<SemanticMap>> Create(int class_count,
                                                             const std::vector<double>& class_prior,
                                                             const SemanticMapOptions& options);
  ~SemanticMap();
  SemanticMap(const SemanticMap&) = delete;
  SemanticMap& operator=(const SemanticMap&) = delete;

  // Fuses one keyframe: depth (CV_32FC1 metres, 0 = none) seen by `intrinsics` at
  // `T_map_camera`, and the forest's per-pixel class probabilities (class_count CV_32FC1 images
  // of the depth's size; all zero where not predicted). Everything is validated before the tree
  // changes: InvalidArgument for a class count that is not the map's (naming both), images of
  // the wrong size or type, NaN or negative probabilities, a camera whose range leaves the
  // octree's addressable cube (±32768 voxels around the origin).
  absl::StatusOr<FusionStats> Fuse(const cv::Mat& depth_m, const CameraIntrinsics& intrinsics,
                                   const Pose& T_map_camera,
                                   const std::vector<cv::Mat>& probabilities);

  // Looks up every `stride`-th pixel's depth point in the octree (the voxel it falls in, else
  // the voxels one step nearer and farther along its ray), copies the result into its stride
  // cell. InvalidArgument for a bad image, stride outside [1, 16] or a pose outside the cube.
  absl::StatusOr<RenderedLabels> Render(const cv::Mat& depth_m, const CameraIntrinsics& intrinsics,
                                        const Pose& T_map_camera, int stride) const;

  // Merges `other` (same class count and resolution; FailedPrecondition otherwise) into this
  // map after moving it by T_this_other: its occupied labelled voxels are fused as one
  // observation each, weighted by their belief, where this map has a class for the voxel, and
  // copied as they are where it has none (so merging into an empty map copies, resampled at
  // this map's voxels when the move turns them).
  absl::Status Merge(const SemanticMap& other, const Pose& T_this_other);
  // A copy holding only the occupied voxels whose most likely class is `class_id`, with their
  // occupancy and belief (for exporting one class in OctoMap's formats).
  std::unique_ptr<SemanticMap> OnlyClass(int class_id) const;

  SemanticSummary Summarize() const;
  // Occupied voxels with a class belief; only those whose arg-max is `only_class` if >= 0.
  std::vector<LabelledVoxel> LabelledVoxels(int only_class = -1) const;
  // The class belief at a point (empty when the voxel is unknown, free or unlabelled).
  std::vector<float> BeliefAt(double x, double y, double z) const;

  // Versioned binary snapshot with a checksum (options not included: the reader passes its
  // own; resolution and class count travel with the data and must match the reader's).
  std::string Serialize() const;
  // InvalidArgument: not a snapshot or resolution / class count differ from the options and
  // `class_count` given; DataLoss: corrupt or truncated; FailedPrecondition: a newer version.
  static absl::StatusOr<std::unique_ptr<SemanticMap>> Deserialize(
      const std::string& bytes, const SemanticMapOptions& options);

  // OctoMap's own formats, readable by octovis and octomap's tools: .bt (binary occupancy,
  // OcTree) and .ot (a ColorOcTree whose occupied voxels carry their class colour,
  // `class_colors` 0xRRGGBB per class; unlabelled occupied voxels grey).
  std::string ToOctomapBinary() const;
  std::string ToOctomapColor(const std::vector<uint32_t>& class_colors) const;

  int class_count() const;
  double resolution_m() const;
  int64_t keyframes() const;  // keyframes fused (SemanticSummary::keyframes, without the walk)
  const SemanticMapOptions& options() const;

 private:
  struct Impl;
  explicit SemanticMap(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace lifemap::semantic
