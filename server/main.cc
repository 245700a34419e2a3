// lifemapd: the lifemap server.
//
//   lifemapd --listen 127.0.0.1:50051 --db /var/lib/lifemap/lifemap.db [--config FILE]
//   lifemapd keys create NAME --role admin --db FILE   (the first key, on this machine)
//   lifemapd keys list --db FILE | lifemapd keys revoke NAME --db FILE
//
// SIGTERM / SIGINT: stop accepting calls, let streams drain, commit pending keyframes, exit 0.
#include <malloc.h>

#include <algorithm>
#include <csignal>
#include <cstdlib>
#include <filesystem>
#include <iostream>
#include <thread>

#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>
#include <CLI/CLI.hpp>

#include "absl/strings/str_join.h"
#include "server/config.h"
#include "server/engine/clock.h"
#include "server/log_format.h"
#include "server/rpc/auth.h"
#include "server/server.h"
#include "server/store/store.h"

namespace {

// `lifemapd keys ...`: API keys administered on the server's machine, straight in the database
// (a running server counts a new key, or a revoked one, within KeyRing::kReloadIntervalS). The
// only way to make the first admin key of a server that requires keys.
int RunKeysCommand(const std::string& action, const std::string& db, const std::string& name,
                   const std::string& role_name, const std::vector<std::string>& maps,
                   const lifemap::store::KeyLimits& limits, bool create_database) {
  using lifemap::server::Role;
  // A mistyped --db must not become a new, empty database that no server reads (issue 33).
  std::error_code ec;
  if (!create_database && !std::filesystem::exists(db, ec)) {
    std::cerr << "lifemapd keys " << action << ": database " << db
              << " does not exist: give the --db the server uses"
              << (action == "create" ? ", or add --create to make a new database for a new server"
                                     : "")
              << "\n";
    return 2;
  }
  lifemap::store::StoreOptions options;
  options.create_if_missing = create_database;
  auto store = lifemap::store::Store::Open(db, options);
  if (!store.ok()) {
    std::cerr << "lifemapd keys: " << store.status().message() << "\n";
    return 1;
  }
  if (action == "create") {
    const auto role = lifemap::server::ParseRole(role_name);
    if (!role) {
      std::cerr << "lifemapd keys create: --role must be robot, operator or admin\n";
      return 2;
    }
    auto created = lifemap::server::CreateApiKey(store->get(), name, *role, maps, limits,
                                                 lifemap::server::NowSeconds());
    if (!created.ok()) {
      std::cerr << "lifemapd keys create: " << created.status().message() << "\n";
      return 1;
    }
    // The secret alone on stdout (`> admin.key`); what it is on stderr.
    std::cout << created->first << std::endl;
    std::cerr << "API key '" << name << "' (" << role_name << ", "
              << (maps.empty() ? std::string("every map") : "maps " + absl::StrJoin(maps, ", "))
              << ") created. This is the only time its secret is shown: keep it in a file only "
                 "its user can read (chmod 600) and pass it with lifemap --api-key-file FILE.\n";
    return 0;
  }
  if (action == "revoke") {
    auto revoked = (*store)->RevokeApiKey(name, lifemap::server::NowSeconds());
    if (!revoked.ok()) {
      std::cerr << "lifemapd keys revoke: " << revoked.status().message() << "\n";
      return 1;
    }
    std::cerr << "API key '" << name << "' revoked\n";
    return 0;
  }
  auto keys = (*store)->ListApiKeys();
  if (!keys.ok()) {
    std::cerr << "lifemapd keys list: " << keys.status().message() << "\n";
    return 1;
  }
  std::cout << "name\trole\tmaps\tcreated_time_s\tlast_used_time_s\trevoked_time_s\n";
  for (const auto& k : *keys) {
    std::cout << k.name << "\t" << k.role << "\t"
              << (k.every_map ? std::string("*") : absl::StrJoin(k.map_names, ",")) << "\t"
              << static_cast<int64_t>(k.created_time_s) << "\t"
              << static_cast<int64_t>(k.last_used_time_s) << "\t"
              << static_cast<int64_t>(k.revoked_time_s) << "\n";
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  using lifemap::server::ServerConfig;
  // glibc gives each thread that allocates its own arena (up to 8 per core), and each keeps
  // the memory freed into it: with frames of several MB decoded and analysed on pool threads,
  // gRPC's threads and the workers, the peak RSS of a stream that sends as fast as it can was
  // 120-149 MB (once over the test's 160) with the default, 107-125 MB with one arena per core
  // (e2e test FastSenderCannotExhaustServerMemory; throughput unchanged, docs/BENCHMARKS.md).
  // MALLOC_ARENA_MAX, when set, is the operator's choice.
  if (std::getenv("MALLOC_ARENA_MAX") == nullptr) {
    mallopt(M_ARENA_MAX, static_cast<int>(std::max(2u, std::thread::hardware_concurrency())));
  }
  CLI::App app{"lifemapd — lifelong indoor maps for robots (gRPC server)"};
  app.set_version_flag("--version", std::string(LIFEMAP_VERSION));
  std::string config_file, listen, db, log_level;
  int max_message_mb = 0, max_streams = 0, max_inflight = 0;
  double grace_s = 0;
  app.add_option("--config", config_file, "JSON config file (see deploy/lifemapd.json)")
      ->check(CLI::ExistingFile);
  app.add_option("--listen", listen, "HOST:PORT to listen on (default 127.0.0.1:50051)");
  app.add_option("--db", db, "SQLite database file (created if missing)");
  std::string http;
  app.add_option("--http", http,
                 "HOST:PORT for the browser view (off by default; same keys and TLS as gRPC)");
  std::vector<std::string> http_allowed_hosts;
  app.add_option("--http-allowed-host", http_allowed_hosts,
                 "a name the browser view answers to besides its address, localhost and this "
                 "host's name (repeat; .example.org: every name under it; *: any)");
  std::string placement, shard;
  app.add_option("--placement", placement,
                 "a shard of a cluster: the placement database, postgresql://USER@HOST:PORT/DB");
  app.add_option("--shard", shard, "a shard of a cluster: this shard's name in the placement");
  app.add_option("--max-message-mb", max_message_mb, "largest message, MiB (default 16)");
  app.add_option("--max-streams", max_streams, "concurrent frame streams (default 16)");
  app.add_option("--max-inflight-frames", max_inflight,
                 "frames per stream in processing before the server stops reading (default 4)");
  app.add_option("--shutdown-grace-s", grace_s, "time streams get to finish on SIGTERM");
  app.add_option("--log-level", log_level, "trace, debug, info, warn, error, off");
  std::string backup_dir;
  app.add_option("--backup-dir", backup_dir,
                 "directory Backup writes into (default: backups/ beside the database)");
  bool require_auth = false, insecure_no_auth = false;
  app.add_flag("--require-auth", require_auth,
               "calls need an API key even on loopback (beyond loopback they always do)");
  app.add_flag("--insecure-no-auth", insecure_no_auth,
               "serve beyond loopback without API keys (trusted networks only)");
  std::string tls_cert, tls_key, tls_client_ca;
  app.add_option("--tls-cert", tls_cert, "TLS: the server's certificate chain (PEM)")
      ->check(CLI::ExistingFile);
  app.add_option("--tls-key", tls_key, "TLS: the server's private key (PEM)")
      ->check(CLI::ExistingFile);
  app.add_option("--tls-client-ca", tls_client_ca,
                 "mTLS: require client certificates signed by this CA (PEM)")
      ->check(CLI::ExistingFile);

  auto* keys = app.add_subcommand("keys", "API keys, straight in the database (no server needed)");
  keys->require_subcommand(1);
  // The same arguments as `lifemap keys` (NAME first; --name is kept as an alias of it).
  std::string keys_db, key_name, key_role;
  std::vector<std::string> key_maps;
  lifemap::store::KeyLimits key_limits;
  auto* keys_create = keys->add_subcommand("create", "create a key; prints its secret once");
  keys_create->add_option("NAME,--name", key_name, "the key's name")->required();
  keys_create->add_option("--db", keys_db, "the server's database file")->required();
  keys_create->add_option("--role", key_role, "robot, operator or admin")->required();
  keys_create
      ->add_option("--maps", key_maps, "only these maps (comma-separated; not for admin keys)")
      ->delimiter(',');
  keys_create->add_option("--max-streams", key_limits.max_streams,
                          "frame streams it may have open at once");
  keys_create->add_option("--max-fps", key_limits.max_frames_per_s,
                          "frames a second it may send (streams and single frames together)");
  keys_create->add_option("--max-maps", key_limits.max_maps, "maps it may have created at once");
  keys_create->add_option("--max-keyframes-per-map", key_limits.max_keyframes_per_map,
                          "keyframes a map may hold for it to add another");
  int64_t max_model_mb = 0;
  keys_create->add_option("--max-model-mb", max_model_mb, "largest model it may upload, MiB");
  keys_create->add_option("--max-visits-per-hour", key_limits.max_visits_per_hour,
                          "visits it may start in any hour");
  bool create_database = false;
  keys_create->add_flag("--create", create_database,
                        "make the database if it does not exist (the first key of a new server)");
  auto* keys_list = keys->add_subcommand("list", "list keys (never their secrets)");
  keys_list->add_option("--db", keys_db, "the server's database file")->required();
  auto* keys_revoke = keys->add_subcommand("revoke", "revoke a key");
  keys_revoke->add_option("--db", keys_db, "the server's database file")->required();
  keys_revoke->add_option("NAME,--name", key_name, "the key's name")->required();
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    // Help and --version exit 0; every bad flag, value or missing file 2, as documented (CLI11's
    // own codes differ by kind: 105 for a file that does not exist).
    return app.exit(e) == 0 ? 0 : 2;
  }
  for (auto* action : {keys_create, keys_list, keys_revoke}) {
    if (action->parsed()) {
      key_limits.max_model_bytes = max_model_mb << 20;
      return RunKeysCommand(action->get_name(), keys_db, key_name, key_role, key_maps, key_limits,
                            create_database);
    }
  }
  // Logs go to stderr (journald under systemd); stdout carries only the "listening on port"
  // line that scripts read.
  spdlog::set_default_logger(spdlog::stderr_color_mt("lifemapd"));
  lifemap::server::EscapeDefaultLogMessages();

  // A file-size limit (ulimit -f) makes a write fail (the store answers RESOURCE_EXHAUSTED,
  // like a full disk) instead of killing the server with SIGXFSZ.
  std::signal(SIGXFSZ, SIG_IGN);
  // Signals are taken by a dedicated thread (sigwait), never by an async handler.
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGTERM);
  sigaddset(&signals, SIGINT);
  pthread_sigmask(SIG_BLOCK, &signals, nullptr);

  ServerConfig config;
  if (!config_file.empty()) {
    auto loaded = lifemap::server::LoadConfigFile(config_file, config);
    if (!loaded.ok()) {
      std::cerr << "lifemapd: " << loaded.status().message() << "\n";
      return 2;
    }
    config = *loaded;
  }
  // Flags given on the command line override the config file.
  auto given = [&app](const char* flag) { return app.count(flag) > 0; };
  if (given("--listen")) config.listen = listen;
  if (given("--db")) config.db_path = db;
  if (given("--http")) config.http_listen = http;
  if (given("--http-allowed-host")) config.http_allowed_hosts = http_allowed_hosts;
  if (given("--placement")) config.placement_uri = placement;
  if (given("--shard")) config.shard_name = shard;
  if (given("--max-message-mb")) {
    config.max_message_bytes = (max_message_mb > 0 && max_message_mb <= 1024)
                                   ? max_message_mb << 20
                                   : 0;  // rejected by Validate with the range
  }
  if (given("--max-streams")) config.max_streams = max_streams;
  if (given("--max-inflight-frames")) config.max_inflight_frames = max_inflight;
  if (given("--shutdown-grace-s")) config.shutdown_grace_s = grace_s;
  if (given("--log-level")) config.log_level = log_level;
  if (given("--backup-dir")) config.backup_dir = backup_dir;
  if (given("--require-auth")) config.require_auth = true;
  if (given("--insecure-no-auth")) config.insecure_no_auth = true;
  if (given("--tls-cert")) config.tls_cert = tls_cert;
  if (given("--tls-key")) config.tls_key = tls_key;
  if (given("--tls-client-ca")) config.tls_client_ca = tls_client_ca;
  if (auto s = config.Validate(); !s.ok()) {
    std::cerr << "lifemapd: " << s.message() << "\n";
    return 2;
  }

  auto server = lifemap::server::LifemapServer::Start(config);
  if (!server.ok()) {
    std::cerr << "lifemapd: " << server.status().message() << "\n";
    return 1;
  }
  // Scripts read the bound port from this line (useful with --listen HOST:0).
  std::cout << "lifemapd listening on port " << (*server)->port() << std::endl;
  if ((*server)->http_port() > 0) {
    std::cout << "lifemapd browser view on port " << (*server)->http_port() << std::endl;
  }

  std::thread waiter([&] {
    int sig = 0;
    sigwait(&signals, &sig);
    spdlog::info("received {}", sig == SIGTERM ? "SIGTERM" : "SIGINT");
    (*server)->Shutdown();
  });
  (*server)->Wait();
  waiter.join();
  return 0;
}
