#include "server/http/web_server.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <list>
#include <map>
#include <optional>
#include <thread>
#include <unordered_map>
#include <utility>
#include <vector>

#include <spdlog/spdlog.h>
#include <nlohmann/json.hpp>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/synchronization/mutex.h"
#include "core/common/cluster_headers.h"
#include "core/common/utf8.h"
#include "core/place/serialize.h"
#include "server/config.h"
#include "server/engine/annotation_export.h"
#include "server/engine/appearance.h"
#include "server/engine/architecture.h"
#include "server/engine/clock.h"
#include "server/engine/cloud_export.h"
#include "server/engine/engine.h"
#include "server/engine/model_registry.h"
#include "server/engine/semantic_export.h"
#include "server/engine/visit_changes.h"
#include "server/engine/visit_frame.h"
#include "server/http/request_guard.h"
#include "server/http/tar_writer.h"
#include "server/http/web_assets.h"
#include "server/http/web_views.h"
#include "server/rpc/auth.h"

// Last: they include <resolv.h>, whose `_res` macro breaks Eigen's headers included after it.
#include <httplib.h>

#include "server/http/connection_pool.h"

namespace lifemap::server {
namespace {

using json = nlohmann::json;

constexpr int kThumbnailWidth = 160;
constexpr int64_t kMaxPageSize = 1000;
constexpr int64_t kDefaultMaxPoints = 1000000;
constexpr int64_t kMaxPoints = 20000000;
constexpr int64_t kMaxCloudKeyframes = 1000;
// Connections served at once (a thread each; more wait in the kernel's backlog), and of those
// one client address's at most (its oldest beyond are cut, every kSweepInterval).
constexpr size_t kMaxConnections = 256;
constexpr size_t kMaxConnectionsPerClient = 32;
constexpr auto kSweepInterval = absl::Seconds(1);
constexpr size_t kCacheBytes = size_t{256} << 20;
constexpr size_t kMaxAnnotationBodyBytes = size_t{16} << 20;

// Recently made images and clouds by key, least recently used dropped beyond a byte budget.
class ByteCache {
 public:
  explicit ByteCache(size_t budget) : budget_(budget) {}
  std::optional<std::string> Get(const std::string& key) {
    absl::MutexLock lock(&mu_);
    auto it = index_.find(key);
    if (it == index_.end()) return std::nullopt;
    order_.splice(order_.begin(), order_, it->second);
    return it->second->second;
  }
  void Put(const std::string& key, const std::string& bytes) {
    if (bytes.size() > budget_ / 4) return;
    absl::MutexLock lock(&mu_);
    if (auto it = index_.find(key); it != index_.end()) {
      used_ -= it->second->second.size();
      order_.erase(it->second);
      index_.erase(it);
    }
    order_.emplace_front(key, bytes);
    index_[key] = order_.begin();
    used_ += bytes.size();
    while (used_ > budget_ && !order_.empty()) {
      used_ -= order_.back().second.size();
      index_.erase(order_.back().first);
      order_.pop_back();
    }
  }

 private:
  const size_t budget_;
  absl::Mutex mu_;
  std::list<std::pair<std::string, std::string>> order_ ABSL_GUARDED_BY(mu_);
  std::unordered_map<std::string, std::list<std::pair<std::string, std::string>>::iterator> index_
      ABSL_GUARDED_BY(mu_);
  size_t used_ ABSL_GUARDED_BY(mu_) = 0;
};

int HttpStatusOf(const absl::Status& s) {
  switch (s.code()) {
    case absl::StatusCode::kInvalidArgument:
    case absl::StatusCode::kOutOfRange:
      return 400;
    case absl::StatusCode::kUnauthenticated:
      return 401;
    case absl::StatusCode::kPermissionDenied:
      return 403;
    case absl::StatusCode::kNotFound:
      return 404;
    case absl::StatusCode::kAlreadyExists:
    case absl::StatusCode::kFailedPrecondition:
    case absl::StatusCode::kAborted:
      return 409;
    case absl::StatusCode::kResourceExhausted:
      return 429;
    case absl::StatusCode::kUnavailable:
      return 503;
    case absl::StatusCode::kUnimplemented:
      return 501;
    default:
      return 500;
  }
}

// Errors are JSON: {"code": "NOT_FOUND", "message": "..."} with the HTTP status of the code.
void SendError(httplib::Response& res, const absl::Status& s) {
  res.status = HttpStatusOf(s);
  const json body = {{"code", absl::StatusCodeToString(s.code())},
                     {"message", std::string(s.message())}};
  res.set_content(body.dump(), "application/json");
}

void SendJson(httplib::Response& res, const json& body, int status = 200) {
  res.status = status;
  res.set_header("Cache-Control", "no-store");
  res.set_content(body.dump(), "application/json");
}

void SendBytes(httplib::Response& res, const std::string& bytes, const char* type) {
  res.set_header("Cache-Control", "private, max-age=60");
  res.set_content(bytes, type);
}

// An integer query parameter within [lo, hi], `fallback` when absent.
absl::StatusOr<int64_t> IntParam(const httplib::Request& req, const char* name, int64_t fallback,
                                 int64_t lo, int64_t hi) {
  if (!req.has_param(name)) return fallback;
  int64_t v = 0;
  if (!absl::SimpleAtoi(req.get_param_value(name), &v) || v < lo || v > hi) {
    return absl::InvalidArgumentError(
        absl::StrCat("query parameter '", name, "' must be an integer in [", lo, ", ", hi, "]"));
  }
  return v;
}

absl::StatusOr<int64_t> PathId(const std::string& text, const char* what) {
  int64_t v = 0;
  if (!absl::SimpleAtoi(text, &v) || v <= 0) {
    return absl::InvalidArgumentError(absl::StrCat(what, " must be a positive integer"));
  }
  return v;
}

json PoseJson(const Pose& p) {
  return {{"t", {p.translation.x(), p.translation.y(), p.translation.z()}},
          {"q", {p.rotation.x(), p.rotation.y(), p.rotation.z(), p.rotation.w()}}};
}

json MapJson(const store::MapRecord& m) {
  return {{"id", m.id},
          {"name", m.name},
          {"description", m.description},
          {"created_time_s", m.created_time_s},
          {"visit_count", m.visit_count},
          {"keyframe_count", m.keyframe_count},
          {"stored_bytes", m.stored_bytes}};
}

const char* PoseSourceName(store::StoredPoseSource s) {
  switch (s) {
    case store::StoredPoseSource::kClient:
      return "client";
    case store::StoredPoseSource::kEstimated:
      return "estimated";
    case store::StoredPoseSource::kRefined:
      return "refined";
    case store::StoredPoseSource::kNone:
      break;
  }
  return "none";
}

json KeyframeJson(const store::KeyframeRecord& k) {
  json j = {{"id", k.id},
            {"visit_id", k.visit_id},
            {"sequence", k.sequence},
            {"timestamp_s", k.timestamp_s},
            {"pose_source", PoseSourceName(k.pose_source)},
            {"width", k.intrinsics.width},
            {"height", k.intrinsics.height},
            {"color_bytes", k.color_bytes},
            {"depth_bytes", k.depth_bytes}};
  if (k.T_world_camera) j["pose"] = PoseJson(*k.T_world_camera);
  if (k.feature_counts) {
    j["superjuts"] = k.feature_counts->superjuts;
    j["keypoints_stored"] = k.feature_counts->keypoints_stored;
    j["keypoints_masked"] = k.feature_counts->keypoints_masked;
  }
  return j;
}

std::string ColorHex(uint32_t rgb) {
  char buf[8];
  std::snprintf(buf, sizeof(buf), "#%06x", rgb & 0xFFFFFF);
  return buf;
}

template <typename T>
void AppendRaw(std::string* out, const T& v) {
  out->append(reinterpret_cast<const char*>(&v), sizeof(T));
}

}  // namespace

struct WebServer::Impl {
  ServerConfig config;
  Engine* engine = nullptr;
  std::unique_ptr<KeyRing> keys;
  std::unique_ptr<httplib::Server> http;
  std::thread thread;
  int port = 0;
  ByteCache cache{kCacheBytes};
  HostPolicy host_policy;
  int listen_fd = -1;  // httplib's listening socket (it owns it)
  std::unique_ptr<ConnectionLimiter> limiter;
  std::thread sweeper;  // limiter->Sweep() every kSweepInterval until stopped
  absl::Mutex stop_mu;
  bool stopped ABSL_GUARDED_BY(stop_mu) = false;
  bool listening_ended ABSL_GUARDED_BY(stop_mu) = false;

  void Sweep();

  store::Store* store() const { return engine->store(); }

  // The caller, or the error already sent.
  std::optional<Principal> Caller(const httplib::Request& req, httplib::Response& res, Role role,
                                  const char* what) {
    std::optional<absl::string_view> header;
    std::string value;
    if (req.has_header("Authorization")) {
      value = req.get_header_value("Authorization");
      header = value;
    }
    auto p = keys->AuthorizeBearer(header, role, what);
    if (!p.ok()) {
      SendError(res, p.status());
      return std::nullopt;
    }
    return *std::move(p);
  }

  // The map named in the path, if the caller may use it; else the error already sent.
  std::optional<store::MapRecord> CallersMap(const Principal& caller, const std::string& name,
                                             httplib::Response& res) {
    auto map = FindCallersMap(store(), caller, name);
    if (!map.ok()) {
      SendError(res, map.status());
      return std::nullopt;
    }
    return *std::move(map);
  }

  // Visit `visit_id` if it is one of `map`'s; NOT_FOUND otherwise.
  absl::StatusOr<store::VisitRecord> MapsVisit(const store::MapRecord& map, int64_t visit_id) {
    auto v = store()->GetVisit(visit_id);
    if (!v.ok() || v->map_id != map.id) {
      return absl::NotFoundError(absl::StrCat("map '", map.name, "' has no visit ", visit_id));
    }
    return v;
  }

  absl::StatusOr<store::KeyframeRecord> MapsKeyframe(const store::MapRecord& map,
                                                     const std::string& id_text) {
    auto id = PathId(id_text, "the keyframe id");
    if (!id.ok()) return id.status();
    return store()->GetKeyframe(map.id, *id);
  }

  void Routes();
  void Static(const httplib::Request& req, httplib::Response& res);
  void Session(const httplib::Request& req, httplib::Response& res);
  void Maps(const httplib::Request& req, httplib::Response& res);
  void Map(const httplib::Request& req, httplib::Response& res);
  void Keyframes(const httplib::Request& req, httplib::Response& res);
  void Keyframe(const httplib::Request& req, httplib::Response& res);
  void KeyframeImage(const httplib::Request& req, httplib::Response& res);
  void Plan(const httplib::Request& req, httplib::Response& res);
  void Scene(const httplib::Request& req, httplib::Response& res);
  void Cloud(const httplib::Request& req, httplib::Response& res);
  void Octree(const httplib::Request& req, httplib::Response& res, bool binary);
  void Changes(const httplib::Request& req, httplib::Response& res);
  void Annotations(const httplib::Request& req, httplib::Response& res);
  void Annotate(const httplib::Request& req, httplib::Response& res);
  void Unannotate(const httplib::Request& req, httplib::Response& res);
  void Training(const httplib::Request& req, httplib::Response& res);
  absl::StatusOr<std::string> RenderImage(const store::MapRecord& map,
                                          const store::KeyframeRecord& k, const std::string& kind);
};

void WebServer::Impl::Static(const httplib::Request& req, httplib::Response& res) {
  const std::string path = req.path == "/" ? "/index.html" : req.path;
  const web::WebAsset* asset = web::FindWebAsset(path);
  if (asset == nullptr) {
    SendError(res, absl::NotFoundError(absl::StrCat("no page ", path)));
    return;
  }
  res.set_header("Cache-Control", "no-cache");
  res.set_content(asset->data, asset->size, asset->content_type);
}

void WebServer::Impl::Session(const httplib::Request& req, httplib::Response& res) {
  auto caller = Caller(req, res, Role::kRobot, "the browser view");
  if (!caller) return;
  SendJson(res, {{"key", caller->key_name},
                 {"role", RoleName(caller->role)},
                 {"auth_required", keys->required()},
                 {"version", LIFEMAP_VERSION},
                 {"may_annotate", caller->role >= Role::kOperator}});
}

void WebServer::Impl::Maps(const httplib::Request& req, httplib::Response& res) {
  auto caller = Caller(req, res, Role::kRobot, "listing maps");
  if (!caller) return;
  auto maps = store()->ListMaps();
  if (!maps.ok()) return SendError(res, maps.status());
  json out = json::array();
  for (const auto& m : *maps) {
    if (caller->MayUseMap(m.id)) out.push_back(MapJson(m));
  }
  SendJson(res, {{"maps", out}});
}

void WebServer::Impl::Map(const httplib::Request& req, httplib::Response& res) {
  auto caller = Caller(req, res, Role::kRobot, "reading a map");
  if (!caller) return;
  auto map = CallersMap(*caller, req.matches[1], res);
  if (!map) return;
  auto visits = store()->ListVisits(map->name);
  if (!visits.ok()) return SendError(res, visits.status());
  auto places = store()->ListVisitPlaces(map->name);
  if (!places.ok()) return SendError(res, places.status());
  auto annotations = store()->ListAnnotations(map->id);
  if (!annotations.ok()) return SendError(res, annotations.status());
  std::map<int64_t, int> plan_keyframes;
  for (const auto& p : *places) plan_keyframes[p.visit_id] = p.keyframes;
  json vs = json::array();
  for (const auto& v : *visits) {
    json j = {{"id", v.id},
              {"robot", v.robot},
              {"label", v.label},
              {"start_time_s", v.start_time_s},
              {"end_time_s", v.end_time_s},
              {"data_start_time_s", v.data_start_time_s},
              {"data_end_time_s", v.data_end_time_s},
              {"ended", v.ended},
              {"keyframe_count", v.keyframe_count},
              {"frame_count", v.frame_count},
              {"lost_frame_count", v.lost_frame_count},
              {"tracked_keyframes", v.tracked_keyframes},
              {"loops_accepted", v.loops_accepted},
              {"first_of_map", v.first_of_map},
              {"in_map_frame", MapFromVisit(v).has_value()},
              {"has_plan", plan_keyframes.count(v.id) > 0}};
    // Why the visit is (or is not) in the map's frame, in words.
    std::string why;
    if (v.first_of_map) {
      why = "the map's first visit: its frame is the map's";
    } else if (v.anchor) {
      why = absl::StrCat("anchored to visit ", v.anchor->to_visit_id, " by appearance");
      j["anchor"] = {{"to_visit_id", v.anchor->to_visit_id},
                     {"time_s", v.anchor->anchored_time_s},
                     {"T_map_visit", PoseJson(v.anchor->T_map_visit)}};
    } else if (MapFromVisit(v)) {
      why = "posed by its client in the map's frame";
    } else {
      why = WhyNotInMapFrame(v);
    }
    if (!v.anchor_dropped.empty()) j["anchor_dropped"] = v.anchor_dropped;
    j["frame_why"] = why;
    vs.push_back(std::move(j));
  }
  json out = MapJson(*map);
  out["visits"] = vs;
  out["annotation_count"] = annotations->size();
  out["may_annotate"] = caller->role >= Role::kOperator;
  SendJson(res, out);
}

void WebServer::Impl::Keyframes(const httplib::Request& req, httplib::Response& res) {
  auto caller = Caller(req, res, Role::kRobot, "listing keyframes");
  if (!caller) return;
  auto map = CallersMap(*caller, req.matches[1], res);
  if (!map) return;
  auto visit = IntParam(req, "visit", 0, 0, INT64_MAX);
  auto offset = IntParam(req, "offset", 0, 0, INT64_MAX);
  auto limit = IntParam(req, "limit", 100, 1, kMaxPageSize);
  for (const auto* p : {&visit, &offset, &limit}) {
    if (!p->ok()) return SendError(res, p->status());
  }
  if (*visit != 0) {
    if (auto v = MapsVisit(*map, *visit); !v.ok()) return SendError(res, v.status());
  }
  auto page = store()->ListKeyframes(map->id, *visit, *offset, *limit);
  if (!page.ok()) return SendError(res, page.status());
  json ks = json::array();
  for (const auto& k : *page) ks.push_back(KeyframeJson(k));
  json out = {{"keyframes", ks}, {"offset", *offset}};
  if (static_cast<int64_t>(page->size()) == *limit) out["next_offset"] = *offset + *limit;
  SendJson(res, out);
}

void WebServer::Impl::Keyframe(const httplib::Request& req, httplib::Response& res) {
  auto caller = Caller(req, res, Role::kRobot, "reading a keyframe");
  if (!caller) return;
  auto map = CallersMap(*caller, req.matches[1], res);
  if (!map) return;
  auto k = MapsKeyframe(*map, req.matches[2]);
  if (!k.ok()) return SendError(res, k.status());
  json out = KeyframeJson(*k);
  out["intrinsics"] = {{"fx", k->intrinsics.fx},
                       {"fy", k->intrinsics.fy},
                       {"cx", k->intrinsics.cx},
                       {"cy", k->intrinsics.cy}};
  if (k->features) {
    out["superjuts"] = k->features->superjuts.size();
    out["entropy_threshold"] = k->features->entropy_threshold;
  }
  // Appearance: the stored keyframes this one's features match, verified as the server does
  // for a frame (its own visit's left out).
  json appearance = json::array();
  auto features = store()->GetKeyframeFeatures(k->id);
  if (!features.ok()) {
    out["appearance_status"] = std::string(features.status().message());
  } else {
    const int64_t own_visit = k->visit_id;
    auto recognition = engine->appearance()->Recognize(
        features->keypoints, k->intrinsics,
        [own_visit](const appearance::KeyframeRef& r) { return r.visit_id == own_visit; });
    if (!recognition.ok()) {
      out["appearance_status"] = std::string(recognition.status().message());
    } else {
      for (const auto& m : recognition->matches) {
        if (!caller->MayUseMap(m.keyframe.map_id)) continue;
        auto other = store()->GetMapById(m.keyframe.map_id);
        appearance.push_back({{"map", other.ok() ? other->name : ""},
                              {"visit_id", m.keyframe.visit_id},
                              {"keyframe_id", m.keyframe.keyframe_id},
                              {"score", m.verification.score},
                              {"inliers", m.verification.inliers}});
      }
    }
  }
  out["appearance_matches"] = appearance;
  // Architecture: the stored visits whose floor plans match this keyframe's visit's.
  json architecture = json::array();
  auto place = store()->GetVisitPlace(k->visit_id);
  if (!place.ok()) {
    out["architecture_status"] = std::string(place.status().message());
  } else if (auto descriptor = place::DescriptorFromJson(place->descriptor_json);
             !descriptor.ok()) {
    out["architecture_status"] = std::string(descriptor.status().message());
  } else if (auto ranked = engine->places()->Rank(*descriptor, k->visit_id, 5); !ranked.ok()) {
    out["architecture_status"] = std::string(ranked.status().message());
  } else {
    for (const auto& m : *ranked) {
      if (!caller->MayUseMap(m.map_id)) continue;
      architecture.push_back({{"map", m.map}, {"visit_id", m.visit_id}, {"score", m.score}});
    }
  }
  out["architecture_matches"] = architecture;
  SendJson(res, out);
}

absl::StatusOr<std::string> WebServer::Impl::RenderImage(const store::MapRecord& map,
                                                         const store::KeyframeRecord& k,
                                                         const std::string& kind) {
  auto frame = DecodeRgbdFrame(store::StoredFrame(k));
  if (!frame.ok()) {
    return absl::DataLossError(
        absl::StrCat("stored keyframe ", k.id, " does not decode: ", frame.status().message()));
  }
  if (kind == "thumb") return web::ThumbnailJpeg(frame->color_bgr, kThumbnailWidth);
  if (kind == "depth") return web::DepthPng(frame->depth_m);
  if (kind == "entropy") {
    pipeline::FrameRequest request;
    if (map.entropy_threshold && *map.entropy_threshold > 0) {
      request.entropy_threshold = static_cast<float>(*map.entropy_threshold);
    }
    auto analysis = engine->pipeline()->Process(store::StoredFrame(k), request);
    if (!analysis.ok()) return analysis.status();
    if (!analysis->entropy) {
      return absl::FailedPreconditionError(
          absl::StrCat("no entropy mask: ", analysis->entropy_status.message()));
    }
    return web::MaskOverlayPng(analysis->entropy->mask, 0xFF00FF, 140);
  }
  if (kind == "labels") {
    auto model = engine->models()->ForMap(map.id);
    if (!model.ok()) return model.status();
    if (*model == nullptr) {
      return absl::FailedPreconditionError(
          absl::StrCat("map '", map.name, "' has no active model to label with"));
    }
    pipeline::FrameRequest request;
    request.labeller = &(*model)->forest;
    request.entropy_masks = false;
    auto analysis = engine->pipeline()->Process(store::StoredFrame(k), request);
    if (!analysis.ok()) return analysis.status();
    if (!analysis->labels) {
      return absl::FailedPreconditionError(
          absl::StrCat("no labels: ", analysis->labels_status.message()));
    }
    return web::LabelOverlayPng(analysis->labels->labels, (*model)->description.class_colors, 150);
  }
  if (kind == "fused") {
    if (!k.T_world_camera) {
      return absl::FailedPreconditionError(
          absl::StrCat("keyframe ", k.id, " has no pose to render the octree into"));
    }
    auto visit = store()->GetVisit(k.visit_id);
    if (!visit.ok()) return visit.status();
    const bool in_map = MapFromVisit(*visit).has_value();
    auto octree = CollectSemanticExport(store(), engine->visits(), engine->semantic_worker(), map,
                                        in_map ? 0 : k.visit_id, engine->options().semantic);
    if (!octree.ok()) return octree.status();
    auto rendered = octree->map->Render(frame->depth_m, frame->intrinsics, *k.T_world_camera, 2);
    if (!rendered.ok()) return rendered.status();
    return web::LabelOverlayPng(rendered->labels, octree->class_colors, 150);
  }
  return absl::NotFoundError(
      absl::StrCat("no keyframe image '", kind, "' (color, thumb, depth, entropy, labels, fused)"));
}

void WebServer::Impl::KeyframeImage(const httplib::Request& req, httplib::Response& res) {
  auto caller = Caller(req, res, Role::kRobot, "reading a keyframe's images");
  if (!caller) return;
  auto map = CallersMap(*caller, req.matches[1], res);
  if (!map) return;
  auto k = MapsKeyframe(*map, req.matches[2]);
  if (!k.ok()) return SendError(res, k.status());
  const std::string kind = req.matches[3];
  if (kind == "color") {
    return SendBytes(
        res, k->color,
        k->color_encoding == store::StoredColorEncoding::kJpeg ? "image/jpeg" : "image/png");
  }
  // Thumbnails and depth never change; analyses change with the model and the octree, so
  // they are cached for a minute at most.
  const bool lasting = kind == "thumb" || kind == "depth";
  const int64_t minute = static_cast<int64_t>(NowSeconds() / 60);
  const std::string key =
      absl::StrCat("kf/", k->id, "/", kind, lasting ? "" : absl::StrCat("/", minute));
  if (auto hit = cache.Get(key)) {
    return SendBytes(res, *hit, kind == "thumb" ? "image/jpeg" : "image/png");
  }
  auto bytes = RenderImage(*map, *k, kind);
  if (!bytes.ok()) return SendError(res, bytes.status());
  cache.Put(key, *bytes);
  SendBytes(res, *bytes, kind == "thumb" ? "image/jpeg" : "image/png");
}

void WebServer::Impl::Plan(const httplib::Request& req, httplib::Response& res) {
  auto caller = Caller(req, res, Role::kRobot, "reading a floor plan");
  if (!caller) return;
  auto map = CallersMap(*caller, req.matches[1], res);
  if (!map) return;
  auto visit_id = PathId(req.matches[2], "the visit id");
  if (!visit_id.ok()) return SendError(res, visit_id.status());
  if (auto visit = MapsVisit(*map, *visit_id); !visit.ok()) {
    return SendError(res, visit.status());
  }
  auto place = store()->GetVisitPlace(*visit_id);
  if (!place.ok()) return SendError(res, place.status());
  auto plan = place::FloorPlanFromJson(place->floor_plan_json);
  if (!plan.ok()) return SendError(res, plan.status());
  auto keyframes = store()->ListKeyframes(map->id, *visit_id);
  if (!keyframes.ok()) return SendError(res, keyframes.status());
  std::vector<place::PlanMarker> markers;
  for (const auto& k : *keyframes) {
    if (!k.T_world_camera) continue;
    const Eigen::Vector3d p = k.T_world_camera->translation;
    markers.push_back({Eigen::Vector2d(plan->e1.dot(p), plan->e2.dot(p)), k.id});
  }
  const std::string svg = place::FloorPlanSvg(
      *plan, nullptr,
      absl::StrCat("map ", map->name, ", visit ", *visit_id, ": ", plan->walls.size(), " walls, ",
                   markers.size(), " keyframes"),
      &markers);
  res.set_header("Cache-Control", "no-store");
  res.set_content(svg, "image/svg+xml");
}

void WebServer::Impl::Scene(const httplib::Request& req, httplib::Response& res) {
  auto caller = Caller(req, res, Role::kRobot, "reading a map's 3D scene");
  if (!caller) return;
  auto map = CallersMap(*caller, req.matches[1], res);
  if (!map) return;
  auto frame = VisitsInMapFrame(store(), map->name);
  if (!frame.ok()) return SendError(res, frame.status());
  auto keyframes = store()->ListKeyframes(map->id, 0);
  if (!keyframes.ok()) return SendError(res, keyframes.status());
  // Per visit in the map's frame: positions (x y z ...) and, for every keyframe, its
  // orientation (qx qy qz qw ...) for the frusta.
  std::map<int64_t, std::pair<std::vector<double>, std::vector<double>>> tracks;
  for (const auto& k : *keyframes) {
    if (!k.T_world_camera || frame->in_map_frame.count(k.visit_id) == 0) continue;
    auto& [pos, rot] = tracks[k.visit_id];
    const Pose& p = *k.T_world_camera;
    pos.insert(pos.end(), {p.translation.x(), p.translation.y(), p.translation.z()});
    rot.insert(rot.end(), {p.rotation.x(), p.rotation.y(), p.rotation.z(), p.rotation.w()});
  }
  json visits = json::array();
  for (const auto& [id, track] : tracks) {
    visits.push_back({{"id", id}, {"positions", track.first}, {"orientations", track.second}});
  }
  SendJson(res, {{"map", map->name}, {"visits", visits}, {"left_out", frame->left_out}});
}

void WebServer::Impl::Cloud(const httplib::Request& req, httplib::Response& res) {
  auto caller = Caller(req, res, Role::kRobot, "reading a map's cloud");
  if (!caller) return;
  auto map = CallersMap(*caller, req.matches[1], res);
  if (!map) return;
  auto max_points = IntParam(req, "max_points", kDefaultMaxPoints, 1, kMaxPoints);
  if (!max_points.ok()) return SendError(res, max_points.status());
  // Level of detail: a coarser voxel for larger maps, then every n-th point up to max_points.
  const double voxel_m =
      req.has_param("voxel_m") ? std::atof(req.get_param_value("voxel_m").c_str()) : 0.02;
  if (!(voxel_m >= 0.005 && voxel_m <= 1.0)) {
    return SendError(res, absl::InvalidArgumentError("voxel_m must be in [0.005, 1]"));
  }
  // Large maps: every n-th keyframe, at most kMaxCloudKeyframes of them decoded.
  const int64_t keyframe_stride = std::max<int64_t>(
      1, (static_cast<int64_t>(map->keyframe_count) + kMaxCloudKeyframes - 1) / kMaxCloudKeyframes);
  const std::string key = absl::StrCat("cloud/", map->id, "/", map->keyframe_count, "/",
                                       map->visit_count, "/", voxel_m);
  std::string points;
  if (auto hit = cache.Get(key)) {
    points = *std::move(hit);
  } else {
    auto cloud = ExportCloud(store(), map->id, map->name, 0, voxel_m, 4, nullptr, keyframe_stride);
    if (!cloud.ok()) return SendError(res, cloud.status());
    for (const auto& p : cloud->points) {
      AppendRaw(&points, p.x);
      AppendRaw(&points, p.y);
      AppendRaw(&points, p.z);
      AppendRaw(&points, p.r);
      AppendRaw(&points, p.g);
      AppendRaw(&points, p.b);
    }
    cache.Put(key, points);
  }
  // 15 bytes a point: x y z (float32 LE, metres), r g b (uint8).
  constexpr size_t kPointBytes = 15;
  const int64_t total = static_cast<int64_t>(points.size() / kPointBytes);
  const int64_t step = std::max<int64_t>(1, (total + *max_points - 1) / *max_points);
  std::string out;
  const uint32_t count = static_cast<uint32_t>((total + step - 1) / step);
  AppendRaw(&out, count);
  out.reserve(4 + count * kPointBytes);
  for (int64_t i = 0; i < total; i += step) {
    out.append(points, static_cast<size_t>(i) * kPointBytes, kPointBytes);
  }
  res.set_header("X-Lifemap-Points-Total", std::to_string(total));
  res.set_header("X-Lifemap-Keyframe-Stride", std::to_string(keyframe_stride));
  res.set_header("Cache-Control", "no-store");
  res.set_content(out, "application/octet-stream");
}

void WebServer::Impl::Octree(const httplib::Request& req, httplib::Response& res, bool binary) {
  auto caller = Caller(req, res, Role::kRobot, "reading a map's semantic octree");
  if (!caller) return;
  auto map = CallersMap(*caller, req.matches[1], res);
  if (!map) return;
  auto octree = CollectSemanticExport(store(), engine->visits(), engine->semantic_worker(), *map, 0,
                                      engine->options().semantic);
  if (!octree.ok()) return SendError(res, octree.status());
  const std::vector<semantic::LabelledVoxel> voxels = octree->map->LabelledVoxels();
  if (!binary) {
    json classes = json::array();
    std::vector<int64_t> counts(octree->class_names.size(), 0);
    for (const auto& v : voxels) {
      if (v.class_id < counts.size()) ++counts[v.class_id];
    }
    for (size_t c = 0; c < octree->class_names.size(); ++c) {
      classes.push_back(
          {{"id", c},
           {"name", octree->class_names[c]},
           {"color",
            ColorHex(c < octree->class_colors.size() ? octree->class_colors[c] : 0x808080)},
           {"voxels", counts[c]}});
    }
    return SendJson(res, {{"model", octree->model},
                          {"resolution_m", octree->map->resolution_m()},
                          {"voxels", voxels.size()},
                          {"classes", classes},
                          {"visits", octree->visits},
                          {"left_out", octree->left_out}});
  }
  // count (uint32), then per voxel x y z size (float32 LE, metres) and class (uint8).
  std::string out;
  AppendRaw(&out, static_cast<uint32_t>(voxels.size()));
  for (const auto& v : voxels) {
    AppendRaw(&out, v.x);
    AppendRaw(&out, v.y);
    AppendRaw(&out, v.z);
    AppendRaw(&out, v.size_m);
    AppendRaw(&out, v.class_id);
  }
  res.set_header("Cache-Control", "no-store");
  res.set_content(out, "application/octet-stream");
}

void WebServer::Impl::Changes(const httplib::Request& req, httplib::Response& res) {
  auto caller = Caller(req, res, Role::kRobot, "comparing visits");
  if (!caller) return;
  auto map = CallersMap(*caller, req.matches[1], res);
  if (!map) return;
  auto from = IntParam(req, "from", 0, 1, INT64_MAX);
  auto to = IntParam(req, "to", 0, 1, INT64_MAX);
  if (!from.ok()) return SendError(res, from.status());
  if (!to.ok()) return SendError(res, to.status());
  if (*from == 0 || *to == 0) {
    return SendError(res, absl::InvalidArgumentError("give the visits as ?from=A&to=B"));
  }
  auto changes = CompareVisits(store(), engine->visits(), engine->semantic_worker(), *map, *from,
                               *to, engine->options().changes, engine->options().semantic, nullptr);
  if (!changes.ok()) return SendError(res, changes.status());
  json objects = json::array();
  for (const auto& o : changes->objects) {
    const auto& c = o.change;
    objects.push_back({{"kind", change::ChangeKindName(c.kind)},
                       {"class", o.class_name},
                       {"center", {c.center.x(), c.center.y(), c.center.z()}},
                       {"from_center", {c.from_center.x(), c.from_center.y(), c.from_center.z()}},
                       {"extent", {c.extent.x(), c.extent.y(), c.extent.z()}},
                       {"voxels", c.voxels}});
  }
  SendJson(res, {{"from_visit", changes->from_visit},
                 {"to_visit", changes->to_visit},
                 {"objects", objects},
                 {"classes", changes->classes},
                 {"seconds", changes->seconds}});
}

void WebServer::Impl::Annotations(const httplib::Request& req, httplib::Response& res) {
  auto caller = Caller(req, res, Role::kRobot, "listing annotations");
  if (!caller) return;
  auto map = CallersMap(*caller, req.matches[1], res);
  if (!map) return;
  auto all = store()->ListAnnotations(map->id);
  if (!all.ok()) return SendError(res, all.status());
  json out = json::array();
  for (const auto& a : *all) {
    json boxes = json::array();
    for (const auto& b : a.boxes) {
      boxes.push_back({b.min[0], b.min[1], b.min[2], b.max[0], b.max[1], b.max[2]});
    }
    out.push_back({{"id", a.id},
                   {"class", a.class_name},
                   {"boxes", boxes},
                   {"author", a.author},
                   {"created_time_s", a.created_time_s}});
  }
  SendJson(res, {{"annotations", out}, {"classes", AnnotationClasses(*all)}});
}

void WebServer::Impl::Annotate(const httplib::Request& req, httplib::Response& res) {
  auto caller = Caller(req, res, Role::kOperator, "annotating a map");
  if (!caller) return;
  auto map = CallersMap(*caller, req.matches[1], res);
  if (!map) return;
  if (auto s = caller->CheckNotRevoked(); !s.ok()) return SendError(res, s);
  store::AnnotationRecord a;
  a.map_id = map->id;
  a.author = caller->key_name;
  a.created_time_s = NowSeconds();
  const json body = json::parse(req.body, nullptr, /*allow_exceptions=*/false);
  if (body.is_discarded() || !body.is_object()) {
    return SendError(res, absl::InvalidArgumentError(
                              "the body must be a JSON object {\"class\": NAME, \"boxes\": "
                              "[[min_x, min_y, min_z, max_x, max_y, max_z], ...]} (metres, the "
                              "map's frame)"));
  }
  if (!body.contains("class") || !body["class"].is_string()) {
    return SendError(res, absl::InvalidArgumentError("\"class\" must be a string"));
  }
  a.class_name = body["class"].get<std::string>();
  if (!body.contains("boxes") || !body["boxes"].is_array()) {
    return SendError(res, absl::InvalidArgumentError("\"boxes\" must be an array of boxes"));
  }
  for (const json& b : body["boxes"]) {
    if (!b.is_array() || b.size() != 6 ||
        !std::all_of(b.begin(), b.end(), [](const json& v) { return v.is_number(); })) {
      return SendError(res, absl::InvalidArgumentError(
                                "each box must be [min_x, min_y, min_z, max_x, max_y, max_z]"));
    }
    store::AnnotationBox box;
    for (int d = 0; d < 3; ++d) {
      box.min[d] = b[d].get<double>();
      box.max[d] = b[d + 3].get<double>();
    }
    a.boxes.push_back(box);
  }
  if (auto s = ValidateAnnotation(a); !s.ok()) return SendError(res, s);
  auto stored = store()->InsertAnnotation(a);
  if (!stored.ok()) return SendError(res, stored.status());
  spdlog::info("annotation {} of map '{}': class '{}', {} boxes, by key '{}'", stored->id,
               map->name, stored->class_name, stored->boxes.size(), stored->author);
  SendJson(res, {{"id", stored->id}, {"class", stored->class_name}, {"boxes", a.boxes.size()}},
           201);
}

void WebServer::Impl::Unannotate(const httplib::Request& req, httplib::Response& res) {
  auto caller = Caller(req, res, Role::kOperator, "deleting an annotation");
  if (!caller) return;
  auto map = CallersMap(*caller, req.matches[1], res);
  if (!map) return;
  auto id = PathId(req.matches[2], "the annotation id");
  if (!id.ok()) return SendError(res, id.status());
  if (auto s = store()->DeleteAnnotation(map->id, *id); !s.ok()) return SendError(res, s);
  SendJson(res, {{"deleted", *id}});
}

void WebServer::Impl::Training(const httplib::Request& req, httplib::Response& res) {
  auto caller = Caller(req, res, Role::kRobot, "exporting a training folder");
  if (!caller) return;
  auto map = CallersMap(*caller, req.matches[1], res);
  if (!map) return;
  web::TarWriter tar;
  const std::string root = absl::StrCat(map->name, "-training/");
  auto folder = ExportTrainingFolder(store(), *map, TrainingFolderOptions{}, nullptr,
                                     [&](const std::string& path, const std::string& bytes) {
                                       return tar.Add(root + path, bytes, NowSeconds());
                                     });
  if (!folder.ok()) return SendError(res, folder.status());
  res.set_header("X-Lifemap-Views", std::to_string(folder->views_written));
  res.set_header("X-Lifemap-Labelled-Pixels", std::to_string(folder->labelled_pixels));
  res.set_header("Content-Disposition",
                 // RFC 6266: an ASCII fallback, and the UTF-8 name percent-encoded (RFC 5987).
                 absl::StrCat("attachment; filename=\"training.tar\"; filename*=UTF-8''",
                              EncodeHeaderValue(map->name), "-training.tar"));
  res.set_header("Cache-Control", "no-store");
  res.set_content(tar.Finish(), "application/x-tar");
}

void WebServer::Impl::Routes() {
  httplib::Server& s = *http;
  const std::string map = "/api/maps/([^/]+)";
  auto bind = [this](void (Impl::*fn)(const httplib::Request&, httplib::Response&)) {
    return
        [this, fn](const httplib::Request& req, httplib::Response& res) { (this->*fn)(req, res); };
  };
  s.Get("/api/session", bind(&Impl::Session));
  s.Get("/api/maps", bind(&Impl::Maps));
  s.Get(map, bind(&Impl::Map));
  s.Get(map + "/keyframes", bind(&Impl::Keyframes));
  s.Get(map + "/keyframes/([0-9]+)", bind(&Impl::Keyframe));
  s.Get(map + "/keyframes/([0-9]+)/([a-z]+)", bind(&Impl::KeyframeImage));
  s.Get(map + "/visits/([0-9]+)/plan.svg", bind(&Impl::Plan));
  s.Get(map + "/scene", bind(&Impl::Scene));
  s.Get(map + "/cloud.bin", bind(&Impl::Cloud));
  s.Get(map + "/octree",
        [this](const httplib::Request& req, httplib::Response& res) { Octree(req, res, false); });
  s.Get(map + "/octree.bin",
        [this](const httplib::Request& req, httplib::Response& res) { Octree(req, res, true); });
  s.Get(map + "/changes", bind(&Impl::Changes));
  s.Get(map + "/annotations", bind(&Impl::Annotations));
  s.Post(map + "/annotations", bind(&Impl::Annotate));
  s.Delete(map + "/annotations/([0-9]+)", bind(&Impl::Unannotate));
  s.Get(map + "/training.tar", bind(&Impl::Training));
  s.Get("/api/.*", [](const httplib::Request& req, httplib::Response& res) {
    SendError(res, absl::NotFoundError(absl::StrCat("no endpoint ", req.path)));
  });
  s.Get("/.*", [this](const httplib::Request& req, httplib::Response& res) { Static(req, res); });
  s.set_exception_handler(
      [](const httplib::Request& req, httplib::Response& res, std::exception_ptr ep) {
        std::string what = "unknown";
        try {
          std::rethrow_exception(ep);
        } catch (const std::exception& e) {
          what = e.what();
        } catch (...) {
        }
        spdlog::error("HTTP {} {} failed: {}", req.method, req.path, what);
        SendError(res, absl::InternalError(absl::StrCat("the request failed: ", what)));
      });
  // Responses are compressed with gzip, never Brotli: Debian's httplib compresses Brotli at its
  // highest quality, which took 4.9 s for three.js (600 kB) and 1 s for a 13 MB scene; gzip
  // takes milliseconds. The request is httplib's own (not const where it is made); only its
  // Accept-Encoding is narrowed.
  s.set_pre_routing_handler([this](const httplib::Request& req, httplib::Response& res) {
    // Before anything is read or routed: a request sent to another name (DNS rebinding), or a
    // change from another site's page, is refused (issue 52, item 8).
    const std::string host = req.get_header_value("Host");
    absl::Status guard = CheckHost(host, host_policy);
    if (guard.ok()) {
      guard = CheckStateChange(
          req.method, host, req.get_header_value("Origin"), req.get_header_value("Sec-Fetch-Site"),
          req.get_header_value("Content-Type"),
          req.has_header("Content-Length") || req.has_header("Transfer-Encoding"));
    }
    if (!guard.ok()) {
      spdlog::warn("HTTP {} {} from {} refused: {}", EscapeForLog(req.method),
                   EscapeForLog(req.path), req.remote_addr, std::string(guard.message()));
      SendError(res, guard);
      if (absl::IsInvalidArgument(guard)) res.status = 415;
      return httplib::Server::HandlerResponse::Handled;
    }
    if (req.has_header("Accept-Encoding")) {
      auto& headers = const_cast<httplib::Request&>(req).headers;
      const bool gzip = req.get_header_value("Accept-Encoding").find("gzip") != std::string::npos;
      headers.erase("Accept-Encoding");
      if (gzip) headers.emplace("Accept-Encoding", "gzip");
    }
    return httplib::Server::HandlerResponse::Unhandled;
  });
  s.set_payload_max_length(kMaxAnnotationBodyBytes);
  // A thread per open connection, idle ones included: a browser keeps six per tab alive, and
  // with httplib's default pool (8) and keep-alive (5 s) a second tab's requests waited for
  // idle connections to time out (a map page took 5.5 s instead of 0.5). With a fixed pool (32)
  // 200 slow clients took every thread (issue 52): ConnectionPool starts threads as
  // connections come, up to kMaxConnections, and the sweeper cuts one client's beyond
  // kMaxConnectionsPerClient. Each read waits at most 5 s for bytes, each write 5 s.
  s.new_task_queue = [] { return new ConnectionPool(kMaxConnections); };
  // httplib listens with a backlog of 5: a burst of new connections (a browser opens six, a
  // client at full speed more) overflowed it and waited for the SYN to be sent again, 1 s.
  // The listening socket is recorded here and Start() listens again with the system's
  // largest backlog (Linux takes a second listen() as a change of backlog).
  s.set_socket_options([this](socket_t fd) {
    httplib::default_socket_options(fd);
    listen_fd = fd;
  });
  s.set_keep_alive_timeout(2);
  s.set_read_timeout(5);
  s.set_write_timeout(5);
  s.set_default_headers({{"X-Content-Type-Options", "nosniff"},
                         {"X-Frame-Options", "DENY"},
                         {"Referrer-Policy", "no-referrer"}});
}

WebServer::WebServer(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}

WebServer::~WebServer() { Stop(); }

absl::StatusOr<std::unique_ptr<WebServer>> WebServer::Start(const ServerConfig& config,
                                                            Engine* engine) {
  auto impl = std::make_unique<Impl>();
  impl->config = config;
  impl->engine = engine;
  const bool required =
      config.AuthRequired() || (!IsLoopbackAddress(config.http_listen) && !config.insecure_no_auth);
  impl->keys = std::make_unique<KeyRing>(engine->store(), required);
  if (required) {
    auto admin = HasLiveAdminKey(engine->store());
    if (!admin.ok()) return admin.status();
    if (!*admin) {
      return absl::FailedPreconditionError(absl::StrCat(
          "the browser view on ", config.http_listen,
          " needs API keys and the database has no live admin key: create one with `lifemapd "
          "keys create NAME --role admin --db ",
          config.db_path, "`"));
    }
  }
  if (config.tls_cert.empty()) {
    impl->http = std::make_unique<httplib::Server>();
  } else {
    auto tls = std::make_unique<httplib::SSLServer>(
        config.tls_cert.c_str(), config.tls_key.c_str(),
        config.tls_client_ca.empty() ? nullptr : config.tls_client_ca.c_str());
    if (!tls->is_valid()) {
      return absl::FailedPreconditionError(
          absl::StrCat("the browser view cannot use the TLS certificate ", config.tls_cert,
                       " and key ", config.tls_key));
    }
    impl->http = std::move(tls);
  }
  impl->Routes();
  const size_t colon = config.http_listen.rfind(':');
  std::string host = config.http_listen.substr(0, colon);
  if (host.size() >= 2 && host.front() == '[' && host.back() == ']') {
    host = host.substr(1, host.size() - 2);
  }
  int port = 0;
  if (colon == std::string::npos ||
      !absl::SimpleAtoi(config.http_listen.substr(colon + 1), &port) || port < 0 || port > 65535) {
    return absl::InvalidArgumentError(absl::StrCat(
        "--http ", config.http_listen, ": give HOST:PORT (e.g. 127.0.0.1:8080; port 0 picks one)"));
  }
  impl->host_policy = MakeHostPolicy(host, config.http_allowed_hosts);
  if (port == 0) {
    impl->port = impl->http->bind_to_any_port(host);
  } else if (impl->http->bind_to_port(host, port)) {
    impl->port = port;
  }
  if (impl->port <= 0) {
    return absl::UnavailableError(
        absl::StrCat("the browser view cannot listen on ", config.http_listen,
                     " (the port is in use, or the address is not one of this host's)"));
  }
  if (impl->listen_fd >= 0) ::listen(impl->listen_fd, SOMAXCONN);
  impl->limiter = std::make_unique<ConnectionLimiter>(impl->port, kMaxConnectionsPerClient);
  Impl* raw = impl.get();
  impl->thread = std::thread([raw] {
    raw->http->listen_after_bind();
    absl::MutexLock lock(&raw->stop_mu);
    raw->listening_ended = true;
  });
  impl->sweeper = std::thread([raw] { raw->Sweep(); });
  spdlog::info("browser view on http{}://{}:{}/ ({})", config.tls_cert.empty() ? "" : "s", host,
               impl->port, required ? "API keys required" : "no authentication");
  return std::unique_ptr<WebServer>(new WebServer(std::move(impl)));
}

int WebServer::port() const { return impl_->port; }

bool WebServer::auth_required() const { return impl_->keys->required(); }

void WebServer::Stop() {
  {
    absl::MutexLock lock(&impl_->stop_mu);
    if (impl_->stopped) return;
    impl_->stopped = true;
  }
  impl_->http->stop();
  // Running requests get a moment to end; then every connection left (a slow client's, an idle
  // keep-alive) is cut, so a stop never waits for a client.
  {
    absl::MutexLock lock(&impl_->stop_mu);
    const absl::Condition ended(&impl_->listening_ended);
    if (!impl_->stop_mu.AwaitWithTimeout(ended, absl::Seconds(2))) {
      while (!impl_->stop_mu.AwaitWithTimeout(ended, absl::Milliseconds(100))) {
        impl_->limiter->ShutdownAll();
      }
    }
  }
  if (impl_->thread.joinable()) impl_->thread.join();
  if (impl_->sweeper.joinable()) impl_->sweeper.join();
}

void WebServer::Impl::Sweep() {
  for (;;) {
    {
      absl::MutexLock lock(&stop_mu);
      if (stop_mu.AwaitWithTimeout(absl::Condition(&stopped), kSweepInterval)) return;
    }
    for (const auto& [client, n] : limiter->Sweep()) {
      spdlog::warn(
          "browser view: cut {} connection(s) of {}, which had more than {} open (slow or "
          "hostile client?)",
          n, client, kMaxConnectionsPerClient);
    }
  }
}

}  // namespace lifemap::server
