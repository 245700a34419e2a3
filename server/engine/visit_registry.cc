#include "server/engine/visit_registry.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <vector>

#include "absl/strings/str_cat.h"
#include "spdlog/spdlog.h"

namespace lifemap::server {

void VisitPath::Advance(const Eigen::Vector3d& position_m) {
  if (last_position_) travelled_m_ += (position_m - *last_position_).norm();
  last_position_ = position_m;
}

void VisitPath::MarkKeyframe(double timestamp_s) {
  if (!keyframes_.empty() && !(timestamp_s > keyframes_.back().first)) return;
  keyframes_.emplace_back(timestamp_s, travelled_m_);
}

std::optional<double> VisitPath::SinceKeyframe(double timestamp_s) const {
  // Timestamps come back from the store as they were given: equal, up to a microsecond.
  auto it = std::lower_bound(keyframes_.begin(), keyframes_.end(),
                             std::make_pair(timestamp_s - 1e-6, -1.0));
  if (it == keyframes_.end() || std::abs(it->first - timestamp_s) > 1e-6) return std::nullopt;
  return travelled_m_ - it->second;
}

absl::Status VisitState::CheckWritable(uint64_t stream) const {
  if (!closed.ok()) return closed;
  if (writer != 0 && writer != stream) {
    return absl::FailedPreconditionError(
        absl::StrCat("visit ", visit_id, " of map '", map_name,
                     "' is being written by another stream (from ", writer_peer,
                     "); a visit has one writer at a time: wait until that stream ends, or "
                     "start a new visit (visit_id 0)"));
  }
  return absl::OkStatus();
}

VisitWriter::VisitWriter(VisitWriter&& other) noexcept
    : state_(std::move(other.state_)), id_(other.id_) {
  other.id_ = 0;
}

VisitWriter& VisitWriter::operator=(VisitWriter&& other) noexcept {
  if (this != &other) {
    VisitWriter old(std::move(*this));  // releases what this held
    state_ = std::move(other.state_);
    id_ = other.id_;
    other.id_ = 0;
  }
  return *this;
}

VisitWriter::~VisitWriter() {
  if (state_ == nullptr || id_ == 0) return;
  absl::MutexLock lock(&state_->mu);
  if (state_->writer == id_) {
    state_->writer = 0;
    state_->writer_peer.clear();
  }
}

absl::StatusOr<VisitWriter> VisitRegistry::ClaimWriter(const std::shared_ptr<VisitState>& state,
                                                       const std::string& peer) {
  uint64_t id = 0;
  {
    absl::MutexLock lock(&mu_);
    id = next_writer_++;
  }
  absl::MutexLock lock(&state->mu);
  if (auto s = state->CheckWritable(id); !s.ok()) return s;
  state->writer = id;
  state->writer_peer = peer;
  return VisitWriter(state, id);
}

absl::StatusOr<std::shared_ptr<VisitState>> VisitRegistry::Get(int64_t visit_id) {
  {
    absl::MutexLock lock(&mu_);
    auto it = visits_.find(visit_id);
    if (it != visits_.end()) return it->second;
  }
  auto visit = store_->GetVisit(visit_id);
  if (!visit.ok()) return visit.status();
  if (visit->ended) {
    return absl::FailedPreconditionError(
        absl::StrCat("visit ", visit_id, " has ended; start a new visit to stream more frames"));
  }
  auto last = store_->LastKeyframe(visit_id);
  if (!last.ok()) return last.status();
  auto state = std::make_shared<VisitState>();
  state->tracker = tracking::Tracker(odometry_);
  state->visit_id = visit_id;
  state->map_id = visit->map_id;
  // A new run of the tracker, distinct from any earlier one of this visit (microseconds since
  // the epoch: a visit is loaded at most once per server run).
  state->odom_segment = std::chrono::duration_cast<std::chrono::microseconds>(
                            std::chrono::system_clock::now().time_since_epoch())
                            .count();
  {
    absl::MutexLock lock(&state->mu);
    state->map_name = visit->map_name;
    state->frame_count = visit->frame_count;
    state->lost_frame_count = visit->lost_frame_count;
    if (*last) {
      state->selector.Accept((*last)->timestamp_s, (*last)->T_world_camera);
      state->last_frame_s = (*last)->timestamp_s;
    }
  }
  // A resumed visit's architecture from its stored key frames (stored already).
  RebuildArchitecture(store_, places_, state->map_id, visit_id, visit->map_name,
                      /*store_plan=*/false, &state->architecture);
  // And its semantic octree from its last snapshot.
  if (semantic_) {
    if (auto snapshot = store_->GetSemanticSnapshot(visit_id); snapshot.ok()) {
      state->semantics.Restore(*snapshot, *semantic_);
    } else if (!absl::IsNotFound(snapshot.status())) {
      spdlog::warn("visit {}: stored semantic octree unreadable ({}); it starts empty", visit_id,
                   std::string(snapshot.status().message()));
    }
  }
  absl::MutexLock lock(&mu_);
  auto [it, inserted] = visits_.emplace(visit_id, std::move(state));
  return it->second;  // another thread may have loaded it first: use that one
}

uint64_t QueueSemanticSnapshot(SerialWorker* worker, store::Store* store,
                               std::shared_ptr<VisitState> visit) {
  return worker->Submit([visit = std::move(visit), store] {
    StoreSemanticSnapshotIfDue(store, visit->visit_id, &visit->semantics, /*every=*/0);
  });
}

std::shared_ptr<VisitState> VisitRegistry::Loaded(int64_t visit_id) {
  absl::MutexLock lock(&mu_);
  auto it = visits_.find(visit_id);
  return it != visits_.end() ? it->second : nullptr;
}

std::vector<std::shared_ptr<VisitState>> VisitRegistry::AllLoaded() {
  absl::MutexLock lock(&mu_);
  std::vector<std::shared_ptr<VisitState>> out;
  for (const auto& [id, state] : visits_) out.push_back(state);
  return out;
}

store::VisitFrameCount VisitRegistry::CloseVisit(int64_t visit_id, const absl::Status& why) {
  std::shared_ptr<VisitState> state;
  {
    absl::MutexLock lock(&mu_);
    auto it = visits_.find(visit_id);
    if (it == visits_.end()) return {visit_id, 0, 0};
    state = std::move(it->second);
    visits_.erase(it);
  }
  absl::MutexLock lock(&state->mu);
  state->closed = why;
  return {visit_id, state->frame_count, state->lost_frame_count};
}

void VisitRegistry::CloseMap(int64_t map_id, const absl::Status& why) {
  std::vector<std::shared_ptr<VisitState>> closing;
  {
    absl::MutexLock lock(&mu_);
    map_settings_.erase(map_id);
    for (auto it = visits_.begin(); it != visits_.end();) {
      if (it->second->map_id != map_id) {
        ++it;
        continue;
      }
      closing.push_back(std::move(it->second));
      it = visits_.erase(it);
    }
  }
  for (const auto& state : closing) {
    absl::MutexLock lock(&state->mu);
    state->closed = why;
  }
}

void VisitRegistry::RenameMap(int64_t map_id, const std::string& new_name) {
  absl::MutexLock lock(&mu_);
  for (auto& [id, state] : visits_) {
    if (state->map_id != map_id) continue;
    absl::MutexLock state_lock(&state->mu);
    state->map_name = new_name;
  }
}

absl::StatusOr<VisitRegistry::MapSettings> VisitRegistry::SettingsOfMap(int64_t map_id) {
  {
    absl::MutexLock lock(&mu_);
    auto it = map_settings_.find(map_id);
    if (it != map_settings_.end()) return it->second;
  }
  auto map = store_->GetMapById(map_id);
  if (!map.ok()) return map.status();
  const MapSettings settings{map->entropy_threshold, map->keep_original_color};
  absl::MutexLock lock(&mu_);
  map_settings_[map_id] = settings;
  return settings;
}

void VisitRegistry::ForgetMapSettings(int64_t map_id) {
  absl::MutexLock lock(&mu_);
  map_settings_.erase(map_id);
}

}  // namespace lifemap::server
