// Integration tests of ModelService and the class labels in frame results: upload, activate
// per map and as the default, labels that match what the model learned, errors, persistence.
#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>

#include "core/forest/forest.h"
#include "tests/integration/model_fixture.h"
#include "tests/integration/server_fixture.h"

namespace lifemap {
namespace {

using testing::ServerTest;

constexpr int kWidth = testing::kModelWidth, kHeight = testing::kModelHeight;
using testing::TwoColorFrame;
using testing::TwoColorModel;
using testing::TwoColors;

// The label image of a result, decoded.
cv::Mat Labels(const v1::FrameResult& r) {
  const std::string& png = r.labels().label_png();
  return cv::imdecode(std::vector<uint8_t>(png.begin(), png.end()), cv::IMREAD_UNCHANGED);
}

const v1::OutputStatus* StatusOf(const v1::FrameResult& r, v1::FrameOutput output) {
  for (const auto& o : r.outputs()) {
    if (o.output() == output) return &o;
  }
  return nullptr;
}

const v1::OutputStatus* LabelStatus(const v1::FrameResult& r) {
  return StatusOf(r, v1::FRAME_OUTPUT_CLASS_LABELS);
}

TEST_F(ServerTest, FramesSayWhyTheyHaveNoLabelsUntilAModelIsActive) {
  v1::ProcessFrameRequest req;
  *req.mutable_frame() = TwoColorFrame(0);
  auto r = client_->ProcessFrame(req);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_FALSE(r->has_labels());
  ASSERT_NE(LabelStatus(*r), nullptr);
  EXPECT_FALSE(LabelStatus(*r)->computed());
  EXPECT_NE(LabelStatus(*r)->reason().find("no model is active"), std::string::npos)
      << LabelStatus(*r)->reason();
  auto classes = client_->ListClasses("");
  EXPECT_TRUE(absl::IsFailedPrecondition(classes.status())) << classes.status();
}

TEST_F(ServerTest, ActiveModelLabelsEveryFrameAndSurvivesARestart) {
  auto info = client_->UploadModel("two-colors", TwoColorModel());
  ASSERT_TRUE(info.ok()) << info.status();
  EXPECT_EQ(info->class_names_size(), 2);
  EXPECT_EQ(info->trees(), 1u);
  EXPECT_FALSE(info->active());
  EXPECT_EQ(info->training_json(), R"({"test":true})");
  ASSERT_TRUE(client_->ActivateModel("two-colors", "").ok());

  auto check = [&](const v1::FrameResult& r, bool swapped) {
    ASSERT_TRUE(r.has_labels());
    EXPECT_EQ(r.labels().model(), swapped ? "swapped" : "two-colors");
    const cv::Mat labels = Labels(r);
    ASSERT_EQ(labels.size(), cv::Size(kWidth, kHeight));
    // Away from the seam, every pixel carries the class the model learned there.
    const cv::Mat left = labels(cv::Rect(0, 0, kWidth / 2 - 10, kHeight));
    const cv::Mat right = labels(cv::Rect(kWidth / 2 + 10, 0, kWidth / 2 - 10, kHeight));
    EXPECT_EQ(cv::countNonZero(left != (swapped ? 1 : 0)), 0);
    EXPECT_EQ(cv::countNonZero(right != (swapped ? 0 : 1)), 0);
    ASSERT_EQ(r.labels().classes_size(), 2);
    for (const auto& c : r.labels().classes()) {
      EXPECT_NEAR(c.pixel_fraction(), 0.5, 0.05) << c.name();
      EXPECT_GT(c.mean_confidence(), 0.9f) << c.name();
    }
    EXPECT_TRUE(LabelStatus(r)->computed());
  };
  v1::ProcessFrameRequest req;
  *req.mutable_frame() = TwoColorFrame(0);
  auto r = client_->ProcessFrame(req);
  ASSERT_TRUE(r.ok()) << r.status();
  check(*r, false);
  EXPECT_EQ(r->labels().stride(), 4u);

  // A map's own model comes before the default.
  ASSERT_TRUE(client_->UploadModel("swapped", TwoColorModel(true)).ok());
  ASSERT_TRUE(client_->CreateMap("lab", "").ok());
  auto act = client_->ActivateModel("swapped", "lab");
  ASSERT_TRUE(act.ok()) << act.status();
  EXPECT_EQ(act->previous(), "");
  req.set_map("lab");
  *req.mutable_frame() = TwoColorFrame(1);
  r = client_->ProcessFrame(req);
  ASSERT_TRUE(r.ok()) << r.status();
  check(*r, true);

  // Streams get labels too, and after a restart the activations are still there.
  RestartServer();
  v1::StreamStart start;
  start.set_map("lab");
  auto stream = client_->OpenStream(start);
  ASSERT_TRUE(stream.ok()) << stream.status();
  ASSERT_TRUE((*stream)->Send(TwoColorFrame(2)));
  (*stream)->CloseSend();
  v1::FrameResult streamed;
  ASSERT_TRUE((*stream)->Receive(&streamed));
  check(streamed, true);
  EXPECT_TRUE((*stream)->Finish().ok());
  req.clear_map();
  *req.mutable_frame() = TwoColorFrame(3);
  r = client_->ProcessFrame(req);
  ASSERT_TRUE(r.ok()) << r.status();
  check(*r, false);

  auto list = client_->ListModels();
  ASSERT_TRUE(list.ok());
  ASSERT_EQ(list->models_size(), 2);
  EXPECT_TRUE(list->models(1).is_default());  // sorted by name: swapped, two-colors
  EXPECT_EQ(list->models(0).active_maps_size(), 1);
  auto classes = client_->ListClasses("lab");
  ASSERT_TRUE(classes.ok());
  EXPECT_EQ(classes->model(), "swapped");
  EXPECT_EQ(classes->class_colors(1), 0x00FF00u);

  // Deactivated, the map falls back to the default; the model can then be deleted.
  EXPECT_TRUE(absl::IsFailedPrecondition(client_->DeleteModel("swapped").status()));
  ASSERT_TRUE(client_->ActivateModel("", "lab").ok());
  ASSERT_TRUE(client_->DeleteModel("swapped").ok());
  req.set_map("lab");
  *req.mutable_frame() = TwoColorFrame(4);
  r = client_->ProcessFrame(req);
  ASSERT_TRUE(r.ok()) << r.status();
  check(*r, false);
}

TEST_F(ServerTest, ModelServiceRejectsBadInputWithClearStatuses) {
  const std::string model = TwoColorModel();
  auto bad_bytes = client_->UploadModel("junk", "this is not a model");
  EXPECT_TRUE(absl::IsInvalidArgument(bad_bytes.status())) << bad_bytes.status();
  EXPECT_NE(bad_bytes.status().message().find("lifemap train"), std::string::npos);
  std::string corrupt = model;
  corrupt[corrupt.size() / 2] ^= 0x10;
  auto flipped = client_->UploadModel("flipped", corrupt);
  EXPECT_TRUE(absl::IsInvalidArgument(flipped.status())) << flipped.status();
  EXPECT_NE(flipped.status().message().find("checksum"), std::string::npos) << flipped.status();
  EXPECT_TRUE(absl::IsInvalidArgument(client_->UploadModel("bad name!", model).status()));
  EXPECT_TRUE(absl::IsInvalidArgument(client_->UploadModel("", model).status()));
  ASSERT_TRUE(client_->UploadModel("ok", model).ok());
  EXPECT_TRUE(absl::IsAlreadyExists(client_->UploadModel("ok", model).status()));
  EXPECT_TRUE(absl::IsNotFound(client_->ActivateModel("missing", "").status()));
  EXPECT_TRUE(absl::IsNotFound(client_->ActivateModel("ok", "no-such-map").status()));
  EXPECT_TRUE(absl::IsNotFound(client_->DeleteModel("missing").status()));
  EXPECT_TRUE(absl::IsNotFound(client_->ListClasses("no-such-map").status()));
  // Nothing half-stored: the failed uploads are not listed.
  auto list = client_->ListModels();
  ASSERT_TRUE(list.ok());
  ASSERT_EQ(list->models_size(), 1);
  EXPECT_EQ(list->models(0).name(), "ok");
}

TEST_F(ServerTest, ModelsAboveTheSizeLimitAreRefused) {
  server::ServerConfig config;
  config.max_model_mb = 1;
  StartServer(config);
  auto s = client_->UploadModel("big", std::string(3 << 20, 'x')).status();
  EXPECT_TRUE(absl::IsResourceExhausted(s)) << s;
  EXPECT_NE(s.message().find("max_model_mb"), std::string::npos) << s;
}

TEST_F(ServerTest, LabelsCanBeDisabledInTheConfig) {
  server::ServerConfig config;
  config.labels_enabled = false;
  StartServer(config);
  ASSERT_TRUE(client_->UploadModel("m", TwoColorModel()).ok());
  ASSERT_TRUE(client_->ActivateModel("m", "").ok());
  v1::ProcessFrameRequest req;
  *req.mutable_frame() = TwoColorFrame(0);
  auto r = client_->ProcessFrame(req);
  ASSERT_TRUE(r.ok());
  EXPECT_FALSE(r->has_labels());
  EXPECT_NE(LabelStatus(*r)->reason().find("labels.enabled"), std::string::npos);
}

// A robot that wants labels only (or masks only) skips the other output's cost; its result
// says "not requested", and a keyframe still stores features pruned by its mask.
TEST_F(ServerTest, ClientsSkipOutputsTheyDoNotWant) {
  ASSERT_TRUE(client_->UploadModel("two-colors", testing::TwoColorModel()).ok());
  ASSERT_TRUE(client_->ActivateModel("two-colors", "").ok());
  ASSERT_TRUE(client_->CreateMap("m", "").ok());
  v1::ProcessFrameRequest req;
  req.set_map("m");
  *req.mutable_frame() = testing::TwoColorFrame(0);
  req.mutable_options()->add_skip_outputs(v1::FRAME_OUTPUT_ENTROPY_MASK);
  auto labels_only = client_->ProcessFrame(req);
  ASSERT_TRUE(labels_only.ok()) << labels_only.status();
  EXPECT_TRUE(labels_only->has_labels());
  EXPECT_FALSE(labels_only->has_entropy());
  const auto* entropy = StatusOf(*labels_only, v1::FRAME_OUTPUT_ENTROPY_MASK);
  ASSERT_NE(entropy, nullptr);
  EXPECT_FALSE(entropy->computed());
  EXPECT_NE(entropy->reason().find("not requested"), std::string::npos) << entropy->reason();
  ASSERT_TRUE(labels_only->keyframe().committed()) << "the visit's first frame";
  auto keyframes = client_->ListKeyframes("m", 0);
  ASSERT_TRUE(keyframes.ok()) << keyframes.status();
  ASSERT_EQ(keyframes->keyframes_size(), 1);
  EXPECT_GE(keyframes->keyframes(0).superjut_count(), 1u) << "the mask was computed to prune";

  req.mutable_options()->clear_skip_outputs();
  req.mutable_options()->add_skip_outputs(v1::FRAME_OUTPUT_CLASS_LABELS);
  req.clear_map();
  auto masks_only = client_->ProcessFrame(req);
  ASSERT_TRUE(masks_only.ok()) << masks_only.status();
  EXPECT_TRUE(masks_only->has_entropy());
  EXPECT_FALSE(masks_only->has_labels());
  const auto* labels = StatusOf(*masks_only, v1::FRAME_OUTPUT_CLASS_LABELS);
  ASSERT_NE(labels, nullptr);
  EXPECT_NE(labels->reason().find("not requested"), std::string::npos) << labels->reason();

  req.mutable_options()->add_skip_outputs(v1::FRAME_OUTPUT_KEYFRAME);
  auto bad = client_->ProcessFrame(req);
  EXPECT_TRUE(absl::IsInvalidArgument(bad.status())) << bad.status();
  EXPECT_NE(bad.status().message().find("FRAME_OUTPUT_KEYFRAME cannot be skipped"),
            std::string::npos)
      << bad.status();
  req.mutable_options()->set_skip_outputs(1, static_cast<v1::FrameOutput>(99));
  EXPECT_TRUE(absl::IsInvalidArgument(client_->ProcessFrame(req).status()));
}

}  // namespace
}  // namespace lifemap
