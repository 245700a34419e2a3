#include "server/engine/appearance.h"

#include <algorithm>

#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "server/engine/clock.h"

namespace lifemap::server {

absl::Status AppearanceOptions::Validate() const {
  if (min_training_keyframes < 2) {
    return absl::InvalidArgumentError(absl::StrCat(
        "appearance.min_training_keyframes must be at least 2, got ", min_training_keyframes));
  }
  if (max_training_keyframes < min_training_keyframes) {
    return absl::InvalidArgumentError(
        "appearance.max_training_keyframes must be at least min_training_keyframes");
  }
  if (!(recognised_weight >= 0 && recognised_weight <= 10)) {
    return absl::InvalidArgumentError(
        absl::StrCat("appearance.recognised_weight must be in [0, 10], got ", recognised_weight));
  }
  if (!(exclude_recent_s >= 0 && exclude_recent_s <= 86400)) {
    return absl::InvalidArgumentError("appearance.exclude_recent_s must be in [0, 86400]");
  }
  if (!(exclude_recent_m >= 0 && exclude_recent_m <= 1e6)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "appearance.exclude_recent_m must be in [0, 1e6] metres, got ", exclude_recent_m));
  }
  if (max_frame_matches < 1 || max_frame_matches > 100) {
    return absl::InvalidArgumentError("appearance.max_frame_matches must be in [1, 100]");
  }
  if (frame_interval_s && !(*frame_interval_s >= 0 && *frame_interval_s <= kMaxFrameIntervalS)) {
    return absl::InvalidArgumentError(absl::StrCat("appearance.frame_interval_s must be in [0, ",
                                                   kMaxFrameIntervalS, "] or null"));
  }
  if (auto s = vocabulary.Validate(); !s.ok()) {
    return absl::InvalidArgumentError(absl::StrCat("appearance.vocabulary: ", s.message()));
  }
  if (auto s = recognizer.Validate(); !s.ok()) {
    return absl::InvalidArgumentError(absl::StrCat("appearance: ", s.message()));
  }
  if (auto s = features.Validate(); !s.ok()) {
    return absl::InvalidArgumentError(absl::StrCat("appearance.", s.message()));
  }
  return absl::OkStatus();
}

AppearanceIndex::AppearanceIndex(store::Store* store, AppearanceOptions options)
    : store_(store), options_(std::move(options)), thread_([this] { Run(); }) {}

AppearanceIndex::~AppearanceIndex() {
  {
    absl::MutexLock lock(&queue_mu_);
    stopping_ = true;
  }
  thread_.join();
}

AppearanceIndex::Snapshot AppearanceIndex::Current() const {
  absl::MutexLock lock(&mu_);
  return {vocabulary_, index_, stored_with_features_};
}

void AppearanceIndex::Push(Job job) {
  absl::MutexLock lock(&queue_mu_);
  queue_.push_back(std::move(job));
}

void AppearanceIndex::Run() {
  for (;;) {
    Job job;
    {
      absl::MutexLock lock(&queue_mu_);
      queue_mu_.Await(absl::Condition(
          +[](AppearanceIndex* self)
               ABSL_NO_THREAD_SAFETY_ANALYSIS { return self->stopping_ || !self->queue_.empty(); },
          this));
      if (queue_.empty()) return;  // stopping, nothing left
      job = std::move(queue_.front());
      queue_.pop_front();
    }
    absl::Status status;
    switch (job.kind) {
      case Job::Kind::kAdd: {
        {
          absl::MutexLock lock(&mu_);
          ++stored_with_features_;
        }
        const auto [vocabulary, index, stored] = Current();
        auto map = MapOfVisit(job.keyframe.visit_id);
        if (!map.ok()) {
          status = map.status();  // the visit is gone (its map deleted meanwhile)
        } else if (vocabulary) {
          job.keyframe.map_id = *map;
          auto bow = vocabulary->Transform(job.descriptors);
          if (bow.ok()) {
            job.keyframe.weight = RecognisedWeight(job.keyframe.keyframe_id);
            index->Add(job.keyframe, *bow);
          }
          status = bow.status();
          // The keyframes it recognised weigh more from now on.
          if (options_.recognised_weight > 0) {
            for (const int64_t seen : job.sighted) {
              recognised_by_[seen].insert(job.keyframe.visit_id);
              index->SetWeight(seen, RecognisedWeight(seen));
            }
          }
        } else if (stored >= options_.min_training_keyframes) {
          status = TrainLocked(/*asked=*/false);
        }
        break;
      }
      case Job::Kind::kAddMap: {
        status = IndexStored(job.map_id);
        const auto [vocabulary, index, stored] = Current();
        if (status.ok() && !vocabulary && stored >= options_.min_training_keyframes) {
          status = TrainLocked(/*asked=*/false);
        }
        break;
      }
      case Job::Kind::kRemove: {
        absl::MutexLock lock(&mu_);
        if (index_) stored_with_features_ -= static_cast<int64_t>(index_->RemoveIf(job.drop));
        break;
      }
      case Job::Kind::kRebuild: {
        bool has_vocabulary = false;
        {
          absl::MutexLock lock(&mu_);
          has_vocabulary = vocabulary_ != nullptr;
        }
        status =
            job.retrain || !has_vocabulary ? TrainLocked(/*asked=*/job.retrain) : IndexStored(0);
        break;
      }
    }
    if (!status.ok()) spdlog::warn("appearance index: {}", status.ToString());
    if (job.done) {
      if (status.ok()) {
        job.done->set_value(Stats());
      } else {
        job.done->set_value(status);
      }
    }
  }
}

absl::Status AppearanceIndex::Load() {
  if (!options_.enabled) return absl::OkStatus();
  auto stored = store_->LatestVocabulary();
  if (!stored.ok()) return stored.status();
  if (*stored) {
    auto vocabulary = appearance::Vocabulary::Deserialize((*stored)->data);
    if (!vocabulary.ok()) {
      return absl::DataLossError(absl::StrCat("stored appearance vocabulary ", (*stored)->id, ": ",
                                              vocabulary.status().message(),
                                              "; run `lifemap places index rebuild --retrain`"));
    }
    absl::MutexLock lock(&mu_);
    vocabulary_ = std::make_shared<appearance::Vocabulary>(*std::move(vocabulary));
    vocabulary_id_ = (*stored)->id;
  }
  auto done = std::make_shared<std::promise<absl::StatusOr<AppearanceIndexStats>>>();
  auto future = done->get_future();
  Job job;
  job.kind = Job::Kind::kRebuild;
  job.done = done;
  Push(std::move(job));
  auto stats = future.get();
  if (!stats.ok()) return stats.status();
  spdlog::info(
      "appearance index: {} keyframes indexed{} ({:.1f} MB)", stats->keyframes,
      stats->has_vocabulary
          ? absl::StrCat(" with vocabulary ", stats->vocabulary_id, " (", stats->words, " words)")
          : absl::StrCat("; no vocabulary yet (trained once ", options_.min_training_keyframes,
                         " keyframes are stored, ", stats->stored_with_features, " now)"),
      static_cast<double>(stats->memory_bytes) / 1e6);
  return absl::OkStatus();
}

absl::StatusOr<int64_t> AppearanceIndex::MapOfVisit(int64_t visit_id) {
  if (auto it = visit_maps_.find(visit_id); it != visit_maps_.end()) return it->second;
  auto visit = store_->GetVisit(visit_id);
  if (!visit.ok()) return visit.status();
  visit_maps_[visit_id] = visit->map_id;
  return visit->map_id;
}

void AppearanceIndex::OnCommitted(const store::KeyframeRecord& k) {
  if (!options_.enabled || !k.features || k.features->keypoints.size() == 0) return;
  Job job;
  job.kind = Job::Kind::kAdd;
  job.keyframe = {0, k.visit_id, k.id, k.timestamp_s};
  job.descriptors = k.features->keypoints.descriptors;
  job.sighted = k.sighted_keyframes;
  Push(std::move(job));
}

void AppearanceIndex::RemoveMap(int64_t map_id) {
  if (!options_.enabled) return;
  Job job;
  job.kind = Job::Kind::kRemove;
  job.drop = [map_id](const appearance::KeyframeRef& k) { return k.map_id == map_id; };
  Push(std::move(job));
}

void AppearanceIndex::AddMap(int64_t map_id) {
  if (!options_.enabled) return;
  Job job;
  job.kind = Job::Kind::kAddMap;
  job.map_id = map_id;
  Push(std::move(job));
}

void AppearanceIndex::RemoveKeyframes(const std::vector<int64_t>& keyframe_ids) {
  if (!options_.enabled || keyframe_ids.empty()) return;
  auto ids =
      std::make_shared<const std::unordered_set<int64_t>>(keyframe_ids.begin(), keyframe_ids.end());
  Job job;
  job.kind = Job::Kind::kRemove;
  job.drop = [ids](const appearance::KeyframeRef& k) { return ids->count(k.keyframe_id) != 0; };
  Push(std::move(job));
}

absl::StatusOr<AppearanceIndexStats> AppearanceIndex::Rebuild(bool retrain) {
  if (!options_.enabled) {
    return absl::FailedPreconditionError("appearance is disabled in this server's config");
  }
  Job job;
  job.kind = Job::Kind::kRebuild;
  job.retrain = retrain;
  job.done = std::make_shared<std::promise<absl::StatusOr<AppearanceIndexStats>>>();
  auto future = job.done->get_future();
  Push(std::move(job));
  return future.get();
}

absl::Status AppearanceIndex::TrainLocked(bool asked) {
  // Count first (without reading descriptors), then keep every n-th keyframe's descriptors so
  // that at most max_training_keyframes are held.
  auto count = store_->CountKeyframesWithFeatures();
  if (!count.ok()) return count.status();
  const int64_t stored = *count;
  if (asked && stored == 0) {
    return absl::FailedPreconditionError(
        "no stored keyframe has features to train a vocabulary on: stream some frames into a "
        "map first (keyframes stored before lifemap 0.1's appearance index have none)");
  }
  if (!asked && stored < options_.min_training_keyframes) {
    absl::MutexLock lock(&mu_);
    stored_with_features_ = stored;
    return absl::OkStatus();  // not yet: Recognize says how many it waits for
  }
  const int64_t step =
      (stored + options_.max_training_keyframes - 1) / options_.max_training_keyframes;
  std::vector<cv::Mat> training;
  int64_t i = 0;
  if (auto s = store_->ForEachKeyframeDescriptors(0,
                                                  [&](const store::KeyframeDescriptors& k) {
                                                    if (i++ % step == 0 && !k.descriptors.empty()) {
                                                      training.push_back(k.descriptors);
                                                    }
                                                    return absl::OkStatus();
                                                  });
      !s.ok()) {
    return s;
  }
  auto vocabulary = appearance::Vocabulary::Train(training, options_.vocabulary);
  if (!vocabulary.ok()) return vocabulary.status();
  store::VocabularyRecord record;
  record.created_time_s = NowSeconds();
  record.source = absl::StrCat("stored keyframes (", training.size(), " of ", stored, ")");
  record.training_keyframes = static_cast<int64_t>(training.size());
  record.words = static_cast<int64_t>(vocabulary->words());
  record.data = vocabulary->Serialize();
  auto id = store_->PutVocabulary(record);
  if (!id.ok()) return id.status();
  spdlog::info("appearance vocabulary {} trained on {} keyframes: {} words", *id, training.size(),
               vocabulary->words());
  {
    absl::MutexLock lock(&mu_);
    vocabulary_ = std::make_shared<appearance::Vocabulary>(*std::move(vocabulary));
    vocabulary_id_ = *id;
  }
  if (auto s = IndexStored(0); !s.ok()) return s;
  absl::MutexLock lock(&on_trained_mu_);
  if (on_trained_) on_trained_();
  return absl::OkStatus();
}

void AppearanceIndex::SetOnTrained(std::function<void()> on_trained) {
  absl::MutexLock lock(&on_trained_mu_);
  on_trained_ = std::move(on_trained);
}

float AppearanceIndex::RecognisedWeight(int64_t keyframe_id) const {
  if (options_.recognised_weight <= 0) return 1.0f;
  const auto it = recognised_by_.find(keyframe_id);
  const size_t n = it == recognised_by_.end() ? 0 : std::min<size_t>(it->second.size(), 3);
  return static_cast<float>(1.0 + options_.recognised_weight * static_cast<double>(n));
}

absl::Status AppearanceIndex::IndexStored(int64_t map_id) {
  std::shared_ptr<const appearance::Vocabulary> vocabulary;
  {
    absl::MutexLock lock(&mu_);
    vocabulary = vocabulary_;
  }
  // A whole rebuild makes a fresh index and swaps it in; a map's keyframes go into the live one.
  std::shared_ptr<appearance::InvertedIndex> index;
  if (vocabulary) {
    if (map_id == 0) {
      index = std::make_shared<appearance::InvertedIndex>(vocabulary->words());
    } else {
      absl::MutexLock lock(&mu_);
      index = index_;
    }
  }
  if (options_.recognised_weight > 0) {
    auto sightings = store_->ListSightings(map_id);
    if (!sightings.ok()) return sightings.status();
    if (map_id == 0) recognised_by_.clear();
    for (const auto& [keyframe, visits] : *sightings) {
      recognised_by_[keyframe].insert(visits.begin(), visits.end());
    }
  }
  int64_t counted = 0;
  auto s = store_->ForEachKeyframeDescriptors(map_id, [&](const store::KeyframeDescriptors& k) {
    ++counted;
    if (!index || k.descriptors.empty()) return absl::OkStatus();
    auto bow = vocabulary->Transform(k.descriptors);
    if (!bow.ok()) return bow.status();
    index->Add(
        {k.map_id, k.visit_id, k.keyframe_id, k.timestamp_s, RecognisedWeight(k.keyframe_id)},
        *bow);
    return absl::OkStatus();
  });
  if (!s.ok()) return s;
  absl::MutexLock lock(&mu_);
  if (map_id == 0) {
    stored_with_features_ = counted;
    if (index) index_ = std::move(index);
  } else {
    stored_with_features_ += counted;
  }
  return absl::OkStatus();
}

absl::StatusOr<appearance::Recognition> AppearanceIndex::Recognize(
    const features::KeypointSet& query, const CameraIntrinsics& intrinsics,
    const appearance::KeyframeFilter& exclude) const {
  if (!options_.enabled) {
    return absl::FailedPreconditionError(
        "appearance is disabled in this server's config (appearance.enabled)");
  }
  const auto [vocabulary, index, stored] = Current();
  if (!vocabulary || !index) {
    return absl::FailedPreconditionError(
        absl::StrCat("no appearance vocabulary yet: one is trained once ",
                     options_.min_training_keyframes, " keyframes with features are stored (",
                     stored, " now), or run `lifemap places index rebuild --retrain`"));
  }
  const appearance::FeatureLoader load = [this](const appearance::KeyframeRef& k) {
    auto f = store_->GetKeyframeFeatures(k.keyframe_id);
    if (!f.ok()) return absl::StatusOr<features::KeypointSet>(f.status());
    return absl::StatusOr<features::KeypointSet>(std::move(f->keypoints));
  };
  return appearance::Recognize(query, intrinsics, *vocabulary, *index, load, exclude,
                               options_.recognizer);
}

AppearanceIndexStats AppearanceIndex::Stats() const {
  absl::MutexLock lock(&mu_);
  AppearanceIndexStats s;
  s.has_vocabulary = vocabulary_ != nullptr;
  s.vocabulary_id = vocabulary_id_;
  s.words = vocabulary_ ? vocabulary_->words() : 0;
  if (index_) {
    const auto is = index_->Stats();
    s.keyframes = is.keyframes;
    s.memory_bytes = is.memory_bytes;
  }
  s.stored_with_features = stored_with_features_;
  return s;
}

const std::string& MapNames::Of(int64_t map_id) {
  auto it = names_.find(map_id);
  if (it == names_.end()) {
    auto m = store_->GetMapById(map_id);
    it = names_.emplace(map_id, m.ok() ? m->name : std::string()).first;
  }
  return it->second;
}

PlaceMatch AppearancePlaceMatch(const appearance::AppearanceMatch& m, MapNames* names) {
  PlaceMatch out;
  out.method = PlaceMatch::Method::kAppearance;
  out.map_id = m.keyframe.map_id;
  out.map = names->Of(m.keyframe.map_id);
  out.visit_id = m.keyframe.visit_id;
  out.keyframe_id = m.keyframe.keyframe_id;
  out.score = m.verification.score;
  out.T_match_query = m.verification.T_match_query;
  return out;
}

}  // namespace lifemap::server
