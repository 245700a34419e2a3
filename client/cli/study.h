// Output of the `lifemap eval ...` studies: their files and the report printed.
#pragma once

#include <filesystem>
#include <string>
#include <utility>
#include <vector>

#include <nlohmann/json_fwd.hpp>
#include <opencv2/core/mat.hpp>

#include "client/cli/commands.h"

namespace lifemap::cli {

// Creates the output folder before a study runs; PermissionDenied says why it cannot.
absl::Status PrepareOut(const std::string& out);

// Writes a study's files to `out` (created): each (name, text), summary.json, report.md and
// each (name, image) as PNG; prints the report (or the summary with --json). Returns the exit
// code.
int FinishStudy(const CliContext& ctx, const std::filesystem::path& out,
                const std::vector<std::pair<std::string, std::string>>& texts,
                const std::vector<std::pair<std::string, cv::Mat>>& pngs,
                const nlohmann::json& summary, const std::string& report);

}  // namespace lifemap::cli
