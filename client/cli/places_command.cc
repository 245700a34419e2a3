// `lifemap places ...`: the floor plans and architecture rankings of stored visits (paper 004).
#include <cmath>
#include <fstream>
#include <iostream>
#include <optional>

#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "client/cli/commands.h"
#include "client/cli/output.h"
#include "core/common/image_codec.h"
#include "core/common/types.h"
#include "core/io/tum_dataset.h"
#include "core/place/serialize.h"
#include "core/tracking/keyframe_selector.h"

namespace lifemap::cli {
namespace {

struct QueryArgs {
  uint64_t visit = 0;
  std::string tum;
  uint32_t max = 5;
  std::string method = "both";
  double accept = -1;  // < 0: the method's threshold from docs/RESULTS.md
};

// Scores a match must reach to be taken as the place, per method: those docs/RESULTS.md chose
// on one synthetic suite and held on others ("Paper 000's purpose", the building world):
// architecture 0.535 (chosen where places look alike in plan; 0.32 accepts look-alikes),
// appearance 0.635 (52 PnP inliers), fused 0.37. Real deployments should choose their own
// (--accept) on places like theirs.
double DefaultAccept(v1::MatchMethod m) {
  switch (m) {
    case v1::MATCH_METHOD_ARCHITECTURE:
      return 0.535;
    case v1::MATCH_METHOD_APPEARANCE:
      return 0.635;
    default:
      return 0.37;
  }
}

// The answer to "which place is this": the best match of the ranking that decides (fused when
// both methods answered, else the one asked or that answered) against its threshold, and for
// appearance where the query camera lies in the map's frame (the matched keyframe's stored
// pose composed with T_match_query).
struct Verdict {
  bool recognised = false;
  const v1::PlaceMatch* best = nullptr;
  double threshold = 0;
  std::optional<Pose> T_map_query;  // appearance matches of a keyframe with a pose
  std::string why;
};

Verdict Judge(const v1::QueryPlaceResponse& r, double accept, client::Client* c) {
  Verdict v;
  const v1::PlaceMatch* candidates[3] = {nullptr, nullptr, nullptr};  // fused, arch., appearance
  for (const auto& m : r.matches()) {
    const int slot = m.method() == v1::MATCH_METHOD_FUSED          ? 0
                     : m.method() == v1::MATCH_METHOD_ARCHITECTURE ? 1
                                                                   : 2;
    if (candidates[slot] == nullptr || m.score() > candidates[slot]->score()) {
      candidates[slot] = &m;
    }
  }
  for (const v1::PlaceMatch* m : candidates) {
    if (m != nullptr) {
      v.best = m;
      break;
    }
  }
  if (v.best == nullptr) {
    v.why = "no stored visit matched";
    return v;
  }
  v.threshold = accept >= 0 ? accept : DefaultAccept(v.best->method());
  v.recognised = v.best->score() >= v.threshold;
  // Where the query is: the best verified appearance match (per visit, or per frame).
  const v1::PlaceMatch* placed = candidates[2];
  for (const auto& f : r.frames()) {
    for (const auto& m : f.matches()) {
      if (placed == nullptr || m.score() > placed->score()) placed = &m;
    }
  }
  if (placed != nullptr && placed->keyframe_id() != 0 && placed->has_t_match_query() &&
      c != nullptr) {
    auto keyframe = c->GetKeyframe(placed->map(), placed->keyframe_id());
    if (keyframe.ok() && keyframe->summary().has_pose()) {
      const auto& k = keyframe->summary().pose();
      const auto& q = placed->t_match_query();
      auto T_map_keyframe =
          Pose::FromComponents(k.tx(), k.ty(), k.tz(), k.qx(), k.qy(), k.qz(), k.qw());
      auto T_keyframe_query =
          Pose::FromComponents(q.tx(), q.ty(), q.tz(), q.qx(), q.qy(), q.qz(), q.qw());
      if (T_map_keyframe.ok() && T_keyframe_query.ok()) {
        v.T_map_query =
            Pose::FromIsometry(T_map_keyframe->ToIsometry() * T_keyframe_query->ToIsometry());
      }
    }
  }
  return v;
}

nlohmann::json VerdictJson(const Verdict& v) {
  nlohmann::json j{{"recognised", v.recognised}};
  if (v.best != nullptr) {
    j["map"] = v.best->map();
    j["visit_id"] = std::to_string(v.best->visit_id());
    j["method"] = v1::MatchMethod_Name(v.best->method());
    j["score"] = v.best->score();
    j["threshold"] = v.threshold;
  } else {
    j["why"] = v.why;
  }
  if (v.T_map_query) {
    const Eigen::Vector3d& t = v.T_map_query->translation;
    const Eigen::Quaterniond& q = v.T_map_query->rotation;
    j["T_map_query"] = {{"tx", t.x()}, {"ty", t.y()}, {"tz", t.z()}, {"qx", q.x()},
                        {"qy", q.y()}, {"qz", q.z()}, {"qw", q.w()}};
  }
  return j;
}

void PrintVerdict(const Verdict& v) {
  if (v.best == nullptr) {
    std::cout << "verdict: not recognised (" << v.why << ")\n";
    return;
  }
  const char* method = v.best->method() == v1::MATCH_METHOD_FUSED          ? "fused"
                       : v.best->method() == v1::MATCH_METHOD_ARCHITECTURE ? "architecture"
                                                                           : "appearance";
  std::cout << absl::StrFormat(
      "verdict: %s map '%s', visit %d (%s score %.3f %s the threshold %.3f)\n",
      v.recognised ? "recognised as" : "not recognised; the nearest is", v.best->map(),
      v.best->visit_id(), method, v.best->score(), v.recognised ? ">=" : "<", v.threshold);
  if (v.T_map_query) {
    const Eigen::Vector3d& t = v.T_map_query->translation;
    const Eigen::AngleAxisd turn(v.T_map_query->rotation);
    const Eigen::Vector3d forward = v.T_map_query->rotation * Eigen::Vector3d::UnitZ();
    std::cout << absl::StrFormat(
        "  the query camera in map '%s''s frame: at (%.3f, %.3f, %.3f) m, looking along (%.2f, "
        "%.2f, %.2f), rotated %.1f deg from the map's axes (by its best verified keyframe match)\n",
        v.best->map(), t.x(), t.y(), t.z(), forward.x(), forward.y(), forward.z(),
        turn.angle() * 180.0 / M_PI);
  }
}

// Adds a recording's key frames (chosen as the server chooses them: on its ground-truth poses
// when it has them, else by time) to `req`: depth, the pose when known, colour when
// `with_color` (appearance needs it), within `max_bytes` of message: when they do not fit, every
// n-th key frame. `need_poses`: architecture alone, which cannot go without them. Returns a
// line saying what was sent.
absl::StatusOr<std::string> AddRecordingKeyframes(const std::string& dir, uint64_t max_bytes,
                                                  bool with_color, bool need_poses,
                                                  v1::QueryPlaceRequest* req) {
  auto seq = io::ReadTumSequence(dir);
  if (!seq.ok()) return seq.status();
  if (need_poses && seq->frames_with_pose < 2) {
    return absl::FailedPreconditionError(
        absl::StrCat(dir, ": ", seq->frames_with_pose,
                     " frames have a ground-truth pose; a floor plan needs the key frames' poses "
                     "(groundtruth.txt); --method appearance works without them"));
  }
  const bool posed = seq->frames_with_pose >= 2;
  tracking::KeyframeSelector selector;
  std::vector<const io::TumFrameEntry*> keyframes;
  for (const auto& e : seq->frames) {
    if (posed && !e.T_world_camera) continue;
    if (!selector.Decide(e.timestamp_s, e.T_world_camera).selected) continue;
    selector.Accept(e.timestamp_s, e.T_world_camera);
    keyframes.push_back(&e);
  }
  if (keyframes.empty()) return absl::FailedPreconditionError(absl::StrCat(dir, ": no frames"));
  // The intrinsics for the depth images' size (the first key frame's).
  auto first = ReadFileBytes(keyframes.front()->depth_path);
  if (!first.ok()) return first.status();
  auto header = ProbeImage(*first);
  if (!header.ok()) {
    return absl::InvalidArgumentError(
        absl::StrCat(keyframes.front()->depth_path, ": ", header.status().message()));
  }
  const v1::CameraIntrinsics k =
      IntrinsicsProto(io::TumSequenceIntrinsics(*seq, header->width, header->height, nullptr));
  std::vector<v1::Frame> frames;
  uint64_t bytes = 0;
  for (const auto* e : keyframes) {
    auto f = client::FrameFromFiles(with_color ? e->rgb_path : "", e->depth_path, 5000, k,
                                    e->timestamp_s, frames.size());
    if (!f.ok()) return f.status();
    if (e->T_world_camera) *f->mutable_pose() = PoseProto(*e->T_world_camera);
    bytes += f->depth().data().size() + f->color().data().size();
    frames.push_back(*std::move(f));
  }
  // Leave a tenth of the message for framing; thin evenly when the key frames do not fit.
  const uint64_t budget = max_bytes - max_bytes / 10;
  size_t every = bytes > budget ? static_cast<size_t>((bytes + budget - 1) / budget) : 1;
  size_t sent = 0;
  // The server takes at most 2000 frames, and 200 for appearance.
  const size_t max_frames = with_color ? 200 : 2000;
  const size_t spread = (frames.size() + max_frames - 1) / max_frames;
  every = std::max(every, spread);
  for (size_t i = 0; i < frames.size() && sent < max_frames; i += every, ++sent) {
    *req->add_frames() = std::move(frames[i]);
  }
  return absl::StrFormat(
      "%s: %d frames, %d key frames, sending %d%s", dir, seq->frames.size(), keyframes.size(), sent,
      every > 1 ? absl::StrFormat(" (every %d-th: message limit %s, at most %d frames)", every,
                                  HumanBytes(max_bytes), max_frames)
                : std::string());
}

const char* MethodName(v1::MatchMethod m) {
  switch (m) {
    case v1::MATCH_METHOD_ARCHITECTURE:
      return "architecture";
    case v1::MATCH_METHOD_APPEARANCE:
      return "appearance";
    case v1::MATCH_METHOD_FUSED:
      return "fused";
    default:
      return "?";
  }
}

void PrintMatch(const v1::PlaceMatch& m) {
  std::cout << absl::StrFormat("  %-12s %-20s visit %-6d", MethodName(m.method()), m.map(),
                               m.visit_id());
  if (m.keyframe_id() != 0) std::cout << absl::StrFormat(" keyframe %-8d", m.keyframe_id());
  std::cout << absl::StrFormat(" score %.3f", m.score());
  if (m.has_t_match_query()) {
    const auto& t = m.t_match_query();
    std::cout << absl::StrFormat("  query at (%.3f, %.3f, %.3f) m in the keyframe's camera", t.tx(),
                                 t.ty(), t.tz());
  }
  std::cout << "\n";
}

void PrintQueryAnswer(const std::string& what, const v1::QueryPlaceResponse& r) {
  std::cout << what << ":\n";
  for (const auto& s : r.method_status()) {
    if (!s.computed()) std::cout << "  " << MethodName(s.method()) << ": " << s.reason() << "\n";
  }
  std::cout << r.descriptor_text();
  if (r.matches().empty()) std::cout << "  no stored visit matches\n";
  for (const auto& m : r.matches()) PrintMatch(m);
  for (const auto& f : r.frames()) {
    std::cout << "frame " << f.index() << ":";
    if (!f.reason().empty()) {
      std::cout << " " << f.reason() << "\n";
    } else if (f.matches().empty()) {
      std::cout << " nothing recognised\n";
    } else {
      std::cout << "\n";
      for (const auto& m : f.matches()) PrintMatch(m);
    }
  }
}

}  // namespace

void AddPlaceCommands(CLI::App* app, CliContext* ctx) {
  auto* places = app->add_subcommand(
      "places",
      "Which stored place a view or visit is: by architecture (floor plans, paper 004) and by "
      "appearance (entropy-pruned features, paper 000)");
  places->require_subcommand(1);

  auto* show = places->add_subcommand("show", "A map's floor plans (one per visit)");
  show->footer(
      "Each visit's plan is its descriptor (paper 004), one line per wall corner, then stairs:\n"
      "  C0 L=4.20 A=90.0 door(0.90@1.10)  corner 0: the wall from it to the next corner is\n"
      "    4.20 m long, the interior angle at the next corner 90.0 deg; a door 0.90 m wide starts\n"
      "    1.10 m from this corner (window(...) alike)\n"
      "  S up L=1.68 W=1.00 D=0.40  stairs going up, 1.68 m long, 1.00 m wide, 0.40 m from the\n"
      "    nearest wall\n"
      "Lengths in metres in the ground plane of the visit's frame.");
  auto map = std::make_shared<std::string>();
  auto svg = std::make_shared<std::string>();
  auto png = std::make_shared<std::string>();
  show->add_option("MAP", *map, "map name")->required();
  show->add_option("--svg", *svg, "write each plan as PREFIX-visit-ID.svg");
  show->add_option("--png", *png, "write each plan as PREFIX-visit-ID.png");
  show->callback([ctx, map, svg, png] {
    ctx->run = [ctx, map, svg, png] {
      bool written = true;
      const int code = RunCall<v1::ListPlacesResponse>(
          *ctx, [&](client::Client& c) { return c.ListPlaces(*map); },
          [&](const v1::ListPlacesResponse& r) {
            if (r.places().empty()) {
              std::cout << "no floor plans in map '" << *map
                        << "' yet (visits streamed with poses build them)\n";
            }
            for (const auto& p : r.places()) {
              std::cout << absl::StrFormat("visit %d: %d key frames, updated %s\n", p.visit_id(),
                                           p.keyframes(), HumanTime(p.updated_time_s()))
                        << p.descriptor_text();
              if (svg->empty() && png->empty()) continue;
              auto plan = place::FloorPlanFromJson(p.floor_plan_json());
              if (!plan.ok()) {
                std::cerr << "lifemap: visit " << p.visit_id()
                          << ": stored floor plan unreadable: " << plan.status().message() << "\n";
                written = false;
                continue;
              }
              const std::string stem = absl::StrCat("-visit-", p.visit_id());
              const std::string title =
                  absl::StrFormat("map '%s', visit %d: floor plan from %d key frames", *map,
                                  p.visit_id(), p.keyframes());
              if (!svg->empty()) {
                const std::string path = *svg + stem + ".svg";
                std::ofstream out(path);
                out << place::FloorPlanSvg(*plan, nullptr, title);
                written = written && static_cast<bool>(out);
                std::cout << (out ? "wrote " : "could not write ") << path << "\n";
              }
              if (!png->empty()) {
                const std::string path = *png + stem + ".png";
                const bool ok = cv::imwrite(path, place::FloorPlanImage(*plan, nullptr, title));
                written = written && ok;
                std::cout << (ok ? "wrote " : "could not write ") << path << "\n";
              }
            }
          });
      return code == 0 && !written ? 1 : code;
    };
  });

  auto* index = places->add_subcommand(
      "index", "The appearance index over every stored keyframe (paper 000)");
  index->require_subcommand(1);
  auto print_index = [](const v1::AppearanceIndexInfo& a) {
    if (!a.enabled()) {
      std::cout << "appearance: disabled in the server's config (appearance.enabled)\n";
    } else if (!a.has_vocabulary()) {
      std::cout << absl::StrFormat(
          "appearance: no vocabulary yet; one is trained once %d keyframes with features are "
          "stored (%d now), or run `lifemap places index rebuild --retrain`\n",
          a.min_training_keyframes(), a.stored_keyframes());
    } else {
      std::cout << absl::StrFormat(
          "appearance: vocabulary %d (%d words); %d of %d stored keyframes indexed, %s in "
          "memory\n",
          a.vocabulary_id(), a.words(), a.keyframes(), a.stored_keyframes(),
          HumanBytes(a.memory_bytes()));
    }
  };
  index->add_subcommand("show", "The index's vocabulary, keyframes and memory")
      ->callback([ctx, print_index] {
        ctx->run = [ctx, print_index] {
          return RunCall<v1::Stats>(
              *ctx, [](client::Client& c) { return c.GetStats(); },
              [&](const v1::Stats& s) { print_index(s.appearance()); });
        };
      });
  auto* rebuild = index->add_subcommand(
      "rebuild", "Re-read every stored keyframe into the index (after a restore, say)");
  auto retrain = std::make_shared<bool>(false);
  rebuild->add_flag("--retrain", *retrain,
                    "first train a new vocabulary on the stored keyframes (kept in the store)");
  rebuild->callback([ctx, retrain, print_index] {
    ctx->run = [ctx, retrain, print_index] {
      return RunCall<v1::AppearanceIndexInfo>(
          *ctx, [&](client::Client& c) { return c.RebuildAppearanceIndex(*retrain); }, print_index);
    };
  });

  auto* query = places->add_subcommand(
      "query",
      "Recognise a stored visit or a recording among the stored visits: by architecture, by "
      "appearance (also per frame), or both (fused)");
  query->footer(
      "What the numbers are: every score is in [0, 1], higher is better. architecture: paper\n"
      "004's floor-plan descriptors matched (1 = the same walls, angles and openings); "
      "appearance:\n"
      "a keyframe verified by PnP, inliers / (inliers + 30) (30 inliers 0.5, 90 0.75); fused: per\n"
      "visit the mean of both (a method that did not find the visit counts 0). 'query at (x, y,\n"
      "z) m in the keyframe's camera' is T_match_query's translation. The verdict takes the best\n"
      "match of the fused ranking (else of the method that answered) against --accept, by\n"
      "default the thresholds docs/RESULTS.md chose on a synthetic suite (fused 0.37,\n"
      "architecture 0.535, appearance 0.635), and places the query camera in the map's frame by\n"
      "its best verified keyframe match. Exit 0 whether or not it is recognised.");
  auto q = std::make_shared<QueryArgs>();
  auto* visit_opt = query->add_option("--visit", q->visit, "a stored visit's id");
  auto* tum_opt = query
                      ->add_option("--tum", q->tum,
                                   "a TUM-format recording; its key frames are sent, not stored "
                                   "(architecture needs its groundtruth.txt poses)")
                      ->check(CLI::ExistingDirectory);
  visit_opt->excludes(tum_opt);
  query->add_option("--max", q->max, "results (default 5)")->check(CLI::Range(1, 1000));
  query->add_option("--method", q->method, "architecture, appearance or both (default)")
      ->check(CLI::IsMember({"architecture", "appearance", "both"}));
  query
      ->add_option("--accept", q->accept,
                   "the score the best match must reach to be taken as the place (default: the "
                   "method's from docs/RESULTS.md: fused 0.37, architecture 0.535, appearance "
                   "0.635)")
      ->check(CLI::Range(0.0, 1.0));
  query->callback([ctx, q] {
    ctx->run = [ctx, q] {
      if (q->visit == 0 && q->tum.empty()) {
        return UsageError("places query needs --visit ID or --tum DIR");
      }
      v1::QueryPlaceRequest req;
      req.set_max_results(q->max);
      const bool architecture = q->method != "appearance";
      const bool appearance = q->method != "architecture";
      if (architecture) req.add_methods(v1::MATCH_METHOD_ARCHITECTURE);
      if (appearance) req.add_methods(v1::MATCH_METHOD_APPEARANCE);
      std::string what = absl::StrCat("visit ", q->visit);
      if (!q->tum.empty()) {
        auto client = ctx->Connect();
        if (!client.ok()) return Fail(client.status());
        auto info = (*client)->GetServerInfo();
        if (!info.ok()) return Fail(info.status());
        auto summary = AddRecordingKeyframes(q->tum, info->max_message_bytes(), appearance,
                                             /*need_poses=*/!appearance, &req);
        if (!summary.ok()) return Fail(summary.status());
        if (!ctx->json) std::cerr << *summary << "\n";
        what = q->tum;
      } else {
        req.set_visit_id(q->visit);
      }
      auto c = ctx->Connect();
      if (!c.ok()) return Fail(c.status());
      auto r = (*c)->QueryPlace(req);
      if (!r.ok()) return Fail(r.status());
      const Verdict verdict = Judge(*r, q->accept, c->get());
      if (ctx->json) {
        nlohmann::json j = nlohmann::json::parse(ToJson(*r));
        j["verdict"] = VerdictJson(verdict);
        std::cout << j.dump(2) << "\n";
      } else {
        for (const auto& shard : r->unreachable_shards()) {
          std::cerr << "warning: shard " << shard << "\n  its maps are missing below\n";
        }
        PrintQueryAnswer(what, *r);
        PrintVerdict(verdict);
      }
      return 0;
    };
  });
}

}  // namespace lifemap::cli
