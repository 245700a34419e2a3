// lifemap: the command-line client of lifemapd. `lifemap --help` lists the commands.
#include <cstdlib>
#include <iostream>
#include <string>

#include <CLI/CLI.hpp>

#include "client/cli/commands.h"
#include "client/cli/output.h"
#include "client/lifemap_client.h"

int main(int argc, char** argv) {
  lifemap::cli::CliContext ctx;
  const char* env = std::getenv("LIFEMAP_SERVER");
  ctx.server = env && *env ? env : "127.0.0.1:50051";

  CLI::App app{"lifemap — administer lifemapd's maps and replay RGB-D recordings into them"};
  app.require_subcommand(1);
  app.add_option("--server", ctx.server,
                 "lifemapd HOST:PORT (default $LIFEMAP_SERVER, else 127.0.0.1:50051)");
  app.add_flag("--json", ctx.json, "machine-readable output");
  app.add_option("--connect-timeout", ctx.timeout_s, "seconds to wait for the server (default 5)");
  app.add_option("--api-key", ctx.api_key,
                 "API key for servers that require one (visible to other users in `ps`: prefer "
                 "--api-key-file or $LIFEMAP_API_KEY)");
  app.add_option("--api-key-file", ctx.api_key_file, "file whose first line is the API key")
      ->check(CLI::ExistingFile);
  app.add_flag("--tls", ctx.tls, "connect over TLS, verifying the server with the system's CAs");
  app.add_option("--tls-ca", ctx.tls_ca,
                 "connect over TLS, verifying the server with this CA (PEM)")
      ->check(CLI::ExistingFile);
  app.add_option("--tls-cert", ctx.tls_cert, "mTLS: this client's certificate (PEM)")
      ->check(CLI::ExistingFile);
  app.add_option("--tls-key", ctx.tls_key, "mTLS: this client's private key (PEM)")
      ->check(CLI::ExistingFile);
  lifemap::cli::AddServerCommands(&app, &ctx);
  lifemap::cli::AddMapCommands(&app, &ctx);
  lifemap::cli::AddVisitCommands(&app, &ctx);
  lifemap::cli::AddChangesCommand(&app, &ctx);
  lifemap::cli::AddKeyframeCommands(&app, &ctx);
  lifemap::cli::AddStreamCommand(&app, &ctx);
  lifemap::cli::AddExportCommand(&app, &ctx);
  lifemap::cli::AddProcessCommand(&app, &ctx);
  lifemap::cli::AddModelCommands(&app, &ctx);
  lifemap::cli::AddPlaceCommands(&app, &ctx);
  lifemap::cli::AddAdminCommands(&app, &ctx);
  lifemap::cli::AddKeyCommands(&app, &ctx);
  lifemap::cli::AddEvalCommands(&app, &ctx);
  lifemap::cli::AddSimCommands(&app, &ctx);
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    if (e.get_exit_code() == 0) return app.exit(e);  // --help, --version
    // With --json, scripts get the usage error as JSON too (the flag may follow the mistake).
    bool json = false;
    for (int i = 1; i < argc; ++i) json = json || std::string(argv[i]) == "--json";
    if (json) {
      lifemap::cli::SetJsonErrors(true);
      return lifemap::cli::UsageError(e.what());
    }
    app.exit(e);
    return 2;  // usage errors exit 2, like most Unix tools
  }
  lifemap::cli::SetJsonErrors(ctx.json);
  // Issue 37: the map is the first argument everywhere; `--map MAP` still works for one
  // release where it used to be the way (stream, export, keyframes list, process, models).
  bool evaluating = false;  // eval commands name scratch maps with --map: not deprecated
  for (int i = 1; i < argc; ++i) evaluating = evaluating || std::string(argv[i]) == "eval";
  for (int i = 1; i < argc && !evaluating; ++i) {
    const std::string arg = argv[i];
    if (arg == "--map" || arg.rfind("--map=", 0) == 0) {
      std::cerr << "lifemap: note: --map MAP is deprecated and goes in the next release: give "
                   "the map as the first argument after the command (e.g. `lifemap stream MAP "
                   "--tum DIR`)\n";
      break;
    }
  }
  if (auto s = lifemap::client::ValidateTarget(ctx.server); !s.ok()) {
    return lifemap::cli::UsageError(std::string(s.message()));
  }
  if (!ctx.run) {
    std::cerr << app.help();
    return 2;
  }
  return ctx.run();
}
