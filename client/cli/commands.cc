#include "client/cli/commands.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>

#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "client/cli/output.h"
#include "core/common/depth_codec.h"
#include "core/common/image_codec.h"
#include "core/common/types.h"

namespace lifemap::cli {
namespace {

// The label PNG (class id per pixel, 255 = none) in the model's class colours (none: black).
absl::StatusOr<std::string> ColorizeLabels(const std::string& label_png,
                                           const v1::ListClassesResponse& classes) {
  const cv::Mat labels =
      cv::imdecode(cv::Mat(1, static_cast<int>(label_png.size()), CV_8UC1,
                           const_cast<char*>(label_png.data())),  // imdecode only reads
                   cv::IMREAD_UNCHANGED);
  if (labels.empty() || labels.type() != CV_8UC1) {
    return absl::InvalidArgumentError("label image is not an 8-bit PNG");
  }
  cv::Mat lut(1, 256, CV_8UC3, cv::Scalar(0, 0, 0));
  for (int c = 0; c < classes.class_colors_size() && c < 255; ++c) {
    const uint32_t rgb = classes.class_colors(c);
    lut.at<cv::Vec3b>(c) = cv::Vec3b(rgb & 0xFF, (rgb >> 8) & 0xFF, (rgb >> 16) & 0xFF);
  }
  cv::Mat bgr;
  cv::cvtColor(labels, bgr, cv::COLOR_GRAY2BGR);
  cv::LUT(bgr, lut, bgr);
  return EncodePng(bgr);
}

namespace fs = std::filesystem;

// Writes `write(out)` to a temporary file beside `path` and renames it into place, so a
// failed or interrupted command never leaves a half-written file under the final name.
absl::Status WriteFileAtomically(const std::string& path,
                                 const std::function<absl::Status(std::ostream*)>& write) {
  const std::string tmp = path + ".partial";
  {
    std::ofstream out(tmp, std::ios::binary | std::ios::trunc);
    if (!out) return absl::PermissionDeniedError(absl::StrCat("cannot write ", tmp));
    if (auto s = write(&out); !s.ok()) {
      out.close();
      fs::remove(tmp);
      return s;
    }
    out.flush();
    if (!out) {
      fs::remove(tmp);
      return absl::DataLossError(absl::StrCat("writing ", tmp, " failed (disk full?)"));
    }
  }
  std::error_code ec;
  fs::rename(tmp, path, ec);
  if (ec) return absl::UnavailableError(absl::StrCat("renaming to ", path, ": ", ec.message()));
  return absl::OkStatus();
}

void PrintMap(const v1::Map& m) {
  std::cout << absl::StrFormat(
      "name:        %s\nid:          %d\ndescription: %s\ncreated:     %s\nvisits:      %d\n"
      "keyframes:   %d\nstored:      %s\nentropy threshold: %s\nkeyframe colour:   %s\n",
      Shown(m.name()), m.id(), Shown(m.description()), HumanTime(m.created_time_s()),
      m.visit_count(), m.keyframe_count(), HumanBytes(m.stored_bytes()),
      m.entropy_threshold() > 0 ? absl::StrFormat("%.2f", m.entropy_threshold())
                                : std::string("server default"),
      m.keep_original_color() ? "as the client sent it" : "JPEG (PNG and raw re-encoded)");
  // Issue 35: what is not in the map's frame, and why.
  for (const auto& why : m.left_out()) std::cout << "left out of the map's frame: " << why << "\n";
}

std::string OutputName(v1::FrameOutput o) {
  switch (o) {
    case v1::FRAME_OUTPUT_POSE:
      return "pose";
    case v1::FRAME_OUTPUT_KEYFRAME:
      return "keyframes";
    case v1::FRAME_OUTPUT_ENTROPY_MASK:
      return "entropy masks";
    case v1::FRAME_OUTPUT_CLASS_LABELS:
      return "class labels";
    case v1::FRAME_OUTPUT_PLACE_MATCHES:
      return "place matches";
    case v1::FRAME_OUTPUT_SEMANTIC_FUSION:
      return "semantic fusion";
    case v1::FRAME_OUTPUT_MOVED_ZONES:
      return "moved zones";
    default:
      // An output of a newer server: its API name rather than "?".
      return v1::FrameOutput_IsValid(o) ? v1::FrameOutput_Name(o) : std::to_string(o);
  }
}

}  // namespace

v1::Pose PoseProto(const Pose& T_world_camera) {
  const auto& t = T_world_camera.translation;
  const auto& q = T_world_camera.rotation;
  v1::Pose p;
  p.set_tx(t.x()), p.set_ty(t.y()), p.set_tz(t.z());
  p.set_qx(q.x()), p.set_qy(q.y()), p.set_qz(q.z()), p.set_qw(q.w());
  return p;
}

v1::CameraIntrinsics IntrinsicsProto(const CameraIntrinsics& k) {
  v1::CameraIntrinsics out;
  out.set_fx(k.fx), out.set_fy(k.fy), out.set_cx(k.cx), out.set_cy(k.cy);
  out.set_width(static_cast<uint32_t>(k.width));
  out.set_height(static_cast<uint32_t>(k.height));
  return out;
}

absl::StatusOr<v1::CameraIntrinsics> ParseIntrinsicsFlag(const std::string& text, int width,
                                                         int height) {
  std::vector<std::string> parts = absl::StrSplit(text, ',');
  if (parts.size() != 4) {
    return absl::InvalidArgumentError(
        absl::StrCat("--intrinsics must be FX,FY,CX,CY (four numbers), got '", text, "'"));
  }
  double v[4];
  for (size_t i = 0; i < 4; ++i) {
    char* end = nullptr;
    v[i] = std::strtod(parts[i].c_str(), &end);
    if (end == parts[i].c_str() || *end != '\0') {
      return absl::InvalidArgumentError(
          absl::StrCat("--intrinsics: '", parts[i], "' is not a number"));
    }
  }
  v1::CameraIntrinsics k;
  k.set_fx(v[0]);
  k.set_fy(v[1]);
  k.set_cx(v[2]);
  k.set_cy(v[3]);
  k.set_width(static_cast<uint32_t>(width));
  k.set_height(static_cast<uint32_t>(height));
  return k;
}

absl::StatusOr<std::unique_ptr<client::Client>> CliContext::Connect() const {
  return ConnectTo(server);
}

absl::StatusOr<std::unique_ptr<client::Client>> CliContext::ConnectTo(
    const std::string& target) const {
  client::ClientOptions options;
  options.target = target;
  options.connect_timeout_s = timeout_s;
  auto key = client::ResolveApiKey(api_key, api_key_file);
  if (!key.ok()) return key.status();
  options.api_key = *key;
  options.tls = tls;
  options.tls_ca_file = tls_ca;
  options.tls_cert_file = tls_cert;
  options.tls_key_file = tls_key;
  return client::Client::Connect(options);
}

std::string RoleName(v1::Role role) {
  switch (role) {
    case v1::ROLE_ROBOT:
      return "robot";
    case v1::ROLE_OPERATOR:
      return "operator";
    case v1::ROLE_ADMIN:
      return "admin";
    default:
      return "unknown";
  }
}

void AddServerCommands(CLI::App* app, CliContext* ctx) {
  auto* server = app->add_subcommand("server", "About the server");
  server->require_subcommand(1);
  server->add_subcommand("info", "Version, limits and the per-frame outputs it computes")
      ->callback([ctx] {
        ctx->run = [ctx] {
          return RunCall<v1::ServerInfo>(
              *ctx, [](client::Client& c) { return c.GetServerInfo(); },
              [ctx](const v1::ServerInfo& info) {
                std::cout << absl::StrFormat(
                    "lifemapd %s (%s) at %s\ndatabase:  %s (schema %d)\nstarted:   %s\n"
                    "limits:    %s per message, %d streams, %d frames in flight per stream\n"
                    "per-frame outputs:\n",
                    info.version(), info.api_version(), ctx->server, info.db_path(),
                    info.schema_version(), HumanTime(info.started_time_s()),
                    HumanBytes(info.max_message_bytes()), info.max_streams(),
                    info.max_inflight_frames());
                for (const auto& o : info.outputs()) {
                  std::cout << absl::StrFormat("  %-16s %s\n", OutputName(o.output()),
                                               o.computed() ? "yes" : "no: " + o.reason());
                }
                std::cout << "transport: " << (info.tls() ? "TLS" : "plaintext") << "\nauth:      "
                          << (info.auth_required()
                                  ? absl::StrCat("API keys required; you are '", info.caller_key(),
                                                 "' (", RoleName(info.caller_role()), ")")
                                  : std::string("none (every caller may do everything)"))
                          << "\n";
              });
        };
      });
}

// `lifemap maps rebuild-octree`.
void AddRebuildOctreeCommand(CLI::App* maps, CliContext* ctx) {
  auto* rebuild = maps->add_subcommand(
      "rebuild-octree",
      "Rebuild visits' semantic octrees from their stored keyframes (missing or stale ones, or "
      "--all)");
  auto req = std::make_shared<v1::RebuildSemanticOctreesRequest>();
  rebuild->add_option("NAME", *req->mutable_map(), "map name")->required();
  rebuild->add_option_function<uint64_t>(
      "--visit", [req](uint64_t v) { req->set_visit_id(v); }, "only this visit");
  rebuild->add_flag_function(
      "--all", [req](int64_t n) { req->set_all(n > 0); },
      "also visits whose octree is up to date (after pose-graph corrections, say)");
  rebuild->callback([ctx, req] {
    ctx->run = [ctx, req] {
      auto c = ctx->Connect();
      if (!c.ok()) return Fail(c.status());
      int counts[4] = {0, 0, 0, 0};
      const absl::Status s =
          (*c)->RebuildSemanticOctrees(*req, [&](const v1::SemanticOctreeRebuild& r) {
            ++counts[std::clamp(static_cast<int>(r.outcome()), 0, 3)];
            if (ctx->json) {  // JSON Lines: one object per visit, then the summary
              std::cout << ToJson(r, false) << std::endl;
              return;
            }
            switch (r.outcome()) {
              case v1::SemanticOctreeRebuild::OUTCOME_REBUILT:
                std::cout << absl::StrFormat(
                    "visit %d: rebuilt from %d keyframes (%d skipped) by '%s': %d labelled "
                    "voxels, %s, %.1f s (%s)\n",
                    r.visit_id(), r.keyframes_fused(), r.keyframes_skipped(), r.model(),
                    r.labelled_voxels(), HumanBytes(r.bytes()), r.seconds(), r.reason());
                break;
              case v1::SemanticOctreeRebuild::OUTCOME_UP_TO_DATE:
                std::cout << absl::StrFormat("visit %d: up to date: %s\n", r.visit_id(),
                                             r.reason());
                break;
              default:
                std::cout << absl::StrFormat("visit %d: left out: %s\n", r.visit_id(), r.reason());
            }
            std::cout.flush();
          });
      if (!s.ok()) return Fail(s);
      if (ctx->json) {
        std::cout << nlohmann::json{{"summary",
                                     {{"rebuilt", counts[1]},
                                      {"up_to_date", counts[2]},
                                      {"left_out", counts[3]}}}}
                         .dump()
                  << "\n";
      } else {
        std::cout << absl::StrFormat("%d rebuilt, %d up to date, %d left out\n", counts[1],
                                     counts[2], counts[3]);
      }
      return 0;
    };
  });
}

// `maps export` / `maps import`: a whole map moved as one archive (issue 37).
void AddMapArchiveCommands(CLI::App* maps, CliContext* ctx) {
  auto* exp = maps->add_subcommand(
      "export",
      "Write a whole map (visits, keyframes, poses, anchors, plans, octrees, its model) to one "
      "checksummed archive for `lifemap maps import` on this or another server");
  auto name = std::make_shared<std::string>();
  auto out = std::make_shared<std::string>();
  exp->add_option("NAME", *name, "map name")->required();
  exp->add_option("--out", *out, "archive file to write (e.g. lab.lifemap)")->required();
  exp->callback([ctx, name, out] {
    ctx->run = [ctx, name, out]() -> int {
      v1::ExportMapRequest req;
      req.set_map(*name);
      req.set_format(v1::EXPORT_MAP_ARCHIVE);
      auto c = ctx->Connect();
      if (!c.ok()) return Fail(c.status());
      uint64_t keyframes = 0;
      auto s = WriteFileAtomically(*out, [&](std::ostream* o) -> absl::Status {
        auto n = (*c)->ExportMap(req, o);
        if (!n.ok()) return n.status();
        keyframes = *n;
        return absl::OkStatus();
      });
      if (!s.ok()) return Fail(s);
      const auto bytes = fs::file_size(*out);
      if (ctx->json) {
        std::cout << nlohmann::json{{"out", *out},
                                    {"map", *name},
                                    {"keyframes", keyframes},
                                    {"bytes", bytes}}
                         .dump()
                  << "\n";
      } else {
        std::cout << "wrote map '" << *name << "' (" << keyframes << " keyframes, "
                  << HumanBytes(bytes) << ") to " << *out
                  << "\nimport it with: lifemap maps import " << *out << " [--rename NAME]\n";
      }
      return 0;
    };
  });

  auto* imp = maps->add_subcommand(
      "import", "Add a map from an archive `lifemap maps export` wrote (all of it, or nothing)");
  auto file = std::make_shared<std::string>();
  auto rename = std::make_shared<std::string>();
  imp->add_option("FILE", *file, "the archive")->required()->check(CLI::ExistingFile);
  imp->add_option("--rename", *rename,
                  "import the map under this name (default: the name it was exported under)");
  imp->callback([ctx, file, rename] {
    ctx->run = [ctx, file, rename] {
      std::ifstream in(*file, std::ios::binary);
      if (!in) return Fail(absl::NotFoundError("cannot read " + *file));
      return RunCall<v1::Map>(
          *ctx, [&](client::Client& c) { return c.ImportMap(&in, *rename); },
          [](const v1::Map& m) {
            std::cout << "imported map '" << m.name() << "' (id " << m.id()
                      << "): " << m.visit_count() << " visits, " << m.keyframe_count()
                      << " keyframes\n";
          });
    };
  });
}

void AddMapCommands(CLI::App* app, CliContext* ctx) {
  auto* maps = app->add_subcommand("maps", "Create, list, inspect, rename and delete maps");
  AddMapsMoveCommand(maps, ctx);
  maps->require_subcommand(1);

  auto* create = maps->add_subcommand("create", "Create an empty map");
  auto name = std::make_shared<std::string>();
  auto description = std::make_shared<std::string>();
  create
      ->add_option("NAME", *name,
                   "map name: letters and digits of any script, '.', '_', '-' and single "
                   "spaces; up to 64 bytes of UTF-8 (e.g. lab, Küche, \"Büro 2\", 東京)")
      ->required();
  create->add_option("--description", *description, "free text");
  create->callback([ctx, name, description] {
    ctx->run = [ctx, name, description] {
      return RunCall<v1::Map>(
          *ctx, [&](client::Client& c) { return c.CreateMap(*name, *description); },
          [](const v1::Map& m) {
            std::cout << "created map '" << m.name() << "' (id " << m.id() << ")\n";
          });
    };
  });

  maps->add_subcommand("list", "List every map")->callback([ctx] {
    ctx->run = [ctx] {
      return RunCall<v1::ListMapsResponse>(
          *ctx, [](client::Client& c) { return c.ListMaps(); },
          [](const v1::ListMapsResponse& list) {
            for (const auto& shard : list.unreachable_shards()) {
              std::cerr << "warning: shard " << shard << "\n  its maps are missing below\n";
            }
            if (list.maps().empty()) {
              std::cout << "no maps yet: create one with 'lifemap maps create NAME'\n";
              return;
            }
            std::cout << absl::StrFormat("%-24s %6s %10s %10s  %s\n", "NAME", "VISITS", "KEYFRAMES",
                                         "STORED", "CREATED");
            for (const auto& m : list.maps()) {
              std::cout << absl::StrFormat("%-24s %6d %10d %10s  %s\n", m.name(), m.visit_count(),
                                           m.keyframe_count(), HumanBytes(m.stored_bytes()),
                                           HumanTime(m.created_time_s()));
            }
          });
    };
  });

  auto* show = maps->add_subcommand("show", "Show one map");
  auto show_name = std::make_shared<std::string>();
  show->add_option("NAME", *show_name, "map name")->required();
  show->callback([ctx, show_name] {
    ctx->run = [ctx, show_name] {
      return RunCall<v1::Map>(
          *ctx, [&](client::Client& c) { return c.GetMap(*show_name); }, PrintMap);
    };
  });

  auto* rename = maps->add_subcommand("rename", "Rename a map");
  auto old_name = std::make_shared<std::string>();
  auto new_name = std::make_shared<std::string>();
  rename->add_option("NAME", *old_name, "current name")->required();
  rename->add_option("NEW_NAME", *new_name, "new name")->required();
  rename->callback([ctx, old_name, new_name] {
    ctx->run = [ctx, old_name, new_name] {
      return RunCall<v1::Map>(
          *ctx, [&](client::Client& c) { return c.RenameMap(*old_name, *new_name); },
          [&](const v1::Map& m) {
            std::cout << "renamed map '" << *old_name << "' to '" << m.name() << "'\n";
          });
    };
  });

  auto* set = maps->add_subcommand("set", "Change a map's description or settings");
  struct SetArgs {
    std::string name, description;
    double entropy_threshold = 0;
    bool keep_original_color = false;
  };
  auto set_args = std::make_shared<SetArgs>();
  set->add_option("NAME", set_args->name, "map name")->required();
  auto* description_flag =
      set->add_option("--description", set_args->description, "new description");
  auto* threshold_flag = set->add_option(
      "--entropy-threshold", set_args->entropy_threshold,
      "neg-entropy below which superjuts are masked for this map, [0, 1]; 0 = server default");
  auto* keep_flag = set->add_option(
      "--keep-original-color", set_args->keep_original_color,
      "true: store keyframe colour as the client sent it (PNG stays PNG); false: re-encode PNG "
      "and raw colour as JPEG (the default, a fraction of the bytes)");
  set->callback([ctx, set_args, description_flag, threshold_flag, keep_flag] {
    ctx->run = [ctx, set_args, description_flag, threshold_flag, keep_flag] {
      v1::UpdateMapRequest req;
      req.set_name(set_args->name);
      if (description_flag->count() > 0) req.set_description(set_args->description);
      if (threshold_flag->count() > 0) req.set_entropy_threshold(set_args->entropy_threshold);
      if (keep_flag->count() > 0) req.set_keep_original_color(set_args->keep_original_color);
      if (!req.has_description() && !req.has_entropy_threshold() &&
          !req.has_keep_original_color()) {
        return UsageError(
            "nothing to change: give --description, --entropy-threshold or --keep-original-color");
      }
      return RunCall<v1::Map>(
          *ctx, [&](client::Client& c) { return c.UpdateMap(req); }, PrintMap);
    };
  });

  AddRebuildOctreeCommand(maps, ctx);
  AddMapArchiveCommands(maps, ctx);

  auto* del = maps->add_subcommand("delete", "Delete a map with all its visits and keyframes");
  auto del_name = std::make_shared<std::string>();
  auto yes = std::make_shared<bool>(false);
  del->add_option("NAME", *del_name, "map name")->required();
  del->add_flag("--yes", *yes, "confirm: the map's data cannot be recovered (except from backup)");
  del->callback([ctx, del_name, yes] {
    ctx->run = [ctx, del_name, yes] {
      if (!*yes) {
        return UsageError("refusing to delete map '" + *del_name +
                          "' without --yes (its visits and keyframes are deleted for good)");
      }
      return RunCall<v1::DeleteMapResponse>(
          *ctx, [&](client::Client& c) { return c.DeleteMap(*del_name); },
          [&](const v1::DeleteMapResponse& r) {
            std::cout << "deleted map '" << *del_name << "': " << r.deleted_visits() << " visits, "
                      << r.deleted_keyframes() << " keyframes\n";
          });
    };
  });
}

void AddVisitCommands(CLI::App* app, CliContext* ctx) {
  auto* visits = app->add_subcommand(
      "visits", "List, end and anchor visits of a map, and show anchor histories");
  visits->require_subcommand(1);
  auto* list = visits->add_subcommand("list", "List a map's visits");
  auto map = std::make_shared<std::string>();
  list->add_option("MAP", *map, "map name")->required();
  list->callback([ctx, map] {
    ctx->run = [ctx, map] {
      return RunCall<v1::ListVisitsResponse>(
          *ctx, [&](client::Client& c) { return c.ListVisits(*map); },
          [](const v1::ListVisitsResponse& r) {
            // LOOPS: loop closures accepted/rejected, and pose-graph solves; FRAME: the map's
            // (first visit or client poses), anchored to a visit (the agreeing matches'
            // residual), or unanchored (issue 15). RECORDED: the capture time of its first
            // stored keyframe (the data's clock); RECEIVED: when the server started the visit.
            std::cout << absl::StrFormat(
                "%6s %-16s %-20s %8s %10s %-14s %-24s  %-23s  %-23s  %s\n", "ID", "ROBOT", "LABEL",
                "FRAMES", "KEYFRAMES", "LOOPS(OK/NO/S)", "FRAME", "RECORDED", "RECEIVED", "STATE");
            for (const auto& v : r.visits()) {
              std::string frame = "map";
              if (v.frame() == v1::VISIT_FRAME_ANCHORED) {
                frame = absl::StrFormat("anchored->%d (%.1fcm)", v.anchor().to_visit(),
                                        v.anchor().residual_m() * 100);
                if (v.anchor().revisions() > 0) {
                  absl::StrAppend(&frame, " revised ", v.anchor().revisions(), "x");
                }
              } else if (v.frame() == v1::VISIT_FRAME_UNANCHORED) {
                frame = "unanchored";
              }
              std::cout << absl::StrFormat(
                  "%6d %-16s %-20s %8d %10d %-14s %-24s  %-23s  %-23s  %s\n", v.id(),
                  Shown(v.robot()), Shown(v.label()), v.frame_count(), v.keyframe_count(),
                  absl::StrCat(v.loops_accepted(), "/", v.loops_rejected(), "/",
                               v.pose_graph_solves()),
                  frame, v.data_start_time_s() > 0 ? HumanTime(v.data_start_time_s()) : "-",
                  HumanTime(v.start_time_s()), v.ended() ? "ended" : "open");
              // The evidence the anchor rests on (issue 35): its matches and checks.
              if (v.frame() == v1::VISIT_FRAME_ANCHORED && !v.anchor().evidence().empty()) {
                std::cout << absl::StrFormat("%6s anchor evidence: %s\n", "",
                                             v.anchor().evidence());
              }
              if (!v.anchor_dropped().empty()) {
                std::cout << absl::StrFormat("%6s anchor dropped: %s\n", "", v.anchor_dropped());
              }
              if (v.frames_lost() > 0) {
                std::cout << absl::StrFormat("%6s tracking lost %d of its %d frames\n", "",
                                             v.frames_lost(), v.frame_count());
              }
            }
          });
    };
  });

  auto* end = visits->add_subcommand("end", "End an open visit");
  auto visit_id = std::make_shared<uint64_t>(0);
  end->add_option("VISIT_ID", *visit_id, "visit id")->required();
  end->callback([ctx, visit_id] {
    ctx->run = [ctx, visit_id] {
      return RunCall<v1::Visit>(
          *ctx, [&](client::Client& c) { return c.EndVisit(*visit_id); },
          [](const v1::Visit& v) {
            std::cout << "ended visit " << v.id() << " of map '" << v.map() << "'\n";
          });
    };
  });

  auto* del = visits->add_subcommand(
      "delete", "Delete an ended visit with its keyframes, floor plan, octree and history");
  auto del_id = std::make_shared<uint64_t>(0);
  auto yes = std::make_shared<bool>(false);
  del->add_option("VISIT_ID", *del_id, "visit id")->required();
  del->add_flag("--yes", *yes,
                "confirm: the visit's data cannot be recovered (except from backup)");
  del->callback([ctx, del_id, yes] {
    ctx->run = [ctx, del_id, yes] {
      if (!*yes) {
        return UsageError("refusing to delete visit " + std::to_string(*del_id) +
                          " without --yes (its keyframes are deleted for good)");
      }
      return RunCall<v1::DeleteVisitResponse>(
          *ctx, [&](client::Client& c) { return c.DeleteVisit(*del_id); },
          [&](const v1::DeleteVisitResponse& r) {
            std::cout << "deleted visit " << *del_id << " of map '" << r.map()
                      << "': " << r.deleted_keyframes() << " keyframes\n";
          });
    };
  });

  // Issue 35: visits tracked before the appearance index could anchor them are retried.
  auto* anchor = visits->add_subcommand(
      "anchor",
      "Retry anchoring a map's tracked visits not in its frame (one, or every ended one) against "
      "the appearance index as it is now");
  auto anchor_map = std::make_shared<std::string>();
  auto anchor_visit = std::make_shared<uint64_t>(0);
  anchor->add_option("MAP", *anchor_map, "map name")->required();
  anchor->add_option("VISIT", *anchor_visit, "only this visit (default: every ended one)");
  auto anchor_dry = std::make_shared<bool>(false);
  anchor->add_flag("--dry-run", *anchor_dry,
                   "judge the candidates, store and anchor nothing, and show each candidate "
                   "match's verdict");
  anchor->callback([ctx, anchor_map, anchor_visit, anchor_dry] {
    ctx->run = [ctx, anchor_map, anchor_visit, anchor_dry] {
      return RunCall<v1::AnchorVisitsResponse>(
          *ctx,
          [&](client::Client& c) {
            return c.AnchorVisits(*anchor_map, *anchor_visit, *anchor_dry);
          },
          [](const v1::AnchorVisitsResponse& r) {
            if (r.attempts().empty()) {
              std::cout << "no visit to retry: every ended tracked visit is in the map's frame\n";
            }
            for (const auto& a : r.attempts()) {
              std::cout << absl::StrFormat(
                  "visit %d: %s (%d keyframes queried, %d candidate matches): %s\n", a.visit_id(),
                  a.anchored() ? absl::StrCat("anchored to visit ", a.to_visit())
                               : std::string("not anchored"),
                  a.keyframes_queried(), a.candidates(), a.reason());
              for (const auto& v : a.verdicts()) std::cout << "  " << v << "\n";
            }
          });
    };
  });

  auto* history = visits->add_subcommand(
      "history", "Show a visit's anchor history: each time it was anchored, revised or dropped");
  auto history_visit = std::make_shared<uint64_t>(0);
  history->add_option("VISIT_ID", *history_visit, "visit id")->required();
  history->callback([ctx, history_visit] {
    ctx->run = [ctx, history_visit] {
      return RunCall<v1::AnchorHistory>(
          *ctx, [&](client::Client& c) { return c.GetAnchorHistory(*history_visit); },
          [](const v1::AnchorHistory& h) {
            if (h.entries().empty()) {
              std::cout << "visit " << h.visit_id() << " of map '" << h.map()
                        << "' was never anchored\n";
              return;
            }
            // POSITION/TURN: where the entry put the visit's own frame in the map's, and by how
            // much it is rotated (for "dropped", the placement that was dropped).
            std::cout << absl::StrFormat("%-23s  %-8s  %8s  %-28s %9s  %s\n", "TIME", "ACTION",
                                         "TO", "POSITION (m)", "TURN(deg)", "WHY");
            for (const auto& e : h.entries()) {
              const auto& p = e.t_map_visit();
              Pose placed;  // the angle alone: scale-free, so the quaternion is taken as sent
              placed.rotation = Eigen::Quaterniond(p.qw(), p.qx(), p.qy(), p.qz());
              const double turn_deg = RotationAngleRad(Pose{}, placed) * 180.0 / M_PI;
              std::cout << absl::StrFormat("%-23s  %-8s  %8d  %8.3f %8.3f %8.3f   %9.1f  %s\n",
                                           HumanTime(e.time_s()), e.action(), e.to_visit(), p.tx(),
                                           p.ty(), p.tz(), turn_deg, e.reason());
            }
          });
    };
  });
}

void AddKeyframeCommands(CLI::App* app, CliContext* ctx) {
  auto* keyframes = app->add_subcommand("keyframes", "Inspect stored keyframes");
  keyframes->require_subcommand(1);
  auto* list = keyframes->add_subcommand("list", "List a map's keyframes");
  auto map = std::make_shared<std::string>();
  auto visit = std::make_shared<uint64_t>(0);
  list->add_option("MAP,--map", *map, "map name (--map MAP: deprecated, as before)")->required();
  list->add_option("--visit", *visit, "only this visit");
  list->callback([ctx, map, visit] {
    ctx->run = [ctx, map, visit] {
      return RunCall<v1::ListKeyframesResponse>(
          *ctx, [&](client::Client& c) { return c.ListKeyframes(*map, *visit); },
          [](const v1::ListKeyframesResponse& r) {
            std::cout << absl::StrFormat("%8s %6s %8s %18s %28s %-9s %10s\n", "ID", "VISIT", "SEQ",
                                         "TIMESTAMP", "POSITION (m)", "POSE", "BYTES");
            for (const auto& k : r.keyframes()) {
              const std::string position = k.has_pose()
                                               ? absl::StrFormat("%8.3f %8.3f %8.3f", k.pose().tx(),
                                                                 k.pose().ty(), k.pose().tz())
                                               : std::string("-");
              const char* source = k.pose_source() == v1::POSE_SOURCE_ESTIMATED ? "estimated"
                                   : k.pose_source() == v1::POSE_SOURCE_CLIENT  ? "client"
                                                                                : "-";
              std::cout << absl::StrFormat("%8d %6d %8d %18.6f %28s %-9s %10s\n", k.id(),
                                           k.visit_id(), k.sequence(), k.timestamp_s(), position,
                                           source, HumanBytes(k.color_bytes() + k.depth_bytes()));
            }
            std::cout << r.keyframes_size() << " keyframes\n";
          });
    };
  });

  auto* get = keyframes->add_subcommand(
      "get", "Write one stored keyframe as files: colour, depth, its entropy mask and score");
  struct GetArgs {
    std::string map, out;
    uint64_t id = 0;
  };
  auto g = std::make_shared<GetArgs>();
  get->add_option("MAP", g->map, "map name")->required();
  get->add_option("ID", g->id, "keyframe id (lifemap keyframes list)")->required();
  get->add_option("--out", g->out, "folder to write into (made if absent)")->required();
  get->footer(
      "Writes OUT/color.jpg or color.png (the stored bytes), OUT/depth.png (16-bit PNG, value / "
      "depth_scale = metres, 0 = no reading), OUT/entropy_mask.png (255 = masked) and "
      "OUT/entropy_score.png (neg-entropy x 255), computed again by the server from the stored "
      "images at the keyframe's threshold, and OUT/keyframe.json (pose, intrinsics, depth_scale, "
      "superjuts as stored).");
  get->callback([ctx, g] {
    ctx->run = [ctx, g]() -> int {
      auto c = ctx->Connect();
      if (!c.ok()) return Fail(c.status());
      auto k = (*c)->GetKeyframe(g->map, g->id);
      if (!k.ok()) return Fail(k.status());
      std::error_code ec;
      fs::create_directories(g->out, ec);
      if (ec) return Fail(absl::UnavailableError("cannot make " + g->out + ": " + ec.message()));
      const auto file = [&](const std::string& name) { return (fs::path(g->out) / name).string(); };
      const auto write = [&](const std::string& name, const std::string& bytes) {
        return WriteFileAtomically(file(name), [&](std::ostream* o) -> absl::Status {
          o->write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
          return absl::OkStatus();
        });
      };
      std::vector<std::string> written;
      const std::string color = k->color().encoding() == v1::COLOR_JPEG ? "color.jpg" : "color.png";
      if (auto s = write(color, k->color().data()); !s.ok()) return Fail(s);
      written.push_back(file(color));
      // Depth as a 16-bit PNG every tool reads (the store keeps it paletted or as PNG-16).
      std::string depth_png = k->depth().data();
      if (k->depth().encoding() == v1::DEPTH_PALETTED) {
        auto depth = DecodePalettedDepth(k->depth().data());
        if (!depth.ok()) return Fail(depth.status());
        std::vector<uchar> png;
        if (!cv::imencode(".png", *depth, png)) {
          return Fail(absl::InternalError("could not encode the depth as PNG"));
        }
        depth_png.assign(png.begin(), png.end());
      }
      if (auto s = write("depth.png", depth_png); !s.ok()) return Fail(s);
      written.push_back(file("depth.png"));
      // The masks, computed again from the stored images (nothing is stored: no map given).
      v1::ProcessFrameRequest req;
      v1::Frame* frame = req.mutable_frame();
      frame->set_sequence(k->summary().sequence());
      frame->set_timestamp_s(k->summary().timestamp_s());
      *frame->mutable_intrinsics() = k->summary().intrinsics();
      *frame->mutable_color() = k->color();
      *frame->mutable_depth() = k->depth();
      if (k->summary().has_pose()) *frame->mutable_pose() = k->summary().pose();
      req.mutable_options()->set_entropy_threshold(k->summary().entropy_threshold());
      req.mutable_options()->add_skip_outputs(v1::FRAME_OUTPUT_CLASS_LABELS);
      req.mutable_options()->add_skip_outputs(v1::FRAME_OUTPUT_SEMANTIC_FUSION);
      req.mutable_options()->add_skip_outputs(v1::FRAME_OUTPUT_MOVED_ZONES);
      auto result = (*c)->ProcessFrame(req);
      if (!result.ok()) return Fail(result.status());
      for (const auto& [name, bytes] :
           {std::pair<std::string, std::string>{"entropy_mask.png", result->entropy().mask_png()},
            {"entropy_score.png", result->entropy().score_png()}}) {
        if (bytes.empty()) continue;
        if (auto s = write(name, bytes); !s.ok()) return Fail(s);
        written.push_back(file(name));
      }
      v1::Keyframe described = *k;
      described.mutable_color()->clear_data();
      described.mutable_depth()->clear_data();
      if (auto s = write("keyframe.json", ToJson(described) + "\n"); !s.ok()) return Fail(s);
      written.push_back(file("keyframe.json"));
      if (ctx->json) {
        std::cout
            << nlohmann::json{{"keyframe_id", std::to_string(g->id)}, {"files", written}}.dump()
            << "\n";
      } else {
        std::cout << "wrote keyframe " << g->id << " of map '" << g->map << "':";
        for (const auto& w : written) std::cout << " " << w;
        std::cout << "\n";
      }
      return 0;
    };
  });
}

// map_server's YAML for a grid export (image beside it; trinary: 0 occupied, 254 free, 205
// unknown exactly as written).
std::string MapServerYaml(const v1::OccupancyGridInfo& g, const std::string& image) {
  return absl::StrFormat(
      "image: %s\nmode: trinary\nresolution: %.6f\norigin: [%.6f, %.6f, 0.0]\nnegate: 0\n"
      "occupied_thresh: 0.65\nfree_thresh: 0.196\n# lifemap: floor z %.3f m (%s), obstacles "
      "%.2f-%.2f m above it\n",
      image, g.resolution_m(), g.origin_x(), g.origin_y(), g.floor_z(),
      g.floor_estimated() ? "estimated" : "given", g.min_height_m(), g.max_height_m());
}

void AddExportCommand(CLI::App* app, CliContext* ctx) {
  auto* exp = app->add_subcommand(
      "export",
      "Export a map's poses (TUM format), cloud (PLY), occupancy (OctoMap .bt, a ROS map_server "
      "grid), semantic octree (OctoMap .ot/.bt, a labelled voxel PLY, a JSON summary) or the "
      "whole map (an archive)");
  struct Args {
    std::string map, what, out, format, class_name;
    uint64_t visit = 0;
    double voxel_m = 0.0;
    uint32_t stride = 0;
    bool visit_column = false;
    double floor_z = 0, min_height_m = 0, max_height_m = 0;
  };
  auto a = std::make_shared<Args>();
  exp->add_option("MAP,--map", a->map, "map name (--map MAP: deprecated, as before)")->required();
  exp->add_option("--what", a->what,
                  "poses | cloud | occupancy (OctoMap .bt from the depth, no model needed) | "
                  "grid (a ROS map_server .pgm + .yaml in the --out folder) | octree (semantic) | "
                  "semantic-cloud | semantic-summary | map (the whole map as an archive for "
                  "`lifemap maps import`)")
      ->required()
      ->check(CLI::IsMember({"poses", "cloud", "occupancy", "grid", "octree", "semantic-cloud",
                             "semantic-summary", "map"}));
  exp->add_option("--out", a->out, "output file (grid: a folder, made if absent)")->required();
  exp->add_option("--visit", a->visit, "only this visit");
  exp->add_option("--voxel", a->voxel_m,
                  "cloud voxel size in metres (default 0.02); occupancy and grid resolution "
                  "(default 0.05)");
  exp->add_option("--stride", a->stride,
                  "cloud, occupancy, grid: use every N-th pixel (default 4)");
  auto* floor_flag = exp->add_option(
      "--floor-z", a->floor_z,
      "grid: the floor's height in the map's frame (m; default: estimated from the depth)");
  auto* min_flag =
      exp->add_option("--min-height", a->min_height_m,
                      "grid: obstacles reach above the floor + this (m, default 0.10)");
  auto* max_flag =
      exp->add_option("--max-height", a->max_height_m,
                      "grid: ... and below the floor + this: the robot's height (m, default 1.50)");
  exp->add_flag("--visit-column", a->visit_column,
                "poses: a ninth column with each keyframe's visit id");
  exp->add_option("--format", a->format,
                  "octree: ot (ColorOcTree, class colours) or bt (OcTree, occupancy); default "
                  "from --out's extension, else ot")
      ->check(CLI::IsMember({"ot", "bt"}));
  exp->add_option("--class", a->class_name,
                  "octree, semantic-cloud: only voxels of this class (a name of the map's model)");
  exp->callback([ctx, a, floor_flag, min_flag, max_flag] {
    ctx->run = [ctx, a, floor_flag, min_flag, max_flag]() -> int {
      const bool semantic = a->what == "octree" || a->what == "semantic-cloud";
      const bool grid_flags = floor_flag->count() + min_flag->count() + max_flag->count() > 0;
      if (grid_flags && a->what != "grid") {
        return UsageError("--floor-z, --min-height and --max-height apply to --what grid only");
      }
      if (!a->format.empty() && a->what != "octree") {
        return UsageError("--format applies to --what octree only");
      }
      if (!a->class_name.empty() && !semantic) {
        return UsageError("--class applies to --what octree and semantic-cloud");
      }
      if ((a->voxel_m != 0.0 || a->stride != 0) && a->what != "cloud" && a->what != "occupancy" &&
          a->what != "grid") {
        return UsageError("--voxel and --stride apply to --what cloud, occupancy and grid only");
      }
      if (a->visit_column && a->what != "poses") {
        return UsageError("--visit-column applies to --what poses only");
      }
      v1::ExportMapRequest req;
      req.set_map(a->map);
      if (a->what == "poses") {
        req.set_format(v1::EXPORT_POSES_TUM);
      } else if (a->what == "cloud") {
        req.set_format(v1::EXPORT_CLOUD_PLY);
      } else if (a->what == "octree") {
        const bool bt =
            a->format == "bt" || (a->format.empty() && fs::path(a->out).extension() == ".bt");
        req.set_format(bt ? v1::EXPORT_OCTREE_BT : v1::EXPORT_OCTREE_OT);
      } else if (a->what == "semantic-cloud") {
        req.set_format(v1::EXPORT_SEMANTIC_CLOUD_PLY);
      } else if (a->what == "map") {
        req.set_format(v1::EXPORT_MAP_ARCHIVE);
      } else if (a->what == "occupancy") {
        req.set_format(v1::EXPORT_OCCUPANCY_OCTREE_BT);
      } else if (a->what == "grid") {
        req.set_format(v1::EXPORT_OCCUPANCY_GRID_PGM);
        if (floor_flag->count() > 0) req.mutable_grid()->set_floor_z(a->floor_z);
        req.mutable_grid()->set_min_height_m(a->min_height_m);
        req.mutable_grid()->set_max_height_m(a->max_height_m);
      } else {
        req.set_format(v1::EXPORT_SEMANTIC_SUMMARY_JSON);
      }
      req.set_visit_id(a->visit);
      req.set_voxel_size_m(a->voxel_m);
      req.set_pixel_stride(a->stride);
      req.set_class_name(a->class_name);
      req.set_visit_column(a->visit_column);
      auto c = ctx->Connect();
      if (!c.ok()) return Fail(c.status());
      uint64_t items = 0;
      std::vector<std::string> left_out;
      v1::OccupancyGridInfo grid;
      // A grid is two files in the --out folder, named after the map (map_server's pair).
      std::string file = a->out;
      if (a->what == "grid") {
        std::error_code ec;
        fs::create_directories(a->out, ec);
        if (ec) return Fail(absl::UnavailableError("cannot make " + a->out + ": " + ec.message()));
        file = (fs::path(a->out) / (a->map + ".pgm")).string();
      }
      auto s = WriteFileAtomically(file, [&](std::ostream* out) -> absl::Status {
        auto n = (*c)->ExportMap(req, out, &left_out, &grid);
        if (!n.ok()) return n.status();
        items = *n;
        return absl::OkStatus();
      });
      if (!s.ok()) return Fail(s);
      std::string yaml;
      if (a->what == "grid") {
        yaml = (fs::path(a->out) / (a->map + ".yaml")).string();
        s = WriteFileAtomically(yaml, [&](std::ostream* out) -> absl::Status {
          *out << MapServerYaml(grid, a->map + ".pgm");
          return absl::OkStatus();
        });
        if (!s.ok()) return Fail(s);
      }
      const char* unit = a->what == "poses"              ? "poses"
                         : a->what == "cloud"            ? "points"
                         : a->what == "semantic-summary" ? "visits"
                         : a->what == "map"              ? "keyframes"
                         : a->what == "grid"             ? "cells"
                                                         : "voxels";
      if (ctx->json) {
        nlohmann::json j{
            {"out", a->out}, {"what", a->what}, {"items", items}, {"left_out", left_out}};
        if (a->what == "grid") {
          j["pgm"] = file;
          j["yaml"] = yaml;
          j["grid"] = nlohmann::json::parse(ToJson(grid));
        }
        std::cout << j.dump() << "\n";
      } else if (a->what == "grid") {
        std::cout << absl::StrFormat(
            "wrote a %dx%d grid of %.3f m cells to %s and %s: %d occupied, %d free; floor at z = "
            "%.3f m (%s), obstacles %.2f-%.2f m above it\n",
            grid.width(), grid.height(), grid.resolution_m(), file, yaml, grid.occupied_cells(),
            grid.free_cells(), grid.floor_z(),
            grid.floor_estimated() ? "estimated; --floor-z to set it" : "given",
            grid.min_height_m(), grid.max_height_m());
        for (const auto& l : left_out) std::cout << "left out: " << l << "\n";
      } else {
        std::cout << "wrote " << items << " " << unit << " to " << a->out
                  << (a->visit == 0 && (a->what == "poses" || a->what == "cloud")
                          ? " (the map's frame)"
                          : "")
                  << "\n";
        for (const auto& l : left_out) std::cout << "left out: " << l << "\n";
      }
      return 0;
    };
  });
}

void AddProcessCommand(CLI::App* app, CliContext* ctx) {
  auto* process = app->add_subcommand(
      "process", "Send one frame through ProcessFrame and write what the server returned");
  struct Args {
    std::string rgb, depth, intrinsics, map, out;
    double depth_scale = 5000.0;
    double timestamp_s = 0.0;
    uint64_t visit = 0;
  };
  auto a = std::make_shared<Args>();
  process->add_option("--rgb", a->rgb, "colour image (PNG or JPEG)")
      ->required()
      ->check(CLI::ExistingFile);
  process->add_option("--depth", a->depth, "depth image (16-bit PNG)")
      ->required()
      ->check(CLI::ExistingFile);
  process->add_option("--depth-scale", a->depth_scale, "depth units per metre (TUM: 5000)");
  process->add_option("--intrinsics", a->intrinsics,
                      "FX,FY,CX,CY in pixels (default: TUM ROS default 525,525,319.5,239.5)");
  process->add_option("--timestamp", a->timestamp_s, "capture time, s (default: now)");
  process->add_option("MAP,--map", a->map,
                      "store into this map, as a visit of its own (started and ended for the "
                      "frame) unless --visit names one (--map MAP: deprecated, as before)");
  process->add_option("--visit", a->visit, "add the frame to this open visit of MAP")
      ->check(CLI::PositiveNumber);
  process->add_option("--out", a->out, "output folder (created)")->required();
  process->callback([ctx, a] {
    ctx->run = [ctx, a]() -> int {
      v1::CameraIntrinsics k;
      auto header = ProbeImage(ReadFileBytes(a->rgb).value_or(""));
      if (!header.ok()) {
        return Fail(
            absl::InvalidArgumentError(absl::StrCat(a->rgb, ": ", header.status().message())));
      }
      k.set_width(static_cast<uint32_t>(header->width));
      k.set_height(static_cast<uint32_t>(header->height));
      if (a->intrinsics.empty()) {
        const double sx = header->width / 640.0, sy = header->height / 480.0;
        k.set_fx(525.0 * sx);
        k.set_fy(525.0 * sy);
        k.set_cx(319.5 * sx);
        k.set_cy(239.5 * sy);
      } else {
        auto parsed = ParseIntrinsicsFlag(a->intrinsics, header->width, header->height);
        if (!parsed.ok()) {
          return UsageError(std::string(parsed.status().message()));
        }
        k = *parsed;
      }
      const double now = static_cast<double>(std::time(nullptr));
      auto frame = client::FrameFromFiles(a->rgb, a->depth, a->depth_scale, k,
                                          a->timestamp_s > 0 ? a->timestamp_s : now, 0);
      if (!frame.ok()) return Fail(frame.status());
      if (a->visit != 0 && a->map.empty()) return UsageError("--visit needs --map");
      auto c = ctx->Connect();
      if (!c.ok()) return Fail(c.status());
      v1::ProcessFrameRequest req;
      req.set_map(a->map);
      // A frame into a map never joins another visit unnamed (one without a pose would make a
      // posed visit "unanchored"): it gets a visit of its own, ended once it is answered.
      uint64_t own_visit = 0;
      if (!a->map.empty() && a->visit == 0) {
        v1::StartVisitRequest start;
        start.set_map(a->map);
        start.set_robot("lifemap process");
        start.set_label("one frame");
        auto visit = (*c)->StartVisit(start);
        if (!visit.ok()) return Fail(visit.status());
        own_visit = visit->id();
      }
      req.set_visit_id(a->visit != 0 ? a->visit : own_visit);
      *req.mutable_frame() = *std::move(frame);
      auto result = (*c)->ProcessFrame(req);
      if (own_visit != 0) {
        if (auto ended = (*c)->EndVisit(own_visit); !ended.ok() && result.ok()) {
          return Fail(ended.status());
        }
      }
      if (!result.ok()) return Fail(result.status());

      std::error_code ec;
      fs::create_directories(a->out, ec);
      if (ec) return Fail(absl::PermissionDeniedError(absl::StrCat("cannot create ", a->out)));
      // Images go to their own PNG files; result.json keeps every other field.
      struct Image {
        const char* file;
        std::string* bytes;
      };
      v1::FrameResult json_copy = *result;
      // A view for people: each class in its model's colour.
      std::string label_colors;
      if (!result->labels().label_png().empty()) {
        auto colors = (*c)->ListClasses(a->map);
        if (colors.ok() && colors->model() == result->labels().model()) {
          auto view = ColorizeLabels(result->labels().label_png(), *colors);
          if (view.ok()) label_colors = *std::move(view);
        }
      }
      const Image images[] = {
          {"entropy_score.png", json_copy.mutable_entropy()->mutable_score_png()},
          {"entropy_mask.png", json_copy.mutable_entropy()->mutable_mask_png()},
          {"labels.png", json_copy.mutable_labels()->mutable_label_png()},
          {"labels_confidence.png", json_copy.mutable_labels()->mutable_confidence_png()},
          {"labels_color.png", &label_colors},
      };
      std::vector<std::string> written;
      for (const auto& img : images) {
        if (img.bytes->empty()) continue;
        const std::string path = (fs::path(a->out) / img.file).string();
        auto s = WriteFileAtomically(path, [&](std::ostream* out) {
          out->write(img.bytes->data(), static_cast<std::streamsize>(img.bytes->size()));
          return absl::OkStatus();
        });
        if (!s.ok()) return Fail(s);
        img.bytes->clear();
        written.push_back(path);
      }
      const std::string json_path = (fs::path(a->out) / "result.json").string();
      auto s = WriteFileAtomically(json_path, [&](std::ostream* out) {
        *out << ToJson(json_copy) << "\n";
        return absl::OkStatus();
      });
      if (!s.ok()) return Fail(s);
      written.push_back(json_path);
      if (ctx->json) {
        std::cout << ToJson(json_copy, false) << "\n";
      } else {
        std::cout << absl::StrFormat(
            "frame %dx%d: %.1f%% valid depth, median %.3f m; server %.1f ms\n", result->width(),
            result->height(), 100.0 * result->valid_depth_fraction(), result->median_depth_m(),
            result->timing().total_ms());
        if (result->keyframe().selected()) {
          std::cout << "keyframe " << result->keyframe().keyframe_id() << " stored in map '"
                    << a->map << "', visit " << req.visit_id()
                    << (own_visit != 0 ? " (its own, ended)" : "") << "\n";
        }
        for (const auto& o : result->outputs()) {
          if (!o.computed()) {
            std::cout << OutputName(o.output()) << " not computed: " << o.reason() << "\n";
          }
        }
        if (result->has_labels()) {
          std::cout << "labels by '" << result->labels().model() << "' (mean confidence "
                    << absl::StrFormat("%.2f", result->labels().mean_confidence()) << "):";
          for (const auto& cl : result->labels().classes()) {
            std::cout << absl::StrFormat(" %s %.1f%%", cl.name(), 100.0 * cl.pixel_fraction());
          }
          std::cout << "\n";
        }
        for (const auto& w : written) std::cout << "wrote " << w << "\n";
      }
      return 0;
    };
  });
}

// "streams 2, 30 frames/s, ..." for the limits a key has; "-" for none.
std::string LimitsText(const v1::KeyLimits& l) {
  std::vector<std::string> parts;
  if (l.max_streams() > 0) parts.push_back(absl::StrCat("streams ", l.max_streams()));
  if (l.max_frames_per_s() > 0) parts.push_back(absl::StrCat(l.max_frames_per_s(), " frames/s"));
  if (l.max_maps() > 0) parts.push_back(absl::StrCat("maps ", l.max_maps()));
  if (l.max_keyframes_per_map() > 0) {
    parts.push_back(absl::StrCat("keyframes/map ", l.max_keyframes_per_map()));
  }
  if (l.max_model_bytes() > 0) parts.push_back("model " + HumanBytes(l.max_model_bytes()));
  if (l.max_visits_per_hour() > 0) {
    parts.push_back(absl::StrCat("visits/hour ", l.max_visits_per_hour()));
  }
  return parts.empty() ? "-" : absl::StrJoin(parts, ", ");
}

// `lifemap keys create|list|revoke` (admin role).
void AddKeyCommands(CLI::App* app, CliContext* ctx) {
  auto* keys = app->add_subcommand("keys", "API keys (needs an admin key)");
  keys->require_subcommand(1);
  auto* create = keys->add_subcommand("create", "Create a key; prints its secret once");
  auto req = std::make_shared<v1::CreateApiKeyRequest>();
  auto role = std::make_shared<std::string>();
  auto maps = std::make_shared<std::vector<std::string>>();
  create->add_option("NAME", *req->mutable_name(), "the key's name")->required();
  create->add_option("--role", *role, "robot, operator or admin")
      ->required()
      ->check(CLI::IsMember({"robot", "operator", "admin"}));
  create->add_option("--maps", *maps, "only these maps (comma-separated; not for admin keys)")
      ->delimiter(',');
  auto* limits = req->mutable_limits();
  create->add_option_function<uint32_t>(
      "--max-streams", [limits](uint32_t n) { limits->set_max_streams(n); },
      "frame streams it may have open at once");
  create->add_option_function<double>(
      "--max-fps", [limits](double f) { limits->set_max_frames_per_s(f); },
      "frames a second it may send (streams and single frames together)");
  create->add_option_function<uint32_t>(
      "--max-maps", [limits](uint32_t n) { limits->set_max_maps(n); },
      "maps it may have created at once");
  create->add_option_function<uint64_t>(
      "--max-keyframes-per-map", [limits](uint64_t n) { limits->set_max_keyframes_per_map(n); },
      "keyframes a map may hold for it to add another");
  create->add_option_function<uint64_t>(
      "--max-model-mb", [limits](uint64_t mb) { limits->set_max_model_bytes(mb << 20); },
      "largest model it may upload, MiB");
  create->add_option_function<uint32_t>(
      "--max-visits-per-hour", [limits](uint32_t n) { limits->set_max_visits_per_hour(n); },
      "visits it may start in any hour (default: the server's "
      "security.max_visits_per_key_per_hour)");
  create->callback([ctx, req, role, maps] {
    ctx->run = [ctx, req, role, maps] {
      req->set_role(*role == "robot"      ? v1::ROLE_ROBOT
                    : *role == "operator" ? v1::ROLE_OPERATOR
                                          : v1::ROLE_ADMIN);
      req->clear_maps();
      for (const auto& m : *maps) req->add_maps(m);
      return RunCall<v1::CreateApiKeyResponse>(
          *ctx, [&](client::Client& c) { return c.CreateApiKey(*req); },
          [](const v1::CreateApiKeyResponse& r) {
            // The secret alone on stdout (`> robot.key`); what it is on stderr.
            std::cout << r.key() << "\n";
            std::cerr << "API key '" << r.info().name() << "' (" << RoleName(r.info().role())
                      << ", "
                      << (r.info().every_map() ? std::string("every map")
                                               : "maps " + absl::StrJoin(r.info().maps(), ", "))
                      << ") created. This is the only time its secret is shown: keep it in a "
                         "file only its user can read (chmod 600).\n";
          });
    };
  });
  keys->add_subcommand("list", "Every key (revoked too), never a secret")->callback([ctx] {
    ctx->run = [ctx] {
      return RunCall<v1::ListApiKeysResponse>(
          *ctx, [](client::Client& c) { return c.ListApiKeys(); },
          [](const v1::ListApiKeysResponse& r) {
            std::cout << absl::StrFormat("%-24s %-9s %-23s %-23s %-23s %-12s %s\n", "NAME", "ROLE",
                                         "CREATED", "LAST USED", "REVOKED", "MAPS", "LIMITS");
            for (const auto& k : r.keys()) {
              std::cout << absl::StrFormat(
                  "%-24s %-9s %-23s %-23s %-23s %-12s %s\n", Shown(k.name()), RoleName(k.role()),
                  HumanTime(k.created_time_s()),
                  k.last_used_time_s() > 0 ? HumanTime(k.last_used_time_s()) : "never",
                  k.revoked_time_s() > 0 ? HumanTime(k.revoked_time_s()) : "-",
                  k.every_map() ? std::string("*") : absl::StrJoin(k.maps(), ","),
                  LimitsText(k.limits()));
            }
          });
    };
  });
  auto* revoke = keys->add_subcommand("revoke", "Refuse a key's calls from now on");
  auto name = std::make_shared<std::string>();
  revoke->add_option("NAME", *name, "the key's name")->required();
  revoke->callback([ctx, name] {
    ctx->run = [ctx, name] {
      return RunCall<v1::ApiKey>(
          *ctx, [&](client::Client& c) { return c.RevokeApiKey(*name); },
          [](const v1::ApiKey& k) {
            std::cout << "API key '" << k.name() << "' revoked at " << HumanTime(k.revoked_time_s())
                      << "\n";
          });
    };
  });
}

void AddAdminCommands(CLI::App* app, CliContext* ctx) {
  auto* admin = app->add_subcommand("admin", "Operate the server's database");
  admin->require_subcommand(1);
  AddShardsCommands(admin, ctx);
  admin->add_subcommand("stats", "Counts, database size, activity")->callback([ctx] {
    ctx->run = [ctx] {
      return RunCall<v1::Stats>(
          *ctx, [](client::Client& c) { return c.GetStats(); },
          [](const v1::Stats& s) {
            for (const auto& shard : s.unreachable_shards()) {
              std::cerr << "warning: shard " << shard << "\n  its figures are missing below\n";
            }
            std::cout << absl::StrFormat(
                "maps %d, visits %d, keyframes %d\ndatabase %s + WAL %s\nactive streams %d; "
                "since start: %d frames processed, %d rejected, %d keyframes committed; "
                "up %.0f s, %.1f s of CPU, %s resident\n",
                s.maps(), s.visits(), s.keyframes(), HumanBytes(s.db_bytes()),
                HumanBytes(s.wal_bytes()), s.active_streams(), s.frames_processed(),
                s.frames_rejected(), s.keyframes_committed(), s.uptime_s(), s.process_cpu_s(),
                HumanBytes(s.resident_bytes()));
          });
    };
  });
  auto* backup = admin->add_subcommand(
      "backup", "Online copy of the database into the server's backup directory");
  auto path = std::make_shared<std::string>();
  backup
      ->add_option("NAME", *path,
                   "the backup file's name (not a path): it is written into the server's backup "
                   "directory (storage.backup_dir) and must not exist there")
      ->required();
  backup->callback([ctx, path] {
    ctx->run = [ctx, path] {
      return RunCall<v1::BackupResponse>(
          *ctx, [&](client::Client& c) { return c.Backup(*path); },
          [](const v1::BackupResponse& r) {
            std::cout << "backup written to " << r.path() << " (" << HumanBytes(r.bytes()) << ")\n";
          });
    };
  });
  admin->add_subcommand("check", "Integrity check of the database")->callback([ctx] {
    ctx->run = [ctx] {
      return RunCall<v1::CheckIntegrityResponse>(
          *ctx, [](client::Client& c) { return c.CheckIntegrity(); },
          [](const v1::CheckIntegrityResponse& r) {
            std::cout << (r.ok() ? "integrity: ok\n" : "integrity: PROBLEMS\n");
            for (const auto& p : r.problems()) std::cout << "  " << p << "\n";
          },
          [](const v1::CheckIntegrityResponse& r) { return r.ok() ? 0 : 1; });
    };
  });
  auto* audit = admin->add_subcommand("audit", "Administrative calls: who, what, when");
  auto audit_req = std::make_shared<v1::ListAuditEventsRequest>();
  audit->add_option_function<uint32_t>(
      "--limit", [audit_req](uint32_t n) { audit_req->set_limit(n); },
      "newest events to show (default 100, at most 10000)");
  audit->add_option_function<double>(
      "--since", [audit_req](double t) { audit_req->set_since_time_s(t); },
      "only events at or after this time (seconds since the Unix epoch)");
  audit->callback([ctx, audit_req] {
    ctx->run = [ctx, audit_req] {
      return RunCall<v1::ListAuditEventsResponse>(
          *ctx, [&](client::Client& c) { return c.ListAuditEvents(*audit_req); },
          [](const v1::ListAuditEventsResponse& r) {
            for (const auto& e : r.events()) {
              std::cout << absl::StrFormat(
                  "%s  %-16s %-36s %-18s %s%s\n", HumanTime(e.time_s()), Shown(e.key()),
                  Shown(e.method()), Shown(e.code()), Shown(e.request(), ""),
                  e.message().empty() ? "" : "  (" + Shown(e.message()) + ")");
            }
          });
    };
  });
  auto retention_req = std::make_shared<v1::ApplyRetentionRequest>();
  CLI::App* retention = admin->add_subcommand(
      "retention",
      "Thin the keyframes of a map's older visits that add no view (docs/OPERATIONS.md "
      "\"Retention\"); --dry-run says what would be removed and why");
  retention->add_option("map", *retention_req->mutable_map(), "map")->required();
  retention->add_flag_function(
      "--dry-run", [retention_req](int64_t) { retention_req->set_dry_run(true); },
      "remove nothing: say what would be removed and why");
  auto list_thinned = std::make_shared<bool>(false);
  retention->add_flag("--list", *list_thinned,
                      "list every keyframe thinned and the keyframe that covers it");
  v1::RetentionPolicy* policy = retention_req->mutable_policy();
  retention->add_option_function<double>(
      "--cover-m", [policy](double v) { policy->set_cover_m(v); },
      "a keyframe within this many metres ... (default: config retention.cover_m)");
  retention->add_option_function<double>(
      "--cover-deg", [policy](double v) { policy->set_cover_deg(v); },
      "... and degrees of a kept one covers its view (retention.cover_deg)");
  retention->add_option_function<uint32_t>(
      "--keep-recent", [policy](uint32_t v) { policy->set_keep_recent_visits(v); },
      "newest visits in the map's frame kept whole (retention.keep_recent_visits)");
  retention->add_option_function<uint32_t>(
      "--compact-after", [policy](uint32_t v) { policy->set_compact_after_visits(v); },
      "visits with this many later ones are compacted (retention.compact_after_visits)");
  retention->add_option_function<uint32_t>(
      "--recognised-within", [policy](uint32_t v) { policy->set_recognised_within_visits(v); },
      "keep keyframes one of the N newest visits recognised (retention.recognised_within_visits)");
  retention->add_option_function<double>(
      "--compact-cover-m", [policy](double v) { policy->set_compact_cover_m(v); },
      "cover distance for compacted visits (retention.compact_cover_m)");
  retention->add_option_function<double>(
      "--compact-cover-deg", [policy](double v) { policy->set_compact_cover_deg(v); },
      "cover rotation for compacted visits (retention.compact_cover_deg)");
  retention->callback([ctx, retention_req, list_thinned] {
    ctx->run = [ctx, retention_req, list_thinned] {
      return RunCall<v1::RetentionReport>(
          *ctx, [&](client::Client& c) { return c.ApplyRetention(*retention_req); },
          [list_thinned](const v1::RetentionReport& r) {
            const auto& p = r.policy();
            std::cout << absl::StrFormat(
                "map '%s'%s: covered within %.2f m / %.0f°, %u newest visits kept whole, "
                "visits with %u later ones compacted (%.2f m / %.0f°)\n",
                r.map(), r.dry_run() ? " (dry run: nothing removed)" : "", p.cover_m(),
                p.cover_deg(), p.keep_recent_visits(), p.compact_after_visits(),
                p.compact_cover_m(), p.compact_cover_deg());
            std::cout << absl::StrFormat("%-8s %9s %9s %11s  %s\n", "visit", "keyframes",
                                         r.dry_run() ? "would go" : "thinned", "bytes", "why kept");
            for (const auto& v : r.visits()) {
              std::string why = v.kept_whole();
              if (why.empty()) {
                std::map<std::string, uint64_t> sorted(v.kept_because().begin(),
                                                       v.kept_because().end());
                for (const auto& [reason, n] : sorted) {
                  why += absl::StrCat(why.empty() ? "" : "; ", n, " ", reason);
                }
                if (v.compacted()) why = "compacted; " + why;
              }
              std::cout << absl::StrFormat("%-8d %9d %9d %11s  %s\n", v.visit_id(), v.keyframes(),
                                           v.thinned(), HumanBytes(v.bytes_freed()), why);
            }
            if (*list_thinned) {
              for (const auto& t : r.thinned()) {
                std::cout << absl::StrFormat(
                    "  keyframe %d (visit %d): covered by keyframe %d (visit %d), %.2f m, "
                    "%.1f°\n",
                    t.keyframe_id(), t.visit_id(), t.covered_by(), t.covered_by_visit(),
                    t.distance_m(), t.angle_deg());
              }
            }
            std::cout << absl::StrFormat(
                "%d keyframes %s; map %s -> %s (%d -> %d keyframes) in %.2f s%s\n",
                r.thinned_size(), r.dry_run() ? "would be thinned" : "thinned",
                HumanBytes(r.before().total_bytes()), HumanBytes(r.after().total_bytes()),
                r.before().keyframes(), r.after().keyframes(), r.seconds(),
                r.dry_run() || r.thinned_size() == 0
                    ? ""
                    : "; `lifemap admin vacuum` returns the freed pages to the file system");
          });
    };
  });
  admin->add_subcommand("vacuum", "Compact the database file")->callback([ctx] {
    ctx->run = [ctx] {
      return RunCall<v1::VacuumResponse>(
          *ctx, [](client::Client& c) { return c.Vacuum(); },
          [](const v1::VacuumResponse& r) {
            std::cout << "database " << HumanBytes(r.bytes_before()) << " -> "
                      << HumanBytes(r.bytes_after()) << "\n";
          });
    };
  });
}

}  // namespace lifemap::cli
