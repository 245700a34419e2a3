// Appearance place recognition served (paper 000): an index over the words of every stored
// keyframe of every map, built with a vocabulary trained here on stored keyframes and kept in
// the store, and queried by keyframes (and frames that ask) with PnP verification.
//
// Lifecycle. At start the newest stored vocabulary is loaded and every stored keyframe's
// descriptors are indexed. Without one, the index waits: once `min_training_keyframes`
// keyframes with features are stored, a vocabulary is trained on them (at most
// `max_training_keyframes`, evenly spread), stored, and everything is indexed. Each committed
// keyframe is indexed after its commit, on this class's own thread, off the reply path.
// `lifemap places index rebuild [--retrain]` (AdminService.RebuildAppearanceIndex) re-reads the
// store, optionally training a new vocabulary first.
#pragma once

#include <cstdint>
#include <deque>
#include <functional>
#include <future>
#include <map>
#include <memory>
#include <optional>
#include <set>
#include <string>
#include <thread>
#include <unordered_map>
#include <unordered_set>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "core/appearance/recognizer.h"
#include "server/engine/architecture.h"
#include "server/engine/options.h"
#include "server/store/store.h"

namespace lifemap::server {

struct AppearanceIndexStats {
  bool has_vocabulary = false;
  int64_t vocabulary_id = 0;
  size_t words = 0;
  size_t keyframes = 0;
  size_t memory_bytes = 0;
  int64_t stored_with_features = 0;  // known at load and counted since
};

// Thread-safe.
class AppearanceIndex {
 public:
  AppearanceIndex(store::Store* store, AppearanceOptions options);
  // Finishes queued work, then stops.
  ~AppearanceIndex();
  AppearanceIndex(const AppearanceIndex&) = delete;
  AppearanceIndex& operator=(const AppearanceIndex&) = delete;

  // Loads the stored vocabulary (or trains one when enough keyframes are stored) and indexes
  // every stored keyframe; errors are those of the store or a damaged vocabulary.
  absl::Status Load();

  // After a keyframe's commit (with its id and features): queued for indexing.
  void OnCommitted(const store::KeyframeRecord& keyframe);
  // Drops a deleted map's keyframes.
  void RemoveMap(int64_t map_id);
  // Queues indexing a map's stored keyframes (an imported map); trains a vocabulary first when
  // there is none and enough keyframes are stored now.
  void AddMap(int64_t map_id);
  // Drops keyframes deleted by retention (server/engine/retention.h).
  void RemoveKeyframes(const std::vector<int64_t>& keyframe_ids);

  // Appearance matches of a view (its features pruned already), verified, best first.
  // FailedPrecondition saying why there can be none: appearance disabled, no vocabulary yet (and
  // how many keyframes it waits for), nothing indexed, no features in the view.
  absl::StatusOr<appearance::Recognition> Recognize(
      const features::KeypointSet& query, const CameraIntrinsics& intrinsics,
      const appearance::KeyframeFilter& exclude) const;

  // Re-reads the store; with `retrain` (or without a vocabulary) trains and stores a new
  // vocabulary first. Blocks until done; returns the stats after.
  absl::StatusOr<AppearanceIndexStats> Rebuild(bool retrain);

  AppearanceIndexStats Stats() const;
  // Called on the index's thread each time a new vocabulary has been trained and the stored
  // keyframes indexed with it (the engine retries unanchored visits then: anchor_retry.h).
  // nullptr to stop; returns once a call in progress has finished.
  void SetOnTrained(std::function<void()> on_trained);
  const AppearanceOptions& options() const { return options_; }

 private:
  struct Job {
    enum class Kind { kAdd, kAddMap, kRemove, kRebuild } kind = Kind::kAdd;
    int64_t map_id = 0;                                        // kAddMap
    std::function<bool(const appearance::KeyframeRef&)> drop;  // kRemove: which entries
    std::vector<int64_t> sighted;  // kAdd: keyframes of other visits it recognised
    appearance::KeyframeRef keyframe;
    cv::Mat descriptors;
    bool retrain = false;
    std::shared_ptr<std::promise<absl::StatusOr<AppearanceIndexStats>>> done;
  };
  // What queries and indexing use, taken together under mu_.
  struct Snapshot {
    std::shared_ptr<const appearance::Vocabulary> vocabulary;
    std::shared_ptr<appearance::InvertedIndex> index;
    int64_t stored_with_features = 0;
  };
  Snapshot Current() const;
  void Run();
  void Push(Job job);
  // Worker thread only. Trains a vocabulary on the stored keyframes and re-indexes them; unless
  // `asked` (an operator's rebuild), only once min_training_keyframes are stored.
  absl::Status TrainLocked(bool asked);
  absl::Status IndexStored(int64_t map_id);
  absl::StatusOr<int64_t> MapOfVisit(int64_t visit_id);
  // Worker thread only: the ranking weight of a keyframe (AppearanceOptions::recognised_weight).
  float RecognisedWeight(int64_t keyframe_id) const;

  store::Store* const store_;
  const AppearanceOptions options_;

  mutable absl::Mutex mu_;
  std::shared_ptr<const appearance::Vocabulary> vocabulary_ ABSL_GUARDED_BY(mu_);
  std::shared_ptr<appearance::InvertedIndex> index_ ABSL_GUARDED_BY(mu_);
  int64_t vocabulary_id_ ABSL_GUARDED_BY(mu_) = 0;
  int64_t stored_with_features_ ABSL_GUARDED_BY(mu_) = 0;

  absl::Mutex queue_mu_;
  std::deque<Job> queue_ ABSL_GUARDED_BY(queue_mu_);
  absl::Mutex on_trained_mu_;
  std::function<void()> on_trained_ ABSL_GUARDED_BY(on_trained_mu_);
  bool stopping_ ABSL_GUARDED_BY(queue_mu_) = false;
  std::unordered_map<int64_t, int64_t> visit_maps_;  // worker thread only
  // Worker thread only (with recognised_weight > 0): the visits that recognised each keyframe.
  std::unordered_map<int64_t, std::set<int64_t>> recognised_by_;
  std::thread thread_;
};

// Names of maps by id, each read from the store once (matches carry only ids); "" for a map
// that is gone.
class MapNames {
 public:
  explicit MapNames(store::Store* store) : store_(store) {}
  const std::string& Of(int64_t map_id);

 private:
  store::Store* store_;
  std::map<int64_t, std::string> names_;
};

// A verified appearance match (a keyframe) as a PlaceMatch, its map named by `names`.
PlaceMatch AppearancePlaceMatch(const appearance::AppearanceMatch& m, MapNames* names);

}  // namespace lifemap::server
