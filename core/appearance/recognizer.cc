#include "core/appearance/recognizer.h"

#include <algorithm>
#include <functional>
#include <optional>
#include <vector>

#include "absl/strings/str_cat.h"
#include "core/common/task_pool.h"

namespace lifemap::appearance {

absl::Status RecognizerOptions::Validate() const {
  if (candidates < 1 || candidates > 100) {
    return absl::InvalidArgumentError(
        absl::StrCat("candidates must be in [1, 100], got ", candidates));
  }
  return verify.Validate();
}

absl::StatusOr<Recognition> Recognize(const features::KeypointSet& query,
                                      const CameraIntrinsics& query_intrinsics,
                                      const Vocabulary& vocabulary, const InvertedIndex& index,
                                      const FeatureLoader& load, const KeyframeFilter& exclude,
                                      const RecognizerOptions& options) {
  if (query.size() == 0) {
    return absl::FailedPreconditionError(
        query.masked > 0 ? absl::StrCat("no features left after pruning (", query.masked, " of ",
                                        query.detected, " masked as likely to move)")
                         : std::string("the view has no features (too little texture or light)"));
  }
  auto bow = vocabulary.Transform(query.descriptors);
  if (!bow.ok()) return bow.status();
  const auto candidates = index.Query(*bow, static_cast<size_t>(options.candidates), exclude);
  if (candidates.empty()) {
    return absl::FailedPreconditionError(
        index.Stats().keyframes == 0
            ? "no keyframe is indexed yet"
            : "no indexed keyframe shares a visual word with this view (outside this one)");
  }
  Recognition out;
  out.candidates = static_cast<int>(candidates.size());
  // Candidates are loaded and verified side by side on the shared pool (each is independent;
  // PnP RANSAC seeds its own generator, so the outcome does not depend on the thread), then
  // taken in the index's order.
  std::vector<std::optional<Verification>> verified(candidates.size());
  std::vector<std::function<void()>> tasks;
  tasks.reserve(candidates.size());
  for (size_t i = 0; i < candidates.size(); ++i) {
    tasks.push_back([&, i] {
      auto stored = load(candidates[i].keyframe);
      if (stored.ok()) verified[i] = VerifyMatch(query, query_intrinsics, *stored, options.verify);
    });
  }
  TaskPool::Shared().RunAll(std::move(tasks));
  for (size_t i = 0; i < candidates.size(); ++i) {
    if (!verified[i] || !verified[i]->verified) {
      ++out.rejected;
      continue;
    }
    out.matches.push_back({candidates[i].keyframe, candidates[i].score, *std::move(verified[i])});
  }
  std::stable_sort(out.matches.begin(), out.matches.end(),
                   [](const AppearanceMatch& a, const AppearanceMatch& b) {
                     return a.verification.score > b.verification.score;
                   });
  return out;
}

}  // namespace lifemap::appearance
