// lifemapd: the lifemap server.
//
//   lifemapd --listen 127.0.0.1:50051 --db /var/lib/lifemap/lifemap.db [--config FILE]
//
// SIGTERM / SIGINT: stop accepting calls, let streams drain, commit pending keyframes, exit 0.
#include <malloc.h>

#include <algorithm>
#include <csignal>
#include <cstdlib>
#include <iostream>
#include <thread>

#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>
#include <CLI/CLI.hpp>

#include "server/config.h"
#include "server/server.h"

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
  app.add_option("--max-message-mb", max_message_mb, "largest message, MiB (default 16)");
  app.add_option("--max-streams", max_streams, "concurrent frame streams (default 16)");
  app.add_option("--max-inflight-frames", max_inflight,
                 "frames per stream in processing before the server stops reading (default 4)");
  app.add_option("--shutdown-grace-s", grace_s, "time streams get to finish on SIGTERM");
  app.add_option("--log-level", log_level, "trace, debug, info, warn, error, off");
  std::string backup_dir;
  app.add_option("--backup-dir", backup_dir,
                 "directory Backup writes into (default: backups/ beside the database)");
  CLI11_PARSE(app, argc, argv);
  // Logs go to stderr (journald under systemd); stdout carries only the "listening on port"
  // line that scripts read.
  spdlog::set_default_logger(spdlog::stderr_color_mt("lifemapd"));

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
