// The frame path driven through the engine alone (no gRPC, no protobuf): a real recording
// streamed into a visit without poses is tracked, its keyframes committed and readable; the
// refusals (a timestamp ahead of the clock, one far after the visit's last frame, a visit that
// ended) come back as typed results.
#include "server/engine/frame_path.h"

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>

#include "core/common/depth_codec.h"
#include "core/common/image_codec.h"
#include "core/io/tum_dataset.h"
#include "server/engine/clock.h"
#include "server/engine/engine.h"
#include "server/engine/visit_registry.h"
#include "server/store/store.h"
#include "tests/testing/test_util.h"

namespace lifemap::server {
namespace {

// A frame's bytes as a robot sends them (JPEG colour, paletted depth) and the view of them.
struct SentFrame {
  std::string jpeg, paletted;
  EncodedRgbdFrame view;
};

class FramePathTest : public ::testing::Test {
 protected:
  void SetUp() override {
    EngineOptions options;
    options.db_path = tmp_.File("lifemap.db");
    auto engine = Engine::Open(options);
    ASSERT_TRUE(engine.ok()) << engine.status();
    engine_ = *std::move(engine);
    auto map = engine_->store()->CreateMap("desk", "", NowSeconds());
    ASSERT_TRUE(map.ok()) << map.status();
    map_id_ = map->id;
  }

  std::shared_ptr<VisitState> StartVisit() {
    auto visit = engine_->store()->StartVisit("desk", "robot", "", NowSeconds());
    EXPECT_TRUE(visit.ok()) << visit.status();
    auto state = engine_->visits()->Get(visit->id);
    EXPECT_TRUE(state.ok()) << state.status();
    return *state;
  }

  // The recording's frame `i` sent at `timestamp_s`, without its pose.
  static std::unique_ptr<SentFrame> Sent(const io::TumSequence& seq, size_t i, double timestamp_s) {
    auto sent = std::make_unique<SentFrame>();
    const cv::Mat color = cv::imread(seq.frames[i].rgb_path, cv::IMREAD_COLOR);
    const cv::Mat depth = cv::imread(seq.frames[i].depth_path, cv::IMREAD_UNCHANGED);
    sent->jpeg = *EncodeJpeg(color, 90);
    sent->paletted = EncodePalettedDepth(depth);
    std::string source;
    EncodedRgbdFrame& f = sent->view;
    f.sequence = i;
    f.timestamp_s = timestamp_s;
    f.intrinsics = io::TumSequenceIntrinsics(seq, color.cols, color.rows, &source);
    f.color = {ColorEncoding::kJpeg, sent->jpeg, color.cols, color.rows};
    f.depth = {DepthEncoding::kPaletted, sent->paletted, depth.cols, depth.rows, 5000.0};
    return sent;
  }

  testing::TempDir tmp_;
  std::unique_ptr<Engine> engine_;
  int64_t map_id_ = 0;
};

TEST_F(FramePathTest, ARecordingSentWithoutPosesIsTrackedAndItsKeyframesStored) {
  LIFEMAP_REQUIRE_DATASET(dir, "tum_fr1_xyz_subset");
  auto seq = io::ReadTumSequence(dir);
  ASSERT_TRUE(seq.ok()) << seq.status();
  auto visit = StartVisit();
  FramePath* path = engine_->frames();
  const FrameSettings settings;
  const double start_s = NowSeconds() - 10;
  size_t tracked = 0, committed = 0;
  for (size_t i = 0; i < seq->frames.size(); ++i) {
    auto sent = Sent(*seq, i, start_s + static_cast<double>(i) / 30.0);
    AnalysedFrame a = path->Analyse(sent->view, map_id_, "desk", settings);
    ASSERT_TRUE(a.refused.ok()) << a.refused;
    ASSERT_TRUE(a.analysis->entropy) << "entropy masks are computed";
    FramePlacement p = path->Place(a, visit, /*writer=*/0, settings);
    ASSERT_TRUE(p.refused.ok() && p.visit_closed.ok());
    ASSERT_TRUE(p.tracking) << "a frame without a pose is tracked";
    ASSERT_TRUE(p.keyframe);
    if (i == 0) {
      EXPECT_TRUE(p.keyframe->selected) << "a visit's first frame is a keyframe";
    }
    if (p.pose_source == store::StoredPoseSource::kEstimated) {
      ++tracked;
      EXPECT_TRUE(p.pose);
    }
    if (p.commit) {
      const absl::StatusOr<int64_t>& id = p.commit->get();
      ASSERT_TRUE(id.ok()) << id.status();
      auto stored = engine_->store()->GetKeyframe(map_id_, *id);
      ASSERT_TRUE(stored.ok()) << stored.status();
      EXPECT_EQ(stored->pose_source, store::StoredPoseSource::kEstimated);
      EXPECT_EQ(stored->sequence, i);
      ++committed;
    }
  }
  EXPECT_EQ(tracked, seq->frames.size()) << "fr1_xyz tracks throughout";
  EXPECT_GE(committed, 2u);
  EXPECT_EQ(path->frames_processed(), seq->frames.size());
  EXPECT_EQ(path->frames_rejected(), 0u);
}

TEST_F(FramePathTest, RefusalsAreTypedResults) {
  LIFEMAP_REQUIRE_DATASET(dir, "tum_fr1_xyz_subset");
  auto seq = io::ReadTumSequence(dir);
  ASSERT_TRUE(seq.ok()) << seq.status();
  auto visit = StartVisit();
  FramePath* path = engine_->frames();
  const FrameSettings settings;
  const double now = NowSeconds();

  // Milliseconds sent as seconds: refused before its analysis.
  auto ahead = Sent(*seq, 0, now * 1000);
  AnalysedFrame refused = path->Analyse(ahead->view, map_id_, "desk", settings);
  EXPECT_EQ(refused.refused.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(refused.refused.message().find("frames.max_future_s"), std::string::npos)
      << refused.refused;
  EXPECT_FALSE(refused.analysis);
  EXPECT_FALSE(path->Place(refused, visit, 0, settings).keyframe) << "nothing is placed";

  auto first = Sent(*seq, 0, now - 30 * 86400.0);
  AnalysedFrame a = path->Analyse(first->view, map_id_, "desk", settings);
  ASSERT_TRUE(a.refused.ok()) << a.refused;
  ASSERT_TRUE(path->Place(a, visit, 0, settings).refused.ok());
  // A month after the visit's previous frame: refused where it is placed.
  auto late = Sent(*seq, 1, now);
  AnalysedFrame b = path->Analyse(late->view, map_id_, "desk", settings);
  ASSERT_TRUE(b.refused.ok()) << b.refused;
  const FramePlacement gap = path->Place(b, visit, 0, settings);
  EXPECT_EQ(gap.refused.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(gap.refused.message().find("frames.max_gap_s"), std::string::npos) << gap.refused;
  EXPECT_EQ(path->frames_rejected(), 2u);

  // The visit ended: the next frame is not added, and says why.
  engine_->visits()->CloseVisit(visit->visit_id, absl::FailedPreconditionError("visit ended"));
  auto next = Sent(*seq, 2, now - 30 * 86400.0 + 1);
  AnalysedFrame c = path->Analyse(next->view, map_id_, "desk", settings);
  const FramePlacement closed = path->Place(c, visit, 0, settings);
  EXPECT_EQ(closed.visit_closed.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_FALSE(closed.commit);
}

}  // namespace
}  // namespace lifemap::server
