// Integration tests of the served semantic octree (issue 16): a visit's keyframes fused off the
// reply path, and every posed frame of the visit given the octree's labels (fused_labels), or
// told why not.
#include <sstream>

#include <gtest/gtest.h>
#include <octomap/AbstractOcTree.h>
#include <octomap/ColorOcTree.h>
#include <octomap/OcTree.h>
#include <nlohmann/json.hpp>
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

// Streams `frames` posed keyframes into a new visit of `map` and leaves it open.
uint64_t StreamVisit(client::Client* client, const std::string& map, int frames,
                     std::unique_ptr<client::FrameStream>* stream) {
  v1::StreamStart start;
  start.set_map(map);
  auto opened = client->OpenStream(start);
  EXPECT_TRUE(opened.ok()) << opened.status();
  if (!opened.ok()) return 0;
  *stream = *std::move(opened);
  for (int i = 0; i < frames; ++i) {
    EXPECT_TRUE((*stream)->Send(PosedFrame(static_cast<uint64_t>(i))));
    v1::FrameResult r;
    EXPECT_TRUE((*stream)->Receive(&r));
  }
  return (*stream)->started().visit_id();
}

// Servers with the two-colour model active by default and a map "lab".
class SemanticServerTest : public ServerTest {
 protected:
  void SetUp() override {
    ServerTest::SetUp();
    ASSERT_TRUE(client_->UploadModel("two-colors", testing::TwoColorModel()).ok());
    ASSERT_TRUE(client_->ActivateModel("two-colors", "").ok());
    ASSERT_TRUE(client_->CreateMap("lab", "").ok());
  }

  // A visit of `keyframes` posed keyframes (a second apart), the server restarted, the visit
  // resumed: the result of its first frame after the restart.
  v1::FrameResult FirstFrameAfterRestart(int keyframes) {
    v1::FrameResult resumed;
    std::unique_ptr<client::FrameStream> stream;
    const uint64_t visit_id = StreamVisit(client_.get(), "lab", keyframes, &stream);
    if (stream == nullptr) return resumed;
    stream->CloseSend();
    EXPECT_TRUE(stream->Finish().ok());

    RestartServer();
    v1::StreamStart start;
    start.set_map("lab");
    start.set_visit_id(visit_id);
    auto resumed_stream = client_->OpenStream(start);
    EXPECT_TRUE(resumed_stream.ok()) << resumed_stream.status();
    if (!resumed_stream.ok()) return resumed;
    EXPECT_TRUE((*resumed_stream)->Send(PosedFrame(20)));
    EXPECT_TRUE((*resumed_stream)->Receive(&resumed));
    (*resumed_stream)->CloseSend();
    EXPECT_TRUE((*resumed_stream)->Finish().ok());
    return resumed;
  }
};

TEST_F(SemanticServerTest, PosedFramesOfAVisitGetTheOctreesLabels) {
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

TEST_F(SemanticServerTest, AResumedVisitStartsFromItsStoredOctree) {
  // Twelve keyframes: a snapshot is stored once ten are fused.
  const v1::FrameResult resumed = FirstFrameAfterRestart(12);
  EXPECT_TRUE(resumed.has_fused_labels())
      << "the resumed visit's first frame is labelled from the stored octree: "
      << FusionStatus(resumed)->reason();
}

TEST_F(SemanticServerTest, ACleanShutdownStoresTheOctreesOfOpenVisits) {
  // Four keyframes: fewer than a periodic snapshot needs.
  const v1::FrameResult resumed = FirstFrameAfterRestart(4);
  EXPECT_TRUE(resumed.has_fused_labels())
      << "the octree was stored at shutdown: " << FusionStatus(resumed)->reason();
}

absl::StatusOr<std::string> Export(client::Client* client, v1::ExportFormat format,
                                   uint64_t visit_id = 0, const std::string& class_name = "",
                                   uint64_t* items = nullptr) {
  v1::ExportMapRequest req;
  req.set_map("lab");
  req.set_format(format);
  req.set_visit_id(visit_id);
  req.set_class_name(class_name);
  std::ostringstream out;
  auto n = client->ExportMap(req, &out);
  if (!n.ok()) return n.status();
  if (items != nullptr) *items = *n;
  return out.str();
}

TEST_F(SemanticServerTest, ExportsTheOctreeInOctomapsFormats) {
  // No octree yet: the operator is told how to get one.
  auto none = Export(client_.get(), v1::EXPORT_OCTREE_OT);
  EXPECT_EQ(none.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_NE(none.status().message().find("has no semantic octree"), std::string::npos)
      << none.status();

  // A live visit (6 keyframes, fewer than a periodic snapshot needs): the export snapshots it.
  std::unique_ptr<client::FrameStream> stream;
  const uint64_t first = StreamVisit(client_.get(), "lab", 6, &stream);
  auto summary_text = Export(client_.get(), v1::EXPORT_SEMANTIC_SUMMARY_JSON);
  ASSERT_TRUE(summary_text.ok()) << summary_text.status();
  const nlohmann::json summary = nlohmann::json::parse(*summary_text);
  EXPECT_EQ(summary["model"], "two-colors");
  EXPECT_EQ(summary["frame"], "map");
  EXPECT_EQ(summary["visits"], nlohmann::json::array({first}));
  EXPECT_GE(summary["keyframes"].get<int>(), 4);
  EXPECT_GT(summary["labelled_voxels"].get<int>(), 100);
  EXPECT_GT(summary["class_volume_m3"]["wall"].get<double>(), 0.0);
  EXPECT_GT(summary["class_volume_m3"]["door"].get<double>(), 0.0);

  // .bt: an OcTree; .ot: a ColorOcTree whose occupied voxels carry the class colours.
  uint64_t voxels = 0;
  auto bt = Export(client_.get(), v1::EXPORT_OCTREE_BT, 0, "", &voxels);
  ASSERT_TRUE(bt.ok()) << bt.status();
  std::istringstream bt_in(*bt);
  octomap::OcTree tree(0.1);
  ASSERT_TRUE(tree.readBinary(bt_in));
  EXPECT_DOUBLE_EQ(tree.getResolution(), summary["resolution_m"].get<double>());
  EXPECT_GT(voxels, 100u);
  auto ot = Export(client_.get(), v1::EXPORT_OCTREE_OT);
  ASSERT_TRUE(ot.ok()) << ot.status();
  std::istringstream ot_in(*ot);
  std::unique_ptr<octomap::AbstractOcTree> read(octomap::AbstractOcTree::read(ot_in));
  auto* color = dynamic_cast<octomap::ColorOcTree*>(read.get());
  ASSERT_NE(color, nullptr);
  int green = 0;
  for (auto it = color->begin_leafs(); it != color->end_leafs(); ++it) {
    if (color->isNodeOccupied(*it) &&
        it->getColor() == octomap::ColorOcTreeNode::Color(0, 255, 0)) {
      ++green;
    }
  }
  EXPECT_GT(green, 10) << "door voxels in the door's colour";

  // One class: a semantic cloud of door voxels only.
  uint64_t doors = 0;
  auto cloud = Export(client_.get(), v1::EXPORT_SEMANTIC_CLOUD_PLY, 0, "door", &doors);
  ASSERT_TRUE(cloud.ok()) << cloud.status();
  EXPECT_GT(doors, 10u);
  EXPECT_NE(cloud->find("element vertex " + std::to_string(doors) + "\n"), std::string::npos);
  const size_t body = cloud->find("end_header\n") + 11;
  ASSERT_EQ(cloud->size() - body, doors * 24);
  for (uint64_t i = 0; i < doors; ++i) EXPECT_EQ((*cloud)[body + i * 24 + 12], 1) << i;
  auto unknown = Export(client_.get(), v1::EXPORT_SEMANTIC_CLOUD_PLY, 0, "window");
  EXPECT_EQ(unknown.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(unknown.status().message().find("wall, door"), std::string::npos) << unknown.status();
  auto summary_of_one = Export(client_.get(), v1::EXPORT_SEMANTIC_SUMMARY_JSON, 0, "door");
  EXPECT_EQ(summary_of_one.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(summary_of_one.status().message().find("leave class_name empty"), std::string::npos)
      << summary_of_one.status();
  auto no_such_format = Export(client_.get(), static_cast<v1::ExportFormat>(99));
  EXPECT_EQ(no_such_format.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(no_such_format.status().message().find("EXPORT_OCTREE_OT"), std::string::npos)
      << no_such_format.status();

  // A second visit with client poses is in the map's frame too: the map's octree merges both.
  stream->CloseSend();
  EXPECT_TRUE(stream->Finish().ok());
  std::unique_ptr<client::FrameStream> second_stream;
  const uint64_t second = StreamVisit(client_.get(), "lab", 4, &second_stream);
  second_stream->CloseSend();
  EXPECT_TRUE(second_stream->Finish().ok());
  auto merged = Export(client_.get(), v1::EXPORT_SEMANTIC_SUMMARY_JSON);
  ASSERT_TRUE(merged.ok()) << merged.status();
  EXPECT_EQ(nlohmann::json::parse(*merged)["visits"], nlohmann::json::array({first, second}));
  auto one = Export(client_.get(), v1::EXPORT_SEMANTIC_SUMMARY_JSON, second);
  ASSERT_TRUE(one.ok()) << one.status();
  EXPECT_EQ(nlohmann::json::parse(*one)["visits"], nlohmann::json::array({second}));
}

absl::StatusOr<std::vector<v1::SemanticOctreeRebuild>> Rebuild(client::Client* client,
                                                               uint64_t visit_id, bool all) {
  v1::RebuildSemanticOctreesRequest req;
  req.set_map("lab");
  req.set_visit_id(visit_id);
  req.set_all(all);
  std::vector<v1::SemanticOctreeRebuild> visits;
  auto s = client->RebuildSemanticOctrees(
      req, [&](const v1::SemanticOctreeRebuild& r) { visits.push_back(r); });
  if (!s.ok()) return s;
  return visits;
}

TEST_F(ServerTest, RebuildsOctreesFromStoredKeyframes) {
  // Five posed keyframes stored while no model labelled the map: no octree.
  ASSERT_TRUE(client_->CreateMap("lab", "").ok());
  std::unique_ptr<client::FrameStream> stream;
  const uint64_t visit = StreamVisit(client_.get(), "lab", 5, &stream);
  stream->CloseSend();
  ASSERT_TRUE(stream->Finish().ok());
  EXPECT_EQ(Export(client_.get(), v1::EXPORT_SEMANTIC_SUMMARY_JSON).status().code(),
            absl::StatusCode::kFailedPrecondition);
  auto no_model = Rebuild(client_.get(), 0, false);
  EXPECT_EQ(no_model.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_NE(no_model.status().message().find("lifemap models activate"), std::string::npos)
      << no_model.status();

  // With a model: the keyframes are labelled and fused again, and the octree is stored.
  ASSERT_TRUE(client_->UploadModel("two-colors", testing::TwoColorModel()).ok());
  ASSERT_TRUE(client_->ActivateModel("two-colors", "").ok());
  auto rebuilt = Rebuild(client_.get(), 0, false);
  ASSERT_TRUE(rebuilt.ok()) << rebuilt.status();
  ASSERT_EQ(rebuilt->size(), 1u);
  const v1::SemanticOctreeRebuild& r = rebuilt->front();
  EXPECT_EQ(r.visit_id(), visit);
  EXPECT_EQ(r.outcome(), v1::SemanticOctreeRebuild::OUTCOME_REBUILT) << r.reason();
  EXPECT_EQ(r.reason(), "no octree stored");
  EXPECT_EQ(r.model(), "two-colors");
  EXPECT_EQ(r.keyframes_fused(), 5u);
  EXPECT_EQ(r.keyframes_skipped(), 0u);
  EXPECT_GT(r.labelled_voxels(), 100u);
  auto summary_text = Export(client_.get(), v1::EXPORT_SEMANTIC_SUMMARY_JSON);
  ASSERT_TRUE(summary_text.ok()) << summary_text.status();
  const nlohmann::json summary = nlohmann::json::parse(*summary_text);
  EXPECT_EQ(summary["keyframes"], 5);
  EXPECT_EQ(summary["labelled_voxels"].get<uint64_t>(), r.labelled_voxels());
  EXPECT_GT(summary["class_volume_m3"]["wall"].get<double>(), 0.0);
  EXPECT_GT(summary["class_volume_m3"]["door"].get<double>(), 0.0);

  // Up to date now: left as it is, unless every visit is asked for.
  auto again = Rebuild(client_.get(), visit, false);
  ASSERT_TRUE(again.ok()) << again.status();
  ASSERT_EQ(again->size(), 1u);
  EXPECT_EQ(again->front().outcome(), v1::SemanticOctreeRebuild::OUTCOME_UP_TO_DATE);
  EXPECT_NE(again->front().reason().find("holds all 5 posed keyframes"), std::string::npos)
      << again->front().reason();
  auto forced = Rebuild(client_.get(), visit, true);
  ASSERT_TRUE(forced.ok()) << forced.status();
  EXPECT_EQ(forced->front().outcome(), v1::SemanticOctreeRebuild::OUTCOME_REBUILT);

  // The visit is still open (its stream ended, it was not): its frames are labelled from the
  // rebuilt octree now.
  v1::ProcessFrameRequest req;
  req.set_map("lab");
  req.set_visit_id(visit);
  *req.mutable_frame() = PosedFrame(30);
  auto labelled = client_->ProcessFrame(req);
  ASSERT_TRUE(labelled.ok()) << labelled.status();
  EXPECT_TRUE(labelled->has_fused_labels()) << FusionStatus(*labelled)->reason();

  // A visit being streamed is left out, saying so; rebuilt once its stream has ended.
  const uint64_t streamed = StreamVisit(client_.get(), "lab", 3, &stream);
  auto while_streamed = Rebuild(client_.get(), streamed, true);
  ASSERT_TRUE(while_streamed.ok()) << while_streamed.status();
  EXPECT_EQ(while_streamed->front().outcome(), v1::SemanticOctreeRebuild::OUTCOME_LEFT_OUT);
  EXPECT_NE(while_streamed->front().reason().find("being streamed"), std::string::npos)
      << while_streamed->front().reason();
  stream->CloseSend();
  ASSERT_TRUE(stream->Finish().ok());
  auto after = Rebuild(client_.get(), streamed, true);
  ASSERT_TRUE(after.ok()) << after.status();
  EXPECT_EQ(after->front().outcome(), v1::SemanticOctreeRebuild::OUTCOME_REBUILT)
      << after->front().reason();
  EXPECT_EQ(after->front().keyframes_fused(), 3u);

  // Bad input: another map's visit, a map that does not exist.
  EXPECT_EQ(Rebuild(client_.get(), 999, false).status().code(), absl::StatusCode::kNotFound);
  v1::RebuildSemanticOctreesRequest bad;
  bad.set_map("no-such-map");
  EXPECT_EQ(client_->RebuildSemanticOctrees(bad, [](const v1::SemanticOctreeRebuild&) {}).code(),
            absl::StatusCode::kNotFound);
}

}  // namespace
}  // namespace lifemap
