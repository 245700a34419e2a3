#include "server/engine/place_query.h"

#include <algorithm>
#include <map>

#include "absl/strings/str_cat.h"
#include "core/common/utf8.h"
#include "core/pipeline/frame_pipeline.h"
#include "core/pipeline/keyframe.h"
#include "core/place/floor_plan.h"
#include "core/place/serialize.h"
#include "server/engine/appearance.h"
#include "server/engine/visit_registry.h"

namespace lifemap::server {
namespace {

bool Better(const PlaceMatch& a, const PlaceMatch& b) {
  return a.score != b.score ? a.score > b.score : a.visit_id < b.visit_id;
}

// Stored visits ranked by their best keyframe match, at most `max`.
std::vector<PlaceMatch> BestPerVisit(const std::vector<PlaceMatch>& keyframe_matches, size_t max) {
  std::map<int64_t, PlaceMatch> best;
  for (const auto& m : keyframe_matches) {
    auto [it, inserted] = best.emplace(m.visit_id, m);
    if (!inserted && m.score > it->second.score) it->second = m;
  }
  std::vector<PlaceMatch> out;
  for (auto& [visit, m] : best) out.push_back(std::move(m));
  std::sort(out.begin(), out.end(), Better);
  if (out.size() > max) out.resize(max);
  return out;
}

// One ranking of visits from both methods: the mean of the two scores, a method that did not
// rank the visit counting 0.
std::vector<PlaceMatch> Fuse(const std::vector<PlaceMatch>& architecture,
                             const std::vector<PlaceMatch>& appearance, size_t max) {
  std::map<int64_t, PlaceMatch> fused;
  for (const auto* list : {&architecture, &appearance}) {
    for (const auto& m : *list) {
      auto [it, inserted] = fused.emplace(m.visit_id, m);
      if (inserted) {
        it->second.score = 0;
        it->second.keyframe_id = 0;
        it->second.T_match_query.reset();
      }
      it->second.score += 0.5 * m.score;
      it->second.method = PlaceMatch::Method::kFused;
    }
  }
  std::vector<PlaceMatch> out;
  for (auto& [visit, m] : fused) out.push_back(std::move(m));
  std::sort(out.begin(), out.end(), Better);
  if (out.size() > max) out.resize(max);
  return out;
}

// A long query stopped between frames because its deadline passed or its client left.
absl::Status StoppedAfter(size_t done, size_t frames) {
  return absl::CancelledError(absl::StrCat("stopped after ", done, " of ", frames,
                                           " frames: the call's deadline passed or its client "
                                           "left"));
}

}  // namespace

PlaceQueries::PlaceQueries(store::Store* store, PlaceIndex* places, VisitRegistry* visits,
                           AppearanceIndex* appearance, const pipeline::FramePipeline* pipeline,
                           const EngineOptions& options)
    : store_(store),
      places_(places),
      visits_(visits),
      appearance_(appearance),
      pipeline_(pipeline),
      options_(options) {}

absl::StatusOr<PlaceQueryResult> PlaceQueries::OfFrames(const std::vector<EncodedRgbdFrame>& frames,
                                                        const PlaceQuery& query) const {
  PlaceQueryResult result;
  if (query.architecture) {
    if (auto s = ArchitectureOfFrames(frames, query, &result.architecture); !s.ok()) return s;
  }
  if (query.appearance) {
    if (auto s = AppearanceOfFrames(frames, query, &result.appearance, &result.frames); !s.ok()) {
      return s;
    }
  }
  Finish(query, &result);
  return result;
}

PlaceQueryResult PlaceQueries::OfVisit(const store::VisitRecord& visit,
                                       const PlaceQuery& query) const {
  PlaceQueryResult result;
  if (query.architecture) ArchitectureOfVisit(visit, query.max_results, &result.architecture);
  if (query.appearance) AppearanceOfVisit(visit, query.max_results, &result.appearance);
  Finish(query, &result);
  return result;
}

void PlaceQueries::Finish(const PlaceQuery& query, PlaceQueryResult* result) const {
  if (query.may_use_map) {
    const auto refused = [&](const PlaceMatch& m) { return !query.may_use_map(m.map_id); };
    for (auto* outcome : {&result->architecture, &result->appearance}) {
      auto& m = outcome->matches;
      m.erase(std::remove_if(m.begin(), m.end(), refused), m.end());
    }
    for (auto& frame : result->frames) {
      auto& m = frame.matches;
      m.erase(std::remove_if(m.begin(), m.end(), refused), m.end());
    }
  }
  if (query.architecture && query.appearance && result->architecture.status.ok() &&
      result->appearance.status.ok()) {
    result->fused =
        Fuse(result->architecture.matches, result->appearance.matches, query.max_results);
  }
}

absl::Status PlaceQueries::ArchitectureOfFrames(const std::vector<EncodedRgbdFrame>& frames,
                                                const PlaceQuery& query, MethodOutcome* out) const {
  // Nothing is stored: the frames fold into a plan of their own, ranked against stored visits.
  place::FloorPlanBuilder builder(ServedPlanOptions());
  for (size_t i = 0; i < frames.size(); ++i) {
    // Each frame costs its depth decoding and planes (a 2,000-frame query, minutes of CPU).
    if (query.stopped && query.stopped()) return StoppedAfter(i, frames.size());
    if (!frames[i].T_world_camera) {
      out->status = absl::InvalidArgumentError(absl::StrCat(
          "frames[", i, "]: pose is missing; architecture needs each key frame's T_world_camera"));
      return absl::OkStatus();
    }
    auto frame =
        DecodeRgbdFrame(frames[i], /*decode_color=*/false, pipeline_->options().frame_limits);
    auto s = frame.ok() ? builder.AddDepthKeyframe(frame->depth_m, frame->intrinsics,
                                                   *frames[i].T_world_camera)
                        : frame.status();
    if (!s.ok()) return absl::InvalidArgumentError(absl::StrCat("frames[", i, "]: ", s.message()));
  }
  if (query.stopped && query.stopped()) return StoppedAfter(frames.size(), frames.size());
  auto plan = builder.Build();
  if (!plan.ok()) {
    out->status = absl::FailedPreconditionError(
        absl::StrCat("the frames give no floor plan: ", plan.status().message()));
    return absl::OkStatus();
  }
  const place::PlaceDescriptor descriptor = place::Describe(*plan);
  auto ranked = places_->Rank(descriptor, /*exclude_visit=*/0, query.max_results);
  if (!ranked.ok()) return ranked.status();
  out->status = absl::OkStatus();
  out->matches = *std::move(ranked);
  out->descriptor_text = place::DescriptorText(descriptor);
  return absl::OkStatus();
}

void PlaceQueries::ArchitectureOfVisit(const store::VisitRecord& visit, size_t max_results,
                                       MethodOutcome* out) const {
  auto record = store_->GetVisitPlace(visit.id);
  if (absl::IsNotFound(record.status())) {
    // Say why, from the live visit when it is open.
    std::string why = "its floor plan has not closed yet (walls all around, floor seen)";
    if (!visit.ended) {
      auto state = visits_->Get(visit.id);
      if (state.ok()) {
        const absl::Status status = (*state)->architecture.Ranking().status;
        if (!status.ok()) why = std::string(status.message());
      }
    }
    out->status = absl::FailedPreconditionError(
        absl::StrCat("visit ", visit.id, " has no floor plan: ", why));
    return;
  }
  if (!record.ok()) {
    out->status = record.status();
    return;
  }
  auto descriptor = place::DescriptorFromJson(record->descriptor_json);
  if (!descriptor.ok()) {
    out->status = descriptor.status();
    return;
  }
  auto ranked = places_->Rank(*descriptor, visit.id, max_results);
  if (!ranked.ok()) {
    out->status = ranked.status();
    return;
  }
  out->status = absl::OkStatus();
  out->matches = *std::move(ranked);
  out->descriptor_text = place::DescriptorText(*descriptor);
}

absl::Status PlaceQueries::AppearanceOfFrames(
    const std::vector<EncodedRgbdFrame>& frames, const PlaceQuery& query, MethodOutcome* out,
    std::vector<FrameAppearanceOutcome>* per_frame) const {
  MapNames names(store_);
  std::vector<PlaceMatch> all;
  int answered = 0;
  absl::Status last_failure;
  for (size_t i = 0; i < frames.size(); ++i) {
    // Each frame costs its entropy mask, features and verification: a call whose deadline
    // passed (or whose client left) stops here instead of finishing for nobody.
    if (query.stopped && query.stopped()) return StoppedAfter(i, frames.size());
    FrameAppearanceOutcome& entry = per_frame->emplace_back();
    entry.index = i;
    if (frames[i].color.data.empty()) {
      entry.reason = "no colour image: appearance needs colour and depth";
      last_failure = absl::InvalidArgumentError(entry.reason);
      continue;
    }
    // The frame's own entropy mask prunes its features, as for a streamed keyframe.
    auto analysis = pipeline_->Process(frames[i], {});
    if (!analysis.ok()) {
      return absl::InvalidArgumentError(
          absl::StrCat("frames[", i, "]: ", analysis.status().message()));
    }
    auto features = pipeline::ExtractKeyframeFeatures(*analysis, options_.appearance.features);
    absl::StatusOr<appearance::Recognition> recognition =
        features.ok() ? appearance_->Recognize(features->keypoints, analysis->frame.intrinsics, {})
                      : absl::StatusOr<appearance::Recognition>(features.status());
    if (!recognition.ok()) {
      entry.reason = ToValidUtf8(recognition.status().message());
      last_failure = recognition.status();
      continue;
    }
    ++answered;
    for (const auto& m : recognition->matches) {
      const PlaceMatch match = AppearancePlaceMatch(m, &names);
      if (entry.matches.size() < query.max_results) entry.matches.push_back(match);
      all.push_back(match);
    }
  }
  if (answered == 0) {
    out->status = absl::FailedPreconditionError(
        absl::StrCat("no frame could be matched: ", last_failure.message()));
    return absl::OkStatus();
  }
  out->status = absl::OkStatus();
  out->matches = BestPerVisit(all, query.max_results);
  return absl::OkStatus();
}

void PlaceQueries::AppearanceOfVisit(const store::VisitRecord& visit, size_t max_results,
                                     MethodOutcome* out) const {
  auto keyframes = store_->ListKeyframes(visit.map_id, visit.id);
  if (!keyframes.ok()) {
    out->status = keyframes.status();
    return;
  }
  MapNames names(store_);
  std::vector<PlaceMatch> all;
  int answered = 0;
  absl::Status last_failure = absl::FailedPreconditionError(
      absl::StrCat("visit ", visit.id, " has no keyframes with features"));
  const int64_t own = visit.id;
  for (const auto& k : *keyframes) {
    auto features = store_->GetKeyframeFeatures(k.id);
    if (!features.ok()) continue;  // stored without entropy masks: nothing to match
    auto recognition = appearance_->Recognize(
        features->keypoints, k.intrinsics,
        [own](const appearance::KeyframeRef& r) { return r.visit_id == own; });
    if (!recognition.ok()) {
      last_failure = recognition.status();
      continue;
    }
    ++answered;
    for (const auto& m : recognition->matches) all.push_back(AppearancePlaceMatch(m, &names));
  }
  if (answered == 0) {
    out->status = last_failure;
    return;
  }
  out->status = absl::OkStatus();
  out->matches = BestPerVisit(all, max_results);
}

}  // namespace lifemap::server
