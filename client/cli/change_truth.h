// The synthetic world's changes between two visits of a place (each visit's scene.json) and
// GetChanges reports matched to them: what `lifemap eval changes`, `eval retention` and
// `eval map` score the server's changes by.
#pragma once

#include <filesystem>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/types.h"

namespace CLI {
class App;
}
namespace lifemap::v1 {
class ObjectChange;
}

namespace lifemap::cli {

// What counts as a true change to be found, and when a report matches one.
struct ChangeScoring {
  double min_size_m = 0.2;     // props this large (largest side) count for recall
  double tolerance_m = 0.3;    // a report this close (ground plane) to a true change matches it
  int min_seen_pixels = 2000;  // a prop seen in fewer pixels over a visit is not observable
};

// Adds `--min-size M` and `--tolerance M` (ChangeScoring's) to a command.
void AddChangeScoringOptions(CLI::App* cmd, ChangeScoring* scoring);

// One change of the place, as scene.json records it, on the world's ground plane (m).
struct TrueChange {
  std::string kind, detail;
  int instance = 0;
  Eigen::Vector2d at{0, 0};    // where it is (appeared, moved) or was (vanished); doors: centre
  Eigen::Vector2d from{0, 0};  // moved: where it was
  double size_m = 0;           // largest side (doors: their width)
  bool counted = false;        // large enough and seen: counts for recall
  bool found = false;
};

// One GetChanges report on the world's ground plane (m).
struct ReportedChange {
  std::string kind, class_name;
  Eigen::Vector2d at{0, 0}, from{0, 0};
  double size_m = 0;
  std::string matched;  // "" or the true change's "kind instance"
};

// A report moved into the world's frame: T_world_map times the map's.
ReportedChange ReportOf(const v1::ObjectChange& change, const Eigen::Isometry3d& T_world_map);

// The true changes from visit folder `reference` to `query` (lifemap sim's, with scene.json and
// labels/instance): props appeared, vanished and moved (counted when at least
// `scoring.min_size_m` and seen in `min_seen_pixels` of the visit that shows them) and doors
// opened or closed (always counted). NotFound / InvalidArgument naming a scene.json that cannot
// be read.
absl::StatusOr<std::vector<TrueChange>> TrueChanges(const std::filesystem::path& reference,
                                                    const std::filesystem::path& query,
                                                    const ChangeScoring& scoring);

// Each report matches the nearest unmatched true change of its kind within
// max(tolerance, half its size) (a move by where it is now or where it was); sets
// `ReportedChange::matched` and `TrueChange::found`.
void MatchReports(std::vector<ReportedChange>* reported, std::vector<TrueChange>* truth,
                  double tolerance_m);

}  // namespace lifemap::cli
