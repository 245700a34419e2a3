// lifemap: the command-line client of lifemapd. `lifemap --help` lists the commands.
#include <cstdlib>
#include <iostream>

#include <CLI/CLI.hpp>

#include "client/cli/commands.h"

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
    const int code = app.exit(e);
    return code == 0 ? 0 : 2;  // usage errors exit 2, like most Unix tools
  }
  lifemap::cli::SetJsonErrors(ctx.json);
  if (!ctx.run) {
    std::cerr << app.help();
    return 2;
  }
  return ctx.run();
}
