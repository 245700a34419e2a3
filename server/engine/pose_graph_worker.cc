#include "server/engine/pose_graph_worker.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <set>
#include <string>
#include <vector>

#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/appearance/recognizer.h"
#include "core/common/image_codec.h"
#include "core/place/descriptor.h"
#include "core/place/layout_check.h"
#include "core/place/serialize.h"
#include "core/posegraph/pose_graph.h"
#include "server/engine/clock.h"
#include "server/engine/visit_frame.h"

namespace lifemap::server {

// The last keyframe depth decoded for a floor-plan check: a keyframe's loop and tie candidates
// are checked one after the other.
struct DecodedKeyframe {
  int64_t id = 0;
  cv::Mat depth_m;
  CameraIntrinsics k;
};

namespace {

constexpr double kRadToDeg = 180.0 / M_PI;

// Standard deviations of an odometry edge over `distance_m` and `angle_rad` of motion: a floor
// for a standing camera, growing with the motion (frame-to-keyframe odometry drifts about 1-2 %
// of the path on the shared recordings).
posegraph::Edge OdometryEdge(const store::KeyframeRecord& a, const store::KeyframeRecord& b) {
  posegraph::Edge e;
  e.from = a.id;
  e.to = b.id;
  e.kind = posegraph::EdgeKind::kOdometry;
  e.T_from_to = posegraph::Relative(*a.T_odom_camera, *b.T_odom_camera);
  const double d = e.T_from_to.translation.norm();
  const double angle = Eigen::AngleAxisd(e.T_from_to.rotation).angle();
  e.sigma_m = 0.003 + 0.02 * d;
  e.sigma_rad = 0.002 + 0.02 * angle + 0.01 * d;
  return e;
}

// A loop edge: PnP on 25+ inliers at indoor range places the camera within about 2 cm and half a
// degree.
constexpr double kLoopSigmaM = 0.02;
constexpr double kLoopSigmaRad = 0.01;

// A visit is anchored when two of its keyframes' matches put it within this of each other, and
// waits with at most this many single matches.
constexpr double kAnchorAgreementM = 0.10;
constexpr double kAnchorAgreementDeg = 3.0;

// Whether two poses are within `m` metres and `deg` degrees of each other.
bool Within(const Pose& a, const Pose& b, double m, double deg) {
  return (a.translation - b.translation).norm() <= m && RotationAngleRad(a, b) * kRadToDeg <= deg;
}
// Whether two estimates of a visit's place in the map agree (kAnchorAgreementM / Deg).
bool AnchorsAgree(const Pose& a, const Pose& b) {
  return Within(a, b, kAnchorAgreementM, kAnchorAgreementDeg);
}
constexpr size_t kMaxPendingAnchors = 64;
// A placement this close to one the floor-plan check refused is the same placement.
constexpr double kRefusedAgreementM = 0.30;
constexpr double kRefusedAgreementDeg = 5.0;
bool SameAsRefused(const std::vector<Pose>& refused, const Pose& T_map_visit) {
  return std::any_of(refused.begin(), refused.end(), [&](const Pose& r) {
    return Within(r, T_map_visit, kRefusedAgreementM, kRefusedAgreementDeg);
  });
}
// The floor-plan check refused placing a visit at `wrong`: remembered in `refused` (up to
// kMaxPendingAnchors), and every estimate in `estimates` that agrees with it dropped.
template <typename Estimate>
void Refuse(const Pose& wrong, std::vector<Pose>* refused, std::vector<Estimate>* estimates) {
  if (refused->size() < kMaxPendingAnchors) refused->push_back(wrong);
  estimates->erase(
      std::remove_if(estimates->begin(), estimates->end(),
                     [&](const Estimate& e) { return AnchorsAgree(e.T_map_visit, wrong); }),
      estimates->end());
}

// A visit's keyframes (without images) by id, for FindKeyframe.
absl::StatusOr<std::vector<store::KeyframeRecord>> KeyframesById(store::Store* store,
                                                                 int64_t map_id, int64_t visit_id) {
  auto keyframes = store->ListKeyframes(map_id, visit_id);
  if (!keyframes.ok()) return keyframes.status();
  std::sort(keyframes->begin(), keyframes->end(),
            [](const auto& a, const auto& b) { return a.id < b.id; });
  return keyframes;
}

const store::KeyframeRecord* FindKeyframe(const std::vector<store::KeyframeRecord>& by_id,
                                          int64_t id) {
  auto it = std::lower_bound(by_id.begin(), by_id.end(), id,
                             [](const auto& k, int64_t v) { return k.id < v; });
  return it != by_id.end() && it->id == id ? &*it : nullptr;
}

// How many of `keyframes` are posed.
size_t PosedCount(const std::vector<store::KeyframeRecord>& keyframes) {
  return static_cast<size_t>(std::count_if(keyframes.begin(), keyframes.end(),
                                           [](const auto& k) { return k.T_world_camera; }));
}

// The architecture check of anchors and loops: at most this many keyframes of a visit are
// placed in a plan (spread over the visit; each costs a depth decode and ~1 ms of rays).
constexpr size_t kLayoutKeyframes = 24;
// ... and an anchor waits until the visit has this many: a visit's first two keyframes (its
// first second) are too little evidence (RESULTS.md "Issue 15 (fifth part)").
constexpr size_t kLayoutMinKeyframes = 6;

// A visit's stored floor plan, if it has one in the frame its stored keyframes are in now: an
// anchored visit's plan derived before the anchor is in its old frame (the next key frame
// re-derives it).
std::optional<place::FloorPlan> StoredPlanOf(store::Store* store, const store::VisitRecord& visit) {
  auto record = store->GetVisitPlace(visit.id);
  if (!record.ok()) return std::nullopt;
  if (visit.anchor && record->updated_time_s < visit.anchor->anchored_time_s) return std::nullopt;
  auto plan = place::FloorPlanFromJson(record->floor_plan_json);
  if (!plan.ok()) return std::nullopt;
  return *std::move(plan);
}

// `plan`, when it has walls enough to place keyframes in.
std::optional<place::FloorPlan> Checkable(std::optional<place::FloorPlan> plan) {
  if (!plan || plan->walls.size() < 3) return std::nullopt;
  return plan;
}

// The visit's stored plan, when it is in its keyframes' frame and checkable.
std::optional<place::FloorPlan> PlanOf(store::Store* store, const store::VisitRecord& visit) {
  return Checkable(StoredPlanOf(store, visit));
}

// The map `map_name`'s first visit (its frame is the map's), if it can be read.
std::optional<store::VisitRecord> FirstVisitOf(store::Store* store, const std::string& map_name) {
  auto visits = store->ListVisits(map_name);
  if (!visits.ok()) return std::nullopt;
  for (auto& v : *visits) {
    if (v.first_of_map) return std::move(v);
  }
  return std::nullopt;
}

// The floor plan a match to `to_visit` is checked against, and whose it is: `to_visit`'s own, or
// where it has none (yet), its map's first visit's (every visit in the map's frame shares it).
std::optional<std::pair<place::FloorPlan, int64_t>> PlanToCheck(
    store::Store* store, const store::VisitRecord& to_visit) {
  // A visit whose anchor was dropped has its plan in its own frame: not the map's.
  if (MapFromVisit(to_visit)) {
    if (auto plan = PlanOf(store, to_visit)) return std::make_pair(*std::move(plan), to_visit.id);
  }
  if (to_visit.first_of_map) return std::nullopt;
  const std::optional<store::VisitRecord> first = FirstVisitOf(store, to_visit.map_name);
  if (!first) return std::nullopt;
  if (auto plan = PlanOf(store, *first)) return std::make_pair(*std::move(plan), first->id);
  return std::nullopt;
}

// What a plan says of cameras placed in it: readings beyond its walls, cameras outside it.
struct LayoutEvidence {
  int keyframes = 0;
  int outside = 0;
  int64_t readings = 0;
  int64_t through = 0;
  double ThroughShare() const {
    return readings > 0 ? static_cast<double>(through) / static_cast<double>(readings) : 0.0;
  }
  std::string Text() const {
    return absl::StrFormat(
        "%.1f %% of %d depth readings of %d keyframes beyond its walls, %d cameras outside it",
        100 * ThroughShare(), readings, keyframes, outside);
  }
};

// Why the evidence contradicts the plan (empty when it does not): too many readings beyond its
// walls, or most cameras outside it.
std::string LayoutDisagreement(const LayoutEvidence& e, double max_through_share) {
  if (e.keyframes == 0) return "";
  if (e.ThroughShare() > max_through_share || 2 * e.outside > e.keyframes) {
    return absl::StrCat("disagrees with the floor plan: ", e.Text(), " (allowed ",
                        absl::StrFormat("%.1f", 100 * max_through_share),
                        " %, and at most half outside)");
  }
  return "";
}

// An edge from a verified match of keyframe `query_id`, not yet judged.
store::PoseEdgeRecord EdgeOf(int64_t map_id, store::StoredEdgeKind kind, const LoopCandidate& c,
                             int64_t query_id) {
  store::PoseEdgeRecord edge;
  edge.map_id = map_id;
  edge.kind = kind;
  edge.from_keyframe = c.keyframe_id;
  edge.to_keyframe = query_id;
  edge.T_from_to = c.T_match_query;
  edge.inliers = c.inliers;
  edge.reprojection_px = c.reprojection_px;
  edge.created_time_s = NowSeconds();
  return edge;
}

// The tracker's path (metres) over the keyframes (by id) after `from_id` up to `to_id`.
double PathM(const std::vector<store::KeyframeRecord>& by_id, int64_t from_id, int64_t to_id) {
  double path_m = 0;
  for (size_t i = 1; i < by_id.size(); ++i) {
    const auto& k = by_id[i];
    const auto& prev = by_id[i - 1];
    if (k.id <= from_id || k.id > to_id) continue;
    if (k.T_odom_camera && prev.T_odom_camera && k.odom_segment == prev.odom_segment) {
      path_m += (k.T_odom_camera->translation - prev.T_odom_camera->translation).norm();
    }
  }
  return path_m;
}

// Whether a stored keyframe's pose is in its map's frame: its visit is the map's first, or was
// anchored (its keyframes were moved into the map's frame), or the pose is the client's.
bool InMapFrame(const store::VisitRecord& visit, const store::KeyframeRecord& k) {
  return visit.first_of_map || visit.anchor.has_value() ||
         k.pose_source == store::StoredPoseSource::kClient ||
         k.pose_source == store::StoredPoseSource::kRefined;
}

// Places each keyframe (its id and T_frame_camera) by `T_plan_frame` in `plan` and checks its
// depth against the walls; `last_decoded` keeps the last depth decoded.
LayoutEvidence CheckLayout(store::Store* store, int64_t map_id,
                           const std::vector<std::pair<int64_t, Pose>>& keyframes,
                           const Eigen::Isometry3d& T_plan_frame, const place::FloorPlan& plan,
                           std::unique_ptr<DecodedKeyframe>* last_decoded,
                           const place::LayoutCheckOptions& options = {}) {
  LayoutEvidence e;
  for (const auto& [id, T_frame_camera] : keyframes) {
    if (!(*last_decoded) || (*last_decoded)->id != id) {
      auto k = store->GetKeyframe(map_id, id);
      auto depth = k.ok() ? DecodeDepthMetres(store::StoredDepth(*k)) : k.status();
      if (!depth.ok()) {
        spdlog::warn("keyframe {}: not checked against the floor plan: {}", id,
                     depth.status().ToString());
        continue;
      }
      (*last_decoded).reset(new DecodedKeyframe{id, *std::move(depth), k->intrinsics});
    }
    const place::LayoutAgreement a =
        place::CheckLayout(plan, (*last_decoded)->depth_m, (*last_decoded)->k,
                           Pose::FromIsometry(T_plan_frame * T_frame_camera.ToIsometry()), options);
    ++e.keyframes;
    e.outside += !a.camera_inside;
    e.readings += a.readings;
    e.through += a.through_walls;
  }
  return e;
}

// The posed keyframes of `keyframes`: id and T_world_camera.
std::vector<std::pair<int64_t, Pose>> PosesOf(const std::vector<store::KeyframeRecord>& keyframes) {
  std::vector<std::pair<int64_t, Pose>> posed;
  for (const auto& k : keyframes) {
    if (k.T_world_camera) posed.emplace_back(k.id, *k.T_world_camera);
  }
  return posed;
}

// At most kLayoutKeyframes of `placed`, spread over them.
std::vector<std::pair<int64_t, Pose>> SpreadForLayout(
    std::vector<std::pair<int64_t, Pose>> placed) {
  if (placed.size() <= kLayoutKeyframes) return placed;
  std::vector<std::pair<int64_t, Pose>> spread;
  for (size_t i = 0; i < kLayoutKeyframes; ++i) {
    spread.push_back(placed[i * placed.size() / kLayoutKeyframes]);
  }
  return spread;
}

// A visit's lost share is judged from this many frames on: one lost frame of the first few is
// not a broken track.
constexpr int64_t kMinFramesToJudgeTracking = 20;

// Why an anchor to `to_visit`, which is no longer in the map's frame, is dropped.
std::string AnchorGoneReason(const store::VisitRecord& to_visit) {
  return absl::StrCat(
      "the visit it was anchored to (", to_visit.id, ") is no longer in the map's frame",
      to_visit.anchor_dropped.empty()
          ? std::string()
          : absl::StrCat(": its anchor was dropped (", to_visit.anchor_dropped, ")"));
}

}  // namespace

// Its keyframes are pieces joined by relocalisation or guesswork, and two of its matches
// agreeing prove little: rooms seed 15 without odometry, every visit of the L room lost 36-61 %
// of its frames and all eight were anchored 1.4-2.6 m wrong.
std::string BrokenTracking(const store::VisitRecord& v, double max_lost_share) {
  if (v.frame_count < kMinFramesToJudgeTracking) return "";
  const double share = static_cast<double>(v.lost_frame_count) / static_cast<double>(v.frame_count);
  if (share <= max_lost_share) return "";
  return absl::StrFormat(
      "visit %d's own tracking lost %d of its %d frames (%.0f %%, more than "
      "pose_graph.anchor_max_lost_share %.0f %%): its keyframes are not one rigid body",
      v.id, v.lost_frame_count, v.frame_count, 100.0 * share, 100.0 * max_lost_share);
}

// A bent track's floor judged from at least this many keyframes' sightings of it: its tilt,
// and its level's drift (over thirds of them: three sightings a third at least; with two, a
// rigid 40-frame visit's drift read 0.18 m, building seed 42).
constexpr int kMinFloorSightings = 5;
constexpr int kMinDriftSightings = 9;

std::string UnanchorableTrack(store::Store* store, const store::VisitRecord& v,
                              const PoseGraphOptions& options) {
  if (std::string broken = BrokenTracking(v, options.anchor_max_lost_share); !broken.empty()) {
    return broken;
  }
  if (v.tracked_keyframes == 0) return "";  // the robot's own poses: not the tracker's to judge
  // Any stored plan in the keyframes' frame, however few its walls: the floor is what is judged.
  const std::optional<place::FloorPlan> plan = StoredPlanOf(store, v);
  if (!plan) return "";
  const place::FloorAgreement& a = plan->floor_agreement;
  const bool tilted = a.tilt_deg_p90 > options.anchor_max_floor_tilt_deg;
  const bool drifted =
      a.keyframes >= kMinDriftSightings && a.drift_m > options.anchor_max_floor_offset_m;
  if (a.keyframes < kMinFloorSightings || (!tilted && !drifted)) return "";
  return absl::StrFormat(
      "visit %d's own track is bent: the floor its keyframes saw tilts %.1f deg and its level "
      "moves %.2f m over the visit (tilt's 90th percentile, level's drift over thirds of %d "
      "keyframes; pose_graph.anchor_max_floor_tilt_deg %.1f, anchor_max_floor_offset_m %.2f)",
      v.id, a.tilt_deg_p90, a.drift_m, a.keyframes, options.anchor_max_floor_tilt_deg,
      options.anchor_max_floor_offset_m);
}

LoopCandidate LoopCandidateOf(const appearance::AppearanceMatch& m) {
  return {m.keyframe.keyframe_id, m.verification.T_match_query, m.verification.inliers,
          m.verification.reprojection_px};
}

std::vector<AnchorCandidate> AnchorCandidatesOf(const appearance::Recognition& recognition,
                                                int64_t map_id, int64_t visit_id) {
  std::vector<AnchorCandidate> out;
  for (const auto& m : recognition.matches) {
    if (m.verification.verified && m.keyframe.visit_id != visit_id && m.keyframe.map_id == map_id) {
      out.push_back({m.keyframe.visit_id, LoopCandidateOf(m)});
    }
  }
  return out;
}

std::string WeakMatchReason(const LoopCandidate& c, const PoseGraphOptions& options) {
  if (c.inliers < options.loop_min_inliers) {
    return absl::StrCat(c.inliers, " PnP inliers, a loop needs ", options.loop_min_inliers);
  }
  if (c.reprojection_px > options.loop_max_reprojection_px) {
    return absl::StrFormat("reprojection %.2f px, a loop allows %.2f", c.reprojection_px,
                           options.loop_max_reprojection_px);
  }
  return "";
}

PoseGraphWorker::PoseGraphWorker(store::Store* store, PoseGraphOptions options)
    : store_(store), options_(options), thread_([this] { Run(); }) {}

PoseGraphWorker::~PoseGraphWorker() {
  {
    absl::MutexLock lock(&mu_);
    stopping_ = true;
  }
  thread_.join();
}

uint64_t PoseGraphWorker::Submit(Job job) {
  absl::MutexLock lock(&mu_);
  const uint64_t ticket = ++submitted_;
  queue_.emplace_back(ticket, std::move(job));
  return ticket;
}

uint64_t PoseGraphWorker::last_ticket() const {
  absl::MutexLock lock(&mu_);
  return submitted_;
}

void PoseGraphWorker::Wait(uint64_t ticket) {
  struct Until {
    const uint64_t* done;
    uint64_t ticket;
  } until{&done_, ticket};
  absl::MutexLock lock(&mu_);
  mu_.Await(absl::Condition(
      +[](Until* u) { return *u->done >= u->ticket; }, &until));
}

LoopClosureStats PoseGraphWorker::Stats() const {
  absl::MutexLock lock(&mu_);
  return stats_;
}

void PoseGraphWorker::Run() {
  for (;;) {
    std::pair<uint64_t, Job> next;
    {
      absl::MutexLock lock(&mu_);
      mu_.Await(absl::Condition(
          +[](PoseGraphWorker* w)
               ABSL_EXCLUSIVE_LOCKS_REQUIRED(w->mu_) { return w->stopping_ || !w->queue_.empty(); },
          this));
      if (queue_.empty()) return;  // stopping, and nothing left
      next = std::move(queue_.front());
      queue_.pop_front();
    }
    Process(std::move(next.second));
    absl::MutexLock lock(&mu_);
    done_ = next.first;
  }
}

void PoseGraphWorker::Process(Job job) {
  if (job.plan_at_end) {
    // The visit ended: its anchor, if any, is re-checked with every keyframe and its final plan.
    auto visit = store_->GetVisit(job.visit_id);
    if (!visit.ok() || !visit->anchor) return;
    auto keyframes = KeyframesById(store_, job.map_id, job.visit_id);
    if (!keyframes.ok()) return;
    if (!RecheckAnchor(job, *visit, *keyframes)) {
      spdlog::info("visit {}: anchor to visit {} kept at the visit's end", job.visit_id,
                   visit->anchor->to_visit_id);
    }
    return;
  }
  const absl::StatusOr<int64_t>& committed = job.committed.get();
  if (!committed.ok()) return;  // the keyframe was not stored: nothing to join
  const int64_t query_id = *committed;
  auto keyframes = KeyframesById(store_, job.map_id, job.visit_id);
  if (!keyframes.ok()) {
    spdlog::warn("visit {}: loop candidates of keyframe {} dropped: {}", job.visit_id, query_id,
                 keyframes.status().ToString());
    return;
  }
  const store::KeyframeRecord* query = FindKeyframe(*keyframes, query_id);
  if (query == nullptr || !query->T_odom_camera) return;
  auto visit = store_->GetVisit(job.visit_id);
  if (!visit.ok()) return;
  // An unanchored visit's matches to other visits may anchor it; an anchored visit's tie it to
  // them in its pose graph.
  const bool was_anchored = visit->anchor.has_value();
  if (job.dry_run) {
    if (was_anchored) {
      job.dry_run->verdicts.push_back(absl::StrCat("keyframe ", query_id,
                                                   ": the visit is anchored (to visit ",
                                                   visit->anchor->to_visit_id, ")"));
    } else {
      ProcessAnchors(job, *visit, *query, *keyframes);
    }
    return;
  }
  const bool anchored =
      !was_anchored && !job.anchors.empty() && ProcessAnchors(job, *visit, *query, *keyframes);
  // An anchor just moved the visit's poses: the checks and the solve read them again.
  if (anchored) {
    keyframes = KeyframesById(store_, job.map_id, job.visit_id);
    if (!keyframes.ok()) return;
    query = FindKeyframe(*keyframes, query_id);
    if (query == nullptr) return;
    visit = store_->GetVisit(job.visit_id);  // anchored now: its plan is in the old frame
    if (!visit.ok()) return;
  }
  // The visit's own floor plan, read once a loop needs it.
  std::optional<std::optional<place::FloorPlan>> own_plan;

  int accepted = 0;
  for (const LoopCandidate& c : job.candidates) {
    store::PoseEdgeRecord edge = EdgeOf(job.map_id, store::StoredEdgeKind::kLoop, c, query_id);
    const store::KeyframeRecord* match = FindKeyframe(*keyframes, c.keyframe_id);
    if (match == nullptr) {
      edge.reason = "the matched keyframe is not in this visit";
    } else if (!match->T_odom_camera || match->odom_segment != query->odom_segment) {
      edge.reason =
          "the matched keyframe was tracked by an earlier run of the tracker (the visit was "
          "resumed): no odometry joins them";
    } else {
      if (!own_plan) own_plan.emplace(PlanOf(store_, *visit));
      // The odometry's own idea of where the query is from the match, up to the drift it can
      // have accumulated over the path between them.
      Judge(c, posegraph::Relative(*match->T_odom_camera, *query->T_odom_camera),
            PathM(*keyframes, match->id, query_id), "the odometry", *match,
            own_plan->has_value() ? &**own_plan : nullptr, &edge);
    }
    if (auto id = store_->InsertPoseEdge(edge); !id.ok()) {
      spdlog::warn("visit {}: loop edge not stored: {}", job.visit_id, id.status().ToString());
      continue;
    }
    accepted += edge.accepted;
    absl::MutexLock lock(&mu_);
    ++stats_.candidates;
    ++(edge.accepted ? stats_.accepted : stats_.rejected);
  }
  if (was_anchored) {
    accepted += ProcessTies(job, *query, *keyframes);
    const int revised = ReviseAnchor(job, *visit, *keyframes);
    // A revision checked the plan with every keyframe; otherwise the anchor may be re-checked.
    if (revised > 0 || RecheckAnchor(job, *visit, *keyframes)) {
      // The keyframes moved: the solve reads them again.
      keyframes = KeyframesById(store_, job.map_id, job.visit_id);
      if (!keyframes.ok()) return;
      accepted += revised;
    }
  }
  if (accepted == 0) return;
  auto correction = Solve(job.map_id, job.visit_id, *keyframes);
  if (!correction.ok()) {
    spdlog::warn("visit {}: pose graph not solved: {}", job.visit_id,
                 correction.status().ToString());
    return;
  }
  if (job.on_corrected) job.on_corrected(*correction);
}

PoseGraphWorker::Verdict PoseGraphWorker::Judge(const LoopCandidate& c, const Pose& predicted,
                                                double path_m, const char* poses,
                                                const store::KeyframeRecord& match,
                                                const place::FloorPlan* plan,
                                                store::PoseEdgeRecord* edge) {
  if (const std::string weak = WeakMatchReason(c, options_); !weak.empty()) {
    edge->reason = weak;
    return Verdict::kWeak;
  }
  const double off_m = (predicted.translation - c.T_match_query.translation).norm();
  const double off_deg = RotationAngleRad(predicted, c.T_match_query) * kRadToDeg;
  const double allow_m =
      options_.loop_max_disagreement_m + options_.loop_max_disagreement_per_m * path_m;
  const double allow_deg =
      options_.loop_max_disagreement_deg + options_.loop_max_disagreement_deg_per_m * path_m;
  if (off_m > allow_m || off_deg > allow_deg) {
    edge->reason = absl::StrFormat(
        "disagrees with %s by %.2f m / %.1f deg after %.1f m of path (allowed %.2f m / %.1f deg)",
        poses, off_m, off_deg, path_m, allow_m, allow_deg);
    return Verdict::kDisagrees;
  }
  edge->reason = absl::StrFormat("%d inliers, %.2f px; %s off by %.3f m / %.2f deg after %.1f m",
                                 c.inliers, c.reprojection_px, poses, off_m, off_deg, path_m);
  // Where the match puts the query must agree with the matched visit's floor plan, if it has
  // one.
  if (!plan || !match.T_world_camera) {
    absl::StrAppend(&edge->reason, "; no floor plan to check against yet");
    edge->accepted = true;
    return Verdict::kAccepted;
  }
  const Pose placed =
      Pose::FromIsometry(match.T_world_camera->ToIsometry() * c.T_match_query.ToIsometry());
  const LayoutEvidence evidence = CheckLayout(store_, edge->map_id, {{edge->to_keyframe, placed}},
                                              Eigen::Isometry3d::Identity(), *plan, &last_decoded_);
  if (const std::string layout = LayoutDisagreement(evidence, options_.layout_max_through_share);
      !layout.empty()) {
    edge->reason = layout;
    absl::MutexLock lock(&mu_);
    ++stats_.rejected_by_layout;
    return Verdict::kLayout;
  }
  absl::StrAppend(&edge->reason, "; floor plan: ", evidence.Text());
  edge->accepted = true;
  return Verdict::kAccepted;
}

int PoseGraphWorker::ProcessTies(const Job& job, const store::KeyframeRecord& query,
                                 const std::vector<store::KeyframeRecord>& visit_keyframes) {
  if (!query.T_world_camera) return 0;
  int accepted = 0;
  // The matched visits as read once: record, keyframes (by id), the plan to check against.
  struct Matched {
    std::optional<store::VisitRecord> visit;
    std::vector<store::KeyframeRecord> keyframes;
    std::optional<std::pair<place::FloorPlan, int64_t>> plan;
  };
  std::map<int64_t, Matched> matched_visits;
  for (const AnchorCandidate& c : job.anchors) {
    if (c.visit_id == job.visit_id) continue;
    auto [entry, added] = matched_visits.try_emplace(c.visit_id);
    Matched& other = entry->second;
    if (added) {
      if (auto v = store_->GetVisit(c.visit_id); v.ok()) {
        if (auto listed = KeyframesById(store_, job.map_id, c.visit_id); listed.ok()) {
          other.keyframes = *std::move(listed);
        }
        other.plan = PlanToCheck(store_, *v);
        other.visit = *std::move(v);
      }
    }
    if (!other.visit || other.visit->map_id != job.map_id) continue;
    const store::KeyframeRecord* matched = FindKeyframe(other.keyframes, c.match.keyframe_id);
    if (matched == nullptr || !matched->T_world_camera || !InMapFrame(*other.visit, *matched)) {
      continue;  // a visit not in the map's frame yet ties nothing
    }
    store::PoseEdgeRecord edge =
        EdgeOf(job.map_id, store::StoredEdgeKind::kAnchor, c.match, query.id);
    // Both visits are in the map's frame: their stored poses predict the match, up to this
    // visit's drift since its start.
    const Verdict verdict =
        Judge(c.match, posegraph::Relative(*matched->T_world_camera, *query.T_world_camera),
              PathM(visit_keyframes, 0, query.id), "the map's poses", *matched,
              other.plan ? &other.plan->first : nullptr, &edge);
    if (edge.accepted) {
      edge.reason =
          absl::StrCat("ties visit ", job.visit_id, " to visit ", c.visit_id, ": ", edge.reason);
      ++anchoring_[job.visit_id].support;
    } else if (verdict == Verdict::kDisagrees) {
      // A strong match that puts the visit elsewhere: dissent against its anchor, with the
      // correction it asks for.
      AnchorState& state = anchoring_[job.visit_id];
      std::vector<AnchorEstimate>& dissent = state.dissent;
      const Pose asked = Pose::FromIsometry(matched->T_world_camera->ToIsometry() *
                                            c.match.T_match_query.ToIsometry() *
                                            query.T_world_camera->ToIsometry().inverse());
      if (dissent.size() < kMaxPendingAnchors && !SameAsRefused(state.refused_revisions, asked)) {
        AnchorEstimate e;
        e.query_keyframe = query.id;
        e.to_visit = c.visit_id;
        e.edge = EdgeOf(job.map_id, store::StoredEdgeKind::kAnchor, c.match, query.id);
        e.edge.accepted = true;
        e.T_map_visit = asked;
        dissent.push_back(std::move(e));
      }
    }
    if (auto id = store_->InsertPoseEdge(edge); !id.ok()) {
      spdlog::warn("visit {}: tie edge not stored: {}", job.visit_id, id.status().ToString());
      continue;
    }
    accepted += edge.accepted;
    absl::MutexLock lock(&mu_);
    ++(edge.accepted ? stats_.ties : stats_.ties_rejected);
  }
  return accepted;
}

bool PoseGraphWorker::ProcessAnchors(const Job& job, const store::VisitRecord& visit,
                                     const store::KeyframeRecord& query,
                                     const std::vector<store::KeyframeRecord>& visit_keyframes) {
  // The map's frame is its first visit's: that one is never anchored.
  if (visit.anchor || visit.first_of_map || !query.T_world_camera) return false;
  auto visits = store_->ListVisits(visit.map_name);
  if (!visits.ok() || visits->empty()) return false;
  std::map<int64_t, const store::VisitRecord*> by_id;
  for (const auto& v : *visits) by_id[v.id] = &v;
  // The matched visits' keyframes (poses, no images), read once per visit.
  std::map<int64_t, std::vector<store::KeyframeRecord>> matched_visits;
  const bool dry = job.dry_run != nullptr;
  if (dry && !job.dry_run->state) job.dry_run->state = std::make_shared<AnchorState>();
  AnchorState& state = dry ? *job.dry_run->state : anchoring_[job.visit_id];
  std::vector<AnchorEstimate>& pending = state.pending;
  // A dry run says what became of each candidate.
  auto verdict = [&](const AnchorCandidate& c, const std::string& what) {
    if (dry) {
      job.dry_run->verdicts.push_back(absl::StrCat("keyframe ", query.id, " -> keyframe ",
                                                   c.match.keyframe_id, " of visit ", c.visit_id,
                                                   ": ", what));
    }
  };
  // A visit whose own track is broken is held unanchored, whatever its matches say.
  if (const std::string broken = UnanchorableTrack(store_, visit, options_); !broken.empty()) {
    for (const AnchorCandidate& c : job.anchors) verdict(c, "held: " + broken);
    pending.clear();
    if (!dry && !job.anchors.empty()) {
      absl::MutexLock lock(&mu_);
      stats_.anchor_candidates += static_cast<int64_t>(job.anchors.size());
      ++stats_.anchors_held;
    }
    return false;
  }
  for (const AnchorCandidate& c : job.anchors) {
    if (!dry) {
      absl::MutexLock lock(&mu_);
      ++stats_.anchor_candidates;
    }
    const LoopCandidate& m = c.match;
    if (const std::string weak = WeakMatchReason(m, options_); !weak.empty()) {
      verdict(c, weak);
      continue;
    }
    auto it = by_id.find(c.visit_id);
    if (it == by_id.end() || c.visit_id == job.visit_id) continue;
    if (!matched_visits.count(c.visit_id)) {
      auto listed = KeyframesById(store_, job.map_id, c.visit_id);
      if (!listed.ok()) continue;
      matched_visits[c.visit_id] = *std::move(listed);
    }
    const store::KeyframeRecord* matched = FindKeyframe(matched_visits[c.visit_id], m.keyframe_id);
    if (matched == nullptr || !matched->T_world_camera) continue;
    // A tracked visit not anchored yet is not in the map's frame: nothing to anchor to.
    if (!InMapFrame(*it->second, *matched)) {
      verdict(c, "that visit is not in the map's frame");
      continue;
    }
    // Nor is a visit whose own track is broken a frame to anchor to: its keyframes' poses are
    // as scattered as its track.
    if (const std::string broken = UnanchorableTrack(store_, *it->second, options_);
        !broken.empty()) {
      verdict(c, "refused: " + broken);
      continue;
    }
    const Eigen::Isometry3d T_map_query =
        matched->T_world_camera->ToIsometry() * m.T_match_query.ToIsometry();
    AnchorEstimate estimate;
    estimate.query_keyframe = query.id;
    estimate.to_visit = c.visit_id;
    estimate.T_map_visit =
        Pose::FromIsometry(T_map_query * query.T_world_camera->ToIsometry().inverse());
    estimate.edge = EdgeOf(job.map_id, store::StoredEdgeKind::kAnchor, m, query.id);
    estimate.edge.accepted = true;
    const std::string placed = absl::StrFormat(
        "puts the visit at (%.2f, %.2f, %.2f) m, %.1f deg; ", estimate.T_map_visit.translation.x(),
        estimate.T_map_visit.translation.y(), estimate.T_map_visit.translation.z(),
        Eigen::AngleAxisd(estimate.T_map_visit.rotation).angle() * kRadToDeg);
    if (SameAsRefused(state.refused_anchors, estimate.T_map_visit)) {
      verdict(c, placed + "where the floor-plan check refused it before");
      continue;
    }
    // Two matches from different keyframes of the visit must agree: one match can be an alias.
    bool agreed = false;     // with another keyframe's match: judged below, and said so
    bool too_close = false;  // agreed only with keyframes too near along the path
    for (const AnchorEstimate& other : pending) {
      if (other.query_keyframe == query.id) continue;
      // Two keyframes close together agree even where the visit's track is bent: only
      // keyframes far enough apart along it test that the visit is one rigid body.
      if (options_.anchor_min_spread_m > 0 &&
          PathM(visit_keyframes, std::min(other.query_keyframe, query.id),
                std::max(other.query_keyframe, query.id)) < options_.anchor_min_spread_m) {
        too_close = too_close || AnchorsAgree(other.T_map_visit, estimate.T_map_visit);
        continue;
      }
      const double off_m =
          (other.T_map_visit.translation - estimate.T_map_visit.translation).norm();
      const double off_deg = RotationAngleRad(other.T_map_visit, estimate.T_map_visit) * kRadToDeg;
      if (!AnchorsAgree(other.T_map_visit, estimate.T_map_visit)) continue;
      agreed = true;
      // Both matches may be to furniture that another place shares: the visit's keyframes,
      // placed in the map by them, must agree with the matched visit's floor plan.
      const std::optional<std::string> checked = CheckAnchorLayout(
          job, *it->second, estimate.T_map_visit, visit_keyframes, &estimate.edge.reason);
      if (!checked) {  // too few keyframes to check yet: kept pending, decided later
        verdict(c, placed + "agrees with keyframe " + std::to_string(other.query_keyframe) +
                       "'s match; too few keyframes for the floor-plan check yet");
        break;
      }
      const std::string& layout = *checked;
      if (!layout.empty()) {
        estimate.edge.accepted = false;
        estimate.edge.reason = layout;
        verdict(c, absl::StrCat(placed, "agrees with keyframe ", other.query_keyframe,
                                "'s match; refused: the visit ", layout));
        if (!dry) {
          if (auto id = store_->InsertPoseEdge(estimate.edge); !id.ok()) {
            spdlog::warn("visit {}: anchor edge not stored: {}", job.visit_id,
                         id.status().ToString());
          }
          spdlog::info("visit {}: anchor to visit {} rejected: {}", job.visit_id, estimate.to_visit,
                       layout);
        }
        // Every pending match that agrees with this one is as wrong, and so are later ones.
        Refuse(estimate.T_map_visit, &state.refused_anchors, &pending);
        if (!dry) {
          absl::MutexLock lock(&mu_);
          ++stats_.anchors_rejected;
        }
        break;
      }
      store::VisitAnchor anchor;
      anchor.to_visit_id = estimate.to_visit;
      anchor.T_map_visit = estimate.T_map_visit;
      anchor.residual_m = off_m;
      anchor.residual_deg = off_deg;
      anchor.anchored_time_s = NowSeconds();
      estimate.edge.reason = absl::StrFormat(
          "anchors visit %d to visit %d: agrees with keyframe %d's match within %.3f m / %.2f "
          "deg; %s",
          job.visit_id, estimate.to_visit, other.query_keyframe, off_m, off_deg,
          estimate.edge.reason);
      if (dry) {
        verdict(c, placed + "would anchor it: " + estimate.edge.reason);
        if (!job.dry_run->would_anchor) job.dry_run->would_anchor = job.dry_run->verdicts.back();
        state = AnchorState{};  // as anchored: later candidates are judged afresh
        return false;
      }
      if (auto s = store_->AnchorVisit(job.visit_id, estimate.edge, &anchor); !s.ok()) {
        spdlog::warn("visit {}: not anchored: {}", job.visit_id, s.ToString());
        return false;
      }
      spdlog::info("visit {} anchored to visit {} of map '{}' (residual {:.3f} m / {:.2f} deg)",
                   job.visit_id, anchor.to_visit_id, visit.map_name, off_m, off_deg);
      state = AnchorState{};  // anchored: supported by its two matches, no dissent yet
      state.checked_keyframes = PosedCount(visit_keyframes);
      {
        absl::MutexLock lock(&mu_);
        ++stats_.anchors;
      }
      if (job.on_anchored) job.on_anchored(anchor.T_map_visit, anchor.T_map_visit);
      return true;
    }
    if (!agreed) {
      verdict(c, placed + (too_close
                               ? absl::StrFormat("agrees only with keyframes less than "
                                                 "pose_graph.anchor_min_spread_m %.1f m away (yet)",
                                                 options_.anchor_min_spread_m)
                               : std::string("no other keyframe's match agrees (yet)")));
    }
    if (pending.size() < kMaxPendingAnchors && estimate.edge.accepted) {
      pending.push_back(std::move(estimate));
    }
  }
  return false;
}

int PoseGraphWorker::ReviseAnchor(const Job& job, const store::VisitRecord& visit,
                                  const std::vector<store::KeyframeRecord>& visit_keyframes) {
  AnchorState& state = anchoring_[job.visit_id];
  std::vector<AnchorEstimate>& dissent = state.dissent;
  if (!visit.anchor || dissent.empty()) return 0;
  // The largest group of dissenting matches that agree with one of them, counted by distinct
  // keyframes: consecutive matches of one keyframe are one piece of evidence.
  auto keyframes_of = [&](const std::vector<size_t>& group) {
    std::vector<int64_t> ids;
    for (size_t j : group) ids.push_back(dissent[j].query_keyframe);
    std::sort(ids.begin(), ids.end());
    return static_cast<int>(std::unique(ids.begin(), ids.end()) - ids.begin());
  };
  size_t best = 0;
  std::vector<size_t> best_group;
  int votes = 0;
  for (size_t i = 0; i < dissent.size(); ++i) {
    std::vector<size_t> group;
    for (size_t j = 0; j < dissent.size(); ++j) {
      if (AnchorsAgree(dissent[i].T_map_visit, dissent[j].T_map_visit)) group.push_back(j);
    }
    const int n = keyframes_of(group);
    if (n > votes || (n == votes && group.size() > best_group.size())) {
      best = i;
      best_group = std::move(group);
      votes = n;
    }
  }
  const int support = state.support;
  if (votes < options_.anchor_revision_min_matches || votes <= support) return 0;
  const Pose T_moved_by = dissent[best].T_map_visit;
  auto to_visit = store_->GetVisit(dissent[best].to_visit);
  if (!to_visit.ok()) return 0;
  std::string evidence;
  const std::optional<std::string> layout =
      CheckAnchorLayout(job, *to_visit, T_moved_by, visit_keyframes, &evidence);
  if (!layout) return 0;  // too few keyframes to check: wait for more
  if (!layout->empty()) {
    spdlog::info("visit {}: anchor revision to visit {} refused: {}", job.visit_id, to_visit->id,
                 *layout);
    // The group is as wrong as an anchor the plan refuses: dropped, and later dissent agreeing
    // with it too.
    Refuse(T_moved_by, &state.refused_revisions, &dissent);
    return 0;
  }
  double spread_m = 0, spread_deg = 0;
  std::vector<store::PoseEdgeRecord> edges;
  for (size_t j : best_group) {
    spread_m =
        std::max(spread_m, (dissent[j].T_map_visit.translation - T_moved_by.translation).norm());
    spread_deg =
        std::max(spread_deg, RotationAngleRad(dissent[j].T_map_visit, T_moved_by) * kRadToDeg);
    store::PoseEdgeRecord e = dissent[j].edge;
    e.reason = absl::StrFormat("revises the anchor of visit %d (to visit %d): %d inliers, %.2f px",
                               job.visit_id, dissent[j].to_visit, e.inliers, e.reprojection_px);
    edges.push_back(std::move(e));
  }
  const Eigen::Isometry3d moved = T_moved_by.ToIsometry();
  store::VisitAnchor anchor;
  anchor.to_visit_id = to_visit->id;
  anchor.T_map_visit = Pose::FromIsometry(moved * visit.anchor->T_map_visit.ToIsometry());
  anchor.residual_m = spread_m;
  anchor.residual_deg = spread_deg;
  anchor.anchored_time_s = NowSeconds();
  const std::string reason = absl::StrFormat(
      "%d keyframes' matches agree (within %.3f m / %.2f deg) on a place %.2f m / %.1f deg from "
      "the anchor, against %d that supported it; %s",
      votes, spread_m, spread_deg, T_moved_by.translation.norm(),
      Eigen::AngleAxisd(T_moved_by.rotation).angle() * kRadToDeg, support, evidence);
  if (auto s = store_->ReviseAnchor(job.visit_id, T_moved_by, edges, reason, &anchor); !s.ok()) {
    spdlog::warn("visit {}: anchor not revised: {}", job.visit_id, s.ToString());
    return 0;
  }
  spdlog::info("visit {}: anchor revised: {}", job.visit_id, reason);
  dissent.clear();
  state.refused_revisions.clear();
  state.support = votes;
  state.checked_keyframes = PosedCount(visit_keyframes);
  {
    absl::MutexLock lock(&mu_);
    ++stats_.anchors_revised;
  }
  if (job.on_anchored) job.on_anchored(T_moved_by, anchor.T_map_visit);
  return votes;
}

bool PoseGraphWorker::RecheckAnchor(const Job& job, const store::VisitRecord& visit,
                                    const std::vector<store::KeyframeRecord>& visit_keyframes) {
  if (!visit.anchor) return false;
  AnchorState& state = anchoring_[job.visit_id];
  std::string reason = UnanchorableTrack(store_, visit, options_);
  auto to_visit = store_->GetVisit(visit.anchor->to_visit_id);
  if (!reason.empty()) {
    reason = "re-checked: " + reason;
  } else if (!to_visit.ok()) {
    return false;
  } else if (!MapFromVisit(*to_visit)) {
    // Anchored to a visit whose own anchor was dropped since: this placement rests on it.
    reason = AnchorGoneReason(*to_visit);
  } else if (std::optional<std::string> layout =
                 RecheckPlan(job, visit, *to_visit, visit_keyframes)) {
    reason = *std::move(layout);
  } else {
    return false;
  }
  auto dropped = store_->DropAnchor(job.visit_id, reason, NowSeconds());
  if (!dropped.ok()) {
    spdlog::warn("visit {}: anchor not dropped: {}", job.visit_id, dropped.status().ToString());
    return false;
  }
  spdlog::info("visit {}: anchor to visit {} dropped: {}", job.visit_id, visit.anchor->to_visit_id,
               reason);
  // Unanchored again: it may be anchored anew, but not where it was.
  std::vector<Pose> refused = std::move(state.refused_anchors);
  state = AnchorState{};
  state.refused_anchors = std::move(refused);
  Refuse(*dropped, &state.refused_anchors, &state.pending);
  {
    absl::MutexLock lock(&mu_);
    ++stats_.anchors_dropped;
  }
  if (job.on_anchored) {
    job.on_anchored(Pose::FromIsometry(dropped->ToIsometry().inverse()), std::nullopt);
  }
  DropDependents(visit);
  return true;
}

void PoseGraphWorker::DropDependents(const store::VisitRecord& dropped) {
  auto visits = store_->ListVisits(dropped.map_name);
  if (!visits.ok()) return;
  // The dropped visit as stored now (read after its drop): its reason is quoted.
  const auto after = std::find_if(visits->begin(), visits->end(),
                                  [&](const store::VisitRecord& v) { return v.id == dropped.id; });
  if (after == visits->end()) return;
  const std::string reason = AnchorGoneReason(*after);
  for (const store::VisitRecord& v : *visits) {
    if (!v.anchor || v.anchor->to_visit_id != dropped.id) continue;
    // An open visit is dropped at its next keyframe, where the frame path that answers its
    // frames is told (RecheckAnchor); an ended one has no frame path left: dropped here.
    if (!v.ended) continue;
    if (auto s = store_->DropAnchor(v.id, reason, NowSeconds()); !s.ok()) {
      spdlog::warn("visit {}: anchor not dropped: {}", v.id, s.status().ToString());
      continue;
    }
    spdlog::info("visit {}: anchor to visit {} dropped: {}", v.id, dropped.id, reason);
    anchoring_.erase(v.id);
    {
      absl::MutexLock lock(&mu_);
      ++stats_.anchors_dropped;
    }
    DropDependents(v);
  }
}

std::optional<std::string> PoseGraphWorker::RecheckPlan(
    const Job& job, const store::VisitRecord& visit, const store::VisitRecord& to_visit,
    const std::vector<store::KeyframeRecord>& visit_keyframes) {
  AnchorState& state = anchoring_[job.visit_id];
  const size_t posed = PosedCount(visit_keyframes);
  const bool at_end = job.plan_at_end != nullptr;  // checked whatever the count
  if (!at_end) {
    if (state.checked_keyframes == 0) {  // anchored before this run: counted from here
      state.checked_keyframes = posed;
      return std::nullopt;
    }
    if (posed < 2 * state.checked_keyframes) return std::nullopt;
  }
  std::string evidence;
  int64_t plan_visit = 0;
  // The stored keyframes are in the map's frame already.
  const std::optional<std::string> layout =
      CheckAnchorLayout(job, to_visit, Pose{}, visit_keyframes, &evidence,
                        options_.anchor_drop_through_share, &plan_visit);
  if (!layout) return std::nullopt;
  const size_t checked_before = state.checked_keyframes;
  state.checked_keyframes = posed;
  if (layout->empty()) return std::nullopt;
  std::string reason = absl::StrFormat(
      "re-checked %swith %d keyframes (anchored or last checked with %d), the visit %s",
      at_end ? "at the visit's end, with its final floor plan, " : "", posed, checked_before,
      *layout);
  // The plan of a visit anchored itself can be partial (a sparse visit's walls cut short, its
  // furniture taken for walls): a right anchor then disagrees with it and agrees with the map's
  // first visit's. A wrong one (another place) disagrees with both. Building seed 9, 40-frame
  // visits: two right anchors (0.6 cm) were dropped at 6.7 % and 22.9 % against their anchor
  // visits' plans.
  // (When the plan checked was the first visit's already, it is not checked twice.)
  if (const std::optional<store::VisitRecord> first = FirstVisitOf(store_, visit.map_name);
      first && first->id != plan_visit) {
    std::string first_evidence;
    int64_t first_plan_visit = 0;
    const std::optional<std::string> by_first =
        CheckAnchorLayout(job, *first, Pose{}, visit_keyframes, &first_evidence,
                          options_.anchor_drop_through_share, &first_plan_visit);
    if (by_first && by_first->empty() && first_plan_visit != 0) {
      spdlog::info("visit {}: anchor kept: it disagrees with visit {}'s plan but agrees with {}",
                   job.visit_id, plan_visit, first_evidence);
      return std::nullopt;
    }
    if (by_first && !by_first->empty()) absl::StrAppend(&reason, "; and with ", first_evidence);
  }
  return reason;
}

std::optional<std::string> PoseGraphWorker::CheckAnchorLayout(
    const Job& job, const store::VisitRecord& to_visit, const Pose& T_map_visit,
    const std::vector<store::KeyframeRecord>& visit_keyframes, std::string* evidence_text,
    std::optional<double> max_through_share, int64_t* plan_visit) {
  const auto plan = PlanToCheck(store_, to_visit);
  if (plan_visit != nullptr) *plan_visit = plan ? plan->second : 0;
  if (!plan) {
    *evidence_text = absl::StrCat("neither visit ", to_visit.id,
                                  " nor the map's first visit has a floor plan to check against");
    return "";
  }
  std::vector<std::pair<int64_t, Pose>> placed = PosesOf(visit_keyframes);
  // An ended visit (a retry) has all the keyframes it will have: checked with those.
  if (placed.size() < kLayoutMinKeyframes && !job.visit_ended) return std::nullopt;
  placed = SpreadForLayout(std::move(placed));
  const double allowed = max_through_share.value_or(options_.layout_max_through_share);
  const LayoutEvidence evidence = CheckLayout(store_, job.map_id, placed, T_map_visit.ToIsometry(),
                                              plan->first, &last_decoded_);
  *evidence_text = absl::StrCat("visit ", plan->second, "'s floor plan: ", evidence.Text());
  // The visit's plan so far, in the frame its keyframes are in now (T_map_visit's source).
  std::optional<place::FloorPlan> own;
  if (job.plan_at_end) {
    own = Checkable(*job.plan_at_end);
  } else if (auto visit = store_->GetVisit(job.visit_id); visit.ok()) {
    own = PlanOf(store_, *visit);
  }
  // Each plan's seen walls placed in the other (a wall where the other has floor): the larger
  // share of their length, decided on after the depth check; -1 without a plan of its own.
  double on_floor_share = -1;
  std::string on_floor_text;
  if (own) {
    // The two plans' likeness by paper 004's descriptor, as evidence (nothing is decided by it).
    const place::MatchResult m =
        place::MatchDescriptors(place::Describe(*own), place::Describe(plan->first));
    const place::PlanAgreement in_map = place::ComparePlans(*own, plan->first, T_map_visit);
    const place::PlanAgreement in_own = place::ComparePlans(
        plan->first, *own, Pose::FromIsometry(T_map_visit.ToIsometry().inverse()));
    on_floor_share = std::max(in_map.OnFloorShare(), in_own.OnFloorShare());
    on_floor_text = absl::StrFormat(
        "its own plan's seen walls: %.1f of %.1f m on visit %d's floor; visit %d's: %.1f of "
        "%.1f m on its own floor",
        in_map.on_floor_m, in_map.seen_wall_m, plan->second, plan->second, in_own.on_floor_m,
        in_own.seen_wall_m);
    absl::StrAppend(
        evidence_text,
        absl::StrFormat("; its own plan (%d walls) matches visit %d's (%d walls) by "
                        "architecture at %.3f; ",
                        own->walls.size(), plan->second, plan->first.walls.size(), m.score),
        on_floor_text);
  }
  spdlog::info("visit {}: anchor to visit {}: {}", job.visit_id, to_visit.id, *evidence_text);
  if (std::string disagreement = LayoutDisagreement(evidence, allowed); !disagreement.empty()) {
    return disagreement;
  }
  // While the visit is under way its plan is partial, its seen walls running to corners guessed
  // where the outline closes: right anchors reached 60 % there, the wrong one 52-73 %. With the
  // final plans right ones gave 0-7 %, the wrong one 39-71 % (RESULTS.md, building suites 41/42).
  if (job.visit_ended && on_floor_share > options_.layout_max_plan_on_floor_share) {
    return absl::StrCat("disagrees with the floor plan of visit ", plan->second, ": ",
                        on_floor_text,
                        absl::StrFormat(" (%.1f %%; allowed %.1f %%, ", 100 * on_floor_share,
                                        100 * options_.layout_max_plan_on_floor_share),
                        "pose_graph.layout_max_plan_on_floor_share)");
  }
  return CheckMapAgainstVisitPlan(job, own ? &*own : nullptr, plan->second, T_map_visit,
                                  evidence_text);
}

std::string PoseGraphWorker::CheckMapAgainstVisitPlan(const Job& job, const place::FloorPlan* own,
                                                      int64_t plan_visit, const Pose& T_map_visit,
                                                      std::string* evidence_text) {
  if (options_.layout_max_own_plan_share >= 1) return "";  // off: nothing to read
  if (own == nullptr) {
    absl::StrAppend(evidence_text, "; visit ", job.visit_id, " has no floor plan of its own yet");
    return "";
  }
  auto keyframes = store_->ListKeyframes(job.map_id, plan_visit);
  if (!keyframes.ok()) return "";
  std::vector<std::pair<int64_t, Pose>> placed = PosesOf(*keyframes);
  if (placed.empty()) return "";
  // Its plan may be partial (the visit is still under way): only the walls it saw count, and
  // the map's cameras may well stand where it has not been.
  place::LayoutCheckOptions seen;
  seen.seen_walls_only = true;
  LayoutEvidence evidence =
      CheckLayout(store_, job.map_id, SpreadForLayout(std::move(placed)),
                  T_map_visit.ToIsometry().inverse(), *own, &last_decoded_, seen);
  evidence.outside = 0;
  const std::string text = absl::StrCat("visit ", plan_visit, "'s keyframes in visit ",
                                        job.visit_id, "'s own floor plan: ", evidence.Text());
  absl::StrAppend(evidence_text, "; ", text);
  spdlog::info("visit {}: {}", job.visit_id, text);
  if (evidence.ThroughShare() <= options_.layout_max_own_plan_share) return "";
  return absl::StrCat("is contradicted by its own floor plan: ", text, " (allowed ",
                      absl::StrFormat("%.1f", 100 * options_.layout_max_own_plan_share),
                      " %, pose_graph.layout_max_own_plan_share)");
}

absl::StatusOr<Pose> PoseGraphWorker::Solve(int64_t map_id, int64_t visit_id,
                                            const std::vector<store::KeyframeRecord>& keyframes) {
  // The graph spans the latest run of the tracker (keyframes joined by its odometry).
  int64_t segment = 0;
  for (const auto& k : keyframes) {
    if (k.T_odom_camera && k.T_world_camera) segment = k.odom_segment;
  }
  std::vector<const store::KeyframeRecord*> nodes;
  std::map<int64_t, Pose> initial;
  for (const auto& k : keyframes) {
    if (!k.T_odom_camera || !k.T_world_camera || k.odom_segment != segment) continue;
    nodes.push_back(&k);
    initial[k.id] = *k.T_world_camera;
  }
  if (nodes.size() < 2) return absl::FailedPreconditionError("fewer than two tracked keyframes");
  std::vector<posegraph::Edge> edges;
  for (size_t i = 1; i < nodes.size(); ++i) edges.push_back(OdometryEdge(*nodes[i - 1], *nodes[i]));
  const int odometry_edges = static_cast<int>(edges.size());
  auto stored = store_->ListPoseEdges(map_id, visit_id);
  if (!stored.ok()) return stored.status();
  std::vector<int64_t> edge_ids;  // of the loop and tie edges, in the order given to the solve
  for (const auto& e : *stored) {
    if (!e.accepted || e.kind != store::StoredEdgeKind::kLoop) continue;
    if (!initial.count(e.from_keyframe) || !initial.count(e.to_keyframe)) continue;
    edges.push_back({e.from_keyframe, e.to_keyframe, e.T_from_to, posegraph::EdgeKind::kLoop,
                     kLoopSigmaM, kLoopSigmaRad});
    edge_ids.push_back(e.id);
  }
  // An anchored visit's anchor and ties join it to keyframes of other visits already in the
  // map's frame: those are held where they are (the map's frame is theirs; a later visit does
  // not bend what earlier ones built), and the visit's own first keyframe is free.
  std::set<int64_t> fixed;
  std::optional<std::vector<store::KeyframeRecord>> map_keyframes;  // read once, if needed
  for (const auto& e : *stored) {
    if (!e.accepted || e.kind != store::StoredEdgeKind::kAnchor) continue;
    if (!initial.count(e.to_keyframe) || initial.count(e.from_keyframe)) continue;
    if (!fixed.count(e.from_keyframe)) {
      if (!map_keyframes) {
        auto listed = KeyframesById(store_, map_id, 0);
        if (!listed.ok()) return listed.status();
        map_keyframes = *std::move(listed);
      }
      const store::KeyframeRecord* k = FindKeyframe(*map_keyframes, e.from_keyframe);
      if (k == nullptr || !k->T_world_camera) continue;  // deleted since
      initial[k->id] = *k->T_world_camera;
      fixed.insert(k->id);
    }
    edges.push_back({e.from_keyframe, e.to_keyframe, e.T_from_to, posegraph::EdgeKind::kAnchor,
                     kLoopSigmaM, kLoopSigmaRad});
    edge_ids.push_back(e.id);
  }
  if (fixed.empty()) fixed.insert(nodes.front()->id);
  posegraph::OptimiseOptions solve_options;
  auto solved = posegraph::Optimise(initial, edges, fixed, solve_options);
  if (!solved.ok()) return solved.status();
  // Only the visit's own keyframes are written.
  for (auto it = solved->poses.begin(); it != solved->poses.end();) {
    it = fixed.count(it->first) && it->first != nodes.front()->id ? solved->poses.erase(it)
                                                                  : std::next(it);
  }
  std::vector<int64_t> rejected;
  for (size_t i : solved->rejected) rejected.push_back(edge_ids[i - odometry_edges]);
  store::PoseOptimisationRecord record;
  record.map_id = map_id;
  record.visit_id = visit_id;
  record.created_time_s = NowSeconds();
  record.keyframes = static_cast<int>(nodes.size());
  record.odometry_edges = odometry_edges;
  record.loop_edges = static_cast<int>(edge_ids.size());
  record.loops_rejected = static_cast<int>(rejected.size());
  record.iterations = solved->iterations;
  record.initial_cost = solved->initial_cost;
  record.final_cost = solved->final_cost;
  record.solve_ms = solved->solve_ms;
  record.max_correction_m = solved->max_correction_m;
  // The newest solved keyframe says where the odometry frame now lies; frames tracked after it
  // follow.
  const store::KeyframeRecord& newest = *nodes.back();
  const Pose correction = Pose::FromIsometry(solved->poses.at(newest.id).ToIsometry() *
                                             newest.T_odom_camera->ToIsometry().inverse());
  auto id = store_->ApplyPoseOptimisation(
      record, solved->poses, rejected,
      absl::StrFormat("outvoted by the visit's other edges in a pose-graph solve (chi-square > "
                      "%.1f)",
                      solve_options.outlier_chi2),
      correction);
  if (!id.ok()) return id.status();
  spdlog::info(
      "visit {}: pose graph solved ({} keyframes, {} loop and anchor edges, {} rejected) in "
      "{:.1f} ms, largest correction {:.3f} m",
      visit_id, record.keyframes, record.loop_edges, record.loops_rejected, record.solve_ms,
      record.max_correction_m);
  absl::MutexLock lock(&mu_);
  ++stats_.solves;
  stats_.rejected_by_solve += record.loops_rejected;
  return correction;
}

}  // namespace lifemap::server
