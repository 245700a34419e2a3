// An inverted file over the words of every indexed keyframe: a query's candidates are the
// keyframes sharing the most weight of its words (the L1 score of Nistér & Stewénius, as in
// DBoW2: s(v, w) = 1 − ½‖v − w‖₁ = Σ_word min(v_word, w_word) for L1-normalised vectors), in
// time proportional to the postings of the query's words rather than to the keyframes stored.
#pragma once

#include <cstdint>
#include <functional>
#include <vector>

#include "absl/synchronization/mutex.h"
#include "core/appearance/vocabulary.h"

namespace lifemap::appearance {

// Which stored keyframe an index entry is.
struct KeyframeRef {
  int64_t map_id = 0;
  int64_t visit_id = 0;
  int64_t keyframe_id = 0;
  double timestamp_s = 0;  // the frame's capture time, seconds
  // Candidates are ranked by their L1 score times this (1: the score alone). lifemapd weighs
  // keyframes that other visits recognised (appearance.recognised_weight).
  float weight = 1.0f;
};

struct Candidate {
  KeyframeRef keyframe;
  float score = 0;  // L1 score in [0, 1]
  float rank = 0;   // score × keyframe.weight: what the candidates are ordered by
};

struct IndexStats {
  size_t keyframes = 0;
  size_t postings = 0;
  size_t memory_bytes = 0;  // postings and entries, as allocated
};

// Thread-safe: queries share a reader lock; Add and Remove take it exclusively.
class InvertedIndex {
 public:
  // `stop_word_share` in (0, 1]: see Query (1 = no stop list).
  explicit InvertedIndex(size_t words, double stop_word_share = kStopWordShare)
      : stop_word_share_(stop_word_share), postings_(words) {}

  // Words outside the vocabulary's size are ignored.
  void Add(const KeyframeRef& keyframe, const BowVector& bow);
  // Sets the ranking weight of the entry of keyframe `keyframe_id` (> 0); false when it is not
  // indexed. Linear in the entries.
  bool SetWeight(int64_t keyframe_id, float weight);
  // Removes the entries `drop` selects; returns how many. Linear in the postings.
  size_t RemoveIf(const std::function<bool(const KeyframeRef&)>& drop);

  // The `top_k` best-ranked entries (score × weight) with score > 0 that `exclude` (may be
  // empty) does not reject, best first. Once the index holds kStopWordMinKeyframes keyframes, words
  // found in more than stop_word_share of them are not scored (a stop list).
  std::vector<Candidate> Query(const BowVector& query, size_t top_k,
                               const std::function<bool(const KeyframeRef&)>& exclude = {}) const;

  IndexStats Stats() const;

  static constexpr size_t kStopWordMinKeyframes = 1000;
  static constexpr double kStopWordShare = 0.2;

 private:
  struct Posting {
    uint32_t entry;
    float weight;
  };
  const double stop_word_share_;
  mutable absl::Mutex mu_;
  std::vector<std::vector<Posting>> postings_ ABSL_GUARDED_BY(mu_);
  std::vector<KeyframeRef> entries_ ABSL_GUARDED_BY(mu_);
};

}  // namespace lifemap::appearance
