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
  lifemap::cli::AddServerCommands(&app, &ctx);
  lifemap::cli::AddMapCommands(&app, &ctx);
  lifemap::cli::AddVisitCommands(&app, &ctx);
  lifemap::cli::AddKeyframeCommands(&app, &ctx);
  lifemap::cli::AddStreamCommand(&app, &ctx);
  lifemap::cli::AddExportCommand(&app, &ctx);
  lifemap::cli::AddProcessCommand(&app, &ctx);
  lifemap::cli::AddModelCommands(&app, &ctx);
  lifemap::cli::AddPlaceCommands(&app, &ctx);
  lifemap::cli::AddAdminCommands(&app, &ctx);
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
