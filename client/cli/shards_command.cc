// `lifemap admin shards list|add|drain|activate|remove|nginx-config` (issue 39): the cluster's
// placement database, read and written directly (PostgreSQL, --placement or
// $LIFEMAP_PLACEMENT), not through a server: it is what says where the servers are.
#include <unistd.h>

#include <cstdio>
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
#include "server/placement/nginx_config.h"
#include "server/placement/placement.h"

namespace lifemap::cli {
namespace {

double Now() { return static_cast<double>(std::time(nullptr)); }

struct ShardFlags {
  std::string placement;  // --placement, else $LIFEMAP_PLACEMENT
  absl::StatusOr<std::unique_ptr<placement::Placement>> Open() const {
    return OpenPlacement(placement);
  }
};

int PrintShards(const CliContext& ctx, placement::Placement& p) {
  auto shards = p.ListShards();
  if (!shards.ok()) return Fail(shards.status());
  auto maps = p.ListMaps("");
  if (!maps.ok()) return Fail(maps.status());
  std::map<std::string, int> count;
  for (const auto& m : *maps) ++count[m.shard];
  const double now = Now();
  if (ctx.json) {
    nlohmann::json out = nlohmann::json::array();
    for (const auto& s : *shards) {
      out.push_back({{"name", s.name},
                     {"address", s.address},
                     {"state", s.state},
                     {"up", s.Up(now)},
                     {"seen_age_s", s.seen_s > 0 ? now - s.seen_s : -1.0},
                     {"maps", count[s.name]}});
    }
    std::cout << out.dump() << "\n";
    return 0;
  }
  std::cout << absl::StrFormat("%-16s %-22s %-9s %-5s %10s %6s\n", "SHARD", "ADDRESS", "STATE",
                               "UP", "SEEN", "MAPS");
  for (const auto& s : *shards) {
    std::cout << absl::StrFormat(
        "%-16s %-22s %-9s %-5s %10s %6d\n", s.name, s.address, s.state, s.Up(now) ? "up" : "DOWN",
        s.seen_s > 0 ? absl::StrFormat("%.0f s ago", now - s.seen_s) : "never", count[s.name]);
  }
  for (const auto& m : *maps) {
    if (m.state == "moving") {
      std::cout << absl::StrFormat("map %s moving %s -> %s (%s)\n", m.map, m.shard, m.move_to,
                                   m.move_phase);
    }
  }
  return 0;
}

// Written beside the target and renamed over it: nginx never reads half a file.
absl::Status WriteAtomically(const std::string& path, const std::string& text) {
  const std::string tmp = absl::StrCat(path, ".tmp.", getpid());
  {
    std::ofstream out(tmp, std::ios::binary | std::ios::trunc);
    out << text;
    out.flush();
    if (!out) return absl::UnavailableError(absl::StrCat("cannot write ", tmp));
  }
  std::error_code ec;
  std::filesystem::rename(tmp, path, ec);
  if (ec) {
    std::filesystem::remove(tmp, ec);
    return absl::UnavailableError(absl::StrCat("cannot replace ", path, ": ", ec.message()));
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<std::unique_ptr<placement::Placement>> OpenPlacement(const std::string& flag) {
  std::string uri = flag;
  if (uri.empty()) {
    const char* env = std::getenv("LIFEMAP_PLACEMENT");
    if (env != nullptr) uri = env;
  }
  return placement::Placement::Open(uri);
}

void AddShardsCommands(CLI::App* admin, CliContext* ctx) {
  auto flags = std::make_shared<ShardFlags>();
  auto* shards = admin->add_subcommand(
      "shards", "A cluster's shards and where its maps live (the placement database)");
  shards->require_subcommand(1);
  shards->add_option("--placement", flags->placement,
                     "placement database, postgresql://USER@HOST:PORT/DB (else "
                     "$LIFEMAP_PLACEMENT)");

  shards->add_subcommand("list", "Shards, their health and how many maps each holds")
      ->callback([ctx, flags] {
        ctx->run = [ctx, flags] {
          auto p = flags->Open();
          if (!p.ok()) return Fail(p.status());
          return PrintShards(*ctx, **p);
        };
      });

  auto name = std::make_shared<std::string>();
  auto address = std::make_shared<std::string>();
  auto* add = shards->add_subcommand("add", "Add a shard (before starting its lifemapd)");
  add->add_option("NAME", *name, "the shard's name (lifemapd --shard NAME)")->required();
  add->add_option("ADDRESS", *address, "HOST:PORT where nginx reaches its gRPC port")->required();
  add->callback([ctx, flags, name, address] {
    ctx->run = [flags, name, address] {
      auto p = flags->Open();
      if (!p.ok()) return Fail(p.status());
      if (auto s = (*p)->AddShard(*name, *address, Now()); !s.ok()) return Fail(s);
      std::cout << "shard " << *name << " added at " << *address
                << "; start it with: lifemapd --shard " << *name
                << " --placement URI, then regenerate nginx's table (admin shards nginx-config)\n";
      return 0;
    };
  });

  const auto set_state = [&](const char* verb, const char* state, const char* help) {
    auto shard = std::make_shared<std::string>();
    auto* cmd = shards->add_subcommand(verb, help);
    cmd->add_option("NAME", *shard, "the shard")->required();
    cmd->callback([ctx, flags, shard, state] {
      ctx->run = [flags, shard, state] {
        auto p = flags->Open();
        if (!p.ok()) return Fail(p.status());
        if (auto s = (*p)->SetShardState(*shard, state); !s.ok()) return Fail(s);
        std::cout << "shard " << *shard << " is " << state
                  << "; regenerate nginx's table (admin shards nginx-config) for new maps to "
                     "follow\n";
        return 0;
      };
    });
  };
  set_state("drain", "draining",
            "Take no new maps (its maps stay until moved: lifemap maps move MAP --to SHARD)");
  set_state("activate", "active", "Take new maps again");

  auto removed = std::make_shared<std::string>();
  auto* remove = shards->add_subcommand("remove", "Forget a shard that holds no map");
  remove->add_option("NAME", *removed, "the shard")->required();
  remove->callback([ctx, flags, removed] {
    ctx->run = [flags, removed] {
      auto p = flags->Open();
      if (!p.ok()) return Fail(p.status());
      if (auto s = (*p)->RemoveShard(*removed); !s.ok()) return Fail(s);
      std::cout << "shard " << *removed << " removed\n";
      return 0;
    };
  });

  auto nginx = std::make_shared<placement::NginxOptions>();
  auto out = std::make_shared<std::string>();
  auto reload = std::make_shared<std::string>();
  auto include_only = std::make_shared<bool>(false);
  auto* conf = shards->add_subcommand(
      "nginx-config", "Write nginx's routing table (grpc_pass by the lifemap-map header)");
  conf->add_option("--out", *out, "file to write (atomically); - for stdout")->required();
  conf->add_option("--listen", nginx->listen, "where nginx listens for clients")
      ->capture_default_str();
  conf->add_option("--prefix", nginx->prefix,
                   "directory for nginx's pid, logs and temporary files (a whole nginx.conf)");
  conf->add_flag("--include", *include_only,
                 "write only what goes inside an existing http { } block");
  conf->add_option("--tls-cert", nginx->tls_cert, "TLS termination at nginx: certificate (PEM)");
  conf->add_option("--tls-key", nginx->tls_key, "... and its private key (PEM)");
  conf->add_option("--reload-command", *reload,
                   "run after writing, e.g. \"nginx -s reload -p DIR -c FILE\"");
  conf->callback([ctx, flags, nginx, out, reload, include_only] {
    ctx->run = [flags, nginx, out, reload, include_only] {
      nginx->standalone = !*include_only;
      if (nginx->standalone && nginx->prefix.empty()) {
        return Fail(absl::InvalidArgumentError(
            "a whole nginx.conf needs --prefix DIR (its pid, logs, temporary files); or give "
            "--include to write only the http { } part"));
      }
      if (nginx->tls_cert.empty() != nginx->tls_key.empty()) {
        return Fail(absl::InvalidArgumentError("give both --tls-cert and --tls-key, or neither"));
      }
      auto p = flags->Open();
      if (!p.ok()) return Fail(p.status());
      auto all = (*p)->ListShards();
      if (!all.ok()) return Fail(all.status());
      auto maps = (*p)->ListMaps("");
      if (!maps.ok()) return Fail(maps.status());
      const std::string text = placement::NginxConfig(*all, *maps, *nginx);
      if (*out == "-") {
        std::cout << text;
      } else if (auto s = WriteAtomically(*out, text); !s.ok()) {
        return Fail(s);
      }
      if (!reload->empty()) {
        const int rc = std::system(reload->c_str());
        if (rc != 0) {
          return Fail(absl::UnavailableError(
              absl::StrCat("the reload command failed (", rc, "): ", *reload,
                           "; nginx keeps its previous table (check it with nginx -t)")));
        }
      }
      if (*out != "-") {
        std::cerr << "nginx table written to " << *out << ": " << all->size() << " shard(s), "
                  << maps->size() << " placed map(s)\n";
      }
      return 0;
    };
  });
}

}  // namespace lifemap::cli
