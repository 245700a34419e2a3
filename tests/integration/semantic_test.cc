// Integration tests of the served semantic octree (issue 16): a visit's keyframes fused off the
// reply path, and every posed frame of the visit given the octree's labels (fused_labels), or
// told why not.
#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>

#include "tests/integration/model_fixture.h"
#include "tests/integration/server_fixture.h"

namespace lifemap {
namespace {

using testing::ServerTest;
constexpr int kWidth = testing::kModelWidth, kHeight = testing::kModelHeight;

const v1::OutputStatus* FusionStatus(const v1::FrameResult& r) {
  for (const auto& o : r.outputs()) {
    if (o.output() == v1::FRAME_OUTPUT_SEMANTIC_FUSION) return &o;
  }
  return nullptr;
}

// The two-colour plane seen from a still camera (identity pose): every frame a second apart is
// a keyframe (keyframe.max_interval_s).
v1::Frame PosedFrame(uint64_t sequence) {
  v1::Frame f = testing::TwoColorFrame(sequence);
  f.mutable_pose()->set_qw(1.0);
  return f;
}

TEST_F(ServerTest, PosedFramesOfAVisitGetTheOctreesLabels) {
  ASSERT_TRUE(client_->UploadModel("two-colors", testing::TwoColorModel()).ok());
  ASSERT_TRUE(client_->ActivateModel("two-colors", "").ok());
  ASSERT_TRUE(client_->CreateMap("lab", "").ok());
  v1::StreamStart start;
  start.set_map("lab");
  auto stream = client_->OpenStream(start);
  ASSERT_TRUE(stream.ok()) << stream.status();

  // The first frame: nothing fused yet, and the result says so.
  ASSERT_TRUE((*stream)->Send(PosedFrame(0)));
  v1::FrameResult first;
  ASSERT_TRUE((*stream)->Receive(&first));
  ASSERT_TRUE(first.keyframe().committed());
  EXPECT_FALSE(first.has_fused_labels());
  ASSERT_NE(FusionStatus(first), nullptr);
  EXPECT_FALSE(FusionStatus(first)->computed());
  EXPECT_NE(FusionStatus(first)->reason().find("no keyframe of this visit fused yet"),
            std::string::npos)
      << FusionStatus(first)->reason();

  // Fusion runs off the reply path, a keyframe or two behind: within a few frames the octree
  // labels what the model labels, away from the seam.
  v1::FrameResult fused;
  for (uint64_t i = 1; i < 20 && !fused.has_fused_labels(); ++i) {
    ASSERT_TRUE((*stream)->Send(PosedFrame(i)));
    ASSERT_TRUE((*stream)->Receive(&fused));
  }
  (*stream)->CloseSend();
  EXPECT_TRUE((*stream)->Finish().ok());
  ASSERT_TRUE(fused.has_fused_labels()) << "never fused in 20 frames";
  EXPECT_TRUE(FusionStatus(fused)->computed());
  EXPECT_EQ(fused.fused_labels().model(), "two-colors");
  EXPECT_EQ(fused.fused_labels().stride(), 8u);
  const std::string& png = fused.fused_labels().label_png();
  const cv::Mat labels =
      cv::imdecode(std::vector<uint8_t>(png.begin(), png.end()), cv::IMREAD_UNCHANGED);
  ASSERT_EQ(labels.size(), cv::Size(kWidth, kHeight));
  const cv::Mat left = labels(cv::Rect(4, 4, kWidth / 2 - 14, kHeight - 8));
  const cv::Mat right = labels(cv::Rect(kWidth / 2 + 10, 4, kWidth / 2 - 14, kHeight - 8));
  EXPECT_LT(cv::countNonZero(left != 0), left.total() / 20) << "left half: wall";
  EXPECT_LT(cv::countNonZero(right != 1), right.total() / 20) << "right half: door";
  ASSERT_EQ(fused.fused_labels().classes_size(), 2);
  EXPECT_FALSE(fused.fused_labels().confidence_png().empty());

  // A client that does not want them is not sent them.
  v1::ProcessFrameRequest req;
  req.set_map("lab");
  *req.mutable_frame() = PosedFrame(40);
  req.mutable_options()->add_skip_outputs(v1::FRAME_OUTPUT_SEMANTIC_FUSION);
  auto skipped = client_->ProcessFrame(req);
  ASSERT_TRUE(skipped.ok()) << skipped.status();
  EXPECT_FALSE(skipped->has_fused_labels());
  EXPECT_NE(FusionStatus(*skipped)->reason().find("not requested"), std::string::npos);
  EXPECT_TRUE(skipped->has_labels());

  // Frames outside a visit have no octree.
  req.clear_map();
  req.mutable_options()->clear_skip_outputs();
  auto alone = client_->ProcessFrame(req);
  ASSERT_TRUE(alone.ok()) << alone.status();
  EXPECT_FALSE(alone->has_fused_labels());
  EXPECT_NE(FusionStatus(*alone)->reason().find("frames of a visit only"), std::string::npos)
      << FusionStatus(*alone)->reason();

  auto info = client_->GetServerInfo();
  ASSERT_TRUE(info.ok());
  bool served = false;
  for (const auto& o : info->outputs()) {
    if (o.output() == v1::FRAME_OUTPUT_SEMANTIC_FUSION) served = o.computed();
  }
  EXPECT_TRUE(served) << "a model is active: fused labels are served";
}

TEST_F(ServerTest, FusedLabelsNeedAModel) {
  ASSERT_TRUE(client_->CreateMap("lab", "").ok());
  v1::ProcessFrameRequest req;
  req.set_map("lab");
  *req.mutable_frame() = PosedFrame(0);
  auto r = client_->ProcessFrame(req);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_FALSE(r->has_fused_labels());
  EXPECT_NE(FusionStatus(*r)->reason().find("need the frame's model"), std::string::npos)
      << FusionStatus(*r)->reason();
  auto info = client_->GetServerInfo();
  ASSERT_TRUE(info.ok());
  for (const auto& o : info->outputs()) {
    if (o.output() != v1::FRAME_OUTPUT_SEMANTIC_FUSION) continue;
    EXPECT_FALSE(o.computed());
    EXPECT_NE(o.reason().find("no model is active"), std::string::npos) << o.reason();
  }
}

TEST_F(ServerTest, AResumedVisitStartsFromItsStoredOctree) {
  ASSERT_TRUE(client_->UploadModel("two-colors", testing::TwoColorModel()).ok());
  ASSERT_TRUE(client_->ActivateModel("two-colors", "").ok());
  ASSERT_TRUE(client_->CreateMap("lab", "").ok());
  v1::StreamStart start;
  start.set_map("lab");
  auto stream = client_->OpenStream(start);
  ASSERT_TRUE(stream.ok()) << stream.status();
  const uint64_t visit_id = (*stream)->started().visit_id();
  // Twelve keyframes (a second apart): a snapshot is stored once ten are fused.
  for (uint64_t i = 0; i < 12; ++i) {
    ASSERT_TRUE((*stream)->Send(PosedFrame(i)));
    v1::FrameResult r;
    ASSERT_TRUE((*stream)->Receive(&r));
  }
  (*stream)->CloseSend();
  EXPECT_TRUE((*stream)->Finish().ok());

  RestartServer();
  start.set_visit_id(visit_id);
  stream = client_->OpenStream(start);
  ASSERT_TRUE(stream.ok()) << stream.status();
  ASSERT_TRUE((*stream)->Send(PosedFrame(20)));
  v1::FrameResult resumed;
  ASSERT_TRUE((*stream)->Receive(&resumed));
  (*stream)->CloseSend();
  EXPECT_TRUE((*stream)->Finish().ok());
  EXPECT_TRUE(resumed.has_fused_labels())
      << "the resumed visit's first frame is labelled from the stored octree: "
      << FusionStatus(resumed)->reason();
}

}  // namespace
}  // namespace lifemap
