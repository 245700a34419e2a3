// `lifemap places ...`: the floor plans and architecture rankings of stored visits (paper 004).
#include <fstream>
#include <iostream>

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
};

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
      return RunCall<v1::QueryPlaceResponse>(
          *ctx, [&](client::Client& c) { return c.QueryPlace(req); },
          [&](const v1::QueryPlaceResponse& r) { PrintQueryAnswer(what, r); });
    };
  });
}

}  // namespace lifemap::cli
