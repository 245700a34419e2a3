// `lifemap maps move MAP --to SHARD` (issue 39): a map moved between the shards of a cluster,
// with nothing lost if any step is killed. The placement database records each phase before
// the next step (server/placement/placement.h, MapPlacement), so running the command again
// finishes a move that was cut short, and `--abort` undoes one that has not switched yet.
//
//   1 frozen   the source refuses writes to the map, ends its streams (they reconnect) and
//              waits for the writes running (RefreshPlacement); the map is exported from the
//              source and imported into the target keeping its ids and open visits
//              (ImportChunk.keep_ids), replacing a copy an earlier attempt left there
//   2 copied   the placement switches the map to the target; both shards read it; nginx's table
//              is rewritten (--reload-command)
//   3 switched the source's copy is deleted; the move is over
//
// The shards are called at their own addresses (from the placement), not through nginx.
#include <signal.h>
#include <unistd.h>

#include <chrono>
#include <cstdlib>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "client/cli/commands.h"
#include "server/placement/placement.h"

namespace lifemap::cli {
namespace {

using Clock = std::chrono::steady_clock;

struct MoveArgs {
  std::string map;
  std::string to;
  std::string placement;  // else $LIFEMAP_PLACEMENT
  std::string reload_command;
  std::string work_dir;  // where the archive is kept while it moves
  bool abort = false;
};

// Fault injection for the tests (tests/cluster): LIFEMAP_MOVE_STOP_AFTER=STEP kills this
// process (SIGKILL) right after STEP, as a crash or an operator's kill -9 would.
void MaybeDieAfter(const char* step) {
  const char* stop = std::getenv("LIFEMAP_MOVE_STOP_AFTER");
  if (stop != nullptr && std::string(stop) == step) {
    std::cerr << "LIFEMAP_MOVE_STOP_AFTER=" << step << ": killed\n" << std::flush;
    raise(SIGKILL);
  }
}

class Mover {
 public:
  Mover(const CliContext& ctx, const MoveArgs& args, placement::Placement* placement)
      : ctx_(ctx), args_(args), placement_(placement), t0_(Clock::now()) {}

  absl::Status Run() {
    auto lock = placement_->LockMove(args_.map);
    if (!lock.ok()) return lock.status();
    auto found = placement_->FindMap(args_.map);
    if (!found.ok()) return found.status();
    if (!found->has_value()) {
      return absl::NotFoundError(
          absl::StrCat("map '", args_.map, "' is not placed on any shard (lifemap maps list)"));
    }
    placement::MapPlacement m = **found;
    map_ = m.map;
    auto shards = placement_->ListShards();
    if (!shards.ok()) return shards.status();
    for (const auto& s : *shards) shards_[s.name] = s;

    if (args_.abort) return Abort(m);
    if (m.state == "active") {
      if (m.shard == args_.to) {
        Say(absl::StrCat("map '", map_, "' is on shard '", m.shard, "' already"));
        return absl::OkStatus();
      }
      if (auto s = CheckUp(m.shard, "source"); !s.ok()) return s;
      if (auto s = CheckUp(args_.to, "target"); !s.ok()) return s;
      if (auto s = placement_->BeginMove(map_, args_.to, Now()); !s.ok()) return s;
      Say(absl::StrCat("moving map '", map_, "' from shard '", m.shard, "' to '", args_.to,
                       "': writes to it are refused until it is there"));
      MaybeDieAfter("begun");
      m.move_phase = "frozen";
      m.move_to = args_.to;
    } else {
      const std::string target = m.move_phase == "switched" ? m.shard : m.move_to;
      if (target != args_.to) {
        return absl::FailedPreconditionError(
            absl::StrCat("map '", map_, "' is already moving to shard '", target, "' (phase ",
                         m.move_phase, "): finish that move with --to ", target,
                         m.move_phase == "switched" ? "" : ", or undo it with --abort"));
      }
      Say(absl::StrCat("resuming the move of map '", map_, "' to shard '", target, "' at phase ",
                       m.move_phase));
    }
    const std::string source = m.move_phase == "switched" ? m.move_from : m.shard;
    if (m.move_phase == "frozen") {
      if (auto s = Copy(source, args_.to); !s.ok()) return s;
      if (auto s = placement_->AdvanceMove(map_, "frozen"); !s.ok()) return s;
      m.move_phase = "copied";
    }
    bool switched_now = false;
    if (m.move_phase == "copied") {
      if (auto s = placement_->AdvanceMove(map_, "copied"); !s.ok()) return s;
      switched_now = true;
      MaybeDieAfter("switched");
      m.move_phase = "switched";
      auto served = Refresh(args_.to);
      if (!served.ok()) return served.status();
      if (*served != "serving") {
        return absl::InternalError(
            absl::StrCat("shard '", args_.to, "' says the map is ", *served, " after the switch"));
      }
      // The source may be down by now: it reads the placement when it starts.
      if (auto moved = Refresh(source); !moved.ok()) {
        Say(absl::StrCat("warning: shard '", source, "' did not take the switch now (",
                         moved.status().message(), "); it refuses the map when it reads it"));
      }
      if (auto s = ReloadNginx(); !s.ok()) return s;
      Say(absl::StrCat("switched: shard '", args_.to, "' serves map '", map_, "' (",
                       absl::StrFormat("%.1f s", Elapsed()), ")"));
    }
    if (m.move_phase == "switched") {
      if (!switched_now) {
        // A move cut after its switch: the table nginx has may still send the map's calls to
        // the source. Write it again before anything else.
        if (auto r = Refresh(args_.to); !r.ok()) return r.status();
        if (auto s = ReloadNginx(); !s.ok()) return s;
        if (auto r = Refresh(source); !r.ok()) return Unfinished(source, r.status());
      }
      auto src = Connect(source);
      if (!src.ok()) return Unfinished(source, src.status());
      if (auto d = (*src)->DeleteMap(map_); !d.ok() && !absl::IsNotFound(d.status())) {
        return Unfinished(source, d.status());
      }
      MaybeDieAfter("deleted");
      if (auto s = placement_->AdvanceMove(map_, "switched"); !s.ok()) return s;
      if (auto r = Refresh(source); !r.ok()) {
        Say(absl::StrCat("warning: shard '", source, "': ", r.status().message()));
      }
      Say(absl::StrCat("done: map '", map_, "' lives on shard '", args_.to, "' (",
                       absl::StrFormat("%.1f s", Elapsed()), ")"));
    }
    return absl::OkStatus();
  }

 private:
  // Step 1: drain the source, export, import into the target with its ids.
  absl::Status Copy(const std::string& source, const std::string& target) {
    auto frozen = Refresh(source);
    if (!frozen.ok()) return frozen.status();
    if (*frozen != "frozen") {
      return absl::InternalError(
          absl::StrCat("shard '", source, "' says the map is ", *frozen, ", not frozen"));
    }
    Say(absl::StrCat("shard '", source, "' drained its writes (",
                     absl::StrFormat("%.1f s", Elapsed()), ")"));
    MaybeDieAfter("drained");
    auto src = Connect(source);
    if (!src.ok()) return src.status();
    auto tgt = Connect(target);
    if (!tgt.ok()) return tgt.status();
    if (auto arriving = (*tgt)->RefreshPlacement(map_); !arriving.ok()) return arriving.status();
    std::string dir = args_.work_dir;
    if (dir.empty()) dir = std::filesystem::temp_directory_path().string();
    const std::string path = absl::StrCat(dir, "/lifemap-move-", map_, "-", getpid(), ".archive");
    struct Remove {
      std::string path;
      ~Remove() {
        std::error_code ec;
        std::filesystem::remove(path, ec);
      }
    } remove{path};
    {
      std::ofstream out(path, std::ios::binary | std::ios::trunc);
      if (!out) return absl::UnavailableError(absl::StrCat("cannot write ", path));
      v1::ExportMapRequest req;
      req.set_map(map_);
      req.set_format(v1::EXPORT_MAP_ARCHIVE);
      if (auto n = (*src)->ExportMap(req, &out); !n.ok()) return n.status();
      out.flush();
      if (!out) return absl::UnavailableError(absl::StrCat("cannot write ", path));
    }
    const auto bytes = std::filesystem::file_size(path);
    Say(absl::StrCat("exported from '", source, "': ", HumanBytes(bytes), " (",
                     absl::StrFormat("%.1f s", Elapsed()), ")"));
    MaybeDieAfter("exported");
    // A copy an earlier, cut attempt left on the target goes first.
    if (auto d = (*tgt)->DeleteMap(map_); !d.ok() && !absl::IsNotFound(d.status())) {
      return d.status();
    }
    std::ifstream in(path, std::ios::binary);
    auto imported = (*tgt)->ImportMap(&in, map_, /*keep_ids=*/true);
    if (!imported.ok()) return imported.status();
    Say(absl::StrCat("imported into '", target, "': ", imported->visit_count(), " visits, ",
                     imported->keyframe_count(), " keyframes (",
                     absl::StrFormat("%.1f s", Elapsed()), ")"));
    MaybeDieAfter("imported");
    return absl::OkStatus();
  }

  absl::Status Abort(const placement::MapPlacement& m) {
    if (m.state == "active") {
      return absl::FailedPreconditionError(
          absl::StrCat("map '", map_, "' is not moving (it is on shard '", m.shard, "')"));
    }
    if (m.move_phase == "switched") {
      return absl::FailedPreconditionError(absl::StrCat(
          "map '", map_, "' has switched to shard '", m.shard,
          "' already: finish the move (lifemap maps move ", map_, " --to ", m.shard, ")"));
    }
    if (auto s = placement_->AbortMove(map_); !s.ok()) return s;
    if (auto r = Refresh(m.shard); !r.ok()) {
      Say(absl::StrCat("warning: shard '", m.shard, "': ", r.status().message()));
    }
    if (auto tgt = Connect(m.move_to); tgt.ok()) {
      if (auto d = (*tgt)->DeleteMap(map_); !d.ok() && !absl::IsNotFound(d.status())) {
        Say(absl::StrCat("warning: the copy on shard '", m.move_to,
                         "' could not be deleted: ", d.status().message()));
      }
      (void)(*tgt)->RefreshPlacement(map_);
    }
    Say(absl::StrCat("move aborted: map '", map_, "' stays on shard '", m.shard,
                     "' and takes writes again"));
    return absl::OkStatus();
  }

  absl::Status CheckUp(const std::string& shard, const char* role) {
    const auto it = shards_.find(shard);
    if (it == shards_.end()) {
      return absl::NotFoundError(absl::StrCat("shard '", shard,
                                              "' is not in the placement database (lifemap "
                                              "admin shards list)"));
    }
    if (!it->second.Up(Now())) {
      return absl::UnavailableError(absl::StrCat(
          "the ", role, " shard '", shard, "' (", it->second.address, ") is down (",
          it->second.seen_s > 0 ? absl::StrFormat("last seen %.0f s ago", Now() - it->second.seen_s)
                                : std::string("never started"),
          "): nothing was changed; move the map once it is up"));
    }
    return absl::OkStatus();
  }

  absl::StatusOr<std::unique_ptr<client::Client>> Connect(const std::string& shard) {
    const auto it = shards_.find(shard);
    if (it == shards_.end()) {
      return absl::NotFoundError(absl::StrCat("shard '", shard, "' is not in the placement"));
    }
    return ctx_.ConnectTo(it->second.address);
  }

  absl::StatusOr<std::string> Refresh(const std::string& shard) {
    auto c = Connect(shard);
    if (!c.ok()) return c.status();
    auto r = (*c)->RefreshPlacement(map_);
    if (!r.ok()) {
      return absl::Status(r.status().code(),
                          absl::StrCat("shard '", shard, "': ", r.status().message()));
    }
    return r->map_phase();
  }

  absl::Status ReloadNginx() {
    if (args_.reload_command.empty()) {
      Say("no --reload-command: regenerate nginx's table now (lifemap admin shards "
          "nginx-config ... --reload-command ...); until then the source answers UNAVAILABLE "
          "for the map");
      return absl::OkStatus();
    }
    const int rc = std::system(args_.reload_command.c_str());
    if (rc != 0) {
      return absl::UnavailableError(
          absl::StrCat("the map has switched, but the reload command failed (", rc,
                       "): ", args_.reload_command, "; fix it and run the move again to finish"));
    }
    MaybeDieAfter("reloaded");
    return absl::OkStatus();
  }

  absl::Status Unfinished(const std::string& source, const absl::Status& why) {
    return absl::Status(why.code(),
                        absl::StrCat("map '", map_, "' is served by shard '", args_.to,
                                     "', but its copy on shard '", source, "' was not deleted (",
                                     why.message(), "): run the move again when that shard is up"));
  }

  void Say(const std::string& line) {
    if (!ctx_.json) std::cerr << line << "\n";
  }
  double Elapsed() const { return std::chrono::duration<double>(Clock::now() - t0_).count(); }
  static double Now() { return static_cast<double>(std::time(nullptr)); }

  const CliContext& ctx_;
  const MoveArgs& args_;
  placement::Placement* placement_;
  const Clock::time_point t0_;
  std::string map_;
  std::map<std::string, placement::Shard> shards_;
};

}  // namespace

void AddMapsMoveCommand(CLI::App* maps, CliContext* ctx) {
  auto a = std::make_shared<MoveArgs>();
  auto* move = maps->add_subcommand(
      "move", "Move a map to another shard of a cluster (nothing lost if any step is killed)");
  move->add_option("MAP", a->map, "the map")->required();
  move->add_option("--to", a->to, "the shard it goes to")->required();
  move->add_option("--placement", a->placement,
                   "placement database, postgresql://USER@HOST:PORT/DB (else $LIFEMAP_PLACEMENT)");
  move->add_option("--reload-command", a->reload_command,
                   "run after the switch to rewrite and reload nginx's table, e.g. \"lifemap "
                   "admin shards nginx-config --out F ... --reload-command 'nginx -s reload'\"");
  move->add_option("--work-dir", a->work_dir,
                   "where the map's archive waits between export and import (default: $TMPDIR)");
  move->add_flag("--abort", a->abort,
                 "undo a move that has not switched yet: the map stays where it was");
  move->callback([ctx, a] {
    ctx->run = [ctx, a] {
      auto p = OpenPlacement(a->placement);
      if (!p.ok()) return Fail(p.status());
      Mover mover(*ctx, *a, p->get());
      if (auto s = mover.Run(); !s.ok()) return Fail(s);
      if (ctx->json) {
        auto where = (*p)->FindMap(a->map);
        nlohmann::json out = {{"map", a->map}};
        if (where.ok() && where->has_value()) {
          out["shard"] = (*where)->shard;
          out["state"] = (*where)->state;
        }
        std::cout << out.dump() << "\n";
      }
      return 0;
    };
  });
}

}  // namespace lifemap::cli
