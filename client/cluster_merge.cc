#include "client/cluster_merge.h"

#include <algorithm>
#include <map>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"

namespace lifemap::client {
namespace {

// FUSED first, then ARCHITECTURE, then APPEARANCE, as the server orders its rankings.
int MethodRank(v1::MatchMethod m) {
  switch (m) {
    case v1::MATCH_METHOD_FUSED:
      return 0;
    case v1::MATCH_METHOD_ARCHITECTURE:
      return 1;
    case v1::MATCH_METHOD_APPEARANCE:
      return 2;
    default:
      return 3;
  }
}

// Best first; ties keep the shards' order. At most `max_results` (0: all).
void RankByScore(google::protobuf::RepeatedPtrField<v1::PlaceMatch>* matches, size_t max_results) {
  std::stable_sort(
      matches->begin(), matches->end(),
      [](const v1::PlaceMatch& a, const v1::PlaceMatch& b) { return a.score() > b.score(); });
  if (max_results > 0) {
    while (static_cast<size_t>(matches->size()) > max_results) matches->RemoveLast();
  }
}

}  // namespace

v1::Stats MergeStats(const std::vector<v1::Stats>& parts) {
  v1::Stats out;
  if (parts.size() == 1) return parts.front();
  bool first = true;
  for (const v1::Stats& s : parts) {
    out.set_maps(out.maps() + s.maps());
    out.set_visits(out.visits() + s.visits());
    out.set_keyframes(out.keyframes() + s.keyframes());
    out.set_db_bytes(out.db_bytes() + s.db_bytes());
    out.set_wal_bytes(out.wal_bytes() + s.wal_bytes());
    out.set_active_streams(out.active_streams() + s.active_streams());
    out.set_frames_processed(out.frames_processed() + s.frames_processed());
    out.set_frames_rejected(out.frames_rejected() + s.frames_rejected());
    out.set_keyframes_committed(out.keyframes_committed() + s.keyframes_committed());
    out.set_uptime_s(first ? s.uptime_s() : std::min(out.uptime_s(), s.uptime_s()));
    out.set_process_cpu_s(out.process_cpu_s() + s.process_cpu_s());
    out.set_resident_bytes(out.resident_bytes() + s.resident_bytes());
    out.set_limited_to_maps(out.limited_to_maps() || s.limited_to_maps());
    const v1::AppearanceIndexInfo& a = s.appearance();
    v1::AppearanceIndexInfo* m = out.mutable_appearance();
    m->set_enabled(first ? a.enabled() : m->enabled() && a.enabled());
    m->set_has_vocabulary(first ? a.has_vocabulary() : m->has_vocabulary() && a.has_vocabulary());
    m->set_words(std::max(m->words(), a.words()));
    m->set_keyframes(m->keyframes() + a.keyframes());
    m->set_memory_bytes(m->memory_bytes() + a.memory_bytes());
    m->set_stored_keyframes(m->stored_keyframes() + a.stored_keyframes());
    m->set_min_training_keyframes(
        std::max(m->min_training_keyframes(), a.min_training_keyframes()));
    first = false;
  }
  return out;
}

v1::QueryPlaceResponse MergePlaceAnswers(
    const std::vector<std::pair<std::string, v1::QueryPlaceResponse>>& parts, size_t max_results) {
  v1::QueryPlaceResponse out;
  std::map<uint32_t, v1::FrameAppearance> frames;  // by query frame index
  struct Method {
    bool computed = false;
    std::vector<std::string> reasons;
  };
  std::vector<std::pair<int, Method>> methods;  // by v1::MatchMethod, in the shards' order
  for (const auto& [shard, part] : parts) {
    for (const v1::PlaceMatch& m : part.matches()) *out.add_matches() = m;
    for (const v1::FrameAppearance& f : part.frames()) {
      v1::FrameAppearance& merged = frames[f.index()];
      merged.set_index(f.index());
      for (const v1::PlaceMatch& m : f.matches()) *merged.add_matches() = m;
      if (merged.reason().empty()) merged.set_reason(f.reason());
    }
    if (out.descriptor_text().empty()) out.set_descriptor_text(part.descriptor_text());
    for (const v1::MethodStatus& s : part.method_status()) {
      auto it = std::find_if(methods.begin(), methods.end(),
                             [&s](const auto& m) { return m.first == s.method(); });
      if (it == methods.end()) it = methods.insert(methods.end(), {s.method(), Method()});
      Method& m = it->second;
      m.computed = m.computed || s.computed();
      if (!s.computed()) m.reasons.push_back(absl::StrCat(shard, ": ", s.reason()));
    }
    for (const std::string& u : part.unreachable_shards()) out.add_unreachable_shards(u);
  }
  // Grouped by method in the server's order, each group best first.
  std::stable_sort(out.mutable_matches()->begin(), out.mutable_matches()->end(),
                   [](const v1::PlaceMatch& a, const v1::PlaceMatch& b) {
                     const int ra = MethodRank(a.method()), rb = MethodRank(b.method());
                     if (ra != rb) return ra < rb;
                     return a.score() > b.score();
                   });
  google::protobuf::RepeatedPtrField<v1::PlaceMatch> kept;
  std::map<int, size_t> per_method;
  for (v1::PlaceMatch& m : *out.mutable_matches()) {
    if (max_results == 0 || per_method[m.method()]++ < max_results) *kept.Add() = std::move(m);
  }
  out.mutable_matches()->Swap(&kept);
  for (auto& [index, f] : frames) {
    RankByScore(f.mutable_matches(), max_results);
    if (!f.matches().empty()) f.clear_reason();
    *out.add_frames() = std::move(f);
  }
  for (const auto& [method, m] : methods) {
    v1::MethodStatus* s = out.add_method_status();
    s->set_method(static_cast<v1::MatchMethod>(method));
    s->set_computed(m.computed);
    if (!m.computed) s->set_reason(absl::StrJoin(m.reasons, "; "));
  }
  return out;
}

}  // namespace lifemap::client
