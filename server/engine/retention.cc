#include "server/engine/retention.h"

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <set>
#include <unordered_map>

#include "absl/strings/str_cat.h"
#include "absl/synchronization/mutex.h"
#include "server/engine/appearance.h"
#include "server/engine/visit_frame.h"

namespace lifemap::server {
namespace {

constexpr double kRadToDeg = 180.0 / M_PI;

// Keyframes kept so far, bucketed by position in cubes of `cell` metres (at least the largest
// cover distance, so a cover lies in the 27 cubes around a keyframe's own).
class KeptGrid {
 public:
  explicit KeptGrid(double cell) : cell_(cell) {}
  using Cell = std::array<int64_t, 3>;
  Cell CellOf(const Eigen::Vector3d& p) const {
    return {static_cast<int64_t>(std::floor(p.x() / cell_)),
            static_cast<int64_t>(std::floor(p.y() / cell_)),
            static_cast<int64_t>(std::floor(p.z() / cell_))};
  }
  void Add(size_t index, const Eigen::Vector3d& p) { cells_[Key(CellOf(p))].push_back(index); }
  void Remove(size_t index, const Eigen::Vector3d& p) {
    auto& v = cells_[Key(CellOf(p))];
    v.erase(std::remove(v.begin(), v.end(), index), v.end());
  }
  template <typename Fn>
  void ForEachNear(const Eigen::Vector3d& p, Fn&& fn) const {
    const Cell c = CellOf(p);
    for (int64_t dx = -1; dx <= 1; ++dx)
      for (int64_t dy = -1; dy <= 1; ++dy)
        for (int64_t dz = -1; dz <= 1; ++dz) {
          auto it = cells_.find(Key({c[0] + dx, c[1] + dy, c[2] + dz}));
          if (it == cells_.end()) continue;
          for (const size_t i : it->second) fn(i);
        }
  }

 private:
  static uint64_t Key(const Cell& c) {
    // 21 bits per axis: ±1M cells, far beyond an indoor map at any cell size used here.
    const auto bits = [](int64_t v) { return static_cast<uint64_t>(v + (1 << 20)) & 0x1FFFFF; };
    return bits(c[0]) << 42 | bits(c[1]) << 21 | bits(c[2]);
  }
  double cell_;
  std::unordered_map<uint64_t, std::vector<size_t>> cells_;
};

}  // namespace

std::vector<ThinnedKeyframe> PlanThinning(const std::vector<RetentionCandidate>& candidates,
                                          int visit_count, const RetentionOptions& options) {
  const size_t n = candidates.size();
  const double cell = std::max({options.cover_m, options.compact_cover_m, 0.05});
  KeptGrid grid(cell);
  for (size_t i = 0; i < n; ++i) grid.Add(i, candidates[i].pose.translation);
  const int thinnable = visit_count - options.keep_recent_visits;  // ranks below it
  const auto compacted = [&](const RetentionCandidate& k) {
    return visit_count - 1 - k.visit_rank >= options.compact_after_visits;
  };
  // Whether `c` covers `k`'s view at the thresholds of `k`'s visit.
  const auto covers = [&](const RetentionCandidate& k, const RetentionCandidate& c) {
    const bool compact = compacted(k);
    return TranslationDistanceM(k.pose, c.pose) <=
               (compact ? options.compact_cover_m : options.cover_m) &&
           RotationAngleRad(k.pose, c.pose) * kRadToDeg <=
               (compact ? options.compact_cover_deg : options.cover_deg);
  };
  std::vector<bool> kept(n, true);
  // The thinned keyframes each kept one covers. A keyframe covering others is thinned only when
  // a kept one covers it and all of them (each at its own visit's thresholds): every thinned
  // view stays covered by a kept keyframe, never by a chain drifting away.
  std::vector<std::vector<size_t>> covered(n);
  for (size_t i = 0; i < n; ++i) {
    const RetentionCandidate& k = candidates[i];
    if (k.protect || k.visit_rank >= thinnable) continue;
    size_t best = n;
    double best_m = 0;
    grid.ForEachNear(k.pose.translation, [&](size_t j) {
      const RetentionCandidate& c = candidates[j];
      if (j == i || !kept[j] || c.visit_rank < k.visit_rank || !covers(k, c)) return;
      for (const size_t d : covered[i]) {
        if (!covers(candidates[d], c)) return;
      }
      const double m = TranslationDistanceM(k.pose, c.pose);
      if (best == n || m < best_m) {
        best = j;
        best_m = m;
      }
    });
    if (best == n) continue;
    kept[i] = false;
    grid.Remove(i, k.pose.translation);
    covered[best].push_back(i);
    covered[best].insert(covered[best].end(), covered[i].begin(), covered[i].end());
    covered[i].clear();
  }
  std::vector<ThinnedKeyframe> out;
  for (size_t c = 0; c < n; ++c) {
    for (const size_t d : covered[c]) {
      out.push_back({candidates[d].keyframe_id, candidates[c].keyframe_id,
                     TranslationDistanceM(candidates[d].pose, candidates[c].pose),
                     RotationAngleRad(candidates[d].pose, candidates[c].pose) * kRadToDeg});
    }
  }
  return out;
}

absl::StatusOr<RetentionReport> ApplyRetention(store::Store* store, AppearanceIndex* appearance,
                                               const store::MapRecord& map,
                                               const RetentionOptions& options, bool dry_run) {
  static absl::Mutex one_at_a_time(absl::kConstInit);
  absl::MutexLock lock(&one_at_a_time);
  const auto start = std::chrono::steady_clock::now();
  RetentionReport report;
  report.dry_run = dry_run;
  auto before = store->GetMapStorage(map.id);
  if (!before.ok()) return before.status();
  report.before = *before;

  auto visits = store->ListVisits(map.name);
  if (!visits.ok()) return visits.status();
  auto frame = VisitsInMapFrame(store, map.name);
  if (!frame.ok()) return frame.status();
  std::sort(visits->begin(), visits->end(), [](const auto& a, const auto& b) {
    return std::tie(a.start_time_s, a.id) < std::tie(b.start_time_s, b.id);
  });
  // Ranks of the ended visits in the map's frame that hold keyframes, oldest 0.
  std::unordered_map<int64_t, int> rank;
  for (const auto& v : *visits) {
    if (v.ended && v.keyframe_count > 0 && frame->in_map_frame.count(v.id) != 0) {
      const int r = static_cast<int>(rank.size());
      rank[v.id] = r;
    }
  }
  const int ranked = static_cast<int>(rank.size());
  const int thinnable = ranked - options.keep_recent_visits;

  auto keyframes = store->ListKeyframes(map.id, 0);
  if (!keyframes.ok()) return keyframes.status();
  std::unordered_map<int64_t, int64_t> visit_of;
  for (const auto& k : *keyframes) visit_of[k.id] = k.visit_id;
  // Keyframes an accepted edge names (their landmarks survived into another view).
  auto edges = store->ListPoseEdges(map.id, 0);
  if (!edges.ok()) return edges.status();
  std::set<int64_t> matched;
  for (const auto& e : *edges) {
    if (!e.accepted) continue;
    matched.insert(e.from_keyframe);
    matched.insert(e.to_keyframe);
  }

  // Keyframes one of the newest visits recognised (their landmarks survived into it).
  std::set<int64_t> recent_visits;
  for (auto v = visits->rbegin(); v != visits->rend(); ++v) {
    if (static_cast<int>(recent_visits.size()) >= options.recognised_within_visits) break;
    if (v->keyframe_count > 0) recent_visits.insert(v->id);
  }
  auto sightings = store->ListSightings(map.id);
  if (!sightings.ok()) return sightings.status();
  std::set<int64_t> recognised;
  for (const auto& [keyframe, by] : *sightings) {
    for (const int64_t v : by) {
      if (recent_visits.count(v) != 0) recognised.insert(keyframe);
    }
  }

  // Candidates in rank, then time order; why protected ones are kept.
  std::map<int64_t, std::vector<const store::KeyframeRecord*>> by_visit;
  for (const auto& k : *keyframes) by_visit[k.visit_id].push_back(&k);
  std::vector<std::pair<int, int64_t>> order;  // (rank, visit)
  for (const auto& [id, r] : rank) order.emplace_back(r, id);
  std::sort(order.begin(), order.end());
  std::vector<RetentionCandidate> candidates;
  std::unordered_map<int64_t, std::string> protected_because;
  for (const auto& [r, visit_id] : order) {
    const auto& list = by_visit[visit_id];
    for (size_t n = 0; n < list.size(); ++n) {
      const store::KeyframeRecord& k = *list[n];
      if (!k.T_world_camera) continue;  // covers nothing and is kept (below)
      RetentionCandidate c{k.id, r, *k.T_world_camera, false};
      if (n == 0) {
        protected_because[k.id] = "first keyframe of its visit";
      } else if (matched.count(k.id) != 0) {
        protected_because[k.id] = "landmarks matched by a later or earlier view (accepted edge)";
      } else if (recognised.count(k.id) != 0) {
        protected_because[k.id] = absl::StrCat("recognised by one of the ",
                                               options.recognised_within_visits, " newest visits");
      }
      c.protect = protected_because.count(k.id) != 0;
      candidates.push_back(c);
    }
  }
  const auto plan = PlanThinning(candidates, ranked, options);
  std::unordered_map<int64_t, const ThinnedKeyframe*> thinned;
  std::set<int64_t> covering;
  for (const auto& t : plan) {
    thinned[t.keyframe_id] = &t;
    covering.insert(t.covered_by);
  }

  // The report per visit, oldest first, and the deletions (one transaction per visit).
  for (const auto& v : *visits) {
    RetentionReport::Visit out;
    out.visit_id = v.id;
    const auto& list = by_visit[v.id];
    out.keyframes = static_cast<int64_t>(list.size());
    const auto r = rank.find(v.id);
    if (!v.ended) {
      out.kept_whole = "open: its keyframes are still being written";
    } else if (list.empty()) {
      out.kept_whole = "no keyframes";
    } else if (r == rank.end()) {
      out.kept_whole =
          "not in the map's frame (tracked and not anchored): its poses compare "
          "with no other visit's";
    } else if (r->second >= thinnable) {
      out.kept_whole = absl::StrCat("one of the ", options.keep_recent_visits,
                                    " newest visits in the map's frame");
    }
    if (out.kept_whole.empty()) {
      out.compacted = ranked - 1 - r->second >= options.compact_after_visits;
      std::vector<int64_t> ids;
      for (const auto* k : list) {
        if (auto t = thinned.find(k->id); t != thinned.end()) {
          ids.push_back(k->id);
          report.thinned.push_back({*t->second, v.id, visit_of[t->second->covered_by]});
        } else if (!k->T_world_camera) {
          ++out.kept_because["no pose"];
        } else if (auto p = protected_because.find(k->id); p != protected_because.end()) {
          ++out.kept_because[p->second];
        } else if (covering.count(k->id) != 0) {
          ++out.kept_because["covers a thinned keyframe's view"];
        } else {
          ++out.kept_because["adds a view: no kept keyframe of this or a later visit covers it"];
        }
        if (dry_run && thinned.count(k->id) != 0)
          out.bytes_freed += k->depth_bytes + k->color_bytes;
      }
      out.thinned = static_cast<int64_t>(ids.size());
      if (!dry_run && !ids.empty()) {
        auto freed = store->DeleteKeyframes(v.id, ids);
        if (!freed.ok()) return freed.status();
        out.bytes_freed = *freed;
        if (appearance != nullptr) appearance->RemoveKeyframes(ids);
      }
    }
    report.visits.push_back(std::move(out));
  }
  if (dry_run) {
    report.after = report.before;
  } else {
    auto after = store->GetMapStorage(map.id);
    if (!after.ok()) return after.status();
    report.after = *after;
  }
  report.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return report;
}

}  // namespace lifemap::server
