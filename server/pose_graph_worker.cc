#include "server/pose_graph_worker.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <string>
#include <vector>

#include <spdlog/spdlog.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/posegraph/pose_graph.h"
#include "server/services.h"

namespace lifemap::server {
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
constexpr size_t kMaxPendingAnchors = 64;

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

}  // namespace

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
  const bool anchored = !job.anchors.empty() && ProcessAnchors(job, *query);

  int accepted = 0;
  for (const LoopCandidate& c : job.candidates) {
    store::PoseEdgeRecord edge;
    edge.map_id = job.map_id;
    edge.kind = store::StoredEdgeKind::kLoop;
    edge.from_keyframe = c.keyframe_id;
    edge.to_keyframe = query_id;
    edge.T_from_to = c.T_match_query;
    edge.inliers = c.inliers;
    edge.reprojection_px = c.reprojection_px;
    edge.created_time_s = NowSeconds();
    const store::KeyframeRecord* match = FindKeyframe(*keyframes, c.keyframe_id);
    const std::string weak = WeakMatchReason(c, options_);
    if (match == nullptr) {
      edge.reason = "the matched keyframe is not in this visit";
    } else if (!match->T_odom_camera || match->odom_segment != query->odom_segment) {
      edge.reason =
          "the matched keyframe was tracked by an earlier run of the tracker (the visit was "
          "resumed): no odometry joins them";
    } else if (!weak.empty()) {
      edge.reason = weak;
    } else {
      // The odometry's own idea of where the query is from the match, and the path between
      // them: the drift the odometry can have accumulated grows with it.
      double path_m = 0;
      for (auto it = keyframes->begin(); it != keyframes->end(); ++it) {
        if (it->id <= match->id || it->id > query_id) continue;
        const auto& prev = *(it - 1);
        if (it->T_odom_camera && prev.T_odom_camera) {
          path_m += (it->T_odom_camera->translation - prev.T_odom_camera->translation).norm();
        }
      }
      const Pose predicted = posegraph::Relative(*match->T_odom_camera, *query->T_odom_camera);
      const double off_m = (predicted.translation - c.T_match_query.translation).norm();
      const double off_deg = RotationAngleRad(predicted, c.T_match_query) * kRadToDeg;
      const double allow_m =
          options_.loop_max_disagreement_m + options_.loop_max_disagreement_per_m * path_m;
      const double allow_deg =
          options_.loop_max_disagreement_deg + options_.loop_max_disagreement_deg_per_m * path_m;
      if (off_m > allow_m || off_deg > allow_deg) {
        edge.reason = absl::StrFormat(
            "disagrees with the odometry by %.2f m / %.1f deg after %.1f m of path (allowed %.2f "
            "m / %.1f deg)",
            off_m, off_deg, path_m, allow_m, allow_deg);
      } else {
        edge.accepted = true;
        edge.reason =
            absl::StrFormat("%d inliers, %.2f px; odometry off by %.3f m / %.2f deg after %.1f m",
                            c.inliers, c.reprojection_px, off_m, off_deg, path_m);
      }
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
  if (accepted == 0) return;
  // An anchor just moved the visit's poses: the solve reads them again.
  if (anchored) keyframes = KeyframesById(store_, job.map_id, job.visit_id);
  if (!keyframes.ok()) return;
  auto correction = Solve(job.map_id, job.visit_id, *keyframes);
  if (!correction.ok()) {
    spdlog::warn("visit {}: pose graph not solved: {}", job.visit_id,
                 correction.status().ToString());
    return;
  }
  if (job.on_corrected) job.on_corrected(*correction);
}

bool PoseGraphWorker::ProcessAnchors(const Job& job, const store::KeyframeRecord& query) {
  auto visit = store_->GetVisit(job.visit_id);
  if (!visit.ok() || visit->anchor || !query.T_world_camera) return false;
  auto visits = store_->ListVisits(visit->map_name);
  if (!visits.ok() || visits->empty()) return false;
  // The map's frame is its first visit's.
  const int64_t root = visits->front().id;
  if (job.visit_id == root) return false;
  std::map<int64_t, const store::VisitRecord*> by_id;
  for (const auto& v : *visits) by_id[v.id] = &v;
  // The matched visits' keyframes (poses, no images), read once per visit.
  std::map<int64_t, std::vector<store::KeyframeRecord>> matched_visits;
  auto& pending = pending_anchors_[job.visit_id];
  for (const AnchorCandidate& c : job.anchors) {
    {
      absl::MutexLock lock(&mu_);
      ++stats_.anchor_candidates;
    }
    const LoopCandidate& m = c.match;
    if (!WeakMatchReason(m, options_).empty()) continue;
    auto it = by_id.find(c.visit_id);
    if (it == by_id.end() || c.visit_id == job.visit_id) continue;
    if (!matched_visits.count(c.visit_id)) {
      auto listed = KeyframesById(store_, job.map_id, c.visit_id);
      if (!listed.ok()) continue;
      matched_visits[c.visit_id] = *std::move(listed);
    }
    const store::KeyframeRecord* matched = FindKeyframe(matched_visits[c.visit_id], m.keyframe_id);
    if (matched == nullptr || !matched->T_world_camera) continue;
    // The matched visit's frame in the map's: the first visit's is the map's; an anchored one
    // says where it lies (its keyframes were moved into the map's frame when it was anchored);
    // client poses are in the map's frame already. A tracked visit not anchored yet is not.
    const bool in_map_frame = c.visit_id == root || it->second->anchor.has_value() ||
                              matched->pose_source == store::StoredPoseSource::kClient ||
                              matched->pose_source == store::StoredPoseSource::kRefined;
    if (!in_map_frame) continue;
    const Eigen::Isometry3d T_map_query =
        matched->T_world_camera->ToIsometry() * m.T_match_query.ToIsometry();
    AnchorEstimate estimate;
    estimate.query_keyframe = query.id;
    estimate.to_visit = c.visit_id;
    estimate.T_map_visit =
        Pose::FromIsometry(T_map_query * query.T_world_camera->ToIsometry().inverse());
    estimate.edge.map_id = job.map_id;
    estimate.edge.kind = store::StoredEdgeKind::kAnchor;
    estimate.edge.from_keyframe = m.keyframe_id;
    estimate.edge.to_keyframe = query.id;
    estimate.edge.T_from_to = m.T_match_query;
    estimate.edge.inliers = m.inliers;
    estimate.edge.reprojection_px = m.reprojection_px;
    estimate.edge.accepted = true;
    estimate.edge.created_time_s = NowSeconds();
    // Two matches from different keyframes of the visit must agree: one match can be an alias.
    for (const AnchorEstimate& other : pending) {
      if (other.query_keyframe == query.id) continue;
      const double off_m =
          (other.T_map_visit.translation - estimate.T_map_visit.translation).norm();
      const double off_deg = RotationAngleRad(other.T_map_visit, estimate.T_map_visit) * kRadToDeg;
      if (off_m > kAnchorAgreementM || off_deg > kAnchorAgreementDeg) continue;
      store::VisitAnchor anchor;
      anchor.to_visit_id = estimate.to_visit;
      anchor.T_map_visit = estimate.T_map_visit;
      anchor.residual_m = off_m;
      anchor.residual_deg = off_deg;
      anchor.anchored_time_s = NowSeconds();
      estimate.edge.reason = absl::StrFormat(
          "anchors visit %d to visit %d: agrees with keyframe %d's match within %.3f m / %.2f deg",
          job.visit_id, estimate.to_visit, other.query_keyframe, off_m, off_deg);
      if (auto s = store_->AnchorVisit(job.visit_id, estimate.edge, &anchor); !s.ok()) {
        spdlog::warn("visit {}: not anchored: {}", job.visit_id, s.ToString());
        return false;
      }
      spdlog::info("visit {} anchored to visit {} of map '{}' (residual {:.3f} m / {:.2f} deg)",
                   job.visit_id, anchor.to_visit_id, visit->map_name, off_m, off_deg);
      pending_anchors_.erase(job.visit_id);
      {
        absl::MutexLock lock(&mu_);
        ++stats_.anchors;
      }
      if (job.on_anchored) job.on_anchored(anchor.T_map_visit);
      return true;
    }
    if (pending.size() < kMaxPendingAnchors) pending.push_back(std::move(estimate));
  }
  return false;
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
  std::vector<int64_t> edge_ids;  // of the loop edges, in the order given to the solve
  for (const auto& e : *stored) {
    if (!e.accepted || e.kind != store::StoredEdgeKind::kLoop) continue;
    if (!initial.count(e.from_keyframe) || !initial.count(e.to_keyframe)) continue;
    edges.push_back({e.from_keyframe, e.to_keyframe, e.T_from_to, posegraph::EdgeKind::kLoop,
                     kLoopSigmaM, kLoopSigmaRad});
    edge_ids.push_back(e.id);
  }
  posegraph::OptimiseOptions solve_options;
  auto solved = posegraph::Optimise(initial, edges, {nodes.front()->id}, solve_options);
  if (!solved.ok()) return solved.status();
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
      "visit {}: pose graph solved ({} keyframes, {} loops, {} rejected) in {:.1f} ms, largest "
      "correction {:.3f} m",
      visit_id, record.keyframes, record.loop_edges, record.loops_rejected, record.solve_ms,
      record.max_correction_m);
  absl::MutexLock lock(&mu_);
  ++stats_.solves;
  stats_.rejected_by_solve += record.loops_rejected;
  return correction;
}

}  // namespace lifemap::server
