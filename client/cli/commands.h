// The `lifemap` CLI's commands. Each registers a CLI11 subcommand whose callback sets the
// function main() runs after parsing.
#pragma once

#include <functional>
#include <iostream>
#include <memory>
#include <string>

#include <CLI/CLI.hpp>

#include "absl/status/statusor.h"
#include "client/cli/output.h"
#include "client/lifemap_client.h"

namespace lifemap {
struct CameraIntrinsics;
struct Pose;
namespace placement {
class Placement;
}  // namespace placement
}  // namespace lifemap

namespace lifemap::cli {

struct CliContext {
  std::string server;        // --server, LIFEMAP_SERVER, else 127.0.0.1:50051
  bool json = false;         // --json
  double timeout_s = 5.0;    // --connect-timeout
  std::string api_key;       // --api-key (else --api-key-file, else $LIFEMAP_API_KEY)
  std::string api_key_file;  // --api-key-file
  bool tls = false;          // --tls (implied by the files below)
  std::string tls_ca;        // --tls-ca
  std::string tls_cert;      // --tls-cert (mTLS)
  std::string tls_key;       // --tls-key (mTLS)
  std::function<int()> run;  // the chosen command

  absl::StatusOr<std::unique_ptr<client::Client>> Connect() const;
  // The same options (keys, TLS) for another server: a shard at its own address.
  absl::StatusOr<std::unique_ptr<client::Client>> ConnectTo(const std::string& target) const;
};

// Core values as the messages a robot sends.
v1::Pose PoseProto(const Pose& T_world_camera);
v1::CameraIntrinsics IntrinsicsProto(const CameraIntrinsics& k);

// Parses "FX,FY,CX,CY" (pixels) for an image of the given size. InvalidArgument otherwise.
absl::StatusOr<v1::CameraIntrinsics> ParseIntrinsicsFlag(const std::string& text, int width,
                                                         int height);

// Connects, makes one call, prints its response (JSON with --json, else `print`); returns the
// exit code (`exit_code` of the response, else 0; Fail's code for errors).
template <typename Response>
int RunCall(const CliContext& ctx,
            const std::function<absl::StatusOr<Response>(client::Client&)>& call,
            const std::function<void(const Response&)>& print,
            const std::function<int(const Response&)>& exit_code = nullptr) {
  auto c = ctx.Connect();
  if (!c.ok()) return Fail(c.status());
  auto response = call(**c);
  if (!response.ok()) return Fail(response.status());
  if (ctx.json) {
    std::cout << ToJson(*response) << "\n";
  } else {
    print(*response);
  }
  return exit_code ? exit_code(*response) : 0;
}

void AddServerCommands(CLI::App* app, CliContext* ctx);
void AddMapCommands(CLI::App* app, CliContext* ctx);
void AddVisitCommands(CLI::App* app, CliContext* ctx);
void AddChangesCommand(CLI::App* app, CliContext* ctx);  // changes_command.cc
void AddKeyframeCommands(CLI::App* app, CliContext* ctx);
void AddExportCommand(CLI::App* app, CliContext* ctx);
void AddProcessCommand(CLI::App* app, CliContext* ctx);
void AddAdminCommands(CLI::App* app, CliContext* ctx);
// `maps move` (move_command.cc), under `maps`.
void AddMapsMoveCommand(CLI::App* maps, CliContext* ctx);
// The cluster's placement database (shards_command.cc): `flag` (--placement), else
// $LIFEMAP_PLACEMENT.
absl::StatusOr<std::unique_ptr<placement::Placement>> OpenPlacement(const std::string& flag);
// `admin shards ...` (shards_command.cc), under `admin`.
void AddShardsCommands(CLI::App* admin, CliContext* ctx);
void AddKeyCommands(CLI::App* app, CliContext* ctx);
void AddStreamCommand(CLI::App* app, CliContext* ctx);
void AddEvalCommands(CLI::App* app, CliContext* ctx);
void AddSimCommands(CLI::App* app, CliContext* ctx);
// `lifemap places show|query`.
void AddPlaceCommands(CLI::App* app, CliContext* ctx);
// `lifemap models upload|list|activate|delete|classes`.
void AddModelCommands(CLI::App* app, CliContext* ctx);
// `lifemap train` on `app` and `lifemap eval segmentation` on `eval`.
void AddForestCommands(CLI::App* app, CLI::App* eval, CliContext* ctx);
// `lifemap eval places` (paper 004's evaluation on a synthetic suite).
void AddPlaceEvalCommand(CLI::App* eval, CliContext* ctx);
void AddAppearanceEvalCommand(CLI::App* eval, CliContext* ctx);
// `lifemap eval trajectory` (issue 15: the server's tracking against ground truth).
void AddTrajectoryEvalCommand(CLI::App* eval, CliContext* ctx);
// `lifemap eval alignment` (issue 15: visits months apart anchored into one map frame).
void AddAlignmentEvalCommand(CLI::App* eval, CliContext* ctx);
void AddChangesEvalCommand(CLI::App* eval, CliContext* ctx);    // changes_eval_command.cc
void AddRetentionEvalCommand(CLI::App* eval, CliContext* ctx);  // changes_eval_command.cc
void AddMapEvalCommand(CLI::App* eval, CliContext* ctx);        // map_eval_command.cc

}  // namespace lifemap::cli
