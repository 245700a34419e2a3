// Store: pose graphs (issue 15): loop and anchor edges, and the solves that rewrite keyframe
// poses.
#include <algorithm>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "server/store/store_impl.h"

namespace lifemap::store {

namespace {

// Inserts `e` on `db` (whose write lock the caller holds); returns its id.
absl::StatusOr<int64_t> InsertEdgeLocked(Database* db, const PoseEdgeRecord& e) {
  auto id = ReserveRowIds(db, "pose_edges");
  if (!id.ok()) return id.status();
  auto stmt = db->Prepare(
      "INSERT INTO pose_edges (map_id, kind, from_keyframe, to_keyframe, tx, ty, tz, qx, qy, qz, "
      "qw, inliers, reprojection_px, accepted, reason, created_time_s, id) VALUES (?1, ?2, ?3, "
      "?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15, ?16, ?17)");
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  BindRowId(&*s, 17, *id);
  s->Bind(1, e.map_id).Bind(2, static_cast<int64_t>(e.kind));
  s->Bind(3, e.from_keyframe).Bind(4, e.to_keyframe);
  BindPose(&*s, 5, e.T_from_to);
  s->Bind(12, int64_t{e.inliers}).Bind(13, e.reprojection_px);
  s->Bind(14, int64_t{e.accepted}).Bind(15, e.reason).Bind(16, e.created_time_s);
  if (auto st = s->Run(); !st.ok()) {
    // The only constraints that can fail are the foreign keys: a keyframe or the map is gone.
    if (IsConstraintViolation(st)) {
      return absl::NotFoundError(absl::StrCat("keyframe ", e.from_keyframe, " or ", e.to_keyframe,
                                              " (or map ", e.map_id,
                                              ") no longer exists; edge not stored"));
    }
    return st;
  }
  return db->LastInsertRowId();
}

// The rows of `select` (bound; its columns: a keyframe id, then a pose's seven), each pose moved
// by `T` (T * pose).
absl::StatusOr<std::vector<std::pair<int64_t, Pose>>> MovedPoses(Statement* select, const Pose& T) {
  std::vector<std::pair<int64_t, Pose>> moved;
  for (;;) {
    auto row = select->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    moved.push_back({select->ColumnInt(0),
                     Pose::FromIsometry(T.ToIsometry() * ReadPose(*select, 1).ToIsometry())});
  }
  return moved;
}

// Moves visit `visit_id`'s posed keyframes by `T` (T * pose), on `db` within the caller's
// transaction.
absl::Status MoveVisitKeyframesLocked(Database* db, int64_t visit_id, const Pose& T) {
  absl::StatusOr<std::vector<std::pair<int64_t, Pose>>> moved;
  {
    auto posed = db->Prepare(
        "SELECT id, tx, ty, tz, qx, qy, qz, qw FROM keyframes WHERE visit_id = ?1 AND "
        "has_pose = 1");
    if (!posed.ok()) return posed.status();
    StatementScope s(*posed);
    s->Bind(1, visit_id);
    moved = MovedPoses(&*s, T);
  }
  if (!moved.ok()) return moved.status();
  auto move = db->Prepare(
      "UPDATE keyframes SET tx = ?1, ty = ?2, tz = ?3, qx = ?4, qy = ?5, qz = ?6, qw = ?7 WHERE "
      "id = ?8");
  if (!move.ok()) return move.status();
  for (const auto& [id, pose] : *moved) {
    StatementScope s(*move);
    BindPose(&*s, 1, pose);
    s->Bind(8, id);
    if (auto st = s->Run(); !st.ok()) return st;
  }
  return absl::OkStatus();
}

absl::Status AppendAnchorHistoryLocked(Database* db, int64_t visit_id, const VisitAnchor& anchor,
                                       const char* action, const std::string& reason);

// Writes `anchor` into the visit's row and appends `action` to its history, on `db` within the
// caller's transaction.
absl::Status RecordAnchorLocked(Database* db, int64_t visit_id, const VisitAnchor& anchor,
                                const char* action, const std::string& reason) {
  auto update = db->Prepare(
      "UPDATE visits SET anchor_visit_id = ?1, anchor_edge_id = ?2, map_tx = ?3, map_ty = ?4, "
      "map_tz = ?5, map_qx = ?6, map_qy = ?7, map_qz = ?8, map_qw = ?9, anchor_residual_m = ?10, "
      "anchor_residual_deg = ?11, anchored_time_s = ?12 WHERE id = ?13");
  if (!update.ok()) return update.status();
  {
    StatementScope s(*update);
    s->Bind(1, anchor.to_visit_id).Bind(2, anchor.edge_id);
    BindPose(&*s, 3, anchor.T_map_visit);
    s->Bind(10, anchor.residual_m).Bind(11, anchor.residual_deg);
    s->Bind(12, anchor.anchored_time_s).Bind(13, visit_id);
    if (auto st = s->Run(); !st.ok()) return st;
  }
  return AppendAnchorHistoryLocked(db, visit_id, anchor, action, reason);
}

// Appends `action` on `anchor` (its time, visit, edge and pose) to the visit's anchor history,
// on `db` within the caller's transaction.
absl::Status AppendAnchorHistoryLocked(Database* db, int64_t visit_id, const VisitAnchor& anchor,
                                       const char* action, const std::string& reason) {
  auto id = ReserveRowIds(db, "anchor_revisions");
  if (!id.ok()) return id.status();
  auto history = db->Prepare(
      "INSERT INTO anchor_revisions (visit_id, time_s, action, to_visit_id, edge_id, map_tx, "
      "map_ty, map_tz, map_qx, map_qy, map_qz, map_qw, reason, id) VALUES (?1, ?2, ?3, ?4, ?5, "
      "?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14)");
  if (!history.ok()) return history.status();
  StatementScope s(*history);
  BindRowId(&*s, 14, *id);
  s->Bind(1, visit_id).Bind(2, anchor.anchored_time_s).Bind(3, std::string(action));
  s->Bind(4, anchor.to_visit_id).Bind(5, anchor.edge_id);
  BindPose(&*s, 6, anchor.T_map_visit);
  s->Bind(13, reason);
  return s->Run();
}

// Marks the visit's accepted anchor and tie edges (kind anchor) rejected, `prefix` put before
// their reason, on `db` within the caller's transaction.
absl::Status SupersedeAnchorEdgesLocked(Database* db, int64_t visit_id, const std::string& prefix) {
  auto supersede = db->Prepare(
      "UPDATE pose_edges SET accepted = 0, reason = ?1 || reason WHERE kind = ?2 AND "
      "accepted = 1 AND to_keyframe IN (SELECT id FROM keyframes WHERE visit_id = ?3)");
  if (!supersede.ok()) return supersede.status();
  StatementScope s(*supersede);
  s->Bind(1, prefix);
  s->Bind(2, static_cast<int64_t>(StoredEdgeKind::kAnchor)).Bind(3, visit_id);
  return s->Run();
}

// The visit `visit_id`'s anchor column: NOT_FOUND for no such visit; nullopt when unanchored.
absl::StatusOr<std::optional<int64_t>> AnchoredToLocked(Database* db, int64_t visit_id) {
  auto check = db->Prepare("SELECT anchor_visit_id FROM visits WHERE id = ?1");
  if (!check.ok()) return check.status();
  StatementScope s(*check);
  s->Bind(1, visit_id);
  auto row = s->Step();
  if (!row.ok()) return row.status();
  if (!*row) return absl::NotFoundError(absl::StrCat("visit ", visit_id, " does not exist"));
  if (s->ColumnIsNull(0)) return std::optional<int64_t>();
  return std::optional<int64_t>(s->ColumnInt(0));
}

}  // namespace

absl::StatusOr<int64_t> Store::InsertPoseEdge(const PoseEdgeRecord& e) {
  absl::MutexLock lock(&impl_->write_mu);
  return InsertEdgeLocked(impl_->write_db.get(), e);
}

absl::Status Store::AnchorVisit(int64_t visit_id, const PoseEdgeRecord& edge, VisitAnchor* anchor) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  Transaction tx(db);
  if (auto s = tx.Begin(); !s.ok()) return s;
  auto anchored_to = AnchoredToLocked(db, visit_id);
  if (!anchored_to.ok()) return anchored_to.status();
  if (*anchored_to) {
    return absl::FailedPreconditionError(
        absl::StrCat("visit ", visit_id, " is anchored already (to visit ", **anchored_to, ")"));
  }
  auto edge_id = InsertEdgeLocked(db, edge);
  if (!edge_id.ok()) return edge_id.status();
  anchor->edge_id = *edge_id;
  if (auto s = RecordAnchorLocked(db, visit_id, *anchor, "anchored", edge.reason); !s.ok()) {
    return s;
  }
  // The visit's keyframes move into the map's frame.
  if (auto s = MoveVisitKeyframesLocked(db, visit_id, anchor->T_map_visit); !s.ok()) return s;
  return tx.Commit();
}

absl::Status Store::ReviseAnchor(int64_t visit_id, const Pose& T_moved_by,
                                 const std::vector<PoseEdgeRecord>& edges,
                                 const std::string& reason, VisitAnchor* anchor) {
  if (edges.empty()) {
    return absl::InvalidArgumentError("an anchor revision needs the matches it rests on");
  }
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  Transaction tx(db);
  if (auto s = tx.Begin(); !s.ok()) return s;
  auto anchored_to = AnchoredToLocked(db, visit_id);
  if (!anchored_to.ok()) return anchored_to.status();
  if (!*anchored_to) {
    return absl::FailedPreconditionError(
        absl::StrCat("visit ", visit_id, " is not anchored: there is no anchor to revise"));
  }
  if (auto s = SupersedeAnchorEdgesLocked(
          db, visit_id, absl::StrCat("superseded by anchor revision (", reason, "): "));
      !s.ok()) {
    return s;
  }
  for (size_t i = 0; i < edges.size(); ++i) {
    auto id = InsertEdgeLocked(db, edges[i]);
    if (!id.ok()) return id.status();
    if (i == 0) anchor->edge_id = *id;
  }
  if (auto s = RecordAnchorLocked(db, visit_id, *anchor, "revised", reason); !s.ok()) return s;
  if (auto s = MoveVisitKeyframesLocked(db, visit_id, T_moved_by); !s.ok()) return s;
  return tx.Commit();
}

absl::StatusOr<Pose> Store::DropAnchor(int64_t visit_id, const std::string& reason, double time_s) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  Transaction tx(db);
  if (auto s = tx.Begin(); !s.ok()) return s;
  auto visit = impl_->GetVisitLocked(db, visit_id);
  if (!visit.ok()) return visit.status();
  if (!visit->anchor) {
    return absl::FailedPreconditionError(
        absl::StrCat("visit ", visit_id, " is not anchored: there is no anchor to drop"));
  }
  const VisitAnchor dropped = *visit->anchor;
  if (auto s =
          SupersedeAnchorEdgesLocked(db, visit_id, absl::StrCat("anchor dropped (", reason, "): "));
      !s.ok()) {
    return s;
  }
  {
    auto clear = db->Prepare(
        "UPDATE visits SET anchor_visit_id = NULL, anchor_edge_id = NULL, map_tx = NULL, map_ty = "
        "NULL, map_tz = NULL, map_qx = NULL, map_qy = NULL, map_qz = NULL, map_qw = NULL, "
        "anchor_residual_m = NULL, anchor_residual_deg = NULL, anchored_time_s = NULL WHERE id = "
        "?1");
    if (!clear.ok()) return clear.status();
    StatementScope s(*clear);
    s->Bind(1, visit_id);
    if (auto st = s->Run(); !st.ok()) return st;
  }
  VisitAnchor history = dropped;
  history.anchored_time_s = time_s;
  if (auto s = AppendAnchorHistoryLocked(db, visit_id, history, "dropped", reason); !s.ok()) {
    return s;
  }
  if (auto s = MoveVisitKeyframesLocked(
          db, visit_id, Pose::FromIsometry(dropped.T_map_visit.ToIsometry().inverse()));
      !s.ok()) {
    return s;
  }
  if (auto s = tx.Commit(); !s.ok()) return s;
  return dropped.T_map_visit;
}

absl::StatusOr<std::vector<AnchorRevision>> Store::ListAnchorRevisions(int64_t visit_id) {
  absl::MutexLock lock(&impl_->read_mu);
  auto stmt = impl_->read_db->Prepare(
      "SELECT id, visit_id, time_s, action, to_visit_id, COALESCE(edge_id, 0), map_tx, map_ty, "
      "map_tz, map_qx, map_qy, map_qz, map_qw, reason FROM anchor_revisions WHERE visit_id = ?1 "
      "ORDER BY id");
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, visit_id);
  std::vector<AnchorRevision> out;
  for (;;) {
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    AnchorRevision r;
    r.id = s->ColumnInt(0);
    r.visit_id = s->ColumnInt(1);
    r.time_s = s->ColumnDouble(2);
    r.action = s->ColumnText(3);
    r.to_visit_id = s->ColumnInt(4);
    r.edge_id = s->ColumnInt(5);
    r.T_map_visit = ReadPose(*s, 6);
    r.reason = s->ColumnText(13);
    out.push_back(std::move(r));
  }
  return out;
}

absl::StatusOr<std::vector<PoseEdgeRecord>> Store::ListPoseEdges(int64_t map_id, int64_t visit_id) {
  absl::MutexLock lock(&impl_->read_mu);
  auto stmt = impl_->read_db->Prepare(
      "SELECT e.id, e.map_id, e.kind, e.from_keyframe, e.to_keyframe, e.tx, e.ty, e.tz, e.qx, "
      "e.qy, e.qz, e.qw, e.inliers, e.reprojection_px, e.accepted, e.reason, e.created_time_s "
      "FROM pose_edges e JOIN keyframes k ON k.id = e.to_keyframe WHERE e.map_id = ?1 AND "
      "(?2 = 0 OR k.visit_id = ?2) ORDER BY e.id");
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, map_id).Bind(2, visit_id);
  std::vector<PoseEdgeRecord> out;
  for (;;) {
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    PoseEdgeRecord e;
    e.id = s->ColumnInt(0);
    e.map_id = s->ColumnInt(1);
    e.kind = static_cast<StoredEdgeKind>(s->ColumnInt(2));
    e.from_keyframe = s->ColumnInt(3);
    e.to_keyframe = s->ColumnInt(4);
    e.T_from_to = ReadPose(*s, 5);
    e.inliers = static_cast<int>(s->ColumnInt(12));
    e.reprojection_px = s->ColumnDouble(13);
    e.accepted = s->ColumnInt(14) != 0;
    e.reason = s->ColumnText(15);
    e.created_time_s = s->ColumnDouble(16);
    out.push_back(std::move(e));
  }
  return out;
}

absl::StatusOr<int64_t> Store::ApplyPoseOptimisation(PoseOptimisationRecord r,
                                                     const std::map<int64_t, Pose>& poses,
                                                     const std::vector<int64_t>& rejected,
                                                     const std::string& reject_reason,
                                                     const Pose& later_correction) {
  absl::MutexLock lock(&impl_->write_mu);
  Database* db = impl_->write_db.get();
  Transaction tx(db);
  if (auto s = tx.Begin(); !s.ok()) return s;
  {
    auto id = ReserveRowIds(db, "pose_optimisations");
    if (!id.ok()) return id.status();
    auto stmt = db->Prepare(
        "INSERT INTO pose_optimisations (map_id, visit_id, created_time_s, keyframes, "
        "odometry_edges, loop_edges, loops_rejected, iterations, initial_cost, final_cost, "
        "solve_ms, max_correction_m, id) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, "
        "?12, ?13)");
    if (!stmt.ok()) return stmt.status();
    StatementScope s(*stmt);
    BindRowId(&*s, 13, *id);
    s->Bind(1, r.map_id).Bind(2, r.visit_id).Bind(3, r.created_time_s);
    s->Bind(4, int64_t{r.keyframes}).Bind(5, int64_t{r.odometry_edges});
    s->Bind(6, int64_t{r.loop_edges}).Bind(7, int64_t{r.loops_rejected});
    s->Bind(8, int64_t{r.iterations}).Bind(9, r.initial_cost).Bind(10, r.final_cost);
    s->Bind(11, r.solve_ms).Bind(12, r.max_correction_m);
    if (auto st = s->Run(); !st.ok()) {
      if (IsConstraintViolation(st)) {
        return absl::NotFoundError(absl::StrCat("map ", r.map_id, " no longer exists"));
      }
      return st;
    }
  }
  r.id = db->LastInsertRowId();
  auto update = db->Prepare(
      "UPDATE keyframes SET tx = ?1, ty = ?2, tz = ?3, qx = ?4, qy = ?5, qz = ?6, qw = ?7, "
      "optimisation_id = ?8 WHERE id = ?9");
  if (!update.ok()) return update.status();
  int64_t newest = 0;
  for (const auto& [id, pose] : poses) {
    StatementScope s(*update);
    BindPose(&*s, 1, pose);
    s->Bind(8, r.id).Bind(9, id);
    if (auto st = s->Run(); !st.ok()) return st;
    newest = std::max(newest, id);
  }
  // Keyframes tracked while the graph was solved follow the newest solved one.
  {
    auto later = db->Prepare(
        "SELECT id, odom_tx, odom_ty, odom_tz, odom_qx, odom_qy, odom_qz, odom_qw FROM "
        "keyframes WHERE visit_id = ?1 AND id > ?2 AND odom_tx IS NOT NULL");
    if (!later.ok()) return later.status();
    absl::StatusOr<std::vector<std::pair<int64_t, Pose>>> moved;
    {
      StatementScope s(*later);
      s->Bind(1, r.visit_id).Bind(2, newest);
      moved = MovedPoses(&*s, later_correction);
    }
    if (!moved.ok()) return moved.status();
    for (const auto& [id, pose] : *moved) {
      StatementScope s(*update);
      BindPose(&*s, 1, pose);
      s->Bind(8, r.id).Bind(9, id);
      if (auto st = s->Run(); !st.ok()) return st;
    }
  }
  if (!rejected.empty()) {
    auto reject = db->Prepare("UPDATE pose_edges SET accepted = 0, reason = ?1 WHERE id = ?2");
    if (!reject.ok()) return reject.status();
    for (int64_t id : rejected) {
      StatementScope s(*reject);
      s->Bind(1, reject_reason).Bind(2, id);
      if (auto st = s->Run(); !st.ok()) return st;
    }
  }
  if (auto s = tx.Commit(); !s.ok()) return s;
  return r.id;
}

absl::StatusOr<std::vector<PoseOptimisationRecord>> Store::ListPoseOptimisations(int64_t map_id,
                                                                                 int64_t visit_id) {
  absl::MutexLock lock(&impl_->read_mu);
  auto stmt = impl_->read_db->Prepare(
      "SELECT id, map_id, visit_id, created_time_s, keyframes, odometry_edges, loop_edges, "
      "loops_rejected, iterations, initial_cost, final_cost, solve_ms, max_correction_m FROM "
      "pose_optimisations WHERE map_id = ?1 AND (?2 = 0 OR visit_id = ?2) ORDER BY id");
  if (!stmt.ok()) return stmt.status();
  StatementScope s(*stmt);
  s->Bind(1, map_id).Bind(2, visit_id);
  std::vector<PoseOptimisationRecord> out;
  for (;;) {
    auto row = s->Step();
    if (!row.ok()) return row.status();
    if (!*row) break;
    PoseOptimisationRecord r;
    r.id = s->ColumnInt(0);
    r.map_id = s->ColumnInt(1);
    r.visit_id = s->ColumnInt(2);
    r.created_time_s = s->ColumnDouble(3);
    r.keyframes = static_cast<int>(s->ColumnInt(4));
    r.odometry_edges = static_cast<int>(s->ColumnInt(5));
    r.loop_edges = static_cast<int>(s->ColumnInt(6));
    r.loops_rejected = static_cast<int>(s->ColumnInt(7));
    r.iterations = static_cast<int>(s->ColumnInt(8));
    r.initial_cost = s->ColumnDouble(9);
    r.final_cost = s->ColumnDouble(10);
    r.solve_ms = s->ColumnDouble(11);
    r.max_correction_m = s->ColumnDouble(12);
    out.push_back(r);
  }
  return out;
}

}  // namespace lifemap::store
