#include "core/forest/forest.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <mutex>
#include <random>
#include <thread>

#include <opencv2/imgproc.hpp>

#include "absl/strings/str_cat.h"
#include "core/common/checksum.h"
#include "core/common/task_pool.h"
#include "core/common/utf8.h"

namespace lifemap::forest {
namespace {

// A feature whose rectangle leaves the image or holds no valid depth evaluates to this.
constexpr float kLarge = 1e4f;

// The largest image whose 8-bit channel sums fit the integral image's uint32 cells.
constexpr int64_t kMaxPixels = (int64_t{1} << 32) / 256;

// One integral image, (rows + 1) x (cols + 1) cells, with every channel of a corner side by
// side: a rectangle's mean reads 4 cells (4 cache lines) whichever channel it is on. Written
// here rather than with cv::integral: five separate CV_64F integral images (12 MB a VGA frame)
// cost 4 cache misses per corner pair of a depth feature and made the trees' lookups 30 % of
// the server's CPU. Sums are exact: depth in double, the count of valid readings and the 8-bit
// L*, a*, b* sums in uint32 (images up to kMaxPixels).
struct Cell {
  double depth_sum;
  uint32_t depth_count;
  uint32_t lab[3];
};

struct Channels {
  std::vector<Cell> cells;
  int rows = 0, cols = 0;
  const Cell& at(int y, int x) const {
    return cells[static_cast<size_t>(y) * static_cast<size_t>(cols + 1) + static_cast<size_t>(x)];
  }
};

Channels MakeChannels(const cv::Mat& depth_m, const cv::Mat& color_bgr) {
  Channels ch;
  ch.rows = depth_m.rows;
  ch.cols = depth_m.cols;
  cv::Mat lab;
  cv::cvtColor(color_bgr, lab, cv::COLOR_BGR2Lab);
  const size_t width = static_cast<size_t>(ch.cols) + 1;
  ch.cells.assign(width * (static_cast<size_t>(ch.rows) + 1), Cell{0.0, 0, {0, 0, 0}});
  for (int y = 0; y < ch.rows; ++y) {
    const float* depth = depth_m.ptr<float>(y);
    const uint8_t* colour = lab.ptr<uint8_t>(y);
    const Cell* above = &ch.cells[static_cast<size_t>(y) * width];
    Cell* out = &ch.cells[static_cast<size_t>(y + 1) * width];
    Cell row{0.0, 0, {0, 0, 0}};  // sums over this row up to x
    for (int x = 0; x < ch.cols; ++x) {
      // NaN and negative count as missing.
      if (depth[x] > 0) {
        row.depth_sum += depth[x];
        ++row.depth_count;
      }
      for (int i = 0; i < 3; ++i) row.lab[i] += colour[3 * x + i];
      Cell& c = out[x + 1];
      c.depth_sum = above[x + 1].depth_sum + row.depth_sum;
      c.depth_count = above[x + 1].depth_count + row.depth_count;
      for (int i = 0; i < 3; ++i) c.lab[i] = above[x + 1].lab[i] + row.lab[i];
    }
  }
  return ch;
}

// Mean of a channel over the rectangle centred at (cx, cy) of size (w, h), clipped to the
// image; kLarge when its centre is outside or it holds no valid depth.
float RectMean(const Channels& ch, int channel, float cx, float cy, float w, float h) {
  // Written so that NaN centres are outside too.
  if (!(cx >= 0 && cy >= 0 && cx < ch.cols && cy < ch.rows)) return kLarge;
  // Edges clipped in float before the conversion: a rectangle far larger than the image (a
  // model's size at a depth near the sensor's minimum) must not overflow an int.
  const int x0 = static_cast<int>(std::max(0.0f, cx - w / 2));
  const int y0 = static_cast<int>(std::max(0.0f, cy - h / 2));
  const int x1 = std::max(x0 + 1, static_cast<int>(std::min<float>(ch.cols - 1, cx + w / 2)) + 1);
  const int y1 = std::max(y0 + 1, static_cast<int>(std::min<float>(ch.rows - 1, cy + h / 2)) + 1);
  const Cell& a = ch.at(y0, x0);
  const Cell& b = ch.at(y0, x1);
  const Cell& c = ch.at(y1, x0);
  const Cell& d = ch.at(y1, x1);
  if (channel == 0) {
    const uint32_t n = d.depth_count - b.depth_count - c.depth_count + a.depth_count;
    return n > 0 ? static_cast<float>((d.depth_sum - b.depth_sum - c.depth_sum + a.depth_sum) / n)
                 : kLarge;
  }
  const int i = channel - 1;
  const uint32_t sum = d.lab[i] - b.lab[i] - c.lab[i] + a.lab[i];
  const double area = static_cast<double>(x1 - x0) * (y1 - y0);
  return static_cast<float>(sum / area);
}

// Eq. 1 at pixel (x, y) whose depth is `depth` (> 0).
float Evaluate(const Channels& ch, const Feature& f, int x, int y, float depth) {
  const float s = 1.0f / depth;
  const float m1 = RectMean(ch, f.channel1, x + f.offset1_x * s, y + f.offset1_y * s,
                            std::max(1.0f, f.size1_x * s), std::max(1.0f, f.size1_y * s));
  const float m2 = RectMean(ch, f.channel2, x + f.offset2_x * s, y + f.offset2_y * s,
                            std::max(1.0f, f.size2_x * s), std::max(1.0f, f.size2_y * s));
  if (m1 == kLarge || m2 == kLarge) return kLarge;
  return m1 - m2;
}

Feature RandomFeature(std::mt19937_64* rng, const TrainOptions& o) {
  std::uniform_real_distribution<float> offset(-o.max_offset, o.max_offset);
  std::uniform_real_distribution<float> size(1.0f, o.max_size);
  Feature f;
  f.offset1_x = offset(*rng), f.offset1_y = offset(*rng);
  f.size1_x = size(*rng), f.size1_y = size(*rng);
  f.offset2_x = offset(*rng), f.offset2_y = offset(*rng);
  f.size2_x = size(*rng), f.size2_y = size(*rng);
  // Depth against depth, or colour against colour (any two of L*, a*, b*).
  // A uniform number in [0, 1) whose most significant bit is the draw's lowest: at a share of
  // 0.5 the choice is the draw's parity, as before the share was an option (models trained
  // before with an even split are reproduced by --depth-features 0.5).
  const uint64_t draw = (*rng)();
  double u = 0, bit = 0.5;
  for (int b = 0; b < 53; ++b, bit /= 2) u += static_cast<double>((draw >> b) & 1) * bit;
  if (u < o.depth_feature_share) {
    f.channel1 = f.channel2 = 0;
  } else {
    f.channel1 = static_cast<uint8_t>(1 + (*rng)() % 3);
    f.channel2 = static_cast<uint8_t>(1 + (*rng)() % 3);
  }
  return f;
}

struct Sample {
  int image;
  int x, y;
  float depth;
  uint8_t label;
};

}  // namespace

double HistogramEntropy(const std::vector<double>& counts) {
  double total = 0;
  for (double c : counts) total += c;
  if (total <= 0) return 0;
  double h = 0;
  for (double c : counts) {
    if (c > 0) h -= (c / total) * std::log(c / total);
  }
  return h;
}

double InformationGain(const std::vector<double>& parent, const std::vector<double>& left,
                       const std::vector<double>& right) {
  double n = 0, nl = 0, nr = 0;
  for (double c : parent) n += c;
  for (double c : left) nl += c;
  for (double c : right) nr += c;
  if (n <= 0) return 0;
  return HistogramEntropy(parent) - nl / n * HistogramEntropy(left) -
         nr / n * HistogramEntropy(right);
}

absl::Status TrainOptions::Validate() const {
  if (trees < 1 || trees > 64 || max_depth < 1 || max_depth > 40 || min_samples < 1 ||
      pixels_per_image < 1 || candidates < 1 || threads < 1 || !(max_offset >= 0) ||
      !(max_size >= 1) || !(depth_feature_share >= 0 && depth_feature_share <= 1)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "training options out of range: trees [1, 64] (", trees, "), depth [1, 40] (", max_depth,
        "), min_samples, pixels_per_image, candidates, threads >= 1, max_offset >= 0 (", max_offset,
        "), max_size >= 1 (", max_size, "), depth_feature_share [0, 1] (", depth_feature_share,
        ")"));
  }
  return absl::OkStatus();
}

size_t Forest::node_count() const {
  size_t n = 0;
  for (const auto& t : trees_) n += t.nodes.size();
  return n;
}

absl::StatusOr<Forest> Forest::Train(const std::vector<LabeledImage>& images, int class_count,
                                     const TrainOptions& options) {
  if (auto s = options.Validate(); !s.ok()) return s;
  if (images.empty()) return absl::InvalidArgumentError("training needs at least one image");
  if (class_count < 2 || class_count > 254) {
    return absl::InvalidArgumentError(
        absl::StrCat("class count must be within [2, 254], got ", class_count));
  }
  Forest forest;
  forest.class_count_ = class_count;
  forest.prior_.assign(static_cast<size_t>(class_count), 0.0);
  std::vector<Channels> channels;
  for (size_t i = 0; i < images.size(); ++i) {
    const auto& im = images[i];
    if (im.depth_m.type() != CV_32FC1 || im.color_bgr.type() != CV_8UC3 ||
        im.labels.type() != CV_8UC1 || im.depth_m.size() != im.color_bgr.size() ||
        im.depth_m.size() != im.labels.size() || im.depth_m.empty()) {
      return absl::InvalidArgumentError(
          absl::StrCat("training image ", i,
                       ": needs CV_32FC1 depth, CV_8UC3 colour, CV_8UC1 labels of one size"));
    }
    if (im.depth_m.total() > static_cast<size_t>(kMaxPixels)) {
      return absl::InvalidArgumentError(
          absl::StrCat("training image ", i, " is larger than ", kMaxPixels, " pixels"));
    }
    for (int r = 0; r < im.labels.rows; ++r) {
      const uint8_t* l = im.labels.ptr<uint8_t>(r);
      const float* d = im.depth_m.ptr<float>(r);
      for (int c = 0; c < im.labels.cols; ++c) {
        if (l[c] == kIgnore || !(d[c] > 0)) continue;
        if (l[c] >= class_count) {
          return absl::InvalidArgumentError(absl::StrCat(
              "training image ", i, " has label ", int{l[c]}, " >= class count ", class_count));
        }
        forest.prior_[l[c]] += 1;
      }
    }
    channels.push_back(MakeChannels(im.depth_m, im.color_bgr));
  }
  double total = 0;
  for (double p : forest.prior_) total += p;
  if (total == 0) return absl::InvalidArgumentError("no labelled pixel with depth to train on");
  for (double& p : forest.prior_) p /= total;

  forest.trees_.resize(static_cast<size_t>(options.trees));
  auto train_tree = [&](int k) {
    std::mt19937_64 rng(options.seed * 1000003ULL + static_cast<uint64_t>(k));
    // Each tree learns from its own share of the images (all of them when there are fewer
    // images than trees), N pixels per image balanced across the classes present.
    std::vector<int> subset;
    for (int i = 0; i < static_cast<int>(images.size()); ++i) {
      if (images.size() < static_cast<size_t>(options.trees) || i % options.trees == k) {
        subset.push_back(i);
      }
    }
    std::vector<Sample> samples;
    for (int i : subset) {
      std::vector<std::vector<Sample>> by_class(static_cast<size_t>(class_count));
      const auto& im = images[static_cast<size_t>(i)];
      for (int r = 0; r < im.labels.rows; ++r) {
        const uint8_t* l = im.labels.ptr<uint8_t>(r);
        const float* d = im.depth_m.ptr<float>(r);
        for (int c = 0; c < im.labels.cols; ++c) {
          if (l[c] != kIgnore && d[c] > 0) by_class[l[c]].push_back({i, c, r, d[c], l[c]});
        }
      }
      int present = 0;
      for (const auto& v : by_class) present += !v.empty();
      if (present == 0) continue;
      const int per_class = std::max(1, options.pixels_per_image / present);
      for (const auto& v : by_class) {
        if (v.empty()) continue;
        std::uniform_int_distribution<size_t> pick(0, v.size() - 1);
        for (int n = 0; n < per_class; ++n) samples.push_back(v[pick(rng)]);
      }
    }
    // Weight of one sample of each class: 1, or (with global balance) such that every class
    // present weighs as much as an even share of all samples.
    std::vector<double> weight(static_cast<size_t>(class_count), 1.0);
    if (options.global_balance) {
      std::vector<double> count(static_cast<size_t>(class_count), 0.0);
      for (const Sample& s : samples) count[s.label] += 1;
      int present = 0;
      for (double c : count) present += c > 0;
      for (size_t c = 0; c < count.size(); ++c) {
        if (count[c] > 0) weight[c] = static_cast<double>(samples.size()) / (present * count[c]);
      }
    }
    Tree& tree = forest.trees_[static_cast<size_t>(k)];
    struct Work {
      int node;
      size_t begin, end;
      int depth;
    };
    tree.nodes.emplace_back();
    std::vector<Work> stack = {{0, 0, samples.size(), 0}};
    std::vector<float> values;
    while (!stack.empty()) {
      const Work w = stack.back();
      stack.pop_back();
      std::vector<double> hist(static_cast<size_t>(class_count), 0.0);
      for (size_t i = w.begin; i < w.end; ++i) hist[samples[i].label] += weight[samples[i].label];
      int nonzero = 0;
      for (double h : hist) nonzero += h > 0;
      auto make_leaf = [&]() {
        tree.nodes[static_cast<size_t>(w.node)].leaf =
            static_cast<int32_t>(tree.leaves.size() / static_cast<size_t>(class_count));
        double n = 0;
        for (double h : hist) n += h;
        for (double h : hist) tree.leaves.push_back(n > 0 ? static_cast<float>(h / n) : 0.0f);
      };
      if (w.depth >= options.max_depth ||
          w.end - w.begin < static_cast<size_t>(options.min_samples) || nonzero <= 1) {
        make_leaf();
        continue;
      }
      double best_gain = 0;
      Feature best_feature{};
      float best_threshold = 0;
      values.resize(w.end - w.begin);
      std::uniform_int_distribution<size_t> pick(w.begin, w.end - 1);
      for (int p = 0; p < options.candidates; ++p) {
        const Feature f = RandomFeature(&rng, options);
        for (size_t i = w.begin; i < w.end; ++i) {
          const Sample& s = samples[i];
          values[i - w.begin] =
              Evaluate(channels[static_cast<size_t>(s.image)], f, s.x, s.y, s.depth);
        }
        const float threshold = values[pick(rng) - w.begin];
        std::vector<double> left(hist.size(), 0.0), right(hist.size(), 0.0);
        for (size_t i = w.begin; i < w.end; ++i) {
          (values[i - w.begin] < threshold ? left : right)[samples[i].label] +=
              weight[samples[i].label];
        }
        const double gain = InformationGain(hist, left, right);
        if (gain > best_gain) {
          best_gain = gain;
          best_feature = f;
          best_threshold = threshold;
        }
      }
      if (best_gain <= 1e-12) {
        make_leaf();
        continue;
      }
      auto middle = std::partition(
          samples.begin() + static_cast<std::ptrdiff_t>(w.begin),
          samples.begin() + static_cast<std::ptrdiff_t>(w.end), [&](const Sample& s) {
            return Evaluate(channels[static_cast<size_t>(s.image)], best_feature, s.x, s.y,
                            s.depth) < best_threshold;
          });
      const size_t mid = static_cast<size_t>(middle - samples.begin());
      const int left_node = static_cast<int>(tree.nodes.size());
      tree.nodes.emplace_back();
      tree.nodes.emplace_back();
      Node& node = tree.nodes[static_cast<size_t>(w.node)];
      node.feature = best_feature;
      node.threshold = best_threshold;
      node.left = left_node;
      node.right = left_node + 1;
      stack.push_back({left_node, w.begin, mid, w.depth + 1});
      stack.push_back({left_node + 1, mid, w.end, w.depth + 1});
    }
  };
  std::vector<std::thread> workers;
  const int threads = std::min(options.threads, options.trees);
  std::mutex progress_mu;
  int done = 0;
  for (int t = 0; t < threads; ++t) {
    workers.emplace_back([&, t] {
      for (int k = t; k < options.trees; k += threads) {
        train_tree(k);
        if (options.progress) {
          std::lock_guard<std::mutex> lock(progress_mu);
          options.progress(++done, options.trees);
        }
      }
    });
  }
  for (auto& w : workers) w.join();
  return forest;
}

absl::StatusOr<Prediction> Forest::Predict(const cv::Mat& depth_m, const cv::Mat& color_bgr,
                                           Decision decision, int stride) const {
  if (depth_m.type() != CV_32FC1 || color_bgr.type() != CV_8UC3 ||
      depth_m.size() != color_bgr.size() || depth_m.empty()) {
    return absl::InvalidArgumentError(
        "prediction needs CV_32FC1 depth and CV_8UC3 colour of one size");
  }
  if (stride < 1 || stride > 16) {
    return absl::InvalidArgumentError(absl::StrCat("stride must be within [1, 16], got ", stride));
  }
  if (trees_.empty()) return absl::FailedPreconditionError("the forest has no trees");
  if (depth_m.total() > static_cast<size_t>(kMaxPixels)) {
    return absl::InvalidArgumentError(absl::StrCat("prediction takes images of at most ",
                                                   kMaxPixels, " pixels, got ", depth_m.cols, "x",
                                                   depth_m.rows));
  }
  const Channels ch = MakeChannels(depth_m, color_bgr);
  Prediction out;
  out.labels = cv::Mat(depth_m.size(), CV_8UC1, cv::Scalar(kIgnore));
  for (int c = 0; c < class_count_; ++c) {
    out.probabilities.emplace_back(depth_m.size(), CV_32FC1, cv::Scalar(0.0f));
  }
  // Pixels go down each tree in batches, one level at a time for the whole batch: a node's
  // feature reads 4-8 integral-image cells far apart, and one pixel's path is a chain of such
  // misses; a batch lets the core overlap the misses of independent pixels (measured in
  // bench_forest BM_PredictFrame).
  constexpr int kBatch = 16;
  const size_t classes = static_cast<size_t>(class_count_);
  auto predict_rows = [&](int first_row_block, int step) {
    std::vector<double> votes(kBatch * classes);
    int xs[kBatch];
    float ds[kBatch];
    int32_t at[kBatch];
    for (int y = first_row_block * stride; y < depth_m.rows; y += step * stride) {
      const float* depth_row = depth_m.ptr<float>(y);
      for (int x_next = 0; x_next < depth_m.cols;) {
        int m = 0;
        for (; x_next < depth_m.cols && m < kBatch; x_next += stride) {
          if (!(depth_row[x_next] > 0)) continue;
          xs[m] = x_next;
          ds[m] = depth_row[x_next];
          ++m;
        }
        if (m == 0) break;
        std::fill(votes.begin(), votes.begin() + static_cast<ptrdiff_t>(m * classes), 0.0);
        for (const auto& tree : trees_) {
          std::fill(at, at + m, 0);
          for (bool descending = true; descending;) {
            descending = false;
            for (int i = 0; i < m; ++i) {
              const Node& node = tree.nodes[static_cast<size_t>(at[i])];
              if (node.left < 0) continue;
              at[i] = Evaluate(ch, node.feature, xs[i], y, ds[i]) < node.threshold ? node.left
                                                                                   : node.right;
              descending = true;
            }
          }
          for (int i = 0; i < m; ++i) {
            const float* leaf =
                &tree.leaves[static_cast<size_t>(tree.nodes[static_cast<size_t>(at[i])].leaf) *
                             classes];
            double* p = &votes[static_cast<size_t>(i) * classes];
            for (size_t c = 0; c < classes; ++c) p[c] += leaf[c];
          }
        }
        for (int i = 0; i < m; ++i) {
          double* p = &votes[static_cast<size_t>(i) * classes];
          double sum = 0;
          for (size_t c = 0; c < classes; ++c) {
            // Eq. 9: balanced training makes p(c|Q) uniform, so re-weighting is by p(c).
            if (decision == Decision::kPriorWeighted) p[c] *= prior_[c];
            sum += p[c];
          }
          size_t best = 0;
          for (size_t c = 0; c < classes; ++c) {
            p[c] = sum > 0 ? p[c] / sum : 0.0;
            if (p[c] > p[best]) best = c;
          }
          // The stride cell copies the prediction; plain loops (cv::Mat ROI + setTo per cell
          // cost more than the trees at stride 4).
          const int x = xs[i];
          const int y1 = std::min(depth_m.rows, y + stride);
          const int x1 = std::min(depth_m.cols, x + stride);
          for (int yy = y; yy < y1; ++yy) {
            std::fill(out.labels.ptr<uint8_t>(yy) + x, out.labels.ptr<uint8_t>(yy) + x1,
                      static_cast<uint8_t>(best));
            for (size_t c = 0; c < classes; ++c) {
              float* row = out.probabilities[c].ptr<float>(yy);
              std::fill(row + x, row + x1, static_cast<float>(p[c]));
            }
          }
        }
      }
    }
  };
  // Rows split over two tasks of the shared pool (the caller runs both when the pool is busy).
  TaskPool::Shared().RunAll({[&] { predict_rows(0, 2); }, [&] { predict_rows(1, 2); }});
  return out;
}

namespace {

template <typename T>
void Put(std::string* out, const T& v) {
  out->append(reinterpret_cast<const char*>(&v), sizeof(T));
}

// Deepest tree a model file may hold: training makes at most 40 levels (TrainOptions).
constexpr uint8_t kMaxLoadedDepth = 64;

class Reader {
 public:
  Reader(const std::string& bytes, size_t end) : bytes_(bytes), end_(end) {}
  template <typename T>
  bool Get(T* v) {
    if (pos_ + sizeof(T) > end_) return false;
    std::memcpy(v, bytes_.data() + pos_, sizeof(T));
    pos_ += sizeof(T);
    return true;
  }
  bool GetString(std::string* s, uint32_t max) {
    uint32_t n = 0;
    if (!Get(&n) || n > max || pos_ + n > end_) return false;
    s->assign(bytes_.data() + pos_, n);
    pos_ += n;
    return true;
  }
  bool done() const { return pos_ == end_; }
  size_t remaining() const { return end_ - pos_; }

 private:
  const std::string& bytes_;
  size_t end_;
  size_t pos_ = 0;
};

// Model file layout (little-endian):
//   "LMRF", u32 version, u32 classes, f64 prior[classes],
//   u32 names, {u32 length, bytes}[names],
//   version >= 2: u32 colours[classes] (0xRRGGBB), u32 length + training JSON,
//   u32 trees, per tree: u32 nodes, node records, u32 leaf values, f32 leaves[],
//   u64 FNV-1a of everything before it.
constexpr char kMagic[4] = {'L', 'M', 'R', 'F'};
constexpr uint32_t kVersion = 2;
constexpr uint32_t kMaxTrainingJson = 1u << 20;

}  // namespace

uint32_t DefaultClassColor(int class_id) {
  // Class 0 (background) grey; the others a fixed, well-separated palette, then hashed.
  static constexpr uint32_t kPalette[] = {0x808080, 0xE6194B, 0x3CB44B, 0x4363D8, 0xF58231,
                                          0x911EB4, 0x42D4F4, 0xF032E6, 0xBFEF45, 0xFABED4,
                                          0x469990, 0xDCBEFF, 0x9A6324, 0xFFFAC8, 0x800000,
                                          0xAAFFC3, 0x808000, 0xFFD8B1, 0x000075, 0xFFE119};
  constexpr int n = sizeof(kPalette) / sizeof(kPalette[0]);
  if (class_id >= 0 && class_id < n) return kPalette[class_id];
  return (static_cast<uint32_t>(class_id) * 2654435761u) & 0xFFFFFFu;
}

std::string Forest::Serialize(const ModelDescription& description) const {
  static_assert(__BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__, "model files are little-endian");
  std::string out(kMagic, 4);
  Put(&out, kVersion);
  Put(&out, static_cast<uint32_t>(class_count_));
  for (double p : prior_) Put(&out, p);
  // Names and colours are written for every class: missing ones get defaults.
  Put(&out, static_cast<uint32_t>(class_count_));
  for (int c = 0; c < class_count_; ++c) {
    const std::string n = static_cast<size_t>(c) < description.class_names.size()
                              ? description.class_names[static_cast<size_t>(c)]
                              : absl::StrCat("class", c);
    Put(&out, static_cast<uint32_t>(n.size()));
    out += n;
  }
  for (int c = 0; c < class_count_; ++c) {
    const uint32_t color = static_cast<size_t>(c) < description.class_colors.size()
                               ? description.class_colors[static_cast<size_t>(c)] & 0xFFFFFFu
                               : DefaultClassColor(c);
    Put(&out, color);
  }
  Put(&out, static_cast<uint32_t>(description.training_json.size()));
  out += description.training_json;
  Put(&out, static_cast<uint32_t>(trees_.size()));
  for (const auto& t : trees_) {
    Put(&out, static_cast<uint32_t>(t.nodes.size()));
    for (const auto& n : t.nodes) {
      // Field by field: the struct has padding bytes, which must not reach the file.
      const Feature& f = n.feature;
      for (float v : {f.offset1_x, f.offset1_y, f.size1_x, f.size1_y, f.offset2_x, f.offset2_y,
                      f.size2_x, f.size2_y}) {
        Put(&out, v);
      }
      Put(&out, f.channel1);
      Put(&out, f.channel2);
      Put(&out, n.threshold);
      Put(&out, n.left);
      Put(&out, n.right);
      Put(&out, n.leaf);
    }
    Put(&out, static_cast<uint32_t>(t.leaves.size()));
    for (float v : t.leaves) Put(&out, v);
  }
  AppendFnv1a64(&out);
  return out;
}

absl::StatusOr<Forest> Forest::Deserialize(const std::string& bytes,
                                           ModelDescription* description) {
  auto corrupt = [](const char* what) {
    return absl::DataLossError(absl::StrCat("model file is corrupt or truncated: ", what));
  };
  if (bytes.size() < 16 || std::memcmp(bytes.data(), kMagic, 4) != 0) {
    return absl::InvalidArgumentError("not a lifemap forest model (bad magic)");
  }
  uint64_t stored = 0;
  std::memcpy(&stored, bytes.data() + bytes.size() - 8, 8);
  if (stored != Fnv1a64(std::string_view(bytes).substr(0, bytes.size() - 8)))
    return corrupt("checksum mismatch");
  Reader r(bytes, bytes.size() - 8);
  char magic[4];
  uint32_t version = 0, classes = 0, names = 0, trees = 0;
  for (char& c : magic) r.Get(&c);
  if (!r.Get(&version)) return corrupt("header");
  if (version < 1 || version > kVersion) {
    return absl::FailedPreconditionError(absl::StrCat(
        "model file version ", version, " is not supported by this build (", kVersion, ")"));
  }
  if (!r.Get(&classes) || classes < 2 || classes > 254) return corrupt("class count");
  Forest f;
  f.class_count_ = static_cast<int>(classes);
  f.prior_.resize(classes);
  for (double& p : f.prior_) {
    if (!r.Get(&p)) return corrupt("prior");
  }
  if (!r.Get(&names) || names > 1024) return corrupt("class names");
  std::vector<std::string> read_names(names);
  for (auto& n : read_names) {
    if (!r.GetString(&n, 1024)) return corrupt("class name");
    // Class names are listed back to every client (ListModels, labels): text, never bytes.
    if (!IsValidUtf8(n)) return corrupt("class name (not UTF-8 text)");
  }
  ModelDescription read;
  read.class_names = std::move(read_names);
  if (version >= 2) {
    if (read.class_names.size() != classes) return corrupt("class names");
    read.class_colors.resize(classes);
    for (uint32_t& c : read.class_colors) {
      if (!r.Get(&c) || c > 0xFFFFFFu) return corrupt("class colours");
    }
    if (!r.GetString(&read.training_json, kMaxTrainingJson) || !IsValidUtf8(read.training_json)) {
      return corrupt("training summary");
    }
  } else {
    for (uint32_t c = 0; c < classes; ++c) {
      if (c >= read.class_names.size()) read.class_names.push_back(absl::StrCat("class", c));
      read.class_colors.push_back(DefaultClassColor(static_cast<int>(c)));
    }
    read.class_names.resize(classes);
  }
  if (!r.Get(&trees) || trees < 1 || trees > 64) return corrupt("tree count");
  f.trees_.resize(trees);
  for (auto& t : f.trees_) {
    uint32_t nodes = 0, leaves = 0;
    // Counts are checked against the bytes left before anything is allocated: a 142-byte file
    // claiming 2^26 nodes made the reader allocate 3.5 GB (found by tests/fuzz/forest_model_fuzz).
    constexpr size_t kNodeBytes =
        8 * sizeof(float) + 2 * sizeof(uint8_t) + sizeof(float) + 3 * sizeof(int32_t);
    if (!r.Get(&nodes) || nodes < 1 || nodes > (1u << 26) || nodes > r.remaining() / kNodeBytes) {
      return corrupt("node count");
    }
    t.nodes.resize(nodes);
    for (auto& n : t.nodes) {
      Feature& ft = n.feature;
      if (!r.Get(&ft.offset1_x) || !r.Get(&ft.offset1_y) || !r.Get(&ft.size1_x) ||
          !r.Get(&ft.size1_y) || !r.Get(&ft.offset2_x) || !r.Get(&ft.offset2_y) ||
          !r.Get(&ft.size2_x) || !r.Get(&ft.size2_y) || !r.Get(&ft.channel1) ||
          !r.Get(&ft.channel2) || !r.Get(&n.threshold) || !r.Get(&n.left) || !r.Get(&n.right) ||
          !r.Get(&n.leaf)) {
        return corrupt("node");
      }
    }
    if (!r.Get(&leaves) || leaves % classes != 0 || leaves > (1u << 28) ||
        leaves > r.remaining() / sizeof(float)) {
      return corrupt("leaves");
    }
    t.leaves.resize(leaves);
    for (float& v : t.leaves) {
      if (!r.Get(&v)) return corrupt("leaf");
    }
    const int32_t leaf_count = static_cast<int32_t>(leaves / classes);
    // Depth per node (children follow their parents, so one pass): a tree deeper than training
    // makes (40) would be a chain that every pixel walks to its end.
    std::vector<uint8_t> depth(nodes, 0);
    for (int32_t i = 0; i < static_cast<int32_t>(nodes); ++i) {
      const Node& n = t.nodes[static_cast<size_t>(i)];
      const bool inner = n.left >= 0;
      // Children always follow their parent: this also rules out cycles.
      if (inner ? (n.left <= i || n.right <= i || n.left >= static_cast<int32_t>(nodes) ||
                   n.right >= static_cast<int32_t>(nodes) || n.feature.channel1 > 3 ||
                   n.feature.channel2 > 3)
                : (n.leaf < 0 || n.leaf >= leaf_count)) {
        return corrupt("a node points outside its tree");
      }
      if (inner) {
        const uint8_t below = static_cast<uint8_t>(depth[static_cast<size_t>(i)] + 1);
        if (below > kMaxLoadedDepth) return corrupt("a tree deeper than 64 levels");
        depth[static_cast<size_t>(n.left)] = std::max(depth[static_cast<size_t>(n.left)], below);
        depth[static_cast<size_t>(n.right)] = std::max(depth[static_cast<size_t>(n.right)], below);
      }
    }
  }
  if (!r.done()) return corrupt("trailing bytes");
  if (description) *description = std::move(read);
  return f;
}

}  // namespace lifemap::forest
