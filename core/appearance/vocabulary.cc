#include "core/appearance/vocabulary.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <random>

#include "absl/strings/str_cat.h"
#include "core/appearance/hamming.h"

namespace lifemap::appearance {

using internal::Descriptor;
using internal::Distance;

namespace {

constexpr char kMagic[] = "LMVOC1";
constexpr size_t kMagicBytes = 6;

Descriptor Load(const uint8_t* d) { return internal::LoadDescriptor(d); }

absl::Status CheckDescriptors(const cv::Mat& d) {
  if (d.empty()) return absl::OkStatus();
  if (d.type() != CV_8UC1 || d.cols != Vocabulary::kDescriptorBytes || !d.isContinuous()) {
    return absl::InvalidArgumentError(absl::StrCat(
        "descriptors must be continuous CV_8UC1 rows of ", Vocabulary::kDescriptorBytes,
        " bytes (ORB); got ", d.cols, " columns of type ", d.type()));
  }
  return absl::OkStatus();
}

// The bitwise majority of some descriptors (ties give 0).
Descriptor Majority(const std::vector<Descriptor>& all, const std::vector<uint32_t>& members) {
  std::array<int, 256> ones{};
  for (uint32_t m : members) {
    const Descriptor& d = all[m];
    for (int w = 0; w < 4; ++w) {
      uint64_t bits = d[static_cast<size_t>(w)];
      while (bits != 0) {
        ones[static_cast<size_t>(w * 64 + __builtin_ctzll(bits))]++;
        bits &= bits - 1;
      }
    }
  }
  Descriptor out{};
  const int half = static_cast<int>(members.size());
  for (size_t b = 0; b < 256; ++b) {
    if (2 * ones[b] > half) out[b / 64] |= uint64_t{1} << (b % 64);
  }
  return out;
}

}  // namespace

int HammingDistance256(const uint8_t* a, const uint8_t* b) { return Distance(Load(a), Load(b)); }

absl::Status VocabularyOptions::Validate() const {
  if (branching < 2 || branching > 64) {
    return absl::InvalidArgumentError(
        absl::StrCat("branching must be in [2, 64], got ", branching));
  }
  if (levels < 1 || levels > 8) {
    return absl::InvalidArgumentError(absl::StrCat("levels must be in [1, 8], got ", levels));
  }
  if (iterations < 1 || iterations > 100) {
    return absl::InvalidArgumentError(
        absl::StrCat("iterations must be in [1, 100], got ", iterations));
  }
  return absl::OkStatus();
}

// Builds the tree top-down: each node's descriptors split into `branching` clusters by
// k-majority (k-means++ seeding on Hamming distance, centres as bitwise majorities).
class VocabularyTrainer {
 public:
  VocabularyTrainer(const std::vector<Descriptor>& all, const VocabularyOptions& options,
                    Vocabulary* v)
      : all_(all), options_(options), v_(v), rng_(options.seed) {}

  void Build(int32_t node, const std::vector<uint32_t>& members, int level) {
    const int k = options_.branching;
    std::vector<std::vector<uint32_t>> clusters;
    std::vector<Descriptor> centres;
    if (static_cast<int>(members.size()) <= k) {
      for (uint32_t m : members) {
        centres.push_back(all_[m]);
        clusters.push_back({m});
      }
    } else {
      Cluster(members, &centres, &clusters);
    }
    const auto first = static_cast<int32_t>(v_->nodes_.size());
    v_->nodes_[static_cast<size_t>(node)].first_child = first;
    v_->nodes_[static_cast<size_t>(node)].children = static_cast<int32_t>(centres.size());
    for (const auto& c : centres) {
      Vocabulary::Node child;
      child.centroid = c;
      v_->nodes_.push_back(child);
    }
    for (size_t i = 0; i < centres.size(); ++i) {
      const auto child = first + static_cast<int32_t>(i);
      if (level + 1 >= options_.levels || clusters[i].size() <= 1) {
        v_->nodes_[static_cast<size_t>(child)].word = static_cast<int32_t>(words_++);
      } else {
        Build(child, clusters[i], level + 1);
      }
    }
  }

  size_t words() const { return words_; }

 private:
  void Cluster(const std::vector<uint32_t>& members, std::vector<Descriptor>* centres,
               std::vector<std::vector<uint32_t>>* clusters) {
    const int k = options_.branching;
    // k-means++ seeding.
    std::uniform_int_distribution<size_t> pick(0, members.size() - 1);
    centres->push_back(all_[members[pick(rng_)]]);
    std::vector<double> nearest(members.size(), 1e18);
    while (static_cast<int>(centres->size()) < k) {
      double total = 0;
      for (size_t i = 0; i < members.size(); ++i) {
        const double d = Distance(all_[members[i]], centres->back());
        nearest[i] = std::min(nearest[i], d * d);
        total += nearest[i];
      }
      if (total <= 0) break;  // every member equals a centre already
      std::uniform_real_distribution<double> u(0, total);
      double target = u(rng_);
      size_t chosen = members.size() - 1;
      for (size_t i = 0; i < members.size(); ++i) {
        target -= nearest[i];
        if (target <= 0) {
          chosen = i;
          break;
        }
      }
      centres->push_back(all_[members[chosen]]);
    }
    std::vector<int> assignment(members.size(), -1);
    for (int it = 0; it < options_.iterations; ++it) {
      bool changed = false;
      clusters->assign(centres->size(), {});
      for (size_t i = 0; i < members.size(); ++i) {
        int best = 0, best_d = 1 << 30;
        for (size_t c = 0; c < centres->size(); ++c) {
          const int d = Distance(all_[members[i]], (*centres)[c]);
          if (d < best_d) {
            best_d = d;
            best = static_cast<int>(c);
          }
        }
        changed |= assignment[i] != best;
        assignment[i] = best;
        (*clusters)[static_cast<size_t>(best)].push_back(members[i]);
      }
      if (!changed && it > 0) break;
      for (size_t c = 0; c < centres->size(); ++c) {
        if (!(*clusters)[c].empty()) (*centres)[c] = Majority(all_, (*clusters)[c]);
      }
    }
    // Clusters left empty are dropped.
    std::vector<Descriptor> kept_centres;
    std::vector<std::vector<uint32_t>> kept;
    for (size_t c = 0; c < centres->size(); ++c) {
      if ((*clusters)[c].empty()) continue;
      kept_centres.push_back((*centres)[c]);
      kept.push_back(std::move((*clusters)[c]));
    }
    *centres = std::move(kept_centres);
    *clusters = std::move(kept);
  }

  const std::vector<Descriptor>& all_;
  const VocabularyOptions& options_;
  Vocabulary* v_;
  std::mt19937_64 rng_;
  size_t words_ = 0;
};

absl::StatusOr<Vocabulary> Vocabulary::Train(const std::vector<cv::Mat>& images,
                                             const VocabularyOptions& options) {
  if (auto s = options.Validate(); !s.ok()) return s;
  std::vector<Descriptor> all;
  for (const auto& d : images) {
    if (auto s = CheckDescriptors(d); !s.ok()) return s;
    for (int r = 0; r < d.rows; ++r) all.push_back(Load(d.ptr<uint8_t>(r)));
  }
  if (static_cast<int>(all.size()) < options.branching) {
    return absl::InvalidArgumentError(absl::StrCat("a vocabulary needs at least ",
                                                   options.branching,
                                                   " descriptors to train on, got ", all.size()));
  }
  Vocabulary v;
  v.options_ = options;
  v.nodes_.emplace_back();
  std::vector<uint32_t> members(all.size());
  for (size_t i = 0; i < all.size(); ++i) members[i] = static_cast<uint32_t>(i);
  VocabularyTrainer trainer(all, options, &v);
  trainer.Build(0, members, 0);
  // Inverse document frequency, smoothed so that no word weighs 0 (a word in every training
  // image still tells a little): log((N + 1) / images containing the word).
  std::vector<int> containing(trainer.words(), 0);
  std::vector<int> last_seen(trainer.words(), -1);
  for (size_t i = 0; i < images.size(); ++i) {
    for (int r = 0; r < images[i].rows; ++r) {
      const WordId w = v.Word(images[i].ptr<uint8_t>(r));
      if (last_seen[w] != static_cast<int>(i)) {
        last_seen[w] = static_cast<int>(i);
        ++containing[w];
      }
    }
  }
  const double n = static_cast<double>(images.size()) + 1.0;
  v.idf_.resize(trainer.words());
  for (size_t w = 0; w < v.idf_.size(); ++w) {
    v.idf_[w] = static_cast<float>(std::log(n / std::max(1, containing[w])));
  }
  v.training_images_ = static_cast<int>(images.size());
  return v;
}

WordId Vocabulary::Word(const uint8_t* descriptor) const {
  const Descriptor d = Load(descriptor);
  const Node* node = &nodes_[0];
  while (node->first_child >= 0) {
    const Node* best = nullptr;
    int best_d = 1 << 30;
    for (int32_t c = 0; c < node->children; ++c) {
      const Node& child = nodes_[static_cast<size_t>(node->first_child + c)];
      const int dist = Distance(d, child.centroid);
      if (dist < best_d) {
        best_d = dist;
        best = &child;
      }
    }
    node = best;
  }
  return static_cast<WordId>(node->word);
}

absl::StatusOr<BowVector> Vocabulary::Transform(const cv::Mat& descriptors) const {
  if (auto s = CheckDescriptors(descriptors); !s.ok()) return s;
  std::vector<WordId> ids;
  ids.reserve(static_cast<size_t>(descriptors.rows));
  for (int r = 0; r < descriptors.rows; ++r) ids.push_back(Word(descriptors.ptr<uint8_t>(r)));
  std::sort(ids.begin(), ids.end());
  BowVector bow;
  double total = 0;
  for (size_t i = 0; i < ids.size();) {
    size_t j = i;
    while (j < ids.size() && ids[j] == ids[i]) ++j;
    const float weight = static_cast<float>(j - i) * idf_[ids[i]];
    if (weight > 0) {
      bow.words.emplace_back(ids[i], weight);
      total += weight;
    }
    i = j;
  }
  if (total > 0) {
    for (auto& [w, weight] : bow.words) weight = static_cast<float>(weight / total);
  }
  return bow;
}

std::string Vocabulary::Serialize() const {
  std::string out(kMagic, kMagicBytes);
  auto put = [&out](const void* p, size_t n) { out.append(static_cast<const char*>(p), n); };
  const int32_t header[6] = {options_.branching,
                             options_.levels,
                             options_.iterations,
                             training_images_,
                             static_cast<int32_t>(nodes_.size()),
                             static_cast<int32_t>(idf_.size())};
  put(header, sizeof(header));
  put(&options_.seed, sizeof(options_.seed));
  for (const auto& n : nodes_) {
    put(n.centroid.data(), sizeof(n.centroid));
    const int32_t links[3] = {n.first_child, n.children, n.word};
    put(links, sizeof(links));
  }
  put(idf_.data(), idf_.size() * sizeof(float));
  return out;
}

absl::StatusOr<Vocabulary> Vocabulary::Deserialize(const std::string& bytes) {
  auto damaged = [](const std::string& what) {
    return absl::DataLossError(absl::StrCat("the vocabulary is damaged: ", what));
  };
  if (bytes.size() < kMagicBytes || bytes.compare(0, kMagicBytes, kMagic) != 0) {
    return damaged("it does not start with LMVOC1");
  }
  size_t at = kMagicBytes;
  auto get = [&](void* p, size_t n) {
    if (bytes.size() - at < n) return false;
    std::memcpy(p, bytes.data() + at, n);
    at += n;
    return true;
  };
  int32_t header[6];
  Vocabulary v;
  if (!get(header, sizeof(header)) || !get(&v.options_.seed, sizeof(v.options_.seed))) {
    return damaged("truncated header");
  }
  v.options_.branching = header[0];
  v.options_.levels = header[1];
  v.options_.iterations = header[2];
  v.training_images_ = header[3];
  const int32_t nodes = header[4], words = header[5];
  constexpr size_t kNodeBytes = sizeof(Descriptor) + 3 * sizeof(int32_t);
  if (auto s = v.options_.Validate(); !s.ok()) return damaged(std::string(s.message()));
  if (nodes < 1 || words < 1 ||
      bytes.size() - at !=
          static_cast<size_t>(nodes) * kNodeBytes + static_cast<size_t>(words) * sizeof(float)) {
    return damaged("node and word counts do not match its size");
  }
  v.nodes_.resize(static_cast<size_t>(nodes));
  for (auto& n : v.nodes_) {
    int32_t links[3] = {-1, 0, -1};
    get(n.centroid.data(), sizeof(n.centroid));
    get(links, sizeof(links));
    n.first_child = links[0];
    n.children = links[1];
    n.word = links[2];
  }
  v.idf_.resize(static_cast<size_t>(words));
  get(v.idf_.data(), v.idf_.size() * sizeof(float));
  // Every link must stay inside the tree and go forward (no cycles), every leaf be a word.
  for (size_t i = 0; i < v.nodes_.size(); ++i) {
    const Node& n = v.nodes_[i];
    if (n.first_child < 0) {
      if (n.word < 0 || n.word >= words) return damaged("a leaf without a valid word");
      continue;
    }
    if (n.children < 1 || static_cast<size_t>(n.first_child) <= i ||
        static_cast<int64_t>(n.first_child) + n.children > nodes) {
      return damaged("a node's children lie outside the tree");
    }
  }
  for (float w : v.idf_) {
    if (!std::isfinite(w) || w < 0) return damaged("a word weight is not a finite number ≥ 0");
  }
  return v;
}

}  // namespace lifemap::appearance
