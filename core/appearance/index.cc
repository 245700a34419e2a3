#include "core/appearance/index.h"

#include <algorithm>

namespace lifemap::appearance {

void InvertedIndex::Add(const KeyframeRef& keyframe, const BowVector& bow) {
  absl::MutexLock lock(&mu_);
  const auto entry = static_cast<uint32_t>(entries_.size());
  entries_.push_back(keyframe);
  for (const auto& [word, weight] : bow.words) {
    if (word < postings_.size()) postings_[word].push_back({entry, weight});
  }
}

bool InvertedIndex::SetWeight(int64_t keyframe_id, float weight) {
  absl::MutexLock lock(&mu_);
  for (auto& e : entries_) {
    if (e.keyframe_id == keyframe_id) {
      e.weight = weight;
      return true;
    }
  }
  return false;
}

size_t InvertedIndex::RemoveIf(const std::function<bool(const KeyframeRef&)>& drop) {
  absl::MutexLock lock(&mu_);
  // Entries are renumbered densely so that query scratch stays proportional to what is kept.
  std::vector<int64_t> renumber(entries_.size(), -1);
  std::vector<KeyframeRef> kept;
  for (size_t i = 0; i < entries_.size(); ++i) {
    if (drop(entries_[i])) continue;
    renumber[i] = static_cast<int64_t>(kept.size());
    kept.push_back(entries_[i]);
  }
  const size_t removed = entries_.size() - kept.size();
  if (removed == 0) return 0;
  for (auto& list : postings_) {
    size_t out = 0;
    for (const Posting& p : list) {
      if (renumber[p.entry] < 0) continue;
      list[out++] = {static_cast<uint32_t>(renumber[p.entry]), p.weight};
    }
    list.resize(out);
  }
  entries_ = std::move(kept);
  return removed;
}

std::vector<Candidate> InvertedIndex::Query(
    const BowVector& query, size_t top_k,
    const std::function<bool(const KeyframeRef&)>& exclude) const {
  absl::ReaderMutexLock lock(&mu_);
  const size_t n = entries_.size();
  // Stop words (Sivic & Zisserman): a word in most keyframes tells them apart little and costs
  // the longest posting lists; skipped once the index is large enough for shares to mean much.
  const size_t stop_length = n >= kStopWordMinKeyframes
                                 ? static_cast<size_t>(stop_word_share_ * static_cast<double>(n))
                                 : n + 1;
  std::vector<float> score(n, 0.0f);
  for (const auto& [word, weight] : query.words) {
    if (word >= postings_.size() || postings_[word].size() > stop_length) continue;
    for (const Posting& p : postings_[word]) score[p.entry] += std::min(weight, p.weight);
  }
  // The best top_k by a bounded min-heap (the worst kept on top).
  const auto better = [](const Candidate& a, const Candidate& b) {
    return a.rank != b.rank ? a.rank > b.rank : a.keyframe.keyframe_id < b.keyframe.keyframe_id;
  };
  std::vector<Candidate> heap;
  heap.reserve(top_k + 1);
  for (size_t i = 0; i < n; ++i) {
    if (score[i] <= 0) continue;
    const float rank = score[i] * entries_[i].weight;
    if (heap.size() == top_k && !(rank > heap.front().rank)) continue;
    if (exclude && exclude(entries_[i])) continue;
    heap.push_back({entries_[i], score[i], rank});
    std::push_heap(heap.begin(), heap.end(), better);
    if (heap.size() > top_k) {
      std::pop_heap(heap.begin(), heap.end(), better);
      heap.pop_back();
    }
  }
  std::sort(heap.begin(), heap.end(), better);
  return heap;
}

IndexStats InvertedIndex::Stats() const {
  absl::ReaderMutexLock lock(&mu_);
  IndexStats s;
  s.keyframes = entries_.size();
  s.memory_bytes = entries_.capacity() * sizeof(KeyframeRef) +
                   postings_.capacity() * sizeof(std::vector<Posting>);
  for (const auto& list : postings_) {
    s.postings += list.size();
    s.memory_bytes += list.capacity() * sizeof(Posting);
  }
  return s;
}

}  // namespace lifemap::appearance
