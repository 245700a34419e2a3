// The `lifemap` CLI's commands. Each registers a CLI11 subcommand whose callback sets the
// function main() runs after parsing.
#pragma once

#include <functional>
#include <memory>
#include <string>

#include <CLI/CLI.hpp>

#include "absl/status/statusor.h"
#include "client/lifemap_client.h"

namespace lifemap::cli {

struct CliContext {
  std::string server;        // --server, LIFEMAP_SERVER, else 127.0.0.1:50051
  bool json = false;         // --json
  double timeout_s = 5.0;    // --connect-timeout
  std::function<int()> run;  // the chosen command

  absl::StatusOr<std::unique_ptr<client::Client>> Connect() const;
};

// Parses "FX,FY,CX,CY" (pixels) for an image of the given size. InvalidArgument otherwise.
absl::StatusOr<v1::CameraIntrinsics> ParseIntrinsicsFlag(const std::string& text, int width,
                                                         int height);

void AddServerCommands(CLI::App* app, CliContext* ctx);
void AddMapCommands(CLI::App* app, CliContext* ctx);
void AddVisitCommands(CLI::App* app, CliContext* ctx);
void AddKeyframeCommands(CLI::App* app, CliContext* ctx);
void AddExportCommand(CLI::App* app, CliContext* ctx);
void AddProcessCommand(CLI::App* app, CliContext* ctx);
void AddAdminCommands(CLI::App* app, CliContext* ctx);
void AddStreamCommand(CLI::App* app, CliContext* ctx);
void AddEvalCommands(CLI::App* app, CliContext* ctx);
void AddSimCommands(CLI::App* app, CliContext* ctx);
// `lifemap train` on `app` and `lifemap eval segmentation` on `eval`.
void AddForestCommands(CLI::App* app, CLI::App* eval, CliContext* ctx);

}  // namespace lifemap::cli
