#include <algorithm>
#include <chrono>
#include <cmath>
#include <deque>
#include <future>
#include <optional>
#include <thread>

#include <spdlog/spdlog.h>

#include "absl/cleanup/cleanup.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/image_codec.h"
#include "core/common/task_pool.h"
#include "core/common/utf8.h"
#include "core/pipeline/keyframe.h"
#include "server/engine/bounded_queue.h"
#include "server/engine/keyframe_committer.h"
#include "server/rpc/convert.h"
#include "server/rpc/services.h"
#include "server/rpc/stream_read.h"
#include "server/rpc/stream_watchdog.h"

namespace lifemap::server {
namespace {

using Clock = std::chrono::steady_clock;

double MsBetween(Clock::time_point a, Clock::time_point b) {
  return std::chrono::duration<double, std::milli>(b - a).count();
}

// What a stream's (or a call's) options ask: of the frame path, and of the results' images.
struct CallSettings {
  FrameSettings frame;
  v1::ResultImages result_images = kDefaultResultImages;
};

// A frame through the frame path's first stage (server/engine/frame_path.h) and its result so
// far (made beside the analysis, on the task pool: the result images are encoded there).
struct AnalysedRequest {
  AnalysedFrame frame;
  v1::FrameResult result;
};

// A frame placed but not yet answered: its result, and the commit it waits for.
struct PendingResult {
  v1::FrameResult result;
  std::optional<std::shared_future<absl::StatusOr<int64_t>>> commit;
  Clock::time_point received;
  uint64_t architecture_ticket = 0;
  uint64_t pose_graph_ticket = 0;
  // Set when the frame could not be added to its visit (ended, its map deleted, or written by
  // another stream): the call ends with this status and the frame gets no result.
  absl::Status visit_closed;
};

// Stage 1 of a received frame: validated, then analysed with its map's settings and model.
// `refused`: not OK when the frame is refused before any work (the key's frame rate). The
// message's bytes are released when this returns.
AnalysedRequest AnalyseRequest(FramePath* frames, v1::Frame message, int64_t map_id,
                               const std::string& map_name, const CallSettings& settings,
                               const absl::Status& refused = absl::OkStatus()) {
  AnalysedRequest out;
  if (!refused.ok()) {
    out.frame = frames->Refuse(message.sequence(), message.timestamp_s(), refused);
  } else if (auto encoded = FrameFromProto(message); !encoded.ok()) {
    out.frame = frames->Refuse(message.sequence(), message.timestamp_s(), encoded.status());
  } else {
    out.frame = frames->Analyse(*encoded, map_id, map_name, settings.frame);
  }
  AnalysisToProto(out.frame, settings.result_images, &out.result);
  return out;
}

// Stage 2: the frame placed in its visit (null: a frame without a map); `writer` is the
// stream's claim on the visit (0 for a unary ProcessFrame). A refused frame passes through.
PendingResult PlaceRequest(FramePath* frames, AnalysedRequest x,
                           const std::shared_ptr<VisitState>& visit, uint64_t writer,
                           const CallSettings& settings) {
  PendingResult p;
  p.received = x.frame.received;
  p.result = std::move(x.result);
  if (!x.frame.refused.ok()) return p;
  const FramePlacement placed = frames->Place(x.frame, visit, writer, settings.frame);
  p.commit = placed.commit;
  p.architecture_ticket = placed.architecture_ticket;
  p.pose_graph_ticket = placed.pose_graph_ticket;
  p.visit_closed = placed.visit_closed;
  if (!placed.refused.ok()) {
    p.result = ErrorResult(p.result, placed.refused);
  } else if (placed.visit_closed.ok()) {
    PlacementToProto(x.frame, placed, frames->pipeline().options(), settings.result_images,
                     &p.result);
  }
  return p;
}

// Waits for the keyframe commit (if any) and completes the result: a keyframe is reported as
// committed only once the store has it.
void FinishResult(PendingResult* p) {
  auto* timing = p->result.mutable_timing();
  if (p->commit) {
    const auto wait_start = Clock::now();
    const absl::StatusOr<int64_t>& id = p->commit->get();
    timing->set_commit_wait_ms(MsBetween(wait_start, Clock::now()));
    auto* kf = p->result.mutable_keyframe();
    if (id.ok()) {
      kf->set_committed(true);
      kf->set_keyframe_id(static_cast<uint64_t>(*id));
    } else {
      kf->set_committed(false);
      kf->set_reason(ToValidUtf8(absl::StrCat("not stored: ", id.status().message())));
    }
  }
  timing->set_total_ms(MsBetween(p->received, Clock::now()));
}

// What a request's options ask, over the server's defaults. InvalidArgument for out-of-range
// values, naming the field.
absl::StatusOr<CallSettings> FrameSettingsFromProto(const v1::FrameOptions& o,
                                                    const ServerConfig& config) {
  CallSettings call;
  FrameSettings& settings = call.frame;
  auto keyframe = KeyframeOptionsFromProto(o, config.keyframe);
  if (!keyframe.ok()) return keyframe.status();
  settings.keyframe = *keyframe;
  auto threshold = EntropyThresholdFromProto(o.entropy_threshold(), "options.entropy_threshold");
  if (!threshold.ok()) return threshold.status();
  if (*threshold) settings.request.entropy_threshold = static_cast<float>(**threshold);
  settings.appearance_interval_s = config.appearance.frame_interval_s;
  if (o.has_appearance_interval_s()) {
    const double t = o.appearance_interval_s();
    if (!(t >= 0 && t <= AppearanceOptions::kMaxFrameIntervalS)) {
      return absl::InvalidArgumentError(
          absl::StrCat("options.appearance_interval_s must be within [0, ",
                       AppearanceOptions::kMaxFrameIntervalS, "] s (0 = every frame), got ", t));
    }
    settings.appearance_interval_s = t;
  }
  for (const int output : o.skip_outputs()) {
    if (output == v1::FRAME_OUTPUT_ENTROPY_MASK) {
      settings.request.entropy_masks = false;
    } else if (output == v1::FRAME_OUTPUT_CLASS_LABELS) {
      settings.skip_labels = true;
    } else if (output == v1::FRAME_OUTPUT_SEMANTIC_FUSION) {
      settings.skip_fusion = true;
    } else if (output == v1::FRAME_OUTPUT_MOVED_ZONES) {
      settings.skip_moved = true;
    } else {
      return absl::InvalidArgumentError(absl::StrCat(
          "options.skip_outputs: ",
          v1::FrameOutput_IsValid(output) ? v1::FrameOutput_Name(output) : std::to_string(output),
          " cannot be skipped; only FRAME_OUTPUT_ENTROPY_MASK, FRAME_OUTPUT_CLASS_LABELS, "
          "FRAME_OUTPUT_SEMANTIC_FUSION and FRAME_OUTPUT_MOVED_ZONES can"));
    }
  }
  settings.refine_pose = o.refine_pose();
  const auto against = IdFromProto(o.moved_against_visit(), "options.moved_against_visit");
  if (!against.ok()) return against.status();
  settings.moved_against_visit = *against;
  switch (o.result_images()) {
    case v1::RESULT_IMAGES_DEFAULT:
      break;
    case v1::RESULT_IMAGES_PNG:
    case v1::RESULT_IMAGES_RAW:
    case v1::RESULT_IMAGES_NONE:
      call.result_images = o.result_images();
      break;
    default:
      return absl::InvalidArgumentError(
          absl::StrCat("options.result_images ", o.result_images(),
                       " is not one of RESULT_IMAGES_PNG, RESULT_IMAGES_RAW, RESULT_IMAGES_NONE"));
  }
  return call;
}

// Resolves the visit a stream or call writes to. visit_id 0: a new visit (or, with
// `reuse_open`, the map's latest open visit).
absl::StatusOr<store::VisitRecord> ResolveVisit(ServiceContext* ctx, const Principal& caller,
                                                const std::string& map, uint64_t visit_id,
                                                const std::string& robot, const std::string& label,
                                                bool reuse_open, bool* created) {
  *created = false;
  if (auto s = store::ValidateMapName(map); !s.ok()) return s;
  if (robot.size() > 256 || label.size() > 256) {
    return absl::InvalidArgumentError("robot and visit label must be at most 256 bytes");
  }
  auto m = ctx->engine->store()->GetMap(map);
  if (!m.ok()) return m.status();
  if (visit_id == 0) {
    if (reuse_open) {
      auto open = ctx->engine->store()->LatestOpenVisit(map);
      if (!open.ok()) return open.status();
      if (*open) return **open;
    }
    if (auto s = caller.TakeVisit(ctx->config.max_visits_per_key_per_hour); !s.ok()) return s;
    *created = true;
    return ctx->engine->store()->StartVisit(map, robot, label, NowSeconds());
  }
  const auto id = IdFromProto(visit_id, "visit_id");
  if (!id.ok()) return id.status();
  auto v = ctx->engine->store()->GetVisit(*id);
  if (!v.ok()) return v.status();
  if (v->map_id != m->id) {
    // The other map is not named: a key limited to some maps must learn nothing of others.
    return absl::NotFoundError(
        absl::StrCat("map '", map, "' has no visit ", visit_id, " (ListVisits names its visits)"));
  }
  if (v->ended) {
    return absl::FailedPreconditionError(
        absl::StrCat("visit ", visit_id, " has ended; start a new visit (visit_id 0)"));
  }
  return v;
}

// What a stream's frames gave: how the call ends, and the last jobs its keyframes queued.
struct StagesOutcome {
  grpc::Status status;
  uint64_t frames = 0;
  uint64_t last_architecture_ticket = 0;
  uint64_t last_pose_graph_ticket = 0;
  bool client_gone = false;
};

using FrameStream = grpc::ServerReaderWriter<v1::StreamFramesResponse, v1::StreamFramesRequest>;
using ReadFrame = std::function<ReadOutcome(v1::StreamFramesRequest*, double timeout_s)>;

// The frames of a stream whose StreamStart was accepted, through the engine's two stages and
// answered in order, until the client ends the stream, the visit closes or a message is wrong.
StagesOutcome RunFrameStages(ServiceContext* ctx, FrameStream* stream, const ReadFrame& read,
                             const StreamWatchdog::Watch& watch, const Principal& caller,
                             const CallSettings& settings, const std::shared_ptr<VisitState>& state,
                             uint64_t writer_id, int64_t visit_id) {
  StagesOutcome out;
  v1::StreamFramesRequest request;
  // Three stages, so that consecutive frames are analysed side by side while a visit still
  // sees its frames one at a time, in order:
  //  - this thread reads frames and queues each one's analysis on the task pool (decode, masks,
  //    labels, result images: no visit state);
  //  - `placer` takes the analyses in the order read and places each in the visit (keyframe
  //    decision, features, record, appearance, commit submission);
  //  - `writer` answers in that order, waiting for keyframe commits so that no acknowledgement
  //    precedes its commit.
  // A frame takes one of max_inflight_frames slots when it is read and gives it back once
  // answered: with none free this thread stops reading, and gRPC's flow control holds back the
  // robot, so a stream holds at most that many frames in all its stages together.
  VisitState* visit_state = state.get();
  const int64_t map_id = visit_state->map_id;
  const auto inflight = static_cast<size_t>(ctx->config.max_inflight_frames);
  Slots slots(inflight);
  BoundedQueue<std::future<AnalysedRequest>> analysing(inflight);
  BoundedQueue<PendingResult> answering(inflight);
  std::atomic<bool> client_gone{false};
  // Set by `placer` when the visit could no longer be written (ended, its map deleted); this
  // thread ends the stream with it at its next read.
  absl::Mutex closed_mu;
  absl::Status closed;  // guarded by closed_mu
  std::atomic<bool> visit_closed{false};
  uint64_t last_architecture_ticket = 0;  // written by `placer`, read after it is joined
  uint64_t last_pose_graph_ticket = 0;    // likewise
  std::thread writer([&] {
    while (auto p = answering.Pop()) {
      FinishResult(&*p);
      if (!client_gone.load()) {  // else still wait for commits: they complete regardless
        v1::StreamFramesResponse response;
        *response.mutable_result() = std::move(p->result);
        KeepCallersMatches(caller, response.mutable_result()->mutable_place_matches());
        if (!stream->Write(response)) client_gone.store(true);
      }
      slots.Release();
    }
  });
  std::thread placer([&] {
    while (auto analysed = analysing.Pop()) {
      AnalysedRequest a = analysed->get();
      if (visit_closed.load()) {  // the stream is ending: nothing more is placed
        slots.Release();
        continue;
      }
      PendingResult p =
          PlaceRequest(ctx->engine->frames(), std::move(a), state, writer_id, settings);
      last_architecture_ticket = std::max(last_architecture_ticket, p.architecture_ticket);
      last_pose_graph_ticket = std::max(last_pose_graph_ticket, p.pose_graph_ticket);
      if (!p.visit_closed.ok()) {
        // The frame was read before the visit closed: it is answered with the error (a robot
        // that waits for each result is not left waiting), and the stream ends with it.
        spdlog::info("stream for visit {} ends: {}", visit_id,
                     std::string(p.visit_closed.message()));
        {
          absl::MutexLock lock(&closed_mu);
          closed = p.visit_closed;
        }
        visit_closed.store(true);
        p.result = ErrorResult(p.result, p.visit_closed);
      }
      answering.Push(std::move(p));
    }
    answering.Close();
  });

  grpc::Status status = grpc::Status::OK;
  uint64_t frames = 0;
  for (;;) {
    slots.Acquire();
    const ReadOutcome got =
        visit_closed.load() ? ReadOutcome::kEnd : read(&request, ctx->config.stream_idle_timeout_s);
    if (got == ReadOutcome::kUnparsable) {
      slots.Release();
      status = grpc::Status(
          grpc::StatusCode::INVALID_ARGUMENT,
          absl::StrCat("message ", frames + 2,
                       " of the stream could not be parsed (not a StreamFramesRequest, or a "
                       "string in it that is not valid UTF-8); the frames before it are answered "
                       "and the stream ends"));
      break;
    }
    if (got == ReadOutcome::kEnd) {
      slots.Release();
      if (watch.timed_out()) {
        status = grpc::Status(grpc::StatusCode::DEADLINE_EXCEEDED,
                              absl::StrCat("no frame for ", ctx->config.stream_idle_timeout_s,
                                           " s (stream_idle_timeout_s)"));
      }
      break;
    }
    if (!request.has_frame()) {
      slots.Release();
      status = grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                            "only the first message of a stream may be StreamStart; send frames");
      break;
    }
    if (auto s = caller.CheckNotRevoked(); !s.ok()) {  // revoked while streaming
      slots.Release();
      status = ToGrpcStatus(s);
      break;
    }
    // Refused before any work when the visit can no longer be written (`placer` checks again
    // where the frame is added).
    std::string map_name;
    if (auto s = CheckWritable(visit_state, writer_id, &map_name); !s.ok()) {
      slots.Release();
      status = ToGrpcStatus(s);
      spdlog::info("stream for visit {} ends: {}", visit_id, std::string(s.message()));
      break;
    }
    // Over the key's frame rate the frame is answered with the error, the stream goes on.
    analysing.Push(TaskPool::Shared().Submit([ctx, frame = std::move(*request.mutable_frame()),
                                              map_id, map_name = std::move(map_name), &settings,
                                              over_rate = caller.TakeFrame()]() mutable {
      return AnalyseRequest(ctx->engine->frames(), std::move(frame), map_id, map_name, settings,
                            over_rate);
    }));
    ++frames;
  }
  analysing.Close();
  placer.join();
  writer.join();
  if (visit_closed.load() && status.ok()) {
    absl::MutexLock lock(&closed_mu);
    status = ToGrpcStatus(closed);
  }
  out.status = status;
  out.frames = frames;
  out.last_architecture_ticket = last_architecture_ticket;
  out.last_pose_graph_ticket = last_pose_graph_ticket;
  out.client_gone = client_gone.load();
  return out;
}

}  // namespace

grpc::Status FrameServiceImpl::StreamFrames(
    grpc::ServerContext* context,
    grpc::ServerReaderWriter<v1::StreamFramesResponse, v1::StreamFramesRequest>* stream) {
  auto caller = ctx_->keys->Authorize(*context, "FrameService/StreamFrames");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  // A stream that goes quiet is ended by the watchdog (stream_start_timeout_s for its first
  // message, stream_idle_timeout_s for each one after).
  const auto watch = ctx_->stream_watchdog->Start(context);
  const auto read = [&](v1::StreamFramesRequest* message, double timeout_s) {
    watch->Waiting(timeout_s);
    const ReadOutcome got = ReadMessage(stream, message);
    watch->Received();
    return got;
  };

  v1::StreamFramesRequest request;
  const ReadOutcome first = read(&request, ctx_->config.stream_start_timeout_s);
  if (first == ReadOutcome::kUnparsable) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        "the stream's first message (StreamStart) could not be parsed: most often "
                        "a string (map, robot, visit_label) holds bytes that are not valid UTF-8; "
                        "send UTF-8 text");
  }
  if (first == ReadOutcome::kEnd) {
    if (watch->timed_out()) {
      return grpc::Status(
          grpc::StatusCode::DEADLINE_EXCEEDED,
          absl::StrCat("no StreamStart within ", ctx_->config.stream_start_timeout_s,
                       " s of opening the stream (stream_start_timeout_s)"));
    }
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        "stream closed before its StreamStart message");
  }
  if (!request.has_start()) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                        "the first message of a stream must be StreamStart (map, visit)");
  }
  const v1::StreamStart start = request.start();
  if (auto m = FindCallersMap(ctx_->engine->store(), *caller, start.map()); !m.ok()) {
    return ToGrpcStatus(m.status());
  }
  // The slots are taken once the stream said what it is for: a client that opens streams and
  // sends nothing holds none (and the watchdog ends those).
  if (auto s = caller->OpenStream(ctx_->config.max_streams_per_key); !s.ok()) {
    return ToGrpcStatus(s);
  }
  absl::Cleanup close_stream = [&caller] { caller->CloseStream(); };
  if (ctx_->active_streams.fetch_add(1) >= ctx_->config.max_streams) {
    ctx_->active_streams.fetch_sub(1);
    return grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED,
                        absl::StrCat("this server already serves ", ctx_->config.max_streams,
                                     " streams (max_streams); retry later"));
  }
  absl::Cleanup release = [this] { ctx_->active_streams.fetch_sub(1); };
  auto settings = FrameSettingsFromProto(start.options(), ctx_->config);
  if (!settings.ok()) return ToGrpcStatus(settings.status());
  settings->frame.key_name = caller->key_name;
  settings->frame.max_keyframes_per_map = caller->limits.max_keyframes_per_map;
  bool created = false;
  auto visit = ResolveVisit(ctx_, *caller, start.map(), start.visit_id(), start.robot(),
                            start.visit_label(), false, &created);
  if (!visit.ok()) return ToGrpcStatus(visit.status());
  auto state = ctx_->engine->visits()->Get(visit->id);
  if (!state.ok()) return ToGrpcStatus(state.status());
  auto claim = ctx_->engine->visits()->ClaimWriter(*state, context->peer());
  if (!claim.ok()) return ToGrpcStatus(claim.status());
  spdlog::info("stream {} visit {} of map '{}' from {}", created ? "started" : "resumed", visit->id,
               visit->map_name, context->peer());

  v1::StreamFramesResponse started;
  started.mutable_started()->set_map(visit->map_name);
  started.mutable_started()->set_visit_id(static_cast<uint64_t>(visit->id));
  started.mutable_started()->set_new_visit(created);
  if (!stream->Write(started)) {
    return grpc::Status(grpc::StatusCode::CANCELLED, "client went away");
  }

  const StagesOutcome run = RunFrameStages(ctx_, stream, read, *watch, *caller, *settings, *state,
                                           claim->id(), visit->id);
  grpc::Status status = run.status;
  const uint64_t frames = run.frames;
  const uint64_t last_architecture_ticket = run.last_architecture_ticket;
  const uint64_t last_pose_graph_ticket = run.last_pose_graph_ticket;
  const bool client_gone = run.client_gone;
  // A stream that ends has its visit's floor plan folded, stored and ranked: a robot (or an
  // operator) that asks right after sees every key frame it sent.
  if (last_architecture_ticket > 0) ctx_->engine->architecture()->Wait(last_architecture_ticket);
  // Likewise its loops closed and its keyframes' poses corrected.
  if (last_pose_graph_ticket > 0) ctx_->engine->pose_graph()->Wait(last_pose_graph_ticket);

  // Persist the visit's frame counter (it rides on keyframe commits otherwise).
  int64_t frame_count = 0;
  {
    absl::MutexLock lock(&(*state)->mu);
    frame_count = (*state)->frame_count;
  }
  auto flushed = ctx_->engine->committer()->Submit(std::nullopt, {visit->id, frame_count}).get();
  if (!flushed.ok() && !absl::IsNotFound(flushed.status())) {
    spdlog::warn("visit {}: frame counter not stored: {}", visit->id, flushed.status().ToString());
  }
  spdlog::info("stream for visit {} ended after {} frames{}", visit->id, frames,
               context->IsCancelled() ? " (cancelled)" : "");
  if (client_gone && status.ok()) {
    return grpc::Status(grpc::StatusCode::CANCELLED, "client went away");
  }
  return status;
}

grpc::Status FrameServiceImpl::ProcessFrame(grpc::ServerContext* context,
                                            const v1::ProcessFrameRequest* req,
                                            v1::FrameResult* resp) {
  auto caller = ctx_->keys->Authorize(*context, "FrameService/ProcessFrame");
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  if (auto s = caller->TakeFrame(); !s.ok()) return ToGrpcStatus(s);
  auto settings = FrameSettingsFromProto(req->options(), ctx_->config);
  if (!settings.ok()) return ToGrpcStatus(settings.status());
  settings->frame.key_name = caller->key_name;
  settings->frame.max_keyframes_per_map = caller->limits.max_keyframes_per_map;
  std::shared_ptr<VisitState> state;
  if (!req->map().empty()) {
    if (!caller->every_map) {
      if (auto m = FindCallersMap(ctx_->engine->store(), *caller, req->map()); !m.ok()) {
        return ToGrpcStatus(m.status());
      }
    }
    bool created = false;
    auto visit = ResolveVisit(ctx_, *caller, req->map(), req->visit_id(), "", "", true, &created);
    if (!visit.ok()) return ToGrpcStatus(visit.status());
    auto s = ctx_->engine->visits()->Get(visit->id);
    if (!s.ok()) return ToGrpcStatus(s.status());
    state = *std::move(s);
  } else if (req->visit_id() != 0) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "visit_id needs map");
  }
  std::string map_name;
  if (auto s = CheckWritable(state.get(), /*writer=*/0, &map_name); !s.ok()) {
    return ToGrpcStatus(s);
  }
  PendingResult p = PlaceRequest(ctx_->engine->frames(),
                                 AnalyseRequest(ctx_->engine->frames(), req->frame(),
                                                state ? state->map_id : 0, map_name, *settings),
                                 state, /*writer=*/0, *settings);
  if (!p.visit_closed.ok()) return ToGrpcStatus(p.visit_closed);
  if (p.result.has_error()) {
    return grpc::Status(static_cast<grpc::StatusCode>(p.result.error().code()),
                        p.result.error().message());
  }
  FinishResult(&p);
  *resp = std::move(p.result);
  KeepCallersMatches(*caller, resp->mutable_place_matches());
  return grpc::Status::OK;
}

}  // namespace lifemap::server
