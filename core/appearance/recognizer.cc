#include "core/appearance/recognizer.h"

#include <algorithm>

#include "absl/strings/str_cat.h"

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
  for (const Candidate& c : candidates) {
    auto stored = load(c.keyframe);
    if (!stored.ok()) {
      ++out.rejected;
      continue;
    }
    Verification v = VerifyMatch(query, query_intrinsics, *stored, options.verify);
    if (!v.verified) {
      ++out.rejected;
      continue;
    }
    out.matches.push_back({c.keyframe, c.score, std::move(v)});
  }
  std::stable_sort(out.matches.begin(), out.matches.end(),
                   [](const AppearanceMatch& a, const AppearanceMatch& b) {
                     return a.verification.score > b.verification.score;
                   });
  return out;
}

}  // namespace lifemap::appearance
