#include "core/semantic/semantic_map.h"

#include <algorithm>
#include <bitset>
#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>
#include <sstream>
#include <unordered_map>
#include <unordered_set>
#include <utility>

#include <octomap/OcTreeNode.h>
#include <octomap/OccupancyOcTreeBase.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/checksum.h"

namespace lifemap::semantic {
namespace {

// An OctoMap occupancy node with a class belief: log p(c) per class, empty until a labelled
// observation arrives (and again once the voxel turns free). Equality includes the belief so
// OctoMap's pruning only merges 8 leaves that agree on occupancy and class.
class SemanticNode : public octomap::OcTreeNode {
 public:
  SemanticNode() = default;
  SemanticNode(const SemanticNode& rhs) : octomap::OcTreeNode(rhs), belief(rhs.belief) {}
  SemanticNode& operator=(const SemanticNode&) = delete;
  bool operator==(const SemanticNode& rhs) const {
    return rhs.value == value && rhs.belief == belief;
  }
  void copyData(const SemanticNode& from) {
    octomap::OcTreeNode::copyData(from);
    belief = from.belief;
  }
  std::vector<float> belief;
};

// Calls fn(centre) for each leaf cell (edge `h`) of a voxel of edge `size` centred at `centre`:
// a pruned voxel stands for (size / h)^3 leaves.
template <typename Fn>
void ForEachLeafCell(const octomap::point3d& centre, double size, double h, Fn fn) {
  const int n = std::max(1, static_cast<int>(std::lround(size / h)));
  for (int i = 0; i < n; ++i) {
    for (int j = 0; j < n; ++j) {
      for (int k = 0; k < n; ++k) {
        fn(Eigen::Vector3d(centre.x() - size / 2 + (i + 0.5) * h,
                           centre.y() - size / 2 + (j + 0.5) * h,
                           centre.z() - size / 2 + (k + 0.5) * h));
      }
    }
  }
}

// The tree: OctoMap's occupancy logic as is; a voxel that the sensor model makes free forgets
// its class (the object that was there has gone). Serialization is ours (bounded depth,
// checked reads) rather than OctoMap's readData, which trusts its input.
class SemanticOcTree : public octomap::OccupancyOcTreeBase<SemanticNode> {
 public:
  explicit SemanticOcTree(double resolution_m)
      : octomap::OccupancyOcTreeBase<SemanticNode>(resolution_m) {}
  SemanticOcTree* create() const override { return new SemanticOcTree(resolution); }
  std::string getTreeType() const override { return "SemanticOcTree"; }

  void updateNodeLogOdds(SemanticNode* node, const float& update) const override {
    octomap::OccupancyOcTreeBase<SemanticNode>::updateNodeLogOdds(node, update);
    if (!node->belief.empty() && !isNodeOccupied(node)) {
      node->belief.clear();
      node->belief.shrink_to_fit();
    }
  }

  SemanticNode* Root() const { return root; }
  unsigned int MaxKey() const { return tree_max_val; }

  // Node: value (float), belief count (uint8), beliefs (floats), child bits (uint8); children
  // depth-first.
  void WriteNodes(const SemanticNode* node, std::string* out) const {
    const float value = node->getLogOdds();
    Append(out, value);
    const auto count = static_cast<uint8_t>(node->belief.size());
    Append(out, count);
    out->append(reinterpret_cast<const char*>(node->belief.data()), count * sizeof(float));
    uint8_t children = 0;
    for (unsigned i = 0; i < 8; ++i) {
      if (nodeChildExists(node, i)) children |= static_cast<uint8_t>(1u << i);
    }
    Append(out, children);
    for (unsigned i = 0; i < 8; ++i) {
      if (children & (1u << i)) WriteNodes(getNodeChild(node, i), out);
    }
  }

  // Reads what WriteNodes wrote into an empty tree; false on truncation, a depth beyond the
  // tree's or a belief of the wrong size.
  bool ReadNodes(const char*& p, const char* end, size_t class_count) {
    if (root != nullptr) return false;
    root = new SemanticNode();
    tree_size = 1;
    const bool ok = ReadNode(root, 0, p, end, class_count);
    tree_size = calcNumNodes();
    size_changed = true;
    return ok;
  }

  // OctoMap's .ot body for a ColorOcTree: per node its log-odds (float) and colour (r, g, b),
  // then the child bits, depth-first (OcTreeBaseImpl::writeNodesRecurs with ColorOcTreeNode).
  void WriteColorNodes(const SemanticNode* node, const std::vector<uint32_t>& colors,
                       std::string* out) const {
    Append(out, node->getLogOdds());
    uint32_t rgb = 0xffffff;  // OctoMap's "no colour"
    if (!node->belief.empty()) {
      rgb = colors[static_cast<size_t>(std::max_element(node->belief.begin(), node->belief.end()) -
                                       node->belief.begin())];
    } else if (isNodeOccupied(node) && !nodeHasChildren(node)) {
      rgb = 0x808080;
    }
    const uint8_t color[3] = {static_cast<uint8_t>(rgb >> 16), static_cast<uint8_t>(rgb >> 8),
                              static_cast<uint8_t>(rgb)};
    out->append(reinterpret_cast<const char*>(color), 3);
    uint8_t children = 0;
    for (unsigned i = 0; i < 8; ++i) {
      if (nodeChildExists(node, i)) children |= static_cast<uint8_t>(1u << i);
    }
    Append(out, children);
    for (unsigned i = 0; i < 8; ++i) {
      if (children & (1u << i)) WriteColorNodes(getNodeChild(node, i), colors, out);
    }
  }

  size_t BeliefBytes() const {
    size_t bytes = 0;
    for (auto it = begin_tree(), end = end_tree(); it != end; ++it) {
      // The vector's heap block plus the allocator's header (16 bytes on glibc).
      if (it->belief.capacity() > 0) bytes += it->belief.capacity() * sizeof(float) + 16;
    }
    return bytes;
  }

 private:
  template <typename T>
  static void Append(std::string* out, const T& v) {
    out->append(reinterpret_cast<const char*>(&v), sizeof(T));
  }
  template <typename T>
  static bool Take(const char*& p, const char* end, T* v) {
    if (end - p < static_cast<std::ptrdiff_t>(sizeof(T))) return false;
    std::memcpy(v, p, sizeof(T));
    p += sizeof(T);
    return true;
  }

  bool ReadNode(SemanticNode* node, unsigned depth, const char*& p, const char* end,
                size_t class_count) {
    float value = 0;
    uint8_t count = 0, children = 0;
    if (!Take(p, end, &value) || !std::isfinite(value) || !Take(p, end, &count)) return false;
    if (count != 0 && count != class_count) return false;
    if (end - p < static_cast<std::ptrdiff_t>(count * sizeof(float))) return false;
    node->setLogOdds(value);
    node->belief.resize(count);
    // No memcpy for none: an empty vector's data() may be null, which memcpy must not get.
    if (count > 0) std::memcpy(node->belief.data(), p, count * sizeof(float));
    p += count * sizeof(float);
    for (float b : node->belief) {
      if (!std::isfinite(b) || b > 0.0f) return false;
    }
    if (!Take(p, end, &children)) return false;
    if (children != 0 && depth >= tree_depth) return false;
    for (unsigned i = 0; i < 8; ++i) {
      if (!(children & (1u << i))) continue;
      if (!ReadNode(createNodeChild(node, i), depth + 1, p, end, class_count)) return false;
    }
    return true;
  }
};

double MsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start)
      .count();
}

// log Σ exp(v), stable.
float LogSumExp(const std::vector<float>& v) {
  const float m = *std::max_element(v.begin(), v.end());
  double s = 0.0;
  for (float x : v) s += std::exp(static_cast<double>(x - m));
  return m + static_cast<float>(std::log(s));
}

absl::Status CheckImage(const cv::Mat& image, int type, const CameraIntrinsics& intrinsics,
                        const char* what) {
  if (image.empty() || image.type() != type || image.cols != intrinsics.width ||
      image.rows != intrinsics.height) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "%s must be a %dx%d image of type %d (the intrinsics' size), got %dx%d of type %d", what,
        intrinsics.width, intrinsics.height, type, image.cols, image.rows, image.type()));
  }
  return absl::OkStatus();
}

constexpr char kMagic[8] = {'L', 'M', 'S', 'E', 'M', 'O', 'C', 'T'};
constexpr uint32_t kVersion = 1;

}  // namespace

struct SemanticMap::Impl {
  Impl(int classes, std::vector<float> log_prior_in, const SemanticMapOptions& opts)
      : class_count(classes),
        log_prior(std::move(log_prior_in)),
        options(opts),
        tree(opts.resolution_m) {}

  // InvalidArgument unless every point within max_range of `origin` has a key.
  absl::Status CheckInCube(const Eigen::Vector3d& origin) const {
    const double half = tree.getResolution() * tree.MaxKey() - options.max_range_m;
    if (origin.cwiseAbs().maxCoeff() < half) return absl::OkStatus();
    return absl::InvalidArgumentError(absl::StrFormat(
        "camera at (%.1f, %.1f, %.1f) m is outside the semantic octree: at %.3g m resolution it "
        "addresses %.0f m around the map origin, less the %.1f m range; is the pose in the map's "
        "frame and in metres?",
        origin.x(), origin.y(), origin.z(), tree.getResolution(),
        tree.getResolution() * tree.MaxKey(), options.max_range_m));
  }

  // Eq. 16 for one observation `p` (class_count probabilities summing to 1): Bel(c) ∝ Bel(c) ·
  // ((1 - α) p(c) + α / C), floored.
  void Observe(SemanticNode* node, const float* p) const {
    if (node->belief.empty()) node->belief = log_prior;
    const auto classes = static_cast<size_t>(class_count);
    const float alpha = static_cast<float>(options.observation_uniform_mix);
    const float uniform = alpha / static_cast<float>(class_count);
    for (size_t c = 0; c < classes; ++c) {
      node->belief[c] += std::log((1.0f - alpha) * p[c] + uniform);
    }
    const float norm = LogSumExp(node->belief);
    const float floor = std::log(static_cast<float>(options.min_class_probability));
    for (float& b : node->belief) b = std::max(b - norm, floor);
  }

  int class_count;
  std::vector<float> log_prior;
  SemanticMapOptions options;
  SemanticOcTree tree;
  int64_t keyframes = 0;
};

absl::Status SemanticMapOptions::Validate() const {
  if (!(resolution_m >= 0.01 && resolution_m <= 1.0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("semantic resolution must be within [0.01, 1] m, got ", resolution_m));
  }
  if (!(max_range_m > resolution_m && max_range_m <= 20.0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("semantic max range must be within (resolution, 20] m, got ", max_range_m));
  }
  if (pixel_stride < 1 || pixel_stride > 32) {
    return absl::InvalidArgumentError(
        absl::StrCat("semantic pixel stride must be within [1, 32], got ", pixel_stride));
  }
  if (free_space_stride < 0 || free_space_stride > 64) {
    return absl::InvalidArgumentError(absl::StrCat(
        "semantic free-space stride must be within [0, 64] (0 = none), got ", free_space_stride));
  }
  if (!(free_space_band_m >= 0.0 && free_space_band_m <= 20.0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("semantic free-space band must be within [0, 20] m (0 = whole rays), got ",
                     free_space_band_m));
  }
  if (!(observation_uniform_mix >= 0.0 && observation_uniform_mix < 1.0)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "observation uniform mix must be within [0, 1), got ", observation_uniform_mix));
  }
  if (!(prior_weight >= 0.0 && prior_weight <= 1.0)) {
    return absl::InvalidArgumentError(
        absl::StrCat("prior weight must be within [0, 1], got ", prior_weight));
  }
  if (!(min_class_probability > 0.0 && min_class_probability < 0.1)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "minimum class probability must be within (0, 0.1), got ", min_class_probability));
  }
  return absl::OkStatus();
}

SemanticMap::SemanticMap(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
SemanticMap::~SemanticMap() = default;

absl::StatusOr<std::unique_ptr<SemanticMap>> SemanticMap::Create(
    int class_count, const std::vector<double>& class_prior, const SemanticMapOptions& options) {
  if (auto s = options.Validate(); !s.ok()) return s;
  if (class_count < 2 || class_count > 254) {
    return absl::InvalidArgumentError(
        absl::StrCat("a semantic map needs 2 to 254 classes, got ", class_count));
  }
  if (class_prior.size() != static_cast<size_t>(class_count)) {
    return absl::InvalidArgumentError(absl::StrCat("the class prior has ", class_prior.size(),
                                                   " values for ", class_count, " classes"));
  }
  double sum = 0.0;
  for (double p : class_prior) {
    if (!(p >= 0.0) || !std::isfinite(p)) {
      return absl::InvalidArgumentError("class prior values must be finite and non-negative");
    }
    sum += p;
  }
  if (!(sum > 0.0)) return absl::InvalidArgumentError("the class prior sums to zero");
  const double floor = options.min_class_probability;
  std::vector<float> log_prior;
  for (double p : class_prior) {
    log_prior.push_back(
        static_cast<float>(options.prior_weight * std::log(std::max(p / sum, floor))));
  }
  const float norm = LogSumExp(log_prior);
  for (float& l : log_prior) l -= norm;
  return std::unique_ptr<SemanticMap>(
      new SemanticMap(std::make_unique<Impl>(class_count, std::move(log_prior), options)));
}

absl::StatusOr<FusionStats> SemanticMap::Fuse(const cv::Mat& depth_m,
                                              const CameraIntrinsics& intrinsics,
                                              const Pose& T_map_camera,
                                              const std::vector<cv::Mat>& probabilities) {
  const auto start = std::chrono::steady_clock::now();
  Impl& m = *impl_;
  if (auto s = intrinsics.Validate(); !s.ok()) return s;
  if (auto s = CheckImage(depth_m, CV_32FC1, intrinsics, "depth"); !s.ok()) return s;
  if (probabilities.size() != static_cast<size_t>(m.class_count)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "the labels have ", probabilities.size(), " classes but this semantic map has ",
        m.class_count, "; a map keeps one model's classes (rebuild it for a new model)"));
  }
  for (const cv::Mat& p : probabilities) {
    if (auto s = CheckImage(p, CV_32FC1, intrinsics, "class probabilities"); !s.ok()) return s;
  }
  const Eigen::Isometry3d T = T_map_camera.ToIsometry();
  const Eigen::Vector3d origin = T.translation();
  if (auto s = m.CheckInCube(origin); !s.ok()) return s;

  // 1. Endpoints, grouped by voxel: summed class probabilities and the number of labelled
  // pixels per voxel (validated here, before the tree changes).
  const auto classes = static_cast<size_t>(m.class_count);
  const int stride = m.options.pixel_stride;
  const float max_range = static_cast<float>(m.options.max_range_m);
  std::unordered_map<octomap::OcTreeKey, size_t, octomap::OcTreeKey::KeyHash> voxel_of;
  std::vector<octomap::OcTreeKey> keys;
  std::vector<float> sums;                // classes per voxel
  std::vector<int> labelled;              // labelled pixels per voxel
  std::vector<Eigen::Vector3d> ray_ends;  // free-space ray ends (map frame)
  voxel_of.reserve(static_cast<size_t>(depth_m.total()) / static_cast<size_t>(stride * stride));
  FusionStats stats;
  const int free_stride = m.options.free_space_stride;
  // The free-space rays start at a different quarter point of their stride cell each keyframe
  // (on the endpoints' grid), so four keyframes together cast a twice as dense grid.
  const int half = free_stride / 2 / stride * stride;
  const int free_u = static_cast<int>(m.keyframes % 2) * half;
  const int free_v = static_cast<int>((m.keyframes / 2) % 2) * half;
  for (int v = 0; v < depth_m.rows; v += stride) {
    const float* depth = depth_m.ptr<float>(v);
    for (int u = 0; u < depth_m.cols; u += stride) {
      const float d = depth[u];
      if (!(d > 0.0f) || !std::isfinite(d)) continue;
      const bool in_range = d <= max_range;
      const float z = std::min(d, max_range);
      const Eigen::Vector3d camera_point((u - intrinsics.cx) * z / intrinsics.fx,
                                         (v - intrinsics.cy) * z / intrinsics.fy, z);
      const Eigen::Vector3d point = T * camera_point;
      if (free_stride > 0 && (u - free_u) % free_stride == 0 && (v - free_v) % free_stride == 0) {
        ray_ends.push_back(point);
      }
      if (!in_range) continue;
      ++stats.endpoints;
      const octomap::OcTreeKey key = m.tree.coordToKey(
          octomap::point3d(static_cast<float>(point.x()), static_cast<float>(point.y()),
                           static_cast<float>(point.z())));
      auto [it, inserted] = voxel_of.emplace(key, keys.size());
      if (inserted) {
        keys.push_back(key);
        sums.resize(sums.size() + classes, 0.0f);
        labelled.push_back(0);
      }
      float pixel_sum = 0.0f;
      float* sum = &sums[it->second * classes];
      for (size_t c = 0; c < classes; ++c) {
        const float p = probabilities[c].ptr<float>(v)[u];
        if (!(p >= 0.0f) || !std::isfinite(p)) {
          return absl::InvalidArgumentError(absl::StrFormat(
              "class %d's probability at pixel (%d, %d) is %g; probabilities must be finite "
              "and non-negative",
              static_cast<int>(c), u, v, p));
        }
        pixel_sum += p;
      }
      if (pixel_sum <= 0.0f) continue;  // not predicted there: occupancy only
      for (size_t c = 0; c < classes; ++c) sum[c] += probabilities[c].ptr<float>(v)[u] / pixel_sum;
      ++labelled[it->second];
    }
  }

  // 2. Free space: one ray per free-space pixel, to the voxel before its endpoint, each voxel
  // updated once per keyframe and never one an endpoint fell into (OctoMap's computeUpdate).
  if (!ray_ends.empty()) {
    const octomap::point3d o(static_cast<float>(origin.x()), static_cast<float>(origin.y()),
                             static_cast<float>(origin.z()));
    std::unordered_set<octomap::OcTreeKey, octomap::OcTreeKey::KeyHash> free_keys;
    free_keys.reserve(ray_ends.size() * 16);
    octomap::KeyRay ray;
    const double band = m.options.free_space_band_m;
    for (const Eigen::Vector3d& e : ray_ends) {
      const octomap::point3d end(static_cast<float>(e.x()), static_cast<float>(e.y()),
                                 static_cast<float>(e.z()));
      octomap::point3d ray_start = o;
      const double length = (e - origin).norm();
      if (band > 0.0 && length > band) {
        const Eigen::Vector3d b = e + (origin - e) * (band / length);
        ray_start = octomap::point3d(static_cast<float>(b.x()), static_cast<float>(b.y()),
                                     static_cast<float>(b.z()));
      }
      if (!m.tree.computeRayKeys(ray_start, end, ray)) continue;
      free_keys.insert(ray.begin(), ray.end());
    }
    for (const octomap::OcTreeKey& k : keys) free_keys.erase(k);
    // Not lazily: OctoMap then keeps inner nodes and pruning up to date on every update
    // (lazy updates with a periodic whole-tree pass measured slower, see docs/BENCHMARKS.md).
    for (const octomap::OcTreeKey& k : free_keys) m.tree.updateNode(k, false, false);
    stats.free_voxels = static_cast<int64_t>(free_keys.size());
  }

  // 3. Endpoints: a hit each, and eq. 16 with the voxel's mean class distribution.
  std::vector<float> mean(classes);
  for (size_t i = 0; i < keys.size(); ++i) {
    SemanticNode* node = m.tree.updateNode(keys[i], true, false);
    if (labelled[i] == 0 || node == nullptr || !m.tree.isNodeOccupied(node)) continue;
    // updateNode returns the leaf, or its parent when the update let 8 equal leaves be pruned
    // (then the parent stands for the voxel).
    for (size_t c = 0; c < classes; ++c) mean[c] = sums[i * classes + c] / labelled[i];
    m.Observe(node, mean.data());
    ++stats.labelled_voxels;
  }
  stats.occupied_voxels = static_cast<int64_t>(keys.size());
  ++m.keyframes;
  stats.ms = MsSince(start);
  return stats;
}

absl::StatusOr<RenderedLabels> SemanticMap::Render(const cv::Mat& depth_m,
                                                   const CameraIntrinsics& intrinsics,
                                                   const Pose& T_map_camera, int stride) const {
  const Impl& m = *impl_;
  if (stride < 1 || stride > 16) {
    return absl::InvalidArgumentError(
        absl::StrCat("render stride must be within [1, 16], got ", stride));
  }
  if (auto s = intrinsics.Validate(); !s.ok()) return s;
  if (auto s = CheckImage(depth_m, CV_32FC1, intrinsics, "depth"); !s.ok()) return s;
  const Eigen::Isometry3d T = T_map_camera.ToIsometry();
  if (auto s = m.CheckInCube(T.translation()); !s.ok()) return s;

  RenderedLabels out;
  out.stride = stride;
  out.labels = cv::Mat(depth_m.size(), CV_8UC1, cv::Scalar(255));
  out.confidence = cv::Mat(depth_m.size(), CV_8UC1, cv::Scalar(0));
  const auto classes = static_cast<size_t>(m.class_count);
  out.class_pixels.assign(classes, 0);
  std::vector<double> sums(classes, 0.0);
  double total = 0.0;
  const float max_range = static_cast<float>(m.options.max_range_m);
  const double step = m.tree.getResolution();
  // The voxel a point falls in; else one voxel nearer or farther along the ray (depth noise
  // and pose error move a surface by about a voxel between views). Neighbouring pixels often
  // fall into the same voxel: the last lookup is remembered.
  octomap::OcTreeKey last_key;
  const SemanticNode* last_node = nullptr;
  bool have_last = false;
  auto lookup = [&](const Eigen::Vector3d& camera_point) -> const SemanticNode* {
    const double norm = camera_point.norm();
    for (const double shift : {0.0, -step, step}) {
      const Eigen::Vector3d p = T * (camera_point * ((norm + shift) / norm));
      octomap::OcTreeKey key;
      if (!m.tree.coordToKeyChecked(p.x(), p.y(), p.z(), key)) continue;
      const SemanticNode* node = nullptr;
      if (have_last && key == last_key) {
        node = last_node;
      } else {
        node = m.tree.search(key);
        last_key = key;
        last_node = node;
        have_last = true;
      }
      if (node != nullptr && !node->belief.empty()) return node;
    }
    return nullptr;
  };
  for (int v0 = 0; v0 < depth_m.rows; v0 += stride) {
    const float* depth = depth_m.ptr<float>(v0);
    for (int u0 = 0; u0 < depth_m.cols; u0 += stride) {
      const float d = depth[u0];
      if (!(d > 0.0f) || !std::isfinite(d) || d > max_range) continue;
      const Eigen::Vector3d camera_point((u0 - intrinsics.cx) * d / intrinsics.fx,
                                         (v0 - intrinsics.cy) * d / intrinsics.fy, d);
      const SemanticNode* node = lookup(camera_point);
      if (node == nullptr) continue;
      const auto best = std::max_element(node->belief.begin(), node->belief.end());
      const auto label = static_cast<uint8_t>(best - node->belief.begin());
      const float belief = std::exp(*best);
      const auto confidence = cv::saturate_cast<uint8_t>(belief * 255.0f);
      // Fill the stride cell where it has depth (like the forest's strided prediction).
      for (int v = v0; v < std::min(v0 + stride, depth_m.rows); ++v) {
        const float* cell_depth = depth_m.ptr<float>(v);
        uint8_t* l = out.labels.ptr<uint8_t>(v);
        uint8_t* c = out.confidence.ptr<uint8_t>(v);
        for (int u = u0; u < std::min(u0 + stride, depth_m.cols); ++u) {
          if (!(cell_depth[u] > 0.0f)) continue;
          l[u] = label;
          c[u] = confidence;
          ++out.class_pixels[label];
          sums[label] += belief;
          total += belief;
          ++out.labelled_pixels;
        }
      }
    }
  }
  for (int v = 0; v < depth_m.rows; ++v) {
    const float* depth = depth_m.ptr<float>(v);
    for (int u = 0; u < depth_m.cols; ++u) out.depth_pixels += depth[u] > 0.0f ? 1 : 0;
  }
  out.class_mean_confidence.resize(classes);
  for (size_t c = 0; c < classes; ++c) {
    out.class_mean_confidence[c] =
        out.class_pixels[c] > 0 ? sums[c] / static_cast<double>(out.class_pixels[c]) : 0.0;
  }
  out.mean_confidence = out.labelled_pixels > 0 ? total / out.labelled_pixels : 0.0;
  return out;
}

absl::Status SemanticMap::Merge(const SemanticMap& other, const Pose& T_this_other) {
  Impl& m = *impl_;
  const Impl& o = *other.impl_;
  if (o.class_count != m.class_count || o.tree.getResolution() != m.tree.getResolution()) {
    return absl::FailedPreconditionError(absl::StrFormat(
        "cannot merge a semantic map of %d classes at %g m into one of %d classes at %g m",
        o.class_count, o.tree.getResolution(), m.class_count, m.tree.getResolution()));
  }
  const Eigen::Isometry3d T = T_this_other.ToIsometry();
  if (auto s = m.CheckInCube(T.translation()); !s.ok()) return s;
  std::vector<float> p(static_cast<size_t>(m.class_count));
  for (auto it = o.tree.begin_leafs(), end = o.tree.end_leafs(); it != end; ++it) {
    if (it->belief.empty() || !o.tree.isNodeOccupied(*it)) continue;
    for (size_t c = 0; c < p.size(); ++c) p[c] = std::exp(it->belief[c]);
    ForEachLeafCell(it.getCoordinate(), it.getSize(), m.options.resolution_m,
                    [&](const Eigen::Vector3d& local) {
                      const Eigen::Vector3d q = T * local;
                      octomap::OcTreeKey key;
                      if (!m.tree.coordToKeyChecked(q.x(), q.y(), q.z(), key)) return;
                      SemanticNode* node = m.tree.updateNode(key, true, false);
                      if (node == nullptr || !m.tree.isNodeOccupied(node)) return;
                      // A voxel this map has no class for takes the other's belief as it is
                      // (merging into an empty map copies it); one it has a belief for fuses
                      // it as one observation.
                      if (node->belief.empty()) {
                        node->belief = it->belief;
                      } else {
                        m.Observe(node, p.data());
                      }
                    });
  }
  m.keyframes += o.keyframes;
  return absl::OkStatus();
}

SemanticSummary SemanticMap::Summarize() const {
  const Impl& m = *impl_;
  SemanticSummary s;
  s.resolution_m = m.tree.getResolution();
  s.class_count = m.class_count;
  s.nodes = static_cast<int64_t>(m.tree.size());
  s.class_volume_m3.assign(static_cast<size_t>(m.class_count), 0.0);
  s.keyframes = m.keyframes;
  const double leaf_volume = std::pow(s.resolution_m, 3);
  bool first = true;
  for (auto it = m.tree.begin_leafs(), end = m.tree.end_leafs(); it != end; ++it) {
    const double size = it.getSize();
    const double volume = size * size * size;
    const auto leaves = static_cast<int64_t>(std::llround(volume / leaf_volume));
    if (!m.tree.isNodeOccupied(*it)) {
      s.free_voxels += leaves;
      continue;
    }
    s.occupied_voxels += leaves;
    const octomap::point3d c = it.getCoordinate();
    const double lo[3] = {c.x() - size / 2, c.y() - size / 2, c.z() - size / 2};
    for (int a = 0; a < 3; ++a) {
      s.min_m[a] = first ? lo[a] : std::min(s.min_m[a], lo[a]);
      s.max_m[a] = first ? lo[a] + size : std::max(s.max_m[a], lo[a] + size);
    }
    first = false;
    if (it->belief.empty()) continue;
    s.labelled_voxels += leaves;
    const auto best = std::max_element(it->belief.begin(), it->belief.end());
    s.class_volume_m3[static_cast<size_t>(best - it->belief.begin())] += volume;
  }
  s.memory_bytes = m.tree.memoryUsage() + m.tree.BeliefBytes();
  return s;
}

std::vector<LabelledVoxel> SemanticMap::LabelledVoxels(int only_class) const {
  const Impl& m = *impl_;
  std::vector<LabelledVoxel> out;
  for (auto it = m.tree.begin_leafs(), end = m.tree.end_leafs(); it != end; ++it) {
    if (it->belief.empty() || !m.tree.isNodeOccupied(*it)) continue;
    const auto best = std::max_element(it->belief.begin(), it->belief.end());
    const int label = static_cast<int>(best - it->belief.begin());
    if (only_class >= 0 && label != only_class) continue;
    const octomap::point3d c = it.getCoordinate();
    out.push_back({c.x(), c.y(), c.z(), static_cast<float>(it.getSize()),
                   static_cast<uint8_t>(label), std::exp(*best)});
  }
  return out;
}

std::unique_ptr<SemanticMap> SemanticMap::OnlyClass(int class_id) const {
  const Impl& m = *impl_;
  auto copy = std::unique_ptr<SemanticMap>(
      new SemanticMap(std::make_unique<Impl>(m.class_count, m.log_prior, m.options)));
  Impl& c = *copy->impl_;
  c.keyframes = m.keyframes;
  const double h = m.tree.getResolution();
  for (auto it = m.tree.begin_leafs(), end = m.tree.end_leafs(); it != end; ++it) {
    if (it->belief.empty() || !m.tree.isNodeOccupied(*it)) continue;
    const auto best = std::max_element(it->belief.begin(), it->belief.end());
    if (best - it->belief.begin() != class_id) continue;
    // Leaf by leaf, pruned again below.
    ForEachLeafCell(it.getCoordinate(), it.getSize(), h, [&](const Eigen::Vector3d& q) {
      SemanticNode* node = c.tree.updateNode(c.tree.coordToKey(q.x(), q.y(), q.z()),
                                             it->getLogOdds(), /*lazy_eval=*/true);
      node->belief = it->belief;
    });
  }
  c.tree.updateInnerOccupancy();
  c.tree.prune();
  return copy;
}

std::string LabelledVoxelsToPly(const std::vector<LabelledVoxel>& voxels,
                                const std::vector<uint32_t>& class_colors) {
  std::string out = absl::StrCat(
      "ply\nformat binary_little_endian 1.0\ncomment written by lifemap (semantic octree)\n"
      "element vertex ",
      voxels.size(),
      "\nproperty float x\nproperty float y\nproperty float z\nproperty uchar class\n"
      "property uchar red\nproperty uchar green\nproperty uchar blue\n"
      "property float confidence\nproperty float size\nend_header\n");
  constexpr size_t kRecord = 3 * sizeof(float) + 4 + 2 * sizeof(float);
  const size_t header = out.size();
  out.resize(header + voxels.size() * kRecord);
  char* p = out.data() + header;
  static_assert(__BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__, "PLY body is written little-endian");
  for (const LabelledVoxel& v : voxels) {
    const uint32_t rgb =
        v.class_id < class_colors.size() ? class_colors[v.class_id] : uint32_t{0x808080};
    std::memcpy(p, &v.x, 4);
    std::memcpy(p + 4, &v.y, 4);
    std::memcpy(p + 8, &v.z, 4);
    p[12] = static_cast<char>(v.class_id);
    p[13] = static_cast<char>(rgb >> 16);
    p[14] = static_cast<char>(rgb >> 8);
    p[15] = static_cast<char>(rgb);
    std::memcpy(p + 16, &v.confidence, 4);
    std::memcpy(p + 20, &v.size_m, 4);
    p += kRecord;
  }
  return out;
}

std::vector<float> SemanticMap::BeliefAt(double x, double y, double z) const {
  const Impl& m = *impl_;
  octomap::OcTreeKey key;
  if (!m.tree.coordToKeyChecked(x, y, z, key)) return {};
  const SemanticNode* node = m.tree.search(key);
  if (node == nullptr || node->belief.empty() || !m.tree.isNodeOccupied(node)) return {};
  std::vector<float> p;
  for (float b : node->belief) p.push_back(std::exp(b));
  return p;
}

std::string SemanticMap::Serialize() const {
  const Impl& m = *impl_;
  std::string out(kMagic, sizeof(kMagic));
  auto append = [&out](const auto& v) { out.append(reinterpret_cast<const char*>(&v), sizeof(v)); };
  append(kVersion);
  append(static_cast<uint32_t>(m.class_count));
  append(m.tree.getResolution());
  for (float p : m.log_prior) append(p);
  append(static_cast<int64_t>(m.keyframes));
  const uint8_t has_root = m.tree.Root() != nullptr ? 1 : 0;
  append(has_root);
  if (has_root) m.tree.WriteNodes(m.tree.Root(), &out);
  AppendFnv1a64(&out);
  return out;
}

absl::StatusOr<std::unique_ptr<SemanticMap>> SemanticMap::Deserialize(
    const std::string& bytes, const SemanticMapOptions& options) {
  if (bytes.size() < sizeof(kMagic) || std::memcmp(bytes.data(), kMagic, sizeof(kMagic)) != 0) {
    return absl::InvalidArgumentError("not a lifemap semantic octree snapshot");
  }
  const char* p = bytes.data() + sizeof(kMagic);
  const char* end = bytes.data() + bytes.size();
  auto take = [&p, &end](auto* v) {
    if (end - p < static_cast<std::ptrdiff_t>(sizeof(*v))) return false;
    std::memcpy(v, p, sizeof(*v));
    p += sizeof(*v);
    return true;
  };
  uint32_t version = 0;
  if (!take(&version)) return absl::DataLossError("semantic octree snapshot truncated");
  if (version > kVersion) {
    return absl::FailedPreconditionError(absl::StrCat("semantic octree snapshot version ", version,
                                                      " is newer than this build (", kVersion,
                                                      ") reads; upgrade lifemap"));
  }
  if (bytes.size() < sizeof(kMagic) + 8) {
    return absl::DataLossError("semantic octree snapshot truncated");
  }
  uint64_t stored = 0;
  std::memcpy(&stored, bytes.data() + bytes.size() - 8, 8);
  if (Fnv1a64(std::string_view(bytes).substr(0, bytes.size() - 8)) != stored) {
    return absl::DataLossError("semantic octree snapshot is corrupt (checksum mismatch)");
  }
  end -= 8;
  uint32_t classes = 0;
  double resolution = 0;
  if (!take(&classes) || !take(&resolution)) {
    return absl::DataLossError("semantic octree snapshot truncated");
  }
  if (resolution != options.resolution_m) {
    return absl::InvalidArgumentError(
        absl::StrFormat("the snapshot's resolution is %g m but %g m was asked for; rebuild the "
                        "semantic map at the new resolution",
                        resolution, options.resolution_m));
  }
  if (classes < 2 || classes > 254) return absl::DataLossError("bad class count in snapshot");
  std::vector<float> log_prior(classes);
  for (float& log_p : log_prior) {
    if (!take(&log_p) || !std::isfinite(log_p)) {
      return absl::DataLossError("semantic octree snapshot truncated");
    }
  }
  // Made with a uniform prior, then given the stored one as it is: it was weighted
  // (prior_weight) when the map was made.
  auto map = Create(static_cast<int>(classes), std::vector<double>(classes, 1.0), options);
  if (!map.ok()) return map.status();
  (*map)->impl_->log_prior = std::move(log_prior);
  int64_t keyframes = 0;
  uint8_t has_root = 0;
  if (!take(&keyframes) || !take(&has_root)) {
    return absl::DataLossError("semantic octree snapshot truncated");
  }
  Impl& m = *(*map)->impl_;
  m.keyframes = keyframes;
  if (has_root && !m.tree.ReadNodes(p, end, classes)) {
    return absl::DataLossError("semantic octree snapshot's tree is corrupt");
  }
  if (p != end) return absl::DataLossError("semantic octree snapshot has trailing bytes");
  return map;
}

std::string SemanticMap::ToOctomapBinary() const {
  const Impl& m = *impl_;
  // OctoMap's .bt header (AbstractOccupancyOcTree::writeBinaryConst) naming an OcTree: the body
  // holds occupancy only, so it is exactly an OcTree binary file.
  std::ostringstream s;
  s << "# Octomap OcTree binary file\n# written by lifemap (semantic octree, occupancy only)\n"
    << "id OcTree\nsize " << m.tree.size() << "\nres " << m.tree.getResolution() << "\ndata\n";
  m.tree.writeBinaryData(s);
  return s.str();
}

std::string SemanticMap::ToOctomapColor(const std::vector<uint32_t>& class_colors) const {
  const Impl& m = *impl_;
  std::vector<uint32_t> colors = class_colors;
  colors.resize(static_cast<size_t>(m.class_count), 0x808080);
  std::ostringstream header;
  header << "# Octomap OcTree file\n# written by lifemap (class colours)\nid ColorOcTree\nsize "
         << m.tree.size() << "\nres " << m.tree.getResolution() << "\ndata\n";
  std::string out = header.str();
  if (m.tree.Root() != nullptr) m.tree.WriteColorNodes(m.tree.Root(), colors, &out);
  return out;
}

int SemanticMap::class_count() const { return impl_->class_count; }
double SemanticMap::resolution_m() const { return impl_->tree.getResolution(); }
int64_t SemanticMap::keyframes() const { return impl_->keyframes; }
const SemanticMapOptions& SemanticMap::options() const { return impl_->options; }

}  // namespace lifemap::semantic
