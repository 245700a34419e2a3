// Loop closure and the pose graph of tracked visits (issue 15), off the reply path.
//
// A keyframe of a tracked visit is queried against the appearance index like every keyframe;
// its verified matches to earlier keyframes of the same visit are loop candidates. This worker
// takes them once the keyframe is committed, checks each one (stricter PnP figures than a place
// match, and agreement with the odometry up to the drift it can have accumulated), stores it as
// an accepted or rejected edge with the reason, and when one is accepted solves the visit's
// pose graph (core/posegraph: odometry edges between consecutive keyframes, every accepted
// loop, the visit's first keyframe fixed), writing the corrected keyframe poses and the solve's
// record in one transaction. The visit's later frames are then reported in the corrected frame.
#pragma once

#include <cstdint>
#include <deque>
#include <functional>
#include <future>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "core/common/types.h"
#include "server/engine/options.h"
#include "server/store/store.h"

namespace lifemap::place {
struct FloorPlan;
}  // namespace lifemap::place
namespace lifemap::appearance {
struct AppearanceMatch;
struct Recognition;
}  // namespace lifemap::appearance

namespace lifemap::server {

struct DecodedKeyframe;  // a keyframe's depth, decoded for a floor-plan check

// A verified appearance match of a keyframe to an earlier keyframe of its visit.
struct LoopCandidate {
  int64_t keyframe_id = 0;  // the matched keyframe
  Pose T_match_query;       // the querying camera in the matched camera's frame
  int inliers = 0;
  double reprojection_px = 0;
};

// Why a match's PnP figures are too weak for a loop, an anchor or a relocalisation
// (`loop_min_inliers`, `loop_max_reprojection_px`); empty when they are not.
std::string WeakMatchReason(const LoopCandidate& c, const PoseGraphOptions& options);

// A verified appearance match of a tracked keyframe to a keyframe of another visit of its map:
// an anchor candidate.
struct AnchorCandidate {
  int64_t visit_id = 0;  // the matched keyframe's visit
  LoopCandidate match;
};

// A verified appearance match as a loop candidate (its matched keyframe and PnP figures).
LoopCandidate LoopCandidateOf(const appearance::AppearanceMatch& m);
// The verified matches of `recognition` to keyframes of other visits of map `map_id` than
// `visit_id`: anchor candidates for that visit.
std::vector<AnchorCandidate> AnchorCandidatesOf(const appearance::Recognition& recognition,
                                                int64_t map_id, int64_t visit_id);

// What the worker counted since it started (all visits), for logs and tests.
struct LoopClosureStats {
  int64_t candidates = 0;
  int64_t accepted = 0;
  int64_t rejected = 0;
  int64_t solves = 0;
  int64_t rejected_by_solve = 0;   // accepted, then outvoted by the others in a solve
  int64_t rejected_by_layout = 0;  // loops whose placed query disagreed with the floor plan
  int64_t anchor_candidates = 0;
  int64_t anchors = 0;           // visits anchored
  int64_t anchors_rejected = 0;  // agreeing matches whose placed visit disagreed with the plan
  int64_t ties = 0;              // edges tying an anchored visit to other visits of its map
  int64_t ties_rejected = 0;
  int64_t anchors_revised = 0;  // anchors moved by later matches that outvoted them
  int64_t anchors_dropped = 0;  // anchors the visit's later keyframes contradicted (RecheckAnchor)
  // Keyframes whose anchor candidates were not judged: their visit's own tracking lost more
  // than PoseGraphOptions::anchor_max_lost_share of its frames.
  int64_t anchors_held = 0;
};

// Why a visit's own tracking is too broken to anchor it or to anchor another visit to it
// (issue 35): more than `max_lost_share` of its frames were lost (judged from 20 frames on),
// so its keyframes are not one rigid body. Empty when it is not.
std::string BrokenTracking(const store::VisitRecord& visit, double max_lost_share);

// The same, or (issue 54) a visit the server tracked whose stored floor plan says its floor tilts
// or rises from keyframe to keyframe beyond pose_graph.anchor_max_floor_tilt_deg /
// anchor_max_floor_offset_m: its track is bent. Empty when neither.
std::string UnanchorableTrack(store::Store* store, const store::VisitRecord& visit,
                              const PoseGraphOptions& options);

// Thread-safe.
class PoseGraphWorker {
  struct AnchorState;

 public:
  PoseGraphWorker(store::Store* store, PoseGraphOptions options);
  // Finishes every queued job, then stops.
  ~PoseGraphWorker();
  PoseGraphWorker(const PoseGraphWorker&) = delete;
  PoseGraphWorker& operator=(const PoseGraphWorker&) = delete;

  struct Job {
    int64_t map_id = 0;
    int64_t visit_id = 0;
    // The querying keyframe's id once committed (the job is dropped if it is not).
    std::shared_future<absl::StatusOr<int64_t>> committed;
    std::vector<LoopCandidate> candidates;
    std::vector<AnchorCandidate> anchors;
    // The visit has ended (an anchor retry, anchor_retry.h, or `plan_at_end`): the floor-plan
    // check of an anchor does not wait for more keyframes than it has, and its own floor plan is
    // final, so the two plans are compared (PoseGraphOptions::layout_max_plan_on_floor_share).
    bool visit_ended = false;
    // Set by Engine::EndVisit for a visit anchored when it ends: its final floor plan, in the
    // frame its stored keyframes are in now (ArchitectureWorker::PlanAtEnd). The job carries no
    // keyframe (`committed` is not read): its anchor is re-checked once more with every keyframe
    // and this plan (RecheckAnchor), and dropped where they disagree.
    std::shared_ptr<const place::FloorPlan> plan_at_end;
    // A dry run (`lifemap visits anchor --dry-run`): the anchor candidates are judged as
    // always, against a state of the dry run's own (kept across its jobs), but nothing is
    // stored, anchored or counted; each candidate's verdict is appended to `verdicts`. Shared
    // by the dry run's jobs; read only after Wait.
    struct DryRun {
      std::vector<std::string> verdicts;
      // The first verdict that would have anchored the visit, when one would.
      std::optional<std::string> would_anchor;
      std::shared_ptr<AnchorState> state;  // the worker's
    };
    std::shared_ptr<DryRun> dry_run;
    // Called on the worker's thread after a solve with the visit's new correction
    // (T_world_odom: its odometry frame in its corrected frame).
    std::function<void(const Pose&)> on_corrected;
    // Called on the worker's thread once the visit is anchored, its anchor revised or dropped,
    // with the transform its stored keyframes were moved by (left-multiplied; later frames must
    // be too) and its T_map_visit now (its frame in the map's; nullopt once dropped). On the
    // first anchor the two are equal; on a drop `moved_by` is the old T_map_visit⁻¹.
    std::function<void(const Pose& moved_by, const std::optional<Pose>& T_map_visit)> on_anchored;
  };
  // Queues a job; returns its ticket for Wait().
  uint64_t Submit(Job job);
  // Blocks until the job with `ticket` (and every one before it) is done.
  void Wait(uint64_t ticket);
  // The ticket of the last job submitted (0: none yet).
  uint64_t last_ticket() const;

  LoopClosureStats Stats() const;
  const PoseGraphOptions& options() const { return options_; }

 private:
  void Run();
  void Process(Job job);
  // Solves the visit's graph over `keyframes` (the visit's, by id, as stored now) and stores the
  // result; returns the new correction.
  absl::StatusOr<Pose> Solve(int64_t map_id, int64_t visit_id,
                             const std::vector<store::KeyframeRecord>& keyframes);
  // Anchors the visit once two of its keyframes' matches agree on where it lies in the map;
  // true when it did (the visit's stored poses moved).
  bool ProcessAnchors(const Job& job, const store::VisitRecord& visit,
                      const store::KeyframeRecord& query,
                      const std::vector<store::KeyframeRecord>& visit_keyframes);
  // An anchored visit's matches to other visits in the map's frame, checked like loops (against
  // both visits' stored poses) and stored as edges that tie the visit to them in its solves;
  // returns how many were accepted. Those that disagree with the map's poses are kept as
  // dissent against the anchor, which they may revise (ReviseAnchor).
  int ProcessTies(const Job& job, const store::KeyframeRecord& query,
                  const std::vector<store::KeyframeRecord>& visit_keyframes);
  // Revises the visit's anchor when its dissent outvotes it (PoseGraphOptions::
  // anchor_revision_min_matches); how many matches the new anchor rests on (0: not revised).
  int ReviseAnchor(const Job& job, const store::VisitRecord& visit,
                   const std::vector<store::KeyframeRecord>& visit_keyframes);
  // Re-checks an anchored visit and drops its anchor (Store::DropAnchor) when its own tracking
  // has lost more than PoseGraphOptions::anchor_max_lost_share of its frames since, when the
  // visit it is anchored to is no longer in the map's frame (its anchor was dropped), or when
  // RecheckPlan says its keyframes disagree with the floor plan. True when dropped. At the
  // visit's end (Job::plan_at_end) it is re-checked whatever the number of keyframes.
  bool RecheckAnchor(const Job& job, const store::VisitRecord& visit,
                     const std::vector<store::KeyframeRecord>& visit_keyframes);
  // After `dropped`'s anchor was dropped: the ended visits anchored to it lose theirs too (and
  // theirs, in turn), since their placement rested on its poses. Open ones are dropped at their
  // next keyframe (RecheckAnchor), where their frame path is told.
  void DropDependents(const store::VisitRecord& dropped);
  // Each time an anchored visit's posed keyframes have doubled since the last check, and at its
  // end: why they disagree with the floor plan of `to_visit`, the visit it is anchored to (and
  // with the map's first visit's), or nullopt. An anchor accepted on 7 keyframes can be
  // contradicted by the next 10 (RESULTS.md, building seed 12).
  std::optional<std::string> RecheckPlan(const Job& job, const store::VisitRecord& visit,
                                         const store::VisitRecord& to_visit,
                                         const std::vector<store::KeyframeRecord>& visit_keyframes);
  // Judges a verified match of the query to `match` into `edge` (accepted, or the reason not):
  // its PnP figures; agreement with `predicted` (the query in the match's frame by `poses`: the
  // odometry, or the map's stored poses) up to the drift allowed over `path_m`; and, where
  // `plan` (the matched visit's floor plan, else its map's first visit's; or null) exists, the
  // query placed by the match against it.
  enum class Verdict { kWeak, kDisagrees, kLayout, kAccepted };
  Verdict Judge(const LoopCandidate& c, const Pose& predicted, double path_m, const char* poses,
                const store::KeyframeRecord& match, const place::FloorPlan* plan,
                store::PoseEdgeRecord* edge);
  // The architecture check of an anchor: the visit's keyframes placed by `T_map_visit` against
  // `to_visit`'s floor plan. Why they disagree (empty when they do not, or when there is no plan
  // to check; nullopt while the visit has too few keyframes to tell); `evidence_text` says what
  // was seen, and `plan_visit` (when given) whose plan it was (0: none). The share of readings
  // allowed beyond the walls is `max_through_share`, else
  // PoseGraphOptions::layout_max_through_share. Where they agree and the visit has a plan of its
  // own, the two plans are compared (place::ComparePlans both ways, in the evidence; once the
  // visit has ended, refused above PoseGraphOptions::layout_max_plan_on_floor_share: a plan under
  // way is partial), and the converse is checked too (CheckMapAgainstVisitPlan). Its own plan is
  // Job::plan_at_end where given, else the stored one.
  std::optional<std::string> CheckAnchorLayout(
      const Job& job, const store::VisitRecord& to_visit, const Pose& T_map_visit,
      const std::vector<store::KeyframeRecord>& visit_keyframes, std::string* evidence_text,
      std::optional<double> max_through_share = std::nullopt, int64_t* plan_visit = nullptr);
  // The converse, once the visit has a floor plan of its own (`own`, in the frame its keyframes
  // are in now; null: none yet, nothing checked; issue 54): the keyframes of `plan_visit` (in the
  // map's frame) placed in it by T_map_visit⁻¹, against the walls it saw. An L room's visit
  // anchored into a rectangular room's map sees nothing beyond the rectangle, but the rectangle's
  // views pass through the L's inner walls. Why they disagree, or empty; appends to
  // `evidence_text`. The share allowed is PoseGraphOptions::layout_max_own_plan_share (1: off,
  // nothing read).
  std::string CheckMapAgainstVisitPlan(const Job& job, const place::FloorPlan* own,
                                       int64_t plan_visit, const Pose& T_map_visit,
                                       std::string* evidence_text);

  // Where an unanchored visit would lie in the map's frame, by one match (worker thread only).
  struct AnchorEstimate {
    int64_t query_keyframe = 0;
    int64_t to_visit = 0;
    store::PoseEdgeRecord edge;
    Pose T_map_visit;
  };
  // What the worker holds of one visit's anchoring between its keyframes (worker thread only;
  // lost on restart).
  struct AnchorState {
    // Unanchored: where its keyframes' matches would put it, until two agree.
    std::vector<AnchorEstimate> pending;
    // Anchored: its matches that disagree with the anchor, each with the correction it asks for
    // (in `T_map_visit`: the transform that would move the visit's keyframes where the match
    // puts them), and how many matches support the anchor as it is (its own two, then every
    // tie accepted since; the revision's votes after a revision).
    std::vector<AnchorEstimate> dissent;
    int support = 2;
    // Where the floor-plan check refused to place the visit (T_map_visit), and the corrections
    // it refused a revision for: a later estimate close to one of them (kRefusedAgreementM /
    // Deg) is refused too. More keyframes of the same visit seeing the same alias do not make it
    // right: on the building world an L room's visit refused 6 times (5.8-14.7 % of its
    // readings beyond the walls) passed at the 7th with 24 keyframes (2.6 %).
    std::vector<Pose> refused_anchors;
    std::vector<Pose> refused_revisions;
    // Anchored: how many posed keyframes the visit had when its placement was last checked
    // against the floor plan (0: not in this run; the next job sets it).
    size_t checked_keyframes = 0;
  };
  std::map<int64_t, AnchorState> anchoring_;  // by visit id
  // The last keyframe decoded for a floor-plan check (worker thread only): a keyframe's loop and
  // tie candidates are checked one after another.
  std::unique_ptr<DecodedKeyframe> last_decoded_;

  store::Store* const store_;
  const PoseGraphOptions options_;
  mutable absl::Mutex mu_;
  std::deque<std::pair<uint64_t, Job>> queue_ ABSL_GUARDED_BY(mu_);
  uint64_t submitted_ ABSL_GUARDED_BY(mu_) = 0;
  uint64_t done_ ABSL_GUARDED_BY(mu_) = 0;
  bool stopping_ ABSL_GUARDED_BY(mu_) = false;
  LoopClosureStats stats_ ABSL_GUARDED_BY(mu_);
  std::thread thread_;
};

}  // namespace lifemap::server
